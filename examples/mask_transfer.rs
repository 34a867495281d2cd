//! Learned-cell detections segmented by HOG's cells (issue 63, "both
//! kinds per object"): on the held-out photographs of each fold of two
//! cross-validations with the same folds (`cv --save-models`, one with
//! learned cells, one with HOG), each learned model's top detection is
//! segmented three ways: by its own cells; by the HOG model's cells at the
//! HOG location whose box best overlaps it (its CRF solved there, no
//! pruning); by the HOG model's cells at its best location whose box
//! overlaps the learned one enough (`Detector::best_near`, `MIN_IOU`,
//! default 0.5); by the learned cells at that location; and, for
//! comparison, the HOG model's own top detection by its own cells. Each mask refined by its model's pixel refinement; refined
//! and raw segerr (1 - IoU with the visible truth), mean per object.
//!
//! `cargo run --release --example mask_transfer -- KO8_ROOT CNN_DIR HOG_DIR FOLDS`
//! (`OBJECTS=cup,...` for a cross-validation of some objects).

use std::path::PathBuf;

use sdhop::data::load_image;
use sdhop::model::Model;
use sdhop::train::ko8::{fold_dir, Ko8Data};
use sdhop::vision::detect::{detection_masks, DetectParams, Detection, Detector, Location};
use sdhop::vision::mask::Mask;
use sdhop::vision::maxflow::Graph;
use sdhop::vision::pyramid::FeaturePyramid;

type Box4 = (f64, f64, f64, f64);

fn iou(a: Box4, b: Box4) -> f64 {
    let x0 = a.0.max(b.0);
    let y0 = a.1.max(b.1);
    let x1 = (a.0 + a.2).min(b.0 + b.2);
    let y1 = (a.1 + a.3).min(b.1 + b.3);
    let i = (x1 - x0).max(0.0) * (y1 - y0).max(0.0);
    let u = a.2 * a.3 + b.2 * b.3 - i;
    if u > 0.0 {
        i / u
    } else {
        0.0
    }
}

/// The locations (any level and viewpoint) within `radius` cells of the
/// one centred on `target`, each with its box's overlap with `target`.
fn around(
    det: &Detector,
    n_views: usize,
    pyr: &FeaturePyramid,
    target: Box4,
    radius: isize,
) -> Vec<(Location, f64)> {
    let mut out = Vec::new();
    for level in 0..pyr.levels.len() {
        for view in 0..n_views {
            let origin = Location {
                level,
                view,
                y: 0,
                x: 0,
            };
            let g = det.grid(pyr, &origin);
            let (_, _, w, h) = g.pixel_box();
            let (sx, sy) = (
                g.cell_size as f64 / g.scale_x,
                g.cell_size as f64 / g.scale_y,
            );
            let cx = ((target.0 + 0.5 * target.2 - 0.5 * w) / sx).round() as isize;
            let cy = ((target.1 + 0.5 * target.3 - 0.5 * h) / sy).round() as isize;
            for dy in -radius..=radius {
                for dx in -radius..=radius {
                    let loc = Location {
                        level,
                        view,
                        y: cy + dy,
                        x: cx + dx,
                    };
                    out.push((loc, iou(det.grid(pyr, &loc).pixel_box(), target)));
                }
            }
        }
    }
    out
}

/// The HOG location whose box best overlaps `target`, and that overlap.
fn best_location(
    det: &Detector,
    n_views: usize,
    pyr: &FeaturePyramid,
    target: Box4,
) -> Option<(Location, f64)> {
    around(det, n_views, pyr, target, 1)
        .into_iter()
        .max_by(|a, b| a.1.total_cmp(&b.1))
}

/// The HOG model's cells at `loc`, its CRF solved without pruning.
fn solved_at(det: &Detector, pyr: &FeaturePyramid, loc: &Location) -> Detection {
    let (mut problem, _, truncated) = det.problem_at(pyr, loc);
    let mut cells = Vec::new();
    let energy = problem.solve(&mut Graph::new(), &mut cells);
    let grid = det.grid(pyr, loc);
    let visible = cells.iter().filter(|&&v| v).count() as f64 / cells.len().max(1) as f64;
    Detection {
        viewpoint: loc.view,
        level: loc.level,
        score: -energy,
        bbox: grid.pixel_box(),
        grid,
        cells,
        truncated: truncated > 0,
        visible_fraction: visible,
    }
}

fn top(m: &Model, det: &Detector, pyr: &FeaturePyramid) -> Result<Option<Detection>, String> {
    let params = DetectParams {
        threshold: -1e9,
        max_detections: 1,
        ..m.meta.detection
    };
    let (dets, _) = det.detect(pyr, &params).map_err(|e| e.to_string())?;
    Ok(dets.into_iter().next())
}

