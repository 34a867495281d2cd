//! What a cell's vector is: the feature kind a model was trained on, and
//! the learned (convolutional) cells.
//!
//! A cell is 8x8 pixels of a pyramid level and carries [`HOG_DIM`] numbers
//! whatever its kind, so that the templates, the visibility model, the
//! bounds and the GPU responses serve both kinds unchanged:
//! - `hog`: Felzenszwalb's 31 HOG features ([`super::hog`]);
//! - `cnn`: the pretrained backbone's 40 channels at stride 8
//!   ([`super::cnn`]; its output cell `i` is centred on input pixel
//!   `8i + 3.5`, as HOG's cell `i` covers `[8i, 8i + 8)`), standardised and
//!   projected onto their 31 principal directions by a fixed
//!   [`CellProjection`], scaled so that a cell's mean squared norm is
//!   HOG's on the same photographs (the regularisation constant and the
//!   thresholds keep their meaning).
//!
//! The backbone and the projection are built into the binary from
//! `models/backbones/` (nothing is read or downloaded at run time); a
//! model of kind `cnn` records the projection's fingerprint, and a model
//! trained on another projection is refused at load.

use std::sync::OnceLock;

use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use super::cnn::{f32_tensor, Backbone, FeatureMap};
use super::hog::{hog_until, HogMap, CELL_SIZE, HOG_DIM, HOG_STRIDE};
use super::image::{area_weights, smooth_weights, ColorImage};
use super::{Deadline, VisionError};

/// The backbone file, as `scripts/convert_efficientnet_lite0.py` wrote it.
pub const BACKBONE_FILE: &[u8] =
    include_bytes!("../../models/backbones/efficientnet_lite0_s8.safetensors");
/// The cells' projection, as `sdhop-train cells` fitted it.
pub const PROJECTION_FILE: &[u8] =
    include_bytes!("../../models/backbones/efficientnet_lite0_s8_cells.safetensors");

/// What a cell's vector is.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FeatureKind {
    /// HOG (every model before learned cells).
    #[default]
    Hog,
    /// The pretrained convolutional backbone's cells, projected.
    Cnn,
}

impl FeatureKind {
    pub fn name(&self) -> &'static str {
        match self {
            FeatureKind::Hog => "hog",
            FeatureKind::Cnn => "cnn",
        }
    }

    /// Parses `hog` or `cnn`.
    pub fn parse(s: &str) -> Result<Self, String> {
        match s {
            "hog" => Ok(FeatureKind::Hog),
            "cnn" => Ok(FeatureKind::Cnn),
            _ => Err(format!("unknown feature kind {s:?} (hog or cnn)")),
        }
    }

    /// The fingerprint of this build's cells of this kind, which a model
    /// trained on them records (`None` for HOG).
    pub fn fingerprint(&self) -> Result<Option<String>, VisionError> {
        match self {
            FeatureKind::Hog => Ok(None),
            FeatureKind::Cnn => Ok(Some(LearnedCells::builtin()?.projection.fingerprint())),
        }
    }

    /// `img` resized to a `w x h` pyramid level as this kind's cells want
    /// it: HOG's levels as ever (area averages, blocks when upsampled),
    /// learned cells' interpolated, since the backbone sees the blocks.
    pub fn resize_until(
        &self,
        img: &ColorImage,
        w: usize,
        h: usize,
        deadline: Deadline,
    ) -> Result<ColorImage, VisionError> {
        match self {
            FeatureKind::Hog => img.resize_area_until(w, h, deadline),
            FeatureKind::Cnn => img.resize_smooth_until(w, h, deadline),
        }
    }

    /// The taps of [`Self::resize_until`] along one axis from `src` to
    /// `dst` pixels (for the GPU's resize, which must agree with it).
    pub fn resize_weights(&self, src: usize, dst: usize) -> Vec<Vec<(usize, f32)>> {
        match self {
            FeatureKind::Hog => area_weights(src, dst),
            FeatureKind::Cnn => smooth_weights(src, dst),
        }
    }

    /// Whether a level of `pixels` is computed strip by strip on the CPU
    /// (learned cells above [`STRIP_PIXELS`], whose backbone's maps would
    /// otherwise grow with the level; HOG's working memory is small).
    pub fn in_strips(&self, pixels: usize) -> bool {
        match self {
            FeatureKind::Hog => false,
            FeatureKind::Cnn => pixels > STRIP_PIXELS,
        }
    }

    /// The cells of `img`: `floor(w / 8) x floor(h / 8)` of them.
    pub fn cells(&self, img: &ColorImage) -> Result<HogMap, VisionError> {
        self.cells_until(img, Deadline::NONE)
    }

    /// [`Self::cells`] that gives up with
    /// [`VisionError::DeadlineExceeded`] once `deadline` has passed (HOG
    /// every few dozen pixel rows, the backbone before every band of
    /// every layer).
    pub fn cells_until(&self, img: &ColorImage, deadline: Deadline) -> Result<HogMap, VisionError> {
        match self {
            FeatureKind::Hog => hog_until(img, deadline),
            FeatureKind::Cnn => LearnedCells::builtin()?.cells_until(img, deadline),
        }
    }
}

