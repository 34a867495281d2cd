//! End-to-end tests on synthetic scenes the project generates itself.

use sdhop::model::Model;
use sdhop::pipeline::{detect_image, DetectOptions, MaskMode};
use sdhop::synth::{hand_model, scene, HandModelParams, Scene, SceneParams, SynthObject};
use sdhop::train::ko8::above_threshold;
use sdhop::vision::cells::FeatureKind;
use sdhop::vision::detect::{box_iou, DetectParams, Detector, PlanarMaps, Region, Transfer};
use sdhop::vision::energy::ViewWeights;
use sdhop::vision::image::ColorImage;
use sdhop::vision::mask::Mask;
use sdhop::vision::pyramid::FeaturePyramid;
use sdhop::vision::VisionError;

const OBJECT: SynthObject = SynthObject {
    cols: 12,
    rows: 10,
    seed: 11,
};

fn scenes(n: u64) -> Vec<Scene> {
    (0..n)
        .map(|seed| {
            scene(
                &OBJECT,
                &SceneParams {
                    seed,
                    ..SceneParams::default()
                },
            )
            .unwrap()
        })
        .collect()
}

/// The hand-built model and `n` scenes with their pyramids.
fn scanned_scenes(n: u64) -> (Model, Vec<(Scene, FeaturePyramid)>) {
    let model = hand_model(&OBJECT, "synthetic", true, &HandModelParams::default()).unwrap();
    let scenes = scenes(n)
        .into_iter()
        .map(|s| {
            let pyr =
                FeaturePyramid::build(&s.image, &model.meta.pyramid, &model.meta.segmentation)
                    .unwrap();
            (s, pyr)
        })
        .collect();
    (model, scenes)
}

/// Mean box IoU and mean visible-mask IoU of the top detection (a miss
/// counts 0 for both).
fn evaluate(model: &Model, scenes: &[Scene], masks: MaskMode) -> (f64, f64) {
    let opts = DetectOptions {
        max_detections: Some(1),
        masks,
        ..DetectOptions::default()
    };
    let (mut b, mut m) = (0.0, 0.0);
    for s in scenes {
        let resp = detect_image(&s.image, &[model], &opts).unwrap();
        if let Some(d) = resp.detections.first() {
            b += box_iou(
                (d.bbox.x, d.bbox.y, d.bbox.width, d.bbox.height),
                s.truth_box,
            );
            let rle = d.mask.as_ref().or(d.raw_mask.as_ref()).unwrap();
            m += Mask::from_rle(rle).unwrap().iou(&s.visible);
        }
    }
    (b / scenes.len() as f64, m / scenes.len() as f64)
}

#[test]
fn finds_full_box_and_visible_mask_and_beats_plain_hog() {
    let scenes = scenes(12);
    let hp = HandModelParams::default();
    let sdhop = hand_model(&OBJECT, "synthetic", true, &hp).unwrap();
    let plain = hand_model(&OBJECT, "plain", false, &hp).unwrap();
    let (box_iou, mask_iou) = evaluate(&sdhop, &scenes, MaskMode::Refined);
    let (_, raw_iou) = evaluate(&sdhop, &scenes, MaskMode::Raw);
    let (plain_box, plain_mask) = evaluate(&plain, &scenes, MaskMode::Refined);
    println!("SD-HOP: box IoU {box_iou:.3}, mask IoU refined {mask_iou:.3} raw {raw_iou:.3}");
    println!("plain : box IoU {plain_box:.3}, mask IoU {plain_mask:.3}");
    assert!(box_iou >= 0.7, "box IoU {box_iou}");
    assert!(mask_iou >= 0.7, "mask IoU {mask_iou}");
    // Without occlusion reasoning the mask is the whole box.
    assert!(
        mask_iou > plain_mask + 0.1,
        "{mask_iou} vs plain {plain_mask}"
    );
    assert!(
        box_iou >= plain_box - 0.02,
        "{box_iou} vs plain {plain_box}"
    );
}

