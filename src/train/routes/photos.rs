//! Training from photographs with boxes (and masks where known): the
//! route of `train --coco`, which `mesh --photos` also takes with its
//! renders drawn over the photographs. Small-object scales where the
//! settings leave them open, background examples, optional mirrored
//! photographs, the structural SVM with latent boxes, then the box
//! correction by cross-validation.

use super::{RouteError, TrainSettings};
use crate::data::{load_image, Sample};
use crate::model::{BoxCorrection, Model};
use crate::train::box_correction::{self, HeldOut};
use crate::train::components::train_choosing_components;
use crate::train::ko8::Source;
use crate::train::mirror;
use crate::train::multiview::{MultiViewParams, Sources};
use crate::train::photo_augment::{self, is_crop, PhotoAugment};
use crate::train::views::View;
use crate::train::{train_model, PyramidCache, TrainError, TrainParams, TrainReport};
use crate::vision::hog::CELL_SIZE;
use crate::vision::image::ColorImage;
use std::collections::HashSet;
use std::path::PathBuf;
use std::sync::Arc;

/// Detection threshold of models trained without masked photographs of
/// the scene (views, box-only photographs): their objects, hidden more in
/// the photographs than any training crop, score lower (views only, 30
/// development photographs per object: mean AUC 0.728 at -0.75, 0.760 at
/// -1.0, the same at -1.25).
const VIEWS_THRESHOLD: f64 = -1.0;

/// Folds of `train --coco`'s box correction (`--box-folds`): LM-O,
/// box-only, learned cells: the windows on held-out photographs are 0.82-
/// 0.85 of the objects' boxes (docs/training.md).
pub const COCO_BOX_FOLDS: usize = 2;

/// CCCP rounds of each box-correction fold (`--box-fold-rounds`), which
/// starts from the full training's imputation of the box-only
/// photographs: LM-O glue, box-only, learned cells: the folds' trainings
/// took 515 of 813 s with the full training's two rounds each, 280 of
/// 585 s with none, the model's AUC the same (docs/training.md).
pub const COCO_BOX_FOLD_ROUNDS: usize = 0;

/// Background examples per photograph of `train --coco`
/// (`--background-regions`): LM-O, box-only, learned cells, the ape 0.509
/// -> 0.634 AUC with 4 (docs/training.md).
const COCO_BACKGROUND_REGIONS: usize = 4;

/// Whether `train --coco` mirrors its photographs (`--mirror-photos`):
/// LM-O box-only, learned cells, without background examples: ape 0.509
/// -> 0.535, duck 0.486 -> 0.569, at 2.8 times the training time; not
/// measured beside the background examples, so off by default.
pub const COCO_MIRROR: bool = false;

/// Full searches at most when [`crate::train::small_object_scales`]
/// applies (unless `--max-passes` says otherwise).
const SMALL_OBJECT_PASSES: usize = 15;

/// Locations per image a mining search reaches ([`BoxRoute::mining`]):
/// on the LM-O duck (mesh + boxes), where an exact search beat an
/// example's cached best, it did so among the first 256 locations in 97%
/// of the first round's searches (later rounds: 24 of 39, and 12 between
/// 1,024 and 4,096), of about 9,600 reached.
const MINING_BUDGET: usize = 1024;

