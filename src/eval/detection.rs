//! Evaluation as the CMU_KO8 acceptance scorer (`ko8_eval.py`) computes it:
//! the area under recall vs false positives per image over FPPI 0..1
//! (correct at box IoU >= 0.5, one match per image), per object and across
//! objects, and the segmentation error of the top detection's mask.

use serde::{Deserialize, Serialize};

use crate::data::Annotation;
use crate::pipeline::DetectionJson;
use crate::vision::detect::box_iou;
use crate::vision::mask::Mask;

/// One evaluated image: its ground truth (`None` for a negative) and the
/// detections of every model on it.
pub struct Evaluated<'a> {
    pub id: &'a str,
    pub truth: Option<&'a Annotation>,
    pub detections: &'a [DetectionJson],
}

/// Figures of one object.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct ObjectScore {
    pub object: String,
    pub images: usize,
    /// AUC of recall vs FPPI in [0, 1], false positives counted on the
    /// object's own images.
    pub auc: f64,
    /// The same with false positives counted on every object's images.
    pub auc_cross: f64,
    pub recall_at_1fppi: f64,
    pub recall_at_1fppi_cross: f64,
    /// Mean `1 - IoU` of the top detection's refined mask (1 if none).
    pub seg_error_refined: f64,
    pub seg_error_raw: f64,
    /// The Pascal VOC segmentation error (the paper's figure, `VOC=1` of
    /// `ko8_eval.py`): pixel counts of the top detection's mask summed over
    /// the object's images, `1 - (IoU of the object + IoU of the
    /// background) / 2`.
    #[serde(default)]
    pub voc_error_refined: f64,
    #[serde(default)]
    pub voc_error_raw: f64,
    /// Recall-FPPI curves on the 1001-point grid (own images, cross).
    #[serde(skip_serializing_if = "Vec::is_empty", default)]
    pub curve: Vec<f64>,
    #[serde(skip_serializing_if = "Vec::is_empty", default)]
    pub curve_cross: Vec<f64>,
}

/// Mean figures over objects.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct MeanScore {
    pub auc: f64,
    pub auc_cross: f64,
    pub seg_error_refined: f64,
    pub seg_error_raw: f64,
    #[serde(default)]
    pub voc_error_refined: f64,
    #[serde(default)]
    pub voc_error_raw: f64,
}

/// The FPPI grid of the scorer: 1001 points over [0, 1].
pub const GRID: usize = 1001;

/// Recall as a step function of FPPI on the grid, and its trapezoid area.
/// `dets` are `(score, image index, IoU with that image's truth)`.
pub fn recall_fppi(
    mut dets: Vec<(f64, usize, f64)>,
    n_images: usize,
    n_positives: usize,
) -> (Vec<f64>, f64) {
    // Stable sort by descending score, as Python's sorted.
    dets.sort_by(|a, b| b.0.total_cmp(&a.0));
    let mut matched = std::collections::HashSet::new();
    let (mut tp, mut fp) = (0usize, 0usize);
    let mut curve = vec![(0.0, 0.0)];
    for (_, img, iou) in dets {
        if iou >= 0.5 && matched.insert(img) {
            tp += 1;
        } else {
            fp += 1;
        }
        curve.push((
            fp as f64 / n_images.max(1) as f64,
            tp as f64 / n_positives.max(1) as f64,
        ));
    }
    let mut rec = vec![0.0f64; GRID];
    for (f, r) in curve {
        for (g, slot) in rec.iter_mut().enumerate() {
            let x = g as f64 / (GRID - 1) as f64;
            if x >= f {
                *slot = slot.max(r);
            }
        }
    }
    let dx = 1.0 / (GRID - 1) as f64;
    let auc = rec.windows(2).map(|w| 0.5 * (w[0] + w[1]) * dx).sum();
    (rec, auc)
}

fn box_of(d: &DetectionJson) -> (f64, f64, f64, f64) {
    (d.bbox.x, d.bbox.y, d.bbox.width, d.bbox.height)
}

