//! The loss of eq. (3) and its decomposition for loss-augmented inference.
//!
//! `Delta(y, y_hat) = (1 - IoU) + IoU * H(v, v_hat)`, where `H` is the mean
//! Hamming distance of the visibility labels. Labels of boxes at different
//! scales are compared at the finest level (pixels): the truth label of a
//! cell of `y_hat` is the majority of the ground-truth visible pixels in the
//! cell's footprint. The first term goes into the constant of the energy, the
//! second into the unaries of the cells (`IoU / n` per disagreeing cell).

use crate::vision::detect::{box_iou, LossAugment};
use crate::vision::energy::BoxProblem;
use crate::vision::mask::{CellGrid, Mask};

/// Which loss to train with.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, clap::ValueEnum,
)]
#[serde(rename_all = "kebab-case")]
pub enum LossKind {
    /// Eq. (3): `(1 - IoU) + IoU * H`.
    SdHop,
    /// The loss of Gao et al. 2011 as the ablation uses it: 1 when the boxes
    /// overlap by less than IoU 0.5, otherwise the mean Hamming distance.
    Gao,
}

/// Summed-area table of a mask, for pixel counts over rectangles.
#[derive(Clone, Debug)]
pub struct IntegralMask {
    width: usize,
    height: usize,
    sums: Vec<u32>,
}

impl IntegralMask {
    pub fn new(m: &Mask) -> Self {
        let (w, h) = (m.width, m.height);
        let mut sums = vec![0u32; (w + 1) * (h + 1)];
        for y in 0..h {
            let mut row = 0u32;
            for x in 0..w {
                row += u32::from(m.data[y * w + x] != 0);
                sums[(y + 1) * (w + 1) + x + 1] = sums[y * (w + 1) + x + 1] + row;
            }
        }
        Self {
            width: w,
            height: h,
            sums,
        }
    }

    /// True pixels in `[x0, x1) x [y0, y1)`, clipped to the mask.
    pub fn count(&self, x0: i64, y0: i64, x1: i64, y1: i64) -> u32 {
        let cx = |v: i64| v.clamp(0, self.width as i64) as usize;
        let cy = |v: i64| v.clamp(0, self.height as i64) as usize;
        let (x0, x1, y0, y1) = (cx(x0), cx(x1), cy(y0), cy(y1));
        if x1 <= x0 || y1 <= y0 {
            return 0;
        }
        let w = self.width + 1;
        self.sums[y1 * w + x1] + self.sums[y0 * w + x0]
            - self.sums[y0 * w + x1]
            - self.sums[y1 * w + x0]
    }
}

/// The pixel footprint `[x0, x1) x [y0, y1)` of cell `i` of a box (the
/// pixels whose centres map into the cell, as [`CellGrid::cell_of`] draws).
fn cell_footprint(grid: &CellGrid, i: usize) -> (i64, i64, i64, i64) {
    let cs = grid.cell_size as f64;
    let (tx, ty) = ((i % grid.cols) as f64, (i / grid.cols) as f64);
    let edge = |c: f64, s: f64| ((c * cs / s) - 0.5).ceil() as i64;
    let (gx, gy) = (grid.cell_x as f64 + tx, grid.cell_y as f64 + ty);
    (
        edge(gx, grid.scale_x),
        edge(gy, grid.scale_y),
        edge(gx + 1.0, grid.scale_x),
        edge(gy + 1.0, grid.scale_y),
    )
}

/// The ground-truth visibility of the cells of a box: a cell is visible when
/// more than half of its footprint is visible object (pixels outside the
/// image count as not visible).
pub fn cell_truth(grid: &CellGrid, visible: &IntegralMask, out: &mut Vec<bool>) {
    out.clear();
    for i in 0..grid.rows * grid.cols {
        let (x0, y0, x1, y1) = cell_footprint(grid, i);
        let area = ((x1 - x0).max(0) * (y1 - y0).max(0)) as u64;
        let on = u64::from(visible.count(x0, y0, x1, y1));
        out.push(area > 0 && 2 * on > area);
    }
}

/// The ground truth a loss is measured against: the box of the ground-truth
/// output and the visible pixels; `None` for an image without the object.
pub struct Truth<'a> {
    pub bbox: (f64, f64, f64, f64),
    pub visible: &'a IntegralMask,
}

