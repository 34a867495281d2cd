//! Training and evaluation data, one file per format: the CMU Kitchen
//! Occlusion layout ([`ko8`]) and a COCO-style JSON format for users' own
//! objects ([`coco`]); here what they share.
//!
//! Every positive sample carries the object's full-extent box (also where it
//! is hidden or cut by the image border) and its visible pixels; negative
//! samples contain no instance. Bad annotations are reported with the file
//! name and skipped ([`Loaded::skipped`]), never a panic.

pub mod bop;
pub mod box_photos;
pub mod coco;
pub mod ko8;

use std::path::{Path, PathBuf};

use thiserror::Error;

use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;

/// Errors of the dataset readers.
#[derive(Debug, Error)]
pub enum DatasetError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: cannot decode image: {msg}")]
    Image { path: PathBuf, msg: String },
    #[error("{path}: {msg}")]
    Invalid { path: PathBuf, msg: String },
}

fn invalid(path: &Path, msg: impl Into<String>) -> DatasetError {
    DatasetError::Invalid {
        path: path.to_path_buf(),
        msg: msg.into(),
    }
}

/// The ground truth of one object instance.
#[derive(Clone, Debug, PartialEq)]
pub struct Annotation {
    /// Object label (the model name it trains).
    pub label: String,
    /// Full-extent box `(x, y, width, height)` in pixels.
    pub bbox: (f64, f64, f64, f64),
    /// Visible pixels of the object over the whole image.
    pub visible: Mask,
    /// Viewpoint (component) index.
    pub viewpoint: usize,
    /// Whether `visible` is known (a mask was annotated). A box-only
    /// annotation has `false`: its `visible` is the whole box to begin
    /// with, and training imputes it (the visibility labelling is latent).
    pub mask_known: bool,
}

/// One image: a positive with its annotation, or a negative without.
#[derive(Clone, Debug)]
pub struct Sample {
    pub image: PathBuf,
    /// Short unique name (the file stem).
    pub id: String,
    pub annotation: Option<Annotation>,
}

impl Sample {
    /// An image without the object, named by its file stem.
    pub fn negative(image: PathBuf) -> Self {
        Self {
            id: file_stem(&image),
            image,
            annotation: None,
        }
    }
}

/// A file's name without its extension (empty when it has none).
pub fn file_stem(path: &Path) -> String {
    path.file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default()
}

/// Samples read from a dataset, plus the ones refused and why.
#[derive(Debug, Default)]
pub struct Loaded {
    pub samples: Vec<Sample>,
    /// `file: reason` for every annotation that was skipped.
    pub skipped: Vec<String>,
}

/// Reads an image file as RGB.
pub fn load_image(path: &Path) -> Result<ColorImage, DatasetError> {
    let bytes = std::fs::read(path).map_err(|source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let img = image::load_from_memory(&bytes).map_err(|e| DatasetError::Image {
        path: path.to_path_buf(),
        msg: e.to_string(),
    })?;
    ColorImage::from_rgb8(&img.to_rgb8()).map_err(|e| DatasetError::Image {
        path: path.to_path_buf(),
        msg: e.to_string(),
    })
}

/// Reads a binary mask PNG: grey value > 0 is true.
pub fn load_mask(path: &Path) -> Result<Mask, DatasetError> {
    let bytes = std::fs::read(path).map_err(|source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let img = image::load_from_memory(&bytes)
        .map_err(|e| DatasetError::Image {
            path: path.to_path_buf(),
            msg: e.to_string(),
        })?
        .to_luma8();
    let (w, h) = (img.width() as usize, img.height() as usize);
    Ok(Mask {
        width: w,
        height: h,
        data: img.as_raw().iter().map(|&v| u8::from(v > 0)).collect(),
    })
}

/// Refuses a box that is degenerate or lies wholly outside the image.
pub(crate) fn check_box(
    path: &Path,
    b: (f64, f64, f64, f64),
    width: usize,
    height: usize,
) -> Result<(), DatasetError> {
    let (x, y, w, h) = b;
    let finite = [x, y, w, h].iter().all(|v| v.is_finite());
    if !finite || w <= 0.0 || h <= 0.0 {
        return Err(invalid(path, format!("degenerate box {b:?}")));
    }
    if x + w <= 0.0 || y + h <= 0.0 || x >= width as f64 || y >= height as f64 {
        return Err(invalid(
            path,
            format!("box {b:?} lies outside the {width}x{height} image"),
        ));
    }
    Ok(())
}

pub use box_photos::{load_box_photos, BoxPhoto, BoxPhotos};
pub use coco::{box_mask, decode_coco_rle_string, load_coco};
pub use ko8::{ko8_visible_mask, parse_ko8_bbox, Ko8, KO8_OBJECTS};
