//! The routes of `sdhop-train mesh` that train beside other data: the
//! renders as views (`--from-views`) and renders with the user's box
//! photographs (`--photos`), with the checks that choose between them.

use super::mesh::{BoxXywh, MeshSettings, Object, PhotoVisibility};
use super::photos::{
    fold_check, photo_params, train_photographs, BoxRoute, PhotoTraining, COCO_BOX_FOLDS,
    COCO_BOX_FOLD_ROUNDS,
};
use super::RouteError;
use crate::data::Sample;
use crate::model::Model;
use crate::pose::mesh::Mesh;
use crate::train::mesh::{representative_rotations, without_boxes, ROTATIONS_PER_COMPONENT};
use crate::train::multiview::{train_sources, MultiViewParams, Sources};
use crate::train::photo_augment::PhotoAugment;
use crate::train::views::{OccluderKinds, View};
use crate::train::{PyramidCache, TrainParams, TrainReport};
use crate::vision::image::ColorImage;
use nalgebra::Vector3;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// A model of one object trained through the views route or `--photos`
/// route `boxes`, and each component's mean viewing direction and
/// representative (start) rotations.
pub struct RouteModel {
    pub model: Model,
    pub report: TrainReport,
    pub directions: Vec<[f64; 3]>,
    pub rotations: Vec<Vec<[f64; 4]>>,
}

/// `--from-views`: the clean `renders` (with their `poses`) become views
/// and train as photographed views do (`train::multiview`); a component's
/// direction is the mean of its views' directions (object towards camera,
/// mesh frame).
#[allow(clippy::too_many_arguments)]
pub fn train_from_views(
    object: &Object,
    renders: &[Sample],
    poses: &[crate::pose::Pose],
    negatives: &[Sample],
    backgrounds: &[ColorImage],
    args: &MeshSettings,
    cache: &PyramidCache,
    params: &TrainParams,
    pb: &indicatif::ProgressBar,
) -> Result<RouteModel, RouteError> {
    let views: Vec<View> = renders
        .iter()
        .map(View::from_sample)
        .collect::<Result<_, _>>()
        .map_err(RouteError::input)?;
    let mut mv = MultiViewParams {
        components: args.components,
        ..MultiViewParams::default()
    };
    mv.augment.per_view = args.per_view;
    // Any viewpoint can be rendered: a mirrored view is not needed, and
    // for an object without a plane of symmetry it would be wrong.
    mv.augment.mirror = false;
    mv.augment.occluded_share = args.occluded_share;
    mv.augment.occlusion = args.occlusion;
    mv.augment.kinds = OccluderKinds {
        objects: 0.0,
        patches: args.patch_occluders,
        smooth: 1.0 - args.patch_occluders,
    };
    mv.augment.seed = args.render_seed;
    mv.validate().map_err(RouteError::input)?;
    let scenes: Vec<Arc<ColorImage>> = backgrounds
        .iter()
        .take(BACKDROP_SCENES)
        .cloned()
        .map(Arc::new)
        .collect();
    let src = Sources {
        fixed: negatives.iter().collect(),
        views,
        occluders: Vec::new(),
        backgrounds: scenes,
        boxes: Vec::new(),
    };
    let (model, mut report) =
        train_sources(&object.name, src, cache, params, &mv, pb).map_err(RouteError::input)?;
    // Each render's component, by its id.
    let index: std::collections::HashMap<&str, usize> = renders
        .iter()
        .enumerate()
        .map(|(i, s)| (s.id.as_str(), i))
        .collect();
    let mut assign = vec![usize::MAX; renders.len()];
    for (c, names) in report.components.iter().enumerate() {
        for n in names {
            if let Some(&i) = index.get(n.as_str()) {
                assign[i] = c;
            }
        }
    }
    let k = report.components.len();
    let (directions, rotations) = component_viewpoints(&object.mesh, poses, &assign, k);
    Ok(RouteModel {
        model,
        report: report.rounds.pop().unwrap_or_default(),
        directions,
        rotations,
    })
}

