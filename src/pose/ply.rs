//! A bounded PLY reader (ASCII and binary, either byte order).
//!
//! Memory and time are bounded by the header before anything is
//! allocated: every element's declared count is checked against the bytes
//! that follow the header (each item needs a least number of bytes, so a
//! count the body cannot hold is refused at once) and the vertex and face
//! counts against [`MeshLimits`]. Only `vertex` (x, y, z and, when asked,
//! red, green, blue) and `face` (`vertex_indices` or `vertex_index`) are
//! stored; every other element and property is stepped over, a
//! fixed-size binary element in one step. The deadline is looked at while
//! reading. Errors are one line that names the element, item and property.
//!
//! Written here rather than taken from a crate: the PLY crates read every
//! element into memory as maps of properties (a 10 MB file declaring ten
//! million unused items took 3.5 GB) and report errors as debug dumps.

use nalgebra::Vector3;

use super::mesh::{Mesh, MeshLimits};
use super::PoseError;
use crate::vision::Deadline;

/// The longest header read.
const MAX_HEADER_BYTES: usize = 64 << 10;
/// Items read between two looks at the deadline.
const DEADLINE_STRIDE: usize = 1 << 14;
/// The fewest indices of a face that is kept.
const MIN_FACE_INDICES: usize = 3;

fn bad(msg: impl std::fmt::Display) -> PoseError {
    PoseError::InvalidMesh(format!("PLY: {msg}"))
}

