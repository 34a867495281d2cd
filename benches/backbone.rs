//! Time of the learned features' backbone (`vision::cnn`, the truncated
//! EfficientNet-Lite0 in `models/backbones/`) on the CPU, one thread, per
//! image at the scales a feature pyramid of a 640x480 photograph asks for
//! (the measurement used 1.26 to 2.52 times the photograph over
//! four levels; ONNX Runtime took 63 ms for those four at one thread,
//! tract 278 ms).
//!
//! `cargo bench --bench backbone` (`-- --iters N`).

use std::path::Path;
use std::time::Instant;

use sdhop::synth::SynthObject;
use sdhop::vision::cnn::Backbone;
use sdhop::vision::image::ColorImage;

mod common;
use common::{arg, median, vga_scenes};

/// `img` resized by `scale` (nearest sample: the content does not matter
/// to the time).
fn scaled(img: &ColorImage, scale: f64) -> ColorImage {
    let (w, h) = (
        (img.width() as f64 * scale).round() as usize,
        (img.height() as f64 * scale).round() as usize,
    );
    let mut data = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            let (sx, sy) = (
                ((x as f64 / scale) as usize).min(img.width() - 1),
                ((y as f64 / scale) as usize).min(img.height() - 1),
            );
            for c in 0..3 {
                data.push(img.get(sx, sy, c));
            }
        }
    }
    ColorImage::new(w, h, data).expect("image")
}

fn main() {
    // One compute thread, as the figure says (the backbone's bands run on
    // every thread of the pool it is called in).
    rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool")
        .install(run);
}

fn run() {
    let iters = arg("--iters", 5usize);
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("models/backbones/efficientnet_lite0_s8.safetensors");
    let net = Backbone::load(&path).expect("backbone");
    let obj = SynthObject {
        cols: 12,
        rows: 10,
        seed: 1,
    };
    let photo = vga_scenes(&obj, 1).remove(0).image;
    let scales = [1.26, 1.59, 2.0, 2.52];
    let mut total = 0.0;
    for &s in &scales {
        let img = scaled(&photo, s);
        net.forward(&img);
        let mut times = Vec::new();
        for _ in 0..iters {
            let t = Instant::now();
            let f = net.forward(&img);
            times.push(t.elapsed().as_secs_f64() * 1e3);
            assert_eq!(f.channels, net.channels);
        }
        let m = median(&mut times);
        total += m;
        println!(
            "scale {s:4.2} ({}x{}): {m:7.1} ms",
            img.width(),
            img.height()
        );
    }
    println!(
        "the four levels of a 640x480 photograph: {total:.1} ms (one thread, median of {iters})"
    );
}
