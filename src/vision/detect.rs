//! SD-HOP detection: an exact min-cut at every viewpoint and pyramid location
//! that can still matter, non-maximum suppression, and masks.
//!
//! Exact pruning works in three stages, each a lower bound on a location's
//! energy that skips the location once it exceeds the cut-off (the score
//! threshold, or the worst of the `max_detections` best detections found so
//! far, since locations are visited in order of their bound):
//! 1. one dense pass per level and viewpoint computes every location's sum
//!    of best unaries `sum_i min(F_i, B_i + R_i)`, plus the smallest clique
//!    potential times an upper bound on the number of cliques in the box
//!    (`CliqueCounter`, O(1) per box);
//! 2. at the survivors, the exact minimum of the energy without its pairwise
//!    term (cliques are then independent; [`BoxProblem::lower_bound_without_pairwise`]);
//! 3. the min-cut itself stops as soon as the flow it has found shows the
//!    minimum above the cut-off ([`BoxProblem::solve_below`]).
//!
//! All three are exact: the detections equal those of solving every
//! location, which a test checks.

use std::time::Instant;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::energy::{
    edge_direction, BoxProblem, PairwiseMode, ViewWeights, NO_CLIQUE, PAIR_DOWN, PAIR_RIGHT,
};
use super::hog::{HogMap, CELL_SIZE, HOG_DIM, HOG_STRIDE};
use super::mask::{raw_mask, refine_mask, CellGrid, Mask, RefineParams};
use super::maxflow::Graph;
use super::pyramid::{FeaturePyramid, Level};
use super::{Deadline, VisionError};

/// Detection settings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DetectParams {
    /// Keep detections whose score (minus the energy) is at least this.
    pub threshold: f64,
    /// At most this many detections after non-maximum suppression.
    pub max_detections: usize,
    /// Suppress a detection whose box IoU with a better one exceeds this.
    pub nms_iou: f64,
    /// Largest fraction of a box's cells that may lie outside the image.
    pub max_truncation: f64,
    /// Skip locations whose bound shows they cannot matter.
    pub prune: bool,
    pub refine: RefineParams,
    /// Only boxes about here (a request's setting, never a model's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub region: Option<Region>,
    /// Give up (with [`VisionError::DeadlineExceeded`]) once this passes (a
    /// request's setting, never stored).
    #[serde(skip)]
    pub deadline: Deadline,
}

/// Where the object is known to be roughly: a location is scanned only
/// when its (full-object) box overlaps `bbox` by an IoU of at least
/// `min_iou`. With one detection asked for, the exact pruning then solves
/// far fewer locations.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Region {
    /// `(x, y, width, height)` in pixels.
    pub bbox: (f64, f64, f64, f64),
    pub min_iou: f64,
}

impl Default for DetectParams {
    fn default() -> Self {
        Self {
            threshold: 0.0,
            max_detections: 10,
            nms_iou: 0.4,
            max_truncation: 0.5,
            prune: true,
            refine: RefineParams::default(),
            region: None,
            deadline: Deadline::NONE,
        }
    }
}

impl DetectParams {
    pub fn validate(&self) -> Result<(), VisionError> {
        let ok = !self.threshold.is_nan()
            && (0.0..=1.0).contains(&self.nms_iou)
            && (0.0..1.0).contains(&self.max_truncation)
            && self.refine.fill.is_finite()
            && self.refine.clear.is_finite()
            && self.region.is_none_or(|r| {
                let (x, y, w, h) = r.bbox;
                x.is_finite()
                    && y.is_finite()
                    && w > 0.0
                    && h > 0.0
                    && w.is_finite()
                    && h.is_finite()
                    && (0.0..=1.0).contains(&r.min_iou)
            });
        if ok {
            Ok(())
        } else {
            Err(VisionError::InvalidParameter(format!(
                "detection needs a threshold, 0 <= nms_iou <= 1 and 0 <= max_truncation < 1, got {self:?}"
            )))
        }
    }
}

/// One detection.
#[derive(Clone, Debug, PartialEq)]
pub struct Detection {
    pub viewpoint: usize,
    pub level: usize,
    /// Score: minus the energy; higher is better.
    pub score: f64,
    /// Full-extent box in image pixels `(x, y, width, height)`.
    pub bbox: (f64, f64, f64, f64),
    /// Box geometry on its level.
    pub grid: CellGrid,
    /// Visibility of the box cells, row-major.
    pub cells: Vec<bool>,
    /// Whether the box extends beyond the image.
    pub truncated: bool,
    /// Fraction of the box cells labelled visible.
    pub visible_fraction: f64,
}

/// Counts and per-stage wall-clock times of one scan.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct DetectStats {
    pub locations: usize,
    pub pruned_stage1: usize,
    /// Skipped by the clique bound or the best energy found so far.
    pub pruned_stage2: usize,
    pub min_cuts: usize,
    pub responses_ms: f64,
    pub mincut_ms: f64,
    pub nms_ms: f64,
}

impl DetectStats {
    /// Fraction of locations that never reached a min-cut.
    pub fn pruned_fraction(&self) -> f64 {
        if self.locations == 0 {
            0.0
        } else {
            1.0 - self.min_cuts as f64 / self.locations as f64
        }
    }
}

/// Upper bounds on the number of cliques (distinct segments) among the
/// cells of any box of a level, in O(1) per box. A box's cells of one
/// segment form one or more 4-connected pieces, and the first cell of each
/// piece in raster order has neither its left nor its upper neighbour in the
/// piece: that neighbour is outside the box or in another segment. Counting
/// such cells with prefix sums bounds the number of pieces, hence of
/// cliques.
struct CliqueCounter {
    w: usize,
    h: usize,
    /// Per row, prefix sums of "the left neighbour is another segment".
    left: Vec<u32>,
    /// Per column, prefix sums of "the upper neighbour is another segment".
    up: Vec<u32>,
    /// 2D prefix sums of "both neighbours are other segments".
    both: Vec<u32>,
}

