//! The companion command-line tool: train SD-HOP models (structured SVM),
//! cross-validate and evaluate them on CMU_KO8, and run the detector on an
//! image or on a synthetic scene it generates itself.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use sdhop::dataset::{load_coco, Sample};
use sdhop::model::Model;
use sdhop::pipeline::{
    detect_image, overlay, DetectOptions, DetectResponse, MaskMode, DEFAULT_MAX_PIXELS,
};
use sdhop::synth::{hand_model, scene, HandModelParams, SceneParams, SynthObject};
use sdhop::train::ko8::{
    above_threshold, choose_threshold, cross_validate, detect_all, score, selection_key,
    threshold_sweep, train_objects, EvalDetect, Evaluation, FoldModels, Ko8Data, NegativeSet,
};
use sdhop::train::loss::LossKind;
use sdhop::train::{progress_bar, train_model, PyramidCache, TrainParams};
use sdhop::vision::detect::box_iou;
use sdhop::vision::energy::PairwiseMode;
use sdhop::vision::image::ColorImage;
use sdhop::vision::mask::Mask;

#[derive(Parser)]
#[command(
    name = "sdhop-train",
    version,
    about = "SD-HOP occlusion-aware detector: companion tool"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(clap::Args)]
struct DetectArgs {
    /// Image to scan (PNG or JPEG).
    image: PathBuf,
    /// Weights file(s); repeat for several models.
    #[arg(long = "model", short = 'm', required_unless_present = "models_dir")]
    models: Vec<PathBuf>,
    /// Load every `*.safetensors` in this folder.
    #[arg(long)]
    models_dir: Option<PathBuf>,
    /// Score threshold (default: each model's own).
    #[arg(long, allow_negative_numbers = true)]
    threshold: Option<f64>,
    /// Maximum detections (default: each model's own).
    #[arg(long)]
    max_detections: Option<usize>,
    /// Masks to include.
    #[arg(long, value_enum, default_value_t = MaskMode::Refined)]
    masks: MaskMode,
    /// Disable exact pruning (same result, slower; for checking).
    #[arg(long)]
    no_prune: bool,
    /// Write the JSON here instead of standard output.
    #[arg(long, short = 'o')]
    output: Option<PathBuf>,
    /// Write a PNG with boxes and masks drawn over the image.
    #[arg(long)]
    overlay: Option<PathBuf>,
    /// Refuse images with more pixels than this.
    #[arg(long, default_value_t = DEFAULT_MAX_PIXELS)]
    max_pixels: usize,
}

#[derive(clap::Args)]
struct DemoArgs {
    /// Folder for the scene, the model, the JSON and the overlay.
    #[arg(long, default_value = "out/demo")]
    out: PathBuf,
    /// Scene seed.
    #[arg(long, default_value_t = 7)]
    seed: u64,
    #[arg(long, default_value_t = 640)]
    width: usize,
    #[arg(long, default_value_t = 480)]
    height: usize,
}

/// Every training setting; flags override the `--config` JSON file.
#[derive(clap::Args, Clone)]
struct TrainSettings {
    /// JSON file with any of the training settings (see `TrainParams` in
    /// the docs: c, k, template_scale, template, pyramid, segmentation,
    /// max_truncation, epsilon, max_passes, max_inner, init_locations,
    /// mining_passes, mining_budget, cache_size, positive_share, loss, hop,
    /// pairwise, pair_mode, seed, threshold).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Regularisation constant C.
    #[arg(long)]
    c: Option<f64>,
    /// Standard clique size K of the higher-order potentials.
    #[arg(long)]
    k: Option<usize>,
    /// Template size as a fraction of the median training box.
    #[arg(long)]
    template_scale: Option<f64>,
    /// Template size in cells, ROWSxCOLS (overrides --template-scale).
    #[arg(long, value_parser = parse_template)]
    template: Option<[usize; 2]>,
    /// Pyramid levels per octave.
    #[arg(long)]
    levels_per_octave: Option<u32>,
    /// Smallest pyramid scale.
    #[arg(long)]
    min_scale: Option<f32>,
    /// Felzenszwalb-Huttenlocher k (segment size preference).
    #[arg(long)]
    seg_k: Option<f32>,
    /// Stopping tolerance of the cutting-plane algorithm.
    #[arg(long)]
    epsilon: Option<f64>,
    /// Full searches over every location, at most.
    #[arg(long)]
    max_passes: Option<usize>,
    /// Iterations over cached locations per full search, at most.
    #[arg(long)]
    max_inner: Option<usize>,
    /// Min-cuts per image in hard-example mining passes.
    #[arg(long)]
    mining_budget: Option<usize>,
    /// First full searches that mine hard examples with a min-cut budget
    /// instead of being exact (default 0: every full search is exact).
    #[arg(long)]
    mining_passes: Option<usize>,
    /// Most locations cached per image between full searches.
    #[arg(long)]
    cache_size: Option<usize>,
    /// Random seed (initial locations).
    #[arg(long)]
    seed: Option<u64>,
    /// Loss: sd-hop (eq. 3) or gao (ablation).
    #[arg(long, value_enum)]
    loss: Option<LossKind>,
    /// Ablation: no higher-order potentials.
    #[arg(long)]
    no_hop: bool,
    /// Ablation: no pairwise term.
    #[arg(long)]
    no_pairwise: bool,
    /// Ablation: pairwise terms only between neighbouring cells along an
    /// image edge, as Gao et al. 2011 (default: every 4-connected pair).
    #[arg(long)]
    edge_pairwise: bool,
    /// Detection threshold saved in the models.
    #[arg(long, allow_negative_numbers = true)]
    threshold: Option<f64>,
    /// Images of each other object used as negatives.
    #[arg(long, default_value_t = 10)]
    other_negatives: usize,
    /// Negative scenes used (from negative/).
    #[arg(long, default_value_t = 100)]
    negative_scenes: usize,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
}