impl std::fmt::Display for FeatureKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A fixed linear map from the backbone's channels to a cell's
/// [`HOG_DIM`] numbers: `cell = basis * (features - mean)`.
#[derive(Clone, Debug, PartialEq)]
pub struct CellProjection {
    /// The backbone's channels.
    pub channels: usize,
    /// Mean of every channel over the fitting photographs.
    pub mean: Vec<f32>,
    /// `HOG_DIM x channels`, row-major (standardisation, principal
    /// directions and the overall scale folded in).
    pub basis: Vec<f32>,
    /// Share of the standardised channels' variance the kept directions
    /// carry.
    pub variance_kept: f64,
}

fn bad(msg: impl Into<String>) -> VisionError {
    VisionError::InvalidParameter(msg.into())
}

impl CellProjection {
    /// Fits the projection to backbone maps of representative photographs
    /// (every cell of every map counts once): channels standardised, the
    /// [`HOG_DIM`] leading principal directions of their covariance kept,
    /// and the whole scaled so that a cell's mean squared norm is
    /// `target_sq_norm`.
    pub fn fit(maps: &[FeatureMap], target_sq_norm: f64) -> Result<Self, VisionError> {
        let c = maps.first().map(|m| m.channels).unwrap_or(0);
        if c < HOG_DIM || maps.iter().any(|m| m.channels != c) {
            return Err(bad(format!(
                "cell projection: needs maps of one channel count >= {HOG_DIM}"
            )));
        }
        let mut sum = vec![0.0f64; c];
        let mut cross = vec![0.0f64; c * c];
        let mut n = 0usize;
        let mut v = vec![0.0f64; c];
        for m in maps {
            let plane = m.width * m.height;
            for i in 0..plane {
                for (ch, x) in v.iter_mut().enumerate() {
                    *x = f64::from(m.data[ch * plane + i]);
                }
                for a in 0..c {
                    sum[a] += v[a];
                    for b in a..c {
                        cross[a * c + b] += v[a] * v[b];
                    }
                }
                n += 1;
            }
        }
        if n < 2 * c {
            return Err(bad("cell projection: too few cells to fit"));
        }
        let nf = n as f64;
        let mean: Vec<f64> = sum.iter().map(|s| s / nf).collect();
        let mut cov = nalgebra::DMatrix::<f64>::zeros(c, c);
        for a in 0..c {
            for b in a..c {
                let v = cross[a * c + b] / nf - mean[a] * mean[b];
                cov[(a, b)] = v;
                cov[(b, a)] = v;
            }
        }
        // Standardise: a channel that never varies (a dead ReLU) keeps
        // unit scale and so contributes nothing.
        let sd: Vec<f64> = (0..c)
            .map(|a| {
                let s = cov[(a, a)].max(0.0).sqrt();
                if s > 1e-6 {
                    s
                } else {
                    1.0
                }
            })
            .collect();
        let mut corr = cov.clone();
        for a in 0..c {
            for b in 0..c {
                corr[(a, b)] /= sd[a] * sd[b];
            }
        }
        let eig = nalgebra::SymmetricEigen::new(corr);
        let mut order: Vec<usize> = (0..c).collect();
        order.sort_by(|&i, &j| eig.eigenvalues[j].total_cmp(&eig.eigenvalues[i]));
        let total: f64 = eig.eigenvalues.iter().map(|&e| e.max(0.0)).sum();
        let kept: f64 = order[..HOG_DIM]
            .iter()
            .map(|&i| eig.eigenvalues[i].max(0.0))
            .sum();
        // Mean squared norm of the projected, standardised cells is the sum
        // of the kept eigenvalues.
        let scale = (target_sq_norm / kept.max(1e-12)).sqrt();
        let mut basis = vec![0.0f32; HOG_DIM * c];
        for (k, &i) in order[..HOG_DIM].iter().enumerate() {
            // A sign that makes the direction's largest loading positive,
            // so that refits agree.
            let col = eig.eigenvectors.column(i);
            let sign = if col
                .iter()
                .fold(0.0f64, |m, &x| if x.abs() > m.abs() { x } else { m })
                < 0.0
            {
                -1.0
            } else {
                1.0
            };
            for a in 0..c {
                basis[k * c + a] = (sign * scale * col[a] / sd[a]) as f32;
            }
        }
        Ok(Self {
            channels: c,
            mean: mean.iter().map(|&m| m as f32).collect(),
            basis,
            variance_kept: if total > 0.0 { kept / total } else { 0.0 },
        })
    }

