//! `sdhop-train mesh` end to end on data the test makes itself: a
//! vertex-coloured box mesh and generated backgrounds. The model it writes
//! must load, carry a viewing direction per component, and find the box
//! in renders it never saw; bad input ends with exit status 2.

use std::path::Path;

use indicatif::ProgressBar;
use sdhop::model::Model;
use sdhop::pose::api::{estimate, MaskUsed, PoseParams};
use sdhop::pose::geometry::Intrinsics;
use sdhop::pose::mesh::Mesh;
use sdhop::pose::render::background;
use sdhop::train::mesh::{render_set, MeshSet, RenderParams};
use sdhop::vision::detect::{box_iou, DetectParams, Detector};
use sdhop::vision::image::ColorImage;
use sdhop::vision::pyramid::FeaturePyramid;

/// An ASCII PLY of a box with one colour per vertex (a red top, a blue
/// bottom: the renders must show colour for the colour model to learn).
fn coloured_box_ply() -> String {
    coloured_cuboid_ply([60.0, 40.0, 30.0], [[220, 90, 40], [40, 90, 200]])
}

/// An ASCII PLY of a cuboid of sides `size`, its top vertices of colour
/// `rgb[0]` and its bottom ones of `rgb[1]`.
fn coloured_cuboid_ply(size: [f64; 3], rgb: [[u8; 3]; 2]) -> String {
    let mesh = Mesh::cuboid(size[0], size[1], size[2]);
    let mut s = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        mesh.vertices.len(),
        mesh.triangles.len()
    );
    for v in &mesh.vertices {
        let [r, g, b] = rgb[usize::from(v.z <= 0.0)];
        s.push_str(&format!("{} {} {} {r} {g} {b}\n", v.x, v.y, v.z));
    }
    for t in &mesh.triangles {
        s.push_str(&format!("3 {} {} {}\n", t[0], t[1], t[2]));
    }
    s
}

fn write_backgrounds(dir: &Path, n: usize) {
    std::fs::create_dir_all(dir).unwrap();
    for i in 0..n {
        let img = background(640, 480, 100 + i as u64).unwrap();
        img.to_rgb8()
            .save(dir.join(format!("bg{i:02}.png")))
            .unwrap();
    }
}

