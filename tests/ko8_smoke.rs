//! The shipped models on a fixed small subset of the CMU_KO8 development
//! split (every tenth image of each object): catches a broken model file or
//! a regression. Needs `../shared/data/cmu_ko8`: ignored by default (the
//! summary counts it), run with `--include-ignored` where the data is (CI
//! does), and there missing data is a failure.

use std::path::{Path, PathBuf};

use sdhop::model::Model;
use sdhop::train::ko8::{detect_all, score, EvalDetect, Ko8Data};
use sdhop::train::PyramidCache;

fn data_root() -> PathBuf {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/cmu_ko8");
    assert!(
        root.join("single/test").is_dir(),
        "needs {} (the CMU_KO8 development split)",
        root.display()
    );
    root
}

#[test]
#[ignore = "needs ../shared/data/cmu_ko8"]
fn shipped_models_localize_a_fixed_ko8_subset() {
    let root = data_root();
    let data = Ko8Data::load(&root, &[]).unwrap();
    assert_eq!(data.objects.len(), 8, "CMU_KO8 should have eight objects");
    let models_dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("models");
    let models: Vec<Model> = data
        .objects
        .iter()
        .map(|o| {
            let p = models_dir.join(format!("{o}.safetensors"));
            Model::load(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
        })
        .collect();
    let refs: Vec<&Model> = models.iter().collect();
    let images: Vec<_> = data
        .images
        .iter()
        .flat_map(|imgs| imgs.iter().step_by(10))
        .collect();
    let cache = PyramidCache::default();
    let m0 = &models[0].meta;
    cache
        .fill(
            &images,
            &m0.pyramid,
            &m0.segmentation,
            &indicatif::ProgressBar::hidden(),
        )
        .unwrap();
    let responses = detect_all(
        &images,
        &refs,
        &cache,
        EvalDetect {
            max_detections: 20,
            threshold: None,
            pixel: None,
        },
    )
    .unwrap();
    let eval = score(&data, &images, &responses);
    eprintln!("{}", sdhop::eval::table(&eval.objects, true));
    assert!(eval.mean.auc >= 0.6, "mean AUC {}", eval.mean.auc);
    assert!(
        eval.mean.seg_error_refined < 0.5,
        "segmentation error {}",
        eval.mean.seg_error_refined
    );
}
