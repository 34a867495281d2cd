//! Admission by cost: a request reserves the memory its computation will
//! take before its image is decoded, against a budget derived from the
//! pod's memory, and gives it back when the worker has dropped the request
//! (not when its caller stopped waiting: a request whose deadline passed
//! still holds its buffers until the worker lets go of them).
//!
//! The cost is estimated from what is known before decoding: the image's
//! declared size and the models' pyramids ([`request_bytes`]). Too much at
//! once waits, in order of arrival, until the request's deadline
//! ([`InferError::MemoryBusy`], 503 with `Retry-After`); a request
//! that alone needs more than the whole budget is refused at once
//! ([`InferError::TooCostly`]).

use std::sync::Arc;
use std::time::Instant;

use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use super::InferError;
use crate::model::Model;
use crate::pipeline::feature_settings;
use crate::vision::cells::{FeatureKind, STRIP_PIXELS};
use crate::vision::pyramid::PyramidParams;

/// The budget's unit: costs are reserved in whole mebibytes.
const MIB: u64 = 1 << 20;

/// The budget without a container memory limit: safe under the Kubernetes
/// manifest's 2560 MiB limit (deploy/sdhop.yaml), with room for the
/// resident models, the runtime and the allocator's retained pages.
pub const DEFAULT_BUDGET_BYTES: u64 = 1536 * MIB;

/// What a container's memory limit keeps back from the budget: the idle
/// process (about 130-300 MB with every model), the bodies of requests
/// waiting for their turn, and the allocator's retained pages.
pub const LIMIT_HEADROOM_BYTES: u64 = 1024 * MIB;

/// The smallest budget derived from a container limit.
pub const MIN_BUDGET_BYTES: u64 = 256 * MIB;

/// Bytes per pixel of the decoded image: RGB `f32`, held by the request
/// and shared by its pyramids.
pub const IMAGE_BYTES_PER_PIXEL: u64 = 12;

/// Bytes per pixel (of the full image) of one pyramid's segmentation at
/// downsample 1: the smoothed image, the 8-connected edges' sort keys and
/// the radix sort's buffer (4 edges of 8 bytes each, twice), the labels;
/// divided by the square of the segmentation's downsampling.
pub const SEGMENT_BYTES_PER_PIXEL: u64 = 96;

/// Bytes per pixel of one level being computed, per compute thread, by
/// feature kind: HOG's planes, gradients and histograms, and the resized
/// level itself where it is not the image (`resized`); the backbone's
/// strip of the level (its rows resized, the stem's 32 channels at stride
/// 2, the next blocks' maps). Learned cells are computed in strips of at
/// most [`STRIP_PIXELS`] (and their margins), so their in-flight memory
/// stops growing there.
pub const fn level_bytes_per_pixel(kind: FeatureKind, resized: bool) -> u64 {
    match (kind, resized) {
        (FeatureKind::Hog, false) => 20,
        (FeatureKind::Hog, true) => 32,
        (FeatureKind::Cnn, _) => 48,
    }
}

/// Bytes per pixel of the levels a pyramid keeps (per unit of level
/// area), with `models` models scanning it: the cells (32 floats per 64
/// pixels) and their segments; for learned cells scanned by several
/// models also the stage-1 planes they share and each one's bounds (HOG
/// models share a low-rank bound whose planes are small).
pub const fn kept_bytes_per_pixel(kind: FeatureKind, models: u64) -> u64 {
    match kind {
        FeatureKind::Hog => 2,
        // The planes are shared by several models of one pyramid, and built
        // only then.
        FeatureKind::Cnn if models > 1 => 2 + 2 * models,
        FeatureKind::Cnn => 2,
    }
}

// Measured against these (benches/request_memory.py, each case the first
// request of a fresh server, peak resident memory above its idle process,
// 2 compute threads), a 4000x4000 photograph: the shipped cup model (HOG,
// 11 levels from 1 to 0.5) 1232 MiB, estimated 1344; the eight shipped
// models 1105 MiB, estimated 1344; an LM-O learned-cell model (pyramid
// 0.80 to 2.11, 8 levels, levels in strips) 1464 MiB, estimated 1530.

