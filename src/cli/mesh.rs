//! `sdhop-train mesh`: a detector of an object from its mesh alone, or
//! with boxed photographs of it; the route is
//! [`crate::train::routes::mesh::train_mesh`]. This command parses the
//! flags into its settings, saves the weights file and prints.

use super::*;
use crate::train::mesh::RenderParams;
use crate::train::multiview::MultiViewParams;
use crate::train::routes::mesh::{
    train_mesh, MeshSettings, MeshTraining, PhotoRoute, PhotoVisibility, MESH_NEGATIVES,
    VIEW_PHOTOS,
};
use crate::train::routes::mesh_photos::CHECK_FOLD_PASSES;

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
    /// Default 0,80.
    #[arg(long, value_parser = parse_pair, allow_negative_numbers = true)]
    pub(crate) elevation: Option<[f64; 2]>,
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
    /// Default 0.1,0.6.
    #[arg(long, value_parser = parse_pair)]
    pub(crate) occlusion: Option<[f64; 2]>,
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
    #[arg(long, default_value_t = MESH_NEGATIVES)]
    pub(crate) negatives: usize,
    /// Seed of the renders.
    #[arg(long, default_value_t = RenderParams::default().seed)]
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
    #[arg(long, default_value_t = VIEW_PHOTOS, requires = "from_views")]
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

impl MeshArgs {
    /// The route's settings from the flags.
    fn settings(&self) -> MeshSettings {
        let d = MeshSettings::default();
        MeshSettings {
            mesh: self.mesh.clone(),
            name: self.name.clone(),
            model_name: self.model_name.clone(),
            backgrounds: self.backgrounds.clone(),
            work: self.work.clone(),
            renders: self.renders,
            components: self.components,
            elevation: self.elevation.unwrap_or(d.elevation),
            roll: self.roll,
            size: self.size,
            occluded_share: self.occluded_share,
            occlusion: self.occlusion.unwrap_or(d.occlusion),
            patch_occluders: self.patch_occluders,
            occluder_mesh: self.occluder_mesh.clone(),
            mesh_occluders: self.mesh_occluders,
            negatives: self.negatives,
            render_seed: self.render_seed,
            from_views: self.from_views,
            per_view: self.per_view,
            photos: self.photos.clone(),
            photo_route: self.photo_route,
            latent_rounds: self.latent_rounds,
            photo_visibility: self.photo_visibility,
            photo_share: self.photo_share,
            keep_renders: self.keep_renders,
            fold_passes: self.fold_passes,
            settings: self.settings.clone(),
        }
    }
}

pub(crate) fn run_mesh(args: &MeshArgs) -> Result<(), Failure> {
    let start = std::time::Instant::now();
    let MeshTraining {
        model,
        report,
        name,
        render_seconds,
    } = train_mesh(&args.settings())?;
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("models").join(format!("{name}.safetensors")));
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
        "{name}: {} components ({}), {} positives, {} negatives, {} passes, converged {}, render {:.0} s, train {:.0} s, total {:.0} s -> {}",
        views.len(),
        views.join(", "),
        report.positives,
        report.negatives,
        report.passes,
        report.converged,
        render_seconds,
        report.seconds,
        start.elapsed().as_secs_f64(),
        out.display()
    );
    Ok(())
}
