//! Synthetic pose scenes with exact ground truth: a mesh rendered with flat
//! Lambert shading at a known pose over a background, optionally hidden in
//! part by a random occluder, with the exact visible mask.

use nalgebra::{Rotation3, Vector3};

use super::edges::rasterize;
use super::geometry::{Intrinsics, Pose};
use super::mesh::Mesh;
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;
use crate::vision::rng::SplitMix64;
use crate::vision::{Deadline, VisionError};

/// A rendered scene.
pub struct PoseScene {
    pub image: ColorImage,
    pub pose: Pose,
    /// Object pixels not hidden by the occluder.
    pub visible: Mask,
    /// Fraction of the object's pixels that the occluder hides.
    pub occluded_fraction: f64,
}

/// Renders `mesh` at `pose` over `background` (the image's size), shading
/// each face by its orientation to a light; with `occlude`, a textured
/// occluder covering about that fraction of the object (its strip enters
/// from a random side); then noise of standard deviation `noise`.
pub fn render(
    mesh: &Mesh,
    k: &Intrinsics,
    pose: &Pose,
    background: &ColorImage,
    occlude: f64,
    noise: f64,
    seed: u64,
) -> Result<PoseScene, VisionError> {
    let (w, h) = (background.width(), background.height());
    let raster = rasterize(
        &mesh.vertices,
        &mesh.triangles,
        k,
        pose,
        w,
        h,
        false,
        &Deadline::NONE,
    )
    .map_err(|_| VisionError::DeadlineExceeded)?;
    let light = Vector3::new(-0.4, -0.5, -0.77).normalize();
    let corners = corner_normals(mesh, SMOOTH_DEGREES);
    let cam: Vec<Vector3<f64>> = mesh.vertices.iter().map(|v| pose.transform(v)).collect();
    // Lambert shading of the normal interpolated over the triangle (Phong
    // normals): smooth across the facets of a rounded surface, a step at
    // a crease.
    let shade = |f: usize, x: usize, y: usize| -> f32 {
        let w = pixel_weights(k, &cam, mesh.triangles[f], x, y);
        let n = corners[f][0] * w[0] + corners[f][1] * w[1] + corners[f][2] * w[2];
        let n = pose.rotation * n.try_normalize(1e-12).unwrap_or_else(Vector3::z);
        (40.0 + 200.0 * n.dot(&light).abs()) as f32
    };
    let mut rng = SplitMix64::new(seed);
    let mut data = background.data().to_vec();
    let mut object = Mask::new(w, h);
    for i in 0..w * h {
        if let Some(f) = raster.face_at(i % w, i / w) {
            object.set(i % w, i / w, true);
            let s = shade(f as usize, i % w, i / w);
            data[i * 3] = s;
            data[i * 3 + 1] = s * 0.9;
            data[i * 3 + 2] = s * 0.8;
        }
    }
    let area = object.area();
    let mut visible = object.clone();
    if occlude > 0.0 && area > 0 {
        // The object's pixel box; a strip from one side covering `occlude`
        // of the box's extent, filled with a random colour and stripes.
        let (x0, y0, x1, y1) = object.tight_box().unwrap_or((0, 0, w, h));
        let side = rng.range_usize(0, 4);
        let base = [
            rng.range_f64(20.0, 235.0) as f32,
            rng.range_f64(20.0, 235.0) as f32,
            rng.range_f64(20.0, 235.0) as f32,
        ];
        let period = rng.range_usize(6, 20);
        let (bw, bh) = ((x1 - x0) as f64, (y1 - y0) as f64);
        let cover = |x: usize, y: usize| -> bool {
            let (fx, fy) = ((x as f64 - x0 as f64) / bw, (y as f64 - y0 as f64) / bh);
            match side {
                0 => fx < occlude,
                1 => fx > 1.0 - occlude,
                2 => fy < occlude,
                _ => fy > 1.0 - occlude,
            }
        };
        // Extend the occluder past the object's box by a margin.
        let m = 10usize;
        for y in y0.saturating_sub(m)..(y1 + m).min(h) {
            for x in x0.saturating_sub(m)..(x1 + m).min(w) {
                let (cx, cy) = (x.clamp(x0, x1 - 1), y.clamp(y0, y1 - 1));
                if cover(cx, cy) {
                    let stripe = if (x + y) / period % 2 == 0 { 1.0 } else { 0.6 };
                    let i = (y * w + x) * 3;
                    for c in 0..3 {
                        data[i + c] = base[c] * stripe;
                    }
                    visible.set(x, y, false);
                }
            }
        }
    }
    if noise > 0.0 {
        for v in data.iter_mut() {
            // Sum of uniforms: close to Gaussian.
            let n: f64 = (0..4).map(|_| rng.next_f64() - 0.5).sum::<f64>() * (3.0f64).sqrt();
            *v = (*v + (n * noise) as f32).clamp(0.0, 255.0);
        }
    }
    let occluded_fraction = if area == 0 {
        0.0
    } else {
        1.0 - visible.area() as f64 / area as f64
    };
    Ok(PoseScene {
        image: ColorImage::new(w, h, data)?,
        pose: *pose,
        visible,
        occluded_fraction,
    })
}

