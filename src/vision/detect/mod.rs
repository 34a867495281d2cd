//! SD-HOP detection: an exact min-cut at every viewpoint and pyramid location
//! that can still matter, non-maximum suppression, and masks.
//!
//! Exact pruning works in three stages, each a lower bound on a location's
//! energy that skips the location once it exceeds the cut-off (the score
//! threshold, or the worst of the `max_detections` best detections found so
//! far, since locations are visited in order of their bound):
//! 1. one dense pass per level and viewpoint computes every location's sum
//!    of best unaries `sum_i min(F_i, B_i + R_i)`, plus the smallest clique
//!    potential times the number of cliques in the box (first one, or an
//!    upper bound on it, `CliqueCounter`, O(1) per box, where the smallest
//!    potential is negative; then, where the location passes, the count
//!    itself, `CliqueCount`);
//! 2. at the survivors, the exact minimum of the energy without its pairwise
//!    term (cliques are then independent; [`BoxProblem::lower_bound_without_pairwise`]);
//! 3. the min-cut itself stops as soon as the flow it has found shows the
//!    minimum above the cut-off ([`BoxProblem::solve_below`]).
//!
//! All three are exact: the detections equal those of solving every
//! location, which a test checks.
//!
//! This file holds the search (visiting locations in order of their
//! bound, branch and bound on the cut-off, suppression); `bounds` the
//! stage-1 bounds, `location` one location's CRF, its stage-2 bounds and
//! its min-cut; `low_rank` the shared basis of stage 1's low-rank bound. The masks of a detection are drawn by [`detection_masks`]
//! with [`super::mask`].

mod bounds;
mod location;
mod low_rank;
mod near;
mod transfer;

use std::time::Instant;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::energy::{
    edge_direction, BoxProblem, PairwiseMode, ViewWeights, NO_CLIQUE, PAIR_DOWN, PAIR_RIGHT,
};
use super::hog::{HogMap, CELL_SIZE, HOG_DIM, HOG_STRIDE};
use super::mask::{raw_mask, CellGrid, Mask};
use super::maxflow::Graph;
use super::pyramid::{FeaturePyramid, Level};
use super::refine::refine_pixels;
use super::refine::{refine_mask, RefineParams};
use super::shape::ShapeModel;
use super::{Deadline, VisionError};
pub use bounds::{
    chain_pair_weight, dense_bounds, dot, responses, scan_range, DenseBounds, LevelBounds,
    PlanarMaps,
};
use bounds::{overlap, positions, CliqueCounter, PlanarMap};
pub use low_rank::{LowRank, LOW_RANK};
pub use transfer::Transfer;

/// Detection settings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DetectParams {
    /// Keep detections whose score (minus the energy) is at least this.
    pub threshold: f64,
    /// At most this many detections after non-maximum suppression.
    pub max_detections: usize,
    /// Suppress a detection whose box IoU with a better one exceeds this.
    pub nms_iou: f64,
    /// Largest fraction of a box's cells that may lie outside the image.
    pub max_truncation: f64,
    /// Skip locations whose bound shows they cannot matter.
    pub prune: bool,
    pub refine: RefineParams,
    /// Weight of the colour agreement in a detection's score: the mean
    /// over its visible mask of the log ratio of the object's learned
    /// colours to the image's (see
    /// [`crate::vision::shape::colour_agreement`]), counted by how far it
    /// falls short of full agreement ([`crate::pipeline::colour_term`]);
    /// 0 (the default): the SD-HOP score alone. The term only lowers a
    /// score, and the threshold applies to the score with it.
    #[serde(default)]
    pub colour_weight: f64,
    /// Only boxes about here (a request's setting, never a model's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub region: Option<Region>,
    /// Give up (with [`VisionError::DeadlineExceeded`]) once this passes (a
    /// request's setting, never stored).
    #[serde(skip)]
    pub deadline: Deadline,
}

/// Where the object is known to be roughly: a location is scanned only
/// when its (full-object) box overlaps `bbox` by an IoU of at least
/// `min_iou`. With one detection asked for, the exact pruning then solves
/// far fewer locations.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Region {
    /// `(x, y, width, height)` in pixels.
    pub bbox: (f64, f64, f64, f64),
    pub min_iou: f64,
}