impl CliqueCounter {
    fn new(seg: &[u32], w: usize, h: usize) -> Self {
        let l = |x: usize, y: usize| u32::from(x > 0 && seg[y * w + x - 1] != seg[y * w + x]);
        let u = |x: usize, y: usize| u32::from(y > 0 && seg[(y - 1) * w + x] != seg[y * w + x]);
        let mut left = vec![0u32; (w + 1) * h];
        let mut up = vec![0u32; (h + 1) * w];
        let mut both = vec![0u32; (w + 1) * (h + 1)];
        for y in 0..h {
            for x in 0..w {
                left[y * (w + 1) + x + 1] = left[y * (w + 1) + x] + l(x, y);
                up[x * (h + 1) + y + 1] = up[x * (h + 1) + y] + u(x, y);
                both[(y + 1) * (w + 1) + x + 1] =
                    both[(y + 1) * (w + 1) + x] + both[y * (w + 1) + x + 1] - both[y * (w + 1) + x]
                        + l(x, y) * u(x, y);
            }
        }
        Self {
            w,
            h,
            left,
            up,
            both,
        }
    }

    /// Bound for the cells `[x0, x1) x [y0, y1)` (non-empty, inside the map).
    fn bound(&self, x0: usize, x1: usize, y0: usize, y1: usize) -> usize {
        debug_assert!(x0 < x1 && x1 <= self.w && y0 < y1 && y1 <= self.h);
        let (w1, h1) = (self.w + 1, self.h + 1);
        let row = self.left[y0 * w1 + x1] - self.left[y0 * w1 + x0 + 1];
        let col = self.up[x0 * h1 + y1] - self.up[x0 * h1 + y0 + 1];
        let b = &self.both;
        let inner = b[y1 * w1 + x1] + b[(y0 + 1) * w1 + x0 + 1]
            - b[(y0 + 1) * w1 + x1]
            - b[y1 * w1 + x0 + 1];
        1 + (row + col + inner) as usize
    }
}

/// A viewpoint prepared for scanning.
struct View<'a> {
    w: &'a ViewWeights,
    /// `min(w_0, w_K)`, the smallest value of any clique potential.
    hop_min: f64,
    w_hop: Vec<f64>,
}

/// A box location: a viewpoint's template placed with its top-left cell at
/// `(x, y)` on a pyramid level (negative or past the edge when truncated).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Location {
    pub level: usize,
    pub view: usize,
    pub y: isize,
    pub x: isize,
}

/// A scanned location that survived stage 1.
#[derive(Clone, Copy, Debug)]
struct Candidate {
    view: usize,
    level: usize,
    x: isize,
    y: isize,
    bound: f64,
}

impl Candidate {
    fn location(&self) -> Location {
        Location {
            level: self.level,
            view: self.view,
            y: self.y,
            x: self.x,
        }
    }
}

/// A loss `Delta(y, y_hat)` that decomposes over a box's cells, for
/// loss-augmented inference (paper section 2.3): at every location it adds a
/// constant and per-cell Hamming terms to the energy, so the same min-cut
/// finds `argmin_y_hat E(y_hat) - Delta(y, y_hat)`.
pub trait LossAugment: Sync {
    /// An upper bound on the loss of any output (subtracted from bounds).
    fn max_loss(&self) -> f64;
    /// Subtracts the loss of the box at `grid` from `problem`'s energy.
    fn augment(&self, grid: &CellGrid, problem: &mut BoxProblem);
}

/// The output of loss-augmented inference at one location.
#[derive(Clone, Debug, PartialEq)]
pub struct Augmented {
    pub location: Location,
    pub cells: Vec<bool>,
    /// `Delta - E` of this output: the larger, the more violated.
    pub value: f64,
}

struct Solved {
    cand: Candidate,
    energy: f64,
    cells: Vec<bool>,
}

/// Per-thread buffers reused between locations.
#[derive(Default)]
struct Scratch {
    graph: Graph,
    problem: BoxProblem,
    labels: Vec<bool>,
    seg_stamp: Vec<u32>,
    seg_local: Vec<u32>,
    generation: u32,
    edge_dirs: Vec<u8>,
}

/// A margin that absorbs float round-off between the bound and the energy.
#[inline]
fn margin(v: f64) -> f64 {
    1e-4 * (1.0 + v.abs())
}

/// Dot product of two equal-length slices with eight accumulators (the
/// compiler vectorises it; see [`dot`] for the dispatch).
#[inline(always)]
fn dot_body(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let ca = a.chunks_exact(8);
    let cb = b.chunks_exact(8);
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for k in 0..8 {
            acc[k] += x[k] * y[k];
        }
    }
    let mut s: f32 = acc.iter().sum();
    for (x, y) in ra.iter().zip(rb) {
        s += x * y;
    }
    s
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn dot_avx2(a: &[f32], b: &[f32]) -> f32 {
    dot_body(a, b)
}

/// Dot product, using AVX2 when the processor has it.
#[inline]
pub fn dot(a: &[f32], b: &[f32]) -> f32 {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the features were detected at run time.
            return unsafe { dot_avx2(a, b) };
        }
    }
    dot_body(a, b)
}

/// Lanes of the dense bound kernel: consecutive positions computed together.
const LANES: usize = 8;

/// The HOG map of a level as one zero-padded plane per feature dimension, so
/// that consecutive box positions read consecutive values.
struct PlanarMap {
    pad_x: usize,
    pad_y: usize,
    width: usize,
    plane_len: usize,
    data: Vec<f32>,
}

impl PlanarMap {
    fn new(hog: &HogMap, pad_x: usize, pad_y: usize) -> Self {
        // Extra lanes on the right so a block of positions never reads past.
        let width = hog.width() + 2 * pad_x + LANES;
        let height = hog.height() + 2 * pad_y;
        let plane_len = width * height;
        let mut data = vec![0.0f32; plane_len * HOG_DIM];
        for y in 0..hog.height() {
            for x in 0..hog.width() {
                let o = (y + pad_y) * width + x + pad_x;
                for (d, &v) in hog.cell(x, y).iter().enumerate() {
                    data[d * plane_len + o] = v;
                }
            }
        }
        Self {
            pad_x,
            pad_y,
            width,
            plane_len,
            data,
        }
    }
}

