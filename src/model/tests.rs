//! The weights file: round trips, refusals, crafted files.

use std::path::Path;

use safetensors::tensor::SafeTensors;

use super::*;

#[test]
fn joined_components_fire_moved_by_the_offset() {
    use crate::pipeline::{detect_image, DetectOptions};
    use crate::synth::{hand_model, scene, HandModelParams, SceneParams, SynthObject};
    let obj = SynthObject {
        cols: 12,
        rows: 10,
        seed: 11,
    };
    let m = hand_model(&obj, "obj", true, &HandModelParams::default()).unwrap();
    let sc = scene(&obj, &SceneParams::default()).unwrap();
    let opts = DetectOptions::default();
    let best = |model: &Model| {
        let r = detect_image(&sc.image, &[model], &opts).unwrap();
        let d = r.detections[0].clone();
        (d.score, d.viewpoint, d.bbox)
    };
    let (s0, v0, b0) = best(&m);
    assert_eq!(v0, 0);
    // Above: the appended copy wins by exactly the offset, same place.
    let up = m.joined(&m, 0.5).unwrap();
    assert_eq!(up.views.len(), 2);
    assert_eq!(up.meta.viewpoints.len(), 2);
    assert_eq!(up.meta.provenance["joined"]["offset"], 0.5);
    let (s1, v1, b1) = best(&up);
    assert_eq!(v1, 1);
    assert!((s1 - s0 - 0.5).abs() < 1e-4, "{s1} vs {s0}");
    assert_eq!(
        (b1.x, b1.y, b1.width, b1.height),
        (b0.x, b0.y, b0.width, b0.height)
    );
    // Below: the model's own component keeps the detection.
    let (s2, v2, _) = best(&m.joined(&m, -0.5).unwrap());
    assert_eq!(v2, 0);
    assert!((s2 - s0).abs() < 1e-9);
    // It round-trips through its file.
    assert_eq!(Model::from_bytes(&up.to_bytes().unwrap()).unwrap(), up);
    // Another object or other cells are refused.
    let other = hand_model(&obj, "other", true, &HandModelParams::default()).unwrap();
    assert!(m.joined(&other, 0.0).is_err());
    let mut cnn = m.clone();
    cnn.meta.pyramid.levels_per_octave += 1;
    assert!(m.joined(&cnn, 0.0).is_err());
    assert!(m.joined(&m, f64::NAN).is_err());
}

fn sample() -> Model {
    let mut w = ViewWeights::zeros(2, 3, 4);
    for (i, v) in w.w_vis.iter_mut().enumerate() {
        if i % HOG_STRIDE < HOG_DIM {
            *v = (i as f32 * 0.37).sin();
        }
    }
    w.w_occ[5] = 0.5;
    w.w_prior = vec![0.1, -0.2, 0.3, 0.0, 1.0, -1.0];
    w.w_pair = 0.25;
    w.w_hop = vec![0.0, 3.0, 4.0, 3.0, 0.0];
    w.bias = -0.7;
    w.w_trunc = 0.05;
    let meta = ModelMeta {
        format_version: FORMAT_VERSION,
        name: "cup".into(),
        cell_size: CELL_SIZE,
        hop_k: 4,
        pairwise: PairwiseMode::Grid,
        pyramid: PyramidParams::default(),
        cells: None,
        segmentation: SegmentParams::default(),
        detection: DetectParams::default(),
        viewpoints: vec![ViewMeta {
            label: "cup".into(),
            rows: 2,
            cols: 3,
            direction: None,
            rotations: Vec::new(),
            views: Vec::new(),
        }],
        box_correction: None,
        provenance: serde_json::json!({"made_by": "test"}),
        segmenter: None,
    };
    Model::new(meta, vec![w]).unwrap()
}

