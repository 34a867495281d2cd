//! The structural SVM's training examples for one model: each positive
//! photograph with its ground truth (the location whose box fits the
//! annotation best, its visible cells and joint feature), each negative,
//! and each positive photograph's background regions searched as
//! negatives; every example seeded with a first cache of locations and
//! weighted in the 1-slack average.

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;

use crate::data::Sample;
use crate::vision::detect::{box_iou, Detector, Location};
use crate::vision::energy::joint_feature;
use crate::vision::pyramid::FeaturePyramid;
use crate::vision::rng::SplitMix64;

use super::cache::{HardKey, PyramidCache};
use super::layout::Layout;
use super::loss::{cell_truth, Background, IntegralMask};
use super::{TrainError, TrainParams, TrainReport};

/// One training image prepared for a model.
pub(super) struct Example {
    pub(super) pyr: Arc<FeaturePyramid>,
    /// Weight in the 1-slack average.
    pub(super) weight: f64,
    pub(super) truth: Option<GroundTruth>,
    /// Locations found by earlier searches (and the seeds).
    pub(super) cache: Vec<Location>,
    /// A part of a positive photograph searched as a negative image
    /// ([`TrainParams::background_regions`]).
    pub(super) background: Option<Background>,
    /// Where its hard locations are kept for later trainings.
    pub(super) key: HardKey,
}

pub(super) struct GroundTruth {
    pub(super) visible: IntegralMask,
    pub(super) location: Location,
    pub(super) bbox: (f64, f64, f64, f64),
    pub(super) cells: Vec<bool>,
    /// The joint feature of the ground truth in training coordinates.
    pub(super) psi: Vec<f64>,
    /// The components of the truth's object in a joint model (`None`: a
    /// model of one object, every component is its).
    pub(super) views: Option<Arc<Vec<bool>>>,
}

/// What the examples are built from: the model's layout, the detector of
/// its zero weights (whose locations and grids are the model's), and
/// each object's components in a joint model.
pub(super) struct ExampleContext<'a> {
    pub(super) label: &'a str,
    pub(super) labels: &'a [&'a str],
    pub(super) layout: &'a Layout,
    pub(super) det0: &'a Detector<'a>,
    pub(super) views_of: &'a HashMap<&'a str, Arc<Vec<bool>>>,
    pub(super) cache: &'a PyramidCache,
    pub(super) params: &'a TrainParams,
}

/// A pixel box `(x, y, width, height)`.
type PixelBox = (f64, f64, f64, f64);

/// Builds every example: the positives and negatives in order, then the
/// background regions; skipped positives are named in `report`, whose
/// counts are set.
pub(super) fn build_examples(
    cx: &ExampleContext,
    positives: &[&Sample],
    negatives: &[&Sample],
    report: &mut TrainReport,
) -> Result<Vec<Example>, TrainError> {
    let params = cx.params;
    let mut rng = SplitMix64::new(params.examples.seed);
    let pos_w = params.examples.positive_share / positives.len() as f64;
    let backgrounds = background_photographs(positives, params);
    let n_background = backgrounds.len() * params.examples.background_regions;
    let neg_w = if negatives.is_empty() && n_background == 0 {
        0.0
    } else {
        (1.0 - params.examples.positive_share) / (negatives.len() + n_background) as f64
    };
    let mut examples: Vec<Example> = Vec::new();
    // Whether each example is a box-only positive.
    let mut box_only: Vec<bool> = Vec::new();
    for s in positives.iter().chain(negatives) {
        let pyr = cx
            .cache
            .get(&s.image)
            .ok_or_else(|| TrainError::NoData(format!("{}: no pyramid", s.image.display())))?;
        let locs = cx.det0.locations(&pyr, params.max_truncation);
        let ann = s
            .annotation
            .as_ref()
            .filter(|a| cx.labels.contains(&a.label.as_str()));
        let truth = match ann {
            Some(a) => match ground_truth(cx, &pyr, &locs, a) {
                Ok(t) => Some(t),
                Err(why) => {
                    report.skipped.push(format!("{}: {why}", s.image.display()));
                    continue;
                }
            },
            None => None,
        };
        // Seeds: random locations away from the object.
        let seeds = random_seeds(&locs, params.examples.init_locations, &mut rng, |l| {
            truth
                .as_ref()
                .is_none_or(|t| box_iou(cx.det0.grid(&pyr, l).pixel_box(), t.bbox) < 0.3)
        });
        let key = HardKey {
            image: s.image.clone(),
            region: None,
            label: cx.label.to_string(),
        };
        let seeds = first_cache(
            truth.as_ref().map(|t| t.location),
            cx.cache.hard(&key),
            seeds,
            &locs,
        );
        let weight = if truth.is_some() { pos_w } else { neg_w };
        box_only.push(truth.is_some() && ann.is_some_and(|a| !a.mask_known));
        examples.push(Example {
            pyr,
            weight,
            truth,
            cache: seeds,
            background: None,
            key,
        });
    }
    for (image, instances) in &backgrounds {
        for ex in background_examples(cx, image, instances, neg_w, &mut rng)? {
            box_only.push(false);
            examples.push(ex);
        }
    }
    report.background_negatives = examples.iter().filter(|e| e.background.is_some()).count();
    report.positives = examples.iter().filter(|e| e.truth.is_some()).count();
    report.negatives = examples.len() - report.positives;
    if report.positives == 0 {
        return Err(TrainError::NoData(format!(
            "no usable positive image of {}",
            cx.label
        )));
    }
    reweight(&mut examples, &box_only, params, report.positives);
    Ok(examples)
}

