//! Structured SVM training on synthetic occluded scenes the project
//! generates itself: the learned model detects and segments held-out scenes,
//! the cutting-plane objective grows while the violation found by the
//! searches shrinks, and the saved weights satisfy the curvature constraint
//! exactly.

use std::path::PathBuf;

use sdhop::data::{Annotation, Sample};
use sdhop::model::Model;
use sdhop::pipeline::{detect_image, DetectOptions, MaskMode};
use sdhop::synth::{hand_model, scene, HandModelParams, Scene, SceneParams, SynthObject};
use sdhop::train::{train_model, ExampleParams, PyramidCache, SolverParams, TrainParams};
use sdhop::vision::cells::FeatureKind;
use sdhop::vision::detect::{box_iou, LossAugment};
use sdhop::vision::energy::hop_curvature;
use sdhop::vision::mask::Mask;
use sdhop::vision::pyramid::FeaturePyramid;

/// Training settings for the synthetic scenes: templates at the median
/// box, at most `passes` full searches of which the first `mining` mine,
/// `seeds` random locations per image.
fn short_params(passes: usize, mining: usize, seeds: usize) -> TrainParams {
    TrainParams {
        template_scale: 1.0,
        solver: SolverParams {
            max_passes: passes,
            mining_passes: mining,
            ..Default::default()
        },
        examples: ExampleParams {
            init_locations: seeds,
            ..Default::default()
        },
        ..TrainParams::default()
    }
}

const OBJECT: SynthObject = SynthObject {
    cols: 9,
    rows: 8,
    seed: 3,
};

fn scene_params(seed: u64) -> SceneParams {
    SceneParams {
        width: 200,
        height: 160,
        scale: (1.0, 1.3),
        occlusion: (0.15, 0.4),
        seed,
    }
}

fn make_sample(
    cache: &PyramidCache,
    params: &TrainParams,
    obj: &SynthObject,
    seed: u64,
    label: Option<&str>,
) -> (Sample, Scene) {
    let sc = scene(obj, &scene_params(seed)).unwrap();
    let path = PathBuf::from(format!("synthetic/{}-{seed}", obj.seed));
    let pyr = FeaturePyramid::build(&sc.image, &params.pyramid, &params.segmentation).unwrap();
    cache.insert(path.clone(), pyr);
    let sample = Sample {
        image: path,
        id: format!("{}-{seed}", obj.seed),
        annotation: label.map(|l| Annotation {
            label: l.to_string(),
            bbox: sc.truth_box,
            visible: sc.visible.clone(),
            viewpoint: 0,
            mask_known: true,
        }),
    };
    (sample, sc)
}

/// Of `n` held-out scenes, those whose top detection by `model` (whatever
/// its score) finds the object's box (IoU at least 0.5).
fn held_out_hits(model: &Model, n: u64) -> u64 {
    let opts = DetectOptions {
        threshold: Some(-1e9),
        max_detections: Some(1),
        ..DetectOptions::default()
    };
    (0..n)
        .filter(|seed| {
            let sc = scene(&OBJECT, &scene_params(900 + seed)).unwrap();
            let resp = detect_image(&sc.image, &[model], &opts).unwrap();
            resp.detections.first().is_some_and(|d| {
                box_iou(
                    (d.bbox.x, d.bbox.y, d.bbox.width, d.bbox.height),
                    sc.truth_box,
                ) >= 0.5
            })
        })
        .count() as u64
}