    /// Reads a projection file (tensors `mean` `[C]` and `basis`
    /// `[31, C]`, metadata `variance_kept`).
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, VisionError> {
        let st = SafeTensors::deserialize(bytes)
            .map_err(|e| bad(format!("cell projection file: {e}")))?;
        let read = |name: &str| {
            f32_tensor(&st, name).map_err(|e| bad(format!("cell projection file: {e}")))
        };
        let (ms, mean) = read("mean")?;
        let (bs, basis) = read("basis")?;
        let c = mean.len();
        if ms != [c] || bs != [HOG_DIM, c] || c < HOG_DIM {
            return Err(bad(format!(
                "cell projection file: mean {ms:?} and basis {bs:?} do not fit"
            )));
        }
        if mean.iter().chain(&basis).any(|v| !v.is_finite()) {
            return Err(VisionError::NonFinite("cell projection"));
        }
        let (_, meta) = SafeTensors::read_metadata(bytes)
            .map_err(|e| bad(format!("cell projection file: {e}")))?;
        let variance_kept = meta
            .metadata()
            .as_ref()
            .and_then(|m| m.get("variance_kept"))
            .and_then(|v| v.parse().ok())
            .unwrap_or(0.0);
        Ok(Self {
            channels: c,
            mean,
            basis,
            variance_kept,
        })
    }

    /// The file [`Self::from_bytes`] reads, with `metadata` added.
    pub fn to_bytes(
        &self,
        metadata: &std::collections::HashMap<String, String>,
    ) -> Result<Vec<u8>, VisionError> {
        let as_bytes = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
        let (mean, basis) = (as_bytes(&self.mean), as_bytes(&self.basis));
        let views = [
            (
                "mean",
                TensorView::new(Dtype::F32, vec![self.channels], &mean)
                    .map_err(|e| bad(e.to_string()))?,
            ),
            (
                "basis",
                TensorView::new(Dtype::F32, vec![HOG_DIM, self.channels], &basis)
                    .map_err(|e| bad(e.to_string()))?,
            ),
        ];
        let mut meta = metadata.clone();
        meta.insert("variance_kept".into(), format!("{:.6}", self.variance_kept));
        safetensors::serialize(views, Some(meta)).map_err(|e| bad(e.to_string()))
    }

