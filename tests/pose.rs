//! Edge-based pose refinement (IRLS and OR-IRLS) on rendered scenes with
//! exact ground truth.

use nalgebra::{Rotation3, Vector2, Vector3, Vector6};

use sdhop::pose::irls::residual_and_jacobian;
use sdhop::pose::render::{background, perturb, render};
use sdhop::pose::{refine, EdgeModel, Intrinsics, IrlsParams, Mesh, Pose};
use sdhop::vision::rng::SplitMix64;

const K: Intrinsics = Intrinsics {
    fx: 600.0,
    fy: 600.0,
    cx: 320.0,
    cy: 240.0,
};

fn truth(seed: u64) -> Pose {
    let mut rng = SplitMix64::new(seed);
    Pose {
        rotation: Rotation3::from_euler_angles(
            rng.range_f64(-0.6, 0.6) + 0.4,
            rng.range_f64(-0.6, 0.6) + 0.5,
            rng.range_f64(-0.8, 0.8),
        )
        .into_inner(),
        translation: Vector3::new(rng.range_f64(-0.03, 0.03), rng.range_f64(-0.03, 0.03), 0.5),
    }
}

#[test]
fn jacobian_matches_finite_differences() {
    let mut rng = SplitMix64::new(5);
    for case in 0..20 {
        let pose = truth(case);
        let point = Vector3::new(
            rng.range_f64(-0.07, 0.07),
            rng.range_f64(-0.07, 0.07),
            rng.range_f64(-0.07, 0.07),
        );
        let a = rng.range_f64(0.0, std::f64::consts::TAU);
        let normal = Vector2::new(a.cos(), a.sin());
        let target = Vector2::new(rng.range_f64(200.0, 400.0), rng.range_f64(150.0, 300.0));
        let (r0, j) = residual_and_jacobian(&K, &pose, &point, &normal, &target).unwrap();
        let h = 1e-7;
        for i in 0..6 {
            let mut xi = Vector6::zeros();
            xi[i] = h;
            let (r1, _) =
                residual_and_jacobian(&K, &pose.updated(&xi), &point, &normal, &target).unwrap();
            let fd = (r1 - r0) / h;
            assert!(
                (fd - j[i]).abs() <= 1e-4 * (1.0 + j[i].abs()),
                "case {case}, component {i}: finite difference {fd}, Jacobian {}",
                j[i]
            );
        }
    }
}

/// Rotation (degrees) and translation (mm) errors of a result.
fn errors(est: &Pose, truth: &Pose) -> (f64, f64) {
    let (angle, dist) = est.distance(truth);
    (angle.to_degrees(), dist * 1e3)
}

/// The rotation (degrees) from `b` to `a` about the object's own z axis
/// (the twist of their relative rotation in the object's frame).
fn spin_degrees(a: &Pose, b: &Pose) -> f64 {
    let rel = Rotation3::from_matrix_unchecked(b.rotation.transpose() * a.rotation);
    let q = nalgebra::UnitQuaternion::from_rotation_matrix(&rel);
    (2.0 * q.k.atan2(q.w)).to_degrees()
}

#[test]
fn unoccluded_scenes_converge_to_the_true_pose() {
    let meshes = [
        ("box", Mesh::cuboid(0.15, 0.1, 0.07)),
        ("cylinder", Mesh::cylinder(0.04, 0.15, 48)),
    ];
    let params = IrlsParams::default();
    for (name, mesh) in &meshes {
        let edges = EdgeModel::new(mesh, params.crease_degrees);
        for seed in 0..3 {
            let pose = truth(seed);
            let bg = background(640, 480, 100 + seed).unwrap();
            let scene = render(mesh, &K, &pose, &bg, 0.0, 0.0, seed).unwrap();
            let start = perturb(&pose, 0.01, 5.0, 200 + seed);
            let r = refine(&scene.image, &edges, &K, &start, None, &params).unwrap();
            let (deg, mm) = errors(&r.pose, &pose);
            let (deg0, mm0) = errors(&start, &pose);
            println!(
                "{name} {seed}: start {deg0:.2} deg {mm0:.1} mm -> {deg:.3} deg {mm:.2} mm, {} iterations, {} inliers of {}, rms {:.2} px",
                r.iterations, r.inliers, r.samples, r.residual_rms_px
            );
            // The cylinder's rotation about its own axis is unobservable
            // from its edges: compare its axis instead.
            let deg = if *name == "cylinder" {
                let a = r.pose.rotation * Vector3::z();
                let b = pose.rotation * Vector3::z();
                a.angle(&b).to_degrees()
            } else {
                deg
            };
            println!("{name} {seed}: error {deg:.3} deg (axis for the cylinder), {mm:.2} mm");
            assert!(mm < 2.0 && deg < 0.5, "{name} {seed}: {deg} deg, {mm} mm");
            if *name == "box" {
                assert!(r.converged, "{name} {seed}: not converged");
            }
        }
    }
}