impl Default for DetectParams {
    fn default() -> Self {
        Self {
            threshold: 0.0,
            max_detections: 10,
            nms_iou: 0.4,
            max_truncation: 0.5,
            prune: true,
            refine: RefineParams::default(),
            colour_weight: 0.0,
            region: None,
            deadline: Deadline::NONE,
        }
    }
}

impl DetectParams {
    pub fn validate(&self) -> Result<(), VisionError> {
        self.refine.pixel.validate()?;
        let ok = !self.threshold.is_nan()
            && (0.0..=1.0).contains(&self.nms_iou)
            && (0.0..1.0).contains(&self.max_truncation)
            && self.refine.fill.is_finite()
            && self.refine.clear.is_finite()
            && self.colour_weight.is_finite()
            && self.colour_weight >= 0.0
            && self.region.is_none_or(|r| {
                let (x, y, w, h) = r.bbox;
                x.is_finite()
                    && y.is_finite()
                    && w > 0.0
                    && h > 0.0
                    && w.is_finite()
                    && h.is_finite()
                    && (0.0..=1.0).contains(&r.min_iou)
            });
        if ok {
            Ok(())
        } else {
            Err(VisionError::InvalidParameter(format!(
                "detection needs a threshold, 0 <= nms_iou <= 1 and 0 <= max_truncation < 1, got {self:?}"
            )))
        }
    }
}

/// One detection.
#[derive(Clone, Debug, PartialEq)]
pub struct Detection {
    pub viewpoint: usize,
    pub level: usize,
    /// Score: minus the energy; higher is better.
    pub score: f64,
    /// Full-extent box in image pixels `(x, y, width, height)`.
    pub bbox: (f64, f64, f64, f64),
    /// Box geometry on its level.
    pub grid: CellGrid,
    /// Visibility of the box cells, row-major.
    pub cells: Vec<bool>,
    /// Whether the box extends beyond the image.
    pub truncated: bool,
    /// Fraction of the box cells labelled visible.
    pub visible_fraction: f64,
}

/// Counts and per-stage wall-clock times of one scan.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct DetectStats {
    pub locations: usize,
    pub pruned_stage1: usize,
    /// Skipped by the clique bound or the best energy found so far.
    pub pruned_stage2: usize,
    pub min_cuts: usize,
    pub responses_ms: f64,
    pub mincut_ms: f64,
    pub nms_ms: f64,
}

impl DetectStats {
    /// Fraction of locations that never reached a min-cut.
    pub fn pruned_fraction(&self) -> f64 {
        if self.locations == 0 {
            0.0
        } else {
            1.0 - self.min_cuts as f64 / self.locations as f64
        }
    }
}

/// A viewpoint prepared for scanning.
struct View<'a> {
    w: &'a ViewWeights,
    /// `min(w_0, w_K)`, the smallest value of any clique potential.
    hop_min: f64,
    w_hop: Vec<f64>,
}

/// A box location: a viewpoint's template placed with its top-left cell at
/// `(x, y)` on a pyramid level (negative or past the edge when truncated).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Location {
    pub level: usize,
    pub view: usize,
    pub y: isize,
    pub x: isize,
}

/// A scanned location that survived stage 1.
#[derive(Clone, Copy, Debug)]
struct Candidate {
    view: usize,
    level: usize,
    x: isize,
    y: isize,
    bound: f64,
}

impl Candidate {
    fn location(&self) -> Location {
        Location {
            level: self.level,
            view: self.view,
            y: self.y,
            x: self.x,
        }
    }
}

/// A loss `Delta(y, y_hat)` that decomposes over a box's cells, for
/// loss-augmented inference (paper section 2.3): at every location it adds a
/// constant and per-cell Hamming terms to the energy, so the same min-cut
/// finds `argmin_y_hat E(y_hat) - Delta(y, y_hat)`.
pub trait LossAugment: Sync {
    /// An upper bound on the loss of any output (subtracted from bounds).
    fn max_loss(&self) -> f64;
    /// Subtracts the loss of the box at `grid` of viewpoint component
    /// `view` from `problem`'s energy.
    fn augment(&self, view: usize, grid: &CellGrid, problem: &mut BoxProblem);
    /// Whether the output at `grid` of component `view` is left out of the
    /// search altogether (never an output of this example).
    fn excludes(&self, _view: usize, _grid: &CellGrid) -> bool {
        false
    }
    /// The pixel rectangle `(x0, y0, x1, y1)` outside which every window
    /// centred there is excluded ([`LossAugment::excludes`]), if there is
    /// one: the search then scans only the positions near it.
    fn centres(&self) -> Option<(f64, f64, f64, f64)> {
        None
    }
}