#[test]
fn pruning_returns_exactly_the_unpruned_detections() {
    let (model, scenes) = scanned_scenes(3);
    let detector = Detector::new(&model.views).unwrap();
    for (_, pyr) in &scenes {
        // Low thresholds keep many locations alive, so the early stop of
        // the min-cut is what prunes there.
        let t0 = model.meta.detection.threshold;
        // Several suppression overlaps: locations overlapping a settled
        // detection are suppressed without a min-cut.
        let cases = [
            (t0, 1, 0.4),
            (t0, 5, 0.4),
            (t0 - 1.0, 5, 0.4),
            (t0 - 3.0, 20, 0.4),
            (t0 - 3.0, 20, 0.1),
            (t0 - 3.0, 20, 0.8),
        ];
        for (threshold, max_detections, nms_iou) in cases {
            let mut p = DetectParams {
                max_detections,
                threshold,
                nms_iou,
                ..model.meta.detection
            };
            p.prune = true;
            let (pruned, st_p) = detector.detect(pyr, &p).unwrap();
            p.prune = false;
            let (full, st_f) = detector.detect(pyr, &p).unwrap();
            assert_eq!(
                pruned, full,
                "threshold {threshold}, max_detections {max_detections}, nms_iou {nms_iou}"
            );
            assert!(!full.is_empty());
            assert_eq!(st_p.locations, st_f.locations);
            assert_eq!(st_f.min_cuts, st_f.locations);
            if threshold == t0 {
                assert!(st_p.min_cuts * 10 < st_p.locations, "{st_p:?}");
            }
        }
    }
}

/// The bounds assume nothing of a cell's numbers (learned cells are signed,
/// HOG's are not): pruning stays exact on learned cells.
#[test]
fn pruning_is_exact_on_learned_cells_too() {
    let model = hand_model(&OBJECT, "synthetic", true, &HandModelParams::default()).unwrap();
    let detector = Detector::new(&model.views).unwrap();
    let mut params = model.meta.pyramid;
    params.features = FeatureKind::Cnn;
    for s in scenes(2) {
        let pyr = FeaturePyramid::build(&s.image, &params, &model.meta.segmentation).unwrap();
        let t0 = model.meta.detection.threshold;
        for (threshold, max_detections) in [(t0, 5), (t0 - 3.0, 20), (-1e6, 5)] {
            let mut p = DetectParams {
                max_detections,
                threshold,
                ..model.meta.detection
            };
            p.prune = true;
            let (pruned, st_p) = detector.detect(&pyr, &p).unwrap();
            p.prune = false;
            let (full, _) = detector.detect(&pyr, &p).unwrap();
            assert_eq!(pruned, full, "threshold {threshold}, max {max_detections}");
            if threshold == -1e6 {
                assert_eq!(full.len(), max_detections);
                assert!(st_p.min_cuts < st_p.locations, "{st_p:?}");
            }
        }
    }
}

#[test]
fn a_region_keeps_only_boxes_about_there_and_pruning_stays_exact() {
    let (model, scenes) = scanned_scenes(3);
    let detector = Detector::new(&model.views).unwrap();
    for (s, pyr) in &scenes {
        let (tx, ty, tw, th) = s.truth_box;
        // The object's own box, and one as large where it is not.
        let away = (
            if tx > 160.0 { 0.0 } else { 320.0 - tw },
            if ty > 120.0 { 0.0 } else { 240.0 - th },
            tw,
            th,
        );
        let mut best = Vec::new();
        for bbox in [s.truth_box, away] {
            let region = Region { bbox, min_iou: 0.3 };
            let mut p = DetectParams {
                max_detections: 1,
                threshold: model.meta.detection.threshold - 2.0,
                region: Some(region),
                ..model.meta.detection
            };
            p.prune = true;
            let (pruned, st_p) = detector.detect(pyr, &p).unwrap();
            p.prune = false;
            let (full, st_f) = detector.detect(pyr, &p).unwrap();
            assert_eq!(pruned, full);
            assert!(st_p.min_cuts <= st_f.min_cuts);
            for d in &full {
                assert!(box_iou(d.bbox, bbox) >= 0.3, "{:?} vs {bbox:?}", d.bbox);
            }
            best.push(
                full.first()
                    .map(|d| (d.score, box_iou(d.bbox, s.truth_box))),
            );
        }
        // A region that is no box, or an IoU beyond 1, is refused.
        for region in [
            Region {
                bbox: (0.0, 0.0, 0.0, 10.0),
                min_iou: 0.3,
            },
            Region {
                bbox: s.truth_box,
                min_iou: 1.5,
            },
        ] {
            let p = DetectParams {
                region: Some(region),
                ..model.meta.detection
            };
            assert!(detector.detect(pyr, &p).is_err());
        }
        // About the object the detection is the object; away from it, any
        // detection scores lower.
        let (on_score, on_iou) = best[0].expect("a detection on the object");
        assert!(on_iou >= 0.5, "{on_iou}");
        if let Some((away_score, _)) = best[1] {
            assert!(away_score < on_score, "{away_score} vs {on_score}");
        }
    }
}