fn parse_template(s: &str) -> Result<[usize; 2], String> {
    let (r, c) = s.split_once('x').ok_or("expected ROWSxCOLS")?;
    let r: usize = r.parse().map_err(|_| "bad rows")?;
    let c: usize = c.parse().map_err(|_| "bad cols")?;
    Ok([r, c])
}

impl TrainSettings {
    fn params(&self) -> Result<(TrainParams, NegativeSet), Failure> {
        let mut p = match &self.config {
            Some(path) => {
                let text = std::fs::read_to_string(path)
                    .map_err(|e| Failure::io(format!("{}: {e}", path.display())))?;
                serde_json::from_str(&text)
                    .map_err(|e| Failure::input(format!("{}: {e}", path.display())))?
            }
            None => TrainParams::default(),
        };
        if let Some(v) = self.c {
            p.c = v;
        }
        if let Some(v) = self.k {
            p.k = v;
        }
        if let Some(v) = self.template_scale {
            p.template_scale = v;
        }
        if self.template.is_some() {
            p.template = self.template;
        }
        if let Some(v) = self.levels_per_octave {
            p.pyramid.levels_per_octave = v;
        }
        if let Some(v) = self.min_scale {
            p.pyramid.min_scale = v;
        }
        if let Some(v) = self.seg_k {
            p.segmentation.k = v;
        }
        if let Some(v) = self.epsilon {
            p.epsilon = v;
        }
        if let Some(v) = self.max_passes {
            p.max_passes = v;
        }
        if let Some(v) = self.max_inner {
            p.max_inner = v;
        }
        if let Some(v) = self.mining_budget {
            p.mining_budget = v;
        }
        if let Some(v) = self.mining_passes {
            p.mining_passes = v;
        }
        if let Some(v) = self.cache_size {
            p.cache_size = v;
        }
        if let Some(v) = self.seed {
            p.seed = v;
        }
        if let Some(v) = self.loss {
            p.loss = v;
        }
        if let Some(v) = self.threshold {
            p.threshold = v;
        }
        p.hop &= !self.no_hop;
        p.pairwise &= !self.no_pairwise;
        if self.edge_pairwise {
            p.pair_mode = PairwiseMode::Edges;
        }
        p.validate().map_err(Failure::input)?;
        if let Some(t) = self.threads {
            rayon::ThreadPoolBuilder::new()
                .num_threads(t)
                .build_global()
                .map_err(Failure::io)?;
        }
        let neg = NegativeSet {
            scenes: self.negative_scenes,
            per_other_object: self.other_negatives,
        };
        Ok((p, neg))
    }
}

#[derive(clap::Args)]
struct TrainArgs {
    /// CMU_KO8 root (with single/ and negative/).
    #[arg(long, required_unless_present = "coco")]
    ko8: Option<PathBuf>,
    /// COCO-style JSON of your own objects (see the README).
    #[arg(long, conflicts_with = "ko8", requires_all = ["images", "category"])]
    coco: Option<PathBuf>,
    /// Folder the COCO file names are relative to.
    #[arg(long)]
    images: Option<PathBuf>,
    /// COCO category to train (repeat for several).
    #[arg(long)]
    category: Vec<String>,
    /// Objects to train (CMU_KO8; default all eight).
    #[arg(long, value_delimiter = ',')]
    objects: Vec<String>,
    /// Folder for the weights files (one per object, named after it).
    #[arg(long, default_value = "models")]
    out: PathBuf,
    /// Cross-validation figures (JSON written by `cv`) to store in the
    /// models' metadata.
    #[arg(long)]
    cv_report: Option<PathBuf>,
    #[command(flatten)]
    settings: TrainSettings,
}

#[derive(clap::Args)]
struct CvArgs {
    /// CMU_KO8 root.
    #[arg(long)]
    ko8: PathBuf,
    #[arg(long, value_delimiter = ',')]
    objects: Vec<String>,
    #[arg(long, default_value_t = 5)]
    folds: usize,
    /// Values of C to compare (the best mean cross-object AUC wins).
    #[arg(long, value_delimiter = ',', allow_negative_numbers = false)]
    c_values: Vec<f64>,
    /// Folder for the report, the per-image JSON responses and the plot.
    #[arg(long, default_value = "out/cv")]
    out: PathBuf,
    /// Detections kept per image (as the acceptance procedure asks).
    #[arg(long, default_value_t = 20)]
    max_detections: usize,
    /// Run only these folds (numbered from 0; all by default).
    #[arg(long, value_delimiter = ',')]
    only_folds: Vec<usize>,
    /// Save each fold's models in DIR/fold-F/ (DIR/c-C/fold-F/ with several
    /// --c-values).
    #[arg(long, value_name = "DIR", conflicts_with = "load_models")]
    save_models: Option<PathBuf>,
    /// Load each fold's models from DIR/fold-F/ (saved by an earlier run
    /// with the same folds) instead of training: compares detection
    /// settings such as --detect-threshold without training again.
    #[arg(long, value_name = "DIR")]
    load_models: Option<PathBuf>,
    /// Detection threshold used in the evaluation (default: the models').
    /// Every threshold from it up to 1 in steps of 0.125 is then scored on
    /// the same detections, and the highest whose figures are within
    /// --threshold-tolerance of the best is chosen.
    #[arg(long, allow_negative_numbers = true)]
    detect_threshold: Option<f64>,
    /// How much of the selection figure (mean cross-object AUC less a tenth
    /// of the refined segmentation error) a higher, faster threshold may
    /// give up.
    #[arg(long, default_value_t = 0.002)]
    threshold_tolerance: f64,
    #[command(flatten)]
    settings: TrainSettings,
}

