//! Where exact pruning spends a model's scan, photograph by photograph:
//! locations, the candidates stage 1 leaves, those stage 2 prunes (or the
//! cut-off skips), the min-cuts finished, and the time of each part. It
//! showed why learned cells' models cut so many more locations than HOG's
//! (issue 63: their positive clique potentials).
//!
//! `cargo run --release --example stage_counts -- MODEL.safetensors [DIR] [N]`
//! (DIR: default ../shared/data/cmu_ko8/single/test/cup; N: default 5).

use sdhop::model::Model;
use sdhop::vision::detect::{DetectParams, Detector};
use sdhop::vision::pyramid::FeaturePyramid;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(model) = args.first() else {
        return Err("usage: stage_counts MODEL.safetensors [DIR] [N]".into());
    };
    let dir = args
        .get(1)
        .cloned()
        .unwrap_or_else(|| "../shared/data/cmu_ko8/single/test/cup".into());
    let n: usize = args.get(2).map_or(Ok(5), |v| v.parse())?;
    let m = Model::load(std::path::Path::new(model))?;
    let det = Detector::new(&m.views)?;
    let mut files: Vec<_> = std::fs::read_dir(&dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "jpg" || x == "png"))
        .collect();
    files.sort();
    for f in files.iter().take(n) {
        let img = sdhop::data::load_image(f)?;
        let pyr = FeaturePyramid::build(&img, &m.meta.pyramid, &m.meta.segmentation)?;
        let p = DetectParams {
            max_detections: 20,
            ..m.meta.detection
        };
        let (d, st) = det.detect(&pyr, &p)?;
        println!(
            "{}: {} detections, {} locations, {} past stage 1, {} pruned after, {} min-cuts; stage 1 {:.1} ms, the rest {:.1} ms",
            f.file_name().unwrap_or_default().to_string_lossy(),
            d.len(),
            st.locations,
            st.locations - st.pruned_stage1,
            st.pruned_stage2,
            st.min_cuts,
            st.responses_ms,
            st.mincut_ms
        );
    }
    Ok(())
}
