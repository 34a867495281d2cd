//! `sdhop-train mesh`: a detector of an object from its mesh alone. Renders
//! a training set (`crate::train::mesh`), trains one SD-HOP model with a
//! component per group of viewpoints, records each component's mean
//! viewing direction and saves the weights file.

use super::*;
use crate::eval::bop_detect::auc_curve;
use crate::pose::mesh::Mesh;
use crate::train::mesh::{
    render_set, render_set_with, representative_rotations, without_boxes, Occluder, RenderParams,
    ROTATIONS_PER_COMPONENT,
};
use crate::train::multiview::{train_sources, MultiViewParams, Sources};
use crate::train::views::{OccluderKinds, View};
use crate::train::{train_joint, TrainReport};
use nalgebra::Vector3;
use std::sync::Arc;

#[derive(clap::Args)]
pub(crate) struct MeshArgs {
    /// The object's mesh (PLY with optional vertex colours, or OBJ), `z`
    /// up: elevations are measured from its `xy` plane. Repeat it (with
    /// as many `--name`s, in the same order) to train several objects
    /// jointly into one model: their components are trained together, each
    /// object's renders are negatives of the others' components, and their
    /// scores are comparable (the paper's compatible components).
    #[arg(long, required = true)]
    pub(crate) mesh: Vec<PathBuf>,
    /// The object's name: the detections' label (and the model's name for
    /// one object). One per `--mesh`.
    #[arg(long, required = true)]
    pub(crate) name: Vec<String>,
    /// The model's name for several objects (default: their names joined
    /// by `-`).
    #[arg(long)]
    pub(crate) model_name: Option<String>,
    /// Folder of background photographs without the object (JPEG or PNG):
    /// pasted behind and over the renders, and the negatives. Optional
    /// with `--photos` (route `boxes`: the renders are pasted into the
    /// photographs; given, its first `--negatives` images are negatives
    /// too).
    #[arg(long, required_unless_present = "photos")]
    pub(crate) backgrounds: Option<PathBuf>,
    /// The weights file to write (default `models/MODEL.safetensors`, MODEL
    /// the model's name).
    #[arg(long)]
    pub(crate) out: Option<PathBuf>,
    /// Folder for the renders (default `out/mesh/MODEL`; one subfolder
    /// per object when there are several).
    #[arg(long)]
    pub(crate) work: Option<PathBuf>,
    /// Renders of each object (default 400; with `--photos`, route
    /// `boxes`: 100).
    #[arg(long)]
    pub(crate) renders: Option<usize>,
    /// Viewpoint components (templates) of each object.
    #[arg(long, default_value_t = RenderParams::default().components)]
    pub(crate) components: usize,
    /// Camera elevation range above the mesh's `xy` plane, degrees.
    #[arg(long, value_parser = parse_pair, default_value = "0,80", allow_negative_numbers = true)]
    pub(crate) elevation: [f64; 2],
    /// Largest in-plane camera rotation, degrees either way.
    #[arg(long, default_value_t = RenderParams::default().roll)]
    pub(crate) roll: f64,
    /// Range of the object's longest box side in the renders, pixels
    /// (default 40,110; with `--photos`, route `boxes`: the range of the
    /// photographs' boxes' longer sides, so that renders and photographs
    /// share the pyramid's levels).
    #[arg(long, value_parser = parse_pair)]
    pub(crate) size: Option<[f64; 2]>,
    /// Share of the renders with an occluder.
    #[arg(long, default_value_t = RenderParams::default().occluded_share)]
    pub(crate) occluded_share: f64,
    /// Range of the share of the object's box an occluder covers.
    #[arg(long, value_parser = parse_pair, default_value = "0.1,0.6")]
    pub(crate) occlusion: [f64; 2],
    /// Share of the occluders filled with a patch of another background
    /// photograph (the rest: a smooth colour).
    #[arg(long, default_value_t = RenderParams::default().patch_occluders)]
    pub(crate) patch_occluders: f64,
    /// Meshes of other objects (PLY/OBJ) that hide part of the renders
    /// (repeat the flag; an object's own mesh file is skipped among its
    /// occluders, so one list serves every object).
    #[arg(long)]
    pub(crate) occluder_mesh: Vec<PathBuf>,
    /// Share of the occluders that are renders of the `--occluder-mesh`es
    /// (the rest as `--patch-occluders` says).
    #[arg(long, default_value_t = RenderParams::default().mesh_occluders)]
    pub(crate) mesh_occluders: f64,
    /// Background images used as negatives (the first ones by name).
    #[arg(long, default_value_t = 50)]
    pub(crate) negatives: usize,
    /// Seed of the renders.
    #[arg(long, default_value_t = 1)]
    pub(crate) render_seed: u64,
    /// Train as `train --sources views` does from photographed views: the
    /// `--renders` are drawn without occluders and become views, grouped
    /// by appearance and shape into `--components`, each made into
    /// `--per-view` training photographs (shifted, scaled, turned,
    /// jittered, half of them on a crop of a background photograph,
    /// `--occluded-share` with an occluder covering `--occlusion` of the
    /// box: smooth colours, or for a `--patch-occluders` share background
    /// patches), and the renders with the object painted over are
    /// negatives. One object per model.
    #[arg(long)]
    pub(crate) from_views: bool,
    /// With `--from-views`: training photographs made from each view.
    #[arg(long, default_value_t = 3, requires = "from_views")]
    pub(crate) per_view: usize,
    /// Photographs of the object's scene with boxes drawn on them: a COCO
    /// file whose boxes of the category named `--name` are the object's
    /// full extent (no masks needed; `file_name`s relative to the file's
    /// folder; `iscrowd` boxes are ignored), e.g. from
    /// `lmo_boxes_coco.py`. Renders and boxes train together (see
    /// `--photo-route`); each box's component and visible cells are
    /// imputed under the model (latent, `--latent-rounds` times). The
    /// photographs' places outside the boxes are hard negatives, and
    /// photographs without the object are negatives. One object per model.
    #[arg(long, conflicts_with = "from_views")]
    pub(crate) photos: Option<PathBuf>,
    /// With `--photos`: how renders and photographs train together.
    /// `boxes` (default): the renders are drawn over the photographs (each
    /// with the object's boxes taken out) and train beside the
    /// photographs' boxes as more box-labelled photographs, as `train
    /// --coco` trains box-only photographs (visibility and component
    /// latent, learned cells, box correction); each component's start
    /// poses are the rotations of the renders imputed to it.
    /// `renders-first`: the renders over the `--backgrounds` train the
    /// components first, then the boxes are imputed into them.
    #[arg(long, value_enum, default_value_t = PhotoRoute::Boxes, requires = "photos")]
    pub(crate) photo_route: PhotoRoute,
    /// With `--photos`: rounds of imputing the boxes and retraining.
    #[arg(long, default_value_t = MultiViewParams::default().latent_rounds, requires = "photos")]
    pub(crate) latent_rounds: usize,
    /// With `--photos`: how a box's visible part is labelled. `latent`:
    /// its visible cells are imputed under the model with its component;
    /// `full`: the whole box is visible and only its component is imputed.
    #[arg(long, value_enum, default_value_t = PhotoVisibility::Latent, requires = "photos")]
    pub(crate) photo_visibility: PhotoVisibility,
    /// With `--photos`: share of the positives' weight in training carried
    /// by the photographs' boxes, between 0 and 1 (the renders carry the
    /// rest). Default: every box and render weighs the same.
    #[arg(long, requires = "photos")]
    pub(crate) photo_share: Option<f64>,
    /// With `--photos`, route `boxes`: keep the model trained with the
    /// renders without checking it. By default the object is also trained
    /// from the photographs alone, each scanning the photographs the box
    /// correction's folds held out (AUC, recall against false positives
    /// per image), and the renders stay only where their model finds more
    /// in at least 90% of 2,000 paired resamples of those photographs (a
    /// gain beyond the chance of which photographs were held out). The
    /// check adds the photographs-alone folds (and its full training where
    /// it wins).
    #[arg(long, requires = "photos")]
    pub(crate) keep_renders: bool,
    /// With `--photos`, route `boxes`: most training passes of each
    /// held-out fold (the box correction's and the check's, both sides
    /// alike; the full trainings keep theirs).
    #[arg(long, default_value_t = CHECK_FOLD_PASSES, requires = "photos")]
    pub(crate) fold_passes: usize,
    #[command(flatten)]
    pub(crate) settings: TrainSettings,
}

