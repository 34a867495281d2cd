//! `sdhop-train mesh`: a detector of an object from its mesh. Renders a
//! training set ([`crate::train::mesh`]), trains one SD-HOP model with a
//! component per group of viewpoints (or the renders as views, or beside
//! the user's boxed photographs: [`super::mesh_photos`]), records each
//! component's mean viewing direction and start rotations, and chooses
//! the colour agreement's weight on held-out renders.

use super::mesh_photos::{
    box_size_range, photo_samples, train_from_views, train_with_photo_boxes, PhotoSamples,
    CHECK_FOLD_PASSES,
};
use super::{image_files, RouteError, TrainSettings};
use crate::data::Sample;
use crate::eval::bop_detect::auc_curve;
use crate::model::Model;
use crate::pose::mesh::Mesh;
use crate::train::mesh::{render_set, render_set_with, Occluder, RenderParams};
use crate::train::multiview::{train_sources, MultiViewParams, Sources};
use crate::train::{progress_bar, train_joint, PyramidCache, TrainParams, TrainReport};
use crate::vision::cells::FeatureKind;
use crate::vision::detect::box_iou;
use crate::vision::image::ColorImage;
use std::path::{Path, PathBuf};

/// What `sdhop-train mesh` trains from, and how. The defaults are the
/// route's (`MeshSettings::default()`); `mesh` and `name` must be given.
#[derive(Clone, Debug)]
pub struct MeshSettings {
    /// The objects' meshes (PLY with optional vertex colours, or OBJ), `z`
    /// up; several train jointly into one model.
    pub mesh: Vec<PathBuf>,
    /// One name per mesh: the detections' labels.
    pub name: Vec<String>,
    /// The model's name for several objects (default: their names joined
    /// by `-`).
    pub model_name: Option<String>,
    /// Background photographs without the object (optional with `photos`).
    pub backgrounds: Option<PathBuf>,
    /// Folder for the renders (default `out/mesh/MODEL`).
    pub work: Option<PathBuf>,
    /// Renders of each object (default 400; with `photos`, route `boxes`:
    /// [`PHOTO_RENDERS`]).
    pub renders: Option<usize>,
    pub components: usize,
    /// Camera elevation range above the mesh's `xy` plane, degrees.
    pub elevation: [f64; 2],
    pub roll: f64,
    /// Range of the object's longest box side in the renders (default
    /// [`RenderParams`]'s; with `photos`, route `boxes`: the photographs').
    pub size: Option<[f64; 2]>,
    pub occluded_share: f64,
    pub occlusion: [f64; 2],
    pub patch_occluders: f64,
    pub occluder_mesh: Vec<PathBuf>,
    pub mesh_occluders: f64,
    /// Background images used as negatives (the first ones by name).
    pub negatives: usize,
    pub render_seed: u64,
    /// Train the clean renders as views (`train --sources views`).
    pub from_views: bool,
    /// With `from_views`: training photographs made from each view.
    pub per_view: usize,
    /// A COCO file of photographs with boxes of the object.
    pub photos: Option<PathBuf>,
    pub photo_route: PhotoRoute,
    pub latent_rounds: usize,
    pub photo_visibility: PhotoVisibility,
    pub photo_share: Option<f64>,
    pub keep_renders: bool,
    pub fold_passes: usize,
    /// The training settings the user gave.
    pub settings: TrainSettings,
}

impl Default for MeshSettings {
    fn default() -> Self {
        let render = RenderParams::default();
        Self {
            mesh: Vec::new(),
            name: Vec::new(),
            model_name: None,
            backgrounds: None,
            work: None,
            renders: None,
            components: render.components,
            elevation: render.elevation,
            roll: render.roll,
            size: None,
            occluded_share: render.occluded_share,
            occlusion: render.occlusion,
            patch_occluders: render.patch_occluders,
            occluder_mesh: Vec::new(),
            mesh_occluders: render.mesh_occluders,
            negatives: MESH_NEGATIVES,
            render_seed: render.seed,
            from_views: false,
            per_view: VIEW_PHOTOS,
            photos: None,
            photo_route: PhotoRoute::default(),
            latent_rounds: MultiViewParams::default().latent_rounds,
            photo_visibility: PhotoVisibility::default(),
            photo_share: None,
            keep_renders: false,
            fold_passes: CHECK_FOLD_PASSES,
            settings: TrainSettings::default(),
        }
    }
}