#[test]
fn response_json_has_the_detect_shape() {
    let s = &scenes(1)[0];
    let model = hand_model(&OBJECT, "synthetic", true, &HandModelParams::default()).unwrap();
    let opts = DetectOptions {
        masks: MaskMode::Both,
        max_detections: Some(3),
        ..DetectOptions::default()
    };
    let resp = detect_image(&s.image, &[&model], &opts).unwrap();
    let v = serde_json::to_value(&resp).unwrap();
    assert_eq!(v["image"]["width"], 320);
    assert_eq!(v["image"]["height"], 240);
    let d = &v["detections"][0];
    assert_eq!(d["label"], "synthetic");
    assert_eq!(d["model"], "synthetic");
    for key in ["x", "y", "width", "height"] {
        assert!(d["box"][key].is_number());
    }
    assert_eq!(d["mask"]["size"], serde_json::json!([240, 320]));
    let counts: u64 = d["mask"]["counts"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c.as_u64().unwrap())
        .sum();
    assert_eq!(counts, 240 * 320);
    assert!(d["raw_mask"]["counts"].is_array());
    assert!(d["visible_fraction"].as_f64().unwrap() > 0.0);
    assert!(v["timing_ms"]["total"].as_f64().unwrap() > 0.0);
    // Masks can be left out.
    let none = detect_image(
        &s.image,
        &[&model],
        &DetectOptions {
            masks: MaskMode::None,
            ..opts
        },
    )
    .unwrap();
    let v = serde_json::to_value(&none).unwrap();
    assert!(
        v["detections"][0].get("mask").is_none() && v["detections"][0].get("raw_mask").is_none()
    );
}

#[test]
fn objects_cut_by_the_border_get_their_full_box() {
    // Shift an unoccluded scene so the object leaves the image on the left.
    let s = &scene(
        &OBJECT,
        &SceneParams {
            seed: 2,
            occlusion: (0.0, 0.0),
            ..SceneParams::default()
        },
    )
    .unwrap();
    let (tx, ty, tw, th) = s.truth_box;
    let shift = (tx + 0.35 * tw).round() as usize;
    let (w, h) = (s.image.width(), s.image.height());
    let mut data = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            for c in 0..3 {
                data.push(s.image.get((x + shift).min(w - 1), y, c));
            }
        }
    }
    let img = ColorImage::new(w, h, data).unwrap();
    let model = hand_model(&OBJECT, "synthetic", true, &HandModelParams::default()).unwrap();
    let opts = DetectOptions {
        max_detections: Some(1),
        ..DetectOptions::default()
    };
    let resp = detect_image(&img, &[&model], &opts).unwrap();
    let d = resp.detections.first().expect("a detection");
    let truth = (tx - shift as f64, ty, tw, th);
    let iou = box_iou((d.bbox.x, d.bbox.y, d.bbox.width, d.bbox.height), truth);
    assert!(d.truncated && d.bbox.x < 0.0, "{d:?}");
    assert!(iou >= 0.6, "IoU {iou} for {d:?} vs {truth:?}");
}

