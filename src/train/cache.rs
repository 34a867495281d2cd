//! The training images' feature pyramids, computed once per image and
//! shared by every model trained in one run, and the hard locations each
//! training found in them (the seeds of the next training of the same
//! object: latent rounds, cross-validation folds).

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;

use indicatif::ProgressBar;
use rayon::prelude::*;

use super::TrainError;
use crate::data::{load_image, Sample};
use crate::vision::detect::Location;
use crate::vision::pyramid::{FeaturePyramid, PyramidParams};
use crate::vision::segment::SegmentParams;

/// Which training example hard locations belong to: an image, the
/// background region of it searched as a negative (`None`: the whole
/// image), and the object (or joined objects) trained.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub(super) struct HardKey {
    pub image: PathBuf,
    pub region: Option<usize>,
    pub label: String,
}

/// A pyramid per image path, computed once and shared by every model.
#[derive(Default)]
pub struct PyramidCache {
    map: std::sync::Mutex<HashMap<PathBuf, Arc<FeaturePyramid>>>,
    /// The locations each example's last training ended with (its most
    /// violated outputs), by example.
    hard: std::sync::Mutex<HashMap<HardKey, Vec<Location>>>,
    /// Keep [`FeaturePyramid::lean`] pyramids.
    lean: bool,
}

impl PyramidCache {
    /// A cache of pyramids without their pixels ([`FeaturePyramid::lean`]):
    /// enough for training, a quarter less memory; masks of detections in
    /// them are the raw cell masks.
    pub fn lean() -> Self {
        Self {
            lean: true,
            ..Self::default()
        }
    }

    /// Computes the missing pyramids in parallel: those of images not in
    /// the cache, and those built with other settings (several objects of
    /// one run may each have their own scales), which are replaced.
    pub fn fill(
        &self,
        samples: &[&Sample],
        pyramid: &PyramidParams,
        seg: &SegmentParams,
        progress: &ProgressBar,
    ) -> Result<(), TrainError> {
        let missing: Vec<&PathBuf> = {
            let map = self
                .map
                .lock()
                .map_err(|_| TrainError::NoData("cache poisoned".into()))?;
            let mut seen = std::collections::HashSet::new();
            samples
                .iter()
                .map(|s| &s.image)
                .filter(|p| {
                    let fits = map
                        .get(*p)
                        .is_some_and(|pyr| pyr.params == *pyramid && pyr.seg_params == *seg);
                    !fits && seen.insert(*p)
                })
                .collect()
        };
        progress.set_length(missing.len() as u64);
        let built: Vec<(PathBuf, Arc<FeaturePyramid>)> = missing
            .par_iter()
            .map(|p| {
                let img = load_image(p)?;
                let mut pyr = FeaturePyramid::build(&img, pyramid, seg)?;
                if self.lean {
                    pyr = pyr.lean()?;
                }
                progress.inc(1);
                Ok(((*p).clone(), Arc::new(pyr)))
            })
            .collect::<Result<_, TrainError>>()?;
        if let Ok(mut hard) = self.hard.lock() {
            // Locations of a rebuilt pyramid mean other windows.
            hard.retain(|k, _| !built.iter().any(|(p, _)| *p == k.image));
        }
        let mut map = self
            .map
            .lock()
            .map_err(|_| TrainError::NoData("cache poisoned".into()))?;
        map.extend(built);
        Ok(())
    }

    /// The hard locations an earlier training left for `key` (none if
    /// there was none).
    pub(super) fn hard(&self, key: &HardKey) -> Vec<Location> {
        self.hard
            .lock()
            .ok()
            .and_then(|h| h.get(key).cloned())
            .unwrap_or_default()
    }

    /// Keeps each example's hard locations for later trainings, replacing
    /// what an earlier training left for the same examples.
    pub(super) fn remember_hard(&self, found: HashMap<HardKey, Vec<Location>>) {
        if let Ok(mut hard) = self.hard.lock() {
            hard.extend(found);
        }
    }

    /// Adds a pyramid built elsewhere (e.g. of a generated image).
    pub fn insert(&self, path: PathBuf, pyr: FeaturePyramid) {
        if let Ok(mut hard) = self.hard.lock() {
            hard.retain(|k, _| k.image != path);
        }
        if let Ok(mut map) = self.map.lock() {
            map.insert(path, Arc::new(pyr));
        }
    }

    pub fn get(&self, path: &PathBuf) -> Option<Arc<FeaturePyramid>> {
        self.map.lock().ok()?.get(path).cloned()
    }
}