/// The memory budget of a server: `budget` if given, else one derived
/// from the container's memory limit (cgroup v2 or v1) minus
/// [`LIMIT_HEADROOM_BYTES`], else [`DEFAULT_BUDGET_BYTES`].
pub fn default_budget_bytes() -> u64 {
    container_limit().map_or(DEFAULT_BUDGET_BYTES, |limit| {
        limit
            .saturating_sub(LIMIT_HEADROOM_BYTES)
            .max(MIN_BUDGET_BYTES)
    })
}

/// The container's memory limit in bytes, if it has one.
fn container_limit() -> Option<u64> {
    [
        "/sys/fs/cgroup/memory.max",
        "/sys/fs/cgroup/memory/memory.limit_in_bytes",
    ]
    .iter()
    .filter_map(|p| std::fs::read_to_string(p).ok())
    .filter_map(|s| s.trim().parse::<u64>().ok())
    // cgroup v1 says "no limit" with a huge number.
    .find(|&l| l < (1 << 50))
}

/// The estimated peak memory of detecting with `models` on a `width x
/// height` image, in bytes: the decoded image, then for each distinct
/// pyramid its segmentation, the levels being computed at once (`threads`
/// of the largest) and the levels it keeps.
pub fn request_bytes(width: usize, height: usize, models: &[&Model], threads: usize) -> u64 {
    let px = (width as u64).saturating_mul(height as u64);
    let pyramids: u64 = feature_settings(models)
        .iter()
        .map(|(p, s)| {
            let scanning = models
                .iter()
                .filter(|m| (m.meta.pyramid, m.meta.segmentation) == (*p, *s))
                .count() as u64;
            let ds = s.downsample.max(1) as u64;
            let seg = px.saturating_mul(SEGMENT_BYTES_PER_PIXEL) / (ds * ds);
            let (largest, total) = level_areas(p);
            let mut level = px as f64 * largest;
            if p.features == FeatureKind::Cnn {
                // A strip and its margins (a quarter more, at most).
                level = level.min(STRIP_PIXELS as f64 * 1.25);
            }
            let per_pixel = level_bytes_per_pixel(p.features, largest > 1.0 + 1e-9);
            let in_flight = (level * per_pixel as f64 * threads.max(1) as f64) as u64;
            let kept =
                (px as f64 * total * kept_bytes_per_pixel(p.features, scanning) as f64) as u64;
            // (The pyramid shares the request's image: no copy of it.)
            seg.saturating_add(in_flight).saturating_add(kept)
        })
        .fold(0u64, u64::saturating_add);
    px.saturating_mul(IMAGE_BYTES_PER_PIXEL)
        .saturating_add(pyramids)
}

/// The largest level's area and the sum of every level's, as fractions
/// of the image's.
fn level_areas(p: &PyramidParams) -> (f64, f64) {
    let scales = p.scales();
    let largest = scales.iter().fold(0.0f64, |m, s| m.max(s * s));
    let total = scales.iter().map(|s| s * s).sum();
    (largest, total)
}

/// The budget: whole mebibytes, handed out in order of arrival.
#[derive(Clone, Debug)]
pub struct MemoryBudget {
    units: Arc<Semaphore>,
    total_mib: u32,
}

/// Memory reserved for one request; given back when dropped.
#[derive(Debug)]
pub struct Reservation {
    _units: OwnedSemaphorePermit,
    mib: u32,
}

impl Reservation {
    /// What it holds, in mebibytes.
    pub fn mib(&self) -> u32 {
        self.mib
    }
}

impl MemoryBudget {
    /// A budget of `bytes` (at least one mebibyte).
    pub fn new(bytes: u64) -> Self {
        let total_mib = (bytes / MIB).clamp(1, u32::MAX as u64) as u32;
        Self {
            units: Arc::new(Semaphore::new(total_mib as usize)),
            total_mib,
        }
    }

    /// The whole budget, in mebibytes.
    pub fn total_mib(&self) -> u32 {
        self.total_mib
    }

