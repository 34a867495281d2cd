//! What each candidate of `sdhop-train join --check-folds` costs to serve,
//! so that the set's choice can hold the shipped models' time to a budget
//! (`--max-time-ratio`): each object's model in each setting is timed
//! alone, on one compute thread, over the same single-pose photographs,
//! their pyramids built once (the service builds one pyramid per photograph
//! for all models). The set's time is then estimated as the pyramid's time
//! plus the sum of its models' times, and its ratio to the unjoined set's
//! is what the budget bounds.
//!
//! Each photograph is timed [`ROUNDS`] times per model and the fastest
//! kept, which takes out most of the noise of a busy machine; the figures
//! are per photograph, in milliseconds.

use super::RouteError;
use crate::data::{load_image, Sample};
use crate::model::Model;
use crate::pipeline::{detect_pyramid, DetectOptions};
use crate::train::ko8::Ko8Data;
use crate::vision::pyramid::FeaturePyramid;
use std::time::Instant;

/// How many times each photograph is timed per model (the fastest kept).
pub const ROUNDS: usize = 2;

/// The cost pass's figures, the same for every candidate: the
/// pyramid's time, the budget's ratio and the photographs timed.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub struct CostInfo {
    pub pyramid_ms: f64,
    pub max_time_ratio: f64,
    pub photographs: usize,
}

/// The photographs the costs are timed on, their pyramids built, on one
/// compute thread.
pub struct CostBench {
    pool: rayon::ThreadPool,
    pyramids: Vec<FeaturePyramid>,
    /// Mean time to build a photograph's pyramid, ms.
    pub pyramid_ms: f64,
}

/// `n` single-pose photographs of `data`, spread evenly over the objects
/// and over each object's photographs.
pub fn cost_photographs(data: &Ko8Data, n: usize) -> Vec<&Sample> {
    let objects = data.images.len().max(1);
    let per = n.div_ceil(objects);
    let mut out = Vec::new();
    for imgs in &data.images {
        let step = (imgs.len() as f64 / per.max(1) as f64).max(1.0);
        out.extend(
            (0..per.min(imgs.len()))
                .map(|i| &imgs[((i as f64 * step) as usize).min(imgs.len() - 1)]),
        );
    }
    out.truncate(n);
    out
}

impl CostBench {
    /// The bench over `images`, with `m`'s pyramid and segmentation
    /// settings (every model the join compares shares them).
    pub fn new(images: &[&Sample], m: &Model) -> Result<Self, RouteError> {
        if images.is_empty() {
            return Err(RouteError::input(
                "the cost pass needs at least one single-pose photograph",
            ));
        }
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .map_err(RouteError::io)?;
        let mut pyramids = Vec::new();
        let mut total = 0.0;
        for s in images {
            let img = load_image(&s.image).map_err(RouteError::input)?;
            let mut best = f64::INFINITY;
            let mut built = None;
            for _ in 0..ROUNDS {
                let t = Instant::now();
                let p = pool
                    .install(|| FeaturePyramid::build(&img, &m.meta.pyramid, &m.meta.segmentation));
                best = best.min(t.elapsed().as_secs_f64() * 1e3);
                built = Some(p.map_err(RouteError::input)?);
            }
            total += best;
            pyramids.extend(built);
        }
        let pyramid_ms = total / pyramids.len() as f64;
        Ok(Self {
            pool,
            pyramids,
            pyramid_ms,
        })
    }

    /// The figures of this bench under the budget `max_time_ratio`.
    pub fn info(&self, max_time_ratio: f64) -> CostInfo {
        CostInfo {
            pyramid_ms: self.pyramid_ms,
            max_time_ratio,
            photographs: self.pyramids.len(),
        }
    }

    /// Mean time per photograph for `m` alone to answer as the service
    /// does by default (every detection at its threshold, refined masks),
    /// its pyramid already built, ms.
    pub fn model_ms(&self, m: &Model) -> Result<f64, RouteError> {
        let opts = DetectOptions::default();
        let mut total = 0.0;
        for pyr in &self.pyramids {
            let mut best = f64::INFINITY;
            for _ in 0..ROUNDS {
                let t = Instant::now();
                self.pool
                    .install(|| detect_pyramid(pyr, &[m], &opts))
                    .map_err(RouteError::input)?;
                best = best.min(t.elapsed().as_secs_f64() * 1e3);
            }
            total += best;
        }
        Ok(total / self.pyramids.len() as f64)
    }
}

/// The set's estimated time over the unjoined set's: the pyramid's time
/// plus the models' each.
pub fn time_ratio(pyramid_ms: f64, chosen: &[f64], plain: &[f64]) -> f64 {
    let (c, p): (f64, f64) = (chosen.iter().sum(), plain.iter().sum());
    (pyramid_ms + c) / (pyramid_ms + p).max(f64::MIN_POSITIVE)
}

/// What the models of a set may take together under `ratio`, the
/// unjoined models taking `plain` (ms per photograph each) and the
/// pyramid `pyramid_ms`: the budget of `join_set`'s search.
pub fn models_budget(ratio: f64, pyramid_ms: f64, plain: &[f64]) -> f64 {
    ratio * (pyramid_ms + plain.iter().sum::<f64>()) - pyramid_ms
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_budget_is_what_the_ratio_leaves_the_models() {
        let plain = [10.0, 20.0];
        let b = models_budget(1.5, 30.0, &plain);
        assert!((b - 60.0).abs() < 1e-9, "{b}");
        // A set spending exactly the budget is at the ratio.
        assert!((time_ratio(30.0, &[25.0, 35.0], &plain) - 1.5).abs() < 1e-9);
        assert!((time_ratio(30.0, &plain, &plain) - 1.0).abs() < 1e-12);
    }
}
