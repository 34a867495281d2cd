//! Start poses from a detection, for a pose request without an initial
//! pose: each of the detected component's representative rotations
//! (learned from the mesh's training renders, see
//! [`crate::model::ViewMeta::rotations`]) placed so that the mesh's
//! projected box matches the detection's full-extent box, then ranked by
//! the image's colours about the detection ([`start_poses_by_colour`]),
//! or where those tell nothing apart by how well the silhouette at that
//! pose agrees with the detection's visible mask ([`start_poses`]).

use nalgebra::{Matrix3, Quaternion, UnitQuaternion, Vector3};

use super::edges::rasterize;
use super::geometry::{projected_box, Intrinsics, Pose};
use super::mesh::Mesh;
use super::region::ColourModel;
use super::PoseError;
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;
use crate::vision::Deadline;

/// A rotation from a unit quaternion `[w, x, y, z]` (normalised here).
pub fn rotation_from_quaternion(q: &[f64; 4]) -> Option<Matrix3<f64>> {
    let q = Quaternion::new(q[0], q[1], q[2], q[3]);
    (q.norm() > 1e-9 && q.coords.iter().all(|v| v.is_finite())).then(|| {
        UnitQuaternion::from_quaternion(q)
            .to_rotation_matrix()
            .into_inner()
    })
}

/// The pose with `rotation` that projects the mesh's vertices to a box of
/// the size of `bbox` `(x, y, w, h)` and centred on it: the depth from the
/// box's area (the projected size goes as one over the depth), the
/// lateral position from its centre, refined by a few fixed-point steps.
/// `None` when the mesh does not project.
pub fn pose_for_box(
    vertices: &[Vector3<f64>],
    k: &Intrinsics,
    rotation: &Matrix3<f64>,
    bbox: (f64, f64, f64, f64),
) -> Option<Pose> {
    let (bx, by, bw, bh) = bbox;
    if !(bw > 0.0 && bh > 0.0) || vertices.is_empty() {
        return None;
    }
    let (lo, hi) = vertices.iter().fold(
        (Vector3::repeat(f64::MAX), Vector3::repeat(f64::MIN)),
        |(lo, hi), v| (lo.inf(v), hi.sup(v)),
    );
    let centre = (lo + hi) / 2.0;
    let diagonal = (hi - lo).norm().max(1e-12);
    let (u, v) = (bx + bw / 2.0, by + bh / 2.0);
    // A first depth: the diagonal seen at the box's longer side.
    let mut z = k.fx.max(k.fy) * diagonal / bw.max(bh);
    let mut target = Vector3::new((u - k.cx) / k.fx, (v - k.cy) / k.fy, 1.0);
    let mut pose = Pose {
        rotation: *rotation,
        translation: target * z - rotation * centre,
    };
    for _ in 0..4 {
        let (px, py, pw, ph) = projected_box(vertices, k, &pose)?;
        if !(pw > 0.0 && ph > 0.0) {
            return None;
        }
        z *= ((pw * ph) / (bw * bh)).sqrt();
        // Move the projected centre onto the box's centre.
        let (du, dv) = (u - (px + pw / 2.0), v - (py + ph / 2.0));
        target.x += du / k.fx;
        target.y += dv / k.fy;
        pose.translation = target * z - rotation * centre;
    }
    (pose.translation.iter().all(|v| v.is_finite()) && pose.translation.z > 0.0).then_some(pose)
}

/// The intersection over union of the mesh's silhouette at `pose` with
/// `mask` (0 when both are empty).
pub fn silhouette_iou(
    mesh: &Mesh,
    k: &Intrinsics,
    pose: &Pose,
    mask: &Mask,
    deadline: &Deadline,
) -> Result<f64, PoseError> {
    let raster = rasterize(
        &mesh.vertices,
        &mesh.triangles,
        k,
        pose,
        mask.width,
        mask.height,
        false,
        deadline,
    )?;
    let (mut inter, mut union) = (0usize, 0usize);
    for y in 0..mask.height {
        for x in 0..mask.width {
            let s = raster.covered(x, y);
            let m = mask.get(x, y);
            inter += usize::from(s && m);
            union += usize::from(s || m);
        }
    }
    Ok(if union == 0 {
        0.0
    } else {
        inter as f64 / union as f64
    })
}

