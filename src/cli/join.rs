//! `sdhop-train join`: each object's single-pose model joined with the
//! view components of a model trained apart (views and box-only
//! photographs), their scores moved by an offset so that a view component
//! fires where the single-pose one does not.

use super::*;

#[derive(clap::Args)]
pub(crate) struct JoinArgs {
    /// Folder of the base models (e.g. the shipped single-pose ones).
    #[arg(long, default_value = "models")]
    pub(crate) base: PathBuf,
    /// Folder of the models whose components are appended (e.g. `train
    /// --sources views,boxes`), matched to the base models by name; base
    /// models without one are written unchanged.
    #[arg(long)]
    pub(crate) add: PathBuf,
    /// Added to the appended components' scores (negative: they fire
    /// less). One value for every object, or `NAME=VALUE` pairs
    /// (comma-separated) for some.
    #[arg(long, value_delimiter = ',', default_value = "0", allow_hyphen_values = true)]
    pub(crate) offset: Vec<String>,
    /// Only these objects get the appended components (default: every one
    /// with a model in `--add`).
    #[arg(long, value_delimiter = ',')]
    pub(crate) objects: Vec<String>,
    /// Output folder (created).
    #[arg(long)]
    pub(crate) out: PathBuf,
}

/// The offset of `name` from `--offset`'s values: `NAME=VALUE` for it,
/// else a bare value, else 0.
fn offset_of(values: &[String], name: &str) -> Result<f64, Failure> {
    let mut bare = None;
    for v in values {
        let parse = |t: &str| {
            t.trim()
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| Failure::input(format!("--offset: {v:?} is not a number")))
        };
        match v.split_once('=') {
            Some((n, x)) if n.trim() == name => return parse(x),
            Some(_) => {}
            None => bare = Some(parse(v)?),
        }
    }
    Ok(bare.unwrap_or(0.0))
}

pub(crate) fn run_join(args: &JoinArgs) -> Result<(), Failure> {
    let base = load_model_dir(&args.base)?;
    if base.is_empty() {
        return Err(Failure::input(format!(
            "--base {}: no *.safetensors models",
            args.base.display()
        )));
    }
    let added = load_model_dir(&args.add)?;
    for o in &args.objects {
        if !base.iter().any(|m| &m.meta.name == o) {
            return Err(Failure::input(format!(
                "--objects: no base model {o:?} in {}",
                args.base.display()
            )));
        }
    }
    std::fs::create_dir_all(&args.out)
        .map_err(|e| Failure::io(format!("{}: {e}", args.out.display())))?;
    for m in &base {
        let name = &m.meta.name;
        let chosen = args.objects.is_empty() || args.objects.contains(name);
        let other = added.iter().find(|a| &a.meta.name == name);
        let out = match other.filter(|_| chosen) {
            Some(o) => {
                let offset = offset_of(&args.offset, name)?;
                let j = m
                    .joined(o, offset)
                    .map_err(|e| Failure::input(format!("{name}: {e}")))?;
                println!(
                    "{name}: {} + {} component(s), offset {offset:+.3}",
                    m.views.len(),
                    o.views.len()
                );
                j
            }
            None => {
                println!("{name}: unchanged");
                m.clone()
            }
        };
        let path = args.out.join(format!("{name}.safetensors"));
        out.save(&path).map_err(Failure::io)?;
    }
    Ok(())
}
