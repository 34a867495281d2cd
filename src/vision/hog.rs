//! Felzenszwalb et al. (PAMI 2010) 31-dimensional HOG features on 8x8 cells.
//!
//! Layout of a cell's feature vector:
//! `0..18` contrast-sensitive orientations (20 degrees each, 0 = gradient
//! pointing along +x, angles measured towards +y, i.e. down in the image),
//! `18..27` contrast-insensitive orientations, `27..31` gradient energies of
//! the four 2x2 normalisation blocks (bottom-right, top-right, bottom-left,
//! top-left of the cell). Cell `(cx, cy)` covers the pixels
//! `[8cx, 8cx+8) x [8cy, 8cy+8)`; the map has `floor(w/8) x floor(h/8)` cells.
//! Neighbours beyond the map count as zero energy in the normalisation, and
//! cells outside the map have all-zero features.

use super::image::{ColorImage, CHANNELS};
use super::{Deadline, VisionError};

/// Dimension of a cell's feature vector.
pub const HOG_DIM: usize = 31;
/// Stored stride of a cell (one zero pad value so rows of filters align).
pub const HOG_STRIDE: usize = 32;
/// Pixels per cell side.
pub const CELL_SIZE: usize = 8;
/// Number of contrast-sensitive orientation bins.
pub const SENSITIVE_BINS: usize = 18;
/// Number of contrast-insensitive orientation bins.
pub const INSENSITIVE_BINS: usize = 9;
/// Truncation of normalised histogram values.
pub const TRUNCATION: f32 = 0.2;
const NORM_EPS: f32 = 1e-4;
/// Weight of the texture (gradient energy) features, as in voc-release.
const TEXTURE_WEIGHT: f32 = 0.2357;

/// `cos` and `sin` of the 9 half-circle orientation directions.
const UU: [f32; 9] = [
    1.0000, 0.9397, 0.7660, 0.5000, 0.1736, -0.1736, -0.5000, -0.7660, -0.9397,
];
const VV: [f32; 9] = [
    0.0000, 0.3420, 0.6428, 0.8660, 0.9848, 0.9848, 0.8660, 0.6428, 0.3420,
];

/// A HOG feature map: `width x height` cells of [`HOG_DIM`] features.
#[derive(Clone, Debug, PartialEq)]
pub struct HogMap {
    width: usize,
    height: usize,
    data: Vec<f32>,
}

impl HogMap {
    /// An all-zero map.
    pub fn zeros(width: usize, height: usize) -> Self {
        Self {
            width,
            height,
            data: vec![0.0; width * height * HOG_STRIDE],
        }
    }