/// The output of loss-augmented inference at one location.
#[derive(Clone, Debug, PartialEq)]
pub struct Augmented {
    pub location: Location,
    pub cells: Vec<bool>,
    /// `Delta - E` of this output: the larger, the more violated.
    pub value: f64,
}

/// A detection that survives the greedy suppression among those solved:
/// `(group, energy, pixel box)`.
type Settled = (usize, f64, (f64, f64, f64, f64));

struct Solved {
    cand: Candidate,
    energy: f64,
    cells: Vec<bool>,
}

/// Per-thread buffers reused between locations.
#[derive(Default)]
struct Scratch {
    graph: Graph,
    problem: BoxProblem,
    labels: Vec<bool>,
    seg_stamp: Vec<u32>,
    seg_local: Vec<u32>,
    generation: u32,
    edge_dirs: Vec<u8>,
}

/// A margin that absorbs float round-off between the bound and the energy.
#[inline]
fn margin(v: f64) -> f64 {
    1e-4 * (1.0 + v.abs())
}

/// An SD-HOP detector over the viewpoints of one model.
pub struct Detector<'a> {
    views: Vec<View<'a>>,
    /// Responses transferred from other objects' detections.
    transfer: Option<&'a Transfer>,
    /// The group (object) of each viewpoint: non-maximum suppression and
    /// `max_detections` apply within a group (all 0: one object).
    groups: Vec<usize>,
    /// Stage 1's feature planes, built once for several models.
    maps: Option<&'a PlanarMaps<'a>>,
    /// Stage 1 bounds through the low-rank basis of the components'
    /// filters (looser, cheaper; the min-cut stage's own full bound and
    /// the min-cuts are unchanged, so the detections are the same).
    low_rank: Option<&'a LowRank>,
}

impl<'a> Detector<'a> {
    /// Prepares the viewpoints; checks them first.
    pub fn new(views: &'a [ViewWeights]) -> Result<Self, VisionError> {
        if views.is_empty() {
            return Err(VisionError::InvalidParameter(
                "a model needs a viewpoint".into(),
            ));
        }
        let views = views
            .iter()
            .map(|w| {
                w.validate()?;
                let w_hop: Vec<f64> = w.w_hop.iter().map(|&v| f64::from(v)).collect();
                let hop_min = w_hop[0].min(w_hop[w_hop.len() - 1]);
                Ok(View { w, hop_min, w_hop })
            })
            .collect::<Result<Vec<_>, VisionError>>()?;
        let groups = vec![0; views.len()];
        Ok(Self {
            views,
            transfer: None,
            groups,
            maps: None,
            low_rank: None,
        })
    }

    /// The detector with its viewpoints in groups (`groups[v]` of viewpoint
    /// `v`, e.g. the objects of a model trained jointly): each group gets
    /// its own non-maximum suppression and `max_detections`, as separate
    /// models would, and the pruning stays exact per group.
    pub fn with_groups(mut self, groups: Vec<usize>) -> Result<Self, VisionError> {
        if groups.len() != self.views.len() {
            return Err(VisionError::InvalidParameter(format!(
                "{} groups for {} viewpoints",
                groups.len(),
                self.views.len()
            )));
        }
        self.groups = groups;
        Ok(self)
    }

    fn n_groups(&self) -> usize {
        self.groups.iter().max().map_or(1, |g| g + 1)
    }

    /// The detector with the occlusion responses of the cells that
    /// `transfer` claims replaced by their collected responses (response
    /// transfer, see [`Transfer`]).
    pub fn with_transfer(mut self, transfer: &'a Transfer) -> Self {
        self.transfer = (!transfer.is_empty()).then_some(transfer);
        self
    }

    /// The detector reading stage 1's feature planes from `maps` (built once
    /// for every model scanning the pyramid) where they were built from the
    /// same pyramid with enough padding for its templates; otherwise it
    /// builds its own. The bounds are the same either way.
    pub fn with_maps(mut self, maps: &'a PlanarMaps<'a>) -> Self {
        self.maps = Some(maps);
        self
    }

    /// The detector bounding stage 1 through `lr` (built from exactly
    /// these viewpoints' weights) instead of the full filters.
    pub fn with_low_rank(mut self, lr: &'a LowRank) -> Self {
        if lr.filters.len() == self.views.len() {
            self.low_rank = Some(lr);
        }
        self
    }