    /// The mean folded into a bias: `basis * mean` (a cell is `basis *
    /// features - bias`).
    pub fn bias(&self) -> Vec<f32> {
        let c = self.channels;
        (0..HOG_DIM)
            .map(|k| {
                (0..c)
                    .map(|a| self.basis[k * c + a] * self.mean[a])
                    .sum::<f32>()
            })
            .collect()
    }

    /// The cells of a backbone map: the first `floor(w / 8) x floor(h /
    /// 8)` of its `ceil` ones (HOG's count), projected.
    pub fn project(
        &self,
        map: &FeatureMap,
        width: usize,
        height: usize,
    ) -> Result<HogMap, VisionError> {
        if map.channels != self.channels || width > map.width || height > map.height {
            return Err(bad(format!(
                "cell projection of {} channels cannot take a {}-channel {}x{} map to {width}x{height} cells",
                self.channels, map.channels, map.width, map.height
            )));
        }
        let c = self.channels;
        let plane = map.width * map.height;
        let bias = self.bias();
        let mut data = vec![0.0f32; width * height * HOG_STRIDE];
        for y in 0..height {
            let out = &mut data[y * width * HOG_STRIDE..(y + 1) * width * HOG_STRIDE];
            for cell in out.chunks_exact_mut(HOG_STRIDE) {
                for (o, b) in cell.iter_mut().zip(&bias) {
                    *o = -b;
                }
            }
            let row = &map.data[y * map.width..];
            // out (width x 31, row stride 32) += A (width x c) * B (c x 31)
            // with A(i, a) = map[a][y][i] and B(a, k) = basis[k][a].
            // SAFETY: A reads map.data[a * plane + y * map.width + i] for i <
            // width <= map.width and a < c: inside the c planes; B reads
            // basis[k * c + a] < 31 * c; C writes out[i * 32 + k] for i <
            // width, k < 31: inside `out`. No aliasing (distinct borrows).
            unsafe {
                matrixmultiply::sgemm(
                    width,
                    c,
                    HOG_DIM,
                    1.0,
                    row.as_ptr(),
                    1,
                    plane as isize,
                    self.basis.as_ptr(),
                    1,
                    c as isize,
                    1.0,
                    out.as_mut_ptr(),
                    HOG_STRIDE as isize,
                    1,
                );
            }
        }
        HogMap::from_raw(width, height, data)
    }

    /// A short fingerprint of the projection (and so of the cells a model
    /// was trained on): the first 16 hex digits of the SHA-256 of its
    /// numbers.
    pub fn fingerprint(&self) -> String {
        let mut h = Sha256::new();
        for v in self.mean.iter().chain(&self.basis) {
            h.update(v.to_le_bytes());
        }
        h.finalize()
            .iter()
            .take(8)
            .map(|b| format!("{b:02x}"))
            .collect()
    }
}

/// The backbone and its projection: what turns an image into learned
/// cells.
#[derive(Debug)]
pub struct LearnedCells {
    pub backbone: Backbone,
    pub projection: CellProjection,
}

static BUILTIN: OnceLock<Result<LearnedCells, VisionError>> = OnceLock::new();

/// Environment variable naming a backbone file (as
/// `scripts/convert_efficientnet_lite0.py` writes them) to use instead of
/// the built-in one: the richer cells' experiments (issue 62) train and
/// score with it. A model records its projection's fingerprint, so one
/// trained on such cells loads only where the same files are named.
pub const BACKBONE_ENV: &str = "SDHOP_CELLS_BACKBONE";
/// Environment variable naming the projection file that goes with
/// [`BACKBONE_ENV`]'s backbone (`sdhop-train cells --out`).
pub const PROJECTION_ENV: &str = "SDHOP_CELLS_PROJECTION";

/// The backbone of [`BACKBONE_ENV`] when it is set, else the built-in one.
pub fn backbone_in_use() -> Result<Backbone, VisionError> {
    let backbone = match std::env::var_os(BACKBONE_ENV) {
        Some(path) => Backbone::load(std::path::Path::new(&path))
            .map_err(|e| bad(format!("{BACKBONE_ENV}: {e}")))?,
        None => Backbone::from_bytes(BACKBONE_FILE)
            .map_err(|e| bad(format!("built-in backbone: {e}")))?,
    };
    if backbone.stride != CELL_SIZE && backbone.stride != 2 * CELL_SIZE {
        return Err(bad(format!(
            "backbone {} has stride {}: cells need {CELL_SIZE} or {}",
            backbone.name,
            backbone.stride,
            2 * CELL_SIZE
        )));
    }
    Ok(backbone)
}

