//! The model's edges at a pose: crease edges (dihedral angle above a
//! threshold, and open boundaries) and silhouette edges (between a face
//! towards the camera and one away from it), with hidden parts removed by a
//! depth buffer from a small software rasteriser; and the sample points
//! along the visible projected edges.

use std::collections::HashMap;

use nalgebra::{Vector2, Vector3};

use super::geometry::{Intrinsics, Pose};
use super::mesh::Mesh;

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
    edges: Vec<Edge>,
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

/// Per-pixel depth (camera z) of the nearest surface (infinity where none)
/// and the triangle seen there.
#[derive(Clone, Debug)]
pub struct DepthBuffer {
    pub width: usize,
    pub height: usize,
    pub depth: Vec<f32>,
    /// Index of the nearest triangle; `u32::MAX` where none.
    pub face: Vec<u32>,
}

/// Rasterises the triangles at `pose` at pixel centres, keeping the
/// nearest (perspective-correct depth); triangles reaching behind the
/// camera are skipped.
pub fn rasterize(
    vertices: &[Vector3<f64>],
    triangles: &[[u32; 3]],
    k: &Intrinsics,
    pose: &Pose,
    width: usize,
    height: usize,
) -> DepthBuffer {
    let mut depth = vec![f32::INFINITY; width * height];
    let mut face = vec![u32::MAX; width * height];
    let cam: Vec<Vector3<f64>> = vertices.iter().map(|v| pose.transform(v)).collect();
    for (fi, t) in triangles.iter().enumerate() {
        let p = t.map(|i| cam[i as usize]);
        if p.iter().any(|q| q.z <= 1e-6) {
            continue;
        }
        let (Some(s0), Some(s1), Some(s2)) = (k.project(&p[0]), k.project(&p[1]), k.project(&p[2]))
        else {
            continue;
        };
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
        for y in y0..=y1 {
            // Only the row's span of the triangle (thin triangles have
            // large boxes): where the row's centre line crosses its edges,
            // widened by a pixel; the barycentric test below decides.
            let yc = y as f64 + 0.5;
            let (mut xl, mut xr) = (f64::INFINITY, f64::NEG_INFINITY);
            for (a, b) in [(s[0], s[1]), (s[1], s[2]), (s[2], s[0])] {
                let (ylo, yhi) = (a.y.min(b.y), a.y.max(b.y));
                if yc < ylo || yc > yhi {
                    continue;
                }
                let x = if (b.y - a.y).abs() < 1e-12 {
                    xl = xl.min(a.x.min(b.x));
                    a.x.max(b.x)
                } else {
                    a.x + (yc - a.y) / (b.y - a.y) * (b.x - a.x)
                };
                xl = xl.min(x);
                xr = xr.max(x);
            }
            if xl > xr {
                continue;
            }
            let xs = ((xl - 1.0).floor().max(x0 as f64)) as usize;
            let xe = ((xr + 1.0).ceil().max(0.0) as usize).min(x1);
            for x in xs..=xe {
                let c = Vector2::new(x as f64 + 0.5, y as f64 + 0.5);
                let w0 = (s[1] - c).perp(&(s[2] - c)) / area;
                let w1 = (s[2] - c).perp(&(s[0] - c)) / area;
                let w2 = 1.0 - w0 - w1;
                if w0 < -1e-9 || w1 < -1e-9 || w2 < -1e-9 {
                    continue;
                }
                let z = (1.0 / (w0 * iz[0] + w1 * iz[1] + w2 * iz[2])) as f32;
                let i = y * width + x;
                if z < depth[i] {
                    depth[i] = z;
                    face[i] = fi as u32;
                }
            }
        }
    }
    DepthBuffer {
        width,
        height,
        depth,
        face,
    }
}

impl DepthBuffer {
    fn at(&self, x: isize, y: isize) -> f32 {
        if x < 0 || y < 0 || x as usize >= self.width || y as usize >= self.height {
            return f32::INFINITY;
        }
        self.depth[y as usize * self.width + x as usize]
    }

    /// Whether the pixel shows the object.
    pub fn covered(&self, x: usize, y: usize) -> bool {
        self.depth[y * self.width + x].is_finite()
    }
}

