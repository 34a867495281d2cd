//! Edge-based pose refinement by iteratively re-weighted least squares
//! (Choi and Christensen 2012), and its occlusion-reasoning variant
//! OR-IRLS (paper section 2.6): correspondences whose model point or image
//! match lies outside the visibility mask are dropped.
//!
//! Each outer iteration projects the visible model edges at the current
//! pose, samples them every few pixels and searches along each sample's
//! normal for the strongest image edge of compatible orientation; then a few
//! Gauss-Newton steps on the 6-d twist minimise the Tukey-weighted
//! point-to-edge distances along the normals (robust scale by the median
//! absolute deviation), with the start pose's uncertainty as a MAP prior.
//! While the search range is still shrinking, the outline samples also
//! take where the colours along their normal change from the object's to
//! the background's ([`super::region`], as RBOT, SRT3D and ICG): rows of
//! the same least squares, weighted by how sharp that step is. It stops
//! when the pose no longer changes.
//!
//! Why one file of about 1100 lines: the edge search, the robust
//! Gauss-Newton step, the restarts and their ranking share one `Context`
//! (gradients, masks, the start pose) and are one algorithm; about 130
//! lines are the tests beside them.

use nalgebra::{Matrix6, Vector2, Vector3, Vector6};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::edges::{EdgeModel, EdgeSample};
use super::geometry::{Intrinsics, Pose};
use super::region::{outward, ColourModel};
use super::PoseError;
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;
use crate::vision::Deadline;

/// Settings of the refinement.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct IrlsParams {
    /// Outer iterations (fresh correspondences) at most.
    pub max_iterations: usize,
    /// Gauss-Newton steps per set of correspondences.
    pub inner_steps: usize,
    /// Pixels between samples along a projected edge.
    pub sample_step: f64,
    /// Search range along the normal, in pixels each way, at the first
    /// iteration; it shrinks by 30% per iteration down to a quarter of it
    /// (coarse to fine: far edges pull early, near ones decide late).
    pub search_range: f64,
    /// Smallest gradient magnitude (0..255 intensity per pixel) of a match.
    pub min_gradient: f64,
    /// Largest angle (degrees) between an image gradient and the normal.
    pub max_angle_degrees: f64,
    /// Smallest dihedral angle (degrees) of a crease edge.
    pub crease_degrees: f64,
    /// Tukey constant, in robust standard deviations.
    pub tukey_c: f64,
    /// Converged when an iteration moves the model's points by less than
    /// this in the image (pixels, at the object's depth).
    pub tolerance_px: f64,
    /// A Gauss-Newton step moves the model's points by at most this many
    /// pixels (longer steps are shortened): a trust region.
    pub max_step_px: f64,
    /// OR-IRLS keeps a correspondence when its sample and its match lie
    /// within this many pixels of the visibility mask (edges lie on the
    /// mask's border).
    pub mask_margin_px: usize,
    /// Restarts turn the initial pose this many degrees (and multiples, see
    /// `restart_rings`) either way about each camera axis (0: none); see
    /// [`restart_poses`].
    pub restart_degrees: f64,
    /// Rings of turned restarts: at `restart_degrees`, twice that, ...
    pub restart_rings: usize,
    /// Restarts move the initial pose this share of its distance nearer
    /// and farther (0: none).
    pub restart_depth: f64,
    /// The start pose's uncertainty as a MAP prior: standard deviation of
    /// its rotation, degrees (0: no prior).
    pub start_sigma_degrees: f64,
    /// Standard deviation of its translation, in mesh units; `None`:
    /// [`START_SIGMA_DIAGONAL`] of the diagonal of the mesh's bounding box.
    #[serde(default)]
    pub start_sigma_translation: Option<f64>,
    /// Edge samples per independent measurement: neighbouring samples of
    /// one outline share their errors (the same wrong edge), so the data
    /// term's information is divided by this against the prior.
    pub sample_correlation: f64,
    /// Weight of the region (colour) evidence of the outline against the
    /// edges (0: edges only); see [`super::region`].
    #[serde(default = "default_region_weight")]
    pub region_weight: f64,
}

fn default_region_weight() -> f64 {
    IrlsParams::default().region_weight
}

impl Default for IrlsParams {
    fn default() -> Self {
        Self {
            max_iterations: 30,
            inner_steps: 3,
            sample_step: 3.0,
            search_range: 30.0,
            min_gradient: 8.0,
            max_angle_degrees: 30.0,
            crease_degrees: 30.0,
            tukey_c: 4.685,
            tolerance_px: 0.5,
            max_step_px: 4.0,
            mask_margin_px: 3,
            restart_degrees: 10.0,
            restart_rings: 1,
            restart_depth: 0.02,
            start_sigma_degrees: 5.0,
            start_sigma_translation: None,
            sample_correlation: 8.0,
            region_weight: 1.0,
        }
    }
}

impl IrlsParams {
    pub fn validate(&self) -> Result<(), PoseError> {
        let ok = self.max_iterations >= 1
            && self.max_iterations <= 1000
            && self.inner_steps >= 1
            && self.sample_step.is_finite()
            && self.sample_step >= 0.5
            && self.search_range.is_finite()
            && self.search_range > 0.0
            && self.search_range <= MAX_RANGE as f64
            && self.min_gradient.is_finite()
            && (0.0..90.0).contains(&self.max_angle_degrees)
            && (0.0..180.0).contains(&self.crease_degrees)
            && self.tukey_c > 0.0
            && self.tolerance_px > 0.0
            && self.max_step_px > 0.0
            && self.mask_margin_px <= 50
            && (0.0..=45.0).contains(&self.restart_degrees)
            && self.restart_rings <= 4
            && (0.0..0.5).contains(&self.restart_depth)
            && self.start_sigma_degrees.is_finite()
            && self.start_sigma_degrees >= 0.0
            && self
                .start_sigma_translation
                .is_none_or(|v| v.is_finite() && v > 0.0)
            && self.sample_correlation.is_finite()
            && self.sample_correlation >= 1.0
            && self.region_weight.is_finite()
            && self.region_weight >= 0.0;
        if ok {
            Ok(())
        } else {
            Err(PoseError::InvalidParameter(format!(
                "invalid pose refinement settings {self:?}"
            )))
        }
    }
}

