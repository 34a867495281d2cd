//! The occlusion pose benchmark (paper section 3.3 on objects the project
//! makes itself): meshes rendered at known poses over real backgrounds,
//! hidden in part by random occluders, with noise and blur; the initial
//! pose perturbed by about 1 cm and 5 degrees. It generates the training
//! set of a detector for each object (COCO, for `sdhop-train train
//! --coco`) and scores IRLS, OR-IRLS with the exact visible mask and
//! OR-IRLS with the mask of that detector on held-out backgrounds.

use std::time::Instant;

use nalgebra::{Rotation3, Vector3};
use serde::Serialize;

use super::median;
use crate::model::Model;
use crate::pipeline::detect_image;
use crate::pose::api::detect_options;
use crate::pose::geometry::{projected_box, Intrinsics, Pose};
use crate::pose::irls::{refine, IrlsParams};
use crate::pose::mesh::Mesh;
use crate::pose::render::{perturb, render, PoseScene};
use crate::pose::EdgeModel;
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;
use crate::vision::rng::SplitMix64;
use crate::vision::segment::gaussian_blur;
use crate::vision::VisionError;

/// The camera of every benchmark scene (640x480).
pub const CAMERA: Intrinsics = Intrinsics {
    fx: 600.0,
    fy: 600.0,
    cx: 320.0,
    cy: 240.0,
};

/// An object of the benchmark: its mesh and the rotation it is seen at
/// (give or take [`BenchSettings::view_jitter_degrees`]).
pub struct BenchObject {
    pub name: &'static str,
    pub mesh: Mesh,
    pub view: Rotation3<f64>,
}

/// The two objects, each seen from above at an angle: a box 15x10x7 cm,
/// and a rounded one, a bottle 10x6 cm across with corners of 2.5 cm
/// radius, 16 cm tall (rounded but not symmetric about an axis, so that
/// its whole rotation can be told from its edges).
pub fn objects() -> Vec<BenchObject> {
    vec![
        BenchObject {
            name: "box",
            mesh: Mesh::cuboid(0.15, 0.10, 0.07),
            view: Rotation3::from_euler_angles(0.5, 0.6, 0.2),
        },
        BenchObject {
            name: "bottle",
            mesh: Mesh::rounded_box(0.10, 0.06, 0.16, 0.025, 8),
            // Upright in the image, its top towards the camera, turned.
            view: Rotation3::from_axis_angle(&Vector3::x_axis(), 1.95)
                * Rotation3::from_axis_angle(&Vector3::z_axis(), 0.5),
        },
    ]
}

/// Settings of the scenes.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct BenchSettings {
    /// Each rotation angle of the view varies within this (degrees).
    pub view_jitter_degrees: f64,
    /// Distances of the object (metres).
    pub depth: (f64, f64),
    /// Start pose: this far (metres) and this many degrees off.
    pub perturb_m: f64,
    pub perturb_degrees: f64,
    /// Image noise (standard deviation, 0..255) and Gaussian blur (sigma,
    /// pixels) drawn per scene within these.
    pub noise: (f64, f64),
    pub blur: (f64, f64),
    /// A refinement succeeds within these errors.
    pub success_mm: f64,
    pub success_degrees: f64,
}

impl Default for BenchSettings {
    fn default() -> Self {
        Self {
            view_jitter_degrees: 10.0,
            depth: (0.45, 0.6),
            perturb_m: 0.01,
            perturb_degrees: 5.0,
            noise: (2.0, 6.0),
            blur: (0.5, 1.2),
            success_mm: 5.0,
            success_degrees: 2.0,
        }
    }
}

/// A benchmark scene: the render with its truth and start pose.
pub struct BenchScene {
    pub scene: PoseScene,
    pub start: Pose,
    /// The object's full extent in pixels, `(x, y, width, height)`.
    pub full_box: (f64, f64, f64, f64),
    /// The box of the mesh at the start pose: where a client would say the
    /// object is (the detector looks there).
    pub start_box: Option<(f64, f64, f64, f64)>,
}

