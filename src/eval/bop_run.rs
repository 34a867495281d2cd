//! The whole pipeline on real photographs in BOP format (LM-O), one
//! folder of models at a time: detection and visible masks as
//! `lmo_detect_eval.py` scores them, and the pose from no start (detect,
//! then OR-IRLS from the detection's start poses, as `POST /pose` without
//! `initial_pose`). `sdhop-train bop-eval` prints, plots and writes the
//! report.

use std::path::Path;
use std::time::Instant;

use nalgebra::Vector3;

use crate::data::bop::{Bop, LINEMOD_NAMES};
use crate::data::load_image;
use crate::eval::bop_detect::{add_s, score_object, scored_instance, DetectScore};
use crate::eval::bop_pose::{
    add, errors, intrinsics, mspd, mspd_recall, mspd_thresholds, truth_pose,
};
use crate::eval::coco_ap::{average_precision, ApFigures, Found, Truth};
use crate::eval::feature_kinds;
use crate::model::Model;
use crate::pipeline::{detect_image, DetectOptions, DetectionJson, MaskMode};
use crate::pose::api::{estimate, MaskSource, PoseParams};
use crate::pose::geometry::Pose;
use crate::pose::Mesh;
use crate::progress::progress_bar;
use crate::vision::detect::box_iou;

/// Why a folder of models could not be scored.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct RunError(pub String);

impl RunError {
    pub fn input(e: impl std::fmt::Display) -> Self {
        Self(e.to_string())
    }
}

/// The pose from no start of every scored instance of the models'
/// objects (`visib_fract` and oracle gap as `scored_instance` says): each
/// photograph's detection, then OR-IRLS from its start poses, as `POST
/// /pose` without `initial_pose` answers.
#[allow(clippy::too_many_arguments)]
fn poses_from_no_start(
    name: &str,
    bop: &Bop,
    images: &[usize],
    labels: &[(String, u32)],
    models: &[Model],
    refs: &[&Model],
    args: &ScanSettings,
    meshes: &std::collections::BTreeMap<u32, (Mesh, Vec<Vector3<f64>>)>,
) -> Result<Vec<PoseOutcome>, RunError> {
    let mut poses = Vec::new();
    let cases: Vec<(usize, usize, &str, u32)> = images
        .iter()
        .flat_map(|&i| {
            let labels = &labels;
            bop.images[i].instances.iter().filter_map(move |g| {
                let (label, _) = labels.iter().find(|(_, id)| *id == g.obj_id)?;
                scored_instance(g, args.max_oracle_gap).then_some((
                    i,
                    g.k,
                    label.as_str(),
                    g.obj_id,
                ))
            })
        })
        .collect();
    let pb = progress_bar(cases.len() as u64, &format!("{name}: pose from no start"));
    for (i, k, label, obj) in cases {
        let image = &bop.images[i];
        let g = &image.instances[k];
        let truth = truth_pose(g)
            .ok_or_else(|| RunError::input(format!("image {}: bad pose", image.id)))?;
        let (mesh, points) = &meshes[&obj];
        let info = &bop.models[&obj];
        let img = load_image(&bop.rgb_path(image)).map_err(RunError::input)?;
        // The model that detects this object (one of several objects'
        // when trained jointly: then the request names the object).
        let model = models
            .iter()
            .find(|m| m.labels().iter().any(|l| l == label))
            .ok_or_else(|| RunError::input(format!("no model detects {label}")))?;
        let (mask_source, mask) = match args.pose_mask {
            PoseMask::Detect => (None, None),
            PoseMask::None => (Some(MaskSource::None), None),
            PoseMask::Oracle => (
                Some(MaskSource::Provided),
                Some(
                    crate::data::load_mask(&bop.mask_visib_path(image, k))
                        .map_err(RunError::input)?,
                ),
            ),
        };
        let params = PoseParams {
            intrinsics: intrinsics(image),
            initial_pose: None,
            label: (model.labels().len() > 1).then(|| label.to_string()),
            model: Some(model.meta.name.clone()),
            mask: mask_source,
            max_iterations: None,
            start_uncertainty: None,
        };
        let t = Instant::now();
        let answer = estimate(&img, mesh, &params, mask, refs);
        let seconds = t.elapsed().as_secs_f64();
        let mut out = PoseOutcome {
            object: label.to_string(),
            image: image.id,
            k,
            visib_fract: g.visib_fract,
            add: None,
            add_ok: false,
            near_miss: false,
            success: false,
            t_error: None,
            depth_error: None,
            lateral_error: None,
            angle: None,
            seconds,
            error: None,
            detection_iou: None,
            start_t_error: None,
            start_angle: None,
            nearest_rotation: None,
            nearest_rotation_any: None,
            mspd: None,
        };
        // The least angle from the truth to a set of start rotations.
        let nearest = |qs: &mut dyn Iterator<Item = &[f64; 4]>| {
            qs.filter_map(crate::pose::start::rotation_from_quaternion)
                .map(|r| {
                    let p = Pose {
                        rotation: r,
                        translation: truth.translation,
                    };
                    errors(&p, &truth, &info.symmetries_discrete).2
                })
                .min_by(f64::total_cmp)
        };
        let views = &model.meta.viewpoints;
        out.nearest_rotation_any = nearest(&mut views.iter().flat_map(|v| v.rotations.iter()));
        match answer {
            Ok(a) => {
                if let (Some(d), Some(b)) = (&a.detection, g.bbox_obj) {
                    out.detection_iou = Some(box_iou(
                        (d.bbox.x, d.bbox.y, d.bbox.width, d.bbox.height),
                        (b[0], b[1], b[2], b[3]),
                    ));
                    out.nearest_rotation = views
                        .get(d.viewpoint)
                        .and_then(|v| nearest(&mut v.rotations.iter()));
                }
                if let Some(sp) = a
                    .start_pose
                    .and_then(|sp| Pose::from_client(sp.rotation, sp.translation).ok())
                {
                    let (_, te, angle) = errors(&sp, &truth, &info.symmetries_discrete);
                    out.start_t_error = Some(te);
                    out.start_angle = Some(angle);
                }
                if let Ok(est) = Pose::from_client(a.pose.rotation, a.pose.translation) {
                    let symmetric = !info.symmetries_discrete.is_empty();
                    let e = if symmetric {
                        add_s(&est, &truth, points)
                    } else {
                        add(&est, &truth, &[], points)
                    };
                    let (_, te, angle) = errors(&est, &truth, &info.symmetries_discrete);
                    out.add = Some(e);
                    out.add_ok = e < 0.1 * info.diameter;
                    out.near_miss = !out.add_ok && e < 0.2 * info.diameter;
                    out.success = te < 0.1 * info.diameter && angle < 5.0;
                    let camera = intrinsics(image);
                    out.mspd = Some(mspd(
                        &est,
                        &truth,
                        &info.symmetries_discrete,
                        points,
                        &camera,
                    ));
                    out.t_error = Some(te);
                    out.angle = Some(angle);
                    // Along and across the truth's viewing ray.
                    let ray = truth.translation.normalize();
                    let d = est.translation - truth.translation;
                    out.depth_error = Some(d.dot(&ray));
                    out.lateral_error = Some((d - ray * d.dot(&ray)).norm());
                }
            }
            Err(e) => out.error = Some(e.to_string()),
        }
        poses.push(out);
        pb.inc(1);
    }
    pb.finish_and_clear();
    Ok(poses)
}

