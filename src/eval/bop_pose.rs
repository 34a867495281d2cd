//! Pose refinement on real photographs in BOP format (LM-O): the protocol
//! of `../shared/tools/lmo_pose.py` run in process. Per object, instances
//! whose `visib_fract` lies in a range (in a seeded order, those whose
//! visible mask was rendered from annotated occluders only: the oracle's
//! visible fraction within a gap of BOP's), each started from the true
//! pose turned by exactly `degrees` about a random axis and moved by
//! exactly `mm` in a random direction (seeded per instance), refined by
//! IRLS (no mask) and OR-IRLS (the visible mask), and scored as the
//! paper's Table 2 (mean X, Y, Z, roll, pitch, yaw), |t|, angle, medians,
//! BOP-style success (|t| < 10% of the diameter and angle < 5 degrees,
//! symmetric objects against their closest symmetric pose) and latency.
//!
//! The starts are drawn with this project's generator, not numpy's: the
//! instances are those of `lmo_pose.py` only where the selection agrees,
//! and the figures agree with it statistically, not start for start.

use std::time::Instant;

use nalgebra::{Matrix3, Rotation3, Unit, Vector3};
use serde::Serialize;

use super::median;
use crate::data::bop::{Bop, BopImage, Instance};
use crate::data::load_image;
use crate::pose::api::{
    estimate, mask_from_image, MaskSource, PoseJson, PoseParams, PoseResponse, StartUncertainty,
};
use crate::pose::geometry::nearest_rotation;
use crate::pose::{Intrinsics, Mesh, Pose, PoseError};
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;
use crate::vision::rng::SplitMix64;

/// A row of the benchmark: which instances and how far the starts are.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Row {
    pub name: String,
    /// `visib_fract` range, inclusive.
    pub visib: (f64, f64),
    pub start_degrees: f64,
    pub start_mm: f64,
    /// Send the start's distance as its uncertainty (`start_uncertainty`:
    /// the row's degrees and mm), as a client that knows it would; else
    /// the service's default.
    pub prior_from_start: bool,
    /// Send this uncertainty (degrees, mesh units) with every request
    /// instead (as a client that states its own).
    #[serde(default)]
    pub uncertainty: Option<(f64, f64)>,
    /// Which instances of the visibility range: all, those whose full
    /// extent touches the image's border, or cropped photographs.
    #[serde(default)]
    pub cut: Cut,
    /// Only instances whose full extent's diagonal is at least this many
    /// pixels (large and near objects).
    #[serde(default)]
    pub min_diagonal: Option<f64>,
    /// The requests' `max_iterations` (default: the service's).
    #[serde(default)]
    pub max_iterations: Option<usize>,
}

/// How a row's instances meet the image's border.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Cut {
    /// Every instance as photographed.
    #[default]
    Any,
    /// Instances whose full extent (`bbox_obj`) reaches the border.
    Border,
    /// The photograph cropped (its mask with it, the camera's principal
    /// point shifted) so that a seeded share in `[lo, hi]` of the
    /// instance's full-extent box is cut away from a seeded side.
    Cropped(f64, f64),
    /// The photograph enlarged this many times about the instance's
    /// full-extent box (bilinear; the mask by its nearest pixel), cut to
    /// its own size and the camera's focal lengths and principal point
    /// with it: the object as a longer lens would see it, near and large
    /// in the image.
    Zoomed(f64),
}

/// Whether a full-extent box `(x, y, w, h)` reaches the border of a
/// `width x height` image (within a pixel).
pub fn touches_border(b: [f64; 4], width: usize, height: usize) -> bool {
    b[0] <= 1.0
        || b[1] <= 1.0
        || b[0] + b[2] >= width as f64 - 1.0
        || b[1] + b[3] >= height as f64 - 1.0
}

/// The crop `(x0, y0, x1, y1)` of a `width x height` photograph that cuts
/// `share` of the box `b` away from `side` (0 left, 1 right, 2 top, 3
/// bottom).
pub fn crop_cutting(
    b: [f64; 4],
    share: f64,
    side: usize,
    width: usize,
    height: usize,
) -> (usize, usize, usize, usize) {
    let (w, h) = (width as f64, height as f64);
    let clampx = |v: f64| v.round().clamp(0.0, w) as usize;
    let clampy = |v: f64| v.round().clamp(0.0, h) as usize;
    match side {
        0 => (clampx(b[0] + share * b[2]), 0, width, height),
        1 => (0, 0, clampx(b[0] + (1.0 - share) * b[2]), height),
        2 => (0, clampy(b[1] + share * b[3]), width, height),
        _ => (0, 0, width, clampy(b[1] + (1.0 - share) * b[3])),
    }
}