/// Renders `object` at a random pose over `background`, hidden by an
/// occluder covering a fraction of the object's pixels within `occlusion`
/// (`(0, 0)`: none), with noise and blur; deterministic from `seed`.
pub fn scene(
    object: &BenchObject,
    background: &ColorImage,
    occlusion: (f64, f64),
    settings: &BenchSettings,
    seed: u64,
) -> Result<BenchScene, VisionError> {
    let mut rng = SplitMix64::new(seed ^ 0x9e37_79b9_7f4a_7c15);
    let j = settings.view_jitter_degrees.to_radians();
    let jitter = Rotation3::from_euler_angles(
        rng.range_f64(-j, j),
        rng.range_f64(-j, j),
        rng.range_f64(-j, j),
    );
    let z = rng.range_f64(settings.depth.0, settings.depth.1);
    let (w, h) = (background.width() as f64, background.height() as f64);
    // The centre anywhere that keeps the object inside the image.
    let margin = 0.12 * CAMERA.fx / z;
    let u = rng.range_f64(margin, (w - margin).max(margin + 1.0));
    let v = rng.range_f64(margin, (h - margin).max(margin + 1.0));
    let pose = Pose {
        rotation: (jitter * object.view).into_inner(),
        translation: Vector3::new(
            (u - CAMERA.cx) / CAMERA.fx * z,
            (v - CAMERA.cy) / CAMERA.fy * z,
            z,
        ),
    };
    let noise = rng.range_f64(settings.noise.0, settings.noise.1);
    let blur = rng.range_f64(settings.blur.0, settings.blur.1);
    let clean = render(&object.mesh, &CAMERA, &pose, background, 0.0, 0.0, seed)?;
    let full_box = clean
        .visible
        .tight_box()
        .map_or((0.0, 0.0, 0.0, 0.0), |(x0, y0, x1, y1)| {
            (x0 as f64, y0 as f64, (x1 - x0) as f64, (y1 - y0) as f64)
        });
    // The occluder's strip covers a share of the object's box; draw shares
    // until the hidden share of its pixels falls in the range.
    let mut scene = clean;
    if occlusion.1 > 0.0 {
        let mut best: Option<PoseScene> = None;
        for attempt in 0..40u64 {
            let strip = rng.range_f64(occlusion.0, occlusion.1 + 0.1).min(0.95);
            let s = render(
                &object.mesh,
                &CAMERA,
                &pose,
                background,
                strip,
                0.0,
                seed.wrapping_mul(131).wrapping_add(attempt),
            )?;
            let f = s.occluded_fraction;
            let inside = f >= occlusion.0 && f <= occlusion.1;
            let mid = 0.5 * (occlusion.0 + occlusion.1);
            let better = best
                .as_ref()
                .is_none_or(|b| (f - mid).abs() < (b.occluded_fraction - mid).abs());
            if inside {
                best = Some(s);
                break;
            }
            if better {
                best = Some(s);
            }
        }
        if let Some(b) = best {
            scene = b;
        }
    }
    // Blur, then noise, as a camera would.
    let blurred = gaussian_blur(&scene.image, blur as f32);
    let mut data = blurred.data().to_vec();
    for v in data.iter_mut() {
        let n: f64 = (0..4).map(|_| rng.next_f64() - 0.5).sum::<f64>() * 3f64.sqrt();
        *v = (*v + (n * noise) as f32).clamp(0.0, 255.0);
    }
    scene.image = ColorImage::new(blurred.width(), blurred.height(), data)?;
    let start = perturb(
        &pose,
        settings.perturb_m,
        settings.perturb_degrees,
        seed.wrapping_add(7919),
    );
    Ok(BenchScene {
        scene,
        start_box: projected_box(&object.mesh.vertices, &CAMERA, &start),
        start,
        full_box,
    })
}

/// How a method's mask is found.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// No mask.
    Irls,
    /// The exact visible mask of the render.
    OrIrlsExact,
    /// The refined mask of the detector's best detection about the start
    /// pose (as `mask: "detect"` finds it).
    OrIrlsSdhop,
}

/// One refinement's outcome.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Outcome {
    pub method: Method,
    /// Absolute errors: X, Y, Z (mm) and roll, pitch, yaw (degrees).
    pub errors: [f64; 6],
    /// Rotation angle (degrees) and translation distance (mm) errors.
    pub angle_degrees: f64,
    pub distance_mm: f64,
    pub success: bool,
    /// The refinement failed (too few edges) or, for the detector's mask,
    /// nothing was detected: the start pose is scored.
    pub failed: bool,
    /// Milliseconds: detection (SD-HOP mask only) and refinement.
    pub detect_ms: f64,
    pub refine_ms: f64,
}

