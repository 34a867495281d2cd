//! `sdhop-train bop-eval`: the whole pipeline on real photographs in BOP
//! format (LM-O). Detection and visible masks exactly as
//! `lmo_detect_eval.py` scores them, and the pose from no start (detect,
//! then OR-IRLS from the detection's start poses, as `POST /pose` without
//! `initial_pose`): the share of instances with ADD(-S) below 10% of the
//! diameter and the BOP-style success. Other model folders (ablations
//! trained on the same renders: `--no-occlusion`, `--no-hop`) are scored
//! on the same photographs beside it. Prints tables, writes a JSON report
//! and a plot.

use super::*;
use crate::data::bop::Bop;
#[cfg(test)]
use crate::eval::bop_detect::DetectScore;
use crate::eval::bop_pose::add_points;
use crate::eval::bop_run::{evaluate, name_of, PoseMask, PoseOutcome, ScanSettings, Variant};
use crate::pose::Mesh;

#[derive(clap::Args)]
pub(crate) struct BopEvalArgs {
    /// BOP dataset root (models/ and test/SCENE/), e.g. ../shared/data/lmo_dev.
    #[arg(long, required_unless_present = "merge")]
    pub(crate) data: Option<PathBuf>,
    /// Folder of the detectors to evaluate; their labels are BOP object
    /// names (ape, can, cat, ...).
    #[arg(long, required_unless_present = "merge")]
    pub(crate) models_dir: Option<PathBuf>,
    /// Instead of scoring: join the reports of earlier runs into one table,
    /// report and plot, as NAME=REPORT.json (repeat it). Each report's
    /// first variant goes into the row NAME, and the reports given the
    /// same NAME are joined object by object: e.g. one run per object and
    /// training route, each with its own model only.
    #[arg(long = "merge", value_parser = parse_named_dir, conflicts_with_all = ["data", "models_dir", "compare", "pose", "transfer"])]
    pub(crate) merge: Vec<(String, PathBuf)>,
    /// Further folders scored the same way, as NAME=DIR (e.g.
    /// plain-hog=out/plain): ablations trained on the same renders.
    #[arg(long = "compare", value_parser = parse_named_dir)]
    pub(crate) compare: Vec<(String, PathBuf)>,
    /// Detection threshold (scores of the acceptance query).
    #[arg(long, default_value_t = -1.5, allow_negative_numbers = true)]
    pub(crate) threshold: f64,
    #[arg(long, default_value_t = 20)]
    pub(crate) max_detections: usize,
    /// Largest |oracle_visib_fract - visib_fract| of the segmentation and
    /// pose instances.
    #[arg(long, default_value_t = 0.10)]
    pub(crate) max_oracle_gap: f64,
    /// Also the pose from no start of every instance scored for
    /// segmentation (visib_fract >= 0.4), with the evaluated models only.
    #[arg(long)]
    pub(crate) pose: bool,
    /// With `--pose`: the mask the refinements fit in. `detect` (the
    /// default, as `POST /pose` without `initial_pose`): the detection's
    /// visible mask; `oracle`: the instance's true visible mask from the
    /// dataset (a diagnostic: how much the detection's mask costs; the
    /// start poses still come from the detection); `none`: no mask.
    #[arg(long, value_enum, default_value_t = PoseMask::Detect, requires = "pose")]
    pub(crate) pose_mask: PoseMask,
    /// Also score the evaluated models with response transfer between
    /// them (`transfer=true` of `POST /detect`), as a further variant.
    #[arg(long)]
    pub(crate) transfer: bool,
    /// Only every n-th photograph (a quick check).
    #[arg(long, default_value_t = 1)]
    pub(crate) every: usize,
    /// The first N photographs (by image id) trained the detectors (their
    /// boxes, as `lmo_boxes_coco.py --first N` writes them): they are left
    /// out of the scoring, as `lmo_detect_eval.py --train-photos N` does.
    #[arg(long, default_value_t = 0)]
    pub(crate) train_photos: usize,
    /// JSON report (default out/bop-eval/report.json) and plot beside it.
    #[arg(long, default_value = "out/bop-eval")]
    pub(crate) out: PathBuf,
}

