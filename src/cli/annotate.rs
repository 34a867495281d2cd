//! `sdhop-train annotate`: stores a `cv` report's figures in models'
//! metadata.

use super::*;

#[derive(clap::Args)]
pub(crate) struct AnnotateArgs {
    /// Folder of weights files (each named after its object).
    #[arg(long, default_value = "models")]
    pub(crate) models_dir: PathBuf,
    /// Report written by `cv`.
    #[arg(long)]
    pub(crate) cv_report: PathBuf,
}

pub(crate) fn run_annotate(args: &AnnotateArgs) -> Result<(), Failure> {
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
