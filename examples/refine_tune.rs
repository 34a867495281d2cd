//! The pixel refinement of masks against the segment snapping, on the
//! held-out images of one cross-validation fold: each model's top
//! detection per image is found once, then its mask is refined with every
//! setting given and scored (`segerr`: 1 - IoU with the visible ground
//! truth, mean per object, then over objects). The shape models are
//! learned from the fold's training images, as training does.
//!
//! `cargo run --release --example refine_tune -- KO8_ROOT MODELS_DIR FOLD FOLDS [off|S,C,G,B,P ...]`
//! (MODELS_DIR/fold-FOLD/<object>.safetensors, as `cv --save-models`;
//! `OBJECTS=cup,...` for a cross-validation of some objects).

use std::path::PathBuf;
use std::time::Instant;

use sdhop::data::load_image;
use sdhop::model::Model;
use sdhop::train::ko8::{fold_dir, Ko8Data, NegativeSet};
use sdhop::train::learn_shapes;
use sdhop::vision::detect::{DetectParams, Detector};
use sdhop::vision::mask::raw_mask;
use sdhop::vision::pyramid::FeaturePyramid;
use sdhop::vision::refine::{refine_mask, RefineParams};
use sdhop::vision::refine::{refine_pixels, PixelRefine};

fn parse(text: &str) -> Option<PixelRefine> {
    if text == "off" {
        return None;
    }
    let v: Vec<f64> = text.split(',').filter_map(|x| x.parse().ok()).collect();
    Some(PixelRefine {
        enabled: true,
        shape: v[0],
        cells: v[1],
        segments: v[2],
        bias: v[3],
        smoothness: v[4],
        colour: v.get(5).copied().unwrap_or(0.0),
        colour_rounds: v.get(6).map_or(1, |&r| r as usize),
        learned_colours: v.get(7).copied().unwrap_or(0.0),
        align: v.get(8).is_some_and(|&a| a > 0.0),
        margin: v.get(9).copied().unwrap_or(0.0),
    })
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let root = PathBuf::from(&args[1]);
    let models_dir = PathBuf::from(&args[2]);
    let fold: usize = args[3].parse()?;
    let folds: usize = args[4].parse()?;
    let mut configs: Vec<String> = args[5..].to_vec();
    if configs.is_empty() {
        configs.push("1,1,1,0,1".into());
    }
    // OBJECTS=cup,pitcher: those objects alone (a cross-validation of some).
    let objects: Vec<String> = std::env::var("OBJECTS")
        .map(|v| v.split(',').map(str::to_string).collect())
        .unwrap_or_default();
    let data = Ko8Data::load(&root, &objects)?;
    let neg = NegativeSet::default();
    let snap = RefineParams::default();
    // Per object: raw, snapped, then each config.
    let mut table: Vec<(String, Vec<f64>)> = Vec::new();
    let mut refine_ms = vec![0.0f64; configs.len()];
    let mut refine_n = 0usize;
    for (oi, o) in data.objects.iter().enumerate() {
        let model = Model::load(&fold_dir(&models_dir, fold).join(format!("{o}.safetensors")))?;
        let set = data.training_set(oi, Some((fold, folds)), &neg);
        let blur: usize = std::env::var("BLUR")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(0);
        let shapes: Vec<_> = learn_shapes(&model, &set, None)
            .into_iter()
            .map(|s| s.map(|s| s.blurred(blur)))
            .collect();
        if let Ok(dir) = std::env::var("DUMP_SHAPES") {
            for (a, sh) in shapes.iter().enumerate() {
                if let Some(sh) = sh {
                    let img =
                        image::GrayImage::from_fn(sh.width as u32, sh.height as u32, |x, y| {
                            image::Luma([
                                (sh.prob[y as usize * sh.width + x as usize] * 255.0) as u8
                            ])
                        });
                    img.save(PathBuf::from(&dir).join(format!("{o}-{a}.png")))?;
                }
            }
        }
        let det = Detector::new(&model.views)?;
        let mut acc = vec![0.0f64; 2 + configs.len()];
        let mut n = 0usize;
        for (i, s) in data.images[oi].iter().enumerate() {
            if i % folds != fold {
                continue;
            }
            let a = s.annotation.as_ref().ok_or("no annotation")?;
            let img = load_image(&s.image)?;
            let pyr = FeaturePyramid::build(&img, &model.meta.pyramid, &model.meta.segmentation)?;
            let params = DetectParams {
                threshold: -1e9,
                max_detections: 1,
                ..model.meta.detection
            };
            let (dets, _) = det.detect(&pyr, &params)?;
            n += 1;
            let Some(d) = dets.first() else {
                for v in acc.iter_mut() {
                    *v += 1.0;
                }
                continue;
            };
            let (w, h) = (pyr.image_width, pyr.image_height);
            let raw = if std::env::var("ORACLE_CELLS").is_ok() {
                let im = sdhop::train::loss::IntegralMask::new(&a.visible);
                let mut t = Vec::new();
                sdhop::train::loss::cell_truth(&d.grid, &im, &mut t);
                raw_mask(&d.grid, &t, w, h)
            } else {
                raw_mask(&d.grid, &d.cells, w, h)
            };
            acc[0] += 1.0 - raw.iou(&a.visible);
            let snapped = refine_mask(&raw, &d.grid, &pyr.segmentation, &snap);
            acc[1] += 1.0 - snapped.iou(&a.visible);
            for (ci, c) in configs.iter().enumerate() {
                let m = match (parse(c), &shapes[d.viewpoint]) {
                    (Some(p), Some(shape)) => {
                        let t = Instant::now();
                        let m = if std::env::var("ORACLE_BOX").is_ok() {
                            sdhop::vision::refine::refine_pixels_at(
                                &raw,
                                &d.grid,
                                shape,
                                &pyr.segmentation,
                                &img,
                                &p,
                                a.bbox,
                            )
                        } else {
                            refine_pixels(&raw, &d.grid, shape, &pyr.segmentation, &img, &p)
                        };
                        refine_ms[ci] += t.elapsed().as_secs_f64() * 1e3;
                        m
                    }
                    _ => snapped.clone(),
                };
                acc[2 + ci] += 1.0 - m.iou(&a.visible);
                if let (0, Ok(dir)) = (ci, std::env::var("DUMP_DIR")) {
                    save_overlay(&dir, &img, &m, &a.visible, &raw, &d.grid, &s.id)?;
                }
                if ci == 0 && std::env::var("BREAKDOWN").is_ok() {
                    let occ_path = s.image.with_extension("occ.png");
                    let occ = image::open(&occ_path)?.to_luma8();
                    let (mut tp, mut fp_occ, mut fp_bg, mut fnn) = (0usize, 0usize, 0usize, 0usize);
                    let (mut fn_rawvis, mut fp_occ_raw) = (0usize, 0usize);
                    for y in 0..h {
                        for x in 0..w {
                            let p = m.get(x, y);
                            let g = a.visible.get(x, y);
                            let o = occ.get_pixel(x as u32, y as u32)[0] > 0;
                            match (p, g) {
                                (true, true) => tp += 1,
                                (true, false) if o => {
                                    fp_occ += 1;
                                    if raw.get(x, y) {
                                        fp_occ_raw += 1;
                                    }
                                }
                                (true, false) => fp_bg += 1,
                                (false, true) => {
                                    fnn += 1;
                                    if raw.get(x, y) {
                                        fn_rawvis += 1;
                                    }
                                }
                                _ => {}
                            }
                        }
                    }
                    let u = (tp + fp_occ + fp_bg + fnn).max(1) as f64;
                    // Localisation floor: the true visible mask carried
                    // from the true box into the detected one.
                    let (gx, gy, gw, gh) = a.bbox;
                    let (dx, dy, dw, dh) = d.bbox;
                    let mut moved = sdhop::vision::mask::Mask::new(w, h);
                    for y in 0..h {
                        for x in 0..w {
                            let sx = gx + (x as f64 + 0.5 - dx) * gw / dw;
                            let sy = gy + (y as f64 + 0.5 - dy) * gh / dh;
                            if sx >= 0.0 && sy >= 0.0 && (sx as usize) < w && (sy as usize) < h {
                                moved.set(x, y, a.visible.get(sx as usize, sy as usize));
                            }
                        }
                    }
                    println!(
                        "FLOOR {} {:.4} {:.2} {:.2} {:.2} {:.2} {:.2} {:.2} {:.2} {:.2}",
                        o,
                        1.0 - moved.iou(&a.visible),
                        gx,
                        gy,
                        gw,
                        gh,
                        dx,
                        dy,
                        dw,
                        dh
                    );
                    println!(
                        "BRK {} {} box_iou {:.3} fp_occ {:.4} fp_bg {:.4} fn {:.4} fn_rawvis {:.4} fp_occ_raw {:.4}",
                        o, s.id,
                        sdhop::vision::detect::box_iou(d.bbox, a.bbox),
                        fp_occ as f64 / u, fp_bg as f64 / u, fnn as f64 / u,
                        fn_rawvis as f64 / u, fp_occ_raw as f64 / u
                    );
                }
                if ci == 0 && std::env::var("PER_IMAGE").is_ok() {
                    println!(
                        "IMG {} box_iou {:.2} raw {:.3} refined {:.3}",
                        s.id,
                        sdhop::vision::detect::box_iou(d.bbox, a.bbox),
                        1.0 - raw.iou(&a.visible),
                        1.0 - m.iou(&a.visible)
                    );
                }
            }
            refine_n += 1;
        }
        let nf = n.max(1) as f64;
        table.push((o.clone(), acc.iter().map(|v| v / nf).collect()));
    }
    print_table(&configs, &table, &refine_ms, refine_n);
    Ok(())
}