/// A 3x3 binomial blur and then Sobel derivatives of one plane (each
/// normalised to intensity per pixel).
fn sobel(plane: &[f32], w: usize, h: usize) -> (Vec<f32>, Vec<f32>) {
    let at = |v: &[f32], x: isize, y: isize| {
        let x = x.clamp(0, w as isize - 1) as usize;
        let y = y.clamp(0, h as isize - 1) as usize;
        v[y * w + x]
    };
    let mut blur = vec![0.0f32; w * h];
    for y in 0..h as isize {
        for x in 0..w as isize {
            let mut s = 0.0;
            for (dy, wy) in [(-1, 1.0), (0, 2.0), (1, 1.0)] {
                for (dx, wx) in [(-1, 1.0), (0, 2.0), (1, 1.0)] {
                    s += wx * wy * at(plane, x + dx, y + dy);
                }
            }
            blur[y as usize * w + x as usize] = s / 16.0;
        }
    }
    let mut gx = vec![0.0f32; w * h];
    let mut gy = vec![0.0f32; w * h];
    for y in 0..h as isize {
        for x in 0..w as isize {
            let p = |dx, dy| at(&blur, x + dx, y + dy);
            let i = y as usize * w + x as usize;
            gx[i] = ((p(1, -1) + 2.0 * p(1, 0) + p(1, 1))
                - (p(-1, -1) + 2.0 * p(-1, 0) + p(-1, 1)))
                / 8.0;
            gy[i] = ((p(-1, 1) + 2.0 * p(0, 1) + p(1, 1))
                - (p(-1, -1) + 2.0 * p(0, -1) + p(1, -1)))
                / 8.0;
        }
    }
    (gx, gy)
}

/// Image gradients: per pixel the strongest colour channel's Sobel
/// gradient, after a 3x3 binomial blur (see [`Gradients::new`]).
pub struct Gradients {
    width: usize,
    height: usize,
    gx: Vec<f32>,
    gy: Vec<f32>,
}

impl Gradients {
    /// The Sobel gradient of each colour channel (after a 3x3 binomial
    /// blur), and at each pixel the channel whose gradient is the
    /// strongest: an outline between two colours of equal brightness is
    /// an edge, which the grey image does not show.
    pub fn new(img: &ColorImage) -> Self {
        let (w, h) = (img.width(), img.height());
        let planes: Vec<(Vec<f32>, Vec<f32>)> = (0..3)
            .map(|c| {
                let plane: Vec<f32> = img.data().iter().skip(c).step_by(3).copied().collect();
                sobel(&plane, w, h)
            })
            .collect();
        let (gx, gy): (Vec<f32>, Vec<f32>) = (0..w * h)
            .map(|i| {
                let strength = |c: usize| planes[c].0[i].powi(2) + planes[c].1[i].powi(2);
                let best = (1..3).fold(0, |b, c| if strength(c) > strength(b) { c } else { b });
                (planes[best].0[i], planes[best].1[i])
            })
            .unzip();
        Self {
            width: w,
            height: h,
            gx,
            gy,
        }
    }

    /// The gradient at the pixel containing `p`, if inside the image.
    fn at(&self, p: &Vector2<f64>) -> Option<Vector2<f64>> {
        let i = pixel_index(p, self.width, self.height)?;
        Some(Vector2::new(f64::from(self.gx[i]), f64::from(self.gy[i])))
    }
}

/// The row-major index of the pixel containing `p` in a `width` x
/// `height` grid, if inside it.
fn pixel_index(p: &Vector2<f64>, width: usize, height: usize) -> Option<usize> {
    if p.x < 0.0 || p.y < 0.0 {
        return None;
    }
    let (x, y) = (p.x as usize, p.y as usize);
    (x < width && y < height).then(|| y * width + x)
}

/// Tolerance (pixels) of the agreement that ranks the restarts.
pub const AGREE_PX: f64 = 1.0;
/// The default standard deviation of the start's translation, as a share
/// of the diagonal of the mesh's bounding box (chosen on the LM-O
/// development objects: 5%, 7% and 10% gave 7.18, 7.34 and 8.08 mm).
pub const START_SIGMA_DIAGONAL: f64 = 0.05;
/// How far (pixels each way) the evidence of a pose looks for an edge.
const EVIDENCE_RANGE_PX: f64 = 8.0;
/// Distance (pixels) at which an edge sample's squared distance stops
/// growing in the evidence (a robust, truncated quadratic).
const EVIDENCE_CUT_PX: f64 = 3.0;

/// Tracks closer than this (mean corner motion, pixels) merge.
const MERGE_PX: f64 = 0.5;

/// How well a pose's edges agree with the image (see `Context::evidence`).
#[derive(Clone, Copy, Debug)]
struct Evidence {
    mean: f64,
    samples: usize,
    agreement: f64,
    /// The share of the outline samples whose colour step (see
    /// [`super::region`]) lies within [`AGREE_PX`]` * 1.5` of the pose's
    /// outline (0 without a colour model).
    region_agreement: f64,
}

/// Half-length (pixels) of the region evidence's lines: the search
/// range, within these bounds.
const REGION_RANGE_MIN: usize = 4;
const REGION_RANGE_MAX: usize = 12;
/// How far (pixels) from an outline sample the projection is probed for
/// the object's side.
const REGION_PROBE_PX: f64 = 2.0;
/// The tempering of the region evidence's likelihoods (neighbouring
/// pixels' colours are not independent).
const REGION_TEMPER: f64 = 0.5;

/// Width (pixels) of the band around the start pose's projection whose
/// colours are the background's.
const REGION_BAND_PX: usize = 20;

/// The largest search range (pixels each way).
const MAX_RANGE: usize = 200;

/// Edge hypotheses kept per sample.
const HYPOTHESES: usize = 3;

/// A sample and its image matches: signed distances along the normal of
/// the strongest compatible edges (the strongest first). Each Gauss-Newton
/// step uses the one nearest to the model's current projection (multiple
/// hypotheses, as Choi and Christensen): a strong edge of the clutter
/// next to the object's own edge does not capture the sample for good.
#[derive(Clone, Copy, Debug)]
struct Match {
    sample: EdgeSample,
    /// Match position minus sample position, along the normal (pixels).
    offsets: [f64; HYPOTHESES],
    count: usize,
}

