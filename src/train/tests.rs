//! Tests of the parent module.

use super::scales::*;
use super::*;

#[test]
fn small_boxes_get_larger_templates_and_upsampled_levels() {
    let params = TrainParams::default();
    // LM-O's ape: 37-84 px tall, median about 51: 5 cells at 0.8.
    let sizes: Vec<(f64, f64)> = (0..21)
        .map(|i| (35.0 + i as f64, 37.0 + 2.0 * i as f64))
        .collect();
    let p = small_object_scales(&sizes, &params).expect("small objects");
    let median = 57.0;
    assert!((p.template_scale - 12.0 * 8.0 / median).abs() < 1e-9);
    // The smallest box is seen at the template's size.
    let expect_max = p.template_scale * median / 37.0;
    assert!((f64::from(p.pyramid.max_scale) - expect_max).abs() < 1e-5);
    assert!(p.pyramid.max_scale > 1.0);
    assert!(f64::from(p.pyramid.min_scale) <= p.template_scale / 4.0 + 1e-6);
    assert_eq!(p.pyramid.levels_per_octave, 5);
    p.validate().unwrap();
    // A narrow object (LM-O's glue, 41x82 px): small by its area.
    let narrow: Vec<(f64, f64)> = (0..9)
        .map(|i| (37.0 + i as f64, 74.0 + 2.0 * i as f64))
        .collect();
    let p = small_object_scales(&narrow, &params).expect("narrow small objects");
    assert!((p.template_scale - 12.0 * 8.0 / 82.0).abs() < 1e-9);
    // On learned cells it gets LEARNED_CELLS_ACROSS cells across
    // (41 px), an octave of levels below that scale.
    let mut learned = params.clone();
    learned.pyramid.features = crate::vision::cells::FeatureKind::Cnn;
    let p = small_object_scales(&narrow, &learned).expect("narrow small objects");
    assert!((p.template_scale - LEARNED_CELLS_ACROSS * 8.0 / 41.0).abs() < 1e-9);
    assert!(p.template_scale > 12.0 * 8.0 / 82.0);
    assert!(
        (f64::from(p.pyramid.min_scale) - p.template_scale / LEARNED_SCALES_BELOW).abs() < 1e-5
    );
    // A box of another aspect (the glue seen from above, 44x40) sets the
    // upsampling by its area on learned cells, by its longer side on HOG.
    let mut seen_above = narrow.clone();
    seen_above.push((44.0, 40.0));
    let p = small_object_scales(&seen_above, &learned).expect("learned");
    let side = |&(w, h): &(f64, f64)| f64::sqrt(w * h);
    let mut sides: Vec<f64> = seen_above.iter().map(side).collect();
    sides.sort_by(f64::total_cmp);
    let below = sides[sides.len() / 2] / (44.0f64 * 40.0).sqrt();
    let levels = (below.log2() * 5.0).round();
    let expect_max = p.template_scale * (levels / 5.0).exp2();
    assert!((f64::from(p.pyramid.max_scale) - expect_max).abs() < 1e-5);
    // Within half a level of the smallest box's scale, and one level at
    // the template's.
    assert!((expect_max / (p.template_scale * below)).log2().abs() <= 0.1 + 1e-9);
    assert!(p
        .pyramid
        .scales()
        .iter()
        .any(|&s| (s / p.template_scale - 1.0).abs() < 1e-6));
    // Capped at 4 by whole levels.
    assert!((anchored_max_scale(3.0, 2.0) - 3.0 * 0.4f64.exp2()).abs() < 1e-9);
    assert_eq!(anchored_max_scale(1.5, 0.5), 1.5);
    let h = small_object_scales(&seen_above, &params).expect("hog");
    assert!((f64::from(h.pyramid.max_scale) - h.template_scale * 82.0 / 44.0).abs() < 1e-5);
    // Large objects keep the settings they have.
    let big: Vec<(f64, f64)> = sizes.iter().map(|&(w, h)| (4.0 * w, 4.0 * h)).collect();
    assert!(small_object_scales(&big, &params).is_none());
    // So does a fixed template size, or no box at all.
    let fixed = TrainParams {
        template: Some([6, 6]),
        ..params.clone()
    };
    assert!(small_object_scales(&sizes, &fixed).is_none());
    assert!(small_object_scales(&[], &params).is_none());
    // Tiny boxes cap the scales at 4.
    let p = small_object_scales(&[(10.0, 12.0), (20.0, 22.0), (24.0, 24.0)], &params).unwrap();
    assert!(p.template_scale <= 4.0 && p.pyramid.max_scale <= 4.0);
    p.validate().unwrap();
}

#[test]
fn grouped_settings_read_and_write_flat_json() {
    // A `--config` file names the settings flat, whatever their group.
    let p: TrainParams = serde_json::from_value(serde_json::json!({
        "c": 3.0, "k": 2, "max_passes": 7, "seed": 9, "template_scale": 1.5
    }))
    .unwrap();
    assert_eq!(p.solver.c, 3.0);
    assert_eq!(p.energy.k, 2);
    assert_eq!(p.solver.max_passes, 7);
    assert_eq!(p.examples.seed, 9);
    assert_eq!(p.template_scale, 1.5);
    assert_eq!(p.energy.loss, TrainParams::default().energy.loss);
    // Written flat as a model's provenance records it, and read back.
    let v = serde_json::to_value(&p).unwrap();
    for key in [
        "c",
        "k",
        "max_passes",
        "seed",
        "positive_share",
        "pair_mode",
    ] {
        assert!(v.get(key).is_some(), "{key} missing from {v}");
    }
    for group in ["energy", "solver", "examples", "renders"] {
        assert!(v.get(group).is_none(), "{group} in {v}");
    }
    let back: TrainParams = serde_json::from_value(v).unwrap();
    assert_eq!(back, p);
}