fn parse_named_dir(text: &str) -> Result<(String, PathBuf), String> {
    match text.split_once('=') {
        Some((n, d)) if !n.trim().is_empty() && !d.trim().is_empty() => {
            Ok((n.trim().to_string(), PathBuf::from(d.trim())))
        }
        _ => Err(format!("expected NAME=DIR, got {text:?}")),
    }
}

fn print_variant(v: &Variant) {
    println!(
        "{} ({}, {} features), detection {:.0} ms per image",
        v.name, v.models_dir, v.features, v.detect_ms_per_image
    );
    println!(
        "{:<12} {:>6} {:>8} {:>5} {:>7} {:>7} {:>5}",
        "object", "AUC", "R@1FPPI", "pos", "segerr", "raw", "nseg"
    );
    for s in &v.objects {
        println!(
            "{:<12} {:>6.3} {:>8.3} {:>5} {:>7.4} {:>7.4} {:>5}",
            s.object,
            s.auc,
            s.recall_at_1fppi,
            s.positives,
            s.seg_error,
            s.seg_error_raw,
            s.seg_instances
        );
    }
    println!(
        "{:<12} {:>6.3} {:>8.3} {:>5} {:>7.4} {:>7.4}",
        "mean", v.mean_auc, v.mean_recall_at_1fppi, "", v.mean_seg_error, v.mean_seg_error_raw
    );
    let pct = |x: Option<f64>| x.map_or("-".to_string(), |x| format!("{:.1}", 100.0 * x));
    println!(
        "COCO AP (BOP 2022, {} objects): boxes AP {} AP50 {} AP75 {}; masks AP {} AP50 {} AP75 {}",
        v.box_ap.categories,
        pct(v.box_ap.ap),
        pct(v.box_ap.ap50),
        pct(v.box_ap.ap75),
        pct(v.mask_ap.ap),
        pct(v.mask_ap.ap50),
        pct(v.mask_ap.ap75)
    );
    if let Some(r) = v.mspd_recall {
        println!("pose from no start: BOP MSPD recall {r:.3} (5-50 px)");
    }
    if !v.pose.is_empty() {
        println!(
            "pose from no start: {:<10} {:>4} {:>9} {:>9} {:>8} {:>8}",
            "object", "n", "ADD<10%d", "BOP succ", "refused", "s median"
        );
        let mut names: Vec<&str> = v.pose.iter().map(|p| p.object.as_str()).collect();
        names.sort_unstable();
        names.dedup();
        for name in names.iter().copied().chain(std::iter::once("all")) {
            let rs: Vec<&PoseOutcome> = v
                .pose
                .iter()
                .filter(|p| name == "all" || p.object == name)
                .collect();
            let n = rs.len().max(1) as f64;
            let mut secs: Vec<f64> = rs.iter().map(|p| p.seconds).collect();
            secs.sort_by(f64::total_cmp);
            println!(
                "                    {:<10} {:>4} {:>9.3} {:>9.3} {:>8} {:>8.2}",
                name,
                rs.len(),
                rs.iter().filter(|p| p.add_ok).count() as f64 / n,
                rs.iter().filter(|p| p.success).count() as f64 / n,
                rs.iter().filter(|p| p.error.is_some()).count(),
                secs.get(secs.len() / 2).copied().unwrap_or(0.0)
            );
        }
        print_pose_stages(&v.pose);
    }
}

