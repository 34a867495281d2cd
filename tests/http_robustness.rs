//! The service against clients that misbehave: pose requests whose work
//! would have no bound (a huge focal length, an object on the camera
//! centre), a computation cut at its deadline, stalled uploads
//! (slow-loris) that must hold no place in the queue, too many connections
//! from one client, and SIGTERM while a long computation runs. Every
//! request ends within its deadline and the server stays ready.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::process::Command;
use std::time::{Duration, Instant};

use nalgebra::{Rotation3, Vector3};
use reqwest::header::CONTENT_TYPE;
use reqwest::StatusCode;
use sdhop::http::conn::ConnLimits;
use sdhop::http::HttpConfig;
use sdhop::infer::InferConfig;
use sdhop::pose::render::{background, render};
use sdhop::pose::{Intrinsics, Mesh, Pose};
use serde_json::{json, Value};

mod common;
use common::*;

const K: Intrinsics = Intrinsics {
    fx: 600.0,
    fy: 600.0,
    cx: 320.0,
    cy: 240.0,
};

/// A rendered box as PNG, its mesh as PLY and its pose.
fn box_scene() -> (Vec<u8>, Mesh, Pose) {
    let pose = Pose {
        rotation: Rotation3::from_euler_angles(0.5, 0.6, 0.2).into_inner(),
        translation: Vector3::new(0.01, -0.01, 0.5),
    };
    let mesh = Mesh::cuboid(0.15, 0.1, 0.07);
    let sc = render(
        &mesh,
        &K,
        &pose,
        &background(640, 480, 3).unwrap(),
        0.0,
        2.0,
        5,
    )
    .unwrap();
    let mut png = Vec::new();
    sc.image
        .to_rgb8()
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    (png, mesh, pose)
}

/// Sends a pose request; its status, body and how long it took.
async fn pose(
    server: &Server,
    png: &[u8],
    mesh: &[u8],
    params: Value,
    query: &str,
) -> (u16, Value, Duration) {
    pose_at(&server.base, png, mesh, params, query).await
}

/// [`pose`] to the server at `base`.
async fn pose_at(
    base: &str,
    png: &[u8],
    mesh: &[u8],
    params: Value,
    query: &str,
) -> (u16, Value, Duration) {
    use reqwest::multipart::{Form, Part};
    let form = Form::new()
        .part("image", Part::bytes(png.to_vec()).file_name("scene.png"))
        .part("mesh", Part::bytes(mesh.to_vec()).file_name("object.ply"))
        .text("params", params.to_string());
    let t = Instant::now();
    let r = reqwest::Client::new()
        .post(format!("{base}/pose{query}"))
        .multipart(form)
        .send()
        .await
        .unwrap();
    let status = r.status().as_u16();
    let body = r.json().await.unwrap_or(Value::Null);
    (status, body, t.elapsed())
}

fn params(fx: f64, rotation: [[f64; 3]; 3], t: [f64; 3]) -> Value {
    json!({
        "intrinsics": {"fx": fx, "fy": fx, "cx": 320.0, "cy": 240.0},
        "initial_pose": {"rotation": rotation, "translation": t},
        "mask": "none"
    })
}

