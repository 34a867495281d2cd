//! COCO average precision as pycocotools' `COCOeval` computes it, the
//! figure BOP reports for 2-D detection and segmentation (BOP 2022's
//! `eval_bop22_coco.py`): for each category, each image's detections in
//! decreasing score (at most [`MAX_DETECTIONS`]) are matched greedily to
//! the unmatched truth of highest overlap at each IoU threshold
//! (0.50:0.05:0.95); precision is made monotone and read at 101 recall
//! points; AP is the mean over thresholds, recall points and categories
//! with truth. The overlap is the caller's (boxes or masks).

/// IoU thresholds of COCO's AP: 0.50, 0.55, ..., 0.95.
pub const IOU_THRESHOLDS: [f64; 10] = [0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95];

/// Recall points at which precision is read (0, 0.01, ..., 1).
pub const RECALL_POINTS: usize = 101;

/// Detections per image that count (COCO's `maxDets` of AP).
pub const MAX_DETECTIONS: usize = 100;

/// A true instance: its image and category.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Truth {
    pub image: usize,
    pub category: u32,
}

/// A detection: its image, category and score.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Found {
    pub image: usize,
    pub category: u32,
    pub score: f64,
}

/// AP over IoU 0.50:0.95, and at 0.50 and 0.75 (0 to 1; `None` without
/// any truth).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ApFigures {
    pub ap: Option<f64>,
    pub ap50: Option<f64>,
    pub ap75: Option<f64>,
    /// Categories with truth, over which the means run.
    pub categories: usize,
}

impl ApFigures {
    /// The figures of two reports on disjoint categories of the same
    /// photographs joined: COCO's AP is the mean over categories of each
    /// category's AP, and a category's AP depends on its own detections
    /// only, so the join is the mean weighted by the categories (a figure
    /// absent from one side is the other's).
    pub fn join(&self, other: &ApFigures) -> ApFigures {
        let (a, b) = (self.categories as f64, other.categories as f64);
        let mean = |x: Option<f64>, y: Option<f64>| match (x, y) {
            (Some(x), Some(y)) if a + b > 0.0 => Some((x * a + y * b) / (a + b)),
            (x, None) => x,
            (None, y) => y,
            (Some(x), Some(_)) => Some(x),
        };
        ApFigures {
            ap: mean(self.ap, other.ap),
            ap50: mean(self.ap50, other.ap50),
            ap75: mean(self.ap75, other.ap75),
            categories: self.categories + other.categories,
        }
    }
}

/// COCO's AP of `found` against `truths`; `overlap(d, t)` is the IoU of
/// detection `d` and truth `t` (indices into the slices), asked only for
/// pairs of the same image and category.
pub fn average_precision(
    truths: &[Truth],
    found: &[Found],
    overlap: impl Fn(usize, usize) -> f64,
) -> ApFigures {
    let mut categories: Vec<u32> = truths.iter().map(|t| t.category).collect();
    categories.sort_unstable();
    categories.dedup();
    // precision[threshold][category][recall point]
    let mut per_threshold: Vec<Vec<[f64; RECALL_POINTS]>> = vec![Vec::new(); IOU_THRESHOLDS.len()];
    for &c in &categories {
        let curves = category_precision(truths, found, c, &overlap);
        for (t, q) in curves.into_iter().enumerate() {
            per_threshold[t].push(q);
        }
    }
    if categories.is_empty() {
        return ApFigures::default();
    }
    let mean = |rows: &[[f64; RECALL_POINTS]]| -> f64 {
        let n = (rows.len() * RECALL_POINTS) as f64;
        rows.iter().flat_map(|q| q.iter()).sum::<f64>() / n
    };
    let all: Vec<f64> = per_threshold.iter().map(|rows| mean(rows)).collect();
    ApFigures {
        ap: Some(all.iter().sum::<f64>() / all.len() as f64),
        ap50: Some(all[0]),
        ap75: Some(all[5]),
        categories: categories.len(),
    }
}

/// One category's precision at each recall point, per IoU threshold.
fn category_precision(
    truths: &[Truth],
    found: &[Found],
    category: u32,
    overlap: &impl Fn(usize, usize) -> f64,
) -> Vec<[f64; RECALL_POINTS]> {
    let mut images: Vec<usize> = truths
        .iter()
        .filter(|t| t.category == category)
        .map(|t| t.image)
        .chain(
            found
                .iter()
                .filter(|d| d.category == category)
                .map(|d| d.image),
        )
        .collect();
    images.sort_unstable();
    images.dedup();
    let n_truth = truths.iter().filter(|t| t.category == category).count();
    // Every counted detection's score and, per threshold, whether it matched.
    let mut scored: Vec<(f64, [bool; IOU_THRESHOLDS.len()])> = Vec::new();
    for &image in &images {
        let ts: Vec<usize> = (0..truths.len())
            .filter(|&t| truths[t].image == image && truths[t].category == category)
            .collect();
        let mut ds: Vec<usize> = (0..found.len())
            .filter(|&d| found[d].image == image && found[d].category == category)
            .collect();
        // Decreasing score, stable (pycocotools' mergesort).
        ds.sort_by(|&a, &b| found[b].score.total_cmp(&found[a].score));
        ds.truncate(MAX_DETECTIONS);
        let ious: Vec<Vec<f64>> = ds
            .iter()
            .map(|&d| ts.iter().map(|&t| overlap(d, t)).collect())
            .collect();
        let mut hits = vec![[false; IOU_THRESHOLDS.len()]; ds.len()];
        for (ti, &threshold) in IOU_THRESHOLDS.iter().enumerate() {
            let mut taken = vec![false; ts.len()];
            for (di, row) in ious.iter().enumerate() {
                let mut best = threshold.min(1.0 - 1e-10);
                let mut m = None;
                for (g, &iou) in row.iter().enumerate() {
                    if taken[g] || iou < best {
                        continue;
                    }
                    best = iou;
                    m = Some(g);
                }
                if let Some(g) = m {
                    taken[g] = true;
                    hits[di][ti] = true;
                }
            }
        }
        for (di, &d) in ds.iter().enumerate() {
            scored.push((found[d].score, hits[di]));
        }
    }
    scored.sort_by(|a, b| b.0.total_cmp(&a.0));
    (0..IOU_THRESHOLDS.len())
        .map(|ti| precision_at_recall(&scored, ti, n_truth))
        .collect()
}