#[test]
fn training_learns_to_detect_and_segment_held_out_scenes() {
    let params = short_params(6, 3, 20);
    let cache = PyramidCache::default();
    let mut samples = Vec::new();
    for seed in 0..14 {
        samples.push(make_sample(&cache, &params, &OBJECT, 100 + seed, Some("thing")).0);
    }
    // Negatives: scenes of two other objects.
    for (k, other) in [11u64, 23].iter().enumerate() {
        let obj = SynthObject {
            seed: *other,
            ..OBJECT
        };
        for seed in 0..5 {
            samples.push(make_sample(&cache, &params, &obj, 200 + 10 * k as u64 + seed, None).0);
        }
    }
    let refs: Vec<&Sample> = samples.iter().collect();
    let pb = indicatif::ProgressBar::hidden();
    let (model, report) = train_model("thing", &refs, &cache, &params, &pb).unwrap();

    // The working-set objective never decreases by more than round-off as
    // planes are added, and the searches find smaller violations at the end.
    for w in report.objective.windows(2) {
        assert!(
            w[1] >= w[0] - 1e-6 * (1.0 + w[0].abs()),
            "objective fell: {:?}",
            report.objective
        );
    }
    let first = report.full_violation[0];
    let last = *report.full_violation.last().unwrap();
    assert!(last < first, "violation {first} -> {last}");
    assert!(report.exact_passes >= 1);

    // The saved weights satisfy W >= 0 and D^2 w_HOP >= 0 exactly, and
    // survive a save/load round trip.
    let bytes = model.to_bytes().unwrap();
    let loaded = Model::from_bytes(&bytes).unwrap();
    assert_eq!(loaded, model);
    // Training learned each viewpoint's pixel shape model and colours.
    for (a, shape) in loaded.shapes.iter().enumerate() {
        let shape = shape.as_ref().expect("a shape model per viewpoint");
        assert_eq!((shape.width, shape.height), loaded.shape_size(a));
        assert!(shape.colours.is_some());
    }
    for v in &loaded.views {
        assert!(v.w_pair >= 0.0);
        let hop: Vec<f64> = v.w_hop.iter().map(|&x| f64::from(x)).collect();
        assert!(
            hop_curvature(&hop).iter().all(|&c| c >= 0.0),
            "{:?}",
            v.w_hop
        );
    }

    // Held-out scenes: the top detection (whatever its score) finds the
    // full box and the visible pixels.
    let opts = DetectOptions {
        threshold: Some(-1e9),
        max_detections: Some(1),
        masks: MaskMode::Both,
        ..DetectOptions::default()
    };
    let mut box_hits = 0;
    let mut mask_iou = 0.0;
    let n = 8;
    for seed in 0..n {
        let sc = scene(&OBJECT, &scene_params(900 + seed)).unwrap();
        let resp = detect_image(&sc.image, &[&model], &opts).unwrap();
        if let Some(d) = resp.detections.first() {
            let b = (d.bbox.x, d.bbox.y, d.bbox.width, d.bbox.height);
            if box_iou(b, sc.truth_box) >= 0.5 {
                box_hits += 1;
            }
            let m = d.mask.as_ref().and_then(Mask::from_rle).unwrap();
            mask_iou += m.iou(&sc.visible);
        }
    }
    let mask_iou = mask_iou / n as f64;
    eprintln!(
        "held-out: {box_hits}/{n} boxes, mean visible-mask IoU {mask_iou:.3}; report {report:?}"
    );
    assert!(box_hits >= n - 1, "{box_hits}/{n} boxes found");
    assert!(mask_iou >= 0.6, "mask IoU {mask_iou}");
}

/// The same training on learned cells (`--features cnn`): the model
/// records its feature kind and the projection it was trained on, round
/// trips, and finds held-out scenes' objects.
#[test]
fn training_on_learned_cells_detects_held_out_scenes() {
    let mut params = short_params(4, 2, 20);
    params.pyramid.features = FeatureKind::Cnn;
    let cache = PyramidCache::default();
    let mut samples = Vec::new();
    for seed in 0..10 {
        samples.push(make_sample(&cache, &params, &OBJECT, 100 + seed, Some("thing")).0);
    }
    for (k, other) in [11u64, 23].iter().enumerate() {
        let obj = SynthObject {
            seed: *other,
            ..OBJECT
        };
        for seed in 0..4 {
            samples.push(make_sample(&cache, &params, &obj, 200 + 10 * k as u64 + seed, None).0);
        }
    }
    let refs: Vec<&Sample> = samples.iter().collect();
    let pb = indicatif::ProgressBar::hidden();
    let (model, _) = train_model("thing", &refs, &cache, &params, &pb).unwrap();
    assert_eq!(model.meta.pyramid.features, FeatureKind::Cnn);
    assert_eq!(model.meta.cells, FeatureKind::Cnn.fingerprint().unwrap());
    let loaded = Model::from_bytes(&model.to_bytes().unwrap()).unwrap();
    assert_eq!(loaded, model);
    let n = 8u64;
    let hits = held_out_hits(&loaded, n);
    eprintln!("learned cells, held-out: {hits}/{n} boxes");
    assert!(hits >= n - 2, "{hits}/{n} boxes found");
}

