//! `sdhop-train upgrade`: rewrites weights files of formats 1 and 2 (no
//! digest) as the current format, with the digest of their contents and
//! their feature kind stated. The operator runs it on files they vouch
//! for; the server refuses the old formats. `--refine` also sets each
//! model's pixel refinement to this build's for its cells
//! ([`crate::model::Model::refresh_refinement`]).

use super::*;
use crate::model::{DIGEST_FORMAT_VERSION, FORMAT_VERSION};

#[derive(clap::Args)]
pub(crate) struct UpgradeArgs {
    /// Weights files to rewrite in place (files already of the current
    /// format are checked and left as they are).
    #[arg(required = true)]
    pub(crate) files: Vec<PathBuf>,
    /// Also set each model's pixel refinement weights to this build's
    /// defaults for its cells (the refinement follows detection and
    /// trains nothing; the old weights are kept in the provenance under
    /// `refine_set`). Files of the current format are rewritten where
    /// their weights differ.
    #[arg(long)]
    pub(crate) refine: bool,
}

pub(crate) fn run_upgrade(args: &UpgradeArgs) -> Result<(), Failure> {
    for path in &args.files {
        let bytes =
            std::fs::read(path).map_err(|e| Failure::io(format!("{}: {e}", path.display())))?;
        let mut model = Model::from_legacy_bytes(&bytes)
            .map_err(|e| Failure::input(format!("{}: {e}", path.display())))?;
        let found = model.meta.format_version;
        let refined = args.refine && model.refresh_refinement();
        if found >= DIGEST_FORMAT_VERSION && !refined {
            println!("{}: already format {found}, digest checked", path.display());
            continue;
        }
        model
            .save(path)
            .map_err(|e| Failure::io(format!("{}: {e}", path.display())))?;
        println!(
            "{}: format {found} -> {FORMAT_VERSION} ({} cells, digest written){}",
            path.display(),
            model.meta.pyramid.features,
            if refined {
                ", pixel refinement set to this build's"
            } else {
                ""
            }
        );
    }
    Ok(())
}