#[test]
fn the_start_prior_holds_what_the_edges_cannot_see() {
    // A cylinder's spin about its axis leaves its edges unchanged: without
    // the start prior it drifts with the image noise, with it it stays
    // where the start had it (one track, no restarts and edges only, to
    // see the edge steps and the prior alone: the colour steps also hold
    // the 48-sided cylinder's faceted outline a little).
    let mesh = Mesh::cylinder(0.04, 0.15, 48);
    let single = IrlsParams {
        restart_degrees: 0.0,
        restart_depth: 0.0,
        region_weight: 0.0,
        ..IrlsParams::default()
    };
    let edges = EdgeModel::new(&mesh, single.crease_degrees);
    let (mut held, mut free) = (0.0f64, 0.0f64);
    for seed in 0..3 {
        let pose = truth(seed);
        let bg = background(640, 480, 100 + seed).unwrap();
        let scene = render(&mesh, &K, &pose, &bg, 0.0, 0.0, seed).unwrap();
        let start = perturb(&pose, 0.01, 5.0, 200 + seed);
        let anchored = refine(&scene.image, &edges, &K, &start, None, &single).unwrap();
        let unanchored = IrlsParams {
            start_sigma_degrees: 0.0,
            start_sigma_translation: Some(0.0),
            ..single
        };
        let drifting = refine(&scene.image, &edges, &K, &start, None, &unanchored).unwrap();
        let (a, b) = (
            spin_degrees(&anchored.pose, &start),
            spin_degrees(&drifting.pose, &start),
        );
        println!("seed {seed}: spin moved {a:.3} deg anchored, {b:.3} deg without");
        // The axis still converges from 5 degrees off (to within 1: the
        // MAP prior weighs the start against the edges, which on these
        // clean renders leaves about half a degree).
        let axis = (anchored.pose.rotation * Vector3::z())
            .angle(&(pose.rotation * Vector3::z()))
            .to_degrees();
        assert!(axis < 1.0, "seed {seed}: axis {axis} deg off");
        held = held.max(a.abs());
        free = free.max(b.abs());
    }
    // With sigma = 5 degrees on the start (the prior weighs it against
    // what the noise suggests) the spin stays within a degree and a half.
    assert!(held < 1.5, "the held spin moved {held} deg");
    assert!(free > 2.0 * held, "without the prior: {free} deg");
}

#[test]
fn occluded_scenes_need_the_visibility_mask() {
    let mesh = Mesh::cuboid(0.15, 0.1, 0.07);
    // Without the start prior, which also holds a plain IRLS fit near a
    // good start and so hides part of what the mask does.
    let params = IrlsParams {
        start_sigma_degrees: 0.0,
        start_sigma_translation: Some(0.0),
        ..IrlsParams::default()
    };
    let edges = EdgeModel::new(&mesh, params.crease_degrees);
    let (mut with_mask, mut without) = (0, 0);
    let n = 16;
    for seed in 0..n {
        let pose = truth(seed);
        let bg = background(640, 480, 300 + seed).unwrap();
        let scene = render(&mesh, &K, &pose, &bg, 0.45, 4.0, seed).unwrap();
        let start = perturb(&pose, 0.01, 5.0, 400 + seed);
        let ok = |r: Result<sdhop::pose::PoseResult, _>| match r {
            Ok(r) => {
                let (deg, mm) = errors(&r.pose, &pose);
                println!(
                    "  {deg:.2} deg {mm:.1} mm, {} iterations, {} inliers of {}",
                    r.iterations, r.inliers, r.samples
                );
                deg < 1.0 && mm < 3.0
            }
            Err(e) => {
                println!("  {e}");
                false
            }
        };
        let a = ok(refine(
            &scene.image,
            &edges,
            &K,
            &start,
            Some(&scene.visible),
            &params,
        ));
        let b = ok(refine(&scene.image, &edges, &K, &start, None, &params));
        println!(
            "seed {seed}: occluded {:.0}%, OR-IRLS {a}, IRLS {b}",
            100.0 * scene.occluded_fraction
        );
        with_mask += usize::from(a);
        without += usize::from(b);
    }
    println!("converged: OR-IRLS {with_mask}/{n}, IRLS {without}/{n}");
    // Measured: OR-IRLS 13/16, IRLS 5/16 (with the default start prior
    // 13/16 and 11/16).
    assert!(
        10 * with_mask as u64 >= 7 * n,
        "OR-IRLS converged {with_mask}/{n}"
    );
    assert!(
        with_mask as u64 >= without as u64 + n / 4,
        "OR-IRLS {with_mask} vs IRLS {without}"
    );
}

