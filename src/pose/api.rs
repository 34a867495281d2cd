//! The pose request and response of `POST /pose` and `sdhop-train pose`:
//! parameters as JSON, the mask from a detection, a client's PNG or none,
//! and the refined pose with its statistics.

use serde::{Deserialize, Serialize};

use super::geometry::{Intrinsics, Pose};
use super::irls::{refine, IrlsParams};
use super::mesh::Mesh;
use super::{EdgeModel, PoseError};
use crate::model::Model;
use crate::pipeline::{detect_image, DetectOptions, DetectResponse, DetectionJson, MaskMode};
use crate::vision::detect::box_iou;
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;

/// A camera-from-object pose as clients write it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseJson {
    pub rotation: [[f64; 3]; 3],
    pub translation: [f64; 3],
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

/// The `params` of a pose request.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseParams {
    pub intrinsics: Intrinsics,
    pub initial_pose: PoseJson,
    /// The detector model whose mask `mask: "detect"` uses.
    #[serde(default)]
    pub model: Option<String>,
    /// Default: `"provided"` when a mask image is sent, else `"none"`.
    #[serde(default)]
    pub mask: Option<MaskSource>,
    #[serde(default)]
    pub max_iterations: Option<usize>,
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
}

/// Detections of the named model that `mask: "detect"` chooses among.
pub const DETECT_CANDIDATES: usize = 5;

/// The detection options of `mask: "detect"`: the best
/// [`DETECT_CANDIDATES`] detections, with their refined masks.
pub fn detect_options() -> DetectOptions {
    DetectOptions {
        max_detections: Some(DETECT_CANDIDATES),
        masks: MaskMode::Refined,
        ..DetectOptions::default()
    }
}

/// The detection whose (full-object) box overlaps `expected` most, the
/// object's box at the initial pose: the client says where the object is,
/// and the best-scoring detection elsewhere would give a mask of something
/// else. Among equal overlaps the better score (detections come best
/// first). `None` when none overlaps it, or none has a refined mask.
pub fn pick_detection(
    detections: Vec<DetectionJson>,
    expected: Option<(f64, f64, f64, f64)>,
) -> Option<(DetectionJson, Mask)> {
    let overlap = |d: &DetectionJson| {
        expected.map_or(1.0, |e| {
            box_iou((d.bbox.x, d.bbox.y, d.bbox.width, d.bbox.height), e)
        })
    };
    let mut best: Option<(f64, DetectionJson)> = None;
    for d in detections {
        let o = overlap(&d);
        if o > 0.0 && d.mask.is_some() && best.as_ref().is_none_or(|(b, _)| o > *b) {
            best = Some((o, d));
        }
    }
    let (_, det) = best?;
    let mask = det.mask.as_ref().and_then(Mask::from_rle)?;
    Some((det, mask))
}

/// A pose request checked before any work: the initial pose (projected to
/// a rotation), the refinement settings and where the mask comes from.
#[derive(Clone, Debug, PartialEq)]
pub struct Checked {
    pub initial: Pose,
    pub irls: IrlsParams,
    pub source: MaskSource,
}

impl PoseParams {
    /// Checks the parameters against the image's size and the mask the
    /// client sent (if any). Without an explicit `mask`, a sent mask is
    /// used and otherwise none; a sent mask with `mask` other than
    /// `"provided"` is refused rather than ignored.
    pub fn check(
        &self,
        image_size: (usize, usize),
        mask: Option<&Mask>,
    ) -> Result<Checked, PoseError> {
        let initial = Pose::from_client(self.initial_pose.rotation, self.initial_pose.translation)?;
        self.intrinsics.validate()?;
        let mut irls = IrlsParams::default();
        if let Some(n) = self.max_iterations {
            irls.max_iterations = n;
        }
        irls.validate()?;
        let source = self.mask.unwrap_or(if mask.is_some() {
            MaskSource::Provided
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
                if (m.width, m.height) != image_size {
                    return Err(PoseError::InvalidParameter(format!(
                        "the mask is {}x{}, the image {}x{}",
                        m.width, m.height, image_size.0, image_size.1
                    )));
                }
            }
            (other, Some(_)) => {
                return Err(PoseError::InvalidParameter(format!(
                    "a mask image was sent but the parameters ask for mask {:?}",
                    other
                )))
            }
            (_, None) => {}
        }
        if source == MaskSource::Detect && self.model.is_none() {
            return Err(PoseError::InvalidParameter(
                "mask \"detect\" needs a model name".into(),
            ));
        }
        Ok(Checked {
            initial,
            irls,
            source,
        })
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
    estimate_with(img, mesh, params, mask, |name| {
        let model = models
            .iter()
            .find(|m| m.meta.name == name)
            .ok_or_else(|| PoseError::UnknownModel(name.to_string()))?;
        detect_image(img, &[model], &detect_options())
            .map_err(|e| PoseError::InvalidParameter(e.to_string()))
    })
}

/// [`estimate`] with the detection left to `detect`, which runs the named
/// model on the image with [`detect_options`] (the service runs it on its
/// backend's pyramids).
pub fn estimate_with<F>(
    img: &ColorImage,
    mesh: &Mesh,
    params: &PoseParams,
    mask: Option<Mask>,
    detect: F,
) -> Result<PoseResponse, PoseError>
where
    F: FnOnce(&str) -> Result<DetectResponse, PoseError>,
{
    let checked = params.check((img.width(), img.height()), mask.as_ref())?;
    let edges = EdgeModel::new(mesh, checked.irls.crease_degrees);
    let (mask, used, detection) = match checked.source {
        MaskSource::None => (None, MaskUsed::None, None),
        MaskSource::Provided => (mask, MaskUsed::Provided, None),
        MaskSource::Detect => {
            let name = params.model.as_deref().unwrap_or_default();
            let expected = edges.projected_box(&params.intrinsics, &checked.initial);
            let (det, m) = pick_detection(detect(name)?.detections, expected)
                .ok_or_else(|| PoseError::NotDetected(name.to_string()))?;
            (Some(m), MaskUsed::Detected, Some(det))
        }
    };
    let r = refine(
        img,
        &edges,
        &params.intrinsics,
        &checked.initial,
        mask.as_ref(),
        &checked.irls,
    )?;
    Ok(PoseResponse {
        pose: PoseOut {
            rotation: r.pose.rotation_rows(),
            translation: [
                r.pose.translation.x,
                r.pose.translation.y,
                r.pose.translation.z,
            ],
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
    })
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
