//! Triangle meshes: their limits and validation, writers for tests, and
//! the generated meshes of the pose benchmark (a box and a rounded
//! cylinder). Reading a file is [`super::mesh_file`].

use std::collections::HashSet;

use nalgebra::Vector3;
use serde::Serialize;

use super::PoseError;

/// Most vertices or triangles a mesh read by the offline tools may have.
pub const MAX_MESH_ELEMENTS: usize = 5_000_000;

/// How large a mesh may be: checked against the counts a file declares
/// before anything is allocated for them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MeshLimits {
    pub max_vertices: usize,
    pub max_triangles: usize,
}

impl MeshLimits {
    /// The offline tools' limits ([`MAX_MESH_ELEMENTS`] of each).
    pub const OFFLINE: MeshLimits = MeshLimits {
        max_vertices: MAX_MESH_ELEMENTS,
        max_triangles: MAX_MESH_ELEMENTS,
    };
}

/// A triangle has no area when twice its area is at most this share of
/// its longest side squared (the sine of its smallest angle, about).
const EMPTY_AREA: f64 = 1e-10;

/// The triangles of a mesh file left out as it was read
/// ([`Mesh::drop_empty_faces`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct DroppedFaces {
    /// Repeating a vertex, or without area.
    pub degenerate: usize,
    /// Repeating an earlier triangle.
    pub duplicate: usize,
}

impl DroppedFaces {
    pub fn total(&self) -> usize {
        self.degenerate + self.duplicate
    }
}

/// A triangle mesh in the client's units.
#[derive(Clone, Debug, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<Vector3<f64>>,
    pub triangles: Vec<[u32; 3]>,
    /// The vertices' colours (0-255), one per vertex, where the file has
    /// them (PLY `red`, `green`, `blue`).
    pub colours: Option<Vec<[f32; 3]>>,
}

fn bad(msg: impl Into<String>) -> PoseError {
    PoseError::InvalidMesh(msg.into())
}

impl Mesh {
    /// Checks the mesh: some triangles, finite coordinates, valid indices,
    /// within `limits`.
    pub fn validate_within(&self, limits: &MeshLimits) -> Result<(), PoseError> {
        if self.vertices.len() > limits.max_vertices || self.triangles.len() > limits.max_triangles
        {
            return Err(PoseError::MeshTooLarge {
                vertices: self.vertices.len(),
                triangles: self.triangles.len(),
                max_vertices: limits.max_vertices,
                max_triangles: limits.max_triangles,
            });
        }
        if self.triangles.is_empty() {
            return Err(bad("the mesh has no triangles"));
        }
        if let Some(c) = &self.colours {
            if c.len() != self.vertices.len() {
                return Err(bad(format!(
                    "{} vertex colours for {} vertices",
                    c.len(),
                    self.vertices.len()
                )));
            }
        }
        if let Some(i) = self
            .vertices
            .iter()
            .position(|v| !v.iter().all(|c| c.is_finite()))
        {
            return Err(bad(format!("vertex {i} has a non-finite coordinate")));
        }
        let n = self.vertices.len();
        if let Some(t) = self
            .triangles
            .iter()
            .position(|t| t.iter().any(|&i| i as usize >= n))
        {
            return Err(bad(format!(
                "triangle {t} refers to a vertex beyond the {n} there are"
            )));
        }
        Ok(())
    }

    /// Leaves out the triangles that carry no surface: those that repeat
    /// a vertex or whose corners are collinear (no area), and repeats of
    /// an earlier triangle (the same three vertices in any order or
    /// winding: the first is kept). Their edges would otherwise be taken
    /// for creases or boundaries of the outline. Expects valid indices
    /// ([`Self::validate_within`]).
    pub fn drop_empty_faces(&mut self) -> DroppedFaces {
        let mut dropped = DroppedFaces::default();
        let mut seen: HashSet<[u32; 3]> = HashSet::with_capacity(self.triangles.len());
        let vertices = &self.vertices;
        self.triangles.retain(|t| {
            let [a, b, c] = t.map(|i| vertices[i as usize]);
            let (u, v) = (b - a, c - a);
            let longest = u
                .norm_squared()
                .max(v.norm_squared())
                .max((c - b).norm_squared());
            if t[0] == t[1]
                || t[1] == t[2]
                || t[0] == t[2]
                || u.cross(&v).norm() <= EMPTY_AREA * longest
            {
                dropped.degenerate += 1;
                return false;
            }
            let mut key = *t;
            key.sort_unstable();
            if !seen.insert(key) {
                dropped.duplicate += 1;
                return false;
            }
            true
        });
        dropped
    }

