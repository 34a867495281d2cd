//! Pixel-level refinement of a detection's visible mask: a binary graph
//! cut over the pixels of the detection's box that fuses the min-cut's
//! cell visibility labels, the viewpoint's pixel shape model (a prior),
//! the image segments, and the image's colour edges (contrast-sensitive
//! Potts terms, as GrabCut), solved exactly with the project's max-flow.
//!
//! Each pixel's log-odds of being a visible object pixel is
//! `shape * logit(s) + cells * (+1 visible cell, -1 occluded) + segments *
//! (2 f - 1) + bias`, where `s` is the shape model's probability at the
//! pixel and `f` the mean over the pixel's segment (its pixels in the box)
//! of `s` times the cell label: segments that mostly lie on visible object
//! cells pull their pixels in, the others push them out. Neighbouring
//! pixels pay `smoothness * exp(-|I_p - I_q|^2 / (2 <|I_p - I_q|^2>))` to
//! differ, so the outline follows the colour edges; pixels outside the box
//! are background.

use serde::{Deserialize, Serialize};

use super::image::ColorImage;
use super::mask::{CellGrid, Mask};
use super::maxflow::Graph;
use super::segment::Segmentation;
use super::shape::{colour_bin, ShapeModel, COLOUR_BINS};
use super::VisionError;

/// The probability of the shape model is clamped to this and 1 minus it
/// before its logit.
const SHAPE_FLOOR: f64 = 0.05;

/// The colour term's log-likelihood ratio is clamped to this either way.
pub const COLOUR_CLAMP: f64 = 3.0;

/// Weights of the pixel refinement.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PixelRefine {
    /// Off: the segment snapping alone (as before pixel refinement).
    pub enabled: bool,
    pub shape: f64,
    pub cells: f64,
    pub segments: f64,
    pub bias: f64,
    pub smoothness: f64,
    /// Weight of the colour log-likelihood ratio (object against the
    /// background around the box), clamped to +-[`COLOUR_CLAMP`].
    pub colour: f64,
    /// Cuts with the colours re-estimated from the last cut (GrabCut's
    /// iterations; 1: the prior's colours only).
    pub colour_rounds: usize,
    /// The share of the object's colour model taken from the training
    /// images' colours (where the viewpoint has them), the rest from the
    /// image's own pixels the prior is surest of.
    pub learned_colours: f64,
}

impl Default for PixelRefine {
    fn default() -> Self {
        // Chosen on folds 0-3 of 5 of the CMU_KO8 development split
        // (`examples/refine_tune.rs`; README "Pixel masks").
        Self {
            enabled: true,
            shape: 0.5,
            cells: 1.0,
            segments: 2.0,
            bias: 0.0,
            smoothness: 1.0,
            colour: 3.0,
            colour_rounds: 1,
            learned_colours: 1.0,
        }
    }
}

impl PixelRefine {
    pub fn validate(&self) -> Result<(), VisionError> {
        let ok = [
            self.shape,
            self.cells,
            self.segments,
            self.bias,
            self.smoothness,
            self.colour,
        ]
        .iter()
        .all(|v| v.is_finite())
            && self.shape >= 0.0
            && self.cells >= 0.0
            && self.segments >= 0.0
            && self.smoothness >= 0.0
            && self.colour >= 0.0
            && (1..=10).contains(&self.colour_rounds)
            && (0.0..=1.0).contains(&self.learned_colours);
        if ok {
            Ok(())
        } else {
            Err(VisionError::InvalidParameter(format!(
                "invalid pixel refinement weights {self:?}"
            )))
        }
    }
}

fn logit(p: f64) -> f64 {
    let p = p.clamp(SHAPE_FLOOR, 1.0 - SHAPE_FLOOR);
    (p / (1.0 - p)).ln()
}