/// How renders and box-labelled photographs train together (`--photo-route`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub(crate) enum PhotoRoute {
    /// Renders drawn over the photographs train as more box photographs.
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
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub(crate) enum PhotoVisibility {
    /// The visible cells are imputed under the model (latent).
    Latent,
    /// The whole box is visible; only its component is imputed.
    Full,
}

/// "A,B" as two numbers.
pub(crate) fn parse_pair(text: &str) -> Result<[f64; 2], String> {
    let v: Vec<f64> = text
        .split(',')
        .map(|x| x.trim().parse::<f64>().map_err(|e| format!("{x:?}: {e}")))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [a, b] if a.is_finite() && b.is_finite() => Ok([a, b]),
        _ => Err(format!("expected two numbers A,B, got {text:?}")),
    }
}

/// Weights of the colour agreement compared by [`choose_colour_weight`].
const COLOUR_WEIGHTS: [f64; 6] = [0.0, 0.25, 0.5, 1.0, 2.0, 4.0];

/// A box `(x, y, width, height)` in pixels.
type BoxXywh = (f64, f64, f64, f64);

/// One object of a model trained from meshes.
struct Object {
    name: String,
    file: PathBuf,
    mesh: Mesh,
    colours: Option<Vec<[f32; 3]>>,
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
) -> Result<(f64, Vec<(f64, f64)>), Failure> {
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
        .map_err(Failure::input)?;
        samples.extend(set.samples);
    }
    let held: Vec<&ColorImage> = backgrounds.iter().rev().take(20).collect();
    pb.set_length((samples.len() + held.len()) as u64);
    let det = Detector::new(&model.views).map_err(Failure::input)?;
    let params = DetectParams {
        threshold: -1.5,
        max_detections: 20,
        ..model.meta.detection
    };
    // (score, colour agreement, true) of every detection.
    let mut found: Vec<(f64, f64, bool)> = Vec::new();
    let mut scan = |img: &ColorImage, truth: Option<(&String, BoxXywh)>| -> Result<(), Failure> {
        let pyr = FeaturePyramid::build(img, &model.meta.pyramid, &model.meta.segmentation)
            .map_err(Failure::input)?;
        let (dets, _) = det.detect(&pyr, &params).map_err(Failure::input)?;
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
        let img = crate::data::load_image(&s.image).map_err(Failure::input)?;
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
            let ranked: Vec<(f64, bool)> = found.iter().map(|&(s, c, t)| (s + w * c, t)).collect();
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
) -> Result<(), Failure> {
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
    std::fs::write(&path, serde_json::to_string(&coco).map_err(Failure::io)?)
        .map_err(|e| Failure::io(format!("{}: {e}", path.display())))
}

