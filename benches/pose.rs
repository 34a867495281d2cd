//! Time of one pose refinement (IRLS and OR-IRLS) on rendered 640x480
//! scenes of a 15 cm box at 50 cm, from a start 5 degrees and 1 cm off, and
//! the resulting errors (for the cylinder, of its axis: its roll is
//! unobservable).
//!
//! `cargo bench --bench pose` (`-- --iters N`).

use std::time::Instant;

use nalgebra::{Rotation3, Vector3};
use sdhop::pose::render::{background, perturb, render};
use sdhop::pose::{refine, EdgeModel, Intrinsics, IrlsParams, Mesh, Pose};

mod common;
use common::{arg, median};

fn main() {
    let iters = arg("--iters", 10u64);
    let k = Intrinsics {
        fx: 600.0,
        fy: 600.0,
        cx: 320.0,
        cy: 240.0,
    };
    let params = IrlsParams::default();
    for (name, mesh) in [
        ("box", Mesh::cuboid(0.15, 0.1, 0.07)),
        ("cylinder", Mesh::cylinder(0.04, 0.15, 48)),
    ] {
        for (label, occlude) in [("unoccluded", 0.0), ("occluded 45%", 0.45)] {
            let mut times = Vec::new();
            let mut iterations = Vec::new();
            let mut errs = Vec::new();
            for seed in 0..iters {
                let pose = Pose {
                    rotation: Rotation3::from_euler_angles(0.5, 0.6, 0.1 * seed as f64)
                        .into_inner(),
                    translation: Vector3::new(0.0, 0.0, 0.5),
                };
                let bg = background(640, 480, seed).expect("background");
                let scene = render(&mesh, &k, &pose, &bg, occlude, 4.0, seed).expect("scene");
                let start = perturb(&pose, 0.01, 5.0, 1000 + seed);
                let mask = (occlude > 0.0).then_some(&scene.visible);
                let t = Instant::now();
                // The edge model is built per request, as a service would.
                let edges = EdgeModel::new(&mesh, params.crease_degrees);
                let r = refine(&scene.image, &edges, &k, &start, mask, &params);
                times.push(t.elapsed().as_secs_f64() * 1e3);
                if let Ok(r) = r {
                    iterations.push(r.iterations as f64);
                    let (a, d) = r.pose.distance(&pose);
                    // A cylinder's roll about its axis is unobservable: its
                    // rotation error is that of the axis.
                    let a = if name == "cylinder" {
                        (r.pose.rotation * Vector3::z()).angle(&(pose.rotation * Vector3::z()))
                    } else {
                        a
                    };
                    errs.push((a.to_degrees(), d * 1e3));
                }
            }
            let mut deg: Vec<f64> = errs.iter().map(|e| e.0).collect();
            let mut mm: Vec<f64> = errs.iter().map(|e| e.1).collect();
            println!(
                "{name:<9} {label:<13} {}: median {:.1} ms per request ({:.0} iterations), median error {:.2} deg {:.2} mm, {} of {iters} returned",
                if occlude > 0.0 { "OR-IRLS (exact mask)" } else { "IRLS" },
                median(&mut times),
                median(&mut iterations),
                median(&mut deg),
                median(&mut mm),
                errs.len()
            );
        }
    }
}
