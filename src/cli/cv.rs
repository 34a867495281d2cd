//! `sdhop-train cv`: k-fold cross-validation of training on CMU_KO8,
//! choosing C; AUC and segmentation errors.

use super::*;

#[derive(clap::Args)]
pub(crate) struct CvArgs {
    /// CMU_KO8 root.
    #[arg(long)]
    pub(crate) ko8: PathBuf,
    #[arg(long, value_delimiter = ',')]
    pub(crate) objects: Vec<String>,
    #[arg(long, default_value_t = 5)]
    pub(crate) folds: usize,
    /// Values of C to compare (the best mean cross-object AUC wins).
    #[arg(long, value_delimiter = ',', allow_negative_numbers = false)]
    pub(crate) c_values: Vec<f64>,
    /// Folder for the report, the per-image JSON responses and the plot.
    #[arg(long, default_value = "out/cv")]
    pub(crate) out: PathBuf,
    /// Detections kept per image (as the acceptance procedure asks).
    #[arg(long, default_value_t = 20)]
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
    #[arg(long, default_value_t = 0.002)]
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

/// The best cross-validation so far: its key, report, figures, image ids
/// and responses.
pub(crate) type BestCv = (
    f64,
    serde_json::Value,
    Evaluation,
    Vec<String>,
    Vec<DetectResponse>,
);

pub(crate) fn run_cv(args: &CvArgs) -> Result<(), Failure> {
    let (mut params, neg) = args.settings.params(FeatureKind::Hog)?;
    if args.folds < 2 {
        return Err(Failure::input("--folds must be at least 2"));
    }
    let data = Ko8Data::load(&args.ko8, &args.objects).map_err(Failure::input)?;
    let cache = PyramidCache::default();
    let cs = if args.c_values.is_empty() {
        vec![params.solver.c]
    } else {
        args.c_values.clone()
    };
    let mut best: Option<BestCv> = None;
    let mut summary = Vec::new();
    for &c in &cs {
        params.solver.c = c;
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
            pixel: args
                .pixel_refine
                .as_deref()
                .map(parse_pixel_refine)
                .transpose()?,
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
            crate::eval::table(&evaluation.objects, true)
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
    write_evaluation(
        &args.out,
        &ids,
        &responses,
        &report,
        &evaluation,
        &args.ko8,
        Part::Single,
    )
}

pub(crate) fn strip_curves(e: &Evaluation) -> serde_json::Value {
    let mut e = e.clone();
    for o in &mut e.objects {
        o.curve = thin(&o.curve);
        o.curve_cross = thin(&o.curve_cross);
    }
    serde_json::to_value(e).unwrap_or_default()
}

/// Every tenth point of a 1001-point curve (FPPI 0, 0.01, ..., 1).
pub(crate) fn thin(c: &[f64]) -> Vec<f64> {
    c.iter().step_by(10).copied().collect()
}