/// The gradient along the sample's normal at `t` pixels along it, where the
/// gradient is strong enough and within the angle of the normal (else 0).
fn edge_strength(g: &Gradients, s: &EdgeSample, p: &IrlsParams, cos_max: f64, t: f64) -> f64 {
    match g.at(&(s.pixel + s.normal * t)) {
        Some(v) => {
            let along = v.dot(&s.normal).abs();
            let m = v.norm();
            if m >= p.min_gradient && along >= cos_max * m {
                along
            } else {
                0.0
            }
        }
        None => 0.0,
    }
}

/// The sub-pixel offset (within half a pixel) of a peak of strength `v0`
/// between neighbours `vm` and `vp`: the vertex of the parabola through
/// the three (none where they do not curve down).
fn subpixel(vm: f64, v0: f64, vp: f64) -> f64 {
    let denom = vm - 2.0 * v0 + vp;
    if denom < -1e-12 {
        (0.5 * (vm - vp) / denom).clamp(-0.5, 0.5)
    } else {
        0.0
    }
}

/// Searches along the sample's normal for the strongest compatible edges
/// (local maxima of the gradient along the normal, up to [`HYPOTHESES`]),
/// each with a parabolic sub-pixel refinement; ties go to the nearer one.
fn search(g: &Gradients, s: &EdgeSample, p: &IrlsParams) -> Option<([f64; HYPOTHESES], usize)> {
    let range = p.search_range.round() as i64;
    let cos_max = p.max_angle_degrees.to_radians().cos();
    let strength = |t: f64| edge_strength(g, s, p, cos_max, t);
    // The profile along the normal, on the stack (the range is at most
    // MAX_RANGE: `IrlsParams::validate`).
    let mut values = [0.0f64; 2 * MAX_RANGE + 3];
    let n = (2 * range + 3) as usize;
    for (i, v) in values[..n].iter_mut().enumerate() {
        *v = strength((i as i64 - range - 1) as f64);
    }
    let at = |t: i64| values[(t + range + 1) as usize];
    // The strongest local maxima, strongest first (nearer first among
    // equals, then the earlier), kept by insertion.
    let mut peaks = [(0.0f64, 0i64); HYPOTHESES];
    let mut found = 0;
    for t in -range..=range {
        let v = at(t);
        let peak = v > 0.0
            && v >= at(t - 1)
            && v >= at(t + 1)
            && !(v == at(t - 1) && t > 0)
            && !(v == at(t + 1) && t < 0);
        if !peak {
            continue;
        }
        let better = |q: &(f64, i64)| v > q.0 || (v == q.0 && t.abs() < q.1.abs());
        // `found` never exceeds HYPOTHESES.
        let Some(pos) = (0..found)
            .find(|&i| better(&peaks[i]))
            .or((found < HYPOTHESES).then_some(found))
        else {
            continue;
        };
        let last = found.min(HYPOTHESES - 1);
        for i in (pos..last).rev() {
            peaks[i + 1] = peaks[i];
        }
        peaks[pos] = (v, t);
        found = (found + 1).min(HYPOTHESES);
    }
    if found == 0 {
        return None;
    }
    // Only edges of comparable strength compete with the strongest.
    let floor = 0.5 * peaks[0].0;
    let peaks = &peaks[..peaks[..found].iter().take_while(|p| p.0 >= floor).count()];
    let mut out = [0.0; HYPOTHESES];
    let count = peaks.len();
    for (o, &(v0, t)) in out.iter_mut().zip(peaks) {
        *o = t as f64 + subpixel(at(t - 1), v0, at(t + 1));
    }
    Some((out, count))
}

/// The chessboard (L-infinity) distance of every pixel to the nearest pixel
/// of a mask: a pixel lies in the mask grown by `r` (square neighbourhood)
/// exactly when its distance is at most `r`. One map answers every growth
/// the refinement asks (the search range shrinks, the margin stays).
pub struct MaskDistance {
    width: usize,
    height: usize,
    /// Saturates at `u16::MAX` (no mask pixel, or farther).
    dist: Vec<u16>,
}

impl MaskDistance {
    /// Two raster passes with unit steps to all 8 neighbours, which is
    /// exact for the chessboard distance.
    pub fn new(m: &Mask) -> Self {
        let (w, h) = (m.width, m.height);
        let mut d = vec![u16::MAX; w * h];
        for y in 0..h {
            for x in 0..w {
                if m.get(x, y) {
                    d[y * w + x] = 0;
                }
            }
        }
        let step = |v: u16| v.saturating_add(1);
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let mut v = d[i];
                if x > 0 {
                    v = v.min(step(d[i - 1]));
                }
                if y > 0 {
                    v = v.min(step(d[i - w]));
                    if x > 0 {
                        v = v.min(step(d[i - w - 1]));
                    }
                    if x + 1 < w {
                        v = v.min(step(d[i - w + 1]));
                    }
                }
                d[i] = v;
            }
        }
        for y in (0..h).rev() {
            for x in (0..w).rev() {
                let i = y * w + x;
                let mut v = d[i];
                if x + 1 < w {
                    v = v.min(step(d[i + 1]));
                }
                if y + 1 < h {
                    v = v.min(step(d[i + w]));
                    if x + 1 < w {
                        v = v.min(step(d[i + w + 1]));
                    }
                    if x > 0 {
                        v = v.min(step(d[i + w - 1]));
                    }
                }
                d[i] = v;
            }
        }
        Self {
            width: w,
            height: h,
            dist: d,
        }
    }

    /// The distance of pixel `(x, y)` to the mask (saturated; outside
    /// the grid: the largest).
    pub fn distance(&self, x: usize, y: usize) -> usize {
        if x < self.width && y < self.height {
            usize::from(self.dist[y * self.width + x])
        } else {
            usize::MAX
        }
    }

    /// Whether the pixel containing `p` lies in the mask grown by `r`.
    pub fn within(&self, p: &Vector2<f64>, r: usize) -> bool {
        pixel_index(p, self.width, self.height).is_some_and(|i| usize::from(self.dist[i]) <= r)
    }
}

