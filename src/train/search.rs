//! The most violated outputs of the structural SVM (the separation oracle
//! of the cutting-plane training): for every example, the loss-augmented
//! best location and its min-cut labelling, over all locations or over
//! the example's cache of recent ones, summed into one plane.

use std::collections::HashMap;
use std::sync::Arc;

use rayon::prelude::*;

use super::examples::Example;
use super::layout::Layout;
use super::loss::{BackgroundLoss, Truth, TruthLoss};
use super::qp::Plane;
use super::{Found, Round, TrainError, TrainParams};
use crate::vision::detect::{DenseBounds, Detector, LossAugment};
use crate::vision::energy::joint_feature;
use crate::vision::pyramid::FeaturePyramid;

/// One cutting-plane round: the most violated output of every example (over
/// all locations when `full`, else over its cache) summed into a plane.
pub(super) fn search(
    det: &Detector,
    layout: &Layout,
    examples: &mut [Example],
    params: &TrainParams,
    full: bool,
    budget: Option<usize>,
) -> Result<Round, TrainError> {
    // A photograph searched as several examples (its background regions)
    // has its stage-1 bounds computed once per full search.
    // (Keyed by the pyramid's address.)
    let key = |pyr: &Arc<FeaturePyramid>| Arc::as_ptr(pyr) as usize;
    let mut shared: HashMap<usize, DenseBounds> = HashMap::new();
    if full {
        let mut uses: HashMap<usize, (usize, &FeaturePyramid)> = HashMap::new();
        for ex in examples.iter() {
            uses.entry(key(&ex.pyr)).or_insert((0, &ex.pyr)).0 += 1;
        }
        shared = uses
            .into_par_iter()
            .filter(|(_, (n, _))| *n > 1)
            .map(|(k, (_, pyr))| (k, det.dense_bounds(pyr, params.max_truncation)))
            .collect();
    }
    let results: Vec<Result<Found, TrainError>> = examples
        .par_iter()
        .map(|ex| {
            let truth_loss = TruthLoss {
                truth: ex.truth.as_ref().map(|t| Truth {
                    bbox: t.bbox,
                    visible: &t.visible,
                }),
                kind: params.energy.loss,
                seg_weight: if params.energy.occlusion {
                    params.energy.seg_weight
                } else {
                    0.0
                },
                views: ex
                    .truth
                    .as_ref()
                    .and_then(|t| t.views.as_deref().map(Vec::as_slice)),
            };
            let background = ex
                .background
                .as_ref()
                .map(|b| BackgroundLoss { background: b });
            let aug: &dyn LossAugment = match &background {
                Some(b) => b,
                None => &truth_loss,
            };
            // The empty output: loss 1 on a positive, 0 on a negative.
            let floor = if ex.truth.is_some() { 1.0 } else { 0.0 };
            // The cached locations first: their best value is a tight
            // cut-off for the exact search over everything.
            let cached = det.most_violated_among(&ex.pyr, &ex.cache, aug, floor);
            let mut cuts = 0;
            let mut extra = Vec::new();
            let best = if full {
                let start = cached.as_ref().map_or(floor, |b| b.value);
                let pre = shared.get(&key(&ex.pyr));
                let (found, others, stats) =
                    det.most_violated(&ex.pyr, aug, start, params.max_truncation, budget, pre)?;
                cuts = stats.min_cuts;
                extra = others;
                found.filter(|f| f.value > start).or(cached)
            } else {
                cached
            };
            let mut g = vec![0.0; layout.len];
            let (loss, loc) = match &best {
                Some(b) => {
                    let (problem, feats, truncated) = det.problem_at(&ex.pyr, &b.location);
                    let psi = joint_feature(&feats, &b.cells, &problem, truncated);
                    layout.add_psi(
                        b.location.view,
                        &psi,
                        ex.weight,
                        &mut g,
                        params.energy.hop,
                        params.energy.pairwise,
                    );
                    let grid = det.grid(&ex.pyr, &b.location);
                    let loss = match &background {
                        Some(_) => 1.0,
                        None => truth_loss.loss(b.location.view, &grid, &b.cells),
                    };
                    (loss, Some(b.location))
                }
                None => (floor, None),
            };
            if let Some(t) = &ex.truth {
                // Skip the constraint of the ground truth against itself.
                let is_truth = best
                    .as_ref()
                    .is_some_and(|b| b.location == t.location && b.cells == t.cells);
                if is_truth {
                    return Ok(Found {
                        g: vec![0.0; layout.len],
                        b: 0.0,
                        loss: 0.0,
                        location: loc,
                        min_cuts: cuts,
                        extra,
                    });
                }
                for (gi, pi) in g.iter_mut().zip(&t.psi) {
                    *gi -= ex.weight * pi;
                }
            }
            Ok(Found {
                g,
                b: ex.weight * loss,
                loss,
                location: loc,
                min_cuts: cuts,
                extra,
            })
        })
        .collect();
    let mut g = vec![0.0; layout.len];
    let mut b = 0.0;
    let mut loss = 0.0;
    let mut wsum = 0.0;
    let mut min_cuts = 0;
    for (ex, r) in examples.iter_mut().zip(results) {
        let Found {
            g: gi,
            b: bi,
            loss: li,
            location: loc,
            min_cuts: cuts,
            extra,
        } = r?;
        min_cuts += cuts;
        for (a, x) in g.iter_mut().zip(&gi) {
            *a += x;
        }
        b += bi;
        loss += ex.weight * li;
        wsum += ex.weight;
        // The cache is kept in order of recent use: the locations found now
        // first (the most violated one at the very front, so the next
        // search starts from a tight cut-off), the least recently useful
        // last, and those leave first (never the ground truth).
        for l in extra.into_iter().rev().chain(loc) {
            if let Some(pos) = ex.cache.iter().position(|c| *c == l) {
                ex.cache.remove(pos);
            }
            ex.cache.insert(0, l);
        }
        if ex.cache.len() > params.solver.cache_size {
            let keep_truth = ex.truth.as_ref().map(|t| t.location);
            let mut excess = ex.cache.len() - params.solver.cache_size;
            let mut i = ex.cache.len();
            while excess > 0 && i > 0 {
                i -= 1;
                if Some(ex.cache[i]) != keep_truth {
                    ex.cache.remove(i);
                    excess -= 1;
                }
            }
        }
    }
    Ok(Round {
        plane: Plane { g, b },
        loss: loss / wsum.max(1e-12),
        min_cuts,
    })
}
