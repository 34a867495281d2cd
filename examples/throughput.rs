//! In-process detection throughput: the images listed in a file (one path
//! per line), detected one after another with the given models (as the
//! service's worker does), after one warm-up pass. Prints images per second
//! and latency percentiles, the figures the HTTP load test is compared with.
//!
//! `cargo run --release --example throughput -- IMAGES.txt SECONDS MODEL.safetensors...`

use std::path::PathBuf;
use std::time::{Duration, Instant};

use sdhop::data::load_image;
use sdhop::model::Model;
use sdhop::pipeline::{detect_image, DetectOptions, MaskMode};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 4 {
        return Err("usage: throughput IMAGES.txt SECONDS MODEL.safetensors...".into());
    }
    let list = std::fs::read_to_string(&args[1])?;
    let seconds: f64 = args[2].parse()?;
    let models: Vec<Model> = args[3..]
        .iter()
        .map(|p| Model::load(&PathBuf::from(p)))
        .collect::<Result<_, _>>()?;
    let refs: Vec<&Model> = models.iter().collect();
    let images = list
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| load_image(&PathBuf::from(l.trim())))
        .collect::<Result<Vec<_>, _>>()?;
    // The service's defaults: refined masks, each model's own threshold.
    let opts = DetectOptions {
        masks: MaskMode::Refined,
        ..DetectOptions::default()
    };
    for img in &images {
        detect_image(img, &refs, &opts)?;
    }
    let mut lat: Vec<Duration> = Vec::new();
    let start = Instant::now();
    let mut i = 0;
    while start.elapsed().as_secs_f64() < seconds {
        let t = Instant::now();
        detect_image(&images[i % images.len()], &refs, &opts)?;
        lat.push(t.elapsed());
        i += 1;
    }
    let total = start.elapsed().as_secs_f64();
    lat.sort();
    let pct = |p: f64| lat[((lat.len() - 1) as f64 * p).round() as usize].as_secs_f64() * 1e3;
    println!(
        "{} models, {} images: {:.2} images/s, p50 {:.1} ms, p99 {:.1} ms ({} detections in {:.1} s)",
        models.len(),
        images.len(),
        lat.len() as f64 / total,
        pct(0.5),
        pct(0.99),
        lat.len(),
        total
    );
    Ok(())
}
