//! Benchmarks and evaluation harnesses, outside the library's core (the
//! vision, pose, backend, inference and HTTP layers never import this):
//! [`detection`] scores detections and masks as the CMU_KO8 acceptance
//! scorer does, [`pose`] is the occlusion pose benchmark on rendered
//! scenes, [`plot`] draws their curves.

pub mod bop_pose;
pub mod detection;
pub mod plot;
pub mod pose;

pub use detection::*;

/// The median of `v` (NaN when empty).
pub fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// The mean of each of the six pose errors (X, Y, Z, roll, pitch, yaw)
/// over `n` outcomes.
pub fn mean_errors(errors: impl Iterator<Item = [f64; 6]>, n: usize) -> [f64; 6] {
    let mut mean = [0.0; 6];
    for e in errors {
        for (m, v) in mean.iter_mut().zip(e) {
            *m += v / n.max(1) as f64;
        }
    }
    mean
}
