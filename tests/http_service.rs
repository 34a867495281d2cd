//! The HTTP service over TCP on an ephemeral port: every status that
//! `openapi.yaml` lists is produced and every response matches its schema;
//! bad inputs get the right 4xx; overload answers 503 with Retry-After;
//! deadlines; PNG label maps; SIGTERM drains requests in flight; the JSON
//! equals the CLI's. Models and images are generated (synthetic scenes).
//!
//! Why one file of about 1,300 lines: one test proves that every status
//! of `openapi.yaml` is produced, so the cases of every endpoint live
//! beside it; the misbehaving-client tests are `http_robustness.rs`, the
//! shared helpers `common/mod.rs`.

use std::collections::BTreeSet;
use std::io::Cursor;
use std::path::Path;
use std::process::Command;
use std::sync::Arc;
use std::time::Duration;

use prometheus::Registry;
use reqwest::header::{ACCEPT, CONTENT_TYPE, RETRY_AFTER};
use reqwest::StatusCode;
use sdhop::backend::CpuBackend;
use sdhop::http::{load_models, warm_up, AppState, HttpConfig};
use sdhop::infer::{Infer, InferConfig, InferMetrics};
use sdhop::pose::render::{background, perturb, render};
use sdhop::pose::{Intrinsics, Mesh, Pose};
use serde_json::Value;

mod common;
use common::*;

/// The API contract as JSON.
fn spec() -> Value {
    let text = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("openapi.yaml"))
        .unwrap();
    serde_norway::from_str(&text).unwrap()
}

/// Validates `body` against the schema the spec gives for this response.
fn check_schema(spec: &Value, path: &str, method: &str, status: u16, ctype: &str, body: &[u8]) {
    let media = ctype.split(';').next().unwrap().trim();
    let resp = &spec["paths"][path][method]["responses"][status.to_string()];
    assert!(
        resp.is_object(),
        "{method} {path} answered {status}, which openapi.yaml does not list"
    );
    let schema = &resp["content"][media]["schema"];
    assert!(
        schema.is_object(),
        "{method} {path} {status} answered {media}, which openapi.yaml does not list"
    );
    if media != "application/json" {
        return;
    }
    let instance: Value = serde_json::from_slice(body).unwrap();
    // The whole document as the root, so that its $refs resolve.
    let mut root = spec.clone();
    root["$ref"] = Value::String("#/x-check".into());
    root["x-check"] = schema.clone();
    let validator = jsonschema::options()
        .with_draft(jsonschema::Draft::Draft202012)
        .build(&root)
        .unwrap();
    let errors: Vec<String> = validator
        .iter_errors(&instance)
        .map(|e| format!("{e} at {}", e.instance_path))
        .collect();
    assert!(
        errors.is_empty(),
        "{method} {path} {status} does not match its schema: {errors:?}\n{instance}"
    );
}

/// What a response was and whether it passed the schema.
struct Seen {
    path: &'static str,
    method: &'static str,
    status: u16,
}

async fn call(
    spec: &Value,
    seen: &mut Vec<Seen>,
    path: &'static str,
    method: &'static str,
    req: reqwest::RequestBuilder,
) -> (u16, reqwest::header::HeaderMap, Vec<u8>) {
    let resp = req.send().await.unwrap();
    let status = resp.status().as_u16();
    let headers = resp.headers().clone();
    let body = resp.bytes().await.unwrap().to_vec();
    let ctype = headers
        .get(CONTENT_TYPE)
        .map(|v| v.to_str().unwrap().to_string())
        .unwrap_or_default();
    check_schema(spec, path, method, status, &ctype, &body);
    if status == 503 {
        assert!(headers.contains_key(RETRY_AFTER), "503 without Retry-After");
    }
    if status >= 400 {
        // Errors may come before the body is read: the connection closes.
        assert_eq!(
            headers
                .get(reqwest::header::CONNECTION)
                .map(|v| v.as_bytes()),
            Some(&b"close"[..]),
            "{status} without Connection: close"
        );
    }
    seen.push(Seen {
        path,
        method,
        status,
    });
    (status, headers, body)
}

const K: Intrinsics = Intrinsics {
    fx: 600.0,
    fy: 600.0,
    cx: 320.0,
    cy: 240.0,
};

/// A box rendered at a known pose (45% occluded when `occlude`), its exact
/// visible mask as PNG, and the start pose perturbed by 1 cm and 5 degrees.
struct PoseScene {
    png: Vec<u8>,
    mask: Vec<u8>,
    truth: Pose,
    start: Pose,
}

