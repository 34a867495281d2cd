//! Parity of the GPU backend (the WGSL kernels of `kernels/`) with the CPU
//! references of the vision layer: resized levels, HOG features, chain
//! bounds, filter responses and the final detections, on real and
//! adversarial images (flat, saturated, tiny, sizes not a multiple of 8).
//!
//! The GPU is forced (software adapters such as lavapipe included). The
//! tests need a Vulkan adapter, so they are ignored by default (the test
//! summary counts them); run them with `cargo test --release --
//! --include-ignored` where one is (`.ci/run` installs Mesa's software
//! Vulkan and does), and there a missing adapter is a failure.

use std::path::Path;

use sdhop::backend::{model_bounds, Backend, CpuBackend, FeatureJob, GpuBackend, GpuOptions};
use sdhop::model::Model;
use sdhop::pipeline::{
    detect_image, detect_prebuilt_with, feature_settings, DetectOptions, MaskMode,
};
use sdhop::synth::{hand_model, scene, HandModelParams, SceneParams, SynthObject};
use sdhop::vision::cells::FeatureKind;
use sdhop::vision::detect::{dense_bounds, responses, DenseBounds, Location};
use sdhop::vision::hog::HogMap;
use sdhop::vision::image::ColorImage;
use sdhop::vision::pyramid::{feature_levels, FeaturePyramid, PyramidParams};
use sdhop::vision::rng::SplitMix64;
use sdhop::vision::segment::SegmentParams;
use sdhop::vision::Deadline;

const OBJECT: SynthObject = SynthObject {
    cols: 12,
    rows: 10,
    seed: 11,
};

/// Why the tests of this file are ignored by default.
const NEEDS_GPU: &str = "needs a Vulkan adapter";

/// The GPU backend on any adapter; a missing one fails the test.
fn gpu() -> GpuBackend {
    let opts = GpuOptions {
        allow_software: true,
        ..GpuOptions::default()
    };
    match GpuBackend::new(&opts) {
        Ok(b) => {
            eprintln!("GPU backend on {}", b.adapter());
            b
        }
        Err(e) => panic!("{NEEDS_GPU} (install Mesa's mesa-vulkan-drivers): {e}"),
    }
}

fn from_fn(w: usize, h: usize, f: impl Fn(usize, usize, usize) -> f32) -> ColorImage {
    let mut data = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            for c in 0..3 {
                data.push(f(x, y, c));
            }
        }
    }
    ColorImage::new(w, h, data).unwrap()
}

fn noise(w: usize, h: usize, seed: u64) -> ColorImage {
    let mut rng = SplitMix64::new(seed);
    let data = (0..w * h * 3)
        .map(|_| (rng.next_f64() * 255.0).round() as f32)
        .collect();
    ColorImage::new(w, h, data).unwrap()
}

/// The first occluded pitcher image and the first negative scene of the
/// CMU_KO8 development split, where it is present.
fn ko8_images() -> Vec<(String, ColorImage)> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/cmu_ko8");
    let mut out = Vec::new();
    for dir in ["single/test/pitcher", "negative"] {
        let Ok(entries) = std::fs::read_dir(root.join(dir)) else {
            continue;
        };
        let mut jpgs: Vec<_> = entries
            .flatten()
            .map(|e| e.path())
            .filter(|p| p.extension().is_some_and(|e| e == "jpg"))
            .collect();
        jpgs.sort();
        if let Some(p) = jpgs.first() {
            let img = image::open(p).expect("a CMU_KO8 image").to_rgb8();
            let name = format!(
                "CMU_KO8 {}",
                p.file_name().unwrap_or_default().to_string_lossy()
            );
            out.push((name, ColorImage::from_rgb8(&img).unwrap()));
        }
    }
    out
}