#[test]
fn bad_inputs_give_errors_or_empty_results() {
    let model = hand_model(&OBJECT, "synthetic", true, &HandModelParams::default()).unwrap();
    let opts = DetectOptions::default();
    // Zero-size images cannot even be built.
    assert!(matches!(
        ColorImage::new(0, 10, vec![]),
        Err(VisionError::EmptyImage { .. })
    ));
    // Smaller than one cell, and smaller than the template: empty results.
    for (w, h) in [(5, 5), (40, 30), (1, 300)] {
        let img = ColorImage::new(w, h, vec![100.0; w * h * 3]).unwrap();
        let resp = detect_image(&img, &[&model], &opts).unwrap();
        assert!(resp.detections.is_empty(), "{w}x{h}");
    }
    // Too many pixels.
    let img = ColorImage::new(64, 64, vec![0.0; 64 * 64 * 3]).unwrap();
    let small = DetectOptions {
        max_pixels: 1000,
        ..opts.clone()
    };
    assert!(matches!(
        detect_image(&img, &[&model], &small),
        Err(VisionError::ImageTooLarge { .. })
    ));
    // Non-finite weights are refused before any scan.
    let mut bad = model.clone();
    bad.views[0].w_vis[3] = f32::NAN;
    assert!(Detector::new(&bad.views).is_err());
    assert!(bad.to_bytes().is_err());
    // Invalid detection parameters.
    let pyr = FeaturePyramid::build(&img, &model.meta.pyramid, &model.meta.segmentation).unwrap();
    let det = Detector::new(&model.views).unwrap();
    let p = DetectParams {
        max_truncation: 1.0,
        ..model.meta.detection
    };
    assert!(det.detect(&pyr, &p).is_err());
    // A flat image has nothing above the threshold.
    let flat = ColorImage::new(320, 240, vec![90.0; 320 * 240 * 3]).unwrap();
    assert!(detect_image(&flat, &[&model], &opts)
        .unwrap()
        .detections
        .is_empty());
}

#[test]
fn dropping_low_scores_equals_detecting_at_a_higher_threshold() {
    // What cross-validation relies on to score many thresholds from one run.
    let model = hand_model(&OBJECT, "synthetic", true, &HandModelParams::default()).unwrap();
    let t0 = model.meta.detection.threshold;
    for s in &scenes(3) {
        let at = |threshold: f64| {
            let opts = DetectOptions {
                threshold: Some(threshold),
                max_detections: Some(20),
                masks: MaskMode::None,
                ..DetectOptions::default()
            };
            let mut r = detect_image(&s.image, &[&model], &opts).unwrap();
            r.timing_ms = Default::default();
            r
        };
        let low = at(t0 - 2.0);
        for t in [t0 - 1.0, t0, t0 + 0.5] {
            let filtered = above_threshold(std::slice::from_ref(&low), t);
            let direct = at(t);
            assert_eq!(
                serde_json::to_value(&filtered[0]).unwrap(),
                serde_json::to_value(&direct).unwrap(),
                "threshold {t}"
            );
        }
        assert!(low.detections.len() > at(t0 + 0.5).detections.len());
    }
}