#[test]
fn round_trips_through_bytes_and_files() {
    let m = sample();
    let bytes = m.to_bytes().unwrap();
    assert_eq!(Model::from_bytes(&bytes).unwrap(), m);
    let dir = std::env::temp_dir().join(format!("sdhop-model-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join("cup.safetensors");
    m.save(&p).unwrap();
    assert_eq!(Model::load(&p).unwrap(), m);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn shape_models_round_trip_and_format_1_files_still_load() {
    let m = sample();
    let shape = ShapeModel {
        width: 3 * CELL_SIZE,
        height: 2 * CELL_SIZE,
        prob: (0..6 * CELL_SIZE * CELL_SIZE)
            .map(|i| (i % 7) as f32 / 7.0)
            .collect(),
        colours: Some((0..4096).map(|i| (i % 3) as f32 / 4096.0).collect()),
    };
    let with = m.clone().with_shapes(vec![Some(shape.clone())]).unwrap();
    let back = Model::from_bytes(&with.to_bytes().unwrap()).unwrap();
    assert_eq!(back.shapes, vec![Some(shape.clone())]);
    assert_eq!(back.meta.format_version, FORMAT_VERSION);
    // A format 1 file (written before shape models): refused by the
    // server's reader, read by the upgrade's, no shapes.
    let old = m.serialize(1).unwrap();
    assert!(matches!(
        Model::from_bytes(&old),
        Err(ModelError::Legacy { found: 1 })
    ));
    let back = Model::from_legacy_bytes(&old).unwrap();
    assert_eq!(back.shapes, vec![None]);
    assert_eq!(back.meta.format_version, 1);
    // Format 2 with its shapes: the same, and upgraded it loads.
    let two = with.serialize(2).unwrap();
    assert!(matches!(
        Model::from_bytes(&two),
        Err(ModelError::Legacy { found: 2 })
    ));
    let upgraded = Model::from_legacy_bytes(&two).unwrap().to_bytes().unwrap();
    let back = Model::from_bytes(&upgraded).unwrap();
    assert_eq!(back.shapes, vec![Some(shape.clone())]);
    assert_eq!(back.meta.format_version, FORMAT_VERSION);
    // A shape of the wrong size or with probabilities out of range.
    let wrong = ShapeModel {
        width: 5,
        ..shape.clone()
    };
    assert!(m.clone().with_shapes(vec![Some(wrong)]).is_err());
    let mut out_of_range = shape;
    out_of_range.prob[0] = 1.5;
    assert!(m.with_shapes(vec![Some(out_of_range)]).is_err());
}

#[test]
fn box_corrections_round_trip_apply_and_are_checked() {
    let mut m = sample();
    let c = BoxCorrection {
        dx: 0.02,
        dy: -0.04,
        sw: 1.18,
        sh: 1.21,
        samples: 40,
    };
    m.meta.box_correction = Some(c);
    let back = Model::from_bytes(&m.to_bytes().unwrap()).unwrap();
    assert_eq!(back.meta.box_correction, Some(c));
    // The box grows about its moved centre.
    let (x, y, w, h) = c.apply((100.0, 200.0, 50.0, 80.0));
    assert!((w - 59.0).abs() < 1e-9 && (h - 96.8).abs() < 1e-9);
    assert!((x + w / 2.0 - 126.0).abs() < 1e-9 && (y + h / 2.0 - 236.8).abs() < 1e-9);
    // Files without one load without one.
    assert_eq!(sample().meta.box_correction, None);
    for bad in [
        BoxCorrection { sw: 3.0, ..c },
        BoxCorrection { sh: 0.0, ..c },
        BoxCorrection { dx: 0.5, ..c },
        BoxCorrection { dy: f64::NAN, ..c },
    ] {
        m.meta.box_correction = Some(bad);
        assert!(
            matches!(m.validate(), Err(ModelError::Invalid(_))),
            "{bad:?}"
        );
    }
}

#[test]
fn truncated_files_are_errors_not_panics() {
    let bytes = sample().to_bytes().unwrap();
    for cut in [0, 1, 7, 8, 20, bytes.len() / 2, bytes.len() - 1] {
        assert!(Model::from_bytes(&bytes[..cut]).is_err(), "cut at {cut}");
    }
    assert!(matches!(
        Model::load(Path::new("/nonexistent/x.safetensors")),
        Err(ModelError::Io { .. })
    ));
}

#[test]
fn inconsistent_models_are_refused() {
    let m = sample();
    let mut bad = m.clone();
    bad.meta.viewpoints[0].rows = 3;
    assert!(matches!(bad.to_bytes(), Err(ModelError::Invalid(_))));
    let mut bad = m.clone();
    bad.views[0].w_hop = vec![0.0, -1.0, 0.0, 0.0, 0.0];
    assert!(matches!(bad.validate(), Err(ModelError::Weights(_))));
    let mut bad = m.clone();
    bad.views[0].bias = f32::INFINITY;
    assert!(matches!(
        bad.validate(),
        Err(ModelError::Weights(VisionError::NonFinite(_)))
    ));
    let mut bad = m.clone();
    bad.meta.format_version = 99;
    assert!(matches!(
        bad.validate(),
        Err(ModelError::Version { found: 99 })
    ));
    // A file whose metadata claims a different template than its tensors.
    let mut meta_only = m.clone();
    meta_only.meta.viewpoints[0].cols = 4;
    meta_only.views[0] = ViewWeights::zeros(2, 4, 4);
    let mut bytes = meta_only.to_bytes().unwrap();
    // The metadata JSON sits escaped inside the header JSON.
    let needle = b"cols\\\":4";
    let at = bytes
        .windows(needle.len())
        .position(|w| w == needle)
        .unwrap();
    bytes[at + needle.len() - 1] = b'5';
    // The digest sees it first; with the digest made to match, the
    // tensors' shapes still refuse it.
    assert!(matches!(
        Model::from_bytes(&bytes),
        Err(ModelError::Digest { .. })
    ));
    let forged = edit_meta(&meta_only.to_bytes().unwrap(), true, |m| {
        m["viewpoints"][0]["cols"] = 5.into();
    });
    assert!(matches!(
        Model::from_bytes(&forged),
        Err(ModelError::Shape { .. })
    ));
}

#[test]
fn a_model_of_each_feature_kind_round_trips_and_cells_must_match() {
    // HOG: the metadata states the kind (format 3), names no cells.
    let hog = sample();
    let bytes = hog.to_bytes().unwrap();
    let meta = serde_json::to_value(&hog.meta).unwrap();
    assert_eq!(meta["pyramid"]["features"], "hog");
    assert!(meta.get("cells").is_none());
    assert_eq!(Model::from_bytes(&bytes).unwrap(), hog);
    // Learned cells: the kind and the projection's fingerprint travel.
    let mut cnn = sample();
    cnn.meta.pyramid.features = FeatureKind::Cnn;
    cnn.meta.cells = FeatureKind::Cnn.fingerprint().unwrap();
    let back = Model::from_bytes(&cnn.to_bytes().unwrap()).unwrap();
    assert_eq!(back, cnn);
    assert_eq!(back.meta.pyramid.features, FeatureKind::Cnn);
    // Trained on other cells, or naming none: refused, saying why.
    let mut other = cnn.clone();
    other.meta.cells = Some("0123456789abcdef".into());
    let err = other.validate().unwrap_err().to_string();
    assert!(
        err.contains("0123456789abcdef") && err.contains("retrain"),
        "{err}"
    );
    let mut none = cnn;
    none.meta.cells = None;
    assert!(matches!(none.validate(), Err(ModelError::Invalid(_))));
    let mut hog_named = hog;
    hog_named.meta.cells = Some("0123456789abcdef".into());
    assert!(matches!(hog_named.validate(), Err(ModelError::Invalid(_))));
}

/// The file's header JSON and where its metadata string lies in it.
fn header_of(bytes: &[u8]) -> (usize, serde_json::Value) {
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    (n, serde_json::from_slice(&bytes[8..8 + n]).unwrap())
}

/// `bytes` with its header replaced by `header` (padded as safetensors
/// pads it), the tensors' bytes unchanged.
fn with_header(bytes: &[u8], header: &serde_json::Value) -> Vec<u8> {
    let (n, _) = header_of(bytes);
    let mut text = serde_json::to_vec(header).unwrap();
    while text.len() % 8 != 0 {
        text.push(b' ');
    }
    let mut out = (text.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&text);
    out.extend_from_slice(&bytes[8 + n..]);
    out
}

/// `bytes` with its metadata JSON edited by `edit` (the digest kept, or
/// recomputed as a careful forger would).
fn edit_meta(bytes: &[u8], recompute: bool, edit: impl Fn(&mut serde_json::Value)) -> Vec<u8> {
    let (_, mut header) = header_of(bytes);
    let mut meta: serde_json::Value =
        serde_json::from_str(header["__metadata__"][META_KEY].as_str().unwrap()).unwrap();
    edit(&mut meta);
    let meta = serde_json::to_string(&meta).unwrap();
    if recompute {
        let st = SafeTensors::deserialize(bytes).unwrap();
        let digest = content_digest(
            &meta,
            st.tensors().into_iter().map(|(name, t)| {
                (
                    name,
                    format!("{:?}", t.dtype()),
                    t.shape().to_vec(),
                    t.data(),
                )
            }),
        );
        header["__metadata__"][DIGEST_KEY] = digest.into();
    }
    header["__metadata__"][META_KEY] = meta.into();
    with_header(bytes, &header)
}

#[test]
fn files_that_were_changed_after_training_are_refused() {
    let mut cnn = sample();
    cnn.meta.pyramid.features = FeatureKind::Cnn;
    cnn.meta.cells = FeatureKind::Cnn.fingerprint().unwrap();
    let cnn_bytes = cnn.to_bytes().unwrap();
    let hog_bytes = sample().to_bytes().unwrap();
    // The helpers themselves change nothing that loads when they edit
    // nothing (the JSON's key order may change; the digest follows).
    let same = edit_meta(&cnn_bytes, true, |_| {});
    assert_eq!(Model::from_bytes(&same).unwrap(), cnn);
    // A learned-cell model whose header no longer names its kind.
    let unkind = edit_meta(&cnn_bytes, false, |m| {
        m["pyramid"].as_object_mut().unwrap().remove("features");
        m.as_object_mut().unwrap().remove("cells");
    });
    assert!(matches!(
        Model::from_bytes(&unkind),
        Err(ModelError::Digest { .. })
    ));
    // The same with the digest recomputed: the kind is required.
    let forged = edit_meta(&cnn_bytes, true, |m| {
        m["pyramid"].as_object_mut().unwrap().remove("features");
        m.as_object_mut().unwrap().remove("cells");
    });
    assert!(matches!(
        Model::from_bytes(&forged),
        Err(ModelError::MissingFeatureKind)
    ));
    // A HOG model whose header claims learned cells.
    let claims = edit_meta(&hog_bytes, false, |m| {
        m["pyramid"]["features"] = "cnn".into();
        m["cells"] = FeatureKind::Cnn.fingerprint().unwrap().into();
    });
    assert!(matches!(
        Model::from_bytes(&claims),
        Err(ModelError::Digest { .. })
    ));
    // One flipped byte inside a weight tensor (the last byte of the
    // file is a tensor's).
    let mut flipped = cnn_bytes.clone();
    let last = flipped.len() - 1;
    flipped[last] ^= 0x01;
    let err = Model::from_bytes(&flipped).unwrap_err();
    assert!(matches!(err, ModelError::Digest { .. }), "{err}");
    assert!(err.to_string().contains("retrain"), "{err}");
    assert!(!err.to_string().contains('\n'), "one line: {err}");
    // The digest removed: refused.
    let (_, mut header) = header_of(&cnn_bytes);
    header["__metadata__"]
        .as_object_mut()
        .unwrap()
        .remove(DIGEST_KEY);
    assert!(matches!(
        Model::from_bytes(&with_header(&cnn_bytes, &header)),
        Err(ModelError::MissingDigest)
    ));
    // A careful forger's format 2 file (no digest): only the upgrade
    // reads it.
    let downgraded = edit_meta(&cnn_bytes, false, |m| m["format_version"] = 2.into());
    assert!(matches!(
        Model::from_bytes(&downgraded),
        Err(ModelError::Legacy { found: 2 })
    ));
}

#[test]
fn a_models_refinement_is_set_to_this_builds_and_the_old_kept() {
    use crate::vision::refine::RefineParams;
    let mut m = sample();
    let mut old = RefineParams::for_cells(m.meta.pyramid.features);
    old.pixel.smoothness += 1.0;
    m.meta.detection.refine = old;
    assert!(m.refresh_refinement());
    assert_eq!(
        m.meta.detection.refine,
        RefineParams::for_cells(m.meta.pyramid.features)
    );
    let kept = &m.meta.provenance["refine_set"][0]["from"]["pixel"]["smoothness"];
    assert_eq!(kept.as_f64(), Some(old.pixel.smoothness));
    // Already this build's: nothing changes, nothing is added.
    assert!(!m.refresh_refinement());
    assert_eq!(m.meta.provenance["refine_set"].as_array().unwrap().len(), 1);
    // It round-trips through its file.
    assert_eq!(Model::from_bytes(&m.to_bytes().unwrap()).unwrap(), m);
}

/// [`sample`] on learned cells.
fn sample_cnn() -> Model {
    let mut cnn = sample();
    cnn.meta.pyramid.features = FeatureKind::Cnn;
    cnn.meta.cells = FeatureKind::Cnn.fingerprint().unwrap();
    cnn.validate().unwrap();
    cnn
}

#[test]
fn a_segmenter_travels_in_its_models_file_and_its_digest() {
    let mut seg = sample();
    seg.views[0].bias = 0.25;
    seg.meta.provenance = serde_json::json!({"made_by": "the segmenter"});
    let m = sample_cnn().with_segmenter(seg.clone()).unwrap();
    assert_eq!(m.meta.segmenter.as_deref(), Some(&seg.meta));
    let bytes = m.to_bytes().unwrap();
    let back = Model::from_bytes(&bytes).unwrap();
    assert_eq!(back, m);
    assert_eq!(back.segmenter.as_deref(), Some(&seg));
    // Its tensors are the file's, under their prefix, and the digest
    // covers them: one changed byte of the segmenter's weights is refused.
    let (n, header) = header_of(&bytes);
    let name = format!("{SEGMENTER_PREFIX}view0.scalars");
    let at = header[name.as_str()]["data_offsets"][0].as_u64().unwrap() as usize;
    let mut changed = bytes.clone();
    changed[8 + n + at] ^= 0x01;
    assert!(matches!(
        Model::from_bytes(&changed),
        Err(ModelError::Digest { .. })
    ));
    // A file whose metadata describes a segmenter whose tensors are not
    // there, the digest recomputed by a careful forger: refused, naming
    // the tensor.
    let plain = sample_cnn().to_bytes().unwrap();
    let seg_meta = serde_json::to_value(&seg.meta).unwrap();
    let described = edit_meta(&plain, true, |meta| meta["segmenter"] = seg_meta.clone());
    let err = Model::from_bytes(&described).unwrap_err();
    assert!(
        matches!(err, ModelError::MissingTensor(ref t) if t.starts_with(SEGMENTER_PREFIX)),
        "{err}"
    );
    // Joined with components, the model keeps its segmenter; given up,
    // it is the model without one.
    let joined = m.joined(&sample_cnn(), 0.5).unwrap();
    assert_eq!(joined.segmenter.as_deref(), Some(&seg));
    assert_eq!(
        Model::from_bytes(&joined.to_bytes().unwrap()).unwrap(),
        joined
    );
    assert_eq!(m.without_segmenter(), sample_cnn());
}

#[test]
fn a_segmenter_must_fit_its_model() {
    let cnn = sample_cnn();
    // On the model's own cells.
    let err = cnn.clone().with_segmenter(sample_cnn()).unwrap_err();
    assert!(err.to_string().contains("other kind"), "{err}");
    // Of another object.
    let mut other = sample();
    other.meta.viewpoints[0].label = "pitcher".into();
    let err = cnn.clone().with_segmenter(other.clone()).unwrap_err();
    assert!(err.to_string().contains("same objects"), "{err}");
    // With a segmenter of its own.
    let nested = sample().with_segmenter(sample_cnn()).unwrap();
    let err = cnn.clone().with_segmenter(nested).unwrap_err();
    assert!(err.to_string().contains("of its own"), "{err}");
    // Metadata and model disagreeing.
    let mut m = cnn.clone().with_segmenter(sample()).unwrap();
    m.meta.segmenter = None;
    assert!(matches!(m.validate(), Err(ModelError::Invalid(_))));
    let mut m = cnn.clone();
    m.meta.segmenter = Some(Box::new(sample().meta));
    assert!(matches!(m.validate(), Err(ModelError::Invalid(_))));
    // Pairing folders: each model takes the segmenter of its objects, and
    // one without, or with two, is an error naming it.
    let paired = with_segmenters(vec![cnn.clone()], vec![other.clone(), sample()]).unwrap();
    assert_eq!(paired[0].segmenter.as_deref(), Some(&sample()));
    let err = with_segmenters(vec![cnn.clone()], vec![other]).unwrap_err();
    assert!(err.to_string().contains("no segmenter"), "{err}");
    let err = with_segmenters(vec![cnn], vec![sample(), sample()]).unwrap_err();
    assert!(err.to_string().contains("several"), "{err}");
}