#[derive(clap::Args)]
struct AnnotateArgs {
    /// Folder of weights files (each named after its object).
    #[arg(long, default_value = "models")]
    models_dir: PathBuf,
    /// Report written by `cv`.
    #[arg(long)]
    cv_report: PathBuf,
}

#[derive(clap::Args)]
struct EvalArgs {
    /// CMU_KO8 root.
    #[arg(long)]
    ko8: PathBuf,
    /// Folder of weights files to evaluate.
    #[arg(long, default_value = "models")]
    models_dir: PathBuf,
    #[arg(long, value_delimiter = ',')]
    objects: Vec<String>,
    /// Folder for the figures, the per-image JSON responses and the plot.
    #[arg(long, default_value = "out/eval")]
    out: PathBuf,
    #[arg(long, default_value_t = 20)]
    max_detections: usize,
    /// Only every n-th image of each object (a quick check).
    #[arg(long, default_value_t = 1)]
    every: usize,
    /// Detection threshold (default: each model's own).
    #[arg(long, allow_negative_numbers = true)]
    detect_threshold: Option<f64>,
}

#[derive(clap::Args)]
struct PoseArgs {
    /// The image (PNG or JPEG).
    #[arg(long)]
    image: PathBuf,
    /// The object's mesh (OBJ or PLY), in the units of the translation.
    #[arg(long)]
    mesh: PathBuf,
    /// JSON parameters: {"intrinsics": {"fx", "fy", "cx", "cy"},
    /// "initial_pose": {"rotation": [[3x3]], "translation": [x, y, z]},
    /// "model": NAME, "mask": "detect" | "provided" | "none",
    /// "max_iterations": N}; the pose is camera-from-object.
    #[arg(long)]
    params: PathBuf,
    /// Visibility mask (PNG, non-zero = visible) for "mask": "provided".
    #[arg(long)]
    mask: Option<PathBuf>,
    /// Folder of detector models for "mask": "detect".
    #[arg(long, default_value = "models")]
    models_dir: PathBuf,
    /// Largest image, in pixels.
    #[arg(long, default_value_t = DEFAULT_MAX_PIXELS)]
    max_pixels: usize,
}

#[derive(clap::Args)]
struct PoseBackgrounds {
    /// Folder of background photographs (JPEG or PNG, resized to 640x480),
    /// e.g. the CMU_KO8 negatives.
    #[arg(long)]
    backgrounds: PathBuf,
    /// The first N backgrounds (by name) are for training; the benchmark
    /// renders over the others.
    #[arg(long, default_value_t = 50)]
    train_backgrounds: usize,
    /// Objects (default both: box, bottle).
    #[arg(long, value_delimiter = ',')]
    objects: Vec<String>,
}

#[derive(clap::Args)]
struct PoseDataArgs {
    #[command(flatten)]
    bg: PoseBackgrounds,
    /// Training renders per object (a third unoccluded, the rest 10-60%
    /// hidden).
    #[arg(long, default_value_t = 360)]
    scenes: usize,
    /// Folder for `coco.json` and `images/`.
    #[arg(long, default_value = "out/pose-data")]
    out: PathBuf,
}

#[derive(clap::Args)]
struct PoseBenchArgs {
    #[command(flatten)]
    bg: PoseBackgrounds,
    /// Scenes per object and condition (unoccluded; 20-60% hidden).
    #[arg(long, default_value_t = 100)]
    scenes: usize,
    /// Detector models of the objects (trained on `pose-data`); without
    /// them the SD-HOP mask is left out.
    #[arg(long, default_value = "out/pose-data/models")]
    models_dir: PathBuf,
    /// Write every outcome and the summaries here as JSON.
    #[arg(long)]
    report: Option<PathBuf>,
}

#[derive(Subcommand)]
enum Command {
    /// Train one model per object (CMU_KO8 or a COCO-style file) and save
    /// them as weights files.
    Train(TrainArgs),
    /// Cross-validate training on CMU_KO8 (k folds, every object), choose C,
    /// and report AUC (per-object and cross-object) and segmentation errors.
    Cv(CvArgs),
    /// Evaluate weights files on CMU_KO8 images: figures, JSON and a plot.
    Eval(EvalArgs),
    /// Store the figures of a `cv` report in the models' metadata (for
    /// models trained with the same settings without `--cv-report`).
    Annotate(AnnotateArgs),
    /// Detect objects in one image; prints the detection JSON of `POST /detect`.
    Detect(DetectArgs),
    /// Refine an object's 3-D pose from an image and its mesh (OR-IRLS with
    /// a detected or given visibility mask, or plain IRLS); prints the JSON
    /// of `POST /pose`.
    Pose(PoseArgs),
    /// Render the pose benchmark's objects over training backgrounds as a
    /// COCO training set (full boxes, visible masks) for `train --coco`.
    PoseData(PoseDataArgs),
    /// The occlusion pose benchmark: IRLS, OR-IRLS with the exact mask and
    /// OR-IRLS with the SD-HOP mask on held-out backgrounds; six mean
    /// errors and success rates.
    PoseBench(PoseBenchArgs),
    /// Generate a synthetic occluded scene and a hand-built model of its object,
    /// detect, and report box and mask accuracy against the exact truth.
    Demo(DemoArgs),
}

/// An error with the process exit code it maps to.
struct Failure {
    code: u8,
    message: String,
}

impl Failure {
    fn input(e: impl std::fmt::Display) -> Self {
        Self {
            code: 2,
            message: e.to_string(),
        }
    }
    fn io(e: impl std::fmt::Display) -> Self {
        Self {
            code: 1,
            message: e.to_string(),
        }
    }
}

