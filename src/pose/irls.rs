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
//! The settings are in [`super::params`], the image's gradients and the
//! edge search in [`super::search`], the distances to the mask in
//! [`super::distance`]; here the robust Gauss-Newton step, the restarts
//! and their ranking, which share one `Context`.

use nalgebra::{Matrix6, Vector2, Vector3, Vector6};
use rayon::prelude::*;

use super::distance::MaskDistance;
use super::edges::{DepthBuffer, EdgeModel, EdgeSample};
use super::geometry::{Intrinsics, Pose};
pub use super::params::{IrlsParams, START_SIGMA_DIAGONAL};
use super::region::{outward, ColourModel};
use super::search::{search, Gradients, Match, HYPOTHESES};
use super::PoseError;
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;
use crate::vision::Deadline;

/// Tolerance (pixels) of the agreement that ranks the restarts.
pub const AGREE_PX: f64 = 1.0;
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

/// Edge samples per outline at most: a larger outline is sampled more
/// sparsely, so that neither the time nor the evidence's weight against
/// the start prior grows with the object's size in the image (the LM-O
/// development objects: median 125 samples, three quarters under 143).
/// A large object is no more certain of its depth than the image's
/// resolution of its outline says: when each kept sample weighed for the
/// ones left out, the development photographs enlarged 2.5 times with the
/// prior a 2.5 times larger object gets ended with a depth error of 7.9
/// mm against the start's 5.3 (see docs/design.md).
pub const MAX_SAMPLES: usize = 160;

/// The least robust scale (pixels) of the edge residuals against the start
/// prior: edges are found to a fraction of a pixel (a parabola through the
/// gradient's peak), so a clean outline is trusted to half a pixel (with a
/// whole pixel, a synthetic box held by the prior ended 4.2 mm off).
const MIN_SCALE_PX: f64 = 0.5;

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

impl<'a> Context<'a> {
    /// What the tracks from `initial` share: the colour model taken at it,
    /// the image's gradients, the mask's distances and the start prior.
    fn new(
        img: &'a ColorImage,
        edges: &'a EdgeModel,
        k: &'a Intrinsics,
        initial: &Pose,
        mask: Option<&Mask>,
        params: &'a IrlsParams,
        deadline: Deadline,
    ) -> Result<Self, PoseError> {
        let colour = if params.region_weight > 0.0 {
            // Pixel by pixel: the colours are told apart at the outline.
            let depth = edges.depth_in_pixels(k, initial, img.width(), img.height(), &deadline)?;
            ColourModel::new(img, &depth, mask, REGION_BAND_PX)
        } else {
            None
        };
        Ok(Context {
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
            prior: start_prior(params, edges),
        })
    }

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

    /// The visible model edge samples at `pose` in the image, at most
    /// [`MAX_SAMPLES`] (evenly thinned: every `stride`-th).
    fn outline(&self, pose: &Pose, depth: &DepthBuffer) -> Result<Vec<EdgeSample>, PoseError> {
        let all: Vec<EdgeSample> = self
            .edges
            .samples(self.k, pose, depth, self.params.sample_step, &self.deadline)?
            .into_iter()
            .filter(|s| self.inside(&s.pixel))
            .collect();
        let stride = all.len().div_ceil(MAX_SAMPLES).max(1);
        Ok(all.into_iter().step_by(stride).collect())
    }

