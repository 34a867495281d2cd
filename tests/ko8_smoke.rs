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

/// Answers true to their threshold: on a few development photographs, for
/// every shipped model (colour-weighted and joined ones among them), the
/// default answer holds exactly the detections that an answer at a lower
/// threshold finds at or above each model's own threshold, and none below
/// it (the same non-maximum suppression; `max_detections` above what
/// either finds).
#[test]
#[ignore = "needs ../shared/data/cmu_ko8"]
fn the_default_answer_is_the_low_threshold_answer_cut_at_each_models_threshold() {
    use sdhop::pipeline::{detect_image, DetectOptions, MaskMode};
    let root = data_root();
    let models_dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("models");
    let mut paths: Vec<PathBuf> = std::fs::read_dir(&models_dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "safetensors"))
        .collect();
    paths.sort();
    let models: Vec<Model> = paths.iter().map(|p| Model::load(p).unwrap()).collect();
    assert!(
        models.iter().any(|m| m.meta.detection.colour_weight > 0.0),
        "the check needs a colour-weighted model"
    );
    let refs: Vec<&Model> = models.iter().collect();
    let lowest = models
        .iter()
        .map(|m| m.meta.detection.threshold)
        .fold(f64::INFINITY, f64::min);
    let opts = DetectOptions {
        max_detections: Some(100),
        masks: MaskMode::None,
        ..DetectOptions::default()
    };
    let photos = [
        "single/test/bakingpan/bakingpan_001.jpg",
        "single/test/thermos/thermos_088.jpg",
        "single/test/shaker/shaker_004.jpg",
    ];
    let key = |d: &sdhop::pipeline::DetectionJson| {
        let b = d.bbox;
        (
            d.model.clone(),
            (b.x * 8.0).round() as i64,
            (b.y * 8.0).round() as i64,
            (b.width * 8.0).round() as i64,
            (b.height * 8.0).round() as i64,
        )
    };
    let mut compared = 0;
    for photo in photos {
        let img = sdhop::data::load_image(&root.join(photo)).unwrap();
        let default = detect_image(&img, &refs, &opts).unwrap();
        let low = detect_image(
            &img,
            &refs,
            &DetectOptions {
                threshold: Some(lowest - 0.5),
                ..opts.clone()
            },
        )
        .unwrap();
        let threshold = |name: &str| {
            models
                .iter()
                .find(|m| m.meta.name == name)
                .unwrap()
                .meta
                .detection
                .threshold
        };
        for d in &default.detections {
            assert!(
                d.score >= threshold(&d.model),
                "{photo}: {} {} below its threshold",
                d.model,
                d.score
            );
        }
        let mut want: Vec<_> = low
            .detections
            .iter()
            .filter(|d| d.score >= threshold(&d.model))
            .map(|d| (key(d), d.score))
            .collect();
        let mut got: Vec<_> = default
            .detections
            .iter()
            .map(|d| (key(d), d.score))
            .collect();
        want.sort_by(|a, b| a.0.cmp(&b.0));
        got.sort_by(|a, b| a.0.cmp(&b.0));
        let keys = |v: &[(_, f64)]| v.iter().map(|(k, _)| k).cloned().collect::<Vec<_>>();
        assert_eq!(keys(&got), keys(&want), "{photo}");
        for ((k, a), (_, b)) in got.iter().zip(&want) {
            assert!((a - b).abs() < 1e-9, "{photo}: {k:?} scores {a} and {b}");
        }
        compared += got.len();
    }
    assert!(compared > 0, "no detection to compare");
}
