//! Training sets rendered from a mesh: the object at viewpoints sampled
//! over the view sphere (an elevation band above the mesh's `xy` plane, any
//! azimuth, a little in-plane rotation), at varied distance and position,
//! with vertex colours and varied Lambert lighting, pasted over background
//! photographs, hidden in part by occluders cut from other backgrounds,
//! then blurred and noised like a camera. Every render keeps the exact
//! full-extent box and visible mask (z-buffer), and the views are grouped
//! into viewpoint components by their viewing direction (k-means on the
//! sphere), each with its mean direction.

use std::path::{Path, PathBuf};

use indicatif::ProgressBar;
use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::TrainError;
use crate::data::{Annotation, Sample};
use crate::pose::geometry::{Intrinsics, Pose};
use crate::pose::mesh::Mesh;
use crate::pose::render::{render_colours, Lighting};
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;
use crate::vision::rng::SplitMix64;

/// How the training renders are drawn.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct RenderParams {
    /// Renders of the object (positives).
    pub renders: usize,
    /// Viewpoint components (templates).
    pub components: usize,
    /// Elevation of the camera above the mesh's `xy` plane, degrees.
    pub elevation: [f64; 2],
    /// Largest in-plane rotation of the camera, degrees either way.
    pub roll: f64,
    /// Longest side of the object's box in the render, pixels.
    pub size: [f64; 2],
    /// Share of the renders with an occluder, and the range of the
    /// fraction of the object's box it covers.
    pub occluded_share: f64,
    pub occlusion: [f64; 2],
    /// Share of the occluders filled with a patch of another background
    /// photograph; the others are a smooth colour. Patches of the very
    /// photographs that are the negatives teach the occlusion filter that
    /// background is occluder: with patches only, LM-O duck scored AUC
    /// 0.000 (every 4th photograph), with smooth colours only 0.148.
    pub patch_occluders: f64,
    /// Share of the occluders that are renders of the occluder meshes
    /// (other objects), when any are given (see [`render_set_with`]).
    pub mesh_occluders: f64,
    /// Render size in pixels (the object and some context).
    pub width: usize,
    pub height: usize,
    /// Focal length of the rendering camera in pixels.
    pub focal: f64,
    pub seed: u64,
}

impl Default for RenderParams {
    fn default() -> Self {
        Self {
            renders: 400,
            components: 4,
            elevation: [0.0, 80.0],
            roll: 20.0,
            size: [40.0, 110.0],
            occluded_share: 0.3,
            occlusion: [0.1, 0.6],
            patch_occluders: 0.0,
            mesh_occluders: 0.5,
            width: 320,
            height: 240,
            focal: 575.0,
            seed: 1,
        }
    }
}

impl RenderParams {
    pub fn validate(&self) -> Result<(), TrainError> {
        let bad = |m: &str| Err(TrainError::NoData(format!("invalid render setting: {m}")));
        if self.renders == 0 || self.components == 0 || self.components > self.renders {
            return bad("need renders >= components >= 1");
        }
        if !(-90.0..=90.0).contains(&self.elevation[0])
            || !(-90.0..=90.0).contains(&self.elevation[1])
            || self.elevation[0] > self.elevation[1]
        {
            return bad("elevation must be MIN,MAX within -90..90");
        }
        if !(0.0..=180.0).contains(&self.roll) {
            return bad("roll must be within 0..180 degrees");
        }
        if !(self.size[0] >= 16.0 && self.size[1] >= self.size[0]) {
            return bad("size must be MIN,MAX with MIN >= 16 px");
        }
        if self.size[1] > 0.9 * self.width.min(self.height) as f64 {
            return bad("the largest size must fit in the render (0.9 of its shorter side)");
        }
        if !(0.0..=1.0).contains(&self.occluded_share)
            || !(0.0..=0.95).contains(&self.occlusion[0])
            || !(self.occlusion[0]..=0.95).contains(&self.occlusion[1])
            || !(0.0..=1.0).contains(&self.patch_occluders)
            || !(0.0..=1.0).contains(&self.mesh_occluders)
        {
            return bad(
                "occlusion shares must lie in 0..0.95, MIN <= MAX, patch_occluders and mesh_occluders in 0..1",
            );
        }
        if !(self.focal > 0.0 && self.focal.is_finite()) {
            return bad("focal must be > 0");
        }
        Ok(())
    }
}

/// Representative rotations kept per component for start poses.
pub const ROTATIONS_PER_COMPONENT: usize = 32;

