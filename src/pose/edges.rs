//! The model's edges at a pose: crease edges (dihedral angle above a
//! threshold, and open boundaries) and silhouette edges (between a face
//! towards the camera and one away from it), with hidden parts removed by a
//! depth buffer from a small software rasteriser; and the sample points
//! along the visible projected edges.

use std::collections::HashMap;

use nalgebra::{Vector2, Vector3};

use super::geometry::{Intrinsics, Pose};
use super::mesh::Mesh;
use super::PoseError;
use crate::vision::Deadline;

/// Triangles (or edges) drawn between two looks at the deadline.
const DEADLINE_STRIDE: usize = 512;

/// An edge of the mesh and its one or two faces.
#[derive(Clone, Copy, Debug)]
struct Edge {
    a: u32,
    b: u32,
    faces: [u32; 2],
    /// Crease (or boundary): used at every pose where it is visible.
    crease: bool,
    boundary: bool,
}

/// The edges of a mesh, prepared once per mesh.
#[derive(Clone, Debug)]
pub struct EdgeModel {
    vertices: Vec<Vector3<f64>>,
    triangles: Vec<[u32; 3]>,
    normals: Vec<Vector3<f64>>,
    /// Each face's `normal . vertex` (any of its vertices): its plane's
    /// offset, for [`EdgeModel::facing`].
    offsets: Vec<f64>,
    edges: Vec<Edge>,
    corners: [Vector3<f64>; 8],
    /// The largest distance of a vertex from the object's origin.
    radius: f64,
    /// Closed, consistently wound and facing outwards (positive volume):
    /// then a face turned away from the camera is never seen, and the
    /// rasteriser skips it.
    solid: bool,
}

/// A point on a visible model edge and where it projects.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EdgeSample {
    /// The point in object coordinates.
    pub point: Vector3<f64>,
    /// Its pixel at the pose.
    pub pixel: Vector2<f64>,
    /// Unit normal of the projected edge in the image.
    pub normal: Vector2<f64>,
}

/// The widest (pixels) that a mesh's bounding sphere is drawn in the
/// depth buffers of [`EdgeModel::depth`]: a larger object's buffers have
/// cells of several pixels.
pub const DEPTH_MAX_PX: f64 = 100.0;

/// Per-pixel depth (camera z) of the nearest surface (infinity where none)
/// and the triangle seen there, stored over the window of the image that
/// the mesh's projection can reach (the rest is empty): filling a whole
/// image's buffers cost more than drawing a small object.
#[derive(Clone, Debug)]
pub struct DepthBuffer {
    /// The image's size.
    pub width: usize,
    pub height: usize,
    /// Image pixels per cell of the buffers, each way (1: a cell a
    /// pixel): a large object's buffers are coarser (see
    /// [`DEPTH_MAX_PX`]).
    scale: f64,
    /// The window: left, top, width, height, in cells.
    window: (usize, usize, usize, usize),
    /// Inverse depth, 0 where no surface: the nearest surface is the
    /// largest, and no pixel pays a division.
    inv_depth: Vec<f32>,
    /// Index of the nearest triangle; `u32::MAX` where none.
    face: Vec<u32>,
}

/// Rasterises the triangles at `pose` at pixel centres, keeping the
/// nearest (perspective-correct depth); triangles reaching behind the
/// camera are skipped.
///
/// With `cull_back`, triangles facing away from the camera are skipped:
/// right only for a closed mesh wound outwards (see [`EdgeModel::solid`]).
/// Gives up once `deadline` has passed.
#[allow(clippy::too_many_arguments)]
pub fn rasterize(
    vertices: &[Vector3<f64>],
    triangles: &[[u32; 3]],
    k: &Intrinsics,
    pose: &Pose,
    width: usize,
    height: usize,
    cull_back: bool,
    deadline: &Deadline,
) -> Result<DepthBuffer, PoseError> {
    let cull = if cull_back { Cull::Winding } else { Cull::None };
    rasterize_culled(
        vertices,
        triangles,
        k,
        pose,
        (width, height, 1.0),
        cull,
        deadline,
    )
}

/// Which triangles [`rasterize_culled`] skips.
enum Cull<'a> {
    None,
    /// Those whose winding faces away from the camera.
    Winding,
    /// Those not marked (the faces towards the camera, computed before).
    Facing(&'a [bool]),
}

