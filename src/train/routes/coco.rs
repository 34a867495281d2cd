//! `train --coco`: one model per category of a COCO-style file of your
//! own photographs (masks, boxes or both), trained as
//! [`super::photos::train_photographs`] trains photographs.

use super::photos::{
    train_photographs, BoxRoute, PhotoTraining, COCO_BOX_FOLDS, COCO_BOX_FOLD_ROUNDS, COCO_MIRROR,
};
use super::{image_files, record_negatives, RouteError, TrainSettings};
use crate::data::{load_coco, Sample};
use crate::model::Model;
use crate::train::ko8::Source;
use crate::train::multiview::MultiViewParams;
use crate::train::photo_augment::PhotoAugment;
use crate::train::{progress_bar, PyramidCache, TrainReport};
use crate::vision::cells::FeatureKind;
use std::path::PathBuf;

/// The cells `train --coco` uses unless the settings name others: the
/// learned ones, which win on the development photographs of that route
/// (LM-O, 50 box-only photographs: mean AUC 0.563 against HOG's 0.265).
pub const COCO_FEATURES: FeatureKind = FeatureKind::Cnn;

/// The photographs and categories of `train --coco`, and the options that
/// shape its training.
#[derive(Clone, Debug)]
pub struct CocoRoute {
    /// The COCO-style JSON file.
    pub coco: PathBuf,
    /// Folder the file names are relative to.
    pub images: PathBuf,
    /// Categories to train, one model each.
    pub categories: Vec<String>,
    /// A folder of negative scenes (images without the objects).
    pub negatives: Option<PathBuf>,
    /// `None`: `single,boxes` (masked annotations as photographs, box-only
    /// ones with latent visibility).
    pub sources: Option<Vec<Source>>,
    pub mirror_photos: bool,
    pub box_folds: usize,
    pub box_fold_rounds: usize,
}

impl Default for CocoRoute {
    fn default() -> Self {
        Self {
            coco: PathBuf::new(),
            images: PathBuf::new(),
            categories: Vec::new(),
            negatives: None,
            sources: None,
            mirror_photos: COCO_MIRROR,
            box_folds: COCO_BOX_FOLDS,
            box_fold_rounds: COCO_BOX_FOLD_ROUNDS,
        }
    }
}

/// Trains each category: the model with the last round's report.
pub fn train_coco(
    route: &CocoRoute,
    settings: &TrainSettings,
    mv: &MultiViewParams,
) -> Result<Vec<(Model, TrainReport)>, RouteError> {
    settings.no_segmenter("train --coco")?;
    let (params, neg) = settings.params(COCO_FEATURES)?;
    let cache = PyramidCache::default();
    let extra_negatives: Vec<Sample> = match &route.negatives {
        Some(d) => image_files(d)?.into_iter().map(Sample::negative).collect(),
        None => Vec::new(),
    };
    let mut out = Vec::new();
    for cat in &route.categories {
        let loaded = load_coco(&route.coco, &route.images, cat).map_err(RouteError::input)?;
        for s in &loaded.skipped {
            eprintln!("skipped: {s}");
        }
        let pb = progress_bar(0, cat);
        let box_route = BoxRoute {
            sources: route
                .sources
                .clone()
                .unwrap_or_else(|| vec![Source::Single, Source::Boxes]),
            mirror_photos: route.mirror_photos,
            box_folds: route.box_folds,
            box_fold_rounds: route.box_fold_rounds,
            box_fold_passes: None,
            renders: Default::default(),
            mining: false,
            augment: PhotoAugment::default(),
        };
        let PhotoTraining {
            mut model, report, ..
        } = train_photographs(
            cat,
            &loaded.samples,
            &extra_negatives,
            &box_route,
            settings,
            &params,
            mv,
            &cache,
            &pb,
        )?;
        pb.finish_and_clear();
        record_negatives(&mut model, &neg)?;
        out.push((model, report));
    }
    Ok(out)
}
