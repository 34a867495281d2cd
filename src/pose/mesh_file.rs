//! Reading a mesh file: PLY when it starts with `ply` ([`super::ply`]),
//! else Wavefront OBJ ([`super::obj`]), within limits, then validated and
//! cleared of faces without surface.

use super::mesh::{DroppedFaces, Mesh, MeshLimits};
use super::PoseError;
use crate::vision::Deadline;

/// A UTF-8 byte-order mark, which some editors put before a text file.
const BOM: &[u8] = b"\xEF\xBB\xBF";

impl Mesh {
    /// Reads an OBJ or PLY file (PLY when it starts with `ply`) within the
    /// offline tools' limits, then validates it.
    pub fn parse(bytes: &[u8]) -> Result<Self, PoseError> {
        Self::parse_within(bytes, &MeshLimits::OFFLINE, &Deadline::NONE)
    }

    /// [`Self::read_within`] without the count of faces left out.
    pub fn parse_within(
        bytes: &[u8],
        limits: &MeshLimits,
        deadline: &Deadline,
    ) -> Result<Self, PoseError> {
        Self::read_within(bytes, limits, deadline).map(|(mesh, _)| mesh)
    }

    /// Reads an OBJ or PLY file within `limits` (refused from its declared
    /// counts before anything is allocated for them), giving up at
    /// `deadline`, validates it and leaves out the faces without surface
    /// ([`Mesh::drop_empty_faces`]), saying how many. A leading UTF-8
    /// byte-order mark is skipped.
    pub fn read_within(
        bytes: &[u8],
        limits: &MeshLimits,
        deadline: &Deadline,
    ) -> Result<(Self, DroppedFaces), PoseError> {
        let bytes = bytes.strip_prefix(BOM).unwrap_or(bytes);
        let mut mesh = if bytes.starts_with(b"ply") {
            let read = super::ply::read(bytes, limits, true, deadline)?;
            Mesh {
                colours: read.colours,
                ..read.mesh
            }
        } else {
            super::obj::read(bytes, limits, deadline)?
        };
        mesh.validate_within(limits)?;
        let dropped = mesh.drop_empty_faces();
        if mesh.triangles.is_empty() {
            return Err(PoseError::InvalidMesh(format!(
                "the mesh has no triangle with an area ({} repeat a vertex or have no area, {} repeat another)",
                dropped.degenerate, dropped.duplicate
            )));
        }
        Ok((mesh, dropped))
    }

    /// The vertex colours of a PLY file (`red`, `green`, `blue`, 0-255 as
    /// integers or 0-1 as floats), `None` when the vertices have none or
    /// the file is not a PLY.
    pub fn ply_vertex_colours(bytes: &[u8]) -> Result<Option<Vec<[f32; 3]>>, PoseError> {
        let bytes = bytes.strip_prefix(BOM).unwrap_or(bytes);
        if !bytes.starts_with(b"ply") {
            return Ok(None);
        }
        Ok(super::ply::read(bytes, &MeshLimits::OFFLINE, true, &Deadline::NONE)?.colours)
    }
}
