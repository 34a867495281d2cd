//! The blocks run band by band: a few output rows at a time on every
//! compute thread, each band's expansion, depthwise convolution and
//! projection on the processor's best instruction set, written straight
//! into the output map.

use rayon::prelude::*;

use super::depthwise::{DepthwiseScratch, Rows};
use super::{relu6, same_padding, Block, FeatureMap};
use crate::vision::{Deadline, VisionError};

/// Output rows of a block computed at a time: the expanded map is held
/// for one band only (a few hundred kilobytes rather than, at the
/// largest pyramid levels, a few hundred megabytes allocated and faulted
/// in per layer), the rows two bands share expanded once where one
/// thread runs both (4 rows: 548-565 ms for the backbone bench's four
/// levels against 578-585 at 8).
pub(super) const BAND_ROWS: usize = 4;

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
pub(super) struct Scratch {
    pub(super) expanded: Vec<f32>,
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
    pub(super) fn apply(
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
pub(super) fn banded<F>(
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
pub(super) struct BandOut<'a> {
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
    pub(super) fn channel(&mut self, c: usize) -> &mut [f32] {
        assert!(c < self.channels);
        // SAFETY: inside the map (`new`'s contract), the band's own, and
        // borrowed from `self` exclusively.
        unsafe {
            std::slice::from_raw_parts_mut(self.ptr.add(c * self.plane + self.offset), self.n)
        }
    }

    /// The band = `a (channels x k, row-major) * b`, `b`'s row `r` at
    /// `b[r * b_stride..][..n]`.
    pub(super) fn gemm(&mut self, k: usize, a: &[f32], b: &[f32], b_stride: usize) {
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
pub(super) fn gemm_general(
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