/// Scratch of the dense bound: the column chains' states and the sums
/// along one output row of positions.
#[derive(Default)]
struct DenseScratch {
    c0: Vec<[f32; LANES]>,
    c1: Vec<[f32; LANES]>,
    acc: Vec<[f32; LANES]>,
}

/// One step of a chain's dynamic programme over [`LANES`] positions: the
/// best energies ending in label 0 and 1 after adding a cell of unaries
/// `(u0, u1)`.
#[inline(always)]
fn chain_step(
    s0: &mut [f32; LANES],
    s1: &mut [f32; LANES],
    u0: &[f32; LANES],
    u1: &[f32; LANES],
    pair: f32,
) {
    for l in 0..LANES {
        let n0 = u0[l] + s0[l].min(s1[l] + pair);
        let n1 = u1[l] + s1[l].min(s0[l] + pair);
        s0[l] = n0;
        s1[l] = n1;
    }
}

/// Lower bounds on the unary and pairwise energy of the boxes whose
/// top-left cells are `(x0 + k, y)` for `k` in `0..out.len()`, by the
/// row-and-column chain decomposition of [`BoxProblem::lower_bound_chains`]:
/// half of every unary goes to the chain of its row, half to the chain of
/// its column, each chain keeps its Potts terms and is minimised exactly by
/// dynamic programming, and the chain minima add up to a lower bound. With
/// `pair = 0` it is the sum of best unaries `sum_i min(F_i, B_i + R_i)`.
///
/// Template rows are the outer loop, so that the feature rows one template
/// row reads (31 planes of one map row) stay in the L1 cache while every
/// block of positions and every template column uses them.
#[inline(always)]
fn dense_row_body(
    map: &PlanarMap,
    w: &ViewWeights,
    pair: f32,
    x0: isize,
    y: isize,
    out: &mut [f32],
    s: &mut DenseScratch,
) {
    let (rows, cols) = (w.rows, w.cols);
    let blocks = out.len().div_ceil(LANES);
    s.c0.clear();
    s.c0.resize(cols * blocks, [0.0; LANES]);
    s.c1.clear();
    s.c1.resize(cols * blocks, [0.0; LANES]);
    s.acc.clear();
    s.acc.resize(blocks, [0.0; LANES]);
    let col_start = (x0 + map.pad_x as isize) as usize;
    for ty in 0..rows {
        let row = (y + ty as isize + map.pad_y as isize) as usize * map.width + col_start;
        for blk in 0..blocks {
            let mut r0 = [0.0f32; LANES];
            let mut r1 = [0.0f32; LANES];
            for tx in 0..cols {
                let i = ty * cols + tx;
                let wv = &w.w_vis[i * HOG_STRIDE..i * HOG_STRIDE + HOG_DIM];
                let wo = &w.w_occ[i * HOG_STRIDE..i * HOG_STRIDE + HOG_DIM];
                let base = row + blk * LANES + tx;
                // Two partial sums per filter hide the multiply-add latency.
                let (mut f0, mut f1) = ([0.0f32; LANES], [0.0f32; LANES]);
                let (mut g0, mut g1) = ([0.0f32; LANES], [0.0f32; LANES]);
                let lanes = |d: usize| -> [f32; LANES] {
                    let o = d * map.plane_len + base;
                    map.data
                        .get(o..o + LANES)
                        .and_then(|v| <[f32; LANES]>::try_from(v).ok())
                        .unwrap_or([0.0; LANES])
                };
                let mut d = 0;
                while d + 1 < HOG_DIM {
                    let (v0, v1) = (lanes(d), lanes(d + 1));
                    let (a0, a1, b0, b1) = (wv[d], wv[d + 1], wo[d], wo[d + 1]);
                    for l in 0..LANES {
                        f0[l] += a0 * v0[l];
                        g0[l] += b0 * v0[l];
                        f1[l] += a1 * v1[l];
                        g1[l] += b1 * v1[l];
                    }
                    d += 2;
                }
                if d < HOG_DIM {
                    let v0 = lanes(d);
                    for l in 0..LANES {
                        f0[l] += wv[d] * v0[l];
                        g0[l] += wo[d] * v0[l];
                    }
                }
                let r = w.w_prior[i];
                // Half of each unary to the row chain, half to the column.
                let mut u0 = [0.0f32; LANES];
                let mut u1 = [0.0f32; LANES];
                for l in 0..LANES {
                    u1[l] = 0.5 * (f0[l] + f1[l]);
                    u0[l] = 0.5 * (g0[l] + g1[l] + r);
                }
                if tx == 0 {
                    r0 = u0;
                    r1 = u1;
                } else {
                    chain_step(&mut r0, &mut r1, &u0, &u1, pair);
                }
                let c = tx * blocks + blk;
                if ty == 0 {
                    s.c0[c] = u0;
                    s.c1[c] = u1;
                } else {
                    let (c0, c1) = (&mut s.c0[c], &mut s.c1[c]);
                    chain_step(c0, c1, &u0, &u1, pair);
                }
            }
            let acc = &mut s.acc[blk];
            for l in 0..LANES {
                acc[l] += r0[l].min(r1[l]);
            }
        }
    }
    for tx in 0..cols {
        for blk in 0..blocks {
            let c = tx * blocks + blk;
            for l in 0..LANES {
                s.acc[blk][l] += s.c0[c][l].min(s.c1[c][l]);
            }
        }
    }
    for (k, v) in out.iter_mut().enumerate() {
        *v = s.acc[k / LANES][k % LANES];
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn dense_row_avx2(
    map: &PlanarMap,
    w: &ViewWeights,
    pair: f32,
    x0: isize,
    y: isize,
    out: &mut [f32],
    s: &mut DenseScratch,
) {
    dense_row_body(map, w, pair, x0, y, out, s)
}

fn dense_row(
    map: &PlanarMap,
    w: &ViewWeights,
    pair: f32,
    x0: isize,
    y: isize,
    out: &mut [f32],
    s: &mut DenseScratch,
) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the features were detected at run time.
            return unsafe { dense_row_avx2(map, w, pair, x0, y, out, s) };
        }
    }
    dense_row_body(map, w, pair, x0, y, out, s)
}

