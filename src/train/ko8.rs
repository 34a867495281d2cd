//! Training and cross-validation on the CMU_KO8 layout.
//!
//! Each object's model trains on its own annotated images, the negative
//! kitchen scenes, and a subset of the other objects' images as further
//! negatives (the cross-object protocol counts detections there as false
//! positives). Cross-validation splits every object's images into folds by
//! their sorted order; the models of fold `f` never see any fold-`f` image,
//! of any object, and are scored on all of them together.

use std::path::Path;
use std::sync::Arc;

use rayon::prelude::*;

use serde::{Deserialize, Serialize};

use super::components::train_choosing_components;
use super::multiview::{MultiViewParams, MultiViewReport, Sources};
use super::views::View;
use super::{progress_bar, train_model, PyramidCache, TrainError, TrainParams, TrainReport};
use crate::data::{load_image, Ko8, Sample};
use crate::eval::{mean_score, score_object, Evaluated, MeanScore, ObjectScore};
use crate::model::Model;
use crate::pipeline::{detect_pyramid, DetectOptions, DetectResponse, MaskMode};
use crate::vision::refine::PixelRefine;

/// Which images train each object's model besides its own.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct NegativeSet {
    /// Negative scenes used (the first ones in sorted order; all by default).
    pub scenes: usize,
    /// Images of each other object used as negatives (evenly spaced).
    pub per_other_object: usize,
}

impl Default for NegativeSet {
    fn default() -> Self {
        Self {
            scenes: 100,
            per_other_object: 10,
        }
    }
}

/// The dataset read once: every object's annotated images and the negatives.
pub struct Ko8Data {
    pub objects: Vec<String>,
    /// Annotated images per object, sorted by id.
    pub images: Vec<Vec<Sample>>,
    pub negatives: Vec<Sample>,
    /// Multi-view part (empty unless [`Ko8Data::with_multiview`] read
    /// it): each object's unoccluded views and its box-only photographs.
    pub views: Vec<Vec<Sample>>,
    pub photos: Vec<Vec<Sample>>,
    pub skipped: Vec<String>,
}

impl Ko8Data {
    pub fn load(root: &Path, objects: &[String]) -> Result<Self, TrainError> {
        let ko8 = Ko8::open(root)?;
        let objects = if objects.is_empty() {
            ko8.objects()
        } else {
            objects.to_vec()
        };
        let mut images = Vec::new();
        let mut skipped = Vec::new();
        for o in &objects {
            let l = ko8.test_samples(o)?;
            skipped.extend(l.skipped);
            images.push(l.samples);
        }
        Ok(Self {
            objects,
            images,
            negatives: ko8.negatives()?,
            views: Vec::new(),
            photos: Vec::new(),
            skipped,
        })
    }

    /// Also reads the multi-view part (every object's views and box-only
    /// photographs), where the root has one.
    pub fn with_multiview(mut self, root: &Path) -> Result<Self, TrainError> {
        let ko8 = Ko8::open(root)?;
        if !ko8.has_multiple() {
            return Ok(self);
        }
        for o in &self.objects {
            let l = ko8.views(o)?;
            self.skipped.extend(l.skipped);
            self.views.push(l.samples);
            let l = ko8.box_photos(o)?;
            self.skipped.extend(l.skipped);
            self.photos.push(l.samples);
        }
        Ok(self)
    }

    /// Training images of object `oi`, leaving out fold `fold` of `folds`
    /// (`None`: all images).
    pub fn training_set(
        &self,
        oi: usize,
        fold: Option<(usize, usize)>,
        neg: &NegativeSet,
    ) -> Vec<&Sample> {
        let keep = |i: usize| fold.is_none_or(|(f, k)| i % k != f);
        let mut out: Vec<&Sample> = self.images[oi]
            .iter()
            .enumerate()
            .filter(|(i, _)| keep(*i))
            .map(|(_, s)| s)
            .collect();
        out.extend(self.negatives.iter().take(neg.scenes));
        for (oj, imgs) in self.images.iter().enumerate() {
            if oj == oi || neg.per_other_object == 0 {
                continue;
            }
            let pool: Vec<&Sample> = imgs
                .iter()
                .enumerate()
                .filter(|(i, _)| keep(*i))
                .map(|(_, s)| s)
                .collect();
            let step = (pool.len() as f64 / neg.per_other_object as f64).max(1.0);
            let mut t = 0.0;
            while (t as usize) < pool.len() {
                out.push(pool[t as usize]);
                t += step;
            }
        }
        out
    }

    /// The held-out images of fold `f` (all objects).
    pub fn fold_images(&self, fold: Option<(usize, usize)>) -> Vec<&Sample> {
        self.images
            .iter()
            .flat_map(|imgs| {
                imgs.iter()
                    .enumerate()
                    .filter(move |(i, _)| fold.is_none_or(|(f, k)| i % k == f))
                    .map(|(_, s)| s)
            })
            .collect()
    }
}

