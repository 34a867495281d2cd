//! Joining each object's single-pose model with the view components of
//! a model trained apart (views and box-only photographs), their scores
//! moved by an offset so that a view component fires where the
//! single-pose one does not (`sdhop-train join`). With `check_folds`,
//! whether to join an object, at which offset, with which colour-agreement
//! weight and at which detection threshold is chosen per object by
//! cross-validation over its box-only photographs, guarded by held-out
//! single-pose photographs ([`super::join_guard`]).

use super::join_check::{self, Check};
use super::join_cost::{self, CostBench, CostInfo};
use super::join_set;
use super::{load_model_dir, RouteError};
use crate::model::Model;
use crate::train::ko8::{EvalDetect, Ko8Data};
use crate::train::progress_bar;
use std::path::PathBuf;

/// What to join and how; see `sdhop-train join --help` for each field.
#[derive(Clone, Debug)]
pub struct JoinSettings {
    pub base: PathBuf,
    pub add: PathBuf,
    pub offset: Vec<String>,
    pub objects: Vec<String>,
    pub ko8: Option<PathBuf>,
    pub check_folds: Vec<PathBuf>,
    /// Single-pose models of a cross-validation (`cv --save-models DIR`):
    /// the single-pose guard scores each fold's held-out photographs with
    /// that fold's models ([`super::join_guard`]).
    pub guard_folds: Option<PathBuf>,
    pub offsets: Vec<f64>,
    pub colour_weights: Vec<f64>,
    pub thresholds: Vec<f64>,
    pub threshold_tolerance: f64,
    pub colour_weight: Option<f64>,
    pub min_gain: f64,
    pub single_tolerance: f64,
    /// What the single-pose guard holds: the set's figures or each
    /// object's.
    pub guard_scope: GuardScope,
    /// The candidates' figures from an earlier check's models (their
    /// provenance's `join_check`) instead of scoring the folds again.
    pub recorded: Option<PathBuf>,
    /// The set's estimated time at most this many times the unjoined
    /// set's (`--guard-scope set` only; `None`: no budget, no cost pass).
    pub max_time_ratio: Option<f64>,
    /// Single-pose photographs the cost pass times each candidate on.
    pub cost_photos: usize,
}

/// What `--check-folds`' single-pose guard holds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum GuardScope {
    /// The set's means over objects no worse than the unjoined set's:
    /// the figures the acceptance measures (the search: `join_set`).
    #[default]
    Set,
    /// Each object's figures no worse than its unjoined model's.
    Object,
}

impl Default for JoinSettings {
    fn default() -> Self {
        Self {
            base: PathBuf::from("models"),
            add: PathBuf::new(),
            offset: vec!["0".into()],
            objects: Vec::new(),
            ko8: None,
            check_folds: Vec::new(),
            guard_folds: None,
            offsets: vec![0.0, 0.25, 0.5],
            colour_weights: vec![0.0, 0.25, 0.5],
            thresholds: vec![-0.5, -0.25],
            threshold_tolerance: 0.005,
            colour_weight: None,
            min_gain: 0.01,
            single_tolerance: 0.002,
            guard_scope: GuardScope::Set,
            recorded: None,
            max_time_ratio: Some(1.4),
            cost_photos: 24,
        }
    }
}

/// What [`join_models`] made.
pub struct Joined {
    /// Every base model, joined or not, with a line saying which.
    pub models: Vec<(Model, String)>,
    /// With `check_folds`: each object's candidates and choice.
    pub choice: Option<Vec<Choice>>,
    /// With `max_time_ratio`: the cost pass's figures.
    pub cost: Option<CostInfo>,
}

/// One way to ship an object's model: joined at an offset or not, with a
/// colour-agreement weight.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Setting {
    /// `None`: not joined.
    pub offset: Option<f64>,
    /// [`crate::vision::detect::DetectParams::colour_weight`].
    pub colour_weight: f64,
    /// The joined model's detection threshold (`None`: the base model's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub threshold: Option<f64>,
}

