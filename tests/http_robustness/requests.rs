//! Requests the service must refuse cheaply and clearly, masks read from
//! their stored values, label maps, `Accept`, and the flags' help.

use super::*;

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
    // Parameters out of range are named, never dumped as a Rust struct.
    let with = |f: &dyn Fn(&mut Value)| {
        let mut q = p.clone();
        f(&mut q);
        q
    };
    for (bad, says) in [
        (
            with(&|q| q["start_uncertainty"] = json!({"degrees": -1})),
            "start_uncertainty.degrees",
        ),
        (with(&|q| q["max_iterations"] = json!(0)), "max_iterations"),
        (
            with(&|q| q["max_iterations"] = json!(1_000_000_000u64)),
            "max_iterations",
        ),
        (with(&|q| q["intrinsics"]["fx"] = json!(0)), "intrinsics.fx"),
    ] {
        let cube = Mesh::cuboid(0.15, 0.1, 0.07).to_obj().into_bytes();
        let (status, body, _) = pose(&server, &png, &cube, bad, "").await;
        assert_eq!(status, 422, "{says}: {body}");
        let msg = body["error"].as_str().unwrap();
        assert!(msg.contains(says), "{says}: {msg}");
        assert!(
            !msg.contains("Params {") && !msg.contains("Intrinsics {"),
            "{msg}"
        );
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
    // Accept as HTTP reads it: the most specific range's weight, the
    // higher weight wins (JSON on a tie), a malformed weight leaves its
    // range out, and 406 where neither answer is acceptable or format=
    // asks for one that Accept refuses.
    for (query, accept, want) in [
        ("", "image/png;q=0.5, application/json", Some(false)),
        ("", "image/png", Some(true)),
        ("", "application/json;q=0.1, image/png", Some(true)),
        ("", "image/*", Some(true)),
        ("", "application/json;q=0.9, image/*;q=1", Some(true)),
        ("", "image/png;q=abc", Some(false)),
        ("", "image/png;q=0, application/json;q=0", None),
        ("", "image/png;q=0", None),
        ("?format=png", "image/png;q=0, */*", None),
        (
            "?format=png",
            "image/png;q=0.2, application/json",
            Some(true),
        ),
    ] {
        let r = detect(query, Some(accept)).await.unwrap();
        let status = r.status();
        let ctype = r.headers()[CONTENT_TYPE].to_str().unwrap().to_string();
        match want {
            Some(png) => {
                assert_eq!(status, StatusCode::OK, "{query} {accept}");
                assert_eq!(ctype == "image/png", png, "{query} {accept}: {ctype}");
            }
            None => {
                assert_eq!(status, StatusCode::NOT_ACCEPTABLE, "{query} {accept}");
                let body: Value = r.json().await.unwrap();
                assert_eq!(body["kind"], "not_acceptable", "{body}");
            }
        }
    }
    // A label map is drawn from one mask per detection and carries no
    // masks in its detections: options it cannot honour are refused.
    for q in [
        "?format=png&masks=none",
        "?format=png&masks=both",
        "?format=png&rle=compressed",
    ] {
        let r = detect(q, None).await.unwrap();
        assert_eq!(r.status(), StatusCode::UNPROCESSABLE_ENTITY, "{q}");
    }
    let r = detect("?format=png&masks=raw", None).await.unwrap();
    assert_eq!(r.status(), StatusCode::OK);
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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_head_is_answered_4xx_however_short_the_deadline() {
    // A malformed query's deadline is the default one, and its stalled
    // body is cut once the grace has passed.
    let server = Server::start(
        InferConfig::default(),
        HttpConfig {
            body_grace: Duration::from_millis(300),
            ..HttpConfig::default()
        },
    )
    .await;
    let addr = server.base.trim_start_matches("http://").to_string();
    // A malformed query with a body that has not arrived in time: the
    // query's 400, not the time-out's 408 (a fuzzer's invalid request
    // must be told it is invalid).
    let mut s = stalled(
        &addr,
        "/detect?timeout_ms=50&masks=bogus",
        "image/png",
        1000,
    );
    let line = tokio::task::spawn_blocking(move || status_line(&mut s, Duration::from_secs(3)))
        .await
        .unwrap();
    assert!(line.starts_with("HTTP/1.1 400"), "{line}");
    // A media type /detect does not take, likewise: 415.
    let mut s = stalled(&addr, "/detect?timeout_ms=50", "text/plain", 1000);
    let line = tokio::task::spawn_blocking(move || status_line(&mut s, Duration::from_secs(3)))
        .await
        .unwrap();
    assert!(line.starts_with("HTTP/1.1 415"), "{line}");
    // A good head: the time-out.
    let mut s = stalled(&addr, "/detect?timeout_ms=50", "image/png", 1000);
    let line = tokio::task::spawn_blocking(move || status_line(&mut s, Duration::from_secs(3)))
        .await
        .unwrap();
    assert!(line.starts_with("HTTP/1.1 408"), "{line}");
    // /pose takes no deadline under 100 ms (no pose is refined faster):
    // 400 naming the range, whatever the body.
    let (png, mesh, truth) = box_scene();
    let p = params(600.0, truth.rotation_rows(), [0.0, 0.0, 0.5]);
    let (status, body, _) = pose(&server, &png, &mesh.to_ply(true), p, "?timeout_ms=1").await;
    assert_eq!(status, 400, "{body}");
    assert!(body["error"].as_str().unwrap().contains("100..="), "{body}");
    assert!(server.stop().await);
}

#[test]
fn the_spec_refuses_an_empty_model_name_as_the_server_does() {
    // `model=a,,b` is answered 400 ("empty model name"); the schema of
    // the parameter's items refuses it too, so that a client (or a
    // fuzzer) checking against openapi.yaml knows it is invalid.
    let spec: Value =
        serde_norway::from_str(&std::fs::read_to_string("openapi.yaml").unwrap()).unwrap();
    let model = spec["paths"]["/detect"]["post"]["parameters"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == "model")
        .unwrap();
    let items = jsonschema::validator_for(&model["schema"]["items"]).unwrap();
    // The server's parser agrees name by name, spaces beyond ASCII
    // included: a fuzzer found `\u{85}` valid by the pattern's (ECMA)
    // `\s` and trimmed to nothing by the server.
    let parses = |v: &str| {
        let encoded: String = v.bytes().map(|b| format!("%{b:02X}")).collect();
        let raw = format!("model={encoded}");
        sdhop::http::detect::DetectQuery::parse(Some(&raw), 100, Duration::from_secs(60)).is_ok()
    };
    for (name, valid) in [
        ("a", true),
        ("a,b", true),
        (" a , b ", true),
        ("\ta\r\n", true),
        ("\u{85}", true),
        ("\u{a0}", true),
        ("\u{3000}", true),
        ("\u{feff}", true),
        ("\u{b}", true),
        ("a,\u{85}", true),
        ("a,,b", false),
        ("a, ,b", false),
        ("a,\t\n\u{c}\r ,b", false),
        (",a", false),
        ("", false),
    ] {
        assert_eq!(items.is_valid(&json!(name)), valid, "schema: {name:?}");
        assert_eq!(parses(name), valid, "server: {name:?}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_body_of_many_parts_is_not_parsed_whole() {
    // A fuzzer's own idea: a million empty parts took 0.8 s of the
    // runtime's thread to parse, past a 300 ms deadline. Now /pose stops
    // at the first unknown part and /detect after 16 parts before its
    // image.
    let server = Server::default().await;
    let boundary = "xyz";
    let part = format!("--{boundary}\r\nContent-Disposition: form-data; name=\"x\"\r\n\r\n\r\n");
    let body = format!("{}--{boundary}--\r\n", part.repeat(200_000));
    let c = reqwest::Client::new();
    for (path, says) in [
        ("/pose?timeout_ms=300", "unknown part"),
        ("/detect?timeout_ms=300", "more than 16 parts"),
    ] {
        let r = c
            .post(server.url(path))
            .header(
                CONTENT_TYPE,
                format!("multipart/form-data; boundary={boundary}"),
            )
            .body(body.clone())
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::BAD_REQUEST, "{path}");
        let msg: Value = r.json().await.unwrap();
        assert!(msg["error"].as_str().unwrap().contains(says), "{msg}");
    }
    // A few parts before the image are still fine.
    let img = encode(&synthetic_scene(3, 320, 240), image::ImageFormat::Png);
    let form = (0..3).fold(reqwest::multipart::Form::new(), |f, i| {
        f.text(format!("note{i}"), "x")
    });
    let form = form.part(
        "image",
        reqwest::multipart::Part::bytes(img).file_name("a.png"),
    );
    let r = c
        .post(server.url("/detect"))
        .multipart(form)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    assert!(server.stop().await);
}