/// Response transfer (paper, Algorithm 1): with the occluder's pixels
/// claimed by another object's detection, every energy can only fall, so
/// the best score rises or stays; the occluded cells under the claim are
/// labelled hidden at least as often; and pruning stays exact (every box
/// meeting a claimed cell is solved).
#[test]
fn response_transfer_explains_the_occluder_and_stays_exact() {
    let (model, scenes) = scanned_scenes(3);
    let plain = Detector::new(&model.views).unwrap();
    for (s, pyr) in &scenes {
        // The occluder: the object's pixels that are hidden.
        let mut occluder = Mask::new(s.object.width, s.object.height);
        for y in 0..s.object.height {
            for x in 0..s.object.width {
                occluder.set(x, y, s.object.get(x, y) && !s.visible.get(x, y));
            }
        }
        let mut transfer = Transfer::new(pyr);
        assert!(transfer.is_empty());
        transfer.claim(pyr, &occluder, -1.0);
        assert!(!transfer.is_empty());
        let with = Detector::new(&model.views)
            .unwrap()
            .with_transfer(&transfer);
        let t0 = model.meta.detection.threshold;
        for (threshold, max_detections) in [(t0, 1), (t0 - 1.0, 5), (t0 - 3.0, 20)] {
            let mut p = DetectParams {
                max_detections,
                threshold,
                ..model.meta.detection
            };
            p.prune = true;
            let (pruned, _) = with.detect(pyr, &p).unwrap();
            p.prune = false;
            let (full, _) = with.detect(pyr, &p).unwrap();
            assert_eq!(pruned, full, "threshold {threshold}, max {max_detections}");
        }
        let p = DetectParams {
            max_detections: 1,
            threshold: t0 - 3.0,
            ..model.meta.detection
        };
        let before = plain.detect(pyr, &p).unwrap().0;
        let after = with.detect(pyr, &p).unwrap().0;
        let (b, a) = (&before[0], &after[0]);
        assert!(a.score >= b.score - 1e-9, "{} < {}", a.score, b.score);
        if a.level == b.level && a.grid.cell_x == b.grid.cell_x && a.grid.cell_y == b.grid.cell_y {
            let hidden = |d: &sdhop::vision::detect::Detection| {
                d.cells
                    .iter()
                    .enumerate()
                    .filter(|(i, v)| {
                        let (cx, cy) = (
                            d.grid.cell_x + (i % d.grid.cols) as isize,
                            d.grid.cell_y + (i / d.grid.cols) as isize,
                        );
                        !**v && cx >= 0
                            && cy >= 0
                            && transfer.at(d.level, cx as usize, cy as usize).is_some()
                    })
                    .count()
            };
            assert!(hidden(a) >= hidden(b), "{} < {}", hidden(a), hidden(b));
        }
    }
}

/// Two objects in one detector (a model trained jointly): each group's
/// detections are exactly those of its object's viewpoints alone (its own
/// suppression and `max_detections`), and pruning stays exact.
#[test]
fn grouped_viewpoints_detect_as_separate_models_and_pruning_stays_exact() {
    let (first, scenes) = scanned_scenes(3);
    let other = SynthObject {
        cols: 8,
        rows: 12,
        seed: 23,
    };
    let second = hand_model(&other, "other", true, &HandModelParams::default()).unwrap();
    let views: Vec<_> = first.views.iter().chain(&second.views).cloned().collect();
    let n1 = first.views.len();
    let groups: Vec<usize> = (0..views.len()).map(|v| usize::from(v >= n1)).collect();
    let joint = Detector::new(&views)
        .unwrap()
        .with_groups(groups.clone())
        .unwrap();
    assert!(Detector::new(&views).unwrap().with_groups(vec![0]).is_err());
    let alone = [
        Detector::new(&first.views).unwrap(),
        Detector::new(&second.views).unwrap(),
    ];
    let t0 = first.meta.detection.threshold;
    for (_, pyr) in &scenes {
        for (threshold, max_detections) in [(t0, 1), (t0 - 1.0, 5), (t0 - 3.0, 20)] {
            let mut p = DetectParams {
                max_detections,
                threshold,
                ..first.meta.detection
            };
            p.prune = true;
            let (pruned, _) = joint.detect(pyr, &p).unwrap();
            p.prune = false;
            let (full, _) = joint.detect(pyr, &p).unwrap();
            assert_eq!(pruned, full, "threshold {threshold}, max {max_detections}");
            for (g, det) in alone.iter().enumerate() {
                let (own, _) = det.detect(pyr, &p).unwrap();
                let mut mine: Vec<_> = full
                    .iter()
                    .filter(|d| groups[d.viewpoint] == g)
                    .cloned()
                    .collect();
                for d in &mut mine {
                    d.viewpoint -= g * n1;
                }
                assert!(mine.len() <= max_detections);
                assert_eq!(mine, own, "group {g}, threshold {threshold}");
            }
        }
    }
}