/// A rendered training set.
pub struct MeshSet {
    /// The renders (positives, label = the object's name).
    pub samples: Vec<Sample>,
    /// Each component's mean viewing direction in the mesh's frame (unit
    /// vector from the object towards the camera).
    pub directions: Vec<[f64; 3]>,
    /// The pose of every render (camera from object).
    pub poses: Vec<Pose>,
    /// Representative rotations of each component (see
    /// [`representative_rotations`]).
    pub rotations: Vec<Vec<[f64; 4]>>,
    /// The share of each render's object that the occluder hides.
    pub occluded: Vec<f64>,
}

/// The camera direction (object towards camera) of azimuth and elevation
/// (radians) in the mesh's frame, `z` up.
fn direction(azimuth: f64, elevation: f64) -> Vector3<f64> {
    Vector3::new(
        elevation.cos() * azimuth.cos(),
        elevation.cos() * azimuth.sin(),
        elevation.sin(),
    )
}

/// The rotation (camera from object) of a camera looking at the origin
/// from `dir`, the mesh's `z` up in the image, turned by `roll` radians
/// about the optical axis.
pub fn look_rotation(dir: &Vector3<f64>, roll: f64) -> Matrix3<f64> {
    let forward = -dir.normalize();
    let up = Vector3::z();
    // Image y points down: away from the up axis projected on the image.
    let mut down = -(up - forward * up.dot(&forward));
    if down.norm() < 1e-6 {
        down = Vector3::x() - forward * forward.x;
    }
    let down = down.normalize();
    let right = down.cross(&forward);
    // Rows: the camera axes in the object's frame.
    let r = Matrix3::from_rows(&[right.transpose(), down.transpose(), forward.transpose()]);
    Rotation3::from_axis_angle(&Vector3::z_axis(), roll).into_inner() * r
}

/// Groups unit directions into `k` clusters (k-means on the sphere,
/// farthest-point start): each direction's cluster and the clusters' mean
/// directions.
pub fn cluster_directions(dirs: &[Vector3<f64>], k: usize) -> (Vec<usize>, Vec<Vector3<f64>>) {
    let k = k.clamp(1, dirs.len().max(1));
    if dirs.is_empty() {
        return (Vec::new(), Vec::new());
    }
    let mut centres = vec![dirs[0]];
    while centres.len() < k {
        let far = dirs
            .iter()
            .max_by(|a, b| {
                let da = centres.iter().map(|c| a.dot(c)).fold(f64::MIN, f64::max);
                let db = centres.iter().map(|c| b.dot(c)).fold(f64::MIN, f64::max);
                db.total_cmp(&da)
            })
            .copied()
            .unwrap_or(dirs[0]);
        centres.push(far);
    }
    let mut assign = vec![0usize; dirs.len()];
    for _ in 0..20 {
        for (a, d) in assign.iter_mut().zip(dirs) {
            *a = (0..k)
                .max_by(|&i, &j| d.dot(&centres[i]).total_cmp(&d.dot(&centres[j])))
                .unwrap_or(0);
        }
        for (c, centre) in centres.iter_mut().enumerate() {
            let sum: Vector3<f64> = dirs
                .iter()
                .zip(&assign)
                .filter(|(_, &a)| a == c)
                .map(|(d, _)| *d)
                .sum();
            if let Some(n) = sum.try_normalize(1e-12) {
                *centre = n;
            }
        }
    }
    (assign, centres)
}

/// The angle (radians) between two rotations.
fn rotation_angle(a: &Matrix3<f64>, b: &Matrix3<f64>) -> f64 {
    let c = ((a.transpose() * b).trace() - 1.0) / 2.0;
    c.clamp(-1.0, 1.0).acos()
}

