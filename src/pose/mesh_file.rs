//! Reading a mesh file: PLY when it starts with `ply` ([`super::ply`]),
//! else Wavefront OBJ ([`super::obj`]), within limits, then validated.

use super::mesh::{Mesh, MeshLimits};
use super::PoseError;
use crate::vision::Deadline;

impl Mesh {
    /// Reads an OBJ or PLY file (PLY when it starts with `ply`) within the
    /// offline tools' limits, then validates it.
    pub fn parse(bytes: &[u8]) -> Result<Self, PoseError> {
        Self::parse_within(bytes, &MeshLimits::OFFLINE, &Deadline::NONE)
    }

    /// Reads an OBJ or PLY file within `limits` (refused from its declared
    /// counts before anything is allocated for them), giving up at
    /// `deadline`, then validates it.
    pub fn parse_within(
        bytes: &[u8],
        limits: &MeshLimits,
        deadline: &Deadline,
    ) -> Result<Self, PoseError> {
        let mesh = if bytes.starts_with(b"ply") {
            super::ply::read(bytes, limits, false, deadline)?.mesh
        } else {
            super::obj::read(bytes, limits, deadline)?
        };
        mesh.validate_within(limits)?;
        Ok(mesh)
    }

    /// The vertex colours of a PLY file (`red`, `green`, `blue`, 0-255 as
    /// integers or 0-1 as floats), `None` when the vertices have none or
    /// the file is not a PLY.
    pub fn ply_vertex_colours(bytes: &[u8]) -> Result<Option<Vec<[f32; 3]>>, PoseError> {
        if !bytes.starts_with(b"ply") {
            return Ok(None);
        }
        Ok(super::ply::read(bytes, &MeshLimits::OFFLINE, true, &Deadline::NONE)?.colours)
    }
}
