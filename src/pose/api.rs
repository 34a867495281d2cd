//! The pose request and response of `POST /pose` and `sdhop-train pose`:
//! parameters as JSON, the mask from a detection, a client's PNG or none,
//! and the refined pose with its statistics.

use serde::{Deserialize, Serialize};

use super::geometry::{projected_box, Intrinsics, Pose};
use super::irls::{refine_until, IrlsParams, PoseResult};
use super::mesh::Mesh;
use super::params::MAX_ITERATIONS;
use super::start::{appearance, start_poses, start_poses_by_colour};
use super::{EdgeModel, PoseError};
use crate::model::Model;
use crate::pipeline::{detect_image, DetectOptions, DetectResponse, DetectionJson, MaskMode};
use crate::vision::detect::Region;
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;
use crate::vision::Deadline;

/// A camera-from-object pose as clients write it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseJson {
    pub rotation: [[f64; 3]; 3],
    pub translation: [f64; 3],
}

impl From<&Pose> for PoseJson {
    fn from(p: &Pose) -> Self {
        let t = p.translation;
        Self {
            rotation: p.rotation_rows(),
            translation: [t.x, t.y, t.z],
        }
    }
}

/// Where OR-IRLS takes its visibility mask from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MaskSource {
    /// The refined mask of the best detection of `model`.
    Detect,
    /// The mask the client sends.
    Provided,
    /// No mask: plain IRLS.
    None,
}

impl MaskSource {
    /// The name as clients write it.
    pub fn name(self) -> &'static str {
        match self {
            MaskSource::Detect => "detect",
            MaskSource::Provided => "provided",
            MaskSource::None => "none",
        }
    }
}

/// The `params` of a pose request.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseParams {
    pub intrinsics: Intrinsics,
    /// Where to start. Without it, `model` must name a detector trained
    /// from this mesh (`sdhop-train mesh`): the object is detected and
    /// the start poses come from the detections (see [`NO_START_DETECTIONS`]).
    #[serde(default)]
    pub initial_pose: Option<PoseJson>,
    /// The detector model whose mask `mask: "detect"` uses.
    #[serde(default)]
    pub model: Option<String>,
    /// The mesh's object among the labels of `model` when it detects
    /// several objects (trained jointly): only its detections are used.
    /// Needed without `initial_pose` when `model` has several labels.
    #[serde(default)]
    pub label: Option<String>,
    /// Default: `"provided"` when a mask image is sent, else `"none"`.
    #[serde(default)]
    pub mask: Option<MaskSource>,
    #[serde(default)]
    pub max_iterations: Option<usize>,
    /// How far the initial pose may be from the truth (one standard
    /// deviation), the MAP prior of the refinement.
    #[serde(default)]
    pub start_uncertainty: Option<StartUncertainty>,
}

/// The uncertainty of a client's initial pose.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StartUncertainty {
    /// Of its rotation, degrees (default 5; 0: no prior on the rotation).
    #[serde(default)]
    pub degrees: Option<f64>,
    /// Of its translation, mesh units (0: no prior on the translation;
    /// default 5% of the diagonal of the
    /// mesh's bounding box).
    #[serde(default)]
    pub translation: Option<f64>,
}

/// The refined pose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseOut {
    pub rotation: [[f64; 3]; 3],
    pub translation: [f64; 3],
    /// `[w, x, y, z]`.
    pub quaternion: [f64; 4],
}

/// Which mask was used.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MaskUsed {
    Detected,
    Provided,
    None,
}