/// Up to `n` representative rotations of each of `k` components: within
/// a component, farthest-point sampling over the rotations of its views
/// (starting from the one nearest to all others), so that they cover the
/// component's range of views and in-plane rotations evenly. Unit
/// quaternions `[w, x, y, z]`.
pub fn representative_rotations(
    rotations: &[Matrix3<f64>],
    assign: &[usize],
    k: usize,
    n: usize,
) -> Vec<Vec<[f64; 4]>> {
    (0..k)
        .map(|c| {
            let members: Vec<&Matrix3<f64>> = rotations
                .iter()
                .zip(assign)
                .filter(|(_, &a)| a == c)
                .map(|(r, _)| r)
                .collect();
            let mut chosen: Vec<usize> = Vec::new();
            // The medoid first: the smallest summed angle to the others.
            let medoid = (0..members.len()).min_by(|&i, &j| {
                let si: f64 = members.iter().map(|m| rotation_angle(members[i], m)).sum();
                let sj: f64 = members.iter().map(|m| rotation_angle(members[j], m)).sum();
                si.total_cmp(&sj)
            });
            let mut nearest = vec![f64::INFINITY; members.len()];
            let mut next = medoid;
            while let Some(i) = next {
                if chosen.len() >= n {
                    break;
                }
                chosen.push(i);
                for (d, m) in nearest.iter_mut().zip(&members) {
                    *d = d.min(rotation_angle(members[i], m));
                }
                next = (0..members.len())
                    .filter(|j| !chosen.contains(j))
                    .max_by(|&a, &b| nearest[a].total_cmp(&nearest[b]));
            }
            chosen
                .into_iter()
                .map(|i| {
                    let q = UnitQuaternion::from_matrix(members[i]);
                    [q.w, q.i, q.j, q.k]
                })
                .collect()
        })
        .collect()
}

/// A `width x height` crop of a background at a random place (the
/// background scaled up first where it is smaller), mirrored at random.
/// A photograph of the object's scene with the object taken out: each of
/// `boxes` `(x, y, width, height)`, grown by a tenth of its size on every
/// side, is covered by the mirror image of the strip of the same size
/// beside it (left, else right, above, below; where none fits, the
/// widest part of the image beside it, stretched). Renders pasted over
/// it meet the user's own clutter and light without a second, unlabelled
/// instance of the object.
pub fn without_boxes(img: &ColorImage, boxes: &[(f64, f64, f64, f64)]) -> ColorImage {
    let (w, h) = (img.width(), img.height());
    let mut data = img.data().to_vec();
    for &(x, y, bw, bh) in boxes {
        let clamp = |v: f64, hi: usize| v.round().clamp(0.0, hi as f64) as usize;
        let (x0, y0) = (clamp(x - 0.1 * bw, w), clamp(y - 0.1 * bh, h));
        let (x1, y1) = (clamp(x + 1.1 * bw, w), clamp(y + 1.1 * bh, h));
        let (cw, ch) = (x1 - x0, y1 - y0);
        if cw == 0 || ch == 0 || (cw == w && ch == h) {
            continue;
        }
        // Source pixel of (px, py) inside the box: a mirror across the
        // box's side where the strip fits, else the nearest pixel beside
        // the box's larger free side, stretched.
        let src = |px: usize, py: usize| -> (usize, usize) {
            let (dx, dy) = (px - x0, py - y0);
            if x0 >= cw {
                (x0 - 1 - dx, py)
            } else if x1 + cw <= w {
                (x1 + (cw - 1 - dx), py)
            } else if y0 >= ch {
                (px, y0 - 1 - dy)
            } else if y1 + ch <= h {
                (px, y1 + (ch - 1 - dy))
            } else if x0.max(w - x1) >= y0.max(h - y1) {
                if x0 >= w - x1 {
                    (dx * x0 / cw, py)
                } else {
                    (x1 + dx * (w - x1) / cw, py)
                }
            } else if y0 >= h - y1 {
                (px, dy * y0 / ch)
            } else {
                (px, y1 + dy * (h - y1) / ch)
            }
        };
        for py in y0..y1 {
            for px in x0..x1 {
                let (sx, sy) = src(px, py);
                let (sx, sy) = (sx.min(w - 1), sy.min(h - 1));
                for c in 0..3 {
                    data[(py * w + px) * 3 + c] = img.get(sx, sy, c);
                }
            }
        }
    }
    // Same size as `img`, so never empty.
    ColorImage::new(w, h, data).unwrap_or_else(|_| img.clone())
}

fn background_crop(bg: &ColorImage, width: usize, height: usize, rng: &mut SplitMix64) -> Vec<f32> {
    let (bw, bh) = (bg.width(), bg.height());
    let scale = (width as f64 / bw as f64)
        .max(height as f64 / bh as f64)
        .max(rng.range_f64(0.5, 1.0));
    let (cw, ch) = (width as f64 / scale, height as f64 / scale);
    let x0 = rng.range_f64(0.0, (bw as f64 - cw).max(0.0));
    let y0 = rng.range_f64(0.0, (bh as f64 - ch).max(0.0));
    let mirror = rng.next_f64() < 0.5;
    let mut out = Vec::with_capacity(width * height * 3);
    for y in 0..height {
        for x in 0..width {
            let xm = if mirror { width - 1 - x } else { x };
            let sx = ((x0 + (xm as f64 + 0.5) / scale) as usize).min(bw - 1);
            let sy = ((y0 + (y as f64 + 0.5) / scale) as usize).min(bh - 1);
            for c in 0..3 {
                out.push(bg.get(sx, sy, c));
            }
        }
    }
    out
}