/// Background images used as negatives by default.
pub const MESH_NEGATIVES: usize = 50;

/// Training photographs made from each view with `from_views`.
pub const VIEW_PHOTOS: usize = 3;

/// The cells of the mesh alone: the learned ones. LM-O, each object's
/// model alone on all 200 development photographs (`scripts/lmo_mesh_alone.sh
/// OUT --features cnn`): ape 0.323, cat 0.289, duck 0.614, glue 0.142
/// against HOG's 0.084, 0.000, 0.423 and 0.000 trained and scored the
/// same way (docs/benchmarks.md, 2026-11-29), in 7-11 minutes and 3.3 GB
/// per object.
pub const MESH_FEATURES: FeatureKind = FeatureKind::Cnn;

/// What [`train_mesh`] made.
pub struct MeshTraining {
    pub model: Model,
    pub report: TrainReport,
    /// The model's name.
    pub name: String,
    /// Seconds spent rendering.
    pub render_seconds: f64,
}

/// How renders and box-labelled photographs train together (`--photo-route`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum PhotoRoute {
    /// Renders drawn over the photographs train as more box photographs.
    #[default]
    Boxes,
    /// Renders train the components; the boxes are imputed into them.
    RendersFirst,
}

/// Renders per object with `--photos`, route `boxes` (`--renders`): LM-O
/// ape, 50 box photographs and 100 renders at the photographs' sizes,
/// AUC 0.650 against 0.601 from the photographs alone, in 23 min against
/// 5.9; the cat's held-out folds keep the photographs alone. Fewer were
/// not measured (docs/training.md).
const PHOTO_RENDERS: usize = 100;

/// The cells of the `--photos` routes: the learned ones (LM-O, mesh and
/// 50 box photographs: ape 0.527 and duck 0.572 against HOG's 0.310 and
/// 0.156 on the `renders-first` route; docs/training.md).
const PHOTO_FEATURES: FeatureKind = FeatureKind::Cnn;

/// How the visible part of a box drawn on a photograph is labelled.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum PhotoVisibility {
    /// The visible cells are imputed under the model (latent).
    #[default]
    Latent,
    /// The whole box is visible; only its component is imputed.
    Full,
}

/// Weights of the colour agreement compared by [`choose_colour_weight`].
const COLOUR_WEIGHTS: [f64; 6] = [0.0, 0.25, 0.5, 1.0, 2.0, 4.0];

/// A box `(x, y, width, height)` in pixels.
pub(crate) type BoxXywh = (f64, f64, f64, f64);

/// One object of a model trained from meshes.
pub struct Object {
    pub name: String,
    pub file: PathBuf,
    pub mesh: Mesh,
    pub colours: Option<Vec<[f32; 3]>>,
}

/// Renders per object of the colour-weight check.
const CHECK_RENDERS: usize = 60;