/// The centre of the mesh's bounding box.
fn mesh_centre(mesh: &Mesh) -> Vector3<f64> {
    let (lo, hi) = mesh.vertices.iter().fold(
        (Vector3::repeat(f64::MAX), Vector3::repeat(f64::MIN)),
        |(lo, hi), v| (lo.inf(v), hi.sup(v)),
    );
    (lo + hi) / 2.0
}

/// A start pose and its agreement with the detection: the IoU of its
/// silhouette with the detection's mask, or without a mask the IoU of its
/// projected box with the detection's box.
#[derive(Clone, Copy, Debug)]
pub struct Start {
    pub pose: Pose,
    pub agreement: f64,
}

/// Depths tried about the one of the box's size, as factors: a
/// detection's box is a template's, whose aspect is the component's and
/// whose size is a pyramid level's, so the depth it gives is off by up to
/// a level or two (about 15% each).
pub const DEPTH_FACTORS: [f64; 7] = [0.7, 0.8, 0.9, 1.0, 1.1, 1.25, 1.4];

/// Each rotation of `rotations` (unit quaternions) placed on the
/// full-extent box `bbox` by [`pose_for_box`], those that place at all;
/// gives up once `deadline` has passed.
fn placed_on_box(
    mesh: &Mesh,
    k: &Intrinsics,
    rotations: &[[f64; 4]],
    bbox: (f64, f64, f64, f64),
    deadline: &Deadline,
) -> Result<Vec<(Matrix3<f64>, Pose)>, PoseError> {
    let mut out = Vec::with_capacity(rotations.len());
    for q in rotations {
        if deadline.passed() {
            return Err(PoseError::DeadlineExceeded);
        }
        let Some(r) = rotation_from_quaternion(q) else {
            continue;
        };
        if let Some(pose) = pose_for_box(&mesh.vertices, k, &r, bbox) {
            out.push((r, pose));
        }
    }
    Ok(out)
}

/// The start poses of a detection with full-extent box `bbox` and visible
/// mask `mask`: every rotation of `rotations` placed on the box by
/// [`pose_for_box`] at the best of the [`DEPTH_FACTORS`] (along the ray
/// through the box's centre), ranked by their agreement with the
/// detection (see [`Start`]; best first), at most `keep`, no two with the
/// same rotation.
pub fn start_poses(
    mesh: &Mesh,
    k: &Intrinsics,
    bbox: (f64, f64, f64, f64),
    mask: Option<&Mask>,
    rotations: &[[f64; 4]],
    keep: usize,
    deadline: &Deadline,
) -> Result<Vec<Start>, PoseError> {
    let mut out = Vec::with_capacity(rotations.len());
    for (r, pose) in placed_on_box(mesh, k, rotations, bbox, deadline)? {
        // The object's centre moves along its ray with the depth; each
        // depth is scored by the silhouette's IoU with the mask, or
        // without a mask by the IoU of its box with the detection's
        // full-extent box. (The sum of both, tried on the synthetic mesh
        // test, put 5 of 20 poses within 10% as the mask alone does, with a
        // worse median: 31 against 21 mm.)
        let mut best: Option<Start> = None;
        let centre_cam = pose.translation + r * mesh_centre(mesh);
        for f in DEPTH_FACTORS {
            let p = Pose {
                rotation: r,
                translation: centre_cam * f - r * mesh_centre(mesh),
            };
            let score = match mask {
                Some(m) => silhouette_iou(mesh, k, &p, m, deadline)?,
                None => projected_box(&mesh.vertices, k, &p)
                    .map_or(0.0, |pb| crate::vision::detect::box_iou(pb, bbox)),
            };
            if best.is_none_or(|b| score > b.agreement) {
                best = Some(Start {
                    pose: p,
                    agreement: score,
                });
            }
        }
        out.extend(best);
    }
    out.sort_by(|a, b| b.agreement.total_cmp(&a.agreement));
    out.truncate(keep);
    Ok(out)
}