/// Feature planes built once with the padding of a larger template (as for
/// several models) give the very detections and bounds of the detector's
/// own; planes of another pyramid are not used.
#[test]
fn shared_feature_planes_change_nothing() {
    let (model, scenes) = scanned_scenes(3);
    let v = &model.views[0];
    let larger = [ViewWeights::zeros(
        v.rows + 3,
        v.cols + 5,
        v.w_hop.len() - 1,
    )];
    let t0 = model.meta.detection.threshold;
    for (i, (_, pyr)) in scenes.iter().enumerate() {
        let maps = PlanarMaps::new(pyr, &[&model.views, &larger]);
        let other = &scenes[(i + 1) % scenes.len()].1;
        let foreign = PlanarMaps::new(other, &[&model.views, &larger]);
        for (threshold, max_detections) in [(t0, 5), (t0 - 2.0, 20)] {
            let p = DetectParams {
                max_detections,
                threshold,
                ..model.meta.detection
            };
            let own = Detector::new(&model.views)
                .unwrap()
                .detect(pyr, &p)
                .unwrap();
            let shared = Detector::new(&model.views)
                .unwrap()
                .with_maps(&maps)
                .detect(pyr, &p)
                .unwrap();
            let wrong = Detector::new(&model.views)
                .unwrap()
                .with_maps(&foreign)
                .detect(pyr, &p)
                .unwrap();
            assert_eq!(own.0, shared.0);
            assert_eq!(own.1.min_cuts, shared.1.min_cuts);
            assert_eq!(own.1.pruned_stage1, shared.1.pruned_stage1);
            assert_eq!(own.0, wrong.0);
        }
    }
}

/// Stage 1 through the low-rank basis of the components' filters gives
/// the same detections as the full filters (it only bounds more loosely;
/// the min-cut stage decides), for a model of several components, with
/// one detection asked for and with many.
#[test]
fn low_rank_stage_one_gives_the_same_detections() {
    let (model, scenes) = scanned_scenes(4);
    let other = SynthObject {
        cols: 8,
        rows: 12,
        seed: 5,
    };
    let second = hand_model(&other, "other", true, &HandModelParams::default()).unwrap();
    // Three components: the object, another shape, the object again with
    // its filters scaled (so the basis must serve different filters).
    let mut scaled = model.views[0].clone();
    scaled.w_vis.iter_mut().for_each(|v| *v *= 0.8);
    let views = vec![model.views[0].clone(), second.views[0].clone(), scaled];
    let lr = sdhop::vision::detect::LowRank::new(&views);
    for max_detections in [1, 10] {
        let params = DetectParams {
            threshold: -1.0,
            max_detections,
            ..model.meta.detection
        };
        for (_, pyr) in &scenes {
            let full = Detector::new(&views).unwrap().detect(pyr, &params).unwrap();
            let low = Detector::new(&views)
                .unwrap()
                .with_low_rank(&lr)
                .detect(pyr, &params)
                .unwrap();
            assert_eq!(full.0, low.0, "max_detections {max_detections}");
            assert!(!full.0.is_empty());
            // The low-rank bound is looser: no more locations leave at
            // stage 1 than with the full one.
            assert!(low.1.pruned_stage1 <= full.1.pruned_stage1);
            eprintln!(
                "stage 1 kept {} of {} (low-rank) against {} (full)",
                low.1.locations - low.1.pruned_stage1,
                low.1.locations,
                full.1.locations - full.1.pruned_stage1
            );
        }
    }
}

