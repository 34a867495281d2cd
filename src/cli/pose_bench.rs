//! `sdhop-train pose-bench`: the occlusion pose benchmark (IRLS, OR-IRLS
//! with the exact and with the SD-HOP mask) on held-out backgrounds.

use super::*;

#[derive(clap::Args)]
pub(crate) struct PoseBenchArgs {
    #[command(flatten)]
    pub(crate) bg: PoseBackgrounds,
    /// Scenes per object and condition (unoccluded; 20-60% hidden).
    #[arg(long, default_value_t = 100)]
    pub(crate) scenes: usize,
    /// Detector models of the objects (trained on `pose-data`); without
    /// them the SD-HOP mask is left out.
    #[arg(long, default_value = "out/pose-data/models")]
    pub(crate) models_dir: PathBuf,
    /// Write every outcome and the summaries here as JSON.
    #[arg(long)]
    pub(crate) report: Option<PathBuf>,
}

pub(crate) fn run_pose_bench(args: &PoseBenchArgs) -> Result<(), Failure> {
    use crate::eval::pose::{evaluate, scene, summarize, BenchSettings, Method};
    use crate::pose::EdgeModel;
    let (objects, _, test) = args.bg.load()?;
    let settings = BenchSettings::default();
    let detectors: Vec<Model> = if args.models_dir.is_dir() {
        load_model_dir(&args.models_dir)?
    } else {
        eprintln!(
            "{}: no models, so no SD-HOP mask (train them: see docs/training.md)",
            args.models_dir.display()
        );
        Vec::new()
    };
    let backgrounds: Vec<ColorImage> = test
        .iter()
        .map(|p| background_image(p))
        .collect::<Result<_, _>>()?;
    let mut report = Vec::new();
    println!(
        "| object | hidden | method | X mm | Y mm | Z mm | roll ° | pitch ° | yaw ° | angle ° mean ± se / median | distance mm mean ± se / median | success | failed | ms |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for (ci, object) in objects.iter().enumerate() {
        let edges = EdgeModel::new(
            &object.mesh,
            crate::pose::IrlsParams::default().crease_degrees,
        );
        let detector = detectors.iter().find(|m| m.meta.name == object.name);
        for (label, occlusion) in [("0%", (0.0, 0.0)), ("20-60%", (0.2, 0.6))] {
            let mut outcomes = Vec::new();
            let mut hidden = 0.0;
            for i in 0..args.scenes {
                let seed = 7_000_000 * (ci as u64 + 1) + i as u64;
                let bg = &backgrounds[i % backgrounds.len()];
                let s = scene(object, bg, occlusion, &settings, seed).map_err(Failure::input)?;
                hidden += s.scene.occluded_fraction / args.scenes as f64;
                outcomes.extend(evaluate(
                    &edges,
                    &s,
                    detector,
                    &settings,
                    &crate::pose::IrlsParams::default(),
                ));
            }
            let mut summaries = Vec::new();
            for method in [Method::Irls, Method::OrIrlsExact, Method::OrIrlsSdhop] {
                let Some(s) = summarize(&outcomes, method) else {
                    continue;
                };
                let e = s.mean_errors;
                println!(
                    "| {} | {label} (mean {:.0}%) | {:?} | {:.1} | {:.1} | {:.1} | {:.2} | {:.2} | {:.2} | {:.2} ± {:.2} / {:.2} | {:.1} ± {:.1} / {:.1} | {:.0}% | {} | {:.0} |",
                    object.name,
                    100.0 * hidden,
                    method,
                    e[0], e[1], e[2], e[3], e[4], e[5],
                    s.mean_angle_degrees,
                    s.se_angle_degrees,
                    s.median_angle_degrees,
                    s.mean_distance_mm,
                    s.se_distance_mm,
                    s.median_distance_mm,
                    100.0 * s.success_rate,
                    s.failed,
                    s.mean_total_ms
                );
                summaries.push(s);
            }
            report.push(serde_json::json!({
                "object": object.name, "occlusion": occlusion, "mean_hidden": hidden,
                "summaries": summaries, "outcomes": outcomes,
            }));
        }
    }
    if let Some(p) = &args.report {
        let doc = serde_json::json!({"settings": settings, "results": report});
        std::fs::write(p, serde_json::to_string_pretty(&doc).map_err(Failure::io)?)
            .map_err(|e| Failure::io(format!("{}: {e}", p.display())))?;
    }
    Ok(())
}
