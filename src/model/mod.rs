//! The trained-weights file: safetensors tensors plus JSON metadata, read by
//! the server and written by the trainer.
//!
//! Tensors, for viewpoint `a` (all `F32`):
//! `view{a}.w_vis` `[rows, cols, 31]`, `view{a}.w_occ` `[rows, cols, 31]`,
//! `view{a}.w_prior` `[rows, cols]`, `view{a}.w_hop` `[K + 1]`,
//! `view{a}.scalars` `[3]` = `(w_trunc, W, bias)`, and from format 2 on,
//! where the trainer learned one, `view{a}.shape` (`rows` times
//! `cell_size` by `cols` times `cell_size`): the viewpoint's pixel shape
//! model ([`crate::vision::shape`]), and `view{a}.colours` `[4096]`: the
//! object's colour histogram from the training images. A model with a
//! segmenter ([`Model::segmenter`]) also holds the segmenter's tensors,
//! named as above with the prefix [`SEGMENTER_PREFIX`], and its
//! description under `segmenter` in the metadata JSON.
//!
//! The safetensors metadata holds two keys: `sdhop`, whose value is the
//! JSON of [`ModelMeta`], and from format 3 on `sdhop.sha256`, the SHA-256
//! of that JSON and of every tensor ([`content_digest`]). Loading
//! recomputes it and refuses a file whose tensors or metadata changed after
//! it was written (a flipped byte, a header edited by hand), and format 3
//! states the feature kind always, so that no learned-cell file is read as
//! HOG. Files of formats 1 and 2 carry no digest: they are refused, and
//! `sdhop-train upgrade` rewrites them as format 3 after the operator has
//! vouched for them.

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::vision::cells::{FeatureKind, LearnedCells};
use crate::vision::detect::{DetectParams, LowRank};
use crate::vision::energy::{PairwiseMode, ViewWeights};
use crate::vision::hog::{CELL_SIZE, HOG_DIM, HOG_STRIDE};
use crate::vision::pyramid::PyramidParams;
use crate::vision::segment::SegmentParams;
use crate::vision::shape::{ShapeModel, COLOUR_BINS};
use crate::vision::VisionError;

/// Version of the weights format this build writes and serves.
pub const FORMAT_VERSION: u32 = 3;
/// The oldest version [`Model::from_legacy_bytes`] (`sdhop-train upgrade`)
/// reads.
pub const MIN_FORMAT_VERSION: u32 = 1;
/// The first version with a digest and an explicit feature kind.
pub const DIGEST_FORMAT_VERSION: u32 = 3;
/// Metadata key of the JSON description.
pub const META_KEY: &str = "sdhop";
/// Metadata key of the digest ([`content_digest`]).
pub const DIGEST_KEY: &str = "sdhop.sha256";
/// Largest template side in cells a file may declare.
pub const MAX_TEMPLATE_CELLS: usize = 256;
/// Least overlap (intersection over union) between a detection's box and
/// the box of the segmenter's location that segments it
/// ([`Model::segmenter`]); at 0.7 the masks came out a little worse
/// (`docs/benchmarks.md`, 2026-11-30).
pub const SEGMENTER_MIN_IOU: f64 = 0.5;
/// Tensor name prefix of the segmenter's weights in a file.
pub const SEGMENTER_PREFIX: &str = "segmenter.";

