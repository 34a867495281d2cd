//! The views route on CMU_KO8's development data: the saucepan's model
//! from its 25 views alone (`train --ko8 DATA --objects saucepan --sources
//! views`, the route's defaults), scored on its 30 development multi-view
//! photographs. The check that would have caught the regression of
//! 48196c9 (0.663 -> 0.201: a training stopped by its caps, far from
//! convergence, whose result a change of seed order moved). Needs
//! `../shared/data/cmu_ko8`: ignored by default, run with
//! `--include-ignored` where the data is (CI does).

use std::path::{Path, PathBuf};

use sdhop::data::Sample;
use sdhop::model::Model;
use sdhop::train::ko8::{detect_all, score, EvalDetect, Ko8Data, Source};
use sdhop::train::multiview::MultiViewParams;
use sdhop::train::routes::ko8::{train_ko8, Ko8Route};
use sdhop::train::routes::TrainSettings;
use sdhop::train::PyramidCache;

fn data_root() -> PathBuf {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/cmu_ko8");
    assert!(
        root.join("multiple/train").is_dir(),
        "needs {} (the CMU_KO8 development split, with its multi-view part)",
        root.display()
    );
    root
}

#[test]
#[ignore = "needs ../shared/data/cmu_ko8"]
fn the_views_route_converges_and_finds_the_saucepan_from_any_side() {
    let root = data_root();
    let route = Ko8Route {
        root: root.clone(),
        objects: vec!["saucepan".into()],
        sources: Some(vec![Source::Views]),
        ..Ko8Route::default()
    };
    let trained = train_ko8(
        &route,
        &TrainSettings::default(),
        &MultiViewParams::default(),
    )
    .unwrap();
    let (model, report) = &trained[0];
    assert!(report.converged, "{report:?}");
    let data = Ko8Data::load(&root, &["saucepan".to_string()])
        .unwrap()
        .with_multiview(&root)
        .unwrap();
    let images: Vec<&Sample> = data.photos.iter().flatten().collect();
    assert_eq!(images.len(), 30);
    let cache = PyramidCache::default();
    cache
        .fill(
            &images,
            &model.meta.pyramid,
            &model.meta.segmentation,
            &indicatif::ProgressBar::hidden(),
        )
        .unwrap();
    let refs: Vec<&Model> = vec![model];
    let how = EvalDetect {
        max_detections: 20,
        threshold: None,
        pixel: None,
    };
    let responses = detect_all(&images, &refs, &cache, how).unwrap();
    let eval = score(&data, &images, &responses);
    eprintln!("{}", sdhop::eval::table(&eval.objects, false));
    // 0.663 before the regression, 0.201 after, 0.651 trained to
    // convergence.
    assert!(eval.mean.auc >= 0.6, "saucepan AUC {}", eval.mean.auc);
}