impl LearnedCells {
    /// The backbone and projection built into the binary (parsed once),
    /// or those [`BACKBONE_ENV`] and [`PROJECTION_ENV`] name.
    pub fn builtin() -> Result<&'static LearnedCells, VisionError> {
        BUILTIN
            .get_or_init(|| {
                let backbone = backbone_in_use()?;
                let projection = match std::env::var_os(PROJECTION_ENV) {
                    Some(path) => {
                        let bytes = std::fs::read(&path).map_err(|e| {
                            bad(format!("{PROJECTION_ENV} {}: {e}", path.to_string_lossy()))
                        })?;
                        CellProjection::from_bytes(&bytes)?
                    }
                    None => CellProjection::from_bytes(PROJECTION_FILE)?,
                };
                if projection.channels != backbone.channels {
                    return Err(bad(format!(
                        "backbone {} ({} channels) and cell projection ({} channels) do not fit{}",
                        backbone.name,
                        backbone.channels,
                        projection.channels,
                        if std::env::var_os(BACKBONE_ENV).is_some() {
                            format!(": set {PROJECTION_ENV} to the projection `sdhop-train cells` fitted to it")
                        } else {
                            String::new()
                        }
                    )));
                }
                Ok(LearnedCells {
                    backbone,
                    projection,
                })
            })
            .as_ref()
            .map_err(Clone::clone)
    }

    /// The backbone's features of `img` on the cell grid
    /// ([`grid_features`]).
    pub fn features_until(
        &self,
        img: &ColorImage,
        deadline: Deadline,
    ) -> Result<FeatureMap, VisionError> {
        grid_features(&self.backbone, img, deadline)
    }

    /// The cells of `img`: `floor(w / 8) x floor(h / 8)` of them, like
    /// HOG's.
    pub fn cells(&self, img: &ColorImage) -> Result<HogMap, VisionError> {
        self.cells_until(img, Deadline::NONE)
    }

    /// [`Self::cells`] that gives up once `deadline` has passed (see
    /// [`crate::vision::cnn::Backbone::forward_until`]).
    pub fn cells_until(&self, img: &ColorImage, deadline: Deadline) -> Result<HogMap, VisionError> {
        let (w, h) = (img.width() / CELL_SIZE, img.height() / CELL_SIZE);
        if w == 0 || h == 0 {
            return HogMap::from_raw(w, h, Vec::new());
        }
        let map = self.features_until(img, deadline)?;
        self.projection.project(&map, w, h)
    }
}

/// The backbone's features of `img` on the cell grid: as they are at
/// stride 8; at stride 16 interpolated (bilinearly, between the
/// centres of the coarse cells, clamped at the borders) onto the
/// 8-pixel cells.
pub fn grid_features(
    backbone: &Backbone,
    img: &ColorImage,
    deadline: Deadline,
) -> Result<FeatureMap, VisionError> {
    let map = backbone.forward_until(img, deadline)?;
    if backbone.stride == CELL_SIZE {
        return Ok(map);
    }
    let k = backbone
        .last_halving_kernel()
        .ok_or_else(|| bad("a stride-16 backbone without a stride-2 block"))?;
    let xs = fine_taps(img.width(), k, map.width);
    let ys = fine_taps(img.height(), k, map.height);
    let (w, h) = (xs.len(), ys.len());
    let mut out = FeatureMap {
        channels: map.channels,
        width: w,
        height: h,
        data: vec![0.0; map.channels * w * h],
    };
    for c in 0..map.channels {
        let src = &map.data[c * map.width * map.height..][..map.width * map.height];
        let dst = &mut out.data[c * w * h..][..w * h];
        for (y, &(y0, y1, fy)) in ys.iter().enumerate() {
            let (r0, r1) = (&src[y0 * map.width..], &src[y1 * map.width..]);
            for (x, &(x0, x1, fx)) in xs.iter().enumerate() {
                let top = r0[x0] + fx * (r0[x1] - r0[x0]);
                let bottom = r1[x0] + fx * (r1[x1] - r1[x0]);
                dst[y * w + x] = top + fy * (bottom - top);
            }
        }
    }
    Ok(out)
}

