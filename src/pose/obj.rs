//! A bounded Wavefront OBJ reader: `v` lines give the vertices (x, y, z;
//! a w or colours after them are ignored), `f` lines the faces (`i`,
//! `i/t`, `i//n` or `i/t/n`, negative indices counting back from the last
//! vertex), fanned into triangles; every other line (normals, texture
//! coordinates, groups, materials, comments) is skipped.
//!
//! One pass counts the vertices and triangles without allocating, and the
//! counts are checked against [`MeshLimits`] before the second pass reads
//! them into buffers of exactly that size. The deadline is looked at on
//! both passes. Errors name the line.
//!
//! Written here rather than taken from tobj, which reads the whole file
//! into its own buffers (a 6 M-triangle file took 1.4 GB before its size
//! could be refused).

use nalgebra::Vector3;

use super::mesh::{Mesh, MeshLimits};
use super::PoseError;
use crate::vision::Deadline;

/// Lines read between two looks at the deadline.
const DEADLINE_STRIDE: usize = 1 << 14;

fn bad(line: usize, msg: impl std::fmt::Display) -> PoseError {
    PoseError::InvalidMesh(format!("OBJ line {line}: {msg}"))
}

/// The lines of the file with their numbers (from 1), leading blanks
/// trimmed.
fn lines(bytes: &[u8]) -> impl Iterator<Item = (usize, &[u8])> {
    bytes
        .split(|&b| b == b'\n')
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim_ascii()))
}

/// Whether `line` is a statement `key` (`v`, `f`).
fn statement<'a>(line: &'a [u8], key: &[u8]) -> Option<&'a [u8]> {
    let rest = line.strip_prefix(key)?;
    rest.first()
        .is_some_and(|b| b.is_ascii_whitespace())
        .then_some(rest)
}

/// Refuses a line whose keyword (its first word) is not ASCII: OBJ's
/// keywords all are, and a `v` or `f` run into a no-break space or
/// another invisible character would otherwise be skipped as an unknown
/// statement, shifting every later index. Comments may hold anything.
fn check_keyword(line: &[u8], n: usize) -> Result<(), PoseError> {
    if line.starts_with(b"#") {
        return Ok(());
    }
    let keyword = line
        .split(|b| b.is_ascii_whitespace())
        .next()
        .unwrap_or_default();
    if keyword.is_ascii() {
        return Ok(());
    }
    let shown = String::from_utf8_lossy(&keyword[..keyword.len().min(20)]);
    Err(bad(
        n,
        format!(
            "{shown:?} is not an OBJ keyword: it holds a character other than ASCII (a no-break space or byte-order mark?)"
        ),
    ))
}

fn words(rest: &[u8]) -> impl Iterator<Item = &[u8]> {
    rest.split(|b| b.is_ascii_whitespace())
        .filter(|w| !w.is_empty())
}

/// `word` of line `n` as a `T`, or an error saying it is not `what`.
fn parse<T: std::str::FromStr>(word: &[u8], n: usize, what: &str) -> Result<T, PoseError> {
    std::str::from_utf8(word)
        .ok()
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| {
            let shown = String::from_utf8_lossy(&word[..word.len().min(20)]);
            bad(n, format!("{shown:?} is not {what}"))
        })
}

