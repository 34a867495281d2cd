//! Exact pruning's bounds (stage 1 of [`super`]): one dense pass per level
//! and viewpoint computes every location's row-and-column chain bound of
//! the unary and pairwise energy, plus the smallest clique potential times
//! the number of cliques in the box: one, or an upper bound on it
//! ([`CliqueCounter`], O(1) per box) where the smallest potential is
//! negative, then at the positions that pass, the count itself
//! ([`CliqueCount`]). `dense_bounds` and `responses` are the CPU
//! references of `kernels/dense_bounds.wgsl` and
//! `kernels/responses.wgsl`.

use super::low_rank::{LowRankBasis, LowRankFilter, LOW_RANK_DIMS};
use super::*;

/// Upper bounds on the number of cliques (distinct segments) among the
/// cells of any box of a level, in O(1) per box. A box's cells of one
/// segment form one or more 4-connected pieces, and the first cell of each
/// piece in raster order has neither its left nor its upper neighbour in the
/// piece: that neighbour is outside the box or in another segment. Counting
/// such cells with prefix sums bounds the number of pieces, hence of
/// cliques.
pub(super) struct CliqueCounter {
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
    pub(super) fn new(seg: &[u32], w: usize, h: usize) -> Self {
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
    pub(super) fn bound(&self, x0: usize, x1: usize, y0: usize, y1: usize) -> usize {
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
/// The exact number of cliques of a box (distinct segments among its
/// cells inside the image; the CRF's clique count), taken only at the
/// positions that the cheaper bounds leave (issue 63: with positive clique
/// potentials, as learned cells' models have, one clique was all stage 1
/// counted, and 4,400-8,500 locations a photograph passed it against
/// HOG's 300). It keeps the cells of the box asked last per segment, so
/// that the next box of the same rows further along them costs only the
/// columns it gains and loses (a scan asks in raster order), and counts
/// the box afresh where that would cost more.
#[derive(Default)]
pub(super) struct CliqueCount {
    /// Cells of each segment in the window (valid where `stamp` is the
    /// current generation).
    cells: Vec<u32>,
    stamp: Vec<u32>,
    generation: u32,
    /// The map, rows and columns held: `(seg's address, mw, y0, y1, x0,
    /// x1)`, and the distinct segments among them.
    window: Option<(usize, usize, usize, usize, usize, usize)>,
    distinct: u32,
}

impl CliqueCount {
    /// The cliques of the `rows x cols` box at top-left cell `(x, y)` of a
    /// level of `mw x mh` cells whose segments are `seg`.
    pub(super) fn count(
        &mut self,
        seg: &[u32],
        (mw, mh): (usize, usize),
        (rows, cols): (usize, usize),
        (x, y): (isize, isize),
    ) -> u32 {
        let (x0, x1) = (
            x.max(0) as usize,
            ((x + cols as isize).max(0) as usize).min(mw),
        );
        let (y0, y1) = (
            y.max(0) as usize,
            ((y + rows as isize).max(0) as usize).min(mh),
        );
        let key = seg.as_ptr() as usize;
        match self.window {
            // The same rows, further along: drop the columns left behind,
            // add the new ones, where that is cheaper than counting anew.
            Some((k, w, wy0, wy1, wx0, wx1))
                if k == key
                    && w == mw
                    && (wy0, wy1) == (y0, y1)
                    && wx0 <= x0
                    && wx1 <= x1
                    && x0 < wx1
                    && (x0 - wx0) + (x1 - wx1) < x1 - x0 =>
            {
                for xx in wx0..x0 {
                    self.column(seg, mw, (y0, y1), xx, false);
                }
                for xx in wx1..x1 {
                    self.column(seg, mw, (y0, y1), xx, true);
                }
            }
            _ => {
                self.generation = self.generation.wrapping_add(1);
                if self.generation == 0 {
                    self.stamp.iter_mut().for_each(|s| *s = 0);
                    self.generation = 1;
                }
                self.distinct = 0;
                for xx in x0..x1 {
                    self.column(seg, mw, (y0, y1), xx, true);
                }
            }
        }
        self.window = Some((key, mw, y0, y1, x0, x1));
        self.distinct
    }

    /// Adds (or removes) the cells of column `x`, rows `y0..y1`.
    fn column(&mut self, seg: &[u32], mw: usize, (y0, y1): (usize, usize), x: usize, add: bool) {
        for yy in y0..y1 {
            let s = seg[yy * mw + x] as usize;
            if s >= self.stamp.len() {
                self.stamp.resize(s + 1, 0);
                self.cells.resize(s + 1, 0);
            }
            if self.stamp[s] != self.generation {
                self.stamp[s] = self.generation;
                self.cells[s] = 0;
            }
            if add {
                self.cells[s] += 1;
                if self.cells[s] == 1 {
                    self.distinct += 1;
                }
            } else {
                self.cells[s] -= 1;
                if self.cells[s] == 0 {
                    self.distinct -= 1;
                }
            }
        }
    }
}

/// Dot product of two equal-length slices with eight accumulators (the
/// compiler vectorises it; see [`dot`] for the dispatch).
#[inline(always)]
pub(super) fn dot_body(a: &[f32], b: &[f32]) -> f32 {
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

/// Dot product, using AVX2 when [`crate::vision::simd::level`] allows it.
#[inline]
pub fn dot(a: &[f32], b: &[f32]) -> f32 {
    #[cfg(target_arch = "x86_64")]
    {
        use crate::vision::simd::{level, Simd};
        if matches!(level(), Simd::Avx2 | Simd::Avx512) {
            // SAFETY: AVX2 and FMA were detected at run time.
            return unsafe { dot_avx2(a, b) };
        }
    }
    dot_body(a, b)
}

/// Lanes of the dense bound kernel: consecutive positions computed together
/// (one AVX-512 register, two AVX2 ones: 16 lanes were faster than 8 on
/// AVX2 as well, 17.8 against 19.7 ms per image with one model).
pub(super) const LANES: usize = 16;

/// The HOG map of a level as one zero-padded plane per feature dimension, so
/// that consecutive box positions read consecutive values.
pub(super) struct PlanarMap {
    pad_x: usize,
    pad_y: usize,
    width: usize,
    plane_len: usize,
    pub(super) data: Vec<f32>,
}

impl PlanarMap {
    pub(super) fn new(hog: &HogMap, pad_x: usize, pad_y: usize) -> Self {
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

    /// The planes of `hog` projected on `basis` (its first
    /// [`LOW_RANK`] planes) and each cell's feature norm, rounded up (the
    /// last plane), for [`LowRankFilter`]s.
    pub(super) fn projected(
        hog: &HogMap,
        basis: &LowRankBasis,
        pad_x: usize,
        pad_y: usize,
    ) -> Self {
        let width = hog.width() + 2 * pad_x + LANES;
        let height = hog.height() + 2 * pad_y;
        let plane_len = width * height;
        let mut data = vec![0.0f32; plane_len * LOW_RANK_DIMS];
        for y in 0..hog.height() {
            for x in 0..hog.width() {
                let o = (y + pad_y) * width + x + pad_x;
                let f = &hog.cell(x, y)[..HOG_DIM];
                for (k, b) in basis.vectors.iter().enumerate() {
                    data[k * plane_len + o] = dot_body(b, f);
                }
                let norm = f.iter().map(|v| v * v).sum::<f32>().sqrt();
                data[LOW_RANK * plane_len + o] = norm * (1.0 + 1e-5) + 1e-7;
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

/// The filters one dense bound reads: `stride` values per cell, the first
/// `D` used.
pub(super) struct BoundFilter<'a> {
    rows: usize,
    cols: usize,
    stride: usize,
    vis: &'a [f32],
    occ: &'a [f32],
    prior: &'a [f32],
}

impl<'a> BoundFilter<'a> {
    pub(super) fn full(w: &'a ViewWeights) -> Self {
        Self {
            rows: w.rows,
            cols: w.cols,
            stride: HOG_STRIDE,
            vis: &w.w_vis,
            occ: &w.w_occ,
            prior: &w.w_prior,
        }
    }

    pub(super) fn low_rank(w: &'a ViewWeights, f: &'a LowRankFilter) -> Self {
        Self {
            rows: w.rows,
            cols: w.cols,
            stride: LOW_RANK_DIMS,
            vis: &f.vis,
            occ: &f.occ,
            prior: &w.w_prior,
        }
    }
}

/// Stage 1's feature planes of every level of one pyramid, padded for the
/// largest template of several models, so that the models scanning the
/// pyramid share them instead of each building its own (the padding only
/// adds zeros: the bounds are the same).
pub struct PlanarMaps<'p> {
    pyr: &'p FeaturePyramid,
    pad_x: usize,
    pad_y: usize,
    pub(super) maps: Vec<PlanarMap>,
}

impl<'p> PlanarMaps<'p> {
    /// The planes of `pyr` for templates of the given viewpoints.
    pub fn new(pyr: &'p FeaturePyramid, views: &[&[ViewWeights]]) -> Self {
        let all = || views.iter().flat_map(|v| v.iter());
        let pad_x = all().map(|v| v.cols).max().unwrap_or(0);
        let pad_y = all().map(|v| v.rows).max().unwrap_or(0);
        let maps = pyr
            .levels
            .par_iter()
            .map(|l| PlanarMap::new(&l.hog, pad_x, pad_y))
            .collect();
        Self {
            pyr,
            pad_x,
            pad_y,
            maps,
        }
    }

    /// Whether these are `pyr`'s planes with at least this padding.
    pub(super) fn serves(&self, pyr: &FeaturePyramid, pad_x: usize, pad_y: usize) -> bool {
        std::ptr::eq(self.pyr, pyr)
            && self.pad_x >= pad_x
            && self.pad_y >= pad_y
            && self.maps.len() == pyr.levels.len()
    }
}

/// Scratch of the dense bound: the column chains' states and the sums
/// along one output row of positions.
#[derive(Default)]
pub(super) struct DenseScratch {
    c0: Vec<[f32; LANES]>,
    c1: Vec<[f32; LANES]>,
    acc: Vec<[f32; LANES]>,
}

/// One step of a chain's dynamic programme over [`LANES`] positions: the
/// best energies ending in label 0 and 1 after adding a cell of unaries
/// `(u0, u1)`.
#[inline(always)]
pub(super) fn chain_step(
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

/// One template row of [`dense_row_body`] over `NB` consecutive blocks of
/// positions from `blk`: the row chains run to the row's end and are added
/// to the blocks' sums, every cell steps the column chains. Each lane does
/// the same operations in the same order whatever `NB` is.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn row_blocks<const NB: usize, const D: usize>(
    map: &PlanarMap,
    w: &BoundFilter,
    pair: f32,
    row: usize,
    ty: usize,
    blk: usize,
    blocks: usize,
    s: &mut DenseScratch,
) {
    let cols = w.cols;
    let mut r0 = [[0.0f32; LANES]; NB];
    let mut r1 = [[0.0f32; LANES]; NB];
    for tx in 0..cols {
        let i = ty * cols + tx;
        let wv = &w.vis[i * w.stride..i * w.stride + D];
        let wo = &w.occ[i * w.stride..i * w.stride + D];
        // Two partial sums per filter hide the multiply-add latency.
        let mut f0 = [[0.0f32; LANES]; NB];
        let mut f1 = [[0.0f32; LANES]; NB];
        let mut g0 = [[0.0f32; LANES]; NB];
        let mut g1 = [[0.0f32; LANES]; NB];
        // The `NB` blocks' features of plane `d`: one range check per plane
        // (the map's padding makes it always succeed; zeros otherwise).
        let start = row + blk * LANES + tx;
        let plane = |d: usize| -> [[f32; LANES]; NB] {
            let o = d * map.plane_len + start;
            let mut v = [[0.0f32; LANES]; NB];
            if let Some(src) = map.data.get(o..o + NB * LANES) {
                for (dst, chunk) in v.iter_mut().zip(src.chunks_exact(LANES)) {
                    dst.copy_from_slice(chunk);
                }
            }
            v
        };
        let mut d = 0;
        while d + 1 < D {
            let (a0, a1, b0, b1) = (wv[d], wv[d + 1], wo[d], wo[d + 1]);
            let (p0, p1) = (plane(d), plane(d + 1));
            for b in 0..NB {
                let (v0, v1) = (p0[b], p1[b]);
                for l in 0..LANES {
                    f0[b][l] += a0 * v0[l];
                    g0[b][l] += b0 * v0[l];
                    f1[b][l] += a1 * v1[l];
                    g1[b][l] += b1 * v1[l];
                }
            }
            d += 2;
        }
        if d < D {
            let p0 = plane(d);
            for b in 0..NB {
                let v0 = p0[b];
                for l in 0..LANES {
                    f0[b][l] += wv[d] * v0[l];
                    g0[b][l] += wo[d] * v0[l];
                }
            }
        }
        let r = w.prior[i];
        for b in 0..NB {
            // Half of each unary to the row chain, half to the column.
            let mut u0 = [0.0f32; LANES];
            let mut u1 = [0.0f32; LANES];
            for l in 0..LANES {
                u1[l] = 0.5 * (f0[b][l] + f1[b][l]);
                u0[l] = 0.5 * (g0[b][l] + g1[b][l] + r);
            }
            if tx == 0 {
                r0[b] = u0;
                r1[b] = u1;
            } else {
                chain_step(&mut r0[b], &mut r1[b], &u0, &u1, pair);
            }
            let c = tx * blocks + blk + b;
            if ty == 0 {
                s.c0[c] = u0;
                s.c1[c] = u1;
            } else {
                let (c0, c1) = (&mut s.c0[c], &mut s.c1[c]);
                chain_step(c0, c1, &u0, &u1, pair);
            }
        }
    }
    for b in 0..NB {
        let acc = &mut s.acc[blk + b];
        for l in 0..LANES {
            acc[l] += r0[b][l].min(r1[b][l]);
        }
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
pub(super) fn dense_row_body<const D: usize>(
    map: &PlanarMap,
    w: &BoundFilter,
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
        // Two blocks at a time: each filter weight loaded once serves 32
        // positions, and one range check per feature plane serves both
        // (8 models, one thread: 76.5 -> 67 ms; four blocks at a time spill
        // registers and take 180 ms).
        let mut blk = 0;
        while blk + 1 < blocks {
            row_blocks::<2, D>(map, w, pair, row, ty, blk, blocks, s);
            blk += 2;
        }
        if blk < blocks {
            row_blocks::<1, D>(map, w, pair, row, ty, blk, blocks, s);
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
#[target_feature(enable = "avx512f,avx512bw,avx512dq,avx512vl,avx2,fma")]
unsafe fn dense_row_avx512<const D: usize>(
    map: &PlanarMap,
    w: &BoundFilter,
    pair: f32,
    x0: isize,
    y: isize,
    out: &mut [f32],
    s: &mut DenseScratch,
) {
    dense_row_body::<D>(map, w, pair, x0, y, out, s)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn dense_row_avx2<const D: usize>(
    map: &PlanarMap,
    w: &BoundFilter,
    pair: f32,
    x0: isize,
    y: isize,
    out: &mut [f32],
    s: &mut DenseScratch,
) {
    dense_row_body::<D>(map, w, pair, x0, y, out, s)
}

/// One row of chain bounds over `D` feature planes with the best
/// instruction set.
pub(super) fn dense_row_with<const D: usize>(
    map: &PlanarMap,
    w: &BoundFilter,
    pair: f32,
    x0: isize,
    y: isize,
    out: &mut [f32],
    s: &mut DenseScratch,
) {
    #[cfg(target_arch = "x86_64")]
    match crate::vision::simd::level() {
        // SAFETY: the features were detected at run time.
        crate::vision::simd::Simd::Avx512 => {
            return unsafe { dense_row_avx512::<D>(map, w, pair, x0, y, out, s) }
        }
        // SAFETY: the features were detected at run time.
        crate::vision::simd::Simd::Avx2 => {
            return unsafe { dense_row_avx2::<D>(map, w, pair, x0, y, out, s) }
        }
        crate::vision::simd::Simd::Portable => {}
    }
    dense_row_body::<D>(map, w, pair, x0, y, out, s)
}

/// One row of the full chain bounds of `w` (see [`dense_row_body`]).
pub(super) fn dense_row(
    map: &PlanarMap,
    w: &ViewWeights,
    pair: f32,
    x0: isize,
    y: isize,
    out: &mut [f32],
    s: &mut DenseScratch,
) {
    dense_row_with::<HOG_DIM>(map, &BoundFilter::full(w), pair, x0, y, out, s)
}

/// Range of top-left positions along one axis whose box of `len` cells has
/// at least `min_inside` cells inside `[0, size)`.
pub(super) fn positions(size: usize, len: usize, min_inside: usize) -> (isize, isize) {
    let lo = min_inside as isize - len as isize;
    let hi = size as isize - min_inside as isize;
    (lo, hi)
}

pub(super) fn overlap(start: isize, len: usize, size: usize) -> usize {
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
    pub(super) fn get(&self, level: usize, view: usize) -> Option<&LevelBounds> {
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
    let views: Vec<&ViewWeights> = views.iter().collect();
    dense_bounds_of(pyr, &views, max_truncation)
}

fn dense_bounds_of(
    pyr: &FeaturePyramid,
    views: &[&ViewWeights],
    max_truncation: f64,
) -> DenseBounds {
    let levels = pyr
        .levels
        .par_iter()
        .map(|level| {
            views
                .iter()
                .map(|&w| {
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

impl Detector<'_> {
    /// Stage 1's chain bounds of every position of `pyr` ([`dense_bounds`]
    /// of this detector's viewpoints): computed once, they serve several
    /// searches of one image (`pre` of [`Detector::most_violated`]).
    pub fn dense_bounds(&self, pyr: &FeaturePyramid, max_truncation: f64) -> DenseBounds {
        let views: Vec<&ViewWeights> = self.views.iter().map(|v| v.w).collect();
        dense_bounds_of(pyr, &views, max_truncation)
    }

    /// Stage 1 at every location of one level and viewpoint: the exact
    /// best-unary bound of each location that passes `cut`, or every location
    /// when not pruning.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn scan_level(
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
        low_map: Option<&PlanarMap>,
        centres: Option<(f64, f64, f64, f64)>,
    ) -> (usize, Vec<Candidate>) {
        let view = &self.views[vi];
        let (rows, cols) = (view.w.rows, view.w.cols);
        let n = rows * cols;
        let (mw, mh) = (level.hog.width(), level.hog.height());
        let Some((mut x_lo, mut x_hi, mut y_lo, mut y_hi, min_inside)) =
            scan_range(mw, mh, rows, cols, params.max_truncation)
        else {
            return (0, Vec::new());
        };
        // Bounds a backend (or an earlier pass) computed for exactly these
        // positions.
        let pre = pre.filter(|b| {
            b.x_lo == x_lo
                && b.y_lo == y_lo
                && b.nx == (x_hi - x_lo + 1) as usize
                && b.ny == (y_hi - y_lo + 1) as usize
                && b.values.len() == b.nx * b.ny
        });
        if let Some((x0, y0, x1, y1)) = centres {
            // Positions whose window centre, `(x + cols / 2)` cells, can
            // fall in the rectangle (a cell wider either way; the exact
            // test is the caller's).
            let cs = CELL_SIZE as f64;
            // In floating point, then cast (saturating): a region may be
            // unbounded.
            let span = |lo: f64, hi: f64, scale: f64, half: f64| {
                (
                    ((lo * scale / cs - half).floor() - 1.0) as isize,
                    ((hi * scale / cs - half).ceil() + 1.0) as isize,
                )
            };
            let (xa, xb) = span(x0, x1, level.scale_x, cols as f64 / 2.0);
            let (ya, yb) = span(y0, y1, level.scale_y, rows as f64 / 2.0);
            x_lo = x_lo.max(xa);
            x_hi = x_hi.min(xb);
            y_lo = y_lo.max(ya);
            y_hi = y_hi.min(yb);
            if x_lo > x_hi || y_lo > y_hi {
                return (0, Vec::new());
            }
        }
        let mut out = Vec::new();
        let mut count = 0;
        let nx = (x_hi - x_lo + 1) as usize;
        let mut sums = vec![0.0f32; nx];
        let mut scratch = DenseScratch::default();
        let pair = chain_pair_weight(view.w);
        // Without usable bounds the caller may not have built the map.
        let low = match (self.low_rank, low_map) {
            (Some(lr), Some(lm)) if pre.is_none() && !lm.data.is_empty() => {
                Some((lm, BoundFilter::low_rank(view.w, &lr.filters[vi])))
            }
            _ => None,
        };
        let own;
        let map = if params.prune && pre.is_none() && low.is_none() && map.data.is_empty() {
            own = PlanarMap::new(&level.hog, cols, rows);
            &own
        } else {
            map
        };
        let mut exact = CliqueCount::default();
        for y in y_lo..=y_hi {
            let oy = overlap(y, rows, mh);
            if params.prune {
                if let Some(b) = pre {
                    // Positions narrowed to `centres` lie inside the full
                    // range `b` covers.
                    let r = (y - b.y_lo) as usize * b.nx + (x_lo - b.x_lo) as usize;
                    sums.copy_from_slice(&b.values[r..r + nx]);
                } else if let Some((lm, f)) = &low {
                    dense_row_with::<LOW_RANK_DIMS>(lm, f, pair, x_lo, y, &mut sums, &mut scratch);
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
                // Every clique costs at least the smallest potential: first
                // with one clique or a bound on their count, then with the
                // count itself.
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
                let rest = f64::from(view.w.w_trunc) * truncated + f64::from(view.w.bias)
                    - max_loss
                    + f64::from(sums[k]);
                let bound = if params.prune {
                    let b = hop + rest;
                    if b - margin(b) > cut {
                        continue;
                    }
                    let n = exact.count(&level.cell_segments, (mw, mh), (rows, cols), (x, y));
                    let b = view.hop_min * f64::from(n) + rest;
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
}

#[cfg(test)]
#[path = "bounds_tests.rs"]
mod tests;