/// Width of LM-O's photographs, which scales BOP's MSPD thresholds.
const LMO_WIDTH: f64 = 640.0;

/// The BOP object id of each detection's label.
fn category_of(labels: &[(String, u32)], label: &str) -> Option<u32> {
    labels.iter().find(|(l, _)| l == label).map(|(_, id)| *id)
}

/// COCO AP of the boxes and of the refined masks over the scored
/// photographs, as BOP 2022 computes it: every instance of a scored
/// object with a visible pixel is a truth (its full-extent box, its
/// visible mask), every detection of a scored object a detection.
fn coco_scores(
    bop: &Bop,
    images: &[usize],
    detections: &[Vec<DetectionJson>],
    labels: &[(String, u32)],
) -> Result<(ApFigures, ApFigures), RunError> {
    let mut truths = Vec::new();
    let mut found = Vec::new();
    // Per truth and detection: its box and mask (decoded one image at a
    // time; the overlaps are kept, not the masks).
    let mut box_iou_of = std::collections::HashMap::new();
    let mut mask_iou_of = std::collections::HashMap::new();
    for &i in images {
        let image = &bop.images[i];
        let mut image_truths = Vec::new();
        for g in &image.instances {
            if labels.iter().all(|(_, id)| *id != g.obj_id) {
                continue;
            }
            let mask = crate::data::load_mask(&bop.mask_visib_path(image, g.k))
                .map_err(RunError::input)?;
            if mask.area() == 0 {
                continue;
            }
            image_truths.push((truths.len(), g.bbox_obj, mask));
            truths.push(Truth {
                image: i,
                category: g.obj_id,
            });
        }
        for d in &detections[i] {
            let Some(category) = category_of(labels, &d.label) else {
                continue;
            };
            let di = found.len();
            found.push(Found {
                image: i,
                category,
                score: d.score,
            });
            let dmask = d
                .mask
                .as_ref()
                .and_then(crate::vision::mask::Mask::from_rle);
            let dbox = (d.bbox.x, d.bbox.y, d.bbox.width, d.bbox.height);
            for (ti, tbox, tmask) in &image_truths {
                if truths[*ti].category != category {
                    continue;
                }
                let b = tbox.map_or(0.0, |b| box_iou(dbox, (b[0], b[1], b[2], b[3])));
                box_iou_of.insert((di, *ti), b);
                let m = dmask.as_ref().map_or(0.0, |m| m.iou(tmask));
                mask_iou_of.insert((di, *ti), m);
            }
        }
    }
    let boxes = average_precision(&truths, &found, |d, t| {
        box_iou_of.get(&(d, t)).copied().unwrap_or(0.0)
    });
    let masks = average_precision(&truths, &found, |d, t| {
        mask_iou_of.get(&(d, t)).copied().unwrap_or(0.0)
    });
    Ok((boxes, masks))
}