    /// [`Self::validate_within`] the offline tools' limits.
    pub fn validate(&self) -> Result<(), PoseError> {
        self.validate_within(&MeshLimits::OFFLINE)
    }

    /// The mesh as OBJ text.
    pub fn to_obj(&self) -> String {
        let mut s = String::new();
        for v in &self.vertices {
            s.push_str(&format!("v {} {} {}\n", v.x, v.y, v.z));
        }
        for t in &self.triangles {
            s.push_str(&format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1));
        }
        s
    }

    /// The mesh as PLY, ASCII or binary little-endian.
    pub fn to_ply(&self, binary: bool) -> Vec<u8> {
        let header = format!(
            "ply\nformat {} 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
            if binary { "binary_little_endian" } else { "ascii" },
            self.vertices.len(),
            self.triangles.len()
        );
        let mut out = header.into_bytes();
        if binary {
            for v in &self.vertices {
                for c in v.iter() {
                    out.extend_from_slice(&(*c as f32).to_le_bytes());
                }
            }
            for t in &self.triangles {
                out.push(3);
                for &i in t {
                    out.extend_from_slice(&(i as i32).to_le_bytes());
                }
            }
        } else {
            for v in &self.vertices {
                out.extend_from_slice(
                    format!("{} {} {}\n", v.x as f32, v.y as f32, v.z as f32).as_bytes(),
                );
            }
            for t in &self.triangles {
                out.extend_from_slice(format!("3 {} {} {}\n", t[0], t[1], t[2]).as_bytes());
            }
        }
        out
    }

    /// An axis-aligned box centred on the origin, outward-facing triangles.
    pub fn cuboid(sx: f64, sy: f64, sz: f64) -> Self {
        let (hx, hy, hz) = (sx / 2.0, sy / 2.0, sz / 2.0);
        let vertices: Vec<Vector3<f64>> = (0..8)
            .map(|i| {
                Vector3::new(
                    if i & 1 == 0 { -hx } else { hx },
                    if i & 2 == 0 { -hy } else { hy },
                    if i & 4 == 0 { -hz } else { hz },
                )
            })
            .collect();
        // Quads as (a, b, c, d) counter-clockwise seen from outside.
        let quads = [
            [0, 2, 3, 1], // z-
            [4, 5, 7, 6], // z+
            [0, 1, 5, 4], // y-
            [2, 6, 7, 3], // y+
            [0, 4, 6, 2], // x-
            [1, 3, 7, 5], // x+
        ];
        let triangles = quads
            .iter()
            .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
            .collect();
        Self {
            vertices,
            triangles,
            colours: None,
        }
    }

    /// A closed cylinder along z, centred on the origin, with `segments`
    /// sides: a rounded object whose outline is mostly silhouette edges.
    pub fn cylinder(radius: f64, height: f64, segments: usize) -> Self {
        let n = segments.max(3);
        let profile: Vec<(f64, f64)> = (0..n)
            .map(|k| {
                let a = std::f64::consts::TAU * k as f64 / n as f64;
                (radius * a.cos(), radius * a.sin())
            })
            .collect();
        Self::prism(&profile, height)
    }

    /// A box `sx` x `sy` x `sz` whose four edges along z are rounded with
    /// radius `r` (`segments` facets per quarter circle), centred on the
    /// origin: a rounded object with a few crease edges (its caps' rims)
    /// and silhouettes on its rounded sides.
    pub fn rounded_box(sx: f64, sy: f64, sz: f64, r: f64, segments: usize) -> Self {
        let r = r.clamp(0.0, sx.min(sy) / 2.0);
        let (hx, hy) = (sx / 2.0 - r, sy / 2.0 - r);
        let m = segments.max(1);
        let mut profile = Vec::with_capacity(4 * (m + 1));
        for (q, (cx, cy)) in [(hx, hy), (-hx, hy), (-hx, -hy), (hx, -hy)]
            .into_iter()
            .enumerate()
        {
            for k in 0..=m {
                let a = std::f64::consts::FRAC_PI_2 * (q as f64 + k as f64 / m as f64);
                profile.push((cx + r * a.cos(), cy + r * a.sin()));
            }
        }
        Self::prism(&profile, sz)
    }

    /// The prism of a convex `profile` (counter-clockwise in the x-y
    /// plane) from `z = -height/2` to `height/2`, closed by fans from the
    /// caps' centres.
    fn prism(profile: &[(f64, f64)], height: f64) -> Self {
        let n = profile.len();
        let h = height / 2.0;
        let mut vertices = Vec::with_capacity(2 * n + 2);
        for z in [-h, h] {
            for &(x, y) in profile {
                vertices.push(Vector3::new(x, y, z));
            }
        }
        vertices.push(Vector3::new(0.0, 0.0, -h));
        vertices.push(Vector3::new(0.0, 0.0, h));
        let (bc, tc) = ((2 * n) as u32, (2 * n + 1) as u32);
        let mut triangles = Vec::with_capacity(4 * n);
        for k in 0..n {
            let (a, b) = (k as u32, ((k + 1) % n) as u32);
            let (at, bt) = (a + n as u32, b + n as u32);
            triangles.push([a, b, bt]);
            triangles.push([a, bt, at]);
            triangles.push([bc, b, a]);
            triangles.push([tc, at, bt]);
        }
        Self {
            vertices,
            triangles,
            colours: None,
        }
    }

    /// Each triangle's unit normal (counter-clockwise corners face it);
    /// zero for a degenerate triangle.
    pub fn face_normals(&self) -> Vec<Vector3<f64>> {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| self.vertices[i as usize]);
                (b - a)
                    .cross(&(c - a))
                    .try_normalize(1e-300)
                    .unwrap_or_else(Vector3::zeros)
            })
            .collect()
    }

    /// The mesh with each triangle split in four at its edges' midpoints,
    /// `levels` times (shared midpoints keep it closed): the same surface
    /// with 4^levels times the triangles, as dense as a scanned mesh.
    pub fn subdivided(&self, levels: usize) -> Self {
        let mut mesh = self.clone();
        for _ in 0..levels {
            let mut mid: std::collections::HashMap<(u32, u32), u32> =
                std::collections::HashMap::new();
            let mut vertices = mesh.vertices.clone();
            let mut colours = mesh.colours.clone();
            let mut midpoint = |a: u32, b: u32| {
                *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                    vertices.push((mesh.vertices[a as usize] + mesh.vertices[b as usize]) / 2.0);
                    if let Some(c) = colours.as_mut() {
                        let (ca, cb) = (c[a as usize], c[b as usize]);
                        c.push([0, 1, 2].map(|i| (ca[i] + cb[i]) / 2.0));
                    }
                    (vertices.len() - 1) as u32
                })
            };
            let mut triangles = Vec::with_capacity(4 * mesh.triangles.len());
            for &[a, b, c] in &mesh.triangles {
                let (ab, bc, ca) = (midpoint(a, b), midpoint(b, c), midpoint(c, a));
                triangles.extend([[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]);
            }
            mesh = Self {
                vertices,
                triangles,
                colours,
            };
        }
        mesh
    }

    /// The largest distance between two vertices along an axis.
    pub fn extent(&self) -> f64 {
        let (lo, hi) = self.bounds();
        (hi - lo).max()
    }

    /// The corners `(lo, hi)` of the vertices' axis-aligned box.
    pub fn bounds(&self) -> (Vector3<f64>, Vector3<f64>) {
        self.vertices.iter().fold(
            (
                Vector3::repeat(f64::INFINITY),
                Vector3::repeat(f64::NEG_INFINITY),
            ),
            |(lo, hi), v| (lo.inf(v), hi.sup(v)),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn obj_and_ply_round_trip() {
        for mesh in [
            Mesh::cuboid(0.1, 0.15, 0.08),
            Mesh::cylinder(0.04, 0.12, 24),
        ] {
            // Compare the triangles' corners (the OBJ writer and reader
            // keep the order, but a reader that renumbered would pass too).
            let corners = |m: &Mesh| -> Vec<Vector3<f64>> {
                m.triangles
                    .iter()
                    .flat_map(|t| t.map(|i| m.vertices[i as usize]))
                    .collect()
            };
            let obj = Mesh::parse(mesh.to_obj().as_bytes()).unwrap();
            assert_eq!(obj.triangles.len(), mesh.triangles.len());
            for (a, b) in corners(&obj).iter().zip(corners(&mesh).iter()) {
                assert!((a - b).norm() < 1e-6);
            }
            for binary in [false, true] {
                let ply = Mesh::parse(&mesh.to_ply(binary)).unwrap();
                assert_eq!(ply.triangles, mesh.triangles);
                for (a, b) in ply.vertices.iter().zip(&mesh.vertices) {
                    assert!((a - b).norm() < 1e-6);
                }
            }
        }
    }

    #[test]
    fn malformed_meshes_are_refused() {
        let cases: [&[u8]; 6] = [
            b"",
            b"v 0 0 0\nv 1 0 0\nf 1 2 3\n",
            b"v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n",
            b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n",
            b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n\x00\x00",
        ];
        for (i, c) in cases.iter().enumerate() {
            assert!(Mesh::parse(c).is_err(), "case {i} was accepted");
        }
    }

    #[test]
    fn subdivision_keeps_the_surface_closed() {
        let coarse = Mesh::cuboid(0.1, 0.15, 0.08);
        let fine = coarse.subdivided(3);
        assert_eq!(fine.triangles.len(), 12 * 64);
        // Euler's formula of a closed genus-0 surface: V - E + F = 2, with
        // every edge shared by two triangles (E = 3F/2).
        let (v, f) = (fine.vertices.len() as i64, fine.triangles.len() as i64);
        assert_eq!(v - 3 * f / 2 + f, 2);
        let mut edges = std::collections::HashMap::new();
        for t in &fine.triangles {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                *edges.entry((a.min(b), a.max(b))).or_insert(0) += 1;
            }
        }
        assert!(edges.values().all(|&n| n == 2));
        // The same box: same extent, and every new vertex on its surface.
        assert!((fine.extent() - coarse.extent()).abs() < 1e-12);
        for p in &fine.vertices {
            let on_face = (p.x.abs() - 0.05).abs() < 1e-12
                || (p.y.abs() - 0.075).abs() < 1e-12
                || (p.z.abs() - 0.04).abs() < 1e-12;
            assert!(on_face, "{p:?} is off the box");
        }
    }

    #[test]
    fn faces_without_surface_are_left_out_and_counted() {
        let clean = Mesh::cuboid(0.1, 0.15, 0.08);
        // Every face twice (once wound the other way), a face repeating a
        // vertex and one of three collinear corners.
        let mut dirty = clean.clone();
        dirty.vertices.push(Vector3::new(0.2, 0.0, 0.0));
        dirty
            .triangles
            .extend(clean.triangles.iter().map(|t| [t[2], t[1], t[0]]));
        dirty.triangles.extend([[0, 0, 1], [0, 1, 8]]);
        // Vertex 8 lies on the line through vertices 0 and 1 (y, z equal).
        dirty.vertices[8] = Vector3::new(0.2, -0.075, -0.04);
        for bytes in [dirty.to_obj().into_bytes(), dirty.to_ply(true)] {
            let (read, dropped) =
                Mesh::read_within(&bytes, &MeshLimits::OFFLINE, &crate::vision::Deadline::NONE)
                    .unwrap();
            assert_eq!(read.triangles, clean.triangles);
            assert_eq!(
                dropped,
                DroppedFaces {
                    degenerate: 2,
                    duplicate: 12
                }
            );
        }
        // A byte-order mark before either format is skipped.
        for bytes in [clean.to_obj().into_bytes(), clean.to_ply(false)] {
            let mut with_bom = b"\xEF\xBB\xBF".to_vec();
            with_bom.extend(&bytes);
            assert_eq!(
                Mesh::parse(&with_bom).unwrap(),
                Mesh::parse(&bytes).unwrap()
            );
        }
        // Nothing left: refused.
        let flat = Mesh {
            vertices: vec![Vector3::zeros(), Vector3::x(), Vector3::x() * 2.0],
            triangles: vec![[0, 1, 2]],
            colours: None,
        };
        assert!(Mesh::parse(flat.to_obj().as_bytes()).is_err());
    }
}