    /// Scans a pyramid. Returns the detections (best first) and statistics.
    pub fn detect(
        &self,
        pyr: &FeaturePyramid,
        params: &DetectParams,
    ) -> Result<(Vec<Detection>, DetectStats), VisionError> {
        self.detect_with_bounds(pyr, params, None)
    }

    /// [`Self::detect`] with the stage-1 chain bounds computed elsewhere (by
    /// a compute backend; see [`dense_bounds`]). Levels and viewpoints whose
    /// bounds are missing or cover other positions are computed here.
    pub fn detect_with_bounds(
        &self,
        pyr: &FeaturePyramid,
        params: &DetectParams,
        bounds: Option<&DenseBounds>,
    ) -> Result<(Vec<Detection>, DetectStats), VisionError> {
        params.validate()?;
        if params.max_detections == 0 {
            return Ok((Vec::new(), DetectStats::default()));
        }
        let (solved, mut stats) = self.run(pyr, params, None, None, bounds);
        // The scan stops early once the deadline passes.
        if params.deadline.passed() {
            return Err(VisionError::DeadlineExceeded);
        }
        let t = Instant::now();
        let dets = self.suppress(pyr, solved, params);
        stats.nms_ms = t.elapsed().as_secs_f64() * 1e3;
        Ok((dets, stats))
    }

    /// Loss-augmented inference over every location, level and viewpoint:
    /// the output maximising `Delta - E`, if any beats `floor` (the value of
    /// the empty output). Exact: pruned locations provably cannot beat the
    /// best value found. Also returns every location found on the way that
    /// beat the best value known when it was solved (hard examples).
    /// With a `budget`, the search stops after about that many min-cuts
    /// (in order of the bound) and is no longer exact. `pre`: stage 1's
    /// bounds of this pyramid ([`Detector::dense_bounds`]), when several
    /// searches share them.
    pub fn most_violated(
        &self,
        pyr: &FeaturePyramid,
        aug: &dyn LossAugment,
        floor: f64,
        max_truncation: f64,
        budget: Option<usize>,
        pre: Option<&DenseBounds>,
    ) -> Result<(Option<Augmented>, Vec<Location>, DetectStats), VisionError> {
        let params = DetectParams {
            threshold: floor,
            max_detections: 1,
            max_truncation,
            prune: true,
            ..DetectParams::default()
        };
        params.validate()?;
        let (solved, stats) = self.run(pyr, &params, Some(aug), budget, pre);
        let found: Vec<Location> = solved.iter().map(|s| s.cand.location()).collect();
        let best = solved
            .into_iter()
            .min_by(|a, b| a.energy.total_cmp(&b.energy))
            .map(|s| Augmented {
                location: s.cand.location(),
                value: -s.energy,
                cells: s.cells,
            });
        Ok((best, found, stats))
    }

    /// Loss-augmented inference restricted to the given locations.
    pub fn most_violated_among(
        &self,
        pyr: &FeaturePyramid,
        locations: &[Location],
        aug: &dyn LossAugment,
        floor: f64,
    ) -> Option<Augmented> {
        let mut s = Scratch::default();
        let mut best: Option<Augmented> = None;
        let mut cut = -floor;
        for loc in locations {
            if aug.excludes(loc.view, &self.grid(pyr, loc)) {
                continue;
            }
            let cand = Candidate {
                view: loc.view,
                level: loc.level,
                x: loc.x,
                y: loc.y,
                bound: f64::NEG_INFINITY,
            };
            if let Some(r) = self.solve(pyr, &cand, cut, true, Some(aug), &mut s) {
                if r.energy < cut {
                    cut = r.energy;
                    best = Some(Augmented {
                        location: *loc,
                        value: -r.energy,
                        cells: r.cells,
                    });
                }
            }
        }
        best
    }

    /// Both stages and the min-cuts; the solved locations with energy at
    /// most `-threshold` (for a single best detection, only those that were
    /// the best when found).
    fn run(
        &self,
        pyr: &FeaturePyramid,
        params: &DetectParams,
        aug: Option<&dyn LossAugment>,
        budget: Option<usize>,
        pre: Option<&DenseBounds>,
    ) -> (Vec<Solved>, DetectStats) {
        let mut stats = DetectStats::default();
        let t = Instant::now();
        let cands = self.candidates(pyr, params, aug, pre, &mut stats);
        stats.pruned_stage1 = stats.locations.saturating_sub(cands.len());
        stats.responses_ms = t.elapsed().as_secs_f64() * 1e3;
        let t = Instant::now();
        let solved = self.branch_and_bound(pyr, params, aug, budget, cands, &mut stats);
        stats.pruned_stage2 = stats.locations - stats.pruned_stage1 - stats.min_cuts;
        stats.mincut_ms = t.elapsed().as_secs_f64() * 1e3;
        (solved, stats)
    }

