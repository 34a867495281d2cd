//! One model per object from any mix of sources: masked occluded
//! photographs of one viewpoint (the single-pose part), unoccluded views
//! from around the object (grouped into components and augmented, see
//! [`super::views`]) and box-only photographs (visibility and component
//! latent, see [`super::latent`]).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use indicatif::ProgressBar;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::latent::{impute_samples, ImputeRound};
use super::views::{
    augment_view, background_negative, group_views, view_descriptor, view_distances, AugmentParams,
    View,
};
use super::{train_joint, PyramidCache, TrainError, TrainParams, TrainReport};
use crate::data::{Annotation, Sample};
use crate::model::Model;
use crate::vision::hog::CELL_SIZE;
use crate::vision::image::ColorImage;
use crate::vision::pyramid::FeaturePyramid;
use crate::vision::rng::SplitMix64;

/// Settings of training from views and boxes; saved in the provenance.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MultiViewParams {
    /// Components the views are grouped into (capped at the number of
    /// views).
    pub components: usize,
    /// Numbers of components to choose from by cross-validation over the
    /// views (`train::components`); empty: `components`.
    pub choose_from: Vec<usize>,
    /// Folds of that cross-validation.
    pub cv_folds: usize,
    pub augment: AugmentParams,
    /// CCCP rounds for box-only photographs: each imputes their
    /// visibility and component under the current model and retrains.
    pub latent_rounds: usize,
    /// Least box overlap of an imputed location with the true box.
    pub min_iou: f64,
    /// Whether a box's visible cells are imputed (latent) or the whole box
    /// is taken as visible (only its component is imputed).
    pub latent_visibility: bool,
    /// The box-only photographs already carry an imputation (another
    /// training's, [`MultiViewReport::imputed_boxes`]): round 0 trains
    /// with their visibility and components instead of every box visible
    /// in components by aspect.
    pub boxes_imputed: bool,
}

impl Default for MultiViewParams {
    fn default() -> Self {
        Self {
            // One component measured best from 25 views (views only, 30
            // development photographs of cup, shaker, scissors: mean AUC
            // 0.649 with one, 0.582 with three).
            components: 1,
            choose_from: Vec::new(),
            cv_folds: 3,
            augment: AugmentParams::default(),
            latent_rounds: 2,
            min_iou: 0.6,
            latent_visibility: true,
            boxes_imputed: false,
        }
    }
}

impl MultiViewParams {
    pub fn validate(&self) -> Result<(), TrainError> {
        if self.components == 0 {
            return Err(TrainError::NoData(
                "invalid setting: components must be >= 1".into(),
            ));
        }
        if self.choose_from.contains(&0) {
            return Err(TrainError::NoData(
                "invalid setting: every number of components to choose from must be >= 1".into(),
            ));
        }
        if self.choose_from.len() > 1 && !(2..=10).contains(&self.cv_folds) {
            return Err(TrainError::NoData(
                "invalid setting: cv_folds must be in 2..10".into(),
            ));
        }
        if !(0.3..=0.95).contains(&self.min_iou) {
            return Err(TrainError::NoData(
                "invalid setting: min_iou must be in 0.3..0.95".into(),
            ));
        }
        self.augment.validate()
    }
}

/// What training from several sources did, besides the SVM's own report.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct MultiViewReport {
    /// Each view component's views (representative first).
    pub components: Vec<Vec<String>>,
    /// Photographs made from the views, and negatives made from them.
    pub view_positives: usize,
    pub view_negatives: usize,
    /// Mean share of a view photograph's object hidden by its occluder.
    pub mean_hidden: f64,
    pub box_photographs: usize,
    pub imputation: Vec<ImputeRound>,
    /// Seconds making the view photographs and their pyramids.
    pub augment_seconds: f64,
    /// The cross-validation that chose the number of components, if one did.
    pub components_cv: Option<ComponentsCv>,
    /// Every round's SVM report (the last one is the model's).
    pub rounds: Vec<TrainReport>,
    /// The box-only photographs as the last round trained on them (their
    /// imputed visibility and components), in the order given.
    #[serde(skip)]
    pub imputed_boxes: Vec<Sample>,
}

