//! OR-IRLS on real photographs: a few LM-O development instances (the
//! protocol of `sdhop-train pose-eval`, 5 degree / 10 mm starts) must end
//! better than they started on average, as photographed (40-80% visible)
//! and cropped so that the border cuts the object. Needs
//! `../shared/data/lmo_dev`: ignored by default, run with
//! `--include-ignored` where the data is (CI does).

use std::collections::BTreeMap;
use std::path::Path;

use sdhop::data::bop::Bop;
use sdhop::eval::bop_pose::{run, select, summarize, table, Cut, Row, Selection};
use sdhop::pose::Mesh;

/// Refines 4 instances per development object of a row from 5 degree /
/// 10 mm starts and checks that OR-IRLS ends better than the start on
/// average, in translation and in rotation.
fn or_irls_improves_the_start(name: &str, visib: (f64, f64), cut: Cut) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/lmo_dev");
    assert!(root.join("test").is_dir(), "needs {}", root.display());
    let bop = Bop::load(&root).unwrap();
    let objects: Vec<u32> = bop.models.keys().copied().collect();
    let meshes: BTreeMap<u32, Mesh> = objects
        .iter()
        .map(|&o| {
            let bytes = std::fs::read(bop.model_path(o)).unwrap();
            (o, Mesh::parse(&bytes).unwrap())
        })
        .collect();
    let row = Row {
        name: name.into(),
        visib,
        start_degrees: 5.0,
        start_mm: 10.0,
        prior_from_start: false,
        uncertainty: None,
        cut,
        min_diagonal: None,
        max_iterations: None,
    };
    let sel = Selection {
        objects,
        per_object: 4,
        max_oracle_gap: 0.1,
        seed: 7,
        starts: 1,
    };
    let cases = select(&bop, &row, &sel);
    assert!(cases.len() >= 12, "{} instances", cases.len());
    let outcomes = run(&bop, &row, &cases, &meshes, || {}).unwrap();
    println!(
        "{}",
        table(&format!("LM-O development, {name}"), &outcomes, None)
    );
    let start = summarize(&outcomes, "initial", None).unwrap();
    let or = summarize(&outcomes, "or_irls", None).unwrap();
    assert!(
        or.mean_t < start.mean_t && or.mean_angle < start.mean_angle,
        "{name}: OR-IRLS {:.2} / {:.2} deg against the start's {:.2} / {:.2} deg",
        or.mean_t,
        or.mean_angle,
        start.mean_t,
        start.mean_angle
    );
}

#[test]
#[ignore = "needs ../shared/data/lmo_dev"]
fn or_irls_improves_the_start_on_real_photographs() {
    or_irls_improves_the_start("occluded", (0.4, 0.8), Cut::Any);
}

/// Development photographs cropped so that 10-50% of a mostly visible
/// object is cut away by the border (`pose-eval`'s cropped row).
#[test]
#[ignore = "needs ../shared/data/lmo_dev"]
fn or_irls_improves_the_start_of_objects_cut_by_the_border() {
    or_irls_improves_the_start("cropped", (0.6, 1.0), Cut::Cropped(0.1, 0.5));
}