/// Figures of one setting for one object.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct Candidate {
    pub setting: Setting,
    /// Per fold: (AUC, cross-object AUC) on its held-out photographs.
    pub folds: Vec<(f64, f64)>,
    /// Mean over folds of (AUC + cross AUC) / 2.
    pub held_out: f64,
    /// On the single-pose photographs: AUC, cross AUC, refined
    /// segmentation error, refined VOC error.
    pub single: Option<[f64; 4]>,
    pub admissible: bool,
    /// Mean time per photograph of the object's model in this setting,
    /// alone on one compute thread, ms ([`join_cost`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cost_ms: Option<f64>,
}

impl Candidate {
    /// `setting`'s candidate, not yet scored.
    pub fn blank(setting: Setting) -> Self {
        Self {
            setting,
            folds: Vec::new(),
            held_out: 0.0,
            single: None,
            admissible: true,
            cost_ms: None,
        }
    }
}

/// What `--check-folds` chose for one object.
pub struct Choice {
    pub name: String,
    /// `None`: the base model unchanged.
    pub setting: Option<Setting>,
    pub candidates: Vec<Candidate>,
    /// The base model as it is among `candidates` (not joined, its own
    /// colour weight).
    pub plain: Option<usize>,
}

/// The set's figures under a choice and left unjoined: the mean over
/// objects of the held-out figure from any side and of the single-pose
/// AUC, cross AUC, refined segmentation and VOC errors.
#[derive(Clone, Debug, serde::Serialize)]
pub struct SetFigures {
    pub guard_scope: &'static str,
    pub any_side: f64,
    pub single: [f64; 4],
    pub unjoined_any_side: f64,
    pub unjoined_single: [f64; 4],
    /// The set's estimated time over the unjoined set's, and the most
    /// `--max-time-ratio` allowed ([`join_cost::time_ratio`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub time_ratio: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_time_ratio: Option<f64>,
}

/// The set's figures of `choice`; `None` where an object lacks them.
/// With the cost pass's `cost`, its estimated time ratio.
pub fn set_figures(
    choice: &[Choice],
    scope: GuardScope,
    cost: Option<&CostInfo>,
) -> Option<SetFigures> {
    let mut sum = [0.0; 10];
    let (mut chosen_ms, mut plain_ms) = (Vec::new(), Vec::new());
    for ch in choice {
        let plain = &ch.candidates[ch.plain?];
        let chosen = match ch.setting {
            Some(s) => ch.candidates.iter().find(|c| c.setting == s)?,
            None => plain,
        };
        chosen_ms.push(chosen.cost_ms);
        plain_ms.push(plain.cost_ms);
        let (a, b) = (chosen.single?, plain.single?);
        let row = [
            chosen.held_out,
            a[0],
            a[1],
            a[2],
            a[3],
            plain.held_out,
            b[0],
            b[1],
            b[2],
            b[3],
        ];
        sum.iter_mut().zip(row).for_each(|(s, x)| *s += x);
    }
    let n = choice.len().max(1) as f64;
    let m: Vec<f64> = sum.iter().map(|s| s / n).collect();
    let ms = |v: Vec<Option<f64>>| v.into_iter().collect::<Option<Vec<f64>>>();
    let time_ratio = match (cost, ms(chosen_ms), ms(plain_ms)) {
        (Some(c), Some(a), Some(b)) => Some(join_cost::time_ratio(c.pyramid_ms, &a, &b)),
        _ => None,
    };
    Some(SetFigures {
        guard_scope: match scope {
            GuardScope::Set => "set",
            GuardScope::Object => "object",
        },
        any_side: m[0],
        single: [m[1], m[2], m[3], m[4]],
        unjoined_any_side: m[5],
        unjoined_single: [m[6], m[7], m[8], m[9]],
        time_ratio,
        max_time_ratio: cost.map(|c| c.max_time_ratio),
    })
}

/// `m` in `setting`, with `add` the components to join (if any).
fn apply(m: &Model, add: Option<&Model>, setting: Setting) -> Result<Model, RouteError> {
    let mut out = match (setting.offset, add) {
        (Some(o), Some(a)) => m
            .joined(a, o)
            .map_err(|e| RouteError::input(format!("{}: {e}", m.meta.name)))?,
        _ => m.clone(),
    };
    out.meta.detection.colour_weight = setting.colour_weight;
    if let (Some(t), Some(_)) = (setting.threshold, setting.offset) {
        out.meta.detection.threshold = t;
    }
    Ok(out)
}