/// The residual (pixels along the normal from the projected model point to
/// its match) and its derivative with respect to the twist at `pose`.
pub fn residual_and_jacobian(
    k: &Intrinsics,
    pose: &Pose,
    point: &Vector3<f64>,
    normal: &Vector2<f64>,
    target: &Vector2<f64>,
) -> Option<(f64, Vector6<f64>)> {
    let pc = pose.transform(point);
    let px = k.project(&pc)?;
    let r = normal.dot(&(px - target));
    let jp = k.project_jacobian(&pc);
    // n^T J_pi, a 1x3 row.
    let a = Vector3::new(
        normal.x * jp[0][0] + normal.y * jp[1][0],
        normal.x * jp[0][1] + normal.y * jp[1][1],
        normal.x * jp[0][2] + normal.y * jp[1][2],
    );
    // dP/dv = I, dP/dw = -[P]x, so a^T (-[P]x) = (P x a)^T.
    let w = pc.cross(&a);
    Some((r, Vector6::new(a.x, a.y, a.z, w.x, w.y, w.z)))
}

/// The result of a refinement.
#[derive(Clone, Debug)]
pub struct PoseResult {
    pub pose: Pose,
    pub converged: bool,
    pub iterations: usize,
    /// Root of the weighted mean squared residual (pixels).
    pub residual_rms_px: f64,
    /// Matches with a non-zero Tukey weight at the end.
    pub inliers: usize,
    /// Samples of the last iteration that found a match and passed the mask.
    pub samples: usize,
    /// 6x6 covariance of the twist `(v, w)` from the weighted normal
    /// equations (`sigma^2 H^-1`); rows of `(vx, vy, vz, wx, wy, wz)`.
    pub covariance: [[f64; 6]; 6],
    /// The share of the visible model edge samples (in the mask) with a
    /// compatible image edge within 1.5 px at the answered pose: how well
    /// the image supports it (see `Context::evidence`).
    pub agreement: f64,
    /// The same share at the initial pose.
    pub start_agreement: f64,
    /// The share of the outline samples (in the mask) whose colour step
    /// lies within 1.5 px of the answered pose's outline, and at the
    /// initial pose (0 without a colour model).
    pub region_agreement: f64,
    pub start_region_agreement: f64,
    /// The refinement found no pose the image supports better than the
    /// start (by the MAP cost), so the start is answered.
    pub start_kept: bool,
}

/// What every track of a refinement shares: the image's gradients, the
/// model, the camera, the masks and the settings.
struct Context<'a> {
    img: &'a ColorImage,
    /// The object's and the background's colours at the start pose (none
    /// without enough of either, or with the region weight 0).
    colour: Option<ColourModel>,
    grads: Gradients,
    edges: &'a EdgeModel,
    k: &'a Intrinsics,
    /// Distances to the mask: matches must lie within the margin of it,
    /// samples within the search range's [`growth`].
    mask: Option<MaskDistance>,
    params: &'a IrlsParams,
    radius: f64,
    initial: Pose,
    /// When to give up.
    deadline: Deadline,
    /// Standard deviations (translation in mesh units, rotation in
    /// radians) of the start pose's prior, if any.
    prior: Option<(f64, f64)>,
}

/// One refinement from one start pose.
struct Track {
    pose: Pose,
    iterations: usize,
    converged: bool,
    /// Weighted RMS residual, inliers, samples and covariance of the last
    /// Gauss-Newton step.
    last: (f64, usize, usize, Matrix6<f64>),
}

/// The search range at outer iteration `i` (from 1): it shrinks by 30% per
/// iteration down to a quarter of the first.
fn range_at(params: &IrlsParams, i: usize) -> f64 {
    let shrink = 0.7f64.powi(i.min(64) as i32 - 1);
    (params.search_range * shrink).max(params.search_range / 4.0)
}

/// How far the mask is grown for the samples at a search range: a model
/// point may still be off by the range.
fn growth(params: &IrlsParams, range: f64) -> usize {
    params.mask_margin_px.max(range.round() as usize)
}

