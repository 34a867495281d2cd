//! 3-D pose from an image and a mesh (paper section 2.6): edge-based IRLS
//! on SE(3) and its occlusion-reasoning variant OR-IRLS, which drops
//! correspondences outside the detector's visibility mask.
//!
//! The vision layer's rules hold here too: no async runtime, web framework
//! or GPU API.

pub mod api;
pub mod distance;
pub mod edges;
pub mod geometry;
pub mod irls;
pub mod mesh;
pub mod mesh_file;
pub mod obj;
pub mod params;
pub mod ply;
pub mod region;
pub mod render;
pub mod search;
pub mod start;

use thiserror::Error;

pub use edges::EdgeModel;
pub use geometry::{Intrinsics, Pose};
pub use irls::{refine, refine_until, IrlsParams, PoseResult};
pub use mesh::{Mesh, MeshLimits};

/// Errors of pose estimation.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum PoseError {
    #[error("invalid mesh: {0}")]
    InvalidMesh(String),
    #[error("the mesh has {vertices} vertices and {triangles} triangles; at most {max_vertices} vertices and {max_triangles} triangles are accepted: simplify it (the pose needs only its outline at image resolution)")]
    MeshTooLarge {
        vertices: usize,
        triangles: usize,
        max_vertices: usize,
        max_triangles: usize,
    },
    #[error("invalid parameter: {0}")]
    InvalidParameter(String),
    #[error("only {0} edge correspondences: the object is not visible enough at this pose")]
    NotEnoughEdges(usize),
    #[error("no model named {0} is loaded")]
    UnknownModel(String),
    #[error("model {model} detects nothing {place}, so there is no {what}")]
    NotDetected {
        model: String,
        /// Where it looked.
        place: &'static str,
        /// What the detection was for.
        what: &'static str,
    },
    /// The refinement passed its deadline and gave up.
    #[error("the deadline passed during the pose refinement")]
    DeadlineExceeded,
}