/// The weight of the colour agreement (see `DetectParams::colour_weight`)
/// that localizes best on renders training never saw (another seed) and
/// on the last background photographs (not among the negatives): the
/// AUC of recall against false positives per image (0 to 1) of the top
/// 20 detections per image, as `lmo_detect_eval.py` computes it (a
/// detection is true only with its object's label).
fn choose_colour_weight(
    model: &Model,
    objects: &[Object],
    backgrounds: &[ColorImage],
    render: &RenderParams,
    dir: &Path,
    pb: &indicatif::ProgressBar,
) -> Result<(f64, Vec<(f64, f64)>), RouteError> {
    use crate::vision::detect::{detection_masks, DetectParams, Detector};
    use crate::vision::pyramid::FeaturePyramid;
    use crate::vision::shape::{colour_agreement, image_colours};
    let per_object = (CHECK_RENDERS / objects.len()).max(20);
    let mut samples = Vec::new();
    for (k, o) in objects.iter().enumerate() {
        let check = RenderParams {
            renders: per_object,
            components: 1,
            seed: render.seed.wrapping_add(1_000_003 + 7919 * k as u64),
            ..render.clone()
        };
        let sub = if objects.len() > 1 {
            dir.join(&o.name)
        } else {
            dir.to_path_buf()
        };
        let set = render_set(
            &o.mesh,
            o.colours.as_deref(),
            &o.name,
            backgrounds,
            &check,
            &sub,
            &indicatif::ProgressBar::hidden(),
        )
        .map_err(RouteError::input)?;
        samples.extend(set.samples);
    }
    let held: Vec<&ColorImage> = backgrounds.iter().rev().take(20).collect();
    pb.set_length((samples.len() + held.len()) as u64);
    let det = Detector::new(&model.views).map_err(RouteError::input)?;
    let params = DetectParams {
        threshold: -1.5,
        max_detections: 20,
        ..model.meta.detection
    };
    // (score, colour agreement, true) of every detection.
    let mut found: Vec<(f64, f64, bool)> = Vec::new();
    let mut scan =
        |img: &ColorImage, truth: Option<(&String, BoxXywh)>| -> Result<(), RouteError> {
            let pyr = FeaturePyramid::build(img, &model.meta.pyramid, &model.meta.segmentation)
                .map_err(RouteError::input)?;
            let (dets, _) = det.detect(&pyr, &params).map_err(RouteError::input)?;
            let ic = image_colours(img);
            let mut matched = false;
            for d in dets {
                let shape = model.shapes.get(d.viewpoint).and_then(Option::as_ref);
                let c = match shape.and_then(|s| s.colours.as_ref()) {
                    Some(oc) => {
                        let (_, refined) = detection_masks(&d, &pyr, &params.refine, shape);
                        colour_agreement(img, &refined, oc, &ic)
                    }
                    None => 0.0,
                };
                let label = model.meta.viewpoints.get(d.viewpoint).map(|v| &v.label);
                let hit = !matched
                    && truth.is_some_and(|(l, t)| label == Some(l) && box_iou(d.bbox, t) >= 0.5);
                matched |= hit;
                found.push((d.score, c, hit));
            }
            pb.inc(1);
            Ok(())
        };
    for s in &samples {
        let img = crate::data::load_image(&s.image).map_err(RouteError::input)?;
        scan(&img, s.annotation.as_ref().map(|a| (&a.label, a.bbox)))?;
    }
    for img in &held {
        scan(img, None)?;
    }
    let n_images = samples.len() + held.len();
    let n_pos = samples.len();
    let table: Vec<(f64, f64)> = COLOUR_WEIGHTS
        .iter()
        .map(|&w| {
            let ranked: Vec<(f64, bool)> = found
                .iter()
                .map(|&(s, c, t)| (s + crate::pipeline::colour_term(w, c), t))
                .collect();
            let (area, _, _) = auc_curve(ranked, n_pos, n_images);
            (w, area)
        })
        .collect();
    let best = table.iter().fold(
        (0.0, f64::MIN),
        |b, &(w, a)| if a > b.1 + 1e-9 { (w, a) } else { b },
    );
    Ok((best.0, table))
}