impl Context<'_> {
    /// The deviation of `pose` from the initial pose, `(t - t0, log(R
    /// R0^T))`.
    fn deviation(&self, pose: &Pose) -> Vector6<f64> {
        let dt = pose.translation - self.initial.translation;
        let dr = nalgebra::Rotation3::from_matrix_unchecked(
            pose.rotation * self.initial.rotation.transpose(),
        )
        .scaled_axis();
        Vector6::new(dt.x, dt.y, dt.z, dr.x, dr.y, dr.z)
    }

    /// The derivative of [`Self::deviation`] in the twist of
    /// [`Pose::updated`]: `[[I, -[t]x], [0, I]]`.
    fn deviation_jacobian(pose: &Pose) -> Matrix6<f64> {
        let t = pose.translation;
        let mut jp = Matrix6::identity();
        // d(t')/dw = -[t]x (t' = t + w x t + v).
        let skew = nalgebra::Matrix3::new(0.0, t.z, -t.y, -t.z, 0.0, t.x, t.y, -t.x, 0.0);
        jp.fixed_view_mut::<3, 3>(0, 3).copy_from(&skew);
        jp
    }

    /// Image motion of the model's points under a twist, at the pose's depth.
    fn motion(&self, pose: &Pose, xi: &Vector6<f64>) -> f64 {
        let z = pose.translation.z.abs().max(1e-9);
        let v = Vector3::new(xi[0], xi[1], xi[2]).norm();
        let w = Vector3::new(xi[3], xi[4], xi[5]).norm();
        self.k.fx.max(self.k.fy) * (v + w * self.radius) / z
    }

    /// Mean image distance (pixels) between the object's box corners at
    /// two poses.
    fn displacement(&self, a: &Pose, b: &Pose) -> f64 {
        let corners = self.edges.box_corners();
        let sum: f64 = corners
            .iter()
            .map(|c| {
                match (
                    self.k.project(&a.transform(c)),
                    self.k.project(&b.transform(c)),
                ) {
                    (Some(p), Some(q)) => (p - q).norm(),
                    // Behind the camera: as far as the image is wide.
                    _ => 2.0 * self.k.cx.abs().max(1.0),
                }
            })
            .sum();
        sum / corners.len() as f64
    }

    /// How well the model's edges at `pose` agree with the image: over
    /// the visible model edge samples in the mask (grown by the margin),
    /// the mean of `min(d, EVIDENCE_CUT_PX)^2` where `d` is the distance
    /// along the normal to the nearest compatible image edge in the mask
    /// (within [`EVIDENCE_RANGE_PX`]; none counts as the cut), the number
    /// of samples, and the share of them with an edge within
    /// [`AGREE_PX`]`* 1.5`.
    fn evidence(&self, pose: &Pose) -> Result<Evidence, PoseError> {
        let (g, params) = (&self.grads, self.params);
        let depth = self
            .edges
            .depth(self.k, pose, g.width, g.height, &self.deadline)?;
        let near = IrlsParams {
            search_range: EVIDENCE_RANGE_PX,
            ..*params
        };
        let margin = params.mask_margin_px;
        let in_mask = |p: &Vector2<f64>| self.mask.as_ref().is_none_or(|m| m.within(p, margin));
        let cut2 = EVIDENCE_CUT_PX * EVIDENCE_CUT_PX;
        let (mut sum, mut n, mut close) = (0.0, 0usize, 0usize);
        let (mut outline, mut outline_close) = (0usize, 0usize);
        for s in self
            .edges
            .samples(self.k, pose, &depth, params.sample_step, &self.deadline)?
            .iter()
            .filter(|s| in_mask(&s.pixel))
        {
            if let Some(colour) = &self.colour {
                let step = outward(&depth, &s.pixel, &s.normal, REGION_PROBE_PX).and_then(|nn| {
                    colour.step(
                        self.img,
                        &s.pixel,
                        &nn,
                        EVIDENCE_RANGE_PX as usize,
                        REGION_TEMPER,
                    )
                });
                if let Some(st) = step {
                    outline += 1;
                    outline_close += usize::from(st.offset.abs() <= 1.5 * AGREE_PX);
                }
            }
            let d = search(g, s, &near).and_then(|(found, m)| {
                found[..m]
                    .iter()
                    .filter(|&&o| in_mask(&(s.pixel + s.normal * o)))
                    .map(|o| o.abs())
                    .min_by(f64::total_cmp)
            });
            let d = d.unwrap_or(EVIDENCE_CUT_PX).min(EVIDENCE_CUT_PX);
            sum += d * d;
            n += 1;
            close += usize::from(d <= 1.5 * AGREE_PX);
        }
        Ok(Evidence {
            mean: if n > 0 { sum / n as f64 } else { cut2 },
            samples: n,
            agreement: if n > 0 { close as f64 / n as f64 } else { 0.0 },
            region_agreement: if outline > 0 {
                outline_close as f64 / outline as f64
            } else {
                0.0
            },
        })
    }

    /// The MAP cost of `pose` (lower is better): the evidence's mean
    /// squared distance times `n_ref` samples (those at the initial pose)
    /// shared by correlated samples, plus the start prior's
    /// `e^T Lambda e`.
    fn map_cost(&self, ev: &Evidence, pose: &Pose, n_ref: usize) -> f64 {
        let data = ev.mean * n_ref as f64 / self.params.sample_correlation;
        let prior = self.prior.map_or(0.0, |(st, sr)| {
            let e = self.deviation(pose);
            let t = e.fixed_rows::<3>(0).norm_squared() / (st * st);
            let r = e.fixed_rows::<3>(3).norm_squared() / (sr * sr);
            t + r
        });
        data + prior
    }

    /// One outer iteration of `t`: fresh correspondences, then a few
    /// Gauss-Newton steps. Marks the track converged when the pose stopped
    /// changing at the finest search range.
    fn iterate(&self, t: &mut Track) -> Result<(), PoseError> {
        let (params, k) = (self.params, self.k);
        t.iterations += 1;
        let (width, height) = (self.grads.width, self.grads.height);
        let depth = self
            .edges
            .depth(k, &t.pose, width, height, &self.deadline)?;
        let range = range_at(params, t.iterations);
        let round = IrlsParams {
            search_range: range,
            ..*params
        };
        let grow = growth(params, range);
        let samples = self
            .edges
            .samples(k, &t.pose, &depth, params.sample_step, &self.deadline)?;
        let in_mask =
            |p: &Vector2<f64>, r: usize| self.mask.as_ref().is_none_or(|m| m.within(p, r));
        // The outline's place along each outline sample's outward normal
        // by the colours (as a sample with its outward normal, and the
        // step's offset and variance), while the search range shrinks:
        // the colours widen the basin, the edges alone decide the last
        // iterations (with the colours to the end, the synthetic
        // benchmark's unoccluded rows lost precision and LM-O gained
        // nothing; see the README).
        let finest = params.search_range / 4.0;
        let region_range = (range.round() as usize).clamp(REGION_RANGE_MIN, REGION_RANGE_MAX);
        let regions: Vec<(EdgeSample, f64, f64)> = match &self.colour {
            Some(colour) if params.region_weight > 0.0 && range > finest + 1e-9 => samples
                .iter()
                .filter(|s| in_mask(&s.pixel, grow))
                .filter_map(|s| {
                    let n = outward(&depth, &s.pixel, &s.normal, REGION_PROBE_PX)?;
                    let st = colour.step(self.img, &s.pixel, &n, region_range, REGION_TEMPER)?;
                    let target = s.pixel + n * st.offset;
                    in_mask(&target, params.mask_margin_px).then_some((
                        EdgeSample { normal: n, ..*s },
                        st.offset,
                        st.variance,
                    ))
                })
                .collect(),
            _ => Vec::new(),
        };
        let matches: Vec<Match> = samples
            .into_iter()
            .filter_map(|s| {
                let (found, n) = search(&self.grads, &s, &round)?;
                let mut offsets = [0.0; HYPOTHESES];
                let mut count = 0;
                for &offset in &found[..n] {
                    let target = s.pixel + s.normal * offset;
                    if let Some(m) = &self.mask {
                        if !m.within(&s.pixel, grow) || !m.within(&target, params.mask_margin_px) {
                            continue;
                        }
                    }
                    offsets[count] = offset;
                    count += 1;
                }
                (count > 0).then_some(Match {
                    sample: s,
                    offsets,
                    count,
                })
            })
            .collect();
        if matches.len() < 6 {
            return Err(PoseError::NotEnoughEdges(matches.len()));
        }
        let start = t.pose;
        for _ in 0..params.inner_steps {
            // Rows: residual, Jacobian, weight before the robust one.
            let mut rows: Vec<(f64, Vector6<f64>, f64)> = matches
                .iter()
                .filter_map(|m| {
                    // The hypothesis nearest to the current projection.
                    m.offsets[..m.count]
                        .iter()
                        .filter_map(|&o| {
                            let target = m.sample.pixel + m.sample.normal * o;
                            residual_and_jacobian(
                                k,
                                &t.pose,
                                &m.sample.point,
                                &m.sample.normal,
                                &target,
                            )
                        })
                        .min_by(|a, b| a.0.abs().total_cmp(&b.0.abs()))
                        .map(|(r, j)| (r, j, 1.0))
                })
                .collect();
            rows.extend(regions.iter().filter_map(|(s, offset, variance)| {
                let target = s.pixel + s.normal * *offset;
                let (r, j) = residual_and_jacobian(k, &t.pose, &s.point, &s.normal, &target)?;
                Some((r, j, params.region_weight / (1.0 + variance)))
            }));
            let mut abs: Vec<f64> = rows.iter().map(|(r, _, _)| r.abs()).collect();
            abs.sort_by(f64::total_cmp);
            let med = abs.get(abs.len() / 2).copied().unwrap_or(0.0);
            let sigma = (1.4826 * med).max(0.3);
            let c = params.tukey_c * sigma;
            let mut h = Matrix6::zeros();
            let mut g = Vector6::zeros();
            let (mut wsum, mut wr2, mut inliers) = (0.0, 0.0, 0usize);
            for (r, j, base) in &rows {
                let u = r / c;
                if u.abs() >= 1.0 {
                    continue;
                }
                let w = base * (1.0 - u * u).powi(2);
                h += j * j.transpose() * w;
                g += j * (w * r);
                wsum += w;
                wr2 += w * r * r;
                inliers += 1;
            }
            if inliers < 6 {
                return Err(PoseError::NotEnoughEdges(inliers));
            }
            if let Some((sigma_t, sigma_r)) = self.prior {
                // The data term in units of its noise, shared by correlated
                // samples; then the start pose's prior on the deviation
                // e = (t - t0, log(R R0^T)), whose derivative in the twist
                // is [[I, -[t]x], [0, I]].
                let scale = 1.0 / (sigma.max(1.0).powi(2) * params.sample_correlation);
                h *= scale;
                g *= scale;
                let (e, jp) = (self.deviation(&t.pose), Self::deviation_jacobian(&t.pose));
                let lambda = Vector6::new(
                    1.0 / (sigma_t * sigma_t),
                    1.0 / (sigma_t * sigma_t),
                    1.0 / (sigma_t * sigma_t),
                    1.0 / (sigma_r * sigma_r),
                    1.0 / (sigma_r * sigma_r),
                    1.0 / (sigma_r * sigma_r),
                );
                let l = Matrix6::from_diagonal(&lambda);
                h += jp.transpose() * l * jp;
                g += jp.transpose() * (l * e);
            }
            // Levenberg-Marquardt damping keeps weakly constrained
            // directions (e.g. rotation about a cylinder's axis) still.
            let mut damped = h;
            for i in 0..6 {
                damped[(i, i)] += 1e-6 * h[(i, i)].max(1e-12);
            }
            let Some(mut step) = damped.cholesky().map(|ch| ch.solve(&(-g))) else {
                return Err(PoseError::NotEnoughEdges(inliers));
            };
            let m = self.motion(&t.pose, &step);
            if m > params.max_step_px {
                step *= params.max_step_px / m;
            }
            t.pose = t.pose.updated(&step);
            let rms = (wr2 / wsum.max(1e-12)).sqrt();
            // With the prior the equations are already in units of the noise.
            let noise = if self.prior.is_some() {
                1.0
            } else {
                sigma * sigma
            };
            let cov = damped.try_inverse().unwrap_or_else(Matrix6::zeros) * noise;
            t.last = (rms, inliers, matches.len(), cov);
        }
        // How far this iteration moved the model's points in the image.
        let moved = matches
            .iter()
            .filter_map(|m| {
                let a = k.project(&start.transform(&m.sample.point))?;
                let b = k.project(&t.pose.transform(&m.sample.point))?;
                Some((a - b).norm())
            })
            .fold(0.0, f64::max);
        t.converged = moved < params.tolerance_px && range <= params.search_range / 4.0 + 1e-9;
        Ok(())
    }
}