    /// Stage 1: every location whose bound can still matter, with its
    /// bound (those a transfer or the region asks for added or kept, those
    /// the loss augmentation excludes left out); counts the locations
    /// scanned in `stats`.
    fn candidates(
        &self,
        pyr: &FeaturePyramid,
        params: &DetectParams,
        aug: Option<&dyn LossAugment>,
        pre: Option<&DenseBounds>,
        stats: &mut DetectStats,
    ) -> Vec<Candidate> {
        let max_loss = aug.map_or(0.0, |a| a.max_loss());
        let cut = -params.threshold;
        let pad_x = self.views.iter().map(|v| v.w.cols).max().unwrap_or(0);
        let pad_y = self.views.iter().map(|v| v.w.rows).max().unwrap_or(0);
        let own: Vec<PlanarMap>;
        let maps: &[PlanarMap] = if params.prune && pre.is_none() && self.low_rank.is_none() {
            match self.maps.filter(|m| m.serves(pyr, pad_x, pad_y)) {
                Some(m) => &m.maps,
                None => {
                    own = pyr
                        .levels
                        .par_iter()
                        .map(|l| PlanarMap::new(&l.hog, pad_x, pad_y))
                        .collect();
                    &own
                }
            }
        } else {
            &[]
        };
        let counters: Vec<CliqueCounter> = if params.prune {
            pyr.levels
                .par_iter()
                .map(|l| CliqueCounter::new(&l.cell_segments, l.hog.width(), l.hog.height()))
                .collect()
        } else {
            Vec::new()
        };
        let low_maps: Vec<PlanarMap> = match self.low_rank {
            Some(lr) if params.prune && pre.is_none() => pyr
                .levels
                .par_iter()
                .map(|l| PlanarMap::projected(&l.hog, &lr.basis, pad_x, pad_y))
                .collect(),
            _ => Vec::new(),
        };
        let empty = PlanarMap::new(&HogMap::zeros(0, 0), 0, 0);
        let jobs: Vec<(usize, usize)> = (0..pyr.levels.len())
            .flat_map(|l| (0..self.views.len()).map(move |v| (l, v)))
            .collect();
        let scanned: Vec<(usize, Vec<Candidate>)> = jobs
            .par_iter()
            .map(|&(l, v)| {
                if params.deadline.passed() {
                    return (0, Vec::new());
                }
                let map = maps.get(l).unwrap_or(&empty);
                let level = &pyr.levels[l];
                let b = pre.and_then(|b| b.get(l, v));
                self.scan_level(
                    l,
                    level,
                    map,
                    counters.get(l),
                    v,
                    params,
                    cut,
                    max_loss,
                    b,
                    low_maps.get(l),
                    aug.and_then(|a| a.centres()),
                )
            })
            .collect();
        let mut cands: Vec<Candidate> = Vec::new();
        for (count, c) in scanned {
            stats.locations += count;
            cands.extend(c);
        }
        if let Some(r) = params.region {
            cands.retain(|c| {
                box_iou(self.grid(pyr, &c.location()).pixel_box(), r.bbox) >= r.min_iou.max(1e-12)
            });
        }
        self.add_transferred(pyr, params, &mut cands);
        if let Some(a) = aug {
            cands.retain(|c| !a.excludes(c.view, &self.grid(pyr, &c.location())));
        }
        cands
    }