/// `coco.json` beside the renders: their full boxes, visible masks,
/// components and poses (`train --coco` retrains from it).
fn write_coco(
    work: &Path,
    name: &str,
    samples: &[Sample],
    poses: &[crate::pose::geometry::Pose],
    first_view: usize,
) -> Result<(), RouteError> {
    let mut images = Vec::new();
    let mut annotations = Vec::new();
    for (i, (s, pose)) in samples.iter().zip(poses).enumerate() {
        let Some(a) = &s.annotation else { continue };
        let file = s
            .image
            .file_name()
            .map(|f| f.to_string_lossy().into_owned())
            .unwrap_or_default();
        images.push(serde_json::json!({
            "id": i + 1, "file_name": file,
            "width": a.visible.width, "height": a.visible.height
        }));
        let (x, y, w, h) = a.bbox;
        annotations.push(serde_json::json!({
            "id": i + 1, "image_id": i + 1, "category_id": 1,
            "bbox": [x, y, w, h], "viewpoint": a.viewpoint - first_view,
            "segmentation": a.visible.to_rle(),
            "pose": {"rotation": pose.rotation_rows(), "translation": [
                pose.translation.x, pose.translation.y, pose.translation.z]},
        }));
    }
    let coco = serde_json::json!({
        "images": images,
        "annotations": annotations,
        "categories": [{"id": 1, "name": name}],
        "info": {"description": format!("sdhop-train mesh renders of {name}")},
    });
    let path = work.join("coco.json");
    std::fs::write(&path, serde_json::to_string(&coco).map_err(RouteError::io)?)
        .map_err(|e| RouteError::io(format!("{}: {e}", path.display())))
}

/// The training parameters of the mesh routes: the settings' over the
/// route's feature kind, with the mesh's scales where the settings leave
/// them open (route `boxes` sets its scales as `train --coco` does, from
/// the photographs' boxes, in `train_photographs`).
pub fn mesh_params(s: &MeshSettings) -> Result<TrainParams, RouteError> {
    let features = if s.photos.is_some() {
        PHOTO_FEATURES
    } else {
        MESH_FEATURES
    };
    s.settings.no_segmenter("mesh")?;
    let (mut params, _) = s.settings.params(features)?;
    let st = &s.settings;
    let mesh_scales = !s.boxes_route() && st.config.is_none();
    // Templates of about 12 cells (smaller ones fit even their own
    // training renders badly: 50% top-1 with 5-8 cells); upsampled levels
    // find objects down to 40% of that (training must see those levels
    // too: a model trained up to 1.4 and run up to 2.5 scored AUC 0.000 on
    // LM-O ape, its upsampled levels full of false positives), several
    // octaves cover a wide range of sizes (unless the flags or the config
    // say otherwise).
    if st.levels_per_octave.is_none() && mesh_scales {
        params.pyramid.levels_per_octave = 5;
    }
    if st.max_scale.is_none() && mesh_scales {
        params.pyramid.max_scale = 2.5;
    }
    if st.min_scale.is_none() && mesh_scales {
        params.pyramid.min_scale = 0.125;
    }
    // Objects in photographs are small (LM-O: 37-343 px, median about
    // 60), and the detector meets them on upsampled levels: the renders
    // are drawn at such sizes and the templates 1.4 times larger, so that
    // training sees the objects on the same upsampled levels (LM-O ape:
    // 80-180 px renders at template scale 0.8 AUC 0.259, 40-110 px at 1.4
    // AUC 0.319).
    if st.template_scale.is_none() && mesh_scales {
        params.template_scale = 1.4;
    }
    // The renders never cut the object at the image border, so the model
    // learns nothing about truncated boxes: allowing them, boxes hanging
    // off LM-O's bottom border scored 5.7 (AUC 0.000); without, 0.099.
    if mesh_scales {
        params.max_truncation = 0.0;
    }
    // With `photos`: the boxes' share of the positives' weight.
    params.examples.box_share = s.photo_share;
    params.validate().map_err(RouteError::input)?;
    Ok(params)
}

impl MeshSettings {
    /// Whether the renders train beside the photographs' boxes (`photos`,
    /// route `boxes`).
    pub fn boxes_route(&self) -> bool {
        self.photos.is_some() && self.photo_route == PhotoRoute::Boxes
    }

    /// The model's name: `model_name`, or the objects' names joined.
    pub fn model_name(&self) -> String {
        match (&self.model_name, &self.name[..]) {
            (Some(m), _) => m.clone(),
            (None, [one]) => one.clone(),
            (None, names) => names.join("-"),
        }
    }

