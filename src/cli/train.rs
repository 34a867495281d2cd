//! `sdhop-train train`: one model per object (CMU_KO8 or a COCO-style
//! file), saved as weights files.

use super::*;

#[derive(clap::Args)]
pub(crate) struct TrainArgs {
    /// CMU_KO8 root (with single/ and negative/).
    #[arg(long, required_unless_present = "coco")]
    pub(crate) ko8: Option<PathBuf>,
    /// COCO-style JSON of your own objects (see docs/training.md).
    #[arg(long, conflicts_with = "ko8", requires_all = ["images", "category"])]
    pub(crate) coco: Option<PathBuf>,
    /// Folder the COCO file names are relative to.
    #[arg(long)]
    pub(crate) images: Option<PathBuf>,
    /// COCO category to train (repeat for several).
    #[arg(long)]
    pub(crate) category: Vec<String>,
    /// Objects to train (CMU_KO8; default all eight).
    #[arg(long, value_delimiter = ',')]
    pub(crate) objects: Vec<String>,
    /// Folder for the weights files (one per object, named after it).
    #[arg(long, default_value = "models")]
    pub(crate) out: PathBuf,
    /// Cross-validation figures (JSON written by `cv`) to store in the
    /// models' metadata.
    #[arg(long)]
    pub(crate) cv_report: Option<PathBuf>,
    #[command(flatten)]
    pub(crate) settings: TrainSettings,
}

pub(crate) fn run_train(args: &TrainArgs) -> Result<(), Failure> {
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

/// Stores a cross-validation report's figures for the model's object in its
/// provenance.
pub(crate) fn add_cv_figures(model: &mut Model, cv: &serde_json::Value) {
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