/// Shifts of a start about its place on the detection's box, each way, as
/// shares of the box's longer side: a detection's box is a template's,
/// off by a cell or two.
pub const SHIFTS: [f64; 5] = [-0.1, -0.05, 0.0, 0.05, 0.1];

/// How far the window of [`start_poses_by_colour`] reaches past the
/// detection's box, as a share of the box's longer side.
const COLOUR_MARGIN: f64 = 0.5;

/// The least difference of the mean log-odds of showing the object
/// between the mask's pixels and those around the box for
/// [`start_poses_by_colour`] to rank by colour.
const MIN_COLOUR_CONTRAST: f64 = 0.5;

/// The detection's box grown by `margin` of its longer side each way and
/// clipped to a `width` x `height` image: `(x0, y0, x1, y1)`, exclusive.
fn grown_box(
    bbox: (f64, f64, f64, f64),
    margin: f64,
    width: usize,
    height: usize,
) -> (usize, usize, usize, usize) {
    let (bx, by, bw, bh) = bbox;
    let g = margin * bw.max(bh);
    let clip = |v: f64, hi: usize| (v.max(0.0) as usize).min(hi);
    (
        clip((bx - g).floor(), width),
        clip((by - g).floor(), height),
        clip((bx + bw + g).ceil(), width),
        clip((by + bh + g).ceil(), height),
    )
}