/// The start poses of the restarts: `initial`, then turned by `degrees`,
/// twice that, ... (`rings` of them) either way about the camera's x, y
/// and z axes through the object's origin, then moved along its viewing
/// ray by `depth` of its distance either way (the directions an edge fit
/// confuses most).
pub fn restart_poses(initial: &Pose, degrees: f64, rings: usize, depth: f64) -> Vec<Pose> {
    let mut out = vec![*initial];
    for ring in (1..=rings).filter(|_| degrees > 0.0) {
        let angle = (ring as f64 * degrees).to_radians();
        for axis in [Vector3::x(), Vector3::y(), Vector3::z()] {
            for sign in [-1.0, 1.0] {
                let turn = nalgebra::Rotation3::new(axis * (sign * angle));
                out.push(Pose {
                    rotation: turn.into_inner() * initial.rotation,
                    translation: initial.translation,
                });
            }
        }
    }
    if depth > 0.0 {
        for sign in [-1.0, 1.0] {
            out.push(Pose {
                rotation: initial.rotation,
                translation: initial.translation * (1.0 + sign * depth),
            });
        }
    }
    out
}

/// Refines `initial` by IRLS; with a `mask`, by OR-IRLS (correspondences
/// whose sample or match lies outside the mask are dropped).
///
/// Edge fits from one start are captured by the wrong edges in clutter or
/// when little of the object is visible, so the refinement restarts from
/// poses around `initial` (see [`restart_poses`]). The tracks run to
/// convergence together (tracks that meet merge), and the answer is the
/// one with the lowest MAP cost: the robust (truncated quadratic) distance
/// of its visible model edge samples to the image's edges in the mask,
/// shared by correlated samples, plus the start prior (see
/// `Context::map_cost`). The initial pose competes too: when no track
/// beats it, it is answered (`start_kept`, not converged).
///
/// The start prior ([`IrlsParams::start_sigma_degrees`],
/// [`IrlsParams::start_sigma_translation`]) also enters every Gauss-Newton
/// step as a MAP term on the deviation from `initial`: on real
/// photographs a few pixels of wrong edge matches are tens of millimetres
/// of depth, and the prior lets a direction move only as far as the image
/// supports.
pub fn refine(
    img: &ColorImage,
    edges: &EdgeModel,
    k: &Intrinsics,
    initial: &Pose,
    mask: Option<&Mask>,
    params: &IrlsParams,
) -> Result<PoseResult, PoseError> {
    refine_until(img, edges, k, initial, mask, params, Deadline::NONE)
}

