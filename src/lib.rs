//! SD-HOP: occlusion-aware object localization, segmentation and pose
//! estimation (Brahmbhatt, Ben Amor, Christensen, BMVC 2015).
//!
//! Layers: [`vision`] holds the paper's mathematics (no async runtime, web
//! framework or GPU API); [`model`] is the weights format shared by the
//! server and the trainer; [`pipeline`] runs models on an image and produces
//! the detection JSON; [`synth`] generates synthetic scenes with exact
//! ground truth.

pub mod backend;
pub mod cli;
pub mod data;
pub mod eval;
pub mod http;
pub mod infer;
pub mod model;
pub mod pipeline;
pub mod pose;
pub mod progress;
pub mod synth;
pub mod train;
pub mod vision;