/// The part `(x0, y0, x1, y1)` of an image.
fn crop_image(img: &ColorImage, c: (usize, usize, usize, usize)) -> Option<ColorImage> {
    let (x0, y0, x1, y1) = c;
    let w = img.width();
    let mut data = Vec::with_capacity((x1 - x0) * (y1 - y0) * 3);
    for y in y0..y1 {
        data.extend_from_slice(&img.data()[(y * w + x0) * 3..(y * w + x1) * 3]);
    }
    ColorImage::new(x1 - x0, y1 - y0, data).ok()
}

/// The part `(x0, y0, x1, y1)` of a mask.
fn crop_mask(m: &Mask, c: (usize, usize, usize, usize)) -> Mask {
    let (x0, y0, x1, y1) = c;
    let mut out = Mask::new(x1 - x0, y1 - y0);
    for y in y0..y1 {
        for x in x0..x1 {
            if m.get(x, y) {
                out.set(x - x0, y - y0, true);
            }
        }
    }
    out
}

/// The window of a `width x height` photograph that, enlarged `f` times,
/// fills the photograph: centred on `(px, py)` where it can be, inside the
/// photograph. Returns its centre.
pub fn zoom_centre(px: f64, py: f64, f: f64, width: usize, height: usize) -> (f64, f64) {
    let clamp = |v: f64, size: usize| {
        let half = size as f64 / (2.0 * f);
        // Pixel centres span [-0.5, size - 0.5].
        v.clamp(half - 0.5, size as f64 - half - 0.5)
    };
    (clamp(px, width), clamp(py, height))
}

/// `img` enlarged `f` times about `centre` (which lands on the image's
/// centre), bilinear, the same size.
fn zoom_image(img: &ColorImage, f: f64, centre: (f64, f64)) -> Option<ColorImage> {
    let (w, h) = (img.width(), img.height());
    let (mid_x, mid_y) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let src = img.data();
    let mut data = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        let sy = ((y as f64 - mid_y) / f + centre.1).clamp(0.0, h as f64 - 1.0);
        let (y0, ty) = (sy.floor() as usize, (sy - sy.floor()) as f32);
        let y1 = (y0 + 1).min(h - 1);
        for x in 0..w {
            let sx = ((x as f64 - mid_x) / f + centre.0).clamp(0.0, w as f64 - 1.0);
            let (x0, tx) = (sx.floor() as usize, (sx - sx.floor()) as f32);
            let x1 = (x0 + 1).min(w - 1);
            for c in 0..3 {
                let at = |xx: usize, yy: usize| src[(yy * w + xx) * 3 + c];
                let top = at(x0, y0) * (1.0 - tx) + at(x1, y0) * tx;
                let bottom = at(x0, y1) * (1.0 - tx) + at(x1, y1) * tx;
                data.push(top * (1.0 - ty) + bottom * ty);
            }
        }
    }
    ColorImage::new(w, h, data).ok()
}

/// The camera of a `width x height` image enlarged as [`zoom_image`]
/// does: `u' = f (u - centre) + middle`.
fn zoom_intrinsics(
    k: &Intrinsics,
    f: f64,
    centre: (f64, f64),
    width: usize,
    height: usize,
) -> Intrinsics {
    let (mid_x, mid_y) = ((width as f64 - 1.0) / 2.0, (height as f64 - 1.0) / 2.0);
    Intrinsics {
        fx: k.fx * f,
        fy: k.fy * f,
        cx: f * (k.cx - centre.0) + mid_x,
        cy: f * (k.cy - centre.1) + mid_y,
    }
}

/// `m` enlarged as [`zoom_image`] does, each pixel from its nearest.
fn zoom_mask(m: &Mask, f: f64, centre: (f64, f64)) -> Mask {
    let (w, h) = (m.width, m.height);
    let (mid_x, mid_y) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let mut out = Mask::new(w, h);
    for y in 0..h {
        let sy = ((y as f64 - mid_y) / f + centre.1).round();
        for x in 0..w {
            let sx = ((x as f64 - mid_x) / f + centre.0).round();
            let inside = sx >= 0.0 && sy >= 0.0 && (sx as usize) < w && (sy as usize) < h;
            if inside && m.get(sx as usize, sy as usize) {
                out.set(x, y, true);
            }
        }
    }
    out
}