impl EdgeModel {
    /// Finds the mesh's edges; `crease_degrees` is the smallest dihedral
    /// angle of a crease.
    pub fn new(mesh: &Mesh, crease_degrees: f64) -> Self {
        let normals = mesh.face_normals();
        let mut map: HashMap<(u32, u32), Vec<u32>> = HashMap::new();
        for (fi, t) in mesh.triangles.iter().enumerate() {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                if a != b {
                    map.entry((a.min(b), a.max(b))).or_default().push(fi as u32);
                }
            }
        }
        let cos_crease = crease_degrees.to_radians().cos();
        let mut edges: Vec<Edge> = map
            .into_iter()
            .map(|((a, b), faces)| {
                let boundary = faces.len() != 2;
                let f0 = faces[0];
                let f1 = *faces.get(1).unwrap_or(&f0);
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
        Self {
            vertices: mesh.vertices.clone(),
            triangles: mesh.triangles.clone(),
            normals,
            edges,
        }
    }

    /// Depth of the mesh at `pose` (see [`rasterize`]).
    pub fn depth(&self, k: &Intrinsics, pose: &Pose, width: usize, height: usize) -> DepthBuffer {
        rasterize(&self.vertices, &self.triangles, k, pose, width, height)
    }

    /// The largest distance of a vertex from the object's origin.
    pub fn radius(&self) -> f64 {
        self.vertices.iter().map(|v| v.norm()).fold(0.0, f64::max)
    }

    /// Whether a face looks towards the camera at `pose`.
    fn front(&self, pose: &Pose, f: u32) -> bool {
        let t = self.triangles[f as usize];
        let c = pose.transform(&self.vertices[t[0] as usize]);
        let n = pose.rotation * self.normals[f as usize];
        n.dot(&c) < 0.0
    }

    /// Samples every `step` pixels along the visible projected crease and
    /// silhouette edges at `pose`, inside the image. The spacing runs on
    /// from one edge to the next, so that a dense mesh (edges shorter than
    /// `step`) gets as many samples as its outline's length asks, not one
    /// per edge.
    pub fn samples(
        &self,
        k: &Intrinsics,
        pose: &Pose,
        depth: &DepthBuffer,
        step: f64,
    ) -> Vec<EdgeSample> {
        let mut out = Vec::new();
        let (w, h) = (depth.width as f64, depth.height as f64);
        // Distance (pixels) from the start of the next edge to its first
        // sample.
        let mut next = 0.5 * step;
        for e in &self.edges {
            let use_it = if e.boundary {
                true
            } else {
                let (f0, f1) = (self.front(pose, e.faces[0]), self.front(pose, e.faces[1]));
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
            for i in 0..n {
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
                // clearly in front of the point.
                let (ix, iy) = (px.x.floor() as isize, px.y.floor() as isize);
                let mut far = 0.0f32;
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        far = far.max(depth.at(ix + dx, iy + dy));
                    }
                }
                let z = c3.z as f32;
                if z <= far + 1e-3 * z.abs() + 1e-6 {
                    out.push(EdgeSample {
                        point: p3,
                        pixel: px,
                        normal,
                    });
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

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
    fn cube_edges_hidden_behind_it_are_removed() {
        let (k, pose) = setup();
        let mesh = Mesh::cuboid(0.1, 0.1, 0.1);
        let em = EdgeModel::new(&mesh, 30.0);
        // 12 crease edges; diagonals of the faces are not creases.
        assert_eq!(em.edges.iter().filter(|e| e.crease).count(), 12);
        let depth = em.depth(&k, &pose, 320, 240);
        let samples = em.samples(&k, &pose, &depth, 2.0);
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
        let z = depth.depth[c.y as usize * 320 + c.x as usize];
        assert!(z < 0.6 && z > 0.6 - 0.0867, "{z}");
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
        let depth = em.depth(&k, &pose, 320, 240);
        let samples = em.samples(&k, &pose, &depth, 2.0);
        // Seen from the side: two long vertical silhouettes of about
        // 0.12 * 600 / 0.6 = 120 px each, plus the near halves of the rims.
        let vertical = samples.iter().filter(|s| s.normal.x.abs() > 0.99).count();
        assert!(vertical >= 100, "{vertical} samples on vertical edges");
    }
}