/// The answer to a pose request.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseResponse {
    pub pose: PoseOut,
    pub converged: bool,
    pub iterations: usize,
    pub residual_rms_px: f64,
    pub inliers: usize,
    pub samples: usize,
    pub covariance: [[f64; 6]; 6],
    pub mask_source: MaskUsed,
    pub detection: Option<DetectionJson>,
    /// Without an initial pose: the start pose the answer was refined
    /// from (placed on the detection's box), and how many starts were
    /// refined.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_pose: Option<PoseJson>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub starts_refined: Option<usize>,
    /// How well the image supports the answered pose: the share of its
    /// visible model edge samples (in the mask) with a compatible image
    /// edge within 1.5 px (see docs/design.md for the cut-off measured on
    /// LM-O).
    pub score: f64,
    /// The same share at the initial pose: how well the image supports the
    /// client's start.
    pub start_score: f64,
    /// No refined pose was supported better than the initial pose (by the
    /// MAP cost), so the initial pose is answered.
    pub start_kept: bool,
    /// The share of the answered pose's outline samples (in the mask)
    /// where the object's and the background's colours change within
    /// 1.5 px of the outline, and the same at the initial pose.
    pub region_score: f64,
    pub start_region_score: f64,
    /// Triangles of the mesh file left out as it was read: repeating a
    /// vertex, without area, or repeating another triangle (see
    /// [`crate::pose::mesh::Mesh::drop_empty_faces`]).
    #[serde(default)]
    pub mesh_faces_dropped: usize,
}

/// The largest `start_uncertainty.degrees` a request may give.
pub const MAX_START_DEGREES: f64 = 1000.0;

/// The least IoU of a detection's box with the box of the mesh at the
/// initial pose, for `mask: "detect"`.
pub const REGION_IOU: f64 = 0.3;

/// The detection options of `mask: "detect"`: the best detection whose box
/// overlaps `expected` (the object's box at the initial pose: the client
/// says where the object is, and the best detection elsewhere would give
/// the mask of something else) by [`REGION_IOU`], with its refined mask.
pub fn detect_options(expected: Option<(f64, f64, f64, f64)>) -> DetectOptions {
    DetectOptions {
        max_detections: Some(1),
        masks: MaskMode::Refined,
        region: expected.map(|bbox| Region {
            bbox,
            min_iou: REGION_IOU,
        }),
        ..DetectOptions::default()
    }
}

/// Without an initial pose: the best detections tried.
pub const NO_START_DETECTIONS: usize = 2;
/// Without an initial pose, the detection threshold (scores in units of
/// the SVM margin): the client says the object is in the image, so weaker
/// detections than a model's own threshold (-0.75) are tried too (the
/// threshold of the LM-O acceptance query).
pub const NO_START_THRESHOLD: f64 = -1.5;
/// Without an initial pose: the start poses refined per detection (the
/// component's rotations whose silhouettes cover the object's colours
/// best, see [`start_poses_by_colour`]; 5 put 9 of 74 LM-O instances
/// within 10% of the diameter against 11 with 3).
pub const NO_START_POSES: usize = 3;
/// Without an initial pose, the default uncertainty of the start poses
/// (rotation, degrees; translation as a share of the start's depth):
/// wider than a client's start, since a component's rotations are some
/// 15 degrees apart and the depth from a detection's box is off by up to
/// a pyramid level.
pub const NO_START_SIGMA_DEGREES: f64 = 15.0;
pub const NO_START_SIGMA_DEPTH: f64 = 0.1;

/// The detections a pose request needs and the start rotations of the
/// model's components (see [`crate::model::ViewMeta::rotations`]).
pub struct Detected {
    pub response: DetectResponse,
    pub view_rotations: Vec<Vec<[f64; 4]>>,
    /// The model's labels (each once, in component order).
    pub labels: Vec<String>,
}

impl Detected {
    /// The detections of `model` in `img` for `params`.
    pub fn run(
        img: &ColorImage,
        model: &Model,
        params: &PoseParams,
        mesh: &Mesh,
        deadline: Deadline,
    ) -> Result<Self, PoseError> {
        let opts = DetectOptions {
            deadline,
            ..params.detect_options(mesh)
        };
        let response = detect_image(img, &[model], &opts).map_err(|e| match e {
            crate::vision::VisionError::DeadlineExceeded => PoseError::DeadlineExceeded,
            e => PoseError::InvalidParameter(e.to_string()),
        })?;
        Ok(Self::from_response(response, model))
    }