    /// The render settings.
    pub fn render_params(&self) -> Result<RenderParams, RouteError> {
        let render = RenderParams {
            renders: self.renders.unwrap_or(if self.boxes_route() {
                PHOTO_RENDERS
            } else {
                RenderParams::default().renders
            }),
            components: self.components,
            elevation: self.elevation,
            roll: self.roll,
            size: self.size.unwrap_or(RenderParams::default().size),
            occluded_share: self.occluded_share,
            occlusion: self.occlusion,
            patch_occluders: self.patch_occluders,
            mesh_occluders: self.mesh_occluders,
            seed: self.render_seed,
            ..RenderParams::default()
        };
        render.validate().map_err(RouteError::input)?;
        Ok(render)
    }

    /// Refuses settings that cannot train, before any work.
    pub fn check(&self) -> Result<(), RouteError> {
        if self.mesh.len() != self.name.len() {
            return Err(RouteError::input(format!(
                "{} --mesh but {} --name: give one name per mesh, in the same order",
                self.mesh.len(),
                self.name.len()
            )));
        }
        let mut seen = std::collections::HashSet::new();
        if let Some(dup) = self.name.iter().find(|n| !seen.insert(n.as_str())) {
            return Err(RouteError::input(format!("--name {dup} given twice")));
        }
        if self.from_views && self.mesh.len() > 1 {
            return Err(RouteError::input(
                "--from-views trains one object per model: run it once per --mesh",
            ));
        }
        if self.from_views && self.photos.is_some() {
            return Err(RouteError::input(
                "--from-views and --photos are two routes: give one",
            ));
        }
        if self.fold_passes == 0 {
            return Err(RouteError::input("--fold-passes must be at least 1"));
        }
        if self.photos.is_some() && self.mesh.len() > 1 {
            return Err(RouteError::input(
                "--photos trains one object per model: run it once per --mesh",
            ));
        }
        if self.photos.is_none() && self.backgrounds.is_none() {
            return Err(RouteError::input(
                "--backgrounds is required without --photos",
            ));
        }
        Ok(())
    }
}

/// A mesh's vertex colours (RGB, 0 to 1), where its file has them.
type VertexColours = Option<Vec<[f32; 3]>>;

/// A mesh file's mesh and vertex colours.
fn read_mesh(file: &Path, validate: bool) -> Result<(Mesh, VertexColours), RouteError> {
    let bytes =
        std::fs::read(file).map_err(|e| RouteError::io(format!("{}: {e}", file.display())))?;
    let mesh = Mesh::parse(&bytes)
        .and_then(|m| match validate {
            true => m.validate().map(|()| m),
            false => Ok(m),
        })
        .map_err(|e| RouteError::input(format!("{}: {e}", file.display())))?;
    let colours = Mesh::ply_vertex_colours(&bytes)
        .map_err(|e| RouteError::input(format!("{}: {e}", file.display())))?;
    Ok((mesh, colours))
}

/// Every object's renders, their components numbered after the previous
/// objects'.
#[derive(Default)]
struct Rendered {
    samples: Vec<Sample>,
    directions: Vec<[f64; 3]>,
    rotations: Vec<Vec<[f64; 4]>>,
    poses: Vec<crate::pose::geometry::Pose>,
}