    /// A map from raw storage (`HOG_STRIDE` values per cell, row-major), as
    /// a compute backend returns it. The pad value of every cell is zeroed.
    pub fn from_raw(width: usize, height: usize, mut data: Vec<f32>) -> Result<Self, VisionError> {
        let expected = width * height * HOG_STRIDE;
        if data.len() != expected {
            return Err(VisionError::BufferSize {
                expected,
                actual: data.len(),
            });
        }
        if data.iter().any(|v| !v.is_finite()) {
            return Err(VisionError::NonFinite("HOG features"));
        }
        for cell in data.chunks_exact_mut(HOG_STRIDE) {
            cell[HOG_DIM] = 0.0;
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    /// The 31 features of cell `(x, y)`.
    #[inline]
    pub fn cell(&self, x: usize, y: usize) -> &[f32] {
        let o = (y * self.width + x) * HOG_STRIDE;
        &self.data[o..o + HOG_DIM]
    }

    /// The padded 32-value block of cell `(x, y)` (last value is zero).
    #[inline]
    pub fn cell_padded(&self, x: usize, y: usize) -> &[f32] {
        let o = (y * self.width + x) * HOG_STRIDE;
        &self.data[o..o + HOG_STRIDE]
    }

    /// The features of cell `(x, y)` in signed coordinates: zeros outside.
    pub fn cell_or_zero(&self, x: isize, y: isize) -> [f32; HOG_DIM] {
        let mut out = [0.0; HOG_DIM];
        if x >= 0 && y >= 0 && (x as usize) < self.width && (y as usize) < self.height {
            out.copy_from_slice(self.cell(x as usize, y as usize));
        }
        out
    }

    /// Raw storage, `HOG_STRIDE` values per cell, row-major.
    pub fn raw(&self) -> &[f32] {
        &self.data
    }

    fn cell_mut(&mut self, x: usize, y: usize) -> &mut [f32] {
        let o = (y * self.width + x) * HOG_STRIDE;
        &mut self.data[o..o + HOG_STRIDE]
    }
}

/// The orientation bin (0..18) of a gradient, by the largest absolute dot
/// product with the 9 half-circle directions (ties keep the lower index).
#[inline]
pub fn orientation_bin(dx: f32, dy: f32) -> usize {
    let mut best = 0.0f32;
    let mut bin = 0usize;
    for o in 0..INSENSITIVE_BINS {
        let dot = UU[o] * dx + VV[o] * dy;
        if dot > best {
            best = dot;
            bin = o;
        } else if -dot > best {
            best = -dot;
            bin = o + INSENSITIVE_BINS;
        }
    }
    bin
}

/// Gradient of the pixel: the channel with the largest gradient magnitude
/// (central differences, edges clamped). Returns `(dx, dy)`.
#[inline]
fn pixel_gradient(img: &ColorImage, x: usize, y: usize) -> (f32, f32) {
    let w = img.width();
    let h = img.height();
    let xl = x.saturating_sub(1);
    let xr = (x + 1).min(w - 1);
    let yu = y.saturating_sub(1);
    let yd = (y + 1).min(h - 1);
    let mut best = (0.0f32, 0.0f32);
    let mut best_m = -1.0f32;
    for c in 0..CHANNELS {
        let dx = img.get(xr, y, c) - img.get(xl, y, c);
        let dy = img.get(x, yd, c) - img.get(x, yu, c);
        let m = dx * dx + dy * dy;
        if m > best_m {
            best_m = m;
            best = (dx, dy);
        }
    }
    best
}

/// Cell-space coordinate of a pixel centre, for bilinear spatial binning.
#[inline]
fn cell_coord(p: usize) -> f32 {
    (p as f32 + 0.5) / CELL_SIZE as f32 - 0.5
}

/// Computes the HOG map of an image (optimised path), on the best
/// instruction set of the processor ([`crate::vision::simd`]; every path
/// gives the same features bit for bit).
pub fn hog(img: &ColorImage) -> HogMap {
    // Without a deadline nothing gives up.
    hog_until(img, Deadline::NONE).unwrap_or_else(|_| HogMap::zeros(0, 0))
}

/// [`hog`] that gives up with [`VisionError::DeadlineExceeded`] once
/// `deadline` has passed, looked at every [`DEADLINE_ROWS`] pixel rows (a
/// few milliseconds of work on the widest image).
pub fn hog_until(img: &ColorImage, deadline: Deadline) -> Result<HogMap, VisionError> {
    #[cfg(target_arch = "x86_64")]
    match crate::vision::simd::level() {
        // SAFETY: the features were detected at run time.
        crate::vision::simd::Simd::Avx512 => return unsafe { hog_avx512(img, deadline) },
        // SAFETY: the features were detected at run time.
        crate::vision::simd::Simd::Avx2 => return unsafe { hog_avx2(img, deadline) },
        crate::vision::simd::Simd::Portable => {}
    }
    hog_body(img, deadline)
}

/// Pixel rows of HOG between two looks at the deadline.
pub const DEADLINE_ROWS: usize = 64;

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512dq,avx512vl,avx2,fma")]
unsafe fn hog_avx512(img: &ColorImage, deadline: Deadline) -> Result<HogMap, VisionError> {
    hog_body(img, deadline)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn hog_avx2(img: &ColorImage, deadline: Deadline) -> Result<HogMap, VisionError> {
    hog_body(img, deadline)
}

#[inline(always)]
fn hog_body(img: &ColorImage, deadline: Deadline) -> Result<HogMap, VisionError> {
    let w = img.width();
    let h = img.height();
    let cw = w / CELL_SIZE;
    let ch = h / CELL_SIZE;
    if cw == 0 || ch == 0 {
        return Ok(HogMap::zeros(cw, ch));
    }
    // Histograms with a border of one cell on every side, so that votes need
    // no bounds checks; the border is dropped before normalisation.
    let hw = cw + 2;
    let mut hist = vec![0.0f32; hw * (ch + 2) * SENSITIVE_BINS];
    let data = img.data();
    let mut gx = vec![0.0f32; w];
    let mut gy = vec![0.0f32; w];
    let mut gm = vec![-1.0f32; w];
    let mut best = vec![0.0f32; w];
    let mut bins = vec![0u32; w];
    // Horizontal interpolation tables.
    let xs: Vec<(isize, f32)> = (0..w)
        .map(|x| {
            let xp = cell_coord(x);
            let ix = xp.floor();
            (ix as isize, xp - ix)
        })
        .collect();
    // Planar channels, so that rows of one channel are contiguous.
    let planes: Vec<Vec<f32>> = (0..CHANNELS)
        .map(|c| data.iter().skip(c).step_by(CHANNELS).copied().collect())
        .collect();
    let mut dxc = vec![0.0f32; w];
    let mut dyc = vec![0.0f32; w];
    for y in 0..h {
        if y % DEADLINE_ROWS == 0 && deadline.passed() {
            return Err(VisionError::DeadlineExceeded);
        }
        let yu = y.saturating_sub(1);
        let yd = (y + 1).min(h - 1);
        gm.iter_mut().for_each(|v| *v = -1.0);
        for plane in &planes {
            let r = &plane[y * w..(y + 1) * w];
            let ru = &plane[yu * w..(yu + 1) * w];
            let rd = &plane[yd * w..(yd + 1) * w];
            // Central differences, clamped at the borders.
            if w >= 3 {
                for (d, (a, b)) in dxc[1..w - 1].iter_mut().zip(r[2..].iter().zip(&r[..w - 2])) {
                    *d = a - b;
                }
            }
            dxc[0] = r[1.min(w - 1)] - r[0];
            dxc[w - 1] = r[w - 1] - r[w.saturating_sub(2)];
            for (d, (a, b)) in dyc.iter_mut().zip(rd.iter().zip(ru)) {
                *d = a - b;
            }
            for ((((&dx, &dy), m), ox), oy) in dxc
                .iter()
                .zip(&dyc)
                .zip(gm.iter_mut())
                .zip(gx.iter_mut())
                .zip(gy.iter_mut())
            {
                let mm = dx * dx + dy * dy;
                let keep = f32::from(u8::from(mm <= *m));
                *m = mm.max(*m);
                *ox = keep * *ox + (1.0 - keep) * dx;
                *oy = keep * *oy + (1.0 - keep) * dy;
            }
        }
        best.iter_mut().for_each(|v| *v = 0.0);
        bins.iter_mut().for_each(|v| *v = 0);
        for o in 0..INSENSITIVE_BINS {
            let (u, v) = (UU[o], VV[o]);
            let (pos, neg) = (o as u32, (o + INSENSITIVE_BINS) as u32);
            // Same choice as `orientation_bin`: the first direction with the
            // largest |dot|, signed (dot > 0 and -dot > 0 exclude each other).
            for (((&dx, &dy), bst), bin) in
                gx.iter().zip(&gy).zip(best.iter_mut()).zip(bins.iter_mut())
            {
                // Branch-free selects: on noisy images the comparisons are
                // unpredictable.
                let dot = u * dx + v * dy;
                let a = dot.abs();
                let better = u32::from(a > *bst).wrapping_neg();
                *bst = a.max(*bst);
                let b = neg - u32::from(dot > 0.0) * (neg - pos);
                *bin = (b & better) | (*bin & !better);
            }
        }
        let yp = cell_coord(y);
        let iy = yp.floor();
        let vy0 = yp - iy;
        // Row of the padded grid; rows beyond the border get no votes.
        let iy = iy as isize + 1;
        for x in 0..w {
            let mag = gm[x].sqrt();
            let (ix, vx0) = xs[x];
            if mag == 0.0 || ix + 1 < 0 || ix + 1 > cw as isize {
                continue;
            }
            let b = bins[x] as usize;
            let wx = [(1.0 - vx0) * mag, vx0 * mag];
            for (dy, wy) in [(0isize, 1.0 - vy0), (1, vy0)] {
                let row = iy + dy;
                if row < 0 || row > ch as isize + 1 {
                    continue;
                }
                let base = (row as usize * hw + (ix + 1) as usize) * SENSITIVE_BINS + b;
                hist[base] += wx[0] * wy;
                hist[base + SENSITIVE_BINS] += wx[1] * wy;
            }
        }
    }
    // Drop the border.
    let mut inner = vec![0.0f32; cw * ch * SENSITIVE_BINS];
    for cy in 0..ch {
        let src = ((cy + 1) * hw + 1) * SENSITIVE_BINS;
        inner[cy * cw * SENSITIVE_BINS..(cy + 1) * cw * SENSITIVE_BINS]
            .copy_from_slice(&hist[src..src + cw * SENSITIVE_BINS]);
    }
    let hist = inner;
    Ok(normalise(&hist, cw, ch))
}

/// Block normalisation, truncation and projection to 31 features.
fn normalise(hist: &[f32], cw: usize, ch: usize) -> HogMap {
    // Energies with a zero border of one cell.
    let pw = cw + 2;
    let mut norm = vec![0.0f32; pw * (ch + 2)];
    for cy in 0..ch {
        for cx in 0..cw {
            let hc = &hist[(cy * cw + cx) * SENSITIVE_BINS..(cy * cw + cx + 1) * SENSITIVE_BINS];
            let mut e = 0.0f32;
            for o in 0..INSENSITIVE_BINS {
                let s = hc[o] + hc[o + INSENSITIVE_BINS];
                e += s * s;
            }
            norm[(cy + 1) * pw + cx + 1] = e;
        }
    }
    let mut out = HogMap::zeros(cw, ch);
    for cy in 0..ch {
        for cx in 0..cw {
            let n = |dx: usize, dy: usize| norm[(cy + dy) * pw + cx + dx];
            // Indices in the padded grid: the cell itself is (1, 1).
            let n1 = 1.0 / (n(1, 1) + n(2, 1) + n(1, 2) + n(2, 2) + NORM_EPS).sqrt();
            let n2 = 1.0 / (n(1, 0) + n(2, 0) + n(1, 1) + n(2, 1) + NORM_EPS).sqrt();
            let n3 = 1.0 / (n(0, 1) + n(1, 1) + n(0, 2) + n(1, 2) + NORM_EPS).sqrt();
            let n4 = 1.0 / (n(0, 0) + n(1, 0) + n(0, 1) + n(1, 1) + NORM_EPS).sqrt();
            let hc = &hist[(cy * cw + cx) * SENSITIVE_BINS..(cy * cw + cx + 1) * SENSITIVE_BINS];
            let dst = out.cell_mut(cx, cy);
            let mut t = [0.0f32; 4];
            for o in 0..SENSITIVE_BINS {
                let h1 = (hc[o] * n1).min(TRUNCATION);
                let h2 = (hc[o] * n2).min(TRUNCATION);
                let h3 = (hc[o] * n3).min(TRUNCATION);
                let h4 = (hc[o] * n4).min(TRUNCATION);
                dst[o] = 0.5 * (h1 + h2 + h3 + h4);
                t[0] += h1;
                t[1] += h2;
                t[2] += h3;
                t[3] += h4;
            }
            for o in 0..INSENSITIVE_BINS {
                let s = hc[o] + hc[o + INSENSITIVE_BINS];
                let h1 = (s * n1).min(TRUNCATION);
                let h2 = (s * n2).min(TRUNCATION);
                let h3 = (s * n3).min(TRUNCATION);
                let h4 = (s * n4).min(TRUNCATION);
                dst[SENSITIVE_BINS + o] = 0.5 * (h1 + h2 + h3 + h4);
            }
            for (k, tk) in t.iter().enumerate() {
                dst[SENSITIVE_BINS + INSENSITIVE_BINS + k] = TEXTURE_WEIGHT * tk;
            }
        }
    }
    out
}

/// A deliberately plain reference: every cell gathers the weighted votes of
/// all pixels around it, with the bilinear weights in closed form, and the
/// normalisation is written out per block. Used to test [`hog`].
pub fn hog_reference(img: &ColorImage) -> HogMap {
    let w = img.width();
    let h = img.height();
    let cw = w / CELL_SIZE;
    let ch = h / CELL_SIZE;
    let mut hist = vec![[0.0f64; SENSITIVE_BINS]; cw * ch];
    for cy in 0..ch {
        for cx in 0..cw {
            let y0 = (cy * CELL_SIZE).saturating_sub(CELL_SIZE);
            let y1 = ((cy + 2) * CELL_SIZE).min(h);
            let x0 = (cx * CELL_SIZE).saturating_sub(CELL_SIZE);
            let x1 = ((cx + 2) * CELL_SIZE).min(w);
            for y in y0..y1 {
                for x in x0..x1 {
                    let wx = 1.0 - (f64::from(cell_coord(x)) - cx as f64).abs();
                    let wy = 1.0 - (f64::from(cell_coord(y)) - cy as f64).abs();
                    if wx <= 0.0 || wy <= 0.0 {
                        continue;
                    }
                    let (dx, dy) = pixel_gradient(img, x, y);
                    let mag = f64::from(dx * dx + dy * dy).sqrt();
                    hist[cy * cw + cx][orientation_bin(dx, dy)] += wx * wy * mag;
                }
            }
        }
    }
    let energy = |x: isize, y: isize| -> f64 {
        if x < 0 || y < 0 || x as usize >= cw || y as usize >= ch {
            return 0.0;
        }
        let hc = &hist[y as usize * cw + x as usize];
        (0..INSENSITIVE_BINS)
            .map(|o| (hc[o] + hc[o + INSENSITIVE_BINS]).powi(2))
            .sum()
    };
    let mut out = HogMap::zeros(cw, ch);
    for cy in 0..ch {
        for cx in 0..cw {
            let (x, y) = (cx as isize, cy as isize);
            // Blocks whose top-left cell is offset by (ox, oy) from this one.
            let blocks = [(0, 0), (0, -1), (-1, 0), (-1, -1)];
            let norms: Vec<f64> = blocks
                .iter()
                .map(|&(ox, oy)| {
                    let s = energy(x + ox, y + oy)
                        + energy(x + ox + 1, y + oy)
                        + energy(x + ox, y + oy + 1)
                        + energy(x + ox + 1, y + oy + 1);
                    1.0 / (s + f64::from(NORM_EPS)).sqrt()
                })
                .collect();
            let hc = hist[cy * cw + cx];
            let trunc = f64::from(TRUNCATION);
            let dst = out.cell_mut(cx, cy);
            for o in 0..SENSITIVE_BINS {
                let v: f64 = norms.iter().map(|n| (hc[o] * n).min(trunc)).sum();
                dst[o] = (0.5 * v) as f32;
            }
            for o in 0..INSENSITIVE_BINS {
                let s = hc[o] + hc[o + INSENSITIVE_BINS];
                let v: f64 = norms.iter().map(|n| (s * n).min(trunc)).sum();
                dst[SENSITIVE_BINS + o] = (0.5 * v) as f32;
            }
            for (k, n) in norms.iter().enumerate() {
                let t: f64 = (0..SENSITIVE_BINS).map(|o| (hc[o] * n).min(trunc)).sum();
                dst[SENSITIVE_BINS + INSENSITIVE_BINS + k] = (f64::from(TEXTURE_WEIGHT) * t) as f32;
            }
        }
    }
    out
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;
    use crate::vision::image::noise_image;
    use proptest::prelude::*;

    /// A grey image whose intensity rises along direction `theta`.
    fn oriented(w: usize, h: usize, theta: f32) -> ColorImage {
        let (c, s) = (theta.cos(), theta.sin());
        let mut d = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            for x in 0..w {
                let v = 128.0 + 0.8 * (x as f32 * c + y as f32 * s);
                d.extend_from_slice(&[v, v, v]);
            }
        }
        ColorImage::new(w, h, d).unwrap()
    }

    #[test]
    fn dimensions_and_bounds() {
        let img = noise_image(67, 45, 1);
        let m = hog(&img);
        assert_eq!((m.width(), m.height()), (8, 5));
        assert_eq!(m.cell(0, 0).len(), HOG_DIM);
        for y in 0..m.height() {
            for x in 0..m.width() {
                let c = m.cell(x, y);
                assert!(c.iter().all(|v| v.is_finite() && *v >= 0.0));
                // Each orientation value is half a sum of four truncated values.
                assert!(c[..27].iter().all(|v| *v <= 2.0 * TRUNCATION + 1e-6));
                assert_eq!(m.cell_padded(x, y)[HOG_DIM], 0.0);
            }
        }
    }

    /// Every instruction-set path gives the same features bit for bit.
    #[test]
    fn hog_paths_are_bit_identical() {
        for (w, h, seed) in [(67, 45, 3), (129, 97, 4), (640, 480, 5)] {
            let img = noise_image(w, h, seed);
            let portable = hog_body(&img, Deadline::NONE).unwrap();
            assert_eq!(hog(&img), portable, "{w}x{h}");
            #[cfg(target_arch = "x86_64")]
            {
                use crate::vision::simd::{level, Simd};
                if matches!(level(), Simd::Avx2 | Simd::Avx512) {
                    // SAFETY: the features were detected at run time.
                    assert_eq!(
                        unsafe { hog_avx2(&img, Deadline::NONE) }.unwrap(),
                        portable,
                        "AVX2 {w}x{h}"
                    );
                }
                if level() == Simd::Avx512 {
                    // SAFETY: as above.
                    assert_eq!(
                        unsafe { hog_avx512(&img, Deadline::NONE) }.unwrap(),
                        portable,
                        "AVX-512 {w}x{h}"
                    );
                }
            }
        }
    }

    #[test]
    fn tiny_images_have_no_cells() {
        let img = noise_image(7, 30, 2);
        let m = hog(&img);
        assert_eq!(m.width(), 0);
        assert!(m.raw().is_empty());
    }

    #[test]
    fn oriented_edges_land_in_their_bin() {
        for o in 0..SENSITIVE_BINS {
            let theta = o as f32 * std::f32::consts::PI / 9.0;
            let img = oriented(48, 48, theta);
            let m = hog(&img);
            let c = m.cell(2, 2);
            let argmax = (0..SENSITIVE_BINS)
                .max_by(|&a, &b| c[a].total_cmp(&c[b]))
                .unwrap();
            assert_eq!(argmax, o, "theta bin {o}: {:?}", &c[..18]);
            let argmax_ins = (0..INSENSITIVE_BINS)
                .max_by(|&a, &b| c[18 + a].total_cmp(&c[18 + b]))
                .unwrap();
            assert_eq!(argmax_ins, o % INSENSITIVE_BINS);
        }
    }

    #[test]
    fn flat_image_is_zero() {
        let img = ColorImage::new(32, 32, vec![128.0; 32 * 32 * 3]).unwrap();
        let m = hog(&img);
        assert!(m.raw().iter().all(|&v| v == 0.0));
    }

    fn rotate180(img: &ColorImage) -> ColorImage {
        let (w, h) = (img.width(), img.height());
        let mut d = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    d.push(img.get(w - 1 - x, h - 1 - y, c));
                }
            }
        }
        ColorImage::new(w, h, d).unwrap()
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]

        #[test]
        fn rotation_by_180_keeps_insensitive_channels(seed in 0u64..1000, cw in 2usize..7, ch in 2usize..7) {
            let img = noise_image(cw * 8, ch * 8, seed);
            let a = hog(&img);
            let b = hog(&rotate180(&img));
            for y in 0..ch {
                for x in 0..cw {
                    let ca = a.cell(x, y);
                    let cb = b.cell(cw - 1 - x, ch - 1 - y);
                    for o in 0..INSENSITIVE_BINS {
                        prop_assert!((ca[18 + o] - cb[18 + o]).abs() < 1e-5);
                        // Sensitive bins swap with their opposite.
                        prop_assert!((ca[o] - cb[o + 9]).abs() < 1e-5);
                    }
                    // Block energies swap: bottom-right <-> top-left etc.
                    prop_assert!((ca[27] - cb[30]).abs() < 1e-5);
                    prop_assert!((ca[28] - cb[29]).abs() < 1e-5);
                }
            }
        }

        #[test]
        fn optimised_matches_reference(seed in 0u64..1000, w in 1usize..60, h in 1usize..60) {
            let img = noise_image(w, h, seed);
            let a = hog(&img);
            let b = hog_reference(&img);
            prop_assert_eq!((a.width(), a.height()), (b.width(), b.height()));
            for (x, y) in a.raw().iter().zip(b.raw()) {
                prop_assert!((x - y).abs() < 1e-4, "{} vs {}", x, y);
            }
        }
    }
}