/// Errors reading or writing a weights file.
#[derive(Debug, Error)]
pub enum ModelError {
    #[error("cannot read or write {path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("not a valid safetensors file: {0}")]
    Format(String),
    #[error("missing metadata key `{META_KEY}`")]
    MissingMeta,
    #[error("bad metadata: {0}")]
    Meta(String),
    #[error("unsupported format version {found} (this build reads {MIN_FORMAT_VERSION} to {FORMAT_VERSION})")]
    Version { found: u32 },
    #[error("format version {found} has no digest of its contents: check the file is the one trained, then rewrite it with `sdhop-train upgrade FILE`")]
    Legacy { found: u32 },
    #[error("the file's contents do not match its digest (written {written}, computed {computed}): its tensors or metadata changed after training; restore or retrain it")]
    Digest { written: String, computed: String },
    #[error("missing metadata key `{DIGEST_KEY}` (a format {FORMAT_VERSION} file always has one)")]
    MissingDigest,
    #[error("the metadata does not state the feature kind (`pyramid.features`), which format {FORMAT_VERSION} requires")]
    MissingFeatureKind,
    #[error("missing tensor `{0}`")]
    MissingTensor(String),
    #[error("tensor `{name}` has dtype {dtype} and shape {shape:?}, expected F32 {expected:?}")]
    Shape {
        name: String,
        dtype: String,
        shape: Vec<usize>,
        expected: Vec<usize>,
    },
    #[error("inconsistent model: {0}")]
    Invalid(String),
    #[error("invalid weights: {0}")]
    Weights(#[from] VisionError),
}

/// A viewpoint's description.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewMeta {
    /// Object label of this component (several objects can share a model).
    pub label: String,
    /// Template height in cells.
    pub rows: usize,
    /// Template width in cells.
    pub cols: usize,
    /// The component's mean viewing direction in the object's mesh frame
    /// (unit vector from the object towards the camera), for models
    /// trained from a mesh.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub direction: Option<[f64; 3]>,
    /// Representative rotations (camera from object, unit quaternions
    /// `[w, x, y, z]`) of the component's training views, for models
    /// trained from a mesh: the start poses of `POST /pose` without an
    /// initial pose.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub rotations: Vec<[f64; 4]>,
    /// Where the component's training examples came from: the names of
    /// its training views, the representative (medoid) first, or
    /// `single-pose` for the masked occluded photographs of one viewpoint.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub views: Vec<String>,
}

/// A correction of the reported box, the simplest form of DPM's
/// bounding-box prediction: the box's centre moves by `(dx * width, dy *
/// height)` and its size is scaled by `(sw, sh)`. Fitted by
/// cross-validation over the training photographs (`sdhop-train train
/// --box-folds`): on photographs a template has not seen, learned cells
/// fire on the core of the object and the window comes out smaller than
/// the object's box (LM-O, box-only: median 0.82-0.85 of its size).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct BoxCorrection {
    pub dx: f64,
    pub dy: f64,
    pub sw: f64,
    pub sh: f64,
    /// Held-out detections it was fitted on.
    pub samples: usize,
}

impl BoxCorrection {
    /// Largest scale and shift a correction may apply.
    pub const MAX_SCALE: f64 = 1.5;
    pub const MAX_SHIFT: f64 = 0.25;

    /// The corrected box of `(x, y, width, height)`.
    pub fn apply(&self, (x, y, w, h): (f64, f64, f64, f64)) -> (f64, f64, f64, f64) {
        let (cx, cy) = (x + 0.5 * w + self.dx * w, y + 0.5 * h + self.dy * h);
        let (nw, nh) = (w * self.sw, h * self.sh);
        (cx - 0.5 * nw, cy - 0.5 * nh, nw, nh)
    }

    /// Whether its numbers are within the limits above.
    pub fn is_valid(&self) -> bool {
        let scale =
            |s: f64| s.is_finite() && (1.0 / Self::MAX_SCALE..=Self::MAX_SCALE).contains(&s);
        let shift = |d: f64| d.is_finite() && d.abs() <= Self::MAX_SHIFT;
        scale(self.sw) && scale(self.sh) && shift(self.dx) && shift(self.dy)
    }
}