/// A scalar type of the PLY format.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(name: &str) -> Option<Self> {
        Some(match name {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    fn is_integer(self) -> bool {
        !matches!(self, Scalar::F32 | Scalar::F64)
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

#[derive(Clone, Debug)]
struct Property {
    name: String,
    kind: Kind,
}

#[derive(Clone, Debug)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Property>,
}

impl Element {
    /// Bytes of one item when every property is a scalar (binary).
    fn fixed_size(&self) -> Option<usize> {
        self.props
            .iter()
            .map(|p| match p.kind {
                Kind::Scalar(s) => Some(s.size()),
                Kind::List { .. } => None,
            })
            .sum()
    }

    /// The least bytes one item takes: binary, the scalars and list
    /// counts; ASCII, two bytes per number (a digit and a separator). A
    /// face's index list holds at least [`MIN_FACE_INDICES`].
    fn min_item_bytes(&self, format: Format) -> usize {
        self.props
            .iter()
            .map(|p| {
                let min_len = if self.name == "face" && is_index_list(&p.name) {
                    MIN_FACE_INDICES
                } else {
                    0
                };
                match (format, p.kind) {
                    (Format::Ascii, Kind::Scalar(_)) => 2,
                    (Format::Ascii, Kind::List { .. }) => 2 * (1 + min_len),
                    (Format::Binary { .. }, Kind::Scalar(s)) => s.size(),
                    (Format::Binary { .. }, Kind::List { count, item }) => {
                        count.size() + min_len * item.size()
                    }
                }
            })
            .sum()
    }
}

fn is_index_list(name: &str) -> bool {
    name == "vertex_indices" || name == "vertex_index"
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Format {
    Ascii,
    Binary { big_endian: bool },
}

struct Header {
    format: Format,
    elements: Vec<Element>,
    /// The declared vertex count.
    vertices: usize,
    /// Where the body starts.
    body: usize,
}

/// Reads and checks the header: its syntax, then every declared count
/// against the body's length and the vertex and face counts against
/// `limits`.
fn header(bytes: &[u8], limits: &MeshLimits) -> Result<Header, PoseError> {
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    let mut pos = 0usize;
    let mut line_no = 0usize;
    let body = loop {
        let Some(len) = bytes[pos..].iter().position(|&b| b == b'\n') else {
            return Err(bad("the header has no end_header line"));
        };
        line_no += 1;
        let raw = &bytes[pos..pos + len];
        pos += len + 1;
        if pos > MAX_HEADER_BYTES {
            return Err(bad(format!(
                "the header is longer than {MAX_HEADER_BYTES} bytes"
            )));
        }
        let line = std::str::from_utf8(raw)
            .map_err(|_| bad(format!("header line {line_no} is not text")))?
            .trim_end_matches('\r');
        let words: Vec<&str> = line.split_ascii_whitespace().collect();
        let at = |why: &str| bad(format!("header line {line_no} ({line:.60}): {why}"));
        match words.as_slice() {
            ["ply"] if line_no == 1 => {}
            _ if line_no == 1 => return Err(bad("the file does not start with `ply`")),
            ["format", f, _version] => {
                format = Some(match *f {
                    "ascii" => Format::Ascii,
                    "binary_little_endian" => Format::Binary { big_endian: false },
                    "binary_big_endian" => Format::Binary { big_endian: true },
                    _ => return Err(at("unknown format")),
                })
            }
            ["comment", ..] | ["obj_info", ..] | [] => {}
            ["element", name, count] => {
                let count = count
                    .parse::<usize>()
                    .map_err(|_| at("the count is not a non-negative integer"))?;
                if elements.iter().any(|e| e.name == *name) {
                    return Err(at("the element is declared twice"));
                }
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    props: Vec::new(),
                });
            }
            ["property", "list", count, item, name] => {
                let (Some(count), Some(item)) = (Scalar::parse(count), Scalar::parse(item)) else {
                    return Err(at("unknown type"));
                };
                if !count.is_integer() {
                    return Err(at("a list's count must be an integer type"));
                }
                let e = elements
                    .last_mut()
                    .ok_or_else(|| at("a property before any element"))?;
                e.props.push(Property {
                    name: name.to_string(),
                    kind: Kind::List { count, item },
                });
            }
            ["property", ty, name] => {
                let s = Scalar::parse(ty).ok_or_else(|| at("unknown type"))?;
                let e = elements
                    .last_mut()
                    .ok_or_else(|| at("a property before any element"))?;
                e.props.push(Property {
                    name: name.to_string(),
                    kind: Kind::Scalar(s),
                });
            }
            ["end_header"] => break pos,
            _ => return Err(at("not a PLY header line")),
        }
    };
    let format = format.ok_or_else(|| bad("the header has no format line"))?;
    let count_of = |name: &str| elements.iter().find(|e| e.name == name).map(|e| e.count);
    let vertices = count_of("vertex").ok_or_else(|| bad("no vertex element"))?;
    let faces = count_of("face").ok_or_else(|| bad("no face element"))?;
    if vertices > limits.max_vertices || faces > limits.max_triangles {
        return Err(PoseError::MeshTooLarge {
            vertices,
            triangles: faces,
            max_vertices: limits.max_vertices,
            max_triangles: limits.max_triangles,
        });
    }
    let available = bytes.len() - body;
    let mut needed = 0usize;
    for e in &elements {
        let item = e.min_item_bytes(format);
        needed = e
            .count
            .checked_mul(item)
            .and_then(|n| n.checked_add(needed))
            .filter(|&n| n <= available + 1)
            .ok_or_else(|| {
                bad(format!(
                    "the header declares {} items of element {} (at least {item} bytes each), more than the {available} bytes after the header hold",
                    e.count, e.name
                ))
            })?;
    }
    Ok(Header {
        format,
        elements,
        vertices,
        body,
    })
}

/// A cursor over the body.
struct Body<'a> {
    bytes: &'a [u8],
    pos: usize,
    format: Format,
}