/// Range of top-left positions along one axis whose box of `len` cells has
/// at least `min_inside` cells inside `[0, size)`.
fn positions(size: usize, len: usize, min_inside: usize) -> (isize, isize) {
    let lo = min_inside as isize - len as isize;
    let hi = size as isize - min_inside as isize;
    (lo, hi)
}

fn overlap(start: isize, len: usize, size: usize) -> usize {
    let a = start.max(0);
    let b = (start + len as isize).min(size as isize);
    (b - a).max(0) as usize
}

/// The top-left positions scanned on a `mw x mh` level for a `rows x cols`
/// template: `(x_lo, x_hi, y_lo, y_hi, min_inside)`, or `None` when no box
/// keeps enough cells inside the map.
pub fn scan_range(
    mw: usize,
    mh: usize,
    rows: usize,
    cols: usize,
    max_truncation: f64,
) -> Option<(isize, isize, isize, isize, usize)> {
    let n = rows * cols;
    let min_inside = (((1.0 - max_truncation) * n as f64).ceil() as usize).max(1);
    // Smallest overlap per axis that can still reach min_inside cells.
    let min_x = min_inside.div_ceil(rows).max(1);
    let min_y = min_inside.div_ceil(cols).max(1);
    if mw < min_x || mh < min_y {
        return None;
    }
    let (x_lo, x_hi) = positions(mw, cols, min_x);
    let (y_lo, y_hi) = positions(mh, rows, min_y);
    Some((x_lo, x_hi, y_lo, y_hi, min_inside))
}

/// The stage-1 chain bounds (unary and pairwise part, without the clique,
/// truncation and bias terms) of every scanned position of one level and
/// viewpoint: `values[(y - y_lo) * nx + (x - x_lo)]`.
#[derive(Clone, Debug, PartialEq)]
pub struct LevelBounds {
    pub x_lo: isize,
    pub y_lo: isize,
    pub nx: usize,
    pub ny: usize,
    pub values: Vec<f32>,
}

/// [`LevelBounds`] of every level and viewpoint of a model on one pyramid
/// (`levels[level][view]`; `None` where the level has no position), as
/// [`dense_bounds`] or a compute backend builds them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DenseBounds {
    pub levels: Vec<Vec<Option<LevelBounds>>>,
}

impl DenseBounds {
    fn get(&self, level: usize, view: usize) -> Option<&LevelBounds> {
        self.levels.get(level)?.get(view)?.as_ref()
    }
}

/// The Potts weight the chain bound may use: the bound holds for the Potts
/// terms of every pair; with pairs along edges only, a pair may carry
/// nothing, so it uses none.
pub fn chain_pair_weight(w: &ViewWeights) -> f32 {
    match w.pair_mode {
        PairwiseMode::Grid => w.w_pair,
        PairwiseMode::Edges => 0.0,
    }
}

/// CPU reference of `kernels/dense_bounds.wgsl`: the chain bounds of every
/// position of every level and viewpoint that a scan with `max_truncation`
/// visits.
pub fn dense_bounds(
    pyr: &FeaturePyramid,
    views: &[ViewWeights],
    max_truncation: f64,
) -> DenseBounds {
    let levels = pyr
        .levels
        .par_iter()
        .map(|level| {
            views
                .iter()
                .map(|w| {
                    let (mw, mh) = (level.hog.width(), level.hog.height());
                    let (x_lo, x_hi, y_lo, y_hi, _) =
                        scan_range(mw, mh, w.rows, w.cols, max_truncation)?;
                    let map = PlanarMap::new(&level.hog, w.cols, w.rows);
                    let nx = (x_hi - x_lo + 1) as usize;
                    let ny = (y_hi - y_lo + 1) as usize;
                    let mut values = vec![0.0f32; nx * ny];
                    let mut scratch = DenseScratch::default();
                    let pair = chain_pair_weight(w);
                    for (row, out) in values.chunks_mut(nx).enumerate() {
                        dense_row(&map, w, pair, x_lo, y_lo + row as isize, out, &mut scratch);
                    }
                    Some(LevelBounds {
                        x_lo,
                        y_lo,
                        nx,
                        ny,
                        values,
                    })
                })
                .collect()
        })
        .collect();
    DenseBounds { levels }
}

/// CPU reference of `kernels/responses.wgsl`: the unaries of every cell of
/// the box at `loc`, `(F_i, B_i + R_i)` (visible, occluded), row-major, as
/// the min-cut uses them.
pub fn responses(
    pyr: &FeaturePyramid,
    views: &[ViewWeights],
    loc: &Location,
) -> Result<Vec<(f64, f64)>, VisionError> {
    if loc.level >= pyr.levels.len() || loc.view >= views.len() {
        return Err(VisionError::InvalidParameter(format!(
            "no level {} or viewpoint {}",
            loc.level, loc.view
        )));
    }
    let det = Detector::new(views)?;
    let (p, _, _) = det.problem_at(pyr, loc);
    Ok(p.u1.iter().zip(&p.u0).map(|(&f, &b)| (f, b)).collect())
}

/// An SD-HOP detector over the viewpoints of one model.
pub struct Detector<'a> {
    views: Vec<View<'a>>,
}

impl<'a> Detector<'a> {
    /// Prepares the viewpoints; checks them first.
    pub fn new(views: &'a [ViewWeights]) -> Result<Self, VisionError> {
        if views.is_empty() {
            return Err(VisionError::InvalidParameter(
                "a model needs a viewpoint".into(),
            ));
        }
        let views = views
            .iter()
            .map(|w| {
                w.validate()?;
                let w_hop: Vec<f64> = w.w_hop.iter().map(|&v| f64::from(v)).collect();
                let hop_min = w_hop[0].min(w_hop[w_hop.len() - 1]);
                Ok(View { w, hop_min, w_hop })
            })
            .collect::<Result<Vec<_>, VisionError>>()?;
        Ok(Self { views })
    }

