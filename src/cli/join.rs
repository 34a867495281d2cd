//! `sdhop-train join`: each object's single-pose model joined with the
//! view components of a model trained apart; the route is
//! [`crate::train::routes::join::join_models`]. This command parses the
//! flags into its settings, prints the choice and saves the models.

use super::*;
use crate::train::routes::join::{choice_table, join_models, GuardScope, JoinSettings, Joined};

#[derive(clap::Args)]
pub(crate) struct JoinArgs {
    /// Folder of the base models (e.g. the shipped single-pose ones).
    #[arg(long, default_value_os_t = JoinSettings::default().base)]
    pub(crate) base: PathBuf,
    /// Folder of the models whose components are appended (e.g. `train
    /// --sources views,boxes`), matched to the base models by name; base
    /// models without one are written unchanged.
    #[arg(long)]
    pub(crate) add: PathBuf,
    /// Added to the appended components' scores (negative: they fire
    /// less). One value for every object, or `NAME=VALUE` pairs
    /// (comma-separated) for some.
    /// Default 0.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
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
    /// object among not joining and joining at each of `--offsets`, each
    /// with each of `--colour-weights`, by the mean of AUC and
    /// cross-object AUC on each fold's held-out box-only photographs,
    /// averaged over the folds. A choice must also keep the single-pose
    /// figures of `--guard-folds` (with `--add`'s components) and gain at
    /// least `--min-gain` over the base model as it is, which is kept
    /// otherwise. Replaces `--offset` and `--colour-weight`.
    #[arg(long, value_delimiter = ',', requires = "ko8")]
    pub(crate) check_folds: Vec<PathBuf>,
    /// The single-pose guard of `--check-folds`: a folder of
    /// cross-validation models (`sdhop-train cv --ko8 DATA --folds K
    /// --save-models DIR`, single-pose models trained as `--base`'s). Each
    /// fold's held-out single-pose photographs are scored with that fold's
    /// models joined as each setting says, so the guard never scores a
    /// photograph that trained what it judges.
    #[arg(long, value_name = "DIR", requires = "check_folds")]
    pub(crate) guard_folds: Option<PathBuf>,
    /// Offsets `--check-folds` chooses among (besides not joining).
    /// Default 0,0.25,0.5.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub(crate) offsets: Vec<f64>,
    /// Colour-agreement weights `--check-folds` chooses among, for each
    /// offset and for not joining (`DetectParams::colour_weight`: the
    /// mean log ratio of the object's learned colours to the image's over
    /// a detection's mask, added to its score).
    /// Default 0,0.25,0.5.
    #[arg(long, value_delimiter = ',')]
    pub(crate) colour_weights: Vec<f64>,
    /// Detection thresholds above the base models' that `--check-folds`
    /// then tries for each joined model in its chosen setting, keeping the
    /// highest whose held-out figure stays within `--threshold-tolerance`
    /// of the setting's at the base threshold (and whose single-pose
    /// figures pass the guard): fewer locations reach the min-cuts and
    /// fewer detections get masks. Sorted increasing.
    /// Default -0.5,-0.25.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub(crate) thresholds: Vec<f64>,
    /// How much held-out figure a higher threshold may cost.
    #[arg(long, default_value_t = JoinSettings::default().threshold_tolerance)]
    pub(crate) threshold_tolerance: f64,
    /// The colour weight of every output model without `--check-folds`
    /// (default: each base model's own).
    #[arg(long)]
    pub(crate) colour_weight: Option<f64>,
    /// Least gain of a setting's held-out figure over the base model's for
    /// `--check-folds` to choose it.
    #[arg(long, default_value_t = JoinSettings::default().min_gain)]
    pub(crate) min_gain: f64,
    /// Most a joined model may lose on the single-pose photographs (AUC,
    /// cross-object AUC; segmentation and VOC errors may rise as much).
    #[arg(long, default_value_t = JoinSettings::default().single_tolerance)]
    pub(crate) single_tolerance: f64,
    /// What the single-pose guard holds. `set`: the means over objects of
    /// the set's single-pose figures no worse than the unjoined set's
    /// (within `--single-tolerance` per object), the choice being the set
    /// that finds the objects best from any side (one object may give up
    /// what another gains). `object`: each object's figures no worse than
    /// its unjoined model's.
    #[arg(long, value_enum, default_value_t = GuardScope::Set)]
    pub(crate) guard_scope: GuardScope,
    /// Choose from the figures an earlier `join --check-folds` wrote into
    /// its models (this folder's `*.safetensors`, their provenance's
    /// `join_check`) instead of scoring the folds again: for a choice
    /// under another `--max-time-ratio`, in minutes instead of an hour.
    /// `--base` and `--add` must be the models that check joined.
    #[arg(
        long,
        value_name = "DIR",
        requires = "ko8",
        conflicts_with = "check_folds"
    )]
    pub(crate) recorded: Option<PathBuf>,
    /// The set's time at most this many times the unjoined set's
    /// (`--guard-scope set`): each candidate is timed alone on one compute
    /// thread on `--cost-photos` single-pose photographs, and the set's
    /// time is estimated as one pyramid's plus its models' each. 0: no
    /// budget and no timing.
    #[arg(long, default_value_t = JoinSettings::default().max_time_ratio.unwrap_or(0.0))]
    pub(crate) max_time_ratio: f64,
    /// Single-pose photographs (spread over the objects) the candidates
    /// are timed on.
    #[arg(long, default_value_t = JoinSettings::default().cost_photos)]
    pub(crate) cost_photos: usize,
}

impl JoinArgs {
    /// The route's settings from the flags (an empty list: the default).
    fn settings(&self) -> JoinSettings {
        let d = JoinSettings::default();
        let or = |v: &Vec<f64>, d: Vec<f64>| if v.is_empty() { d } else { v.clone() };
        JoinSettings {
            base: self.base.clone(),
            add: self.add.clone(),
            offset: if self.offset.is_empty() {
                d.offset
            } else {
                self.offset.clone()
            },
            objects: self.objects.clone(),
            ko8: self.ko8.clone(),
            check_folds: self.check_folds.clone(),
            guard_folds: self.guard_folds.clone(),
            offsets: or(&self.offsets, d.offsets),
            colour_weights: or(&self.colour_weights, d.colour_weights),
            thresholds: or(&self.thresholds, d.thresholds),
            threshold_tolerance: self.threshold_tolerance,
            colour_weight: self.colour_weight,
            min_gain: self.min_gain,
            single_tolerance: self.single_tolerance,
            guard_scope: self.guard_scope,
            recorded: self.recorded.clone(),
            max_time_ratio: (self.max_time_ratio != 0.0).then_some(self.max_time_ratio),
            cost_photos: self.cost_photos,
        }
    }
}

pub(crate) fn run_join(args: &JoinArgs) -> Result<(), Failure> {
    let Joined {
        models,
        choice,
        cost,
    } = join_models(&args.settings())?;
    if let Some(c) = &choice {
        for line in choice_table(c, args.guard_scope, cost.as_ref()) {
            println!("{line}");
        }
    }
    std::fs::create_dir_all(&args.out)
        .map_err(|e| Failure::io(format!("{}: {e}", args.out.display())))?;
    for (model, line) in &models {
        println!("{line}");
        let path = args.out.join(format!("{}.safetensors", model.meta.name));
        model.save(&path).map_err(Failure::io)?;
    }
    Ok(())
}