/// `1 - IoU` of a detection's mask with the visible ground truth (1 when
/// the detection carries no such mask), and the pixel counts TP, FP, FN,
/// TN of the mask (an empty mask when none) for the VOC error.
fn seg_error(det: Option<&DetectionJson>, truth: &Mask, raw: bool) -> (f64, [u64; 4]) {
    let rle = det.and_then(|d| {
        if raw {
            d.raw_mask.as_ref()
        } else {
            d.mask.as_ref()
        }
    });
    let m = rle
        .and_then(Mask::from_rle)
        .filter(|m| m.width == truth.width && m.height == truth.height);
    let mut counts = [0u64; 4];
    for (i, &t) in truth.data.iter().enumerate() {
        let p = m.as_ref().is_some_and(|m| m.data[i] != 0);
        let k = match (p, t != 0) {
            (true, true) => 0,
            (true, false) => 1,
            (false, true) => 2,
            (false, false) => 3,
        };
        counts[k] += 1;
    }
    let err = match &m {
        Some(m) => 1.0 - m.iou(truth),
        None => 1.0,
    };
    (err, counts)
}

/// The VOC segmentation error of summed pixel counts TP, FP, FN, TN.
fn voc_error(c: &[u64; 4]) -> f64 {
    let [tp, fp, fn_, tn] = c.map(|v| v as f64);
    let obj = if tp + fp + fn_ > 0.0 {
        tp / (tp + fp + fn_)
    } else {
        0.0
    };
    let bg = if tn + fp + fn_ > 0.0 {
        tn / (tn + fp + fn_)
    } else {
        0.0
    };
    1.0 - 0.5 * (obj + bg)
}

/// Scores one object over the evaluated images. Images whose truth is
/// `object` are its own; every other image with a truth of another object
/// counts in the cross-object protocol (negatives without truth do not, as
/// in the scorer).
pub fn score_object(object: &str, images: &[Evaluated]) -> ObjectScore {
    let mine = |e: &Evaluated| e.truth.is_some_and(|t| t.label == object);
    let mut own = Vec::new();
    let mut cross = Vec::new();
    let mut n_own = 0;
    let mut n_all = 0;
    let mut seg_refined = Vec::new();
    let mut seg_raw = Vec::new();
    let (mut voc_refined, mut voc_raw) = ([0u64; 4], [0u64; 4]);
    for (idx, e) in images.iter().enumerate() {
        let Some(t) = e.truth else { continue };
        n_all += 1;
        let mut dets: Vec<&DetectionJson> =
            e.detections.iter().filter(|d| d.label == object).collect();
        dets.sort_by(|a, b| b.score.total_cmp(&a.score));
        if mine(e) {
            n_own += 1;
            for d in &dets {
                let iou = box_iou(t.bbox, box_of(d));
                own.push((d.score, idx, iou));
                cross.push((d.score, idx, iou));
            }
            for (raw, seg, voc) in [
                (false, &mut seg_refined, &mut voc_refined),
                (true, &mut seg_raw, &mut voc_raw),
            ] {
                let (e, c) = seg_error(dets.first().copied(), &t.visible, raw);
                seg.push(e);
                for (v, x) in voc.iter_mut().zip(c) {
                    *v += x;
                }
            }
        } else {
            for d in &dets {
                cross.push((d.score, idx, 0.0));
            }
        }
    }
    let (curve, auc) = recall_fppi(own, n_own, n_own);
    let (curve_cross, auc_cross) = recall_fppi(cross, n_all, n_own);
    let mean = |v: &[f64]| {
        if v.is_empty() {
            1.0
        } else {
            v.iter().sum::<f64>() / v.len() as f64
        }
    };
    ObjectScore {
        object: object.to_string(),
        images: n_own,
        auc,
        auc_cross,
        recall_at_1fppi: curve[GRID - 1],
        recall_at_1fppi_cross: curve_cross[GRID - 1],
        seg_error_refined: mean(&seg_refined),
        seg_error_raw: mean(&seg_raw),
        voc_error_refined: voc_error(&voc_refined),
        voc_error_raw: voc_error(&voc_raw),
        curve,
        curve_cross,
    }
}