    /// Stage 1 at every location of one level and viewpoint: the exact
    /// best-unary bound of each location that passes `cut`, or every location
    /// when not pruning.
    #[allow(clippy::too_many_arguments)]
    fn scan_level(
        &self,
        level_idx: usize,
        level: &Level,
        map: &PlanarMap,
        cliques: Option<&CliqueCounter>,
        vi: usize,
        params: &DetectParams,
        cut: f64,
        max_loss: f64,
        pre: Option<&LevelBounds>,
    ) -> (usize, Vec<Candidate>) {
        let view = &self.views[vi];
        let (rows, cols) = (view.w.rows, view.w.cols);
        let n = rows * cols;
        let (mw, mh) = (level.hog.width(), level.hog.height());
        let Some((x_lo, x_hi, y_lo, y_hi, min_inside)) =
            scan_range(mw, mh, rows, cols, params.max_truncation)
        else {
            return (0, Vec::new());
        };
        let mut out = Vec::new();
        let mut count = 0;
        let nx = (x_hi - x_lo + 1) as usize;
        let mut sums = vec![0.0f32; nx];
        let mut scratch = DenseScratch::default();
        let pair = chain_pair_weight(view.w);
        // Bounds a backend computed for exactly these positions.
        let pre = pre.filter(|b| {
            b.x_lo == x_lo
                && b.y_lo == y_lo
                && b.nx == nx
                && b.ny == (y_hi - y_lo + 1) as usize
                && b.values.len() == b.nx * b.ny
        });
        // Without usable bounds the caller may not have built the map.
        let own;
        let map = if params.prune && pre.is_none() && map.data.is_empty() {
            own = PlanarMap::new(&level.hog, cols, rows);
            &own
        } else {
            map
        };
        for y in y_lo..=y_hi {
            let oy = overlap(y, rows, mh);
            if params.prune {
                if let Some(b) = pre {
                    let r = (y - y_lo) as usize * nx;
                    sums.copy_from_slice(&b.values[r..r + nx]);
                } else {
                    dense_row(map, view.w, pair, x_lo, y, &mut sums, &mut scratch);
                }
            }
            for (k, x) in (x_lo..=x_hi).enumerate() {
                let inside = overlap(x, cols, mw) * oy;
                if inside < min_inside {
                    continue;
                }
                count += 1;
                let truncated = (n - inside) as f64;
                let hop = if view.hop_min >= 0.0 {
                    view.hop_min
                } else {
                    let most = cliques.map_or(inside, |c| {
                        let (x0, y0) = (x.max(0) as usize, y.max(0) as usize);
                        let x1 = ((x + cols as isize) as usize).min(mw);
                        let y1 = ((y + rows as isize) as usize).min(mh);
                        c.bound(x0, x1, y0, y1).min(inside)
                    });
                    view.hop_min * most as f64
                };
                let base =
                    hop + f64::from(view.w.w_trunc) * truncated + f64::from(view.w.bias) - max_loss;
                let bound = if params.prune {
                    let b = base + f64::from(sums[k]);
                    if b - margin(b) > cut {
                        continue;
                    }
                    b
                } else {
                    f64::NEG_INFINITY
                };
                out.push(Candidate {
                    view: vi,
                    level: level_idx,
                    x,
                    y,
                    bound,
                });
            }
        }
        (count, out)
    }

    /// Stage 2b and the min-cut at one candidate. `None` when pruned.
    #[allow(clippy::too_many_arguments)]
    fn solve(
        &self,
        pyr: &FeaturePyramid,
        cand: &Candidate,
        cut: f64,
        prune: bool,
        aug: Option<&dyn LossAugment>,
        s: &mut Scratch,
    ) -> Option<Solved> {
        self.fill_problem(pyr, &cand.location(), s, None);
        if let Some(a) = aug {
            a.augment(&self.grid(pyr, &cand.location()), &mut s.problem);
        }
        let p = &mut s.problem;
        if prune {
            let lb = p.lower_bound_chains();
            if lb - margin(lb) > cut {
                return None;
            }
            let lb = p.lower_bound_without_pairwise();
            if lb - margin(lb) > cut {
                return None;
            }
        }
        let limit = if prune {
            cut + margin(cut)
        } else {
            f64::INFINITY
        };
        let energy = p.solve_below(&mut s.graph, &mut s.labels, limit)?;
        Some(Solved {
            cand: *cand,
            energy,
            cells: s.labels.clone(),
        })
    }

    /// The geometry of a location's box.
    pub fn grid(&self, pyr: &FeaturePyramid, loc: &Location) -> CellGrid {
        let w = self.views[loc.view].w;
        let level = &pyr.levels[loc.level];
        CellGrid {
            cell_x: loc.x,
            cell_y: loc.y,
            rows: w.rows,
            cols: w.cols,
            scale_x: level.scale_x,
            scale_y: level.scale_y,
            cell_size: CELL_SIZE,
        }
    }

    /// Every location of every level and viewpoint with at most
    /// `max_truncation` of its cells outside the image.
    pub fn locations(&self, pyr: &FeaturePyramid, max_truncation: f64) -> Vec<Location> {
        let mut out = Vec::new();
        for (li, level) in pyr.levels.iter().enumerate() {
            for (vi, view) in self.views.iter().enumerate() {
                let (rows, cols) = (view.w.rows, view.w.cols);
                let n = rows * cols;
                let (mw, mh) = (level.hog.width(), level.hog.height());
                let min_inside = (((1.0 - max_truncation) * n as f64).ceil() as usize).max(1);
                let (x_lo, x_hi) = positions(mw, cols, min_inside.div_ceil(rows).max(1));
                let (y_lo, y_hi) = positions(mh, rows, min_inside.div_ceil(cols).max(1));
                for y in y_lo..=y_hi {
                    for x in x_lo..=x_hi {
                        if overlap(x, cols, mw) * overlap(y, rows, mh) >= min_inside {
                            out.push(Location {
                                level: li,
                                view: vi,
                                y,
                                x,
                            });
                        }
                    }
                }
            }
        }
        out
    }