#[test]
fn cli_refines_a_pose_with_a_given_mask_and_refuses_bad_meshes() {
    use std::process::Command;
    let dir = std::env::temp_dir().join(format!("sdhop-pose-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let mesh = Mesh::cuboid(0.15, 0.1, 0.07);
    let pose = truth(6);
    let bg = background(640, 480, 306).unwrap();
    let scene = render(&mesh, &K, &pose, &bg, 0.45, 4.0, 6).unwrap();
    scene.image.to_rgb8().save(dir.join("scene.png")).unwrap();
    let mut mask = image::GrayImage::new(640, 480);
    for (x, y, p) in mask.enumerate_pixels_mut() {
        p.0[0] = if scene.visible.get(x as usize, y as usize) {
            255
        } else {
            0
        };
    }
    mask.save(dir.join("mask.png")).unwrap();
    std::fs::write(dir.join("box.ply"), mesh.to_ply(true)).unwrap();
    std::fs::write(dir.join("bad.obj"), "v 0 0 0\nf 1 2 3\n").unwrap();
    let start = perturb(&pose, 0.01, 5.0, 406);
    let rows = start.rotation_rows();
    let params = serde_json::json!({
        "intrinsics": {"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy},
        "initial_pose": {"rotation": rows, "translation": [start.translation.x, start.translation.y, start.translation.z]},
        "mask": "provided"
    });
    std::fs::write(dir.join("params.json"), params.to_string()).unwrap();
    let run = |mesh: &str| {
        Command::new(env!("CARGO_BIN_EXE_sdhop-train"))
            .arg("pose")
            .arg("--image")
            .arg(dir.join("scene.png"))
            .arg("--mesh")
            .arg(dir.join(mesh))
            .arg("--params")
            .arg(dir.join("params.json"))
            .arg("--mask")
            .arg(dir.join("mask.png"))
            .output()
            .unwrap()
    };
    let out = run("box.ply");
    assert_succeeded(&out);
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["mask_source"], "provided");
    let r = &v["pose"]["rotation"];
    let est = Pose::from_client(
        std::array::from_fn(|i| std::array::from_fn(|j| r[i][j].as_f64().unwrap())),
        std::array::from_fn(|i| v["pose"]["translation"][i].as_f64().unwrap()),
    )
    .unwrap();
    let (deg, mm) = errors(&est, &pose);
    assert!(deg < 1.0 && mm < 3.0, "{deg} deg, {mm} mm");
    assert_eq!(v["covariance"].as_array().unwrap().len(), 6);
    let bad = run("bad.obj");
    assert_eq!(bad.status.code(), Some(2), "a bad mesh is bad input");
    assert!(String::from_utf8_lossy(&bad.stderr).contains("mesh"));
    let _ = std::fs::remove_dir_all(&dir);
}

/// The occlusion benchmark end to end on a few scenes over the CMU_KO8
/// negatives: the training set it writes is a COCO file the trainer reads,
/// and the benchmark reports every method's six errors. Needs
/// `../shared/data/cmu_ko8` (ignored by default; CI runs it with
/// `--include-ignored`).
#[test]
#[ignore = "needs ../shared/data/cmu_ko8"]
fn occlusion_benchmark_writes_training_data_and_scores_the_methods() {
    use std::process::Command;
    let negatives =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/cmu_ko8/negative");
    assert!(negatives.is_dir(), "needs {}", negatives.display());
    let dir = std::env::temp_dir().join(format!("sdhop-pose-bench-{}", std::process::id()));
    let bin = env!("CARGO_BIN_EXE_sdhop-train");
    let out = Command::new(bin)
        .args([
            "pose-data",
            "--scenes",
            "3",
            "--train-backgrounds",
            "4",
            "--backgrounds",
        ])
        .arg(&negatives)
        .arg("--out")
        .arg(&dir)
        .output()
        .unwrap();
    assert_succeeded(&out);
    for object in ["box", "bottle"] {
        let loaded = sdhop::data::load_coco(&dir.join("coco.json"), &dir, object).unwrap();
        assert!(loaded.skipped.is_empty(), "{:?}", loaded.skipped);
        let positives: Vec<_> = loaded
            .samples
            .iter()
            .filter_map(|s| s.annotation.as_ref())
            .collect();
        assert_eq!(positives.len(), 3);
        // The full box holds the visible pixels.
        for a in positives {
            let (x0, y0, x1, y1) = a.visible.tight_box().unwrap();
            let (x, y, w, h) = a.bbox;
            assert!(x <= x0 as f64 && y <= y0 as f64 && x + w >= x1 as f64 && y + h >= y1 as f64);
        }
        assert_eq!(
            loaded.samples.len(),
            3 + 3 + 4,
            "3 of each object and 4 negatives"
        );
    }
    let report = dir.join("report.json");
    let out = Command::new(bin)
        .args([
            "pose-bench",
            "--scenes",
            "2",
            "--train-backgrounds",
            "4",
            "--backgrounds",
        ])
        .arg(&negatives)
        .arg("--models-dir")
        .arg(dir.join("no-models"))
        .arg("--report")
        .arg(&report)
        .output()
        .unwrap();
    assert_succeeded(&out);
    let doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    let results = doc["results"].as_array().unwrap();
    assert_eq!(results.len(), 4, "two objects, two conditions");
    for r in results {
        let summaries = r["summaries"].as_array().unwrap();
        let methods: Vec<&str> = summaries
            .iter()
            .map(|s| s["method"].as_str().unwrap())
            .collect();
        assert_eq!(
            methods,
            ["irls", "or_irls_exact"],
            "no detector models: no SD-HOP mask"
        );
        for s in summaries {
            let e = s["mean_errors"].as_array().unwrap();
            assert_eq!(e.len(), 6);
            assert!(e.iter().all(|v| v.as_f64().unwrap().is_finite()));
        }
        if r["occlusion"][1].as_f64().unwrap() > 0.0 {
            let hidden = r["mean_hidden"].as_f64().unwrap();
            assert!((0.2..=0.6).contains(&hidden), "{hidden}");
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Asserts that a CLI run exited 0, showing its stderr otherwise.
fn assert_succeeded(out: &std::process::Output) {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A box whose render is cut by the image's left border (its centre 20
/// pixels inside, so about 40% of it is outside) converges to the true pose
/// from a 5 degree / 10 mm start: the missing part gives no edge samples
/// and no colour steps, and the border is no edge.
#[test]
fn a_render_cut_by_the_border_converges() {
    let mesh = Mesh::cuboid(0.15, 0.1, 0.07);
    let params = IrlsParams::default();
    let edges = EdgeModel::new(&mesh, params.crease_degrees);
    let k = Intrinsics { cx: 20.0, ..K };
    for seed in 0..3 {
        let mut pose = truth(seed);
        pose.translation.x = 0.0;
        let bg = background(640, 480, 300 + seed).unwrap();
        let scene = render(&mesh, &k, &pose, &bg, 0.0, 0.0, seed).unwrap();
        let start = perturb(&pose, 0.01, 5.0, 400 + seed);
        let r = refine(&scene.image, &edges, &k, &start, None, &params).unwrap();
        let (deg, mm) = errors(&r.pose, &pose);
        let (deg0, mm0) = errors(&start, &pose);
        println!(
            "cut box {seed}: start {deg0:.2} deg {mm0:.1} mm -> {deg:.3} deg {mm:.2} mm, {} iterations, {} samples",
            r.iterations, r.samples
        );
        assert!(mm < 3.0 && deg < 1.0, "cut box {seed}: {deg} deg, {mm} mm");
    }
}