/// Runs `sdhop-train mesh` with `args` and asserts that it succeeded.
fn train_mesh(args: &[&str]) {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_sdhop-train"))
        .arg("mesh")
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// 20 renders of `mesh` with another seed over other scenes (written to
/// `dir`), and in how many of them `model`'s top detection is the object
/// (IoU >= 0.5).
fn found_in_new_renders(
    model: &Model,
    mesh: &Mesh,
    colours: Option<&[[f32; 3]]>,
    dir: &Path,
) -> (usize, MeshSet) {
    let others: Vec<ColorImage> = (0..3)
        .map(|i| background(640, 480, 900 + i).unwrap())
        .collect();
    let test = render_set(
        mesh,
        colours,
        "box",
        &others,
        &RenderParams {
            renders: 20,
            components: 1,
            seed: 77,
            ..RenderParams::default()
        },
        dir,
        &ProgressBar::hidden(),
    )
    .unwrap();
    let det = Detector::new(&model.views).unwrap();
    let params = DetectParams {
        threshold: -1e9,
        max_detections: 1,
        ..model.meta.detection
    };
    let mut hits = 0;
    for s in &test.samples {
        let img = sdhop::data::load_image(&s.image).unwrap();
        let pyr =
            FeaturePyramid::build(&img, &model.meta.pyramid, &model.meta.segmentation).unwrap();
        let (dets, _) = det.detect(&pyr, &params).unwrap();
        let a = s.annotation.as_ref().unwrap();
        if dets.first().is_some_and(|d| box_iou(d.bbox, a.bbox) >= 0.5) {
            hits += 1;
        }
    }
    (hits, test)
}

#[test]
fn a_model_trained_from_a_mesh_finds_the_object_in_new_renders() {
    let dir = std::env::temp_dir().join(format!("sdhop-mesh-cli-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let ply = dir.join("box.ply");
    std::fs::write(&ply, coloured_box_ply()).unwrap();
    let bgs = dir.join("bg");
    write_backgrounds(&bgs, 8);
    let out = dir.join("models/box.safetensors");
    let work = dir.join("work");
    train_mesh(&[
        "--mesh",
        ply.to_str().unwrap(),
        "--name",
        "box",
        "--backgrounds",
        bgs.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--work",
        work.to_str().unwrap(),
        "--renders",
        "80",
        "--components",
        "2",
        // The mechanics on HOG cells, an eighth of the learned cells'
        // cost (the library test below trains the route's default).
        "--features",
        "hog",
        "--negatives",
        "6",
        "--max-passes",
        "3",
    ]);
    let coco: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(work.join("coco.json")).unwrap()).unwrap();
    assert_eq!(coco["annotations"].as_array().unwrap().len(), 80);
    let model = Model::load(&out).unwrap();
    assert_eq!(model.meta.name, "box");
    assert_eq!(model.meta.viewpoints.len(), 2);
    for v in &model.meta.viewpoints {
        assert!(!v.rotations.is_empty());
        let d = v.direction.expect("a viewing direction per component");
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        assert!((n - 1.0).abs() < 1e-6);
    }
    assert!(model.shapes.iter().all(|s| s.is_some()));
    // Renders with another seed over other backgrounds: the top
    // detection is the box in most of them.
    let mesh = Mesh::parse(&std::fs::read(&ply).unwrap()).unwrap();
    let colours = Mesh::ply_vertex_colours(&std::fs::read(&ply).unwrap()).unwrap();
    assert!(colours.is_some());
    let (hits, test) = found_in_new_renders(&model, &mesh, colours.as_deref(), &dir.join("test"));
    assert!(hits >= 14, "{hits} of 20 new renders found");

    // Pose from no start: the model's training views placed on its
    // detections, refined by OR-IRLS. The box is symmetric, so the error
    // is ADD-S (mean distance of each corner to the nearest true corner).
    let k = Intrinsics {
        fx: 575.0,
        fy: 575.0,
        cx: 160.0,
        cy: 120.0,
    };
    let params = PoseParams {
        intrinsics: k,
        initial_pose: None,
        label: None,
        model: Some("box".into()),
        mask: None,
        max_iterations: None,
        start_uncertainty: None,
    };
    let diagonal = (60.0f64 * 60.0 + 40.0 * 40.0 + 30.0 * 30.0).sqrt();
    let mut close = 0;
    for (s, truth) in test.samples.iter().zip(&test.poses) {
        let img = sdhop::data::load_image(&s.image).unwrap();
        let r = estimate(&img, &mesh, &params, None, &[&model]).unwrap();
        assert_eq!(r.mask_source, MaskUsed::Detected);
        assert!(r.detection.is_some() && r.start_pose.is_some());
        assert!(r.starts_refined.unwrap() >= 1);
        let rot = nalgebra::Matrix3::from_fn(|i, j| r.pose.rotation[i][j]);
        let t = nalgebra::Vector3::from(r.pose.translation);
        let est: Vec<_> = mesh.vertices.iter().map(|v| rot * v + t).collect();
        let tru: Vec<_> = mesh.vertices.iter().map(|v| truth.transform(v)).collect();
        let adds = est
            .iter()
            .map(|e| {
                tru.iter()
                    .map(|q| (e - q).norm())
                    .fold(f64::INFINITY, f64::min)
            })
            .sum::<f64>()
            / est.len() as f64;
        eprintln!("pose from no start: ADD-S {adds:.1} (diagonal {diagonal:.1})");
        close += usize::from(adds < 0.1 * diagonal);
    }
    // Starts from a coarse component and a template's box are far from
    // the truth (a start sits 20-40% of the diagonal away, mostly in
    // depth); a random rotation is never within 10%.
    assert!(
        close >= 3,
        "{close} of 20 poses from no start within 10% of the diagonal"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// A file that is no mesh, or a bad range, ends with status 2 and a
/// message naming the problem.
#[test]
fn mesh_training_refuses_bad_input_with_status_2() {
    let bin = env!("CARGO_BIN_EXE_sdhop-train");
    let dir = std::env::temp_dir().join(format!("sdhop-mesh-bad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let junk = dir.join("junk.ply");
    std::fs::write(&junk, "ply\nthis is not a mesh\n").unwrap();
    let bgs = dir.join("bg");
    write_backgrounds(&bgs, 1);
    let run = |extra: &[&str]| {
        let mut args = vec![
            "mesh",
            "--name",
            "x",
            "--backgrounds",
            bgs.to_str().unwrap(),
            "--out",
            "/nonexistent-dir-sdhop/x.safetensors",
        ];
        args.extend_from_slice(extra);
        let out = std::process::Command::new(bin)
            .args(&args)
            .output()
            .unwrap();
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let (code, err) = run(&["--mesh", junk.to_str().unwrap()]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("junk.ply"), "{err}");
    let (code, err) = run(&["--mesh", junk.to_str().unwrap(), "--elevation", "80,10"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("elevation"), "{err}");
    let (code, err) = run(&["--mesh", junk.to_str().unwrap(), "--size", "300,400"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("size"), "{err}");
    // Several meshes need as many names, each once.
    let (code, err) = run(&["--mesh", junk.to_str().unwrap(), "--mesh", "b.ply"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("one name per mesh"), "{err}");
    let (code, err) = run(&[
        "--mesh",
        junk.to_str().unwrap(),
        "--mesh",
        "b.ply",
        "--name",
        "x",
    ]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("twice"), "{err}");
    // Box photographs: an empty file is refused before any rendering,
    // naming it; so is a second object beside them.
    let empty = dir.join("empty.json");
    std::fs::write(&empty, "{}").unwrap();
    let (code, err) = run(&[
        "--mesh",
        junk.to_str().unwrap(),
        "--photos",
        empty.to_str().unwrap(),
    ]);
    assert_eq!(code, Some(2), "{err}");
    assert!(
        err.contains("empty.json") && err.contains("no photographs"),
        "{err}"
    );
    let (code, err) = run(&[
        "--mesh",
        junk.to_str().unwrap(),
        "--mesh",
        "b.ply",
        "--name",
        "y",
        "--photos",
        empty.to_str().unwrap(),
    ]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("one object per model"), "{err}");
    // A fold needs at least one training pass.
    let (code, err) = run(&[
        "--mesh",
        junk.to_str().unwrap(),
        "--photos",
        empty.to_str().unwrap(),
        "--fold-passes",
        "0",
    ]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("--fold-passes"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Two objects trained jointly into one model (`--mesh a --name a --mesh b
/// --name b`): the components carry their objects' labels, each object is
/// the best detection of its own label in new renders of it, the other
/// object's best detection there scores lower, and a pose without a start
/// needs the mesh's label.
#[test]
fn two_meshes_trained_jointly_detect_each_object_under_its_own_label() {
    let dir = std::env::temp_dir().join(format!("sdhop-mesh-joint-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let plys = [
        ("box", coloured_box_ply()),
        (
            "bar",
            coloured_cuboid_ply([24.0, 24.0, 80.0], [[40, 200, 60], [230, 220, 40]]),
        ),
    ];
    for (name, ply) in &plys {
        std::fs::write(dir.join(format!("{name}.ply")), ply).unwrap();
    }
    let bgs = dir.join("bg");
    write_backgrounds(&bgs, 8);
    let out = dir.join("models/joint.safetensors");
    let ply = |n: &str| dir.join(format!("{n}.ply")).to_str().unwrap().to_string();
    train_mesh(&[
        "--mesh",
        &ply("box"),
        "--name",
        "box",
        "--mesh",
        &ply("bar"),
        "--name",
        "bar",
        "--backgrounds",
        bgs.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--work",
        dir.join("work").to_str().unwrap(),
        "--renders",
        "60",
        "--components",
        "2",
        // The mechanics on HOG cells, an eighth of the learned cells'
        // cost (the library test below trains the route's default).
        "--features",
        "hog",
        "--negatives",
        "6",
        "--max-passes",
        "6",
    ]);
    let model = Model::load(&out).unwrap();
    assert_eq!(model.meta.name, "box-bar");
    let labels: Vec<&str> = model
        .meta
        .viewpoints
        .iter()
        .map(|v| v.label.as_str())
        .collect();
    assert_eq!(labels, ["box", "box", "bar", "bar"]);
    assert!(model
        .meta
        .viewpoints
        .iter()
        .all(|v| !v.rotations.is_empty()));
    let opts = sdhop::pipeline::DetectOptions {
        threshold: Some(-1e9),
        max_detections: Some(1),
        masks: sdhop::pipeline::MaskMode::None,
        ..Default::default()
    };
    let others: Vec<ColorImage> = (0..3)
        .map(|i| background(640, 480, 700 + i).unwrap())
        .collect();
    let mut meshes = Vec::new();
    for (k, (name, ply)) in plys.iter().enumerate() {
        let mesh = Mesh::parse(ply.as_bytes()).unwrap();
        let colours = Mesh::ply_vertex_colours(ply.as_bytes()).unwrap();
        let test = render_set(
            &mesh,
            colours.as_deref(),
            name,
            &others,
            &RenderParams {
                renders: 10,
                components: 1,
                seed: 55 + k as u64,
                ..RenderParams::default()
            },
            &dir.join(format!("test-{name}")),
            &ProgressBar::hidden(),
        )
        .unwrap();
        let (mut found, mut above) = (0, 0);
        for s in &test.samples {
            let img = sdhop::data::load_image(&s.image).unwrap();
            // The best detection of each label (each label is suppressed
            // and counted on its own).
            let best = |label: &str| {
                let o = sdhop::pipeline::DetectOptions {
                    label: Some(label.to_string()),
                    ..opts.clone()
                };
                let dets = sdhop::pipeline::detect_image(&img, &[&model], &o)
                    .unwrap()
                    .detections;
                assert_eq!(dets.len(), 1, "{dets:?}");
                assert_eq!(dets[0].label, label);
                dets.into_iter().next().unwrap()
            };
            let a = s.annotation.as_ref().unwrap();
            let mine = best(name);
            let other = best(plys[1 - k].0);
            let b = &mine.bbox;
            found += usize::from(box_iou((b.x, b.y, b.width, b.height), a.bbox) >= 0.5);
            above += usize::from(mine.score > other.score);
        }
        eprintln!("{name}: found in {found} of 10, above the other object in {above}");
        assert!(found >= 4, "{name}: found in {found} of 10 new renders");
        assert!(
            above >= 7,
            "{name}: above the other object in {above} of 10"
        );
        meshes.push((mesh, test));
    }
    // Pose without a start: the model has two labels, so the request must
    // name the mesh's; with it, the detection used is of that label.
    let (mesh, test) = &meshes[0];
    let img = sdhop::data::load_image(&test.samples[0].image).unwrap();
    let mut params = PoseParams {
        intrinsics: Intrinsics {
            fx: 575.0,
            fy: 575.0,
            cx: 160.0,
            cy: 120.0,
        },
        initial_pose: None,
        label: None,
        model: Some("box-bar".into()),
        mask: None,
        max_iterations: None,
        start_uncertainty: None,
    };
    let err = estimate(&img, mesh, &params, None, &[&model]).unwrap_err();
    assert!(err.to_string().contains("label"), "{err}");
    params.label = Some("cup".into());
    let err = estimate(&img, mesh, &params, None, &[&model]).unwrap_err();
    assert!(err.to_string().contains("cup"), "{err}");
    params.label = Some("box".into());
    let r = estimate(&img, mesh, &params, None, &[&model]).unwrap();
    assert_eq!(r.detection.unwrap().label, "box");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `--photos` with its default route (`boxes`): box-labelled photographs
/// of the box (renders of one seed over generated scenes, saved with their
/// boxes only) and the mesh's renders drawn over those photographs train
/// one model; it records the route, gives its component start poses, and
/// finds the box in renders over other scenes.
#[test]
fn mesh_with_box_photographs_trains_them_beside_renders_drawn_over_them() {
    let dir = std::env::temp_dir().join(format!("sdhop-mesh-photos-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let ply = dir.join("box.ply");
    std::fs::write(&ply, coloured_box_ply()).unwrap();
    let mesh = Mesh::parse(&std::fs::read(&ply).unwrap()).unwrap();
    let colours = Mesh::ply_vertex_colours(&std::fs::read(&ply).unwrap()).unwrap();
    let scenes: Vec<ColorImage> = (0..4)
        .map(|i| background(640, 480, 300 + i).unwrap())
        .collect();
    // The user's photographs: boxes only (no masks, no poses).
    let photos = render_set(
        &mesh,
        colours.as_deref(),
        "box",
        &scenes,
        &RenderParams {
            renders: 16,
            components: 1,
            seed: 5,
            ..RenderParams::default()
        },
        &dir.join("photos"),
        &ProgressBar::hidden(),
    )
    .unwrap();
    let mut images = Vec::new();
    let mut annotations = Vec::new();
    for (i, s) in photos.samples.iter().enumerate() {
        let a = s.annotation.as_ref().unwrap();
        images.push(serde_json::json!({
            "id": i + 1, "width": 320, "height": 240,
            "file_name": s.image.file_name().unwrap().to_str().unwrap(),
        }));
        let (x, y, w, h) = a.bbox;
        annotations.push(serde_json::json!({
            "id": i + 1, "image_id": i + 1, "category_id": 1,
            "bbox": [x, y, w, h], "iscrowd": 0,
        }));
    }
    let coco = dir.join("photos/boxes.json");
    std::fs::write(
        &coco,
        serde_json::json!({
            "images": images, "annotations": annotations,
            "categories": [{"id": 1, "name": "box"}],
        })
        .to_string(),
    )
    .unwrap();
    let out = dir.join("models/box.safetensors");
    let work = dir.join("work");
    train_mesh(&[
        "--mesh",
        ply.to_str().unwrap(),
        "--name",
        "box",
        "--photos",
        coco.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--work",
        work.to_str().unwrap(),
        "--renders",
        "40",
        "--features",
        "hog",
        "--max-passes",
        "3",
        "--latent-rounds",
        "1",
    ]);
    let model = Model::load(&out).unwrap();
    let photos_meta = &model.meta.provenance["mesh"]["photos"];
    assert_eq!(photos_meta["route"], "boxes", "{photos_meta}");
    assert_eq!(photos_meta["boxes"], 16);
    assert_eq!(photos_meta["fold_passes"], 8, "{photos_meta}");
    // The renders were drawn at the photographs' boxes' sizes.
    let sides: Vec<f64> = photos
        .samples
        .iter()
        .map(|s| {
            let b = s.annotation.as_ref().unwrap().bbox;
            b.2.max(b.3)
        })
        .collect();
    let size = &model.meta.provenance["mesh"]["render"]["size"];
    let lo = sides.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = sides.iter().copied().fold(0.0, f64::max);
    assert!((size[0].as_f64().unwrap() - lo).abs() < 1e-9, "{size} {lo}");
    assert!((size[1].as_f64().unwrap() - hi).abs() < 1e-9, "{size} {hi}");
    // Both models were scored on the held-out photographs, and the
    // better one kept.
    let check = &model.meta.provenance["renders_check"];
    let auc = |key: &str| {
        check[key]
            .as_f64()
            .unwrap_or_else(|| panic!("no {key} in {check}"))
    };
    let (with, alone) = (
        auc("held_out_auc_with_renders"),
        auc("held_out_auc_photographs_alone"),
    );
    // The renders stay only ahead beyond the resamples' chance.
    let kept = if with > alone && auc("renders_ahead_in_resamples") >= auc("confidence_needed") {
        "renders"
    } else {
        "photographs-alone"
    };
    assert_eq!(check["kept"], kept, "{check}");
    // The kept model carries its own folds' figure (the photographs
    // alone are checked by their folds before their full training).
    assert_eq!(
        model.meta.provenance["held_out_auc"].as_f64(),
        Some(if kept == "renders" { with } else { alone }),
        "{}",
        model.meta.provenance
    );
    for v in &model.meta.viewpoints {
        assert!(!v.rotations.is_empty());
        let d = v.direction.expect("a viewing direction per component");
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        assert!((n - 1.0).abs() < 1e-6);
    }
    // The renders were drawn over the photographs: 40 of them, each a
    // positive beside the 16 photographs.
    assert!(work.join("box_00039.jpg").is_file());
    let (hits, _) = found_in_new_renders(&model, &mesh, colours.as_deref(), &dir.join("test"));
    assert!(hits >= 14, "{hits} of 20 new renders found");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The mesh route is a library function: called without the binary, with
/// its settings' defaults and a few overrides, it trains the same kind of
/// model the command saves; settings that cannot train are refused before
/// any work, as bad input.
#[test]
fn the_mesh_route_trains_from_the_library_and_refuses_bad_settings() {
    use sdhop::train::routes::mesh::{train_mesh, MeshSettings};
    use sdhop::train::routes::{RouteError, TrainSettings};
    let dir = std::env::temp_dir().join(format!("sdhop-mesh-lib-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let ply = dir.join("box.ply");
    std::fs::write(&ply, coloured_box_ply()).unwrap();
    let bgs = dir.join("bg");
    write_backgrounds(&bgs, 6);
    let settings = MeshSettings {
        mesh: vec![ply.clone()],
        name: vec!["box".into()],
        backgrounds: Some(bgs.clone()),
        work: Some(dir.join("work")),
        renders: Some(24),
        components: 2,
        negatives: 4,
        settings: TrainSettings {
            max_passes: Some(2),
            ..TrainSettings::default()
        },
        ..MeshSettings::default()
    };
    let trained = train_mesh(&settings).unwrap();
    assert_eq!(trained.name, "box");
    assert_eq!(trained.model.meta.viewpoints.len(), 2);
    assert!(trained
        .model
        .meta
        .viewpoints
        .iter()
        .all(|v| v.direction.is_some()));
    // The mesh route's defaults, stated beside it, reached the model.
    assert_eq!(trained.model.meta.pyramid.levels_per_octave, 5);
    assert!((trained.model.meta.pyramid.max_scale - 2.5).abs() < 1e-6);
    assert!(trained.report.passes <= 2);
    let refused = |s: MeshSettings| match train_mesh(&s) {
        Err(RouteError::Input(m)) => m,
        Err(e) => panic!("not an input error: {e}"),
        Ok(_) => panic!("trained with bad settings"),
    };
    let msg = refused(MeshSettings {
        name: vec!["box".into(), "other".into()],
        ..settings.clone()
    });
    assert!(msg.contains("one name per mesh"), "{msg}");
    let msg = refused(MeshSettings {
        backgrounds: None,
        ..settings.clone()
    });
    assert!(msg.contains("--backgrounds"), "{msg}");
    let _ = std::fs::remove_dir_all(&dir);
}
