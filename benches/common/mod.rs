//! Helpers shared by the bench binaries.

/// The median of `v` (sorted in place); NaN when empty.
pub fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

/// The value after `--name` on the command line, or `default`.
pub fn arg<T: std::str::FromStr>(name: &str, default: T) -> T {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// `n` synthetic 640x480 scenes of `obj`, seeds 0 to n - 1.
#[allow(dead_code)] // not every bench draws scenes
pub fn vga_scenes(obj: &sdhop::synth::SynthObject, n: u64) -> Vec<sdhop::synth::Scene> {
    (0..n)
        .map(|seed| {
            sdhop::synth::scene(
                obj,
                &sdhop::synth::SceneParams {
                    width: 640,
                    height: 480,
                    seed,
                    ..sdhop::synth::SceneParams::default()
                },
            )
            .expect("scene")
        })
        .collect()
}

/// A detection's wall time (ms) and its stage times, in the order the
/// benches print them: total, features, segmentation, cell segments,
/// responses and bounds, min-cuts, masks, then the min-cut count.
#[allow(dead_code)] // not every bench detects
pub fn stage_times(wall_ms: f64, tm: &sdhop::pipeline::Timing) -> [f64; 8] {
    [
        wall_ms,
        tm.features,
        tm.segmentation,
        tm.cell_segments,
        tm.responses,
        tm.mincut,
        tm.masks,
        tm.min_cuts as f64,
    ]
}