/// [`rasterize`], skipping the triangles `cull` says. `image`: the
/// image's width and height and the image pixels per cell of the buffers
/// (at least 1): the triangles are drawn at the cells' centres, a camera
/// whose pixels are that much larger.
fn rasterize_culled(
    vertices: &[Vector3<f64>],
    triangles: &[[u32; 3]],
    k: &Intrinsics,
    pose: &Pose,
    image: (usize, usize, f64),
    cull: Cull<'_>,
    deadline: &Deadline,
) -> Result<DepthBuffer, PoseError> {
    let (image_width, image_height, scale) = (image.0, image.1, image.2.max(1.0));
    let (width, height, k) = if scale > 1.0 {
        (
            (image_width as f64 / scale).ceil() as usize,
            (image_height as f64 / scale).ceil() as usize,
            // A cell covers image pixels [c s, (c + 1) s).
            &Intrinsics {
                fx: k.fx / scale,
                fy: k.fy / scale,
                cx: k.cx / scale,
                cy: k.cy / scale,
            },
        )
    } else {
        (image_width, image_height, k)
    };
    let cam: Vec<Vector3<f64>> = vertices.iter().map(|v| pose.transform(v)).collect();
    // Each vertex projected once (the image of one in front of the camera;
    // only triangles wholly in front are drawn).
    let proj: Vec<Option<Vector2<f64>>> = cam
        .iter()
        .map(|q| if q.z > 1e-6 { k.project(q) } else { None })
        .collect();
    // The window: the projections within the image.
    let (mut lo, mut hi) = (
        Vector2::new(f64::INFINITY, f64::INFINITY),
        Vector2::new(f64::NEG_INFINITY, f64::NEG_INFINITY),
    );
    for s in proj.iter().flatten() {
        lo = lo.inf(s);
        hi = hi.sup(s);
    }
    let wx0 = lo.x.floor().clamp(0.0, width as f64) as usize;
    let wy0 = lo.y.floor().clamp(0.0, height as f64) as usize;
    let wx1 = (hi.x.ceil() + 1.0).clamp(0.0, width as f64) as usize;
    let wy1 = (hi.y.ceil() + 1.0).clamp(0.0, height as f64) as usize;
    let (ww, wh) = (wx1.saturating_sub(wx0), wy1.saturating_sub(wy0));
    let mut inv_depth = vec![0.0f32; ww * wh];
    let mut face = vec![u32::MAX; ww * wh];
    for (fi, t) in triangles.iter().enumerate() {
        if fi % DEADLINE_STRIDE == 0 && deadline.passed() {
            return Err(PoseError::DeadlineExceeded);
        }
        if let Cull::Facing(front) = cull {
            if !front[fi] {
                continue;
            }
        }
        let (Some(s0), Some(s1), Some(s2)) = (
            proj[t[0] as usize],
            proj[t[1] as usize],
            proj[t[2] as usize],
        ) else {
            continue;
        };
        let p = t.map(|i| cam[i as usize]);
        if matches!(cull, Cull::Winding) && (p[1] - p[0]).cross(&(p[2] - p[0])).dot(&p[0]) >= 0.0 {
            continue;
        }
        let s = [s0, s1, s2];
        let area = (s[1] - s[0]).perp(&(s[2] - s[0]));
        if area.abs() < 1e-12 {
            continue;
        }
        let lo = |f: fn(&Vector2<f64>) -> f64| s.iter().map(f).fold(f64::INFINITY, f64::min);
        let hi = |f: fn(&Vector2<f64>) -> f64| s.iter().map(f).fold(f64::NEG_INFINITY, f64::max);
        let (x0, x1) = (lo(|v| v.x).floor().max(0.0), hi(|v| v.x).ceil());
        let (y0, y1) = (lo(|v| v.y).floor().max(0.0), hi(|v| v.y).ceil());
        if x1 < 0.0 || y1 < 0.0 || x0 >= width as f64 || y0 >= height as f64 {
            continue;
        }
        let (x0, y0) = (x0 as usize, y0 as usize);
        let x1 = (x1 as usize).min(width.saturating_sub(1));
        let y1 = (y1 as usize).min(height.saturating_sub(1));
        let iz = [1.0 / p[0].z, 1.0 / p[1].z, 1.0 / p[2].z];
        // Barycentric weights are affine in the pixel centre: w_i(x, y) =
        // (s_j - c) x (s_k - c) / area = a_i + b_i x + c_i y.
        let affine = |j: usize, l: usize| {
            let (sj, sl) = (s[j], s[l]);
            (
                sj.perp(&sl) / area,
                (sj.y - sl.y) / area,
                (sl.x - sj.x) / area,
            )
        };
        let (e0, e1) = (affine(1, 2), affine(2, 0));
        // The weights' coefficients in x and, per row, their constants.
        let bx = [e0.1, e1.1, -e0.1 - e1.1];
        // Inverse depth is affine too: sum of w_i / z_i.
        let ibx = bx[0] * iz[0] + bx[1] * iz[1] + bx[2] * iz[2];
        let inv_bx = bx.map(|b| if b != 0.0 { 1.0 / b } else { 0.0 });
        for y in y0..=y1 {
            let yc = y as f64 + 0.5;
            let r = [e0.0 + e0.2 * yc, e1.0 + e1.2 * yc];
            let r = [r[0], r[1], 1.0 - r[0] - r[1]];
            // The pixel centres xc = x + 0.5 of the row with every weight
            // at least -1e-9: an interval, from each affine weight.
            let (mut lo, mut hi) = (x0 as f64 + 0.5, x1 as f64 + 0.5);
            for i in 0..3 {
                let bound = (-1e-9 - r[i]) * inv_bx[i];
                if bx[i] > 0.0 {
                    lo = lo.max(bound);
                } else if bx[i] < 0.0 {
                    hi = hi.min(bound);
                } else if r[i] < -1e-9 {
                    hi = f64::NEG_INFINITY;
                }
            }
            if lo.is_nan() || hi.is_nan() || lo > hi {
                continue;
            }
            // lo - 0.5 and hi - 0.5 lie in [x0, x1], so not negative:
            // truncation floors (std's floor and ceil are calls here).
            let (a, b) = (lo - 0.5, hi - 0.5);
            let xs = a as usize + usize::from((a as usize as f64) < a);
            let xe = b as usize;
            if xe < xs {
                continue;
            }
            let ir = r[0] * iz[0] + r[1] * iz[1] + r[2] * iz[2];
            // Inside the window: the triangle's box lies within it.
            let row = (y - wy0) * ww;
            let span = row + xs - wx0..=row + xe - wx0;
            let mut inv = ir + ibx * (xs as f64 + 0.5);
            for (d, f) in inv_depth[span.clone()].iter_mut().zip(&mut face[span]) {
                let v = inv as f32;
                if v > *d {
                    *d = v;
                    *f = fi as u32;
                }
                inv += ibx;
            }
        }
    }
    Ok(DepthBuffer {
        width: image_width,
        height: image_height,
        scale,
        window: (wx0, wy0, ww, wh),
        inv_depth,
        face,
    })
}

