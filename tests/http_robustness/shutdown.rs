//! Shutdown as an orchestrator does it: SIGTERM, the drain, the grace
//! period.

use super::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_exits_within_the_grace_period_while_a_long_computation_runs() {
    let (mut child, base) = spawn_binary(&[
        "--grace-seconds",
        "2",
        "--drain-seconds",
        "0",
        "--max-batch",
        "1",
    ]);
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
