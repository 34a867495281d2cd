use sdhop::synth::{hand_model, scene, HandModelParams, SceneParams, SynthObject};
use sdhop::vision::detect::{box_iou, DetectParams, Detector};
use sdhop::vision::pyramid::FeaturePyramid;
fn main() {
    let obj = SynthObject { cols: 12, rows: 10, seed: 11 };
    let model = hand_model(&obj, "s", true, &HandModelParams::default()).unwrap();
    let s = scene(&obj, &SceneParams { seed: 3, ..SceneParams::default() }).unwrap();
    let pyr = FeaturePyramid::build(&s.image, &model.meta.pyramid, &model.meta.segmentation).unwrap();
    let det = Detector::new(&model.views).unwrap();
    let (d, _) = det.detect(&pyr, &DetectParams { max_detections: 200, nms_iou: 1.0, threshold: -1e9, prune: false, ..model.meta.detection }).unwrap();
    for l in 0..pyr.levels.len() {
        if let Some(b) = d.iter().filter(|x| x.level == l).max_by(|a, b| a.score.total_cmp(&b.score)) {
            println!("level {l} scale {:.3} best {:.2} box {:?} iou {:.3} vis {:.2}", pyr.levels[l].scale_x, b.score, b.bbox, box_iou(b.bbox, s.truth_box), b.visible_fraction);
        }
    }
    println!("truth {:?}", s.truth_box);
}
