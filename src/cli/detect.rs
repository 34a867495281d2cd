//! `sdhop-train detect`: the detector on one image; prints the JSON of
//! `POST /detect` (and optionally draws an overlay).

use super::*;
use crate::pipeline::RleFormat;
use serde::Serialize;

#[derive(clap::Args)]
pub(crate) struct DetectArgs {
    /// Image to scan (PNG or JPEG).
    pub(crate) image: PathBuf,
    /// Weights file(s); repeat for several models.
    #[arg(long = "model", short = 'm', required_unless_present = "models_dir")]
    pub(crate) models: Vec<PathBuf>,
    /// Load every `*.safetensors` in this folder.
    #[arg(long)]
    pub(crate) models_dir: Option<PathBuf>,
    /// Score threshold (default: each model's own).
    #[arg(long, allow_negative_numbers = true)]
    pub(crate) threshold: Option<f64>,
    /// Maximum detections (default: each model's own).
    #[arg(long)]
    pub(crate) max_detections: Option<usize>,
    /// Masks to include.
    #[arg(long, value_enum, default_value_t = MaskMode::Refined)]
    pub(crate) masks: MaskMode,
    /// How masks are written: COCO uncompressed RLE (run lengths) or
    /// compressed RLE (pycocotools' string), as `POST /detect?rle=`.
    #[arg(long, value_enum, default_value_t = RleFormat::Uncompressed)]
    pub(crate) rle: RleFormat,
    /// Disable exact pruning (same result, slower; for checking).
    #[arg(long)]
    pub(crate) no_prune: bool,
    /// Write the JSON here instead of standard output.
    #[arg(long, short = 'o')]
    pub(crate) output: Option<PathBuf>,
    /// Write a PNG with boxes and masks drawn over the image.
    #[arg(long)]
    pub(crate) overlay: Option<PathBuf>,
    /// Refuse images with more pixels than this.
    #[arg(long, default_value_t = DEFAULT_MAX_PIXELS)]
    pub(crate) max_pixels: usize,
}

pub(crate) fn load_models(args: &DetectArgs) -> Result<Vec<Model>, Failure> {
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

pub(crate) fn write_json(resp: &DetectResponse, out: Option<&Path>) -> Result<(), Failure> {
    write_value(resp, out)
}

/// Writes a value as JSON to `out`, or to standard output.
pub(crate) fn write_value<T: Serialize>(value: &T, out: Option<&Path>) -> Result<(), Failure> {
    let text = serde_json::to_string_pretty(value).map_err(Failure::io)?;
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

pub(crate) fn run_detect(args: &DetectArgs) -> Result<(), Failure> {
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
    match args.rle {
        RleFormat::Uncompressed => write_json(&resp, args.output.as_deref()),
        RleFormat::Compressed => write_value(
            &resp.to_json(args.rle).map_err(Failure::io)?,
            args.output.as_deref(),
        ),
    }
}
