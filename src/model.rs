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
//! object's colour histogram from the training images.
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

use std::collections::HashMap;
use std::path::Path;

use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
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
}

/// A model: metadata, one weight set per viewpoint, and per viewpoint its
/// pixel shape model where one was learned.
#[derive(Clone, Debug, PartialEq)]
pub struct Model {
    pub meta: ModelMeta,
    pub views: Vec<ViewWeights>,
    pub shapes: Vec<Option<ShapeModel>>,
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

/// The digest a file of format 3 carries under [`DIGEST_KEY`]: SHA-256
/// (hex) of the metadata JSON exactly as stored and of every tensor in
/// order of name (its name, dtype, shape and bytes, each length-prefixed),
/// so that no byte that decides how the weights are read or what they are
/// can change unseen.
pub fn content_digest<'a, N, D>(
    meta_json: &str,
    tensors: impl Iterator<Item = (N, D, Vec<usize>, &'a [u8])>,
) -> String
where
    N: AsRef<str>,
    D: AsRef<str>,
{
    let mut tensors: Vec<_> = tensors.collect();
    tensors.sort_by(|a, b| a.0.as_ref().cmp(b.0.as_ref()));
    let mut h = Sha256::new();
    let mut field = |bytes: &[u8]| {
        h.update((bytes.len() as u64).to_le_bytes());
        h.update(bytes);
    };
    field(b"sdhop model digest 1");
    field(meta_json.as_bytes());
    for (name, dtype, shape, data) in &tensors {
        field(name.as_ref().as_bytes());
        field(dtype.as_ref().as_bytes());
        let dims: Vec<u8> = shape
            .iter()
            .flat_map(|d| (*d as u64).to_le_bytes())
            .collect();
        field(&dims);
        field(data);
    }
    h.finalize().iter().map(|b| format!("{b:02x}")).collect()
}

fn f32_bytes(v: impl Iterator<Item = f32>) -> Vec<u8> {
    v.flat_map(|x| x.to_le_bytes()).collect()
}

fn strip(padded: &[f32]) -> impl Iterator<Item = f32> + '_ {
    padded
        .chunks(HOG_STRIDE)
        .flat_map(|c| c[..HOG_DIM].iter().copied())
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
        let m = Self {
            meta,
            views,
            shapes,
            low_rank: LowRankCache::default(),
        };
        m.validate()?;
        Ok(m)
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
                let here = LearnedCells::builtin()?.projection.fingerprint();
                if cells.as_deref() != Some(here.as_str()) {
                    return Err(ModelError::Invalid(format!(
                        "trained on learned cells {}, this build computes cells {here}: retrain the model with this build",
                        cells.as_deref().unwrap_or("(none named)")
                    )));
                }
            }
        }
        m.segmentation.validate()?;
        m.detection.validate()?;
        Ok(())
    }

    /// Serialises to safetensors bytes of the current format, with the
    /// digest of the contents.
    pub fn to_bytes(&self) -> Result<Vec<u8>, ModelError> {
        self.serialize(FORMAT_VERSION)
    }

    /// Serialises as format `version` (a digest from
    /// [`DIGEST_FORMAT_VERSION`] on; older versions only for tests of
    /// their refusal and upgrade).
    fn serialize(&self, version: u32) -> Result<Vec<u8>, ModelError> {
        let mut meta = self.meta.clone();
        meta.format_version = version;
        Model::checked(meta.clone(), self.views.clone(), self.shapes.clone())?;
        let mut buffers: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::new();
        for (a, w) in self.views.iter().enumerate() {
            let (r, c) = (w.rows, w.cols);
            buffers.push((
                format!("view{a}.w_vis"),
                vec![r, c, HOG_DIM],
                f32_bytes(strip(&w.w_vis)),
            ));
            buffers.push((
                format!("view{a}.w_occ"),
                vec![r, c, HOG_DIM],
                f32_bytes(strip(&w.w_occ)),
            ));
            buffers.push((
                format!("view{a}.w_prior"),
                vec![r, c],
                f32_bytes(w.w_prior.iter().copied()),
            ));
            buffers.push((
                format!("view{a}.w_hop"),
                vec![w.w_hop.len()],
                f32_bytes(w.w_hop.iter().copied()),
            ));
            buffers.push((
                format!("view{a}.scalars"),
                vec![3],
                f32_bytes([w.w_trunc, w.w_pair, w.bias].into_iter()),
            ));
            if let Some(Some(s)) = self.shapes.get(a) {
                buffers.push((
                    format!("view{a}.shape"),
                    vec![s.height, s.width],
                    f32_bytes(s.prob.iter().copied()),
                ));
                if let Some(c) = &s.colours {
                    buffers.push((
                        format!("view{a}.colours"),
                        vec![c.len()],
                        f32_bytes(c.iter().copied()),
                    ));
                }
            }
        }
        let meta = serde_json::to_string(&meta).map_err(|e| ModelError::Meta(e.to_string()))?;
        let mut info = HashMap::from([(META_KEY.to_string(), meta.clone())]);
        if version >= DIGEST_FORMAT_VERSION {
            let tensors = buffers
                .iter()
                .map(|(name, shape, data)| (name.as_str(), "F32", shape.clone(), data.as_slice()));
            info.insert(DIGEST_KEY.to_string(), content_digest(&meta, tensors));
        }
        let views: Vec<(String, TensorView<'_>)> = buffers
            .iter()
            .map(|(name, shape, data)| {
                TensorView::new(Dtype::F32, shape.clone(), data)
                    .map(|t| (name.clone(), t))
                    .map_err(|e| ModelError::Format(e.to_string()))
            })
            .collect::<Result<_, _>>()?;
        safetensors::serialize(views, Some(info)).map_err(|e| ModelError::Format(e.to_string()))
    }

    /// Parses safetensors bytes of the current format; every inconsistency
    /// is an error, and so is a digest that does not match the contents,
    /// a missing feature kind, or an older format ([`ModelError::Legacy`]).
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, ModelError> {
        Self::parse(bytes, false)
    }

    /// [`Self::from_bytes`] that also reads formats 1 and 2, which carry no
    /// digest (a HOG model's metadata there names no feature kind): for
    /// `sdhop-train upgrade`, which rewrites them as the current format.
    pub fn from_legacy_bytes(bytes: &[u8]) -> Result<Self, ModelError> {
        Self::parse(bytes, true)
    }

    fn parse(bytes: &[u8], legacy: bool) -> Result<Self, ModelError> {
        let (_, header) =
            SafeTensors::read_metadata(bytes).map_err(|e| ModelError::Format(e.to_string()))?;
        let info = header.metadata().as_ref();
        let meta_json = info
            .and_then(|m| m.get(META_KEY))
            .ok_or(ModelError::MissingMeta)?;
        let meta: ModelMeta =
            serde_json::from_str(meta_json).map_err(|e| ModelError::Meta(e.to_string()))?;
        if !(MIN_FORMAT_VERSION..=FORMAT_VERSION).contains(&meta.format_version) {
            return Err(ModelError::Version {
                found: meta.format_version,
            });
        }
        let st = SafeTensors::deserialize(bytes).map_err(|e| ModelError::Format(e.to_string()))?;
        if meta.format_version >= DIGEST_FORMAT_VERSION {
            let written = info
                .and_then(|m| m.get(DIGEST_KEY))
                .ok_or(ModelError::MissingDigest)?;
            let computed = content_digest(
                meta_json,
                st.tensors().into_iter().map(|(name, t)| {
                    let dtype = format!("{:?}", t.dtype());
                    (name, dtype, t.shape().to_vec(), t.data())
                }),
            );
            if *written != computed {
                return Err(ModelError::Digest {
                    written: written.clone(),
                    computed,
                });
            }
            let raw: serde_json::Value =
                serde_json::from_str(meta_json).map_err(|e| ModelError::Meta(e.to_string()))?;
            if raw["pyramid"].get("features").is_none() {
                return Err(ModelError::MissingFeatureKind);
            }
        } else if !legacy {
            return Err(ModelError::Legacy {
                found: meta.format_version,
            });
        }
        let read = |name: &str, expected: Vec<usize>| -> Result<Vec<f32>, ModelError> {
            let t = st
                .tensor(name)
                .map_err(|_| ModelError::MissingTensor(name.to_string()))?;
            if t.dtype() != Dtype::F32 || t.shape() != expected.as_slice() {
                return Err(ModelError::Shape {
                    name: name.to_string(),
                    dtype: format!("{:?}", t.dtype()),
                    shape: t.shape().to_vec(),
                    expected,
                });
            }
            Ok(t.data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect())
        };
        let k = meta.hop_k;
        let mut views = Vec::with_capacity(meta.viewpoints.len());
        for (a, vm) in meta.viewpoints.iter().enumerate() {
            let (r, c) = (vm.rows, vm.cols);
            if r == 0 || c == 0 || r > MAX_TEMPLATE_CELLS || c > MAX_TEMPLATE_CELLS {
                return Err(ModelError::Invalid(format!(
                    "viewpoint {a}: template {r}x{c} cells out of range"
                )));
            }
            let pad = |v: Vec<f32>| -> Vec<f32> {
                v.chunks(HOG_DIM)
                    .flat_map(|cell| cell.iter().copied().chain(std::iter::once(0.0)))
                    .collect()
            };
            let w_vis = pad(read(&format!("view{a}.w_vis"), vec![r, c, HOG_DIM])?);
            let w_occ = pad(read(&format!("view{a}.w_occ"), vec![r, c, HOG_DIM])?);
            let w_prior = read(&format!("view{a}.w_prior"), vec![r, c])?;
            let w_hop = read(&format!("view{a}.w_hop"), vec![k + 1])?;
            let s = read(&format!("view{a}.scalars"), vec![3])?;
            views.push(ViewWeights {
                rows: r,
                cols: c,
                w_vis,
                w_occ,
                w_prior,
                w_trunc: s[0],
                w_pair: s[1],
                pair_mode: meta.pairwise,
                w_hop,
                bias: s[2],
            });
        }
        let mut shapes = Vec::with_capacity(views.len());
        for (a, vm) in meta.viewpoints.iter().enumerate() {
            let name = format!("view{a}.shape");
            let (sw, sh) = (
                vm.cols.saturating_mul(meta.cell_size),
                vm.rows.saturating_mul(meta.cell_size),
            );
            shapes.push(if st.tensor(&name).is_ok() {
                let colours_name = format!("view{a}.colours");
                let colours = if st.tensor(&colours_name).is_ok() {
                    Some(read(&colours_name, vec![COLOUR_BINS.pow(3)])?)
                } else {
                    None
                };
                Some(ShapeModel {
                    width: sw,
                    height: sh,
                    prob: read(&name, vec![sh, sw])?,
                    colours,
                })
            } else {
                None
            });
        }
        Self::checked(meta, views, shapes)
    }

    /// Writes the model to a file (atomically: a temporary file is renamed).
    pub fn save(&self, path: &Path) -> Result<(), ModelError> {
        let bytes = self.to_bytes()?;
        let io = |source| ModelError::Io {
            path: path.display().to_string(),
            source,
        };
        let tmp = path.with_extension("safetensors.tmp");
        std::fs::write(&tmp, bytes).map_err(io)?;
        std::fs::rename(&tmp, path).map_err(io)
    }

    /// Reads a model from a file.
    pub fn load(path: &Path) -> Result<Self, ModelError> {
        let bytes = std::fs::read(path).map_err(|source| ModelError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::from_bytes(&bytes)
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
        Self::checked(meta, views, shapes)
    }
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;

    #[test]
    fn joined_components_fire_moved_by_the_offset() {
        use crate::pipeline::{detect_image, DetectOptions};
        use crate::synth::{hand_model, scene, HandModelParams, SceneParams, SynthObject};
        let obj = SynthObject {
            cols: 12,
            rows: 10,
            seed: 11,
        };
        let m = hand_model(&obj, "obj", true, &HandModelParams::default()).unwrap();
        let sc = scene(&obj, &SceneParams::default()).unwrap();
        let opts = DetectOptions::default();
        let best = |model: &Model| {
            let r = detect_image(&sc.image, &[model], &opts).unwrap();
            let d = r.detections[0].clone();
            (d.score, d.viewpoint, d.bbox)
        };
        let (s0, v0, b0) = best(&m);
        assert_eq!(v0, 0);
        // Above: the appended copy wins by exactly the offset, same place.
        let up = m.joined(&m, 0.5).unwrap();
        assert_eq!(up.views.len(), 2);
        assert_eq!(up.meta.viewpoints.len(), 2);
        assert_eq!(up.meta.provenance["joined"]["offset"], 0.5);
        let (s1, v1, b1) = best(&up);
        assert_eq!(v1, 1);
        assert!((s1 - s0 - 0.5).abs() < 1e-4, "{s1} vs {s0}");
        assert_eq!(
            (b1.x, b1.y, b1.width, b1.height),
            (b0.x, b0.y, b0.width, b0.height)
        );
        // Below: the model's own component keeps the detection.
        let (s2, v2, _) = best(&m.joined(&m, -0.5).unwrap());
        assert_eq!(v2, 0);
        assert!((s2 - s0).abs() < 1e-9);
        // It round-trips through its file.
        assert_eq!(Model::from_bytes(&up.to_bytes().unwrap()).unwrap(), up);
        // Another object or other cells are refused.
        let other = hand_model(&obj, "other", true, &HandModelParams::default()).unwrap();
        assert!(m.joined(&other, 0.0).is_err());
        let mut cnn = m.clone();
        cnn.meta.pyramid.levels_per_octave += 1;
        assert!(m.joined(&cnn, 0.0).is_err());
        assert!(m.joined(&m, f64::NAN).is_err());
    }

    fn sample() -> Model {
        let mut w = ViewWeights::zeros(2, 3, 4);
        for (i, v) in w.w_vis.iter_mut().enumerate() {
            if i % HOG_STRIDE < HOG_DIM {
                *v = (i as f32 * 0.37).sin();
            }
        }
        w.w_occ[5] = 0.5;
        w.w_prior = vec![0.1, -0.2, 0.3, 0.0, 1.0, -1.0];
        w.w_pair = 0.25;
        w.w_hop = vec![0.0, 3.0, 4.0, 3.0, 0.0];
        w.bias = -0.7;
        w.w_trunc = 0.05;
        let meta = ModelMeta {
            format_version: FORMAT_VERSION,
            name: "cup".into(),
            cell_size: CELL_SIZE,
            hop_k: 4,
            pairwise: PairwiseMode::Grid,
            pyramid: PyramidParams::default(),
            cells: None,
            segmentation: SegmentParams::default(),
            detection: DetectParams::default(),
            viewpoints: vec![ViewMeta {
                label: "cup".into(),
                rows: 2,
                cols: 3,
                direction: None,
                rotations: Vec::new(),
                views: Vec::new(),
            }],
            box_correction: None,
            provenance: serde_json::json!({"made_by": "test"}),
        };
        Model::new(meta, vec![w]).unwrap()
    }

    #[test]
    fn round_trips_through_bytes_and_files() {
        let m = sample();
        let bytes = m.to_bytes().unwrap();
        assert_eq!(Model::from_bytes(&bytes).unwrap(), m);
        let dir = std::env::temp_dir().join(format!("sdhop-model-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("cup.safetensors");
        m.save(&p).unwrap();
        assert_eq!(Model::load(&p).unwrap(), m);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn shape_models_round_trip_and_format_1_files_still_load() {
        let m = sample();
        let shape = ShapeModel {
            width: 3 * CELL_SIZE,
            height: 2 * CELL_SIZE,
            prob: (0..6 * CELL_SIZE * CELL_SIZE)
                .map(|i| (i % 7) as f32 / 7.0)
                .collect(),
            colours: Some((0..4096).map(|i| (i % 3) as f32 / 4096.0).collect()),
        };
        let with = m.clone().with_shapes(vec![Some(shape.clone())]).unwrap();
        let back = Model::from_bytes(&with.to_bytes().unwrap()).unwrap();
        assert_eq!(back.shapes, vec![Some(shape.clone())]);
        assert_eq!(back.meta.format_version, FORMAT_VERSION);
        // A format 1 file (written before shape models): refused by the
        // server's reader, read by the upgrade's, no shapes.
        let old = m.serialize(1).unwrap();
        assert!(matches!(
            Model::from_bytes(&old),
            Err(ModelError::Legacy { found: 1 })
        ));
        let back = Model::from_legacy_bytes(&old).unwrap();
        assert_eq!(back.shapes, vec![None]);
        assert_eq!(back.meta.format_version, 1);
        // Format 2 with its shapes: the same, and upgraded it loads.
        let two = with.serialize(2).unwrap();
        assert!(matches!(
            Model::from_bytes(&two),
            Err(ModelError::Legacy { found: 2 })
        ));
        let upgraded = Model::from_legacy_bytes(&two).unwrap().to_bytes().unwrap();
        let back = Model::from_bytes(&upgraded).unwrap();
        assert_eq!(back.shapes, vec![Some(shape.clone())]);
        assert_eq!(back.meta.format_version, FORMAT_VERSION);
        // A shape of the wrong size or with probabilities out of range.
        let wrong = ShapeModel {
            width: 5,
            ..shape.clone()
        };
        assert!(m.clone().with_shapes(vec![Some(wrong)]).is_err());
        let mut out_of_range = shape;
        out_of_range.prob[0] = 1.5;
        assert!(m.with_shapes(vec![Some(out_of_range)]).is_err());
    }

    #[test]
    fn box_corrections_round_trip_apply_and_are_checked() {
        let mut m = sample();
        let c = BoxCorrection {
            dx: 0.02,
            dy: -0.04,
            sw: 1.18,
            sh: 1.21,
            samples: 40,
        };
        m.meta.box_correction = Some(c);
        let back = Model::from_bytes(&m.to_bytes().unwrap()).unwrap();
        assert_eq!(back.meta.box_correction, Some(c));
        // The box grows about its moved centre.
        let (x, y, w, h) = c.apply((100.0, 200.0, 50.0, 80.0));
        assert!((w - 59.0).abs() < 1e-9 && (h - 96.8).abs() < 1e-9);
        assert!((x + w / 2.0 - 126.0).abs() < 1e-9 && (y + h / 2.0 - 236.8).abs() < 1e-9);
        // Files without one load without one.
        assert_eq!(sample().meta.box_correction, None);
        for bad in [
            BoxCorrection { sw: 3.0, ..c },
            BoxCorrection { sh: 0.0, ..c },
            BoxCorrection { dx: 0.5, ..c },
            BoxCorrection { dy: f64::NAN, ..c },
        ] {
            m.meta.box_correction = Some(bad);
            assert!(
                matches!(m.validate(), Err(ModelError::Invalid(_))),
                "{bad:?}"
            );
        }
    }

    #[test]
    fn truncated_files_are_errors_not_panics() {
        let bytes = sample().to_bytes().unwrap();
        for cut in [0, 1, 7, 8, 20, bytes.len() / 2, bytes.len() - 1] {
            assert!(Model::from_bytes(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        assert!(matches!(
            Model::load(Path::new("/nonexistent/x.safetensors")),
            Err(ModelError::Io { .. })
        ));
    }

    #[test]
    fn inconsistent_models_are_refused() {
        let m = sample();
        let mut bad = m.clone();
        bad.meta.viewpoints[0].rows = 3;
        assert!(matches!(bad.to_bytes(), Err(ModelError::Invalid(_))));
        let mut bad = m.clone();
        bad.views[0].w_hop = vec![0.0, -1.0, 0.0, 0.0, 0.0];
        assert!(matches!(bad.validate(), Err(ModelError::Weights(_))));
        let mut bad = m.clone();
        bad.views[0].bias = f32::INFINITY;
        assert!(matches!(
            bad.validate(),
            Err(ModelError::Weights(VisionError::NonFinite(_)))
        ));
        let mut bad = m.clone();
        bad.meta.format_version = 99;
        assert!(matches!(
            bad.validate(),
            Err(ModelError::Version { found: 99 })
        ));
        // A file whose metadata claims a different template than its tensors.
        let mut meta_only = m.clone();
        meta_only.meta.viewpoints[0].cols = 4;
        meta_only.views[0] = ViewWeights::zeros(2, 4, 4);
        let mut bytes = meta_only.to_bytes().unwrap();
        // The metadata JSON sits escaped inside the header JSON.
        let needle = b"cols\\\":4";
        let at = bytes
            .windows(needle.len())
            .position(|w| w == needle)
            .unwrap();
        bytes[at + needle.len() - 1] = b'5';
        // The digest sees it first; with the digest made to match, the
        // tensors' shapes still refuse it.
        assert!(matches!(
            Model::from_bytes(&bytes),
            Err(ModelError::Digest { .. })
        ));
        let forged = edit_meta(&meta_only.to_bytes().unwrap(), true, |m| {
            m["viewpoints"][0]["cols"] = 5.into();
        });
        assert!(matches!(
            Model::from_bytes(&forged),
            Err(ModelError::Shape { .. })
        ));
    }

    #[test]
    fn a_model_of_each_feature_kind_round_trips_and_cells_must_match() {
        // HOG: the metadata states the kind (format 3), names no cells.
        let hog = sample();
        let bytes = hog.to_bytes().unwrap();
        let meta = serde_json::to_value(&hog.meta).unwrap();
        assert_eq!(meta["pyramid"]["features"], "hog");
        assert!(meta.get("cells").is_none());
        assert_eq!(Model::from_bytes(&bytes).unwrap(), hog);
        // Learned cells: the kind and the projection's fingerprint travel.
        let mut cnn = sample();
        cnn.meta.pyramid.features = FeatureKind::Cnn;
        cnn.meta.cells = FeatureKind::Cnn.fingerprint().unwrap();
        let back = Model::from_bytes(&cnn.to_bytes().unwrap()).unwrap();
        assert_eq!(back, cnn);
        assert_eq!(back.meta.pyramid.features, FeatureKind::Cnn);
        // Trained on other cells, or naming none: refused, saying why.
        let mut other = cnn.clone();
        other.meta.cells = Some("0123456789abcdef".into());
        let err = other.validate().unwrap_err().to_string();
        assert!(
            err.contains("0123456789abcdef") && err.contains("retrain"),
            "{err}"
        );
        let mut none = cnn;
        none.meta.cells = None;
        assert!(matches!(none.validate(), Err(ModelError::Invalid(_))));
        let mut hog_named = hog;
        hog_named.meta.cells = Some("0123456789abcdef".into());
        assert!(matches!(hog_named.validate(), Err(ModelError::Invalid(_))));
    }

    /// The file's header JSON and where its metadata string lies in it.
    fn header_of(bytes: &[u8]) -> (usize, serde_json::Value) {
        let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
        (n, serde_json::from_slice(&bytes[8..8 + n]).unwrap())
    }

    /// `bytes` with its header replaced by `header` (padded as safetensors
    /// pads it), the tensors' bytes unchanged.
    fn with_header(bytes: &[u8], header: &serde_json::Value) -> Vec<u8> {
        let (n, _) = header_of(bytes);
        let mut text = serde_json::to_vec(header).unwrap();
        while text.len() % 8 != 0 {
            text.push(b' ');
        }
        let mut out = (text.len() as u64).to_le_bytes().to_vec();
        out.extend_from_slice(&text);
        out.extend_from_slice(&bytes[8 + n..]);
        out
    }

    /// `bytes` with its metadata JSON edited by `edit` (the digest kept, or
    /// recomputed as a careful forger would).
    fn edit_meta(bytes: &[u8], recompute: bool, edit: impl Fn(&mut serde_json::Value)) -> Vec<u8> {
        let (_, mut header) = header_of(bytes);
        let mut meta: serde_json::Value =
            serde_json::from_str(header["__metadata__"][META_KEY].as_str().unwrap()).unwrap();
        edit(&mut meta);
        let meta = serde_json::to_string(&meta).unwrap();
        if recompute {
            let st = SafeTensors::deserialize(bytes).unwrap();
            let digest = content_digest(
                &meta,
                st.tensors().into_iter().map(|(name, t)| {
                    (
                        name,
                        format!("{:?}", t.dtype()),
                        t.shape().to_vec(),
                        t.data(),
                    )
                }),
            );
            header["__metadata__"][DIGEST_KEY] = digest.into();
        }
        header["__metadata__"][META_KEY] = meta.into();
        with_header(bytes, &header)
    }

    #[test]
    fn files_that_were_changed_after_training_are_refused() {
        let mut cnn = sample();
        cnn.meta.pyramid.features = FeatureKind::Cnn;
        cnn.meta.cells = FeatureKind::Cnn.fingerprint().unwrap();
        let cnn_bytes = cnn.to_bytes().unwrap();
        let hog_bytes = sample().to_bytes().unwrap();
        // The helpers themselves change nothing that loads when they edit
        // nothing (the JSON's key order may change; the digest follows).
        let same = edit_meta(&cnn_bytes, true, |_| {});
        assert_eq!(Model::from_bytes(&same).unwrap(), cnn);
        // A learned-cell model whose header no longer names its kind.
        let unkind = edit_meta(&cnn_bytes, false, |m| {
            m["pyramid"].as_object_mut().unwrap().remove("features");
            m.as_object_mut().unwrap().remove("cells");
        });
        assert!(matches!(
            Model::from_bytes(&unkind),
            Err(ModelError::Digest { .. })
        ));
        // The same with the digest recomputed: the kind is required.
        let forged = edit_meta(&cnn_bytes, true, |m| {
            m["pyramid"].as_object_mut().unwrap().remove("features");
            m.as_object_mut().unwrap().remove("cells");
        });
        assert!(matches!(
            Model::from_bytes(&forged),
            Err(ModelError::MissingFeatureKind)
        ));
        // A HOG model whose header claims learned cells.
        let claims = edit_meta(&hog_bytes, false, |m| {
            m["pyramid"]["features"] = "cnn".into();
            m["cells"] = FeatureKind::Cnn.fingerprint().unwrap().into();
        });
        assert!(matches!(
            Model::from_bytes(&claims),
            Err(ModelError::Digest { .. })
        ));
        // One flipped byte inside a weight tensor (the last byte of the
        // file is a tensor's).
        let mut flipped = cnn_bytes.clone();
        let last = flipped.len() - 1;
        flipped[last] ^= 0x01;
        let err = Model::from_bytes(&flipped).unwrap_err();
        assert!(matches!(err, ModelError::Digest { .. }), "{err}");
        assert!(err.to_string().contains("retrain"), "{err}");
        assert!(!err.to_string().contains('\n'), "one line: {err}");
        // The digest removed: refused.
        let (_, mut header) = header_of(&cnn_bytes);
        header["__metadata__"]
            .as_object_mut()
            .unwrap()
            .remove(DIGEST_KEY);
        assert!(matches!(
            Model::from_bytes(&with_header(&cnn_bytes, &header)),
            Err(ModelError::MissingDigest)
        ));
        // A careful forger's format 2 file (no digest): only the upgrade
        // reads it.
        let downgraded = edit_meta(&cnn_bytes, false, |m| m["format_version"] = 2.into());
        assert!(matches!(
            Model::from_bytes(&downgraded),
            Err(ModelError::Legacy { found: 2 })
        ));
    }
}