/// Renders every object over `backgrounds` into `work` (a subfolder per
/// object when there are several), with its `coco.json`.
fn render_objects(
    s: &MeshSettings,
    objects: &[Object],
    occluders: &[(PathBuf, Occluder)],
    backgrounds: &[ColorImage],
    render: &RenderParams,
    work: &Path,
    start: std::time::Instant,
) -> Result<Rendered, RouteError> {
    let mut out = Rendered::default();
    for (k, o) in objects.iter().enumerate() {
        let sub = if objects.len() > 1 {
            work.join(&o.name)
        } else {
            work.to_path_buf()
        };
        let first_view = out.directions.len();
        let pb = progress_bar(render.renders as u64, &format!("{}: rendering", o.name));
        let seeded = RenderParams {
            seed: render.seed.wrapping_add(104_729 * k as u64),
            // Views are clean: the occluders come with the augmentation.
            occluded_share: if s.from_views {
                0.0
            } else {
                render.occluded_share
            },
            ..render.clone()
        };
        let same = |f: &PathBuf| match (f.canonicalize(), o.file.canonicalize()) {
            (Ok(a), Ok(b)) => a == b,
            _ => *f == o.file,
        };
        let mine: Vec<Occluder> = occluders
            .iter()
            .filter(|(f, _)| !same(f))
            .map(|(_, occ)| Occluder {
                mesh: occ.mesh.clone(),
                colours: occ.colours.clone(),
            })
            .collect();
        let mut set = render_set_with(
            &o.mesh,
            o.colours.as_deref(),
            &o.name,
            backgrounds,
            &mine,
            &seeded,
            &sub,
            &pb,
        )
        .map_err(RouteError::input)?;
        pb.finish_and_clear();
        for a in set.samples.iter_mut().filter_map(|s| s.annotation.as_mut()) {
            a.viewpoint += first_view;
        }
        eprintln!(
            "{}: {} renders ({} components, {}) in {:.0} s -> {}",
            o.name,
            set.samples.len(),
            set.directions.len(),
            if o.colours.is_some() {
                "vertex colours"
            } else {
                "no vertex colours: grey"
            },
            start.elapsed().as_secs_f64(),
            sub.display()
        );
        write_coco(&sub, &o.name, &set.samples, &set.poses, first_view)?;
        out.directions.extend(set.directions);
        out.rotations.extend(set.rotations);
        out.poses.extend(set.poses);
        out.samples.extend(set.samples);
    }
    Ok(out)
}

/// The model of the route the settings choose, from the renders (and the
/// photographs); `rendered`'s directions and rotations become the
/// route's where it imputes components.
#[allow(clippy::too_many_arguments)]
fn train_route(
    s: &MeshSettings,
    objects: &[Object],
    photos: Option<&PhotoSamples>,
    rendered: &mut Rendered,
    negatives: &[Sample],
    backgrounds: &[ColorImage],
    params: &TrainParams,
    model_name: &str,
) -> Result<(Model, TrainReport), RouteError> {
    // Pyramids without their pixels: the renders' and negatives' images
    // and per-pixel segments are a quarter of the memory, and training
    // needs none of them (LM-O cat: 3.79 GiB peak with them).
    // Route `boxes` keeps the pixels, as `train --coco` does (its box
    // correction detects on held-out photographs).
    let cache = if s.boxes_route() {
        PyramidCache::default()
    } else {
        PyramidCache::lean()
    };
    let pb = progress_bar(0, &format!("{model_name}: training"));
    let samples = &rendered.samples;
    let imputing = match photos {
        Some(photos) if s.boxes_route() => Some(train_with_photo_boxes(
            &s.name[0],
            photos,
            samples,
            &rendered.poses,
            &objects[0].mesh,
            negatives,
            s,
            &cache,
            params,
            &pb,
        )?),
        _ if s.from_views => Some(train_from_views(
            &objects[0],
            samples,
            &rendered.poses,
            negatives,
            backgrounds,
            s,
            &cache,
            params,
            &pb,
        )?),
        _ => None,
    };
    let trained = if let Some(route) = imputing {
        // The components' directions and start rotations are those of the
        // renders the route imputed to them.
        rendered.directions = route.directions;
        rendered.rotations = route.rotations;
        (route.model, route.report)
    } else if let Some(photos) = photos {
        renders_first(s, photos, samples, negatives, &cache, params, &pb)?
    } else {
        let refs: Vec<&Sample> = samples.iter().chain(negatives).collect();
        let labels: Vec<&str> = s.name.iter().map(String::as_str).collect();
        train_joint(model_name, &labels, &refs, &cache, params, &pb).map_err(RouteError::input)?
    };
    pb.finish_and_clear();
    Ok(trained)
}