fn masks(m: &Model, d: &Detection, pyr: &FeaturePyramid) -> (Mask, Mask) {
    let shape = m.shapes.get(d.viewpoint).and_then(Option::as_ref);
    detection_masks(d, pyr, &m.meta.detection.refine, shape)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let [_, root, cnn_dir, hog_dir, folds] = &args[..] else {
        return Err("usage: mask_transfer KO8_ROOT CNN_DIR HOG_DIR FOLDS".into());
    };
    let (root, cnn_dir, hog_dir) = (
        PathBuf::from(root),
        PathBuf::from(cnn_dir),
        PathBuf::from(hog_dir),
    );
    let folds: usize = folds.parse()?;
    let objects: Vec<String> = std::env::var("OBJECTS")
        .map(|v| v.split(',').map(str::to_string).collect())
        .unwrap_or_default();
    let data = Ko8Data::load(&root, &objects)?;
    println!("object      n  learned refined/raw  HOG-at-learned refined/raw  HOG own refined/raw  box IoU  found learned/HOG  HOG-best-near refined/raw  learned-at-HOG-near refined/raw");
    let min_iou: f64 = std::env::var("MIN_IOU")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0.5);
    let mut means = [0.0f64; 10];
    for (oi, o) in data.objects.iter().enumerate() {
        // Refined, raw: learned own, HOG at the learned box, HOG own.
        let mut acc = [0.0f64; 10];
        let (mut n, mut overlap, mut found_c, mut found_h) = (0usize, 0.0, 0usize, 0usize);
        for fold in 0..folds {
            let load =
                |d: &PathBuf| Model::load(&fold_dir(d, fold).join(format!("{o}.safetensors")));
            let (cnn, hog) = (load(&cnn_dir)?, load(&hog_dir)?);
            let (dc, dh) = (Detector::new(&cnn.views)?, Detector::new(&hog.views)?);
            for (i, s) in data.images[oi].iter().enumerate() {
                if i % folds != fold {
                    continue;
                }
                let a = s.annotation.as_ref().ok_or("no annotation")?;
                let img = load_image(&s.image)?;
                let pc = FeaturePyramid::build(&img, &cnn.meta.pyramid, &cnn.meta.segmentation)?;
                let ph = FeaturePyramid::build(&img, &hog.meta.pyramid, &hog.meta.segmentation)?;
                n += 1;
                let err = |m: &Mask| 1.0 - m.iou(&a.visible);
                let (Some(c), Some(h)) = (top(&cnn, &dc, &pc)?, top(&hog, &dh, &ph)?) else {
                    acc.iter_mut().for_each(|v| *v += 1.0);
                    continue;
                };
                found_c += usize::from(iou(c.bbox, a.bbox) >= 0.5);
                found_h += usize::from(iou(h.bbox, a.bbox) >= 0.5);
                let (raw, refined) = masks(&cnn, &c, &pc);
                acc[0] += err(&refined);
                acc[1] += err(&raw);
                let (loc, o) =
                    best_location(&dh, hog.views.len(), &ph, c.bbox).ok_or("no HOG location")?;
                overlap += o;
                let t = solved_at(&dh, &ph, &loc);
                let (raw, refined) = masks(&hog, &t, &ph);
                acc[2] += err(&refined);
                acc[3] += err(&raw);
                let (raw, refined) = masks(&hog, &h, &ph);
                acc[4] += err(&refined);
                acc[5] += err(&raw);
                let near = dh
                    .best_near(&ph, c.bbox, min_iou, hog.meta.detection.max_truncation)
                    .unwrap_or(t);
                let (raw, refined) = masks(&hog, &near, &ph);
                acc[6] += err(&refined);
                acc[7] += err(&raw);
                // The learned cells at that HOG location (the two grids
                // are the same where the pyramids' levels are).
                let loc = Location {
                    level: near.level,
                    view: near.viewpoint.min(cnn.views.len() - 1),
                    y: near.grid.cell_y,
                    x: near.grid.cell_x,
                };
                let (raw, refined) = masks(&cnn, &solved_at(&dc, &pc, &loc), &pc);
                acc[8] += err(&refined);
                acc[9] += err(&raw);
            }
        }
        let k = n.max(1) as f64;
        println!(
            "{o:<10} {n:>3}  {:.4}/{:.4}  {:.4}/{:.4}  {:.4}/{:.4}  {:.3}  {found_c}/{found_h}  {:.4}/{:.4}  {:.4}/{:.4}",
            acc[0] / k,
            acc[1] / k,
            acc[2] / k,
            acc[3] / k,
            acc[4] / k,
            acc[5] / k,
            overlap / k,
            acc[6] / k,
            acc[7] / k,
            acc[8] / k,
            acc[9] / k
        );
        for (m, v) in means.iter_mut().zip(acc) {
            *m += v / k / data.objects.len() as f64;
        }
    }
    println!(
        "mean            {:.4}/{:.4}  {:.4}/{:.4}  {:.4}/{:.4}  (near, IoU >= {min_iou}) {:.4}/{:.4}  {:.4}/{:.4}",
        means[0],
        means[1],
        means[2],
        means[3],
        means[4],
        means[5],
        means[6],
        means[7],
        means[8],
        means[9]
    );
    Ok(())
}
