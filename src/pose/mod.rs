//! 3-D pose from an image and a mesh (paper section 2.6): edge-based IRLS
//! on SE(3) and its occlusion-reasoning variant OR-IRLS, which drops
//! correspondences outside the detector's visibility mask.
//!
//! The vision layer's rules hold here too: no async runtime, web framework
//! or GPU API.

pub mod api;
pub mod edges;
pub mod geometry;
pub mod irls;
pub mod mesh;
pub mod region;
pub mod render;
pub mod start;

use thiserror::Error;

pub use edges::EdgeModel;
pub use geometry::{Intrinsics, Pose};
pub use irls::{refine, refine_until, IrlsParams, PoseResult};
pub use mesh::Mesh;

/// Errors of pose estimation.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum PoseError {
    #[error("invalid mesh: {0}")]
    InvalidMesh(String),
    #[error("mesh too large: {vertices} vertices, {triangles} triangles")]
    MeshTooLarge { vertices: usize, triangles: usize },
    #[error("invalid parameter: {0}")]
    InvalidParameter(String),
    #[error("only {0} edge correspondences: the object is not visible enough at this pose")]
    NotEnoughEdges(usize),
    #[error("no model named {0} is loaded")]
    UnknownModel(String),
    #[error(
        "model {0} detects nothing where the request looks for the object (around the initial pose, or anywhere without one), so there is no mask or start pose"
    )]
    NotDetected(String),
    /// The refinement passed its deadline and gave up.
    #[error("the deadline passed during the pose refinement")]
    DeadlineExceeded,
}
