//! Detection speed on CMU_KO8 development photographs with the shipped
//! models, as the speed targets measure it: per-image median time and the stage
//! breakdown for one model (cup) and all eight, at 1 and 2 threads, with
//! refined masks; and the same for one model with pruning off, which must
//! give the very same detections (exact pruning), to show what it saves.
//!
//! `cargo bench --bench ko8_speed [-- --images 20 --iters 3 --no-prune-images 3 --threads 1|2 --models 1|8
//! --models-dir models]`
//! (skips with a message without ../shared/data/cmu_ko8).

use std::path::{Path, PathBuf};
use std::time::Instant;

use sdhop::data::ko8::KO8_OBJECTS;
use sdhop::model::Model;
use sdhop::pipeline::{detect_image, DetectOptions, DetectResponse, MaskMode};
use sdhop::vision::image::ColorImage;

mod common;

// The servers' allocator, so that the figures are theirs.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;
use common::{arg, median, stage_times};

fn images(dir: &Path, n: usize) -> Vec<ColorImage> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|r| r.filter_map(|e| e.ok().map(|e| e.path())).collect())
        .unwrap_or_default();
    files.retain(|p| p.extension().is_some_and(|x| x == "jpg"));
    files.sort();
    files
        .iter()
        .take(n)
        .map(|p| sdhop::data::load_image(p).expect("image"))
        .collect()
}

/// Median wall time and stage times (ms) over `iters` passes of `imgs`.
fn run(
    imgs: &[ColorImage],
    models: &[&Model],
    opts: &DetectOptions,
    threads: usize,
    iters: usize,
) -> (Vec<f64>, Vec<DetectResponse>) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("pool");
    let mut stage: [Vec<f64>; 8] = Default::default();
    let mut last = Vec::new();
    pool.install(|| {
        for it in 0..iters {
            for img in imgs {
                let t = Instant::now();
                let r = detect_image(img, models, opts).expect("detect");
                let wall = t.elapsed().as_secs_f64() * 1e3;
                for (k, v) in stage_times(wall, &r.timing_ms).into_iter().enumerate() {
                    stage[k].push(v);
                }
                if it + 1 == iters {
                    last.push(r);
                }
            }
        }
    });
    let mut m: Vec<f64> = stage.iter_mut().map(|v| median(v)).collect();
    let mut counts: Vec<f64> = last.iter().map(|r| r.detections.len() as f64).collect();
    m.push(median(&mut counts));
    (m, last)
}

fn print(label: &str, m: &[f64]) {
    println!(
        "{label:<34} {:>8.1} | features {:.1}, segmentation {:.1}, cell segments {:.1}, responses+bounds {:.1}, min-cuts {:.1} ({:.0}), masks {:.1} ({:.0} detections)",
        m[0], m[1], m[2], m[3], m[4], m[5], m[7], m[6], m[8]
    );
}

fn main() {
    // The server's allocator settings too.
    sdhop::infer::memory::keep_freed_pages();
    let root = PathBuf::from(arg("--data", "../shared/data/cmu_ko8".to_string()));
    // `--image-dir multiple/test/bakingpan`: the multi-view part's
    // photographs of an object (any side) instead of the cup's single-pose
    // ones.
    let dir = root.join(arg("--image-dir", "single/test/cup".to_string()));
    if !dir.is_dir() {
        println!(
            "skipped: {} not found (CMU_KO8 development data)",
            dir.display()
        );
        return;
    }
    let n = arg("--images", 20usize);
    let iters = arg("--iters", 3usize);
    let n_full = arg("--no-prune-images", 3usize);
    let imgs = images(&dir, n);
    let models_dir = PathBuf::from(arg("--models-dir", "models".to_string()));
    let mut models: Vec<Model> = KO8_OBJECTS
        .iter()
        .map(|m| Model::load(&models_dir.join(format!("{m}.safetensors"))).expect("model"))
        .collect();
    let cup_at = models
        .iter()
        .position(|m| m.meta.name == "cup")
        .expect("cup");
    let cup = models.swap_remove(cup_at);
    let all: Vec<&Model> = std::iter::once(&cup).chain(models.iter()).collect();
    let opts = DetectOptions {
        masks: MaskMode::Refined,
        ..DetectOptions::default()
    };
    println!(
        "{} test images of {}, median per image in ms over {iters} passes (stage times: the server's own)",
        imgs.len(),
        dir.display()
    );
    // `--threads 1` or `--models 8` run one case only (for profiling).
    let only_threads = arg("--threads", 0usize);
    let only_models = arg("--models", 0usize);
    for threads in [1, 2] {
        if only_threads != 0 && only_threads != threads {
            continue;
        }
        if only_models != 8 {
            let (m, _) = run(&imgs, &[&cup], &opts, threads, iters);
            print(&format!("1 model (cup), {threads} thread(s)"), &m);
        }
        if only_models != 1 {
            let (m, _) = run(&imgs, &all, &opts, threads, iters);
            print(&format!("8 models, {threads} thread(s)"), &m);
        }
    }
    // Pruning off: the same detections, at what cost.
    let few = &imgs[..n_full.min(imgs.len())];
    if few.is_empty() {
        return;
    }
    let (m_on, on) = run(few, &[&cup], &opts, 2, 1);
    let off_opts = DetectOptions {
        prune: false,
        ..opts.clone()
    };
    let (m_off, off) = run(few, &[&cup], &off_opts, 2, 1);
    let same = on
        .iter()
        .zip(&off)
        .all(|(a, b)| a.detections == b.detections);
    print(
        &format!("cup, pruning on, {} images, 2 thr", few.len()),
        &m_on,
    );
    print(
        &format!("cup, pruning off, {} images, 2 thr", few.len()),
        &m_off,
    );
    println!("pruned detections identical to unpruned: {same}");
    assert!(same, "exact pruning changed the detections");
}
