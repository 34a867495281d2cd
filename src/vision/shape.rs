//! A viewpoint's pixel shape model: at the template's pixel resolution
//! (cells times the cell size), the probability that each pixel of the
//! full-extent box shows the object, learned from the training masks of
//! that viewpoint.
//!
//! The training masks are visible masks: where an occluder hid part of a
//! training object, that image says nothing true about the shape there.
//! Occluders come from every side, so the mean of the visible masks is the
//! shape times a roughly even visibility; the model divides it by its own
//! high quantile (the pixels that are nearly always the object), which
//! gives back the shape's probability.

use super::image::ColorImage;
use super::mask::Mask;

/// The quantile of the mean visible masks, within the box, taken as "the
/// object for sure".
const TOP_QUANTILE: f64 = 0.95;

/// Per-pixel object probability over a viewpoint's box, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct ShapeModel {
    pub width: usize,
    pub height: usize,
    pub prob: Vec<f32>,
    /// The object's colour histogram from the visible pixels of the
    /// training images ([`COLOUR_BINS`] per channel, summing to 1), where
    /// learned.
    pub colours: Option<Vec<f32>>,
}

/// Histogram bins per colour channel of the colour models.
pub const COLOUR_BINS: usize = 16;

/// The colour histogram bin of a pixel.
pub fn colour_bin(img: &ColorImage, x: usize, y: usize) -> usize {
    let q = |c: usize| {
        ((img.get(x, y, c).clamp(0.0, 255.0) as usize) * COLOUR_BINS / 256).min(COLOUR_BINS - 1)
    };
    (q(0) * COLOUR_BINS + q(1)) * COLOUR_BINS + q(2)
}

/// The normalised colour histogram of the pixels of `masks` in their
/// images (`None` without any pixel).
pub fn learn_colours<'a>(
    examples: impl IntoIterator<Item = (&'a ColorImage, &'a Mask)>,
) -> Option<Vec<f32>> {
    let mut h = vec![0.0f64; COLOUR_BINS * COLOUR_BINS * COLOUR_BINS];
    for (img, m) in examples {
        if (img.width(), img.height()) != (m.width, m.height) {
            continue;
        }
        for y in 0..m.height {
            for x in 0..m.width {
                if m.get(x, y) {
                    h[colour_bin(img, x, y)] += 1.0;
                }
            }
        }
    }
    let n: f64 = h.iter().sum();
    (n > 0.0).then(|| h.iter().map(|v| (v / n) as f32).collect())
}

/// The normalised colour histogram of a whole image (every other pixel in
/// each direction).
pub fn image_colours(img: &ColorImage) -> Vec<f32> {
    let mut h = vec![0.0f64; COLOUR_BINS * COLOUR_BINS * COLOUR_BINS];
    for y in (0..img.height()).step_by(2) {
        for x in (0..img.width()).step_by(2) {
            h[colour_bin(img, x, y)] += 1.0;
        }
    }
    let n: f64 = h.iter().sum::<f64>().max(1.0);
    h.iter().map(|v| (v / n) as f32).collect()
}

/// Largest magnitude of a pixel's colour log ratio in
/// [`colour_agreement`].
pub const AGREEMENT_CLAMP: f64 = 3.0;

/// How much more the pixels of `mask` look like the object's colours
/// (`object`, a normalised histogram) than like the image's (`image`):
/// the mean over the mask of `ln((p_obj + e) / (p_img + e))`, clamped to
/// +-[`AGREEMENT_CLAMP`] per pixel; 0 for an empty mask.
pub fn colour_agreement(img: &ColorImage, mask: &Mask, object: &[f32], image: &[f32]) -> f64 {
    let e = 0.5 / object.len().max(1) as f64;
    let (mut sum, mut n) = (0.0, 0usize);
    if (img.width(), img.height()) != (mask.width, mask.height) || mask.width == 0 {
        return 0.0;
    }
    // Each bin's log ratio, made the first time a pixel of the bin is met
    // (the same value as made for every pixel, summed in the same order).
    let mut ratio = vec![f64::NAN; COLOUR_BINS * COLOUR_BINS * COLOUR_BINS];
    for (y, row) in mask.data.chunks_exact(mask.width).enumerate() {
        for (x, _) in row.iter().enumerate().filter(|(_, v)| **v != 0) {
            let b = colour_bin(img, x, y);
            let r = &mut ratio[b];
            if r.is_nan() {
                let (o, i) = (
                    object.get(b).copied().unwrap_or(0.0),
                    image.get(b).copied().unwrap_or(0.0),
                );
                *r = ((f64::from(o) + e) / (f64::from(i) + e))
                    .ln()
                    .clamp(-AGREEMENT_CLAMP, AGREEMENT_CLAMP);
            }
            sum += *r;
            n += 1;
        }
    }
    if n == 0 {
        0.0
    } else {
        sum / n as f64
    }
}