/// Means over objects.
pub fn mean_score(scores: &[ObjectScore]) -> MeanScore {
    let n = scores.len().max(1) as f64;
    MeanScore {
        auc: scores.iter().map(|s| s.auc).sum::<f64>() / n,
        auc_cross: scores.iter().map(|s| s.auc_cross).sum::<f64>() / n,
        seg_error_refined: scores.iter().map(|s| s.seg_error_refined).sum::<f64>() / n,
        seg_error_raw: scores.iter().map(|s| s.seg_error_raw).sum::<f64>() / n,
        voc_error_refined: scores.iter().map(|s| s.voc_error_refined).sum::<f64>() / n,
        voc_error_raw: scores.iter().map(|s| s.voc_error_raw).sum::<f64>() / n,
    }
}

/// A table of the figures, one row per object and the mean.
/// A text table of the figures; `segmentation` false (box-only truth)
/// leaves the segmentation columns out and adds recall at 1 FPPI.
pub fn table(scores: &[ObjectScore], segmentation: bool) -> String {
    let m = mean_score(scores);
    if !segmentation {
        let n = scores.len().max(1) as f64;
        let r1 = scores.iter().map(|o| o.recall_at_1fppi).sum::<f64>() / n;
        let r1c = scores.iter().map(|o| o.recall_at_1fppi_cross).sum::<f64>() / n;
        let mut s = format!(
            "{:10} {:>6} {:>9} {:>8} {:>14} {:>5}\n",
            "object", "AUC", "AUC-cross", "R@1FPPI", "R@1FPPI-cross", "n"
        );
        for o in scores {
            s += &format!(
                "{:10} {:6.3} {:9.3} {:8.3} {:14.3} {:5}\n",
                o.object, o.auc, o.auc_cross, o.recall_at_1fppi, o.recall_at_1fppi_cross, o.images
            );
        }
        s += &format!(
            "{:10} {:6.3} {:9.3} {:8.3} {:14.3}\n",
            "mean", m.auc, m.auc_cross, r1, r1c
        );
        return s;
    }
    let mut s = format!(
        "{:10} {:>6} {:>9} {:>10} {:>9} {:>10} {:>9} {:>5}\n",
        "object", "AUC", "AUC-cross", "seg-refine", "seg-raw", "VOC-refine", "VOC-raw", "n"
    );
    for o in scores {
        s += &format!(
            "{:10} {:6.3} {:9.3} {:10.4} {:9.4} {:10.4} {:9.4} {:5}\n",
            o.object,
            o.auc,
            o.auc_cross,
            o.seg_error_refined,
            o.seg_error_raw,
            o.voc_error_refined,
            o.voc_error_raw,
            o.images
        );
    }
    s += &format!(
        "{:10} {:6.3} {:9.3} {:10.4} {:9.4} {:10.4} {:9.4}\n",
        "mean",
        m.auc,
        m.auc_cross,
        m.seg_error_refined,
        m.seg_error_raw,
        m.voc_error_refined,
        m.voc_error_raw
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn perfect_detections_score_one_and_misses_zero() {
        let dets = vec![(2.0, 0, 0.9), (1.0, 1, 0.8)];
        let (_, auc) = recall_fppi(dets, 2, 2);
        assert!((auc - 1.0).abs() < 1e-12);
        let (_, auc) = recall_fppi(vec![], 2, 2);
        assert_eq!(auc, 0.0);
    }

    /// A false positive above the true one: recall 1 is reached at FPPI 0.5
    /// on two images; the area is the step function's trapezoid sum.
    #[test]
    fn false_positives_shift_the_curve() {
        let dets = vec![(3.0, 0, 0.1), (2.0, 0, 0.9), (1.0, 1, 0.7)];
        let (rec, auc) = recall_fppi(dets, 2, 2);
        assert_eq!(rec[0], 0.0);
        assert_eq!(rec[499], 0.0);
        assert_eq!(rec[500], 1.0);
        // Recall 1 over [0.5, 1] plus the trapezoid of the jump's step.
        assert!((auc - (0.5 + 0.0005)).abs() < 1e-9, "{auc}");
        // A second match on the same image is a false positive.
        let (_, auc2) = recall_fppi(vec![(2.0, 0, 0.9), (1.0, 0, 0.9)], 1, 1);
        assert!((auc2 - 1.0).abs() < 1e-12);
    }
}