/// For each 8-pixel cell of an axis of `n` pixels (`2 * coarse` of them),
/// the two stride-16 cells it lies between and its share of the second.
/// The last stride-2 block (kernel `k`) reads its input's `ceil(n / 8)`
/// cells with "same" padding `top` before, so its output cell `j` is
/// centred on input cell `2j - top + (k - 1) / 2`.
fn fine_taps(n: usize, k: usize, coarse: usize) -> Vec<(usize, usize, f32)> {
    let (_, top) = super::cnn::same_padding(n.div_ceil(CELL_SIZE), k, 2);
    let last = coarse.saturating_sub(1);
    (0..2 * coarse)
        .map(|i| {
            let u = ((i + top) as f32 - ((k - 1) / 2) as f32) / 2.0;
            let u = u.clamp(0.0, last as f32);
            let j0 = (u.floor() as usize).min(last);
            let j1 = (j0 + 1).min(last);
            (j0, j1, u - j0 as f32)
        })
        .collect()
}

/// Level pixels above which learned cells are computed strip by strip
/// ([`LearnedCells::level_cells_until`]): the backbone's maps of a whole
/// 16 MP level upsampled twice took 5 GB.
pub const STRIP_PIXELS: usize = 4 << 20;

impl LearnedCells {
    /// The cells of `img` resized to `lw x lh` (as
    /// [`ColorImage::resize_smooth`] resizes it), the same as
    /// [`Self::cells_until`] of the resized image, computed in strips of
    /// cell rows: each strip's rows of the level are resized alone, with a
    /// margin of the backbone's receptive field above and below, at offsets
    /// and heights that keep every layer's "same" padding where the whole
    /// level has it. Memory is then bounded by a strip, not the level.
    pub fn level_cells_until(
        &self,
        img: &ColorImage,
        (lw, lh): (usize, usize),
        strip_pixels: usize,
        deadline: Deadline,
    ) -> Result<HogMap, VisionError> {
        let (cw, ch) = (lw / CELL_SIZE, lh / CELL_SIZE);
        if cw == 0 || ch == 0 {
            return HogMap::from_raw(cw, ch, Vec::new());
        }
        // Strips start and keep heights on the backbone's grid (its
        // stride, 8 or 16 pixels), in whole cells.
        let align = self.backbone.stride;
        let per = align / CELL_SIZE;
        // The margin: half the receptive field and one grid step more.
        let margin = (self.backbone.receptive_field() / 2 + align).div_ceil(align) * align;
        let rows = (strip_pixels / lw)
            .saturating_sub(2 * margin)
            .max(4 * align)
            / align
            * per;
        let rest = lh % align;
        let mut data = Vec::with_capacity(cw * ch * HOG_STRIDE);
        for c0 in (0..ch).step_by(rows) {
            let c1 = (c0 + rows).min(ch);
            let y0 = (c0 * CELL_SIZE).saturating_sub(margin);
            // Heights congruent to the level's modulo the grid: every
            // stride-2 layer then pads the strip's top as the level's.
            let need = c1 * CELL_SIZE + margin - y0;
            let height = need.saturating_sub(rest).div_ceil(align) * align + rest;
            let y1 = (y0 + height).min(lh);
            let strip = if (lw, lh) == (img.width(), img.height()) {
                img.rows(y0, y1)?
            } else {
                img.resize_smooth_rows(lw, lh, y0, y1)?
            };
            let map = self.features_until(&strip, deadline)?;
            let cells = self.projection.project(&map, cw, (y1 - y0) / CELL_SIZE)?;
            let first = c0 - y0 / CELL_SIZE;
            data.extend_from_slice(
                &cells.raw()[first * cw * HOG_STRIDE..(first + c1 - c0) * cw * HOG_STRIDE],
            );
        }
        HogMap::from_raw(cw, ch, data)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::image::noise_image;

    #[test]
    fn learned_cells_are_the_projected_backbone_cells_in_hogs_layout() {
        let cells = LearnedCells::builtin().unwrap();
        let img = noise_image(67, 45, 3);
        let map = cells.cells(&img).unwrap();
        assert_eq!((map.width(), map.height()), (8, 5));
        // Each cell is the projection of the backbone's cell.
        let f = cells.backbone.forward(&img);
        let p = &cells.projection;
        for (x, y) in [(0, 0), (7, 4), (3, 2)] {
            for k in [0, 13, HOG_DIM - 1] {
                let want: f32 = (0..p.channels)
                    .map(|a| p.basis[k * p.channels + a] * (f.get(a, x, y) - p.mean[a]))
                    .sum();
                let got = map.cell(x, y)[k];
                assert!(
                    (got - want).abs() < 1e-3 * (1.0 + want.abs()),
                    "{got} {want}"
                );
            }
        }
    }

    /// The cells of a noise image's `lw x lh` level computed in strips of
    /// `strip` pixels are those of the whole level.
    fn strips_match_the_whole(
        cells: &LearnedCells,
        (w, h): (usize, usize),
        (lw, lh): (usize, usize),
        strip: usize,
    ) {
        let img = noise_image(w, h, 7);
        let level = img.resize_smooth(lw, lh).unwrap();
        let whole = cells.cells(&level).unwrap();
        let strips = cells
            .level_cells_until(&img, (lw, lh), strip, Deadline::NONE)
            .unwrap();
        assert_eq!(
            (strips.width(), strips.height()),
            (whole.width(), whole.height())
        );
        let worst = strips
            .raw()
            .iter()
            .zip(whole.raw())
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(worst <= 1e-4, "{w}x{h} -> {lw}x{lh}: worst {worst}");
    }

    #[test]
    fn strips_of_a_level_give_the_whole_levels_cells() {
        let cells = LearnedCells::builtin().unwrap();
        // Heights and widths off the cell grid, up- and downscaled levels,
        // the image's own size, strips of a few cell rows (a small strip
        // budget) down to one strip.
        for (w, h, lw, lh, strip) in [
            (150, 131, 150, 131, 60_000),
            (150, 131, 317, 285, 60_000),
            (203, 170, 173, 149, 40_000),
            (96, 77, 211, 203, 1 << 30),
        ] {
            strips_match_the_whole(cells, (w, h), (lw, lh), strip);
        }
        // Rows of a resize are the resize's rows.
        let img = noise_image(90, 70, 3);
        let whole = img.resize_smooth(130, 151).unwrap();
        let part = img.resize_smooth_rows(130, 151, 37, 99).unwrap();
        let row = 130 * 3;
        assert_eq!(part.data(), &whole.data()[37 * row..99 * row]);
        let passed = Deadline::at(std::time::Instant::now());
        assert_eq!(
            cells
                .level_cells_until(&img, (130, 151), 20_000, passed)
                .unwrap_err(),
            VisionError::DeadlineExceeded
        );
    }

    /// Lite0's blocks 0-5 (80 channels at stride 16) and their projection,
    /// as committed for the richer cells' experiments.
    fn stride_16_cells() -> LearnedCells {
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/models/backbones/");
        let backbone = Backbone::load(std::path::Path::new(&format!(
            "{dir}efficientnet_lite0_s16_b6.safetensors"
        )))
        .unwrap();
        let bytes =
            std::fs::read(format!("{dir}efficientnet_lite0_s16_b6_cells.safetensors")).unwrap();
        LearnedCells {
            backbone,
            projection: CellProjection::from_bytes(&bytes).unwrap(),
        }
    }

    #[test]
    fn stride_16_features_are_interpolated_onto_the_cell_grid() {
        let cells = stride_16_cells();
        assert_eq!((cells.backbone.stride, cells.backbone.channels), (16, 80));
        // Odd and even numbers of stride-8 cells (both paddings of the
        // halving block).
        for (w, h) in [(100, 75), (97, 130)] {
            let img = noise_image(w, h, 5);
            let coarse = cells.backbone.forward(&img);
            let fine = cells.features_until(&img, Deadline::NONE).unwrap();
            assert_eq!(
                (fine.width, fine.height),
                (2 * w.div_ceil(16), 2 * h.div_ceil(16))
            );
            let xs = fine_taps(w, 3, coarse.width);
            let ys = fine_taps(h, 3, coarse.height);
            for c in [0, 41, 79] {
                for (y, &(y0, y1, fy)) in ys.iter().enumerate() {
                    for (x, &(x0, x1, fx)) in xs.iter().enumerate() {
                        let v = fine.get(c, x, y);
                        let corners = [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
                            .map(|(a, b)| coarse.get(c, a, b));
                        let lo = corners.iter().copied().fold(f32::INFINITY, f32::min);
                        let hi = corners.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                        assert!(v >= lo - 1e-4 && v <= hi + 1e-4, "{v} outside {lo}..{hi}");
                        // A cell on a coarse centre is the coarse cell.
                        if fx == 0.0 && fy == 0.0 {
                            assert_eq!(v, coarse.get(c, x0, y0));
                        }
                    }
                }
            }
            // Every coarse cell is some fine cell's centre, or the grid's
            // edge is clamped to it.
            assert!(xs.iter().filter(|t| t.2 == 0.0).count() >= coarse.width);
        }
        // The coarse cell j is centred on stride-8 cell 2j - top + 1.
        assert_eq!(fine_taps(64, 3, 4)[3], (1, 2, 0.0));
        assert_eq!(fine_taps(72, 3, 5)[2], (1, 2, 0.0));
    }

    #[test]
    fn strips_of_a_stride_16_level_give_the_whole_levels_cells() {
        let cells = stride_16_cells();
        for (w, h, lw, lh, strip) in [(150, 131, 317, 285, 60_000), (203, 170, 173, 149, 40_000)] {
            strips_match_the_whole(&cells, (w, h), (lw, lh), strip);
        }
    }

    #[test]
    fn projection_round_trips_and_fit_keeps_the_leading_variance() {
        // Maps whose 40 channels are mixtures of 3 sources: 3 directions
        // carry all the variance.
        let mut rng = crate::vision::rng::SplitMix64::new(9);
        let (c, w, h) = (40, 20, 10);
        let mix: Vec<f64> = (0..c * 3).map(|_| rng.next_f64() - 0.5).collect();
        let mut data = vec![0.0f32; c * w * h];
        for i in 0..w * h {
            let s = [rng.next_f64(), rng.next_f64(), rng.next_f64()];
            for a in 0..c {
                data[a * w * h + i] =
                    (1.0 + (0..3).map(|j| mix[a * 3 + j] * s[j]).sum::<f64>()) as f32;
            }
        }
        let map = FeatureMap {
            channels: c,
            width: w,
            height: h,
            data,
        };
        let p = CellProjection::fit(std::slice::from_ref(&map), 2.0).unwrap();
        assert!(p.variance_kept > 0.999, "{}", p.variance_kept);
        let cells = p.project(&map, w, h).unwrap();
        let msq: f64 = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| {
                cells
                    .cell(x, y)
                    .iter()
                    .map(|&v| f64::from(v * v))
                    .sum::<f64>()
            })
            .sum::<f64>()
            / (w * h) as f64;
        assert!((msq - 2.0).abs() < 0.05, "{msq}");
        let back = CellProjection::from_bytes(&p.to_bytes(&Default::default()).unwrap()).unwrap();
        assert_eq!(back.mean, p.mean);
        assert_eq!(back.basis, p.basis);
        assert_eq!(back.fingerprint(), p.fingerprint());
        assert!(CellProjection::from_bytes(b"not a file").is_err());
    }
}
