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

#[path = "../common/mod.rs"]
mod common;
use common::*;

mod deadlines;
mod lanes;
mod meshes;
mod requests;
mod shutdown;

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
