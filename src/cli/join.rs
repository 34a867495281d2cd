//! `sdhop-train join`: each object's single-pose model joined with the
//! view components of a model trained apart (views and box-only
//! photographs), their scores moved by an offset so that a view component
//! fires where the single-pose one does not. With `--check-folds`, whether
//! to join an object and at which offset is chosen per object by
//! cross-validation over its box-only photographs, guarded by the
//! single-pose photographs.

use super::*;
use crate::eval::detection::ObjectScore;
use crate::train::ko8::Ko8Data;
use train::fold_range;

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
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0",
        allow_hyphen_values = true
    )]
    pub(crate) offset: Vec<String>,
    /// Only these objects get the appended components (default: every one
    /// with a model in `--add`).
    #[arg(long, value_delimiter = ',')]
    pub(crate) objects: Vec<String>,
    /// Output folder (created).
    #[arg(long)]
    pub(crate) out: PathBuf,
    /// CMU_KO8 root, for `--check-folds`.
    #[arg(long)]
    pub(crate) ko8: Option<PathBuf>,
    /// Folders of fold models, fold K's (from 0) trained as `--add`'s with
    /// `train --box-fold K/N` (N = the number of folders): choose per
    /// object among not joining and joining at each of `--offsets` by the
    /// mean of AUC and cross-object AUC on each fold's held-out box-only
    /// photographs, averaged over the folds. A choice must also keep the
    /// single-pose photographs' figures (with `--add`'s components) and
    /// gain at least `--min-gain` over not joining. Replaces `--offset`.
    #[arg(long, value_delimiter = ',', requires = "ko8")]
    pub(crate) check_folds: Vec<PathBuf>,
    /// Offsets `--check-folds` chooses among.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0,0.25,0.5,0.75",
        allow_hyphen_values = true
    )]
    pub(crate) offsets: Vec<f64>,
    /// Least gain of a joined model's held-out figure over the base's for
    /// `--check-folds` to join it.
    #[arg(long, default_value_t = 0.01)]
    pub(crate) min_gain: f64,
    /// Most a joined model may lose on the single-pose photographs (AUC,
    /// cross-object AUC; segmentation and VOC errors may rise as much).
    #[arg(long, default_value_t = 0.002)]
    pub(crate) single_tolerance: f64,
}

/// Figures of one candidate (not joined, or joined at an offset) for one
/// object.
#[derive(Clone, Debug, Default, serde::Serialize)]
struct Candidate {
    offset: Option<f64>,
    /// Per fold: (AUC, cross-object AUC) on its held-out photographs.
    folds: Vec<(f64, f64)>,
    /// Mean over folds of (AUC + cross AUC) / 2.
    held_out: f64,
    /// On the single-pose photographs: AUC, cross AUC, refined
    /// segmentation error, refined VOC error.
    single: Option<[f64; 4]>,
    admissible: bool,
}

/// What `--check-folds` chose for one object.
struct Choice {
    name: String,
    /// `None`: not joined.
    offset: Option<f64>,
    candidates: Vec<Candidate>,
}

/// `base`'s models with `add`'s components joined at `offset` (none:
/// unchanged), for the objects `add` has.
fn joined_all(base: &[Model], add: &[Model], offset: Option<f64>) -> Result<Vec<Model>, Failure> {
    base.iter()
        .map(
            |m| match (offset, add.iter().find(|a| a.meta.name == m.meta.name)) {
                (Some(o), Some(a)) => m
                    .joined(a, o)
                    .map_err(|e| Failure::input(format!("{}: {e}", m.meta.name))),
                _ => Ok(m.clone()),
            },
        )
        .collect()
}

/// Detections of `models` on `images` scored per object.
fn evaluate(
    data: &Ko8Data,
    images: &[&Sample],
    models: &[Model],
    cache: &PyramidCache,
) -> Result<Vec<ObjectScore>, Failure> {
    let refs: Vec<&Model> = models.iter().collect();
    let how = EvalDetect {
        max_detections: 20,
        ..EvalDetect::default()
    };
    let responses = detect_all(images, &refs, cache, how).map_err(Failure::input)?;
    Ok(score(data, images, &responses).objects)
}

fn fill_cache(cache: &PyramidCache, images: &[&Sample], m: &Model) -> Result<(), Failure> {
    let pb = progress_bar(0, "pyramids");
    cache
        .fill(images, &m.meta.pyramid, &m.meta.segmentation, &pb)
        .map_err(Failure::input)?;
    pb.finish_and_clear();
    Ok(())
}

