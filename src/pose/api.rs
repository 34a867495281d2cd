//! The pose request and response of `sdhop-train pose` (and of the coming
//! `POST /pose`): parameters as JSON, the mask from a detection, a client's
//! PNG or none, and the refined pose with its statistics.

use serde::{Deserialize, Serialize};

use super::geometry::{Intrinsics, Pose};
use super::irls::{refine, IrlsParams};
use super::mesh::Mesh;
use super::{EdgeModel, PoseError};
use crate::model::Model;
use crate::pipeline::{detect_image, DetectOptions, DetectionJson, MaskMode};
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;

/// A camera-from-object pose as clients write it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseJson {
    pub rotation: [[f64; 3]; 3],
    pub translation: [f64; 3],
}

/// Where OR-IRLS takes its visibility mask from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MaskSource {
    /// The refined mask of the best detection of `model`.
    Detect,
    /// The mask the client sends.
    Provided,
    /// No mask: plain IRLS.
    #[default]
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
    #[serde(default)]
    pub mask: MaskSource,
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

/// Estimates the pose of `mesh` in `img` as `params` ask; `mask` is the
/// client's mask (needed with `mask: "provided"`), `models` the loaded
/// detector models (one is needed by name with `mask: "detect"`).
pub fn estimate(
    img: &ColorImage,
    mesh: &Mesh,
    params: &PoseParams,
    mask: Option<Mask>,
    models: &[&Model],
) -> Result<PoseResponse, PoseError> {
    let initial = Pose::from_client(
        params.initial_pose.rotation,
        params.initial_pose.translation,
    )?;
    params.intrinsics.validate()?;
    let mut irls = IrlsParams::default();
    if let Some(n) = params.max_iterations {
        irls.max_iterations = n;
    }
    irls.validate()?;
    let (mask, used, detection) = match params.mask {
        MaskSource::None => (None, MaskUsed::None, None),
        MaskSource::Provided => {
            let m = mask.ok_or_else(|| {
                PoseError::InvalidParameter("mask \"provided\" needs a mask image".into())
            })?;
            (Some(m), MaskUsed::Provided, None)
        }
        MaskSource::Detect => {
            let name = params.model.as_deref().ok_or_else(|| {
                PoseError::InvalidParameter("mask \"detect\" needs a model name".into())
            })?;
            let model = models
                .iter()
                .find(|m| m.meta.name == name)
                .ok_or_else(|| PoseError::UnknownModel(name.to_string()))?;
            let opts = DetectOptions {
                max_detections: Some(1),
                masks: MaskMode::Refined,
                ..DetectOptions::default()
            };
            let resp = detect_image(img, &[model], &opts)
                .map_err(|e| PoseError::InvalidParameter(e.to_string()))?;
            let det = resp
                .detections
                .into_iter()
                .next()
                .ok_or_else(|| PoseError::NotDetected(name.to_string()))?;
            let m = det
                .mask
                .as_ref()
                .and_then(Mask::from_rle)
                .ok_or_else(|| PoseError::NotDetected(name.to_string()))?;
            (Some(m), MaskUsed::Detected, Some(det))
        }
    };
    let edges = EdgeModel::new(mesh, irls.crease_degrees);
    let r = refine(
        img,
        &edges,
        &params.intrinsics,
        &initial,
        mask.as_ref(),
        &irls,
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