/// Settings of the selection.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Selection {
    pub objects: Vec<u32>,
    pub per_object: usize,
    /// Largest |oracle_visib_fract - visib_fract| kept (the mask's
    /// occluders are annotated).
    pub max_oracle_gap: f64,
    pub seed: u64,
    /// Starts per instance (the first as with one; more narrow the
    /// figures' noise).
    pub starts: usize,
}

/// One instance chosen for a row.
#[derive(Clone, Debug)]
pub struct Case<'a> {
    pub image: &'a BopImage,
    pub instance: &'a Instance,
    pub truth: Pose,
    pub start: Pose,
    /// Which of the instance's starts.
    pub start_index: usize,
}

/// A method's answer on one case.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Outcome {
    pub obj_id: u32,
    pub im_id: u32,
    pub k: usize,
    /// Which of the instance's starts.
    pub start_index: usize,
    pub visib_fract: f64,
    /// `initial`, `irls` or `or_irls`.
    pub method: &'static str,
    /// |dX|, |dY|, |dZ| (mesh units) and roll, pitch, yaw (degrees).
    pub errors: [f64; 6],
    pub t: f64,
    pub angle: f64,
    pub success: bool,
    /// No worse than the start in both |t| and angle.
    pub no_worse: bool,
    /// The mean distance of the mesh's points between the answered and
    /// the true pose (ADD; for a symmetric object the least over its
    /// symmetric true poses), mesh units.
    pub add: f64,
    /// No worse than the start by ADD.
    pub no_worse_add: bool,
    /// The request failed (the start is scored).
    pub failed: bool,
    pub ms: f64,
    pub score: f64,
    /// The score of the start pose.
    pub start_score: f64,
    pub start_kept: bool,
    pub converged: bool,
    /// The answered pose.
    pub pose: PoseJson,
    /// The response's region scores (answered, start) and the standard
    /// deviations of its rotation (degrees) and translation from the
    /// covariance.
    pub region: (f64, f64),
    pub sigma: (f64, f64),
}

/// The errors of `est` against `truth` (or the symmetric pose of `truth`
/// closest in rotation): six absolute errors, |t|, angle.
pub fn errors(est: &Pose, truth: &Pose, symmetries: &[Vec<f64>]) -> ([f64; 6], f64, f64) {
    let mut best: Option<([f64; 6], f64, f64)> = None;
    let identity = [
        1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
    ];
    for s in std::iter::once(&identity[..]).chain(symmetries.iter().map(|v| v.as_slice())) {
        if s.len() != 16 {
            continue;
        }
        let sr = Matrix3::new(s[0], s[1], s[2], s[4], s[5], s[6], s[8], s[9], s[10]);
        let st = Vector3::new(s[3], s[7], s[11]);
        let gt = Pose {
            rotation: truth.rotation * sr,
            translation: truth.rotation * st + truth.translation,
        };
        // The angle from the trace, clamped: nalgebra's `angle` is NaN for
        // a rotation a rounding error from the identity.
        let cos = 0.5 * ((est.rotation * gt.rotation.transpose()).trace() - 1.0);
        let angle = cos.clamp(-1.0, 1.0).acos().to_degrees();
        if best.as_ref().is_none_or(|b| angle < b.2) {
            let e = super::six_errors_scaled(est, &gt, 1.0);
            best = Some((e, (est.translation - gt.translation).norm(), angle));
        }
    }
    best.unwrap_or(([0.0; 6], 0.0, 0.0))
}

/// The standard deviations of a twist covariance's rotation (degrees,
/// root of the trace of its block) and translation (mesh units).
fn sigmas(cov: &[[f64; 6]; 6]) -> (f64, f64) {
    let t = (0..3).map(|i| cov[i][i]).sum::<f64>().max(0.0).sqrt();
    let r = (3..6).map(|i| cov[i][i]).sum::<f64>().max(0.0).sqrt();
    (r.to_degrees(), t)
}

/// The symmetric poses of `truth` (itself first): `symmetries` are BOP's
/// discrete ones, 4x4 row-major; malformed ones are skipped.
fn symmetric_truths(truth: &Pose, symmetries: &[Vec<f64>]) -> Vec<Pose> {
    let mut out = vec![*truth];
    for s in symmetries.iter().filter(|s| s.len() == 16) {
        let sr = Matrix3::new(s[0], s[1], s[2], s[4], s[5], s[6], s[8], s[9], s[10]);
        let st = Vector3::new(s[3], s[7], s[11]);
        out.push(Pose {
            rotation: truth.rotation * sr,
            translation: truth.rotation * st + truth.translation,
        });
    }
    out
}