/// The training inputs of one object.
pub struct Sources<'a> {
    /// Samples with known masks (positives of viewpoint 0.. and negatives).
    pub fixed: Vec<&'a Sample>,
    /// The object's unoccluded views.
    pub views: Vec<View>,
    /// Other objects' views: occluders.
    pub occluders: Vec<View>,
    /// Scenes for background patches and view negatives.
    pub backgrounds: Vec<Arc<ColorImage>>,
    /// Box-only photographs of the object.
    pub boxes: Vec<Sample>,
}

/// The views' components: `(assignment per view, medoid-first names per
/// component)`.
pub fn view_components(
    views: &[View],
    k: usize,
    mirror: bool,
    params: &TrainParams,
) -> (Vec<usize>, Vec<Vec<String>>) {
    let mut ws: Vec<f64> = views.iter().map(|v| v.bbox.2).collect();
    let mut hs: Vec<f64> = views.iter().map(|v| v.bbox.3).collect();
    ws.sort_by(f64::total_cmp);
    hs.sort_by(f64::total_cmp);
    let s = params.template_scale / CELL_SIZE as f64;
    let cols = ((ws[ws.len() / 2] * s).round() as usize).clamp(2, 24);
    let rows = ((hs[hs.len() / 2] * s).round() as usize).clamp(2, 24);
    let desc: Vec<Vec<f32>> = views
        .iter()
        .map(|v| view_descriptor(v, rows, cols, false))
        .collect();
    let aspects: Vec<f64> = views.iter().map(|v| v.bbox.2 / v.bbox.3).collect();
    let mut dist = view_distances(&desc, &aspects);
    if mirror {
        // A view and the mirror image of another are as alike as they look.
        let mirrored: Vec<Vec<f32>> = views
            .iter()
            .map(|v| view_descriptor(v, rows, cols, true))
            .collect();
        for (i, row) in dist.iter_mut().enumerate() {
            for (j, d) in row.iter_mut().enumerate() {
                if i != j {
                    let cos: f32 = desc[i].iter().zip(&mirrored[j]).map(|(a, b)| a * b).sum();
                    let dm = (1.0 - f64::from(cos)) + (aspects[i].ln() - aspects[j].ln()).abs();
                    *d = d.min(dm);
                }
            }
        }
    }
    let assign = group_views(&dist, k);
    let n_comp = assign.iter().max().map_or(0, |m| m + 1);
    let names = (0..n_comp)
        .map(|c| {
            let members: Vec<usize> = (0..views.len()).filter(|&i| assign[i] == c).collect();
            let medoid = members
                .iter()
                .copied()
                .min_by(|&a, &b| {
                    let sa: f64 = members.iter().map(|&j| dist[a][j]).sum();
                    let sb: f64 = members.iter().map(|&j| dist[b][j]).sum();
                    sa.total_cmp(&sb)
                })
                .unwrap_or(0);
            std::iter::once(medoid)
                .chain(members.iter().copied().filter(|&m| m != medoid))
                .map(|i| views[i].id.clone())
                .collect()
        })
        .collect();
    (assign, names)
}

/// Box-only photographs alone: their boxes of `label` grouped into at most
/// `k` components of equal size by aspect ratio (height over width), the
/// initialisation of a mixture of DPM (Felzenszwalb et al. 2010); each
/// component's template takes its boxes' median shape and the latent
/// rounds reassign the boxes. Sets every box's viewpoint; returns each
/// component's name (its range of aspect ratios).
pub fn aspect_components(boxes: &mut [Sample], label: &str, k: usize) -> Vec<Vec<String>> {
    let mut order: Vec<(f64, usize)> = boxes
        .iter()
        .enumerate()
        .filter_map(|(i, s)| {
            let a = s.annotation.as_ref().filter(|a| a.label == label)?;
            let aspect = a.bbox.3 / a.bbox.2;
            aspect.is_finite().then_some((aspect, i))
        })
        .collect();
    order.sort_by(|x, y| x.0.total_cmp(&y.0));
    let k = k.clamp(1, order.len().max(1));
    let mut names = Vec::with_capacity(k);
    for c in 0..k {
        let group = &order[c * order.len() / k..(c + 1) * order.len() / k];
        for &(_, i) in group {
            if let Some(a) = boxes[i].annotation.as_mut() {
                a.viewpoint = c;
            }
        }
        let (lo, hi) = (
            group.first().map_or(0.0, |g| g.0),
            group.last().map_or(0.0, |g| g.0),
        );
        names.push(vec![format!("boxes, height/width {lo:.2}-{hi:.2}")]);
    }
    names
}

