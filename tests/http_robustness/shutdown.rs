//! Shutdown as an orchestrator does it: SIGTERM, the drain, the grace
//! period.

use super::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_exits_within_the_grace_period_while_a_long_computation_runs() {
    let (mut child, base) = spawn_binary(&[
        "--grace-seconds",
        "1",
        "--drain-seconds",
        "0",
        "--max-batch",
        "1",
    ]);
    wait_ready(&base).await;
    // A detection of a few seconds (2.5 s on the 2-core machine) with a
    // deadline far away; SIGTERM comes 0.2 s into it, and the grace
    // period's cut 0.75 s later.
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
    // Until the worker computes it (the warm-up was the first batch).
    wait_for_metric(&base, "sdhop_batch_size_count 2", Duration::from_secs(5)).await;
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
    tokio::time::sleep(Duration::from_millis(200)).await;
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
        took < Duration::from_millis(2500),
        "exited {took:?} after SIGTERM with a 1 s grace period"
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

/// Sends `kill -TERM` to `pid`.
fn sigterm(pid: u32) {
    assert!(Command::new("kill")
        .args(["-TERM", &pid.to_string()])
        .status()
        .unwrap()
        .success());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_drains_and_a_slow_upload_gets_a_status() {
    let (mut child, base) = spawn_binary(&["--drain-seconds", "2", "--grace-seconds", "2"]);
    wait_ready(&base).await;
    let addr = base.trim_start_matches("http://").to_string();
    // An upload still arriving when the grace period ends: 40 KB/s (above
    // --min-body-rate) of a 10 MB body.
    let mut upload = stalled(&addr, "/detect", "image/jpeg", 10_000_000);
    let mut writer = upload.try_clone().unwrap();
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let stopped = stop.clone();
    let sender = std::thread::spawn(move || {
        while !stopped.load(std::sync::atomic::Ordering::Relaxed) {
            if writer.write_all(&[0u8; 2048]).is_err() {
                break;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    });
    tokio::time::sleep(Duration::from_millis(300)).await;
    let sent = Instant::now();
    sigterm(child.id());
    // During the drain: new connections are accepted, readiness answers
    // 503 and requests are answered (they used to be refused 0.3 s after
    // SIGTERM).
    let c = reqwest::Client::new();
    let img = encode(&synthetic_scene(3, 320, 240), image::ImageFormat::Png);
    let r = c
        .post(format!("{base}/detect?timeout_ms=1500"))
        .header(CONTENT_TYPE, "image/png")
        .body(img)
        .send()
        .await
        .expect("a request during the drain was refused");
    assert_eq!(r.status(), StatusCode::OK);
    let mut probes = 0;
    while sent.elapsed() < Duration::from_millis(1700) {
        let r = reqwest::Client::new()
            .get(format!("{base}/health/ready"))
            .send()
            .await
            .expect("a readiness probe during the drain was refused");
        assert_eq!(r.status(), StatusCode::SERVICE_UNAVAILABLE);
        let body: Value = r.json().await.unwrap();
        assert!(
            body["error"].as_str().unwrap().contains("draining"),
            "{body}"
        );
        probes += 1;
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(probes >= 5, "{probes} probes");
    // The upload is answered as the grace period ends (drain 2 s, grace
    // 2 s: 3.5 s after SIGTERM), not cut without a status.
    let line =
        tokio::task::spawn_blocking(move || status_line(&mut upload, Duration::from_secs(6)))
            .await
            .unwrap();
    let answered = sent.elapsed();
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    assert!(
        line.starts_with("HTTP/1.1 503"),
        "{line:?} after {answered:?}"
    );
    assert!(answered > Duration::from_secs(3), "{answered:?}");
    let status = tokio::task::spawn_blocking(move || child.wait().unwrap())
        .await
        .unwrap();
    assert!(status.code().is_some(), "killed by a signal: {status:?}");
    assert!(
        sent.elapsed() < Duration::from_secs(5),
        "{:?}",
        sent.elapsed()
    );
    sender.join().unwrap();
}