/// The service says it is ready (within a few seconds: while the worker
/// finishes giving up on a request past its deadline, the watchdog keeps
/// it not ready) and still answers a detection.
async fn still_serving(server: &Server) {
    let c = reqwest::Client::new();
    let t = Instant::now();
    loop {
        let r = c.get(server.url("/health/ready")).send().await.unwrap();
        if r.status() == StatusCode::OK {
            break;
        }
        let body: Value = r.json().await.unwrap();
        assert!(
            t.elapsed() < Duration::from_secs(5),
            "not ready 5 s afterwards: {body}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    eprintln!("ready again after {:?}", t.elapsed());
    let img = encode(&synthetic_scene(3, 320, 240), image::ImageFormat::Png);
    let r = c
        .post(server.url("/detect?timeout_ms=10000"))
        .header(CONTENT_TYPE, "image/png")
        .body(img)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK, "/detect fails afterwards");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pathological_poses_are_refused_or_cut_at_their_deadline() {
    let server = Server::default().await;
    let (png, mesh, truth) = box_scene();
    let ply = mesh.to_ply(true);
    let r = truth.rotation_rows();
    // fx = fy = 1e12 projects the object to 1e11 pixels: 422 at once (it
    // used to hold the worker for ever).
    let (status, body, took) = pose(
        &server,
        &png,
        &ply,
        params(1e12, r, [0.0, 0.0, 1000.0]),
        "?timeout_ms=3000",
    )
    .await;
    assert_eq!(status, 422, "{body}");
    assert!(took < Duration::from_secs(2), "{took:?}");
    // The object on the camera centre: refused like one behind it.
    let (status, body, _) = pose(&server, &png, &ply, params(600.0, r, [0.0, 0.0, 1e-6]), "").await;
    assert_eq!(status, 422, "{body}");
    assert!(body["error"].as_str().unwrap().contains("camera plane"));
    // A tiny projection (a box 1e-6 wide at 0.5 m): nothing to fit.
    let (status, body, _) = pose(
        &server,
        &png,
        &Mesh::cuboid(1e-6, 1e-6, 1e-6).to_ply(true),
        params(600.0, r, [0.0, 0.0, 0.5]),
        "",
    )
    .await;
    assert_eq!(status, 422, "{body}");
    // Work that is allowed but dear (a dense mesh filling three image
    // widths) with a short deadline: answered by the deadline, and the
    // worker gives up rather than computing on.
    let dense = Mesh::cuboid(0.15, 0.1, 0.07).subdivided(5).to_ply(true);
    let (status, body, took) = pose(
        &server,
        &png,
        &dense,
        params(600.0, r, [0.0, 0.0, 0.12]),
        "?timeout_ms=150",
    )
    .await;
    assert!(matches!(status, 200 | 422 | 503), "{status} {body}");
    assert!(took < Duration::from_millis(1500), "{took:?}");
    still_serving(&server).await;
    assert!(server.stop().await, "the drain did not finish");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_detection_past_its_deadline_gives_the_worker_back() {
    let server = Server::start(
        InferConfig {
            max_batch: 1,
            ..InferConfig::default()
        },
        HttpConfig::default(),
    )
    .await;
    let c = reqwest::Client::new();
    let big = encode(&synthetic_scene(4, 4000, 3000), image::ImageFormat::Png);
    let detect = |q: &str, body: Vec<u8>| {
        c.post(server.url(&format!("/detect{q}")))
            .header(CONTENT_TYPE, "image/png")
            .body(body)
            .send()
    };
    // The whole computation, for reference.
    let t = Instant::now();
    let r = detect(
        "?timeout_ms=120000&threshold=-1000&max_detections=100&masks=both",
        big.clone(),
    )
    .await
    .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    let full = t.elapsed();
    // With a short deadline it is answered 503 at the deadline, and the
    // worker stops computing it: a small request right behind it is
    // answered long before the whole computation would have ended.
    let t = Instant::now();
    let cut = tokio::spawn(detect(
        "?timeout_ms=1500&threshold=-1000&max_detections=100&masks=both",
        big,
    ));
    // Past its upload and decoding: the worker computes it.
    tokio::time::sleep(Duration::from_millis(1000)).await;
    let small = encode(&synthetic_scene(3, 320, 240), image::ImageFormat::Png);
    let r = detect("?timeout_ms=60000", small).await.unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    let behind = t.elapsed();
    let r = cut.await.unwrap().unwrap();
    assert_eq!(r.status().as_u16(), 503);
    let body: Value = r.json().await.unwrap();
    assert_eq!(body["kind"], "deadline_exceeded");
    eprintln!("whole computation {full:?}; the request behind the cut one {behind:?}");
    assert!(
        behind < full.mul_f64(0.7),
        "the worker kept computing past the deadline: {behind:?} against {full:?}"
    );
    still_serving(&server).await;
    assert!(server.stop().await);
}

/// A raw connection that sent the headers and the first bytes of a body
/// of `length` bytes, and then stalls.
fn stalled(addr: &str, path: &str, ctype: &str, length: usize) -> TcpStream {
    let mut s = TcpStream::connect(addr).unwrap();
    let head = format!(
        "POST {path} HTTP/1.1\r\nHost: x\r\nContent-Type: {ctype}\r\nContent-Length: {length}\r\n\r\n"
    );
    s.write_all(head.as_bytes()).unwrap();
    s.write_all(b"\xff\xd8\xff").unwrap();
    s
}

/// The status line a raw connection reads within `wait`.
fn status_line(s: &mut TcpStream, wait: Duration) -> String {
    s.set_read_timeout(Some(wait)).unwrap();
    let mut buf = [0u8; 64];
    let n = s.read(&mut buf).unwrap_or(0);
    String::from_utf8_lossy(&buf[..n])
        .lines()
        .next()
        .unwrap_or_default()
        .to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stalled_uploads_hold_no_place_in_the_queue() {
    let server = Server::start(
        InferConfig {
            queue_size: 4,
            ..InferConfig::default()
        },
        HttpConfig {
            body_grace: Duration::from_secs(2),
            ..HttpConfig::default()
        },
    )
    .await;
    let addr = server.base.trim_start_matches("http://").to_string();
    // Ten times the queue: stalled /detect and /pose uploads.
    let mut socks: Vec<TcpStream> = (0..30)
        .map(|_| stalled(&addr, "/detect", "image/jpeg", 100_000))
        .chain(
            (0..10).map(|_| stalled(&addr, "/pose", "multipart/form-data; boundary=xyz", 100_000)),
        )
        .collect();
    tokio::time::sleep(Duration::from_millis(200)).await;
    // Others are served meanwhile.
    still_serving(&server).await;
    // The stalled uploads are cut off once the grace has passed: 408 and
    // closed.
    let started = Instant::now();
    let lines = tokio::task::spawn_blocking(move || {
        socks
            .iter_mut()
            .map(|s| status_line(s, Duration::from_secs(10)))
            .collect::<Vec<_>>()
    })
    .await
    .unwrap();
    for line in &lines {
        assert!(line.starts_with("HTTP/1.1 408"), "{line:?}");
    }
    assert!(started.elapsed() < Duration::from_secs(6));
    still_serving(&server).await;
    assert!(server.stop().await);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_over_the_per_client_limit_are_refused() {
    let server = Server::start(
        InferConfig::default(),
        HttpConfig {
            connections: ConnLimits {
                max_total: 64,
                max_per_client: 4,
            },
            ..HttpConfig::default()
        },
    )
    .await;
    let addr = server.base.trim_start_matches("http://").to_string();
    let idle: Vec<TcpStream> = (0..4).map(|_| TcpStream::connect(&addr).unwrap()).collect();
    tokio::time::sleep(Duration::from_millis(100)).await;
    let mut fifth = TcpStream::connect(&addr).unwrap();
    fifth
        .write_all(b"GET /health/live HTTP/1.1\r\nHost: x\r\n\r\n")
        .unwrap();
    let line = tokio::task::spawn_blocking(move || status_line(&mut fifth, Duration::from_secs(5)))
        .await
        .unwrap();
    assert!(line.starts_with("HTTP/1.1 429"), "{line:?}");
    // The places come back when the connections close.
    drop(idle);
    tokio::time::sleep(Duration::from_millis(200)).await;
    let text = reqwest::get(server.url("/metrics"))
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    assert!(
        text.contains("sdhop_http_connections_refused_total{limit=\"per_client\"} 1"),
        "{text}"
    );
    assert!(text.contains("sdhop_http_connections_open 1"), "{text}");
    assert!(server.stop().await);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_exits_within_the_grace_period_while_a_long_computation_runs() {
    let (mut child, base) = spawn_binary(&["--grace-seconds", "2", "--max-batch", "1"]);
    wait_ready(&base).await;
    // A detection of a few seconds with a deadline far away.
    let img = encode(&synthetic_scene(4, 4000, 3000), image::ImageFormat::Png);
    let long = tokio::spawn(
        reqwest::Client::new()
            .post(format!(
                "{base}/detect?timeout_ms=300000&threshold=-1000&max_detections=100&masks=both"
            ))
            .header(CONTENT_TYPE, "image/png")
            .body(img)
            .send(),
    );
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert!(!long.is_finished(), "the computation must still run");
    // Two more behind it in the queue (one request per batch).
    let small = encode(&synthetic_scene(3, 320, 240), image::ImageFormat::Png);
    let queued: Vec<_> = (0..2)
        .map(|_| {
            tokio::spawn(
                reqwest::Client::new()
                    .post(format!("{base}/detect?timeout_ms=300000"))
                    .header(CONTENT_TYPE, "image/png")
                    .body(small.clone())
                    .send(),
            )
        })
        .collect();
    tokio::time::sleep(Duration::from_millis(300)).await;
    let sent = Instant::now();
    assert!(Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap()
        .success());
    let status = tokio::task::spawn_blocking(move || child.wait().unwrap())
        .await
        .unwrap();
    let took = sent.elapsed();
    assert!(
        took < Duration::from_millis(3500),
        "exited {took:?} after SIGTERM with a 2 s grace period"
    );
    assert!(status.code().is_some(), "killed by a signal: {status:?}");
    // The cut request and those queued behind it are answered 503 as
    // the grace period ends (they used to see the connection close).
    let r = long.await.unwrap().expect("the long request got no answer");
    assert_eq!(
        r.status(),
        StatusCode::SERVICE_UNAVAILABLE,
        "the long computation finished within the grace period: make it longer"
    );
    for q in queued {
        let r = q.await.unwrap().expect("a queued request got no answer");
        assert_eq!(r.status(), StatusCode::SERVICE_UNAVAILABLE);
        let body: Value = r.json().await.unwrap();
        assert_eq!(body["kind"], "not_ready", "{body}");
    }
}

/// The peak of process `pid`'s resident memory (MB) above its start while
/// `f` runs, sampled every 10 ms from /proc; 0 where /proc is missing.
async fn peak_rss_mb<F: std::future::Future>(pid: u32, f: F) -> (F::Output, f64) {
    let rss = move || -> f64 {
        std::fs::read_to_string(format!("/proc/{pid}/status"))
            .ok()
            .and_then(|s| {
                s.lines()
                    .find(|l| l.starts_with("VmRSS"))
                    .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
            })
            .map_or(0.0, |kb| kb / 1024.0)
    };
    let before = rss();
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let s = stop.clone();
    let sampler = std::thread::spawn(move || {
        let mut peak = 0.0f64;
        while !s.load(std::sync::atomic::Ordering::Relaxed) {
            peak = peak.max(rss());
            std::thread::sleep(Duration::from_millis(10));
        }
        peak.max(rss())
    });
    let out = f.await;
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let peak = sampler.join().unwrap();
    (out, (peak - before).max(0.0))
}

/// A binary PLY of the 8-vertex cube (one face) and an extra element of
/// `junk` one-byte items, of which `present` bytes are in the file.
fn junk_ply(junk: usize, present: usize) -> Vec<u8> {
    let mut f = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex 8\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nelement junk {junk}\nproperty uchar a\nend_header\n"
    )
    .into_bytes();
    for i in 0..8 {
        for c in [i & 1, (i >> 1) & 1, (i >> 2) & 1] {
            f.extend_from_slice(&(c as f32 * 0.1 - 0.05).to_le_bytes());
        }
    }
    f.push(3);
    for i in [0i32, 1, 2] {
        f.extend_from_slice(&i.to_le_bytes());
    }
    f.extend(vec![0u8; present]);
    f
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_mesh_that_declares_more_than_its_bytes_hold_is_refused_at_once() {
    // The real binary, so that its memory is its own (the other tests of
    // this process run beside this one).
    let (mut child, base) = spawn_binary(&[]);
    wait_ready(&base).await;
    let (png, _, truth) = box_scene();
    let p = params(600.0, truth.rotation_rows(), [0.0, 0.0, 0.5]);
    // Ten million junk items declared, one million present: the reader
    // used to allocate for every declared item (3.8 GB) before failing.
    let junk = junk_ply(10_000_000, 1_000_000);
    let ((status, body, took), peak) = peak_rss_mb(
        child.id(),
        pose_at(&base, &png, &junk, p.clone(), "?timeout_ms=2000"),
    )
    .await;
    assert_eq!(status, 422, "{body}");
    let msg = body["error"].as_str().unwrap();
    assert!(msg.contains("element junk") && !msg.contains('\n'), "{msg}");
    assert!(took < Duration::from_millis(1000), "{took:?}");
    eprintln!("junk element: {took:?}, peak {peak:.0} MB above before");
    assert!(peak < 200.0, "peak {peak:.0} MB");
    // The same junk, all of it present: stepped over, and the cube's pose
    // is computed (or its edges found too few), never a 5xx or a 413.
    let junk = junk_ply(1_000_000, 1_000_000);
    let (status, body, _) = pose_at(&base, &png, &junk, p, "?timeout_ms=5000").await;
    assert!(matches!(status, 200 | 422), "{status} {body}");
    assert!(
        !body["error"].as_str().unwrap_or("").contains("PLY"),
        "{body}"
    );
    let _ = child.kill();
    let _ = child.wait();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn meshes_above_the_limits_are_refused_from_their_counts() {
    let server = Server::start(
        InferConfig::default(),
        HttpConfig {
            mesh: sdhop::pose::MeshLimits {
                max_vertices: 1000,
                max_triangles: 1000,
            },
            ..HttpConfig::default()
        },
    )
    .await;
    let (png, _, truth) = box_scene();
    let p = params(600.0, truth.rotation_rows(), [0.0, 0.0, 0.5]);
    // 3072 triangles: 413 naming the limits.
    let fine = Mesh::cuboid(0.15, 0.1, 0.07).subdivided(4);
    let (status, body, took) = pose(&server, &png, &fine.to_ply(true), p.clone(), "").await;
    assert_eq!(status, 413, "{body}");
    assert!(
        body["error"].as_str().unwrap().contains("at most 1000"),
        "{body}"
    );
    assert!(took < Duration::from_millis(1000), "{took:?}");
    // An OBJ of 4 vertices and one face of 200 000 indices (199 998
    // triangles): refused by the counting pass.
    let mut bomb = b"v 0 0 0.5\nv 0.1 0 0.5\nv 0.1 0.1 0.5\nv 0 0.1 0.5\nf".to_vec();
    for _ in 0..50_000 {
        bomb.extend_from_slice(b" 1 2 3 4");
    }
    bomb.push(b'\n');
    let (status, body, _) = pose(&server, &png, &bomb, p.clone(), "").await;
    assert_eq!(status, 413, "{body}");
    assert!(body["error"].as_str().unwrap().contains("199998 triangles"));
    // Within the limits: read.
    let (status, body, _) = pose(
        &server,
        &png,
        &Mesh::cuboid(0.15, 0.1, 0.07).to_obj().into_bytes(),
        p,
        "",
    )
    .await;
    assert!(matches!(status, 200 | 422), "{status} {body}");
    assert!(
        !body["error"].as_str().unwrap_or("").contains("mesh"),
        "{body}"
    );
    // /info says the limits.
    let info: Value = reqwest::get(server.url("/info"))
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(info["limits"]["max_mesh_triangles"], 1000);
    assert_eq!(info["limits"]["max_mesh_vertices"], 1000);
    assert!(server.stop().await);
}

/// A pose that keeps the pose pool busy until its deadline: a dense mesh
/// filling several image widths.
fn dear_pose() -> (Vec<u8>, Value) {
    let (_, _, truth) = box_scene();
    let dense = Mesh::cuboid(0.15, 0.1, 0.07).subdivided(6).to_ply(true);
    (
        dense,
        params(600.0, truth.rotation_rows(), [0.0, 0.0, 0.12]),
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_poses_keep_to_their_lane() {
    let server = Server::start(
        InferConfig {
            pose_queue_size: 2,
            pose_threads: 1,
            ..InferConfig::default()
        },
        HttpConfig::default(),
    )
    .await;
    let server = std::sync::Arc::new(server);
    let (png, _, _) = box_scene();
    let (dense, p) = dear_pose();
    let slow: Vec<_> = (0..2)
        .map(|_| {
            let (s, png, dense, p) = (server.clone(), png.clone(), dense.clone(), p.clone());
            tokio::spawn(async move { pose(&s, &png, &dense, p, "?timeout_ms=8000").await })
        })
        .collect();
    // Both admitted and computing (or waiting for the pose thread).
    let c = reqwest::Client::new();
    let t = Instant::now();
    loop {
        let text = c
            .get(server.url("/metrics"))
            .send()
            .await
            .unwrap()
            .text()
            .await
            .unwrap();
        if text.contains("sdhop_lane_taken{lane=\"pose\"} 2") {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(4), "{text}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // A third pose is refused at once, naming its lane.
    let (status, body, took) = pose(&server, &png, &dense, p.clone(), "").await;
    assert_eq!(status, 503, "{body}");
    assert!(
        body["error"].as_str().unwrap().contains("pose lane"),
        "{body}"
    );
    assert!(took < Duration::from_millis(1000), "{took:?}");
    // Readiness says the lane is saturated.
    let r = c.get(server.url("/health/ready")).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::SERVICE_UNAVAILABLE);
    let body: Value = r.json().await.unwrap();
    assert!(
        body["error"].as_str().unwrap().contains("pose lane"),
        "{body}"
    );
    // Detections are served meanwhile, well before the poses end.
    let img = encode(&synthetic_scene(3, 320, 240), image::ImageFormat::Png);
    let t = Instant::now();
    for _ in 0..3 {
        let r = c
            .post(server.url("/detect?timeout_ms=5000"))
            .header(CONTENT_TYPE, "image/png")
            .body(img.clone())
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::OK);
    }
    let detects = t.elapsed();
    let mut pose_times = Vec::new();
    for s in slow {
        let (status, body, took) = s.await.unwrap();
        assert!(matches!(status, 200 | 422 | 503), "{status} {body}");
        pose_times.push(took);
    }
    eprintln!("3 detections in {detects:?} beside poses of {pose_times:?}");
    assert!(
        pose_times.iter().all(|&p| detects < p),
        "the detections waited for the poses"
    );
    let server = std::sync::Arc::into_inner(server).unwrap();
    still_serving(&server).await;
    assert!(server.stop().await);
}

/// A PNG of `img`.
fn png_of<P, C>(img: &image::ImageBuffer<P, C>) -> Vec<u8>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
    C: std::ops::Deref<Target = [P::Subpixel]>,
{
    let mut out = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png)
        .unwrap();
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cheap_refusals_come_before_any_work() {
    let server = Server::default().await;
    let (png, mesh, truth) = box_scene();
    let ply = mesh.to_ply(true);
    let r = truth.rotation_rows();
    let detect_with = |extra: Value| {
        let mut p = params(600.0, r, [0.0, 0.0, 0.5]);
        p["mask"] = json!("detect");
        for (k, v) in extra.as_object().unwrap() {
            p[k] = v.clone();
        }
        p
    };
    let no_start = |extra: Value| {
        let mut p = json!({"intrinsics": {"fx": 600.0, "fy": 600.0, "cx": 320.0, "cy": 240.0}});
        for (k, v) in extra.as_object().unwrap() {
            p[k] = v.clone();
        }
        p
    };
    let huge_mask = png_of(&image::GrayImage::new(4000, 4000));
    let long_name = "m".repeat(60_000);
    for (what, p, mask, status, says) in [
        (
            "a label the model lacks",
            detect_with(json!({"model": "synthetic", "label": "ape"})),
            None,
            422,
            "label \"ape\" is not among",
        ),
        (
            "an empty label",
            no_start(json!({"model": "synthetic", "label": ""})),
            None,
            422,
            "is not among",
        ),
        (
            "a model without training views",
            no_start(json!({"model": "synthetic"})),
            None,
            422,
            "carries no training views",
        ),
        (
            "a mask of another size",
            {
                let mut p = params(600.0, r, [0.0, 0.0, 0.5]);
                p.as_object_mut().unwrap().remove("mask");
                p
            },
            Some(huge_mask),
            422,
            "the mask is 4000x4000, the image 640x480",
        ),
        (
            "a 60 KB model name",
            detect_with(json!({"model": long_name})),
            None,
            404,
            "(60000 characters)",
        ),
        (
            "model and label where no detection runs",
            {
                let mut p = params(600.0, r, [0.0, 0.0, 0.5]);
                p["model"] = json!("synthetic");
                p["label"] = json!("synthetic");
                p
            },
            None,
            422,
            "model and label are used only with mask \"detect\"",
        ),
        (
            "a mask sent with mask none",
            params(600.0, r, [0.0, 0.0, 0.5]),
            Some(png_of(&image::GrayImage::new(640, 480))),
            422,
            "ask for mask \"none\"",
        ),
    ] {
        use reqwest::multipart::{Form, Part};
        let mut form = Form::new()
            .part("image", Part::bytes(png.clone()).file_name("scene.png"))
            .part("mesh", Part::bytes(ply.clone()).file_name("object.ply"))
            .text("params", p.to_string());
        if let Some(m) = mask {
            form = form.part("mask", Part::bytes(m).file_name("mask.png"));
        }
        let t = Instant::now();
        let resp = reqwest::Client::new()
            .post(server.url("/pose"))
            .multipart(form)
            .send()
            .await
            .unwrap();
        let took = t.elapsed();
        let code = resp.status().as_u16();
        let body: Value = resp.json().await.unwrap();
        let msg = body["error"].as_str().unwrap();
        eprintln!("{what}: {code} in {took:?}: {msg}");
        assert_eq!(code, status, "{what}: {body}");
        assert!(msg.contains(says), "{what}: {msg}");
        assert!(msg.len() < 400, "{what}: a {} byte message", msg.len());
        assert!(!msg.contains('\n'), "{what}: {msg}");
        // No detection, no decoding of the mask: well under the time
        // either takes (the upload of the test's body included).
        assert!(took < Duration::from_millis(500), "{what}: {took:?}");
    }
    assert!(server.stop().await);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn messages_name_the_problem_in_one_line() {
    let server = Server::default().await;
    let (png, _, truth) = box_scene();
    let p = params(600.0, truth.rotation_rows(), [0.0, 0.0, 0.5]);
    for (mesh, says) in [
        (
            &b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 x\n0 1 0\n3 0 1 2\n"[..],
            "invalid mesh: PLY: \"x\" is not a number",
        ),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quux x\nend_header\n", "unknown type"),
        (b"v 0 0 0\nv 1 0 0\nf 1 2 three\n", "OBJ line 3"),
    ] {
        let (status, body, _) = pose(&server, &png, mesh, p.clone(), "").await;
        assert_eq!(status, 422, "{body}");
        let msg = body["error"].as_str().unwrap();
        assert!(msg.contains(says) && !msg.contains('\n'), "{msg}");
        assert!(!msg.contains("Custom {") && !msg.contains("ParseError"), "{msg}");
    }
    // An image of another format says which, in words.
    let mut gif = b"GIF89a".to_vec();
    gif.extend([0u8; 20]);
    let r = reqwest::Client::new()
        .post(server.url("/detect"))
        .header(CONTENT_TYPE, "image/png")
        .body(gif)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 415);
    let body: Value = r.json().await.unwrap();
    assert!(
        body["error"].as_str().unwrap().contains("this one is GIF"),
        "{body}"
    );
    assert!(server.stop().await);
}

#[test]
fn masks_are_read_from_their_stored_values() {
    use sdhop::http::image::{decode_mask, ImageLimits};
    let limits = ImageLimits::default();
    let inside = |x: u32, y: u32| (2..6).contains(&x) && (1..3).contains(&y);
    // 16-bit grey with value 1 where visible (it used to read as empty).
    let g16 = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(8, 4, |x, y| {
        image::Luma([u16::from(inside(x, y))])
    });
    // RGBA: opaque white inside, and white but fully transparent outside.
    let rgba = image::RgbaImage::from_fn(8, 4, |x, y| {
        image::Rgba([255, 255, 255, if inside(x, y) { 255 } else { 0 }])
    });
    // A palette whose index 1 is black: index 1 inside.
    let palette = {
        let mut out = Vec::new();
        let mut e = png::Encoder::new(&mut out, 8, 4);
        e.set_color(png::ColorType::Indexed);
        e.set_depth(png::BitDepth::Eight);
        e.set_palette(vec![255, 255, 255, 0, 0, 0]);
        let mut w = e.write_header().unwrap();
        let data: Vec<u8> = (0..4)
            .flat_map(|y| (0..8).map(move |x| u8::from(inside(x, y))))
            .collect();
        w.write_image_data(&data).unwrap();
        w.finish().unwrap();
        out
    };
    // 1-bit grey.
    let bits = {
        let mut out = Vec::new();
        let mut e = png::Encoder::new(&mut out, 8, 4);
        e.set_color(png::ColorType::Grayscale);
        e.set_depth(png::BitDepth::One);
        let mut w = e.write_header().unwrap();
        let data: Vec<u8> = (0..4u32)
            .map(|y| (0..8u32).fold(0u8, |b, x| (b << 1) | u8::from(inside(x, y))))
            .collect();
        w.write_image_data(&data).unwrap();
        w.finish().unwrap();
        out
    };
    for (what, bytes) in [
        ("16-bit", png_of(&g16)),
        ("rgba", png_of(&rgba)),
        ("palette", palette),
        ("1-bit", bits),
    ] {
        let m = decode_mask(&bytes, &limits, Some((8, 4))).unwrap();
        for y in 0..4 {
            for x in 0..8 {
                assert_eq!(m.get(x, y), inside(x as u32, y as u32), "{what} ({x}, {y})");
            }
        }
    }
    // The size is checked from the header, before the pixels.
    let big = png_of(&image::GrayImage::new(400, 300));
    let err = decode_mask(&big, &limits, Some((8, 4))).unwrap_err();
    assert!(err.to_string().contains("400x300"), "{err}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn label_maps_keep_their_header_small_and_every_detection() {
    let server = Server::default().await;
    let img = encode(&synthetic_scene(4, 640, 480), image::ImageFormat::Png);
    let r = reqwest::Client::new()
        .post(server.url("/detect?format=png&threshold=-1000&max_detections=100&masks=refined"))
        .header(CONTENT_TYPE, "image/png")
        .body(img)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    let header = r.headers()["x-detections"].to_str().unwrap().to_string();
    let total: usize = r.headers()["x-detections-total"]
        .to_str()
        .unwrap()
        .parse()
        .unwrap();
    assert!(header.len() <= 7 << 10, "{} bytes", header.len());
    let in_header: Vec<Value> = serde_json::from_str(&header).unwrap();
    assert!(in_header.len() <= total && total >= 1);
    let bytes = r.bytes().await.unwrap();
    let reader = png::Decoder::new(std::io::Cursor::new(&bytes[..]))
        .read_info()
        .unwrap();
    let chunk = reader
        .info()
        .utf8_text
        .iter()
        .find(|t| t.keyword == "sdhop-detections")
        .unwrap()
        .get_text()
        .unwrap();
    let all: Vec<Value> = serde_json::from_str(&chunk).unwrap();
    assert_eq!(all.len(), total);
    for (h, a) in in_header.iter().zip(&all) {
        assert_eq!(h["label"], a["label"]);
        assert!((h["score"].as_f64().unwrap() - a["score"].as_f64().unwrap()).abs() < 1e-3);
    }
    // More than 255 detections: a 16-bit map (built from a response of
    // 300 one-pixel detections).
    use sdhop::pipeline::{BoxJson, DetectResponse, DetectionJson, ImageSize, Timing};
    let mut resp = DetectResponse {
        image: ImageSize {
            width: 20,
            height: 20,
        },
        detections: Vec::new(),
        timing_ms: Timing::default(),
    };
    for k in 0..300usize {
        let mut m = sdhop::vision::mask::Mask::new(20, 20);
        m.set(k % 20, k / 20, true);
        resp.detections.push(DetectionJson {
            label: "l".into(),
            model: "m".into(),
            score: 0.0,
            bbox: BoxJson {
                x: 0.0,
                y: 0.0,
                width: 1.0,
                height: 1.0,
            },
            viewpoint: 0,
            view: None,
            level: 0,
            visible_fraction: 1.0,
            truncated: false,
            mask: Some(m.to_rle()),
            raw_mask: None,
        });
    }
    let map = sdhop::http::detect::label_map(&resp);
    assert_eq!(map.iter().copied().max(), Some(300));
    // Encoded as a 16-bit PNG that keeps label 300.
    let png16 = sdhop::http::detect::label_map_png(&resp, "[]".into()).unwrap();
    let decoded = image::load_from_memory(&png16).unwrap();
    assert_eq!(decoded.color(), image::ColorType::L16);
    let decoded = decoded.to_luma16();
    assert_eq!(decoded.get_pixel(299 % 20, 299 / 20).0[0], 300);
    assert!(server.stop().await);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn repeated_options_and_weights_of_accept_are_heeded() {
    let server = Server::default().await;
    let c = reqwest::Client::new();
    let img = encode(&synthetic_scene(3, 320, 240), image::ImageFormat::Png);
    let detect = |q: &str, accept: Option<&str>| {
        let mut r = c
            .post(server.url(&format!("/detect{q}")))
            .header(CONTENT_TYPE, "image/png")
            .body(img.clone());
        if let Some(a) = accept {
            r = r.header(reqwest::header::ACCEPT, a);
        }
        r.send()
    };
    let r = detect("?threshold=0&threshold=1", None).await.unwrap();
    assert_eq!(r.status().as_u16(), 400);
    let body: Value = r.json().await.unwrap();
    assert!(
        body["error"].as_str().unwrap().contains("repeated"),
        "{body}"
    );
    // model may repeat.
    let r = detect("?model=synthetic&model=synthetic", None)
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    for (accept, png) in [
        ("image/png;q=0", false),
        ("image/png;q=0.5, application/json", false),
        ("image/png", true),
        ("application/json;q=0.1, image/png", true),
    ] {
        let r = detect("", Some(accept)).await.unwrap();
        assert_eq!(r.status(), StatusCode::OK);
        let ctype = r.headers()[CONTENT_TYPE].to_str().unwrap().to_string();
        assert_eq!(ctype == "image/png", png, "{accept}: {ctype}");
    }
    // /pose's only option, repeated.
    let (png, mesh, truth) = box_scene();
    let (status, body, _) = pose(
        &server,
        &png,
        &mesh.to_ply(true),
        params(600.0, truth.rotation_rows(), [0.0, 0.0, 0.5]),
        "?timeout_ms=1000&timeout_ms=2000",
    )
    .await;
    assert_eq!(status, 400, "{body}");
    assert!(server.stop().await);
}

#[test]
fn help_documents_every_flag() {
    let out = Command::new(env!("CARGO_BIN_EXE_sdhop-serve"))
        .arg("--help")
        .output()
        .unwrap();
    let text = String::from_utf8(out.stdout).unwrap();
    // Each flag's text follows it (clap puts it on the next lines).
    let after = |flag: &str| -> String {
        let i = text.find(flag).unwrap_or_else(|| panic!("{flag} missing"));
        text[i + flag.len()..]
            .lines()
            .skip(1)
            .take(2)
            .collect::<Vec<_>>()
            .join(" ")
    };
    assert!(
        after("--min-body-rate")
            .trim()
            .starts_with("A request body"),
        "{}",
        after("--min-body-rate")
    );
    assert!(
        after("--grace-seconds").contains("SIGTERM"),
        "{}",
        after("--grace-seconds")
    );
    for flag in [
        "--max-mesh-vertices",
        "--max-mesh-triangles",
        "--pose-queue-size",
        "--pose-threads",
    ] {
        assert!(after(flag).trim().len() > 20, "{flag}: {}", after(flag));
    }
}
