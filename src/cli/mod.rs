//! The companion command-line tool `sdhop-train`, one module per command:
//! train SD-HOP models (structured SVM), cross-validate and evaluate them on
//! CMU_KO8, run the detector or the pose refinement on an image, and the
//! pose benchmark. The binary only calls [`main`]. Exit status 2 means bad
//! input, 1 an I/O failure.

mod annotate;
mod args;
mod bop_eval;
mod cells;
mod cv;
mod demo;
mod detect;
mod eval;
mod join;
mod mesh;
mod pair;
mod pose;
mod pose_bench;
mod pose_data;
mod pose_eval;
mod train;
mod upgrade;

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use crate::model::Model;
use crate::pipeline::{
    detect_image, overlay, DetectOptions, DetectResponse, MaskMode, DEFAULT_MAX_PIXELS,
};
use clap::{Parser, Subcommand};

use crate::synth::{hand_model, scene, HandModelParams, SceneParams, SynthObject};
use crate::train::ko8::{detect_all, score, EvalDetect, Evaluation, Ko8Data};

use crate::train::routes::{add_cv_figures, background_image, image_files, TrainSettings};
use crate::train::{progress_bar, PyramidCache};
use crate::vision::detect::box_iou;
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;
use crate::vision::refine::PixelRefine;

use annotate::*;
use args::*;
use bop_eval::*;
use cells::*;
use cv::*;
use demo::*;
use detect::*;
use eval::*;
use join::*;
use mesh::*;
use pair::*;
use pose::*;
use pose_bench::*;
use pose_data::*;
use pose_eval::*;
use train::*;
use upgrade::*;

#[derive(Parser)]
#[command(
    name = "sdhop-train",
    version,
    about = "SD-HOP occlusion-aware detector: companion tool"
)]
pub(crate) struct Cli {
    #[command(subcommand)]
    pub(crate) command: Command,
}

#[derive(Subcommand)]
pub(crate) enum Command {
    /// Train one model per object (CMU_KO8 or a COCO-style file) and save
    /// them as weights files.
    Train(TrainArgs),
    /// Cross-validate training on CMU_KO8 (k folds, every object), choose C,
    /// and report AUC (per-object and cross-object) and segmentation errors.
    Cv(CvArgs),
    /// Evaluate weights files on CMU_KO8 images: figures, JSON and a plot.
    Eval(EvalArgs),
    /// Store the figures of a `cv` report in the models' metadata (for
    /// models trained with the same settings without `--cv-report`).
    Annotate(AnnotateArgs),
    /// Join each object's model with the components of another model of
    /// it trained apart (single-pose with view components), their scores
    /// moved by an offset.
    Join(JoinArgs),
    /// Both kinds per object: each model of a folder (learned cells) with
    /// the model of the same object from another folder (HOG) as the
    /// segmenter that places and segments its detections.
    Pair(PairArgs),
    /// Detect objects in one image; prints the detection JSON of `POST /detect`.
    Detect(DetectArgs),
    /// Refine an object's 3-D pose from an image and its mesh (OR-IRLS with
    /// a detected or given visibility mask, or plain IRLS); prints the JSON
    /// of `POST /pose`.
    Pose(PoseArgs),
    /// Render the pose benchmark's objects over training backgrounds as a
    /// COCO training set (full boxes, visible masks) for `train --coco`.
    PoseData(PoseDataArgs),
    /// Train a detector of an object from its mesh alone: renders over
    /// background photographs (viewpoints over the view sphere, lighting,
    /// occluders, camera noise), one SD-HOP model with a component per
    /// group of viewpoints.
    Mesh(MeshArgs),
    /// The whole pipeline on real photographs in BOP format (LM-O):
    /// detection and visible masks as lmo_detect_eval.py scores them,
    /// ablations beside, and the pose from no start (ADD(-S) < 10% d);
    /// JSON report and plot.
    BopEval(BopEvalArgs),
    /// The occlusion pose benchmark: IRLS, OR-IRLS with the exact mask and
    /// OR-IRLS with the SD-HOP mask on held-out backgrounds; six mean
    /// errors and success rates.
    PoseBench(PoseBenchArgs),
    /// Pose refinement on real photographs in BOP format (LM-O): IRLS and
    /// OR-IRLS from seeded starts, the paper's Table 2 per object, rows for
    /// unoccluded instances and other starts, JSON report.
    PoseEval(PoseEvalArgs),
    /// Generate a synthetic occluded scene and a hand-built model of its object,
    /// detect, and report box and mask accuracy against the exact truth.
    Demo(DemoArgs),
    /// Fit the fixed projection of the learned (convolutional) cells to
    /// the backbone's features of representative photographs (written to
    /// models/backbones/, built into the binary at the next build).
    Cells(CellsArgs),
    /// Rewrite weights files of formats 1 and 2 (no digest) as the current
    /// format, which the server requires.
    Upgrade(UpgradeArgs),
}