fn pose_scene(occlude: bool) -> PoseScene {
    use nalgebra::{Rotation3, Vector3};
    let truth = Pose {
        rotation: Rotation3::from_euler_angles(0.5, 0.6, 0.2).into_inner(),
        translation: Vector3::new(0.01, -0.01, 0.5),
    };
    let mesh = Mesh::cuboid(0.15, 0.1, 0.07);
    let bg = background(640, 480, 77).unwrap();
    let sc = render(
        &mesh,
        &K,
        &truth,
        &bg,
        if occlude { 0.45 } else { 0.0 },
        2.0,
        7,
    )
    .unwrap();
    let mut png = Vec::new();
    sc.image
        .to_rgb8()
        .write_to(&mut Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    let m = image::GrayImage::from_fn(640, 480, |x, y| {
        image::Luma([u8::from(sc.visible.get(x as usize, y as usize)) * 255])
    });
    let mut mask = Vec::new();
    m.write_to(&mut Cursor::new(&mut mask), image::ImageFormat::Png)
        .unwrap();
    PoseScene {
        png,
        mask,
        truth,
        start: perturb(&truth, 0.01, 5.0, 8),
    }
}

/// The `params` part for a start pose.
fn pose_params(start: &Pose, extra: Value) -> String {
    let t = start.translation;
    let mut p = serde_json::json!({
        "intrinsics": {"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy},
        "initial_pose": {"rotation": start.rotation_rows(), "translation": [t.x, t.y, t.z]},
    });
    for (k, v) in extra.as_object().unwrap() {
        p[k] = v.clone();
    }
    p.to_string()
}

/// A `POST /pose` form; `None` leaves a part out.
fn pose_form(
    image: Option<&[u8]>,
    mesh: Option<&[u8]>,
    mask: Option<&[u8]>,
    params: Option<&str>,
) -> reqwest::multipart::Form {
    use reqwest::multipart::{Form, Part};
    let mut f = Form::new();
    if let Some(b) = image {
        f = f.part("image", Part::bytes(b.to_vec()).file_name("scene.png"));
    }
    if let Some(b) = mesh {
        f = f.part("mesh", Part::bytes(b.to_vec()).file_name("object.ply"));
    }
    if let Some(b) = mask {
        f = f.part("mask", Part::bytes(b.to_vec()).file_name("mask.png"));
    }
    if let Some(p) = params {
        f = f.text("params", p.to_string());
    }
    f
}

/// Rotation (degrees) and translation (mm) error of a pose response.
fn pose_error(resp: &Value, truth: &Pose) -> (f64, f64) {
    let r: [[f64; 3]; 3] = serde_json::from_value(resp["pose"]["rotation"].clone()).unwrap();
    let t: [f64; 3] = serde_json::from_value(resp["pose"]["translation"].clone()).unwrap();
    let est = Pose::from_client(r, t).unwrap();
    let (angle, dist) = est.distance(truth);
    (angle.to_degrees(), dist * 1e3)
}

/// Every documented answer of `POST /pose` but the 503 of a full queue.
async fn pose_statuses(spec: &Value, seen: &mut Vec<Seen>, server: &Server, c: &reqwest::Client) {
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
    let jpeg_mask = encode(&sc, image::ImageFormat::Jpeg);
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
            "deadline passes",
            post("?timeout_ms=1").multipart(ok()),
            503,
        ),
    ];
    for (what, req, want) in cases {
        let (s, _, body) = call(spec, seen, "/pose", "post", req).await;
        assert_eq!(s, want, "{what}: {}", String::from_utf8_lossy(&body));
    }
}

/// A PNG whose header claims 100000 x 100000 pixels (and nothing more).
fn huge_png_header() -> Vec<u8> {
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(b"IHDR");
    ihdr.extend_from_slice(&100_000u32.to_be_bytes());
    ihdr.extend_from_slice(&100_000u32.to_be_bytes());
    ihdr.extend_from_slice(&[8, 2, 0, 0, 0]);
    let crc = crc32(&ihdr);
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    png.extend_from_slice(&13u32.to_be_bytes());
    png.extend_from_slice(&ihdr);
    png.extend_from_slice(&crc.to_be_bytes());
    // A first, tiny data chunk and the end: decoders read up to the data.
    for (kind, data) in [
        (
            &b"IDAT"[..],
            &[0x78u8, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01][..],
        ),
        (&b"IEND"[..], &[][..]),
    ] {
        let mut chunk = kind.to_vec();
        chunk.extend_from_slice(data);
        png.extend_from_slice(&(data.len() as u32).to_be_bytes());
        png.extend_from_slice(&chunk);
        png.extend_from_slice(&crc32(&chunk).to_be_bytes());
    }
    png
}