    /// The detections found elsewhere (the service's backend), with the
    /// model's rotations.
    pub fn from_response(response: DetectResponse, model: &Model) -> Self {
        Self {
            response,
            view_rotations: model
                .meta
                .viewpoints
                .iter()
                .map(|v| v.rotations.clone())
                .collect(),
            labels: model.labels(),
        }
    }
}

/// The largest projected size of the mesh at the initial pose, in image
/// sizes (each side): a larger projection is refused rather than drawn,
/// since the work of a refinement grows with it.
pub const MAX_PROJECTED_IMAGES: f64 = 4.0;

/// The smallest projected size (pixels, the larger side of its box) of
/// the mesh at the initial pose: nothing smaller has edges to fit.
pub const MIN_PROJECTED_PX: f64 = 4.0;

/// A pose request checked before any work: the initial pose (projected to
/// a rotation), the refinement settings and where the mask comes from.
#[derive(Clone, Debug, PartialEq)]
pub struct Checked {
    /// `None`: the start poses come from the detections.
    pub initial: Option<Pose>,
    pub irls: IrlsParams,
    pub source: MaskSource,
}

impl PoseParams {
    /// The requested `label`, checked against the model's `labels`
    /// (`None`: no label asked).
    pub fn label_of(&self, labels: &[String]) -> Result<Option<&str>, PoseError> {
        match &self.label {
            None => Ok(None),
            Some(l) if labels.contains(l) => Ok(Some(l.as_str())),
            Some(l) => Err(PoseError::InvalidParameter(format!(
                "label {l:?} is not among the labels of model {} ({})",
                self.model.as_deref().unwrap_or_default(),
                labels.join(", ")
            ))),
        }
    }

    /// The detection options of `mask: "detect"` for this request (see
    /// [`detect_options`]): around the mesh's box at the initial pose,
    /// anywhere when the initial pose is unusable (the request then fails
    /// its checks).
    ///
    /// Without an initial pose: the [`NO_START_DETECTIONS`] best
    /// detections anywhere, down to [`NO_START_THRESHOLD`].
    pub fn detect_options(&self, mesh: &Mesh) -> DetectOptions {
        let Some(start) = &self.initial_pose else {
            return DetectOptions {
                threshold: Some(NO_START_THRESHOLD),
                max_detections: Some(NO_START_DETECTIONS),
                label: self.label.clone(),
                masks: MaskMode::Refined,
                ..DetectOptions::default()
            };
        };
        let expected = Pose::from_client(start.rotation, start.translation)
            .ok()
            .and_then(|p| projected_box(&mesh.vertices, &self.intrinsics, &p));
        DetectOptions {
            label: self.label.clone(),
            ..detect_options(expected)
        }
    }

    /// Checks `model` and `label` against the named model's labels before
    /// any work: a model of several objects needs the mesh's object named
    /// without an initial pose, and a label must be one of the model's.
    pub fn check_labels(&self, labels: &[String]) -> Result<(), PoseError> {
        self.label_of(labels)?;
        if self.initial_pose.is_none() && labels.len() > 1 && self.label.is_none() {
            return Err(PoseError::InvalidParameter(format!(
                "model {} detects several objects ({}): name the mesh's object in label",
                self.model.as_deref().unwrap_or_default(),
                labels.join(", ")
            )));
        }
        Ok(())
    }

    /// Checks the request against the model its detection will run
    /// (before any work): the labels (see [`Self::check_labels`]) and,
    /// without an initial pose, that the model carries the training views
    /// that give the start poses.
    pub fn check_model(&self, model: &Model) -> Result<(), PoseError> {
        self.check_labels(&model.labels())?;
        if self.initial_pose.is_none()
            && model.meta.viewpoints.iter().all(|v| v.rotations.is_empty())
        {
            return Err(no_views(&model.meta.name));
        }
        Ok(())
    }