/// Background photographs that views are set on (`--from-views`).
pub const BACKDROP_SCENES: usize = 20;

/// `--photos`: the box-only photographs as training samples.
pub struct PhotoSamples {
    pub file: PathBuf,
    /// One box of the object each, its visibility and component latent
    /// (to begin with: the whole box, component 0).
    pub boxes: Vec<Sample>,
    /// Photographs without the object (nor an ignored box of it).
    pub negatives: Vec<Sample>,
    /// Photographs left out, and why.
    pub skipped: Vec<String>,
    /// Every photograph and the boxes of the object in it (ignored ones
    /// too): the scenes route `boxes` draws the renders over.
    pub scenes: Vec<(PathBuf, Vec<BoxXywh>)>,
}

/// Longest side of a scene the renders are drawn over (larger photographs
/// are shrunk to it).
pub const SCENE_SIDE: usize = 640;

impl PhotoSamples {
    /// The photographs with the object taken out (see
    /// [`crate::train::mesh::without_boxes`]), at most [`SCENE_SIDE`]
    /// pixels on their longer side.
    pub fn scenes(&self) -> Result<Vec<ColorImage>, RouteError> {
        self.scenes
            .iter()
            .map(|(path, boxes)| {
                let img = crate::data::load_image(path).map_err(RouteError::input)?;
                let out = without_boxes(&img, boxes);
                let longer = out.width().max(out.height());
                if longer <= SCENE_SIDE {
                    return Ok(out);
                }
                let f = SCENE_SIDE as f64 / longer as f64;
                let (w, h) = (
                    ((out.width() as f64 * f).round() as usize).max(1),
                    ((out.height() as f64 * f).round() as usize).max(1),
                );
                out.resize_area(w, h).map_err(RouteError::input)
            })
            .collect()
    }
}

/// Most training passes of a held-out fold with `--photos` (`--fold-passes`):
/// the folds only rank the held-out photographs and place their boxes.
/// LM-O, 8 instead of 15: the renders' folds 276 s instead of 435 (glue),
/// 254 instead of 486 (ape), every object's check keeping the same side
/// (docs/training.md, "The folds' passes capped").
pub const CHECK_FOLD_PASSES: usize = 8;

/// Paired bootstrap draws of the held-out photographs that compare the
/// models with and without the renders.
pub const CHECK_RESAMPLES: usize = 2000;

/// Share of those draws in which the model with the renders must find
/// more (a higher held-out AUC) to be kept: a one-sided test at 10%, so
/// that a gain within the chance of which photographs were held out keeps
/// the photographs alone (the box-only route's own model).
pub const RENDERS_CONFIDENCE: f64 = 0.9;

