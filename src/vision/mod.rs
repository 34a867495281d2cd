//! The paper's mathematics: features, over-segmentation, max-flow, the
//! SD-HOP energy and detection. Pure functions on plain data; this layer
//! imports no async runtime, web framework or GPU API.

pub mod cells;
pub mod cnn;
pub mod deadline;
pub mod detect;
pub mod energy;
pub mod gridflow;
pub mod hog;
pub mod image;
pub mod mask;
pub mod maxflow;
pub mod pyramid;
pub mod refine;
pub mod rng;
pub mod segment;
pub mod shape;
pub mod simd;

use thiserror::Error;

pub use deadline::Deadline;

/// Errors of the vision layer.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum VisionError {
    #[error("image is empty ({width}x{height})")]
    EmptyImage { width: usize, height: usize },
    #[error("image is too large ({width}x{height})")]
    ImageTooLarge { width: usize, height: usize },
    #[error("buffer has {actual} values, expected {expected}")]
    BufferSize { expected: usize, actual: usize },
    #[error("non-finite values in {0}")]
    NonFinite(&'static str),
    #[error("invalid parameter: {0}")]
    InvalidParameter(String),
    /// The computation passed its deadline and gave up.
    #[error("the deadline passed during the computation")]
    DeadlineExceeded,
}
