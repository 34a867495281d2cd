//! Times each stage of a pose request on a large mesh.
use std::time::Instant;

use nalgebra::{Rotation3, Vector3};
use sdhop::pose::render::{background, perturb, render};
use sdhop::pose::{refine, EdgeModel, Intrinsics, IrlsParams, Mesh, Pose};
use sdhop::vision::Deadline;

fn main() {
    let segments: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(8);
    let k = Intrinsics {
        fx: 600.0,
        fy: 600.0,
        cx: 320.0,
        cy: 240.0,
    };
    let truth = Pose {
        rotation: Rotation3::from_euler_angles(0.5, 0.6, 0.2).into_inner(),
        translation: Vector3::new(0.01, -0.01, 0.5),
    };
    let mesh = Mesh::cuboid(0.15, 0.1, 0.07).subdivided(segments);
    let ply = mesh.to_ply(false);
    let t = Instant::now();
    let parsed = Mesh::parse(&ply).expect("parse");
    println!(
        "{} bytes, {} triangles: parse {:.0} ms",
        ply.len(),
        parsed.triangles.len(),
        t.elapsed().as_secs_f64() * 1e3
    );
    let bg = background(640, 480, 77).expect("background");
    let t = Instant::now();
    let sc = render(&mesh, &k, &truth, &bg, 0.0, 2.0, 7).expect("render");
    println!("render {:.0} ms", t.elapsed().as_secs_f64() * 1e3);
    let params = IrlsParams::default();
    let t = Instant::now();
    let edges = EdgeModel::new(&parsed, params.crease_degrees);
    println!("edge model {:.0} ms", t.elapsed().as_secs_f64() * 1e3);
    let start = perturb(&truth, 0.01, 5.0, 8);
    let t = Instant::now();
    let depth = edges
        .depth(&k, &start, 640, 480, &Deadline::NONE)
        .expect("depth");
    println!("depth {:.0} ms", t.elapsed().as_secs_f64() * 1e3);
    let t = Instant::now();
    let s = edges
        .samples(&k, &start, &depth, 3.0, &Deadline::NONE)
        .expect("samples");
    println!(
        "{} samples {:.0} ms",
        s.len(),
        t.elapsed().as_secs_f64() * 1e3
    );
    let t = Instant::now();
    let r = refine(&sc.image, &edges, &k, &start, None, &params).expect("refine");
    let (a, d) = r.pose.distance(&truth);
    println!(
        "refine {:.0} ms, {} iterations, {:.2} deg {:.2} mm",
        t.elapsed().as_secs_f64() * 1e3,
        r.iterations,
        a.to_degrees(),
        d * 1e3
    );
}
