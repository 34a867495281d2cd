//! Detector speed on one 640x480 synthetic scene, one viewpoint with an
//! 18x16-cell template and the default pyramid: median per-image time and
//! per-stage times, and the fraction of locations pruned.
//!
//! `cargo bench --bench detect` (add `-- --iters N` for more runs).

use std::time::Instant;

use sdhop::pipeline::{detect_image, DetectOptions, MaskMode};
use sdhop::synth::{hand_model, HandModelParams, SynthObject};

mod common;
use common::{arg, median, stage_times, vga_scenes};

fn main() {
    let iters = arg("--iters", 30usize);
    let obj = SynthObject {
        cols: 18,
        rows: 16,
        seed: 3,
    };
    let model = hand_model(&obj, "synthetic", true, &HandModelParams::default()).expect("model");
    let scenes = vga_scenes(&obj, 5);
    println!("threads: {}", rayon::current_num_threads());
    for (mode, max_det, prune) in [
        ("top-1", 1, true),
        ("threshold, 10 best", 10, true),
        ("no pruning, top-1", 1, false),
    ] {
        let opts = DetectOptions {
            max_detections: Some(max_det),
            masks: MaskMode::Refined,
            prune,
            ..DetectOptions::default()
        };
        let runs = if prune { iters } else { 3.min(iters) };
        let mut stage: [Vec<f64>; 7] = Default::default();
        let mut pruned = Vec::new();
        for i in 0..runs {
            let s = &scenes[i % scenes.len()];
            let t = Instant::now();
            let r = detect_image(&s.image, &[&model], &opts).expect("detect");
            let wall = t.elapsed().as_secs_f64() * 1e3;
            for (k, v) in stage_times(wall, &r.timing_ms)
                .into_iter()
                .take(7)
                .enumerate()
            {
                stage[k].push(v);
            }
            pruned.push(r.timing_ms.pruned_fraction);
        }
        let names = [
            "total",
            "features",
            "segmentation",
            "cell-segments",
            "responses+bounds",
            "min-cuts",
            "masks",
        ];
        let line: Vec<String> = names
            .iter()
            .zip(stage.iter_mut())
            .map(|(n, v)| format!("{n} {:.1}", median(v)))
            .collect();
        println!(
            "{mode:<20} median ms over {runs}: {}; pruned {:.2}%",
            line.join(", "),
            100.0 * median(&mut pruned)
        );
    }
}
