//! Region (colour) evidence of the object's outline, as the region-based
//! trackers do (RBOT, SRT3D, ICG): colour histograms of the object and of
//! the background around it give every pixel a probability of showing the
//! object, and along a line across the projected outline the most likely
//! place of the step from object to background is where the outline is.
//! Unlike the strongest image edge near a model edge, this ignores the
//! texture and shading edges inside the object and the clutter edges
//! outside it whose colours do not change from object to background.
//!
//! The histograms are taken once per refinement, at the start pose: the
//! object's pixels are those its projection covers (and, with a
//! visibility mask, only those in the mask: an occluder's colours are not
//! the object's), the background's those within a band around the
//! projection.

use nalgebra::Vector2;

use super::edges::DepthBuffer;
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;

/// Histogram bins per colour channel.
const BINS: usize = 8;
/// Smallest number of pixels of either histogram.
const MIN_PIXELS: usize = 30;
/// A pixel's probability of showing the object is clamped to
/// `[FLOOR, 1 - FLOOR]`: no single pixel decides the outline.
const FLOOR: f64 = 0.1;

/// Where along a line the outline most likely lies.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Step {
    /// Mean offset (pixels along the outward normal) of the outline.
    pub offset: f64,
    /// Its variance (pixels squared).
    pub variance: f64,
}

/// The probability that a pixel of a colour shows the object.
#[derive(Clone, Debug)]
pub struct ColourModel {
    posterior: Vec<f32>,
}

/// The histogram bin of a pixel.
fn bin(img: &ColorImage, x: usize, y: usize) -> usize {
    let q = |c: usize| ((img.get(x, y, c).clamp(0.0, 255.0) as usize) * BINS / 256).min(BINS - 1);
    (q(0) * BINS + q(1)) * BINS + q(2)
}

impl ColourModel {
    /// The model from the projection `depth` of the object at the start
    /// pose: object pixels are covered (and in `visible`, when given),
    /// background pixels lie outside the projection within `band` pixels
    /// (chessboard distance) of it. `None` when either has fewer than
    /// [`MIN_PIXELS`].
    pub fn new(
        img: &ColorImage,
        depth: &DepthBuffer,
        visible: Option<&Mask>,
        band: usize,
    ) -> Option<Self> {
        let (w, h) = (img.width(), img.height());
        let mut coverage = Mask::new(w, h);
        for y in 0..h {
            for x in 0..w {
                if depth.covered(x, y) {
                    coverage.set(x, y, true);
                }
            }
        }
        let dist = super::distance::MaskDistance::new(&coverage);
        Self::from_regions(img, (0, 0, w, h), |x, y| {
            let d = dist.distance(x, y);
            if d == 0 {
                visible.is_none_or(|m| m.get(x, y)).then_some(true)
            } else {
                (d <= band).then_some(false)
            }
        })
    }

    /// The model from the pixels of the window `(x, y, width, height)`
    /// (clipped to the image) that `label` calls the object's (`Some(true)`)
    /// or the background's (`Some(false)`). `None` when either has fewer
    /// than [`MIN_PIXELS`].
    pub fn from_regions(
        img: &ColorImage,
        window: (usize, usize, usize, usize),
        label: impl Fn(usize, usize) -> Option<bool>,
    ) -> Option<Self> {
        let (x0, y0) = (window.0.min(img.width()), window.1.min(img.height()));
        let (x1, y1) = (
            (x0 + window.2).min(img.width()),
            (y0 + window.3).min(img.height()),
        );
        let n = BINS * BINS * BINS;
        let (mut fg, mut bg) = (vec![0u32; n], vec![0u32; n]);
        let (mut nf, mut nb) = (0usize, 0usize);
        for y in y0..y1 {
            for x in x0..x1 {
                match label(x, y) {
                    Some(true) => {
                        fg[bin(img, x, y)] += 1;
                        nf += 1;
                    }
                    Some(false) => {
                        bg[bin(img, x, y)] += 1;
                        nb += 1;
                    }
                    None => {}
                }
            }
        }
        if nf < MIN_PIXELS || nb < MIN_PIXELS {
            return None;
        }
        // Smoothed frequencies (half a count in every bin).
        let (sf, sb) = (nf as f64 + 0.5 * n as f64, nb as f64 + 0.5 * n as f64);
        let posterior = fg
            .iter()
            .zip(&bg)
            .map(|(&f, &b)| {
                let pf = (f64::from(f) + 0.5) / sf;
                let pb = (f64::from(b) + 0.5) / sb;
                (pf / (pf + pb)) as f32
            })
            .collect();
        Some(Self { posterior })
    }