/// Real and adversarial images, named.
fn images() -> Vec<(String, ColorImage)> {
    let mut out = vec![
        ("flat".to_string(), from_fn(64, 48, |_, _, _| 128.0)),
        (
            "saturated".to_string(),
            from_fn(61, 45, |x, y, c| {
                if (x / 3 + y / 5 + c) % 2 == 0 {
                    0.0
                } else {
                    255.0
                }
            }),
        ),
        ("tiny 8x8".to_string(), noise(8, 8, 1)),
        ("tiny 9x13".to_string(), noise(9, 13, 2)),
        ("too small 7x30".to_string(), noise(7, 30, 3)),
        ("37x29".to_string(), noise(37, 29, 4)),
        (
            "ramp 101x67".to_string(),
            from_fn(101, 67, |x, y, c| ((x * 3 + y * 5 + c * 40) % 256) as f32),
        ),
    ];
    let s = scene(&OBJECT, &SceneParams::default()).unwrap();
    out.push(("synthetic scene".to_string(), s.image));
    let real = ko8_images();
    if real.is_empty() {
        eprintln!("(../shared/data/cmu_ko8 is not here; its real images are left out)");
    }
    out.extend(real);
    out
}

#[test]
#[ignore = "needs a Vulkan adapter"]
fn resized_levels_match_the_cpu() {
    let mut gpu = gpu();
    let p = PyramidParams::default();
    for (name, img) in images() {
        let levels = gpu.resized_levels(&img, &p).unwrap();
        let pyr = FeaturePyramid::build(&img, &p, &SegmentParams::default()).unwrap();
        assert_eq!(levels.len(), pyr.levels.len(), "{name}: level count");
        for (l, g) in levels.iter().enumerate() {
            let c = img.resize_area(g.width(), g.height()).unwrap();
            let worst = g
                .data()
                .iter()
                .zip(c.data())
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            eprintln!("{name}, level {l}: resize max |diff| {worst:.2e}");
            assert!(
                worst <= 1e-3,
                "{name}, level {l}: resize differs by {worst}"
            );
        }
    }
}

/// Largest difference and the fraction of values differing by more than
/// 1e-4 between two HOG maps.
fn hog_diff(a: &HogMap, b: &HogMap) -> (f32, f64) {
    assert_eq!((a.width(), a.height()), (b.width(), b.height()));
    let mut worst = 0.0f32;
    let mut off = 0usize;
    for (x, y) in a.raw().iter().zip(b.raw()) {
        let d = (x - y).abs();
        worst = worst.max(d);
        off += usize::from(d > 1e-4);
    }
    (worst, off as f64 / a.raw().len().max(1) as f64)
}

#[test]
#[ignore = "needs a Vulkan adapter"]
fn hog_features_match_the_cpu() {
    let mut gpu = gpu();
    let p = PyramidParams::default();
    for (name, img) in images() {
        let maps = gpu.hog_levels(&img, &p).unwrap();
        let pyr = FeaturePyramid::build(&img, &p, &SegmentParams::default()).unwrap();
        assert_eq!(maps.len(), pyr.levels.len(), "{name}: level count");
        for (l, (g, c)) in maps.iter().zip(&pyr.levels).enumerate() {
            let (worst, frac) = hog_diff(g, &c.hog);
            eprintln!(
                "{name}, level {l}: max |diff| {worst:.2e}, {:.4}% above 1e-4",
                frac * 100.0
            );
            // Values agree to float round-off; a gradient lying within
            // round-off of the boundary between two orientation bins may
            // vote into the other bin on the GPU, which moves that cell's
            // values by more, so a tiny fraction may differ beyond 1e-4.
            assert!(
                frac <= 2e-3,
                "{name}, level {l}: {frac} of the values differ"
            );
            assert!(worst <= 0.2, "{name}, level {l}: max difference {worst}");
        }
    }
}

