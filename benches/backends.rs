//! Per-image time of each stage on both backends, through the backend trait
//! as the service runs it: pyramids of a batch (HOG on the backend, the
//! over-segmentation on the CPU beside it), the stage-1 bounds (on the GPU
//! backend), then the min-cuts and masks on the CPU.
//!
//! `cargo bench --bench backends` (`-- --iters N`, `-- --batch B`). The GPU
//! backend runs on the best adapter there is, software ones included (their
//! figures say nothing about a real GPU), and is left out where none exists.

use std::path::Path;
use std::time::Instant;

use sdhop::backend::{model_bounds, Backend, CpuBackend, FeatureJob, GpuBackend, GpuOptions};
use sdhop::model::Model;
use sdhop::pipeline::{detect_prebuilt_with, feature_settings, DetectOptions, MaskMode};
use sdhop::synth::{hand_model, HandModelParams, SynthObject};
use sdhop::vision::detect::DenseBounds;
use sdhop::vision::image::ColorImage;
use sdhop::vision::pyramid::FeaturePyramid;

mod common;
use common::{arg, median, vga_scenes};

/// Stage times of one batch, per image: pyramids, bounds, min-cuts+masks,
/// total; and the backend's own features time.
fn run_batch(
    backend: &mut dyn Backend,
    images: &[ColorImage],
    models: &[&Model],
    opts: &DetectOptions,
) -> [f64; 5] {
    let settings = feature_settings(models);
    let shared: Vec<std::sync::Arc<ColorImage>> = images
        .iter()
        .map(|i| std::sync::Arc::new(i.clone()))
        .collect();
    let t0 = Instant::now();
    let jobs: Vec<FeatureJob<'_>> = shared
        .iter()
        .map(|image| FeatureJob {
            image,
            settings: &settings,
            deadline: sdhop::vision::Deadline::NONE,
        })
        .collect();
    let pyramids: Vec<Vec<FeaturePyramid>> = backend
        .pyramids(&jobs)
        .into_iter()
        .map(|r| r.expect("pyramids"))
        .collect();
    let t1 = Instant::now();
    let all_bounds: Vec<Vec<Option<DenseBounds>>> = pyramids
        .iter()
        .map(|pyrs| model_bounds(backend, pyrs, models))
        .collect();
    let t2 = Instant::now();
    for (pyrs, bounds) in pyramids.iter().zip(&all_bounds) {
        let refs: Vec<&FeaturePyramid> = pyrs.iter().collect();
        let pre: Vec<Option<&DenseBounds>> = bounds.iter().map(Option::as_ref).collect();
        detect_prebuilt_with(&refs, models, &pre, opts).expect("detect");
    }
    let t3 = Instant::now();
    let n = images.len() as f64;
    let ms = |a: Instant, b: Instant| (b - a).as_secs_f64() * 1e3 / n;
    let features = pyramids
        .iter()
        .flat_map(|p| p.iter().map(|p| p.timing.features_ms))
        .sum::<f64>()
        / n;
    [ms(t0, t1), ms(t1, t2), ms(t2, t3), ms(t0, t3), features]
}

fn main() {
    let iters = arg("--iters", 10usize);
    let batch = arg("--batch", 1usize).max(1);
    let obj = SynthObject {
        cols: 18,
        rows: 16,
        seed: 3,
    };
    let synthetic =
        hand_model(&obj, "synthetic", true, &HandModelParams::default()).expect("model");
    let shipped: Vec<Model> =
        std::fs::read_dir(Path::new(env!("CARGO_MANIFEST_DIR")).join("models"))
            .map(|d| {
                let mut paths: Vec<_> = d
                    .flatten()
                    .map(|e| e.path())
                    .filter(|p| p.extension().is_some_and(|e| e == "safetensors"))
                    .collect();
                paths.sort();
                paths.iter().filter_map(|p| Model::load(p).ok()).collect()
            })
            .unwrap_or_default();
    let images: Vec<ColorImage> = vga_scenes(&obj, batch.max(4) as u64)
        .into_iter()
        .map(|s| s.image)
        .collect();
    let mut backends: Vec<(String, Box<dyn Backend>)> = vec![("cpu".into(), Box::new(CpuBackend))];
    match GpuBackend::new(&GpuOptions {
        allow_software: true,
        ..GpuOptions::default()
    }) {
        Ok(g) => backends.push((format!("gpu on {}", g.adapter()), Box::new(g))),
        Err(e) => println!("no GPU backend: {e}"),
    }
    println!(
        "threads: {}, batch {batch}, 640x480 synthetic scenes, median of {iters}",
        rayon::current_num_threads()
    );
    let opts = DetectOptions {
        masks: MaskMode::Refined,
        ..DetectOptions::default()
    };
    let mut cases: Vec<(String, Vec<&Model>)> = vec![("one 18x16 model".into(), vec![&synthetic])];
    if let Some(m) = shipped.first() {
        cases.push((format!("shipped {}", m.meta.name), vec![m]));
    }
    if shipped.len() > 1 {
        cases.push((
            format!("{} shipped models", shipped.len()),
            shipped.iter().collect(),
        ));
    }
    for (name, backend) in backends.iter_mut() {
        for (case, models) in &cases {
            // Warm-up: pipelines, buffers.
            run_batch(backend.as_mut(), &images[..batch], models, &opts);
            let mut stages: [Vec<f64>; 5] = Default::default();
            for i in 0..iters {
                let start = (i * batch) % images.len();
                let chunk: Vec<ColorImage> = (0..batch)
                    .map(|k| images[(start + k) % images.len()].clone())
                    .collect();
                let r = run_batch(backend.as_mut(), &chunk, models, &opts);
                for (s, v) in stages.iter_mut().zip(r) {
                    s.push(v);
                }
            }
            let [pyr, bounds, rest, total, feats] = &mut stages;
            println!(
                "{name:<40} {case:<22} ms/image: total {:7.1} | pyramid {:6.1} (HOG {:6.1}) | bounds {:6.1} | min-cuts+masks {:6.1}",
                median(total),
                median(pyr),
                median(feats),
                median(bounds),
                median(rest),
            );
        }
    }
}
