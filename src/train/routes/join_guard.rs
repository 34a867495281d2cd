//! The single-pose guard of `sdhop-train join --check-folds`: whether
//! joining view components costs single-pose accuracy, judged on
//! single-pose photographs that trained neither side. The shipped
//! single-pose models trained on every development single-pose
//! photograph, so the guard scores each cross-validation fold's held-out
//! photographs with that fold's single-pose models (`sdhop-train cv
//! --save-models DIR`), joined as the setting says, and pools the
//! responses of the folds before scoring them, as `cv` does.

use super::join::{applied_each, Setting, CHECK_DETECT};
use super::join_check::filled_cache;
use super::{load_model_dir, RouteError};
use crate::data::Sample;
use crate::eval::detection::ObjectScore;
use crate::model::Model;
use crate::train::ko8::{detect_all, fold_dir, score, FoldOf, Ko8Data, FOLD_FILE};
use crate::train::PyramidCache;
use std::path::Path;

/// The photographs the guard scores for `fold`: the held-out single-pose
/// photographs of that fold (every object's), none of which trained the
/// fold's models, as positives or as another object's negatives.
pub fn guard_photographs(data: &Ko8Data, fold: FoldOf) -> Vec<&Sample> {
    data.fold_images(Some((fold.fold, fold.folds)))
}

/// One fold of the guard: its single-pose models in the base models'
/// order, its held-out photographs and their pyramids.
struct GuardFold<'a> {
    base: Vec<Model>,
    images: Vec<&'a Sample>,
    cache: PyramidCache,
}

/// The single-pose guard over the folds of a `cv --save-models` folder.
pub struct SinglePoseGuard<'a> {
    folds: Vec<GuardFold<'a>>,
}

impl<'a> SinglePoseGuard<'a> {
    /// The folds saved in `dir` (`fold-F/` with [`FOLD_FILE`] and a model
    /// of every object of `base`), their photographs' pyramids built.
    pub fn load(dir: &Path, data: &'a Ko8Data, base: &[Model]) -> Result<Self, RouteError> {
        let m0 = base
            .first()
            .ok_or_else(|| RouteError::input("no base model"))?;
        let mut folds = Vec::new();
        let mut count = None;
        for f in 0.. {
            let d = fold_dir(dir, f);
            if !d.is_dir() {
                if count.is_some_and(|k| f < k) {
                    continue;
                }
                break;
            }
            let fold = read_fold_file(&d)?;
            if fold.fold != f || count.is_some_and(|k| k != fold.folds) {
                return Err(RouteError::input(format!(
                    "{}: fold {} of {} does not belong with the other folds of {}",
                    d.display(),
                    fold.fold,
                    fold.folds,
                    dir.display()
                )));
            }
            count = Some(fold.folds);
            let models = load_model_dir(&d)?;
            let ordered = in_base_order(base, models, &d)?;
            let images = guard_photographs(data, fold);
            let cache = filled_cache(&images, m0, None)?;
            folds.push(GuardFold {
                base: ordered,
                images,
                cache,
            });
        }
        if folds.is_empty() {
            return Err(RouteError::input(format!(
                "{}: no fold-F/ folder of single-pose models (make them with `sdhop-train cv --ko8 DATA --folds K --save-models {}`)",
                dir.display(),
                dir.display()
            )));
        }
        Ok(Self { folds })
    }

    /// Photographs scored, over all folds.
    pub fn photographs(&self) -> usize {
        self.folds.iter().map(|f| f.images.len()).sum()
    }

    /// Folds loaded.
    pub fn folds(&self) -> usize {
        self.folds.len()
    }

    /// Each fold's single-pose models in `settings` (one per base model,
    /// `None`: unchanged), joined with `add`'s model of their object, on
    /// the fold's photographs; the folds' responses scored together.
    pub fn score(
        &self,
        data: &Ko8Data,
        add: &[Model],
        settings: &[Option<Setting>],
    ) -> Result<Vec<ObjectScore>, RouteError> {
        let mut images = Vec::new();
        let mut responses = Vec::new();
        for f in &self.folds {
            let models = applied_each(&f.base, add, settings)?;
            let refs: Vec<&Model> = models.iter().collect();
            responses.extend(
                detect_all(&f.images, &refs, &f.cache, CHECK_DETECT).map_err(RouteError::input)?,
            );
            images.extend(f.images.iter().copied());
        }
        Ok(score(data, &images, &responses).objects)
    }
}