/// Learned cells of the GPU (`kernels/backbone.wgsl`, levels resized with
/// the smooth taps) against the CPU's, level by level: the same cells, and
/// values within 1e-4 (the backbone's sixteen layers sum in another order
/// than the CPU's GEMM; a cell's squared norm is about 1). Small images also
/// go through upsampled levels (linear taps).
#[test]
#[ignore = "needs a Vulkan adapter"]
fn learned_cells_match_the_cpu() {
    let mut gpu = gpu();
    let down = PyramidParams {
        levels_per_octave: 2,
        max_scale: 1.0,
        min_scale: 0.5,
        features: FeatureKind::Cnn,
        computed_every: 1,
    };
    let up = PyramidParams {
        max_scale: 2.3,
        ..down
    };
    let mut compared = 0;
    for (name, img) in images() {
        let small = img.width() * img.height() <= 12_000;
        for p in if small { vec![down, up] } else { vec![down] } {
            let maps = gpu.learned_levels(&img, &p).unwrap();
            let cpu = feature_levels(&img, &p, Deadline::NONE).unwrap();
            assert_eq!(maps.len(), cpu.len(), "{name}: level count");
            for (l, (g, (_, _, c))) in maps.iter().zip(&cpu).enumerate() {
                assert_eq!(
                    (g.width(), g.height()),
                    (c.width(), c.height()),
                    "{name}, level {l}: cells"
                );
                let (worst, frac) = hog_diff(g, c);
                eprintln!(
                    "{name}, scales {}-{}, level {l}: learned cells max |diff| {worst:.2e}, {:.4}% above 1e-4",
                    p.min_scale,
                    p.max_scale,
                    frac * 100.0
                );
                assert!(worst <= 1e-4, "{name}, level {l}: max difference {worst}");
                compared += g.raw().len();
            }
        }
    }
    assert!(compared > 10_000, "too few values compared: {compared}");
}

fn models() -> Vec<Model> {
    let hp = HandModelParams::default();
    // A model of learned cells beside the HOG ones: its pyramid is built
    // apart (the backbone on the CPU) and served through the same bounds,
    // responses and min-cuts.
    let mut learned = hand_model(&OBJECT, "learned", true, &hp).unwrap();
    learned.meta.pyramid.features = FeatureKind::Cnn;
    learned.meta.cells = FeatureKind::Cnn.fingerprint().unwrap();
    learned.validate().unwrap();
    let mut out = vec![
        hand_model(&OBJECT, "occlusion", true, &hp).unwrap(),
        hand_model(&OBJECT, "plain", false, &hp).unwrap(),
        learned,
    ];
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("models");
    for name in ["cup", "scissors"] {
        if let Ok(m) = Model::load(&dir.join(format!("{name}.safetensors"))) {
            out.push(m);
        }
    }
    out
}

fn assert_bounds_close(name: &str, g: &DenseBounds, c: &DenseBounds) {
    assert_eq!(g.levels.len(), c.levels.len(), "{name}");
    for (l, (gl, cl)) in g.levels.iter().zip(&c.levels).enumerate() {
        for (v, (gb, cb)) in gl.iter().zip(cl).enumerate() {
            match (gb, cb) {
                (None, None) => {}
                (Some(gb), Some(cb)) => {
                    assert_eq!(
                        (gb.x_lo, gb.y_lo, gb.nx, gb.ny),
                        (cb.x_lo, cb.y_lo, cb.nx, cb.ny)
                    );
                    let worst = gb
                        .values
                        .iter()
                        .zip(&cb.values)
                        .map(|(a, b)| (a - b).abs() / (1.0 + b.abs()))
                        .fold(0.0f32, f32::max);
                    eprintln!("{name}, level {l}, view {v}: bounds max relative diff {worst:.2e}");
                    for (k, (a, b)) in gb.values.iter().zip(&cb.values).enumerate() {
                        let tol = 2e-5 * (1.0 + b.abs());
                        assert!(
                            (a - b).abs() <= tol,
                            "{name}, level {l}, view {v}, position {k}: GPU {a} CPU {b}"
                        );
                    }
                }
                _ => panic!("{name}, level {l}, view {v}: positions differ"),
            }
        }
    }
}

