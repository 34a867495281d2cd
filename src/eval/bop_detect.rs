//! Detection and visible-mask scores on BOP photographs, exactly as the
//! LM-O acceptance scorer (`lmo_detect_eval.py`) defines them, and the
//! pose from no start (ADD(-S)) on the same instances.
//!
//! Per object: the detections of its label in every photograph, matched
//! greedily by score within the photograph to its annotated instances
//! (box IoU >= 0.5 with the full-extent box `bbox_obj`, each instance
//! once); a match with an instance whose `visib_fract` is below 0.1 counts
//! neither way, every other unmatched detection is a false positive. AUC:
//! the area under recall against false positives per image over FPPI 0..1
//! (a step function), normalised to 1; also the recall at 1 FPPI.
//! Segmentation: per instance with `visib_fract >= 0.4` whose oracle
//! visible fraction is within `max_oracle_gap` of BOP's, the top-scoring
//! detection of the label in the photograph whose box overlaps the
//! instance's by IoU >= 0.5; error `1 - IoU` of its mask with `mask_visib`,
//! 1 without such a detection.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::data::bop::{Bop, BopImage, Instance};
use crate::pipeline::DetectionJson;
use crate::pose::geometry::Pose;
use crate::vision::detect::box_iou;
use crate::vision::mask::Mask;

/// The instances below this visible fraction are ignored by localization.
pub const IGNORE_VISIB: f64 = 0.1;
/// The instances at or above this visible fraction are scored for
/// segmentation and pose.
pub const SEGMENT_VISIB: f64 = 0.4;

/// Localization and segmentation figures of one object.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct DetectScore {
    pub object: String,
    pub obj_id: u32,
    pub auc: f64,
    pub recall_at_1fppi: f64,
    /// Instances with `visib_fract >= 0.1`.
    pub positives: usize,
    /// Mean segmentation error over the scored instances (the refined
    /// pixel masks, `mask`).
    pub seg_error: f64,
    /// The same with the raw cell masks (`raw_mask`), where the
    /// detections carry them (else NaN).
    pub seg_error_raw: f64,
    pub seg_instances: usize,
    /// Recall against FPPI: the points `(fppi, recall)` of the curve.
    #[serde(skip_serializing_if = "Vec::is_empty", default)]
    pub curve: Vec<(f64, f64)>,
}

fn box_of(d: &DetectionJson) -> (f64, f64, f64, f64) {
    (d.bbox.x, d.bbox.y, d.bbox.width, d.bbox.height)
}

fn bbox(inst: &Instance) -> Option<(f64, f64, f64, f64)> {
    inst.bbox_obj.map(|b| (b[0], b[1], b[2], b[3]))
}

/// Whether an instance is scored for segmentation and pose: visible
/// enough, and its oracle mask agrees with BOP's visibility (unannotated
/// clutter hides the rest).
pub fn scored_instance(inst: &Instance, max_oracle_gap: f64) -> bool {
    inst.visib_fract >= SEGMENT_VISIB
        && (inst.visib_fract - inst.oracle_visib_fract.unwrap_or(inst.visib_fract)).abs()
            <= max_oracle_gap
}

/// The area under recall against FPPI in [0, 1] and the recall at 1 FPPI
/// of `scored` (score, true positive) detections, and the curve's points.
pub fn auc_curve(
    mut scored: Vec<(f64, bool)>,
    positives: usize,
    images: usize,
) -> (f64, f64, Vec<(f64, f64)>) {
    scored.sort_by(|a, b| b.0.total_cmp(&a.0));
    let (mut tp, mut fp) = (0usize, 0usize);
    let mut pts = vec![(0.0, 0.0)];
    for (_, t) in scored {
        if t {
            tp += 1;
        } else {
            fp += 1;
        }
        pts.push((
            fp as f64 / images.max(1) as f64,
            tp as f64 / positives.max(1) as f64,
        ));
    }
    let (mut area, mut r1) = (0.0, 0.0);
    for w in pts.windows(2) {
        let ((f0, r0), (f1, r)) = (w[0], w[1]);
        if f0 >= 1.0 {
            break;
        }
        if f1 > f0 {
            area += (f1.min(1.0) - f0) * r0;
        }
        if f1 <= 1.0 {
            r1 = r;
        }
    }
    if let Some(&(last_f, last_r)) = pts.last() {
        if last_f < 1.0 {
            area += (1.0 - last_f) * last_r;
            r1 = last_r;
        }
    }
    (area, r1, pts)
}