/// The photographs made from the views (positives of components
/// `offset..`) and the view negatives, their pyramids put in `cache`.
#[allow(clippy::too_many_arguments)]
fn view_samples(
    label: &str,
    src: &Sources,
    assign: &[usize],
    offset: usize,
    params: &TrainParams,
    mv: &MultiViewParams,
    cache: &PyramidCache,
    report: &mut MultiViewReport,
    progress: &ProgressBar,
) -> Result<Vec<Sample>, TrainError> {
    let a = &mv.augment;
    let occluders: Vec<&View> = src.occluders.iter().collect();
    let mirrors: &[bool] = if a.mirror { &[false, true] } else { &[false] };
    let mut jobs: Vec<(usize, bool, usize)> = Vec::new();
    for i in 0..src.views.len() {
        for &m in mirrors {
            for j in 0..a.per_view {
                jobs.push((i, m, j));
            }
        }
    }
    progress.set_length(jobs.len() as u64);
    progress.set_position(0);
    progress.set_message(format!("{label}: view photographs"));
    let made: Vec<(Sample, f64)> = jobs
        .par_iter()
        .map(|&(i, m, j)| {
            let v = &src.views[i];
            let mut rng = SplitMix64::new(
                a.seed ^ (i as u64).wrapping_mul(0x9E37_79B9) ^ ((j as u64) << 32) ^ u64::from(m),
            );
            let aug = augment_view(v, m, j == 0, &occluders, &src.backgrounds, a, &mut rng)?;
            let pyr = FeaturePyramid::build(&aug.image, &params.pyramid, &params.segmentation)?;
            let path = PathBuf::from(format!(
                "{label}/views/{}#{j}{}",
                v.id,
                if m { "m" } else { "" }
            ));
            cache.insert(path.clone(), pyr);
            progress.inc(1);
            Ok((
                Sample {
                    id: format!("{}#{j}{}", v.id, if m { "m" } else { "" }),
                    image: path,
                    annotation: Some(Annotation {
                        label: label.to_string(),
                        bbox: aug.bbox,
                        visible: aug.visible,
                        viewpoint: offset + assign[i],
                        mask_known: true,
                    }),
                },
                aug.hidden,
            ))
        })
        .collect::<Result<_, TrainError>>()?;
    report.view_positives = made.len();
    report.mean_hidden = made.iter().map(|(_, h)| h).sum::<f64>() / made.len().max(1) as f64;
    let mut out: Vec<Sample> = made.into_iter().map(|(s, _)| s).collect();
    if a.view_negatives && !src.backgrounds.is_empty() {
        let negs: Vec<Sample> = src
            .views
            .par_iter()
            .enumerate()
            .map(|(i, v)| {
                let mut rng = SplitMix64::new(a.seed.wrapping_add(1000 + i as u64));
                let bg = &src.backgrounds[i % src.backgrounds.len()];
                let img = background_negative(v, bg, &mut rng)?;
                let pyr = FeaturePyramid::build(&img, &params.pyramid, &params.segmentation)?;
                let path = PathBuf::from(format!("{label}/views/{}#background", v.id));
                cache.insert(path.clone(), pyr);
                Ok(Sample {
                    id: format!("{}#background", v.id),
                    image: path,
                    annotation: None,
                })
            })
            .collect::<Result<_, TrainError>>()?;
        report.view_negatives = negs.len();
        out.extend(negs);
    }
    Ok(out)
}

/// The figures of a choice of the number of components by
/// cross-validation ([`super::components`]); saved in the model's
/// provenance.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct ComponentsCv {
    pub folds: usize,
    /// Each candidate with its mean AUC over the folds and per fold.
    pub candidates: Vec<(usize, f64, Vec<f64>)>,
    pub chosen: usize,
}