/// The (screen-space) barycentric weights of pixel `(x, y)`'s centre in
/// triangle `t` of the camera-frame vertices `cam`, clamped to the
/// triangle.
fn pixel_weights(
    k: &Intrinsics,
    cam: &[Vector3<f64>],
    t: [u32; 3],
    x: usize,
    y: usize,
) -> [f64; 3] {
    let s = t.map(|i| k.project(&cam[i as usize]).unwrap_or_default());
    let c = nalgebra::Vector2::new(x as f64 + 0.5, y as f64 + 0.5);
    let area = (s[1] - s[0]).perp(&(s[2] - s[0]));
    let (w0, w1) = if area.abs() < 1e-12 {
        (1.0 / 3.0, 1.0 / 3.0)
    } else {
        (
            (s[1] - c).perp(&(s[2] - c)) / area,
            (s[2] - c).perp(&(s[0] - c)) / area,
        )
    };
    [w0, w1, 1.0 - w0 - w1].map(|v| v.clamp(0.0, 1.0))
}

/// Lighting of a coloured render: Lambert's law with a directional light
/// plus an ambient share, times a per-channel gain.
#[derive(Clone, Copy, Debug)]
pub struct Lighting {
    /// Direction the light travels, in the camera frame (`+z`: from the
    /// camera into the scene).
    pub light: Vector3<f64>,
    pub ambient: f64,
    pub gain: [f64; 3],
}

/// A mesh rendered with its vertex colours (grey without), shaded by
/// `lighting` with smooth normals: the colour of every pixel the object
/// covers (row-major, zero elsewhere) and its silhouette.
pub fn render_colours(
    mesh: &Mesh,
    colours: Option<&[[f32; 3]]>,
    k: &Intrinsics,
    pose: &Pose,
    width: usize,
    height: usize,
    lighting: &Lighting,
) -> Result<(Vec<[f32; 3]>, Mask), VisionError> {
    let raster = rasterize(
        &mesh.vertices,
        &mesh.triangles,
        k,
        pose,
        width,
        height,
        false,
        &Deadline::NONE,
    )
    .map_err(|_| VisionError::DeadlineExceeded)?;
    let corners = corner_normals(mesh, SMOOTH_DEGREES);
    let cam: Vec<Vector3<f64>> = mesh.vertices.iter().map(|v| pose.transform(v)).collect();
    let light = lighting
        .light
        .try_normalize(1e-12)
        .unwrap_or_else(Vector3::z);
    let mut out = vec![[0.0f32; 3]; width * height];
    let mut mask = Mask::new(width, height);
    for y in 0..height {
        for x in 0..width {
            let Some(f) = raster.face_at(x, y) else {
                continue;
            };
            let f = f as usize;
            let t = mesh.triangles[f];
            let w = pixel_weights(k, &cam, t, x, y);
            let n = corners[f][0] * w[0] + corners[f][1] * w[1] + corners[f][2] * w[2];
            let n = pose.rotation * n.try_normalize(1e-12).unwrap_or_else(Vector3::z);
            // Light on the side facing the camera (normals of thin or
            // badly oriented meshes may point away).
            let n = if n.z > 0.0 { -n } else { n };
            let lit = lighting.ambient + (1.0 - lighting.ambient) * n.dot(&-light).max(0.0);
            let base = match colours {
                Some(c) => {
                    let mut v = [0.0f64; 3];
                    for (j, &vi) in t.iter().enumerate() {
                        let cv = c.get(vi as usize).copied().unwrap_or([180.0; 3]);
                        for ch in 0..3 {
                            v[ch] += w[j] * f64::from(cv[ch]);
                        }
                    }
                    v
                }
                None => [180.0; 3],
            };
            out[y * width + x] = std::array::from_fn(|ch| {
                (base[ch] * lit * lighting.gain[ch]).clamp(0.0, 255.0) as f32
            });
            mask.set(x, y, true);
        }
    }
    Ok((out, mask))
}

