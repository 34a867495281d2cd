//! Per-scene accuracy of the hand-built model on synthetic scenes.
use sdhop::pipeline::{detect_image, DetectOptions, MaskMode};
use sdhop::synth::{hand_model, scene, HandModelParams, SceneParams, SynthObject};
use sdhop::vision::detect::box_iou;
use sdhop::vision::mask::Mask;

fn main() {
    let args: Vec<f64> = std::env::args()
        .skip(1)
        .map(|a| a.parse().unwrap())
        .collect();
    let obj = SynthObject {
        cols: 12,
        rows: 10,
        seed: 11,
    };
    let mut hp = HandModelParams::default();
    if args.len() >= 3 {
        hp.alpha = args[0] as f32;
        hp.pairwise = args[1] as f32;
        hp.hop = args[2] as f32;
    }
    let model = hand_model(&obj, "s", true, &hp).unwrap();
    let opts = DetectOptions {
        max_detections: Some(1),
        masks: MaskMode::Both,
        ..DetectOptions::default()
    };
    let (mut tb, mut tm, mut tr) = (0.0, 0.0, 0.0);
    let n = 24;
    for seed in 0..n {
        let s = scene(
            &obj,
            &SceneParams {
                seed,
                ..SceneParams::default()
            },
        )
        .unwrap();
        let r = detect_image(&s.image, &[&model], &opts).unwrap();
        let (b, m, raw, sc, lvl) = match r.detections.first() {
            Some(d) => (
                box_iou(
                    (d.bbox.x, d.bbox.y, d.bbox.width, d.bbox.height),
                    s.truth_box,
                ),
                Mask::from_rle(d.mask.as_ref().unwrap())
                    .unwrap()
                    .iou(&s.visible),
                Mask::from_rle(d.raw_mask.as_ref().unwrap())
                    .unwrap()
                    .iou(&s.visible),
                d.score,
                d.level,
            ),
            None => (0.0, 0.0, 0.0, f64::NAN, 0),
        };
        tb += b;
        tm += m;
        tr += raw;
        println!("seed {seed:2} hidden {:.2} truth w {:.0} box {b:.3} mask {m:.3} raw {raw:.3} score {sc:.2} level {lvl}",
            1.0 - s.visible.area() as f64 / s.object.area() as f64, s.truth_box.2);
    }
    println!(
        "mean box {:.3} mask {:.3} raw {:.3}",
        tb / n as f64,
        tm / n as f64,
        tr / n as f64
    );
}