impl ShapeModel {
    /// A model of `width x height` pixels from training examples: each a
    /// visible mask over its image and the full-extent box `(x, y, w, h)`
    /// stretched over the model's grid. `None` without examples or when
    /// every mean is zero.
    pub fn learn<'a>(
        width: usize,
        height: usize,
        examples: impl IntoIterator<Item = (&'a Mask, (f64, f64, f64, f64))>,
    ) -> Option<Self> {
        if width == 0 || height == 0 {
            return None;
        }
        let mut sum = vec![0.0f64; width * height];
        let mut n = 0usize;
        for (mask, (bx, by, bw, bh)) in examples {
            if bw <= 0.0 || bh <= 0.0 || !bw.is_finite() || !bh.is_finite() {
                continue;
            }
            n += 1;
            for v in 0..height {
                let y = by + (v as f64 + 0.5) / height as f64 * bh;
                for u in 0..width {
                    let x = bx + (u as f64 + 0.5) / width as f64 * bw;
                    if x >= 0.0 && y >= 0.0 {
                        let (xi, yi) = (x as usize, y as usize);
                        if xi < mask.width && yi < mask.height && mask.get(xi, yi) {
                            sum[v * width + u] += 1.0;
                        }
                    }
                }
            }
        }
        if n == 0 {
            return None;
        }
        let mut sorted: Vec<f64> = sum.iter().map(|s| s / n as f64).collect();
        sorted.sort_by(f64::total_cmp);
        let top = sorted[((sorted.len() - 1) as f64 * TOP_QUANTILE).round() as usize];
        if top <= 0.0 {
            return None;
        }
        let prob = sum
            .iter()
            .map(|s| ((s / n as f64) / top).min(1.0) as f32)
            .collect();
        Some(Self {
            width,
            height,
            prob,
            colours: None,
        })
    }

    /// The model smoothed by two passes of a box filter of half-width
    /// `r` pixels each way (about a Gaussian of sigma `r`; edges clamp):
    /// the shape as a detection's box, a few pixels off the object, sees
    /// it.
    pub fn blurred(&self, r: usize) -> Self {
        if r == 0 {
            return self.clone();
        }
        let (w, h) = (self.width, self.height);
        let a = box_blur(self.prob.iter().map(|&p| f64::from(p)).collect(), w, h, r);
        Self {
            width: w,
            height: h,
            prob: a.iter().map(|&p| p.clamp(0.0, 1.0) as f32).collect(),
            colours: self.colours.clone(),
        }
    }

    /// Checks the sizes and that every probability lies in [0, 1].
    pub fn valid(&self) -> bool {
        self.width > 0
            && self.height > 0
            && self.prob.len() == self.width * self.height
            && self.prob.iter().all(|p| (0.0..=1.0).contains(p))
            && self.colours.as_ref().is_none_or(|c| {
                c.len() == COLOUR_BINS * COLOUR_BINS * COLOUR_BINS
                    && c.iter().all(|v| v.is_finite() && *v >= 0.0)
            })
    }

    /// The probability at a point of the box given as fractions `(fx, fy)`
    /// of its width and height (nearest pixel; 0 outside the box).
    pub fn at(&self, fx: f64, fy: f64) -> f64 {
        if !(0.0..1.0).contains(&fx) || !(0.0..1.0).contains(&fy) {
            return 0.0;
        }
        let u = ((fx * self.width as f64) as usize).min(self.width - 1);
        let v = ((fy * self.height as f64) as usize).min(self.height - 1);
        f64::from(self.prob[v * self.width + u])
    }
}

