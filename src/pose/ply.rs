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
/// Numbers read between two looks at the deadline (every item of every
/// element loop reads at least one, so no loop runs past it).
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

    /// The values an integer type holds (`None`: a float type).
    fn range(self) -> Option<(f64, f64)> {
        Some(match self {
            Scalar::I8 => (i8::MIN.into(), i8::MAX.into()),
            Scalar::U8 => (0.0, u8::MAX.into()),
            Scalar::I16 => (i16::MIN.into(), i16::MAX.into()),
            Scalar::U16 => (0.0, u16::MAX.into()),
            Scalar::I32 => (i32::MIN.into(), i32::MAX.into()),
            Scalar::U32 => (0.0, u32::MAX.into()),
            Scalar::F32 | Scalar::F64 => return None,
        })
    }

    fn name(self) -> &'static str {
        match self {
            Scalar::I8 => "char",
            Scalar::U8 => "uchar",
            Scalar::I16 => "short",
            Scalar::U16 => "ushort",
            Scalar::I32 => "int",
            Scalar::U32 => "uint",
            Scalar::F32 => "float",
            Scalar::F64 => "double",
        }
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
            ["format", ..] if format.is_some() => return Err(at("a second format line")),
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
                // Digits only: no sign, no blanks, no exponent.
                let count = Some(*count)
                    .filter(|c| c.bytes().all(|b| b.is_ascii_digit()))
                    .and_then(|c| c.parse::<usize>().ok())
                    .ok_or_else(|| at("the count is not a non-negative integer"))?;
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
    // An item without properties takes no bytes, so that no length of the
    // body could bound how many of them are stepped over.
    if let Some(e) = elements.iter().find(|e| e.props.is_empty() && e.count > 0) {
        return Err(bad(format!(
            "element {} declares {} items but no properties",
            e.name, e.count
        )));
    }
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

/// A cursor over the body. Every number read counts towards a look at
/// the deadline, so that no loop over items or list entries runs past it.
struct Body<'a> {
    bytes: &'a [u8],
    pos: usize,
    format: Format,
    deadline: Deadline,
    /// Numbers read so far.
    reads: usize,
}