/// Where the pose from no start fails, stage by stage: shares of all the
/// instances (per object and all).
fn print_pose_stages(pose: &[PoseOutcome]) {
    let share = |rs: &[&PoseOutcome], f: &dyn Fn(&PoseOutcome) -> bool| {
        rs.iter().filter(|p| f(p)).count() as f64 / rs.len().max(1) as f64
    };
    let below = |v: Option<f64>, limit: f64| v.is_some_and(|v| v < limit);
    println!(
        "pose stages:        {:<10} {:>9} {:>10} {:>10} {:>10} {:>10} {:>9}",
        "object", "det IoU.5", "near 30deg", "any 30deg", "start 30d", "start 50mm", "ADD<10%d"
    );
    let mut names: Vec<&str> = pose.iter().map(|p| p.object.as_str()).collect();
    names.sort_unstable();
    names.dedup();
    for name in names.iter().copied().chain(std::iter::once("all")) {
        let rs: Vec<&PoseOutcome> = pose
            .iter()
            .filter(|p| name == "all" || p.object == name)
            .collect();
        println!(
            "                    {:<10} {:>9.3} {:>10.3} {:>10.3} {:>10.3} {:>10.3} {:>9.3}",
            name,
            share(&rs, &|p| p.detection_iou.is_some_and(|v| v >= 0.5)),
            share(&rs, &|p| below(p.nearest_rotation, 30.0)),
            share(&rs, &|p| below(p.nearest_rotation_any, 30.0)),
            share(&rs, &|p| below(p.start_angle, 30.0)),
            share(&rs, &|p| below(p.start_t_error, 50.0)),
            share(&rs, &|p| p.add_ok),
        );
    }
    // The answers just past (ADD(-S) 10-20% d) and those within: their
    // median errors along and across the viewing ray, and of rotation.
    println!(
        "pose errors:        {:<10} {:>9} {:>4} {:>10} {:>10} {:>10}",
        "object", "answers", "n", "|depth| mm", "across mm", "angle deg"
    );
    for name in names.iter().copied().chain(std::iter::once("all")) {
        for (what, keep) in [
            (
                "within",
                (|p: &PoseOutcome| p.add_ok) as fn(&PoseOutcome) -> bool,
            ),
            ("just past", |p: &PoseOutcome| p.near_miss),
        ] {
            let rs: Vec<&PoseOutcome> = pose
                .iter()
                .filter(|p| (name == "all" || p.object == name) && keep(p))
                .collect();
            let med = |f: &dyn Fn(&PoseOutcome) -> Option<f64>| {
                let v: Vec<f64> = rs.iter().filter_map(|p| f(p)).collect();
                crate::eval::median(v)
            };
            println!(
                "                    {:<10} {:>9} {:>4} {:>10.1} {:>10.1} {:>10.1}",
                name,
                what,
                rs.len(),
                med(&|p| p.depth_error.map(f64::abs)),
                med(&|p| p.lateral_error),
                med(&|p| p.angle),
            );
        }
    }
}

pub(crate) fn run_bop_eval(args: &BopEvalArgs) -> Result<(), Failure> {
    if !args.merge.is_empty() {
        return merge_reports(&args.merge, &args.out);
    }
    if args.every == 0 {
        return Err(Failure::input("--every must be at least 1"));
    }
    let (Some(data), Some(models_dir)) = (&args.data, &args.models_dir) else {
        return Err(Failure::input(
            "--data and --models-dir are needed to score",
        ));
    };
    let bop = Bop::load(data).map_err(Failure::input)?;
    if bop
        .images
        .iter()
        .all(|im| im.instances.iter().all(|g| g.bbox_obj.is_none()))
    {
        return Err(Failure::input(format!(
            "{}: scene_gt_info.json carries no bbox_obj: nothing to score against",
            data.display()
        )));
    }
    // Photographs by image id (scene by scene), those that trained
    // nothing.
    let mut order: Vec<usize> = (0..bop.images.len()).collect();
    order.sort_by_key(|&i| bop.images[i].id);
    if args.train_photos >= order.len() {
        return Err(Failure::input(format!(
            "--train-photos {}: {} has only {} photographs, none left to score",
            args.train_photos,
            data.display(),
            order.len()
        )));
    }
    let images: Vec<usize> = order
        .into_iter()
        .skip(args.train_photos)
        .step_by(args.every)
        .collect();
    let mut meshes = std::collections::BTreeMap::new();
    if args.pose {
        for &obj in bop.models.keys() {
            if name_of(obj).is_none() {
                continue;
            }
            let path = bop.model_path(obj);
            let Ok(bytes) = std::fs::read(&path) else {
                continue;
            };
            let mesh = Mesh::parse(&bytes)
                .map_err(|e| Failure::input(format!("{}: {e}", path.display())))?;
            let points = add_points(&mesh, 1000);
            meshes.insert(obj, (mesh, points));
        }
    }
    let scan = ScanSettings {
        threshold: args.threshold,
        max_detections: args.max_detections,
        max_oracle_gap: args.max_oracle_gap,
        pose_mask: args.pose_mask,
    };
    let mut variants = vec![evaluate(
        "sdhop", models_dir, &bop, &images, &scan, args.pose, false, &meshes,
    )?];
    print_variant(&variants[0]);
    if args.transfer {
        let v = evaluate(
            "sdhop+transfer",
            models_dir,
            &bop,
            &images,
            &scan,
            false,
            true,
            &meshes,
        )?;
        print_variant(&v);
        variants.push(v);
    }
    for (name, dir) in &args.compare {
        let v = evaluate(name, dir, &bop, &images, &scan, false, false, &meshes)?;
        print_variant(&v);
        variants.push(v);
    }
    let json = serde_json::json!({
        "data": data.display().to_string(),
        "images": images.len(),
        "train_photos": args.train_photos,
        "threshold": args.threshold,
        "max_detections": args.max_detections,
        "variants": variants,
    });
    write_report(&json, &variants, &args.out)
}