impl Body<'_> {
    fn truncated(&self) -> PoseError {
        bad("the file ends before the elements its header declares")
    }

    /// The next number (ASCII: the next word).
    fn read(&mut self, s: Scalar) -> Result<f64, PoseError> {
        match self.format {
            Format::Ascii => {
                let rest = &self.bytes[self.pos..];
                let start = rest
                    .iter()
                    .position(|b| !b.is_ascii_whitespace())
                    .ok_or_else(|| self.truncated())?;
                let len = rest[start..]
                    .iter()
                    .position(|b| b.is_ascii_whitespace())
                    .unwrap_or(rest.len() - start);
                let word = &rest[start..start + len];
                self.pos += start + len;
                // A float property holds what an f32 holds, as in a
                // binary file of the same header.
                let v = std::str::from_utf8(word)
                    .ok()
                    .and_then(|w| match s {
                        Scalar::F32 => w.parse::<f32>().ok().map(f64::from),
                        _ => w.parse::<f64>().ok(),
                    })
                    .ok_or_else(|| {
                        bad(format!(
                            "{:?} is not a number",
                            String::from_utf8_lossy(&word[..word.len().min(20)])
                        ))
                    })?;
                if s.is_integer() && v.fract() != 0.0 {
                    return Err(bad(format!("{v} is not an integer")));
                }
                Ok(v)
            }
            Format::Binary { big_endian } => {
                let n = s.size();
                let b = self
                    .bytes
                    .get(self.pos..self.pos + n)
                    .ok_or_else(|| self.truncated())?;
                self.pos += n;
                let mut a = [0u8; 8];
                a[..n].copy_from_slice(b);
                if big_endian {
                    a[..n].reverse();
                }
                Ok(match s {
                    Scalar::I8 => f64::from(a[0] as i8),
                    Scalar::U8 => f64::from(a[0]),
                    Scalar::I16 => f64::from(i16::from_le_bytes([a[0], a[1]])),
                    Scalar::U16 => f64::from(u16::from_le_bytes([a[0], a[1]])),
                    Scalar::I32 => f64::from(i32::from_le_bytes([a[0], a[1], a[2], a[3]])),
                    Scalar::U32 => f64::from(u32::from_le_bytes([a[0], a[1], a[2], a[3]])),
                    Scalar::F32 => f64::from(f32::from_le_bytes([a[0], a[1], a[2], a[3]])),
                    Scalar::F64 => f64::from_le_bytes(a),
                })
            }
        }
    }

    /// Steps over `n` numbers of type `s`.
    fn skip(&mut self, s: Scalar, n: usize) -> Result<(), PoseError> {
        match self.format {
            Format::Ascii => (0..n).try_for_each(|_| self.read(s).map(drop)),
            Format::Binary { .. } => {
                let end = n
                    .checked_mul(s.size())
                    .and_then(|b| b.checked_add(self.pos))
                    .filter(|&e| e <= self.bytes.len())
                    .ok_or_else(|| self.truncated())?;
                self.pos = end;
                Ok(())
            }
        }
    }

    /// A list's length.
    fn list_len(&mut self, count: Scalar) -> Result<usize, PoseError> {
        let n = self.read(count)?;
        if n < 0.0 {
            return Err(bad(format!("a list of length {n}")));
        }
        Ok(n as usize)
    }

    /// Steps over one item of `e`.
    fn skip_item(&mut self, e: &Element) -> Result<(), PoseError> {
        for p in &e.props {
            match p.kind {
                Kind::Scalar(s) => self.skip(s, 1)?,
                Kind::List { count, item } => {
                    let n = self.list_len(count)?;
                    self.skip(item, n)?;
                }
            }
        }
        Ok(())
    }

    /// Steps over every item of `e`.
    fn skip_element(&mut self, e: &Element, deadline: &Deadline) -> Result<(), PoseError> {
        if let (Format::Binary { .. }, Some(size)) = (self.format, e.fixed_size()) {
            return self.skip(Scalar::U8, e.count.saturating_mul(size));
        }
        for i in 0..e.count {
            if i % DEADLINE_STRIDE == 0 && deadline.passed() {
                return Err(PoseError::DeadlineExceeded);
            }
            self.skip_item(e)?;
        }
        Ok(())
    }
}