    /// The CRF of a location (unaries, cliques, constant) into
    /// `s.problem`; also the cells' HOG features when `features` is given.
    /// Returns the number of cells outside the image.
    fn fill_problem(
        &self,
        pyr: &FeaturePyramid,
        loc: &Location,
        s: &mut Scratch,
        mut features: Option<&mut Vec<[f32; HOG_DIM]>>,
    ) -> usize {
        let view = &self.views[loc.view];
        let w = view.w;
        let level = &pyr.levels[loc.level];
        let (rows, cols) = (w.rows, w.cols);
        let (mw, mh) = (level.hog.width(), level.hog.height());
        if s.problem.rows != rows || s.problem.cols != cols || s.problem.w_hop != view.w_hop {
            s.problem = BoxProblem::new(rows, cols, view.w_hop.clone());
        }
        if let Some(f) = features.as_deref_mut() {
            f.clear();
        }
        let nseg = pyr.segmentation.count();
        if s.seg_stamp.len() < nseg {
            s.seg_stamp.resize(nseg, 0);
            s.seg_local.resize(nseg, 0);
        }
        s.generation = s.generation.wrapping_add(1);
        if s.generation == 0 {
            s.seg_stamp.iter_mut().for_each(|v| *v = 0);
            s.generation = 1;
        }
        let p = &mut s.problem;
        p.pairwise = f64::from(w.w_pair);
        let edges = w.pair_mode == PairwiseMode::Edges;
        if edges {
            p.pairs.clear();
            p.pairs.resize(rows * cols, 0);
            s.edge_dirs.clear();
            s.edge_dirs.resize(rows * cols, 0);
        } else {
            p.pairs.clear();
        }
        let mut n_cliques = 0u32;
        let mut truncated = 0usize;
        for ty in 0..rows {
            for tx in 0..cols {
                let i = ty * cols + tx;
                let (cx, cy) = (loc.x + tx as isize, loc.y + ty as isize);
                let prior = f64::from(w.w_prior[i]);
                if cx < 0 || cy < 0 || cx as usize >= mw || cy as usize >= mh {
                    p.u1[i] = 0.0;
                    p.u0[i] = prior;
                    p.clique_of[i] = NO_CLIQUE;
                    truncated += 1;
                    if let Some(f) = features.as_deref_mut() {
                        f.push([0.0; HOG_DIM]);
                    }
                    continue;
                }
                let (cx, cy) = (cx as usize, cy as usize);
                let phi = level.hog.cell_padded(cx, cy);
                if edges {
                    s.edge_dirs[i] = edge_direction(phi);
                }
                if let Some(f) = features.as_deref_mut() {
                    let mut c = [0.0f32; HOG_DIM];
                    c.copy_from_slice(&phi[..HOG_DIM]);
                    f.push(c);
                }
                let f = &w.w_vis[i * HOG_STRIDE..(i + 1) * HOG_STRIDE];
                let b = &w.w_occ[i * HOG_STRIDE..(i + 1) * HOG_STRIDE];
                p.u1[i] = f64::from(dot(f, phi));
                p.u0[i] = f64::from(dot(b, phi)) + prior;
                let seg = level.cell_segments[cy * mw + cx] as usize;
                if s.seg_stamp[seg] != s.generation {
                    s.seg_stamp[seg] = s.generation;
                    s.seg_local[seg] = n_cliques;
                    n_cliques += 1;
                }
                p.clique_of[i] = s.seg_local[seg];
            }
        }
        p.n_cliques = n_cliques as usize;
        p.constant = f64::from(w.w_trunc) * truncated as f64 + f64::from(w.bias);
        if edges {
            // A pair runs along an edge when both cells lie on an edge in
            // the pair's direction (cells outside the image lie on none).
            for i in 0..rows * cols {
                let d = s.edge_dirs[i];
                if i % cols + 1 < cols && d == 1 && s.edge_dirs[i + 1] == 1 {
                    p.pairs[i] |= PAIR_RIGHT;
                }
                if i + cols < rows * cols && d == 2 && s.edge_dirs[i + cols] == 2 {
                    p.pairs[i] |= PAIR_DOWN;
                }
            }
        }
        truncated
    }

    /// The CRF of a location, the HOG features of its cells (zero outside
    /// the image) and its number of cells outside the image: what
    /// [`super::energy::joint_feature`] needs.
    pub fn problem_at(
        &self,
        pyr: &FeaturePyramid,
        loc: &Location,
    ) -> (BoxProblem, Vec<[f32; HOG_DIM]>, usize) {
        let mut s = Scratch::default();
        let mut feats = Vec::new();
        let truncated = self.fill_problem(pyr, loc, &mut s, Some(&mut feats));
        (s.problem, feats, truncated)
    }

    /// Scans a pyramid. Returns the detections (best first) and statistics.
    pub fn detect(
        &self,
        pyr: &FeaturePyramid,
        params: &DetectParams,
    ) -> Result<(Vec<Detection>, DetectStats), VisionError> {
        self.detect_with_bounds(pyr, params, None)
    }

    /// [`Self::detect`] with the stage-1 chain bounds computed elsewhere (by
    /// a compute backend; see [`dense_bounds`]). Levels and viewpoints whose
    /// bounds are missing or cover other positions are computed here.
    pub fn detect_with_bounds(
        &self,
        pyr: &FeaturePyramid,
        params: &DetectParams,
        bounds: Option<&DenseBounds>,
    ) -> Result<(Vec<Detection>, DetectStats), VisionError> {
        params.validate()?;
        if params.max_detections == 0 {
            return Ok((Vec::new(), DetectStats::default()));
        }
        let (solved, mut stats) = self.run(pyr, params, None, None, bounds);
        // The scan stops early once the deadline passes.
        if params.deadline.passed() {
            return Err(VisionError::DeadlineExceeded);
        }
        let t = Instant::now();
        let dets = self.suppress(pyr, solved, params);
        stats.nms_ms = t.elapsed().as_secs_f64() * 1e3;
        Ok((dets, stats))
    }

