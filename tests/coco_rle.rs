//! `POST /detect?rle=compressed` answers masks that pycocotools decodes as
//! they are, equal to the uncompressed ones. Needs python3 with numpy and
//! pycocotools (CI installs them from PyPI and runs it with
//! `--include-ignored`).

use std::process::Command;

use reqwest::header::CONTENT_TYPE;
use sdhop::vision::mask::{Mask, Rle};
use serde_json::Value;

mod common;
use common::*;

const DECODE: &str = r#"
import json, sys
import numpy as np
from pycocotools import mask as cocomask
plain, packed = (json.load(open(p)) for p in sys.argv[1:3])
n = 0
for a, b in zip(plain["detections"], packed["detections"]):
    for key in ("mask", "raw_mask"):
        u, c = a[key], b[key]
        assert isinstance(c["counts"], str), c
        mu = cocomask.decode(cocomask.frPyObjects(u, *u["size"]))
        mc = cocomask.decode({"size": c["size"], "counts": c["counts"].encode()})
        assert mu.shape == tuple(u["size"]) and (mu == mc).all(), key
        n += int(mc.sum())
print(n)
"#;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs python3 with numpy and pycocotools"]
async fn compressed_masks_decode_in_pycocotools_as_the_uncompressed_ones() {
    let server = Server::default().await;
    let png = encode(&synthetic_scene(21, 320, 240), image::ImageFormat::Png);
    let c = reqwest::Client::new();
    let get = |q: &'static str| {
        let req = c
            .post(server.url(&format!("/detect?masks=both&threshold=-5{q}")))
            .header(CONTENT_TYPE, "image/png")
            .body(png.clone());
        async move { req.send().await.unwrap().json::<Value>().await.unwrap() }
    };
    let plain = get("").await;
    let packed = get("&rle=compressed").await;
    let dets = plain["detections"].as_array().unwrap();
    assert!(!dets.is_empty(), "no detection to compare");
    // The visible pixels the uncompressed masks hold, as the service's own
    // decoder reads them.
    let mut pixels = 0usize;
    for d in dets {
        for key in ["mask", "raw_mask"] {
            let rle: Rle = serde_json::from_value(d[key].clone()).unwrap();
            pixels += Mask::from_rle(&rle).unwrap().area();
        }
    }
    let dir = std::env::temp_dir().join(format!("sdhop-rle-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (a, b) = (dir.join("plain.json"), dir.join("packed.json"));
    std::fs::write(&a, plain.to_string()).unwrap();
    std::fs::write(&b, packed.to_string()).unwrap();
    let out = Command::new("python3")
        .args(["-c", DECODE])
        .arg(&a)
        .arg(&b)
        .output()
        .expect("python3");
    assert!(
        out.status.success(),
        "pycocotools: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let decoded: usize = String::from_utf8_lossy(&out.stdout).trim().parse().unwrap();
    assert_eq!(decoded, pixels);
    assert!(server.stop().await);
}