    /// Whether a point lies within the image's pixel centres: past the
    /// border a model outline shows nothing and the colours say nothing
    /// (a margin of 2 pixels more made the cropped photographs worse).
    fn inside(&self, p: &Vector2<f64>) -> bool {
        let (w, h) = (self.grads.width as f64, self.grads.height as f64);
        p.x >= 0.0 && p.y >= 0.0 && p.x <= w - 1.0 && p.y <= h - 1.0
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
        let drawn = self.outline(pose, &depth)?;
        for s in drawn.iter().filter(|s| in_mask(&s.pixel)) {
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
                    .filter(|&&o| {
                        let target = s.pixel + s.normal * o;
                        in_mask(&target) && self.inside(&target)
                    })
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
        let samples = self.outline(&t.pose, &depth)?;
        let in_mask =
            |p: &Vector2<f64>, r: usize| self.mask.as_ref().is_none_or(|m| m.within(p, r));
        // The outline's place along each outline sample's outward normal
        // by the colours (as a sample with its outward normal, and the
        // step's offset and variance), while the search range shrinks:
        // the colours widen the basin, the edges alone decide the last
        // iterations (with the colours to the end, the synthetic
        // benchmark's unoccluded rows lost precision and LM-O gained
        // nothing; see docs/design.md).
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
                    // The background side must be in the image: past the
                    // border the colours say nothing, and the step would
                    // pull the outline out to it.
                    let beyond = target + n * REGION_PROBE_PX;
                    (in_mask(&target, params.mask_margin_px)
                        && self.inside(&target)
                        && self.inside(&beyond))
                    .then_some((EdgeSample { normal: n, ..*s }, st.offset, st.variance))
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
                    if !self.inside(&target) {
                        continue;
                    }
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
                let scale = 1.0 / (sigma.max(MIN_SCALE_PX).powi(2) * params.sample_correlation);
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
/// The standard deviations (translation, rotation in radians) of the start
/// prior; a part that is off is infinite (no weight), and with both off
/// there is none.
fn start_prior(params: &IrlsParams, edges: &EdgeModel) -> Option<(f64, f64)> {
    let c = edges.box_corners();
    let diagonal = (c[7] - c[0]).norm();
    let sigma_t = match params.start_sigma_translation {
        Some(v) if v <= 0.0 => f64::INFINITY,
        Some(v) => v,
        None => (START_SIGMA_DIAGONAL * diagonal).max(1e-12),
    };
    let sigma_r = if params.start_sigma_degrees > 0.0 {
        params.start_sigma_degrees.to_radians()
    } else {
        f64::INFINITY
    };
    (sigma_t.is_finite() || sigma_r.is_finite()).then_some((sigma_t, sigma_r))
}

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
    let ctx = Context::new(img, edges, k, initial, mask, params, deadline)?;
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

    /// A 15 x 10 x 7 cm box rendered `z` in front of a 640x480 camera: the
    /// camera, the mesh, its pose and the scene.
    fn box_scene(
        z: f64,
    ) -> (
        Intrinsics,
        crate::pose::Mesh,
        Pose,
        crate::pose::render::PoseScene,
    ) {
        let k = Intrinsics {
            fx: 600.0,
            fy: 600.0,
            cx: 320.0,
            cy: 240.0,
        };
        let mesh = crate::pose::Mesh::cuboid(0.15, 0.1, 0.07);
        let pose = Pose {
            rotation: nalgebra::Rotation3::from_euler_angles(0.5, 0.6, 0.2).into_inner(),
            translation: Vector3::new(0.0, 0.0, z),
        };
        let bg = crate::pose::render::background(640, 480, 1).unwrap();
        let sc = crate::pose::render::render(&mesh, &k, &pose, &bg, 0.0, 2.0, 1).unwrap();
        (k, mesh, pose, sc)
    }

    #[test]
    fn a_refinement_past_its_deadline_gives_up() {
        let (k, mesh, pose, sc) = box_scene(0.5);
        let edges = EdgeModel::new(&mesh, 30.0);
        let params = IrlsParams::default();
        let past = Deadline::at(std::time::Instant::now());
        let r = refine_until(&sc.image, &edges, &k, &pose, None, &params, past);
        assert_eq!(r.unwrap_err(), PoseError::DeadlineExceeded);
        let far = Deadline::at(std::time::Instant::now() + std::time::Duration::from_secs(600));
        assert!(refine_until(&sc.image, &edges, &k, &pose, None, &params, far).is_ok());
    }

    /// A near object's long outline is thinned to [`MAX_SAMPLES`], and the
    /// evidence counts the kept samples only: its weight against the start
    /// prior does not grow with the object's size in the image.
    #[test]
    fn a_large_outline_weighs_no_more_than_max_samples() {
        let (k, mesh, pose, sc) = box_scene(0.25);
        let params = IrlsParams::default();
        let edges = EdgeModel::new(&mesh, params.crease_degrees);
        let ctx =
            Context::new(&sc.image, &edges, &k, &pose, None, &params, Deadline::NONE).unwrap();
        let depth = edges.depth(&k, &pose, 640, 480, &Deadline::NONE).unwrap();
        let all = edges
            .samples(&k, &pose, &depth, params.sample_step, &Deadline::NONE)
            .unwrap();
        assert!(all.len() > 2 * MAX_SAMPLES, "{} samples", all.len());
        let kept = ctx.outline(&pose, &depth).unwrap();
        assert!(kept.len() <= MAX_SAMPLES && kept.len() >= MAX_SAMPLES / 2);
        let ev = ctx.evidence(&pose).unwrap();
        assert!(ev.samples <= MAX_SAMPLES, "{}", ev.samples);
        // At the true pose the rendered edges are found.
        assert!(ev.agreement > 0.8, "{}", ev.agreement);
    }

    #[test]
    fn each_part_of_the_start_prior_is_on_or_off_by_itself() {
        let edges = EdgeModel::new(&crate::pose::Mesh::cuboid(0.3, 0.4, 1.2), 30.0);
        let with = |degrees: f64, translation: Option<f64>| {
            start_prior(
                &IrlsParams {
                    start_sigma_degrees: degrees,
                    start_sigma_translation: translation,
                    ..IrlsParams::default()
                },
                &edges,
            )
        };
        // No rotation prior: the translation's stays (5% of the diagonal,
        // 1.3 here); it used to switch both off.
        let (t, r) = with(0.0, None).unwrap();
        assert!((t - 0.065).abs() < 1e-9 && r.is_infinite(), "{t} {r}");
        let (t, r) = with(5.0, Some(0.0)).unwrap();
        assert!(t.is_infinite() && (r - 5f64.to_radians()).abs() < 1e-12);
        assert!(with(0.0, Some(0.0)).is_none());
        let (t, _) = with(5.0, Some(0.02)).unwrap();
        assert_eq!(t, 0.02);
    }
}
