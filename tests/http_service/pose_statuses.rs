//! The statuses of `POST /pose`, each produced and checked against
//! openapi.yaml (called by the status test in `main.rs`).

use super::*;

/// Every documented answer of `POST /pose` but the 503 of a full queue.
pub(super) async fn pose_statuses(
    spec: &Value,
    seen: &mut Vec<Seen>,
    server: &Server,
    c: &reqwest::Client,
) {
    let plain = pose_scene(false);
    let occluded = pose_scene(true);
    let mesh = Mesh::cuboid(0.15, 0.1, 0.07);
    let ply = mesh.to_ply(false);
    let obj = mesh.to_obj().into_bytes();
    let post = |q: &str| c.post(server.url(&format!("/pose{q}")));

    // 200: plain IRLS on the unoccluded box (OBJ), OR-IRLS with the given
    // mask on the occluded one (PLY).
    let params = pose_params(&plain.start, serde_json::json!({}));
    let form = pose_form(Some(&plain.png), Some(&obj), None, Some(&params));
    let (s, _, body) = call(spec, seen, "/pose", "post", post("").multipart(form)).await;
    assert_eq!(s, 200, "{}", String::from_utf8_lossy(&body));
    let r: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(r["mask_source"], "none");
    assert!(r["detection"].is_null());
    let (deg, mm) = pose_error(&r, &plain.truth);
    assert!(
        deg < 0.5 && mm < 2.0,
        "unoccluded: {deg:.2} deg, {mm:.2} mm"
    );
    let params = pose_params(&occluded.start, serde_json::json!({"max_iterations": 40}));
    let form = pose_form(
        Some(&occluded.png),
        Some(&ply),
        Some(&occluded.mask),
        Some(&params),
    );
    let (s, _, body) = call(
        spec,
        seen,
        "/pose",
        "post",
        post("?timeout_ms=60000").multipart(form),
    )
    .await;
    assert_eq!(s, 200, "{}", String::from_utf8_lossy(&body));
    let r: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(r["mask_source"], "provided");
    let (deg, mm) = pose_error(&r, &occluded.truth);
    assert!(
        deg < 1.0 && mm < 3.0,
        "occluded with mask: {deg:.2} deg, {mm:.2} mm"
    );

    // 200 with the mask of a detection: the synthetic model finds its
    // object, and the box starts over the detection.
    let sc = synthetic_scene(3, 640, 480);
    let png = encode(&sc, image::ImageFormat::Png);
    let (s, _, body) = call(
        spec,
        seen,
        "/detect",
        "post",
        c.post(server.url("/detect?model=synthetic&max_detections=1"))
            .header(CONTENT_TYPE, "image/png")
            .body(png.clone()),
    )
    .await;
    assert_eq!(s, 200);
    let det: Value = serde_json::from_slice(&body).unwrap();
    let b = &det["detections"][0]["box"];
    let (bx, by) = (
        b["x"].as_f64().unwrap() + b["width"].as_f64().unwrap() / 2.0,
        b["y"].as_f64().unwrap() + b["height"].as_f64().unwrap() / 2.0,
    );
    let mut start = plain.start;
    start.translation = nalgebra::Vector3::new((bx - K.cx) / K.fx, (by - K.cy) / K.fy, 1.0);
    let params = pose_params(
        &start,
        serde_json::json!({"mask": "detect", "model": "synthetic"}),
    );
    let form = pose_form(Some(&png), Some(&ply), None, Some(&params));
    let (s, _, body) = call(spec, seen, "/pose", "post", post("").multipart(form)).await;
    assert_eq!(s, 200, "{}", String::from_utf8_lossy(&body));
    let r: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(r["mask_source"], "detected");
    assert_eq!(r["detection"]["model"], "synthetic");
    pose_refusals(spec, seen, server, c, &sc).await;
}