/// The detections of the scored photographs in BOP's results format
/// (`eval_bop22_coco.py`): the full-extent box, the refined visible mask
/// as compressed RLE, and the photograph's detection time in seconds
/// (`seconds`, by image index).
fn bop_results(
    bop: &Bop,
    images: &[usize],
    detections: &[Vec<DetectionJson>],
    labels: &[(String, u32)],
    seconds: &[f64],
) -> Vec<serde_json::Value> {
    let mut out = Vec::new();
    for &i in images {
        let image = &bop.images[i];
        let scene: u64 = image.scene.trim_start_matches('0').parse().unwrap_or(0);
        for d in &detections[i] {
            let Some(category) = category_of(labels, &d.label) else {
                continue;
            };
            out.push(serde_json::json!({
                "scene_id": scene,
                "image_id": image.id,
                "category_id": category,
                "score": d.score,
                "bbox": [d.bbox.x, d.bbox.y, d.bbox.width, d.bbox.height],
                "segmentation": d.mask.as_ref().map(|m| m.compress()),
                "time": seconds[i],
            }));
        }
    }
    out
}

/// The models of a folder, each error naming its file.
fn load_models(dir: &Path) -> Result<Vec<Model>, RunError> {
    crate::model::model_paths(dir)
        .map_err(RunError::input)?
        .iter()
        .map(|p| Model::load(p).map_err(|e| RunError::input(format!("{}: {e}", p.display()))))
        .collect()
}

/// How the photographs are scanned and the poses found.
#[derive(Clone, Copy, Debug)]
pub struct ScanSettings {
    /// Detection threshold.
    pub threshold: f64,
    /// Detections kept per image and model.
    pub max_detections: usize,
    /// Most distance (m) of the oracle mask's pose from the truth for the
    /// instance to count among the oracle's.
    pub max_oracle_gap: f64,
    /// The mask of the pose's refinements.
    pub pose_mask: PoseMask,
}

/// The mask of the pose from no start's refinements (`--pose-mask`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum PoseMask {
    Detect,
    Oracle,
    None,
}

/// Pose from no start of one instance.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct PoseOutcome {
    pub object: String,
    pub image: u32,
    pub k: usize,
    pub visib_fract: f64,
    /// `None`: no pose (the request was refused, e.g. nothing detected).
    pub add: Option<f64>,
    pub add_ok: bool,
    /// ADD(-S) between 10% and 20% of the diameter: just past.
    #[serde(default)]
    pub near_miss: bool,
    pub success: bool,
    pub t_error: Option<f64>,
    /// The answer's depth less the truth's (mm; positive: too far), and
    /// its error across the viewing direction.
    #[serde(default)]
    pub depth_error: Option<f64>,
    #[serde(default)]
    pub lateral_error: Option<f64>,
    pub angle: Option<f64>,
    pub seconds: f64,
    pub error: Option<String>,
    /// Where it failed, stage by stage: the box IoU of the detection the
    /// answer came from with the object's true box; the start pose's
    /// translation error and angle; the least angle between the truth and
    /// any start rotation of the detected component (could any start
    /// have been near?), and of every component.
    #[serde(default)]
    pub detection_iou: Option<f64>,
    #[serde(default)]
    pub start_t_error: Option<f64>,
    #[serde(default)]
    pub start_angle: Option<f64>,
    #[serde(default)]
    pub nearest_rotation: Option<f64>,
    #[serde(default)]
    pub nearest_rotation_any: Option<f64>,
    /// BOP's MSPD of the answer (pixels; `None`: no pose).
    #[serde(default)]
    pub mspd: Option<f64>,
}

