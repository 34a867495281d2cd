//! The companion command-line tool: run the detector on an image, or on a
//! synthetic scene it generates itself (training and evaluation come later).

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use sdhop::model::Model;
use sdhop::pipeline::{
    detect_image, overlay, DetectOptions, DetectResponse, MaskMode, DEFAULT_MAX_PIXELS,
};
use sdhop::synth::{hand_model, scene, HandModelParams, SceneParams, SynthObject};
use sdhop::vision::detect::box_iou;
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

#[derive(Subcommand)]
enum Command {
    /// Detect objects in one image; prints the detection JSON of `POST /detect`.
    Detect(DetectArgs),
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
        let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(|e| Failure::io(format!("{}: {e}", dir.display())))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "safetensors"))
            .collect();
        found.sort();
        paths.extend(found);
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
    };
    let resp = detect_image(&img, &refs, &opts).map_err(Failure::input)?;
    if let Some(p) = &args.overlay {
        overlay(&img, &resp)
            .save(p)
            .map_err(|e| Failure::io(format!("{}: {e}", p.display())))?;
    }
    write_json(&resp, args.output.as_deref())
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

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match &cli.command {
        Command::Detect(a) => run_detect(a),
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