    /// Loss-augmented inference over every location, level and viewpoint:
    /// the output maximising `Delta - E`, if any beats `floor` (the value of
    /// the empty output). Exact: pruned locations provably cannot beat the
    /// best value found. Also returns every location found on the way that
    /// beat the best value known when it was solved (hard examples).
    /// With a `budget`, the search stops after about that many min-cuts
    /// (in order of the bound) and is no longer exact.
    pub fn most_violated(
        &self,
        pyr: &FeaturePyramid,
        aug: &dyn LossAugment,
        floor: f64,
        max_truncation: f64,
        budget: Option<usize>,
    ) -> Result<(Option<Augmented>, Vec<Location>, DetectStats), VisionError> {
        let params = DetectParams {
            threshold: floor,
            max_detections: 1,
            max_truncation,
            prune: true,
            ..DetectParams::default()
        };
        params.validate()?;
        let (solved, stats) = self.run(pyr, &params, Some(aug), budget, None);
        let found: Vec<Location> = solved.iter().map(|s| s.cand.location()).collect();
        let best = solved
            .into_iter()
            .min_by(|a, b| a.energy.total_cmp(&b.energy))
            .map(|s| Augmented {
                location: s.cand.location(),
                value: -s.energy,
                cells: s.cells,
            });
        Ok((best, found, stats))
    }

    /// Loss-augmented inference restricted to the given locations.
    pub fn most_violated_among(
        &self,
        pyr: &FeaturePyramid,
        locations: &[Location],
        aug: &dyn LossAugment,
        floor: f64,
    ) -> Option<Augmented> {
        let mut s = Scratch::default();
        let mut best: Option<Augmented> = None;
        let mut cut = -floor;
        for loc in locations {
            let cand = Candidate {
                view: loc.view,
                level: loc.level,
                x: loc.x,
                y: loc.y,
                bound: f64::NEG_INFINITY,
            };
            if let Some(r) = self.solve(pyr, &cand, cut, true, Some(aug), &mut s) {
                if r.energy < cut {
                    cut = r.energy;
                    best = Some(Augmented {
                        location: *loc,
                        value: -r.energy,
                        cells: r.cells,
                    });
                }
            }
        }
        best
    }

    /// Both stages and the min-cuts; the solved locations with energy at
    /// most `-threshold` (for a single best detection, only those that were
    /// the best when found).
    fn run(
        &self,
        pyr: &FeaturePyramid,
        params: &DetectParams,
        aug: Option<&dyn LossAugment>,
        budget: Option<usize>,
        pre: Option<&DenseBounds>,
    ) -> (Vec<Solved>, DetectStats) {
        let mut stats = DetectStats::default();
        let max_loss = aug.map_or(0.0, |a| a.max_loss());
        let cut = -params.threshold;
        let t = Instant::now();
        let pad_x = self.views.iter().map(|v| v.w.cols).max().unwrap_or(0);
        let pad_y = self.views.iter().map(|v| v.w.rows).max().unwrap_or(0);
        let maps: Vec<PlanarMap> = if params.prune && pre.is_none() {
            pyr.levels
                .par_iter()
                .map(|l| PlanarMap::new(&l.hog, pad_x, pad_y))
                .collect()
        } else {
            Vec::new()
        };
        let counters: Vec<CliqueCounter> = if params.prune {
            pyr.levels
                .par_iter()
                .map(|l| CliqueCounter::new(&l.cell_segments, l.hog.width(), l.hog.height()))
                .collect()
        } else {
            Vec::new()
        };
        let empty = PlanarMap::new(&HogMap::zeros(0, 0), 0, 0);
        let jobs: Vec<(usize, usize)> = (0..pyr.levels.len())
            .flat_map(|l| (0..self.views.len()).map(move |v| (l, v)))
            .collect();
        let scanned: Vec<(usize, Vec<Candidate>)> = jobs
            .par_iter()
            .map(|&(l, v)| {
                if params.deadline.passed() {
                    return (0, Vec::new());
                }
                let map = maps.get(l).unwrap_or(&empty);
                let level = &pyr.levels[l];
                let b = pre.and_then(|b| b.get(l, v));
                self.scan_level(l, level, map, counters.get(l), v, params, cut, max_loss, b)
            })
            .collect();
        let mut cands: Vec<Candidate> = Vec::new();
        for (count, c) in scanned {
            stats.locations += count;
            cands.extend(c);
        }
        if let Some(r) = params.region {
            cands.retain(|c| {
                box_iou(self.grid(pyr, &c.location()).pixel_box(), r.bbox) >= r.min_iou.max(1e-12)
            });
        }
        stats.pruned_stage1 = stats.locations - cands.len();
        stats.responses_ms = t.elapsed().as_secs_f64() * 1e3;
        // Visit in order of the bound (ties in a fixed order).
        cands.sort_by(|a, b| {
            a.bound
                .total_cmp(&b.bound)
                .then((a.level, a.view, a.y, a.x).cmp(&(b.level, b.view, b.y, b.x)))
        });

        let t = Instant::now();
        // Branch and bound: locations are visited in order of their bound,
        // and once `max_detections` detections survive non-maximum
        // suppression among those solved, the worst of them is the cut-off:
        // a location whose bound is above it ranks after all of them in the
        // greedy suppression, so it can never be reported.
        let single = params.max_detections == 1 && params.prune;
        let ranked = params.prune && budget.is_none();
        let mut solved: Vec<Solved> = Vec::new();
        let mut best = cut;
        let chunk = if single {
            64
        } else if ranked {
            256
        } else {
            cands.len().max(1)
        };
        for block in cands.chunks(chunk) {
            if (single || ranked) && block[0].bound - margin(block[0].bound) > best {
                break;
            }
            if budget.is_some_and(|b| stats.min_cuts >= b) || params.deadline.passed() {
                break;
            }
            let cutoff = best;
            let out: Vec<Option<Solved>> = block
                .par_iter()
                .map_init(Scratch::default, |s, c| {
                    if (single || ranked) && c.bound - margin(c.bound) > cutoff {
                        return None;
                    }
                    self.solve(pyr, c, cutoff, params.prune, aug, s)
                })
                .collect();
            for r in out.into_iter().flatten() {
                stats.min_cuts += 1;
                if r.energy <= cut {
                    if single {
                        best = best.min(r.energy);
                    }
                    solved.push(r);
                }
            }
            if ranked && !single && solved.len() >= params.max_detections {
                if let Some(e) = self.kth_energy(pyr, &mut solved, params) {
                    best = best.min(e);
                }
            }
        }
        stats.pruned_stage2 = stats.locations - stats.pruned_stage1 - stats.min_cuts;
        stats.mincut_ms = t.elapsed().as_secs_f64() * 1e3;
        (solved, stats)
    }

