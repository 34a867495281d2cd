//! Time of the learned features' backbone (`vision::cnn`, the truncated
//! EfficientNet-Lite0 in `models/backbones/`) on the CPU, one thread, per
//! image at the scales a feature pyramid of a 640x480 photograph asks for
//! (the measurement used 1.26 to 2.52 times the photograph over
//! four levels; ONNX Runtime took 63 ms for those four at one thread,
//! tract 278 ms).
//!
//! It also counts the multiply-adds of the pyramids a learned model scans
//! (`Backbone::macs`; a 640x480 photograph, levels from 1 to 0.5 at 10
//! and at 5 an octave, the CMU_KO8 routes' pyramids) and measures this
//! core's ceiling of 32-bit fused multiply-adds (16 independent AVX-512
//! accumulators; the same loop on 8-lane AVX2 where AVX-512 is absent),
//! so that the time those pyramids need at the least can be read.
//!
//! `cargo bench --bench backbone` (`-- --iters N`).

use std::path::Path;
use std::time::Instant;

use sdhop::synth::SynthObject;
use sdhop::vision::cnn::Backbone;
use sdhop::vision::image::ColorImage;
use sdhop::vision::pyramid::PyramidParams;

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
    let four: u64 = scales
        .iter()
        .map(|s| {
            let img = scaled(&photo, *s);
            net.macs(img.width(), img.height())
        })
        .sum();
    println!(
        "  {:.2} GMAC, {:.1} GMAC/s",
        four as f64 / 1e9,
        four as f64 / 1e6 / total
    );
    let peak = fma_ceiling();
    match peak {
        Some(p) => println!("this core's fused multiply-add ceiling: {p:.1} GMAC/s (32-bit)"),
        None => {
            println!("this core's fused multiply-add ceiling: not measured (no AVX2 or AVX-512)")
        }
    }
    for lpo in [10, 5] {
        let pyr = PyramidParams {
            levels_per_octave: lpo,
            ..PyramidParams::default()
        };
        let macs: u64 = pyr
            .scales()
            .iter()
            .map(|s| {
                let (w, h) = ((640.0 * s).round() as usize, (480.0 * s).round() as usize);
                net.macs(w, h)
            })
            .sum();
        let at_least = peak.map_or(String::new(), |p| {
            format!(", at least {:.1} ms at the ceiling", macs as f64 / 1e6 / p)
        });
        println!(
            "pyramid 1..0.5 at {lpo} levels an octave ({} levels): {:.2} GMAC{at_least}",
            pyr.scales().len(),
            macs as f64 / 1e9
        );
    }
}

/// Multiply-adds a second of this core's best vector unit (GMAC/s), the
/// best of five runs of 256 independent fused multiply-adds an iteration
/// (16 accumulators of 16 lanes), compiled for AVX-512 or AVX2 (written
/// portably, as `vision::simd`'s loops are, for the crate's MSRV).
fn fma_ceiling() -> Option<f64> {
    #[cfg(target_arch = "x86_64")]
    {
        let fma = is_x86_feature_detected!("fma");
        let run: fn(u64) -> f32 = if fma && is_x86_feature_detected!("avx512f") {
            // SAFETY: the features were detected.
            |n| unsafe { fma_avx512(n) }
        } else if fma && is_x86_feature_detected!("avx2") {
            // SAFETY: the features were detected.
            |n| unsafe { fma_avx2(n) }
        } else {
            return None;
        };
        let iters = 20_000_000u64;
        let mut best = f64::INFINITY;
        for _ in 0..5 {
            let t = Instant::now();
            std::hint::black_box(run(std::hint::black_box(iters)));
            best = best.min(t.elapsed().as_secs_f64());
        }
        Some((iters * 256) as f64 / best / 1e9)
    }
    #[cfg(not(target_arch = "x86_64"))]
    None
}

/// `n` rounds of a fused multiply-add on each of 256 independent values,
/// compiled for the named features.
macro_rules! fma_rounds {
    ($name:ident, $features:literal) => {
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = $features)]
        unsafe fn $name(n: u64) -> f32 {
            let (a, b) = (
                std::hint::black_box(0.999_999f32),
                std::hint::black_box(1e-7f32),
            );
            let mut acc = [1.0f32; 256];
            for _ in 0..n {
                for x in acc.iter_mut() {
                    *x = x.mul_add(a, b);
                }
            }
            acc.iter().sum()
        }
    };
}

fma_rounds!(fma_avx512, "avx512f,fma");
fma_rounds!(fma_avx2, "avx2,fma");
