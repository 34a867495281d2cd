//! The multi-view loaders (CMU_KO8's `multiple/` layout and COCO files of
//! views and box-only photographs) on a small layout written here: the
//! data they accept, and clear errors naming the file for what they refuse.

use std::path::{Path, PathBuf};

use sdhop::data::{load_coco, Ko8};
use sdhop::eval::{score_object, Evaluated};
use sdhop::model::Model;
use sdhop::pipeline::{BoxJson, DetectionJson};

fn write_jpg(path: &Path, w: u32, h: u32) {
    let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 3) as u8, (y * 5) as u8, 90]));
    img.save(path).unwrap();
}

fn write_mask(path: &Path, w: u32, h: u32, r: (u32, u32, u32, u32)) {
    let img = image::GrayImage::from_fn(w, h, |x, y| {
        let inside = x >= r.0 && x < r.0 + r.2 && y >= r.1 && y < r.1 + r.3;
        image::Luma([if inside { 255 } else { 0 }])
    });
    img.save(path).unwrap();
}

/// A CMU_KO8-like root with a multi-view part for `cup`.
fn layout(tag: &str) -> PathBuf {
    let root = std::env::temp_dir().join(format!("sdhop-mv-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    std::fs::create_dir_all(root.join("single/test/cup")).unwrap();
    let train = root.join("multiple/train/cup");
    let test = root.join("multiple/test/cup");
    std::fs::create_dir_all(&train).unwrap();
    std::fs::create_dir_all(&test).unwrap();
    // Two views with masks, one without.
    for i in 1..=3 {
        write_jpg(&train.join(format!("cup_00{i}.jpg")), 64, 48);
    }
    write_mask(&train.join("cup_001_mask.png"), 64, 48, (10, 8, 30, 20));
    write_mask(&train.join("cup_003_mask.png"), 64, 48, (20, 10, 16, 30));
    // Photographs: a good box, a bad .bbox, a box outside the image.
    for i in 1..=3 {
        write_jpg(&test.join(format!("cup_00{i}.jpg")), 64, 48);
    }
    std::fs::write(test.join("cup_001.bbox"), "32 24 20 16\n").unwrap();
    std::fs::write(test.join("cup_002.bbox"), "32 24 twenty\n").unwrap();
    std::fs::write(test.join("cup_003.bbox"), "500 400 20 16\n").unwrap();
    root
}

#[test]
fn views_load_with_their_masks_and_a_view_without_its_mask_is_named() {
    let root = layout("views");
    let ko8 = Ko8::open(&root).unwrap();
    assert!(ko8.has_multiple());
    let l = ko8.views("cup").unwrap();
    assert_eq!(l.samples.len(), 2);
    let a = l.samples[0].annotation.as_ref().unwrap();
    assert_eq!(a.bbox, (10.0, 8.0, 30.0, 20.0));
    assert!(a.mask_known);
    assert_eq!(a.visible.area(), 600);
    assert_eq!(l.skipped.len(), 1);
    assert!(
        l.skipped[0].contains("cup_002.jpg") && l.skipped[0].contains("without its mask"),
        "{}",
        l.skipped[0]
    );
    std::fs::remove_dir_all(&root).ok();
}

#[test]
fn box_photographs_are_box_only_and_bad_boxes_are_named() {
    let root = layout("boxes");
    let ko8 = Ko8::open(&root).unwrap();
    let l = ko8.box_photos("cup").unwrap();
    assert_eq!(l.samples.len(), 1);
    let a = l.samples[0].annotation.as_ref().unwrap();
    // `.bbox` is a centre: (32, 24) with size 20x16.
    assert_eq!(a.bbox, (22.0, 16.0, 20.0, 16.0));
    assert!(!a.mask_known);
    assert_eq!(a.visible.area(), 20 * 16, "the whole box to begin with");
    assert_eq!(l.skipped.len(), 2, "{:?}", l.skipped);
    assert!(l
        .skipped
        .iter()
        .any(|s| s.contains("cup_002.bbox") && s.contains("four numbers")));
    assert!(l
        .skipped
        .iter()
        .any(|s| s.contains("cup_003.bbox") && s.contains("outside")));
    std::fs::remove_dir_all(&root).ok();
}

#[test]
fn coco_views_box_only_annotations_and_annotations_with_neither() {
    let root = layout("coco");
    let dir = root.join("multiple/train/cup");
    let json = serde_json::json!({
        "images": [
            {"id": 1, "file_name": "cup_001.jpg", "width": 64, "height": 48},
            {"id": 2, "file_name": "cup_002.jpg", "width": 64, "height": 48},
            {"id": 3, "file_name": "cup_003.jpg", "width": 64, "height": 48},
            {"id": 4, "file_name": "missing.jpg", "width": 64, "height": 48}
        ],
        "categories": [{"id": 5, "name": "cup"}],
        "annotations": [
            // A view: mask, no box (the box is the mask's tight box).
            {"image_id": 1, "category_id": 5,
             "segmentation": [[10, 8, 40, 8, 40, 28, 10, 28]]},
            // Box only.
            {"image_id": 2, "category_id": 5, "bbox": [5, 6, 20, 10]},
            // Neither.
            {"image_id": 3, "category_id": 5}
        ]
    });
    let path = root.join("views.json");
    std::fs::write(&path, json.to_string()).unwrap();
    let l = load_coco(&path, &dir, "cup").unwrap();
    assert_eq!(l.samples.len(), 2, "{:?}", l.skipped);
    let view = l.samples[0].annotation.as_ref().unwrap();
    assert!(view.mask_known);
    assert_eq!(view.bbox, (10.0, 8.0, 30.0, 20.0));
    let boxed = l.samples[1].annotation.as_ref().unwrap();
    assert!(!boxed.mask_known);
    assert_eq!(boxed.visible.area(), 200);
    assert!(l
        .skipped
        .iter()
        .any(|s| s.contains("cup_003.jpg") && s.contains("neither a bbox nor a segmentation")));
    assert!(l.skipped.iter().any(|s| s.contains("missing.jpg")));
    // A box outside its image is refused, naming the file.
    let json = serde_json::json!({
        "images": [{"id": 1, "file_name": "cup_001.jpg", "width": 64, "height": 48}],
        "categories": [{"id": 5, "name": "cup"}],
        "annotations": [{"image_id": 1, "category_id": 5, "bbox": [100, 100, 10, 10]}]
    });
    std::fs::write(&path, json.to_string()).unwrap();
    let l = load_coco(&path, &dir, "cup").unwrap();
    assert!(l.samples.is_empty());
    assert!(
        l.skipped[0].contains("cup_001.jpg") && l.skipped[0].contains("outside"),
        "{:?}",
        l.skipped
    );
    std::fs::remove_dir_all(&root).ok();
}

fn det(label: &str, score: f64, b: (f64, f64, f64, f64), viewpoint: usize) -> DetectionJson {
    DetectionJson {
        label: label.into(),
        model: label.into(),
        score,
        bbox: BoxJson {
            x: b.0,
            y: b.1,
            width: b.2,
            height: b.3,
        },
        viewpoint,
        view: Some(format!("{label}_{viewpoint:03}")),
        level: 0,
        visible_fraction: 1.0,
        truncated: false,
        mask: None,
        raw_mask: None,
    }
}

/// CROSS scoring of a combined model: a detection of any of its components
/// on another object's photograph is a false positive, on its own a true
/// one whichever component fired.
#[test]
fn cross_scoring_counts_every_component_of_a_combined_model() {
    let cup = sdhop::data::Annotation {
        label: "cup".into(),
        bbox: (10.0, 10.0, 40.0, 40.0),
        visible: sdhop::vision::mask::Mask::new(100, 100),
        viewpoint: 0,
        mask_known: false,
    };
    let pan = sdhop::data::Annotation {
        label: "pan".into(),
        ..cup.clone()
    };
    let own = [det("cup", 2.0, (10.0, 10.0, 40.0, 40.0), 3)];
    let other = [det("cup", 3.0, (10.0, 10.0, 40.0, 40.0), 0)];
    let images = [
        Evaluated {
            id: "cup_001",
            truth: Some(&cup),
            detections: &own,
        },
        Evaluated {
            id: "pan_001",
            truth: Some(&pan),
            detections: &other,
        },
    ];
    let s = score_object("cup", &images);
    assert!((s.auc - 1.0).abs() < 1e-9, "own AUC {}", s.auc);
    // The pan photograph's stronger cup detection comes first: recall 1
    // only after one false positive over two images (FPPI 0.5).
    assert!(
        s.auc_cross < 0.6 && s.auc_cross > 0.4,
        "cross {}",
        s.auc_cross
    );
}

/// A model with many components keeps them, and their views, through a
/// save and a load.
#[test]
fn models_with_many_components_round_trip() {
    let obj = sdhop::synth::SynthObject {
        cols: 6,
        rows: 4,
        seed: 3,
    };
    let mut m = sdhop::synth::hand_model(&obj, "obj", true, &Default::default()).unwrap();
    let v0 = m.views[0].clone();
    let mut meta = m.meta.clone();
    let vm0 = meta.viewpoints[0].clone();
    meta.viewpoints = (0..12)
        .map(|i| sdhop::model::ViewMeta {
            views: vec![format!("obj_{i:03}"), format!("obj_{:03}", i + 12)],
            ..vm0.clone()
        })
        .collect();
    m = Model::new(meta, vec![v0; 12]).unwrap();
    let path =
        std::env::temp_dir().join(format!("sdhop-mv-model-{}.safetensors", std::process::id()));
    m.save(&path).unwrap();
    let back = Model::load(&path).unwrap();
    assert_eq!(back.views.len(), 12);
    assert_eq!(back.views, m.views);
    assert_eq!(back.meta.viewpoints[11].views, vec!["obj_011", "obj_023"]);
    std::fs::remove_file(&path).ok();
}