    /// Checks the parameters against the image's size and the size of the
    /// mask the client sent (if any). Without an explicit `mask`, a sent
    /// mask is used and otherwise none; a sent mask with `mask` other than
    /// `"provided"` is refused rather than ignored, and so are `model` and
    /// `label` where no detection uses them.
    pub fn check(
        &self,
        image_size: (usize, usize),
        mask: Option<(usize, usize)>,
    ) -> Result<Checked, PoseError> {
        let initial = self
            .initial_pose
            .map(|p| Pose::from_client(p.rotation, p.translation))
            .transpose()?;
        self.intrinsics.validate()?;
        let mut irls = IrlsParams::default();
        if initial.is_none() {
            if self.model.is_none() {
                return Err(PoseError::InvalidParameter(
                    "without initial_pose, model must name a detector of the object (trained from its mesh by sdhop-train mesh): the start poses come from its detections".into(),
                ));
            }
            irls.start_sigma_degrees = NO_START_SIGMA_DEGREES;
        }
        // Each client field checked by its own name (IrlsParams' own
        // check below is the library's, in its terms).
        let field = |name: &str, v: f64, range: &str| {
            PoseError::InvalidParameter(format!("{name} must be {range}, got {v}"))
        };
        if let Some(n) = self.max_iterations {
            if !(1..=MAX_ITERATIONS).contains(&n) {
                return Err(field(
                    "max_iterations",
                    n as f64,
                    &format!("an integer in 1..={MAX_ITERATIONS}"),
                ));
            }
            irls.max_iterations = n;
        }
        if let Some(u) = self.start_uncertainty {
            if let Some(d) = u.degrees {
                if !(d.is_finite() && (0.0..=MAX_START_DEGREES).contains(&d)) {
                    return Err(field(
                        "start_uncertainty.degrees",
                        d,
                        &format!("a number in 0..={MAX_START_DEGREES}"),
                    ));
                }
                irls.start_sigma_degrees = d;
            }
            if let Some(t) = u.translation {
                if !(t.is_finite() && t >= 0.0) {
                    return Err(field(
                        "start_uncertainty.translation",
                        t,
                        "a finite number, 0 or more (mesh units)",
                    ));
                }
            }
            irls.start_sigma_translation = u.translation;
        }
        irls.validate()?;
        let source = self.mask.unwrap_or(if mask.is_some() {
            MaskSource::Provided
        } else if initial.is_none() {
            MaskSource::Detect
        } else {
            MaskSource::None
        });
        match (source, mask) {
            (MaskSource::Provided, None) => {
                return Err(PoseError::InvalidParameter(
                    "mask \"provided\" needs a mask image".into(),
                ))
            }
            (MaskSource::Provided, Some(m)) => {
                if m != image_size {
                    return Err(PoseError::InvalidParameter(format!(
                        "the mask is {}x{}, the image {}x{}: send a mask of the image's size",
                        m.0, m.1, image_size.0, image_size.1
                    )));
                }
            }
            (other, Some(_)) => {
                return Err(PoseError::InvalidParameter(format!(
                    "a mask image was sent but the parameters ask for mask \"{}\": leave mask out or ask for \"provided\"",
                    other.name()
                )))
            }
            (_, None) => {}
        }
        if source == MaskSource::Detect && self.model.is_none() {
            return Err(PoseError::InvalidParameter(
                "mask \"detect\" needs a model name".into(),
            ));
        }
        if initial.is_some() && source != MaskSource::Detect {
            let unused = match (&self.model, &self.label) {
                (Some(_), Some(_)) => Some("model and label are"),
                (Some(_), None) => Some("model is"),
                (None, Some(_)) => Some("label is"),
                (None, None) => None,
            };
            if let Some(what) = unused {
                return Err(PoseError::InvalidParameter(format!(
                    "{what} used only with mask \"detect\" or without initial_pose; this request refines its initial pose with mask \"{}\"",
                    source.name()
                )));
            }
        }
        Ok(Checked {
            initial,
            irls,
            source,
        })
    }