    /// The energy of the last of `max_detections` detections that survive
    /// greedy non-maximum suppression among `solved` (sorted in place), if
    /// that many survive.
    fn kth_energy(
        &self,
        pyr: &FeaturePyramid,
        solved: &mut [Solved],
        params: &DetectParams,
    ) -> Option<f64> {
        sort_solved(solved);
        let mut kept: Vec<(f64, f64, f64, f64)> = Vec::new();
        for s in solved.iter() {
            let b = self.grid(pyr, &s.cand.location()).pixel_box();
            if kept.iter().any(|k| box_iou(*k, b) > params.nms_iou) {
                continue;
            }
            kept.push(b);
            if kept.len() == params.max_detections {
                return Some(s.energy);
            }
        }
        None
    }

    /// Sorts by score (ties in a fixed order), converts to image boxes and
    /// applies greedy non-maximum suppression.
    fn suppress(
        &self,
        pyr: &FeaturePyramid,
        mut solved: Vec<Solved>,
        params: &DetectParams,
    ) -> Vec<Detection> {
        sort_solved(&mut solved);
        let mut out: Vec<Detection> = Vec::new();
        for s in solved {
            if out.len() >= params.max_detections {
                break;
            }
            let view = &self.views[s.cand.view];
            let level = &pyr.levels[s.cand.level];
            let grid = self.grid(pyr, &s.cand.location());
            let bbox = grid.pixel_box();
            if out.iter().any(|d| box_iou(d.bbox, bbox) > params.nms_iou) {
                continue;
            }
            let (mw, mh) = (level.hog.width(), level.hog.height());
            let truncated = s.cand.x < 0
                || s.cand.y < 0
                || s.cand.x + view.w.cols as isize > mw as isize
                || s.cand.y + view.w.rows as isize > mh as isize;
            let visible = s.cells.iter().filter(|&&v| v).count();
            out.push(Detection {
                viewpoint: s.cand.view,
                level: s.cand.level,
                score: -s.energy,
                bbox,
                grid,
                visible_fraction: visible as f64 / s.cells.len() as f64,
                cells: s.cells,
                truncated,
            });
        }
        out
    }
}

/// Best energy first, ties in a fixed order.
fn sort_solved(solved: &mut [Solved]) {
    solved.sort_by(|a, b| {
        a.energy
            .total_cmp(&b.energy)
            .then(a.cand.location().cmp(&b.cand.location()))
    });
}

/// IoU of two boxes `(x, y, w, h)`.
pub fn box_iou(a: (f64, f64, f64, f64), b: (f64, f64, f64, f64)) -> f64 {
    let ix = (a.0 + a.2).min(b.0 + b.2) - a.0.max(b.0);
    let iy = (a.1 + a.3).min(b.1 + b.3) - a.1.max(b.1);
    if ix <= 0.0 || iy <= 0.0 {
        return 0.0;
    }
    let inter = ix * iy;
    inter / (a.2 * a.3 + b.2 * b.3 - inter)
}

/// The raw and refined pixel masks of a detection.
pub fn detection_masks(
    det: &Detection,
    pyr: &FeaturePyramid,
    refine: &RefineParams,
) -> (Mask, Mask) {
    let raw = raw_mask(&det.grid, &det.cells, pyr.image_width, pyr.image_height);
    let refined = refine_mask(&raw, &det.grid, &pyr.segmentation, refine);
    (raw, refined)
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;

    #[test]
    fn iou_of_boxes() {
        assert_eq!(box_iou((0.0, 0.0, 2.0, 2.0), (2.0, 0.0, 2.0, 2.0)), 0.0);
        assert!((box_iou((0.0, 0.0, 2.0, 2.0), (1.0, 0.0, 2.0, 2.0)) - 1.0 / 3.0).abs() < 1e-12);
    }

    #[test]
    fn clique_counter_bounds_distinct_segments() {
        let mut rng = crate::vision::rng::SplitMix64::new(5);
        for t in 0..300 {
            let (w, h) = (1 + t % 9, 1 + (t / 9) % 7);
            let labels = 1 + rng.range_usize(0, 6);
            let seg: Vec<u32> = (0..w * h)
                .map(|_| rng.range_usize(0, labels) as u32)
                .collect();
            let c = CliqueCounter::new(&seg, w, h);
            for x0 in 0..w {
                for x1 in x0 + 1..=w {
                    for y0 in 0..h {
                        for y1 in y0 + 1..=h {
                            let mut seen: Vec<u32> = (y0..y1)
                                .flat_map(|y| (x0..x1).map(move |x| (x, y)))
                                .map(|(x, y)| seg[y * w + x])
                                .collect();
                            seen.sort_unstable();
                            seen.dedup();
                            let b = c.bound(x0, x1, y0, y1);
                            assert!(b >= seen.len(), "{seg:?} {w}x{h} [{x0},{x1})x[{y0},{y1})");
                            assert!(b <= (x1 - x0) * (y1 - y0));
                        }
                    }
                }
            }
        }
        // One segment: exactly one clique; a checkerboard: every cell.
        let c = CliqueCounter::new(&[3; 12], 4, 3);
        assert_eq!(c.bound(0, 4, 0, 3), 1);
        let board: Vec<u32> = (0..12).map(|i| ((i % 4 + i / 4) % 2) as u32).collect();
        assert_eq!(CliqueCounter::new(&board, 4, 3).bound(1, 4, 0, 3), 9);
    }

    #[test]
    fn positions_keep_enough_cells_inside() {
        let (lo, hi) = positions(10, 4, 2);
        assert_eq!((lo, hi), (-2, 8));
        assert_eq!(overlap(-2, 4, 10), 2);
        assert_eq!(overlap(8, 4, 10), 2);
    }

    #[test]
    fn dot_matches_plain_sum() {
        let a: Vec<f32> = (0..77).map(|i| i as f32 * 0.1).collect();
        let b: Vec<f32> = (0..77).map(|i| 1.0 - i as f32 * 0.01).collect();
        let plain: f32 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
        assert!((dot(&a, &b) - plain).abs() < 1e-3);
    }
}