    /// With a transfer, every location meeting a claimed cell is visited:
    /// transferred responses can lower an energy below its stage-1 bound.
    fn add_transferred(
        &self,
        pyr: &FeaturePyramid,
        params: &DetectParams,
        cands: &mut Vec<Candidate>,
    ) {
        let Some(tr) = self.transfer else {
            return;
        };
        let mut seen = std::collections::HashSet::new();
        for c in cands.iter_mut() {
            let w = self.views[c.view].w;
            if tr.meets(c.level, c.x, c.y, w.cols, w.rows) {
                c.bound = f64::NEG_INFINITY;
            }
            seen.insert(c.location());
        }
        for loc in self.locations(pyr, params.max_truncation) {
            let w = self.views[loc.view].w;
            if seen.contains(&loc) || !tr.meets(loc.level, loc.x, loc.y, w.cols, w.rows) {
                continue;
            }
            let c = Candidate {
                view: loc.view,
                level: loc.level,
                x: loc.x,
                y: loc.y,
                bound: f64::NEG_INFINITY,
            };
            if params.region.is_none_or(|r| {
                box_iou(self.grid(pyr, &loc).pixel_box(), r.bbox) >= r.min_iou.max(1e-12)
            }) {
                cands.push(c);
            }
        }
    }

    /// Stages 2 and 3: the candidates' min-cuts in order of their bound,
    /// branch and bound on the cut-off; the solved locations at or under
    /// the threshold's energy.
    fn branch_and_bound(
        &self,
        pyr: &FeaturePyramid,
        params: &DetectParams,
        aug: Option<&dyn LossAugment>,
        budget: Option<usize>,
        mut cands: Vec<Candidate>,
        stats: &mut DetectStats,
    ) -> Vec<Solved> {
        let cut = -params.threshold;
        // Visit in order of the bound (ties in a fixed order).
        let order = |a: &Candidate, b: &Candidate| {
            a.bound
                .total_cmp(&b.bound)
                .then((a.level, a.view, a.y, a.x).cmp(&(b.level, b.view, b.y, b.x)))
        };

        // Branch and bound: locations are visited in order of their bound,
        // and once `max_detections` detections survive non-maximum
        // suppression among those solved, the worst of them is the cut-off:
        // a location whose bound is above it ranks after all of them in the
        // greedy suppression, so it can never be reported.
        let single = params.max_detections == 1 && params.prune;
        let ranked = params.prune && budget.is_none();
        // Suppressed unsolved: a solved detection whose place in the greedy
        // suppression is settled (no unsolved location can rank before it)
        // suppresses every location it overlaps whose bound is above its
        // energy, so those need no min-cut (they would rank after it and be
        // suppressed by it, or fall beyond `max_detections` of their group;
        // either way never reported, and suppressed ones suppress nothing).
        let suppress_unsolved = ranked && !single && aug.is_none();
        let mut solved: Vec<Solved> = Vec::new();
        // The cut-off of each group (a location can only be reported among
        // its own group's detections).
        let mut best = vec![cut; self.n_groups()];
        // Settled detections: (group, energy, pixel box).
        let mut settled: Vec<Settled> = Vec::new();
        let chunk = if single {
            64
        } else if suppress_unsolved {
            // Small blocks, so that settled detections take effect early.
            (4 * rayon::current_num_threads()).max(8)
        } else if ranked {
            256
        } else {
            cands.len().max(1)
        };
        // A budget reaches only the first blocks: those alone are sorted.
        if let Some(b) = budget {
            let keep = b.div_ceil(chunk) * chunk;
            if keep < cands.len() {
                cands.select_nth_unstable_by(keep, order);
                cands.truncate(keep);
            }
        }
        cands.sort_by(order);
        let mut own_scratch = Scratch::default();
        for (bi, block) in cands.chunks(chunk).enumerate() {
            let worst = best.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            if (single || ranked) && block[0].bound - margin(block[0].bound) > worst {
                break;
            }
            // A budget counts the locations reached in order of the bound,
            // whether their min-cut finished or was cut off.
            if budget.is_some_and(|b| bi * chunk >= b) || params.deadline.passed() {
                break;
            }
            let cutoff = &best;
            let settled_now = &settled;
            let solve_one = |s: &mut Scratch, c: &Candidate| {
                let group = self.groups[c.view];
                let lower = c.bound - margin(c.bound);
                if (single || ranked) && lower > cutoff[group] {
                    return None;
                }
                if settled_now.iter().any(|&(g, e, _)| g == group && e < lower) {
                    let b = self.grid(pyr, &c.location()).pixel_box();
                    if settled_now
                        .iter()
                        .any(|&(g, e, k)| g == group && e < lower && box_iou(k, b) > params.nms_iou)
                    {
                        return None;
                    }
                }
                self.solve(pyr, c, cutoff[group], params.prune, aug, s)
            };
            // A budgeted search is training's, whose examples already run
            // in parallel: its short blocks run in turn (in parallel, 2 cores
            // spent a fifth of a mining search switching threads).
            let out: Vec<Option<Solved>> = if budget.is_some() {
                block
                    .iter()
                    .map(|c| solve_one(&mut own_scratch, c))
                    .collect()
            } else {
                block
                    .par_iter()
                    .map_init(Scratch::default, solve_one)
                    .collect()
            };
            for r in out.into_iter().flatten() {
                stats.min_cuts += 1;
                if r.energy <= cut {
                    if single {
                        let g = self.groups[r.cand.view];
                        best[g] = best[g].min(r.energy);
                    }
                    solved.push(r);
                }
            }
            let rank = ranked && !single && solved.len() >= params.max_detections;
            if rank || suppress_unsolved {
                sort_solved(&mut solved);
                let survivors = self.survivors(pyr, &solved, params);
                if rank {
                    // The energy of each group's last of `max_detections`
                    // survivors, if that many survive.
                    for (g, b) in best.iter_mut().enumerate() {
                        let kth = params
                            .max_detections
                            .checked_sub(1)
                            .and_then(|k| survivors.iter().filter(|s| s.0 == g).nth(k));
                        if let Some(&(_, e, _)) = kth {
                            *b = b.min(e);
                        }
                    }
                }
                if suppress_unsolved {
                    // Every later location has an energy of at least
                    // `floor` (the blocks are in order of the bound, and the
                    // bound minus its margin grows with the bound); a
                    // survivor below it keeps its place whatever comes.
                    let floor = cands
                        .get((bi + 1) * chunk)
                        .map_or(f64::INFINITY, |c| c.bound - margin(c.bound));
                    settled = survivors.into_iter().take_while(|s| s.1 < floor).collect();
                }
            }
        }
        solved
    }

