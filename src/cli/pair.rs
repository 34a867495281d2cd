//! `sdhop-train pair`: both kinds per object from models trained apart.
//! Each model of one folder (learned cells) takes the model of the same
//! object from another folder (HOG) as its segmenter
//! ([`crate::model::Model::segmenter`]), or, without a second folder,
//! gives its segmenter up (`--extract`: writes it alone). What `train
//! --segmenter` makes in one run.

use super::*;

#[derive(clap::Args)]
pub(crate) struct PairArgs {
    /// Folder of the models that find (their scores and boxes are
    /// answered).
    pub(crate) models: PathBuf,
    /// Folder of the models that place and segment their detections, one
    /// per object of the first folder, on the other kind of cells. Absent:
    /// the models are written without segmenters.
    pub(crate) segmenters: Option<PathBuf>,
    /// Folder to write the paired models to (created; files of the same
    /// names are replaced).
    #[arg(long)]
    pub(crate) out: PathBuf,
    /// Write each model's segmenter instead, as a model of its own (to
    /// score the two kinds apart on the same folds); a model without one
    /// is an error.
    #[arg(long, conflicts_with = "segmenters")]
    pub(crate) extract: bool,
}

pub(crate) fn run_pair(args: &PairArgs) -> Result<(), Failure> {
    let models = load_model_dir(&args.models)?;
    if models.is_empty() {
        return Err(Failure::input(format!(
            "{}: no *.safetensors models",
            args.models.display()
        )));
    }
    let paired = match &args.segmenters {
        None if args.extract => models
            .into_iter()
            .map(|m| {
                m.segmenter.map(|s| *s).ok_or_else(|| {
                    Failure::input(format!(
                        "{}: model {} has no segmenter",
                        args.models.display(),
                        m.meta.name
                    ))
                })
            })
            .collect::<Result<Vec<_>, _>>()?,
        Some(dir) => {
            let segs = load_model_dir(dir)?;
            crate::model::with_segmenters(models, segs)
                .map_err(|e| Failure::input(format!("{}: {e}", dir.display())))?
        }
        None => models.into_iter().map(Model::without_segmenter).collect(),
    };
    std::fs::create_dir_all(&args.out)
        .map_err(|e| Failure::io(format!("{}: {e}", args.out.display())))?;
    for m in &paired {
        let path = args.out.join(format!("{}.safetensors", m.meta.name));
        m.save(&path)
            .map_err(|e| Failure::io(format!("{}: {e}", path.display())))?;
        match &m.segmenter {
            Some(s) => println!(
                "{}: {} cells, segmented by {} ({} cells)",
                path.display(),
                m.meta.pyramid.features,
                s.meta.name,
                s.meta.pyramid.features
            ),
            None => println!(
                "{}: {} cells, no segmenter",
                path.display(),
                m.meta.pyramid.features
            ),
        }
    }
    Ok(())
}