impl DepthBuffer {
    /// Index into the window's buffers of an image pixel, if in it.
    fn index(&self, x: isize, y: isize) -> Option<usize> {
        let (x, y) = if self.scale > 1.0 {
            // The cell of the pixel's centre.
            (
                ((x as f64 + 0.5) / self.scale).floor() as isize,
                ((y as f64 + 0.5) / self.scale).floor() as isize,
            )
        } else {
            (x, y)
        };
        let (x0, y0, w, h) = self.window;
        let (dx, dy) = (x - x0 as isize, y - y0 as isize);
        (dx >= 0 && dy >= 0 && (dx as usize) < w && (dy as usize) < h)
            .then(|| dy as usize * w + dx as usize)
    }

    /// Depth at an image pixel (infinity where no surface or outside).
    pub fn at(&self, x: isize, y: isize) -> f32 {
        self.index(x, y)
            .map(|i| self.inv_depth[i])
            .filter(|&v| v > 0.0)
            .map_or(f32::INFINITY, |v| 1.0 / v)
    }

    /// The triangle seen at an image pixel, if any.
    pub fn face_at(&self, x: usize, y: usize) -> Option<u32> {
        let i = self.index(x as isize, y as isize)?;
        (self.face[i] != u32::MAX).then_some(self.face[i])
    }

    /// Image pixels per cell of the buffers, each way.
    pub fn cell_px(&self) -> f64 {
        self.scale
    }

    /// Whether the pixel shows the object.
    pub fn covered(&self, x: usize, y: usize) -> bool {
        self.at(x as isize, y as isize).is_finite()
    }
}

