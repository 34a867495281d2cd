//! The weights file itself: safetensors tensors and the JSON metadata,
//! written with and checked against the digest of their contents.

use std::collections::HashMap;
use std::path::Path;

use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use sha2::{Digest, Sha256};

use super::*;

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

/// Appends the tensors of `views` and `shapes`, their names prefixed.
fn push_parts(
    buffers: &mut Vec<(String, Vec<usize>, Vec<u8>)>,
    prefix: &str,
    views: &[ViewWeights],
    shapes: &[Option<ShapeModel>],
) {
    for (a, w) in views.iter().enumerate() {
        let (r, c) = (w.rows, w.cols);
        let mut push = |name: &str, shape: Vec<usize>, data: Vec<u8>| {
            buffers.push((format!("{prefix}view{a}.{name}"), shape, data));
        };
        push("w_vis", vec![r, c, HOG_DIM], f32_bytes(strip(&w.w_vis)));
        push("w_occ", vec![r, c, HOG_DIM], f32_bytes(strip(&w.w_occ)));
        push("w_prior", vec![r, c], f32_bytes(w.w_prior.iter().copied()));
        push(
            "w_hop",
            vec![w.w_hop.len()],
            f32_bytes(w.w_hop.iter().copied()),
        );
        push(
            "scalars",
            vec![3],
            f32_bytes([w.w_trunc, w.w_pair, w.bias].into_iter()),
        );
        if let Some(Some(s)) = shapes.get(a) {
            push(
                "shape",
                vec![s.height, s.width],
                f32_bytes(s.prob.iter().copied()),
            );
            if let Some(c) = &s.colours {
                push("colours", vec![c.len()], f32_bytes(c.iter().copied()));
            }
        }
    }
}

/// An `F32` tensor of the expected shape, as numbers.
fn read_tensor(st: &SafeTensors, name: &str, expected: Vec<usize>) -> Result<Vec<f32>, ModelError> {
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
}

/// The weights and shape models `meta` describes, from the tensors whose
/// names start with `prefix`.
#[allow(clippy::type_complexity)]
fn read_parts(
    st: &SafeTensors,
    meta: &ModelMeta,
    prefix: &str,
) -> Result<(Vec<ViewWeights>, Vec<Option<ShapeModel>>), ModelError> {
    let read =
        |name: &str, expected: Vec<usize>| read_tensor(st, &format!("{prefix}{name}"), expected);
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
        shapes.push(if st.tensor(&format!("{prefix}{name}")).is_ok() {
            let colours_name = format!("view{a}.colours");
            let colours = if st.tensor(&format!("{prefix}{colours_name}")).is_ok() {
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
    Ok((views, shapes))
}

impl Model {
    /// This model as format `version` writes it (its segmenter's too),
    /// checked.
    fn as_version(&self, version: u32) -> Result<Model, ModelError> {
        let segmenter = match &self.segmenter {
            Some(seg) => {
                let mut meta = seg.meta.clone();
                meta.format_version = version;
                Some(Model::checked(meta, seg.views.clone(), seg.shapes.clone())?)
            }
            None => None,
        };
        let mut meta = self.meta.clone();
        meta.format_version = version;
        meta.segmenter = segmenter.as_ref().map(|s| Box::new(s.meta.clone()));
        Model::assembled(meta, self.views.clone(), self.shapes.clone(), segmenter)
    }

    /// Serialises to safetensors bytes of the current format, with the
    /// digest of the contents.
    pub fn to_bytes(&self) -> Result<Vec<u8>, ModelError> {
        self.serialize(FORMAT_VERSION)
    }

    /// Serialises as format `version` (a digest from
    /// [`DIGEST_FORMAT_VERSION`] on; older versions only for tests of
    /// their refusal and upgrade).
    pub(super) fn serialize(&self, version: u32) -> Result<Vec<u8>, ModelError> {
        let checked = self.as_version(version)?;
        let meta = checked.meta;
        let mut buffers: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::new();
        push_parts(&mut buffers, "", &self.views, &self.shapes);
        if let Some(seg) = &self.segmenter {
            push_parts(&mut buffers, SEGMENTER_PREFIX, &seg.views, &seg.shapes);
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
        let (views, shapes) = read_parts(&st, &meta, "")?;
        let segmenter = match &meta.segmenter {
            Some(sm) => {
                let (views, shapes) = read_parts(&st, sm, SEGMENTER_PREFIX)?;
                Some(Self::checked((**sm).clone(), views, shapes)?)
            }
            None => None,
        };
        Self::assembled(meta, views, shapes, segmenter)
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
}