#[test]
#[ignore = "needs a Vulkan adapter"]
fn dense_bounds_and_responses_match_the_cpu() {
    let mut gpu = gpu();
    let models = models();
    for (name, img) in images() {
        for m in &models {
            let pyr = FeaturePyramid::build(&img, &m.meta.pyramid, &m.meta.segmentation).unwrap();
            let trunc = m.meta.detection.max_truncation;
            // The bounds of the CPU features, so the kernel is compared
            // alone.
            let g = gpu.gpu_dense_bounds(&pyr, &[(&m.views, trunc)]).unwrap();
            let c = dense_bounds(&pyr, &m.views, trunc);
            assert_bounds_close(&format!("{name}, {}", m.meta.name), &g[0], &c);
            // Responses at a spread of locations, truncated ones included.
            let mut locs = Vec::new();
            for (li, level) in pyr.levels.iter().enumerate().step_by(3) {
                for (vi, w) in m.views.iter().enumerate() {
                    let (mw, mh) = (level.hog.width() as isize, level.hog.height() as isize);
                    for (x, y) in [
                        (0, 0),
                        (-(w.cols as isize) / 2, 1),
                        (mw / 2, mh / 3),
                        (mw - 2, mh - 2),
                    ] {
                        locs.push(Location {
                            level: li,
                            view: vi,
                            x,
                            y,
                        });
                    }
                }
            }
            let got = gpu.responses(&pyr, &m.views, &locs).unwrap();
            let mut worst = 0.0f64;
            for (loc, g) in locs.iter().zip(&got) {
                let c = responses(&pyr, &m.views, loc).unwrap();
                assert_eq!(g.len(), c.len());
                for (i, (&(gf, gb), &(cf, cb))) in g.iter().zip(&c).enumerate() {
                    worst = worst
                        .max((f64::from(gf) - cf).abs() / (1.0 + cf.abs()))
                        .max((f64::from(gb) - cb).abs() / (1.0 + cb.abs()));
                    assert!(
                        (f64::from(gf) - cf).abs() <= 1e-5 * (1.0 + cf.abs())
                            && (f64::from(gb) - cb).abs() <= 1e-5 * (1.0 + cb.abs()),
                        "{name}, {loc:?}, cell {i}: GPU ({gf}, {gb}) CPU ({cf}, {cb})"
                    );
                }
            }
            eprintln!(
                "{name}, {}: responses max relative diff {worst:.2e}",
                m.meta.name
            );
        }
    }
}

/// Detections of the GPU path (pyramids and bounds from the backend, then
/// the CPU's min-cuts) against the CPU path.
fn detect_gpu(
    gpu: &mut GpuBackend,
    img: &ColorImage,
    models: &[&Model],
    opts: &DetectOptions,
) -> sdhop::pipeline::DetectResponse {
    detect_through(gpu, img, models, opts, true)
}

/// The service's path through `gpu`; `on_gpu` says whether the device
/// should still compute every model's bounds (it no longer does once lost).
fn detect_through(
    gpu: &mut GpuBackend,
    img: &ColorImage,
    models: &[&Model],
    opts: &DetectOptions,
    on_gpu: bool,
) -> sdhop::pipeline::DetectResponse {
    let settings = feature_settings(models);
    let img = std::sync::Arc::new(img.clone());
    let job = FeatureJob {
        image: &img,
        settings: &settings,
        deadline: sdhop::vision::Deadline::NONE,
    };
    let pyrs = gpu.pyramids(&[job]).pop().unwrap().unwrap();
    let bounds = model_bounds(gpu, &pyrs, models);
    assert_eq!(
        bounds.iter().all(Option::is_some),
        on_gpu,
        "bounds from the GPU exactly while it works"
    );
    let refs: Vec<&FeaturePyramid> = pyrs.iter().collect();
    let pre: Vec<Option<&DenseBounds>> = bounds.iter().map(Option::as_ref).collect();
    detect_prebuilt_with(&refs, models, &pre, opts).unwrap()
}

