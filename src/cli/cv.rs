//! `sdhop-train cv`: k-fold cross-validation of training on CMU_KO8,
//! choosing C; AUC and segmentation errors.

use super::*;
use crate::train::routes::cv::{cross_validate_route, CvSettings};

#[derive(clap::Args)]
pub(crate) struct CvArgs {
    /// CMU_KO8 root.
    #[arg(long)]
    pub(crate) ko8: PathBuf,
    #[arg(long, value_delimiter = ',')]
    pub(crate) objects: Vec<String>,
    #[arg(long, default_value_t = CvSettings::default().folds)]
    pub(crate) folds: usize,
    /// Values of C to compare (the best mean cross-object AUC wins).
    #[arg(long, value_delimiter = ',', allow_negative_numbers = false)]
    pub(crate) c_values: Vec<f64>,
    /// Folder for the report, the per-image JSON responses and the plot.
    #[arg(long, default_value = "out/cv")]
    pub(crate) out: PathBuf,
    /// Detections kept per image (as the acceptance procedure asks).
    #[arg(long, default_value_t = CvSettings::default().max_detections)]
    pub(crate) max_detections: usize,
    /// Run only these folds (numbered from 0; all by default).
    #[arg(long, value_delimiter = ',')]
    pub(crate) only_folds: Vec<usize>,
    /// Save each fold's models in DIR/fold-F/ (DIR/c-C/fold-F/ with several
    /// --c-values).
    #[arg(long, value_name = "DIR", conflicts_with = "load_models")]
    pub(crate) save_models: Option<PathBuf>,
    /// Load each fold's models from DIR/fold-F/ (saved by an earlier run
    /// with the same folds) instead of training: compares detection
    /// settings such as --detect-threshold without training again.
    #[arg(long, value_name = "DIR")]
    pub(crate) load_models: Option<PathBuf>,
    /// Detection threshold used in the evaluation (default: the models').
    /// Every threshold from it up to 1 in steps of 0.125 is then scored on
    /// the same detections, and the highest whose figures are within
    /// --threshold-tolerance of the best is chosen.
    #[arg(long, allow_negative_numbers = true)]
    pub(crate) detect_threshold: Option<f64>,
    /// Pixel refinement of the masks for this evaluation, overriding the
    /// models': "off" (segment snapping alone) or the weights
    /// "SHAPE,CELLS,SEGMENTS,BIAS,SMOOTHNESS" (0 drops a source).
    #[arg(long, value_name = "off|S,C,G,B,P")]
    pub(crate) pixel_refine: Option<String>,
    /// How much of the selection figure (mean cross-object AUC less a tenth
    /// of the refined segmentation error) a higher, faster threshold may
    /// give up.
    #[arg(long, default_value_t = CvSettings::default().threshold_tolerance)]
    pub(crate) threshold_tolerance: f64,
    #[command(flatten)]
    pub(crate) settings: TrainSettings,
}

/// Writes the per-image responses (`<id>.json`, the scorer's input), the
/// figures and the plot into `out`.
pub(crate) fn write_evaluation(
    out: &Path,
    ids: &[&str],
    responses: &[DetectResponse],
    report: &serde_json::Value,
    evaluation: &Evaluation,
    ko8: &Path,
    part: Part,
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
    crate::eval::plot::recall_fppi_png(
        &evaluation.objects,
        &ko8.join("plots").join(part.name()),
        &plot,
    )
    .map_err(Failure::io)?;
    println!(
        "{}",
        crate::eval::table(&evaluation.objects, part == Part::Single)
    );
    println!(
        "wrote {}, {} and {}",
        path.display(),
        plot.display(),
        pred.display()
    );
    Ok(())
}

pub(crate) fn run_cv(args: &CvArgs) -> Result<(), Failure> {
    let route = CvSettings {
        ko8: args.ko8.clone(),
        objects: args.objects.clone(),
        folds: args.folds,
        only_folds: args.only_folds.clone(),
        c_values: args.c_values.clone(),
        save_models: args.save_models.clone(),
        load_models: args.load_models.clone(),
        max_detections: args.max_detections,
        detect_threshold: args.detect_threshold,
        pixel_refine: args
            .pixel_refine
            .as_deref()
            .map(parse_pixel_refine)
            .transpose()?,
        threshold_tolerance: args.threshold_tolerance,
    };
    let outcome = cross_validate_route(&route, &args.settings, |r| {
        println!(
            "C = {} ({:.0} s), threshold {}\n{}",
            r.c,
            r.seconds,
            r.threshold,
            crate::eval::table(&r.evaluation.objects, true)
        );
        for t in &r.sweep {
            println!(
                "  threshold {:6.3}: AUC {:.3}, cross {:.3}, seg refined {:.4}, raw {:.4}",
                t.threshold,
                t.mean.auc,
                t.mean.auc_cross,
                t.mean.seg_error_refined,
                t.mean.seg_error_raw
            );
        }
    })?;
    println!(
        "chosen C = {}, threshold = {}",
        outcome.report["c"], outcome.report["threshold"]
    );
    let ids: Vec<&str> = outcome.ids.iter().map(String::as_str).collect();
    write_evaluation(
        &args.out,
        &ids,
        &outcome.responses,
        &outcome.report,
        &outcome.evaluation,
        &args.ko8,
        Part::Single,
    )
}