/// An occluder over `occlude` of the object's box `(x0, y0, x1, y1)`: an
/// ellipse or a band entering from a random side, reaching past the box;
/// `true` where it covers.
fn occluder_shape(
    b: (usize, usize, usize, usize),
    occlude: f64,
    width: usize,
    height: usize,
    rng: &mut SplitMix64,
) -> Mask {
    let (x0, y0, x1, y1) = b;
    let (bw, bh) = ((x1 - x0).max(1) as f64, (y1 - y0).max(1) as f64);
    let side = rng.range_usize(0, 4);
    let ellipse = rng.next_f64() < 0.5;
    let mut m = Mask::new(width, height);
    for y in 0..height {
        for x in 0..width {
            let fx = (x as f64 + 0.5 - x0 as f64) / bw;
            let fy = (y as f64 + 0.5 - y0 as f64) / bh;
            // Depth into the box from the chosen side, and the position
            // along that side.
            let (depth, along) = match side {
                0 => (fx, fy),
                1 => (1.0 - fx, fy),
                2 => (fy, fx),
                _ => (1.0 - fy, fx),
            };
            let on = if ellipse {
                // Centred on the side, reaching `occlude` into the box.
                let (dx, dy) = (depth / occlude.max(0.05), (along - 0.5) / 0.7);
                dx * dx + dy * dy < 1.0 && depth > -0.3
            } else {
                depth < occlude && depth > -0.3 && (-0.2..1.2).contains(&along)
            };
            m.set(x, y, on);
        }
    }
    m
}

/// A render's colours per pixel (zero where nothing is drawn) and its
/// silhouette.
type Drawn = (Vec<[f32; 3]>, Mask);

/// Another object's mesh that hides part of the renders.
pub struct Occluder {
    pub mesh: Mesh,
    pub colours: Option<Vec<[f32; 3]>>,
}

/// Renders the training set of `mesh` into `dir` (JPEG files) over
/// `backgrounds`, advancing `progress` per render.
pub fn render_set(
    mesh: &Mesh,
    colours: Option<&[[f32; 3]]>,
    name: &str,
    backgrounds: &[ColorImage],
    params: &RenderParams,
    dir: &Path,
    progress: &ProgressBar,
) -> Result<MeshSet, TrainError> {
    render_set_with(mesh, colours, name, backgrounds, &[], params, dir, progress)
}