    /// The detections of `solved` (sorted) that survive greedy non-maximum
    /// suppression within their group, in order, as `(group, energy, pixel
    /// box)`. Whether one survives depends only on those before it.
    fn survivors(
        &self,
        pyr: &FeaturePyramid,
        solved: &[Solved],
        params: &DetectParams,
    ) -> Vec<Settled> {
        let mut kept: Vec<Settled> = Vec::new();
        for s in solved {
            let g = self.groups[s.cand.view];
            let b = self.grid(pyr, &s.cand.location()).pixel_box();
            if kept
                .iter()
                .any(|&(kg, _, k)| kg == g && box_iou(k, b) > params.nms_iou)
            {
                continue;
            }
            kept.push((g, s.energy, b));
        }
        kept
    }

    /// Sorts by score (ties in a fixed order), converts to image boxes and
    /// applies greedy non-maximum suppression.
    fn suppress(
        &self,
        pyr: &FeaturePyramid,
        mut solved: Vec<Solved>,
        params: &DetectParams,
    ) -> Vec<Detection> {
        sort_solved(&mut solved);
        let mut out: Vec<Detection> = Vec::new();
        let mut count = vec![0usize; self.n_groups()];
        for s in solved {
            let group = self.groups[s.cand.view];
            if count[group] >= params.max_detections {
                continue;
            }
            let bbox = self.grid(pyr, &s.cand.location()).pixel_box();
            if out.iter().any(|d| {
                self.groups[d.viewpoint] == group && box_iou(d.bbox, bbox) > params.nms_iou
            }) {
                continue;
            }
            count[group] += 1;
            out.push(self.detection_of(pyr, s));
        }
        out
    }

    /// The detection of a solved location.
    fn detection_of(&self, pyr: &FeaturePyramid, s: Solved) -> Detection {
        let view = &self.views[s.cand.view];
        let level = &pyr.levels[s.cand.level];
        let grid = self.grid(pyr, &s.cand.location());
        let (mw, mh) = (level.hog.width(), level.hog.height());
        let truncated = s.cand.x < 0
            || s.cand.y < 0
            || s.cand.x + view.w.cols as isize > mw as isize
            || s.cand.y + view.w.rows as isize > mh as isize;
        let visible = s.cells.iter().filter(|&&v| v).count();
        Detection {
            viewpoint: s.cand.view,
            level: s.cand.level,
            score: -s.energy,
            bbox: grid.pixel_box(),
            grid,
            visible_fraction: visible as f64 / s.cells.len().max(1) as f64,
            cells: s.cells,
            truncated,
        }
    }
}