/// Reads an OBJ file within `limits`, giving up at `deadline`.
pub fn read(bytes: &[u8], limits: &MeshLimits, deadline: &Deadline) -> Result<Mesh, PoseError> {
    // The counts first, without allocating.
    let (mut nv, mut nt) = (0usize, 0usize);
    for (n, line) in lines(bytes) {
        if n % DEADLINE_STRIDE == 0 && deadline.passed() {
            return Err(PoseError::DeadlineExceeded);
        }
        check_keyword(line, n)?;
        if statement(line, b"v").is_some() {
            nv += 1;
        } else if let Some(rest) = statement(line, b"f") {
            nt += words(rest).count().saturating_sub(2);
        }
    }
    if nv > limits.max_vertices || nt > limits.max_triangles {
        return Err(PoseError::MeshTooLarge {
            vertices: nv,
            triangles: nt,
            max_vertices: limits.max_vertices,
            max_triangles: limits.max_triangles,
        });
    }
    let mut mesh = Mesh {
        vertices: Vec::with_capacity(nv),
        triangles: Vec::with_capacity(nt),
        colours: None,
    };
    let mut face: Vec<u32> = Vec::new();
    for (n, line) in lines(bytes) {
        if n % DEADLINE_STRIDE == 0 && deadline.passed() {
            return Err(PoseError::DeadlineExceeded);
        }
        if let Some(rest) = statement(line, b"v") {
            let mut c = [0.0f64; 3];
            let mut w = words(rest);
            for v in &mut c {
                let word = w
                    .next()
                    .ok_or_else(|| bad(n, "a vertex needs x, y and z"))?;
                *v = parse(word, n, "a number")?;
            }
            mesh.vertices.push(Vector3::new(c[0], c[1], c[2]));
        } else if let Some(rest) = statement(line, b"f") {
            face.clear();
            for word in words(rest) {
                let first = word.split(|&b| b == b'/').next().unwrap_or_default();
                let i: i64 = parse(first, n, "a vertex index")?;
                // 1-based; negative counts back from the last vertex read.
                let index = match i {
                    0 => return Err(bad(n, "vertex index 0 (indices start at 1)")),
                    i if i > 0 => i - 1,
                    i => mesh.vertices.len() as i64 + i,
                };
                face.push(
                    u32::try_from(index)
                        .map_err(|_| bad(n, format!("vertex index {i} refers to no vertex")))?,
                );
            }
            if face.len() < 3 {
                return Err(bad(n, format!("a face of {} vertices", face.len())));
            }
            for k in 1..face.len() - 1 {
                mesh.triangles.push([face[0], face[k], face[k + 1]]);
            }
        }
    }
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits() -> MeshLimits {
        MeshLimits {
            max_vertices: 100,
            max_triangles: 100,
        }
    }

    #[test]
    fn faces_of_every_form_and_negative_indices() {
        let f = b"# a quad\nmtllib x.mtl\nv 0 0 0\nv 1 0 0 1.0\nv 1 1 0\nvn 0 0 1\nvt 0 0\ng side\nv 0 1 0 0.5 0.5 0.5\nf 1/1/1 2//1 3/1 4\nf -4 -3 -2\n";
        let m = read(f, &limits(), &Deadline::NONE).unwrap();
        assert_eq!(m.vertices.len(), 4);
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3], [0, 1, 2]]);
    }

    #[test]
    fn counts_above_the_limits_are_refused_before_reading() {
        let mut f = String::new();
        for _ in 0..60 {
            f.push_str("f 1 2 3 4\n");
        }
        assert!(matches!(
            read(f.as_bytes(), &limits(), &Deadline::NONE),
            Err(PoseError::MeshTooLarge { triangles: 120, .. })
        ));
    }

    #[test]
    fn bad_lines_are_named() {
        for (f, line) in [
            (&b"v 0 0 0\nv 1 0\n"[..], "line 2"),
            (b"v 0 0 0\nv 1 0 x\n", "line 2"),
            (b"v 0 0 0\n\nf 1 0 1\n", "line 3"),
            (b"v 0 0 0\nf 1 -5 1\n", "line 2"),
            (b"v 0 0 0\nf 1 2\n", "line 2"),
        ] {
            match read(f, &limits(), &Deadline::NONE) {
                Err(PoseError::InvalidMesh(m)) => assert!(m.contains(line), "{m}"),
                other => panic!("{other:?}"),
            }
        }
    }

    #[test]
    fn a_keyword_with_a_character_other_than_ascii_is_named() {
        // A no-break space after `v` used to skip the vertex and shift
        // every later index by one.
        let f = "v 0 0 0\nv\u{a0}1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\n# a comment may hold \u{a0} and \u{feff}\ng c\u{f4}t\u{e9}\n";
        match read(f.as_bytes(), &limits(), &Deadline::NONE) {
            Err(PoseError::InvalidMesh(m)) => {
                assert!(
                    m.contains("line 2") && m.contains("not an OBJ keyword"),
                    "{m}"
                )
            }
            other => panic!("{other:?}"),
        }
        let clean = f.replace("v\u{a0}1", "v 1");
        assert_eq!(
            read(clean.as_bytes(), &limits(), &Deadline::NONE)
                .unwrap()
                .vertices
                .len(),
            4
        );
    }
}
