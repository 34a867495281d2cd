//! How many view components an object gets, by cross-validation over its
//! views: each fold trains from the other views (as `train_sources` does),
//! and is scored on photographs made from its own held-out views (occluded,
//! half on clutter, as training makes them) among negatives made from the
//! same held-out views with the object painted over. The number of
//! components with the best mean area under recall against false positives
//! per image wins; a smaller number wins ties within `TIE`.

use std::sync::Arc;

use indicatif::ProgressBar;

use super::multiview::{train_sources, ComponentsCv, MultiViewParams, MultiViewReport, Sources};
use super::views::{augment_view, background_negative, View};
use super::{PyramidCache, TrainError, TrainParams};
use crate::eval::bop_detect::auc_curve;
use crate::model::Model;
use crate::pipeline::{detect_image, DetectOptions, MaskMode};
use crate::vision::detect::box_iou;
use crate::vision::image::ColorImage;
use crate::vision::rng::SplitMix64;

/// A larger number of components must beat a smaller one by more than
/// this mean AUC.
pub const TIE: f64 = 0.01;

/// Test photographs made from each held-out view.
const TESTS_PER_VIEW: usize = 2;

/// Trains the model of `label` from `src`, its number of view components
/// chosen among `mv.choose_from` by cross-validation over the views
/// ([`choose_components`]) when there are several and views to choose
/// with; else with `mv.components` ([`train_sources`]).
pub fn train_choosing_components(
    label: &str,
    src: Sources,
    cache: &PyramidCache,
    params: &TrainParams,
    mv: &MultiViewParams,
    progress: &ProgressBar,
) -> Result<(Model, MultiViewReport), TrainError> {
    if mv.choose_from.len() < 2 || src.views.is_empty() {
        return train_sources(label, src, cache, params, mv, progress);
    }
    mv.validate()?;
    let cv = choose_components(label, &src, cache, params, mv, progress)?;
    let chosen = MultiViewParams {
        components: cv.chosen,
        ..mv.clone()
    };
    let (model, mut report) = train_sources(label, src, cache, params, &chosen, progress)?;
    report.components_cv = Some(cv);
    Ok((model, report))
}

/// A held-out test photograph: the image and its object's box, if any.
struct TestImage {
    image: ColorImage,
    truth: Option<(f64, f64, f64, f64)>,
}

/// The test photographs of the views `held`.
fn test_images(
    held: &[&View],
    backgrounds: &[Arc<ColorImage>],
    occluders: &[&View],
    mv: &MultiViewParams,
) -> Result<Vec<TestImage>, TrainError> {
    let mut out = Vec::new();
    for (i, v) in held.iter().enumerate() {
        // Seeds of their own: never the training photographs' crops.
        let mut rng = SplitMix64::new(mv.augment.seed ^ 0x5EED_CAFE ^ ((i as u64) << 20));
        for _ in 0..TESTS_PER_VIEW {
            let a = augment_view(
                v,
                false,
                false,
                occluders,
                backgrounds,
                &mv.augment,
                &mut rng,
            )?;
            out.push(TestImage {
                image: a.image,
                truth: Some(a.bbox),
            });
        }
        if let Some(bg) = backgrounds.get(rng.range_usize(0, backgrounds.len().max(1))) {
            out.push(TestImage {
                image: background_negative(v, bg, &mut rng)?,
                truth: None,
            });
        }
    }
    Ok(out)
}

/// The AUC of `model` on `tests` (20 detections per photograph, a
/// detection is true when it overlaps its photograph's box by half and no
/// earlier one did).
fn score(model: &Model, tests: &[TestImage]) -> Result<f64, TrainError> {
    let opts = DetectOptions {
        max_detections: Some(20),
        masks: MaskMode::None,
        ..DetectOptions::default()
    };
    let mut scored = Vec::new();
    let mut positives = 0;
    for t in tests {
        let r = detect_image(&t.image, &[model], &opts)?;
        let mut found = false;
        positives += usize::from(t.truth.is_some());
        for d in &r.detections {
            let b = (d.bbox.x, d.bbox.y, d.bbox.width, d.bbox.height);
            let hit = !found && t.truth.is_some_and(|g| box_iou(b, g) >= 0.5);
            found |= hit;
            scored.push((d.score, hit));
        }
    }
    Ok(auc_curve(scored, positives, tests.len()).0)
}