/// The refusals of `POST /pose` (4xx, and the deadline's answer), over
/// the unoccluded scene, with `sc` as a JPEG where a mask should be.
async fn pose_refusals(
    spec: &Value,
    seen: &mut Vec<Seen>,
    server: &Server,
    c: &reqwest::Client,
    sc: &sdhop::synth::Scene,
) {
    let plain = pose_scene(false);
    let mesh = Mesh::cuboid(0.15, 0.1, 0.07);
    let ply = mesh.to_ply(false);
    let post = |q: &str| c.post(server.url(&format!("/pose{q}")));
    // Errors.
    let good = pose_params(&plain.start, serde_json::json!({}));
    let skewed = {
        let mut p: Value = serde_json::from_str(&good).unwrap();
        p["initial_pose"]["rotation"][0][0] = Value::from(1.5);
        p.to_string()
    };
    let tiny_mask = {
        let mut out = Vec::new();
        image::GrayImage::new(8, 8)
            .write_to(&mut Cursor::new(&mut out), image::ImageFormat::Png)
            .unwrap();
        out
    };
    let jpeg_mask = encode(sc, image::ImageFormat::Jpeg);
    let with_mask = |p: Value| pose_params(&plain.start, p);
    // Params without an initial pose.
    let no_start = |extra: Value| {
        let mut p =
            serde_json::json!({"intrinsics": {"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy}});
        for (k, v) in extra.as_object().unwrap() {
            p[k] = v.clone();
        }
        p.to_string()
    };
    // The unoccluded image with this mesh, mask and params.
    let form = |mesh: &[u8], mask: Option<&[u8]>, params: &str| {
        pose_form(Some(&plain.png), Some(mesh), mask, Some(params))
    };
    let ok = || form(&ply, None, &good);
    // A mesh whose pose takes longer than 100 ms.
    let dense = mesh.subdivided(6).to_ply(true);
    let cases: Vec<(&str, reqwest::RequestBuilder, u16)> = vec![
        (
            "no mesh part",
            post("").multipart(pose_form(Some(&plain.png), None, None, Some(&good))),
            400,
        ),
        (
            "no params part",
            post("").multipart(pose_form(Some(&plain.png), Some(&ply), None, None)),
            400,
        ),
        (
            "unknown part",
            post("").multipart(ok().text("colour", "red")),
            400,
        ),
        (
            "params not JSON",
            post("").multipart(form(&ply, None, "{\"intr")),
            400,
        ),
        (
            "unknown query parameter",
            post("?model=cup").multipart(ok()),
            400,
        ),
        (
            "unknown model",
            post("").multipart(form(
                &ply,
                None,
                &with_mask(serde_json::json!({"mask": "detect", "model": "teapot"})),
            )),
            404,
        ),
        (
            // Six times the 4 MiB limit: the server reads the rest before
            // it answers, so the client, still writing, reads the 413
            // rather than a broken pipe.
            "oversized body",
            post("").multipart(form(&vec![b'#'; 24 << 20], None, &good)),
            413,
        ),
        (
            "not multipart",
            post("")
                .header(CONTENT_TYPE, "image/png")
                .body(plain.png.clone()),
            415,
        ),
        (
            "malformed mesh",
            post("").multipart(form(b"v 0 0 0\nv 1 0 0\nf 1 2 7\n", None, &good)),
            422,
        ),
        (
            "non-finite mesh",
            post("").multipart(form(b"v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n", None, &good)),
            422,
        ),
        (
            "truncated binary PLY",
            post("").multipart(form(&mesh.to_ply(true)[..200], None, &good)),
            422,
        ),
        (
            "rotation far from orthonormal",
            post("").multipart(form(&ply, None, &skewed)),
            422,
        ),
        (
            "params of the wrong shape",
            post("").multipart(form(&ply, None, "{\"intrinsics\": [1, 2]}")),
            422,
        ),
        (
            "mask of another size",
            post("").multipart(form(&ply, Some(&tiny_mask), &good)),
            422,
        ),
        (
            "mask not a PNG",
            post("").multipart(form(&ply, Some(&jpeg_mask), &good)),
            422,
        ),
        (
            "no initial pose and no model to detect it",
            post("").multipart(form(&ply, None, &no_start(serde_json::json!({})))),
            422,
        ),
        (
            "no initial pose and a model not trained from a mesh",
            post("").multipart(form(
                &ply,
                None,
                &no_start(serde_json::json!({"model": "synthetic"})),
            )),
            422,
        ),
        (
            "mask asked for but not sent",
            post("").multipart(form(
                &ply,
                None,
                &with_mask(serde_json::json!({"mask": "provided"})),
            )),
            422,
        ),
        (
            "deadline shorter than any pose",
            post("?timeout_ms=99").multipart(ok()),
            400,
        ),
        (
            "deadline passes",
            post("?timeout_ms=100").multipart(form(&dense, None, &good)),
            503,
        ),
    ];
    for (what, req, want) in cases {
        let (s, _, body) = call(spec, seen, "/pose", "post", req).await;
        assert_eq!(s, want, "{what}: {}", String::from_utf8_lossy(&body));
    }
}
