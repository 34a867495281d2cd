//! The figures `sdhop-train join --check-folds` chooses by: each setting
//! of each object scored on the held-out box-only photographs of each
//! check fold (from any side) and on the single-pose guard's held-out
//! photographs ([`super::join_guard`]); or, with `--recorded DIR`, the
//! figures an earlier check wrote into its models' provenance
//! (`join_check`), so that a choice under other constraints (a time
//! budget) needs no new scoring.

use super::join::{applied_all, applied_each, Candidate, Setting, CHECK_DETECT};
use super::join_guard::SinglePoseGuard;
use super::photos::fold_range;
use super::{load_model_dir, RouteError};
use crate::data::Sample;
use crate::eval::detection::ObjectScore;
use crate::model::Model;
use crate::train::ko8::{detect_all, score, Ko8Data};
use crate::train::{progress_bar, PyramidCache};
use std::path::{Path, PathBuf};

/// The check folds and the guard, their photographs' pyramids built.
pub(super) struct Check<'a> {
    data: &'a Ko8Data,
    folds: Vec<(Vec<Model>, Vec<&'a Sample>, PyramidCache)>,
    guard: SinglePoseGuard<'a>,
}

fn position(scores: &[ObjectScore], name: &str) -> Option<usize> {
    scores.iter().position(|s| s.object == name)
}

fn single_of(s: &ObjectScore) -> [f64; 4] {
    [s.auc, s.auc_cross, s.seg_error_refined, s.voc_error_refined]
}

/// `images`' pyramids with `m`'s settings (every model the join compares
/// shares them), behind a progress bar that first prints `note`.
pub(super) fn filled_cache(
    images: &[&Sample],
    m: &Model,
    note: Option<&str>,
) -> Result<PyramidCache, RouteError> {
    let cache = PyramidCache::default();
    let pb = progress_bar(0, "pyramids");
    if let Some(n) = note {
        pb.println(n);
    }
    cache
        .fill(images, &m.meta.pyramid, &m.meta.segmentation, &pb)
        .map_err(RouteError::input)?;
    pb.finish_and_clear();
    Ok(cache)
}

/// Detections of `models` on `images` scored per object.
fn evaluate(
    data: &Ko8Data,
    images: &[&Sample],
    models: &[Model],
    cache: &PyramidCache,
) -> Result<Vec<ObjectScore>, RouteError> {
    let refs: Vec<&Model> = models.iter().collect();
    let responses = detect_all(images, &refs, cache, CHECK_DETECT).map_err(RouteError::input)?;
    Ok(score(data, images, &responses).objects)
}

impl<'a> Check<'a> {
    /// The folds of `check_folds` (fold K's models hold out the K-th
    /// share of each object's box-only photographs) and the guard's
    /// (`guard_dir`), for `base`'s objects.
    pub(super) fn load(
        data: &'a Ko8Data,
        base: &[Model],
        check_folds: &[PathBuf],
        guard_dir: &Path,
    ) -> Result<Self, RouteError> {
        let m0 = base
            .first()
            .ok_or_else(|| RouteError::input("no base model"))?;
        let guard = SinglePoseGuard::load(guard_dir, data, base)?;
        let n = check_folds.len();
        let mut folds = Vec::new();
        for (k, dir) in check_folds.iter().enumerate() {
            let fold = load_model_dir(dir)?;
            let images: Vec<&Sample> = data
                .photos
                .iter()
                .flat_map(|p| p[fold_range(k, n, p.len())].iter())
                .collect();
            let note = format!(
                "fold {k}/{n} ({}): {} held-out box-only photographs",
                dir.display(),
                images.len()
            );
            let cache = filled_cache(&images, m0, Some(&note))?;
            folds.push((fold, images, cache));
        }
        progress_bar(0, "").println(format!(
            "single-pose guard: {} held-out photographs of {} fold(s) ({})",
            guard.photographs(),
            guard.folds(),
            guard_dir.display()
        ));
        Ok(Self { data, folds, guard })
    }

    /// Every object's candidate in every setting, scored (`held_out` is
    /// left for the choice to set).
    pub(super) fn score_grid(
        &self,
        base: &[Model],
        added: &[Model],
        settings: &[Setting],
    ) -> Result<Vec<Vec<Candidate>>, RouteError> {
        let mut cands: Vec<Vec<Candidate>> = base
            .iter()
            .map(|_| settings.iter().map(|&s| Candidate::blank(s)).collect())
            .collect();
        let pb = progress_bar(
            (settings.len() * (self.folds.len() + 1)) as u64,
            "settings on the folds and single-pose photographs",
        );
        for (fold, images, cache) in &self.folds {
            for (ci, &setting) in settings.iter().enumerate() {
                let models = applied_all(base, fold, setting)?;
                let scores = evaluate(self.data, images, &models, cache)?;
                for (mi, m) in base.iter().enumerate() {
                    let s = position(&scores, &m.meta.name).map(|i| &scores[i]);
                    cands[mi][ci]
                        .folds
                        .push(s.map_or((0.0, 0.0), |s| (s.auc, s.auc_cross)));
                }
                pb.inc(1);
            }
        }
        // The single-pose guard, with the components the output will
        // carry, on single-pose photographs that trained neither side.
        for (ci, &setting) in settings.iter().enumerate() {
            let scores = self
                .guard
                .score(self.data, added, &vec![Some(setting); base.len()])?;
            for (mi, m) in base.iter().enumerate() {
                cands[mi][ci].single =
                    position(&scores, &m.meta.name).map(|i| single_of(&scores[i]));
            }
            pb.inc(1);
        }
        pb.finish_and_clear();
        Ok(cands)
    }