/// Each positive photograph whose background trains (once per image,
/// with all its instances of the labels; never a render).
fn background_photographs<'a>(
    positives: &[&'a Sample],
    params: &TrainParams,
) -> Vec<(&'a PathBuf, Vec<PixelBox>)> {
    let mut backgrounds: Vec<(&PathBuf, Vec<PixelBox>)> = Vec::new();
    if params.examples.background_regions == 0 {
        return backgrounds;
    }
    for s in positives {
        let Some(a) = s.annotation.as_ref() else {
            continue;
        };
        if params.examples.renders.contains(&s.image) {
            continue;
        }
        match backgrounds.iter_mut().find(|(p, _)| *p == &s.image) {
            Some((_, boxes)) => boxes.push(a.bbox),
            None => backgrounds.push((&s.image, vec![a.bbox])),
        }
    }
    backgrounds
}

/// The ground truth of a positive: the location of its component with the
/// best box IoU (at least 0.5), its visible cells and joint feature; or
/// why there is none.
fn ground_truth(
    cx: &ExampleContext,
    pyr: &FeaturePyramid,
    locs: &[Location],
    a: &crate::data::Annotation,
) -> Result<GroundTruth, String> {
    let (det0, layout, params) = (cx.det0, cx.layout, cx.params);
    let best = locs
        .iter()
        .filter(|l| l.view == a.viewpoint)
        .map(|l| (box_iou(det0.grid(pyr, l).pixel_box(), a.bbox), *l))
        .max_by(|x, y| x.0.total_cmp(&y.0).then(y.1.cmp(&x.1)));
    let Some((iou, location)) = best else {
        return Err("no location fits".into());
    };
    if iou < 0.5 {
        return Err(format!(
            "best template box overlaps the annotation only {iou:.2}"
        ));
    }
    let visible = IntegralMask::new(&a.visible);
    let grid = det0.grid(pyr, &location);
    let mut cells = Vec::new();
    cell_truth(&grid, &visible, &mut cells);
    if !params.energy.occlusion {
        cells.iter_mut().for_each(|c| *c = true);
    }
    let mut psi = vec![0.0; layout.len];
    let (problem, feats, truncated) = det0.problem_at(pyr, &location);
    let j = joint_feature(&feats, &cells, &problem, truncated);
    layout.add_psi(
        location.view,
        &j,
        1.0,
        &mut psi,
        params.energy.hop,
        params.energy.pairwise,
    );
    Ok(GroundTruth {
        visible,
        location,
        bbox: grid.pixel_box(),
        cells,
        psi,
        views: cx
            .views_of
            .get(a.label.as_str())
            .filter(|_| cx.labels.len() > 1)
            .cloned(),
    })
}