/// The fast pyramid (cells computed every fifth level, the rest resampled)
/// against the exact one, on the fixed scenes: the same object found, the
/// top boxes within IoU 0.7 of each other and of the truth within 0.6 (the
/// stated tolerance of the approximation; issue 63). Scores are not
/// compared: a model trained on exact cells scores lower on resampled
/// ones (the hand-built model here 12.8 against 9.5 on one scene), which
/// is why models are trained on the pyramid they scan.
#[test]
fn the_fast_pyramid_finds_what_the_exact_one_finds() {
    let model = hand_model(&OBJECT, "synthetic", true, &HandModelParams::default()).unwrap();
    let detector = Detector::new(&model.views).unwrap();
    let exact = model.meta.pyramid;
    let fast = sdhop::vision::pyramid::PyramidParams {
        computed_every: 5,
        ..exact
    };
    let p = DetectParams {
        max_detections: 1,
        ..model.meta.detection
    };
    for s in scenes(4) {
        let top = |params| {
            let pyr = FeaturePyramid::build(&s.image, params, &model.meta.segmentation).unwrap();
            detector.detect(&pyr, &p).unwrap().0.remove(0)
        };
        let (a, b) = (top(&exact), top(&fast));
        let iou = box_iou(a.bbox, b.bbox);
        println!(
            "exact {:.3} fast {:.3} IoU {iou:.3} (truth {:.3})",
            a.score,
            b.score,
            box_iou(b.bbox, s.truth_box)
        );
        assert!(iou >= 0.7, "{a:?} vs {b:?}");
        assert!(box_iou(b.bbox, s.truth_box) >= 0.6);
    }
}

/// Both kinds per object: a model with a segmenter answers its own
/// detections (scores, boxes, components) with the masks of the
/// segmenter's best location whose box overlaps each by
/// `SEGMENTER_MIN_IOU` or more, or its own masks where none does.
#[test]
fn a_segmenter_places_and_segments_each_detection() {
    use sdhop::model::SEGMENTER_MIN_IOU;
    use sdhop::vision::detect::detection_masks;
    let hog = hand_model(&OBJECT, "synthetic", true, &HandModelParams::default()).unwrap();
    // The finder: the same weights on learned cells (what they find does
    // not matter here, only how its detections are segmented).
    let mut finder = hog.clone();
    finder.meta.pyramid.features = FeatureKind::Cnn;
    finder.meta.cells = FeatureKind::Cnn.fingerprint().unwrap();
    finder.meta.detection.threshold = -1e6;
    let paired = finder.clone().with_segmenter(hog.clone()).unwrap();
    let opts = DetectOptions {
        max_detections: Some(4),
        masks: MaskMode::Both,
        ..DetectOptions::default()
    };
    let detector = Detector::new(&hog.views).unwrap();
    let (mut segmented, mut differ) = (0, 0);
    for s in scenes(2) {
        let alone = detect_image(&s.image, &[&finder], &opts).unwrap();
        let both = detect_image(&s.image, &[&paired], &opts).unwrap();
        assert_eq!(alone.detections.len(), 4);
        assert_eq!(alone.detections.len(), both.detections.len());
        let pyr =
            FeaturePyramid::build(&s.image, &hog.meta.pyramid, &hog.meta.segmentation).unwrap();
        for (a, b) in alone.detections.iter().zip(&both.detections) {
            assert_eq!(
                (a.score, a.bbox, a.viewpoint, a.level),
                (b.score, b.bbox, b.viewpoint, b.level)
            );
            let target = (a.bbox.x, a.bbox.y, a.bbox.width, a.bbox.height);
            let near = detector.best_near(
                &pyr,
                target,
                SEGMENTER_MIN_IOU,
                hog.meta.detection.max_truncation,
            );
            match near {
                Some(n) => {
                    let shape = hog.shapes[n.viewpoint].as_ref();
                    let (raw, refined) =
                        detection_masks(&n, &pyr, &hog.meta.detection.refine, shape);
                    assert_eq!(b.mask, Some(refined.to_rle()));
                    assert_eq!(b.raw_mask, Some(raw.to_rle()));
                    assert_eq!(b.visible_fraction, n.visible_fraction);
                    segmented += 1;
                    differ += usize::from(a.mask != b.mask);
                }
                None => assert_eq!((&a.mask, &a.raw_mask), (&b.mask, &b.raw_mask)),
            }
        }
    }
    assert!(
        segmented > 0 && differ > 0,
        "{segmented} segmented, {differ} differ"
    );
}