/// JSON metadata of a weights file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelMeta {
    pub format_version: u32,
    /// Model name (by convention the file stem).
    pub name: String,
    pub cell_size: usize,
    /// Standard clique size `K` of the higher-order potentials.
    pub hop_k: usize,
    /// Which neighbour pairs carry the Potts term (absent in older files:
    /// every 4-connected pair).
    #[serde(default)]
    pub pairwise: PairwiseMode,
    pub pyramid: PyramidParams,
    /// For learned cells (`pyramid.features` = `cnn`): the fingerprint of
    /// the cell projection the model was trained on
    /// ([`crate::vision::cells::CellProjection::fingerprint`]); a build
    /// with other cells refuses the model. Absent for HOG.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cells: Option<String>,
    pub segmentation: SegmentParams,
    /// Default detection settings (threshold, NMS, truncation, refinement).
    pub detection: DetectParams,
    pub viewpoints: Vec<ViewMeta>,
    /// How to turn a detection's template window into the box reported
    /// (fitted on held-out training photographs; absent: the window as it
    /// is).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub box_correction: Option<BoxCorrection>,
    /// Free-form provenance: how the weights were made, settings, figures.
    #[serde(default)]
    pub provenance: serde_json::Value,
    /// The description of the model that segments this one's detections
    /// ([`Model::segmenter`]), where it has one; always that model's own.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub segmenter: Option<Box<ModelMeta>>,
}

/// A model: metadata, one weight set per viewpoint, and per viewpoint its
/// pixel shape model where one was learned.
#[derive(Clone, Debug, PartialEq)]
pub struct Model {
    pub meta: ModelMeta,
    pub views: Vec<ViewWeights>,
    pub shapes: Vec<Option<ShapeModel>>,
    /// "Both kinds per object": a model of the same object on other cells
    /// (HOG beside learned cells) that places and segments each of this
    /// model's detections: its best location whose box overlaps the
    /// detection's by [`SEGMENTER_MIN_IOU`] or more gives the masks, while
    /// the score and the box stay this model's. Learned cells find the
    /// kitchen objects better and HOG segments them better (issue 63,
    /// `docs/benchmarks.md` 2026-11-30). Set with [`Model::with_segmenter`].
    pub segmenter: Option<Box<Model>>,
    /// Stage 1's low-rank bound of `views`, built on first use (see
    /// [`Model::low_rank`]).
    low_rank: LowRankCache,
}

/// A [`LowRank`] built once per model (not part of its value: two models
/// with equal weights are equal whether it was built or not).
#[derive(Clone, Default)]
struct LowRankCache(std::sync::OnceLock<std::sync::Arc<LowRank>>);

impl PartialEq for LowRankCache {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl std::fmt::Debug for LowRankCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(if self.0.get().is_some() {
            "LowRank(built)"
        } else {
            "LowRank(not built)"
        })
    }
}

impl Model {
    /// Builds a model and checks it.
    pub fn new(meta: ModelMeta, views: Vec<ViewWeights>) -> Result<Self, ModelError> {
        let shapes = vec![None; views.len()];
        Self::checked(meta, views, shapes)
    }

    /// The model of these parts, checked.
    fn checked(
        meta: ModelMeta,
        views: Vec<ViewWeights>,
        shapes: Vec<Option<ShapeModel>>,
    ) -> Result<Self, ModelError> {
        Self::assembled(meta, views, shapes, None)
    }

    /// The model of these parts and this segmenter, checked.
    fn assembled(
        meta: ModelMeta,
        views: Vec<ViewWeights>,
        shapes: Vec<Option<ShapeModel>>,
        segmenter: Option<Model>,
    ) -> Result<Self, ModelError> {
        let m = Self {
            meta,
            views,
            shapes,
            segmenter: segmenter.map(Box::new),
            low_rank: LowRankCache::default(),
        };
        m.validate()?;
        Ok(m)
    }

    /// This model with `segmenter` placing and segmenting its detections
    /// ([`Model::segmenter`]): a model of the same object labels on other
    /// cells, without a segmenter of its own. Its description is kept in
    /// this model's metadata (`segmenter`), so the file carries both.
    pub fn with_segmenter(mut self, segmenter: Model) -> Result<Self, ModelError> {
        self.meta.segmenter = Some(Box::new(segmenter.meta.clone()));
        self.segmenter = Some(Box::new(segmenter));
        self.validate()?;
        Ok(self)
    }

    /// This model without a segmenter.
    pub fn without_segmenter(mut self) -> Self {
        self.meta.segmenter = None;
        self.segmenter = None;
        self
    }