/// The six errors of `est` against `truth`: the translation's difference
/// per camera axis (mm, the benchmark's poses being in metres), and the
/// relative rotation `R_est R_trueᵀ` as roll, pitch and yaw about the
/// camera's x, y and z axes (degrees).
pub fn six_errors(est: &Pose, truth: &Pose) -> [f64; 6] {
    super::six_errors_scaled(est, truth, 1e3)
}

/// Refines the scene's start pose with each method.
pub fn evaluate(
    edges: &EdgeModel,
    bench: &BenchScene,
    detector: Option<&Model>,
    settings: &BenchSettings,
    params: &IrlsParams,
) -> Vec<Outcome> {
    let img = &bench.scene.image;
    let truth = &bench.scene.pose;
    let mut out = Vec::new();
    let mut run = |method: Method, mask: Option<&Mask>, detect_ms: f64, missed: bool| {
        let t = Instant::now();
        let result = if missed {
            None
        } else {
            refine(img, edges, &CAMERA, &bench.start, mask, params).ok()
        };
        let refine_ms = t.elapsed().as_secs_f64() * 1e3;
        let failed = result.is_none();
        let est = result.map_or(bench.start, |r| r.pose);
        let (angle, dist) = est.distance(truth);
        let (angle_degrees, distance_mm) = (angle.to_degrees(), dist * 1e3);
        out.push(Outcome {
            method,
            errors: six_errors(&est, truth),
            angle_degrees,
            distance_mm,
            success: angle_degrees <= settings.success_degrees
                && distance_mm <= settings.success_mm,
            failed,
            detect_ms,
            refine_ms,
        });
    };
    run(Method::Irls, None, 0.0, false);
    run(Method::OrIrlsExact, Some(&bench.scene.visible), 0.0, false);
    if let Some(model) = detector {
        let t = Instant::now();
        let mask = detect_image(img, &[model], &detect_options(bench.start_box))
            .ok()
            .and_then(|r| r.detections.into_iter().next())
            .and_then(|d| d.mask.as_ref().and_then(Mask::from_rle));
        let detect_ms = t.elapsed().as_secs_f64() * 1e3;
        let missed = mask.is_none();
        run(Method::OrIrlsSdhop, mask.as_ref(), detect_ms, missed);
    }
    out
}

/// Means of a set of outcomes of one method.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Summary {
    pub method: Method,
    pub scenes: usize,
    /// Mean X, Y, Z (mm), roll, pitch, yaw (degrees).
    pub mean_errors: [f64; 6],
    pub mean_angle_degrees: f64,
    pub mean_distance_mm: f64,
    /// Standard errors of the two means (sample standard deviation over
    /// the square root of the scene count; 0 for a single scene).
    pub se_angle_degrees: f64,
    pub se_distance_mm: f64,
    pub median_angle_degrees: f64,
    pub median_distance_mm: f64,
    pub success_rate: f64,
    pub failed: usize,
    pub mean_total_ms: f64,
}

/// Mean and standard error of the mean of `v` (not empty).
fn mean_and_se(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    if v.len() < 2 {
        return (mean, 0.0);
    }
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
    (mean, (var / n).sqrt())
}