/// One variant's figures.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct Variant {
    pub name: String,
    pub models_dir: String,
    /// The models' cell features (`hog`, `cnn`).
    #[serde(default)]
    pub features: String,
    pub objects: Vec<DetectScore>,
    pub mean_auc: f64,
    pub mean_seg_error: f64,
    pub mean_seg_error_raw: f64,
    pub mean_recall_at_1fppi: f64,
    pub detect_ms_per_image: f64,
    /// COCO AP of the boxes (full extent, BOP's amodal boxes) and of the
    /// refined visible masks, as BOP's `eval_bop22_coco.py` scores them.
    #[serde(default)]
    pub box_ap: ApFigures,
    #[serde(default)]
    pub mask_ap: ApFigures,
    /// BOP's MSPD recall of the pose from no start (thresholds 5-50 px at
    /// 640 px of width; an instance without a pose counts as missed).
    #[serde(default)]
    pub mspd_recall: Option<f64>,
    #[serde(skip_serializing_if = "Vec::is_empty", default)]
    pub pose: Vec<PoseOutcome>,
    /// The detections in BOP's results format (`scene_id`, `image_id`,
    /// `category_id`, `score`, `bbox`, `segmentation`, `time`); written to
    /// a file of their own, not to the report.
    #[serde(skip)]
    pub results: Vec<serde_json::Value>,
}

impl Variant {
    /// The means over the objects of their figures.
    pub fn set_means(&mut self) {
        let n = self.objects.len().max(1) as f64;
        let mean = |f: &dyn Fn(&DetectScore) -> f64| self.objects.iter().map(f).sum::<f64>() / n;
        self.mean_auc = mean(&|s| s.auc);
        self.mean_seg_error = mean(&|s| s.seg_error);
        self.mean_seg_error_raw = mean(&|s| s.seg_error_raw);
        self.mean_recall_at_1fppi = mean(&|s| s.recall_at_1fppi);
    }
}

pub fn name_of(obj: u32) -> Option<&'static str> {
    LINEMOD_NAMES
        .iter()
        .find(|(id, _)| *id == obj)
        .map(|(_, n)| *n)
}

pub fn id_of(label: &str) -> Option<u32> {
    LINEMOD_NAMES
        .iter()
        .find(|(_, n)| *n == label)
        .map(|(id, _)| *id)
}

/// The labels of `models` that name an object annotated in `bop`, with its
/// BOP id; refused when there is none.
pub fn annotated_labels(
    models: &[Model],
    bop: &Bop,
    dir: &Path,
) -> Result<Vec<(String, u32)>, RunError> {
    let labels: Vec<(String, u32)> = models
        .iter()
        .flat_map(|m| m.meta.viewpoints.iter().map(|v| v.label.clone()))
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .filter_map(|l| id_of(&l).map(|id| (l, id)))
        .filter(|(_, id)| {
            bop.images
                .iter()
                .any(|im| im.instances.iter().any(|g| g.obj_id == *id))
        })
        .collect();
    if labels.is_empty() {
        return Err(RunError::input(format!(
            "{}: no model carries the BOP name of an annotated object (ape, can, cat, ...)",
            dir.display()
        )));
    }
    Ok(labels)
}