/// Bad training input ends with exit status 2 and a message naming it.
#[test]
fn training_cli_refuses_bad_input_with_status_2() {
    let bin = env!("CARGO_BIN_EXE_sdhop-train");
    let dir = std::env::temp_dir().join(format!("sdhop-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let run = |args: &[&str]| {
        let out = std::process::Command::new(bin).args(args).output().unwrap();
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let missing = dir.join("nowhere");
    let (code, err) = run(&[
        "train",
        "--ko8",
        missing.to_str().unwrap(),
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("not a CMU_KO8 root"), "{err}");
    let (code, err) = run(&["train", "--ko8", missing.to_str().unwrap(), "--c", "0"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("C must be > 0"), "{err}");
    let config = dir.join("bad.json");
    std::fs::write(&config, "{\"c\": \"ten\"}").unwrap();
    let (code, err) = run(&[
        "train",
        "--ko8",
        missing.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
    ]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("bad.json"), "{err}");
    let (code, _) = run(&["cv", "--ko8", missing.to_str().unwrap(), "--folds", "1"]);
    assert_eq!(code, Some(2));
    // A segmenter on the models' own cells, or on a route that trains
    // none.
    let ko8 = missing.to_str().unwrap();
    for args in [
        &["train", "--ko8", ko8, "--segmenter", "hog"][..],
        &[
            "cv",
            "--ko8",
            ko8,
            "--features",
            "cnn",
            "--segmenter",
            "cnn",
        ],
    ] {
        let (code, err) = run(args);
        assert_eq!(code, Some(2), "{err}");
        assert!(err.contains("a segmenter uses the other kind"), "{err}");
    }
    let coco = dir.join("labels.json");
    std::fs::write(&coco, "{}").unwrap();
    let (code, err) = run(&[
        "train",
        "--coco",
        coco.to_str().unwrap(),
        "--images",
        dir.to_str().unwrap(),
        "--category",
        "cup",
        "--segmenter",
        "hog",
    ]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("does not train segmenters"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

/// Pyramids without their pixels (`PyramidCache::lean`, what `sdhop-train
/// mesh` keeps to save memory) train exactly the same weights: training
/// never reads the image or the per-pixel segments.
#[test]
fn lean_pyramids_train_the_same_weights() {
    let params = short_params(2, 1, 10);
    let full = PyramidCache::default();
    let lean = PyramidCache::lean();
    let mut samples = Vec::new();
    for (seed, label) in [
        (300, Some("thing")),
        (301, Some("thing")),
        (302, Some("thing")),
        (303, None),
        (304, None),
    ] {
        let (s, sc) = make_sample(&full, &params, &OBJECT, seed, label);
        let pyr = FeaturePyramid::build(&sc.image, &params.pyramid, &params.segmentation)
            .unwrap()
            .lean()
            .unwrap();
        assert!(!pyr.has_pixels());
        assert!(full.get(&s.image).unwrap().has_pixels());
        lean.insert(s.image.clone(), pyr);
        samples.push(s);
    }
    let refs: Vec<&Sample> = samples.iter().collect();
    let pb = indicatif::ProgressBar::hidden();
    let (a, _) = train_model("thing", &refs, &full, &params, &pb).unwrap();
    let (b, _) = train_model("thing", &refs, &lean, &params, &pb).unwrap();
    assert_eq!(a.views, b.views);
}

/// The box correction (`train --coco --box-folds`): fitted by 2-fold
/// cross-validation over the training scenes (a model per fold, scored on
/// the other fold's scenes), it leaves boxes that already fit about as they
/// are, and the service reports every box corrected from its window.
#[test]
fn box_correction_is_fitted_on_held_out_scenes_and_applied_to_every_box() {
    use sdhop::train::box_correction;
    let params = short_params(4, 2, 20);
    let cache = PyramidCache::default();
    let mut samples = Vec::new();
    for seed in 0..20 {
        samples.push(make_sample(&cache, &params, &OBJECT, 300 + seed, Some("thing")).0);
    }
    let other = SynthObject { seed: 11, ..OBJECT };
    for seed in 0..4 {
        samples.push(make_sample(&cache, &params, &other, 400 + seed, None).0);
    }
    let pb = indicatif::ProgressBar::hidden();
    let mut trained = 0;
    // The first four scenes stand for renders: in every fold's training,
    // never held out.
    let always: std::collections::HashSet<std::path::PathBuf> =
        samples[..4].iter().map(|s| s.image.clone()).collect();
    let (fitted, found) = box_correction::fit(&samples, 2, &always, &cache, |subset| {
        trained += 1;
        // Each fold trains on the other fold's positives, the four kept
        // ones and every negative.
        assert_eq!(subset.iter().filter(|s| s.annotation.is_none()).count(), 4);
        assert_eq!(subset.iter().filter(|s| s.annotation.is_some()).count(), 12);
        assert!(always.iter().all(|p| subset.iter().any(|s| &s.image == p)));
        let refs: Vec<&Sample> = subset.iter().collect();
        Ok(train_model("thing", &refs, &cache, &params, &pb)?.0)
    })
    .unwrap();
    assert_eq!(trained, 2);
    assert_eq!((found.photos(), found.objects()), (16, 16));
    let auc = found.auc().expect("held-out objects");
    eprintln!("held-out AUC {auc:.3}");
    assert!(auc > 0.8, "held-out AUC {auc:.3}");
    let c = fitted.expect("a correction from the held-out scenes");
    eprintln!("box correction {c:?} from {} offsets", found.offsets.len());
    assert!(c.samples >= box_correction::MIN_SAMPLES && c.samples <= 16);
    assert!(c.is_valid());
    // Synthetic windows fit their boxes: the correction stays small.
    assert!(
        (c.sw.ln().abs() < 0.25) && (c.sh.ln().abs() < 0.25),
        "{c:?}"
    );
    assert!(c.dx.abs() < 0.15 && c.dy.abs() < 0.15, "{c:?}");

    // Applied to every reported box: the same detections as without it,
    // each box the corrected window.
    let refs: Vec<&Sample> = samples.iter().collect();
    let (plain, _) = train_model("thing", &refs, &cache, &params, &pb).unwrap();
    let mut corrected = plain.clone();
    let strong = sdhop::model::BoxCorrection {
        dx: 0.1,
        sw: 1.3,
        ..c
    };
    corrected.meta.box_correction = Some(strong);
    let corrected = Model::from_bytes(&corrected.to_bytes().unwrap()).unwrap();
    let sc = scene(&OBJECT, &scene_params(999)).unwrap();
    let opts = DetectOptions {
        masks: MaskMode::None,
        threshold: Some(-1.0),
        ..DetectOptions::default()
    };
    let a = detect_image(&sc.image, &[&plain], &opts).unwrap();
    let b = detect_image(&sc.image, &[&corrected], &opts).unwrap();
    assert!(!a.detections.is_empty());
    assert_eq!(a.detections.len(), b.detections.len());
    for (p, q) in a.detections.iter().zip(&b.detections) {
        assert_eq!(p.score, q.score);
        let (x, y, w, h) = strong.apply((p.bbox.x, p.bbox.y, p.bbox.width, p.bbox.height));
        for (u, v) in [
            (x, q.bbox.x),
            (y, q.bbox.y),
            (w, q.bbox.width),
            (h, q.bbox.height),
        ] {
            assert!((u - v).abs() < 1e-9, "{p:?} -> {q:?}");
        }
    }
}

/// Background examples (`--background-regions`): with no negative image at
/// all, each positive scene's own clutter, searched region by region away
/// from the object, is what teaches the model to score background low.
/// The searches of those examples never return a window overlapping the
/// object or centred outside their region; the model finds held-out
/// objects and scores the training scenes' clutter below their objects.
/// A loss augmentation without its scan rectangle: the search scans every
/// position and only then drops the excluded ones.
struct Unrestricted<'a>(&'a dyn LossAugment);

impl LossAugment for Unrestricted<'_> {
    fn max_loss(&self) -> f64 {
        self.0.max_loss()
    }
    fn augment(
        &self,
        view: usize,
        grid: &sdhop::vision::mask::CellGrid,
        problem: &mut sdhop::vision::energy::BoxProblem,
    ) {
        self.0.augment(view, grid, problem)
    }
    fn excludes(&self, view: usize, grid: &sdhop::vision::mask::CellGrid) -> bool {
        self.0.excludes(view, grid)
    }
}

#[test]
fn background_regions_train_from_positive_scenes_alone() {
    use sdhop::train::loss::{Background, BackgroundLoss};
    use sdhop::vision::detect::{DetectParams, Detector};
    let params = background_params();
    let cache = PyramidCache::default();
    let made: Vec<(Sample, Scene)> = (0..10)
        .map(|seed| make_sample(&cache, &params, &OBJECT, 300 + seed, Some("thing")))
        .collect();
    let samples: Vec<Sample> = made.iter().map(|(s, _)| s.clone()).collect();
    let refs: Vec<&Sample> = samples.iter().collect();
    let pb = indicatif::ProgressBar::hidden();
    let (model, report) = train_model("thing", &refs, &cache, &params, &pb).unwrap();
    assert_eq!(report.background_negatives, 10 * 4);
    assert_eq!(report.negatives, 10 * 4);

    // The loss-augmented search of a background example stays in its part
    // of the photograph, though the object outscores everything there.
    let det = Detector::new(&model.views).unwrap();
    let mut below = 0;
    for (s, sc) in &made {
        let pyr = cache.get(&s.image).unwrap();
        let (w, h) = (pyr.image_width as f64, pyr.image_height as f64);
        let mut best_background = f64::NEG_INFINITY;
        for bg in Background::regions(4, w, h, &[sc.truth_box]) {
            let aug = BackgroundLoss { background: &bg };
            let (found, _, _) = det
                .most_violated(&pyr, &aug, f64::NEG_INFINITY, 0.5, None, None)
                .unwrap();
            // Scanning only the positions near the region (`centres`)
            // finds exactly what the whole scan, filtered, finds; so do
            // both with the photograph's bounds computed beforehand (as
            // training shares them between a photograph's examples).
            let key = |f: &Option<sdhop::vision::detect::Augmented>| {
                f.as_ref().map(|f| (f.location, f.value.to_bits()))
            };
            let pre = det.dense_bounds(&pyr, 0.5);
            let unrestricted = Unrestricted(&aug);
            for (a, p) in [
                (&unrestricted as &dyn LossAugment, None),
                (&aug, Some(&pre)),
                (&unrestricted, Some(&pre)),
            ] {
                let (other, _, _) = det
                    .most_violated(&pyr, a, f64::NEG_INFINITY, 0.5, None, p)
                    .unwrap();
                assert_eq!(key(&found), key(&other));
            }
            if let Some(f) = found {
                let b = det.grid(&pyr, &f.location).pixel_box();
                assert!(bg.contains(b), "{b:?} outside {:?}", bg.region);
                assert!(box_iou(b, sc.truth_box) < 0.3);
                // Value = loss 1 + score.
                best_background = best_background.max(f.value - 1.0);
            }
        }
        let dp = DetectParams {
            threshold: f64::NEG_INFINITY,
            max_detections: 1,
            ..model.meta.detection
        };
        let (top, _) = det.detect(&pyr, &dp).unwrap();
        let object = top
            .first()
            .filter(|d| box_iou(d.bbox, sc.truth_box) >= 0.5)
            .map_or(f64::NEG_INFINITY, |d| d.score);
        if best_background < object {
            below += 1;
        }
    }
    assert!(
        below >= 9,
        "clutter below the object in {below} of 10 scenes"
    );

    let n = 8u64;
    let hits = held_out_hits(&model, n);
    assert!(hits >= n - 1, "{hits}/{n} held-out objects found");
}

/// Six passes over small scenes, each positive photograph also four
/// background examples.
fn background_params() -> TrainParams {
    TrainParams {
        template_scale: 1.0,
        solver: SolverParams {
            max_passes: 6,
            ..Default::default()
        },
        examples: ExampleParams {
            init_locations: 20,
            background_regions: 4,
            ..Default::default()
        },
        ..TrainParams::default()
    }
}

/// A training on a cache an earlier training of the same object used
/// starts from that training's hard locations in each example (latent
/// rounds and cross-validation folds train again on the same images): it
/// runs far fewer min-cuts, a fresh cache trains exactly as the first
/// time, and the warm-started model finds held-out objects as well.
#[test]
fn a_second_training_starts_from_the_hard_locations_of_the_first() {
    let params = background_params();
    let pb = indicatif::ProgressBar::hidden();
    // The scenes' pyramids into `cache` (a pyramid put in anew forgets
    // its hard locations).
    let scenes = |cache: &PyramidCache| -> Vec<Sample> {
        (0..8)
            .map(|seed| make_sample(cache, &params, &OBJECT, 700 + seed, Some("thing")).0)
            .chain((0..4).map(|seed| make_sample(cache, &params, &OBJECT, 800 + seed, None).0))
            .collect()
    };
    let train = |cache: &PyramidCache, samples: &[Sample]| {
        let refs: Vec<&Sample> = samples.iter().collect();
        train_model("thing", &refs, cache, &params, &pb).unwrap()
    };
    let cache = PyramidCache::default();
    let samples = scenes(&cache);
    let (_, cold) = train(&cache, &samples);
    let (warm_model, warm) = train(&cache, &samples);
    let fresh_cache = PyramidCache::default();
    let (_, fresh) = train(&fresh_cache, &scenes(&fresh_cache));
    let cuts = |r: &sdhop::train::TrainReport| r.full_min_cuts.iter().sum::<usize>();
    assert_eq!(cuts(&fresh), cuts(&cold));
    assert_eq!(fresh.objective, cold.objective);
    assert!(
        2 * cuts(&warm) < cuts(&cold),
        "warm start ran {} min-cuts, cold {}",
        cuts(&warm),
        cuts(&cold)
    );
    assert!(warm.converged);
    let n = 8u64;
    let hits = held_out_hits(&warm_model, n);
    assert!(hits >= n - 1, "{hits}/{n} held-out objects found");
}

/// The mesh route's training: full searches that mine with a budget of
/// locations until one finds nothing, without an exact check. It ends
/// without an exact search and finds held-out objects as an exact
/// training does; with the check, a converged training ran one.
#[test]
fn mining_searches_alone_train_a_detector() {
    let base = background_params();
    let pb = indicatif::ProgressBar::hidden();
    let cache = PyramidCache::default();
    let samples: Vec<Sample> = (0..10)
        .map(|seed| make_sample(&cache, &base, &OBJECT, 1700 + seed, Some("thing")).0)
        .chain((0..4).map(|seed| make_sample(&cache, &base, &OBJECT, 1800 + seed, None).0))
        .collect();
    let refs: Vec<&Sample> = samples.iter().collect();
    let mut mined = base.clone();
    mined.solver.mining_passes = base.solver.max_passes;
    mined.solver.mining_budget = 64;
    mined.solver.exact_check = false;
    let (model, report) = train_model("thing", &refs, &cache, &mined, &pb).unwrap();
    assert_eq!(report.exact_passes, 0, "{report:?}");
    assert!(report.passes >= 2, "{report:?}");
    assert_eq!(report.background_negatives, 40);
    let n = 8u64;
    let hits = held_out_hits(&model, n);
    assert!(hits >= n - 1, "mining: {hits}/{n} held-out objects found");

    // With the exact check, a mining search that finds nothing is checked.
    let mut checked = mined.clone();
    checked.solver.exact_check = true;
    let (_, report) = train_model("thing", &refs, &cache, &checked, &pb).unwrap();
    if report.converged {
        assert!(report.exact_passes >= 1, "{report:?}");
    }
}

/// `train --coco` from box-only photographs, end to end through the
/// binary: by default each photograph also trains as four background
/// examples, unmirrored; `--mirror-photos true` adds mirrored photographs,
/// `--background-regions 0` turns the background examples off (both
/// recorded in the model's provenance). Every model finds held-out
/// objects.
#[test]
fn coco_box_only_training_with_background_regions_and_mirrored_photographs() {
    let bin = env!("CARGO_BIN_EXE_sdhop-train");
    let dir = std::env::temp_dir().join(format!("sdhop-coco-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let mut images = Vec::new();
    let mut annotations = Vec::new();
    for seed in 0..8u64 {
        let sc = scene(&OBJECT, &scene_params(500 + seed)).unwrap();
        let name = format!("{seed}.png");
        sc.image.to_rgb8().save(dir.join(&name)).unwrap();
        images.push(serde_json::json!({"id": seed, "file_name": name,
            "width": sc.image.width(), "height": sc.image.height()}));
        let (x, y, w, h) = sc.truth_box;
        annotations.push(
            serde_json::json!({"id": seed, "image_id": seed, "category_id": 1,
            "bbox": [x, y, w, h], "area": w * h, "iscrowd": 0}),
        );
    }
    let coco = serde_json::json!({"images": images, "annotations": annotations,
        "categories": [{"id": 1, "name": "thing"}]});
    let json = dir.join("boxes.json");
    std::fs::write(&json, coco.to_string()).unwrap();
    let train = |out: &str, extra: &[&str]| -> Model {
        let out = dir.join(out);
        let mut args = vec![
            "train",
            "--coco",
            json.to_str().unwrap(),
            "--images",
            dir.to_str().unwrap(),
            "--category",
            "thing",
            "--features",
            "hog",
            "--max-passes",
            "3",
            "--box-folds",
            "0",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let run = std::process::Command::new(bin)
            .args(&args)
            .output()
            .unwrap();
        assert!(
            run.status.success(),
            "{}",
            String::from_utf8_lossy(&run.stderr)
        );
        Model::from_bytes(&std::fs::read(out.join("thing.safetensors")).unwrap()).unwrap()
    };
    let found = |model: &Model| held_out_hits(model, 8);
    let default = train("default", &[]);
    let p = &default.meta.provenance;
    assert_eq!(p["mirror_photos"], serde_json::json!(false), "{p}");
    assert_eq!(
        p["params"]["background_regions"],
        serde_json::json!(4),
        "{p}"
    );
    let mirrored = train("mirrored", &["--mirror-photos", "true"]);
    let p = &mirrored.meta.provenance;
    assert_eq!(p["mirror_photos"], serde_json::json!(true), "{p}");
    // Twice the box photographs: each and its mirror image.
    let boxes = |p: &serde_json::Value| p["multiview"]["box_photographs"].as_u64();
    assert_eq!(boxes(&default.meta.provenance), Some(8));
    assert_eq!(boxes(p), Some(16));
    let plain = train("plain", &["--background-regions", "0"]);
    let p = &plain.meta.provenance;
    assert_eq!(
        p["params"]["background_regions"],
        serde_json::json!(0),
        "{p}"
    );
    let (a, m, b) = (found(&default), found(&mirrored), found(&plain));
    assert!(
        a >= 6 && m >= 6 && b >= 5,
        "held-out objects found: default {a}/8, mirrored {m}/8, plain {b}/8"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// `join` appends another model's components at an offset (its scores
/// move by it), leaves objects without one unchanged, and refuses a base
/// that is already joined, a bad offset, and a check without its data.
#[test]
fn join_cli_appends_components_and_refuses_bad_input() {
    let bin = env!("CARGO_BIN_EXE_sdhop-train");
    let dir = std::env::temp_dir().join(format!("sdhop-join-{}", std::process::id()));
    let (base, add, out) = (dir.join("base"), dir.join("add"), dir.join("out"));
    for d in [&base, &add] {
        std::fs::create_dir_all(d).unwrap();
    }
    let hp = HandModelParams::default();
    let obj = hand_model(&OBJECT, "obj", true, &hp).unwrap();
    obj.save(&base.join("obj.safetensors")).unwrap();
    hand_model(&OBJECT, "other", true, &hp)
        .unwrap()
        .save(&base.join("other.safetensors"))
        .unwrap();
    obj.save(&add.join("obj.safetensors")).unwrap();
    let run = |args: &[&str]| {
        let o = std::process::Command::new(bin).args(args).output().unwrap();
        (
            o.status.code(),
            String::from_utf8_lossy(&o.stdout).into_owned(),
            String::from_utf8_lossy(&o.stderr).into_owned(),
        )
    };
    let p = |d: &std::path::Path| d.to_str().unwrap().to_owned();
    let (code, stdout, stderr) = run(&[
        "join",
        "--base",
        &p(&base),
        "--add",
        &p(&add),
        "--offset=0.5",
        "--out",
        &p(&out),
    ]);
    assert_eq!(code, Some(0), "{stderr}");
    assert!(
        stdout.contains("other: 1 component(s) not joined"),
        "{stdout}"
    );
    let joined = Model::load(&out.join("obj.safetensors")).unwrap();
    assert_eq!(joined.views.len(), 2);
    assert_eq!(
        Model::load(&out.join("other.safetensors"))
            .unwrap()
            .views
            .len(),
        1
    );
    // The appended copy wins by the offset.
    let sc = scene(&OBJECT, &scene_params(7)).unwrap();
    let best = |m: &Model| {
        let r = detect_image(&sc.image, &[m], &DetectOptions::default()).unwrap();
        (r.detections[0].score, r.detections[0].viewpoint)
    };
    let ((s0, _), (s1, v1)) = (best(&obj), best(&joined));
    assert_eq!(v1, 1);
    assert!((s1 - s0 - 0.5).abs() < 1e-4, "{s1} vs {s0}");
    // Refusals, each with status 2 and a message naming the cause.
    let refused = |base: &std::path::Path, extra: &[&str], cause: &str| {
        let mut args = vec![
            "join".to_string(),
            "--base".into(),
            p(base),
            "--add".into(),
            p(&add),
        ];
        args.extend(extra.iter().map(|s| s.to_string()));
        args.extend(["--out".to_string(), p(&dir.join("refused"))]);
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        let (code, _, stderr) = run(&refs);
        assert_eq!(code, Some(2), "{stderr}");
        assert!(stderr.contains(cause), "{stderr}");
    };
    refused(&out, &[], "already a joined model");
    refused(&base, &["--offset=abc"], "--offset");
    refused(&base, &["--check-folds", &p(&add)], "--ko8");
    // The single-pose guard needs photographs that trained neither side.
    refused(
        &base,
        &["--check-folds", &p(&add), "--ko8", &p(&dir)],
        "--guard-folds",
    );
    // A choice from recorded figures needs a join's record, and a time
    // budget below the unjoined set's time is none.
    refused(
        &base,
        &["--recorded", &p(&add), "--ko8", &p(&dir)],
        "has no join_check",
    );
    refused(&base, &["--recorded", &p(&add)], "--ko8");
    refused(
        &base,
        &[
            "--recorded",
            &p(&add),
            "--ko8",
            &p(&dir),
            "--max-time-ratio",
            "0.5",
        ],
        "--max-time-ratio",
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn pair_cli_gives_each_model_its_segmenter_and_refuses_bad_input() {
    let bin = env!("CARGO_BIN_EXE_sdhop-train");
    let dir = std::env::temp_dir().join(format!("sdhop-pair-{}", std::process::id()));
    let (finders, segs, out) = (dir.join("finders"), dir.join("segs"), dir.join("out"));
    for d in [&finders, &segs] {
        std::fs::create_dir_all(d).unwrap();
    }
    let hp = HandModelParams::default();
    let hog = hand_model(&OBJECT, "obj", true, &hp).unwrap();
    let mut cnn = hog.clone();
    cnn.meta.pyramid.features = FeatureKind::Cnn;
    cnn.meta.cells = FeatureKind::Cnn.fingerprint().unwrap();
    cnn.save(&finders.join("obj.safetensors")).unwrap();
    hog.save(&segs.join("obj.safetensors")).unwrap();
    let run = |args: &[&std::path::Path], out: &std::path::Path| {
        let o = std::process::Command::new(bin)
            .arg("pair")
            .args(args)
            .arg("--out")
            .arg(out)
            .output()
            .unwrap();
        (
            o.status.code(),
            String::from_utf8_lossy(&o.stdout).into_owned(),
            String::from_utf8_lossy(&o.stderr).into_owned(),
        )
    };
    let (code, stdout, stderr) = run(&[&finders, &segs], &out);
    assert_eq!(code, Some(0), "{stderr}");
    assert!(stdout.contains("segmented by obj (hog cells)"), "{stdout}");
    let paired = Model::load(&out.join("obj.safetensors")).unwrap();
    assert_eq!(paired.segmenter.as_deref(), Some(&hog));
    assert_eq!(paired.clone().without_segmenter(), cnn);
    // Without a second folder: the segmenters given up.
    let bare = dir.join("bare");
    let (code, _, stderr) = run(&[&out], &bare);
    assert_eq!(code, Some(0), "{stderr}");
    assert_eq!(Model::load(&bare.join("obj.safetensors")).unwrap(), cnn);
    // Extracted: the segmenters alone; a model without one is refused.
    let extracted = dir.join("extracted");
    let o = std::process::Command::new(bin)
        .args(["pair", "--extract", "--out"])
        .arg(&extracted)
        .arg(&out)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(0));
    assert_eq!(
        Model::load(&extracted.join("obj.safetensors")).unwrap(),
        hog
    );
    let o = std::process::Command::new(bin)
        .args(["pair", "--extract", "--out"])
        .arg(dir.join("r0"))
        .arg(&bare)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("has no segmenter"));
    // Refusals with status 2, naming the cause: a segmenter on the same
    // cells, none for an object, no models at all.
    let (code, _, stderr) = run(&[&finders, &finders], &dir.join("r1"));
    assert_eq!(code, Some(2), "{stderr}");
    assert!(stderr.contains("other kind"), "{stderr}");
    let other = dir.join("other");
    std::fs::create_dir_all(&other).unwrap();
    hand_model(&OBJECT, "pitcher", true, &hp)
        .unwrap()
        .save(&other.join("pitcher.safetensors"))
        .unwrap();
    let (code, _, stderr) = run(&[&finders, &other], &dir.join("r2"));
    assert_eq!(code, Some(2), "{stderr}");
    assert!(stderr.contains("no segmenter"), "{stderr}");
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let (code, _, stderr) = run(&[&empty, &segs], &dir.join("r3"));
    assert_eq!(code, Some(2), "{stderr}");
    assert!(stderr.contains("no *.safetensors"), "{stderr}");
    std::fs::remove_dir_all(&dir).ok();
}
