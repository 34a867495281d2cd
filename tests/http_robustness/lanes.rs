//! The lanes: slow poses keep to theirs, readiness does not follow them.

use super::*;

/// A pose that keeps the pose pool busy for seconds: a dense mesh (196 608
/// triangles) filling several image widths, from a start it does not
/// converge from, allowed the most iterations a client may ask for (about
/// 5 s here; with 49 152 triangles and the default 30 iterations it took
/// 0.2 s, less than three detections beside the other tests in CI).
fn dear_pose() -> (Vec<u8>, Value) {
    let (_, _, truth) = box_scene();
    let dense = Mesh::cuboid(0.15, 0.1, 0.07).subdivided(7).to_ply(true);
    let mut p = params(600.0, truth.rotation_rows(), [0.0, 0.0, 0.12]);
    p["max_iterations"] = json!(sdhop::pose::params::MAX_ITERATIONS);
    (dense, p)
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
            tokio::spawn(async move {
                let (status, body, took) = pose(&s, &png, &dense, p, "?timeout_ms=8000").await;
                (status, body, took, Instant::now())
            })
        })
        .collect();
    // Both admitted and computing (or waiting for the pose thread).
    let c = reqwest::Client::new();
    wait_for_metric(
        &server.base,
        "sdhop_lane_taken{lane=\"pose\"} 2",
        Duration::from_secs(4),
    )
    .await;
    // A third pose is refused at once, naming its lane.
    let (status, body, took) = pose(&server, &png, &dense, p.clone(), "").await;
    assert_eq!(status, 503, "{body}");
    assert!(
        body["error"].as_str().unwrap().contains("pose lane"),
        "{body}"
    );
    assert!(took < Duration::from_millis(1000), "{took:?}");
    // Readiness does not follow a full lane: the pod still serves
    // /detect, and taking it out of the Service would take /detect down
    // wherever every pod's pose lane is full (it answered 503 here).
    for _ in 0..5 {
        let r = c.get(server.url("/health/ready")).send().await.unwrap();
        assert_eq!(r.status(), StatusCode::OK);
    }
    // The saturation shows in /metrics, for an autoscaler.
    let text = metrics_text(&server.base).await;
    assert!(
        text.contains("sdhop_lane_occupancy{lane=\"pose\"} 1\n"),
        "{text}"
    );
    assert!(
        text.contains("sdhop_lane_rejected_total{lane=\"pose\"} 1\n"),
        "{text}"
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
    let (detects, detects_end) = (t.elapsed(), Instant::now());
    let mut pose_times = Vec::new();
    for s in slow {
        let (status, body, took, end) = s.await.unwrap();
        assert!(matches!(status, 200 | 422 | 503), "{status} {body}");
        pose_times.push((took, end));
    }
    let took: Vec<_> = pose_times.iter().map(|&(took, _)| took).collect();
    eprintln!("3 detections in {detects:?} beside poses of {took:?}");
    // Each pose ended after the detections: they were served while both
    // poses held the lane.
    assert!(
        pose_times.iter().all(|&(_, end)| detects_end < end),
        "the detections waited for the poses"
    );
    let server = std::sync::Arc::into_inner(server).unwrap();
    still_serving(&server).await;
    assert!(server.stop().await);
}
