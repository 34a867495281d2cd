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

use super::gridflow::GridGraph;
use super::image::ColorImage;
use super::mask::{CellGrid, Mask};
use super::segment::Segmentation;
use super::shape::{colour_bin, ShapeModel, COLOUR_BINS};
use super::VisionError;

/// The probability of the shape model is clamped to this and 1 minus it
/// before its logit.
const SHAPE_FLOOR: f64 = 0.05;

// A colour bin fits the `u16` of [`Cut::bins`].
const _: () = assert!(COLOUR_BINS * COLOUR_BINS * COLOUR_BINS <= 1 << 16);

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
    /// Re-place the shape model where it best agrees with a first cut
    /// (shifted and stretched within the box's uncertainty), then cut
    /// again.
    pub align: bool,
    /// The cut's region: the box grown by this share of its size each
    /// side (the cells' labels hold in the box only).
    pub margin: f64,
}

impl Default for PixelRefine {
    fn default() -> Self {
        // Chosen on folds 0-3 of the 5-fold cross-validation of the eight
        // HOG single-pose models (`sdhop-train cv --save-models`),
        // checked on fold 4 (`examples/refine_tune.rs`; docs/benchmarks.md,
        // "Refinement weights", issue 63): segments 3, bias 0.75 and
        // smoothness 6 took the refined segerr from 0.2599 to 0.2500 on
        // folds 0-3 and from 0.2738 to 0.2621 on fold 4.
        Self {
            enabled: true,
            shape: 0.5,
            cells: 1.0,
            segments: 3.0,
            bias: 0.75,
            smoothness: 6.0,
            colour: 3.0,
            colour_rounds: 1,
            learned_colours: 1.0,
            align: false,
            margin: 0.0,
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
            && (0.0..=1.0).contains(&self.learned_colours)
            && (0.0..=0.5).contains(&self.margin);
        if ok {
            Ok(())
        } else {
            Err(VisionError::InvalidParameter(format!(
                "invalid pixel refinement weights {self:?}"
            )))
        }
    }
}

/// Refinement thresholds: a segment whose pixels inside the box are more than
/// `fill` visible becomes wholly visible (the paper's 0.8); one less than
/// `clear` visible becomes wholly occluded (0 disables that).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RefineParams {
    pub fill: f64,
    pub clear: f64,
    /// The pixel-level graph cut that follows (where the viewpoint has a
    /// shape model); absent in older files: on, default weights.
    #[serde(default)]
    pub pixel: PixelRefine,
}

impl Default for RefineParams {
    fn default() -> Self {
        Self {
            fill: 0.8,
            clear: 0.2,
            pixel: PixelRefine::default(),
        }
    }
}

impl RefineParams {
    /// The refinement a model of `features` cells is trained with: the
    /// same for both kinds. Learned cells' models refined with half the
    /// colour weight under the weights before (their cell labels are
    /// blurrier), but under these the full weight segments them better on
    /// every one of four objects' 5-fold cross-validation (mean refined
    /// segerr 0.3073 at the old weights with half the colour, 0.3027 at
    /// these with half, 0.2978 at these; issue 63, docs/benchmarks.md).
    pub fn for_cells(_features: crate::vision::cells::FeatureKind) -> Self {
        Self::default()
    }
}

/// Snaps a raw mask to the image segments inside the box.
pub fn refine_mask(raw: &Mask, grid: &CellGrid, seg: &Segmentation, params: &RefineParams) -> Mask {
    let (x0, y0, x1, y1) = grid.pixel_range(raw.width, raw.height);
    let mut total = vec![0u32; seg.count()];
    let mut on = vec![0u32; seg.count()];
    for y in y0..y1 {
        for x in x0..x1 {
            let s = seg.label(x, y) as usize;
            total[s] += 1;
            on[s] += u32::from(raw.get(x, y));
        }
    }
    let mut out = raw.clone();
    for y in y0..y1 {
        for x in x0..x1 {
            let s = seg.label(x, y) as usize;
            let frac = f64::from(on[s]) / f64::from(total[s]);
            if frac > params.fill {
                out.set(x, y, true);
            } else if frac < params.clear {
                out.set(x, y, false);
            }
        }
    }
    out
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
    if x1 <= x0 || y1 <= y0 || img.width() != w || img.height() != h {
        return Mask::new(w, h);
    }
    refine_pixels_at(raw, grid, shape, seg, img, params, grid.pixel_box())
}