/// The refined visible mask of a detection over the image: `raw` is its
/// cell mask (visible cells drawn in pixels), `grid` its box.
pub fn refine_pixels(
    raw: &Mask,
    grid: &CellGrid,
    shape: &ShapeModel,
    seg: &Segmentation,
    img: &ColorImage,
    params: &PixelRefine,
) -> Mask {
    let (w, h) = (raw.width, raw.height);
    let (x0, y0, x1, y1) = grid.pixel_range(w, h);
    let mut out = Mask::new(w, h);
    if x1 <= x0 || y1 <= y0 || img.width() != w || img.height() != h {
        return out;
    }
    let (bw, bh) = (x1 - x0, y1 - y0);
    let (bx, by, bwf, bhf) = grid.pixel_box();
    let n = bw * bh;
    // The prior per pixel: shape probability, and it times the cell label.
    let mut s = vec![0.0f64; n];
    let mut q = vec![0.0f64; n];
    let mut seg_sum = std::collections::HashMap::<u32, (f64, f64)>::new();
    for y in y0..y1 {
        for x in x0..x1 {
            let i = (y - y0) * bw + (x - x0);
            let fx = (x as f64 + 0.5 - bx) / bwf;
            let fy = (y as f64 + 0.5 - by) / bhf;
            s[i] = shape.at(fx, fy);
            q[i] = if raw.get(x, y) { s[i] } else { 0.0 };
            let e = seg_sum.entry(seg.label(x, y)).or_insert((0.0, 0.0));
            e.0 += q[i];
            e.1 += 1.0;
        }
    }
    // Colour differences of the 4-neighbour pairs, and their mean.
    let diff = |a: (usize, usize), b: (usize, usize)| -> f64 {
        (0..3)
            .map(|c| f64::from(img.get(a.0, a.1, c) - img.get(b.0, b.1, c)).powi(2))
            .sum()
    };
    let (mut dsum, mut dn) = (0.0, 0usize);
    for y in y0..y1 {
        for x in x0..x1 {
            if x + 1 < x1 {
                dsum += diff((x, y), (x + 1, y));
                dn += 1;
            }
            if y + 1 < y1 {
                dsum += diff((x, y), (x, y + 1));
                dn += 1;
            }
        }
    }
    let beta = if dn > 0 && dsum > 0.0 {
        dn as f64 / (2.0 * dsum)
    } else {
        0.0
    };
    // Colour log-likelihood ratios: at first the object's colours from
    // the pixels the prior is surest of (shape at least a half on visible
    // cells), the background's from a ring around the box (an occluder
    // usually reaches past the box) and the box pixels the shape excludes;
    // in later rounds (GrabCut) the object's from the last cut's mask and
    // the background's from the rest of the box and the ring.
    let nb = COLOUR_BINS * COLOUR_BINS * COLOUR_BINS;
    let ring = (bw.max(bh) / 10).max(4);
    let (rx0, ry0) = (x0.saturating_sub(ring), y0.saturating_sub(ring));
    let (rx1, ry1) = ((x1 + ring).min(w), (y1 + ring).min(h));
    let mut ring_hist = vec![0.0f64; nb];
    if params.colour > 0.0 {
        for y in ry0..ry1 {
            for x in rx0..rx1 {
                if !(x0..x1).contains(&x) || !(y0..y1).contains(&y) {
                    ring_hist[colour_bin(img, x, y)] += 1.0;
                }
            }
        }
    }
    let rounds = if params.colour > 0.0 {
        params.colour_rounds.max(1)
    } else {
        1
    };
    let mut g = Graph::new();
    let mut ratio = vec![0.0f64; nb];
    for round in 0..rounds {
        if params.colour > 0.0 {
            let (mut hf, mut hb) = (vec![0.0f64; nb], ring_hist.clone());
            for y in y0..y1 {
                for x in x0..x1 {
                    let i = (y - y0) * bw + (x - x0);
                    let (fg, bg) = if round == 0 {
                        (q[i] >= 0.5, s[i] < 0.1)
                    } else {
                        (out.get(x, y), !out.get(x, y))
                    };
                    if fg {
                        hf[colour_bin(img, x, y)] += 1.0;
                    } else if bg {
                        hb[colour_bin(img, x, y)] += 1.0;
                    }
                }
            }
            let (nf, nbg): (f64, f64) = (hf.iter().sum(), hb.iter().sum());
            if nf > 0.0 && nbg > 0.0 {
                let learned = shape
                    .colours
                    .as_ref()
                    .filter(|_| params.learned_colours > 0.0);
                for (k, (r, (f, b))) in ratio.iter_mut().zip(hf.iter().zip(&hb)).enumerate() {
                    let mut pf = (f + 0.5) / (nf + 0.5 * nb as f64);
                    if let Some(l) = learned {
                        let a = params.learned_colours;
                        pf = (1.0 - a) * pf + a * (f64::from(l[k]) + 0.5 / nb as f64) / 1.5;
                    }
                    let pb = (b + 0.5) / (nbg + 0.5 * nb as f64);
                    *r = (pf / pb).ln().clamp(-COLOUR_CLAMP, COLOUR_CLAMP);
                }
            }
        }
        g.reset();
        g.add_nodes(n);
        for y in y0..y1 {
            for x in x0..x1 {
                let i = (y - y0) * bw + (x - x0);
                let (fsum, fcount) = seg_sum.get(&seg.label(x, y)).copied().unwrap_or((0.0, 1.0));
                let f = fsum / fcount.max(1.0);
                let cell = if raw.get(x, y) { 1.0 } else { -1.0 };
                let l = params.shape * logit(s[i])
                    + params.cells * cell
                    + params.segments * (2.0 * f - 1.0)
                    + params.colour * ratio[colour_bin(img, x, y)] / COLOUR_CLAMP
                    + params.bias;
                // Source side is the object: labelling a pixel background
                // cuts its source capacity.
                g.add_tweights(i, l.max(0.0), (-l).max(0.0));
                if params.smoothness > 0.0 {
                    if x + 1 < x1 {
                        let c = params.smoothness * (-beta * diff((x, y), (x + 1, y))).exp();
                        g.add_edge(i, i + 1, c, c);
                    }
                    if y + 1 < y1 {
                        let c = params.smoothness * (-beta * diff((x, y), (x, y + 1))).exp();
                        g.add_edge(i, i + bw, c, c);
                    }
                }
            }
        }
        g.maxflow();
        for y in y0..y1 {
            for x in x0..x1 {
                out.set(x, y, g.is_source_side((y - y0) * bw + (x - x0)));
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A box of 4x4 cells of 8 px over a red disc on green, all cells
    /// labelled visible: the raw mask is the whole box, the refined one
    /// the disc (the shape model says disc-like, the edges say where).
    #[test]
    fn background_in_the_box_is_removed_along_the_colour_edge() {
        let (w, h) = (48usize, 48usize);
        let inside = |x: usize, y: usize| {
            let (dx, dy) = (x as f64 + 0.5 - 24.0, y as f64 + 0.5 - 24.0);
            dx * dx + dy * dy < 13.0 * 13.0
        };
        let mut data = Vec::new();
        for y in 0..h {
            for x in 0..w {
                data.extend_from_slice(if inside(x, y) {
                    &[200.0, 40.0, 40.0]
                } else {
                    &[40.0, 160.0, 60.0]
                });
            }
        }
        let img = ColorImage::new(w, h, data).unwrap();
        let grid = CellGrid {
            cell_x: 1,
            cell_y: 1,
            rows: 4,
            cols: 4,
            scale_x: 1.0,
            scale_y: 1.0,
            cell_size: 8,
        };
        let raw = super::super::mask::raw_mask(&grid, &[true; 16], w, h);
        // A blurred disc of radius 12 over the 32 px box as the prior.
        let shape = ShapeModel {
            width: 32,
            height: 32,
            prob: (0..32 * 32)
                .map(|i| {
                    let (u, v) = ((i % 32) as f64 + 0.5 - 16.0, (i / 32) as f64 + 0.5 - 16.0);
                    (1.0 / (1.0 + ((u * u + v * v).sqrt() - 12.0).exp())) as f32
                })
                .collect(),
            colours: None,
        };
        let labels: Vec<u32> = (0..w * h)
            .map(|i| u32::from(inside(i % w, i / w)))
            .collect();
        let seg = Segmentation::from_labels(w, h, &labels).unwrap();
        let refined = refine_pixels(&raw, &grid, &shape, &seg, &img, &PixelRefine::default());
        let mut truth = Mask::new(w, h);
        for y in 8..40 {
            for x in 8..40 {
                truth.set(x, y, inside(x, y));
            }
        }
        assert!(raw.iou(&truth) < 0.6, "{}", raw.iou(&truth));
        assert!(refined.iou(&truth) > 0.97, "{}", refined.iou(&truth));
        // A blue occluder over the right half of the disc, whose cells are
        // labelled occluded: it stays out, the red left half stays in.
        let mut data = img.data().to_vec();
        for y in 0..h {
            for x in 24..w {
                if inside(x, y) {
                    data[(y * w + x) * 3..(y * w + x) * 3 + 3]
                        .copy_from_slice(&[40.0, 60.0, 200.0]);
                }
            }
        }
        let img = ColorImage::new(w, h, data).unwrap();
        let labels: Vec<u32> = (0..w * h)
            .map(|i| match (inside(i % w, i / w), i % w >= 24) {
                (false, _) => 0,
                (true, false) => 1,
                (true, true) => 2,
            })
            .collect();
        let seg = Segmentation::from_labels(w, h, &labels).unwrap();
        let half: Vec<bool> = (0..16).map(|i| i % 4 < 2).collect();
        let raw = super::super::mask::raw_mask(&grid, &half, w, h);
        let refined = refine_pixels(&raw, &grid, &shape, &seg, &img, &PixelRefine::default());
        assert!(!refined.get(36, 24) && refined.get(14, 24));
    }
}