/// Trains one model per object; `fold` leaves a fold out.
pub fn train_objects(
    data: &Ko8Data,
    fold: Option<(usize, usize)>,
    params: &TrainParams,
    neg: &NegativeSet,
    cache: &PyramidCache,
) -> Result<Vec<(Model, TrainReport)>, TrainError> {
    let mut out = Vec::new();
    for (oi, o) in data.objects.iter().enumerate() {
        let set = data.training_set(oi, fold, neg);
        let pb = progress_bar(0, o);
        let r = train_model(o, &set, cache, params, &pb)?;
        pb.finish_and_clear();
        out.push(r);
    }
    Ok(out)
}

/// Where a model's training examples come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Source {
    /// Masked occluded photographs of one viewpoint (single-pose part).
    Single,
    /// Unoccluded views from around the object (multi-view part's train/).
    Views,
    /// Box-only photographs (multi-view part's development photographs).
    Boxes,
}

impl Source {
    /// `single`, `views` or `boxes`.
    pub fn parse(s: &str) -> Result<Self, String> {
        match s.trim() {
            "single" => Ok(Self::Single),
            "views" => Ok(Self::Views),
            "boxes" => Ok(Self::Boxes),
            other => Err(format!(
                "unknown source {other:?} (expected single, views or boxes)"
            )),
        }
    }
}

/// Every `step`-th sample (evenly spaced), at most `n`.
fn evenly(pool: &[Sample], n: usize) -> impl Iterator<Item = &Sample> {
    let step = (pool.len() as f64 / n.max(1) as f64).max(1.0);
    (0..n.min(pool.len())).map(move |i| &pool[((i as f64 * step) as usize).min(pool.len() - 1)])
}

/// Trains object `oi` from `sources` (see [`super::multiview`]): the
/// single-pose photographs with the usual negatives, the views (other
/// objects' views are occluders) and the box-only photographs.
#[allow(clippy::too_many_arguments)]
pub fn train_object_sources(
    data: &Ko8Data,
    oi: usize,
    sources: &[Source],
    params: &TrainParams,
    neg: &NegativeSet,
    mv: &MultiViewParams,
    cache: &PyramidCache,
    progress: &indicatif::ProgressBar,
) -> Result<(Model, MultiViewReport), TrainError> {
    let label = &data.objects[oi];
    let want = |s: Source| sources.contains(&s);
    let multi = !data.views.is_empty();
    if (want(Source::Views) || want(Source::Boxes)) && !multi {
        return Err(TrainError::NoData(
            "views and boxes need the multi-view part (multiple/) of CMU_KO8".into(),
        ));
    }
    let fixed: Vec<&Sample> = if want(Source::Single) {
        data.training_set(oi, None, neg)
    } else {
        data.negatives.iter().take(neg.scenes).collect()
    };
    // Other objects' multi-view images are not negatives: they are the
    // same tables, where this object often stands in the background (the
    // cup beside the thermos); training on them as negatives took the
    // cup's AUC from 0.787 to 0.529 on the development photographs.
    let views = if want(Source::Views) {
        data.views[oi]
            .par_iter()
            .map(View::from_sample)
            .collect::<Result<Vec<_>, _>>()?
    } else {
        Vec::new()
    };
    let occluders = if want(Source::Views) {
        data.objects
            .iter()
            .enumerate()
            .filter(|(oj, _)| *oj != oi)
            .flat_map(|(oj, _)| evenly(&data.views[oj], 3))
            .collect::<Vec<_>>()
            .par_iter()
            .map(|s| View::from_sample(s))
            .collect::<Result<Vec<_>, _>>()?
    } else {
        Vec::new()
    };
    let backgrounds = if want(Source::Views) {
        evenly(&data.negatives, 20)
            .collect::<Vec<_>>()
            .par_iter()
            .map(|s| load_image(&s.image).map(Arc::new))
            .collect::<Result<Vec<_>, _>>()?
    } else {
        Vec::new()
    };
    let boxes = if want(Source::Boxes) {
        data.photos[oi].clone()
    } else {
        Vec::new()
    };
    let src = Sources {
        fixed,
        views,
        occluders,
        backgrounds,
        boxes,
    };
    train_choosing_components(label, src, cache, params, mv, progress)
}

/// How detection runs in an evaluation.
#[derive(Clone, Copy, Debug, Default)]
pub struct EvalDetect {
    /// Detections kept per image (all models together).
    pub max_detections: usize,
    /// Overrides the models' own thresholds.
    pub threshold: Option<f64>,
    /// Overrides the models' pixel refinement settings.
    pub pixel: Option<PixelRefine>,
}