/// The scores of object `obj_id` (detections labelled `label`) from the
/// detections of every image (`detections[i]` for `bop.images[i]`, only
/// the images in `images`); `visible(image, k)` loads an instance's
/// visible mask.
pub fn score_object<F>(
    bop: &Bop,
    images: &[usize],
    detections: &[Vec<DetectionJson>],
    obj_id: u32,
    label: &str,
    max_oracle_gap: f64,
    mut visible: F,
) -> DetectScore
where
    F: FnMut(&BopImage, usize) -> Option<Mask>,
{
    let (mut scored, mut positives, mut seg, mut seg_raw) =
        (Vec::new(), 0usize, Vec::new(), Vec::new());
    for &i in images {
        let image = &bop.images[i];
        let insts: Vec<&Instance> = image
            .instances
            .iter()
            .filter(|g| g.obj_id == obj_id)
            .collect();
        let mut dets: Vec<&DetectionJson> = detections
            .get(i)
            .map(|d| d.iter().filter(|d| d.label == label).collect())
            .unwrap_or_default();
        dets.sort_by(|a, b| b.score.total_cmp(&a.score));
        positives += insts
            .iter()
            .filter(|g| g.visib_fract >= IGNORE_VISIB)
            .count();
        let mut used = vec![false; insts.len()];
        for d in &dets {
            let mut best: Option<(f64, usize)> = None;
            for (j, g) in insts.iter().enumerate() {
                if used[j] {
                    continue;
                }
                let o = bbox(g).map_or(0.0, |b| box_iou(box_of(d), b));
                if o > best.map_or(0.0, |b| b.0) {
                    best = Some((o, j));
                }
            }
            match best {
                Some((o, j)) if o >= 0.5 => {
                    used[j] = true;
                    if insts[j].visib_fract >= IGNORE_VISIB {
                        scored.push((d.score, true));
                    }
                }
                _ => scored.push((d.score, false)),
            }
        }
        for g in insts.iter().filter(|g| scored_instance(g, max_oracle_gap)) {
            let Some(b) = bbox(g) else { continue };
            let hit = dets
                .iter()
                .find(|d| box_iou(box_of(d), b) >= 0.5 && d.mask.is_some());
            let truth = visible(image, g.k);
            seg.push(mask_error(
                hit.and_then(|d| d.mask.as_ref()),
                truth.as_ref(),
            ));
            if hit.is_none_or(|d| d.raw_mask.is_some()) {
                seg_raw.push(mask_error(
                    hit.and_then(|d| d.raw_mask.as_ref()),
                    truth.as_ref(),
                ));
            }
        }
    }
    let (auc, recall_at_1fppi, curve) = auc_curve(scored, positives, images.len());
    let mean = |v: &[f64]| {
        if v.is_empty() {
            f64::NAN
        } else {
            v.iter().sum::<f64>() / v.len() as f64
        }
    };
    DetectScore {
        object: label.to_string(),
        obj_id,
        auc,
        recall_at_1fppi,
        positives,
        seg_error: mean(&seg),
        seg_error_raw: if seg_raw.len() == seg.len() {
            mean(&seg_raw)
        } else {
            f64::NAN
        },
        seg_instances: seg.len(),
        curve,
    }
}

/// `1 - IoU` of a detection's mask with the visible truth; 1 without a
/// mask, a truth or when their sizes differ.
fn mask_error(rle: Option<&crate::vision::mask::Rle>, truth: Option<&Mask>) -> f64 {
    match (rle.and_then(Mask::from_rle), truth) {
        (Some(m), Some(v)) if (m.width, m.height) == (v.width, v.height) => {
            let (mut inter, mut union) = (0usize, 0usize);
            for (a, t) in m.data.iter().zip(&v.data) {
                let (a, t) = (*a != 0, *t != 0);
                inter += usize::from(a && t);
                union += usize::from(a || t);
            }
            1.0 - if union > 0 {
                inter as f64 / union as f64
            } else {
                0.0
            }
        }
        _ => 1.0,
    }
}