fn read_fold_file(dir: &Path) -> Result<FoldOf, RouteError> {
    let p = dir.join(FOLD_FILE);
    let text = std::fs::read_to_string(&p).map_err(|e| {
        RouteError::input(format!(
            "{}: {e} (fold folders need the {FOLD_FILE} that `sdhop-train cv --save-models` writes)",
            p.display()
        ))
    })?;
    let fold: FoldOf = serde_json::from_str(&text)
        .map_err(|e| RouteError::input(format!("{}: {e}", p.display())))?;
    if fold.folds < 2 || fold.fold >= fold.folds {
        return Err(RouteError::input(format!(
            "{}: fold {} of {} is not a fold of a cross-validation",
            p.display(),
            fold.fold,
            fold.folds
        )));
    }
    Ok(fold)
}

/// `models` (a fold's) in the order of `base`, each found by name.
fn in_base_order(base: &[Model], models: Vec<Model>, dir: &Path) -> Result<Vec<Model>, RouteError> {
    base.iter()
        .map(|b| {
            models
                .iter()
                .find(|m| m.meta.name == b.meta.name)
                .cloned()
                .ok_or_else(|| {
                    RouteError::input(format!(
                        "{}: no single-pose model of {}",
                        dir.display(),
                        b.meta.name
                    ))
                })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::train::ko8::NegativeSet;
    use std::path::PathBuf;

    fn data() -> Ko8Data {
        let objects = ["cup", "pitcher", "shaker"];
        let images = objects
            .iter()
            .map(|o| {
                (0..23)
                    .map(|i| Sample::negative(PathBuf::from(format!("{o}/{o}_{i:03}.jpg"))))
                    .collect()
            })
            .collect();
        Ko8Data {
            objects: objects.iter().map(|o| o.to_string()).collect(),
            images,
            negatives: (0..5)
                .map(|i| Sample::negative(PathBuf::from(format!("negative/n{i}.jpg"))))
                .collect(),
            views: Vec::new(),
            photos: Vec::new(),
            skipped: Vec::new(),
        }
    }

    #[test]
    fn the_guard_never_scores_a_photograph_that_trained_its_folds_models() {
        let data = data();
        let neg = NegativeSet {
            scenes: 5,
            per_other_object: 30,
        };
        for folds in [2, 3, 5] {
            let mut scored = 0;
            for fold in 0..folds {
                let guard = guard_photographs(&data, FoldOf { fold, folds });
                assert!(!guard.is_empty());
                for oi in 0..data.objects.len() {
                    let trained = data.training_set(oi, Some((fold, folds)), &neg);
                    for g in &guard {
                        assert!(
                            !trained.iter().any(|t| t.id == g.id),
                            "{} trained {}'s model of fold {fold}/{folds} and is scored",
                            g.id,
                            data.objects[oi]
                        );
                    }
                }
                scored += guard.len();
            }
            // Over the folds, every single-pose photograph once.
            assert_eq!(scored, 3 * 23);
        }
    }

    #[test]
    fn fold_files_round_trip_and_bad_ones_are_refused() {
        let dir = std::env::temp_dir().join(format!("sdhop-fold-file-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = FoldOf { fold: 1, folds: 3 };
        crate::train::ko8::write_fold_file(&dir, f).unwrap();
        assert_eq!(read_fold_file(&dir).unwrap(), f);
        std::fs::write(dir.join(FOLD_FILE), r#"{"fold": 3, "folds": 3}"#).unwrap();
        assert!(read_fold_file(&dir).is_err());
        std::fs::remove_file(dir.join(FOLD_FILE)).unwrap();
        let e = read_fold_file(&dir).unwrap_err().to_string();
        assert!(e.contains("cv --save-models"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }
}