/// The median of the boxes' longer sides (pixels).
fn median_longer(sizes: &[(f64, f64)]) -> f64 {
    let mut v: Vec<f64> = sizes.iter().map(|&(w, h)| w.max(h)).collect();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

/// The indices of fold `k` of `n` over `len` items: the k-th of n runs of
/// consecutive items, as even as they can be.
pub fn fold_range(k: usize, n: usize, len: usize) -> std::ops::Range<usize> {
    (k * len / n)..((k + 1) * len / n)
}

/// `params` with the threshold of `sources` unless one was given (by
/// `--threshold`, or a `--config` file that changes it).
pub(crate) fn params_for(params: &TrainParams, sources: &[Source], flag: bool) -> TrainParams {
    let mut p = params.clone();
    let explicit = flag || p.threshold != TrainParams::default().threshold;
    if !explicit && !sources.contains(&Source::Single) {
        p.threshold = VIEWS_THRESHOLD;
    }
    p
}

/// How [`train_photographs`] trains a COCO category: its sources, and the
/// `train --coco` options that shape it.
pub struct BoxRoute {
    pub sources: Vec<Source>,
    pub mirror_photos: bool,
    pub box_folds: usize,
    pub box_fold_rounds: usize,
    /// Most passes of each box-correction fold's training (and its
    /// mining); `None`: as many as the full training's.
    pub box_fold_passes: Option<usize>,
    /// Images the caller drew (renders over the photographs): they give
    /// no background examples, stay in every box-correction fold's
    /// training and are never held out.
    pub renders: Arc<HashSet<PathBuf>>,
    /// Every full search mines with a budget ([`TrainParams::mining_passes`],
    /// [`MINING_BUDGET`]) where the flags leave it open; the first that
    /// finds nothing ends the training, or is checked by an exact one with
    /// `--exact-check` ([`TrainParams::exact_check`]).
    pub mining: bool,
    /// Crops of the photographs' objects seen again at other sizes
    /// (the flags' `--augment*` over it).
    pub augment: PhotoAugment,
}

/// What [`train_photographs`] made.
pub struct PhotoTraining {
    pub model: Model,
    pub report: TrainReport,
    /// The samples as the last round trained on them (box-only ones with
    /// their imputed visibility and components; mirrored ones after their
    /// originals).
    pub trained: Vec<Sample>,
    /// What the box correction's fold models found on their held-out
    /// photographs (`None` without folds).
    pub held_out: Option<HeldOut>,
}

/// One category of photographs as `train --coco` trains it: the
/// small-object scales where the flags leave them open, background
/// examples, optional mirrored photographs, the structural SVM with latent
/// boxes, then the box correction by cross-validation. `params` are the
/// settings' (`settings` tells which the user set).
#[allow(clippy::too_many_arguments)]
pub fn train_photographs(
    cat: &str,
    loaded: &[Sample],
    extra_negatives: &[Sample],
    route: &BoxRoute,
    st: &TrainSettings,
    params: &TrainParams,
    mv: &MultiViewParams,
    cache: &PyramidCache,
    pb: &indicatif::ProgressBar,
) -> Result<PhotoTraining, RouteError> {
    let started = std::time::Instant::now();
    let sources = &route.sources;
    let mut params = photo_params(cat, loaded, route, st, params);
    let samples = if route.mirror_photos {
        pb.set_message(format!("{cat}: mirrored photographs"));
        let views = sources.contains(&Source::Views);
        mirror::with_mirrors(
            loaded,
            |a| !views || !a.mask_known,
            cache,
            &params.pyramid,
            &params.segmentation,
            pb,
        )
        .map_err(RouteError::input)?
    } else {
        loaded.to_vec()
    };
    let augment = st.augment.over(&route.augment);
    pb.set_message(format!("{cat}: crops"));
    let (samples, crops) =
        photo_augment::with_crops(&samples, &augment, &route.renders, cache, &params, pb)
            .map_err(RouteError::input)?;
    if !crops.is_empty() {
        eprintln!(
            "{cat}: {} crops of the photographs' objects (sizes x{:.2}..{:.2}, paste {}, occluded {})",
            crops.len(),
            augment.scale[0],
            augment.scale[1],
            augment.paste,
            augment.occluded
        );
        let mut renders = (*params.examples.renders).clone();
        renders.extend(crops.iter().cloned());
        params.examples.renders = Arc::new(renders);
    }
    let (mut model, report, imputed) = train_coco(
        cat,
        samples.clone(),
        extra_negatives,
        sources,
        cache,
        &params,
        mv,
        pb,
    )
    .map_err(RouteError::input)?;
    let trained = with_imputed(&samples, imputed, sources);
    let mut correction_seconds = None;
    let mut held_out = None;
    if route.box_folds >= 2 {
        let t = std::time::Instant::now();
        pb.set_message(format!("{cat}: box correction"));
        let (fitted, found) =
            fold_check(cat, &trained, extra_negatives, route, &params, mv, cache)?;
        if let (Some(auc), Some(p)) = (found.auc(), model.meta.provenance.as_object_mut()) {
            p.insert("held_out_auc".into(), serde_json::json!(auc));
        }
        held_out = Some(found);
        model.meta.box_correction = fitted;
        correction_seconds = Some(t.elapsed().as_secs_f64());
    }
    let seconds = started.elapsed().as_secs_f64();
    match correction_seconds {
        Some(c) => eprintln!(
            "{cat}: trained in {seconds:.0} s ({c:.0} s of it the box correction's {}-fold trainings)",
            route.box_folds
        ),
        None => eprintln!("{cat}: trained in {seconds:.0} s"),
    }
    if let Some(p) = model.meta.provenance.as_object_mut() {
        p.insert(
            "mirror_photos".into(),
            serde_json::Value::Bool(route.mirror_photos),
        );
        if augment.per_box > 0 {
            p.insert("photo_augment".into(), serde_json::json!(augment));
        }
    }
    Ok(PhotoTraining {
        model,
        report,
        trained,
        held_out,
    })
}

/// The training settings of [`train_photographs`] for `loaded`: the
/// route's sources, background examples (none from the route's renders),
/// and the small-object scales where the flags leave them open.
pub fn photo_params(
    cat: &str,
    loaded: &[Sample],
    route: &BoxRoute,
    st: &TrainSettings,
    params: &TrainParams,
) -> TrainParams {
    let mut params = params_for(params, &route.sources, st.threshold.is_some());
    if !route.renders.is_empty() {
        params.examples.renders = route.renders.clone();
    }
    if st.background_regions.is_none() && st.config.is_none() {
        params.examples.background_regions = COCO_BACKGROUND_REGIONS;
    }
    if !st.scales_set() {
        // The photographs' boxes set the scales, not the renders': a
        // render of another aspect (the LM-O glue end-on, its longer side
        // at the smallest box's) stretched the pyramid from 2.06 to 3.77
        // and the glue's training past 37 minutes; a render no level fits
        // is left out of training as any such box is.
        let sizes: Vec<(f64, f64)> = loaded
            .iter()
            .filter(|s| !route.renders.contains(&s.image))
            .filter_map(|s| s.annotation.as_ref())
            .map(|a| (a.bbox.2, a.bbox.3))
            .collect();
        if let Some(mut p) = crate::train::small_object_scales(&sizes, &params) {
            // Few, small photographs: training to convergence pays
            // (LM-O duck, 45 photographs with true masks: 5 passes
            // AUC 0.256, segmentation error 0.688; converged after
            // 13, 0.271 and 0.426; 93 s against 155 s).
            if st.max_passes.is_none() {
                p.solver.max_passes = SMALL_OBJECT_PASSES;
            }
            eprintln!(
                "{cat}: small objects: template scale {:.2} (about {:.0} cells along the median box's longer side), pyramid {:.2}..{:.2} at {} levels per octave, up to {} passes",
                p.template_scale,
                p.template_scale * median_longer(&sizes) / CELL_SIZE as f64,
                p.pyramid.min_scale,
                p.pyramid.max_scale,
                p.pyramid.levels_per_octave,
                p.solver.max_passes
            );
            params = p;
        }
    }
    if route.mining {
        if st.mining_passes.is_none() {
            params.solver.mining_passes = params.solver.max_passes;
        }
        if st.mining_budget.is_none() {
            params.solver.mining_budget = MINING_BUDGET;
        }
        params.solver.exact_check = st.exact_check;
    }
    params
}

/// The box correction's `route.box_folds`-fold cross-validation over the
/// photographs of `trained` (each box with the visibility and component
/// a full training imputed to it; the route's renders are never held
/// out): the correction fitted to the held-out detections, and what the
/// fold models found on their held-out photographs (its AUC is the
/// route's check of a training). `params` as [`photo_params`] gives them.
pub fn fold_check(
    cat: &str,
    trained: &[Sample],
    extra_negatives: &[Sample],
    route: &BoxRoute,
    params: &TrainParams,
    mv: &MultiViewParams,
    cache: &PyramidCache,
) -> Result<(Option<BoxCorrection>, HeldOut), RouteError> {
    // The folds start from the full training's imputation of the
    // box-only photographs.
    let fold_mv = MultiViewParams {
        latent_rounds: route.box_fold_rounds,
        boxes_imputed: true,
        ..mv.clone()
    };
    let params = &fold_params(params, route);
    // Crops stay out of the folds' held-out photographs, and train a fold
    // only with the photograph they were cut from.
    let mut always = (*route.renders).clone();
    always.extend(
        trained
            .iter()
            .filter(|s| is_crop(&s.image))
            .map(|s| s.image.clone()),
    );
    let (fitted, found) = box_correction::fit(trained, route.box_folds, &always, cache, |subset| {
        let subset = photo_augment::with_their_photographs(subset);
        let hidden = indicatif::ProgressBar::hidden();
        train_coco(
            cat,
            subset,
            extra_negatives,
            &route.sources,
            cache,
            params,
            &fold_mv,
            &hidden,
        )
        .map(|(m, _, _)| m)
    })
    .map_err(RouteError::input)?;
    match &fitted {
        Some(c) => eprintln!(
            "{cat}: box correction by {}-fold cross-validation over {} held-out detections: centre moved by ({:+.3}, {:+.3}) of the window, size x ({:.3}, {:.3})",
            route.box_folds, c.samples, c.dx, c.dy, c.sw, c.sh
        ),
        None => eprintln!(
            "{cat}: no box correction ({} held-out detections, {} needed)",
            found.offsets.len(),
            box_correction::MIN_SAMPLES
        ),
    }
    if let Some(auc) = found.auc() {
        eprintln!(
            "{cat}: held out by the folds: AUC {auc:.3} on {} photographs ({} objects)",
            found.photos(),
            found.objects()
        );
    }
    Ok((fitted, found))
}

/// The settings of each box-correction fold's training: `params` with
/// their passes (and mining passes) at most `route.box_fold_passes`.
fn fold_params(params: &TrainParams, route: &BoxRoute) -> TrainParams {
    let mut p = params.clone();
    if let Some(most) = route.box_fold_passes {
        p.solver.max_passes = p.solver.max_passes.min(most);
        p.solver.mining_passes = p.solver.mining_passes.min(most);
    }
    p
}

/// Whether `train_coco` trains `s` as a box-only photograph (latent
/// visibility).
fn is_box_only(s: &Sample, sources: &[Source]) -> bool {
    sources.contains(&Source::Boxes) && s.annotation.as_ref().is_some_and(|a| !a.mask_known)
}

/// `samples` with their box-only photographs replaced, in order, by
/// `imputed` (what `train_coco` returned for them); as they are where the
/// counts differ.
fn with_imputed(samples: &[Sample], imputed: Vec<Sample>, sources: &[Source]) -> Vec<Sample> {
    let boxes = samples.iter().filter(|s| is_box_only(s, sources)).count();
    if boxes != imputed.len() {
        return samples.to_vec();
    }
    let mut imputed = imputed.into_iter();
    samples
        .iter()
        .map(|s| match is_box_only(s, sources) {
            true => imputed.next().unwrap_or_else(|| s.clone()),
            false => s.clone(),
        })
        .collect()
}

/// One COCO category from its samples and `sources`: masked annotations
/// are views (`views`) or masked photographs (`single`, the default
/// without `views`), box-only ones train with latent visibility (`boxes`).
/// Also returns the box-only photographs as the last round trained on
/// them (imputed visibility and components).
#[allow(clippy::too_many_arguments)]
fn train_coco(
    cat: &str,
    samples: Vec<Sample>,
    extra_negatives: &[Sample],
    sources: &[Source],
    cache: &PyramidCache,
    params: &TrainParams,
    mv: &MultiViewParams,
    pb: &indicatif::ProgressBar,
) -> Result<(Model, TrainReport, Vec<Sample>), TrainError> {
    let as_views = sources.contains(&Source::Views);
    let use_boxes = sources.contains(&Source::Boxes);
    let mut fixed: Vec<Sample> = Vec::new();
    let mut views = Vec::new();
    let mut boxes = Vec::new();
    for s in samples {
        match &s.annotation {
            None => fixed.push(s),
            Some(a) if !a.mask_known => {
                if use_boxes {
                    boxes.push(s);
                }
            }
            Some(_) if as_views => views.push(View::from_sample(&s)?),
            Some(_) => fixed.push(s),
        }
    }
    fixed.extend(extra_negatives.iter().cloned());
    let backgrounds: Vec<Arc<ColorImage>> = if as_views {
        fixed
            .iter()
            .filter(|s| s.annotation.is_none())
            .take(20)
            .map(|s| load_image(&s.image).map(Arc::new))
            .collect::<Result<_, _>>()?
    } else {
        Vec::new()
    };
    if views.is_empty() && boxes.is_empty() {
        let refs: Vec<&Sample> = fixed.iter().collect();
        return train_model(cat, &refs, cache, params, pb).map(|(m, r)| (m, r, Vec::new()));
    }
    let src = Sources {
        fixed: fixed.iter().collect(),
        views,
        occluders: Vec::new(),
        backgrounds,
        boxes,
    };
    let (m, mut r) = train_choosing_components(cat, src, cache, params, mv, pb)?;
    eprintln!("{cat}: {}", round_times(&r.rounds));
    let imputed = std::mem::take(&mut r.imputed_boxes);
    Ok((m, r.rounds.pop().unwrap_or_default(), imputed))
}

/// Where each training round's time went: its passes and cutting-plane
/// iterations, and its seconds in full searches, cached searches and QPs.
fn round_times(rounds: &[TrainReport]) -> String {
    let each: Vec<String> = rounds
        .iter()
        .map(|r| {
            format!(
                "{} passes, {} iterations, {:.0} s (full {:.0}, cached {:.0}, qp {:.0})",
                r.passes, r.iterations, r.seconds, r.full_seconds, r.cached_seconds, r.qp_seconds
            )
        })
        .collect();
    format!("training rounds: {}", each.join("; "))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::Annotation;
    use crate::vision::mask::Mask;
    use std::path::PathBuf;

    #[test]
    fn box_folds_cover_every_photograph_once() {
        for len in [0, 1, 7, 30, 31] {
            for n in 2..5 {
                let mut seen = vec![0; len];
                for k in 0..n {
                    for i in fold_range(k, n, len) {
                        seen[i] += 1;
                    }
                }
                assert!(seen.iter().all(|&c| c == 1), "{len} {n}");
            }
        }
        assert_eq!(fold_range(0, 2, 30), 0..15);
        assert_eq!(fold_range(1, 2, 30), 15..30);
    }

    fn sample(id: &str, mask_known: Option<bool>, viewpoint: usize) -> Sample {
        Sample {
            image: PathBuf::from(format!("{id}.png")),
            id: id.into(),
            annotation: mask_known.map(|mask_known| Annotation {
                label: "glue".into(),
                bbox: (0.0, 0.0, 4.0, 4.0),
                visible: Mask::new(4, 4),
                viewpoint,
                mask_known,
            }),
        }
    }

    #[test]
    fn folds_get_the_imputed_box_photographs_in_order() {
        let samples = vec![
            sample("a", Some(false), 0),
            sample("neg", None, 0),
            sample("masked", Some(true), 0),
            sample("b", Some(false), 0),
        ];
        let imputed = vec![sample("a", Some(false), 1), sample("b", Some(false), 2)];
        let boxes = [Source::Boxes];
        let out = with_imputed(&samples, imputed.clone(), &boxes);
        let views: Vec<(String, Option<usize>)> = out
            .iter()
            .map(|s| (s.id.clone(), s.annotation.as_ref().map(|a| a.viewpoint)))
            .collect();
        assert_eq!(
            views,
            vec![
                ("a".into(), Some(1)),
                ("neg".into(), None),
                ("masked".into(), Some(0)),
                ("b".into(), Some(2)),
            ]
        );
        // Without box-only training, or where the counts differ, as given.
        let same = |out: Vec<Sample>| {
            out.iter()
                .all(|s| s.annotation.as_ref().is_none_or(|a| a.viewpoint == 0))
        };
        assert!(same(with_imputed(
            &samples,
            imputed.clone(),
            &[Source::Single]
        )));
        assert!(same(with_imputed(&samples, imputed[..1].to_vec(), &boxes)));
    }

    #[test]
    fn the_photographs_boxes_set_the_scales_not_the_renders() {
        let settings = TrainSettings::default();
        let boxed = |id: &str, w: f64, h: f64| {
            let mut s = sample(id, Some(false), 0);
            if let Some(a) = s.annotation.as_mut() {
                a.bbox = (0.0, 0.0, w, h);
            }
            s
        };
        // Small photographed boxes, and thin renders at their longer side
        // (an object seen end-on).
        let photos: Vec<Sample> = (0..5)
            .map(|i| boxed(&format!("p{i}"), 40.0, 36.0))
            .collect();
        let renders: Vec<Sample> = (0..5).map(|i| boxed(&format!("r{i}"), 30.0, 8.0)).collect();
        let all: Vec<Sample> = photos.iter().chain(&renders).cloned().collect();
        let route = |renders: &[Sample]| BoxRoute {
            sources: vec![Source::Single, Source::Boxes],
            mirror_photos: false,
            box_folds: 0,
            box_fold_rounds: 0,
            box_fold_passes: None,
            renders: Arc::new(renders.iter().map(|s| s.image.clone()).collect()),
            mining: true,
            augment: PhotoAugment::default(),
        };
        let base = TrainParams::default();
        let with = photo_params("glue", &all, &route(&renders), &settings, &base);
        let alone = photo_params("glue", &photos, &route(&[]), &settings, &base);
        assert_eq!(with.pyramid.max_scale, alone.pyramid.max_scale);
        assert_eq!(with.template_scale, alone.template_scale);
        // Counted as photographs, the renders stretch the pyramid.
        let counted = photo_params("glue", &all, &route(&[]), &settings, &base);
        assert!(
            counted.pyramid.max_scale > alone.pyramid.max_scale,
            "{} {}",
            counted.pyramid.max_scale,
            alone.pyramid.max_scale
        );
        // Mining where the flags leave it open.
        assert_eq!(with.solver.mining_budget, MINING_BUDGET);
    }

    #[test]
    fn the_folds_train_at_most_their_passes() {
        let route = |most: Option<usize>| BoxRoute {
            sources: vec![Source::Single, Source::Boxes],
            mirror_photos: false,
            box_folds: 2,
            box_fold_rounds: 0,
            box_fold_passes: most,
            renders: Default::default(),
            mining: true,
            augment: PhotoAugment::default(),
        };
        let mut full = TrainParams::default();
        full.solver.max_passes = 15;
        full.solver.mining_passes = 15;
        let capped = fold_params(&full, &route(Some(8)));
        assert_eq!(
            (capped.solver.max_passes, capped.solver.mining_passes),
            (8, 8)
        );
        // Never more than the full training's.
        let loose = fold_params(&full, &route(Some(30)));
        assert_eq!(
            (loose.solver.max_passes, loose.solver.mining_passes),
            (15, 15)
        );
        let same = fold_params(&full, &route(None));
        assert_eq!(
            (same.solver.max_passes, same.solver.mining_passes),
            (15, 15)
        );
        assert_eq!(same.template_scale, full.template_scale);
    }
}
