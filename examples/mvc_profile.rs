//! Profiles the loss-augmented search of training on CMU_KO8 images.
//!
//! `cargo run --release --example mvc_profile -- KO8_ROOT MODEL.safetensors OBJECT N`

use std::path::PathBuf;
use std::time::Instant;

use sdhop::data::load_image;
use sdhop::model::Model;
use sdhop::train::ko8::Ko8Data;
use sdhop::train::loss::{IntegralMask, LossKind, Truth, TruthLoss};
use sdhop::vision::detect::{box_iou, Detector};
use sdhop::vision::pyramid::FeaturePyramid;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let root = PathBuf::from(&args[1]);
    let model = Model::load(&PathBuf::from(&args[2]))?;
    let object = &args[3];
    let n: usize = args[4].parse()?;
    let data = Ko8Data::load(&root, &[])?;
    let oi = data
        .objects
        .iter()
        .position(|o| o == object)
        .ok_or("no such object")?;
    let det = Detector::new(&model.views)?;
    let mut samples: Vec<_> = data.images[oi].iter().take(n).collect();
    samples.extend(data.negatives.iter().take(n));
    let mut tot = [0.0f64; 6];
    for s in samples {
        let img = load_image(&s.image)?;
        let pyr = FeaturePyramid::build(&img, &model.meta.pyramid, &model.meta.segmentation)?;
        let vis;
        let truth = match &s.annotation {
            Some(a) => {
                let best = det
                    .locations(&pyr, 0.5)
                    .into_iter()
                    .map(|l| (box_iou(det.grid(&pyr, &l).pixel_box(), a.bbox), l))
                    .max_by(|x, y| x.0.total_cmp(&y.0))
                    .ok_or("no location")?;
                vis = IntegralMask::new(&a.visible);
                Some(Truth {
                    bbox: det.grid(&pyr, &best.1).pixel_box(),
                    visible: &vis,
                })
            }
            None => None,
        };
        let floor = if truth.is_some() { 1.0 } else { 0.0 };
        let pos = truth.is_some();
        let aug = TruthLoss {
            truth,
            kind: LossKind::SdHop,
            seg_weight: 1.0,
            views: None,
        };
        if std::env::var("BOUNDS").is_ok() && !pos {
            bound_gaps(&det, &pyr);
        }
        let t = Instant::now();
        let (best, found, stats) = det.most_violated(&pyr, &aug, floor, 0.5, None, None)?;
        let ms = t.elapsed().as_secs_f64() * 1e3;
        println!(
            "{} {:>5} total {:7.1} ms stage1 {:6.1} ms mincut-stage {:7.1} ms  locations {} cands {} cuts {} found {} value {:?}",
            s.id,
            if pos { "pos" } else { "neg" },
            ms,
            stats.responses_ms,
            stats.mincut_ms,
            stats.locations,
            stats.locations - stats.pruned_stage1,
            stats.min_cuts,
            found.len(),
            best.map(|b| b.value)
        );
        let k = if pos { 0 } else { 3 };
        tot[k] += ms;
        tot[k + 1] += stats.responses_ms;
        tot[k + 2] += stats.mincut_ms;
    }
    println!(
        "positives: total {:.0} ms stage1 {:.0} mincut {:.0}",
        tot[0], tot[1], tot[2]
    );
    println!(
        "negatives: total {:.0} ms stage1 {:.0} mincut {:.0}",
        tot[3], tot[4], tot[5]
    );
    Ok(())
}

/// Gaps between the bounds and the exact energy at every 7th location of
/// a negative image (called from `main` when BOUNDS=1).
pub fn bound_gaps(det: &Detector, pyr: &FeaturePyramid) {
    use sdhop::vision::maxflow::Graph;
    let mut g = Graph::new();
    let mut v = Vec::new();
    let (mut n, mut gap_a, mut gap_b, mut gap_hop) = (0usize, 0.0, 0.0, 0.0);
    for l in det.locations(pyr, 0.5).into_iter().step_by(7) {
        let (mut p, _, _) = det.problem_at(pyr, &l);
        let a = p.lower_bound();
        let b = p.lower_bound_without_pairwise();
        let e = p.solve(&mut g, &mut v);
        let k = p.w_hop.len() - 1;
        let hop_min = p.w_hop[0].min(p.w_hop[k]);
        let hop_part = p.n_cliques as f64 * hop_min;
        n += 1;
        gap_a += e - a;
        gap_b += e - b;
        gap_hop += hop_part;
    }
    let nf = n as f64;
    println!(
        "{n} locations: mean exact - lower_bound {:.4}, exact - without_pairwise {:.4}, mean clique term {:.4}",
        gap_a / nf,
        gap_b / nf,
        gap_hop / nf
    );
}