/// Faces meeting at less than this (degrees) are shaded as one smooth
/// surface.
const SMOOTH_DEGREES: f64 = 30.0;

/// Each triangle's normals at its corners: the mean of the normals of the
/// triangles around the corner that turn by less than `degrees` from it.
fn corner_normals(mesh: &Mesh, degrees: f64) -> Vec<[Vector3<f64>; 3]> {
    let normals = mesh.face_normals();
    let mut around: Vec<Vec<u32>> = vec![Vec::new(); mesh.vertices.len()];
    for (f, t) in mesh.triangles.iter().enumerate() {
        for &v in t {
            around[v as usize].push(f as u32);
        }
    }
    let cos = degrees.to_radians().cos();
    mesh.triangles
        .iter()
        .enumerate()
        .map(|(f, t)| {
            t.map(|v| {
                let sum: Vector3<f64> = around[v as usize]
                    .iter()
                    .map(|&g| normals[g as usize])
                    .filter(|n| n.dot(&normals[f]) >= cos)
                    .sum();
                sum.try_normalize(1e-300).unwrap_or(normals[f])
            })
        })
        .collect()
}

/// A textured background: smooth gradients and blocks (no strong edges
/// inside blocks), deterministic from `seed`.
pub fn background(width: usize, height: usize, seed: u64) -> Result<ColorImage, VisionError> {
    let mut rng = SplitMix64::new(seed);
    let block = 40usize;
    let cols = width.div_ceil(block);
    let rows = height.div_ceil(block);
    let tones: Vec<f32> = (0..cols * rows)
        .map(|_| rng.range_f64(60.0, 160.0) as f32)
        .collect();
    let mut data = Vec::with_capacity(width * height * 3);
    for y in 0..height {
        for x in 0..width {
            let t = tones[(y / block) * cols + x / block];
            data.extend_from_slice(&[t, t * 1.05, t * 0.95]);
        }
    }
    ColorImage::new(width, height, data)
}

/// `pose` moved by about `trans` (units of the mesh) and `degrees`, in
/// random directions.
pub fn perturb(pose: &Pose, trans: f64, degrees: f64, seed: u64) -> Pose {
    let mut rng = SplitMix64::new(seed);
    let mut unit = || {
        let v = Vector3::new(
            rng.range_f64(-1.0, 1.0),
            rng.range_f64(-1.0, 1.0),
            rng.range_f64(-1.0, 1.0),
        );
        v.try_normalize(1e-9).unwrap_or_else(Vector3::x)
    };
    let axis = unit();
    let dir = unit();
    let r = Rotation3::new(axis * degrees.to_radians()).into_inner();
    Pose {
        rotation: r * pose.rotation,
        translation: pose.translation + dir * trans,
    }
}