/// `photos`, route `renders-first`: the renders train the components,
/// then the boxes are imputed into them.
fn renders_first(
    s: &MeshSettings,
    photos: &PhotoSamples,
    samples: &[Sample],
    negatives: &[Sample],
    cache: &PyramidCache,
    params: &TrainParams,
    pb: &indicatif::ProgressBar,
) -> Result<(Model, TrainReport), RouteError> {
    let fixed: Vec<&Sample> = samples
        .iter()
        .chain(negatives)
        .chain(&photos.negatives)
        .collect();
    let src = Sources {
        fixed,
        views: Vec::new(),
        occluders: Vec::new(),
        backgrounds: Vec::new(),
        boxes: photos.boxes.clone(),
    };
    let mv = MultiViewParams {
        latent_rounds: s.latent_rounds,
        latent_visibility: s.photo_visibility == PhotoVisibility::Latent,
        ..MultiViewParams::default()
    };
    let (mut m, mut r) =
        train_sources(&s.name[0], src, cache, params, &mv, pb).map_err(RouteError::input)?;
    for v in &mut m.meta.viewpoints {
        v.views.clear();
    }
    for (i, round) in r.imputation.iter().enumerate() {
        eprintln!(
            "{}: round {}: {} boxes imputed ({} fit no component), {} changed component, {:.2} of their cells visible",
            s.name[0],
            i + 1,
            round.boxes,
            round.unfit,
            round.component_changes,
            round.mean_visible
        );
    }
    Ok((m, r.rounds.pop().unwrap_or_default()))
}