/// Reads an image, checking its declared size before decoding it.
fn read_image(path: &Path, max_pixels: usize) -> Result<ColorImage, Failure> {
    let bytes = std::fs::read(path).map_err(|e| Failure::io(format!("{}: {e}", path.display())))?;
    let reader = || {
        image::ImageReader::new(std::io::Cursor::new(&bytes))
            .with_guessed_format()
            .map_err(|e| Failure::io(format!("{}: {e}", path.display())))
    };
    let (w, h) = reader()?.into_dimensions().map_err(|e| {
        Failure::input(format!(
            "{}: not a readable PNG or JPEG: {e}",
            path.display()
        ))
    })?;
    if (w as usize).saturating_mul(h as usize) > max_pixels {
        return Err(Failure::input(format!(
            "{}: image of {w}x{h} pixels exceeds the limit of {max_pixels}",
            path.display()
        )));
    }
    let img = reader()?
        .decode()
        .map_err(|e| Failure::input(format!("{}: cannot decode: {e}", path.display())))?;
    ColorImage::from_rgb8(&img.to_rgb8())
        .map_err(|e| Failure::input(format!("{}: {e}", path.display())))
}

fn load_models(args: &DetectArgs) -> Result<Vec<Model>, Failure> {
    let mut paths = args.models.clone();
    if let Some(dir) = &args.models_dir {
        paths.extend(model_paths(dir)?);
    }
    if paths.is_empty() {
        return Err(Failure::input("no model to run"));
    }
    paths
        .iter()
        .map(|p| Model::load(p).map_err(|e| Failure::input(format!("{}: {e}", p.display()))))
        .collect()
}

fn write_json(resp: &DetectResponse, out: Option<&Path>) -> Result<(), Failure> {
    let text = serde_json::to_string_pretty(resp).map_err(Failure::io)?;
    match out {
        Some(p) => {
            std::fs::write(p, text).map_err(|e| Failure::io(format!("{}: {e}", p.display())))
        }
        None => {
            println!("{text}");
            Ok(())
        }
    }
}

fn run_detect(args: &DetectArgs) -> Result<(), Failure> {
    let img = read_image(&args.image, args.max_pixels)?;
    let models = load_models(args)?;
    let refs: Vec<&Model> = models.iter().collect();
    let opts = DetectOptions {
        threshold: args.threshold,
        max_detections: args.max_detections,
        masks: args.masks,
        prune: !args.no_prune,
        max_pixels: args.max_pixels,
        ..DetectOptions::default()
    };
    let resp = detect_image(&img, &refs, &opts).map_err(Failure::input)?;
    if let Some(p) = &args.overlay {
        overlay(&img, &resp)
            .save(p)
            .map_err(|e| Failure::io(format!("{}: {e}", p.display())))?;
    }
    write_json(&resp, args.output.as_deref())
}

fn run_pose(args: &PoseArgs) -> Result<(), Failure> {
    use sdhop::pose::api::{estimate, mask_from_image, MaskSource, PoseParams};
    let img = read_image(&args.image, args.max_pixels)?;
    let read =
        |p: &Path| std::fs::read(p).map_err(|e| Failure::io(format!("{}: {e}", p.display())));
    let mesh = sdhop::pose::Mesh::parse(&read(&args.mesh)?)
        .map_err(|e| Failure::input(format!("{}: {e}", args.mesh.display())))?;
    let params: PoseParams = serde_json::from_slice(&read(&args.params)?)
        .map_err(|e| Failure::input(format!("{}: {e}", args.params.display())))?;
    let mask = match &args.mask {
        Some(p) => {
            let m = image::load_from_memory(&read(p)?)
                .map_err(|e| Failure::input(format!("{}: {e}", p.display())))?;
            Some(mask_from_image(&m))
        }
        None => None,
    };
    let models = if params.mask == Some(MaskSource::Detect) {
        model_paths(&args.models_dir)?
            .iter()
            .map(|p| Model::load(p).map_err(|e| Failure::input(format!("{}: {e}", p.display()))))
            .collect::<Result<Vec<_>, _>>()?
    } else {
        Vec::new()
    };
    let refs: Vec<&Model> = models.iter().collect();
    let resp = estimate(&img, &mesh, &params, mask, &refs).map_err(Failure::input)?;
    println!(
        "{}",
        serde_json::to_string_pretty(&resp).map_err(Failure::io)?
    );
    Ok(())
}

impl PoseBackgrounds {
    /// The chosen objects and the background files: training ones, then
    /// the benchmark's.
    #[allow(clippy::type_complexity)]
    fn load(
        &self,
    ) -> Result<
        (
            Vec<sdhop::pose::bench::BenchObject>,
            Vec<PathBuf>,
            Vec<PathBuf>,
        ),
        Failure,
    > {
        let mut objects = sdhop::pose::bench::objects();
        if !self.objects.is_empty() {
            for name in &self.objects {
                if !objects.iter().any(|o| o.name == name) {
                    return Err(Failure::input(format!(
                        "no benchmark object {name:?} (box, bottle)"
                    )));
                }
            }
            objects.retain(|o| self.objects.iter().any(|n| n == o.name));
        }
        let dir = &self.backgrounds;
        let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(|e| Failure::io(format!("{}: {e}", dir.display())))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.extension().and_then(|x| x.to_str()).is_some_and(|x| {
                    matches!(x.to_ascii_lowercase().as_str(), "jpg" | "jpeg" | "png")
                })
            })
            .collect();
        files.sort();
        if files.len() <= self.train_backgrounds {
            return Err(Failure::input(format!(
                "{}: {} images, more than --train-backgrounds {} are needed",
                dir.display(),
                files.len(),
                self.train_backgrounds
            )));
        }
        let test = files.split_off(self.train_backgrounds);
        Ok((objects, files, test))
    }
}

