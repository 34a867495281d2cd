//! Benchmarks and evaluation harnesses, outside the library's core (the
//! vision, pose, backend, inference and HTTP layers never import this):
//! [`detection`] scores detections and masks as the CMU_KO8 acceptance
//! scorer does, [`bop_detect`] as the LM-O scorer does (with the pose
//! from no start), [`pose`] is the occlusion pose benchmark on rendered
//! scenes, [`plot`] draws their curves.

pub mod bop_detect;
pub mod bop_pose;
pub mod bop_run;
pub mod coco_ap;
pub mod detection;
pub mod plot;
pub mod pose;

pub use detection::*;

/// The six errors of `est` against `truth`: the translation's difference
/// per camera axis times `scale`, and the relative rotation `R_est
/// R_trueᵀ` as roll, pitch and yaw about the camera's x, y and z axes
/// (degrees), all absolute.
pub fn six_errors_scaled(
    est: &crate::pose::Pose,
    truth: &crate::pose::Pose,
    scale: f64,
) -> [f64; 6] {
    let dt = (est.translation - truth.translation) * scale;
    let rel = nalgebra::Rotation3::from_matrix_unchecked(est.rotation * truth.rotation.transpose());
    let (r, p, y) = rel.euler_angles();
    [
        dt.x.abs(),
        dt.y.abs(),
        dt.z.abs(),
        r.to_degrees().abs(),
        p.to_degrees().abs(),
        y.to_degrees().abs(),
    ]
}

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

/// The feature kinds of `models` (`hog`, `cnn` or both, comma-separated),
/// as every evaluation report names them.
pub fn feature_kinds<'a>(models: impl IntoIterator<Item = &'a crate::model::Model>) -> String {
    let kinds: std::collections::BTreeSet<&str> = models
        .into_iter()
        .map(|m| m.meta.pyramid.features.name())
        .collect();
    kinds.into_iter().collect::<Vec<_>>().join(",")
}