/// [`refine_pixels`] with the shape model stretched over `placement`
/// (`x, y, w, h` in pixels) instead of the detection's box.
pub fn refine_pixels_at(
    raw: &Mask,
    grid: &CellGrid,
    shape: &ShapeModel,
    seg: &Segmentation,
    img: &ColorImage,
    params: &PixelRefine,
    placement: (f64, f64, f64, f64),
) -> Mask {
    let (w, h) = (raw.width, raw.height);
    let inner = grid.pixel_range(w, h);
    let (x0, y0, x1, y1) = inner;
    if x1 <= x0 || y1 <= y0 || img.width() != w || img.height() != h {
        return Mask::new(w, h);
    }
    let (mx, my) = (
        (params.margin * (x1 - x0) as f64).round() as usize,
        (params.margin * (y1 - y0) as f64).round() as usize,
    );
    let range = (
        x0.saturating_sub(mx),
        y0.saturating_sub(my),
        (x1 + mx).min(w),
        (y1 + my).min(h),
    );
    let mut cut = Cut::new(raw, range, inner, seg, img, params);
    cut.set_prior(shape, placement);
    let mut out = cut.solve(shape);
    if params.align {
        let aligned = cut.align(shape, &out, placement);
        if aligned != placement {
            cut.set_prior(shape, aligned);
            out = cut.solve(shape);
        }
    }
    out
}

/// One detection's graph cut: the box, its pixels' priors and the
/// pairwise terms' colour scale.
struct Cut<'a> {
    raw: &'a Mask,
    seg: &'a Segmentation,
    img: &'a ColorImage,
    params: &'a PixelRefine,
    range: (usize, usize, usize, usize),
    /// The detection's box (within `range`): the cells' labels hold there.
    inner: (usize, usize, usize, usize),
    /// Shape probability per box pixel, and it times the cell label.
    s: Vec<f64>,
    q: Vec<f64>,
    /// Per segment of the image: the sum of `q` and the pixel count over
    /// the box (indexed by segment label).
    seg_sum: Vec<(f64, f64)>,
    beta: f64,
    ring_hist: Vec<f64>,
    /// The smoothness capacities to the right and lower neighbour of each
    /// range pixel (the same for every cut of the detection: made once).
    pair_caps: Vec<[f64; 2]>,
    /// The colour bin of each range pixel.
    bins: Vec<u16>,
    graph: GridGraph,
}

impl<'a> Cut<'a> {
    fn new(
        raw: &'a Mask,
        range: (usize, usize, usize, usize),
        inner: (usize, usize, usize, usize),
        seg: &'a Segmentation,
        img: &'a ColorImage,
        params: &'a PixelRefine,
    ) -> Self {
        let (x0, y0, x1, y1) = range;
        let (w, h) = (raw.width, raw.height);
        let (bw, bh) = (x1 - x0, y1 - y0);
        // Colour differences of the 4-neighbour pairs, and their mean.
        let (mut dsum, mut dn) = (0.0, 0usize);
        for y in y0..y1 {
            for x in x0..x1 {
                if x + 1 < x1 {
                    dsum += colour_diff(img, (x, y), (x + 1, y));
                    dn += 1;
                }
                if y + 1 < y1 {
                    dsum += colour_diff(img, (x, y), (x, y + 1));
                    dn += 1;
                }
            }
        }
        let beta = if dn > 0 && dsum > 0.0 {
            dn as f64 / (2.0 * dsum)
        } else {
            0.0
        };
        // The background's colours from a ring around the box (an occluder
        // usually reaches past the box).
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
        let bins = (y0..y1)
            .flat_map(|y| (x0..x1).map(move |x| colour_bin(img, x, y) as u16))
            .collect();
        Self {
            raw,
            seg,
            img,
            params,
            range,
            inner,
            bins,
            s: vec![0.0; bw * bh],
            q: vec![0.0; bw * bh],
            seg_sum: vec![(0.0, 0.0); seg.count()],
            beta,
            ring_hist,
            pair_caps: Vec::new(),
            graph: GridGraph::new(),
        }
    }