/// `--photos`, route `boxes`: the renders (drawn over the photographs)
/// become box-labelled photographs beside the user's, and the whole set
/// trains as `train --coco` trains box-only photographs
/// ([`super::photos::train_photographs`]). A component's direction and
/// start rotations are those of the renders imputed to it (of all renders
/// where none was).
#[allow(clippy::too_many_arguments)]
pub fn train_with_photo_boxes(
    name: &str,
    photos: &PhotoSamples,
    renders: &[Sample],
    poses: &[crate::pose::Pose],
    mesh: &Mesh,
    negatives: &[Sample],
    args: &MeshSettings,
    cache: &PyramidCache,
    params: &TrainParams,
    pb: &indicatif::ProgressBar,
) -> Result<RouteModel, RouteError> {
    let as_boxes: Vec<Sample> = renders.iter().map(as_box_photograph).collect();
    let samples: Vec<Sample> = photos
        .boxes
        .iter()
        .chain(&as_boxes)
        .chain(&photos.negatives)
        .cloned()
        .collect();
    let route = |renders: &[Sample]| BoxRoute {
        sources: vec![
            crate::train::ko8::Source::Single,
            crate::train::ko8::Source::Boxes,
        ],
        mirror_photos: false,
        box_folds: COCO_BOX_FOLDS,
        box_fold_rounds: COCO_BOX_FOLD_ROUNDS,
        box_fold_passes: Some(args.fold_passes),
        // The renders' backgrounds are the photographs themselves: they
        // give no background examples, and the folds hold out photographs
        // alone.
        renders: Arc::new(renders.iter().map(|s| s.image.clone()).collect()),
        // Budgeted full searches until one finds nothing, then an exact
        // one: both sides of the check alike.
        mining: true,
        augment: PhotoAugment::default(),
    };
    let mv = MultiViewParams {
        latent_rounds: args.latent_rounds,
        latent_visibility: args.photo_visibility == PhotoVisibility::Latent,
        ..MultiViewParams::default()
    };
    let train = |samples: &[Sample], route: &BoxRoute| {
        train_photographs(
            name,
            samples,
            negatives,
            route,
            &args.settings,
            params,
            &mv,
            cache,
            pb,
        )
    };
    pb.set_message(format!("{name}: photographs and renders"));
    let with_route = route(&as_boxes);
    let with = train(&samples, &with_route)?;
    let mut check = serde_json::Value::Null;
    let chosen = if args.keep_renders {
        with
    } else {
        // The check: the photographs alone by the box correction's folds
        // first, each box as the model with the renders imputed it; the
        // photographs-alone model is trained in full only when it wins.
        pb.set_message(format!("{name}: photographs alone, by the folds"));
        let alone_samples: Vec<Sample> = photos
            .boxes
            .iter()
            .chain(&photos.negatives)
            .cloned()
            .collect();
        let alone_route = route(&[]);
        let alone_trained: Vec<Sample> = with
            .trained
            .iter()
            .filter(|s| !with_route.renders.contains(&s.image))
            .cloned()
            .collect();
        let alone_params = photo_params(name, &alone_samples, &alone_route, &args.settings, params);
        let (alone_fit, alone_found) = fold_check(
            name,
            &alone_trained,
            negatives,
            &alone_route,
            &alone_params,
            &mv,
            cache,
        )?;
        let (a, b) = (
            with.held_out.as_ref().and_then(|h| h.auc()),
            alone_found.auc(),
        );
        // The renders stay only where they beat the photographs alone
        // beyond the chance of which photographs the folds held out.
        let confidence = with
            .held_out
            .as_ref()
            .and_then(|h| h.wins_over(&alone_found, CHECK_RESAMPLES));
        let keep_renders = match (a, b, confidence) {
            (Some(a), Some(b), Some(c)) => a > b && c >= RENDERS_CONFIDENCE,
            (Some(a), Some(b), None) => a > b,
            _ => true,
        };
        let show = |v: Option<f64>| v.map_or("none".to_string(), |v| format!("{v:.3}"));
        eprintln!(
            "{name}: held-out photographs, AUC with the renders {}, from the photographs alone {}; the renders ahead in {} of {CHECK_RESAMPLES} resamples of the photographs ({RENDERS_CONFIDENCE} needed): keeping {}",
            show(a),
            show(b),
            show(confidence),
            if keep_renders { "the renders" } else { "the photographs alone" }
        );
        check = serde_json::json!({
            "held_out_auc_with_renders": a,
            "held_out_auc_photographs_alone": b,
            "renders_ahead_in_resamples": confidence,
            "confidence_needed": RENDERS_CONFIDENCE,
            "kept": if keep_renders { "renders" } else { "photographs-alone" },
        });
        if keep_renders {
            with
        } else {
            pb.set_message(format!("{name}: photographs alone"));
            // Its folds ran above: the full training alone, then their
            // correction.
            let mut alone = train(
                &alone_samples,
                &BoxRoute {
                    box_folds: 0,
                    ..alone_route
                },
            )?;
            alone.model.meta.box_correction = alone_fit;
            if let (Some(auc), Some(p)) = (b, alone.model.meta.provenance.as_object_mut()) {
                p.insert("held_out_auc".into(), serde_json::json!(auc));
            }
            alone.held_out = Some(alone_found);
            alone
        }
    };
    let PhotoTraining {
        mut model,
        report,
        trained,
        ..
    } = chosen;
    if let Some(p) = model.meta.provenance.as_object_mut() {
        p.insert("renders_check".into(), check);
    }
    for v in &mut model.meta.viewpoints {
        v.views.clear();
    }
    let (directions, rotations) = imputed_viewpoints(
        name,
        photos.boxes.len(),
        renders,
        poses,
        mesh,
        &trained,
        model.meta.viewpoints.len(),
    );
    Ok(RouteModel {
        model,
        report,
        directions,
        rotations,
    })
}

