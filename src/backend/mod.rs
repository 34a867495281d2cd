//! Compute backends: the feature pyramids (HOG levels and over-segmentation)
//! of a batch of images, behind one small synchronous trait. The CPU backend
//! is the reference; a GPU backend plugs in behind the same trait. A backend
//! is owned by one thread (the inference queue's worker), so it needs no
//! locking of its own.

pub mod cpu;
pub mod gpu;

use serde::Serialize;
use thiserror::Error;

use crate::model::Model;
use crate::vision::detect::DenseBounds;
use crate::vision::energy::ViewWeights;
use crate::vision::image::ColorImage;
use crate::vision::pyramid::{FeaturePyramid, PyramidParams};
use crate::vision::segment::SegmentParams;
use crate::vision::{Deadline, VisionError};

pub use cpu::CpuBackend;
pub use gpu::{GpuBackend, GpuError, GpuOptions};

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

/// One image of a batch and the feature settings it needs. The pyramids
/// built share the image (no copy of it).
pub struct FeatureJob<'a> {
    pub image: &'a std::sync::Arc<ColorImage>,
    pub settings: &'a [(PyramidParams, SegmentParams)],
    /// The request's deadline: a backend may give up on the job once it
    /// has passed ([`VisionError::DeadlineExceeded`]).
    pub deadline: Deadline,
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

    /// The stage-1 chain bounds of every model (its viewpoints and the
    /// largest truncation it scans) on one pyramid, or `None` when the
    /// backend leaves them to the detector (the CPU backend: the detector
    /// computes them as it scans).
    fn dense_bounds(
        &mut self,
        _pyr: &FeaturePyramid,
        _models: &[(&[ViewWeights], f64)],
    ) -> Result<Option<Vec<DenseBounds>>, BackendError> {
        Ok(None)
    }
}

/// Each model's stage-1 bounds on the pyramid with its feature settings, as
/// `backend` computes them (`None` where it leaves them to the detector,
/// or fails): what [`crate::pipeline::detect_prebuilt_with`] takes.
pub fn model_bounds(
    backend: &mut dyn Backend,
    pyramids: &[FeaturePyramid],
    models: &[&Model],
) -> Vec<Option<DenseBounds>> {
    let mut out: Vec<Option<DenseBounds>> = vec![None; models.len()];
    for pyr in pyramids {
        let idx: Vec<usize> = (0..models.len())
            .filter(|&i| {
                let m = &models[i].meta;
                pyr.params == m.pyramid && pyr.seg_params == m.segmentation
            })
            .collect();
        let asks: Vec<(&[ViewWeights], f64)> = idx
            .iter()
            .map(|&i| {
                let m = models[i];
                (m.views.as_slice(), m.meta.detection.max_truncation)
            })
            .collect();
        if let Ok(Some(bounds)) = backend.dense_bounds(pyr, &asks) {
            for (i, b) in idx.into_iter().zip(bounds) {
                out[i] = Some(b);
            }
        }
    }
    out
}

/// Which backend `sdhop-serve --backend` asks for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum BackendChoice {
    /// A real (discrete or integrated) GPU when there is one, else the CPU;
    /// a software adapter (llvmpipe, lavapipe) counts as none.
    #[default]
    Auto,
    Cpu,
    /// The GPU backend on the best adapter, software ones included; fails
    /// when there is no adapter at all.
    Gpu,
}

/// Builds the backend `choice` asks for. With `auto`, also returns why the
/// GPU was not taken, when it was not.
pub fn select(
    choice: BackendChoice,
    options: &GpuOptions,
) -> Result<(Box<dyn Backend>, Option<String>), GpuError> {
    match choice {
        BackendChoice::Cpu => Ok((Box::new(CpuBackend), None)),
        BackendChoice::Gpu => {
            let opts = GpuOptions {
                allow_software: true,
                ..*options
            };
            Ok((Box::new(GpuBackend::new(&opts)?), None))
        }
        BackendChoice::Auto => match GpuBackend::new(options) {
            Ok(b) => Ok((Box::new(b), None)),
            Err(e) => Ok((Box::new(CpuBackend), Some(e.to_string()))),
        },
    }
}