/// The loss against one ground truth, decomposed for the min-cut.
pub struct TruthLoss<'a> {
    pub truth: Option<Truth<'a>>,
    pub kind: LossKind,
    /// Weight of the visibility term (1: eq. (3) as the paper writes it).
    pub seg_weight: f64,
    /// The viewpoint components of the truth's object in a model of several
    /// objects trained jointly (`None`: every component): a box of another
    /// object's component is a false positive wherever it lies (loss 1).
    pub views: Option<&'a [bool]>,
}

impl TruthLoss<'_> {
    /// The box part of the loss at a box and the weight of each disagreeing
    /// cell: `Delta = constant + weight * #disagreements`.
    fn terms(&self, view: usize, grid: &CellGrid) -> (f64, f64) {
        let Some(t) = &self.truth else {
            return (1.0, 0.0);
        };
        if self
            .views
            .is_some_and(|v| !v.get(view).copied().unwrap_or(false))
        {
            return (1.0, 0.0);
        }
        let n = (grid.rows * grid.cols) as f64;
        let iou = box_iou(t.bbox, grid.pixel_box());
        match self.kind {
            LossKind::SdHop => (1.0 - iou, self.seg_weight * iou / n),
            LossKind::Gao => {
                if iou < 0.5 {
                    (1.0, 0.0)
                } else {
                    (0.0, self.seg_weight / n)
                }
            }
        }
    }

    /// The loss of labelling `v` of the box at `grid` of component `view`,
    /// computed directly.
    pub fn loss(&self, view: usize, grid: &CellGrid, v: &[bool]) -> f64 {
        let (c, w) = self.terms(view, grid);
        let Some(t) = self.truth.as_ref().filter(|_| w > 0.0) else {
            return c;
        };
        let mut truth = Vec::new();
        cell_truth(grid, t.visible, &mut truth);
        let wrong = truth.iter().zip(v).filter(|(a, b)| a != b).count();
        c + w * wrong as f64
    }
}

impl LossAugment for TruthLoss<'_> {
    fn max_loss(&self) -> f64 {
        self.seg_weight.max(1.0)
    }

    fn augment(&self, view: usize, grid: &CellGrid, problem: &mut BoxProblem) {
        let (c, w) = self.terms(view, grid);
        problem.constant -= c;
        if w > 0.0 {
            if let Some(t) = &self.truth {
                let mut truth = Vec::with_capacity(problem.len());
                cell_truth(grid, t.visible, &mut truth);
                problem.add_hamming_loss(&truth, w);
            }
        }
    }
}

/// Largest overlap (IoU) with an instance of the object that a window of
/// a background example may have: windows overlapping more are neither
/// the object nor background, and are left out.
pub const BACKGROUND_MAX_IOU: f64 = 0.3;

/// The loss of a background example ([`Background`]): every output is a
/// false positive (loss 1, as on a negative image), and only windows
/// centred in the example's region and away from the photograph's
/// instances are searched.
pub struct BackgroundLoss<'a> {
    pub background: &'a Background,
}

/// A part of a positive photograph away from its instances, searched as a
/// negative image: windows whose centre lies in `region` (`x0, y0, x1, y1`
/// in pixels) and that overlap every box of `instances` by less than
/// [`BACKGROUND_MAX_IOU`].
#[derive(Clone, Debug, PartialEq)]
pub struct Background {
    pub region: (f64, f64, f64, f64),
    pub instances: Vec<(f64, f64, f64, f64)>,
}

impl Background {
    /// The `n` regions of a `width x height` photograph (rows of
    /// `ceil(sqrt n)` columns, as many as `n` needs, the last row split
    /// into what is left), each with the same instances.
    pub fn regions(
        n: usize,
        width: f64,
        height: f64,
        instances: &[(f64, f64, f64, f64)],
    ) -> Vec<Background> {
        if n == 0 {
            return Vec::new();
        }
        let cols = (n as f64).sqrt().ceil() as usize;
        let rows = n.div_ceil(cols);
        let mut out = Vec::with_capacity(n);
        for r in 0..rows {
            let cols = if r + 1 == rows { n - cols * r } else { cols };
            for c in 0..cols {
                // The outer edges reach past the photograph: a window of a
                // truncated object may have its centre outside it.
                let edge = |i: usize, k: usize, len: f64| {
                    if i == 0 {
                        f64::NEG_INFINITY
                    } else if i == k {
                        f64::INFINITY
                    } else {
                        len * i as f64 / k as f64
                    }
                };
                out.push(Background {
                    region: (
                        edge(c, cols, width),
                        edge(r, rows, height),
                        edge(c + 1, cols, width),
                        edge(r + 1, rows, height),
                    ),
                    instances: instances.to_vec(),
                });
            }
        }
        out
    }

