//! `sdhop-train demo`: a synthetic occluded scene, a hand-built model of its
//! object, the detection and its accuracy against the exact truth.

use super::*;

#[derive(clap::Args)]
pub(crate) struct DemoArgs {
    /// Folder for the scene, the model, the JSON and the overlay.
    #[arg(long, default_value = "out/demo")]
    pub(crate) out: PathBuf,
    /// Scene seed.
    #[arg(long, default_value_t = 7)]
    pub(crate) seed: u64,
    #[arg(long, default_value_t = 640)]
    pub(crate) width: usize,
    #[arg(long, default_value_t = 480)]
    pub(crate) height: usize,
}

pub(crate) fn run_demo(args: &DemoArgs) -> Result<(), Failure> {
    std::fs::create_dir_all(&args.out)
        .map_err(|e| Failure::io(format!("{}: {e}", args.out.display())))?;
    let obj = SynthObject {
        cols: 18,
        rows: 16,
        seed: 3,
    };
    let params = SceneParams {
        width: args.width,
        height: args.height,
        seed: args.seed,
        ..SceneParams::default()
    };
    let sc = scene(&obj, &params).map_err(Failure::input)?;
    let model =
        hand_model(&obj, "synthetic", true, &HandModelParams::default()).map_err(Failure::input)?;
    let model_path = args.out.join("synthetic.safetensors");
    model.save(&model_path).map_err(Failure::io)?;
    let scene_path = args.out.join("scene.png");
    sc.image
        .to_rgb8()
        .save(&scene_path)
        .map_err(|e| Failure::io(format!("{}: {e}", scene_path.display())))?;
    let img = read_image(&scene_path, DEFAULT_MAX_PIXELS)?;
    let opts = DetectOptions {
        max_detections: Some(1),
        masks: MaskMode::Both,
        ..DetectOptions::default()
    };
    let resp = detect_image(&img, &[&model], &opts).map_err(Failure::input)?;
    write_json(&resp, Some(&args.out.join("detections.json")))?;
    let overlay_path = args.out.join("overlay.png");
    overlay(&img, &resp)
        .save(&overlay_path)
        .map_err(|e| Failure::io(format!("{}: {e}", overlay_path.display())))?;
    let (tx, ty, tw, th) = sc.truth_box;
    println!(
        "scene      {} ({}x{}), object box x={tx:.1} y={ty:.1} w={tw:.1} h={th:.1}, {:.0}% hidden",
        scene_path.display(),
        args.width,
        args.height,
        100.0 * (1.0 - sc.visible.area() as f64 / sc.object.area() as f64)
    );
    match resp.detections.first() {
        None => println!("detection  none above the threshold"),
        Some(d) => {
            let b = (d.bbox.x, d.bbox.y, d.bbox.width, d.bbox.height);
            let miou = |r: &Option<crate::vision::mask::Rle>| {
                r.as_ref()
                    .and_then(Mask::from_rle)
                    .map_or(0.0, |m| m.iou(&sc.visible))
            };
            println!(
                "detection  score {:.3}, box x={:.1} y={:.1} w={:.1} h={:.1}, box IoU {:.3}",
                d.score,
                b.0,
                b.1,
                b.2,
                b.3,
                box_iou(b, sc.truth_box)
            );
            println!(
                "mask IoU   raw {:.3}, refined {:.3} (visible fraction {:.2})",
                miou(&d.raw_mask),
                miou(&d.mask),
                d.visible_fraction
            );
        }
    }
    let t = &resp.timing_ms;
    println!("timing ms  total {:.1}: features {:.1}, segmentation {:.1}, cell segments {:.1}, responses {:.1}, min-cuts {:.1}, masks {:.1}",
        t.total, t.features, t.segmentation, t.cell_segments, t.responses, t.mincut, t.masks);
    println!(
        "pruning    {} locations, {} min-cuts ({:.2}% pruned)",
        t.locations,
        t.min_cuts,
        100.0 * t.pruned_fraction
    );
    println!(
        "wrote      {}, {}, {}",
        model_path.display(),
        args.out.join("detections.json").display(),
        overlay_path.display()
    );
    Ok(())
}