fn crc32(data: &[u8]) -> u32 {
    let mut c = 0xffff_ffffu32;
    for &b in data {
        c ^= u32::from(b);
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xedb8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

/// Sends `request` over a raw connection (which then stalls) and reads
/// the answer to its end.
async fn raw_exchange(addr: &str, request: String) -> String {
    use std::io::{Read, Write};
    let addr = addr.to_string();
    tokio::task::spawn_blocking(move || {
        let mut s = std::net::TcpStream::connect(addr).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let _ = s.write_all(request.as_bytes());
        let mut out = Vec::new();
        let _ = s.read_to_end(&mut out);
        String::from_utf8(out).unwrap()
    })
    .await
    .unwrap()
}

/// Checks a raw answer against the spec as `call` does and expects
/// `status`.
fn check_raw(spec: &Value, seen: &mut Vec<Seen>, path: &'static str, answer: &str, status: u16) {
    let (head, body) = answer.split_once("\r\n\r\n").unwrap_or((answer, ""));
    let line = head.lines().next().unwrap_or_default();
    assert!(
        line.starts_with(&format!("HTTP/1.1 {status} ")),
        "{path}: expected {status}, got {answer:?}"
    );
    let header = |name: &str| {
        head.lines()
            .find_map(|l| {
                let (k, v) = l.split_once(':')?;
                k.eq_ignore_ascii_case(name).then(|| v.trim().to_string())
            })
            .unwrap_or_default()
    };
    check_schema(
        spec,
        path,
        "post",
        status,
        &header("content-type"),
        body.as_bytes(),
    );
    assert_eq!(
        header("connection"),
        "close",
        "{status} without Connection: close"
    );
    if status == 429 || status == 503 {
        assert!(
            !header("retry-after").is_empty(),
            "{status} without Retry-After"
        );
    }
    seen.push(Seen {
        path,
        method: "post",
        status,
    });
}

/// Waits (at most 5 s) until a connection from this client is admitted
/// again (a probe answered other than 429).
async fn wait_released(addr: &str) {
    for _ in 0..100 {
        let probe = raw_exchange(
            addr,
            "GET /health/live HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n".into(),
        )
        .await;
        if !probe.starts_with("HTTP/1.1 429") {
            return;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// A connection over the per-client limit: idle connections are opened
/// until the server refuses one, then `request` is sent on one more. A
/// slot that frees meanwhile (the server sees a client's close only when
/// it next reads) is filled and the request sent again.
async fn over_the_limit(addr: &str, request: String) -> String {
    let mut idle: Vec<std::net::TcpStream> = Vec::new();
    let mut answer = String::new();
    for _ in 0..5 {
        for _ in 0..400 {
            let probe = raw_exchange(
                addr,
                "GET /health/live HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n".into(),
            )
            .await;
            if probe.starts_with("HTTP/1.1 429") {
                break;
            }
            idle.push(std::net::TcpStream::connect(addr).unwrap());
        }
        answer = raw_exchange(addr, request.clone()).await;
        if answer.starts_with("HTTP/1.1 429") {
            break;
        }
    }
    drop(idle);
    answer
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_documented_status_is_produced_and_matches_its_schema() {
    let spec = spec();
    // A small body limit so that an oversized body is cheap to send; a
    // one-slot queue to produce the 503.
    let server = Server::start(
        InferConfig {
            queue_size: 1,
            max_batch: 1,
            ..InferConfig::default()
        },
        HttpConfig {
            max_body_bytes: 4 << 20,
            max_pose_body_bytes: 4 << 20,
            body_grace: Duration::from_millis(300),
            ..HttpConfig::default()
        },
    )
    .await;
    let c = reqwest::Client::new();
    let mut seen = Vec::new();
    pose_statuses(&spec, &mut seen, &server, &c).await;
    let sc = synthetic_scene(3, 320, 240);
    let png = encode(&sc, image::ImageFormat::Png);
    let jpeg = encode(&sc, image::ImageFormat::Jpeg);
    let detect = |q: &str| c.post(server.url(&format!("/detect{q}")));

    // 200 JSON (PNG and JPEG bodies, multipart) and 200 PNG.
    let (s, _, body) = call(
        &spec,
        &mut seen,
        "/detect",
        "post",
        detect("?masks=both")
            .header(CONTENT_TYPE, "image/png")
            .body(png.clone()),
    )
    .await;
    assert_eq!(s, 200);
    let r: Value = serde_json::from_slice(&body).unwrap();
    assert!(
        !r["detections"].as_array().unwrap().is_empty(),
        "the object is found"
    );
    let (s, _, body) = call(
        &spec,
        &mut seen,
        "/detect",
        "post",
        detect("?rle=compressed")
            .header(CONTENT_TYPE, "image/jpeg")
            .body(jpeg.clone()),
    )
    .await;
    assert_eq!(s, 200);
    let r: Value = serde_json::from_slice(&body).unwrap();
    assert!(r["detections"][0]["mask"]["counts"].is_string(), "{r}");
    let form = reqwest::multipart::Form::new().part(
        "image",
        reqwest::multipart::Part::bytes(png.clone()).file_name("scene.png"),
    );
    let (s, _, _) = call(
        &spec,
        &mut seen,
        "/detect",
        "post",
        detect("?model=synthetic").multipart(form),
    )
    .await;
    assert_eq!(s, 200);
    let (s, h, _) = call(
        &spec,
        &mut seen,
        "/detect",
        "post",
        detect("")
            .header(CONTENT_TYPE, "image/png")
            .header(ACCEPT, "image/png")
            .body(png.clone()),
    )
    .await;
    assert_eq!(s, 200);
    assert_eq!(h[CONTENT_TYPE], "image/png");
    assert!(h.contains_key("x-detections"));
    // Response transfer between the loaded models.
    let (s, _, _) = call(
        &spec,
        &mut seen,
        "/detect",
        "post",
        detect("?transfer=true")
            .header(CONTENT_TYPE, "image/png")
            .body(png.clone()),
    )
    .await;
    assert_eq!(s, 200);

    // 4xx.
    let cases: Vec<(&str, reqwest::RequestBuilder, u16)> = vec![
        (
            "empty body",
            detect("").header(CONTENT_TYPE, "image/png"),
            400,
        ),
        (
            "malformed query",
            detect("?max_detections=lots")
                .header(CONTENT_TYPE, "image/png")
                .body(png.clone()),
            400,
        ),
        (
            // Read to its end before the query is refused: the client
            // gets the 400, not a connection reset while still sending.
            "malformed query with a 3 MB body",
            detect("?max_detections=lots")
                .header(CONTENT_TYPE, "image/png")
                .body(vec![7u8; 3 << 20]),
            400,
        ),
        (
            "transfer neither true nor false",
            detect("?transfer=maybe")
                .header(CONTENT_TYPE, "image/png")
                .body(png.clone()),
            400,
        ),
        (
            "unknown parameter",
            detect("?colour=red")
                .header(CONTENT_TYPE, "image/png")
                .body(png.clone()),
            400,
        ),
        (
            "multipart without image",
            detect("").multipart(reqwest::multipart::Form::new().text("other", "x")),
            400,
        ),
        (
            "unknown model",
            detect("?model=teapot")
                .header(CONTENT_TYPE, "image/png")
                .body(png.clone()),
            404,
        ),
        (
            "oversized body",
            detect("")
                .header(CONTENT_TYPE, "image/png")
                .body(vec![0u8; 24 << 20]),
            413,
        ),
        (
            "huge PNG header",
            detect("")
                .header(CONTENT_TYPE, "image/png")
                .body(huge_png_header()),
            413,
        ),
        (
            // 3 MiB, read before the answer, as every refused body.
            "wrong content type",
            detect("")
                .header(CONTENT_TYPE, "text/plain")
                .body("hello ".repeat(1 << 19)),
            415,
        ),
        ("no content type", detect("").body(png.clone()), 415),
        (
            "GIF image",
            detect("")
                .header(CONTENT_TYPE, "image/png")
                .body(b"GIF89a\x01\x00\x01\x00\x00\x00\x00;".to_vec()),
            415,
        ),
        (
            "random bytes",
            detect("").header(CONTENT_TYPE, "image/jpeg").body(
                (0..4000u32)
                    .map(|i| (i * 7919 % 251) as u8)
                    .collect::<Vec<u8>>(),
            ),
            422,
        ),
        (
            "truncated JPEG",
            detect("")
                .header(CONTENT_TYPE, "image/jpeg")
                .body(jpeg[..jpeg.len() / 3].to_vec()),
            422,
        ),
        (
            "truncated PNG",
            detect("")
                .header(CONTENT_TYPE, "image/png")
                .body(png[..png.len() / 2].to_vec()),
            422,
        ),
    ];
    for (what, req, want) in cases {
        let (s, _, body) = call(&spec, &mut seen, "/detect", "post", req).await;
        assert_eq!(s, want, "{what}: {}", String::from_utf8_lossy(&body));
    }

    // 503: one request computing, one in the queue's only place, the next
    // refused at once (requests arriving together may be refused too).
    let big = encode(&synthetic_scene(5, 2560, 1920), image::ImageFormat::Jpeg);
    let slow: Vec<_> = (0..3)
        .map(|_| {
            tokio::spawn(
                c.post(server.url("/detect"))
                    .header(CONTENT_TYPE, "image/jpeg")
                    .body(big.clone())
                    .send(),
            )
        })
        .collect();
    let mut refused = false;
    for _ in 0..200 {
        let text = c
            .get(server.url("/metrics"))
            .send()
            .await
            .unwrap()
            .text()
            .await
            .unwrap();
        if metric(&text, "sdhop_queue_size") >= 1.0 {
            let (s, _, body) = call(
                &spec,
                &mut seen,
                "/detect",
                "post",
                detect("")
                    .header(CONTENT_TYPE, "image/png")
                    .body(png.clone()),
            )
            .await;
            assert!(
                s == 503 || s == 200,
                "{s}: {}",
                String::from_utf8_lossy(&body)
            );
            if s == 503 {
                refused = true;
                break;
            }
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    assert!(refused, "a full queue refuses at once");
    for t in slow {
        let r = t.await.unwrap().unwrap();
        assert!(
            r.status() == StatusCode::OK
                || (r.status() == StatusCode::SERVICE_UNAVAILABLE
                    && r.headers().contains_key(RETRY_AFTER)),
            "{}",
            r.status()
        );
    }

    // Operations.
    for (path, want) in [
        ("/health/live", 200),
        ("/health/ready", 200),
        ("/metrics", 200),
        ("/info", 200),
        ("/models", 200),
        ("/openapi.yaml", 200),
    ] {
        let path: &'static str = path;
        let (s, _, body) = call(&spec, &mut seen, path, "get", c.get(server.url(path))).await;
        assert_eq!(s, want, "{path}");
        if path == "/metrics" {
            let text = String::from_utf8(body).unwrap();
            for name in [
                "sdhop_queue_size",
                "sdhop_queue_duration_seconds",
                "sdhop_compute_duration_seconds",
                "sdhop_batch_size",
                "sdhop_http_requests_total",
                "sdhop_queue_requests_total",
            ] {
                assert!(text.contains(name), "metric {name} missing");
            }
            assert!(
                text.contains("outcome=\"rejected\""),
                "the refused request is counted"
            );
        }
    }

    // 408: uploads that stall past the body grace; 429: a connection over
    // the per-client limit (the others held idle).
    let addr = server.base.trim_start_matches("http://").to_string();
    for (path, ctype) in [
        ("/detect", "image/jpeg"),
        ("/pose", "multipart/form-data; boundary=xyz"),
    ] {
        let head = format!(
            "POST {path} HTTP/1.1\r\nHost: x\r\nContent-Type: {ctype}\r\nContent-Length: 100000\r\n\r\n--"
        );
        // The previous round's idle connections are released by the
        // server a little after they close: until then this one would be
        // refused with 429 instead of timing out with 408.
        wait_released(&addr).await;
        let answer = raw_exchange(&addr, head.clone()).await;
        check_raw(&spec, &mut seen, path, &answer, 408);
        let answer = over_the_limit(&addr, head).await;
        check_raw(&spec, &mut seen, path, &answer, 429);
    }

    // Not ready while shutting down: readiness 503, and /detect refuses.
    let client = c.clone();
    let ready_url = server.url("/health/ready");
    let detect_url = server.url("/detect");
    let stop = server.stop;
    let done = server.done;
    if let Some(tx) = stop {
        let _ = tx.send(());
    }
    // The listener closes on shutdown; requests on a kept-alive connection
    // can still arrive, so check through the state right after the signal.
    let mut ready_503 = false;
    for _ in 0..50 {
        match client.get(&ready_url).send().await {
            Ok(r) => {
                let status = r.status().as_u16();
                let ctype = r.headers()[CONTENT_TYPE].to_str().unwrap().to_string();
                let body = r.bytes().await.unwrap();
                check_schema(&spec, "/health/ready", "get", status, &ctype, &body);
                if status == 503 {
                    ready_503 = true;
                    seen.push(Seen {
                        path: "/health/ready",
                        method: "get",
                        status,
                    });
                    let r = client
                        .post(&detect_url)
                        .header(CONTENT_TYPE, "image/png")
                        .body(png.clone())
                        .send()
                        .await;
                    if let Ok(r) = r {
                        assert_eq!(r.status().as_u16(), 503);
                    }
                    break;
                }
            }
            Err(_) => break,
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    if let Some(d) = done {
        assert!(d.await.unwrap().unwrap(), "clean shutdown");
    }

    // Every (path, method, status) of the document was produced.
    let produced: BTreeSet<(String, String, u16)> = seen
        .iter()
        .map(|s| (s.path.to_string(), s.method.to_string(), s.status))
        .collect();
    let mut missing = Vec::new();
    for (path, item) in spec["paths"].as_object().unwrap() {
        for (method, op) in item.as_object().unwrap() {
            for status in op["responses"].as_object().unwrap().keys() {
                let key = (path.clone(), method.clone(), status.parse::<u16>().unwrap());
                if !produced.contains(&key) {
                    missing.push(key);
                }
            }
        }
    }
    // The not-ready 503 of /health/ready depends on catching the window
    // between the signal and the listener closing; it is checked directly
    // in `readiness_follows_warm_up_and_shutdown`.
    missing.retain(|k| !(k.0 == "/health/ready" && k.2 == 503 && !ready_503));
    assert!(missing.is_empty(), "statuses never produced: {missing:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn readiness_follows_warm_up_and_shutdown() {
    let registry = Registry::new();
    let metrics = InferMetrics::new(&registry).unwrap();
    let infer = Infer::start(Box::new(CpuBackend), InferConfig::default(), metrics).unwrap();
    let state = AppState::new(
        infer,
        load_models(&models_dir()).unwrap(),
        HttpConfig::default(),
        registry,
    )
    .unwrap();
    assert!(state.readiness().is_err(), "not ready before the warm-up");
    warm_up(&state).await.unwrap();
    assert!(state.readiness().is_ok());
    state.begin_shutdown();
    assert!(state.readiness().is_err(), "not ready once shutting down");
    let app = sdhop::http::router(Arc::clone(&state));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}/health/ready", listener.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(listener, app).await });
    let r = reqwest::get(&url).await.unwrap();
    assert_eq!(r.status().as_u16(), 503);
    assert!(r.headers().contains_key(RETRY_AFTER));
    let body: Value = r.json().await.unwrap();
    assert_eq!(body["kind"], "not_ready");
    assert!(state.infer.shutdown(Duration::from_secs(10)).await);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn overload_refuses_with_retry_after_and_completes_the_admitted() {
    let server = Server::start(
        InferConfig {
            queue_size: 2,
            max_batch: 1,
            ..InferConfig::default()
        },
        HttpConfig::default(),
    )
    .await;
    let c = reqwest::Client::new();
    let img = encode(&synthetic_scene(9, 960, 720), image::ImageFormat::Png);
    let tasks: Vec<_> = (0..12)
        .map(|_| {
            let req = c
                .post(server.url("/detect?masks=none"))
                .header(CONTENT_TYPE, "image/png")
                .body(img.clone());
            tokio::spawn(async move {
                let r = req.send().await.unwrap();
                let retry = r.headers().contains_key(RETRY_AFTER);
                (r.status().as_u16(), retry)
            })
        })
        .collect();
    let (mut ok, mut refused) = (0, 0);
    for t in tasks {
        match tokio::time::timeout(Duration::from_secs(120), t)
            .await
            .unwrap()
            .unwrap()
        {
            (200, _) => ok += 1,
            (503, true) => refused += 1,
            other => panic!("unexpected answer {other:?}"),
        }
    }
    assert!(
        refused > 0,
        "a queue of 2 must refuse some of 12 concurrent requests"
    );
    assert!(ok >= 1, "admitted requests complete");
    assert_eq!(ok + refused, 12);
    // Still healthy afterwards.
    let r = c.get(server.url("/health/ready")).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    assert!(server.stop().await);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_whose_deadline_passes_in_the_queue_is_never_computed() {
    let server = Server::start(
        InferConfig {
            queue_size: 8,
            max_batch: 1,
            ..InferConfig::default()
        },
        HttpConfig::default(),
    )
    .await;
    let c = reqwest::Client::new();
    let big = encode(&synthetic_scene(5, 1280, 960), image::ImageFormat::Png);
    let small = encode(&synthetic_scene(6, 320, 240), image::ImageFormat::Png);
    let busy = tokio::spawn(
        c.post(server.url("/detect"))
            .header(CONTENT_TYPE, "image/png")
            .body(big)
            .send(),
    );
    tokio::time::sleep(Duration::from_millis(100)).await;
    let r = c
        .post(server.url("/detect?timeout_ms=20"))
        .header(CONTENT_TYPE, "image/png")
        .body(small)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 503);
    assert!(r.headers().contains_key(RETRY_AFTER));
    let body: Value = r.json().await.unwrap();
    assert_eq!(body["kind"], "deadline_exceeded");
    assert_eq!(busy.await.unwrap().unwrap().status(), StatusCode::OK);
    // The expired request leaves the queue without being computed (the
    // worker drops it when it reaches it, after the busy request).
    let mut counts = (0.0, 0.0);
    for _ in 0..200 {
        let text = c
            .get(server.url("/metrics"))
            .send()
            .await
            .unwrap()
            .text()
            .await
            .unwrap();
        counts = (
            metric(&text, "sdhop_queue_requests_total{outcome=\"completed\"}"),
            metric(&text, "sdhop_queue_requests_total{outcome=\"cancelled\"}")
                + metric(&text, "sdhop_queue_requests_total{outcome=\"expired\"}"),
        );
        if counts.1 >= 1.0 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    // The warm-up and the busy request were computed; the expired one not.
    assert_eq!(counts, (2.0, 1.0));
    assert!(server.stop().await);
}

fn metric(text: &str, name: &str) -> f64 {
    text.lines()
        .find_map(|l| l.strip_prefix(name).map(|v| v.trim().parse().unwrap()))
        .unwrap_or(0.0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn png_answer_is_a_label_map_of_the_detections() {
    let server = Server::default().await;
    let sc = synthetic_scene(4, 320, 240);
    let png = encode(&sc, image::ImageFormat::Png);
    let c = reqwest::Client::new();
    let json: Value = c
        .post(server.url("/detect?masks=refined"))
        .header(CONTENT_TYPE, "image/png")
        .body(png.clone())
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let r = c
        .post(server.url("/detect?format=png"))
        .header(CONTENT_TYPE, "image/png")
        .body(png)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    let header: Value =
        serde_json::from_str(r.headers()["x-detections"].to_str().unwrap()).unwrap();
    let r_total: usize = r.headers()["x-detections-total"]
        .to_str()
        .unwrap()
        .parse()
        .unwrap();
    let bytes = r.bytes().await.unwrap();
    let map = image::load_from_memory(&bytes).unwrap().to_luma8();
    assert_eq!((map.width(), map.height()), (320, 240));
    let dets = json["detections"].as_array().unwrap();
    assert_eq!(header.as_array().unwrap().len(), dets.len());
    assert_eq!(r_total, dets.len());
    // The header rounds (scores to 3 decimals, boxes to 1).
    let close =
        |a: &Value, b: &Value, tol: f64| (a.as_f64().unwrap() - b.as_f64().unwrap()).abs() <= tol;
    assert!(close(&header[0]["score"], &dets[0]["score"], 5e-4));
    assert!(close(&header[0]["box"]["x"], &dets[0]["box"]["x"], 0.05));
    // Label 1 covers exactly the best detection's refined mask.
    let m = sdhop::vision::mask::Mask::from_rle(
        &serde_json::from_value(dets[0]["mask"].clone()).unwrap(),
    )
    .unwrap();
    assert!(m.area() > 0);
    for (px, on) in map.iter().zip(&m.data) {
        assert_eq!(*px == 1, *on != 0);
    }
    assert!(server.stop().await);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_lets_requests_in_flight_complete_and_exits_zero() {
    let (mut child, base) = spawn_binary(&["--max-batch", "1"]);
    wait_ready(&base).await;
    let c = reqwest::Client::new();
    let img = encode(&synthetic_scene(8, 1280, 960), image::ImageFormat::Png);
    let inflight: Vec<_> = (0..3)
        .map(|_| {
            tokio::spawn(
                c.post(format!("{base}/detect?masks=none"))
                    .header(CONTENT_TYPE, "image/png")
                    .body(img.clone())
                    .send(),
            )
        })
        .collect();
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert!(
        inflight.iter().any(|t| !t.is_finished()),
        "requests must still be in flight when SIGTERM arrives"
    );
    let kill = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(kill.success());
    for t in inflight {
        let r = t.await.unwrap().unwrap();
        assert_eq!(r.status(), StatusCode::OK, "a request in flight was cut");
    }
    let status = tokio::task::spawn_blocking(move || child.wait().unwrap())
        .await
        .unwrap();
    assert!(status.success(), "exit status {status:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn service_json_equals_the_cli_json() {
    let sc = synthetic_scene(12, 320, 240);
    let png = encode(&sc, image::ImageFormat::Png);
    let dir = std::env::temp_dir().join(format!("sdhop-cli-parity-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let img_path = dir.join("scene.png");
    std::fs::write(&img_path, &png).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_sdhop-train"))
        .arg("detect")
        .arg("--model")
        .arg(models_dir().join("synthetic.safetensors"))
        .arg(&img_path)
        .args(["--masks", "both"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut cli: Value = serde_json::from_slice(&out.stdout).unwrap();
    let server = Server::default().await;
    let svc = detect_json(&reqwest::Client::new(), &server.url(""), png).await;
    // Timings differ from run to run; everything else is the same.
    cli.as_object_mut().unwrap().remove("timing_ms");
    assert!(!svc["detections"].as_array().unwrap().is_empty());
    assert_eq!(cli, svc);
    assert!(server.stop().await);
}

/// The JSON of `POST /detect?model=synthetic&masks=both` for a PNG at
/// `base`, without its timings (they differ from run to run).
async fn detect_json(c: &reqwest::Client, base: &str, png: Vec<u8>) -> Value {
    let mut v: Value = c
        .post(format!("{base}/detect?model=synthetic&masks=both"))
        .header(CONTENT_TYPE, "image/png")
        .body(png)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    v.as_object_mut().unwrap().remove("timing_ms");
    v
}

async fn info_backend(base: &str) -> Value {
    reqwest::get(format!("{base}/info"))
        .await
        .unwrap()
        .json::<Value>()
        .await
        .unwrap()["backend"]
        .clone()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn backend_choice_is_honoured_and_reported() {
    // No adapter at all (wgpu looks at Metal only, which Linux lacks):
    // `--backend gpu` refuses to start with a clear message, `auto` and
    // `cpu` run on the CPU.
    let none = [("WGPU_BACKEND", "metal")];
    let out = Command::new(env!("CARGO_BIN_EXE_sdhop-serve"))
        .args(["--addr", "127.0.0.1:0", "--backend", "gpu", "--models-dir"])
        .arg(models_dir())
        .envs(none)
        .output()
        .unwrap();
    assert!(
        !out.status.success(),
        "--backend gpu without an adapter must fail"
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("--backend gpu") && err.contains("adapter"),
        "{err}"
    );
    for choice in ["auto", "cpu"] {
        let (mut child, base) = spawn_binary_env(&["--backend", choice], &none);
        wait_ready(&base).await;
        assert_eq!(
            info_backend(&base).await["kind"],
            "cpu",
            "--backend {choice}"
        );
        child.kill().unwrap();
        child.wait().unwrap();
    }
    // With the machine's own adapters: `auto` takes a hardware GPU only,
    // `gpu` takes any adapter, software included.
    let adapters = sdhop::backend::gpu::adapters(&sdhop::backend::GpuOptions::default());
    let (mut child, base) = spawn_binary(&["--backend", "auto"]);
    wait_ready(&base).await;
    let kind = info_backend(&base).await["kind"].clone();
    let hardware = adapters.first().is_some_and(|a| !a.software);
    assert_eq!(kind, if hardware { "gpu" } else { "cpu" }, "{adapters:?}");
    child.kill().unwrap();
    child.wait().unwrap();
}

/// `--backend gpu` takes any adapter, software included, and answers as
/// the CPU backend does.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs a Vulkan adapter"]
async fn gpu_backend_is_taken_on_any_adapter_and_answers_as_the_cpu() {
    let adapters = sdhop::backend::gpu::adapters(&sdhop::backend::GpuOptions::default());
    let best = adapters
        .first()
        .expect("needs a Vulkan adapter (install Mesa's mesa-vulkan-drivers)");
    let (mut child, base) = spawn_binary(&["--backend", "gpu"]);
    wait_ready(&base).await;
    let b = info_backend(&base).await;
    assert_eq!(b["kind"], "gpu");
    assert!(b["device"].as_str().unwrap().contains(&best.name), "{b}");
    // The GPU service answers as the CPU one does (timings aside).
    let png = encode(&synthetic_scene(12, 320, 240), image::ImageFormat::Png);
    let c = reqwest::Client::new();
    let mut gpu = detect_json(&c, &base, png.clone()).await;
    child.kill().unwrap();
    child.wait().unwrap();
    let server = Server::default().await;
    let mut cpu = detect_json(&c, &server.url(""), png).await;
    assert!(server.stop().await);
    assert!(!cpu["detections"].as_array().unwrap().is_empty());
    // Scores may differ by float round-off on a real GPU; all else agrees.
    for doc in [&mut gpu, &mut cpu] {
        for d in doc["detections"].as_array_mut().unwrap() {
            let s = d.as_object_mut().unwrap().remove("score").unwrap();
            d["score_rounded"] = serde_json::json!((s.as_f64().unwrap() * 1e3).round());
        }
    }
    assert_eq!(gpu, cpu);
}

/// Scanned meshes are large: the default limit of `POST /pose` admits a
/// 30 MB request, and such a mesh (the box subdivided into 786,432
/// triangles, ASCII PLY with normals and colours as scanners write it) is
/// refined to the true pose.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pose_admits_a_30_mb_mesh() {
    let server = Server::default().await;
    let mesh = Mesh::cuboid(0.15, 0.1, 0.07).subdivided(8);
    let mut ply = format!(
        "ply\nformat ascii 1.0\ncomment scanned\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        mesh.vertices.len(),
        mesh.triangles.len()
    );
    for v in &mesh.vertices {
        let n = v.normalize();
        ply.push_str(&format!(
            "{:.6} {:.6} {:.6} {:.4} {:.4} {:.4} 200 180 160\n",
            v.x, v.y, v.z, n.x, n.y, n.z
        ));
    }
    for t in &mesh.triangles {
        ply.push_str(&format!("3 {} {} {}\n", t[0], t[1], t[2]));
    }
    let ply = ply.into_bytes();
    let sc = pose_scene(false);
    let params = pose_params(&sc.start, serde_json::json!({}));
    let form = pose_form(Some(&sc.png), Some(&ply), None, Some(&params));
    let total = ply.len() + sc.png.len() + params.len();
    assert!(total > 30_000_000, "the request is {total} bytes");
    let t = std::time::Instant::now();
    let resp = reqwest::Client::new()
        .post(server.url("/pose"))
        .multipart(form)
        .send()
        .await
        .unwrap();
    let status = resp.status();
    let body = resp.bytes().await.unwrap();
    println!(
        "{total} bytes, {} triangles: {status} in {:.0} ms",
        mesh.triangles.len(),
        t.elapsed().as_secs_f64() * 1e3
    );
    assert_eq!(status, StatusCode::OK, "{}", String::from_utf8_lossy(&body));
    let r: Value = serde_json::from_slice(&body).unwrap();
    let (deg, mm) = pose_error(&r, &sc.truth);
    assert!(deg < 0.5 && mm < 2.0, "{deg:.2} deg, {mm:.2} mm");
    assert!(server.stop().await);
}