/// ADD-S: the mean over `points` of the distance from each point at `est`
/// to the nearest point at `truth` (the error of symmetric objects).
pub fn add_s(est: &Pose, truth: &Pose, points: &[Vector3<f64>]) -> f64 {
    if points.is_empty() {
        return 0.0;
    }
    let at_truth: Vec<Vector3<f64>> = points.iter().map(|p| truth.transform(p)).collect();
    points
        .iter()
        .map(|p| {
            let e = est.transform(p);
            at_truth
                .iter()
                .map(|q| (e - q).norm_squared())
                .fold(f64::INFINITY, f64::min)
                .sqrt()
        })
        .sum::<f64>()
        / points.len() as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The step-function area of `lmo_detect_eval.py`'s `auc_curve`,
    /// worked by hand: TP, FP, TP, FP, FP over 2 images and 2 positives.
    #[test]
    fn auc_matches_the_scorer_by_hand() {
        let scored = vec![
            (5.0, true),
            (4.0, false),
            (3.0, true),
            (2.0, false),
            (1.0, false),
        ];
        let (auc, r1, _) = auc_curve(scored, 2, 2);
        // Points (0,0) (0,.5) (.5,.5) (.5,1) (1,1) (1.5,1): area 0.5*0.5 + 0.5*1.
        assert!((auc - 0.75).abs() < 1e-12, "{auc}");
        assert!((r1 - 1.0).abs() < 1e-12);
        let (auc, r1, _) = auc_curve(vec![(1.0, false)], 3, 10);
        assert_eq!((auc, r1), (0.0, 0.0));
        // Never reaching 1 FPPI: the last recall holds to the end.
        let (auc, r1, _) = auc_curve(vec![(1.0, true)], 2, 10);
        assert!((auc - 0.5).abs() < 1e-12 && (r1 - 0.5).abs() < 1e-12);
    }

    fn det(label: &str, score: f64, b: (f64, f64, f64, f64), mask: Option<&Mask>) -> DetectionJson {
        let mut d: DetectionJson = serde_json::from_value(serde_json::json!({
            "label": label, "model": label, "score": score,
            "box": {"x": b.0, "y": b.1, "width": b.2, "height": b.3},
            "viewpoint": 0, "level": 0, "visible_fraction": 1.0, "truncated": false
        }))
        .unwrap();
        d.mask = mask.map(|m| m.to_rle());
        d
    }

    fn inst(k: usize, obj_id: u32, visib: f64, b: [f64; 4]) -> Instance {
        Instance {
            k,
            obj_id,
            rotation: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            translation: [0.0, 0.0, 500.0],
            visib_fract: visib,
            oracle_visib_fract: None,
            bbox_obj: Some(b),
        }
    }

    /// Matching as the scorer does: greedy by score within a photograph,
    /// a detection on an ignored instance (visib < 0.1) counts neither way,
    /// duplicates and other labels' detections are false positives or
    /// left out; the segmentation takes the top detection on the box.
    #[test]
    fn score_object_matches_the_scorer_rules() {
        let (w, h) = (40usize, 30usize);
        let mut truth = Mask::new(w, h);
        for y in 10..20 {
            for x in 10..20 {
                truth.set(x, y, true);
            }
        }
        let mut half = Mask::new(w, h);
        for y in 10..20 {
            for x in 10..15 {
                half.set(x, y, true);
            }
        }
        let bop = Bop {
            root: std::path::PathBuf::new(),
            models: Default::default(),
            images: vec![
                BopImage {
                    scene: "000002".into(),
                    id: 1,
                    cam_k: [0.0; 9],
                    instances: vec![
                        inst(0, 1, 0.9, [10.0, 10.0, 10.0, 10.0]),
                        inst(1, 6, 0.9, [0.0, 0.0, 5.0, 5.0]),
                    ],
                },
                BopImage {
                    scene: "000002".into(),
                    id: 2,
                    cam_k: [0.0; 9],
                    instances: vec![inst(0, 1, 0.05, [10.0, 10.0, 10.0, 10.0])],
                },
            ],
        };
        let dets = vec![
            vec![
                // The best on the instance (half its mask), a duplicate,
                // a false positive elsewhere, another object's.
                det("ape", 2.0, (10.0, 10.0, 10.0, 10.0), Some(&half)),
                det("ape", 1.5, (10.5, 10.0, 10.0, 10.0), Some(&truth)),
                det("ape", 1.0, (25.0, 0.0, 10.0, 10.0), None),
                det("cat", 3.0, (10.0, 10.0, 10.0, 10.0), None),
            ],
            // On an ignored instance: neither way.
            vec![det("ape", 5.0, (10.0, 10.0, 10.0, 10.0), None)],
        ];
        let s = score_object(&bop, &[0, 1], &dets, 1, "ape", 0.1, |_, _| {
            Some(truth.clone())
        });
        assert_eq!(s.positives, 1);
        // Points: (0,0) (0,1) (.5,1) (1,1): recall 1 from FPPI 0.
        assert!((s.auc - 1.0).abs() < 1e-12, "{s:?}");
        assert!((s.recall_at_1fppi - 1.0).abs() < 1e-12);
        assert_eq!(s.seg_instances, 1);
        assert!((s.seg_error - 0.5).abs() < 1e-12, "{}", s.seg_error);
        // Without raw masks on the hit, no raw figure.
        assert!(s.seg_error_raw.is_nan());
    }

    /// ADD-S of a pose turned about a symmetry axis of the point set is 0.
    #[test]
    fn add_s_ignores_a_symmetry() {
        let pts: Vec<Vector3<f64>> = (0..8)
            .map(|i| {
                let a = i as f64 * std::f64::consts::FRAC_PI_4;
                Vector3::new(a.cos(), a.sin(), 0.0) * 10.0
            })
            .collect();
        let truth = Pose {
            rotation: nalgebra::Matrix3::identity(),
            translation: Vector3::new(0.0, 0.0, 100.0),
        };
        let turned = Pose {
            rotation: nalgebra::Rotation3::from_axis_angle(
                &Vector3::z_axis(),
                std::f64::consts::FRAC_PI_4,
            )
            .into_inner(),
            ..truth
        };
        assert!(add_s(&turned, &truth, &pts) < 1e-9);
        let moved = Pose {
            translation: Vector3::new(0.0, 0.0, 103.0),
            ..truth
        };
        assert!((add_s(&moved, &truth, &pts) - 3.0).abs() < 1e-9);
    }
}