    /// The model with these shape models (one per viewpoint); the file it
    /// writes is of the current format.
    pub fn with_shapes(mut self, shapes: Vec<Option<ShapeModel>>) -> Result<Self, ModelError> {
        self.shapes = shapes;
        self.meta.format_version = FORMAT_VERSION;
        self.validate()?;
        Ok(self)
    }

    /// Stage 1's low-rank bound of the components' filters, built on the
    /// first call (the weights must not change afterwards).
    pub fn low_rank(&self) -> &LowRank {
        self.low_rank
            .0
            .get_or_init(|| std::sync::Arc::new(LowRank::new(&self.views)))
    }

    /// The pixel size `(width, height)` of viewpoint `a`'s shape model.
    pub fn shape_size(&self, a: usize) -> (usize, usize) {
        let v = &self.meta.viewpoints[a];
        (v.cols * self.meta.cell_size, v.rows * self.meta.cell_size)
    }

    /// Distinct object labels, in viewpoint order.
    pub fn labels(&self) -> Vec<String> {
        let mut out: Vec<String> = Vec::new();
        for v in &self.meta.viewpoints {
            if !out.contains(&v.label) {
                out.push(v.label.clone());
            }
        }
        out
    }

    /// Checks the metadata against the weights and the weights themselves.
    pub fn validate(&self) -> Result<(), ModelError> {
        let m = &self.meta;
        if !(MIN_FORMAT_VERSION..=FORMAT_VERSION).contains(&m.format_version) {
            return Err(ModelError::Version {
                found: m.format_version,
            });
        }
        if self.shapes.len() != self.views.len() {
            return Err(ModelError::Invalid(format!(
                "{} shape model slots for {} viewpoints",
                self.shapes.len(),
                self.views.len()
            )));
        }
        if m.cell_size != CELL_SIZE {
            return Err(ModelError::Invalid(format!(
                "cell size {} (this build computes {CELL_SIZE}-pixel cells)",
                m.cell_size
            )));
        }
        if m.hop_k == 0 || m.hop_k > 64 {
            return Err(ModelError::Invalid(format!(
                "K = {} out of range 1..=64",
                m.hop_k
            )));
        }
        if m.viewpoints.is_empty() || m.viewpoints.len() != self.views.len() {
            return Err(ModelError::Invalid(format!(
                "{} viewpoints described, {} weight sets",
                m.viewpoints.len(),
                self.views.len()
            )));
        }
        if m.name.is_empty() {
            return Err(ModelError::Invalid("empty model name".into()));
        }
        if let Some(c) = m.box_correction.filter(|c| !c.is_valid()) {
            return Err(ModelError::Invalid(format!(
                "box correction {c:?} out of range (shift at most {}, scale within 1/{} .. {})",
                BoxCorrection::MAX_SHIFT,
                BoxCorrection::MAX_SCALE,
                BoxCorrection::MAX_SCALE
            )));
        }
        for (a, (vm, w)) in m.viewpoints.iter().zip(&self.views).enumerate() {
            if vm.rows == 0
                || vm.cols == 0
                || vm.rows > MAX_TEMPLATE_CELLS
                || vm.cols > MAX_TEMPLATE_CELLS
            {
                return Err(ModelError::Invalid(format!(
                    "viewpoint {a}: template {}x{} cells out of range",
                    vm.rows, vm.cols
                )));
            }
            if (vm.rows, vm.cols) != (w.rows, w.cols)
                || w.w_hop.len() != m.hop_k + 1
                || w.pair_mode != m.pairwise
            {
                return Err(ModelError::Invalid(format!(
                    "viewpoint {a}: metadata and weights disagree"
                )));
            }
            w.validate()?;
            if let Some(Some(s)) = self.shapes.get(a) {
                let (sw, sh) = (vm.cols * m.cell_size, vm.rows * m.cell_size);
                if !s.valid() || (s.width, s.height) != (sw, sh) {
                    return Err(ModelError::Invalid(format!(
                        "viewpoint {a}: shape model {}x{} (expected {sw}x{sh}, probabilities in [0, 1])",
                        s.width, s.height
                    )));
                }
                if m.format_version < 2 {
                    return Err(ModelError::Invalid(
                        "shape models need format version 2".into(),
                    ));
                }
            }
        }
        m.pyramid.validate()?;
        match (m.pyramid.features, &m.cells) {
            (FeatureKind::Hog, None) => {}
            (FeatureKind::Hog, Some(_)) => {
                return Err(ModelError::Invalid(
                    "a HOG model names a cell projection".into(),
                ))
            }
            (FeatureKind::Cnn, cells) => {
                let lc = LearnedCells::builtin()?;
                let here = lc.projection.fingerprint();
                if cells.as_deref() != Some(here.as_str()) {
                    return Err(ModelError::Invalid(format!(
                        "trained on learned cells {}, this build computes cells {here} ({}): retrain the model with this build, or name the backbone and projection it was trained on in {} and {}",
                        cells.as_deref().unwrap_or("(none named)"),
                        lc.backbone.name,
                        crate::vision::cells::BACKBONE_ENV,
                        crate::vision::cells::PROJECTION_ENV,
                    )));
                }
            }
        }
        m.segmentation.validate()?;
        m.detection.validate()?;
        self.validate_segmenter()
    }