/// Up to `n` random locations that `keep` accepts (at most `4 n` draws).
fn random_seeds(
    locs: &[Location],
    n: usize,
    rng: &mut SplitMix64,
    keep: impl Fn(&Location) -> bool,
) -> Vec<Location> {
    let mut seeds = Vec::new();
    for _ in 0..n * 4 {
        if seeds.len() >= n || locs.is_empty() {
            break;
        }
        let l = locs[rng.range_usize(0, locs.len())];
        if keep(&l) {
            seeds.push(l);
        }
    }
    seeds
}

/// The background regions of one positive photograph, away from its
/// `instances`, each a negative example.
fn background_examples(
    cx: &ExampleContext,
    image: &PathBuf,
    instances: &[PixelBox],
    neg_w: f64,
    rng: &mut SplitMix64,
) -> Result<Vec<Example>, TrainError> {
    let params = cx.params;
    let pyr = cx
        .cache
        .get(image)
        .ok_or_else(|| TrainError::NoData(format!("{}: no pyramid", image.display())))?;
    let locs = cx.det0.locations(&pyr, params.max_truncation);
    let regions = Background::regions(
        params.examples.background_regions,
        pyr.image_width as f64,
        pyr.image_height as f64,
        instances,
    );
    let mut out = Vec::new();
    for (ri, bg) in regions.into_iter().enumerate() {
        let seeds = random_seeds(&locs, params.examples.init_locations, rng, |l| {
            bg.contains(cx.det0.grid(&pyr, l).pixel_box())
        });
        let key = HardKey {
            image: image.clone(),
            region: Some(ri),
            label: cx.label.to_string(),
        };
        let seeds = first_cache(None, cx.cache.hard(&key), seeds, &locs);
        out.push(Example {
            pyr: pyr.clone(),
            weight: neg_w,
            truth: None,
            cache: seeds,
            background: Some(bg),
            key,
        });
    }
    Ok(out)
}

/// Re-weights the positives in case some were skipped; box-only positives
/// carry `box_share` of the positives' weight where there are both kinds.
fn reweight(examples: &mut [Example], box_only: &[bool], params: &TrainParams, positives: usize) {
    let n_box = examples
        .iter()
        .zip(box_only)
        .filter(|(e, &b)| b && e.truth.is_some())
        .count();
    let n_known = positives - n_box;
    let (known_w, box_w) = match params.examples.box_share {
        Some(share) if n_box > 0 && n_known > 0 => (
            params.examples.positive_share * (1.0 - share) / n_known as f64,
            params.examples.positive_share * share / n_box as f64,
        ),
        _ => {
            let w = params.examples.positive_share / positives as f64;
            (w, w)
        }
    };
    for (e, &b) in examples.iter_mut().zip(box_only) {
        if e.truth.is_some() {
            e.weight = if b { box_w } else { known_w };
        }
    }
}

/// Each example's hard locations, to seed the next training of this
/// object on these images (a latent round, a cross-validation fold).
pub(super) fn remember_hard(examples: &[Example], cache: &PyramidCache) {
    let mut found: HashMap<HardKey, Vec<Location>> = HashMap::new();
    for ex in examples {
        let kept = found.entry(ex.key.clone()).or_default();
        for l in &ex.cache {
            if !kept.contains(l) {
                kept.push(*l);
            }
        }
    }
    cache.remember_hard(found);
}

/// An example's first cache of locations: its ground truth, the hard
/// locations an earlier training of the same object left for it (those
/// that are locations of this model: the template may have changed), then
/// the random seeds; each once.
fn first_cache(
    truth: Option<Location>,
    warm: Vec<Location>,
    seeds: Vec<Location>,
    locations: &[Location],
) -> Vec<Location> {
    let valid: std::collections::HashSet<Location> = if warm.is_empty() {
        Default::default()
    } else {
        locations.iter().copied().collect()
    };
    let mut out: Vec<Location> = Vec::with_capacity(1 + warm.len() + seeds.len());
    let chosen = truth
        .into_iter()
        .chain(warm.into_iter().filter(|l| valid.contains(l)))
        .chain(seeds);
    for l in chosen {
        if !out.contains(&l) {
            out.push(l);
        }
    }
    out
}