/// `base`'s models each in its setting (`None`: unchanged), each with
/// `add`'s model of its object.
pub(super) fn applied_each(
    base: &[Model],
    add: &[Model],
    settings: &[Option<Setting>],
) -> Result<Vec<Model>, RouteError> {
    base.iter()
        .zip(settings)
        .map(|(m, s)| match s {
            Some(s) => apply(m, add.iter().find(|a| a.meta.name == m.meta.name), *s),
            None => Ok(m.clone()),
        })
        .collect()
}

/// `base`'s models all in `setting`.
pub(super) fn applied_all(
    base: &[Model],
    add: &[Model],
    setting: Setting,
) -> Result<Vec<Model>, RouteError> {
    applied_each(base, add, &vec![Some(setting); base.len()])
}

/// How the check detects: the best 20 detections per photograph, as the
/// acceptance procedure keeps.
pub(super) const CHECK_DETECT: EvalDetect = EvalDetect {
    max_detections: 20,
    threshold: None,
    pixel: None,
};

/// The settings the check compares: for each colour weight asked for (the
/// base model's own without any), not joining and joining at each offset.
fn settings_grid(args: &JoinSettings, m0: &Model) -> Vec<Setting> {
    let mut weights = args.colour_weights.clone();
    if weights.is_empty() {
        weights.push(m0.meta.detection.colour_weight);
    }
    weights
        .iter()
        .flat_map(|&colour_weight| {
            std::iter::once(None)
                .chain(args.offsets.iter().map(|&o| Some(o)))
                .map(move |offset| Setting {
                    offset,
                    colour_weight,
                    threshold: None,
                })
        })
        .collect()
}

/// The setting chosen per object by the folds (or by the figures
/// `--recorded` holds), with every candidate's figures, and the cost
/// pass's where `--max-time-ratio` asks for one.
fn choose_settings(
    args: &JoinSettings,
    base: &[Model],
    added: &[Model],
) -> Result<(Vec<Choice>, Option<CostInfo>), RouteError> {
    let root = args
        .ko8
        .as_ref()
        .ok_or_else(|| RouteError::input("--check-folds and --recorded need --ko8"))?;
    if args
        .offsets
        .iter()
        .chain(&args.colour_weights)
        .any(|o| !o.is_finite())
        || args.colour_weights.iter().any(|&w| w < 0.0)
    {
        return Err(RouteError::input(
            "--offsets and --thresholds must be finite numbers, --colour-weights finite and >= 0",
        ));
    }
    if args
        .max_time_ratio
        .is_some_and(|r| !(r >= 1.0 && r.is_finite()))
        || args.cost_photos == 0
    {
        return Err(RouteError::input(
            "--max-time-ratio must be a finite number >= 1 and --cost-photos at least 1",
        ));
    }
    let m0 = base
        .first()
        .ok_or_else(|| RouteError::input("no base model"))?;
    // Checked before the data are read: a check without its guard is
    // refused as such.
    let guard_dir = match &args.recorded {
        Some(_) => None,
        None => Some(args.guard_folds.as_ref().ok_or_else(|| {
            RouteError::input(
                "--check-folds needs --guard-folds DIR: single-pose models of a cross-validation \
                 (`sdhop-train cv --ko8 DATA --folds K --save-models DIR`), so that the single-pose \
                 guard scores photographs that trained neither side",
            )
        })?),
    };
    let recorded = match &args.recorded {
        Some(d) => Some(join_check::recorded_candidates(d, base)?),
        None => None,
    };
    let data = match guard_dir {
        None => Ko8Data::load(root, &[]),
        Some(_) => Ko8Data::load(root, &[]).and_then(|d| d.with_multiview(root)),
    }
    .map_err(RouteError::input)?;
    // The candidates' figures: recorded, or scored on the folds and the
    // guard (whose check also scores the thresholds below).
    let (check, mut cands, recorded_higher) = match (recorded, guard_dir) {
        (Some((grid, higher)), _) => (None, grid, Some(higher)),
        (None, guard_dir) => {
            let guard_dir = guard_dir.ok_or_else(|| RouteError::input("no --guard-folds"))?;
            let check = Check::load(&data, base, &args.check_folds, guard_dir)?;
            let cands = check.score_grid(base, added, &settings_grid(args, m0))?;
            (Some(check), cands, None)
        }
    };
    let bench = match args.max_time_ratio {
        Some(r) => Some((
            CostBench::new(&join_cost::cost_photographs(&data, args.cost_photos), m0)?,
            r,
        )),
        None => None,
    };
    if let Some((b, _)) = &bench {
        time_candidates(b, base, added, &mut cands)?;
    }
    let budget = bench
        .as_ref()
        .and_then(|(b, r)| models_budget_of(&cands, base, b.pyramid_ms, *r));
    let mut out = pick_all(args, base, added, cands, budget);
    // Higher thresholds for the joined models (fewer locations reach the
    // min-cuts, fewer masks), each object's chosen setting at each.
    let mut extra = match (&check, recorded_higher) {
        (_, Some(higher)) => recorded_at_chosen(&out, higher),
        (Some(check), None) => threshold_candidates(check, args, base, added, &out, m0)?,
        (None, None) => Vec::new(),
    };
    if let Some((b, _)) = &bench {
        time_candidates(b, base, added, &mut extra)?;
    }
    settle_thresholds(&mut out, extra, args);
    Ok((out, bench.map(|(b, r)| b.info(r))))
}