    /// Checks where the initial pose puts `mesh` in an image of
    /// `image_size`: wholly in front of the camera, projected to at most
    /// [`MAX_PROJECTED_IMAGES`] times the image and at least
    /// [`MIN_PROJECTED_PX`]. Cheap (one pass over the vertices), so it runs
    /// before a request queues.
    pub fn check_projection(
        &self,
        mesh: &Mesh,
        image_size: (usize, usize),
    ) -> Result<(), PoseError> {
        let Some(start) = &self.initial_pose else {
            // The start poses are placed on detections inside the image.
            return self.intrinsics.validate();
        };
        let pose = Pose::from_client(start.rotation, start.translation)?;
        self.intrinsics.validate()?;
        let nearest = mesh
            .vertices
            .iter()
            .map(|v| pose.transform(v).z)
            .fold(f64::INFINITY, f64::min);
        let extent = mesh.vertices.iter().map(|v| v.norm()).fold(0.0, f64::max);
        // In front of the camera by more than a sliver of the object's
        // size: a mesh through the camera plane projects without bound.
        if nearest.is_nan() || nearest <= 1e-3 * extent.max(f64::MIN_POSITIVE) {
            return Err(PoseError::InvalidParameter(format!(
                "the initial pose puts the object at or behind the camera plane (its nearest vertex at z = {nearest:.3e}): the translation must place it in front of the camera"
            )));
        }
        let (w, h) = (image_size.0 as f64, image_size.1 as f64);
        let Some((_, _, bw, bh)) = projected_box(&mesh.vertices, &self.intrinsics, &pose) else {
            return Err(PoseError::InvalidParameter(
                "the initial pose projects no vertex into the camera".into(),
            ));
        };
        if bw > MAX_PROJECTED_IMAGES * w || bh > MAX_PROJECTED_IMAGES * h {
            return Err(PoseError::InvalidParameter(format!(
                "the initial pose and intrinsics project the object to {bw:.3e} x {bh:.3e} pixels, more than {MAX_PROJECTED_IMAGES} times the {w}x{h} image: check fx, fy and the translation's units"
            )));
        }
        if bw.max(bh) < MIN_PROJECTED_PX {
            return Err(PoseError::InvalidParameter(format!(
                "the initial pose and intrinsics project the object to {bw:.3e} x {bh:.3e} pixels, less than {MIN_PROJECTED_PX}: check fx, fy and the translation's units"
            )));
        }
        Ok(())
    }
}

/// Estimates the pose of `mesh` in `img` as `params` ask; `mask` is the
/// client's mask, `models` the loaded detector models (one is needed by
/// name with `mask: "detect"`).
pub fn estimate(
    img: &ColorImage,
    mesh: &Mesh,
    params: &PoseParams,
    mask: Option<Mask>,
    models: &[&Model],
) -> Result<PoseResponse, PoseError> {
    estimate_with(
        img,
        mesh,
        params,
        mask,
        |name| {
            let model = models
                .iter()
                .find(|m| m.meta.name == name)
                .ok_or_else(|| PoseError::UnknownModel(name.to_string()))?;
            Detected::run(img, model, params, mesh, Deadline::NONE)
        },
        Deadline::NONE,
    )
}