/// ADD: the mean distance of `points` between `est` and `truth`, the
/// least over the symmetric poses of `truth`.
pub fn add(est: &Pose, truth: &Pose, symmetries: &[Vec<f64>], points: &[Vector3<f64>]) -> f64 {
    if points.is_empty() {
        return 0.0;
    }
    symmetric_truths(truth, symmetries)
        .iter()
        .map(|gt| {
            points
                .iter()
                .map(|p| (est.transform(p) - gt.transform(p)).norm())
                .sum::<f64>()
                / points.len() as f64
        })
        .fold(f64::INFINITY, f64::min)
}

/// MSPD, BOP's maximum symmetry-aware projection distance: the largest
/// distance in pixels between `points` projected by `est` and by `truth`,
/// the least over the symmetric poses of `truth` (infinite where a point
/// falls behind the camera).
pub fn mspd(
    est: &Pose,
    truth: &Pose,
    symmetries: &[Vec<f64>],
    points: &[Vector3<f64>],
    camera: &Intrinsics,
) -> f64 {
    let far = |p: Option<nalgebra::Vector2<f64>>, q: Option<nalgebra::Vector2<f64>>| match (p, q) {
        (Some(p), Some(q)) => (p - q).norm(),
        _ => f64::INFINITY,
    };
    symmetric_truths(truth, symmetries)
        .iter()
        .map(|gt| {
            points
                .iter()
                .map(|x| {
                    far(
                        camera.project(&est.transform(x)),
                        camera.project(&gt.transform(x)),
                    )
                })
                .fold(0.0, f64::max)
        })
        .fold(f64::INFINITY, f64::min)
}

/// BOP's MSPD thresholds for an image `width` pixels wide: 5, 10, ..., 50
/// pixels times `width / 640`.
pub fn mspd_thresholds(width: f64) -> [f64; 10] {
    std::array::from_fn(|i| 5.0 * (i + 1) as f64 * width / 640.0)
}

/// BOP's MSPD recall: over the thresholds, the mean share of `errors`
/// below each (a missing estimate is an infinite error).
pub fn mspd_recall(errors: &[f64], thresholds: &[f64]) -> Option<f64> {
    if errors.is_empty() || thresholds.is_empty() {
        return None;
    }
    let share = |t: f64| errors.iter().filter(|&&e| e < t).count() as f64 / errors.len() as f64;
    Some(thresholds.iter().map(|&t| share(t)).sum::<f64>() / thresholds.len() as f64)
}

/// A unit vector uniform on the sphere.
fn direction(rng: &mut SplitMix64) -> Vector3<f64> {
    loop {
        let v = Vector3::new(
            rng.next_f64() * 2.0 - 1.0,
            rng.next_f64() * 2.0 - 1.0,
            rng.next_f64() * 2.0 - 1.0,
        );
        let n = v.norm();
        if n > 1e-3 && n <= 1.0 {
            return v / n;
        }
    }
}

/// The start of an instance: `truth` turned by exactly `degrees` about a
/// random axis (camera frame, about the object's origin) and moved by
/// exactly `mm`, seeded by the instance.
pub fn start_pose(truth: &Pose, seed: u64, key: (u32, u32, usize), degrees: f64, mm: f64) -> Pose {
    let mut rng =
        SplitMix64::new(seed ^ (u64::from(key.0) << 40) ^ (u64::from(key.1) << 16) ^ key.2 as u64);
    let axis = Unit::new_normalize(direction(&mut rng));
    let turn = Rotation3::from_axis_angle(&axis, degrees.to_radians());
    Pose {
        rotation: turn.into_inner() * truth.rotation,
        translation: truth.translation + direction(&mut rng) * mm,
    }
}

/// The instances of a row: per object, those in the row's visibility
/// range and within the oracle gap, in a seeded order, at most
/// `per_object`.
/// The annotated pose of an instance, its rotation projected to the
/// nearest rotation (BOP's are up to 1% off orthonormal).
pub fn truth_pose(instance: &Instance) -> Option<Pose> {
    let r = &instance.rotation;
    let m = Matrix3::new(r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8]);
    Some(Pose {
        rotation: nearest_rotation(&m)?,
        translation: Vector3::from(instance.translation),
    })
}