pub(crate) use crate::eval::feature_kinds;

/// An error with the process exit code it maps to.
#[derive(Debug)]
pub(crate) struct Failure {
    pub(crate) code: u8,
    pub(crate) message: String,
}

impl Failure {
    fn input(e: impl std::fmt::Display) -> Self {
        Self {
            code: 2,
            message: e.to_string(),
        }
    }
    fn io(e: impl std::fmt::Display) -> Self {
        Self {
            code: 1,
            message: e.to_string(),
        }
    }
}

/// Reads an image, checking its declared size before decoding it.
pub(crate) fn read_image(path: &Path, max_pixels: usize) -> Result<ColorImage, Failure> {
    let bytes = std::fs::read(path).map_err(|e| Failure::io(format!("{}: {e}", path.display())))?;
    let reader = || {
        image::ImageReader::new(std::io::Cursor::new(&bytes))
            .with_guessed_format()
            .map_err(|e| Failure::io(format!("{}: {e}", path.display())))
    };
    let (w, h) = reader()?.into_dimensions().map_err(|e| {
        Failure::input(format!(
            "{}: not a readable PNG or JPEG: {e}",
            path.display()
        ))
    })?;
    if (w as usize).saturating_mul(h as usize) > max_pixels {
        return Err(Failure::input(format!(
            "{}: image of {w}x{h} pixels exceeds the limit of {max_pixels}",
            path.display()
        )));
    }
    let img = reader()?
        .decode()
        .map_err(|e| Failure::input(format!("{}: cannot decode: {e}", path.display())))?;
    ColorImage::from_rgb8(&img.to_rgb8())
        .map_err(|e| Failure::input(format!("{}: {e}", path.display())))
}

pub(crate) fn read_json(p: &Path) -> Result<serde_json::Value, Failure> {
    let text =
        std::fs::read_to_string(p).map_err(|e| Failure::io(format!("{}: {e}", p.display())))?;
    serde_json::from_str(&text).map_err(|e| Failure::input(format!("{}: {e}", p.display())))
}

/// The `*.safetensors` files of a folder, sorted.
pub(crate) fn model_paths(dir: &Path) -> Result<Vec<PathBuf>, Failure> {
    Ok(crate::train::routes::model_paths(dir)?)
}

pub(crate) fn load_model_dir(dir: &Path) -> Result<Vec<Model>, Failure> {
    Ok(crate::train::routes::load_model_dir(dir)?)
}

impl From<crate::eval::bop_run::RunError> for Failure {
    fn from(e: crate::eval::bop_run::RunError) -> Self {
        Self::input(e.0)
    }
}

impl From<crate::train::routes::RouteError> for Failure {
    fn from(e: crate::train::routes::RouteError) -> Self {
        match e {
            crate::train::routes::RouteError::Input(m) => Self::input(m),
            crate::train::routes::RouteError::Io(m) => Self::io(m),
        }
    }
}

/// Parses the command line and runs the command; the process exit code.
pub fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match &cli.command {
        Command::Train(a) => run_train(a),
        Command::Cv(a) => run_cv(a),
        Command::Eval(a) => run_eval(a),
        Command::Annotate(a) => run_annotate(a),
        Command::Upgrade(a) => run_upgrade(a),
        Command::Join(a) => run_join(a),
        Command::Pair(a) => run_pair(a),
        Command::Detect(a) => run_detect(a),
        Command::Pose(a) => run_pose(a),
        Command::PoseData(a) => run_pose_data(a),
        Command::Mesh(a) => run_mesh(a),
        Command::BopEval(a) => run_bop_eval(a),
        Command::PoseBench(a) => run_pose_bench(a),
        Command::PoseEval(a) => run_pose_eval(a),
        Command::Demo(a) => run_demo(a),
        Command::Cells(a) => run_cells(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(f) => {
            eprintln!("error: {}", f.message);
            ExitCode::from(f.code)
        }
    }
}