    /// What is free now, in mebibytes.
    pub fn free_mib(&self) -> u32 {
        self.units.available_permits() as u32
    }

    /// Reserves `bytes` (rounded up to whole mebibytes), waiting in order
    /// of arrival at most until `deadline`. A cost above the whole budget
    /// is refused at once.
    pub async fn reserve(&self, bytes: u64, deadline: Instant) -> Result<Reservation, InferError> {
        let mib = bytes.div_ceil(MIB).max(1);
        if mib > self.total_mib as u64 {
            return Err(InferError::TooCostly {
                needed_mib: mib,
                budget_mib: self.total_mib as u64,
            });
        }
        let mib = mib as u32;
        let acquire = Arc::clone(&self.units).acquire_many_owned(mib);
        match tokio::time::timeout_at(deadline.into(), acquire).await {
            Ok(Ok(units)) => Ok(Reservation { _units: units, mib }),
            Ok(Err(_)) => Err(InferError::ShuttingDown),
            Err(_) => Err(InferError::MemoryBusy {
                needed_mib: mib as u64,
                budget_mib: self.total_mib as u64,
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[tokio::test]
    async fn reservations_wait_their_turn_and_come_back_when_dropped() {
        let budget = MemoryBudget::new(100 * MIB);
        let far = Instant::now() + Duration::from_secs(30);
        let a = budget.reserve(60 * MIB, far).await.unwrap();
        assert_eq!((a.mib(), budget.free_mib()), (60, 40));
        // Too much at once: waits, and gives up at its deadline.
        let soon = Instant::now() + Duration::from_millis(50);
        assert_eq!(
            budget.reserve(50 * MIB, soon).await.unwrap_err(),
            InferError::MemoryBusy {
                needed_mib: 50,
                budget_mib: 100
            }
        );
        // Once the first is dropped, the waiting one gets its turn.
        let b = budget.clone();
        let waiting = tokio::spawn(async move { b.reserve(50 * MIB, far).await.map(|r| r.mib()) });
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert!(!waiting.is_finished());
        drop(a);
        assert_eq!(waiting.await.unwrap().unwrap(), 50);
        assert_eq!(budget.free_mib(), 100);
        // More than the whole budget: refused at once, saying both.
        let err = budget.reserve(101 * MIB, far).await.unwrap_err();
        assert_eq!(
            err,
            InferError::TooCostly {
                needed_mib: 101,
                budget_mib: 100
            }
        );
    }

    #[test]
    fn the_cost_grows_with_pixels_levels_and_learned_cells() {
        use crate::synth::{hand_model, HandModelParams, SynthObject};
        let obj = SynthObject {
            cols: 12,
            rows: 10,
            seed: 11,
        };
        let hog = hand_model(&obj, "obj", true, &HandModelParams::default()).unwrap();
        let mut cnn = hog.clone();
        cnn.meta.pyramid.features = FeatureKind::Cnn;
        let mut upsampled = hog.clone();
        upsampled.meta.pyramid.max_scale = 2.0;
        let vga = request_bytes(640, 480, &[&hog], 2);
        let big = request_bytes(4000, 4000, &[&hog], 2);
        assert!(big > 50 * vga, "{big} vs {vga}");
        // Learned cells cost more a pixel, until their levels are computed
        // in strips: then their in-flight memory stops growing.
        assert!(request_bytes(640, 480, &[&cnn], 2) > vga);
        let strips = request_bytes(8000, 8000, &[&cnn], 2) - request_bytes(4000, 4000, &[&cnn], 2);
        let whole = request_bytes(8000, 8000, &[&hog], 2) - big;
        assert!(strips < whole, "{strips} vs {whole}");
        assert!(request_bytes(4000, 4000, &[&upsampled], 2) > 2 * big);
        // Two kinds: two pyramids.
        assert!(
            request_bytes(4000, 4000, &[&hog, &cnn], 2) > request_bytes(4000, 4000, &[&cnn], 2)
        );
        // One pyramid for any number of models of the same settings.
        assert_eq!(request_bytes(640, 480, &[&hog, &hog], 2), vga);
    }
}