/// The summary of `method`'s outcomes.
pub fn summarize(outcomes: &[Outcome], method: Method) -> Option<Summary> {
    let o: Vec<&Outcome> = outcomes.iter().filter(|o| o.method == method).collect();
    if o.is_empty() {
        return None;
    }
    let n = o.len() as f64;
    let mean = super::mean_errors(o.iter().map(|x| x.errors), o.len());
    let angles: Vec<f64> = o.iter().map(|x| x.angle_degrees).collect();
    let distances: Vec<f64> = o.iter().map(|x| x.distance_mm).collect();
    let (mean_angle_degrees, se_angle_degrees) = mean_and_se(&angles);
    let (mean_distance_mm, se_distance_mm) = mean_and_se(&distances);
    Some(Summary {
        method,
        scenes: o.len(),
        mean_errors: mean,
        mean_angle_degrees,
        mean_distance_mm,
        se_angle_degrees,
        se_distance_mm,
        median_angle_degrees: median(angles),
        median_distance_mm: median(distances),
        success_rate: o.iter().filter(|x| x.success).count() as f64 / n,
        failed: o.iter().filter(|x| x.failed).count(),
        mean_total_ms: o.iter().map(|x| x.detect_ms + x.refine_ms).sum::<f64>() / n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose::render::background;

    #[test]
    fn six_errors_are_per_axis() {
        let truth = Pose {
            rotation: Rotation3::from_euler_angles(0.3, 0.2, 0.1).into_inner(),
            translation: Vector3::new(0.0, 0.0, 0.5),
        };
        let est = Pose {
            rotation: (Rotation3::from_euler_angles(0.0, 0.0, 2f64.to_radians())
                * Rotation3::from_matrix_unchecked(truth.rotation))
            .into_inner(),
            translation: truth.translation + Vector3::new(0.001, -0.002, 0.003),
        };
        let e = six_errors(&est, &truth);
        for (a, b) in e.iter().zip([1.0, 2.0, 3.0, 0.0, 0.0, 2.0]) {
            assert!((a - b).abs() < 1e-9, "{e:?}");
        }
    }

    #[test]
    fn summaries_give_means_standard_errors_and_medians_per_method() {
        let outcome = |method, angle_degrees: f64, distance_mm: f64| Outcome {
            method,
            errors: [distance_mm, 0.0, 0.0, angle_degrees, 0.0, 0.0],
            angle_degrees,
            distance_mm,
            success: angle_degrees <= 2.0,
            failed: false,
            detect_ms: 0.0,
            refine_ms: 1.0,
        };
        let outcomes = [
            outcome(Method::Irls, 1.0, 2.0),
            outcome(Method::OrIrlsExact, 100.0, 100.0),
            outcome(Method::Irls, 3.0, 4.0),
            outcome(Method::Irls, 8.0, 6.0),
        ];
        let s = summarize(&outcomes, Method::Irls).unwrap();
        assert_eq!(s.scenes, 3);
        assert!((s.mean_angle_degrees - 4.0).abs() < 1e-12);
        // Deviations -3, -1, 4: variance 26 / 2 = 13, se sqrt(13 / 3).
        assert!((s.se_angle_degrees - (13.0f64 / 3.0).sqrt()).abs() < 1e-12);
        // Deviations -2, 0, 2: variance 4, se sqrt(4 / 3).
        assert!((s.se_distance_mm - (4.0f64 / 3.0).sqrt()).abs() < 1e-12);
        assert_eq!((s.median_angle_degrees, s.median_distance_mm), (3.0, 4.0));
        assert!((s.success_rate - 1.0 / 3.0).abs() < 1e-12);
        assert_eq!(s.mean_errors[0], 4.0);
        let one = summarize(&outcomes, Method::OrIrlsExact).unwrap();
        assert_eq!((one.se_angle_degrees, one.se_distance_mm), (0.0, 0.0));
        assert!(summarize(&outcomes, Method::OrIrlsSdhop).is_none());
    }

    #[test]
    fn scenes_are_hidden_within_the_asked_range_and_in_the_image() {
        let bg = background(640, 480, 1).unwrap();
        let settings = BenchSettings::default();
        for object in objects() {
            for seed in 0..6 {
                let s = scene(&object, &bg, (0.2, 0.6), &settings, seed).unwrap();
                let f = s.scene.occluded_fraction;
                assert!((0.2..=0.6).contains(&f), "{} {seed}: {f}", object.name);
                let (x, y, w, h) = s.full_box;
                assert!(x >= 0.0 && y >= 0.0 && x + w <= 640.0 && y + h <= 480.0);
                let (angle, dist) = s.start.distance(&s.scene.pose);
                assert!((angle.to_degrees() - 5.0).abs() < 1e-6 && (dist - 0.01).abs() < 1e-9);
                let clean = scene(&object, &bg, (0.0, 0.0), &settings, seed).unwrap();
                assert_eq!(clean.scene.occluded_fraction, 0.0);
            }
        }
    }
}