/// Each candidate's `cost_ms`: its object's model in its setting, timed
/// alone on the bench.
fn time_candidates(
    bench: &CostBench,
    base: &[Model],
    added: &[Model],
    cands: &mut [Vec<Candidate>],
) -> Result<(), RouteError> {
    let total = cands.iter().map(Vec::len).sum::<usize>();
    let pb = progress_bar(total as u64, "each candidate's time, alone on one thread");
    for (m, cs) in base.iter().zip(cands.iter_mut()) {
        let add = added.iter().find(|a| a.meta.name == m.meta.name);
        for c in cs.iter_mut() {
            // Joined without components to join: not a model to time.
            if add.is_some() || c.setting.offset.is_none() {
                c.cost_ms = Some(bench.model_ms(&apply(m, add, c.setting)?)?);
            }
            pb.inc(1);
        }
    }
    pb.finish_and_clear();
    Ok(())
}

/// What the models may take together under `ratio`: `None` where an
/// object's unjoined model has no time.
fn models_budget_of(
    cands: &[Vec<Candidate>],
    base: &[Model],
    pyramid_ms: f64,
    ratio: f64,
) -> Option<f64> {
    let plain: Option<Vec<f64>> = cands
        .iter()
        .zip(base)
        .map(|(cs, m)| cs[plain_of(cs, m.meta.detection.colour_weight)?].cost_ms)
        .collect();
    Some(join_cost::models_budget(ratio, pyramid_ms, &plain?))
}

/// Of the recorded candidates at higher thresholds, those of each
/// object's chosen setting.
fn recorded_at_chosen(out: &[Choice], higher: Vec<Vec<Candidate>>) -> Vec<Vec<Candidate>> {
    out.iter()
        .zip(higher)
        .map(|(c, h)| match c.setting.filter(|s| s.offset.is_some()) {
            Some(s) => h
                .into_iter()
                .filter(|x| {
                    x.setting.offset == s.offset && x.setting.colour_weight == s.colour_weight
                })
                .collect(),
            None => Vec::new(),
        })
        .collect()
}

