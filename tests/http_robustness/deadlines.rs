//! Deadlines and stalls: pathological poses cut at their deadline, a
//! detection past its deadline, stalled uploads, too many connections.

use super::*;

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
async fn memory_is_reserved_before_decoding_and_too_much_is_refused_saying_so() {
    // The smallest budget: a 4000x3000 photograph with every shipped model
    // needs more than all of it; a 640x480 one fits.
    let server = Server::start(
        InferConfig {
            memory_budget_bytes: sdhop::infer::budget::MIN_BUDGET_BYTES,
            ..InferConfig::default()
        },
        HttpConfig::default(),
    )
    .await;
    let c = reqwest::Client::new();
    let big = encode(&synthetic_scene(4, 4000, 3000), image::ImageFormat::Png);
    let t = Instant::now();
    let r = c
        .post(server.url("/detect"))
        .header(CONTENT_TYPE, "image/png")
        .body(big)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::PAYLOAD_TOO_LARGE);
    let body: Value = r.json().await.unwrap();
    let msg = body["error"].as_str().unwrap();
    assert!(msg.contains("memory budget of 256 MiB"), "{msg}");
    assert!(
        t.elapsed() < Duration::from_secs(5),
        "refused before decoding"
    );
    // /info says what the budget is.
    let info: Value = c
        .get(server.url("/info"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(info["limits"]["memory_budget_mb"], 256);
    // A photograph that fits is answered, and the budget is whole again.
    let small = encode(&synthetic_scene(3, 640, 480), image::ImageFormat::Png);
    let r = c
        .post(server.url("/detect"))
        .header(CONTENT_TYPE, "image/png")
        .body(small)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    still_serving(&server).await;
    assert!(server.stop().await);
}
