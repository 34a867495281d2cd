//! Benchmarks and evaluation harnesses, outside the library's core (the
//! vision, pose, backend, inference and HTTP layers never import this):
//! [`detection`] scores detections and masks as the CMU_KO8 acceptance
//! scorer does, [`pose`] is the occlusion pose benchmark on rendered
//! scenes, [`plot`] draws their curves.

pub mod bop_pose;
pub mod detection;
pub mod plot;
pub mod pose;

pub use detection::*;
