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
    /// Which part of CMU_KO8: `single` (masked occluded photographs of
    /// one viewpoint: localization and segmentation) or `multiple` (the
    /// multi-view part's box-only photographs from any side: localization
    /// only, as `PART=multiple ko8_eval.py`).
    #[arg(long, value_enum, default_value_t = Part::Single)]
    pub(crate) part: Part,
    /// Leave out the first N images of each object (those a model trained
    /// on with `train --boxes-first N`).
    #[arg(long, default_value_t = 0)]
    pub(crate) skip_first: usize,
    /// Only the first N images of each object (after `--skip-first`).
    #[arg(long)]
    pub(crate) first: Option<usize>,
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
    let data = match args.part {
        Part::Single => data,
        Part::Multiple => data.with_multiview(&args.ko8).map_err(Failure::input)?,
    };
    let models = load_model_dir(&args.models_dir)?;
    let refs: Vec<&Model> = models.iter().collect();
    let every = args.every.max(1);
    let part_images = match args.part {
        Part::Single => &data.images,
        Part::Multiple if data.photos.is_empty() => {
            return Err(Failure::input(format!(
                "{}: no multi-view part (multiple/)",
                args.ko8.display()
            )))
        }
        Part::Multiple => &data.photos,
    };
    let images: Vec<_> = part_images
        .iter()
        .flat_map(|imgs| {
            imgs.iter()
                .skip(args.skip_first)
                .take(args.first.unwrap_or(usize::MAX))
                .step_by(every)
        })
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
        "features": feature_kinds(&models),
        "part": args.part.name(),
        "images": images.len(),
        "evaluation": crate::train::routes::cv::strip_curves(&evaluation),
    });
    println!(
        "{} model(s), {} features, {} photographs",
        models.len(),
        feature_kinds(&models),
        images.len()
    );
    let ids: Vec<&str> = images.iter().map(|s| s.id.as_str()).collect();
    write_evaluation(
        &args.out,
        &ids,
        &responses,
        &report,
        &evaluation,
        &args.ko8,
        args.part,
    )
}

/// A part of CMU_KO8.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum Part {
    Single,
    Multiple,
}

impl Part {
    pub(crate) fn name(self) -> &'static str {
        match self {
            Part::Single => "single",
            Part::Multiple => "multiple",
        }
    }
}
