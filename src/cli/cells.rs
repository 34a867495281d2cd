//! `sdhop-train cells`: fits the fixed projection of the learned cells
//! (`models/backbones/efficientnet_lite0_s8_cells.safetensors`, built into
//! the binary) to the backbone's features of representative photographs.

use super::*;
use crate::data::load_image;
use crate::vision::cells::{backbone_in_use, grid_features, CellProjection};
use crate::vision::hog::hog;
use std::collections::HashMap;

#[derive(clap::Args)]
pub(crate) struct CellsArgs {
    /// Folders of photographs (every PNG or JPEG in them, sorted by name;
    /// repeat the flag for several folders).
    #[arg(long, required = true)]
    pub(crate) images: Vec<PathBuf>,
    /// Photographs taken from each folder, at most (evenly spaced).
    #[arg(long, default_value_t = 40)]
    pub(crate) per_folder: usize,
    /// Scales each photograph is seen at (comma-separated), as pyramid
    /// levels see them.
    #[arg(long, value_delimiter = ',', default_value = "0.5,1,2")]
    pub(crate) scales: Vec<f64>,
    /// Where to write the projection.
    #[arg(
        long,
        default_value = "models/backbones/efficientnet_lite0_s8_cells.safetensors"
    )]
    pub(crate) out: PathBuf,
}

pub(crate) fn run_cells(args: &CellsArgs) -> Result<(), Failure> {
    use rayon::prelude::*;
    if args.per_folder == 0
        || args
            .scales
            .iter()
            .any(|s| !(s.is_finite() && *s > 0.0 && *s <= 4.0))
    {
        return Err(Failure::input(
            "--per-folder must be >= 1 and every --scales in (0, 4]",
        ));
    }
    let backbone = &backbone_in_use().map_err(Failure::input)?;
    let mut files = Vec::new();
    for dir in &args.images {
        let all = image_files(dir)?;
        let k = args.per_folder.min(all.len());
        files.extend((0..k).map(|j| all[j * all.len() / k].clone()));
    }
    if files.is_empty() {
        return Err(Failure::input("no photographs in --images"));
    }
    let pb = progress_bar(files.len() as u64, "backbone features");
    let per: Result<Vec<_>, Failure> = files
        .par_iter()
        .map(|f| {
            let img = load_image(f).map_err(Failure::input)?;
            let mut maps = Vec::new();
            let mut hog_sq = (0.0f64, 0usize);
            for &s in &args.scales {
                let w = ((img.width() as f64 * s).round() as usize).max(16);
                let h = ((img.height() as f64 * s).round() as usize).max(16);
                let level = img.resize_smooth(w, h).map_err(Failure::input)?;
                let map = grid_features(backbone, &level, crate::vision::Deadline::NONE)
                    .map_err(Failure::input)?;
                let hm = hog(&level);
                for y in 0..hm.height() {
                    for x in 0..hm.width() {
                        hog_sq.0 += hm.cell(x, y).iter().map(|&v| f64::from(v * v)).sum::<f64>();
                        hog_sq.1 += 1;
                    }
                }
                maps.push(map);
            }
            pb.inc(1);
            Ok((maps, hog_sq))
        })
        .collect();
    pb.finish_and_clear();
    let per = per?;
    let (sq, n) = per
        .iter()
        .fold((0.0, 0usize), |a, (_, h)| (a.0 + h.0, a.1 + h.1));
    let target = sq / n.max(1) as f64;
    let maps: Vec<_> = per.into_iter().flat_map(|(m, _)| m).collect();
    let p = CellProjection::fit(&maps, target).map_err(Failure::input)?;
    let mut meta = HashMap::new();
    meta.insert("kind".into(), "sdhop-cell-projection".into());
    meta.insert("backbone".into(), backbone.name.clone());
    meta.insert(
        "fitted_on".into(),
        serde_json::json!({
            "folders": args.images.iter().map(|d| d.display().to_string()).collect::<Vec<_>>(),
            "photographs": files.len(),
            "scales": args.scales,
            "cells": maps.iter().map(|m| m.width * m.height).sum::<usize>(),
            "hog_mean_squared_norm": target,
        })
        .to_string(),
    );
    let bytes = p.to_bytes(&meta).map_err(Failure::input)?;
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| Failure::io(format!("{}: {e}", dir.display())))?;
    }
    std::fs::write(&args.out, bytes)
        .map_err(|e| Failure::io(format!("{}: {e}", args.out.display())))?;
    println!(
        "{} photographs at scales {:?}: {} channels -> {} directions keep {:.1}% of the standardised variance; cells scaled to HOG's mean squared norm {:.4}; fingerprint {} -> {} (rebuild to use it)",
        files.len(),
        args.scales,
        p.channels,
        crate::vision::hog::HOG_DIM,
        100.0 * p.variance_kept,
        target,
        p.fingerprint(),
        args.out.display()
    );
    Ok(())
}
