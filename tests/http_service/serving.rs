//! Serving as a client and an operator see it: readiness, overload,
//! deadlines, label maps, SIGTERM, the CLI's JSON, the backends, a large
//! mesh.

use super::*;

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
        let text = metrics_text(&server.base).await;
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
    let (mut child, base) = spawn_binary(&["--max-batch", "1", "--drain-seconds", "1"]);
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

/// Both kinds per object through the service: a learned-cell model with a
/// HOG segmenter answers `POST /detect` as the library does (the CPU
/// backend builds the HOG pyramid beside the learned one), and `GET
/// /models` names the segmenter's cells, both as openapi.yaml says.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_model_with_a_segmenter_is_served_as_the_library_answers() {
    use sdhop::pipeline::{detect_image, DetectOptions, MaskMode};
    use sdhop::synth::{hand_model, HandModelParams};
    use sdhop::vision::cells::FeatureKind;
    let spec = spec();
    let hog = hand_model(&OBJECT, "synthetic", true, &HandModelParams::default()).unwrap();
    let mut finder = hog.clone();
    finder.meta.pyramid.features = FeatureKind::Cnn;
    finder.meta.cells = FeatureKind::Cnn.fingerprint().unwrap();
    finder.meta.detection.threshold = -1e6;
    let paired = finder.with_segmenter(hog).unwrap();
    let dir = std::env::temp_dir().join(format!("sdhop-segmenter-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    paired.save(&dir.join("synthetic.safetensors")).unwrap();
    let registry = Registry::new();
    let metrics = InferMetrics::new(&registry).unwrap();
    let infer = Infer::start(Box::new(CpuBackend), InferConfig::default(), metrics).unwrap();
    let state = AppState::new(
        infer,
        load_models(&dir).unwrap(),
        HttpConfig::default(),
        registry,
    )
    .unwrap();
    warm_up(&state).await.unwrap();
    let app = sdhop::http::router(Arc::clone(&state));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let base = format!("http://{}", listener.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(listener, app).await });
    let c = reqwest::Client::new();
    let r = c.get(format!("{base}/models")).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    let body = r.bytes().await.unwrap();
    check_schema(&spec, "/models", "get", 200, "application/json", &body);
    let models: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(models[0]["features"], "cnn");
    assert_eq!(models[0]["segmenter_features"], "hog");
    let png = encode(&synthetic_scene(3, 320, 240), image::ImageFormat::Png);
    // The library sees the pixels the service decodes.
    let decoded = image::load_from_memory(&png).unwrap().to_rgb8();
    let img = sdhop::vision::image::ColorImage::from_rgb8(&decoded).unwrap();
    let r = c
        .post(format!("{base}/detect?max_detections=3&masks=both"))
        .header(CONTENT_TYPE, "image/png")
        .body(png)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    let body = r.bytes().await.unwrap();
    check_schema(&spec, "/detect", "post", 200, "application/json", &body);
    let served: Value = serde_json::from_slice(&body).unwrap();
    let opts = DetectOptions {
        max_detections: Some(3),
        masks: MaskMode::Both,
        ..DetectOptions::default()
    };
    let want = detect_image(&img, &[&paired], &opts).unwrap();
    let own = detect_image(&img, &[&paired.clone().without_segmenter()], &opts).unwrap();
    assert!(
        want.detections
            .iter()
            .zip(&own.detections)
            .any(|(a, b)| a.mask != b.mask),
        "the segmenter changes some mask"
    );
    let dets = served["detections"].as_array().unwrap();
    assert_eq!(dets.len(), 3);
    for (got, want) in dets.iter().zip(&want.detections) {
        assert_eq!(got["score"].as_f64(), Some(want.score));
        assert_eq!(got["mask"], serde_json::to_value(&want.mask).unwrap());
        assert_eq!(
            got["raw_mask"],
            serde_json::to_value(&want.raw_mask).unwrap()
        );
    }
    assert!(state.infer.shutdown(Duration::from_secs(10)).await);
    std::fs::remove_dir_all(&dir).ok();
}