/// The camera of an image (`cam_K`).
pub fn intrinsics(image: &BopImage) -> Intrinsics {
    let k = &image.cam_k;
    Intrinsics {
        fx: k[0],
        fy: k[4],
        cx: k[2],
        cy: k[5],
    }
}

/// At most about `most` of a mesh's vertices, evenly through its list:
/// the points of ADD(-S).
pub fn add_points(mesh: &Mesh, most: usize) -> Vec<Vector3<f64>> {
    let stride = mesh.vertices.len().div_ceil(most.max(1)).max(1);
    mesh.vertices.iter().step_by(stride).copied().collect()
}

pub fn select<'a>(bop: &'a Bop, row: &Row, sel: &Selection) -> Vec<Case<'a>> {
    let mut out = Vec::new();
    for &obj in &sel.objects {
        let mut cands: Vec<(&BopImage, &Instance)> = bop
            .images
            .iter()
            .flat_map(|im| im.instances.iter().map(move |i| (im, i)))
            .filter(|(_, i)| {
                i.obj_id == obj
                    && (row.visib.0..=row.visib.1).contains(&i.visib_fract)
                    && i.oracle_visib_fract
                        .is_none_or(|o| (o - i.visib_fract).abs() <= sel.max_oracle_gap)
            })
            .filter(|(im, i)| {
                // The photograph's size from its header (only where asked).
                let size = (row.cut != Cut::Any)
                    .then(|| image::image_dimensions(bop.rgb_path(im)).ok())
                    .flatten()
                    .map(|(w, h)| (w as usize, h as usize));
                let border = i
                    .bbox_obj
                    .zip(size)
                    .is_some_and(|(b, (w, h))| touches_border(b, w, h));
                let cut_ok = match row.cut {
                    Cut::Any => true,
                    Cut::Border => border,
                    // Cropping needs the box, whole in the photograph.
                    Cut::Cropped(..) => i.bbox_obj.is_some() && !border,
                    // The enlarged object must fit in the photograph.
                    Cut::Zoomed(f) => {
                        !border
                            && i.bbox_obj.zip(size).is_some_and(|(b, (w, h))| {
                                b[2] * f <= w as f64 && b[3] * f <= h as f64
                            })
                    }
                };
                let size_ok = row
                    .min_diagonal
                    .is_none_or(|d| i.bbox_obj.is_some_and(|b| b[2].hypot(b[3]) >= d));
                cut_ok && size_ok
            })
            .collect();
        // A seeded shuffle (Fisher-Yates).
        let mut rng = SplitMix64::new(sel.seed ^ (u64::from(obj) << 32));
        for i in (1..cands.len()).rev() {
            let j = (rng.next_u64() % (i as u64 + 1)) as usize;
            cands.swap(i, j);
        }
        for (image, instance) in cands.into_iter().take(sel.per_object) {
            let Some(truth) = truth_pose(instance) else {
                continue;
            };
            for start_index in 0..sel.starts.max(1) {
                let start = start_pose(
                    &truth,
                    sel.seed,
                    (obj, image.id, instance.k + 1000 * start_index),
                    row.start_degrees,
                    row.start_mm,
                );
                out.push(Case {
                    image,
                    instance,
                    truth,
                    start,
                    start_index,
                });
            }
        }
    }
    out
}