/// Detections of `models` on `images`, in the response shape of `/detect`
/// (both masks).
pub fn detect_all(
    images: &[&Sample],
    models: &[&Model],
    cache: &PyramidCache,
    how: EvalDetect,
) -> Result<Vec<DetectResponse>, TrainError> {
    let overridden: Vec<Model>;
    let models: Vec<&Model> = match how.pixel {
        Some(p) => {
            overridden = models
                .iter()
                .map(|m| {
                    let mut m = (*m).clone();
                    m.meta.detection.refine.pixel = p;
                    m
                })
                .collect();
            overridden.iter().collect()
        }
        None => models.to_vec(),
    };
    let models = &models[..];
    let opts = DetectOptions {
        max_detections: Some(how.max_detections),
        threshold: how.threshold,
        masks: MaskMode::Both,
        ..DetectOptions::default()
    };
    let pb = progress_bar(images.len() as u64, "detect");
    let out = images
        .par_iter()
        .map(|s| {
            let pyr = cache
                .get(&s.image)
                .ok_or_else(|| TrainError::NoData(format!("{}: no pyramid", s.image.display())))?;
            let r = detect_pyramid(&pyr, models, &opts)?;
            pb.inc(1);
            Ok(r)
        })
        .collect::<Result<Vec<_>, TrainError>>();
    pb.finish_and_clear();
    out
}

/// Figures of an evaluation.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Evaluation {
    pub objects: Vec<ObjectScore>,
    pub mean: MeanScore,
}

/// Scores responses against the images' truth.
pub fn score(data: &Ko8Data, images: &[&Sample], responses: &[DetectResponse]) -> Evaluation {
    let evaluated: Vec<Evaluated> = images
        .iter()
        .zip(responses)
        .map(|(s, r)| Evaluated {
            id: &s.id,
            truth: s.annotation.as_ref(),
            detections: &r.detections,
        })
        .collect();
    let objects: Vec<ObjectScore> = data
        .objects
        .iter()
        .map(|o| score_object(o, &evaluated))
        .collect();
    Evaluation {
        mean: mean_score(&objects),
        objects,
    }
}

/// The mean figures of responses with every detection scoring below
/// `threshold` dropped.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ThresholdScore {
    pub threshold: f64,
    pub mean: MeanScore,
}

/// Keeps the detections scoring at least `threshold`. For a threshold at or
/// above the one detection ran with, this is exactly what detection at that
/// threshold returns: suppression is greedy by score, so a kept detection
/// was only ever suppressed by higher-scoring ones, which are kept too.
pub fn above_threshold(responses: &[DetectResponse], threshold: f64) -> Vec<DetectResponse> {
    responses
        .iter()
        .map(|r| {
            let mut r = r.clone();
            r.detections.retain(|d| d.score >= threshold);
            r
        })
        .collect()
}

/// Scores the same responses at each threshold (see [`above_threshold`]).
pub fn threshold_sweep(
    data: &Ko8Data,
    images: &[&Sample],
    responses: &[DetectResponse],
    thresholds: &[f64],
) -> Vec<ThresholdScore> {
    thresholds
        .par_iter()
        .map(|&t| ThresholdScore {
            threshold: t,
            mean: score(data, images, &above_threshold(responses, t)).mean,
        })
        .collect()
}

/// What model selection maximises: the mean cross-object AUC, less a tenth
/// of the mean refined segmentation error.
pub fn selection_key(m: &MeanScore) -> f64 {
    m.auc_cross - 0.1 * m.seg_error_refined
}

/// The highest threshold whose key is within `tolerance` of the best one
/// (higher thresholds prune more, so detection is faster).
pub fn choose_threshold(sweep: &[ThresholdScore], tolerance: f64) -> Option<&ThresholdScore> {
    let best = sweep
        .iter()
        .map(|t| selection_key(&t.mean))
        .fold(f64::NEG_INFINITY, f64::max);
    sweep
        .iter()
        .filter(|t| selection_key(&t.mean) >= best - tolerance)
        .max_by(|a, b| a.threshold.total_cmp(&b.threshold))
}

/// Result of a cross-validation.
pub struct CrossValidation {
    pub evaluation: Evaluation,
    /// Every annotated image with the response of its fold's models.
    pub images: Vec<Sample>,
    pub responses: Vec<DetectResponse>,
    pub reports: Vec<Vec<TrainReport>>,
}