impl EdgeModel {
    /// Finds the mesh's edges; `crease_degrees` is the smallest dihedral
    /// angle of a crease.
    pub fn new(mesh: &Mesh, crease_degrees: f64) -> Self {
        let normals = mesh.face_normals();
        // Per undirected edge, its triangles and whether each runs along
        // it from the lower vertex index to the higher.
        let mut map: HashMap<(u32, u32), Vec<(u32, bool)>> = HashMap::new();
        let mut degenerate = false;
        for (fi, t) in mesh.triangles.iter().enumerate() {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                if a != b {
                    map.entry((a.min(b), a.max(b)))
                        .or_default()
                        .push((fi as u32, a < b));
                } else {
                    degenerate = true;
                }
            }
        }
        // Solid: every edge joins two triangles running along it in
        // opposite directions (closed, consistently wound) and the volume
        // is positive (wound outwards).
        let volume: f64 = mesh
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
                a.dot(&b.cross(&c))
            })
            .sum();
        let solid =
            !degenerate && volume > 0.0 && map.values().all(|f| f.len() == 2 && f[0].1 != f[1].1);
        let cos_crease = crease_degrees.to_radians().cos();
        let mut edges: Vec<Edge> = map
            .into_iter()
            .map(|((a, b), faces)| {
                let boundary = faces.len() != 2;
                let f0 = faces[0].0;
                let f1 = faces.get(1).map_or(f0, |f| f.0);
                let crease =
                    boundary || normals[f0 as usize].dot(&normals[f1 as usize]) < cos_crease;
                Edge {
                    a,
                    b,
                    faces: [f0, f1],
                    crease,
                    boundary,
                }
            })
            .collect();
        edges.sort_by_key(|e| (e.a, e.b));
        let (lo, hi) = mesh.bounds();
        let corners = std::array::from_fn(|i| {
            Vector3::new(
                if i & 1 == 0 { lo.x } else { hi.x },
                if i & 2 == 0 { lo.y } else { hi.y },
                if i & 4 == 0 { lo.z } else { hi.z },
            )
        });
        Self {
            solid,
            corners,
            radius: mesh.vertices.iter().map(|v| v.norm()).fold(0.0, f64::max),
            vertices: mesh.vertices.clone(),
            triangles: mesh.triangles.clone(),
            offsets: normals
                .iter()
                .zip(&mesh.triangles)
                .map(|(n, t)| n.dot(&mesh.vertices[t[0] as usize]))
                .collect(),
            normals,
            edges,
        }
    }

    /// Depth of the mesh at `pose` (see [`rasterize`]); a large object's
    /// in cells of several pixels (see [`DEPTH_MAX_PX`]).
    pub fn depth(
        &self,
        k: &Intrinsics,
        pose: &Pose,
        width: usize,
        height: usize,
        deadline: &Deadline,
    ) -> Result<DepthBuffer, PoseError> {
        // A large object's buffers are coarser: the visibility of its
        // edges needs no finer cells, and time no longer grows with its
        // size in the image.
        let z = pose.translation.norm();
        let diameter = 2.0 * k.fx.max(k.fy) * self.radius / z.max(1e-12);
        let scale = (diameter / DEPTH_MAX_PX).max(1.0);
        self.depth_scaled(k, pose, (width, height, scale), deadline)
    }

    /// [`Self::depth`] in cells of a pixel, whatever the object's size.
    pub fn depth_in_pixels(
        &self,
        k: &Intrinsics,
        pose: &Pose,
        width: usize,
        height: usize,
        deadline: &Deadline,
    ) -> Result<DepthBuffer, PoseError> {
        self.depth_scaled(k, pose, (width, height, 1.0), deadline)
    }

    fn depth_scaled(
        &self,
        k: &Intrinsics,
        pose: &Pose,
        image: (usize, usize, f64),
        deadline: &Deadline,
    ) -> Result<DepthBuffer, PoseError> {
        let front;
        let cull = if self.solid {
            front = self.facing(pose);
            Cull::Facing(&front)
        } else {
            Cull::None
        };
        rasterize_culled(
            &self.vertices,
            &self.triangles,
            k,
            pose,
            image,
            cull,
            deadline,
        )
    }

    /// Whether the mesh bounds a solid seen from outside: closed, wound
    /// consistently and outwards (the depth buffer then skips back faces).
    pub fn solid(&self) -> bool {
        self.solid
    }

    /// The 8 corners of the vertices' axis-aligned box (object
    /// coordinates).
    pub fn box_corners(&self) -> &[Vector3<f64>; 8] {
        &self.corners
    }

    /// The largest distance of a vertex from the object's origin.
    pub fn radius(&self) -> f64 {
        self.radius
    }

    /// Whether each face looks towards the camera at `pose`: its normal
    /// points away from the camera's centre `o` in the object's frame,
    /// `n . (v - o) < 0` for a vertex `v` of the face (the same as the
    /// camera frame's `(R n) . (R v + t) < 0`, at a dot product a face).
    fn facing(&self, pose: &Pose) -> Vec<bool> {
        let o = -(pose.rotation.transpose() * pose.translation);
        self.normals
            .iter()
            .zip(&self.offsets)
            .map(|(n, &d)| d < n.dot(&o))
            .collect()
    }

    /// Samples every `step` pixels along the visible projected crease and
    /// silhouette edges at `pose`, inside the image. The spacing runs on
    /// from one edge to the next, so that a dense mesh (edges shorter than
    /// `step`) gets as many samples as its outline's length asks, not one
    /// per edge. Only the part of each projected edge inside the image is
    /// walked, so the work is bounded by the image whatever the
    /// projection; gives up once `deadline` has passed.
    pub fn samples(
        &self,
        k: &Intrinsics,
        pose: &Pose,
        depth: &DepthBuffer,
        step: f64,
        deadline: &Deadline,
    ) -> Result<Vec<EdgeSample>, PoseError> {
        let mut out = Vec::new();
        let (w, h) = (depth.width as f64, depth.height as f64);
        let front = self.facing(pose);
        // How much (a share of the depth) a face inclined by up to 70
        // degrees moves in depth over the depth buffers' cells beyond a
        // pixel.
        let cell_slope = ((depth.scale - 1.0) * 70f64.to_radians().tan() / k.fx.min(k.fy)) as f32;
        // Distance (pixels) from the start of the next edge to its first
        // sample.
        let mut next = 0.5 * step;
        for (ei, e) in self.edges.iter().enumerate() {
            if ei % DEADLINE_STRIDE == 0 && deadline.passed() {
                return Err(PoseError::DeadlineExceeded);
            }
            let use_it = if e.boundary {
                true
            } else {
                let (f0, f1) = (front[e.faces[0] as usize], front[e.faces[1] as usize]);
                // Silhouettes, and creases on the visible side.
                f0 != f1 || (e.crease && f0)
            };
            if !use_it {
                continue;
            }
            let (a, b) = (self.vertices[e.a as usize], self.vertices[e.b as usize]);
            let (ca, cb) = (pose.transform(&a), pose.transform(&b));
            let (Some(pa), Some(pb)) = (k.project(&ca), k.project(&cb)) else {
                continue;
            };
            let d = pb - pa;
            let len = d.norm();
            if len < 1e-9 {
                continue;
            }
            let normal = Vector2::new(-d.y, d.x) / len;
            let first = next;
            let n = if first < len {
                ((len - first) / step).floor() as usize + 1
            } else {
                0
            };
            next = first + n as f64 * step - len;
            // The samples whose 2-D point lies in the image (a pixel of
            // margin): the rest were dropped below anyway.
            let Some((c0, c1)) = clip_to_box(pa, d, w, h) else {
                continue;
            };
            let i0 = ((c0 * len - first) / step).ceil().max(0.0);
            let i1 = ((c1 * len - first) / step).floor().min(n as f64 - 1.0);
            if i0.is_nan() || i1.is_nan() || i0 > i1 {
                continue;
            }
            for i in i0 as usize..=i1 as usize {
                // Parameter along the 3-D edge whose projection is the
                // 2-D point at fraction f (projection is not linear).
                let f = (first + i as f64 * step) / len;
                let s = f * ca.z / (f * ca.z + (1.0 - f) * cb.z);
                let p3 = a + (b - a) * s;
                let c3 = pose.transform(&p3);
                let Some(px) = k.project(&c3) else { continue };
                if px.x < 0.0 || px.y < 0.0 || px.x >= w || px.y >= h {
                    continue;
                }
                // Visible when no surface in the pixel's neighbourhood is
                // clearly in front of the point (in coarser buffers, by
                // more than a steep face's depth changes over a cell).
                let (ix, iy) = (px.x.floor() as isize, px.y.floor() as isize);
                let mut far = 0.0f32;
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        far = far.max(depth.at(ix + dx, iy + dy));
                    }
                }
                let z = c3.z as f32;
                if z <= far + (1e-3 + cell_slope) * z.abs() + 1e-6 {
                    out.push(EdgeSample {
                        point: p3,
                        pixel: px,
                        normal,
                    });
                }
            }
        }
        Ok(out)
    }
}