/// A background photograph at the benchmark's 640x480.
fn background_image(path: &Path) -> Result<ColorImage, Failure> {
    let img = image::open(path)
        .map_err(|e| Failure::input(format!("{}: {e}", path.display())))?
        .to_rgb8();
    let img = if img.dimensions() == (640, 480) {
        img
    } else {
        image::imageops::resize(&img, 640, 480, image::imageops::FilterType::Triangle)
    };
    ColorImage::from_rgb8(&img).map_err(Failure::input)
}

fn run_pose_data(args: &PoseDataArgs) -> Result<(), Failure> {
    use sdhop::pose::bench::{scene, BenchSettings};
    let (objects, train, _) = args.bg.load()?;
    let images_dir = args.out.join("images");
    std::fs::create_dir_all(&images_dir)
        .map_err(|e| Failure::io(format!("{}: {e}", images_dir.display())))?;
    let settings = BenchSettings::default();
    let mut images = Vec::new();
    let mut annotations = Vec::new();
    let categories: Vec<_> = objects
        .iter()
        .enumerate()
        .map(|(i, o)| serde_json::json!({"id": i + 1, "name": o.name}))
        .collect();
    let backgrounds: Vec<ColorImage> = train
        .iter()
        .map(|p| background_image(p))
        .collect::<Result<_, _>>()?;
    for (ci, object) in objects.iter().enumerate() {
        for i in 0..args.scenes {
            let occlusion = if i % 3 == 0 { (0.0, 0.0) } else { (0.1, 0.6) };
            let seed = 1_000_000 * (ci as u64 + 1) + i as u64;
            let bg = &backgrounds[i % backgrounds.len()];
            let s = scene(object, bg, occlusion, &settings, seed).map_err(Failure::input)?;
            let name = format!("{}_{i:04}.jpg", object.name);
            let path = images_dir.join(&name);
            s.scene
                .image
                .to_rgb8()
                .save(&path)
                .map_err(|e| Failure::io(format!("{}: {e}", path.display())))?;
            let id = images.len() + 1;
            images.push(serde_json::json!({
                "id": id, "file_name": format!("images/{name}"), "width": 640, "height": 480
            }));
            let (x, y, w, h) = s.full_box;
            annotations.push(serde_json::json!({
                "id": annotations.len() + 1,
                "image_id": id,
                "category_id": ci + 1,
                "bbox": [x, y, w, h],
                "segmentation": s.scene.visible.to_rle(),
            }));
        }
    }
    // The training backgrounds themselves are the negatives, referred to
    // where they are (absolute paths): nothing third-party is copied.
    for p in &train {
        let abs =
            std::fs::canonicalize(p).map_err(|e| Failure::io(format!("{}: {e}", p.display())))?;
        images.push(serde_json::json!({
            "id": images.len() + 1, "file_name": abs, "width": 640, "height": 480
        }));
    }
    let coco = serde_json::json!({
        "images": images, "categories": categories, "annotations": annotations,
        "info": {"description": "sdhop pose benchmark training renders", "settings": settings}
    });
    let path = args.out.join("coco.json");
    std::fs::write(&path, serde_json::to_string(&coco).map_err(Failure::io)?)
        .map_err(|e| Failure::io(format!("{}: {e}", path.display())))?;
    println!(
        "{} renders of {} objects and {} negatives -> {}",
        annotations.len(),
        objects.len(),
        train.len(),
        path.display()
    );
    Ok(())
}

fn run_pose_bench(args: &PoseBenchArgs) -> Result<(), Failure> {
    use sdhop::pose::bench::{evaluate, scene, summarize, BenchSettings, Method};
    use sdhop::pose::EdgeModel;
    let (objects, _, test) = args.bg.load()?;
    let settings = BenchSettings::default();
    let detectors: Vec<Model> = if args.models_dir.is_dir() {
        load_model_dir(&args.models_dir)?
    } else {
        eprintln!(
            "{}: no models, so no SD-HOP mask (train them: see the README)",
            args.models_dir.display()
        );
        Vec::new()
    };
    let backgrounds: Vec<ColorImage> = test
        .iter()
        .map(|p| background_image(p))
        .collect::<Result<_, _>>()?;
    let mut report = Vec::new();
    println!(
        "| object | hidden | method | X mm | Y mm | Z mm | roll ° | pitch ° | yaw ° | angle ° mean ± se / median | distance mm mean ± se / median | success | failed | ms |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for (ci, object) in objects.iter().enumerate() {
        let edges = EdgeModel::new(
            &object.mesh,
            sdhop::pose::IrlsParams::default().crease_degrees,
        );
        let detector = detectors.iter().find(|m| m.meta.name == object.name);
        for (label, occlusion) in [("0%", (0.0, 0.0)), ("20-60%", (0.2, 0.6))] {
            let mut outcomes = Vec::new();
            let mut hidden = 0.0;
            for i in 0..args.scenes {
                let seed = 7_000_000 * (ci as u64 + 1) + i as u64;
                let bg = &backgrounds[i % backgrounds.len()];
                let s = scene(object, bg, occlusion, &settings, seed).map_err(Failure::input)?;
                hidden += s.scene.occluded_fraction / args.scenes as f64;
                outcomes.extend(evaluate(
                    &edges,
                    &s,
                    detector,
                    &settings,
                    &sdhop::pose::IrlsParams::default(),
                ));
            }
            let mut summaries = Vec::new();
            for method in [Method::Irls, Method::OrIrlsExact, Method::OrIrlsSdhop] {
                let Some(s) = summarize(&outcomes, method) else {
                    continue;
                };
                let e = s.mean_errors;
                println!(
                    "| {} | {label} (mean {:.0}%) | {:?} | {:.1} | {:.1} | {:.1} | {:.2} | {:.2} | {:.2} | {:.2} ± {:.2} / {:.2} | {:.1} ± {:.1} / {:.1} | {:.0}% | {} | {:.0} |",
                    object.name,
                    100.0 * hidden,
                    method,
                    e[0], e[1], e[2], e[3], e[4], e[5],
                    s.mean_angle_degrees,
                    s.se_angle_degrees,
                    s.median_angle_degrees,
                    s.mean_distance_mm,
                    s.se_distance_mm,
                    s.median_distance_mm,
                    100.0 * s.success_rate,
                    s.failed,
                    s.mean_total_ms
                );
                summaries.push(s);
            }
            report.push(serde_json::json!({
                "object": object.name, "occlusion": occlusion, "mean_hidden": hidden,
                "summaries": summaries, "outcomes": outcomes,
            }));
        }
    }
    if let Some(p) = &args.report {
        let doc = serde_json::json!({"settings": settings, "results": report});
        std::fs::write(p, serde_json::to_string_pretty(&doc).map_err(Failure::io)?)
            .map_err(|e| Failure::io(format!("{}: {e}", p.display())))?;
    }
    Ok(())
}