    /// Whether the window `bbox` (`x, y, width, height`) belongs to this
    /// example.
    pub fn contains(&self, bbox: (f64, f64, f64, f64)) -> bool {
        let (cx, cy) = (bbox.0 + 0.5 * bbox.2, bbox.1 + 0.5 * bbox.3);
        let (x0, y0, x1, y1) = self.region;
        cx >= x0
            && cx < x1
            && cy >= y0
            && cy < y1
            && self
                .instances
                .iter()
                .all(|&b| box_iou(b, bbox) < BACKGROUND_MAX_IOU)
    }
}

impl LossAugment for BackgroundLoss<'_> {
    fn max_loss(&self) -> f64 {
        1.0
    }

    fn augment(&self, _view: usize, _grid: &CellGrid, problem: &mut BoxProblem) {
        problem.constant -= 1.0;
    }

    fn excludes(&self, _view: usize, grid: &CellGrid) -> bool {
        !self.background.contains(grid.pixel_box())
    }

    fn centres(&self) -> Option<(f64, f64, f64, f64)> {
        Some(self.background.region)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::rng::SplitMix64;

    fn grid(x: isize, y: isize, rows: usize, cols: usize, scale: f64) -> CellGrid {
        CellGrid {
            cell_x: x,
            cell_y: y,
            rows,
            cols,
            scale_x: scale,
            scale_y: scale,
            cell_size: 8,
        }
    }

    fn random_mask(rng: &mut SplitMix64, w: usize, h: usize) -> Mask {
        let mut m = Mask::new(w, h);
        let (x0, y0) = (rng.range_usize(0, w / 2), rng.range_usize(0, h / 2));
        let (x1, y1) = (rng.range_usize(x0 + 1, w), rng.range_usize(y0 + 1, h));
        for y in y0..y1 {
            for x in x0..x1 {
                m.set(x, y, rng.next_f64() < 0.8);
            }
        }
        m
    }

    #[test]
    fn integral_counts_match_direct_counts() {
        let mut rng = SplitMix64::new(3);
        let m = random_mask(&mut rng, 23, 17);
        let im = IntegralMask::new(&m);
        for _ in 0..200 {
            let (x0, y0) = (
                rng.range_usize(0, 30) as i64 - 4,
                rng.range_usize(0, 25) as i64 - 4,
            );
            let (x1, y1) = (
                x0 + rng.range_usize(0, 20) as i64,
                y0 + rng.range_usize(0, 20) as i64,
            );
            let mut direct = 0;
            for y in y0.max(0)..y1.min(17) {
                for x in x0.max(0)..x1.min(23) {
                    direct += u32::from(m.get(x as usize, y as usize));
                }
            }
            assert_eq!(im.count(x0, y0, x1, y1), direct);
        }
    }

    /// Zero for the ground truth itself, 1 for disjoint boxes, symmetric for
    /// boxes on the same cell grid, and in [0, 1].
    #[test]
    fn properties_of_eq_3() {
        let mut rng = SplitMix64::new(11);
        for _ in 0..50 {
            let m = random_mask(&mut rng, 96, 80);
            let im = IntegralMask::new(&m);
            let g = grid(
                rng.range_usize(0, 4) as isize,
                rng.range_usize(0, 4) as isize,
                4,
                5,
                1.0,
            );
            let mut tv = Vec::new();
            cell_truth(&g, &im, &mut tv);
            let at = |b: &CellGrid| TruthLoss {
                truth: Some(Truth {
                    bbox: b.pixel_box(),
                    visible: &im,
                }),
                kind: LossKind::SdHop,
                seg_weight: 1.0,
                views: None,
            };
            assert_eq!(at(&g).loss(0, &g, &tv), 0.0);
            let far = grid(g.cell_x + 6, g.cell_y, 4, 5, 1.0);
            let v: Vec<bool> = (0..20).map(|_| rng.next_f64() < 0.5).collect();
            assert_eq!(at(&g).loss(0, &far, &v), 1.0);
            // Same grid, shifted: symmetric when both sides use their own
            // truth labels as the labelling.
            let other = grid(g.cell_x + 1, g.cell_y, 4, 5, 1.0);
            let mut ov = Vec::new();
            cell_truth(&other, &im, &mut ov);
            let d1 = at(&g).loss(0, &other, &ov);
            let d2 = at(&other).loss(0, &g, &tv);
            assert!((d1 - d2).abs() < 1e-12, "{d1} vs {d2}");
            let d = at(&g).loss(0, &other, &v);
            assert!((0.0..=1.0).contains(&d));
        }
    }

    /// `E(v) - Delta(v)` equals the augmented problem's energy for every
    /// labelling of small boxes at several scales, for both losses.
    #[test]
    fn background_regions_tile_the_photograph_away_from_its_instances() {
        let object = (40.0, 30.0, 20.0, 20.0);
        for n in [1, 2, 3, 4, 9] {
            let regions = Background::regions(n, 100.0, 80.0, &[object]);
            assert_eq!(regions.len(), n);
            // Every window away from the object (centres inside the
            // photograph or past its border) is in exactly one region.
            for (cx, cy) in [
                (5.0, 5.0),
                (95.0, 75.0),
                (-3.0, 40.0),
                (50.0, 90.0),
                (10.0, 60.0),
            ] {
                let w = (cx - 5.0, cy - 5.0, 10.0, 10.0);
                let n_in = regions.iter().filter(|r| r.contains(w)).count();
                assert_eq!(n_in, 1, "{n} regions, window at ({cx}, {cy})");
            }
            // The object and windows overlapping it by IoU 0.3 or more are
            // in none.
            for w in [object, (42.0, 30.0, 20.0, 20.0), (35.0, 25.0, 28.0, 28.0)] {
                assert!(regions.iter().all(|r| !r.contains(w)), "{w:?}");
            }
        }
        assert!(Background::regions(0, 100.0, 80.0, &[object]).is_empty());
        // The loss: 1 for every output searched, none searched in the
        // object.
        let bg = &Background::regions(1, 100.0, 80.0, &[object])[0];
        let aug = BackgroundLoss { background: bg };
        let g = grid(5, 3, 2, 2, 10.0);
        let mut problem = BoxProblem::default();
        aug.augment(0, &g, &mut problem);
        assert_eq!(problem.constant, -1.0);
        assert_eq!(aug.max_loss(), 1.0);
        assert!(!aug.excludes(0, &g));
        // Cells of 10 px: exactly the object's box.
        assert!(aug.excludes(0, &grid(4, 3, 2, 2, 0.8)));
    }

    #[test]
    fn decomposition_equals_the_direct_loss_for_every_labelling() {
        let mut rng = SplitMix64::new(5);
        for case in 0..40 {
            let m = random_mask(&mut rng, 64, 48);
            let im = IntegralMask::new(&m);
            let (rows, cols) = (rng.range_usize(1, 4), rng.range_usize(1, 4));
            let scale = [1.0, 0.8, 0.6][case % 3];
            let g = grid(
                rng.range_usize(0, 5) as isize - 1,
                rng.range_usize(0, 5) as isize - 1,
                rows,
                cols,
                scale,
            );
            let truth_box = (
                rng.range_f64(0.0, 30.0),
                rng.range_f64(0.0, 20.0),
                rng.range_f64(8.0, 40.0),
                rng.range_f64(8.0, 30.0),
            );
            let kind = if case % 2 == 0 {
                LossKind::SdHop
            } else {
                LossKind::Gao
            };
            let loss = TruthLoss {
                truth: Some(Truth {
                    bbox: truth_box,
                    visible: &im,
                }),
                kind,
                seg_weight: 1.0,
                // Component 1 is another object's in a joint model.
                views: Some(&[true, false]),
            };
            // The truth's own component, then another object's: loss 1
            // for every labelling, even on the truth's box.
            let view = case / 3 % 2;
            let n = rows * cols;
            let mut p = BoxProblem::new(rows, cols, vec![0.0, 0.5, 0.7, 0.5, 0.0]);
            for i in 0..n {
                p.u1[i] = rng.range_f64(-1.0, 1.0);
                p.u0[i] = rng.range_f64(-1.0, 1.0);
                p.clique_of[i] = 0;
            }
            p.n_cliques = 1;
            p.pairwise = 0.2;
            let mut aug = p.clone();
            loss.augment(view, &g, &mut aug);
            for bits in 0..1u32 << n {
                let v: Vec<bool> = (0..n).map(|i| bits >> i & 1 == 1).collect();
                let delta = loss.loss(view, &g, &v);
                if view == 1 {
                    assert_eq!(delta, 1.0);
                }
                let direct = p.energy(&v) - delta;
                assert!((aug.energy(&v) - direct).abs() < 1e-12);
            }
        }
    }
}