/// The start poses of a detection ranked by its colours, as the
/// region-based trackers score a pose (PWP3D, RBOT): the object's colours
/// are those of the detection's visible `mask` inside its box, the
/// background's those around the box, and a pose scores the sum over its
/// silhouette of each pixel's log-odds of showing the object (so a
/// silhouette gains where it covers the object's colours and loses where
/// it covers the background's). Every rotation of `rotations` is placed
/// on the box by [`pose_for_box`], then moved along its ray by the
/// [`DEPTH_FACTORS`] and across it by the [`SHIFTS`] (the silhouette
/// scaled and shifted in the image); each rotation keeps its best place,
/// and the best `keep` rotations are returned, best first. `None` when the
/// colours cannot be told apart (too few pixels of either).
#[allow(clippy::too_many_arguments)]
pub fn start_poses_by_colour(
    mesh: &Mesh,
    k: &Intrinsics,
    img: &ColorImage,
    bbox: (f64, f64, f64, f64),
    mask: &Mask,
    rotations: &[[f64; 4]],
    keep: usize,
    deadline: &Deadline,
) -> Result<Option<Vec<Start>>, PoseError> {
    let (w, h) = (img.width(), img.height());
    let (bx, by, bw, bh) = bbox;
    let side = bw.max(bh);
    let (x0, y0, x1, y1) = grown_box(bbox, COLOUR_MARGIN, w, h);
    if x1 <= x0 || y1 <= y0 || (mask.width, mask.height) != (w, h) {
        return Ok(None);
    }
    // The background's pixels lie outside the box grown by 10%: a
    // detection's box is off by a cell or two.
    let inner = grown_box(bbox, 0.1, w, h);
    let in_box = |x: usize, y: usize| {
        let (fx, fy) = (x as f64 + 0.5, y as f64 + 0.5);
        fx >= bx && fx < bx + bw && fy >= by && fy < by + bh
    };
    let Some(colour) = ColourModel::from_regions(img, (x0, y0, x1 - x0, y1 - y0), |x, y| {
        if in_box(x, y) {
            mask.get(x, y).then_some(true)
        } else if x < inner.0 || x >= inner.2 || y < inner.1 || y >= inner.3 {
            Some(false)
        } else {
            None
        }
    }) else {
        return Ok(None);
    };
    let rw = x1 - x0;
    let odds: Vec<f32> = (y0..y1)
        .flat_map(|y| (x0..x1).map(move |x| (x, y)))
        .map(|(x, y)| colour.log_odds(img, x, y) as f32)
        .collect();
    // Colours that do not tell the mask from the background rank nothing.
    let (mut inside, mut outside) = ((0.0, 0usize), (0.0, 0usize));
    for y in y0..y1 {
        for x in x0..x1 {
            let o = f64::from(odds[(y - y0) * rw + (x - x0)]);
            if in_box(x, y) && mask.get(x, y) {
                inside = (inside.0 + o, inside.1 + 1);
            } else if !in_box(x, y) {
                outside = (outside.0 + o, outside.1 + 1);
            }
        }
    }
    let mean = |(s, n): (f64, usize)| s / n.max(1) as f64;
    if mean(inside) - mean(outside) < MIN_COLOUR_CONTRAST {
        return Ok(None);
    }
    // The log-odds at image point (u, v); nothing outside the window.
    let at = |u: f64, v: f64| -> f64 {
        if u < x0 as f64 || v < y0 as f64 {
            return 0.0;
        }
        let (x, y) = (u as usize, v as usize);
        if x >= x1 || y >= y1 {
            return 0.0;
        }
        f64::from(odds[(y - y0) * rw + (x - x0)])
    };
    let centre = mesh_centre(mesh);
    // Where a silhouette placed on the box lies (with a margin).
    let (sx0, sy0, sx1, sy1) = grown_box(bbox, 0.05, w, h);
    // The finer shifts: a quarter of the coarse ones.
    let step = (SHIFTS[1] - SHIFTS[0]) / 4.0 * side;
    let mut out = Vec::with_capacity(rotations.len());
    for (r, pose) in placed_on_box(mesh, k, rotations, bbox, deadline)? {
        let centre_cam = pose.translation + r * centre;
        let Some(c) = k.project(&centre_cam) else {
            continue;
        };
        let raster = rasterize(
            &mesh.vertices,
            &mesh.triangles,
            k,
            &pose,
            w,
            h,
            false,
            deadline,
        )?;
        // The silhouette's pixels, about the projected centre.
        let pixels: Vec<(f64, f64)> = (sy0..sy1)
            .flat_map(|y| (sx0..sx1).map(move |x| (x, y)))
            .filter(|&(x, y)| raster.covered(x, y))
            .map(|(x, y)| (x as f64 + 0.5 - c.x, y as f64 + 0.5 - c.y))
            .collect();
        if pixels.is_empty() {
            continue;
        }
        // The silhouette farther by `f` (shrunk by 1/f about its centre,
        // each pixel standing for (1/f)^2 of the image's) and centred on
        // (u, v).
        let score_at = |f: f64, u: f64, v: f64| {
            let s = 1.0 / f;
            s * s
                * pixels
                    .iter()
                    .map(|&(ox, oy)| at(u + s * ox, v + s * oy))
                    .sum::<f64>()
        };
        let mut best: Option<(f64, f64, f64, f64)> = None;
        let keep_best = |best: &mut Option<(f64, f64, f64, f64)>, f: f64, u: f64, v: f64| {
            let score = score_at(f, u, v);
            if best.is_none_or(|b| score > b.0) {
                *best = Some((score, f, u, v));
            }
        };
        for f in DEPTH_FACTORS {
            for dy in SHIFTS {
                for dx in SHIFTS {
                    keep_best(&mut best, f, c.x + dx * side, c.y + dy * side);
                }
            }
        }
        // Then finer about the best: depths 1.5% apart (the coarse ones
        // 10%), shifts a quarter of the coarse ones.
        if let Some((_, f0, u0, v0)) = best {
            for i in -3..=3 {
                for dy in -2..=2 {
                    for dx in -2..=2 {
                        keep_best(
                            &mut best,
                            f0 * (1.0 + 0.015 * f64::from(i)),
                            u0 + f64::from(dx) * step,
                            v0 + f64::from(dy) * step,
                        );
                    }
                }
            }
        }
        let Some((score, f, u, v)) = best else {
            continue;
        };
        let z = centre_cam.z * f;
        let moved = Vector3::new((u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z);
        out.push(Start {
            pose: Pose {
                rotation: r,
                translation: moved - r * centre,
            },
            agreement: score,
        });
    }
    out.sort_by(|a, b| b.agreement.total_cmp(&a.agreement));
    out.truncate(keep);
    Ok(Some(out))
}

/// The correlation (-1 to 1) of the mesh's vertex colours at `pose` (each
/// pixel the mean of its triangle's corners) with the image's, over the
/// pixels the mesh covers inside `mask`, each channel about its mean:
/// a change of the light's strength or of the camera's gain leaves it as
/// it is. `None` without colours or with fewer than 20 such pixels.
pub fn appearance(
    mesh: &Mesh,
    k: &Intrinsics,
    img: &ColorImage,
    pose: &Pose,
    mask: &Mask,
    deadline: &Deadline,
) -> Result<Option<f64>, PoseError> {
    let Some(colours) = &mesh.colours else {
        return Ok(None);
    };
    let (w, h) = (img.width(), img.height());
    let Some((bx, by, bw, bh)) = projected_box(&mesh.vertices, k, pose) else {
        return Ok(None);
    };
    let raster = rasterize(
        &mesh.vertices,
        &mesh.triangles,
        k,
        pose,
        w,
        h,
        false,
        deadline,
    )?;
    let (x0, y0, x1, y1) = grown_box((bx, by, bw, bh), 0.0, w, h);
    let mut pairs: Vec<([f64; 3], [f64; 3])> = Vec::new();
    for y in y0..y1.min(mask.height) {
        for x in x0..x1.min(mask.width) {
            if !mask.get(x, y) {
                continue;
            }
            let Some(f) = raster.face_at(x, y) else {
                continue;
            };
            let Some(t) = mesh.triangles.get(f as usize) else {
                continue;
            };
            let rendered = [0, 1, 2].map(|c| {
                t.iter()
                    .map(|&v| f64::from(colours.get(v as usize).map_or(0.0, |col| col[c])))
                    .sum::<f64>()
                    / 3.0
            });
            let seen = [0, 1, 2].map(|c| f64::from(img.get(x, y, c)));
            pairs.push((rendered, seen));
        }
    }
    if pairs.len() < 20 {
        return Ok(None);
    }
    let n = pairs.len() as f64;
    let (mut cov, mut var_r, mut var_s) = (0.0, 0.0, 0.0);
    for c in 0..3 {
        let mr = pairs.iter().map(|p| p.0[c]).sum::<f64>() / n;
        let ms = pairs.iter().map(|p| p.1[c]).sum::<f64>() / n;
        for (r, s) in &pairs {
            let (dr, ds) = (r[c] - mr, s[c] - ms);
            cov += dr * ds;
            var_r += dr * dr;
            var_s += ds * ds;
        }
    }
    Ok((var_r > 1e-9 && var_s > 1e-9).then(|| cov / (var_r * var_s).sqrt()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn k() -> Intrinsics {
        Intrinsics {
            fx: 570.0,
            fy: 570.0,
            cx: 320.0,
            cy: 240.0,
        }
    }

    /// The unit quaternion `[w, x, y, z]` of Euler angles.
    fn quat(a: f64, b: f64, c: f64) -> [f64; 4] {
        let r = nalgebra::Rotation3::from_euler_angles(a, b, c);
        let q = UnitQuaternion::from_rotation_matrix(&r);
        [q.w, q.i, q.j, q.k]
    }

    /// The mesh drawn at `pose` in a `w` x `h` image.
    fn drawn(mesh: &Mesh, pose: &Pose, w: usize, h: usize) -> super::super::edges::DepthBuffer {
        rasterize(
            &mesh.vertices,
            &mesh.triangles,
            &k(),
            pose,
            w,
            h,
            false,
            &Deadline::NONE,
        )
        .unwrap()
    }

    /// A box placed by `pose_for_box` projects onto the box it was asked
    /// for, at the depth that gives it that size.
    #[test]
    fn pose_for_box_matches_the_box() {
        let mesh = Mesh::cuboid(60.0, 40.0, 30.0);
        let truth = Pose {
            rotation: nalgebra::Rotation3::from_euler_angles(0.4, -0.3, 0.2).into_inner(),
            translation: Vector3::new(40.0, -25.0, 600.0),
        };
        let b = projected_box(&mesh.vertices, &k(), &truth).unwrap();
        let p = pose_for_box(&mesh.vertices, &k(), &truth.rotation, b).unwrap();
        let q = projected_box(&mesh.vertices, &k(), &p).unwrap();
        for (a, c) in [(b.0, q.0), (b.1, q.1), (b.2, q.2), (b.3, q.3)] {
            assert!((a - c).abs() < 0.5, "{b:?} {q:?}");
        }
        assert!((p.translation - truth.translation).norm() < 5.0, "{p:?}");
        assert!(
            pose_for_box(&mesh.vertices, &k(), &truth.rotation, (0.0, 0.0, 0.0, 5.0)).is_none()
        );
    }

    /// Among rotations placed on the box, the true one agrees best with
    /// the true silhouette and box, and ranks first.
    #[test]
    fn the_true_rotation_ranks_first_by_silhouette() {
        let mesh = Mesh::cuboid(80.0, 30.0, 20.0);
        let truth_q = quat(0.3, 0.2, 0.9);
        let truth = Pose {
            rotation: rotation_from_quaternion(&truth_q).unwrap(),
            translation: Vector3::new(0.0, 0.0, 500.0),
        };
        let raster = drawn(&mesh, &truth, 640, 480);
        let mut mask = Mask::new(640, 480);
        for y in 0..480 {
            for x in 0..640 {
                mask.set(x, y, raster.covered(x, y));
            }
        }
        let b = projected_box(&mesh.vertices, &k(), &truth).unwrap();
        let rotations = [
            quat(0.3, 0.2, 0.0),
            truth_q,
            quat(1.2, 0.2, 0.9),
            quat(0.3, 1.0, -0.5),
        ];
        let starts =
            start_poses(&mesh, &k(), b, Some(&mask), &rotations, 2, &Deadline::NONE).unwrap();
        assert_eq!(starts.len(), 2);
        assert!(starts[0].agreement > 0.95, "{:?}", starts[0]);
        assert!((starts[0].pose.rotation - truth.rotation).norm() < 1e-9);
        assert!(starts[1].agreement < starts[0].agreement);
    }

    /// On an image whose object has its own colour, a coarse mask (the
    /// silhouette's cells of 8 pixels) and a box shifted and grown as a
    /// detection's would be, the true rotation ranks first by colour and
    /// lands near the true place and depth.
    #[test]
    fn the_true_rotation_ranks_first_by_colour() {
        let mesh = Mesh::cuboid(80.0, 30.0, 20.0);
        let truth_q = quat(0.3, 0.2, 0.9);
        let truth = Pose {
            rotation: rotation_from_quaternion(&truth_q).unwrap(),
            translation: Vector3::new(10.0, -5.0, 500.0),
        };
        let (w, h) = (640, 480);
        let raster = drawn(&mesh, &truth, w, h);
        let mut data = Vec::with_capacity(w * h * 3);
        let mut coarse = Mask::new(w, h);
        for y in 0..h {
            for x in 0..w {
                // A checkerboard of greys behind a red object.
                let on = raster.covered(x, y);
                let g = if (x / 7 + y / 5) % 2 == 0 {
                    60.0
                } else {
                    190.0
                };
                data.extend(if on { [200.0, 30.0, 40.0] } else { [g, g, g] });
                let (cx, cy) = (x / 8 * 8 + 4, y / 8 * 8 + 4);
                coarse.set(x, y, raster.covered(cx.min(w - 1), cy.min(h - 1)));
            }
        }
        let img = ColorImage::new(w, h, data).unwrap();
        let (bx, by, bw, bh) = projected_box(&mesh.vertices, &k(), &truth).unwrap();
        let detected = (bx + 0.06 * bw, by - 0.04 * bh, bw * 1.1, bh * 1.05);
        let rotations = [
            quat(0.3, 0.2, 0.0),
            quat(1.2, 0.2, 0.9),
            truth_q,
            quat(0.3, 1.0, -0.5),
        ];
        let starts = start_poses_by_colour(
            &mesh,
            &k(),
            &img,
            detected,
            &coarse,
            &rotations,
            2,
            &Deadline::NONE,
        )
        .unwrap()
        .expect("the colours differ");
        assert_eq!(starts.len(), 2);
        assert!((starts[0].pose.rotation - truth.rotation).norm() < 1e-9);
        assert!(starts[1].agreement < starts[0].agreement);
        let off = starts[0].pose.translation - truth.translation;
        assert!(off.norm() < 30.0, "{off:?}");
        // One colour everywhere: nothing to rank by.
        let flat = ColorImage::new(w, h, vec![100.0; w * h * 3]).unwrap();
        let none = start_poses_by_colour(
            &mesh,
            &k(),
            &flat,
            detected,
            &coarse,
            &rotations,
            2,
            &Deadline::NONE,
        )
        .unwrap();
        assert!(none.is_none(), "{none:?}");
    }

    /// The mesh's own colours tell a pose from the same pose turned about:
    /// the image drawn from the mesh's colours (lit, with a gain)
    /// correlates with them at the true pose and against them turned half
    /// a turn about the camera's vertical axis, whose outline is the same.
    #[test]
    fn appearance_tells_a_turned_about_pose() {
        use crate::pose::render::{render_colours, Lighting};
        let mut mesh = Mesh::cuboid(60.0, 60.0, 60.0);
        // One side red, the other blue.
        mesh.colours = Some(
            mesh.vertices
                .iter()
                .map(|v| {
                    if v.x > 0.0 {
                        [220.0, 40.0, 30.0]
                    } else {
                        [30.0, 50.0, 200.0]
                    }
                })
                .collect(),
        );
        // Small triangles, as a scanned mesh has: a triangle's mean colour
        // is then its pixels'.
        let mesh = mesh.subdivided(3);
        let truth = Pose {
            rotation: nalgebra::Rotation3::from_euler_angles(0.0, 0.5, 0.0).into_inner(),
            translation: Vector3::new(0.0, 0.0, 500.0),
        };
        let (w, h) = (640, 480);
        let lighting = Lighting {
            light: Vector3::new(0.3, -0.2, 1.0),
            ambient: 0.4,
            gain: [0.8, 0.8, 0.8],
        };
        let (drawn, mask) = render_colours(
            &mesh,
            mesh.colours.as_deref(),
            &k(),
            &truth,
            w,
            h,
            &lighting,
        )
        .unwrap();
        let data: Vec<f32> = drawn
            .iter()
            .enumerate()
            .flat_map(|(i, c)| {
                if mask.get(i % w, i / w) {
                    *c
                } else {
                    [90.0; 3]
                }
            })
            .collect();
        let img = ColorImage::new(w, h, data).unwrap();
        let score = |p: &Pose| appearance(&mesh, &k(), &img, p, &mask, &Deadline::NONE).unwrap();
        let turned = Pose {
            rotation: nalgebra::Rotation3::from_euler_angles(0.0, std::f64::consts::PI, 0.0)
                .into_inner()
                * truth.rotation,
            ..truth
        };
        let (at_truth, at_turned) = (score(&truth).unwrap(), score(&turned).unwrap());
        assert!(at_truth > 0.8, "{at_truth}");
        assert!(at_turned < 0.0, "{at_turned}");
        // Without colours there is nothing to compare.
        let plain = Mesh::cuboid(60.0, 60.0, 60.0);
        assert!(
            appearance(&plain, &k(), &img, &truth, &mask, &Deadline::NONE)
                .unwrap()
                .is_none()
        );
    }
}