/// Trains the model of `label` from `src` with `mv.components` view
/// components (see the module's notes; choosing their number among
/// `mv.choose_from` by cross-validation is
/// [`super::components::train_choosing_components`]).
pub fn train_sources(
    label: &str,
    src: Sources,
    cache: &PyramidCache,
    params: &TrainParams,
    mv: &MultiViewParams,
    progress: &ProgressBar,
) -> Result<(Model, MultiViewReport), TrainError> {
    mv.validate()?;
    let mut report = MultiViewReport::default();
    let ours = |s: &Sample| s.annotation.as_ref().is_some_and(|a| a.label == label);
    // Components of the masked photographs come first.
    let offset = src
        .fixed
        .iter()
        .filter(|s| ours(s))
        .filter_map(|s| s.annotation.as_ref().map(|a| a.viewpoint + 1))
        .max()
        .unwrap_or(0);
    let mut component_views: Vec<Vec<String>> = vec![vec!["single-pose".to_string()]; offset];
    let mut made = Vec::new();
    if !src.views.is_empty() {
        let t = Instant::now();
        let (assign, names) = view_components(&src.views, mv.components, mv.augment.mirror, params);
        report.components = names.clone();
        component_views.extend(names);
        made = view_samples(
            label,
            &src,
            &assign,
            offset,
            params,
            mv,
            cache,
            &mut report,
            progress,
        )?;
        report.augment_seconds = t.elapsed().as_secs_f64();
    }
    let mut boxes = src.boxes;
    report.box_photographs = boxes.len();
    let known: Vec<&Sample> = src.fixed.iter().copied().chain(made.iter()).collect();
    let has_known_positive = known.iter().any(|s| ours(s));
    if !has_known_positive && mv.components > 1 && !mv.boxes_imputed {
        let names = aspect_components(&mut boxes, label, mv.components);
        report.components = names.clone();
        component_views.extend(names);
    }
    if !boxes.is_empty() {
        let refs: Vec<&Sample> = boxes.iter().collect();
        cache.fill(&refs, &params.pyramid, &params.segmentation, progress)?;
    }
    // Round 0: the masked data alone, or (boxes only) every box as visible.
    let mut model = if has_known_positive {
        let (m, r) = train_joint(label, &[label], &known, cache, params, progress)?;
        report.rounds.push(r);
        m
    } else {
        if component_views.is_empty() {
            component_views.push(vec!["boxes".to_string()]);
        }
        let all: Vec<&Sample> = known.iter().copied().chain(boxes.iter()).collect();
        let (m, r) = train_joint(label, &[label], &all, cache, params, progress)?;
        report.rounds.push(r);
        m
    };
    // Box-only photographs go to the view components where there are
    // any: the masked photographs' components keep their exact masks
    // (with the boxes imputed into the single-pose component too, the cup's
    // segmentation error on its own single-pose photographs rose from
    // 0.152 to 0.189 while 29 of its 30 box photographs went there).
    let first = if src.views.is_empty() { 0 } else { offset };
    if !boxes.is_empty() {
        for _ in 0..mv.latent_rounds {
            let before: Vec<Option<usize>> = boxes
                .iter()
                .map(|s| s.annotation.as_ref().map(|a| a.viewpoint))
                .collect();
            let round = impute_samples(
                &model,
                label,
                first,
                &mut boxes,
                cache,
                mv.min_iou,
                mv.latent_visibility,
            )?;
            progress.set_message(format!(
                "{label}: imputed {} boxes, {} component changes, {:.2} visible",
                round.boxes, round.component_changes, round.mean_visible
            ));
            report.imputation.push(round);
            // A component left without a box would have no template: the
            // boxes keep their components then (their visibility is still
            // the imputed one).
            let n_components = model.meta.viewpoints.len();
            let mut used = vec![false; n_components];
            for a in known
                .iter()
                .copied()
                .chain(boxes.iter())
                .filter_map(|s| s.annotation.as_ref().filter(|a| a.label == label))
            {
                if let Some(u) = used.get_mut(a.viewpoint) {
                    *u = true;
                }
            }
            if used.contains(&false) {
                for (s, v) in boxes.iter_mut().zip(&before) {
                    if let (Some(a), Some(v)) = (s.annotation.as_mut(), v) {
                        a.viewpoint = *v;
                    }
                }
            }
            let all: Vec<&Sample> = known.iter().copied().chain(boxes.iter()).collect();
            let (m, r) = train_joint(label, &[label], &all, cache, params, progress)?;
            report.rounds.push(r);
            model = m;
        }
    }
    report.imputed_boxes = boxes;
    for (vm, names) in model.meta.viewpoints.iter_mut().zip(&component_views) {
        vm.views = names.clone();
    }
    if let Some(obj) = model.meta.provenance.as_object_mut() {
        obj.insert(
            "multiview".into(),
            serde_json::json!({
                "params": mv,
                "components": report.components,
                "components_cv": report.components_cv,
                "view_positives": report.view_positives,
                "view_negatives": report.view_negatives,
                "mean_hidden": report.mean_hidden,
                "box_photographs": report.box_photographs,
                "imputation": report.imputation,
                "augment_seconds": report.augment_seconds,
                "round_seconds": report.rounds.iter().map(|r| r.seconds).collect::<Vec<_>>(),
            }),
        );
    }
    Ok((model, report))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::mask::Mask;

    /// A view of a textured block `bw x bh` at (20, 16) on a 96x80 image.
    fn block_view(id: &str, bw: usize, bh: usize, stripes_vertical: bool) -> View {
        let (w, h) = (96, 80);
        let mut data = vec![40.0f32; w * h * 3];
        let mut mask = Mask::new(w, h);
        for y in 16..16 + bh {
            for x in 20..20 + bw {
                mask.set(x, y, true);
                let t = if stripes_vertical { x } else { y };
                let v = if (t / 4) % 2 == 0 { 210.0 } else { 90.0 };
                for c in 0..3 {
                    data[(y * w + x) * 3 + c] = v;
                }
            }
        }
        View {
            id: id.into(),
            image: Arc::new(ColorImage::new(w, h, data).unwrap()),
            mask,
            bbox: (20.0, 16.0, bw as f64, bh as f64),
        }
    }

    #[test]
    fn box_only_components_split_the_boxes_by_aspect() {
        let sample = |label: &str, w: f64, h: f64| Sample {
            image: PathBuf::from(format!("{label}-{w}x{h}.png")),
            id: format!("{label}-{w}x{h}"),
            annotation: Some(Annotation {
                label: label.into(),
                bbox: (0.0, 0.0, w, h),
                visible: Mask::new(4, 4),
                viewpoint: 0,
                mask_known: false,
            }),
        };
        // Tall bottles, bottles seen from above, and another object.
        let mut boxes = vec![
            sample("glue", 40.0, 84.0),
            sample("glue", 44.0, 42.0),
            sample("glue", 38.0, 80.0),
            sample("duck", 50.0, 20.0),
            sample("glue", 46.0, 50.0),
        ];
        let names = aspect_components(&mut boxes, "glue", 2);
        let view = |i: usize| boxes[i].annotation.as_ref().unwrap().viewpoint;
        assert_eq!(names.len(), 2);
        assert_eq!((view(1), view(4)), (0, 0));
        assert_eq!((view(0), view(2)), (1, 1));
        assert_eq!(view(3), 0, "another object's box is left alone");
        assert_eq!(names[0], vec!["boxes, height/width 0.95-1.09".to_string()]);
        // No more components than boxes.
        assert_eq!(aspect_components(&mut boxes, "glue", 9).len(), 4);
    }

    #[test]
    fn views_group_by_shape_and_appearance() {
        let views = vec![
            block_view("a1", 48, 24, true),
            block_view("b1", 24, 48, false),
            block_view("a2", 50, 24, true),
            block_view("b2", 24, 50, false),
            block_view("a3", 46, 22, true),
        ];
        let params = TrainParams::default();
        let (assign, names) = view_components(&views, 2, true, &params);
        assert_eq!(assign, vec![0, 1, 0, 1, 0]);
        assert_eq!(names.len(), 2);
        let mut a = names[0].clone();
        a.sort();
        assert_eq!(a, vec!["a1", "a2", "a3"]);
        // The representative comes first and belongs to its component.
        assert!(names[1][0].starts_with('b'));
        // One component: every view in it.
        let (assign, names) = view_components(&views, 1, true, &params);
        assert_eq!(assign, vec![0; 5]);
        assert_eq!(names[0].len(), 5);
    }
}