/// `report.json` and `recall_fppi.png` of `variants` in `out`.
fn write_report(json: &serde_json::Value, variants: &[Variant], out: &Path) -> Result<(), Failure> {
    std::fs::create_dir_all(out).map_err(|e| Failure::io(format!("{}: {e}", out.display())))?;
    let report = out.join("report.json");
    std::fs::write(
        &report,
        serde_json::to_string_pretty(&json).map_err(Failure::io)?,
    )
    .map_err(|e| Failure::io(format!("{}: {e}", report.display())))?;
    let plot = out.join("recall_fppi.png");
    let curves: Vec<crate::eval::plot::VariantCurves> = variants
        .iter()
        .map(|v| {
            (
                v.name.clone(),
                v.objects
                    .iter()
                    .map(|s| (s.object.clone(), s.curve.clone()))
                    .collect(),
            )
        })
        .collect();
    crate::eval::plot::variants_png(&curves, &plot).map_err(Failure::io)?;
    println!("report {}, plot {}", report.display(), plot.display());
    // Each scored variant's detections in BOP's results format, named as
    // the BOP toolkit parses them (METHOD_DATASET-SPLIT.json).
    for v in variants.iter().filter(|v| !v.results.is_empty()) {
        let method: String = v
            .name
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() { c } else { '-' })
            .collect();
        let path = out.join(format!("{method}_lmo-test.json"));
        let text = serde_json::to_string(&v.results).map_err(Failure::io)?;
        std::fs::write(&path, text).map_err(|e| Failure::io(format!("{}: {e}", path.display())))?;
        println!("BOP detection results {}", path.display());
    }
    Ok(())
}