    /// The segmenter's own checks, and that it fits this model: described
    /// in the metadata as it is, of the same objects, on other cells, with
    /// no segmenter of its own.
    fn validate_segmenter(&self) -> Result<(), ModelError> {
        let described = self.meta.segmenter.as_deref();
        let Some(seg) = self.segmenter.as_deref() else {
            return match described {
                None => Ok(()),
                Some(_) => Err(ModelError::Invalid(
                    "the metadata describes a segmenter the model lacks".into(),
                )),
            };
        };
        if described != Some(&seg.meta) {
            return Err(ModelError::Invalid(
                "the metadata's segmenter is not the model's".into(),
            ));
        }
        if seg.segmenter.is_some() {
            return Err(ModelError::Invalid(
                "a segmenter cannot have a segmenter of its own".into(),
            ));
        }
        if seg.labels() != self.labels() {
            return Err(ModelError::Invalid(format!(
                "the segmenter finds {:?}, the model {:?}: they must be models of the same objects",
                seg.labels(),
                self.labels()
            )));
        }
        if seg.meta.pyramid.features == self.meta.pyramid.features {
            return Err(ModelError::Invalid(
                "the segmenter uses the model's own cells; it must use the other kind".into(),
            ));
        }
        seg.validate()
    }

    /// Sets the pixel refinement to this build's for the model's cells
    /// ([`crate::vision::refine::RefineParams::for_cells`]): the refinement
    /// follows detection and trains nothing, so a model made before its
    /// weights were chosen again can take them (`sdhop-train upgrade
    /// --refine`). The change is recorded in the provenance under
    /// `refine_set`; returns whether anything changed.
    pub fn refresh_refinement(&mut self) -> bool {
        let want = crate::vision::refine::RefineParams::for_cells(self.meta.pyramid.features);
        let old = self.meta.detection.refine;
        if old == want {
            return false;
        }
        self.meta.detection.refine = want;
        if !self.meta.provenance.is_object() {
            self.meta.provenance = serde_json::json!({});
        }
        if let Some(p) = self.meta.provenance.as_object_mut() {
            let entry = serde_json::json!({ "from": old, "to": want });
            match p.get_mut("refine_set").and_then(|v| v.as_array_mut()) {
                Some(list) => list.push(entry),
                None => {
                    p.insert("refine_set".into(), serde_json::json!([entry]));
                }
            }
        }
        true
    }