/// Refines every case of a row with IRLS and OR-IRLS; `progress` is
/// called after each case.
pub fn run(
    bop: &Bop,
    row: &Row,
    cases: &[Case<'_>],
    meshes: &std::collections::BTreeMap<u32, Mesh>,
    mut progress: impl FnMut(),
) -> Result<Vec<Outcome>, crate::data::DatasetError> {
    let mut out = Vec::new();
    for case in cases {
        let (im, inst) = (case.image, case.instance);
        let mut img = load_image(&bop.rgb_path(im))?;
        let mask_path = bop.mask_visib_path(im, inst.k);
        let mut mask = image::open(&mask_path)
            .map(|m| mask_from_image(&m))
            .map_err(|e| crate::data::DatasetError::Image {
                path: mask_path.clone(),
                msg: e.to_string(),
            })?;
        let mut intrinsics = intrinsics(im);
        if let (Cut::Cropped(lo, hi), Some(b)) = (row.cut, inst.bbox_obj) {
            let mut rng = SplitMix64::new(
                0xC0FFEE
                    ^ (u64::from(inst.obj_id) << 40)
                    ^ (u64::from(im.id) << 16)
                    ^ inst.k as u64,
            );
            let share = rng.range_f64(lo, hi);
            let side = rng.range_usize(0, 4);
            let c = crop_cutting(b, share, side, img.width(), img.height());
            if c.2 > c.0 + 16 && c.3 > c.1 + 16 {
                if let Some(cropped) = crop_image(&img, c) {
                    img = cropped;
                    mask = crop_mask(&mask, c);
                    intrinsics.cx -= c.0 as f64;
                    intrinsics.cy -= c.1 as f64;
                }
            }
        }
        if let (Cut::Zoomed(f), Some(b)) = (row.cut, inst.bbox_obj) {
            let centre = zoom_centre(
                b[0] + b[2] / 2.0 - 0.5,
                b[1] + b[3] / 2.0 - 0.5,
                f,
                img.width(),
                img.height(),
            );
            if let Some(zoomed) = zoom_image(&img, f, centre) {
                mask = zoom_mask(&mask, f, centre);
                intrinsics = zoom_intrinsics(&intrinsics, f, centre, img.width(), img.height());
                img = zoomed;
            }
        }
        let info = bop.models.get(&inst.obj_id);
        let diameter = info.map_or(f64::INFINITY, |m| m.diameter);
        let symmetries = info.map_or(&[][..], |m| &m.symmetries_discrete[..]);
        let (_, t0, a0) = errors(&case.start, &case.truth, symmetries);
        let points = meshes
            .get(&inst.obj_id)
            .map_or(Vec::new(), |m| add_points(m, 2000));
        let add0 = add(&case.start, &case.truth, symmetries, &points);
        // The outcome of an answer (`None`: the start, or a failed
        // request, which is scored as the start).
        let outcome = |method, resp: Option<&PoseResponse>, failed, ms| {
            let pose = resp.map_or(case.start, |r| Pose {
                rotation: Matrix3::from_fn(|i, j| r.pose.rotation[i][j]),
                translation: Vector3::from(r.pose.translation),
            });
            let (e, t, a) = errors(&pose, &case.truth, symmetries);
            let d = add(&pose, &case.truth, symmetries, &points);
            Outcome {
                obj_id: inst.obj_id,
                im_id: im.id,
                k: inst.k,
                start_index: case.start_index,
                visib_fract: inst.visib_fract,
                method,
                errors: e,
                t,
                angle: a,
                success: t < 0.1 * diameter && a < 5.0 - 1e-6,
                no_worse: t <= t0 + 1e-9 && a <= a0 + 1e-9,
                add: d,
                no_worse_add: d <= add0 + 1e-9,
                failed,
                ms,
                score: resp.map_or(0.0, |r| r.score),
                start_score: resp.map_or(0.0, |r| r.start_score),
                start_kept: resp.is_none_or(|r| r.start_kept),
                converged: resp.is_some_and(|r| r.converged),
                pose: PoseJson::from(&pose),
                region: resp.map_or((0.0, 0.0), |r| (r.region_score, r.start_region_score)),
                sigma: resp.map_or((0.0, 0.0), |r| sigmas(&r.covariance)),
            }
        };
        out.push(outcome("initial", None, false, 0.0));
        let Some(mesh) = meshes.get(&inst.obj_id) else {
            continue;
        };
        for (method, source) in [
            ("irls", MaskSource::None),
            ("or_irls", MaskSource::Provided),
        ] {
            let params = PoseParams {
                intrinsics,
                initial_pose: Some(PoseJson::from(&case.start)),
                label: None,
                model: None,
                mask: Some(source),
                max_iterations: row.max_iterations,
                start_uncertainty: row
                    .uncertainty
                    .or(row
                        .prior_from_start
                        .then_some((row.start_degrees, row.start_mm)))
                    .map(|(degrees, mm)| StartUncertainty {
                        degrees: Some(degrees),
                        translation: Some(mm),
                    }),
            };
            let m = (source == MaskSource::Provided).then(|| mask.clone());
            let t = Instant::now();
            let r: Result<_, PoseError> = estimate(&img, mesh, &params, m, &[]);
            let ms = t.elapsed().as_secs_f64() * 1e3;
            out.push(match r {
                Ok(resp) => outcome(method, Some(&resp), false, ms),
                Err(_) => outcome(method, None, true, ms),
            });
        }
        progress();
    }
    Ok(out)
}

/// Means and medians of one method's outcomes.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Summary {
    pub method: String,
    pub n: usize,
    /// Mean |dX|, |dY|, |dZ|, roll, pitch, yaw.
    pub mean_errors: [f64; 6],
    pub mean_t: f64,
    pub mean_angle: f64,
    pub median_t: f64,
    pub median_angle: f64,
    pub success: f64,
    pub no_worse: f64,
    pub mean_add: f64,
    pub no_worse_add: f64,
    pub failed: usize,
    pub start_kept: usize,
    pub median_ms: f64,
    pub max_ms: f64,
}

