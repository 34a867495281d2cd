//! Where does the segmentation error come from? For the held-out images of
//! one cross-validation fold, compares the model's top detection with
//! oracles: the same box with perfect cell labels, the best-fitting template
//! box with the model's labels and with perfect labels.
//!
//! `cargo run --release --example seg_diag -- KO8_ROOT MODELS_DIR FOLD FOLDS`

#![allow(clippy::needless_range_loop)]

use std::path::PathBuf;

use sdhop::data::{ko8_visible_mask, load_image, load_mask, Annotation};
use sdhop::model::Model;
use sdhop::train::ko8::Ko8Data;
use sdhop::train::loss::{cell_truth, IntegralMask};
use sdhop::vision::detect::{box_iou, DetectParams, Detector};
use sdhop::vision::mask::{raw_mask, CellGrid, Mask};
use sdhop::vision::maxflow::Graph;
use sdhop::vision::pyramid::FeaturePyramid;
use sdhop::vision::refine::{refine_mask, RefineParams};
use sdhop::vision::segment::{segment, SegmentParams};

fn err(m: &Mask, truth: &Mask) -> f64 {
    1.0 - m.iou(truth)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let root = PathBuf::from(&args[1]);
    let models_dir = PathBuf::from(&args[2]);
    let fold: usize = args[3].parse()?;
    let folds: usize = args[4].parse()?;
    let only: Option<&str> = args.get(5).map(|s| s.as_str());
    let data = Ko8Data::load(&root, &[])?;
    let refine = RefineParams::default();
    let sp = |k: f32, min_size: usize, downsample: usize| SegmentParams {
        sigma: 0.8,
        k,
        min_size,
        downsample,
    };
    let variants = [
        (sp(300.0, 50, 2), 0.8, 0.2),
        (sp(300.0, 50, 2), 0.5, 0.5),
        (sp(100.0, 20, 1), 0.5, 0.5),
        (sp(50.0, 10, 1), 0.5, 0.5),
        (sp(150.0, 30, 1), 0.5, 0.5),
    ];
    print_header();
    for (oi, o) in data.objects.iter().enumerate() {
        if only.is_some_and(|x| x != o) {
            continue;
        }
        let model = Model::load(&models_dir.join(format!("{o}.safetensors")))?;
        let det = Detector::new(&model.views)?;
        let mut acc = [0.0f64; 8];
        let mut conf = [0usize; 4];
        let mut n = 0;
        let mut sil_acc = [0.0f64; 2];
        let mut best_iou = 0.0;
        let mut split = [0usize; 6];
        let train_mask = load_mask(&root.join(format!("single/train/{o}/{o}_mask.png")))?;
        let mut ref_acc = vec![[0.0f64; 2]; variants.len()];
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
            let Some(d) = dets.first() else { continue };
            n += 1;
            let vis = IntegralMask::new(&a.visible);
            let (w, h) = (pyr.image_width, pyr.image_height);
            let truth = &a.visible;
            acc[0] += box_iou(d.bbox, a.bbox);
            let raw = raw_mask(&d.grid, &d.cells, w, h);
            acc[1] += err(&raw, truth);
            acc[2] += err(
                &refine_mask(&raw, &d.grid, &pyr.segmentation, &refine),
                truth,
            );
            let mut tc = Vec::new();
            cell_truth(&d.grid, &vis, &mut tc);
            let oraw = raw_mask(&d.grid, &tc, w, h);
            acc[3] += err(&oraw, truth);
            acc[4] += err(
                &refine_mask(&oraw, &d.grid, &pyr.segmentation, &refine),
                truth,
            );
            for (t, p) in tc.iter().zip(&d.cells) {
                conf[match (*t, *p) {
                    (true, true) => 0,
                    (true, false) => 1,
                    (false, true) => 2,
                    (false, false) => 3,
                }] += 1;
            }
            // Silhouette refinement with the training mask as the shape.
            let sil = ko8_visible_mask(
                &train_mask,
                (
                    d.bbox.0 + d.bbox.2 / 2.0,
                    d.bbox.1 + d.bbox.3 / 2.0,
                    d.bbox.2,
                    d.bbox.3,
                ),
                &Mask::new(w, h),
            )
            .ok_or("empty")?;
            sil_acc[0] += err(&silhouette(&d.grid, &tc, &sil), truth);
            sil_acc[1] += err(&silhouette(&d.grid, &d.cells, &sil), truth);
            // Refinement variants: (segmentation, fill, clear).
            for (vi, (sp, fill, clear)) in variants.iter().enumerate() {
                let seg = segment(&img, sp)?;
                let rp = RefineParams {
                    fill: *fill,
                    clear: *clear,
                    ..RefineParams::default()
                };
                ref_acc[vi][0] += err(&refine_mask(&oraw, &d.grid, &seg, &rp), truth);
                ref_acc[vi][1] += err(&refine_mask(&raw, &d.grid, &seg, &rp), truth);
            }
            // Best template location for the truth box.
            if let Some(t) = at_truth_box(&det, &pyr, a, &train_mask, &mut split)? {
                best_iou += t[0];
                acc[5] += t[1];
                acc[6] += t[2];
            }
            // Prior-only labels at the detected box (the mask the model
            // expects without looking at the cells): w_prior > 0 means
            // occluded costs, so visible.
            let pr: Vec<bool> = model.views[d.viewpoint]
                .w_prior
                .iter()
                .map(|&r| r > 0.0)
                .collect();
            acc[7] += err(&raw_mask(&d.grid, &pr, w, h), truth);
        }
        let nf = n.max(1) as f64;
        println!(
            "{:10} {:5} {:6.3} {:7.4} {:7.4} {:7.4} {:7.4} {:7.4} {:7.4} {:7.4} {:6} {:6} {:6} {:6}",
            o,
            n,
            acc[0] / nf,
            acc[1] / nf,
            acc[2] / nf,
            acc[3] / nf,
            acc[4] / nf,
            acc[5] / nf,
            acc[6] / nf,
            acc[7] / nf,
            conf[0],
            conf[1],
            conf[2],
            conf[3]
        );
        let refs: Vec<String> = ref_acc
            .iter()
            .map(|r| format!("{:.4}/{:.4}", r[0] / nf, r[1] / nf))
            .collect();
        println!(
            "  best template IoU {:.3} silhouette (oracle/model): {:.4}/{:.4}",
            best_iou / nf,
            sil_acc[0] / nf,
            sil_acc[1] / nf
        );
        println!(
            "  at truth box: bg->vis {} bg->occ {} | vis->occ {} vis->vis {} | occ->vis {} occ->occ {}",
            split[0], split[1], split[2], split[4], split[3], split[5]
        );
        println!("  refine variants (oracle/model): {}", refs.join(" "));
    }
    Ok(())
}

