//! The depthwise convolutions of the backbone's blocks: the tap-by-tap
//! reference and the fused 3x3 and 5x5 kernels, and the input rows they
//! read (as they are, or split into even and odd samples at stride 2).

#[cfg(test)]
use super::FeatureMap;
use super::{relu6, same_padding, Depthwise};

impl Depthwise {
    /// The whole map at once (the reference the banded path is tested
    /// against).
    #[cfg(test)]
    pub(super) fn apply(&self, x: &FeatureMap) -> FeatureMap {
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
    pub(super) fn apply_rows(
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
pub(super) fn fused_taps<const N: usize>(
    out: &mut [f32],
    bias: f32,
    kernel: &[f32; N],
    taps: &[&[f32]; N],
) {
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
pub(super) fn split_phases(src: &[f32], width: usize, half: usize, phases: &mut [f32]) {
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
pub(super) struct DepthwiseScratch {
    pub(super) phases: Vec<f32>,
    pub(super) zeros: Vec<f32>,
}

/// Rows `y0..y0 + rows` of a channels-first map of `height` rows: channel
/// `c`'s row `y0 + r` at `data[c * plane + r * width..]`, or where
/// `phased`, at `data[c * plane + r * 2 * ceil(width / 2)..]`, its even
/// samples then its odd ones (as [`split_phases`] leaves them).
pub(super) struct Rows<'a> {
    pub(super) data: &'a [f32],
    pub(super) plane: usize,
    pub(super) width: usize,
    pub(super) y0: usize,
    pub(super) rows: usize,
    pub(super) height: usize,
    pub(super) phased: bool,
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