/// The summary of the outcomes of `method` (`obj`: one object, or all).
pub fn summarize(outcomes: &[Outcome], method: &str, obj: Option<u32>) -> Option<Summary> {
    let o: Vec<&Outcome> = outcomes
        .iter()
        .filter(|x| x.method == method && obj.is_none_or(|id| x.obj_id == id))
        .collect();
    if o.is_empty() {
        return None;
    }
    let n = o.len() as f64;
    let mean = super::mean_errors(o.iter().map(|x| x.errors), o.len());
    let ms: Vec<f64> = o.iter().map(|x| x.ms).collect();
    Some(Summary {
        method: method.to_string(),
        n: o.len(),
        mean_errors: mean,
        mean_t: o.iter().map(|x| x.t).sum::<f64>() / n,
        mean_angle: o.iter().map(|x| x.angle).sum::<f64>() / n,
        median_t: median(o.iter().map(|x| x.t).collect()),
        median_angle: median(o.iter().map(|x| x.angle).collect()),
        success: o.iter().filter(|x| x.success).count() as f64 / n,
        no_worse: o.iter().filter(|x| x.no_worse).count() as f64 / n,
        mean_add: o.iter().map(|x| x.add).sum::<f64>() / n,
        no_worse_add: o.iter().filter(|x| x.no_worse_add).count() as f64 / n,
        failed: o.iter().filter(|x| x.failed).count(),
        start_kept: o.iter().filter(|x| x.start_kept).count(),
        median_ms: median(ms.clone()),
        max_ms: ms.into_iter().fold(0.0, f64::max),
    })
}