/// `a` (`w x h`, row-major) smoothed by two passes of a box filter of
/// half-width `r` each way, horizontal then vertical (about a Gaussian of
/// sigma `r`; edges clamp).
pub fn box_blur(mut a: Vec<f64>, w: usize, h: usize, r: usize) -> Vec<f64> {
    let pass = |src: &[f64], horizontal: bool| -> Vec<f64> {
        let mut out = vec![0.0; w * h];
        for y in 0..h {
            for x in 0..w {
                let (mut sum, mut n) = (0.0, 0.0);
                for d in -(r as isize)..=(r as isize) {
                    let (xx, yy) = if horizontal {
                        ((x as isize + d).clamp(0, w as isize - 1) as usize, y)
                    } else {
                        (x, (y as isize + d).clamp(0, h as isize - 1) as usize)
                    };
                    sum += src[yy * w + xx];
                    n += 1.0;
                }
                out[y * w + x] = sum / n;
            }
        }
        out
    };
    for _ in 0..2 {
        a = pass(&a, true);
        a = pass(&a, false);
    }
    a
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two examples of a disc, one half hidden on the left, one on the
    /// right: the mean is half of the disc each side, the quantile scaling
    /// gives the disc back wherever either example saw it.
    #[test]
    fn occlusion_from_both_sides_averages_back_to_the_shape() {
        let (w, h) = (40, 40);
        let disc = |x: usize, y: usize| {
            let (dx, dy) = (x as f64 + 0.5 - 20.0, y as f64 + 0.5 - 20.0);
            dx * dx + dy * dy < 15.0 * 15.0
        };
        let mut left = Mask::new(w, h);
        let mut right = Mask::new(w, h);
        let mut centre = Mask::new(w, h);
        for y in 0..h {
            for x in 0..w {
                if disc(x, y) {
                    left.set(x, y, x >= 15);
                    right.set(x, y, x < 25);
                    centre.set(x, y, true);
                }
            }
        }
        let b = (0.0, 0.0, 40.0, 40.0);
        let m = ShapeModel::learn(20, 20, [(&left, b), (&right, b), (&centre, b)]).unwrap();
        assert!(m.valid());
        // The centre column: seen by all three.
        assert!((m.at(0.5, 0.5) - 1.0).abs() < 1e-6);
        // Far left of the disc: seen by two of three, scaled up to 1.
        assert!(m.at(0.15, 0.5) > 0.6, "{}", m.at(0.15, 0.5));
        // Corners: never the object.
        assert_eq!(m.at(0.02, 0.02), 0.0);
        assert_eq!(m.at(1.2, 0.5), 0.0);
        assert!(ShapeModel::learn(20, 20, std::iter::empty()).is_none());
    }

    /// A red object on a green image: its own pixels agree with the
    /// object's colours, the background's do not.
    #[test]
    fn colour_agreement_tells_object_colours_from_the_image() {
        let (w, h) = (20usize, 10usize);
        let mut data = Vec::new();
        for _y in 0..h {
            for x in 0..w {
                data.extend_from_slice(if x < 5 {
                    &[220.0, 30.0, 30.0]
                } else {
                    &[30.0, 200.0, 40.0]
                });
            }
        }
        let img = ColorImage::new(w, h, data).unwrap();
        let mut red = Mask::new(w, h);
        let mut green = Mask::new(w, h);
        for y in 0..h {
            for x in 0..w {
                red.set(x, y, x < 5);
                green.set(x, y, x >= 10);
            }
        }
        let object = learn_colours([(&img, &red)]).unwrap();
        let image = image_colours(&img);
        let on = colour_agreement(&img, &red, &object, &image);
        let off = colour_agreement(&img, &green, &object, &image);
        assert!(on > 1.0 && off < -1.0, "{on} {off}");
        assert_eq!(
            colour_agreement(&img, &Mask::new(w, h), &object, &image),
            0.0
        );
    }
}