/// The number of components among `mv.choose_from` (each capped at the
/// training views of a fold) that cross-validates best over `mv.cv_folds`
/// folds of `src`'s views (view `i` is held out in fold `i % folds`: the views
/// circle the object, so a held-out view lies between training ones).
pub fn choose_components(
    label: &str,
    src: &Sources,
    cache: &PyramidCache,
    params: &TrainParams,
    mv: &MultiViewParams,
    progress: &ProgressBar,
) -> Result<ComponentsCv, TrainError> {
    let (candidates, folds) = (&mv.choose_from, mv.cv_folds);
    let n = src.views.len();
    if folds < 2 || n < folds {
        return Err(TrainError::NoData(format!(
            "choosing components by cross-validation needs at least 2 folds and a view per fold ({n} views, {folds} folds)"
        )));
    }
    let mut candidates: Vec<usize> = candidates.iter().copied().filter(|&k| k > 0).collect();
    candidates.sort_unstable();
    candidates.dedup();
    if candidates.is_empty() {
        return Err(TrainError::NoData(
            "no number of components to choose from".into(),
        ));
    }
    let occluders: Vec<&View> = src.occluders.iter().collect();
    let mut per_fold: Vec<Vec<f64>> = vec![Vec::new(); candidates.len()];
    for f in 0..folds {
        let mut train: Vec<&View> = Vec::new();
        let mut held: Vec<&View> = Vec::new();
        for (i, v) in src.views.iter().enumerate() {
            if i % folds == f {
                held.push(v);
            } else {
                train.push(v);
            }
        }
        let tests = test_images(&held, &src.backgrounds, &occluders, mv)?;
        for (c, &k) in candidates.iter().enumerate() {
            progress.set_message(format!("{label}: components {k}, fold {}/{folds}", f + 1));
            let fold_src = Sources {
                fixed: src.fixed.clone(),
                views: train.iter().map(|v| (*v).clone()).collect(),
                occluders: src.occluders.clone(),
                backgrounds: src.backgrounds.clone(),
                boxes: Vec::new(),
            };
            let fold_mv = MultiViewParams {
                components: k.min(train.len()),
                choose_from: Vec::new(),
                latent_rounds: 0,
                ..mv.clone()
            };
            let (model, _) = train_sources(label, fold_src, cache, params, &fold_mv, progress)?;
            per_fold[c].push(score(&model, &tests)?);
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let mut chosen = candidates[0];
    let mut best = mean(&per_fold[0]);
    for (c, &k) in candidates.iter().enumerate().skip(1) {
        let m = mean(&per_fold[c]);
        if m > best + TIE {
            chosen = k;
            best = m;
        }
    }
    Ok(ComponentsCv {
        folds,
        candidates: candidates
            .iter()
            .zip(&per_fold)
            .map(|(&k, v)| (k, mean(v), v.clone()))
            .collect(),
        chosen,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::mask::Mask;

    /// A view of a textured `bw x bh` block (stripes `period` apart) at the
    /// middle of a 96x80 image of speckled grey.
    fn block_view(id: &str, bw: usize, bh: usize, period: usize) -> View {
        let (w, h) = (96, 80);
        let mut rng = SplitMix64::new(id.len() as u64 * 7 + period as u64);
        let mut data: Vec<f32> = (0..w * h * 3)
            .map(|_| 60.0 + 40.0 * rng.next_f64() as f32)
            .collect();
        let mut mask = Mask::new(w, h);
        let (x0, y0) = ((w - bw) / 2, (h - bh) / 2);
        for y in y0..y0 + bh {
            for x in x0..x0 + bw {
                mask.set(x, y, true);
                let v = if ((x + y) / period) % 2 == 0 {
                    230.0
                } else {
                    20.0
                };
                for c in 0..3 {
                    data[(y * w + x) * 3 + c] = v;
                }
            }
        }
        View {
            id: id.into(),
            image: Arc::new(ColorImage::new(w, h, data).unwrap()),
            mask,
            bbox: (x0 as f64, y0 as f64, bw as f64, bh as f64),
        }
    }

    fn scene(seed: u64) -> Arc<ColorImage> {
        let mut rng = SplitMix64::new(seed);
        let (w, h) = (160, 120);
        let data: Vec<f32> = (0..w * h * 3)
            .map(|i| (((i / 3) % 17) as f32 * 9.0 + 80.0 * rng.next_f64() as f32).min(255.0))
            .collect();
        Arc::new(ColorImage::new(w, h, data).unwrap())
    }

    #[test]
    fn cross_validation_scores_every_candidate_on_every_fold_and_learns() {
        let views: Vec<View> = (0..6)
            .map(|i| block_view(&format!("v{i}"), 40 + 2 * (i % 3), 32, 4))
            .collect();
        let src = Sources {
            fixed: Vec::new(),
            views,
            occluders: Vec::new(),
            backgrounds: (0..4).map(scene).collect(),
            boxes: Vec::new(),
        };
        let mut params = TrainParams::default();
        params.solver.max_passes = 2;
        let mv = MultiViewParams {
            augment: super::super::views::AugmentParams {
                per_view: 2,
                mirror: false,
                ..Default::default()
            },
            ..MultiViewParams::default()
        };
        let cache = PyramidCache::default();
        let pb = ProgressBar::hidden();
        let mv = MultiViewParams {
            choose_from: vec![2, 1, 2],
            cv_folds: 2,
            ..mv
        };
        let cv = choose_components("block", &src, &cache, &params, &mv, &pb).unwrap();
        assert_eq!(cv.folds, 2);
        let ks: Vec<usize> = cv.candidates.iter().map(|c| c.0).collect();
        assert_eq!(ks, vec![1, 2], "candidates sorted, duplicates dropped");
        for (_, mean, folds) in &cv.candidates {
            assert_eq!(folds.len(), 2);
            assert!((0.0..=1.0).contains(mean));
        }
        // The held-out blocks are found: far better than chance.
        assert!(cv.candidates[0].1 > 0.5, "{:?}", cv.candidates);
        assert!(ks.contains(&cv.chosen));
        // A fold needs a view.
        let seven = MultiViewParams { cv_folds: 7, ..mv };
        let err = choose_components("block", &src, &cache, &params, &seven, &pb);
        assert!(matches!(err, Err(TrainError::NoData(m)) if m.contains("6 views, 7 folds")));
    }
}