/// A render of `occ` at a random rotation, its size `size` pixels, placed
/// so that it hides about `occlude` of the object's silhouette `full`
/// (the best of a few placements): its colours and silhouette, `None`
/// where nothing could be drawn.
#[allow(clippy::too_many_arguments)]
fn mesh_occluder(
    occ: &Occluder,
    full: &Mask,
    occlude: f64,
    size: f64,
    k: &Intrinsics,
    lighting: &Lighting,
    rng: &mut SplitMix64,
) -> Result<Option<Drawn>, TrainError> {
    let (w, h) = (full.width, full.height);
    let Some((bx0, by0, bx1, by1)) = full.tight_box() else {
        return Ok(None);
    };
    let (lo, hi) = occ.mesh.bounds();
    let centre = (lo + hi) / 2.0;
    let diagonal = (hi - lo).norm().max(1e-9);
    let dir = direction(
        rng.range_f64(0.0, std::f64::consts::TAU),
        rng.range_f64(-1.0, 1.0).asin(),
    );
    let rotation = look_rotation(&dir, rng.range_f64(-180.0, 180.0).to_radians());
    let occ_size = size * rng.range_f64(0.6, 1.4);
    let z = k.fx * 0.7 * diagonal / occ_size;
    let (cx, cy) = ((bx0 + bx1) as f64 / 2.0, (by0 + by1) as f64 / 2.0);
    let reach = ((bx1 - bx0).max(by1 - by0) as f64 + occ_size) / 2.0;
    let area = full.area().max(1) as f64;
    let mut best: Option<(f64, Vec<[f32; 3]>, Mask)> = None;
    for _ in 0..6 {
        // From a random side, as far in as the share to hide asks.
        let angle = rng.range_f64(0.0, std::f64::consts::TAU);
        let d = reach * (1.0 - 1.6 * occlude).clamp(0.0, 1.0) * rng.range_f64(0.8, 1.2);
        let (u, v) = (cx + d * angle.cos(), cy + d * angle.sin());
        let at = Vector3::new((u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z);
        let pose = Pose {
            rotation,
            translation: at - rotation * centre,
        };
        let (colours, sil) =
            render_colours(&occ.mesh, occ.colours.as_deref(), k, &pose, w, h, lighting)?;
        let hidden = full
            .data
            .iter()
            .zip(&sil.data)
            .filter(|(a, b)| **a != 0 && **b != 0)
            .count() as f64
            / area;
        let miss = (hidden - occlude).abs();
        if best.as_ref().is_none_or(|b| miss < b.0) {
            best = Some((miss, colours, sil));
        }
        if miss < 0.1 {
            break;
        }
    }
    Ok(best.map(|(_, c, m)| (c, m)))
}

/// [`render_set`] where some occluders are renders of other objects'
/// meshes (`occluders`, see [`RenderParams::mesh_occluders`]).
#[allow(clippy::too_many_arguments)]
pub fn render_set_with(
    mesh: &Mesh,
    colours: Option<&[[f32; 3]]>,
    name: &str,
    backgrounds: &[ColorImage],
    occluders: &[Occluder],
    params: &RenderParams,
    dir: &Path,
    progress: &ProgressBar,
) -> Result<MeshSet, TrainError> {
    params.validate()?;
    mesh.validate()
        .map_err(|e| TrainError::NoData(format!("mesh: {e}")))?;
    if backgrounds.is_empty() {
        return Err(TrainError::NoData("no background image".into()));
    }
    std::fs::create_dir_all(dir).map_err(|source| TrainError::Io {
        path: dir.display().to_string(),
        source,
    })?;
    let (w, h) = (params.width, params.height);
    let k = Intrinsics {
        fx: params.focal,
        fy: params.focal,
        cx: w as f64 / 2.0,
        cy: h as f64 / 2.0,
    };
    // The mesh's box centre and its diagonal.
    let (lo, hi) = mesh.bounds();
    let centre = (lo + hi) / 2.0;
    let diagonal = (hi - lo).norm().max(1e-9);
    let mut master = SplitMix64::new(params.seed);
    let (e0, e1) = (
        params.elevation[0].to_radians().sin(),
        params.elevation[1].to_radians().sin(),
    );
    let mut samples = Vec::with_capacity(params.renders);
    let mut poses = Vec::with_capacity(params.renders);
    let mut dirs = Vec::with_capacity(params.renders);
    let mut occluded = Vec::with_capacity(params.renders);
    let mut attempts = 0usize;
    while samples.len() < params.renders {
        attempts += 1;
        if attempts > params.renders * 20 {
            return Err(TrainError::NoData(format!(
                "only {} of {} renders show the object whole in the image: check the mesh's size and units",
                samples.len(),
                params.renders
            )));
        }
        let i = samples.len();
        // A generator per attempt, seeded from the master's stream.
        let mut rng = SplitMix64::new(master.next_u64());
        let dir_obj = direction(
            rng.range_f64(0.0, std::f64::consts::TAU),
            rng.range_f64(e0, e1).clamp(-1.0, 1.0).asin(),
        );
        let roll = rng.range_f64(-params.roll, params.roll).to_radians();
        let rotation = look_rotation(&dir_obj, roll);
        // Distance for the wanted size (the projected box is about 0.7 of
        // the diagonal's projection), position anywhere the box fits.
        let size = rng.range_f64(params.size[0], params.size[1]);
        let z = params.focal * 0.7 * diagonal / size;
        let margin = size * 0.6;
        let u = rng.range_f64(margin, (w as f64 - margin).max(margin + 1.0));
        let v = rng.range_f64(margin, (h as f64 - margin).max(margin + 1.0));
        let at = Vector3::new((u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z);
        let pose = Pose {
            rotation,
            translation: at - rotation * centre,
        };
        let lighting = Lighting {
            light: Vector3::new(
                rng.range_f64(-0.8, 0.8),
                rng.range_f64(-0.8, 0.8),
                rng.range_f64(0.3, 1.0),
            ),
            ambient: rng.range_f64(0.25, 0.6),
            gain: {
                let g = rng.range_f64(0.7, 1.25);
                [g * rng.range_f64(0.9, 1.1), g, g * rng.range_f64(0.9, 1.1)]
            },
        };
        let (object, full) = render_colours(mesh, colours, &k, &pose, w, h, &lighting)?;
        let Some((bx0, by0, bx1, by1)) = full.tight_box() else {
            continue;
        };
        // The whole object inside the render, not touching its border.
        if bx0 == 0 || by0 == 0 || bx1 >= w || by1 >= h || full.area() < 64 {
            continue;
        }
        let bg = &backgrounds[rng.range_usize(0, backgrounds.len())];
        let mut data = background_crop(bg, w, h, &mut rng);
        for (p, c) in object.iter().enumerate() {
            if full.data[p] != 0 {
                data[p * 3..p * 3 + 3].copy_from_slice(c);
            }
        }
        let mut visible = full.clone();
        let occluded_now = rng.next_f64() < params.occluded_share;
        let by_mesh =
            occluded_now && !occluders.is_empty() && rng.next_f64() < params.mesh_occluders;
        if by_mesh {
            let occlude = rng.range_f64(params.occlusion[0], params.occlusion[1]);
            let occ = &occluders[rng.range_usize(0, occluders.len())];
            let light = Lighting {
                gain: {
                    let g = rng.range_f64(0.7, 1.25);
                    [g, g, g]
                },
                ..lighting
            };
            if let Some((cols, sil)) =
                mesh_occluder(occ, &full, occlude, size, &k, &light, &mut rng)?
            {
                for (p, c) in cols.iter().enumerate() {
                    if sil.data[p] != 0 {
                        data[p * 3..p * 3 + 3].copy_from_slice(c);
                        visible.data[p] = 0;
                    }
                }
            }
        } else if occluded_now {
            let object_box = (bx0, by0, bx1, by1);
            paste_patch_occluder(
                &mut data,
                &mut visible,
                object_box,
                backgrounds,
                params,
                &mut rng,
            );
        }
        let visible_area = visible.area();
        if visible_area < full.area() / 10 {
            continue;
        }
        camera_noise(&mut data, w, h, &mut rng);
        let img = ColorImage::new(w, h, data)?;
        let path: PathBuf = dir.join(format!("{name}_{i:05}.jpg"));
        img.to_rgb8().save(&path).map_err(|e| TrainError::Io {
            path: path.display().to_string(),
            source: std::io::Error::other(e.to_string()),
        })?;
        samples.push(Sample {
            image: path,
            id: format!("{name}_{i:05}"),
            annotation: Some(Annotation {
                label: name.to_string(),
                bbox: (
                    bx0 as f64,
                    by0 as f64,
                    (bx1 - bx0) as f64,
                    (by1 - by0) as f64,
                ),
                visible,
                viewpoint: 0,
                mask_known: true,
            }),
        });
        poses.push(pose);
        dirs.push(dir_obj);
        occluded.push(1.0 - visible_area as f64 / full.area() as f64);
        progress.inc(1);
    }
    let (assign, centres) = cluster_directions(&dirs, params.components);
    for (s, a) in samples.iter_mut().zip(&assign) {
        if let Some(an) = s.annotation.as_mut() {
            an.viewpoint = *a;
        }
    }
    let rs: Vec<Matrix3<f64>> = poses.iter().map(|p| p.rotation).collect();
    let rotations = representative_rotations(&rs, &assign, centres.len(), ROTATIONS_PER_COMPONENT);
    Ok(MeshSet {
        samples,
        directions: centres.iter().map(|c| [c.x, c.y, c.z]).collect(),
        rotations,
        poses,
        occluded,
    })
}

/// An occluder over a share of the object's box (`object_box`, pixel
/// corners): a patch of another background photograph, or for the rest
/// of `params.patch_occluders` a smooth colour, tinted; the pixels it
/// covers leave `visible`.
fn paste_patch_occluder(
    data: &mut [f32],
    visible: &mut Mask,
    object_box: (usize, usize, usize, usize),
    backgrounds: &[ColorImage],
    params: &RenderParams,
    rng: &mut SplitMix64,
) {
    let (w, h) = (params.width, params.height);
    let occlude = rng.range_f64(params.occlusion[0], params.occlusion[1]);
    let shape = occluder_shape(object_box, occlude, w, h, rng);
    let other = &backgrounds[rng.range_usize(0, backgrounds.len())];
    let mut patch = background_crop(other, w, h, rng);
    if rng.next_f64() >= params.patch_occluders {
        // A smooth colour (a random colour with a gentle
        // gradient): unlike a patch of a background photograph,
        // it never looks like the negatives.
        let base: [f64; 3] = std::array::from_fn(|_| rng.range_f64(20.0, 235.0));
        let (gx, gy) = (rng.range_f64(-0.6, 0.6), rng.range_f64(-0.6, 0.6));
        for y in 0..h {
            for x in 0..w {
                for (c, b) in base.iter().enumerate() {
                    patch[(y * w + x) * 3 + c] =
                        (b + gx * x as f64 + gy * y as f64).clamp(0.0, 255.0) as f32;
                }
            }
        }
    }
    let tint = rng.range_f64(0.6, 1.3) as f32;
    for p in 0..w * h {
        if shape.data[p] != 0 {
            for c in 0..3 {
                data[p * 3 + c] = (patch[p * 3 + c] * tint).min(255.0);
            }
            visible.data[p] = 0;
        }
    }
}

/// The camera's blur (a light one in half of the renders) and noise.
fn camera_noise(data: &mut Vec<f32>, w: usize, h: usize, rng: &mut SplitMix64) {
    if rng.next_f64() < 0.5 {
        *data = box_blur(data, w, h);
    }
    let sigma = rng.range_f64(1.0, 6.0);
    for v in data.iter_mut() {
        let n: f64 = (0..4).map(|_| rng.next_f64() - 0.5).sum::<f64>() * 3f64.sqrt();
        *v = (*v + (n * sigma) as f32).clamp(0.0, 255.0);
    }
}

/// A 3x3 box blur (edges clamped) of an interleaved RGB buffer.
fn box_blur(data: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut out = vec![0.0f32; data.len()];
    for y in 0..h {
        for x in 0..w {
            for c in 0..3 {
                let mut s = 0.0;
                for dy in -1i64..=1 {
                    for dx in -1i64..=1 {
                        let xx = (x as i64 + dx).clamp(0, w as i64 - 1) as usize;
                        let yy = (y as i64 + dy).clamp(0, h as i64 - 1) as usize;
                        s += data[(yy * w + xx) * 3 + c];
                    }
                }
                out[(y * w + x) * 3 + c] = s / 9.0;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A box taken out of a scene: no pixel of the object is left in it,
    /// and the pixels away from it are the scene's.
    #[test]
    fn without_boxes_takes_the_object_out_and_keeps_the_rest() {
        let (w, h) = (80usize, 60usize);
        let mut data = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            for x in 0..w {
                let object = (50..62).contains(&x) && (20..35).contains(&y);
                let v = if object { 255.0 } else { (x + y) as f32 };
                data.extend([v, v * 0.5, 10.0]);
            }
        }
        let img = ColorImage::new(w, h, data).unwrap();
        // Near the right border: the strip to its left is used.
        let out = without_boxes(&img, &[(50.0, 20.0, 12.0, 15.0)]);
        for y in 0..h {
            for x in 0..w {
                assert!(out.get(x, y, 0) < 255.0, "object left at ({x}, {y})");
                let inside = (48..64).contains(&x) && (18..37).contains(&y);
                if !inside {
                    assert_eq!(out.get(x, y, 0), img.get(x, y, 0), "({x}, {y}) changed");
                }
            }
        }
        // A box as large as the image leaves it as it is; one that fits no
        // strip beside it is still covered.
        let whole = without_boxes(&img, &[(0.0, 0.0, 80.0, 60.0)]);
        assert_eq!(whole.data(), img.data());
        let wide = without_boxes(&img, &[(20.0, 15.0, 50.0, 25.0)]);
        for y in 20..35 {
            for x in 50..62 {
                assert!(wide.get(x, y, 0) < 255.0, "object left at ({x}, {y})");
            }
        }
    }

    /// A camera placed by `look_rotation` sees the origin on its optical
    /// axis, the mesh's `z` axis upwards in the image.
    #[test]
    fn look_rotation_puts_the_object_ahead_and_z_up() {
        for (az, el) in [(0.0f64, 0.3f64), (1.0, 0.8), (2.5, -0.2), (4.0, 1.2)] {
            let d = direction(az, el);
            let r = look_rotation(&d, 0.0);
            assert!((r * r.transpose() - Matrix3::identity()).norm() < 1e-9);
            assert!((r.determinant() - 1.0).abs() < 1e-9);
            // The camera at 5 d: the origin at depth 5 on the axis.
            let t = -(r * (d * 5.0));
            let o = t;
            assert!(o.x.abs() < 1e-9 && o.y.abs() < 1e-9 && (o.z - 5.0).abs() < 1e-9);
            // A point above the origin is higher in the image (smaller y).
            let up = r * Vector3::z() + t;
            assert!(up.y / up.z < 0.0, "{az} {el}");
        }
    }

    /// Rotations about one axis from 0 to 90 degrees: two representatives
    /// are the two ends' neighbourhood, spread apart; a component without
    /// views has none.
    #[test]
    fn representative_rotations_spread_over_the_component() {
        let rs: Vec<Matrix3<f64>> = (0..=9)
            .map(|i| {
                Rotation3::from_axis_angle(&Vector3::z_axis(), (i as f64 * 10.0).to_radians())
                    .into_inner()
            })
            .collect();
        let assign = vec![0; rs.len()];
        let reps = representative_rotations(&rs, &assign, 2, 3);
        assert_eq!(reps.len(), 2);
        assert!(reps[1].is_empty());
        let angles: Vec<f64> = reps[0]
            .iter()
            .map(|q| 2.0 * q[3].atan2(q[0]).to_degrees())
            .collect();
        // The medoid (40 or 50 degrees), then the two ends.
        assert!((angles[0] - 45.0).abs() <= 5.0 + 1e-9, "{angles:?}");
        let mut ends = [angles[1], angles[2]];
        ends.sort_by(f64::total_cmp);
        assert!(
            ends[0].abs() < 1e-6 && (ends[1] - 90.0).abs() < 1e-6,
            "{angles:?}"
        );
    }

    /// Directions from two opposite caps fall into two clusters whose
    /// means point at the caps.
    #[test]
    fn clusters_split_opposite_caps() {
        let mut rng = SplitMix64::new(4);
        let mut dirs = Vec::new();
        for i in 0..40 {
            let az = if i % 2 == 0 {
                0.0
            } else {
                std::f64::consts::PI
            };
            dirs.push(direction(
                az + rng.range_f64(-0.3, 0.3),
                rng.range_f64(0.0, 0.4),
            ));
        }
        let (assign, centres) = cluster_directions(&dirs, 2);
        assert_eq!(centres.len(), 2);
        for (i, a) in assign.iter().enumerate() {
            assert_eq!(*a, assign[i % 2]);
        }
        assert_ne!(assign[0], assign[1]);
        assert!(centres[assign[0]].x > 0.9 && centres[assign[1]].x < -0.9);
    }

    /// Renders of a cube: every sample keeps its full box around its
    /// visible mask, the occluded ones hide part of the object, and the
    /// images are written.
    #[test]
    fn renders_keep_exact_boxes_and_masks() {
        let dir = std::env::temp_dir().join(format!("sdhop-mesh-{}", std::process::id()));
        let mesh = Mesh::cuboid(60.0, 40.0, 30.0);
        let bg = ColorImage::new(64, 48, vec![90.0; 64 * 48 * 3]).unwrap();
        let params = RenderParams {
            renders: 12,
            components: 3,
            size: [40.0, 80.0],
            occluded_share: 0.5,
            ..RenderParams::default()
        };
        let set = render_set(
            &mesh,
            None,
            "cube",
            &[bg],
            &params,
            &dir,
            &ProgressBar::hidden(),
        )
        .unwrap();
        assert_eq!(set.samples.len(), 12);
        assert_eq!(set.directions.len(), 3);
        for s in &set.samples {
            assert!(s.image.is_file());
            let a = s.annotation.as_ref().unwrap();
            let (x, y, w, h) = a.bbox;
            assert!(w >= 20.0 && h >= 20.0 && a.viewpoint < 3);
            let (vx0, vy0, vx1, vy1) = a.visible.tight_box().unwrap();
            assert!(vx0 as f64 >= x && vy0 as f64 >= y);
            assert!(vx1 as f64 <= x + w && vy1 as f64 <= y + h);
        }
        assert!(set.occluded.iter().any(|&f| f > 0.05), "{:?}", set.occluded);
        assert!(set.occluded.contains(&0.0));
        assert_eq!(set.rotations.len(), 3);
        for (c, qs) in set.rotations.iter().enumerate() {
            let members = set
                .samples
                .iter()
                .filter(|s| s.annotation.as_ref().unwrap().viewpoint == c)
                .count();
            assert_eq!(qs.len(), members.min(ROTATIONS_PER_COMPONENT));
            for q in qs {
                let n: f64 = q.iter().map(|v| v * v).sum();
                assert!((n - 1.0).abs() < 1e-9);
            }
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