    fn in_box(&self, x: usize, y: usize) -> bool {
        in_box(self.inner, x, y)
    }

    /// The shape prior with the shape model stretched over `placement`
    /// (`x, y, w, h` in pixels).
    fn set_prior(&mut self, shape: &ShapeModel, placement: (f64, f64, f64, f64)) {
        let (x0, y0, x1, y1) = self.range;
        let bw = x1 - x0;
        let (bx, by, bwf, bhf) = placement;
        self.seg_sum.fill((0.0, 0.0));
        for y in y0..y1 {
            for x in x0..x1 {
                let i = (y - y0) * bw + (x - x0);
                let fx = (x as f64 + 0.5 - bx) / bwf;
                let fy = (y as f64 + 0.5 - by) / bhf;
                self.s[i] = shape.at(fx, fy);
                self.q[i] = if self.raw.get(x, y) { self.s[i] } else { 0.0 };
                let e = &mut self.seg_sum[self.seg.label(x, y) as usize];
                e.0 += self.q[i];
                e.1 += 1.0;
            }
        }
    }

    /// The minimum cut under the current prior (GrabCut rounds where
    /// asked).
    fn solve(&mut self, shape: &ShapeModel) -> Mask {
        let params = self.params;
        let img = self.img;
        let (x0, y0, x1, y1) = self.range;
        let (bw, bh) = (x1 - x0, y1 - y0);
        let mut out = Mask::new(self.raw.width, self.raw.height);
        // Colour log-likelihood ratios: at first the object's colours from
        // the pixels the prior is surest of (shape at least a half on
        // visible cells), the background's from the ring and the box
        // pixels the shape excludes; in later rounds (GrabCut) the
        // object's from the last cut's mask and the background's from the
        // rest of the box and the ring.
        let nb = COLOUR_BINS * COLOUR_BINS * COLOUR_BINS;
        let rounds = if params.colour > 0.0 {
            params.colour_rounds.max(1)
        } else {
            1
        };
        let mut ratio = vec![0.0f64; nb];
        for round in 0..rounds {
            if params.colour > 0.0 {
                let (mut hf, mut hb) = (vec![0.0f64; nb], self.ring_hist.clone());
                for y in y0..y1 {
                    for x in x0..x1 {
                        let i = (y - y0) * bw + (x - x0);
                        let (fg, bg) = if round == 0 {
                            (self.q[i] >= 0.5, self.s[i] < 0.1)
                        } else {
                            (out.get(x, y), !out.get(x, y))
                        };
                        let b = usize::from(self.bins[i]);
                        if fg {
                            hf[b] += 1.0;
                        } else if bg {
                            hb[b] += 1.0;
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
            if params.smoothness > 0.0 && self.pair_caps.is_empty() {
                let beta = self.beta;
                let cap = |a, b| params.smoothness * (-beta * colour_diff(img, a, b)).exp();
                self.pair_caps = (y0..y1)
                    .flat_map(|y| (x0..x1).map(move |x| (x, y)))
                    .map(|(x, y)| {
                        [
                            if x + 1 < x1 {
                                cap((x, y), (x + 1, y))
                            } else {
                                0.0
                            },
                            if y + 1 < y1 {
                                cap((x, y), (x, y + 1))
                            } else {
                                0.0
                            },
                        ]
                    })
                    .collect();
            }
            let inner = self.inner;
            let g = &mut self.graph;
            g.reset(bw, bh);
            for y in y0..y1 {
                for x in x0..x1 {
                    let i = (y - y0) * bw + (x - x0);
                    // Every pixel of the range counted its own segment.
                    let (fsum, fcount) = self.seg_sum[self.seg.label(x, y) as usize];
                    let f = fsum / fcount.max(1.0);
                    let cell = if !in_box(inner, x, y) {
                        0.0
                    } else if self.raw.get(x, y) {
                        1.0
                    } else {
                        -1.0
                    };
                    let l = params.shape * logit(self.s[i])
                        + params.cells * cell
                        + params.segments * (2.0 * f - 1.0)
                        + params.colour * ratio[usize::from(self.bins[i])] / COLOUR_CLAMP
                        + params.bias;
                    // Source side is the object: labelling a pixel
                    // background cuts its source capacity.
                    g.add_tweights(i, l.max(0.0), (-l).max(0.0));
                    if params.smoothness > 0.0 {
                        let [right, down] = self.pair_caps[i];
                        g.add_right(i, right, right);
                        g.add_down(i, down, down);
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

    /// The placement of the shape model (shifted and stretched from
    /// `start`) that agrees best with a cut `m`: its pixels pull the shape
    /// in, the box's other pixels push it out except on occluded cells,
    /// where the object may be hidden. Coordinate descent over the four
    /// box parameters, within [`ALIGN_SHIFT`] and [`ALIGN_SCALE`].
    fn align(
        &self,
        shape: &ShapeModel,
        m: &Mask,
        start: (f64, f64, f64, f64),
    ) -> (f64, f64, f64, f64) {
        let (x0, y0, x1, y1) = self.range;
        let mut pts: Vec<(f64, f64, f64)> = Vec::new();
        for y in (y0..y1).step_by(2) {
            for x in (x0..x1).step_by(2) {
                let e = if m.get(x, y) {
                    1.0
                } else if self.raw.get(x, y) || !self.in_box(x, y) {
                    -1.0
                } else {
                    0.0
                };
                if e != 0.0 {
                    pts.push((x as f64 + 0.5, y as f64 + 0.5, e));
                }
            }
        }
        let (sx, sy, sw, sh) = start;
        let (cx0, cy0) = (sx + sw / 2.0, sy + sh / 2.0);
        let place = |p: &[f64; 4]| {
            let (w, h) = (sw * p[2].exp(), sh * p[3].exp());
            (cx0 + p[0] * sw - w / 2.0, cy0 + p[1] * sh - h / 2.0, w, h)
        };
        let score = |p: &[f64; 4]| {
            let (bx, by, bw, bh) = place(p);
            pts.iter()
                .map(|&(x, y, e)| e * logit(shape.at((x - bx) / bw, (y - by) / bh)))
                .sum::<f64>()
        };
        let mut p = [0.0f64; 4];
        let mut best = score(&p);
        let mut step = [ALIGN_STEP, ALIGN_STEP, ALIGN_STEP, ALIGN_STEP];
        let limit = [ALIGN_SHIFT, ALIGN_SHIFT, ALIGN_SCALE, ALIGN_SCALE];
        for _ in 0..ALIGN_ITERATIONS {
            let mut moved = false;
            for k in 0..4 {
                for dir in [-1.0, 1.0] {
                    let mut c = p;
                    c[k] += dir * step[k];
                    if c[k].abs() > limit[k] {
                        continue;
                    }
                    let v = score(&c);
                    if v > best {
                        best = v;
                        p = c;
                        moved = true;
                    }
                }
            }
            if !moved {
                for st in step.iter_mut() {
                    *st /= 2.0;
                }
                if step[0] < ALIGN_STEP / 8.0 {
                    break;
                }
            }
        }
        if p == [0.0; 4] {
            start
        } else {
            place(&p)
        }
    }
}

/// First step of the shape alignment (share of the box; log scale).
const ALIGN_STEP: f64 = 0.04;
/// Largest shift of the aligned shape, as a share of the box.
const ALIGN_SHIFT: f64 = 0.15;
/// Largest change of the aligned shape's log size.
const ALIGN_SCALE: f64 = 0.2;
const ALIGN_ITERATIONS: usize = 40;

fn in_box(b: (usize, usize, usize, usize), x: usize, y: usize) -> bool {
    (b.0..b.2).contains(&x) && (b.1..b.3).contains(&y)
}

fn colour_diff(img: &ColorImage, a: (usize, usize), b: (usize, usize)) -> f64 {
    (0..3)
        .map(|c| f64::from(img.get(a.0, a.1, c) - img.get(b.0, b.1, c)).powi(2))
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_cell_kinds_refine_with_the_default_weights() {
        use crate::vision::cells::FeatureKind;
        for kind in [FeatureKind::Hog, FeatureKind::Cnn] {
            assert_eq!(RefineParams::for_cells(kind), RefineParams::default());
        }
    }
    use crate::vision::mask::CellGrid;

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

    /// The alignment moves a shape model placed off a disc back onto the
    /// first cut's disc.
    #[test]
    fn alignment_moves_a_shifted_shape_back_onto_the_object() {
        let (w, h) = (64usize, 64usize);
        let inside = |x: usize, y: usize| {
            let (dx, dy) = (x as f64 + 0.5 - 32.0, y as f64 + 0.5 - 32.0);
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
        // A 32 px box (4x4 cells of 8) at (16, 16) around the disc.
        let grid = CellGrid {
            cell_x: 2,
            cell_y: 2,
            rows: 4,
            cols: 4,
            scale_x: 1.0,
            scale_y: 1.0,
            cell_size: 8,
        };
        let raw = super::super::mask::raw_mask(&grid, &[true; 16], w, h);
        let shape = ShapeModel {
            width: 32,
            height: 32,
            prob: (0..32 * 32)
                .map(|i| {
                    let (u, v) = ((i % 32) as f64 + 0.5 - 16.0, (i / 32) as f64 + 0.5 - 16.0);
                    if u * u + v * v < 13.0 * 13.0 {
                        0.95
                    } else {
                        0.02
                    }
                })
                .collect(),
            colours: None,
        };
        let seg = Segmentation::from_labels(w, h, &vec![0u32; w * h]).unwrap();
        let mut truth = Mask::new(w, h);
        for y in 0..h {
            for x in 0..w {
                truth.set(x, y, inside(x, y));
            }
        }
        // A first cut that found the disc: the shape placed 5 px right
        // and 10% too wide is moved back onto it.
        let params = PixelRefine::default();
        let range = grid.pixel_range(w, h);
        let cut = Cut::new(&raw, range, range, &seg, &img, &params);
        let (x, y, bw, bh) = cut.align(&shape, &truth, (19.4, 16.0, 35.2, 32.0));
        assert!((x - 16.0).abs() < 1.5 && (y - 16.0).abs() < 1.5, "{x} {y}");
        assert!(
            (bw - 32.0).abs() < 2.0 && (bh - 32.0).abs() < 2.0,
            "{bw} {bh}"
        );
    }

    #[test]
    fn refinement_fills_and_clears_segments() {
        // Two segments: left half (label 0) and right half (label 1) of 16x8.
        let raw: Vec<u32> = (0..8)
            .flat_map(|_| (0..16).map(|x| u32::from(x >= 8)))
            .collect();
        let seg = Segmentation::from_labels(16, 8, &raw).unwrap();
        let grid = CellGrid {
            cell_x: 0,
            cell_y: 0,
            rows: 1,
            cols: 2,
            scale_x: 1.0,
            scale_y: 1.0,
            cell_size: 8,
        };
        let mut m = Mask::new(16, 8);
        for y in 0..8 {
            for x in 0..8 {
                m.set(x, y, !(x == 0 && y == 0)); // 63/64 of segment 0 visible
            }
        }
        m.set(12, 3, true); // 1/64 of segment 1 visible
        let r = refine_mask(&m, &grid, &seg, &RefineParams::default());
        assert_eq!(r.area(), 64);
        assert!(r.get(0, 0) && !r.get(12, 3));
        let keep = refine_mask(
            &m,
            &grid,
            &seg,
            &RefineParams {
                fill: 1.0,
                clear: 0.0,
                ..RefineParams::default()
            },
        );
        assert_eq!(keep, m);
    }
}