/// [`estimate`] with the detection left to `detect`, which runs the named
/// model on the image with [`PoseParams::detect_options`] (the service runs
/// it on its backend's pyramids); gives up once `deadline` has passed.
///
/// With an initial pose, OR-IRLS refines it (with the best detection's
/// mask for `mask: "detect"`). Without, each of the
/// [`NO_START_DETECTIONS`] best detections gives [`NO_START_POSES`] start
/// poses (its component's rotations placed on its box and moved about
/// it, ranked by the colours of the object in its mask against those
/// around its box, see [`start_poses_by_colour`]); OR-IRLS refines each
/// with the detection's mask (or the client's, or none, as `mask` says)
/// and the answer with the best sum of edge and colour agreement (`score`
/// plus `region_score`, plus the [`appearance`] of the mesh's vertex
/// colours where it has them) wins, refined once more as a client's
/// start is where that does not lower its agreement.
pub fn estimate_with<F>(
    img: &ColorImage,
    mesh: &Mesh,
    params: &PoseParams,
    mask: Option<Mask>,
    detect: F,
    deadline: Deadline,
) -> Result<PoseResponse, PoseError>
where
    F: FnOnce(&str) -> Result<Detected, PoseError>,
{
    let checked = params.check(
        (img.width(), img.height()),
        mask.as_ref().map(|m| (m.width, m.height)),
    )?;
    params.check_projection(mesh, (img.width(), img.height()))?;
    let edges = EdgeModel::new(mesh, checked.irls.crease_degrees);
    let name = params.model.as_deref().unwrap_or_default();
    let Some(initial) = checked.initial else {
        // No start: the detections give them.
        let found = detect(name)?;
        return from_detections(img, mesh, &edges, params, &checked, mask, found, deadline);
    };
    let (mask, used, detection) = match checked.source {
        MaskSource::None => (None, MaskUsed::None, None),
        MaskSource::Provided => (mask, MaskUsed::Provided, None),
        MaskSource::Detect => {
            let found = detect(name)?;
            let label = params.label_of(&found.labels)?;
            let det = found
                .response
                .detections
                .into_iter()
                .find(|d| label.is_none_or(|l| d.label == l))
                .ok_or_else(|| not_detected(name, AROUND_START))?;
            let m = det
                .mask
                .as_ref()
                .and_then(Mask::from_rle)
                .ok_or_else(|| not_detected(name, AROUND_START))?;
            (Some(m), MaskUsed::Detected, Some(det))
        }
    };
    let r = refine_until(
        img,
        &edges,
        &params.intrinsics,
        &initial,
        mask.as_ref(),
        &checked.irls,
        deadline,
    )?;
    Ok(response(&r, used, detection, None))
}

/// A model without training views cannot give start poses.
fn no_views(name: &str) -> PoseError {
    PoseError::InvalidParameter(format!(
        "model {name} carries no training views (it was not trained from a mesh by sdhop-train mesh), so it cannot give start poses: send initial_pose"
    ))
}

/// Where a detection with an initial pose looks.
const AROUND_START: (&str, &str) = (
    "around the initial pose (its box overlapping the mesh's box there)",
    "visibility mask",
);
/// Where a detection without an initial pose looks.
const ANYWHERE: (&str, &str) = ("anywhere in the image", "start pose");

fn not_detected(model: &str, (place, what): (&'static str, &'static str)) -> PoseError {
    PoseError::NotDetected {
        model: model.to_string(),
        place,
        what,
    }
}

/// The answer of a refinement.
fn response(
    r: &PoseResult,
    used: MaskUsed,
    detection: Option<DetectionJson>,
    start: Option<(&Pose, usize)>,
) -> PoseResponse {
    let pose = PoseJson::from(&r.pose);
    PoseResponse {
        pose: PoseOut {
            rotation: pose.rotation,
            translation: pose.translation,
            quaternion: r.pose.quaternion(),
        },
        converged: r.converged,
        iterations: r.iterations,
        residual_rms_px: r.residual_rms_px,
        inliers: r.inliers,
        samples: r.samples,
        covariance: r.covariance,
        mask_source: used,
        detection,
        start_pose: start.map(|(p, _)| PoseJson::from(p)),
        starts_refined: start.map(|(_, n)| n),
        score: r.agreement,
        start_score: r.start_agreement,
        start_kept: r.start_kept,
        region_score: r.region_agreement,
        start_region_score: r.start_region_agreement,
        mesh_faces_dropped: 0,
    }
}

