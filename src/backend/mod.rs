//! Compute backends: the feature pyramids (HOG levels and over-segmentation)
//! of a batch of images, behind one small synchronous trait. The CPU backend
//! is the reference; a GPU backend plugs in behind the same trait. A backend
//! is owned by one thread (the inference queue's worker), so it needs no
//! locking of its own.

pub mod cpu;

use serde::Serialize;
use thiserror::Error;

use crate::vision::image::ColorImage;
use crate::vision::pyramid::{FeaturePyramid, PyramidParams};
use crate::vision::segment::SegmentParams;
use crate::vision::VisionError;

pub use cpu::CpuBackend;

/// Errors of a backend.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum BackendError {
    /// The input was refused (too small, too large, bad settings).
    #[error(transparent)]
    Vision(#[from] VisionError),
    /// The device stopped working; the backend is unhealthy from now on.
    #[error("compute device lost: {0}")]
    DeviceLost(String),
}

/// What a backend runs on, for `/info` and the logs.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct BackendInfo {
    /// `cpu` or `gpu`.
    pub kind: String,
    /// The device: CPU threads, or the GPU adapter's name and driver.
    pub device: String,
}

/// One image of a batch and the feature settings it needs.
pub struct FeatureJob<'a> {
    pub image: &'a ColorImage,
    pub settings: &'a [(PyramidParams, SegmentParams)],
}

/// A compute backend.
pub trait Backend: Send {
    fn info(&self) -> BackendInfo;

    /// False once the device failed; the service then reports not ready.
    fn healthy(&self) -> bool {
        true
    }

    /// The pyramids of every job of a batch, one per feature setting of the
    /// job, in order. An error refuses one job, not the batch.
    fn pyramids(
        &mut self,
        batch: &[FeatureJob<'_>],
    ) -> Vec<Result<Vec<FeaturePyramid>, BackendError>>;
}
