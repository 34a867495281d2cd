//! Hostile meshes through `POST /pose`: counts their bytes cannot hold,
//! counts above the limits, elements without properties, long lists,
//! invisible characters, faces without surface.

use super::*;

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

/// The spin mesh of issue 42: an element of 2^64-1 items without
/// properties, which the reader stepped over until the deadline.
const SPIN_PLY: &[u8] = b"ply\nformat ascii 1.0\nelement junk 18446744073709551615\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n10 0 0\n0 10 0\n3 0 1 2\n";

/// A binary PLY of 3 vertices and one face of `n` `uchar` indices.
fn long_face(n: u32) -> Vec<u8> {
    let mut f = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uint uchar vertex_indices\nend_header\n".to_vec();
    for v in [[0.0f32, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]] {
        for c in v {
            f.extend(c.to_le_bytes());
        }
    }
    f.extend(n.to_le_bytes());
    f.extend((0..n).map(|i| (i % 3) as u8));
    f
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn meshes_cost_what_their_bytes_allow_whatever_they_declare() {
    // The real binary, so that its memory is its own.
    let (mut child, base) = spawn_binary(&[]);
    wait_ready(&base).await;
    let (png, _, truth) = box_scene();
    let p = params(600.0, truth.rotation_rows(), [0.0, 0.0, 0.5]);
    // The spin mesh: refused at once, naming the element (it answered 503
    // at its 3 s deadline after 2.9 CPU-seconds).
    let (status, body, took) = pose_at(&base, &png, SPIN_PLY, p.clone(), "?timeout_ms=3000").await;
    assert_eq!(status, 422, "{body}");
    let msg = body["error"].as_str().unwrap();
    assert!(
        msg.contains("element junk") && msg.contains("no properties"),
        "{msg}"
    );
    assert!(took < Duration::from_millis(500), "{took:?}");
    // One face of 60 M indices (60 MB, under the body limit): refused
    // from its count against the triangle limit before an index is kept
    // (it took 436-555 MB above idle).
    let face = long_face(60_000_000);
    let ((status, body, took), peak) = peak_rss_mb(
        child.id(),
        pose_at(&base, &png, &face, p.clone(), "?timeout_ms=20000"),
    )
    .await;
    drop(face);
    assert_eq!(status, 413, "{body}");
    eprintln!("60 M-index face: {took:?}, peak {peak:.0} MB above before");
    assert!(peak < 200.0, "peak {peak:.0} MB");
    // The ASCII form: refused from the bytes left before the indices.
    let mut ascii = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uint uchar vertex_indices\nend_header\n0 0 0\n0.1 0 0\n0 0.1 0\n60000000".to_vec();
    ascii.extend(b" 0 1 2".repeat(1_000_000));
    let (status, body, _) = pose_at(&base, &png, &ascii, p, "?timeout_ms=20000").await;
    assert_eq!(status, 422, "{body}");
    assert!(
        body["error"]
            .as_str()
            .unwrap()
            .contains("a list of 60000000"),
        "{body}"
    );
    let _ = child.kill();
    let _ = child.wait();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn equivalent_meshes_give_the_same_pose_and_invisible_characters_are_named() {
    let server = Server::default().await;
    let (png, mesh, truth) = box_scene();
    // A start a little off the truth.
    let p = params(600.0, truth.rotation_rows(), [0.012, -0.006, 0.51]);
    let obj = mesh.to_obj();
    let (status, clean, _) = pose(&server, &png, obj.as_bytes(), p.clone(), "").await;
    assert_eq!(status, 200, "{clean}");
    assert_eq!(clean["mesh_faces_dropped"], 0);
    let same = |body: &Value, what: &str| {
        let (a, b) = (&clean["pose"]["translation"], &body["pose"]["translation"]);
        for i in 0..3 {
            let d = (a[i].as_f64().unwrap() - b[i].as_f64().unwrap()).abs();
            assert!(d < 1e-6, "{what}: {a} against {b}");
        }
        assert_eq!(clean["score"], body["score"], "{what}");
    };
    // A byte-order mark before the OBJ (it used to skip the first vertex
    // and shift every index) and before a PLY: read as the clean file.
    let with_bom = |b: &[u8]| [&b"\xEF\xBB\xBF"[..], b].concat();
    for (what, bytes) in [
        ("OBJ with a BOM", with_bom(obj.as_bytes())),
        ("PLY with a BOM", with_bom(&mesh.to_ply(false))),
    ] {
        let (status, body, _) = pose(&server, &png, &bytes, p.clone(), "").await;
        assert_eq!(status, 200, "{what}: {body}");
        same(&body, what);
    }
    // Every face twice (once the other way round) and a face without
    // area: the same pose, the faces left out counted.
    let mut dirty = mesh.clone();
    dirty
        .triangles
        .extend(mesh.triangles.iter().map(|t| [t[2], t[1], t[0]]));
    dirty.triangles.push([0, 0, 1]);
    let (status, body, _) = pose(&server, &png, &dirty.to_ply(true), p.clone(), "").await;
    assert_eq!(status, 200, "{body}");
    same(&body, "faces twice");
    assert_eq!(body["mesh_faces_dropped"], 13, "{body}");
    // A no-break space after `v`: refused naming the line (it was skipped,
    // and with an unused last vertex answered a pose 7.6 mm off).
    let mut lines: Vec<String> = obj.lines().map(str::to_string).collect();
    lines.insert(0, "v 9 9 9".into());
    lines[0] = "v\u{a0}9 9 9".into();
    let nbsp = lines.join("\n");
    let (status, body, _) = pose(&server, &png, nbsp.as_bytes(), p.clone(), "").await;
    assert_eq!(status, 422, "{body}");
    let msg = body["error"].as_str().unwrap();
    assert!(
        msg.contains("OBJ line 1") && msg.contains("not an OBJ keyword"),
        "{msg}"
    );
    // Data after the declared elements: a face count short of the faces.
    let ply = String::from_utf8(mesh.to_ply(false)).unwrap();
    let short = ply.replace("element face 12", "element face 10");
    let (status, body, _) = pose(&server, &png, short.as_bytes(), p, "").await;
    assert_eq!(status, 422, "{body}");
    assert!(
        body["error"]
            .as_str()
            .unwrap()
            .contains("follow the last declared element"),
        "{body}"
    );
    assert!(server.stop().await);
}