/// Cells mostly covered by the silhouette keep their label; the others take
/// the label of the nearest mostly-covered cell; the mask is the silhouette
/// where the effective label is visible.
fn silhouette(g: &CellGrid, labels: &[bool], sil: &Mask) -> Mask {
    let n = g.rows * g.cols;
    let mut cov = vec![[0u32; 2]; n];
    let (x0, y0, x1, y1) = g.pixel_range(sil.width, sil.height);
    for y in y0..y1 {
        for x in x0..x1 {
            if let Some(i) = g.cell_of(x, y) {
                cov[i][1] += 1;
                cov[i][0] += u32::from(sil.get(x, y));
            }
        }
    }
    let core: Vec<bool> = cov.iter().map(|c| c[1] > 0 && 2 * c[0] >= c[1]).collect();
    let mut eff = labels.to_vec();
    for i in 0..n {
        if core[i] {
            continue;
        }
        let (r, c) = ((i / g.cols) as i64, (i % g.cols) as i64);
        let mut best: Option<(i64, usize)> = None;
        for j in 0..n {
            if !core[j] {
                continue;
            }
            let (rj, cj) = ((j / g.cols) as i64, (j % g.cols) as i64);
            let dist = (rj - r).abs() + (cj - c).abs();
            if best.is_none_or(|b| dist < b.0) {
                best = Some((dist, j));
            }
        }
        if let Some((_, j)) = best {
            eff[i] = labels[j];
        }
    }
    let mut m = Mask::new(sil.width, sil.height);
    for y in y0..y1 {
        for x in x0..x1 {
            if let Some(i) = g.cell_of(x, y) {
                if eff[i] && sil.get(x, y) {
                    m.set(x, y, true);
                }
            }
        }
    }
    m
}

/// The model's labels at the template location that best covers the
/// truth box: that location's box IoU, the model's and the truth cells'
/// errors there; `split` counts the model's cell errors by kind.
fn at_truth_box(
    det: &Detector,
    pyr: &FeaturePyramid,
    a: &Annotation,
    train_mask: &Mask,
    split: &mut [usize; 6],
) -> Result<Option<[f64; 3]>, Box<dyn std::error::Error>> {
    let truth = &a.visible;
    let vis = IntegralMask::new(truth);
    let (w, h) = (pyr.image_width, pyr.image_height);
    let best = det
        .locations(pyr, 0.5)
        .into_iter()
        .map(|l| (box_iou(det.grid(pyr, &l).pixel_box(), a.bbox), l))
        .max_by(|x, y| x.0.total_cmp(&y.0));
    let Some((biou, l)) = best else {
        return Ok(None);
    };
    let g: CellGrid = det.grid(pyr, &l);
    let (mut p, _, _) = det.problem_at(pyr, &l);
    let mut graph = Graph::new();
    let mut v = Vec::new();
    p.solve(&mut graph, &mut v);
    let model_err = err(&raw_mask(&g, &v, w, h), truth);
    let mut tg = Vec::new();
    cell_truth(&g, &vis, &mut tg);
    // Split the model's errors at the truth box by whether the cell is
    // object (full mask, occluded or not) or background.
    let full = ko8_visible_mask(
        train_mask,
        (
            a.bbox.0 + a.bbox.2 / 2.0,
            a.bbox.1 + a.bbox.3 / 2.0,
            a.bbox.2,
            a.bbox.3,
        ),
        &Mask::new(w, h),
    )
    .ok_or("empty")?;
    let mut tf = Vec::new();
    cell_truth(&g, &IntegralMask::new(&full), &mut tf);
    for i in 0..tg.len() {
        let k = match (tf[i], tg[i], v[i]) {
            (false, _, true) => 0,    // background called visible
            (false, _, false) => 1,   // background called occluded
            (true, true, false) => 2, // visible object called occluded
            (true, false, true) => 3, // occluded object called visible
            (true, true, true) => 4,
            (true, false, false) => 5,
        };
        split[k] += 1;
    }
    Ok(Some([
        biou,
        model_err,
        err(&raw_mask(&g, &tg, w, h), truth),
    ]))
}

/// The table's header.
fn print_header() {
    println!(
        "{:10} {:>5} {:>6} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>6} {:>6} {:>6} {:>6}",
        "object",
        "n",
        "boxIoU",
        "raw",
        "ref",
        "orc@det",
        "orcRef",
        "mdl@gt",
        "orc@gt",
        "full@d",
        "TP",
        "FN",
        "FP",
        "TN"
    );
}