fn run_demo(args: &DemoArgs) -> Result<(), Failure> {
    std::fs::create_dir_all(&args.out)
        .map_err(|e| Failure::io(format!("{}: {e}", args.out.display())))?;
    let obj = SynthObject {
        cols: 18,
        rows: 16,
        seed: 3,
    };
    let params = SceneParams {
        width: args.width,
        height: args.height,
        seed: args.seed,
        ..SceneParams::default()
    };
    let sc = scene(&obj, &params).map_err(Failure::input)?;
    let model =
        hand_model(&obj, "synthetic", true, &HandModelParams::default()).map_err(Failure::input)?;
    let model_path = args.out.join("synthetic.safetensors");
    model.save(&model_path).map_err(Failure::io)?;
    let scene_path = args.out.join("scene.png");
    sc.image
        .to_rgb8()
        .save(&scene_path)
        .map_err(|e| Failure::io(format!("{}: {e}", scene_path.display())))?;
    let img = read_image(&scene_path, DEFAULT_MAX_PIXELS)?;
    let opts = DetectOptions {
        max_detections: Some(1),
        masks: MaskMode::Both,
        ..DetectOptions::default()
    };
    let resp = detect_image(&img, &[&model], &opts).map_err(Failure::input)?;
    write_json(&resp, Some(&args.out.join("detections.json")))?;
    let overlay_path = args.out.join("overlay.png");
    overlay(&img, &resp)
        .save(&overlay_path)
        .map_err(|e| Failure::io(format!("{}: {e}", overlay_path.display())))?;
    let (tx, ty, tw, th) = sc.truth_box;
    println!(
        "scene      {} ({}x{}), object box x={tx:.1} y={ty:.1} w={tw:.1} h={th:.1}, {:.0}% hidden",
        scene_path.display(),
        args.width,
        args.height,
        100.0 * (1.0 - sc.visible.area() as f64 / sc.object.area() as f64)
    );
    match resp.detections.first() {
        None => println!("detection  none above the threshold"),
        Some(d) => {
            let b = (d.bbox.x, d.bbox.y, d.bbox.width, d.bbox.height);
            let miou = |r: &Option<sdhop::vision::mask::Rle>| {
                r.as_ref()
                    .and_then(Mask::from_rle)
                    .map_or(0.0, |m| m.iou(&sc.visible))
            };
            println!(
                "detection  score {:.3}, box x={:.1} y={:.1} w={:.1} h={:.1}, box IoU {:.3}",
                d.score,
                b.0,
                b.1,
                b.2,
                b.3,
                box_iou(b, sc.truth_box)
            );
            println!(
                "mask IoU   raw {:.3}, refined {:.3} (visible fraction {:.2})",
                miou(&d.raw_mask),
                miou(&d.mask),
                d.visible_fraction
            );
        }
    }
    let t = &resp.timing_ms;
    println!("timing ms  total {:.1}: features {:.1}, segmentation {:.1}, cell segments {:.1}, responses {:.1}, min-cuts {:.1}, masks {:.1}",
        t.total, t.features, t.segmentation, t.cell_segments, t.responses, t.mincut, t.masks);
    println!(
        "pruning    {} locations, {} min-cuts ({:.2}% pruned)",
        t.locations,
        t.min_cuts,
        100.0 * t.pruned_fraction
    );
    println!(
        "wrote      {}, {}, {}",
        model_path.display(),
        args.out.join("detections.json").display(),
        overlay_path.display()
    );
    Ok(())
}

/// Stores a cross-validation report's figures for the model's object in its
/// provenance.
fn add_cv_figures(model: &mut Model, cv: &serde_json::Value) {
    let name = model.meta.name.clone();
    let figures = cv["evaluation"]["objects"]
        .as_array()
        .and_then(|a| a.iter().find(|o| o["object"] == name.as_str()))
        .cloned();
    if let Some(obj) = model.meta.provenance.as_object_mut() {
        obj.insert(
            "cross_validation".into(),
            serde_json::json!({
                "folds": cv["folds"],
                "c": cv["c"],
                "params": cv["params"],
                "threshold": cv["threshold"],
                "figures": figures,
                "mean": cv["evaluation"]["mean"],
            }),
        );
    }
    // The cross-validated threshold becomes the model's default.
    if let Some(t) = cv["threshold"].as_f64() {
        model.meta.detection.threshold = t;
    }
}

fn read_json(p: &Path) -> Result<serde_json::Value, Failure> {
    let text =
        std::fs::read_to_string(p).map_err(|e| Failure::io(format!("{}: {e}", p.display())))?;
    serde_json::from_str(&text).map_err(|e| Failure::input(format!("{}: {e}", p.display())))
}

fn run_annotate(args: &AnnotateArgs) -> Result<(), Failure> {
    let cv = read_json(&args.cv_report)?;
    let mut models = load_model_dir(&args.models_dir)?;
    for m in &mut models {
        add_cv_figures(m, &cv);
        let path = args.models_dir.join(format!("{}.safetensors", m.meta.name));
        m.save(&path).map_err(Failure::io)?;
        println!("{}: cross-validated figures stored", path.display());
    }
    Ok(())
}