#[test]
#[ignore = "needs a Vulkan adapter"]
fn detections_of_both_backends_agree() {
    let mut gpu = gpu();
    let mut models = models();
    // Both kinds per object: learned cells find, a HOG segmenter places
    // and segments (its pyramid shares the segmentation on both paths).
    let hp = HandModelParams::default();
    let mut finder = hand_model(&OBJECT, "paired", true, &hp).unwrap();
    finder.meta.pyramid.features = FeatureKind::Cnn;
    finder.meta.cells = FeatureKind::Cnn.fingerprint().unwrap();
    let segmenter = hand_model(&OBJECT, "paired", true, &hp).unwrap();
    models.push(finder.with_segmenter(segmenter).unwrap());
    let refs: Vec<&Model> = models.iter().collect();
    let opts = DetectOptions {
        masks: MaskMode::Both,
        threshold: Some(-0.5),
        ..DetectOptions::default()
    };
    let mut cases: Vec<(String, ColorImage)> = (0..4)
        .map(|seed| {
            let s = scene(
                &OBJECT,
                &SceneParams {
                    seed,
                    ..SceneParams::default()
                },
            )
            .unwrap();
            (format!("synthetic scene {seed}"), s.image)
        })
        .collect();
    cases.extend(images());
    let mut compared = 0;
    for (name, img) in cases {
        let cpu = detect_image(&img, &refs, &opts).unwrap();
        let g = detect_gpu(&mut gpu, &img, &refs, &opts);
        assert_eq!(
            cpu.detections.len(),
            g.detections.len(),
            "{name}: number of detections"
        );
        for (a, b) in cpu.detections.iter().zip(&g.detections) {
            assert_eq!(
                (&a.model, a.level, a.viewpoint),
                (&b.model, b.level, b.viewpoint),
                "{name}"
            );
            assert_eq!(a.bbox, b.bbox, "{name}: boxes");
            assert!(
                (a.score - b.score).abs() <= 1e-3,
                "{name}: scores {} {}",
                a.score,
                b.score
            );
            assert_eq!(a.raw_mask, b.raw_mask, "{name}: raw masks");
            compared += 1;
        }
    }
    assert!(compared >= 4, "too few detections compared: {compared}");
}

#[test]
#[ignore = "needs a Vulkan adapter"]
fn buffers_are_reused_and_device_loss_falls_back_to_the_cpu() {
    let mut gpu = gpu();
    let models = models();
    let refs: Vec<&Model> = models.iter().take(1).collect();
    let opts = DetectOptions::default();
    let s = scene(&OBJECT, &SceneParams::default()).unwrap();
    let first = detect_gpu(&mut gpu, &s.image, &refs, &opts);
    let allocated = gpu.allocations();
    for seed in 1..4 {
        let s = scene(
            &OBJECT,
            &SceneParams {
                seed,
                ..SceneParams::default()
            },
        )
        .unwrap();
        detect_gpu(&mut gpu, &s.image, &refs, &opts);
    }
    assert_eq!(
        gpu.allocations(),
        allocated,
        "steady state allocates no buffers"
    );
    assert!(gpu.healthy());

    gpu.destroy_device();
    let settings = feature_settings(&refs);
    let image = std::sync::Arc::new(s.image.clone());
    let job = FeatureJob {
        image: &image,
        settings: &settings,
        deadline: sdhop::vision::Deadline::NONE,
    };
    let pyrs = gpu.pyramids(&[job]).pop().unwrap().unwrap();
    assert!(!gpu.healthy(), "a lost device marks the backend unhealthy");
    assert!(
        gpu.info().device.contains("serving on the CPU"),
        "{}",
        gpu.info().device
    );
    let cpu = CpuBackend
        .pyramids(&[FeatureJob {
            image: &image,
            settings: &settings,
            deadline: sdhop::vision::Deadline::NONE,
        }])
        .pop()
        .unwrap()
        .unwrap();
    assert_eq!(pyrs[0].levels.len(), cpu[0].levels.len());
    for (a, b) in pyrs[0].levels.iter().zip(&cpu[0].levels) {
        assert_eq!(a.hog, b.hog, "after the loss the CPU builds the features");
    }
    assert!(gpu
        .dense_bounds(&pyrs[0], &[(&models[0].views, 0.5)])
        .unwrap()
        .is_none());
    let again = detect_through(&mut gpu, &s.image, &refs, &opts, false);
    assert_eq!(again.detections.len(), first.detections.len());
}
