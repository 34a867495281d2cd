//! The CPU backend: the vision layer's own pyramid code, images of a batch
//! in parallel on the rayon pool.

use rayon::prelude::*;

use super::{Backend, BackendError, BackendInfo, FeatureJob};
use crate::vision::pyramid::FeaturePyramid;

/// Builds pyramids on the CPU.
#[derive(Debug, Default)]
pub struct CpuBackend;

impl Backend for CpuBackend {
    fn info(&self) -> BackendInfo {
        BackendInfo {
            kind: "cpu".into(),
            device: format!("{} threads", rayon::current_num_threads()),
        }
    }

    fn pyramids(
        &mut self,
        batch: &[FeatureJob<'_>],
    ) -> Vec<Result<Vec<FeaturePyramid>, BackendError>> {
        batch
            .par_iter()
            .map(|job| {
                FeaturePyramid::build_all(job.image, job.settings, job.deadline)
                    .map_err(BackendError::from)
            })
            .collect()
    }
}