/// What a PLY file gives: the mesh and, when asked and present, the
/// vertices' colours (0-255).
pub struct PlyMesh {
    pub mesh: Mesh,
    pub colours: Option<Vec<[f32; 3]>>,
}

/// A colour channel as 0-255: 8-bit as is, 16-bit scaled, floats taken as
/// 0-1; other types are not colours.
fn channel(s: Scalar, v: f64) -> Option<f32> {
    match s {
        Scalar::U8 => Some(v as f32),
        Scalar::U16 => Some(v as f32 / 257.0),
        Scalar::F32 | Scalar::F64 => Some((v.clamp(0.0, 1.0) * 255.0) as f32),
        _ => None,
    }
}

/// Reads a PLY file within `limits`, giving up at `deadline`; with
/// `colours`, the vertices' `red`, `green`, `blue` too.
pub fn read(
    bytes: &[u8],
    limits: &MeshLimits,
    colours: bool,
    deadline: &Deadline,
) -> Result<PlyMesh, PoseError> {
    let h = header(bytes, limits)?;
    let mut body = Body {
        bytes,
        pos: h.body,
        format: h.format,
    };
    let mut vertices: Vec<Vector3<f64>> = Vec::new();
    let mut rgb: Option<Vec<[f32; 3]>> = None;
    let mut triangles: Vec<[u32; 3]> = Vec::new();
    for e in &h.elements {
        match e.name.as_str() {
            "vertex" => {
                let slot = |name: &str| {
                    e.props
                        .iter()
                        .position(|p| p.name == name && matches!(p.kind, Kind::Scalar(_)))
                };
                let (Some(x), Some(y), Some(z)) = (slot("x"), slot("y"), slot("z")) else {
                    return Err(bad("the vertex element lacks a numeric x, y or z"));
                };
                // Where and of which type red, green and blue are, when
                // asked and all three are colour channels.
                let rgb_slots: Option<[(usize, Scalar); 3]> = if colours {
                    let channel_slot = |name: &str| {
                        let i = slot(name)?;
                        match e.props[i].kind {
                            Kind::Scalar(t) if channel(t, 0.0).is_some() => Some((i, t)),
                            _ => None,
                        }
                    };
                    match [
                        channel_slot("red"),
                        channel_slot("green"),
                        channel_slot("blue"),
                    ] {
                        [Some(r), Some(g), Some(b)] => Some([r, g, b]),
                        _ => None,
                    }
                } else {
                    None
                };
                vertices.reserve_exact(e.count);
                let mut cols = Vec::with_capacity(if rgb_slots.is_some() { e.count } else { 0 });
                let mut values = vec![0.0f64; e.props.len()];
                for i in 0..e.count {
                    if i % DEADLINE_STRIDE == 0 && deadline.passed() {
                        return Err(PoseError::DeadlineExceeded);
                    }
                    for (v, p) in values.iter_mut().zip(&e.props) {
                        match p.kind {
                            Kind::Scalar(s) => *v = body.read(s)?,
                            Kind::List { count, item } => {
                                let n = body.list_len(count)?;
                                body.skip(item, n)?;
                            }
                        }
                    }
                    vertices.push(Vector3::new(values[x], values[y], values[z]));
                    if let Some(slots) = &rgb_slots {
                        cols.push(slots.map(|(i, t)| channel(t, values[i]).unwrap_or(0.0)));
                    }
                }
                if rgb_slots.is_some() {
                    rgb = Some(cols);
                }
            }
            "face" => {
                let Some(list) = e.props.iter().position(|p| is_index_list(&p.name)) else {
                    return Err(bad("the face element has no vertex_indices list"));
                };
                match e.props[list].kind {
                    Kind::List { item, .. } if item.is_integer() => {}
                    _ => return Err(bad("vertex_indices must be a list of integers")),
                }
                triangles.reserve_exact(e.count);
                let mut idx: Vec<u32> = Vec::new();
                for fi in 0..e.count {
                    if fi % DEADLINE_STRIDE == 0 && deadline.passed() {
                        return Err(PoseError::DeadlineExceeded);
                    }
                    for (pi, p) in e.props.iter().enumerate() {
                        match p.kind {
                            Kind::Scalar(s) => body.skip(s, 1)?,
                            Kind::List { count, item } if pi == list => {
                                let n = body.list_len(count)?;
                                if n < MIN_FACE_INDICES {
                                    return Err(bad(format!("face {fi} has {n} vertices")));
                                }
                                // A list longer than the rest of the file
                                // is cut short by the reads below.
                                idx.clear();
                                for _ in 0..n {
                                    let v = body.read(item)?;
                                    idx.push(u32::try_from(v as i64).map_err(|_| {
                                        bad(format!("face {fi} has vertex index {v}"))
                                    })?);
                                }
                                if triangles.len() + n - 2 > limits.max_triangles {
                                    return Err(PoseError::MeshTooLarge {
                                        vertices: h.vertices,
                                        triangles: triangles.len() + n - 2,
                                        max_vertices: limits.max_vertices,
                                        max_triangles: limits.max_triangles,
                                    });
                                }
                                for k in 1..n - 1 {
                                    triangles.push([idx[0], idx[k], idx[k + 1]]);
                                }
                            }
                            Kind::List { count, item } => {
                                let n = body.list_len(count)?;
                                body.skip(item, n)?;
                            }
                        }
                    }
                }
            }
            _ => body.skip_element(e, deadline)?,
        }
    }
    Ok(PlyMesh {
        mesh: Mesh {
            vertices,
            triangles,
        },
        colours: rgb,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits() -> MeshLimits {
        MeshLimits {
            max_vertices: 1000,
            max_triangles: 1000,
        }
    }

    fn cube_header(extra: &str, format: &str) -> String {
        format!("ply\nformat {format} 1.0\ncomment made by a test\nelement vertex 8\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\n{extra}end_header\n")
    }

    fn cube_body() -> Vec<u8> {
        let mut out = Vec::new();
        for i in 0..8 {
            for c in [i & 1, (i >> 1) & 1, (i >> 2) & 1] {
                out.extend_from_slice(&(c as f32).to_le_bytes());
            }
        }
        out.push(3);
        for i in [0i32, 1, 2] {
            out.extend_from_slice(&i.to_le_bytes());
        }
        out
    }

    #[test]
    fn a_count_the_body_cannot_hold_is_refused_before_reading() {
        let mut f = cube_header(
            "element junk 10000000\nproperty uchar a\n",
            "binary_little_endian",
        )
        .into_bytes();
        f.extend(cube_body());
        f.extend(vec![0u8; 1000]);
        match read(&f, &limits(), false, &Deadline::NONE) {
            Err(PoseError::InvalidMesh(m)) => {
                assert!(m.contains("10000000 items of element junk"), "{m}");
                assert!(!m.contains('\n'));
            }
            Err(e) => panic!("{e}"),
            Ok(_) => panic!("accepted"),
        }
    }

    #[test]
    fn unused_elements_and_properties_are_stepped_over() {
        for big in [false, true] {
            // A junk element of fixed size and one with lists, before and
            // after the mesh, and unused vertex properties.
            let format = if big {
                "binary_big_endian"
            } else {
                "binary_little_endian"
            };
            let head = format!("ply\nformat {format} 1.0\nelement junk 3\nproperty uchar a\nproperty double b\nelement vertex 3\nproperty float x\nproperty uchar red\nproperty float y\nproperty list uchar short normals\nproperty float z\nelement face 1\nproperty uchar flags\nproperty list uchar uint vertex_indices\nelement tail 2\nproperty list uchar int stuff\nend_header\n");
            let mut f = head.into_bytes();
            let put = |f: &mut Vec<u8>, b: &[u8]| {
                let mut b = b.to_vec();
                if big {
                    b.reverse();
                }
                f.extend(b);
            };
            for _ in 0..3 {
                f.push(9);
                put(&mut f, &1.5f64.to_le_bytes());
            }
            for (i, v) in [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.5]]
                .iter()
                .enumerate()
            {
                put(&mut f, &v[0].to_le_bytes());
                f.push(200);
                put(&mut f, &v[1].to_le_bytes());
                f.push(i as u8);
                for _ in 0..i {
                    put(&mut f, &7i16.to_le_bytes());
                }
                put(&mut f, &v[2].to_le_bytes());
            }
            f.push(1);
            f.push(3);
            for i in [0u32, 1, 2] {
                put(&mut f, &i.to_le_bytes());
            }
            for n in [2u8, 0] {
                f.push(n);
                for _ in 0..n {
                    put(&mut f, &5i32.to_le_bytes());
                }
            }
            let m = read(&f, &limits(), true, &Deadline::NONE).unwrap();
            assert_eq!(m.mesh.triangles, vec![[0, 1, 2]]);
            assert_eq!(m.mesh.vertices[2], Vector3::new(0.0, 1.0, 0.5));
            // Red alone is no colour.
            assert!(m.colours.is_none());
        }
    }

    #[test]
    fn ascii_with_colours_and_polygons() {
        let f = "ply\nformat ascii 1.0\nelement vertex 4\nproperty double x\nproperty double y\nproperty double z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nelement face 1\nproperty list uchar int vertex_index\nend_header\n0 0 0 255 0 0\n1 0 0 0 255 0\n1 1 0 0 0 255\n0 1 0 10 20 30\n4 0 1 2 3\n";
        let m = read(f.as_bytes(), &limits(), true, &Deadline::NONE).unwrap();
        assert_eq!(m.mesh.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        assert_eq!(m.colours.unwrap()[3], [10.0, 20.0, 30.0]);
    }

    #[test]
    fn counts_above_the_limits_are_refused_from_the_header() {
        let f = "ply\nformat ascii 1.0\nelement vertex 5000\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n";
        assert!(matches!(
            read(f.as_bytes(), &limits(), false, &Deadline::NONE),
            Err(PoseError::MeshTooLarge { vertices: 5000, .. })
        ));
        // Polygons fanned past the triangle limit.
        let small = MeshLimits {
            max_vertices: 10,
            max_triangles: 2,
        };
        let f = "ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n0 2 0\n5 0 1 2 3 4\n";
        assert!(matches!(
            read(f.as_bytes(), &small, false, &Deadline::NONE),
            Err(PoseError::MeshTooLarge { triangles: 3, .. })
        ));
    }

    #[test]
    fn bad_files_give_one_line_errors() {
        let cases: [&[u8]; 7] = [
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n",
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quux x\nend_header\n",
            b"ply\nformat ascii 1.0\nelement vertex -1\nend_header\n",
            b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 x\n3 0 1 2\n",
            b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 -2\n",
            b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n\x00\x00",
            b"plx\n",
        ];
        for (i, c) in cases.iter().enumerate() {
            match read(c, &limits(), false, &Deadline::NONE) {
                Err(PoseError::InvalidMesh(m)) => {
                    assert!(m.starts_with("PLY: ") && !m.contains('\n'), "case {i}: {m}")
                }
                Err(e) => panic!("case {i}: {e}"),
                Ok(_) => panic!("case {i} was accepted"),
            }
        }
    }

    #[test]
    fn a_passed_deadline_stops_the_reading() {
        let mut f = cube_header("", "binary_little_endian").into_bytes();
        f.extend(cube_body());
        let past = Deadline::at(std::time::Instant::now());
        assert!(matches!(
            read(&f, &limits(), false, &past),
            Err(PoseError::DeadlineExceeded)
        ));
        assert!(read(&f, &limits(), false, &Deadline::NONE).is_ok());
    }
}
