//! A small planar-free RGB float image type used by the vision layer, and
//! area-averaging resampling for the scale pyramid.

use super::{Deadline, VisionError};

/// Number of colour channels of [`ColorImage`].
pub const CHANNELS: usize = 3;

/// An interleaved RGB image with `f32` samples in `[0, 255]`.
#[derive(Clone, Debug, PartialEq)]
pub struct ColorImage {
    width: usize,
    height: usize,
    data: Vec<f32>,
}

impl ColorImage {
    /// Builds an image from interleaved RGB samples.
    pub fn new(width: usize, height: usize, data: Vec<f32>) -> Result<Self, VisionError> {
        if width == 0 || height == 0 {
            return Err(VisionError::EmptyImage { width, height });
        }
        let expected = width
            .checked_mul(height)
            .and_then(|n| n.checked_mul(CHANNELS))
            .ok_or(VisionError::ImageTooLarge { width, height })?;
        if data.len() != expected {
            return Err(VisionError::BufferSize {
                expected,
                actual: data.len(),
            });
        }
        if data.iter().any(|v| !v.is_finite()) {
            return Err(VisionError::NonFinite("image samples"));
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// Converts an 8-bit RGB image.
    pub fn from_rgb8(img: &image::RgbImage) -> Result<Self, VisionError> {
        let (w, h) = img.dimensions();
        let data = img.as_raw().iter().map(|&v| f32::from(v)).collect();
        Self::new(w as usize, h as usize, data)
    }

    /// Converts back to 8-bit RGB (rounded and clamped).
    pub fn to_rgb8(&self) -> image::RgbImage {
        let raw: Vec<u8> = self
            .data
            .iter()
            .map(|v| v.round().clamp(0.0, 255.0) as u8)
            .collect();
        // The buffer length is width*height*3 by construction.
        image::RgbImage::from_raw(self.width as u32, self.height as u32, raw)
            .unwrap_or_else(|| image::RgbImage::new(self.width as u32, self.height as u32))
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    /// Interleaved samples, row-major, `CHANNELS` per pixel.
    pub fn data(&self) -> &[f32] {
        &self.data
    }

    /// The image mirrored left to right.
    pub fn mirrored(&self) -> Self {
        let row = self.width * CHANNELS;
        let mut data = Vec::with_capacity(self.data.len());
        for line in self.data.chunks_exact(row) {
            for px in line.chunks_exact(CHANNELS).rev() {
                data.extend_from_slice(px);
            }
        }
        Self {
            width: self.width,
            height: self.height,
            data,
        }
    }

    /// The sample of channel `c` at `(x, y)`.
    #[inline]
    pub fn get(&self, x: usize, y: usize, c: usize) -> f32 {
        self.data[(y * self.width + x) * CHANNELS + c]
    }

    /// Resizes by area averaging to `new_w x new_h`: every output pixel is the
    /// exact mean of the input area it covers (an anti-aliased downscale, and a
    /// bilinear-like box upscale). Resizing to the same size is the identity.
    pub fn resize_area(&self, new_w: usize, new_h: usize) -> Result<Self, VisionError> {
        self.resize_with(new_w, new_h, area_weights, Deadline::NONE)
    }

    /// [`Self::resize_area`] that gives up with
    /// [`VisionError::DeadlineExceeded`] once `deadline` has passed (looked
    /// at every [`DEADLINE_ROWS`] rows of each pass).
    pub fn resize_area_until(
        &self,
        new_w: usize,
        new_h: usize,
        deadline: Deadline,
    ) -> Result<Self, VisionError> {
        self.resize_with(new_w, new_h, area_weights, deadline)
    }

    /// [`Self::resize_smooth`] that gives up once `deadline` has passed.
    pub fn resize_smooth_until(
        &self,
        new_w: usize,
        new_h: usize,
        deadline: Deadline,
    ) -> Result<Self, VisionError> {
        self.resize_with(new_w, new_h, smooth_weights, deadline)
    }

    /// Resizes by area averaging along an axis that shrinks and by linear
    /// interpolation (pixel centres aligned) along one that grows: what a
    /// network trained on photographs resampled smoothly should see, where
    /// [`Self::resize_area`]'s box upscale makes every pixel a block.
    pub fn resize_smooth(&self, new_w: usize, new_h: usize) -> Result<Self, VisionError> {
        self.resize_with(new_w, new_h, smooth_weights, Deadline::NONE)
    }

    /// Rows `y0..y1` of the image.
    pub fn rows(&self, y0: usize, y1: usize) -> Result<Self, VisionError> {
        if y0 >= y1 || y1 > self.height {
            return Err(VisionError::EmptyImage {
                width: self.width,
                height: y1.saturating_sub(y0),
            });
        }
        let row = self.width * CHANNELS;
        Ok(Self {
            width: self.width,
            height: y1 - y0,
            data: self.data[y0 * row..y1 * row].to_vec(),
        })
    }

    /// Rows `y0..y1` of [`Self::resize_smooth`]'s `new_w x new_h` image,
    /// computed from the input rows they read alone (the very same values):
    /// a large level is made strip by strip, never whole.
    pub fn resize_smooth_rows(
        &self,
        new_w: usize,
        new_h: usize,
        y0: usize,
        y1: usize,
    ) -> Result<Self, VisionError> {
        if new_w == 0 || new_h == 0 || y0 >= y1 || y1 > new_h {
            return Err(VisionError::EmptyImage {
                width: new_w,
                height: y1.saturating_sub(y0),
            });
        }
        let wy = smooth_weights(self.height, new_h);
        let rows = &wy[y0..y1];
        let lo = rows.iter().flatten().map(|&(i, _)| i).min().unwrap_or(0);
        let hi = rows.iter().flatten().map(|&(i, _)| i).max().unwrap_or(0);
        let row_in = self.width * CHANNELS;
        let src = &self.data[lo * row_in..(hi + 1) * row_in];
        let row = new_w * CHANNELS;
        let mut tmp = vec![0.0f32; (hi + 1 - lo) * row];
        if new_w == self.width {
            tmp.copy_from_slice(src);
        } else {
            let wx = FlatTaps::new(&smooth_weights(self.width, new_w));
            match wx.width {
                1 => wx.horizontal::<1>(src, self.width, &mut tmp),
                2 => wx.horizontal::<2>(src, self.width, &mut tmp),
                3 => wx.horizontal::<3>(src, self.width, &mut tmp),
                4 => wx.horizontal::<4>(src, self.width, &mut tmp),
                _ => wx.horizontal_any(src, self.width, &mut tmp),
            }
        }
        let mut out = vec![0.0f32; (y1 - y0) * row];
        for (dst, taps) in out.chunks_exact_mut(row).zip(rows) {
            if new_h == self.height {
                // No vertical resampling: the row itself (as `resize_with`
                // copies an image of the same size).
                let iy = taps.first().map_or(lo, |&(i, _)| i);
                dst.copy_from_slice(&tmp[(iy - lo) * row..(iy - lo + 1) * row]);
                continue;
            }
            for &(iy, w) in taps {
                let src = &tmp[(iy - lo) * row..(iy - lo + 1) * row];
                for (d, s) in dst.iter_mut().zip(src) {
                    *d += w * s;
                }
            }
        }
        Ok(Self {
            width: new_w,
            height: y1 - y0,
            data: out,
        })
    }

    /// A separable resize with the taps `weights(src, dst)` gives per axis.
    fn resize_with(
        &self,
        new_w: usize,
        new_h: usize,
        weights: impl Fn(usize, usize) -> Vec<Vec<(usize, f32)>>,
        deadline: Deadline,
    ) -> Result<Self, VisionError> {
        let check = || {
            if deadline.passed() {
                Err(VisionError::DeadlineExceeded)
            } else {
                Ok(())
            }
        };
        if new_w == 0 || new_h == 0 {
            return Err(VisionError::EmptyImage {
                width: new_w,
                height: new_h,
            });
        }
        if new_w == self.width && new_h == self.height {
            return Ok(self.clone());
        }
        let wx = FlatTaps::new(&weights(self.width, new_w));
        let wy = weights(self.height, new_h);
        // Horizontal pass: height x new_w, DEADLINE_ROWS rows at a time.
        let mut tmp = vec![0.0f32; self.height * new_w * CHANNELS];
        let bands = self
            .data
            .chunks(DEADLINE_ROWS * self.width * CHANNELS)
            .zip(tmp.chunks_mut(DEADLINE_ROWS * new_w * CHANNELS));
        for (src, dst) in bands {
            check()?;
            match wx.width {
                1 => wx.horizontal::<1>(src, self.width, dst),
                2 => wx.horizontal::<2>(src, self.width, dst),
                3 => wx.horizontal::<3>(src, self.width, dst),
                4 => wx.horizontal::<4>(src, self.width, dst),
                _ => wx.horizontal_any(src, self.width, dst),
            }
        }
        // Vertical pass.
        let row = new_w * CHANNELS;
        let mut out = vec![0.0f32; new_h * row];
        for (oy, taps) in wy.iter().enumerate() {
            if oy % DEADLINE_ROWS == 0 {
                check()?;
            }
            let dst = &mut out[oy * row..(oy + 1) * row];
            for &(iy, w) in taps {
                let src = &tmp[iy * row..(iy + 1) * row];
                for (d, s) in dst.iter_mut().zip(src) {
                    *d += w * s;
                }
            }
        }
        Ok(Self {
            width: new_w,
            height: new_h,
            data: out,
        })
    }
}

/// Rows of a resize pass between two looks at the deadline.
const DEADLINE_ROWS: usize = 64;

/// The taps of [`area_weights`] flattened to `width` per output (the
/// widest output's count), the missing ones with weight 0 on the output's
/// last input: adding `0 * x` after the real taps leaves every sum as it
/// was, so the resize computes the very same values without a branch or a
/// pointer per output.
struct FlatTaps {
    width: usize,
    index: Vec<usize>,
    weight: Vec<f32>,
}

impl FlatTaps {
    fn new(taps: &[Vec<(usize, f32)>]) -> Self {
        let width = taps.iter().map(Vec::len).max().unwrap_or(1).max(1);
        let mut index = Vec::with_capacity(taps.len() * width);
        let mut weight = Vec::with_capacity(taps.len() * width);
        for t in taps {
            let last = t.last().map_or(0, |&(i, _)| i);
            for k in 0..width {
                let (i, w) = t.get(k).copied().unwrap_or((last, 0.0));
                index.push(i);
                weight.push(w);
            }
        }
        Self {
            width,
            index,
            weight,
        }
    }

    /// One row pass of `T` taps per output over every row of `src` (rows of
    /// `src_w` pixels) into `dst` (rows of `self.index.len() / T` pixels).
    fn horizontal<const T: usize>(&self, src: &[f32], src_w: usize, dst: &mut [f32]) {
        let out_w = self.index.len() / T;
        let rows = src.chunks_exact(src_w * CHANNELS);
        for (s, d) in rows.zip(dst.chunks_exact_mut(out_w * CHANNELS)) {
            let outs = d.chunks_exact_mut(CHANNELS);
            let idx = self.index.chunks_exact(T);
            let wts = self.weight.chunks_exact(T);
            for ((o, i), w) in outs.zip(idx).zip(wts) {
                let mut acc = [0.0f32; CHANNELS];
                for k in 0..T {
                    let p = &s[i[k] * CHANNELS..i[k] * CHANNELS + CHANNELS];
                    for c in 0..CHANNELS {
                        acc[c] += w[k] * p[c];
                    }
                }
                o.copy_from_slice(&acc);
            }
        }
    }

    /// [`FlatTaps::horizontal`] for any width (upscales by large factors).
    fn horizontal_any(&self, src: &[f32], src_w: usize, dst: &mut [f32]) {
        let t = self.width;
        let out_w = self.index.len() / t;
        let rows = src.chunks_exact(src_w * CHANNELS);
        for (s, d) in rows.zip(dst.chunks_exact_mut(out_w * CHANNELS)) {
            let outs = d.chunks_exact_mut(CHANNELS);
            let idx = self.index.chunks_exact(t);
            let wts = self.weight.chunks_exact(t);
            for ((o, i), w) in outs.zip(idx).zip(wts) {
                let mut acc = [0.0f32; CHANNELS];
                for (&ik, &wk) in i.iter().zip(w) {
                    let p = &s[ik * CHANNELS..ik * CHANNELS + CHANNELS];
                    for (a, v) in acc.iter_mut().zip(p) {
                        *a += wk * v;
                    }
                }
                o.copy_from_slice(&acc);
            }
        }
    }
}

/// The taps of [`ColorImage::resize_smooth`] along one axis: linear
/// interpolation up, area averaging down (also uploaded to the GPU
/// backend for learned cells).
pub fn smooth_weights(src: usize, dst: usize) -> Vec<Vec<(usize, f32)>> {
    if dst > src {
        linear_weights(src, dst)
    } else {
        area_weights(src, dst)
    }
}

/// Linear interpolation's taps: output `o` samples the input at `(o + 0.5)
/// * src / dst - 0.5` (pixel centres aligned, clamped to the border).
pub fn linear_weights(src: usize, dst: usize) -> Vec<Vec<(usize, f32)>> {
    let scale = src as f64 / dst as f64;
    (0..dst)
        .map(|o| {
            let x = ((o as f64 + 0.5) * scale - 0.5).clamp(0.0, (src - 1) as f64);
            let i = x.floor() as usize;
            let f = x - i as f64;
            if i + 1 < src && f > 0.0 {
                vec![(i, (1.0 - f) as f32), (i + 1, f as f32)]
            } else {
                vec![(i, 1.0)]
            }
        })
        .collect()
}

/// For each output coordinate, the input coordinates it overlaps and the
/// normalised overlap weights (the taps of [`ColorImage::resize_area`],
/// also uploaded to the GPU backend's `kernels/resize_area.wgsl`).
pub fn area_weights(src: usize, dst: usize) -> Vec<Vec<(usize, f32)>> {
    area_weights_at(src, dst, src as f64 / dst as f64)
}

/// [`area_weights`] with `scale` source samples per output sample (not
/// necessarily `src / dst`: a pyramid level's cells resampled from a
/// larger level's, whose cell counts are floored), each footprint clamped
/// to the source.
pub fn area_weights_at(src: usize, dst: usize, scale: f64) -> Vec<Vec<(usize, f32)>> {
    let last_start = src.saturating_sub(1) as f64;
    (0..dst)
        .map(|o| {
            let a = (o as f64 * scale).min(last_start);
            let b = ((o as f64 + 1.0) * scale).min(src as f64);
            let mut taps = Vec::new();
            let first = a.floor() as usize;
            let last = (b.ceil() as usize).min(src);
            let mut total = 0.0;
            for i in first..last {
                let lo = a.max(i as f64);
                let hi = b.min(i as f64 + 1.0);
                if hi > lo {
                    taps.push((i, hi - lo));
                    total += hi - lo;
                }
            }
            if taps.is_empty() {
                // Upscaling with a footprint inside one pixel.
                taps.push((first.min(src - 1), 1.0));
                total = 1.0;
            }
            taps.into_iter()
                .map(|(i, w)| (i, (w / total) as f32))
                .collect()
        })
        .collect()
}

/// An image of uniform noise in 0..255 (tests of the feature layers).
#[cfg(test)]
pub(crate) fn noise_image(w: usize, h: usize, seed: u64) -> ColorImage {
    let mut rng = super::rng::SplitMix64::new(seed);
    let data = (0..w * h * 3)
        .map(|_| (rng.next_f64() * 255.0) as f32)
        .collect();
    ColorImage::new(w, h, data).unwrap()
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;

    #[test]
    fn mirroring_reverses_every_row_and_twice_is_the_identity() {
        let data: Vec<f32> = (0..2 * 3 * CHANNELS).map(|v| v as f32).collect();
        let img = ColorImage::new(3, 2, data).unwrap();
        let m = img.mirrored();
        for y in 0..2 {
            for x in 0..3 {
                for c in 0..CHANNELS {
                    assert_eq!(m.get(x, y, c), img.get(2 - x, y, c));
                }
            }
        }
        assert_eq!(m.mirrored(), img);
    }

    fn ramp(w: usize, h: usize) -> ColorImage {
        let mut d = Vec::new();
        for y in 0..h {
            for x in 0..w {
                d.extend_from_slice(&[x as f32, y as f32, 7.0]);
            }
        }
        ColorImage::new(w, h, d).unwrap()
    }

    #[test]
    fn rejects_empty_and_mismatched() {
        assert!(matches!(
            ColorImage::new(0, 5, vec![]),
            Err(VisionError::EmptyImage { .. })
        ));
        assert!(matches!(
            ColorImage::new(2, 2, vec![0.0; 5]),
            Err(VisionError::BufferSize { .. })
        ));
        assert!(matches!(
            ColorImage::new(1, 1, vec![0.0, f32::NAN, 0.0]),
            Err(VisionError::NonFinite(_))
        ));
    }

    #[test]
    fn resize_identity_and_mean_preserving() {
        let img = ramp(16, 12);
        assert_eq!(img.resize_area(16, 12).unwrap(), img);
        let half = img.resize_area(8, 6).unwrap();
        // Each output pixel is the mean of a 2x2 block.
        assert!((half.get(0, 0, 0) - 0.5).abs() < 1e-5);
        assert!((half.get(3, 2, 1) - 4.5).abs() < 1e-5);
        assert!((half.get(5, 5, 2) - 7.0).abs() < 1e-5);
        let mean_in: f32 = img.data().iter().step_by(3).sum::<f32>() / (16.0 * 12.0);
        let odd = img.resize_area(5, 7).unwrap();
        let mean_out: f32 = odd.data().iter().step_by(3).sum::<f32>() / 35.0;
        assert!((mean_in - mean_out).abs() < 1e-3);
    }

    /// The resize as first written (a list of taps per output, summed in
    /// order), which the flattened taps must match bit for bit.
    fn resize_reference(img: &ColorImage, new_w: usize, new_h: usize) -> Vec<f32> {
        let wx = area_weights(img.width, new_w);
        let wy = area_weights(img.height, new_h);
        let mut tmp = vec![0.0f32; img.height * new_w * CHANNELS];
        for y in 0..img.height {
            for (ox, taps) in wx.iter().enumerate() {
                let mut acc = [0.0f32; CHANNELS];
                for &(ix, w) in taps {
                    for c in 0..CHANNELS {
                        acc[c] += w * img.get(ix, y, c);
                    }
                }
                let at = (y * new_w + ox) * CHANNELS;
                tmp[at..at + CHANNELS].copy_from_slice(&acc);
            }
        }
        let row = new_w * CHANNELS;
        let mut out = vec![0.0f32; new_h * row];
        for (oy, taps) in wy.iter().enumerate() {
            for &(iy, w) in taps {
                for x in 0..row {
                    out[oy * row + x] += w * tmp[iy * row + x];
                }
            }
        }
        out
    }

    #[test]
    fn flat_taps_resize_bit_identical_to_reference() {
        // Noise-like samples so that rounding differences would show.
        let (w, h) = (97, 61);
        let data = (0..w * h * CHANNELS)
            .map(|i| (i as f32 * 0.618_034).fract() * 255.0)
            .collect();
        let img = ColorImage::new(w, h, data).unwrap();
        for (nw, nh) in [
            (48, 30),
            (80, 50),
            (55, 43),
            (96, 60),
            (130, 90),
            (300, 200),
            (7, 3),
        ] {
            let got = img.resize_area(nw, nh).unwrap();
            let want = resize_reference(&img, nw, nh);
            let same = got
                .data()
                .iter()
                .zip(&want)
                .all(|(a, b)| a.to_bits() == b.to_bits());
            assert!(same, "{nw}x{nh} differs from the reference");
        }
    }

    #[test]
    fn smooth_resize_interpolates_upward_and_averages_downward() {
        let img = ramp(16, 12);
        // Down: the area average itself.
        assert_eq!(
            img.resize_smooth(8, 6).unwrap(),
            img.resize_area(8, 6).unwrap()
        );
        // Up 2x along a ramp: interior samples on the line between the
        // input pixels' centres (no blocks: neighbours differ).
        let up = img.resize_smooth(32, 12).unwrap();
        let (a, b, c) = (up.get(10, 5, 0), up.get(11, 5, 0), up.get(12, 5, 0));
        assert!(
            (b - a) > 0.0 && ((c - b) - (b - a)).abs() < 1e-3,
            "{a} {b} {c}"
        );
        let x = (11.0 + 0.5) * 0.5 - 0.5;
        let want = img.get(5, 5, 0) + (x - 5.0) as f32 * (img.get(6, 5, 0) - img.get(5, 5, 0));
        assert!((b - want).abs() < 1e-3, "{b} {want}");
    }
}