/// Each of `k` components' direction and start rotations from the renders
/// training imputed to it (`trained`: the samples as the last round
/// trained them), said on stderr.
fn imputed_viewpoints(
    name: &str,
    photographs: usize,
    renders: &[Sample],
    poses: &[crate::pose::Pose],
    mesh: &Mesh,
    trained: &[Sample],
    k: usize,
) -> (Vec<[f64; 3]>, Vec<Vec<[f64; 4]>>) {
    // The component each render was imputed to, by its image.
    let component: std::collections::HashMap<&Path, usize> = trained
        .iter()
        .filter_map(|s| {
            s.annotation
                .as_ref()
                .map(|a| (s.image.as_path(), a.viewpoint))
        })
        .collect();
    let assign: Vec<usize> = renders
        .iter()
        .map(|s| {
            component
                .get(s.image.as_path())
                .copied()
                .unwrap_or(usize::MAX)
        })
        .collect();
    let (directions, rotations) = component_viewpoints(mesh, poses, &assign, k);
    let imputed = assign.iter().filter(|&&c| c < k).count();
    if imputed == 0 {
        eprintln!(
            "{name}: trained from {} photographs' boxes; the {} renders' rotations are every component's start poses",
            photographs,
            renders.len()
        );
    } else {
        eprintln!(
            "{name}: {} photographs' boxes and {} renders trained together; renders per component {:?}",
            photographs,
            renders.len(),
            (0..k)
                .map(|c| assign.iter().filter(|&&a| a == c).count())
                .collect::<Vec<_>>()
        );
    }
    if imputed > 0 && imputed < renders.len() {
        eprintln!(
            "{name}: {} renders not found among the trained samples: their rotations count for every component",
            renders.len() - imputed
        );
    }
    (directions, rotations)
}

/// Each of `k` components' mean viewing direction (object towards camera,
/// mesh frame) and representative start rotations, from the render
/// `poses` assigned to it (`assign`; `usize::MAX` or beyond `k`: none); a
/// component without a render gets those of all renders.
pub fn component_viewpoints(
    mesh: &Mesh,
    poses: &[crate::pose::Pose],
    assign: &[usize],
    k: usize,
) -> (Vec<[f64; 3]>, Vec<Vec<[f64; 4]>>) {
    let (lo, hi) = mesh.bounds();
    let centre = (lo + hi) / 2.0;
    let toward_camera = |p: &crate::pose::Pose| {
        let camera = -(p.rotation.transpose() * p.translation);
        (camera - centre).normalize()
    };
    let mean_direction = |chosen: &dyn Fn(usize) -> bool| -> Option<[f64; 3]> {
        let sum: Vector3<f64> = poses
            .iter()
            .zip(assign)
            .filter(|(_, &c)| chosen(c))
            .map(|(p, _)| toward_camera(p))
            .sum();
        (sum.norm() > 1e-12).then(|| sum.normalize().into())
    };
    let rs: Vec<nalgebra::Matrix3<f64>> = poses.iter().map(|p| p.rotation).collect();
    let own = representative_rotations(&rs, assign, k, ROTATIONS_PER_COMPONENT);
    let all = representative_rotations(&rs, &vec![0; rs.len()], 1, ROTATIONS_PER_COMPONENT)
        .into_iter()
        .next()
        .unwrap_or_default();
    let everywhere = mean_direction(&|_| true).unwrap_or([0.0, 0.0, 1.0]);
    let directions = (0..k)
        .map(|c| mean_direction(&|a| a == c).unwrap_or(everywhere))
        .collect();
    let rotations = own
        .into_iter()
        .map(|r| if r.is_empty() { all.clone() } else { r })
        .collect();
    (directions, rotations)
}