fn run_train(args: &TrainArgs) -> Result<(), Failure> {
    let (params, neg) = args.settings.params()?;
    std::fs::create_dir_all(&args.out)
        .map_err(|e| Failure::io(format!("{}: {e}", args.out.display())))?;
    let cv: Option<serde_json::Value> = match &args.cv_report {
        Some(p) => Some(
            serde_json::from_str(
                &std::fs::read_to_string(p)
                    .map_err(|e| Failure::io(format!("{}: {e}", p.display())))?,
            )
            .map_err(|e| Failure::input(format!("{}: {e}", p.display())))?,
        ),
        None => None,
    };
    let cache = PyramidCache::default();
    let trained = if let Some(coco) = &args.coco {
        let dir = args.images.clone().unwrap_or_default();
        let mut out = Vec::new();
        for cat in &args.category {
            let loaded = load_coco(coco, &dir, cat).map_err(Failure::input)?;
            for s in &loaded.skipped {
                eprintln!("skipped: {s}");
            }
            let refs: Vec<_> = loaded.samples.iter().collect();
            let pb = progress_bar(0, cat);
            let r = train_model(cat, &refs, &cache, &params, &pb).map_err(Failure::input)?;
            pb.finish_and_clear();
            out.push(r);
        }
        out
    } else {
        let root = args
            .ko8
            .as_ref()
            .ok_or_else(|| Failure::input("--ko8 or --coco is required"))?;
        let data = Ko8Data::load(root, &args.objects).map_err(Failure::input)?;
        for s in &data.skipped {
            eprintln!("skipped: {s}");
        }
        train_objects(&data, None, &params, &neg, &cache).map_err(Failure::input)?
    };
    for (mut model, report) in trained {
        if let Some(obj) = model.meta.provenance.as_object_mut() {
            obj.insert(
                "negatives".into(),
                serde_json::to_value(&neg).map_err(Failure::io)?,
            );
        }
        if let Some(cv) = &cv {
            add_cv_figures(&mut model, cv);
        }
        let path = args.out.join(format!("{}.safetensors", model.meta.name));
        model.save(&path).map_err(Failure::io)?;
        eprintln!(
            "{}: full-search violations {:?}, min-cuts {:?}",
            model.meta.name, report.full_violation, report.full_min_cuts
        );
        println!(
            "{:10} {}x{} cells, {} positives, {} negatives, {} passes, {} iterations, converged {}, {:.1} s (full {:.1}, cached {:.1}, qp {:.1}) -> {}",
            model.meta.name,
            model.views[0].rows,
            model.views[0].cols,
            report.positives,
            report.negatives,
            report.passes,
            report.iterations,
            report.converged,
            report.seconds,
            report.full_seconds,
            report.cached_seconds,
            report.qp_seconds,
            path.display()
        );
    }
    Ok(())
}

/// Writes the per-image responses (`<id>.json`, the scorer's input), the
/// figures and the plot into `out`.
fn write_evaluation(
    out: &Path,
    ids: &[&str],
    responses: &[DetectResponse],
    report: &serde_json::Value,
    evaluation: &Evaluation,
    ko8: &Path,
) -> Result<(), Failure> {
    let pred = out.join("predictions");
    std::fs::create_dir_all(&pred).map_err(|e| Failure::io(format!("{}: {e}", pred.display())))?;
    for (id, r) in ids.iter().zip(responses) {
        write_json(r, Some(&pred.join(format!("{id}.json"))))?;
    }
    let path = out.join("report.json");
    let text = serde_json::to_string_pretty(report).map_err(Failure::io)?;
    std::fs::write(&path, text).map_err(|e| Failure::io(format!("{}: {e}", path.display())))?;
    let plot = out.join("recall_fppi.png");
    sdhop::eval::plot::recall_fppi_png(&evaluation.objects, &ko8.join("plots/single"), &plot)
        .map_err(Failure::io)?;
    println!("{}", sdhop::eval::table(&evaluation.objects));
    println!(
        "wrote {}, {} and {}",
        path.display(),
        plot.display(),
        pred.display()
    );
    Ok(())
}

/// The best cross-validation so far: its key, report, figures, image ids
/// and responses.
type BestCv = (
    f64,
    serde_json::Value,
    Evaluation,
    Vec<String>,
    Vec<DetectResponse>,
);