impl Body<'_> {
    fn truncated(&self) -> PoseError {
        bad("the file ends before the elements its header declares")
    }

    /// Bytes not yet read.
    fn left(&self) -> usize {
        self.bytes.len() - self.pos
    }

    /// The least bytes `n` numbers of type `s` take (ASCII: a digit and a
    /// separator each).
    fn min_bytes(&self, s: Scalar, n: usize) -> Option<usize> {
        match self.format {
            Format::Ascii => n.checked_mul(2),
            Format::Binary { .. } => n.checked_mul(s.size()),
        }
    }

    /// The next number (ASCII: the next word, checked against its type).
    fn read(&mut self, s: Scalar) -> Result<f64, PoseError> {
        self.reads += 1;
        if self.reads % DEADLINE_STRIDE == 1 && self.deadline.passed() {
            return Err(PoseError::DeadlineExceeded);
        }
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
                if let Some((lo, hi)) = s.range() {
                    if v.fract() != 0.0 {
                        return Err(bad(format!("{v} is not an integer")));
                    }
                    if !(lo..=hi).contains(&v) {
                        return Err(bad(format!(
                            "{v} is out of range for a {} ({lo} to {hi})",
                            s.name()
                        )));
                    }
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
            Format::Ascii => {
                if self.min_bytes(s, n).is_none_or(|b| b > self.left() + 1) {
                    return Err(self.truncated());
                }
                (0..n).try_for_each(|_| self.read(s).map(drop))
            }
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

    /// A list's length, checked against the bytes left for its `item`s
    /// before any of them is read.
    fn list_len(&mut self, count: Scalar, item: Scalar) -> Result<usize, PoseError> {
        let n = self.read(count)?;
        if n < 0.0 {
            return Err(bad(format!("a list of length {n}")));
        }
        let n = n as usize;
        let left = self.left();
        // ASCII: the last number of the file may end without a separator.
        if self.min_bytes(item, n).is_none_or(|b| b > left + 1) {
            return Err(bad(format!(
                "a list of {n} {}s, more than the {left} bytes left in the file hold",
                item.name()
            )));
        }
        Ok(n)
    }

    /// Steps over one item of `e`.
    fn skip_item(&mut self, e: &Element) -> Result<(), PoseError> {
        for p in &e.props {
            match p.kind {
                Kind::Scalar(s) => self.skip(s, 1)?,
                Kind::List { count, item } => {
                    let n = self.list_len(count, item)?;
                    self.skip(item, n)?;
                }
            }
        }
        Ok(())
    }

    /// Steps over every item of `e`.
    fn skip_element(&mut self, e: &Element) -> Result<(), PoseError> {
        if let (Format::Binary { .. }, Some(size)) = (self.format, e.fixed_size()) {
            return self.skip(Scalar::U8, e.count.saturating_mul(size));
        }
        (0..e.count).try_for_each(|_| self.skip_item(e))
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
        deadline: *deadline,
        reads: 0,
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
                for _ in 0..e.count {
                    for (v, p) in values.iter_mut().zip(&e.props) {
                        match p.kind {
                            Kind::Scalar(s) => *v = body.read(s)?,
                            Kind::List { count, item } => {
                                let n = body.list_len(count, item)?;
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
                    for (pi, p) in e.props.iter().enumerate() {
                        match p.kind {
                            Kind::Scalar(s) => body.skip(s, 1)?,
                            Kind::List { count, item } if pi == list => {
                                // Checked against the bytes left, the
                                // triangle limit and the indices' range
                                // before any index is kept.
                                let n = body.list_len(count, item)?;
                                if n < MIN_FACE_INDICES {
                                    return Err(bad(format!("face {fi} has {n} vertices")));
                                }
                                let fanned = triangles.len().saturating_add(n - 2);
                                if fanned > limits.max_triangles {
                                    return Err(PoseError::MeshTooLarge {
                                        vertices: h.vertices,
                                        triangles: fanned,
                                        max_vertices: limits.max_vertices,
                                        max_triangles: limits.max_triangles,
                                    });
                                }
                                idx.clear();
                                for _ in 0..n {
                                    let v = body.read(item)?;
                                    idx.push(
                                        u32::try_from(v as i64)
                                            .ok()
                                            .filter(|&i| (i as usize) < h.vertices)
                                            .ok_or_else(|| {
                                                bad(format!(
                                                    "face {fi} has vertex index {v} (the vertices are 0 to {})",
                                                    h.vertices.saturating_sub(1)
                                                ))
                                            })?,
                                    );
                                }
                                for k in 1..n - 1 {
                                    triangles.push([idx[0], idx[k], idx[k + 1]]);
                                }
                            }
                            Kind::List { count, item } => {
                                let n = body.list_len(count, item)?;
                                body.skip(item, n)?;
                            }
                        }
                    }
                }
            }
            _ => body.skip_element(e)?,
        }
    }
    // What follows the declared elements (ASCII: past blanks) means the
    // header's counts do not describe the data: refused, not ignored.
    let rest = &bytes[body.pos..];
    let extra = match h.format {
        Format::Ascii => rest
            .iter()
            .position(|b| !b.is_ascii_whitespace())
            .map(|i| rest.len() - i),
        Format::Binary { .. } => (!rest.is_empty()).then_some(rest.len()),
    };
    if let Some(n) = extra {
        return Err(bad(format!(
            "{n} bytes follow the last declared element: the header's counts do not match the data"
        )));
    }
    Ok(PlyMesh {
        mesh: Mesh {
            vertices,
            triangles,
            colours: None,
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
        // A mesh read for a pose request keeps them; subdivided, its new
        // vertices take their edge's mean colour.
        let mesh = Mesh::parse(f.as_bytes()).unwrap();
        let colours = mesh.colours.as_ref().expect("the vertex colours");
        assert_eq!(colours.len(), mesh.vertices.len());
        assert_eq!(colours[1], [0.0, 255.0, 0.0]);
        let fine = mesh.subdivided(1);
        assert_eq!(
            fine.colours.as_ref().map(Vec::len),
            Some(fine.vertices.len())
        );
        assert!(fine.colours.unwrap().contains(&[127.5, 127.5, 0.0]));
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

    /// The reading's result as its one-line message (or "ok").
    fn outcome(f: &[u8], limits: &MeshLimits, deadline: &Deadline) -> String {
        match read(f, limits, false, deadline) {
            Ok(_) => "ok".into(),
            Err(e) => {
                let m = e.to_string();
                assert!(!m.contains('\n'), "{m}");
                m
            }
        }
    }

    const TRIANGLE: &str = "element vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n10 0 0\n0 10 0\n3 0 1 2\n";

    #[test]
    fn an_element_without_properties_is_refused_from_the_header() {
        // 2^64-1 items of no bytes: the spin mesh of issue 42, which
        // stepped over its items until the deadline.
        let f = format!("ply\nformat ascii 1.0\nelement junk 18446744073709551615\n{TRIANGLE}");
        let t = std::time::Instant::now();
        let m = outcome(f.as_bytes(), &limits(), &Deadline::NONE);
        assert!(
            m.contains("element junk declares 18446744073709551615 items but no properties"),
            "{m}"
        );
        assert!(t.elapsed() < std::time::Duration::from_millis(50));
        // None of them is harmless.
        let f = format!("ply\nformat ascii 1.0\nelement junk 0\n{TRIANGLE}");
        assert_eq!(outcome(f.as_bytes(), &limits(), &Deadline::NONE), "ok");
    }

    #[test]
    fn a_long_list_is_refused_before_its_entries_are_read() {
        // One face of a million indices against a limit of 1000
        // triangles: refused from its count, nothing read.
        let mut f = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uint uchar vertex_indices\nend_header\n".to_vec();
        f.extend(vec![0u8; 36]);
        f.extend(1_000_000u32.to_le_bytes());
        f.extend(vec![0u8; 1_000_000]);
        match read(&f, &limits(), false, &Deadline::NONE) {
            Err(PoseError::MeshTooLarge { triangles, .. }) => assert_eq!(triangles, 999_998),
            Err(e) => panic!("{e}"),
            Ok(_) => panic!("accepted"),
        }
        // A list longer than the bytes left: refused from its count.
        let mut short = f[..f.len() - 1_000_000].to_vec();
        short.extend(vec![1u8; 100]);
        let m = outcome(&short, &MeshLimits::OFFLINE, &Deadline::NONE);
        assert!(
            m.contains("a list of 1000000 uchars, more than the 100 bytes left"),
            "{m}"
        );
        // The ASCII form too.
        let mut f = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uint uchar vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n4000000".to_string();
        f.push_str(&" 0".repeat(1000));
        let m = outcome(f.as_bytes(), &MeshLimits::OFFLINE, &Deadline::NONE);
        assert!(m.contains("a list of 4000000 uchars"), "{m}");
    }

    #[test]
    fn the_deadline_is_looked_at_inside_a_long_list() {
        // After the mesh, one item of an unused element holding a list of
        // 20 million ASCII numbers (some seconds of reading): a deadline
        // that passes while it is read stops it there.
        let n = 20_000_000;
        let mut f = format!(
            "ply\nformat ascii 1.0\n{}",
            TRIANGLE.replace(
                "end_header\n",
                "element junk 1\nproperty list uint int stuff\nend_header\n"
            )
        );
        f.push_str(&n.to_string());
        f.push_str(&" 1".repeat(n));
        let soon = Deadline::at(std::time::Instant::now() + std::time::Duration::from_millis(30));
        assert!(matches!(
            read(f.as_bytes(), &MeshLimits::OFFLINE, false, &soon),
            Err(PoseError::DeadlineExceeded)
        ));
    }

    #[test]
    fn ascii_values_keep_to_their_type_and_the_header_to_its_syntax() {
        let cases = [
            // A uchar count of 300.
            ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n300 0 1 2\n", "300 is out of range for a uchar"),
            ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nproperty char c\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0 1\n1 0 0 -129\n0 1 0 1\n3 0 1 2\n", "-129 is out of range for a char"),
            ("ply\nformat ascii 1.0\nformat binary_little_endian 1.0\nelement vertex 0\n", "a second format line"),
            ("ply\nformat ascii 1.0\nelement vertex +3\n", "not a non-negative integer"),
            // Data after the declared elements: a face count of 1 for 2.
            ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 2 1 0\n", "8 bytes follow the last declared element"),
            ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n", "face 0 has vertex index 3 (the vertices are 0 to 2)"),
        ];
        for (f, why) in cases {
            let m = outcome(f.as_bytes(), &limits(), &Deadline::NONE);
            assert!(m.contains(why), "{why}: {m}");
        }
        // Trailing blanks are fine; a binary file's trailing bytes not.
        let f = format!("ply\nformat ascii 1.0\n{TRIANGLE}\n\n  \r\n");
        assert_eq!(outcome(f.as_bytes(), &limits(), &Deadline::NONE), "ok");
        let mut f = cube_header("", "binary_little_endian").into_bytes();
        f.extend(cube_body());
        f.push(b'\n');
        let m = outcome(&f, &limits(), &Deadline::NONE);
        assert!(m.contains("1 bytes follow"), "{m}");
    }
}