/// The offset chosen per object by the folds (`None`: not joined), with
/// every candidate's figures.
fn choose_offsets(
    args: &JoinArgs,
    base: &[Model],
    added: &[Model],
) -> Result<Vec<Choice>, Failure> {
    let root = args
        .ko8
        .as_ref()
        .ok_or_else(|| Failure::input("--check-folds needs --ko8"))?;
    let data = Ko8Data::load(root, &[])
        .and_then(|d| d.with_multiview(root))
        .map_err(Failure::input)?;
    let m0 = base
        .first()
        .ok_or_else(|| Failure::input("no base model"))?;
    let offsets: Vec<Option<f64>> = std::iter::once(None)
        .chain(args.offsets.iter().map(|&o| Some(o)))
        .collect();
    if args.offsets.iter().any(|o| !o.is_finite()) {
        return Err(Failure::input("--offsets must be finite numbers"));
    }
    let mut cands: Vec<Vec<Candidate>> = base
        .iter()
        .map(|_| {
            offsets
                .iter()
                .map(|&offset| Candidate {
                    offset,
                    ..Candidate::default()
                })
                .collect()
        })
        .collect();
    let position =
        |scores: &[ObjectScore], name: &str| scores.iter().position(|s| s.object == name);
    let n = args.check_folds.len();
    for (k, dir) in args.check_folds.iter().enumerate() {
        let fold = load_model_dir(dir)?;
        let images: Vec<&Sample> = data
            .photos
            .iter()
            .flat_map(|p| p[fold_range(k, n, p.len())].iter())
            .collect();
        eprintln!(
            "fold {k}/{n} ({}): {} held-out box-only photographs",
            dir.display(),
            images.len()
        );
        let cache = PyramidCache::default();
        fill_cache(&cache, &images, m0)?;
        for (ci, &offset) in offsets.iter().enumerate() {
            let models = joined_all(base, &fold, offset)?;
            let scores = evaluate(&data, &images, &models, &cache)?;
            for (mi, m) in base.iter().enumerate() {
                let s = position(&scores, &m.meta.name).map(|i| &scores[i]);
                cands[mi][ci]
                    .folds
                    .push(s.map_or((0.0, 0.0), |s| (s.auc, s.auc_cross)));
            }
        }
    }
    // The single-pose guard, with the components the output will carry.
    let images: Vec<&Sample> = data.images.iter().flatten().collect();
    eprintln!("single-pose guard: {} photographs", images.len());
    let cache = PyramidCache::default();
    fill_cache(&cache, &images, m0)?;
    for (ci, &offset) in offsets.iter().enumerate() {
        let models = joined_all(base, added, offset)?;
        let scores = evaluate(&data, &images, &models, &cache)?;
        for (mi, m) in base.iter().enumerate() {
            cands[mi][ci].single = position(&scores, &m.meta.name).map(|i| {
                let s = &scores[i];
                [s.auc, s.auc_cross, s.seg_error_refined, s.voc_error_refined]
            });
        }
    }
    let tol = args.single_tolerance;
    let mut out = Vec::new();
    for (m, mut cs) in base.iter().zip(cands) {
        for c in &mut cs {
            c.held_out = c.folds.iter().map(|(a, x)| 0.5 * (a + x)).sum::<f64>()
                / c.folds.len().max(1) as f64;
        }
        let plain = cs[0].clone();
        for c in &mut cs {
            c.admissible = match (c.single, plain.single) {
                (Some(s), Some(p)) => {
                    s[0] >= p[0] - tol
                        && s[1] >= p[1] - tol
                        && s[2] <= p[2] + tol
                        && s[3] <= p[3] + tol
                }
                _ => true,
            };
        }
        let has_add = added.iter().any(|a| a.meta.name == m.meta.name);
        let chosen = cs
            .iter()
            .filter(|c| c.offset.is_some() && c.admissible && has_add)
            .max_by(|a, b| a.held_out.total_cmp(&b.held_out))
            .filter(|c| c.held_out >= plain.held_out + args.min_gain)
            .and_then(|c| c.offset);
        out.push(Choice {
            name: m.meta.name.clone(),
            offset: chosen,
            candidates: cs,
        });
    }
    Ok(out)
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
    let choice = if args.check_folds.is_empty() {
        None
    } else {
        let c = choose_offsets(args, &base, &added)?;
        print_choice(&c);
        Some(c)
    };
    std::fs::create_dir_all(&args.out)
        .map_err(|e| Failure::io(format!("{}: {e}", args.out.display())))?;
    for m in &base {
        let name = &m.meta.name;
        let chosen = args.objects.is_empty() || args.objects.contains(name);
        let other = added.iter().find(|a| &a.meta.name == name);
        let picked = match &choice {
            Some(c) => c
                .iter()
                .find(|ch| &ch.name == name)
                .and_then(|ch| ch.offset),
            None => Some(offset_of(&args.offset, name)?),
        };
        let out = match (other.filter(|_| chosen), picked) {
            (Some(o), Some(offset)) => {
                let mut j = m
                    .joined(o, offset)
                    .map_err(|e| Failure::input(format!("{name}: {e}")))?;
                if let (Some(c), Some(p)) = (&choice, j.meta.provenance.as_object_mut()) {
                    if let Some(ch) = c.iter().find(|ch| &ch.name == name) {
                        p.insert(
                            "join_check".into(),
                            serde_json::to_value(&ch.candidates).map_err(Failure::io)?,
                        );
                    }
                }
                println!(
                    "{name}: {} + {} component(s), offset {offset:+.3}",
                    m.views.len(),
                    o.views.len()
                );
                j
            }
            _ => {
                println!("{name}: unchanged");
                m.clone()
            }
        };
        let path = args.out.join(format!("{name}.safetensors"));
        out.save(&path).map_err(Failure::io)?;
    }
    Ok(())
}

/// The table of `--check-folds`' figures.
fn print_choice(choice: &[Choice]) {
    println!("object      offset  held-out (AUC+cross)/2 per fold          single AUC/cross/seg/VOC   ok");
    for ch in choice {
        let (name, chosen) = (&ch.name, ch.offset);
        for c in &ch.candidates {
            let folds: Vec<String> = c
                .folds
                .iter()
                .map(|(a, x)| format!("{:.3}", 0.5 * (a + x)))
                .collect();
            let single = c.single.map_or("-".into(), |s| {
                format!("{:.3}/{:.3}/{:.4}/{:.4}", s[0], s[1], s[2], s[3])
            });
            let mark = if c.offset == chosen { " <" } else { "" };
            println!(
                "{name:<11} {:>6}  {:.3}  [{}]  {single}  {}{mark}",
                c.offset.map_or("none".into(), |o| format!("{o:+.2}")),
                c.held_out,
                folds.join(" "),
                if c.admissible { "yes" } else { "no" },
            );
        }
    }
}