    /// The probability that the pixel containing `p` shows the object
    /// (`None` outside the image).
    pub fn at(&self, img: &ColorImage, p: &Vector2<f64>) -> Option<f64> {
        if p.x < 0.0 || p.y < 0.0 {
            return None;
        }
        let (x, y) = (p.x as usize, p.y as usize);
        (x < img.width() && y < img.height()).then(|| f64::from(self.posterior[bin(img, x, y)]))
    }

    /// The log-odds `ln(p / (1 - p))` that the pixel `(x, y)` shows the
    /// object, `p` clamped to `[FLOOR, 1 - FLOOR]` as in [`Self::step`]
    /// (the caller keeps `(x, y)` in the image).
    pub fn log_odds(&self, img: &ColorImage, x: usize, y: usize) -> f64 {
        let p = f64::from(self.posterior[bin(img, x, y)]).clamp(FLOOR, 1.0 - FLOOR);
        (p / (1.0 - p)).ln()
    }

    /// The distribution of the outline's place along the line through
    /// `pixel` along the outward normal `n`, `range` pixels each way: the
    /// outline at `d` explains the pixels before it as the object and
    /// those after it as background; each place's likelihood is the
    /// product of those probabilities (tempered by `temper`, as the
    /// pixels' errors are not independent). Pixels outside the image say
    /// nothing. `None` when the line says nothing.
    pub fn step(
        &self,
        img: &ColorImage,
        pixel: &Vector2<f64>,
        n: &Vector2<f64>,
        range: usize,
        temper: f64,
    ) -> Option<Step> {
        let len = 2 * range + 1;
        // Log-probabilities of object and background at t = -range..=range.
        let mut lf = Vec::with_capacity(len);
        let mut lb = Vec::with_capacity(len);
        let mut informative = false;
        for i in 0..len {
            let t = i as f64 - range as f64;
            match self.at(img, &(pixel + n * t)) {
                Some(p) => {
                    let p = p.clamp(FLOOR, 1.0 - FLOOR);
                    lf.push(p.ln());
                    lb.push((1.0 - p).ln());
                    informative = true;
                }
                None => {
                    lf.push(0.0);
                    lb.push(0.0);
                }
            }
        }
        if !informative {
            return None;
        }
        // The outline between sample j-1 and j (j = 0..=len), at offset
        // j - range - 0.5: the object before, the background from j on.
        let total_b: f64 = lb.iter().sum();
        let mut ll = Vec::with_capacity(len + 1);
        let (mut f, mut b) = (0.0, total_b);
        ll.push(f + b);
        for i in 0..len {
            f += lf[i];
            b -= lb[i];
            ll.push(f + b);
        }
        let top = ll.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let (mut z, mut m1, mut m2) = (0.0, 0.0, 0.0);
        for (j, l) in ll.iter().enumerate() {
            let d = j as f64 - range as f64 - 0.5;
            let p = (temper * (l - top)).exp();
            z += p;
            m1 += p * d;
            m2 += p * d * d;
        }
        let mean = m1 / z;
        Some(Step {
            offset: mean,
            variance: (m2 / z - mean * mean).max(0.0),
        })
    }
}