/// Chooses the colour agreement's weight on held-out renders and stores
/// it, with the table it was chosen from, in the model.
fn add_colour_weight(
    model: &mut Model,
    objects: &[Object],
    backgrounds: &[ColorImage],
    render: &RenderParams,
    work: &Path,
) -> Result<(), RouteError> {
    let name = model.meta.name.clone();
    let pb = progress_bar(0, &format!("{name}: colour weight"));
    let (weight, table) = choose_colour_weight(
        model,
        objects,
        backgrounds,
        render,
        &work.join("check"),
        &pb,
    )?;
    pb.finish_and_clear();
    eprintln!(
        "{name}: colour weight {weight} (AUC on held-out renders per weight: {})",
        table
            .iter()
            .map(|(w, a)| format!("{w}: {a:.3}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    model.meta.detection.colour_weight = weight;
    if let Some(obj) = model.meta.provenance.as_object_mut() {
        obj.insert(
            "colour_weight".into(),
            serde_json::json!({"chosen": weight, "auc_per_weight": table}),
        );
    }
    Ok(())
}

/// What the model was trained from, in its provenance.
fn record_mesh(
    model: &mut Model,
    s: &MeshSettings,
    objects: &[Object],
    render: &RenderParams,
    photos: Option<&PhotoSamples>,
    negatives: usize,
) {
    let Some(obj) = model.meta.provenance.as_object_mut() else {
        return;
    };
    let meshes: Vec<serde_json::Value> = objects
        .iter()
        .map(|o| {
            serde_json::json!({
                "name": o.name,
                "file": o.file.display().to_string(),
                "vertex_colours": o.colours.is_some(),
            })
        })
        .collect();
    obj.insert(
        "mesh".into(),
        serde_json::json!({
            "objects": meshes,
            "occluder_meshes": s
                .occluder_mesh
                .iter()
                .map(|f| f.display().to_string())
                .collect::<Vec<_>>(),
            "render": render,
            "from_views": s.from_views,
            "photos": photos.map(|p| serde_json::json!({
                "file": p.file.display().to_string(),
                "boxes": p.boxes.len(),
                "negatives": p.negatives.len(),
                "skipped": p.skipped,
                "route": s.photo_route,
                "latent_rounds": s.latent_rounds,
                "fold_passes": s.fold_passes,
                "visibility": s.photo_visibility,
                "share": s.photo_share,
            })),
            "backgrounds": s.backgrounds.as_ref().map(|b| b.display().to_string()),
            "negatives": negatives,
        }),
    );
}

/// Trains a detector of the settings' objects from their meshes (and the
/// photographs, with `photos`).
pub fn train_mesh(s: &MeshSettings) -> Result<MeshTraining, RouteError> {
    let start = std::time::Instant::now();
    s.check()?;
    let params = mesh_params(s)?;
    let mut render = s.render_params()?;
    // The photographs first: a bad file is refused before any rendering.
    let photos = match &s.photos {
        Some(file) => Some(photo_samples(file, &s.name[0])?),
        None => None,
    };
    // Route `boxes`: renders at the photographs' sizes. Renders smaller
    // than every box stretched the pyramid (LM-O cat, renders of 40-110 px
    // beside boxes of about 65: levels up to 2.70 instead of 1.70, 41 min
    // of training against 5 for the photographs alone).
    if let (Some(p), None, true) = (&photos, s.size, s.boxes_route()) {
        if let Some(range) = box_size_range(&p.boxes) {
            // No larger than a render holds.
            let most = 0.9 * render.width.min(render.height) as f64;
            let range = [range[0].min(most), range[1].min(most)];
            render.size = range;
            eprintln!(
                "{}: renders at {:.0}-{:.0} px (the photographs' boxes' longer sides)",
                s.name[0], range[0], range[1]
            );
            render.validate().map_err(RouteError::input)?;
        }
    }
    let model_name = s.model_name();
    let objects: Vec<Object> = s
        .mesh
        .iter()
        .zip(&s.name)
        .map(|(file, name)| {
            let (mesh, colours) = read_mesh(file, false)?;
            Ok(Object {
                name: name.clone(),
                file: file.clone(),
                mesh,
                colours,
            })
        })
        .collect::<Result<_, RouteError>>()?;
    let occluders: Vec<(PathBuf, Occluder)> = s
        .occluder_mesh
        .iter()
        .map(|file| {
            let (mesh, colours) = read_mesh(file, true)?;
            Ok((file.clone(), Occluder { mesh, colours }))
        })
        .collect::<Result<_, RouteError>>()?;
    let files =
        match &s.backgrounds {
            Some(dir) => image_files(dir)?,
            None if s.boxes_route() => Vec::new(),
            None => return Err(RouteError::input(
                "--photo-route renders-first draws the renders over --backgrounds: give the folder",
            )),
        };
    // Route `boxes`: the renders are drawn over the user's photographs,
    // the object taken out of them.
    let backgrounds: Vec<ColorImage> = match &photos {
        Some(p) if s.boxes_route() => p.scenes()?,
        _ => files
            .iter()
            .map(|p| super::background_image(p))
            .collect::<Result<_, _>>()?,
    };
    let work = s
        .work
        .clone()
        .unwrap_or_else(|| PathBuf::from("out/mesh").join(&model_name));
    let mut rendered =
        render_objects(s, &objects, &occluders, &backgrounds, &render, &work, start)?;
    let render_seconds = start.elapsed().as_secs_f64();
    // The negatives as they are (downsized copies at the renders' size
    // found less: LM-O ape AUC 0.067 against 0.123).
    let negatives: Vec<Sample> = files
        .iter()
        .take(s.negatives)
        .map(|p| Sample::negative(p.clone()))
        .collect();
    let (mut model, report) = train_route(
        s,
        &objects,
        photos.as_ref(),
        &mut rendered,
        &negatives,
        &backgrounds,
        &params,
        &model_name,
    )?;
    eprintln!(
        "{model_name}: full-search violations {:?}, min-cuts {:?}",
        report.full_violation, report.full_min_cuts
    );
    for ((view, dir), rots) in model
        .meta
        .viewpoints
        .iter_mut()
        .zip(&rendered.directions)
        .zip(&rendered.rotations)
    {
        view.direction = Some(*dir);
        view.rotations = rots.clone();
    }
    // Route `boxes` trains as `train --coco` does, without the colour
    // agreement (it was chosen on renders, which its photographs outrank).
    if !s.boxes_route() {
        add_colour_weight(&mut model, &objects, &backgrounds, &render, &work)?;
    }
    record_mesh(
        &mut model,
        s,
        &objects,
        &render,
        photos.as_ref(),
        negatives.len(),
    );
    Ok(MeshTraining {
        model,
        report,
        name: model_name,
        render_seconds,
    })
}