/// Scores one folder of models.
#[allow(clippy::too_many_arguments)]
pub fn evaluate(
    name: &str,
    dir: &Path,
    bop: &Bop,
    images: &[usize],
    args: &ScanSettings,
    pose: bool,
    transfer: bool,
    meshes: &std::collections::BTreeMap<u32, (Mesh, Vec<Vector3<f64>>)>,
) -> Result<Variant, RunError> {
    let models = load_models(dir)?;
    let refs: Vec<&Model> = models.iter().collect();
    let labels = annotated_labels(&models, bop, dir)?;
    let opts = DetectOptions {
        threshold: Some(args.threshold),
        max_detections: Some(args.max_detections),
        masks: MaskMode::Both,
        transfer,
        ..DetectOptions::default()
    };
    let pb = progress_bar(images.len() as u64, &format!("{name}: detecting"));
    let mut detections: Vec<Vec<DetectionJson>> = vec![Vec::new(); bop.images.len()];
    let mut seconds = vec![0.0; bop.images.len()];
    let t = Instant::now();
    for &i in images {
        let img = load_image(&bop.rgb_path(&bop.images[i])).map_err(RunError::input)?;
        let ti = Instant::now();
        detections[i] = detect_image(&img, &refs, &opts)
            .map_err(RunError::input)?
            .detections;
        seconds[i] = ti.elapsed().as_secs_f64();
        pb.inc(1);
    }
    pb.finish_and_clear();
    let detect_ms = t.elapsed().as_secs_f64() * 1e3 / images.len().max(1) as f64;
    let objects: Vec<DetectScore> = labels
        .iter()
        .map(|(label, id)| {
            score_object(
                bop,
                images,
                &detections,
                *id,
                label,
                args.max_oracle_gap,
                |im, k| crate::data::load_mask(&bop.mask_visib_path(im, k)).ok(),
            )
        })
        .collect();
    let poses = if pose {
        poses_from_no_start(name, bop, images, &labels, &models, &refs, args, meshes)?
    } else {
        Vec::new()
    };
    let (box_ap, mask_ap) = coco_scores(bop, images, &detections, &labels)?;
    let errors: Vec<f64> = poses
        .iter()
        .map(|p| p.mspd.unwrap_or(f64::INFINITY))
        .collect();
    let mut v = Variant {
        name: name.to_string(),
        models_dir: dir.display().to_string(),
        features: feature_kinds(&models),
        mean_auc: 0.0,
        mean_seg_error: 0.0,
        mean_seg_error_raw: 0.0,
        mean_recall_at_1fppi: 0.0,
        detect_ms_per_image: detect_ms,
        box_ap,
        mask_ap,
        mspd_recall: mspd_recall(&errors, &mspd_thresholds(LMO_WIDTH)),
        objects,
        pose: poses,
        results: bop_results(bop, images, &detections, &labels, &seconds),
    };
    v.set_means();
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::bop::BopImage;
    use crate::pipeline::BoxJson;
    use crate::vision::mask::Mask;

    fn detection(label: &str, score: f64, mask: &Mask) -> DetectionJson {
        DetectionJson {
            label: label.into(),
            model: label.into(),
            score,
            bbox: BoxJson {
                x: 2.0,
                y: 3.0,
                width: 4.0,
                height: 5.0,
            },
            viewpoint: 0,
            view: None,
            level: 0,
            visible_fraction: 1.0,
            truncated: false,
            mask: Some(mask.to_rle()),
            raw_mask: None,
        }
    }

    /// The results read back in the field names and types of BOP's
    /// `eval_bop22_coco.py`, the mask as the compressed RLE pycocotools
    /// reads, only the scored photographs' detections of scored objects.
    #[test]
    fn results_read_back_in_bops_field_names() {
        let bop = Bop {
            root: std::path::PathBuf::new(),
            models: Default::default(),
            images: (0..2)
                .map(|id| BopImage {
                    scene: "000002".into(),
                    id: 17 + id,
                    cam_k: [0.0; 9],
                    instances: Vec::new(),
                })
                .collect(),
        };
        let mut mask = Mask::new(8, 6);
        mask.set(3, 4, true);
        mask.set(4, 4, true);
        let detections = vec![
            vec![detection("ape", 0.5, &mask)],
            vec![detection("ape", 0.7, &mask), detection("mug", 0.9, &mask)],
        ];
        let labels = vec![("ape".to_string(), 1)];
        let out = bop_results(&bop, &[1], &detections, &labels, &[0.0, 0.25]);
        let text = serde_json::to_string(&out).unwrap();
        let back: Vec<serde_json::Value> = serde_json::from_str(&text).unwrap();
        assert_eq!(back.len(), 1, "{back:?}");
        let r = &back[0];
        assert_eq!(r["scene_id"], 2);
        assert_eq!(r["image_id"], 18);
        assert_eq!(r["category_id"], 1);
        assert_eq!(r["score"], 0.7);
        assert_eq!(r["bbox"], serde_json::json!([2.0, 3.0, 4.0, 5.0]));
        assert_eq!(r["time"], 0.25);
        assert_eq!(r["segmentation"]["size"], serde_json::json!([6, 8]));
        let counts: crate::vision::mask::CompressedRle =
            serde_json::from_value(r["segmentation"].clone()).unwrap();
        let decoded = counts.decompress().and_then(|rle| Mask::from_rle(&rle));
        assert_eq!(decoded, Some(mask));
    }
}