/// Each joined object's chosen setting at each of `--thresholds` above
/// the base models', scored on the folds and the guard (increasing).
fn threshold_candidates(
    check: &Check,
    args: &JoinSettings,
    base: &[Model],
    added: &[Model],
    out: &[Choice],
    m0: &Model,
) -> Result<Vec<Vec<Candidate>>, RouteError> {
    let mut thresholds: Vec<f64> = args
        .thresholds
        .iter()
        .copied()
        .filter(|&t| t > m0.meta.detection.threshold)
        .collect();
    thresholds.sort_by(f64::total_cmp);
    let mut extra: Vec<Vec<Candidate>> = vec![Vec::new(); base.len()];
    if out
        .iter()
        .all(|c| c.setting.is_none_or(|s| s.offset.is_none()))
    {
        return Ok(extra);
    }
    let pb = progress_bar(thresholds.len() as u64, "thresholds of the joined models");
    for &t in &thresholds {
        let chosen: Vec<Option<Setting>> = out
            .iter()
            .map(|c| {
                c.setting.map(|s| Setting {
                    threshold: s.offset.map(|_| t),
                    ..s
                })
            })
            .collect();
        for (e, c) in extra
            .iter_mut()
            .zip(check.score_chosen(base, added, &chosen)?)
        {
            e.extend(c);
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    Ok(extra)
}

/// Each object's choice among its scored candidates, as `--guard-scope`
/// says.
fn pick_all(
    args: &JoinSettings,
    base: &[Model],
    added: &[Model],
    cands: Vec<Vec<Candidate>>,
    budget: Option<f64>,
) -> Vec<Choice> {
    let has_add = |m: &Model| added.iter().any(|a| a.meta.name == m.meta.name);
    match args.guard_scope {
        GuardScope::Object => base
            .iter()
            .zip(cands)
            .map(|(m, mut cs)| {
                let own = m.meta.detection.colour_weight;
                let setting = pick_setting(
                    &mut cs,
                    own,
                    has_add(m),
                    args.single_tolerance,
                    args.min_gain,
                );
                Choice {
                    name: m.meta.name.clone(),
                    setting,
                    plain: plain_of(&cs, own),
                    candidates: cs,
                }
            })
            .collect(),
        GuardScope::Set => {
            let mut objects: Vec<(Vec<Candidate>, Option<usize>, bool)> = base
                .iter()
                .zip(cands)
                .map(|(m, mut cs)| {
                    set_held_out(&mut cs);
                    let plain = plain_of(&cs, m.meta.detection.colour_weight);
                    (cs, plain, has_add(m))
                })
                .collect();
            let picks =
                join_set::pick_set(&mut objects, args.single_tolerance, args.min_gain, budget);
            base.iter()
                .zip(objects)
                .zip(picks)
                .map(|((m, (cs, plain, _)), p)| Choice {
                    name: m.meta.name.clone(),
                    setting: p.map(|i| cs[i].setting),
                    candidates: cs,
                    plain,
                })
                .collect()
        }
    }
}

/// Each candidate's `held_out`: the mean over folds of (AUC + cross) / 2.
fn set_held_out(cs: &mut [Candidate]) {
    for c in cs.iter_mut() {
        c.held_out =
            c.folds.iter().map(|(a, x)| 0.5 * (a + x)).sum::<f64>() / c.folds.len().max(1) as f64;
    }
}

/// The index of the base model as it is: not joined, its own colour
/// weight `own`.
fn plain_of(cs: &[Candidate], own: f64) -> Option<usize> {
    cs.iter()
        .position(|c| c.setting.offset.is_none() && c.setting.colour_weight == own)
}

/// Each joined object's highest threshold whose held-out figure stays
/// within `--threshold-tolerance` of its chosen setting's and whose
/// single-pose figures pass the guard (of `--guard-scope`); `extra` holds
/// each object's candidates at the higher thresholds, in increasing order.
fn settle_thresholds(out: &mut [Choice], extra: Vec<Vec<Candidate>>, args: &JoinSettings) {
    let plains: Vec<Option<[f64; 4]>> = out
        .iter()
        .map(|c| c.plain.and_then(|i| c.candidates[i].single))
        .collect();
    let single_of = |c: &Choice, plain: Option<[f64; 4]>| match c.setting {
        Some(s) => c
            .candidates
            .iter()
            .find(|x| x.setting == s)
            .and_then(|x| x.single),
        None => plain,
    };
    let mut chosen: Vec<Option<[f64; 4]>> = out
        .iter()
        .zip(&plains)
        .map(|(c, p)| single_of(c, *p))
        .collect();
    for (k, (c, more)) in out.iter_mut().zip(extra).enumerate() {
        let Some(best) = c
            .setting
            .and_then(|s| c.candidates.iter().find(|x| x.setting == s))
        else {
            continue;
        };
        let floor = best.held_out - args.threshold_tolerance;
        let mut more = more;
        for x in &mut more {
            x.admissible = x.held_out >= floor
                && match (x.single, plains[k]) {
                    (Some(s), Some(p)) => match args.guard_scope {
                        GuardScope::Object => single_within(&s, &p, args.single_tolerance),
                        GuardScope::Set => {
                            join_set::set_allows(&chosen, &plains, k, s, args.single_tolerance)
                        }
                    },
                    _ => true,
                };
        }
        // The highest admissible threshold (they come in increasing order).
        if let Some(x) = more.iter().rev().find(|x| x.admissible) {
            c.setting = Some(x.setting);
            chosen[k] = x.single;
        }
        c.candidates.extend(more);
    }
}

/// Whether single-pose figures `s` are within `tol` of `p`'s: AUC and
/// cross AUC no lower, segmentation and VOC errors no higher.
fn single_within(s: &[f64; 4], p: &[f64; 4], tol: f64) -> bool {
    s[0] >= p[0] - tol && s[1] >= p[1] - tol && s[2] <= p[2] + tol && s[3] <= p[3] + tol
}

/// The best admissible setting by its held-out figure (mean over the
/// folds), where it gains at least `min_gain` over the base model as it is
/// (not joined, its own colour weight `own`); `None`: keep that. A setting
/// is admissible where its single-pose figures are within `tol` of the
/// base's (AUC and cross AUC no lower, segmentation and VOC errors no
/// higher) and, joined, there are components to join (`has_add`). Sets
/// each candidate's `held_out` and `admissible`.
fn pick_setting(
    cs: &mut [Candidate],
    own: f64,
    has_add: bool,
    tol: f64,
    min_gain: f64,
) -> Option<Setting> {
    set_held_out(cs);
    let plain = plain_of(cs, own).map(|i| cs[i].clone());
    for c in cs.iter_mut() {
        let guard = match (c.single, plain.as_ref().and_then(|p| p.single)) {
            (Some(s), Some(p)) => single_within(&s, &p, tol),
            _ => true,
        };
        c.admissible = guard && (c.setting.offset.is_none() || has_add);
    }
    let floor = plain.as_ref().map_or(f64::NEG_INFINITY, |p| p.held_out) + min_gain;
    cs.iter()
        .filter(|c| c.admissible)
        .max_by(|a, b| a.held_out.total_cmp(&b.held_out))
        .filter(|c| c.held_out >= floor)
        .map(|c| c.setting)
}

/// The offset of `name` from `--offset`'s values: `NAME=VALUE` for it,
/// else a bare value, else 0.
fn offset_of(values: &[String], name: &str) -> Result<f64, RouteError> {
    let mut bare = None;
    for v in values {
        let parse = |t: &str| {
            t.trim()
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| RouteError::input(format!("--offset: {v:?} is not a number")))
        };
        match v.split_once('=') {
            Some((n, x)) if n.trim() == name => return parse(x),
            Some(_) => {}
            None => bare = Some(parse(v)?),
        }
    }
    Ok(bare.unwrap_or(0.0))
}

/// Joins each base model with the added model of its object as the
/// settings say (or as `check_folds` chooses): every base model, joined
/// or not, with a line saying what became of it, and the choice's figures.
pub fn join_models(args: &JoinSettings) -> Result<Joined, RouteError> {
    let base = load_model_dir(&args.base)?;
    if base.is_empty() {
        return Err(RouteError::input(format!(
            "--base {}: no *.safetensors models",
            args.base.display()
        )));
    }
    if let Some(m) = base
        .iter()
        .find(|m| m.meta.provenance.get("joined").is_some())
    {
        return Err(RouteError::input(format!(
            "--base {}: {} is already a joined model; join the single-pose models (train --sources single)",
            args.base.display(),
            m.meta.name
        )));
    }
    let added = load_model_dir(&args.add)?;
    for o in &args.objects {
        if !base.iter().any(|m| &m.meta.name == o) {
            return Err(RouteError::input(format!(
                "--objects: no base model {o:?} in {}",
                args.base.display()
            )));
        }
    }
    let (choice, cost) = if args.check_folds.is_empty() && args.recorded.is_none() {
        (None, None)
    } else {
        let (c, cost) = choose_settings(args, &base, &added)?;
        (Some(c), cost)
    };
    // The set's figures, the same in every model's provenance.
    let set_json = match choice
        .as_ref()
        .and_then(|c| set_figures(c, args.guard_scope, cost.as_ref()))
    {
        Some(f) => Some(serde_json::to_value(&f).map_err(RouteError::io)?),
        None => None,
    };
    let mut models = Vec::new();
    for m in &base {
        let name = &m.meta.name;
        let chosen = args.objects.is_empty() || args.objects.contains(name);
        let other = added.iter().find(|a| &a.meta.name == name);
        let setting = match &choice {
            Some(c) => c
                .iter()
                .find(|ch| &ch.name == name)
                .and_then(|ch| ch.setting),
            None => Some(Setting {
                offset: Some(offset_of(&args.offset, name)?),
                colour_weight: args.colour_weight.unwrap_or(m.meta.detection.colour_weight),
                threshold: None,
            }),
        };
        let (mut j, line) = match setting.filter(|_| chosen) {
            Some(setting) => {
                let j = apply(m, other, setting)?;
                let joined = match (setting.offset, other) {
                    (Some(o), Some(a)) => format!(
                        "+ {} component(s) at offset {o:+.3}, threshold {}",
                        a.views.len(),
                        j.meta.detection.threshold
                    ),
                    _ => "not joined".into(),
                };
                let line = format!(
                    "{name}: {} component(s) {joined}, colour weight {}",
                    m.views.len(),
                    setting.colour_weight
                );
                (j, line)
            }
            None => (m.clone(), format!("{name}: unchanged")),
        };
        // The check's figures go with every model it judged, joined or not.
        if let (Some(c), Some(p)) = (&choice, j.meta.provenance.as_object_mut()) {
            if let Some(ch) = c.iter().find(|ch| &ch.name == name) {
                p.insert(
                    "join_check".into(),
                    serde_json::to_value(&ch.candidates).map_err(RouteError::io)?,
                );
            }
            if let Some(f) = &set_json {
                p.insert("join_set".into(), f.clone());
            }
            if let Some(c) = &cost {
                p.insert(
                    "join_cost".into(),
                    serde_json::to_value(c).map_err(RouteError::io)?,
                );
            }
        }
        models.push((j, line));
    }
    Ok(Joined {
        models,
        choice,
        cost,
    })
}

/// The table of `--check-folds`' figures, a line each, then the set's
/// figures under the choice and unjoined.
pub fn choice_table(choice: &[Choice], scope: GuardScope, cost: Option<&CostInfo>) -> Vec<String> {
    let mut lines = vec![format!(
        "object      offset (threshold) colour  held-out (AUC+cross)/2 [per fold]  single AUC/cross/seg/VOC  ms  ok"
    )];
    for ch in choice {
        for c in &ch.candidates {
            let folds: Vec<String> = c
                .folds
                .iter()
                .map(|(a, x)| format!("{:.3}", 0.5 * (a + x)))
                .collect();
            let single = c.single.map_or("-".into(), |s| {
                format!("{:.3}/{:.3}/{:.4}/{:.4}", s[0], s[1], s[2], s[3])
            });
            let mark = if Some(c.setting) == ch.setting {
                " <"
            } else {
                ""
            };
            let ms = c.cost_ms.map_or("-".into(), |t| format!("{t:.1}"));
            lines.push(format!(
                "{:<11} {:>6} {:>6.2}  {:.3} [{}]  {single}  {ms}  {}{mark}",
                ch.name,
                match (c.setting.offset, c.setting.threshold) {
                    (None, _) => "none".to_string(),
                    (Some(o), None) => format!("{o:+.2}"),
                    (Some(o), Some(t)) => format!("{o:+.2} t{t}"),
                },
                c.setting.colour_weight,
                c.held_out,
                folds.join(" "),
                if c.admissible { "yes" } else { "no" },
            ));
        }
    }
    if let Some(f) = set_figures(choice, scope, cost) {
        let single = |s: [f64; 4]| format!("{:.4}/{:.4}/{:.4}/{:.4}", s[0], s[1], s[2], s[3]);
        lines.push(format!(
            "set ({} guard), mean over objects: any side held out {:.4} (unjoined {:.4}); \
             single pose AUC/cross/seg/VOC {} (unjoined {})",
            f.guard_scope,
            f.any_side,
            f.unjoined_any_side,
            single(f.single),
            single(f.unjoined_single)
        ));
        if let (Some(r), Some(c)) = (f.time_ratio, cost) {
            lines.push(format!(
                "time (each model alone on one thread, {} single-pose photographs, pyramid {:.1} ms): \
                 {r:.2}x the unjoined set's (at most {:.2})",
                c.photographs, c.pyramid_ms, c.max_time_ratio
            ));
        }
    }
    lines
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cand(
        offset: Option<f64>,
        colour_weight: f64,
        folds: &[(f64, f64)],
        single: [f64; 4],
    ) -> Candidate {
        Candidate {
            setting: Setting {
                offset,
                colour_weight,
                threshold: None,
            },
            folds: folds.to_vec(),
            held_out: 0.0,
            single: Some(single),
            admissible: false,
            cost_ms: None,
        }
    }

    const SP: [f64; 4] = [1.0, 1.0, 0.20, 0.10];

    #[test]
    fn the_best_held_out_setting_wins_within_the_single_pose_guard() {
        let mut cs = vec![
            cand(None, 0.0, &[(0.5, 0.5), (0.7, 0.7)], SP),
            cand(Some(0.0), 0.0, &[(0.7, 0.7), (0.8, 0.8)], SP),
            // Best held out, but it segments the single-pose photographs worse.
            cand(
                Some(0.5),
                0.0,
                &[(0.9, 0.9), (0.9, 0.9)],
                [1.0, 1.0, 0.21, 0.10],
            ),
            cand(None, 0.5, &[(0.6, 0.6), (0.7, 0.7)], SP),
        ];
        let s = pick_setting(&mut cs, 0.0, true, 0.002, 0.01);
        assert_eq!(
            s,
            Some(Setting {
                offset: Some(0.0),
                colour_weight: 0.0,
                threshold: None
            })
        );
        assert!((cs[1].held_out - 0.75).abs() < 1e-12);
        assert!(!cs[2].admissible && cs[3].admissible);
        // Without components to join, only the colour weight can change.
        let s = pick_setting(&mut cs, 0.0, false, 0.002, 0.01);
        assert_eq!(
            s,
            Some(Setting {
                offset: None,
                colour_weight: 0.5,
                threshold: None
            })
        );
        // A gain below the least one keeps the base model.
        assert_eq!(pick_setting(&mut cs, 0.0, false, 0.002, 0.1), None);
    }

    #[test]
    fn the_sets_figures_are_the_means_of_each_objects_choice() {
        let mut a = vec![
            cand(None, 0.0, &[(0.5, 0.5)], [0.9, 0.9, 0.3, 0.2]),
            cand(Some(0.0), 0.0, &[(0.9, 0.9)], [0.8, 0.8, 0.4, 0.3]),
        ];
        let mut b = vec![cand(None, 0.0, &[(0.7, 0.7)], [1.0, 1.0, 0.1, 0.0])];
        set_held_out(&mut a);
        set_held_out(&mut b);
        let choice = vec![
            Choice {
                name: "a".into(),
                setting: Some(a[1].setting),
                candidates: a,
                plain: Some(0),
            },
            Choice {
                name: "b".into(),
                setting: None,
                candidates: b,
                plain: Some(0),
            },
        ];
        let f = set_figures(&choice, GuardScope::Set, None).unwrap();
        assert!((f.any_side - 0.8).abs() < 1e-12);
        assert!((f.unjoined_any_side - 0.6).abs() < 1e-12);
        let near = |got: [f64; 4], want: [f64; 4]| {
            got.iter().zip(want).all(|(x, y)| (x - y).abs() < 1e-12)
        };
        assert!(near(f.single, [0.9, 0.9, 0.25, 0.15]), "{:?}", f.single);
        assert!(
            near(f.unjoined_single, [0.95, 0.95, 0.2, 0.1]),
            "{:?}",
            f.unjoined_single
        );
        assert_eq!(
            choice_table(&choice, GuardScope::Set, None).len(),
            1 + 3 + 1
        );
    }

    #[test]
    fn offsets_per_object_or_for_all() {
        let v: Vec<String> = ["0.25", "cup=-0.5"].iter().map(|s| s.to_string()).collect();
        assert_eq!(offset_of(&v, "cup").unwrap(), -0.5);
        assert_eq!(offset_of(&v, "shaker").unwrap(), 0.25);
        assert_eq!(offset_of(&[], "cup").unwrap(), 0.0);
        assert!(offset_of(&["cup=x".to_string()], "cup").is_err());
        assert!(offset_of(&["inf".to_string()], "cup").is_err());
    }
}