/// The outward normal (from the object to the background) of an outline
/// sample at `pixel` with edge normal `n`: the side `probe` pixels away
/// (at least a cell of the buffers) that the projection covers is the
/// inside. `None` for an edge with the
/// object on both sides or neither (creases, inner outlines).
pub fn outward(
    depth: &DepthBuffer,
    pixel: &Vector2<f64>,
    n: &Vector2<f64>,
    probe: f64,
) -> Option<Vector2<f64>> {
    let probe = probe.max(depth.cell_px());
    let covered =
        |p: Vector2<f64>| p.x >= 0.0 && p.y >= 0.0 && depth.covered(p.x as usize, p.y as usize);
    match (covered(pixel - n * probe), covered(pixel + n * probe)) {
        (true, false) => Some(*n),
        (false, true) => Some(-n),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On a render over the synthetic background (histograms taken at a
    /// start 3 degrees and 1 cm off), the steps lie near the true outline
    /// at the true pose (within 1.5 px in the median: the shading darkens
    /// the rim, which pulls them inwards by about half a pixel), and
    /// several pixels out at a pose moved 5 px aside.
    #[test]
    fn on_a_render_the_steps_find_the_outline() {
        use crate::pose::geometry::{Intrinsics, Pose};
        use crate::pose::render::{background, perturb, render};
        use crate::pose::{EdgeModel, Mesh};
        use crate::vision::Deadline;
        use nalgebra::{Rotation3, Vector3};
        let k = Intrinsics {
            fx: 600.0,
            fy: 600.0,
            cx: 320.0,
            cy: 240.0,
        };
        let mesh = Mesh::rounded_box(0.1, 0.06, 0.16, 0.025, 4);
        let truth = Pose {
            rotation: Rotation3::from_euler_angles(0.4, -0.3, 0.2).into_inner(),
            translation: Vector3::new(0.02, -0.01, 0.5),
        };
        let bg = background(640, 480, 3).unwrap();
        let scene = render(&mesh, &k, &truth, &bg, 0.0, 2.0, 3).unwrap();
        let edges = EdgeModel::new(&mesh, 30.0);
        let none = Deadline::NONE;
        let start = perturb(&truth, 0.01, 3.0, 5);
        let depth = edges.depth(&k, &start, 640, 480, &none).unwrap();
        let model = ColourModel::new(&scene.image, &depth, None, 20).unwrap();
        let median_offset = |pose: &Pose| {
            let depth = edges.depth(&k, pose, 640, 480, &none).unwrap();
            let mut offsets: Vec<f64> = edges
                .samples(&k, pose, &depth, 3.0, &none)
                .unwrap()
                .iter()
                .filter_map(|s| {
                    let n = outward(&depth, &s.pixel, &s.normal, 2.0)?;
                    Some(
                        model
                            .step(&scene.image, &s.pixel, &n, 12, 0.5)?
                            .offset
                            .abs(),
                    )
                })
                .collect();
            assert!(offsets.len() > 50, "{}", offsets.len());
            offsets.sort_by(f64::total_cmp);
            offsets[offsets.len() / 2]
        };
        let at_truth = median_offset(&truth);
        assert!(at_truth < 1.5, "{at_truth}");
        let aside = Pose {
            translation: truth.translation + Vector3::new(5.0 * 0.5 / 600.0, 0.0, 0.0),
            ..truth
        };
        let moved = median_offset(&aside);
        assert!(moved > 2.5 * at_truth, "{moved} {at_truth}");
    }

    /// A red disc on a green background: the step along a radius lies on
    /// the disc's rim, sharply, from either side.
    #[test]
    fn the_step_lies_on_the_colour_boundary() {
        let (w, h) = (80usize, 60usize);
        let (cx, cy, r) = (40.0, 30.0, 15.0);
        let mut data = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            for x in 0..w {
                let inside =
                    ((x as f64 + 0.5 - cx).powi(2) + (y as f64 + 0.5 - cy).powi(2)).sqrt() < r;
                data.extend_from_slice(if inside {
                    &[200.0, 30.0, 30.0]
                } else {
                    &[30.0, 160.0, 40.0]
                });
            }
        }
        let img = ColorImage::new(w, h, data).unwrap();
        let mut posterior = vec![0.5f32; BINS * BINS * BINS];
        posterior[bin(&img, 40, 30)] = 0.95;
        posterior[bin(&img, 2, 2)] = 0.05;
        let model = ColourModel { posterior };
        let n = Vector2::new(1.0, 0.0);
        for start in [50.0, 58.0] {
            let s = model
                .step(&img, &Vector2::new(start, 30.5), &n, 12, 1.0)
                .unwrap();
            let rim = cx + r - start;
            assert!((s.offset - rim).abs() < 0.6, "{s:?} {rim}");
            assert!(s.variance < 0.5, "{s:?}");
        }
    }
}
