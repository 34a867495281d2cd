//! `sdhop-train eval`: weights files on CMU_KO8 images: figures, the
//! scorer's JSON and a plot.

use super::*;

#[derive(clap::Args)]
pub(crate) struct EvalArgs {
    /// CMU_KO8 root.
    #[arg(long)]
    pub(crate) ko8: PathBuf,
    /// Folder of weights files to evaluate.
    #[arg(long, default_value = "models")]
    pub(crate) models_dir: PathBuf,
    #[arg(long, value_delimiter = ',')]
    pub(crate) objects: Vec<String>,
    /// Folder for the figures, the per-image JSON responses and the plot.
    #[arg(long, default_value = "out/eval")]
    pub(crate) out: PathBuf,
    #[arg(long, default_value_t = 20)]
    pub(crate) max_detections: usize,
    /// Only every n-th image of each object (a quick check).
    #[arg(long, default_value_t = 1)]
    pub(crate) every: usize,
    /// Detection threshold (default: each model's own).
    #[arg(long, allow_negative_numbers = true)]
    pub(crate) detect_threshold: Option<f64>,
    /// Pixel refinement of the masks for this evaluation, overriding the
    /// models': "off" (segment snapping alone) or the weights
    /// "SHAPE,CELLS,SEGMENTS,BIAS,SMOOTHNESS" (0 drops a source).
    #[arg(long, value_name = "off|S,C,G,B,P")]
    pub(crate) pixel_refine: Option<String>,
}

pub(crate) fn run_eval(args: &EvalArgs) -> Result<(), Failure> {
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
        pixel: args
            .pixel_refine
            .as_deref()
            .map(parse_pixel_refine)
            .transpose()?,
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