/// The pose from no start: see [`estimate_with`].
#[allow(clippy::too_many_arguments)]
fn from_detections(
    img: &ColorImage,
    mesh: &Mesh,
    edges: &EdgeModel,
    params: &PoseParams,
    checked: &Checked,
    client_mask: Option<Mask>,
    found: Detected,
    deadline: Deadline,
) -> Result<PoseResponse, PoseError> {
    let name = params.model.as_deref().unwrap_or_default();
    if found.view_rotations.iter().all(Vec::is_empty) {
        return Err(no_views(name));
    }
    params.check_labels(&found.labels)?;
    let label = params.label_of(&found.labels)?;
    let mut best: Option<(PoseResult, DetectionJson, Pose, f64)> = None;
    let mut refined = 0usize;
    let mut too_few: Option<PoseError> = None;
    for det in found
        .response
        .detections
        .into_iter()
        .filter(|d| label.is_none_or(|l| d.label == l))
        .take(NO_START_DETECTIONS)
    {
        // An empty mask has nothing to fit: the box alone then.
        let det_mask = det
            .mask
            .as_ref()
            .and_then(Mask::from_rle)
            .filter(|m| m.area() > 0);
        let rotations = found
            .view_rotations
            .get(det.viewpoint)
            .map(Vec::as_slice)
            .unwrap_or_default();
        let b = &det.bbox;
        let bbox = (b.x, b.y, b.width, b.height);
        // The starts ranked by the image's colours; by the silhouette's
        // agreement with the mask where the colours tell nothing apart
        // (LM-O ape, 37 instances: the chosen start within 30 degrees in
        // 38% against 11%, ADD(-S) < 10% d 3 against 1; docs/training.md).
        let by_colour = match det_mask.as_ref() {
            Some(m) => start_poses_by_colour(
                mesh,
                &params.intrinsics,
                img,
                bbox,
                m,
                rotations,
                NO_START_POSES,
                &deadline,
            )?,
            _ => None,
        };
        let starts = match by_colour {
            Some(s) => s,
            None => start_poses(
                mesh,
                &params.intrinsics,
                bbox,
                det_mask.as_ref(),
                rotations,
                NO_START_POSES,
                &deadline,
            )?,
        };
        let refine_mask = match checked.source {
            MaskSource::Detect => det_mask.as_ref(),
            MaskSource::Provided => client_mask.as_ref(),
            MaskSource::None => None,
        };
        for s in starts {
            let mut irls = checked.irls;
            if params
                .start_uncertainty
                .and_then(|u| u.translation)
                .is_none()
            {
                irls.start_sigma_translation =
                    Some(NO_START_SIGMA_DEPTH * s.pose.translation.norm());
            }
            let r = match refine_until(
                img,
                edges,
                &params.intrinsics,
                &s.pose,
                refine_mask,
                &irls,
                deadline,
            ) {
                Ok(r) => r,
                // A start whose object shows too few edges: try the next.
                Err(e @ PoseError::NotEnoughEdges(_)) => {
                    too_few = Some(e);
                    continue;
                }
                Err(e) => return Err(e),
            };
            refined += 1;
            // Edges and colours both: either alone is fooled by a start
            // that fits part of the outline (a wrong depth matches the
            // nearer edges of a box, a wrong turn the colours of a side).
            // With the mesh's vertex colours, also how well they match the
            // image's in the mask: an object turned about shows the same
            // outline, but not its colours in the same places (LM-O ape
            // and duck, 74 instances: ADD(-S) < 10% d 11 against 9;
            // ranking the starts by them instead lost 3; docs/training.md).
            let look = match det_mask.as_ref() {
                Some(m) => {
                    appearance(mesh, &params.intrinsics, img, &r.pose, m, &deadline)?.unwrap_or(0.0)
                }
                None => 0.0,
            };
            let score = r.agreement + r.region_agreement + look;
            if best.as_ref().is_none_or(|(_, _, _, b)| score > *b) {
                best = Some((r, det.clone(), s.pose, score));
            }
        }
    }
    // Detections whose starts all showed too few edges say so; none at
    // all is "not detected".
    let (mut r, det, start, _) =
        best.ok_or_else(|| too_few.unwrap_or_else(|| not_detected(name, ANYWHERE)))?;
    // The best answer refined once more as a client's start is (the
    // default start prior, unless the client gave one), kept where the
    // image supports it at least as well (LM-O ape and duck, 74
    // instances: ADD(-S) < 10% d for 9 against 7, the median time
    // unchanged; without the mask 7, three times over 8; docs/training.md).
    {
        let mut irls = checked.irls;
        if params.start_uncertainty.and_then(|u| u.degrees).is_none() {
            irls.start_sigma_degrees = IrlsParams::default().start_sigma_degrees;
        }
        let refine_mask = match checked.source {
            MaskSource::Detect => det
                .mask
                .as_ref()
                .and_then(Mask::from_rle)
                .filter(|m| m.area() > 0),
            MaskSource::Provided => client_mask.clone(),
            MaskSource::None => None,
        };
        match refine_until(
            img,
            edges,
            &params.intrinsics,
            &r.pose,
            refine_mask.as_ref(),
            &irls,
            deadline,
        ) {
            Ok(p) if p.agreement + p.region_agreement >= r.agreement + r.region_agreement => {
                r = PoseResult {
                    start_agreement: r.start_agreement,
                    start_region_agreement: r.start_region_agreement,
                    ..p
                };
            }
            Ok(_) | Err(PoseError::NotEnoughEdges(_)) => {}
            Err(e) => return Err(e),
        }
    }
    let used = match checked.source {
        MaskSource::Detect => MaskUsed::Detected,
        MaskSource::Provided => MaskUsed::Provided,
        MaskSource::None => MaskUsed::None,
    };
    Ok(response(&r, used, Some(det), Some((&start, refined))))
}