/// `--merge`: the first variant of each report, joined by row name.
fn merge_reports(inputs: &[(String, PathBuf)], out: &Path) -> Result<(), Failure> {
    let mut rows: Vec<Variant> = Vec::new();
    let mut sources = Vec::new();
    for (name, file) in inputs {
        let text = std::fs::read_to_string(file)
            .map_err(|e| Failure::io(format!("{}: {e}", file.display())))?;
        let report: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| Failure::input(format!("{}: {e}", file.display())))?;
        let first = report
            .get("variants")
            .and_then(|v| v.get(0))
            .cloned()
            .ok_or_else(|| {
                Failure::input(format!(
                    "{}: no variants: not a bop-eval report",
                    file.display()
                ))
            })?;
        let v: Variant = serde_json::from_value(first)
            .map_err(|e| Failure::input(format!("{}: {e}", file.display())))?;
        sources.push(serde_json::json!({
            "row": name,
            "report": file.display().to_string(),
            "images": report.get("images"),
            "train_photos": report.get("train_photos"),
        }));
        match rows.iter_mut().find(|r| &r.name == name) {
            None => rows.push(Variant {
                name: name.clone(),
                ..v
            }),
            Some(row) => {
                if let Some(o) = v
                    .objects
                    .iter()
                    .find(|o| row.objects.iter().any(|r| r.object == o.object))
                {
                    return Err(Failure::input(format!(
                        "{}: {} is already in row {name}",
                        file.display(),
                        o.object
                    )));
                }
                let n = (row.objects.len() + v.objects.len()).max(1) as f64;
                let (a, b) = (row.objects.len() as f64, v.objects.len() as f64);
                row.detect_ms_per_image =
                    (row.detect_ms_per_image * a + v.detect_ms_per_image * b) / n;
                row.models_dir = format!("{}, {}", row.models_dir, v.models_dir);
                row.box_ap = row.box_ap.join(&v.box_ap);
                row.mask_ap = row.mask_ap.join(&v.mask_ap);
                row.objects.extend(v.objects);
                row.pose.extend(v.pose);
            }
        }
    }
    // Reports of different photographs are not comparable: say so.
    let scored = |v: &serde_json::Value| (v["images"].clone(), v["train_photos"].clone());
    if let Some(first) = sources.first() {
        for s in sources.iter().filter(|s| scored(s) != scored(first)) {
            eprintln!(
                "warning: {} scored {} photographs after {} training ones, {} scored {} after {}",
                s["report"],
                s["images"],
                s["train_photos"],
                first["report"],
                first["images"],
                first["train_photos"]
            );
        }
    }
    for row in &mut rows {
        row.objects.sort_by_key(|a| a.obj_id);
        row.set_means();
    }
    for row in &rows {
        print_variant(row);
    }
    let json = serde_json::json!({"merged": sources, "variants": rows});
    write_report(&json, &rows, out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report(objects: &[(&str, u32, f64)]) -> serde_json::Value {
        let objects: Vec<DetectScore> = objects
            .iter()
            .map(|&(o, id, auc)| DetectScore {
                object: o.into(),
                obj_id: id,
                auc,
                recall_at_1fppi: auc,
                positives: 10,
                seg_error: 0.5,
                seg_error_raw: 0.6,
                seg_instances: 5,
                curve: vec![(0.0, 0.0), (0.5, auc)],
            })
            .collect();
        let first = objects.first().map_or(0.0, |o| o.auc);
        serde_json::json!({"images": 150, "train_photos": 50, "variants": [{
            "name": "sdhop", "models_dir": "m", "objects": objects, "mean_auc": 0.0,
            "mean_seg_error": 0.0, "mean_seg_error_raw": 0.0,
            "mean_recall_at_1fppi": 0.0, "detect_ms_per_image": 100.0,
            "box_ap": {"ap": first / 2.0, "ap50": first, "ap75": null, "categories": objects.len()}
        }]})
    }

    /// Per-object reports join into rows by name with their means
    /// recomputed; an object twice in a row and a file that is not a
    /// report are refused, naming the file.
    #[test]
    fn merge_joins_reports_into_rows() {
        let dir = std::env::temp_dir().join(format!("sdhop-merge-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let write = |name: &str, v: serde_json::Value| {
            let p = dir.join(name);
            std::fs::write(&p, v.to_string()).unwrap();
            p
        };
        let cat = write("cat.json", report(&[("cat", 6, 0.4)]));
        let ape = write("ape.json", report(&[("ape", 1, 0.2)]));
        let both = write("both.json", report(&[("ape", 1, 0.1), ("cat", 6, 0.3)]));
        let out = dir.join("rows");
        let inputs = vec![
            ("photos".to_string(), cat.clone()),
            ("photos".to_string(), ape.clone()),
            ("mesh".to_string(), both),
        ];
        merge_reports(&inputs, &out).unwrap();
        let merged: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap())
                .unwrap();
        let rows = merged["variants"].as_array().unwrap();
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[0]["name"], "photos");
        assert_eq!(rows[0]["objects"][0]["object"], "ape");
        assert!((rows[0]["mean_auc"].as_f64().unwrap() - 0.3).abs() < 1e-12);
        assert!((rows[1]["mean_auc"].as_f64().unwrap() - 0.2).abs() < 1e-12);
        // COCO AP: the mean over the objects of the rows' reports.
        assert!((rows[0]["box_ap"]["ap"].as_f64().unwrap() - 0.15).abs() < 1e-12);
        assert_eq!(rows[0]["box_ap"]["categories"], 2);
        assert!(rows[0]["box_ap"]["ap75"].is_null());
        assert!(out.join("recall_fppi.png").exists());
        let twice = vec![
            ("photos".to_string(), cat.clone()),
            ("photos".to_string(), cat),
        ];
        let e = merge_reports(&twice, &out).unwrap_err().message;
        assert!(e.contains("cat is already in row photos"), "{e}");
        let bad = write("bad.json", serde_json::json!({"auc": 1}));
        let e = merge_reports(&[("x".to_string(), bad)], &out)
            .unwrap_err()
            .message;
        assert!(
            e.contains("bad.json") && e.contains("not a bop-eval report"),
            "{e}"
        );
        std::fs::remove_dir_all(&dir).ok();
    }
}