fn run_cv(args: &CvArgs) -> Result<(), Failure> {
    let (mut params, neg) = args.settings.params()?;
    if args.folds < 2 {
        return Err(Failure::input("--folds must be at least 2"));
    }
    let data = Ko8Data::load(&args.ko8, &args.objects).map_err(Failure::input)?;
    let cache = PyramidCache::default();
    let cs = if args.c_values.is_empty() {
        vec![params.c]
    } else {
        args.c_values.clone()
    };
    let mut best: Option<BestCv> = None;
    let mut summary = Vec::new();
    for &c in &cs {
        params.c = c;
        let t = std::time::Instant::now();
        // With several values of C, each keeps its models in DIR/c-C.
        let per_c = |d: &Path| {
            if cs.len() > 1 {
                d.join(format!("c-{c}"))
            } else {
                d.to_path_buf()
            }
        };
        let (save, load) = (
            args.save_models.as_deref().map(per_c),
            args.load_models.as_deref().map(per_c),
        );
        let source = match (&save, &load) {
            (_, Some(d)) => FoldModels::Load(d),
            (Some(d), None) => FoldModels::TrainAndSave(d),
            (None, None) => FoldModels::Train,
        };
        let how = EvalDetect {
            max_detections: args.max_detections,
            threshold: args.detect_threshold,
        };
        let cv = cross_validate(
            &data,
            args.folds,
            &args.only_folds,
            &params,
            &neg,
            &cache,
            how,
            source,
        )
        .map_err(Failure::input)?;
        let secs = t.elapsed().as_secs_f64();
        // Thresholds at or above the one detection ran with, scored on the
        // same responses; the highest that keeps (nearly) the best figures.
        let floor = args.detect_threshold.unwrap_or(params.threshold);
        let grid: Vec<f64> = (0..)
            .map(|i| floor + 0.125 * f64::from(i))
            .take_while(|t| *t <= 1.0 + 1e-9)
            .collect();
        let refs: Vec<&Sample> = cv.images.iter().collect();
        let sweep = threshold_sweep(&data, &refs, &cv.responses, &grid);
        let chosen =
            choose_threshold(&sweep, args.threshold_tolerance).map_or(floor, |t| t.threshold);
        let responses = above_threshold(&cv.responses, chosen);
        let evaluation = score(&data, &refs, &responses);
        println!(
            "C = {c} ({secs:.0} s), threshold {chosen}\n{}",
            sdhop::eval::table(&evaluation.objects)
        );
        for t in &sweep {
            println!(
                "  threshold {:6.3}: AUC {:.3}, cross {:.3}, seg refined {:.4}, raw {:.4}",
                t.threshold,
                t.mean.auc,
                t.mean.auc_cross,
                t.mean.seg_error_refined,
                t.mean.seg_error_raw
            );
        }
        summary.push(serde_json::json!({
            "c": c,
            "threshold": chosen,
            "mean": evaluation.mean,
            "seconds": secs,
            "threshold_search": sweep,
        }));
        let key = selection_key(&evaluation.mean);
        if best.as_ref().is_none_or(|b| key > b.0) {
            let report = serde_json::json!({
                "folds": args.folds,
                "only_folds": args.only_folds,
                "c": c,
                "threshold": chosen,
                "detect_threshold": floor,
                "max_detections": args.max_detections,
                "params": params,
                "negatives": neg,
                "evaluation": strip_curves(&evaluation),
                "train_reports": cv.reports,
            });
            let ids = cv.images.iter().map(|s| s.id.clone()).collect();
            best = Some((key, report, evaluation, ids, responses));
        }
    }
    let Some((_, mut report, evaluation, ids, responses)) = best else {
        return Err(Failure::input("no value of C to try"));
    };
    report["c_search"] = serde_json::Value::Array(summary);
    let ids: Vec<&str> = ids.iter().map(|s| s.as_str()).collect();
    println!(
        "chosen C = {}, threshold = {}",
        report["c"], report["threshold"]
    );
    write_evaluation(&args.out, &ids, &responses, &report, &evaluation, &args.ko8)
}

fn strip_curves(e: &Evaluation) -> serde_json::Value {
    let mut e = e.clone();
    for o in &mut e.objects {
        o.curve = thin(&o.curve);
        o.curve_cross = thin(&o.curve_cross);
    }
    serde_json::to_value(e).unwrap_or_default()
}

/// Every tenth point of a 1001-point curve (FPPI 0, 0.01, ..., 1).
fn thin(c: &[f64]) -> Vec<f64> {
    c.iter().step_by(10).copied().collect()
}

fn run_eval(args: &EvalArgs) -> Result<(), Failure> {
    let data = Ko8Data::load(&args.ko8, &args.objects).map_err(Failure::input)?;
    let models = load_model_dir(&args.models_dir)?;
    let refs: Vec<&Model> = models.iter().collect();
    let every = args.every.max(1);
    let images: Vec<_> = data
        .images
        .iter()
        .flat_map(|imgs| imgs.iter().step_by(every))
        .collect();
    let cache = PyramidCache::default();
    let m0 = refs.first().ok_or_else(|| Failure::input("no model"))?;
    let pb = progress_bar(0, "pyramids");
    cache
        .fill(&images, &m0.meta.pyramid, &m0.meta.segmentation, &pb)
        .map_err(Failure::input)?;
    pb.finish_and_clear();
    let how = EvalDetect {
        max_detections: args.max_detections,
        threshold: args.detect_threshold,
    };
    let responses = detect_all(&images, &refs, &cache, how).map_err(Failure::input)?;
    let evaluation = score(&data, &images, &responses);
    let report = serde_json::json!({
        "models": models.iter().map(|m| &m.meta.name).collect::<Vec<_>>(),
        "images": images.len(),
        "evaluation": strip_curves(&evaluation),
    });
    let ids: Vec<&str> = images.iter().map(|s| s.id.as_str()).collect();
    write_evaluation(&args.out, &ids, &responses, &report, &evaluation, &args.ko8)
}

/// The `*.safetensors` files of a folder, sorted.
fn model_paths(dir: &Path) -> Result<Vec<PathBuf>, Failure> {
    let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| Failure::io(format!("{}: {e}", dir.display())))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "safetensors"))
        .collect();
    found.sort();
    Ok(found)
}

fn load_model_dir(dir: &Path) -> Result<Vec<Model>, Failure> {
    model_paths(dir)?
        .iter()
        .map(|p| Model::load(p).map_err(|e| Failure::input(format!("{}: {e}", p.display()))))
        .collect()
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match &cli.command {
        Command::Train(a) => run_train(a),
        Command::Cv(a) => run_cv(a),
        Command::Eval(a) => run_eval(a),
        Command::Annotate(a) => run_annotate(a),
        Command::Detect(a) => run_detect(a),
        Command::Pose(a) => run_pose(a),
        Command::PoseData(a) => run_pose_data(a),
        Command::PoseBench(a) => run_pose_bench(a),
        Command::Demo(a) => run_demo(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(f) => {
            eprintln!("error: {}", f.message);
            ExitCode::from(f.code)
        }
    }
}