/// The parameter interval `[t0, t1]` within `[0, 1]` of the segment
/// `a + t d` that lies in the box `[-1, w + 1] x [-1, h + 1]` (Liang-Barsky);
/// `None` when it misses the box.
fn clip_to_box(a: Vector2<f64>, d: Vector2<f64>, w: f64, h: f64) -> Option<(f64, f64)> {
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [
        (-d.x, a.x + 1.0),
        (d.x, w + 1.0 - a.x),
        (-d.y, a.y + 1.0),
        (d.y, h + 1.0 - a.y),
    ] {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else {
            let r = q / p;
            if p < 0.0 {
                t0 = t0.max(r);
            } else {
                t1 = t1.min(r);
            }
        }
    }
    (t0 <= t1).then_some((t0, t1))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::rng::SplitMix64;
    use nalgebra::Rotation3;

    /// The nearest depth at a pixel centre by testing every triangle, and
    /// the smallest barycentric weight's distance from 0 among the
    /// triangles (near 0: on an edge, where rounding may decide).
    fn brute_depth(mesh: &Mesh, k: &Intrinsics, pose: &Pose, x: usize, y: usize) -> (f32, f64) {
        let c = Vector2::new(x as f64 + 0.5, y as f64 + 0.5);
        let (mut best, mut edge) = (f32::INFINITY, f64::INFINITY);
        for t in &mesh.triangles {
            let p = t.map(|i| pose.transform(&mesh.vertices[i as usize]));
            if p.iter().any(|q| q.z <= 1e-6) {
                continue;
            }
            let s = p.map(|q| k.project(&q).expect("in front"));
            let area = (s[1] - s[0]).perp(&(s[2] - s[0]));
            if area.abs() < 1e-12 {
                continue;
            }
            let w0 = (s[1] - c).perp(&(s[2] - c)) / area;
            let w1 = (s[2] - c).perp(&(s[0] - c)) / area;
            let w = [w0, w1, 1.0 - w0 - w1];
            edge = edge.min(w.iter().map(|v| v.abs()).fold(f64::INFINITY, f64::min));
            if w.iter().all(|&v| v >= -1e-9) {
                let z = 1.0 / (w[0] / p[0].z + w[1] / p[1].z + w[2] / p[2].z);
                best = best.min(z as f32);
            }
        }
        (best, edge)
    }

    #[test]
    fn solids_are_closed_consistent_and_wound_outwards() {
        let is_solid = |m: &Mesh| EdgeModel::new(m, 30.0).solid();
        let cube = Mesh::cuboid(0.1, 0.1, 0.1);
        assert!(is_solid(&cube));
        assert!(is_solid(&Mesh::rounded_box(0.1, 0.06, 0.16, 0.025, 4)));
        let mut flipped = cube.clone();
        flipped.triangles[3].swap(0, 1);
        assert!(!is_solid(&flipped));
        let mut inside_out = cube.clone();
        for t in &mut inside_out.triangles {
            t.swap(0, 1);
        }
        assert!(!is_solid(&inside_out));
        let mut open = cube;
        open.triangles.pop();
        assert!(!is_solid(&open));
    }

    #[test]
    fn rasterizer_matches_a_per_pixel_test_of_every_triangle() {
        let k = Intrinsics {
            fx: 150.0,
            fy: 150.0,
            cx: 40.0,
            cy: 30.0,
        };
        let mut rng = SplitMix64::new(11);
        let meshes = [
            Mesh::cuboid(0.15, 0.1, 0.07),
            Mesh::cylinder(0.05, 0.12, 12),
            Mesh::rounded_box(0.1, 0.06, 0.16, 0.025, 3),
        ];
        for mesh in &meshes {
            for _ in 0..6 {
                let pose = Pose {
                    rotation: Rotation3::from_euler_angles(
                        rng.range_f64(-3.0, 3.0),
                        rng.range_f64(-3.0, 3.0),
                        rng.range_f64(-3.0, 3.0),
                    )
                    .into_inner(),
                    // Some poses reach past the image's border.
                    translation: Vector3::new(
                        rng.range_f64(-0.1, 0.1),
                        rng.range_f64(-0.08, 0.08),
                        rng.range_f64(0.25, 0.5),
                    ),
                };
                assert!(EdgeModel::new(mesh, 30.0).solid());
                // Culling the back faces of a solid changes nothing.
                let cull = rng.next_f64() < 0.5;
                let d = rasterize(
                    &mesh.vertices,
                    &mesh.triangles,
                    &k,
                    &pose,
                    80,
                    60,
                    cull,
                    &Deadline::NONE,
                )
                .unwrap();
                let mut covered = 0;
                for y in 0..60 {
                    for x in 0..80 {
                        let (want, edge) = brute_depth(mesh, &k, &pose, x, y);
                        let got = d.at(x as isize, y as isize);
                        if edge < 1e-6 {
                            continue;
                        }
                        covered += usize::from(want.is_finite());
                        assert_eq!(got.is_finite(), want.is_finite(), "({x}, {y})");
                        if want.is_finite() {
                            assert!((got - want).abs() <= 1e-5 * want, "({x}, {y}) {got} {want}");
                            assert!(d.face_at(x, y).is_some());
                        }
                    }
                }
                assert!(covered > 0);
            }
        }
    }

    fn setup() -> (Intrinsics, Pose) {
        let k = Intrinsics {
            fx: 600.0,
            fy: 600.0,
            cx: 160.0,
            cy: 120.0,
        };
        let pose = Pose {
            rotation: Rotation3::from_euler_angles(0.5, 0.4, 0.3).into_inner(),
            translation: Vector3::new(0.0, 0.0, 0.6),
        };
        (k, pose)
    }

    #[test]
    fn a_huge_projection_is_sampled_only_inside_the_image() {
        let (mut k, pose) = setup();
        let em = EdgeModel::new(&Mesh::cuboid(0.1, 0.1, 0.1), 30.0);
        // With a focal length of 1e9 the edges project to ~1e8 pixels:
        // walked whole, that is ~1e8 steps per edge.
        k.fx = 1e9;
        k.fy = 1e9;
        let depth = em.depth(&k, &pose, 320, 240, &Deadline::NONE).unwrap();
        let t = std::time::Instant::now();
        let samples = em.samples(&k, &pose, &depth, 2.0, &Deadline::NONE).unwrap();
        assert!(t.elapsed().as_secs_f64() < 1.0, "{:?}", t.elapsed());
        // At most every edge across the image's diagonal.
        assert!(samples.len() <= 12 * 400 / 2, "{}", samples.len());
        for s in &samples {
            assert!(s.pixel.x >= 0.0 && s.pixel.x < 320.0);
            assert!(s.pixel.y >= 0.0 && s.pixel.y < 240.0);
        }
        // A deadline that has passed stops the sampler and the rasteriser.
        let past = Deadline::at(std::time::Instant::now());
        assert_eq!(
            em.samples(&k, &pose, &depth, 2.0, &past).unwrap_err(),
            PoseError::DeadlineExceeded
        );
        assert!(matches!(
            em.depth(&k, &pose, 320, 240, &past),
            Err(PoseError::DeadlineExceeded)
        ));
    }

    #[test]
    fn clipping_keeps_the_part_of_a_segment_in_the_box() {
        let a = Vector2::new(-100.0, 50.0);
        let d = Vector2::new(300.0, 0.0);
        let (t0, t1) = clip_to_box(a, d, 100.0, 100.0).unwrap();
        assert!((a.x + t0 * d.x + 1.0).abs() < 1e-9);
        assert!((a.x + t1 * d.x - 101.0).abs() < 1e-9);
        assert_eq!(clip_to_box(a, Vector2::new(0.0, 10.0), 100.0, 100.0), None);
        assert_eq!(
            clip_to_box(Vector2::new(5.0, 5.0), Vector2::new(1.0, 1.0), 100.0, 100.0),
            Some((0.0, 1.0))
        );
    }

    #[test]
    fn cube_edges_hidden_behind_it_are_removed() {
        let (k, pose) = setup();
        let mesh = Mesh::cuboid(0.1, 0.1, 0.1);
        let em = EdgeModel::new(&mesh, 30.0);
        // 12 crease edges; diagonals of the faces are not creases.
        assert_eq!(em.edges.iter().filter(|e| e.crease).count(), 12);
        let depth = em.depth(&k, &pose, 320, 240, &Deadline::NONE).unwrap();
        let samples = em.samples(&k, &pose, &depth, 2.0, &Deadline::NONE).unwrap();
        // A cube seen in general position shows 9 of its 12 edges: no
        // sample lies on the 3 edges at the hidden corner.
        let hidden_corner = (0..8)
            .map(|i| {
                let h = 0.05;
                Vector3::new(
                    if i & 1 == 0 { -h } else { h },
                    if i & 2 == 0 { -h } else { h },
                    if i & 4 == 0 { -h } else { h },
                )
            })
            .max_by(|a, b| pose.transform(a).z.total_cmp(&pose.transform(b).z))
            .unwrap();
        for s in &samples {
            // A point on an edge through the hidden corner has two
            // coordinates equal to the corner's.
            let same = (0..3)
                .filter(|&i| (s.point[i] - hidden_corner[i]).abs() < 1e-9)
                .count();
            assert!(same < 2, "sample {:?} lies on a hidden edge", s.point);
        }
        assert!(samples.len() > 50);
        // Depth is the nearest surface: the cube's centre is behind it.
        let c = k.project(&pose.translation).unwrap();
        let z = depth.at(c.x as isize, c.y as isize);
        assert!(z < 0.6 && z > 0.6 - 0.0867, "{z}");
    }

    #[test]
    fn a_large_object_is_drawn_in_coarser_cells_with_the_same_visible_edges() {
        // A 0.2 m cube at 0.6 m, 640x480 at 1200 px focal length: its
        // bounding sphere is ~690 px wide, so cells of ~6.9 pixels.
        let (_, pose) = setup();
        let k = Intrinsics {
            fx: 1200.0,
            fy: 1200.0,
            cx: 320.0,
            cy: 240.0,
        };
        let mesh = Mesh::cuboid(0.2, 0.2, 0.2);
        let em = EdgeModel::new(&mesh, 30.0);
        let coarse = em.depth(&k, &pose, 640, 480, &Deadline::NONE).unwrap();
        assert!(coarse.scale > 6.0, "{}", coarse.scale);
        let fine = rasterize(
            &mesh.vertices,
            &mesh.triangles,
            &k,
            &pose,
            640,
            480,
            true,
            &Deadline::NONE,
        )
        .unwrap();
        assert_eq!(fine.scale, 1.0);
        // The same pixels covered, except within a cell of the outline.
        let (mut differ, mut covered) = (0, 0);
        for y in 0..480 {
            for x in 0..640 {
                covered += usize::from(fine.covered(x, y));
                differ += usize::from(fine.covered(x, y) != coarse.covered(x, y));
            }
        }
        assert!(
            covered > 50_000 && differ * 10 < covered,
            "{differ} of {covered}"
        );
        // The depth inside: within the cube's depth change over a cell.
        let c = k.project(&pose.translation).unwrap();
        let (zf, zc) = (
            fine.at(c.x as isize, c.y as isize),
            coarse.at(c.x as isize, c.y as isize),
        );
        assert!((zf - zc).abs() < 0.01, "{zf} {zc}");
        // The same visible edges: the same samples, but for a few at the
        // corners where the hidden edges meet the outline.
        let a = em.samples(&k, &pose, &fine, 2.0, &Deadline::NONE).unwrap();
        let b = em
            .samples(&k, &pose, &coarse, 2.0, &Deadline::NONE)
            .unwrap();
        let missing = a.iter().filter(|s| !b.contains(s)).count();
        let extra = b.iter().filter(|s| !a.contains(s)).count();
        assert!(a.len() > 500, "{}", a.len());
        assert!(
            missing + extra <= a.len() / 50,
            "{missing} missing, {extra} extra of {}",
            a.len()
        );
    }

    #[test]
    fn cylinder_outline_is_silhouette_edges() {
        let (k, _) = setup();
        let pose = Pose {
            rotation: Rotation3::from_euler_angles(std::f64::consts::FRAC_PI_2, 0.0, 0.0)
                .into_inner(),
            translation: Vector3::new(0.0, 0.0, 0.6),
        };
        let mesh = Mesh::cylinder(0.04, 0.12, 48);
        let em = EdgeModel::new(&mesh, 30.0);
        let depth = em.depth(&k, &pose, 320, 240, &Deadline::NONE).unwrap();
        let samples = em.samples(&k, &pose, &depth, 2.0, &Deadline::NONE).unwrap();
        // Seen from the side: two long vertical silhouettes of about
        // 0.12 * 600 / 0.6 = 120 px each, plus the near halves of the rims.
        let vertical = samples.iter().filter(|s| s.normal.x.abs() > 0.99).count();
        assert!(vertical >= 100, "{vertical} samples on vertical edges");
    }
}