/// [`refine`] that gives up with [`PoseError::DeadlineExceeded`] once
/// `deadline` has passed (looked at in every iteration, and inside the
/// rasteriser and the edge sampler).
pub fn refine_until(
    img: &ColorImage,
    edges: &EdgeModel,
    k: &Intrinsics,
    initial: &Pose,
    mask: Option<&Mask>,
    params: &IrlsParams,
    deadline: Deadline,
) -> Result<PoseResult, PoseError> {
    params.validate()?;
    k.validate()?;
    if let Some(m) = mask {
        if (m.width, m.height) != (img.width(), img.height()) {
            return Err(PoseError::InvalidParameter(format!(
                "the mask is {}x{}, the image {}x{}",
                m.width,
                m.height,
                img.width(),
                img.height()
            )));
        }
    }
    let colour = if params.region_weight > 0.0 {
        let depth = edges.depth(k, initial, img.width(), img.height(), &deadline)?;
        ColourModel::new(img, &depth, mask, REGION_BAND_PX)
    } else {
        None
    };
    let ctx = Context {
        img,
        colour,
        grads: Gradients::new(img),
        edges,
        k,
        mask: mask.map(MaskDistance::new),
        params,
        radius: edges.radius(),
        initial: *initial,
        deadline,
        prior: (params.start_sigma_degrees > 0.0).then(|| {
            let c = edges.box_corners();
            let diagonal = (c[7] - c[0]).norm();
            (
                params
                    .start_sigma_translation
                    .unwrap_or(START_SIGMA_DIAGONAL * diagonal)
                    .max(1e-12),
                params.start_sigma_degrees.to_radians(),
            )
        }),
    };
    let new_track = |pose: Pose| Track {
        pose,
        iterations: 0,
        converged: false,
        last: (0.0, 0, 0, Matrix6::zeros()),
    };
    let starts = restart_poses(
        initial,
        params.restart_degrees,
        params.restart_rings,
        params.restart_depth,
    );
    // All tracks advance together, an iteration at a time (in parallel);
    // a track that comes within MERGE_PX of an earlier one (same iteration,
    // so same search range from here on) follows it, and is dropped.
    let mut tracks: Vec<Track> = starts.into_iter().map(new_track).collect();
    let mut first_error = None;
    while tracks
        .iter()
        .any(|t| !t.converged && t.iterations < params.max_iterations)
    {
        if deadline.passed() {
            return Err(PoseError::DeadlineExceeded);
        }
        let stepped: Vec<Result<Track, PoseError>> = tracks
            .into_par_iter()
            .map(|mut t| {
                if !t.converged && t.iterations < params.max_iterations {
                    ctx.iterate(&mut t)?;
                }
                Ok(t)
            })
            .collect();
        tracks = Vec::new();
        for r in stepped {
            match r {
                Ok(t) => {
                    if !tracks
                        .iter()
                        .any(|u| ctx.displacement(&u.pose, &t.pose) < MERGE_PX)
                    {
                        tracks.push(t);
                    }
                }
                Err(e) => {
                    first_error.get_or_insert(e);
                }
            }
        }
    }
    // The MAP cost ranks the tracks, and the initial pose itself competes:
    // a refinement that the image supports no better than the start is
    // not answered (the start is, marked not converged).
    let start_ev = ctx.evidence(initial)?;
    let n_ref = start_ev.samples.max(1);
    let scored: Vec<(f64, Evidence, Track)> = tracks
        .into_par_iter()
        .map(|t| {
            let ev = ctx.evidence(&t.pose)?;
            Ok((ctx.map_cost(&ev, &t.pose, n_ref), ev, t))
        })
        .collect::<Result<_, PoseError>>()?;
    // The best; among equals the earlier start (the initial pose first).
    let mut best: Option<(f64, Evidence, Track)> = None;
    for t in scored {
        if best.as_ref().is_none_or(|b| t.0 < b.0) {
            best = Some(t);
        }
    }
    let Some((best_cost, mut ev, mut best)) = best else {
        return Err(first_error.unwrap_or(PoseError::NotEnoughEdges(0)));
    };
    let start_kept = ctx.map_cost(&start_ev, initial, n_ref) <= best_cost;
    if start_kept {
        best.pose = *initial;
        best.converged = false;
        ev = start_ev;
    }
    let (rms, inliers, samples, cov) = best.last;
    let mut covariance = [[0.0; 6]; 6];
    for (r, row) in covariance.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = cov[(r, c)];
        }
    }
    Ok(PoseResult {
        pose: best.pose,
        converged: best.converged,
        iterations: best.iterations,
        residual_rms_px: rms,
        inliers,
        samples,
        covariance,
        agreement: ev.agreement,
        start_agreement: start_ev.agreement,
        region_agreement: ev.region_agreement,
        start_region_agreement: start_ev.region_agreement,
        start_kept,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::rng::SplitMix64;

    /// The search by its definition: every local maximum, sorted by
    /// strength (nearer, then earlier, first among equals), those under
    /// half the strongest dropped, the first HYPOTHESES kept.
    fn search_reference(g: &Gradients, s: &EdgeSample, p: &IrlsParams) -> Vec<f64> {
        let range = p.search_range.round() as i64;
        let cos_max = p.max_angle_degrees.to_radians().cos();
        let strength = |t: i64| edge_strength(g, s, p, cos_max, t as f64);
        let mut peaks: Vec<(f64, i64)> = (-range..=range)
            .filter(|&t| {
                let v = strength(t);
                v > 0.0
                    && v >= strength(t - 1)
                    && v >= strength(t + 1)
                    && !(v == strength(t - 1) && t > 0)
                    && !(v == strength(t + 1) && t < 0)
            })
            .map(|t| (strength(t), t))
            .collect();
        peaks.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.abs().cmp(&b.1.abs())));
        let floor = peaks.first().map_or(0.0, |p| 0.5 * p.0);
        peaks
            .iter()
            .filter(|p| p.0 >= floor)
            .take(HYPOTHESES)
            .map(|&(v0, t)| t as f64 + subpixel(strength(t - 1), v0, strength(t + 1)))
            .collect()
    }

    #[test]
    fn an_outline_between_colours_of_equal_brightness_is_an_edge() {
        // Red left, green right, both of grey level 40: the grey image has
        // no edge there, the colour gradient does.
        let (w, h) = (32, 16);
        let data: Vec<f32> = (0..w * h)
            .flat_map(|i| {
                if i % w < w / 2 {
                    [120.0, 0.0, 0.0]
                } else {
                    [0.0, 120.0, 0.0]
                }
            })
            .collect();
        let img = ColorImage::new(w, h, data).unwrap();
        let g = Gradients::new(&img);
        let at_edge = g.at(&Vector2::new(16.0, 8.0)).unwrap();
        assert!(
            at_edge.x.abs() > 20.0 && at_edge.y.abs() < 1e-3,
            "{at_edge:?}"
        );
        let flat = g.at(&Vector2::new(4.0, 8.0)).unwrap();
        assert!(flat.norm() < 1e-3, "{flat:?}");
    }

    #[test]
    fn a_refinement_past_its_deadline_gives_up() {
        let k = Intrinsics {
            fx: 600.0,
            fy: 600.0,
            cx: 320.0,
            cy: 240.0,
        };
        let mesh = crate::pose::Mesh::cuboid(0.15, 0.1, 0.07);
        let pose = Pose {
            rotation: nalgebra::Rotation3::from_euler_angles(0.5, 0.6, 0.2).into_inner(),
            translation: Vector3::new(0.0, 0.0, 0.5),
        };
        let bg = crate::pose::render::background(640, 480, 1).unwrap();
        let sc = crate::pose::render::render(&mesh, &k, &pose, &bg, 0.0, 2.0, 1).unwrap();
        let edges = EdgeModel::new(&mesh, 30.0);
        let params = IrlsParams::default();
        let past = Deadline::at(std::time::Instant::now());
        let r = refine_until(&sc.image, &edges, &k, &pose, None, &params, past);
        assert_eq!(r.unwrap_err(), PoseError::DeadlineExceeded);
        let far = Deadline::at(std::time::Instant::now() + std::time::Duration::from_secs(600));
        assert!(refine_until(&sc.image, &edges, &k, &pose, None, &params, far).is_ok());
    }

    #[test]
    fn search_keeps_the_strongest_peaks_as_defined() {
        let mut rng = SplitMix64::new(17);
        let (w, h) = (64, 48);
        // Blocks of grey levels, noise only on the right half: exact
        // block steps make peaks of equal strength (ties to order).
        let data: Vec<f32> = (0..w * h)
            .flat_map(|i| {
                let (x, y) = (i % w, i / w);
                let block = ((x / 5) * 31 + (y / 7) * 17) % 9;
                let v = (block * 28) as f32;
                [v, v, v].map(|c| (x, c))
            })
            .map(|(x, v)| {
                if x >= w / 2 {
                    v + (rng.next_f64() * 3.0) as f32
                } else {
                    v
                }
            })
            .collect();
        let g = Gradients::new(&ColorImage::new(w, h, data).unwrap());
        let mut compared = 0;
        for i in 0..400 {
            let angle = rng.range_f64(0.0, std::f64::consts::TAU);
            let s = EdgeSample {
                point: Vector3::zeros(),
                pixel: Vector2::new(rng.range_f64(0.0, w as f64), rng.range_f64(0.0, h as f64)),
                normal: Vector2::new(angle.cos(), angle.sin()),
            };
            let p = IrlsParams {
                search_range: [1.0, 3.0, 7.5, 30.0][i % 4],
                ..IrlsParams::default()
            };
            let want = search_reference(&g, &s, &p);
            let got = search(&g, &s, &p).map_or(Vec::new(), |(o, n)| o[..n].to_vec());
            assert_eq!(got, want, "sample {s:?}, range {}", p.search_range);
            compared += usize::from(want.len() > 1);
        }
        // Enough samples had several hypotheses to compare their order.
        assert!(compared > 20, "{compared}");
    }

    #[test]
    fn mask_distance_equals_the_square_neighbourhood_test() {
        let mut rng = SplitMix64::new(3);
        let (w, h) = (37, 23);
        let mut m = Mask::new(w, h);
        for _ in 0..12 {
            m.set(rng.range_usize(0, w), rng.range_usize(0, h), true);
        }
        let d = MaskDistance::new(&m);
        for r in [0, 1, 3, 30] {
            for y in 0..h {
                for x in 0..w {
                    let near = (y.saturating_sub(r)..(y + r + 1).min(h)).any(|yy| {
                        (x.saturating_sub(r)..(x + r + 1).min(w)).any(|xx| m.get(xx, yy))
                    });
                    let p = Vector2::new(x as f64 + 0.5, y as f64 + 0.5);
                    assert_eq!(d.within(&p, r), near, "r {r}, ({x}, {y})");
                }
            }
        }
        // No mask pixel: nothing is near it.
        let none = MaskDistance::new(&Mask::new(5, 4));
        assert!(!none.within(&Vector2::new(1.0, 1.0), 1000));
        assert!(!d.within(&Vector2::new(-0.5, 1.0), 1000));
    }
}