    /// This model with `other`'s components appended, each of their scores
    /// moved by `offset` (taken from their bias): a single-pose model joined
    /// with view components trained apart, their scores calibrated against
    /// its own (`sdhop-train join`). Both must be models of one object, of
    /// the same cells, pyramid, segmentation, `K` and pairwise mode; the
    /// detection settings, box correction and name are this model's, and
    /// `other`'s provenance is kept under `joined`.
    pub fn joined(&self, other: &Model, offset: f64) -> Result<Model, ModelError> {
        let (a, b) = (&self.meta, &other.meta);
        let differ = |what: &str| {
            Err(ModelError::Invalid(format!(
                "cannot join {} and {}: their {what} differ",
                a.name, b.name
            )))
        };
        if self.labels() != other.labels() || self.labels().len() != 1 {
            return differ("objects (each must be a model of the same one object)");
        }
        if a.pyramid != b.pyramid || a.cells != b.cells {
            return differ("cell features or pyramids");
        }
        if a.segmentation != b.segmentation {
            return differ("segmentation settings");
        }
        if (a.hop_k, a.pairwise) != (b.hop_k, b.pairwise) {
            return differ("higher-order K or pairwise modes");
        }
        if !offset.is_finite() {
            return Err(ModelError::Invalid(format!(
                "join offset must be finite, got {offset}"
            )));
        }
        let mut meta = a.clone();
        meta.viewpoints.extend(b.viewpoints.iter().cloned());
        meta.format_version = a.format_version.max(b.format_version);
        if let Some(p) = meta.provenance.as_object_mut() {
            p.insert(
                "joined".into(),
                serde_json::json!({
                    "components_from": b.name,
                    "offset": offset,
                    "provenance": b.provenance,
                }),
            );
        }
        let mut views = self.views.clone();
        views.extend(other.views.iter().map(|w| {
            // A detection's score is minus its energy, which adds the bias.
            let mut w = w.clone();
            w.bias -= offset as f32;
            w
        }));
        let mut shapes = self.shapes.clone();
        shapes.extend(other.shapes.iter().cloned());
        // The base's segmenter segments the joined components' detections
        // too.
        meta.segmenter = None;
        let joined = Self::checked(meta, views, shapes)?;
        match &self.segmenter {
            Some(seg) => joined.with_segmenter((**seg).clone()),
            None => Ok(joined),
        }
    }
}

mod file;
pub use file::content_digest;

#[cfg(test)]
mod tests;

/// Each of `models` with the one of `segmenters` that finds the same
/// objects as its segmenter ([`Model::with_segmenter`]); a model without
/// one, or with several, is an error.
pub fn with_segmenters(
    models: Vec<Model>,
    segmenters: Vec<Model>,
) -> Result<Vec<Model>, ModelError> {
    models
        .into_iter()
        .map(|m| {
            let mut same = segmenters.iter().filter(|s| s.labels() == m.labels());
            match (same.next(), same.next()) {
                (Some(s), None) => m.with_segmenter(s.clone()),
                (None, _) => Err(ModelError::Invalid(format!(
                    "no segmenter of {:?} for model {}",
                    m.labels(),
                    m.meta.name
                ))),
                (Some(_), Some(_)) => Err(ModelError::Invalid(format!(
                    "several segmenters of {:?} for model {}",
                    m.labels(),
                    m.meta.name
                ))),
            }
        })
        .collect()
}

/// [`with_segmenters`] of models that travel with something each (a
/// training report): each keeps its own.
pub fn with_segmenters_kept<R, S>(
    models: Vec<(Model, R)>,
    segmenters: Vec<(Model, S)>,
) -> Result<Vec<(Model, R)>, ModelError> {
    let (models, kept): (Vec<Model>, Vec<R>) = models.into_iter().unzip();
    let segs = segmenters.into_iter().map(|(m, _)| m).collect();
    Ok(with_segmenters(models, segs)?
        .into_iter()
        .zip(kept)
        .collect())
}

/// The `*.safetensors` files of a folder, sorted by name.
pub fn model_paths(dir: &std::path::Path) -> Result<Vec<std::path::PathBuf>, ModelError> {
    let mut found: Vec<std::path::PathBuf> = std::fs::read_dir(dir)
        .map_err(|source| ModelError::Io {
            path: dir.display().to_string(),
            source,
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "safetensors"))
        .collect();
    found.sort();
    Ok(found)
}