/// The paper's Table 2 for the three methods, as text.
pub fn table(title: &str, outcomes: &[Outcome], obj: Option<u32>) -> String {
    let s: Vec<Option<Summary>> = ["initial", "irls", "or_irls"]
        .iter()
        .map(|m| summarize(outcomes, m, obj))
        .collect();
    let n = s[0].as_ref().map_or(0, |x| x.n);
    let mut out = format!("{title} (n={n})\n                     initial      IRLS   OR-IRLS\n");
    type Column = (&'static str, fn(&Summary) -> f64);
    let rows: [Column; 17] = [
        ("X", |x| x.mean_errors[0]),
        ("Y", |x| x.mean_errors[1]),
        ("Z", |x| x.mean_errors[2]),
        ("roll (deg)", |x| x.mean_errors[3]),
        ("pitch (deg)", |x| x.mean_errors[4]),
        ("yaw (deg)", |x| x.mean_errors[5]),
        ("|t|", |x| x.mean_t),
        ("angle (deg)", |x| x.mean_angle),
        ("success (%)", |x| 100.0 * x.success),
        ("no worse (%)", |x| 100.0 * x.no_worse),
        ("ADD", |x| x.mean_add),
        ("ADD no worse (%)", |x| 100.0 * x.no_worse_add),
        ("median |t|", |x| x.median_t),
        ("median angle", |x| x.median_angle),
        ("start kept", |x| x.start_kept as f64),
        ("failed", |x| x.failed as f64),
        ("median ms", |x| x.median_ms),
    ];
    for (name, f) in rows {
        out.push_str(&format!("  {name:<16}"));
        for x in &s {
            out.push_str(&format!("{:>10.2}", x.as_ref().map_or(f64::NAN, f)));
        }
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {

    #[test]
    fn mspd_is_the_largest_projected_distance_and_sees_symmetries() {
        let camera = Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
        };
        let truth = Pose {
            rotation: Matrix3::identity(),
            translation: Vector3::new(0.0, 0.0, 1000.0),
        };
        let points = vec![Vector3::new(-50.0, 0.0, 0.0), Vector3::new(50.0, 0.0, 0.0)];
        // Moved 10 mm sideways at 1 m: every point 5 px away.
        let moved = Pose {
            translation: Vector3::new(10.0, 0.0, 1000.0),
            ..truth
        };
        assert!((mspd(&moved, &truth, &[], &points, &camera) - 5.0).abs() < 1e-9);
        // Turned half a turn about z: the points swap places, 50 px each
        // way, unless the object has that symmetry.
        let turned = Pose {
            rotation: Matrix3::new(-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0),
            ..truth
        };
        assert!((mspd(&turned, &truth, &[], &points, &camera) - 50.0).abs() < 1e-9);
        let half_turn = vec![vec![
            -1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
        ]];
        assert!(mspd(&turned, &truth, &half_turn, &points, &camera) < 1e-9);
        // The recall over BOP's thresholds: 5 px is below 10..50 (9 of 10).
        let t = mspd_thresholds(640.0);
        assert_eq!(t[0], 5.0);
        assert_eq!(t[9], 50.0);
        let r = mspd_recall(&[5.0, f64::INFINITY], &t).unwrap();
        assert!((r - 0.45).abs() < 1e-12, "{r}");
        assert_eq!(mspd_recall(&[], &t), None);
    }

    use super::*;

    #[test]
    fn an_enlarged_photograph_and_its_camera_agree() {
        // A dark left half, a bright right half: the step at u = 19.5.
        let (w, h) = (64, 48);
        let data: Vec<f32> = (0..w * h)
            .flat_map(|i| [if i % w < 20 { 0.0 } else { 200.0 }; 3])
            .collect();
        let img = ColorImage::new(w, h, data).unwrap();
        let k = Intrinsics {
            fx: 100.0,
            fy: 100.0,
            cx: 31.5,
            cy: 23.5,
        };
        // A point of the step's plane, seen at u = 19.5.
        let p = Vector3::new((19.5 - k.cx) / k.fx, 0.1, 1.0);
        let f = 2.5;
        let centre = zoom_centre(22.0, 20.0, f, w, h);
        // Clamped so that the window stays in the photograph.
        assert!((centre.1 - (h as f64 / (2.0 * f) - 0.5)).abs() < 1e-9 || centre.1 == 20.0);
        let zoomed = zoom_image(&img, f, centre).unwrap();
        let kz = zoom_intrinsics(&k, f, centre, w, h);
        let u = kz.project(&p).unwrap().x;
        // The zoomed step (half way between the two levels) lies at u.
        let row = 20;
        let level = |x: usize| zoomed.get(x, row, 0);
        let x = (0..w - 1)
            .find(|&x| level(x) < 100.0 && level(x + 1) >= 100.0)
            .unwrap();
        let crossing = x as f64 + (100.0 - level(x) as f64) / (level(x + 1) - level(x)) as f64;
        assert!((crossing - u).abs() < 0.1, "{crossing} {u}");
        // The mask goes with it.
        let mut m = Mask::new(w, h);
        m.set(30, 20, true);
        let mz = zoom_mask(&m, f, centre);
        let q = kz.project(&Vector3::new(
            (30.0 - k.cx) / k.fx,
            (20.0 - k.cy) / k.fy,
            1.0,
        ));
        let q = q.unwrap();
        assert!(mz.get(q.x.round() as usize, q.y.round() as usize));
        assert!(mz.area() >= 4 && mz.area() <= 9, "{}", mz.area());
    }

    #[test]
    fn starts_are_exactly_as_far_as_asked_and_errors_see_symmetries() {
        let truth = Pose {
            rotation: Rotation3::from_euler_angles(0.3, -0.2, 1.0).into_inner(),
            translation: Vector3::new(100.0, -50.0, 1000.0),
        };
        let a = start_pose(&truth, 7, (1, 3, 0), 5.0, 10.0);
        let b = start_pose(&truth, 7, (1, 3, 1), 5.0, 10.0);
        assert_ne!(a, b);
        let (_, t, angle) = errors(&a, &truth, &[]);
        assert!(
            (t - 10.0).abs() < 1e-9 && (angle - 5.0).abs() < 1e-9,
            "{t} {angle}"
        );
        // A half turn about z is a symmetry: the flipped pose has no error.
        let flip = vec![
            -1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
        ];
        let flipped = Pose {
            rotation: truth.rotation
                * Rotation3::from_euler_angles(0.0, 0.0, std::f64::consts::PI).into_inner(),
            translation: truth.translation,
        };
        // At the truth itself: zero, not NaN.
        let (_, t, angle) = errors(&truth, &truth, &[]);
        assert!(t == 0.0 && angle.abs() < 1e-6, "{t} {angle}");
        let (_, t, angle) = errors(&flipped, &truth, &[flip]);
        assert!(t < 1e-9 && angle < 1e-6, "{t} {angle}");
        let (_, _, angle) = errors(&flipped, &truth, &[]);
        assert!((angle - 180.0).abs() < 1e-3);
    }
}