/// Best energy first, ties in a fixed order.
fn sort_solved(solved: &mut [Solved]) {
    solved.sort_by(|a, b| {
        a.energy
            .total_cmp(&b.energy)
            .then(a.cand.location().cmp(&b.cand.location()))
    });
}

/// IoU of two boxes `(x, y, w, h)`.
pub fn box_iou(a: (f64, f64, f64, f64), b: (f64, f64, f64, f64)) -> f64 {
    let ix = (a.0 + a.2).min(b.0 + b.2) - a.0.max(b.0);
    let iy = (a.1 + a.3).min(b.1 + b.3) - a.1.max(b.1);
    if ix <= 0.0 || iy <= 0.0 {
        return 0.0;
    }
    let inter = ix * iy;
    inter / (a.2 * a.3 + b.2 * b.3 - inter)
}

/// The raw and refined pixel masks of a detection: with the viewpoint's
/// shape model (and the pixel refinement on), the pixel-level graph cut
/// ([`crate::vision::refine`]); else the segment snapping.
pub fn detection_masks(
    det: &Detection,
    pyr: &FeaturePyramid,
    refine: &RefineParams,
    shape: Option<&ShapeModel>,
) -> (Mask, Mask) {
    let raw = raw_mask(&det.grid, &det.cells, pyr.image_width, pyr.image_height);
    if !pyr.has_pixels() {
        return (raw.clone(), raw);
    }
    let refined = match shape {
        Some(s) if refine.pixel.enabled => refine_pixels(
            &raw,
            &det.grid,
            s,
            &pyr.segmentation,
            &pyr.image,
            &refine.pixel,
        ),
        _ => refine_mask(&raw, &det.grid, &pyr.segmentation, refine),
    };
    (raw, refined)
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;

    #[test]
    fn iou_of_boxes() {
        assert_eq!(box_iou((0.0, 0.0, 2.0, 2.0), (2.0, 0.0, 2.0, 2.0)), 0.0);
        assert!((box_iou((0.0, 0.0, 2.0, 2.0), (1.0, 0.0, 2.0, 2.0)) - 1.0 / 3.0).abs() < 1e-12);
    }

    #[test]
    fn clique_counter_bounds_distinct_segments() {
        let mut rng = crate::vision::rng::SplitMix64::new(5);
        for t in 0..300 {
            let (w, h) = (1 + t % 9, 1 + (t / 9) % 7);
            let labels = 1 + rng.range_usize(0, 6);
            let seg: Vec<u32> = (0..w * h)
                .map(|_| rng.range_usize(0, labels) as u32)
                .collect();
            let c = CliqueCounter::new(&seg, w, h);
            for x0 in 0..w {
                for x1 in x0 + 1..=w {
                    for y0 in 0..h {
                        for y1 in y0 + 1..=h {
                            let mut seen: Vec<u32> = (y0..y1)
                                .flat_map(|y| (x0..x1).map(move |x| (x, y)))
                                .map(|(x, y)| seg[y * w + x])
                                .collect();
                            seen.sort_unstable();
                            seen.dedup();
                            let b = c.bound(x0, x1, y0, y1);
                            assert!(b >= seen.len(), "{seg:?} {w}x{h} [{x0},{x1})x[{y0},{y1})");
                            assert!(b <= (x1 - x0) * (y1 - y0));
                        }
                    }
                }
            }
        }
        // One segment: exactly one clique; a checkerboard: every cell.
        let c = CliqueCounter::new(&[3; 12], 4, 3);
        assert_eq!(c.bound(0, 4, 0, 3), 1);
        let board: Vec<u32> = (0..12).map(|i| ((i % 4 + i / 4) % 2) as u32).collect();
        assert_eq!(CliqueCounter::new(&board, 4, 3).bound(1, 4, 0, 3), 9);
    }

    #[test]
    fn positions_keep_enough_cells_inside() {
        let (lo, hi) = positions(10, 4, 2);
        assert_eq!((lo, hi), (-2, 8));
        assert_eq!(overlap(-2, 4, 10), 2);
        assert_eq!(overlap(8, 4, 10), 2);
    }

    #[test]
    fn dot_matches_plain_sum() {
        let a: Vec<f32> = (0..77).map(|i| i as f32 * 0.1).collect();
        let b: Vec<f32> = (0..77).map(|i| 1.0 - i as f32 * 0.01).collect();
        let plain: f32 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
        assert!((dot(&a, &b) - plain).abs() < 1e-3);
    }
}