    /// Each object's candidate in `chosen` (the objects joined only),
    /// scored, its held-out figure set; `None` for the others.
    pub(super) fn score_chosen(
        &self,
        base: &[Model],
        added: &[Model],
        chosen: &[Option<Setting>],
    ) -> Result<Vec<Option<Candidate>>, RouteError> {
        let mut fold_scores = Vec::new();
        for (fold, images, cache) in &self.folds {
            fold_scores.push(evaluate(
                self.data,
                images,
                &applied_each(base, fold, chosen)?,
                cache,
            )?);
        }
        let single = self.guard.score(self.data, added, chosen)?;
        Ok(base
            .iter()
            .zip(chosen)
            .map(|(m, s)| {
                let setting = s.filter(|s| s.offset.is_some())?;
                let name = &m.meta.name;
                let folds: Vec<(f64, f64)> = fold_scores
                    .iter()
                    .map(|sc| {
                        position(sc, name).map_or((0.0, 0.0), |i| (sc[i].auc, sc[i].auc_cross))
                    })
                    .collect();
                let mut c = Candidate::blank(setting);
                c.held_out = folds.iter().map(|(a, x)| 0.5 * (a + x)).sum::<f64>()
                    / folds.len().max(1) as f64;
                c.folds = folds;
                c.single = position(&single, name).map(|i| single_of(&single[i]));
                Some(c)
            })
            .collect())
    }
}

/// The candidates an earlier check recorded in `dir`'s models (their
/// provenance's `join_check`), for `base`'s objects in its order: those at
/// the base threshold, and those at the higher thresholds tried for the
/// setting that check chose (increasing).
pub(super) type Recorded = (Vec<Vec<Candidate>>, Vec<Vec<Candidate>>);

pub(super) fn recorded_candidates(dir: &Path, base: &[Model]) -> Result<Recorded, RouteError> {
    let models = load_model_dir(dir)?;
    let mut grid = Vec::new();
    let mut higher = Vec::new();
    for b in base {
        let name = &b.meta.name;
        let m = models
            .iter()
            .find(|m| &m.meta.name == name)
            .ok_or_else(|| {
                RouteError::input(format!("--recorded {}: no model of {name}", dir.display()))
            })?;
        let record = m.meta.provenance.get("join_check").ok_or_else(|| {
            RouteError::input(format!(
                "--recorded {}: {name} has no join_check figures (not written by join --check-folds)",
                dir.display()
            ))
        })?;
        let cs: Vec<Candidate> = serde_json::from_value(record.clone()).map_err(|e| {
            RouteError::input(format!(
                "--recorded {}: {name}'s join_check: {e}",
                dir.display()
            ))
        })?;
        let (mut at, mut base_t): (Vec<Candidate>, Vec<Candidate>) =
            cs.into_iter().partition(|c| c.setting.threshold.is_some());
        at.sort_by(|a, b| {
            a.setting
                .threshold
                .partial_cmp(&b.setting.threshold)
                .unwrap_or(std::cmp::Ordering::Equal)
        });
        base_t.iter_mut().for_each(|c| c.cost_ms = None);
        at.iter_mut().for_each(|c| c.cost_ms = None);
        grid.push(base_t);
        higher.push(at);
    }
    Ok((grid, higher))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{hand_model, HandModelParams, SynthObject};

    #[test]
    fn a_recorded_check_is_read_back_as_it_was_written() {
        let obj = SynthObject {
            cols: 12,
            rows: 10,
            seed: 11,
        };
        let mut m = hand_model(&obj, "obj", true, &HandModelParams::default()).unwrap();
        let setting = |offset, colour_weight, threshold| Setting {
            offset,
            colour_weight,
            threshold,
        };
        let mut cs = vec![
            Candidate::blank(setting(None, 0.0, None)),
            Candidate::blank(setting(Some(0.25), 0.25, None)),
            Candidate::blank(setting(Some(0.25), 0.25, Some(-0.25))),
            Candidate::blank(setting(Some(0.25), 0.25, Some(-0.5))),
        ];
        for (i, c) in cs.iter_mut().enumerate() {
            c.folds = vec![(0.9, 0.8 + i as f64 * 0.01)];
            c.held_out = 0.85;
            c.single = Some([0.97, 0.96, 0.25, 0.12]);
            c.cost_ms = Some(12.5);
        }
        let dir = std::env::temp_dir().join(format!("sdhop-recorded-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("obj.safetensors");
        // Without a record, the model is refused with its name.
        m.save(&path).unwrap();
        let err = recorded_candidates(&dir, std::slice::from_ref(&m)).unwrap_err();
        assert!(err.to_string().contains("obj has no join_check"), "{err}");
        m.meta.provenance["join_check"] = serde_json::to_value(&cs).unwrap();
        m.save(&path).unwrap();
        let (grid, higher) = recorded_candidates(&dir, std::slice::from_ref(&m)).unwrap();
        assert_eq!(grid[0].len(), 2);
        assert_eq!(grid[0][1].setting, cs[1].setting);
        assert_eq!(grid[0][1].folds, cs[1].folds);
        assert_eq!(grid[0][1].single, cs[1].single);
        // The thresholds in increasing order; the times are the new
        // pass's to measure, not the record's.
        let t: Vec<_> = higher[0].iter().map(|c| c.setting.threshold).collect();
        assert_eq!(t, vec![Some(-0.5), Some(-0.25)]);
        assert!(grid[0]
            .iter()
            .chain(&higher[0])
            .all(|c| c.cost_ms.is_none()));
        // A base model the record lacks is named.
        let mut other = m.clone();
        other.meta.name = "other".into();
        let err = recorded_candidates(&dir, &[other]).unwrap_err();
        assert!(err.to_string().contains("no model of other"), "{err}");
        std::fs::remove_dir_all(&dir).ok();
    }
}