/// The refined mask `m` over the photograph in grey: green where it and
/// the truth agree, blue where it alone is, red where the truth alone is,
/// the template's box yellow, the raw mask dotted white; saved under `dir`
/// as `ERROR-ID.png`.
fn save_overlay(
    dir: &str,
    img: &sdhop::vision::image::ColorImage,
    m: &sdhop::vision::mask::Mask,
    visible: &sdhop::vision::mask::Mask,
    raw: &sdhop::vision::mask::Mask,
    grid: &sdhop::vision::mask::CellGrid,
    id: &str,
) -> Result<(), Box<dyn std::error::Error>> {
    let (w, h) = (img.width(), img.height());
    let (x0, y0, x1, y1) = grid.pixel_range(w, h);
    let mut out = image::RgbImage::new(w as u32, h as u32);
    for y in 0..h {
        for x in 0..w {
            let g = (img.get(x, y, 0) + img.get(x, y, 1) + img.get(x, y, 2)) / 6.0;
            let g = g as u8;
            let (p, t, r) = (m.get(x, y), visible.get(x, y), raw.get(x, y));
            let mut c = match (p, t) {
                (true, true) => [g / 2, 128 + g / 2, g / 2],
                (true, false) => [g / 2, g / 2, 128 + g / 2],
                (false, true) => [128 + g / 2, g / 2, g / 2],
                _ => [g, g, g],
            };
            let edge = (x == x0 || x + 1 == x1) && (y0..y1).contains(&y)
                || (y == y0 || y + 1 == y1) && (x0..x1).contains(&x);
            if edge {
                c = [255, 255, 0];
            }
            if r && (x + y) % 6 == 0 {
                c = [255, 255, 255];
            }
            out.put_pixel(x as u32, y as u32, image::Rgb(c));
        }
    }
    let e = 1.0 - m.iou(visible);
    out.save(PathBuf::from(dir).join(format!("{e:.3}-{id}.png")))?;
    Ok(())
}

/// The errors per object and configuration, their means and the
/// refinement's time per detection.
fn print_table(
    configs: &[String],
    table: &[(String, Vec<f64>)],
    refine_ms: &[f64],
    refine_n: usize,
) {
    print!("{:10} {:>7} {:>7}", "object", "raw", "snap");
    for c in configs {
        print!(" {c:>14}");
    }
    println!();
    let mut mean = vec![0.0; 2 + configs.len()];
    for (o, v) in table {
        print!("{o:10}");
        for (i, x) in v.iter().enumerate() {
            mean[i] += x / table.len() as f64;
            print!(" {:>w$.4}", x, w = if i < 2 { 7 } else { 14 });
        }
        println!();
    }
    print!("{:10}", "mean");
    for (i, x) in mean.iter().enumerate() {
        print!(" {:>w$.4}", x, w = if i < 2 { 7 } else { 14 });
    }
    println!();
    print!("{:10} {:>7} {:>7}", "ms/det", "", "");
    for ms in refine_ms {
        print!(" {:>14.2}", ms / refine_n.max(1) as f64);
    }
    println!();
}
