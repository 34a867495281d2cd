//! The training routes a user has, as library functions: each takes a
//! typed settings struct whose defaults are stated beside it, trains and
//! returns the models, so that a test can call it without the binary.
//! `sdhop-train` parses its arguments into these settings, shows progress
//! and prints.
//!
//! | data | route |
//! |---|---|
//! | CMU_KO8 (single-pose masks, views, box-only photographs) | [`ko8::train_ko8`] |
//! | a COCO file of your photographs (masks, boxes or both) | [`coco::train_coco`] |
//! | a mesh alone, or a mesh and boxed photographs | [`mesh::train_mesh`] |
//! | two models of an object to join | [`join::join_models`] |
//! | a choice of settings to check on CMU_KO8 | [`cv::cross_validate_route`] |

pub mod coco;
pub mod cv;
pub mod join;
pub mod join_check;
pub mod join_cost;
pub mod join_guard;
mod join_set;
pub mod ko8;
pub mod mesh;
pub mod mesh_photos;
pub mod photos;
pub mod settings;

pub use settings::TrainSettings;

use crate::model::Model;

/// Why a route could not train: bad input (exit status 2 from the CLI)
/// or a failed read or write (1).
#[derive(Debug, thiserror::Error)]
pub enum RouteError {
    #[error("{0}")]
    Input(String),
    #[error("{0}")]
    Io(String),
}

impl RouteError {
    /// Bad input: files, settings or data that cannot train.
    pub fn input(e: impl std::fmt::Display) -> Self {
        Self::Input(e.to_string())
    }

    /// A read or write that failed.
    pub fn io(e: impl std::fmt::Display) -> Self {
        Self::Io(e.to_string())
    }
}

/// The JPEG and PNG images of a folder, sorted by name (background or
/// negative scenes).
pub fn image_files(dir: &std::path::Path) -> Result<Vec<std::path::PathBuf>, RouteError> {
    let mut files: Vec<std::path::PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| RouteError::io(format!("{}: {e}", dir.display())))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|x| x.to_str())
                .is_some_and(|x| matches!(x.to_ascii_lowercase().as_str(), "jpg" | "jpeg" | "png"))
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(RouteError::input(format!(
            "{}: no JPEG or PNG images",
            dir.display()
        )));
    }
    Ok(files)
}

/// Stores a cross-validation report's figures (JSON written by `cv`) for
/// the model's object in its provenance; the cross-validated threshold
/// becomes the model's default.
pub fn add_cv_figures(model: &mut Model, cv: &serde_json::Value) {
    let name = model.meta.name.clone();
    let figures = cv["evaluation"]["objects"]
        .as_array()
        .and_then(|a| a.iter().find(|o| o["object"] == name.as_str()))
        .cloned();
    if let Some(obj) = model.meta.provenance.as_object_mut() {
        obj.insert(
            "cross_validation".into(),
            serde_json::json!({
                "folds": cv["folds"],
                "c": cv["c"],
                "params": cv["params"],
                "threshold": cv["threshold"],
                "figures": figures,
                "mean": cv["evaluation"]["mean"],
            }),
        );
    }
    if let Some(t) = cv["threshold"].as_f64() {
        model.meta.detection.threshold = t;
    }
}

/// Records the negatives a model trained with in its provenance.
pub(crate) fn record_negatives(
    model: &mut Model,
    neg: &crate::train::ko8::NegativeSet,
) -> Result<(), RouteError> {
    if let Some(obj) = model.meta.provenance.as_object_mut() {
        obj.insert(
            "negatives".into(),
            serde_json::to_value(neg).map_err(RouteError::io)?,
        );
    }
    Ok(())
}

/// A background photograph at the renders' and the pose benchmark's
/// 640x480.
pub fn background_image(
    path: &std::path::Path,
) -> Result<crate::vision::image::ColorImage, RouteError> {
    let img = image::open(path)
        .map_err(|e| RouteError::input(format!("{}: {e}", path.display())))?
        .to_rgb8();
    let img = if img.dimensions() == (640, 480) {
        img
    } else {
        image::imageops::resize(&img, 640, 480, image::imageops::FilterType::Triangle)
    };
    crate::vision::image::ColorImage::from_rgb8(&img).map_err(RouteError::input)
}

/// The `*.safetensors` files of a folder, sorted.
pub fn model_paths(dir: &std::path::Path) -> Result<Vec<std::path::PathBuf>, RouteError> {
    crate::model::model_paths(dir).map_err(RouteError::io)
}

/// The models of a folder, sorted by file name.
pub fn load_model_dir(dir: &std::path::Path) -> Result<Vec<Model>, RouteError> {
    model_paths(dir)?
        .iter()
        .map(|p| Model::load(p).map_err(|e| RouteError::input(format!("{}: {e}", p.display()))))
        .collect()
}