/// The least and greatest longer side of the boxes of `samples` (at least
/// [`MIN_RENDER_SIDE`] px); `None` without a box.
pub fn box_size_range(samples: &[Sample]) -> Option<[f64; 2]> {
    let sides: Vec<f64> = samples
        .iter()
        .filter_map(|s| s.annotation.as_ref())
        .map(|a| a.bbox.2.max(a.bbox.3))
        .filter(|v| v.is_finite())
        .collect();
    let lo = sides.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = sides.iter().copied().fold(0.0, f64::max);
    (!sides.is_empty()).then(|| [lo.max(MIN_RENDER_SIDE), hi.max(MIN_RENDER_SIDE)])
}

/// Smallest longer side of the object in a render drawn at the
/// photographs' sizes, pixels.
pub const MIN_RENDER_SIDE: f64 = 16.0;

/// A render as a box-labelled photograph: its box, its visibility and
/// component left to training.
pub fn as_box_photograph(render: &Sample) -> Sample {
    let mut s = render.clone();
    if let Some(a) = s.annotation.as_mut() {
        a.visible = crate::data::box_mask(a.bbox, a.visible.width, a.visible.height);
        a.viewpoint = 0;
        a.mask_known = false;
    }
    s
}

/// Reads `file`'s photographs for the object `name` (see
/// [`crate::data::load_box_photos`]). A photograph with two boxes of the
/// object, or only an ignored one, is left out (one sample holds one box,
/// and either would make a negative of an instance), named on stderr.
pub fn photo_samples(file: &Path, name: &str) -> Result<PhotoSamples, RouteError> {
    let loaded = crate::data::load_box_photos(file, name).map_err(RouteError::input)?;
    let mut out = PhotoSamples {
        file: file.to_path_buf(),
        boxes: Vec::new(),
        negatives: Vec::new(),
        skipped: Vec::new(),
        scenes: Vec::new(),
    };
    for p in loaded.photos {
        out.scenes.push((
            p.image.clone(),
            p.boxes.iter().chain(&p.ignore).copied().collect(),
        ));
        let id = crate::data::file_stem(&p.image);
        match (&p.boxes[..], p.ignore.is_empty()) {
            ([b], true) => out.boxes.push(Sample {
                image: p.image.clone(),
                id,
                annotation: Some(crate::data::Annotation {
                    label: name.to_string(),
                    bbox: *b,
                    visible: crate::data::box_mask(*b, p.width, p.height),
                    viewpoint: 0,
                    mask_known: false,
                }),
            }),
            ([], true) => out.negatives.push(Sample::negative(p.image.clone())),
            ([], false) => out.skipped.push(format!(
                "{}: only a hardly visible {name} (iscrowd): neither a box nor a negative",
                p.image.display()
            )),
            (boxes, _) => out.skipped.push(format!(
                "{}: {} boxes of {name} and {} hardly visible (iscrowd): a photograph trains one box, and the others would be negatives",
                p.image.display(),
                boxes.len(),
                p.ignore.len()
            )),
        }
    }
    for s in &out.skipped {
        eprintln!("--photos: left out {s}");
    }
    eprintln!(
        "--photos {}: {} boxes of {name}, {} photographs without it, {} left out",
        file.display(),
        out.boxes.len(),
        out.negatives.len(),
        out.skipped.len()
    );
    if out.boxes.is_empty() {
        return Err(RouteError::input(format!(
            "--photos {}: no photograph with exactly one box of {name}",
            file.display()
        )));
    }
    Ok(out)
}