/// The interpolated precision at the 101 recall points of detections in
/// decreasing score, `hit` at threshold `ti`, against `n_truth` instances.
fn precision_at_recall(
    scored: &[(f64, [bool; IOU_THRESHOLDS.len()])],
    ti: usize,
    n_truth: usize,
) -> [f64; RECALL_POINTS] {
    let mut q = [0.0; RECALL_POINTS];
    if n_truth == 0 {
        return q;
    }
    let (mut tp, mut fp) = (0.0f64, 0.0f64);
    let mut recall = Vec::with_capacity(scored.len());
    let mut precision = Vec::with_capacity(scored.len());
    for (_, hit) in scored {
        if hit[ti] {
            tp += 1.0;
        } else {
            fp += 1.0;
        }
        recall.push(tp / n_truth as f64);
        precision.push(tp / (tp + fp + f64::EPSILON));
    }
    // The precision envelope: each point at least what comes after it.
    for i in (1..precision.len()).rev() {
        if precision[i] > precision[i - 1] {
            precision[i - 1] = precision[i];
        }
    }
    for (r, out) in q.iter_mut().enumerate() {
        let at = r as f64 / (RECALL_POINTS - 1) as f64;
        // The first detection whose recall reaches the point.
        if let Some(i) = recall.iter().position(|&rc| rc >= at) {
            *out = precision[i];
        }
    }
    q
}

#[cfg(test)]
mod tests {
    use super::*;

    fn truth(image: usize, category: u32) -> Truth {
        Truth { image, category }
    }

    fn found(image: usize, category: u32, score: f64) -> Found {
        Found {
            image,
            category,
            score,
        }
    }

    #[test]
    fn perfect_detections_score_one_and_none_score_zero() {
        let ts = vec![truth(0, 1), truth(1, 1), truth(1, 2)];
        let ds = vec![found(0, 1, 0.9), found(1, 1, 0.8), found(1, 2, 0.7)];
        // Detection i is exactly truth i.
        let ap = average_precision(&ts, &ds, |d, t| if d == t { 1.0 } else { 0.0 });
        assert_eq!(ap.categories, 2);
        assert!((ap.ap.unwrap() - 1.0).abs() < 1e-12, "{ap:?}");
        let none = average_precision(&ts, &[], |_, _| 0.0);
        assert_eq!(none.ap, Some(0.0));
        assert_eq!(average_precision(&[], &ds, |_, _| 1.0).ap, None);
    }

    #[test]
    fn overlap_decides_the_thresholds_a_detection_counts_at() {
        // One instance, one detection at IoU 0.72: a hit at 0.50..0.70
        // (5 of 10 thresholds), a miss above.
        let ap = average_precision(&[truth(0, 1)], &[found(0, 1, 1.0)], |_, _| 0.72);
        assert!((ap.ap.unwrap() - 0.5).abs() < 1e-12, "{ap:?}");
        assert!((ap.ap50.unwrap() - 1.0).abs() < 1e-12, "{ap:?}");
        assert_eq!(ap.ap75, Some(0.0));
    }

    #[test]
    fn a_false_positive_ranked_first_halves_the_precision() {
        // Two detections on the one instance's image: the higher-scoring
        // one misses, the other hits. Precision at recall 1 is 1/2.
        let ds = vec![found(0, 1, 0.9), found(0, 1, 0.5)];
        let ap = average_precision(&[truth(0, 1)], &ds, |d, _| if d == 1 { 1.0 } else { 0.0 });
        assert!((ap.ap.unwrap() - 0.5).abs() < 1e-12, "{ap:?}");
        // A second detection of a matched instance is a false positive.
        let ds = vec![found(0, 1, 0.9), found(0, 1, 0.5)];
        let ap = average_precision(&[truth(0, 1)], &ds, |_, _| 1.0);
        assert!((ap.ap.unwrap() - 1.0).abs() < 1e-12, "{ap:?}");
        // Half the instances found, every detection right: recall stops at
        // 0.5, so half the recall points have precision 1.
        let ts = vec![truth(0, 1), truth(1, 1)];
        let ap = average_precision(
            &ts,
            &[found(0, 1, 0.9)],
            |_, t| if t == 0 { 1.0 } else { 0.0 },
        );
        assert!((ap.ap.unwrap() - 51.0 / 101.0).abs() < 1e-12, "{ap:?}");
    }
}