/// The JPEG and PNG images of a folder, sorted by name (background or
/// negative scenes).
pub(crate) fn image_files(dir: &Path) -> Result<Vec<PathBuf>, Failure> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| Failure::io(format!("{}: {e}", dir.display())))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|x| x.to_str())
                .is_some_and(|x| matches!(x.to_ascii_lowercase().as_str(), "jpg" | "jpeg" | "png"))
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(Failure::input(format!(
            "{}: no JPEG or PNG images",
            dir.display()
        )));
    }
    Ok(files)
}

pub(crate) fn run_mesh(args: &MeshArgs) -> Result<(), Failure> {
    let start = std::time::Instant::now();
    let boxes_route = args.photos.is_some() && args.photo_route == PhotoRoute::Boxes;
    let features = if args.photos.is_some() {
        PHOTO_FEATURES
    } else {
        FeatureKind::Hog
    };
    let (mut params, _) = args.settings.params(features)?;
    // Route `boxes` sets its scales as `train --coco` does (from the
    // photographs' boxes), in `train_photographs`.
    let mesh_scales = !boxes_route && args.settings.config.is_none();
    // Templates of about 12 cells (smaller ones fit even their own
    // training renders badly: 50% top-1 with 5-8 cells); upsampled levels
    // find objects down to 40% of that (training must see those levels
    // too: a model trained up to 1.4 and run up to 2.5 scored AUC 0.000 on
    // LM-O ape, its upsampled levels full of false positives), several
    // octaves cover a wide range of sizes (unless the flags or the config
    // say otherwise).
    if args.settings.levels_per_octave.is_none() && mesh_scales {
        params.pyramid.levels_per_octave = 5;
    }
    if args.settings.max_scale.is_none() && mesh_scales {
        params.pyramid.max_scale = 2.5;
    }
    if args.settings.min_scale.is_none() && mesh_scales {
        params.pyramid.min_scale = 0.125;
    }
    // Objects in photographs are small (LM-O: 37-343 px, median about
    // 60), and the detector meets them on upsampled levels: the renders
    // are drawn at such sizes and the templates 1.4 times larger, so that
    // training sees the objects on the same upsampled levels (LM-O ape:
    // 80-180 px renders at template scale 0.8 AUC 0.259, 40-110 px at 1.4
    // AUC 0.319).
    if args.settings.template_scale.is_none() && mesh_scales {
        params.template_scale = 1.4;
    }
    // The renders never cut the object at the image border, so the model
    // learns nothing about truncated boxes: allowing them, boxes hanging
    // off LM-O's bottom border scored 5.7 (AUC 0.000); without, 0.099.
    if mesh_scales {
        params.max_truncation = 0.0;
    }
    // With `--photos`: the boxes' share of the positives' weight.
    params.box_share = args.photo_share;
    params.validate().map_err(Failure::input)?;
    let mut render = RenderParams {
        renders: args.renders.unwrap_or(if boxes_route {
            PHOTO_RENDERS
        } else {
            RenderParams::default().renders
        }),
        components: args.components,
        elevation: args.elevation,
        roll: args.roll,
        size: args.size.unwrap_or(RenderParams::default().size),
        occluded_share: args.occluded_share,
        occlusion: args.occlusion,
        patch_occluders: args.patch_occluders,
        mesh_occluders: args.mesh_occluders,
        seed: args.render_seed,
        ..RenderParams::default()
    };
    render.validate().map_err(Failure::input)?;
    if args.mesh.len() != args.name.len() {
        return Err(Failure::input(format!(
            "{} --mesh but {} --name: give one name per mesh, in the same order",
            args.mesh.len(),
            args.name.len()
        )));
    }
    let mut seen = std::collections::HashSet::new();
    if let Some(dup) = args.name.iter().find(|n| !seen.insert(n.as_str())) {
        return Err(Failure::input(format!("--name {dup} given twice")));
    }
    if args.from_views && args.mesh.len() > 1 {
        return Err(Failure::input(
            "--from-views trains one object per model: run it once per --mesh",
        ));
    }
    if args.fold_passes == 0 {
        return Err(Failure::input("--fold-passes must be at least 1"));
    }
    if args.photos.is_some() && args.mesh.len() > 1 {
        return Err(Failure::input(
            "--photos trains one object per model: run it once per --mesh",
        ));
    }
    // The photographs first: a bad file is refused before any rendering.
    let photos = match &args.photos {
        Some(file) => Some(photo_samples(file, &args.name[0])?),
        None => None,
    };
    // Route `boxes`: renders at the photographs' sizes. Renders smaller
    // than every box stretched the pyramid (LM-O cat, renders of 40-110 px
    // beside boxes of about 65: levels up to 2.70 instead of 1.70, 41 min
    // of training against 5 for the photographs alone).
    if let (Some(p), None, true) = (&photos, args.size, boxes_route) {
        if let Some(range) = box_size_range(&p.boxes) {
            // No larger than a render holds.
            let most = 0.9 * render.width.min(render.height) as f64;
            let range = [range[0].min(most), range[1].min(most)];
            render.size = range;
            eprintln!(
                "{}: renders at {:.0}-{:.0} px (the photographs' boxes' longer sides)",
                args.name[0], range[0], range[1]
            );
            render.validate().map_err(Failure::input)?;
        }
    }
    let model_name = match (&args.model_name, &args.name[..]) {
        (Some(m), _) => m.clone(),
        (None, [one]) => one.clone(),
        (None, names) => names.join("-"),
    };
    let objects: Vec<Object> = args
        .mesh
        .iter()
        .zip(&args.name)
        .map(|(file, name)| {
            let bytes =
                std::fs::read(file).map_err(|e| Failure::io(format!("{}: {e}", file.display())))?;
            let mesh = Mesh::parse(&bytes)
                .map_err(|e| Failure::input(format!("{}: {e}", file.display())))?;
            let colours = Mesh::ply_vertex_colours(&bytes)
                .map_err(|e| Failure::input(format!("{}: {e}", file.display())))?;
            Ok(Object {
                name: name.clone(),
                file: file.clone(),
                mesh,
                colours,
            })
        })
        .collect::<Result<_, Failure>>()?;
    let occluders: Vec<(PathBuf, Occluder)> = args
        .occluder_mesh
        .iter()
        .map(|file| {
            let bytes =
                std::fs::read(file).map_err(|e| Failure::io(format!("{}: {e}", file.display())))?;
            let mesh = Mesh::parse(&bytes)
                .and_then(|m| m.validate().map(|()| m))
                .map_err(|e| Failure::input(format!("{}: {e}", file.display())))?;
            let colours = Mesh::ply_vertex_colours(&bytes)
                .map_err(|e| Failure::input(format!("{}: {e}", file.display())))?;
            Ok((file.clone(), Occluder { mesh, colours }))
        })
        .collect::<Result<_, Failure>>()?;
    let files =
        match &args.backgrounds {
            Some(dir) => image_files(dir)?,
            None if boxes_route => Vec::new(),
            None => return Err(Failure::input(
                "--photo-route renders-first draws the renders over --backgrounds: give the folder",
            )),
        };
    // Route `boxes`: the renders are drawn over the user's photographs,
    // the object taken out of them.
    let backgrounds: Vec<ColorImage> = match &photos {
        Some(p) if boxes_route => p.scenes()?,
        _ => files
            .iter()
            .map(|p| pose_data::background_image(p))
            .collect::<Result<_, _>>()?,
    };
    let work = args
        .work
        .clone()
        .unwrap_or_else(|| PathBuf::from("out/mesh").join(&model_name));
    // Every object's renders, their components numbered after the
    // previous objects'.
    let mut samples: Vec<Sample> = Vec::new();
    let mut directions = Vec::new();
    let mut rotations = Vec::new();
    let mut poses = Vec::new();
    for (k, o) in objects.iter().enumerate() {
        let sub = if objects.len() > 1 {
            work.join(&o.name)
        } else {
            work.clone()
        };
        let first_view = directions.len();
        let pb = progress_bar(render.renders as u64, &format!("{}: rendering", o.name));
        let seeded = RenderParams {
            seed: render.seed.wrapping_add(104_729 * k as u64),
            // Views are clean: the occluders come with the augmentation.
            occluded_share: if args.from_views {
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
            &backgrounds,
            &mine,
            &seeded,
            &sub,
            &pb,
        )
        .map_err(Failure::input)?;
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
        directions.extend(set.directions);
        rotations.extend(set.rotations);
        poses.extend(set.poses);
        samples.extend(set.samples);
    }
    let render_s = start.elapsed().as_secs_f64();
    // The negatives as they are (downsized copies at the renders' size
    // found less: LM-O ape AUC 0.067 against 0.123).
    let negatives: Vec<Sample> = files
        .iter()
        .take(args.negatives)
        .map(|p| Sample {
            image: p.clone(),
            id: p
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default(),
            annotation: None,
        })
        .collect();
    // Pyramids without their pixels: the renders' and negatives' images
    // and per-pixel segments are a quarter of the memory, and training
    // needs none of them (LM-O cat: 3.79 GiB peak with them).
    // Route `boxes` keeps the pixels, as `train --coco` does (its box
    // correction detects on held-out photographs).
    let cache = if boxes_route {
        PyramidCache::default()
    } else {
        PyramidCache::lean()
    };
    let pb = progress_bar(0, &format!("{model_name}: training"));
    let (mut model, report) = if let (Some(photos), true) = (&photos, boxes_route) {
        let route = train_with_photo_boxes(
            &args.name[0],
            photos,
            &samples,
            &poses,
            &objects[0].mesh,
            &negatives,
            args,
            &cache,
            &params,
            &pb,
        )?;
        directions = route.directions;
        rotations = route.rotations;
        (route.model, route.report)
    } else if args.from_views {
        let views_route = train_from_views(
            &objects[0],
            &samples,
            &poses,
            &negatives,
            &backgrounds,
            args,
            &cache,
            &params,
            &pb,
        )?;
        directions = views_route.directions;
        rotations = views_route.rotations;
        (views_route.model, views_route.report)
    } else if let Some(photos) = &photos {
        let fixed: Vec<&Sample> = samples
            .iter()
            .chain(&negatives)
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
            latent_rounds: args.latent_rounds,
            latent_visibility: args.photo_visibility == PhotoVisibility::Latent,
            ..MultiViewParams::default()
        };
        let (mut m, mut r) =
            train_sources(&args.name[0], src, &cache, &params, &mv, &pb).map_err(Failure::input)?;
        for v in &mut m.meta.viewpoints {
            v.views.clear();
        }
        for (i, round) in r.imputation.iter().enumerate() {
            eprintln!(
                "{}: round {}: {} boxes imputed ({} fit no component), {} changed component, {:.2} of their cells visible",
                args.name[0],
                i + 1,
                round.boxes,
                round.unfit,
                round.component_changes,
                round.mean_visible
            );
        }
        (m, r.rounds.pop().unwrap_or_default())
    } else {
        let refs: Vec<&Sample> = samples.iter().chain(&negatives).collect();
        let labels: Vec<&str> = args.name.iter().map(String::as_str).collect();
        train_joint(&model_name, &labels, &refs, &cache, &params, &pb).map_err(Failure::input)?
    };
    pb.finish_and_clear();
    drop(cache);
    eprintln!(
        "{model_name}: full-search violations {:?}, min-cuts {:?}",
        report.full_violation, report.full_min_cuts
    );
    for ((view, dir), rots) in model
        .meta
        .viewpoints
        .iter_mut()
        .zip(&directions)
        .zip(&rotations)
    {
        view.direction = Some(*dir);
        view.rotations = rots.clone();
    }
    // Route `boxes` trains as `train --coco` does, without the colour
    // agreement (it was chosen on renders, which its photographs outrank).
    if !boxes_route {
        let pb = progress_bar(0, &format!("{model_name}: colour weight"));
        let (weight, table) = choose_colour_weight(
            &model,
            &objects,
            &backgrounds,
            &render,
            &work.join("check"),
            &pb,
        )?;
        pb.finish_and_clear();
        eprintln!(
            "{model_name}: colour weight {weight} (AUC on held-out renders per weight: {})",
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
    }
    if let Some(obj) = model.meta.provenance.as_object_mut() {
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
                "occluder_meshes": args
                    .occluder_mesh
                    .iter()
                    .map(|f| f.display().to_string())
                    .collect::<Vec<_>>(),
                "render": render,
                "from_views": args.from_views,
                "photos": photos.as_ref().map(|p| serde_json::json!({
                    "file": p.file.display().to_string(),
                    "boxes": p.boxes.len(),
                    "negatives": p.negatives.len(),
                    "skipped": p.skipped,
                    "route": args.photo_route,
                    "latent_rounds": args.latent_rounds,
                    "fold_passes": args.fold_passes,
                    "visibility": args.photo_visibility,
                    "share": args.photo_share,
                })),
                "backgrounds": args.backgrounds.as_ref().map(|b| b.display().to_string()),
                "negatives": negatives.len(),
            }),
        );
    }
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("models").join(format!("{model_name}.safetensors")));
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| Failure::io(format!("{}: {e}", dir.display())))?;
    }
    model.save(&out).map_err(Failure::io)?;
    let views: Vec<String> = model
        .meta
        .viewpoints
        .iter()
        .map(|v| format!("{} {}x{}", v.label, v.rows, v.cols))
        .collect();
    println!(
        "{model_name}: {} components ({}), {} positives, {} negatives, {} passes, converged {}, render {:.0} s, train {:.0} s, total {:.0} s -> {}",
        views.len(),
        views.join(", "),
        report.positives,
        report.negatives,
        report.passes,
        report.converged,
        render_s,
        report.seconds,
        start.elapsed().as_secs_f64(),
        out.display()
    );
    Ok(())
}

#[path = "mesh_routes.rs"]
mod routes;
use routes::*;