/// A mask from an image: non-zero pixels (any channel) are visible.
pub fn mask_from_image(img: &image::DynamicImage) -> Mask {
    let rgb = img.to_rgb8();
    let (w, h) = rgb.dimensions();
    let mut m = Mask::new(w as usize, h as usize);
    for (x, y, p) in rgb.enumerate_pixels() {
        if p.0.iter().any(|&v| v != 0) {
            m.set(x as usize, y as usize, true);
        }
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(fx: f64, t: [f64; 3]) -> PoseParams {
        PoseParams {
            intrinsics: Intrinsics {
                fx,
                fy: fx,
                cx: 320.0,
                cy: 240.0,
            },
            label: None,
            initial_pose: Some(PoseJson {
                rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                translation: t,
            }),
            model: None,
            mask: None,
            max_iterations: None,
            start_uncertainty: None,
        }
    }

    #[test]
    fn projections_without_bound_or_without_size_are_refused() {
        let mesh = Mesh::cuboid(0.1, 0.1, 0.1);
        let size = (640, 480);
        assert!(params(600.0, [0.0, 0.0, 0.5])
            .check_projection(&mesh, size)
            .is_ok());
        for (p, why) in [
            (params(1e12, [0.0, 0.0, 1.0]), "more than 4 times"),
            (params(600.0, [0.0, 0.0, 1e-6]), "camera plane"),
            (params(600.0, [0.0, 0.0, -0.5]), "camera plane"),
            (params(600.0, [0.0, 0.0, 0.06]), "more than 4 times"),
            (params(1e-3, [0.0, 0.0, 0.5]), "less than 4"),
        ] {
            match p.check_projection(&mesh, size) {
                Err(PoseError::InvalidParameter(m)) => assert!(m.contains(why), "{m}"),
                other => panic!("{:?}: {other:?}", p.initial_pose),
            }
        }
    }
}