/// Where the models of each fold come from.
#[derive(Clone, Copy, Debug)]
pub enum FoldModels<'a> {
    /// Trained and dropped.
    Train,
    /// Trained and saved as `DIR/fold-F/<object>.safetensors`.
    TrainAndSave(&'a Path),
    /// Loaded from `DIR/fold-F/<object>.safetensors` (saved by an earlier run
    /// with the same number of folds), so detection settings can be compared
    /// without training again.
    Load(&'a Path),
}

/// The folder of fold `f`'s models.
pub fn fold_dir(dir: &Path, f: usize) -> std::path::PathBuf {
    dir.join(format!("fold-{f}"))
}

/// File in each fold folder of `cv --save-models` naming its fold and the
/// number of folds, so that a later check (`join`'s single-pose guard)
/// takes the same photographs out.
pub const FOLD_FILE: &str = "fold.json";

/// Which fold of how many a folder's models left out.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct FoldOf {
    pub fold: usize,
    pub folds: usize,
}

/// Writes [`FOLD_FILE`] into `dir`.
pub fn write_fold_file(dir: &Path, fold: FoldOf) -> Result<(), TrainError> {
    let p = dir.join(FOLD_FILE);
    let text = serde_json::to_string(&fold).map_err(|e| TrainError::Io {
        path: p.display().to_string(),
        source: std::io::Error::other(e),
    })?;
    std::fs::write(&p, text).map_err(|source| TrainError::Io {
        path: p.display().to_string(),
        source,
    })
}

/// The models of fold `f`, trained or loaded; trained with their
/// segmenters where `segmenter` gives the segmenters' settings and cache.
#[allow(clippy::too_many_arguments)]
fn fold_models(
    data: &Ko8Data,
    fold: (usize, usize),
    params: &TrainParams,
    neg: &NegativeSet,
    cache: &PyramidCache,
    source: FoldModels,
    segmenter: Option<(&TrainParams, &PyramidCache)>,
) -> Result<Vec<(Model, Option<TrainReport>)>, TrainError> {
    if let FoldModels::Load(dir) = source {
        return data
            .objects
            .iter()
            .enumerate()
            .map(|(oi, o)| {
                let p = fold_dir(dir, fold.0).join(format!("{o}.safetensors"));
                let m = Model::load(&p)?;
                // Models saved before shape models were learned get them
                // from the fold's own training images (what training
                // would have learned).
                let m = if m.shapes.iter().all(Option::is_none) {
                    let set = data.training_set(oi, Some(fold), neg);
                    let shapes = super::learn_shapes(&m, &set, Some(cache));
                    m.with_shapes(shapes)?
                } else {
                    m
                };
                Ok((m, None))
            })
            .collect();
    }
    let mut trained = train_objects(data, Some(fold), params, neg, cache)?;
    if let Some((sp, seg_cache)) = segmenter {
        let segs = train_objects(data, Some(fold), sp, neg, seg_cache)?;
        trained = crate::model::with_segmenters_kept(trained, segs)?;
    }
    if let FoldModels::TrainAndSave(dir) = source {
        let d = fold_dir(dir, fold.0);
        std::fs::create_dir_all(&d).map_err(|source| TrainError::Io {
            path: d.display().to_string(),
            source,
        })?;
        for (m, _) in &trained {
            m.save(&d.join(format!("{}.safetensors", m.meta.name)))?;
        }
        write_fold_file(
            &d,
            FoldOf {
                fold: fold.0,
                folds: fold.1,
            },
        )?;
    }
    Ok(trained.into_iter().map(|(m, r)| (m, Some(r))).collect())
}

/// `folds`-fold cross-validation of every object's model, over the folds
/// listed in `only` (all when empty).
#[allow(clippy::too_many_arguments)]
pub fn cross_validate(
    data: &Ko8Data,
    folds: usize,
    only: &[usize],
    params: &TrainParams,
    neg: &NegativeSet,
    cache: &PyramidCache,
    how: EvalDetect,
    source: FoldModels,
    segmenter: Option<&TrainParams>,
) -> Result<CrossValidation, TrainError> {
    let mut images: Vec<Sample> = Vec::new();
    let mut responses = Vec::new();
    let mut reports = Vec::new();
    // The segmenters' training pyramids (other cells than the models').
    let seg_cache = PyramidCache::default();
    let segmenter = segmenter.map(|p| (p, &seg_cache));
    for f in (0..folds).filter(|f| only.is_empty() || only.contains(f)) {
        let trained = fold_models(data, (f, folds), params, neg, cache, source, segmenter)?;
        let models: Vec<&Model> = trained.iter().map(|(m, _)| m).collect();
        let held = data.fold_images(Some((f, folds)));
        let pb = progress_bar(0, "pyramids");
        cache.fill(&held, &params.pyramid, &params.segmentation, &pb)?;
        pb.finish_and_clear();
        responses.extend(detect_all(&held, &models, cache, how)?);
        images.extend(held.into_iter().cloned());
        reports.push(trained.into_iter().filter_map(|(_, r)| r).collect());
    }
    let refs: Vec<&Sample> = images.iter().collect();
    let evaluation = score(data, &refs, &responses);
    Ok(CrossValidation {
        evaluation,
        images,
        responses,
        reports,
    })
}
