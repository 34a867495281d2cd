//! The scale-space pyramid: HOG features and segment-per-cell maps at every
//! level, plus the pixel-level over-segmentation of the input image.

use std::time::Instant;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::cells::{FeatureKind, LearnedCells, STRIP_PIXELS};
use super::hog::{HogMap, CELL_SIZE, HOG_STRIDE};
use super::image::{area_weights_at, ColorImage};
use super::segment::{segment_until, SegmentParams, Segmentation};
use super::{Deadline, VisionError};

/// Pyramid settings: levels at `max_scale * 2^(-l / levels_per_octave)` down
/// to `min_scale` (scale = level size / image size).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PyramidParams {
    pub levels_per_octave: u32,
    pub max_scale: f32,
    pub min_scale: f32,
    /// What a cell's vector is. Always written; absent from the files of
    /// formats 1 and 2 for HOG models (which all models were before
    /// learned cells), where it reads as HOG.
    #[serde(default)]
    pub features: FeatureKind,
    /// Every how many levels the cells are computed from pixels: the
    /// levels between are resampled (area-weighted) from the cells of the
    /// computed level above them, Dollár's fast feature pyramids. 1
    /// computes every level (exact), the default and what files without
    /// the field mean.
    #[serde(default = "every_level", skip_serializing_if = "is_every_level")]
    pub computed_every: u32,
}

fn every_level() -> u32 {
    1
}

fn is_every_level(v: &u32) -> bool {
    *v == 1
}

impl Default for PyramidParams {
    /// 11 levels from full size down to half size, HOG cells.
    fn default() -> Self {
        Self {
            levels_per_octave: 10,
            max_scale: 1.0,
            min_scale: 0.5,
            features: FeatureKind::Hog,
            computed_every: 1,
        }
    }
}

/// Upper limit of pyramid levels, whatever the settings.
pub const MAX_LEVELS: usize = 64;

impl PyramidParams {
    pub fn validate(&self) -> Result<(), VisionError> {
        let ok = self.levels_per_octave >= 1
            && self.levels_per_octave <= 64
            && self.max_scale.is_finite()
            && self.min_scale.is_finite()
            && self.min_scale > 0.0
            && self.max_scale >= self.min_scale
            && self.max_scale <= 4.0
            && (1..=MAX_LEVELS as u32).contains(&self.computed_every);
        if !ok {
            return Err(VisionError::InvalidParameter(format!(
                "pyramid needs 1 <= levels_per_octave <= 64, 0 < min_scale <= max_scale <= 4 and 1 <= computed_every <= {MAX_LEVELS}, got {self:?}"
            )));
        }
        if self.scales().len() > MAX_LEVELS {
            return Err(VisionError::InvalidParameter(format!(
                "pyramid would have more than {MAX_LEVELS} levels"
            )));
        }
        Ok(())
    }

    /// The nominal scale of every level, largest first.
    pub fn scales(&self) -> Vec<f64> {
        let mut out = Vec::new();
        let lambda = f64::from(self.levels_per_octave.max(1));
        for l in 0..=MAX_LEVELS {
            let s = f64::from(self.max_scale) * (-(l as f64) / lambda).exp2();
            if s < f64::from(self.min_scale) * (1.0 - 1e-9) {
                break;
            }
            out.push(s);
        }
        out
    }
}

/// One pyramid level.
#[derive(Clone, Debug)]
pub struct Level {
    /// Level width over image width (exact, after rounding the level size).
    pub scale_x: f64,
    /// Level height over image height.
    pub scale_y: f64,
    pub hog: HogMap,
    /// Segment of every cell, row-major over the HOG map.
    pub cell_segments: Vec<u32>,
}

/// Wall-clock time of the pyramid's stages in milliseconds (features and
/// segmentation run concurrently).
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct PyramidTiming {
    pub features_ms: f64,
    pub segmentation_ms: f64,
    pub cell_segments_ms: f64,
    /// Wall-clock time of the whole build (features and segmentation run
    /// concurrently).
    pub total_ms: f64,
}

/// HOG pyramid and over-segmentation of one image.
#[derive(Clone, Debug)]
pub struct FeaturePyramid {
    pub image_width: usize,
    pub image_height: usize,
    /// The image itself (the pixel refinement of masks follows its colour
    /// edges).
    pub image: std::sync::Arc<ColorImage>,
    pub levels: Vec<Level>,
    pub segmentation: Segmentation,
    pub timing: PyramidTiming,
    /// The settings it was built with.
    pub params: PyramidParams,
    pub seg_params: SegmentParams,
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

impl FeaturePyramid {
    /// The pyramid without its pixels (the image and the per-pixel segment
    /// labels; the HOG levels, their cell segments and the segment count
    /// stay): what training needs of it, at a quarter less memory. Masks
    /// made from it are the raw cell masks (see [`Self::has_pixels`]).
    pub fn lean(mut self) -> Result<Self, VisionError> {
        self.image = std::sync::Arc::new(ColorImage::new(1, 1, vec![0.0; 3])?);
        self.segmentation = self.segmentation.without_labels();
        Ok(self)
    }

    /// Whether the image and its per-pixel segments are here (not a
    /// [`Self::lean`] pyramid).
    pub fn has_pixels(&self) -> bool {
        (self.image.width(), self.image.height()) == (self.image_width, self.image_height)
            && (self.segmentation.width(), self.segmentation.height())
                == (self.image_width, self.image_height)
    }

    /// Builds the pyramid: segmentation and the HOG levels in parallel.
    pub fn build(
        img: &ColorImage,
        params: &PyramidParams,
        seg: &SegmentParams,
    ) -> Result<Self, VisionError> {
        Self::build_until(img, params, seg, Deadline::NONE)
    }

    /// [`Self::build`] that gives up with
    /// [`VisionError::DeadlineExceeded`] once `deadline` has passed (looked
    /// at before each level and after the segmentation).
    pub fn build_until(
        img: &ColorImage,
        params: &PyramidParams,
        seg: &SegmentParams,
        deadline: Deadline,
    ) -> Result<Self, VisionError> {
        Self::build_keeping(
            img,
            || std::sync::Arc::new(img.clone()),
            params,
            seg,
            deadline,
        )
    }

    /// [`Self::build_until`] of an image the pyramid shares instead of
    /// copying (a 16 MP image is 192 MB).
    pub fn build_shared(
        img: &std::sync::Arc<ColorImage>,
        params: &PyramidParams,
        seg: &SegmentParams,
        deadline: Deadline,
    ) -> Result<Self, VisionError> {
        Self::build_keeping(img, || std::sync::Arc::clone(img), params, seg, deadline)
    }

    /// The pyramid of the same image with other cell settings (`params`),
    /// sharing this one's over-segmentation instead of computing it again:
    /// a model's segmenter on other cells ([`crate::model::Model::segmenter`])
    /// needs both pyramids of one photograph. Needs the pixels (not a
    /// [`Self::lean`] pyramid).
    pub fn build_beside(
        &self,
        params: &PyramidParams,
        deadline: Deadline,
    ) -> Result<Self, VisionError> {
        params.validate()?;
        if !self.has_pixels() {
            return Err(VisionError::InvalidParameter(
                "a pyramid without its pixels cannot build another beside it".into(),
            ));
        }
        let start = Instant::now();
        let (w, h) = (self.image_width, self.image_height);
        let hogs = feature_levels(&self.image, params, deadline)?;
        let features_ms = ms(start);
        let t = Instant::now();
        let levels = cell_levels(hogs, &self.segmentation, (w, h), deadline)?;
        Ok(Self {
            image_width: w,
            image_height: h,
            image: std::sync::Arc::clone(&self.image),
            levels,
            segmentation: self.segmentation.clone(),
            timing: PyramidTiming {
                features_ms,
                segmentation_ms: 0.0,
                cell_segments_ms: ms(t),
                total_ms: ms(start),
            },
            params: *params,
            seg_params: self.seg_params,
        })
    }

    /// The pyramids of `img` for each of `settings`, in order; those
    /// whose over-segmentation settings agree share one segmentation
    /// ([`Self::build_beside`]).
    pub fn build_all(
        img: &std::sync::Arc<ColorImage>,
        settings: &[(PyramidParams, SegmentParams)],
        deadline: Deadline,
    ) -> Result<Vec<Self>, VisionError> {
        let mut out: Vec<Self> = Vec::with_capacity(settings.len());
        for (p, s) in settings {
            let pyr = match out.iter().find(|o| o.seg_params == *s) {
                Some(first) => first.build_beside(p, deadline)?,
                None => Self::build_shared(img, p, s, deadline)?,
            };
            out.push(pyr);
        }
        Ok(out)
    }

    /// The pyramids of this pyramid's image for those of `settings` that
    /// are not its own, in order, built beside it where they can be.
    pub fn build_others(
        &self,
        settings: &[(PyramidParams, SegmentParams)],
        deadline: Deadline,
    ) -> Result<Vec<Self>, VisionError> {
        settings
            .iter()
            .filter(|(p, s)| (*p, *s) != (self.params, self.seg_params))
            .map(|(p, s)| {
                if *s == self.seg_params {
                    self.build_beside(p, deadline)
                } else {
                    Self::build_shared(&self.image, p, s, deadline)
                }
            })
            .collect()
    }

    /// The pyramid of `img`, which keeps the image `keep` gives once built.
    fn build_keeping(
        img: &ColorImage,
        keep: impl FnOnce() -> std::sync::Arc<ColorImage>,
        params: &PyramidParams,
        seg: &SegmentParams,
        deadline: Deadline,
    ) -> Result<Self, VisionError> {
        params.validate()?;
        seg.validate()?;
        let start = Instant::now();
        let (w, h) = (img.width(), img.height());
        let (segmentation, hogs) = rayon::join(
            || {
                let t = Instant::now();
                segment_until(img, seg, deadline).map(|s| (s, ms(t)))
            },
            || {
                let t = Instant::now();
                feature_levels(img, params, deadline).map(|l| (l, ms(t)))
            },
        );
        let (segmentation, segmentation_ms) = segmentation?;
        let (hogs, features_ms) = hogs?;
        if deadline.passed() {
            return Err(VisionError::DeadlineExceeded);
        }
        let t = Instant::now();
        let levels = cell_levels(hogs, &segmentation, (w, h), deadline)?;
        Ok(Self {
            image_width: w,
            image_height: h,
            image: keep(),
            levels,
            segmentation,
            timing: PyramidTiming {
                features_ms,
                segmentation_ms,
                cell_segments_ms: ms(t),
                total_ms: ms(start),
            },
            params: *params,
            seg_params: *seg,
        })
    }
}

/// The size of every level of `params` on a `w x h` image, largest first:
/// the levels at least one cell on each side.
pub fn level_sizes(w: usize, h: usize, params: &PyramidParams) -> Vec<(usize, usize)> {
    params
        .scales()
        .into_iter()
        .filter_map(|s| {
            let lw = (w as f64 * s).round() as usize;
            let lh = (h as f64 * s).round() as usize;
            (lw >= CELL_SIZE && lh >= CELL_SIZE).then_some((lw, lh))
        })
        .collect()
}

/// The cells of every level ([`level_sizes`]) of `img`, of the kind
/// `params` names, levels in parallel; gives up with
/// [`VisionError::DeadlineExceeded`] once `deadline` has passed (looked at
/// before each level). Only every [`PyramidParams::computed_every`]-th
/// level is computed from pixels; the others are resampled from the
/// computed level above ([`fill_between`]).
pub fn feature_levels(
    img: &ColorImage,
    params: &PyramidParams,
    deadline: Deadline,
) -> Result<Vec<(usize, usize, HogMap)>, VisionError> {
    let (w, h) = (img.width(), img.height());
    let sizes = level_sizes(w, h, params);
    let every = params.computed_every.max(1) as usize;
    let computed = sizes
        .par_iter()
        .enumerate()
        .filter(|(l, _)| l % every == 0)
        .map(|(_, &(lw, lh))| level_cells(img, (lw, lh), params, deadline))
        .collect::<Result<Vec<_>, _>>()?;
    fill_between(&sizes, computed, every, deadline)
}

/// The cells of `img` at level size `lw x lh`, computed from its pixels.
fn level_cells(
    img: &ColorImage,
    (lw, lh): (usize, usize),
    params: &PyramidParams,
    deadline: Deadline,
) -> Result<HogMap, VisionError> {
    if deadline.passed() {
        return Err(VisionError::DeadlineExceeded);
    }
    // A large level of learned cells, strip by strip.
    if params.features.in_strips(lw * lh) {
        let cells = LearnedCells::builtin()?;
        return cells.level_cells_until(img, (lw, lh), STRIP_PIXELS, deadline);
    }
    // The full-size level reads the image itself.
    if (lw, lh) == (img.width(), img.height()) {
        return params.features.cells_until(img, deadline);
    }
    // HOG levels as ever; learned cells see upsampled levels
    // interpolated, not in blocks.
    let resized = params.features.resize_until(img, lw, lh, deadline)?;
    if deadline.passed() {
        return Err(VisionError::DeadlineExceeded);
    }
    params.features.cells_until(&resized, deadline)
}

/// Every level of `sizes` from the cells of its every `every`-th level
/// (`computed`, in order): each level between resampled from the computed
/// level above it.
pub fn fill_between(
    sizes: &[(usize, usize)],
    computed: Vec<HogMap>,
    every: usize,
    deadline: Deadline,
) -> Result<Vec<(usize, usize, HogMap)>, VisionError> {
    let every = every.max(1);
    if computed.len() != sizes.len().div_ceil(every) {
        return Err(VisionError::InvalidParameter(format!(
            "{} computed levels for {} levels computed every {every}",
            computed.len(),
            sizes.len()
        )));
    }
    if every == 1 {
        return Ok(sizes
            .iter()
            .zip(computed)
            .map(|(&(lw, lh), m)| (lw, lh, m))
            .collect());
    }
    let resampled = sizes
        .par_iter()
        .enumerate()
        .map(|(l, &(lw, lh))| {
            if l % every == 0 {
                return Ok(None);
            }
            if deadline.passed() {
                return Err(VisionError::DeadlineExceeded);
            }
            let (sw, _) = sizes[l - l % every];
            let ratio = sw as f64 / lw as f64;
            resample_cells(&computed[l / every], lw, lh, ratio).map(Some)
        })
        .collect::<Result<Vec<_>, _>>()?;
    let mut computed = computed.into_iter();
    sizes
        .iter()
        .zip(resampled)
        .map(|(&(lw, lh), r)| {
            let m = match r {
                Some(m) => m,
                None => computed.next().ok_or_else(|| {
                    VisionError::InvalidParameter("a computed level missing".into())
                })?,
            };
            Ok((lw, lh, m))
        })
        .collect()
}

/// Every level's cells as [`feature_levels`] gives them, from the cells of
/// every level computed from pixels (`all`, as a compute backend that
/// computes every level returns them): the levels
/// [`PyramidParams::computed_every`] skips are replaced by their
/// resampling, so that both paths give the same cells.
pub fn approximate_levels(
    (w, h): (usize, usize),
    params: &PyramidParams,
    all: Vec<HogMap>,
    deadline: Deadline,
) -> Result<Vec<HogMap>, VisionError> {
    let every = params.computed_every.max(1) as usize;
    if every == 1 {
        return Ok(all);
    }
    let sizes = level_sizes(w, h, params);
    let computed = all.into_iter().step_by(every).collect();
    Ok(fill_between(&sizes, computed, every, deadline)?
        .into_iter()
        .map(|(_, _, m)| m)
        .collect())
}

/// The cells of a `lw x lh` level from those of a larger level (`ratio`
/// times its size): each cell the area-weighted mean of the larger
/// level's cells its 8x8 pixels cover there (a linear map of the cells,
/// so learned cells resample as their backbone's features would before
/// the affine projection).
pub fn resample_cells(
    src: &HogMap,
    lw: usize,
    lh: usize,
    ratio: f64,
) -> Result<HogMap, VisionError> {
    let (cw, ch) = (lw / CELL_SIZE, lh / CELL_SIZE);
    if cw == 0 || ch == 0 || src.width() == 0 || src.height() == 0 {
        return HogMap::from_raw(cw, ch, vec![0.0; cw * ch * HOG_STRIDE]);
    }
    // Cell o covers o * ratio..(o + 1) * ratio of the source's cells.
    let xs = area_weights_at(src.width(), cw, ratio);
    let ys = area_weights_at(src.height(), ch, ratio);
    let raw = src.raw();
    let row = src.width() * HOG_STRIDE;
    let mut data = vec![0.0f32; cw * ch * HOG_STRIDE];
    let mut line = vec![0.0f32; row];
    for (y, ty) in ys.iter().enumerate() {
        // The source rows blended, then the columns.
        line.fill(0.0);
        for &(sy, wy) in ty {
            for (o, &v) in line.iter_mut().zip(&raw[sy * row..(sy + 1) * row]) {
                *o += wy * v;
            }
        }
        let out = &mut data[y * cw * HOG_STRIDE..(y + 1) * cw * HOG_STRIDE];
        for (cell, tx) in out.chunks_exact_mut(HOG_STRIDE).zip(&xs) {
            for &(sx, wx) in tx {
                for (o, &v) in cell
                    .iter_mut()
                    .zip(&line[sx * HOG_STRIDE..(sx + 1) * HOG_STRIDE])
                {
                    *o += wx * v;
                }
            }
        }
    }
    HogMap::from_raw(cw, ch, data)
}

/// The levels of these cell maps (each with its level's size), each with
/// its cells' segments of `segmentation` (of an image `w x h`).
fn cell_levels(
    hogs: Vec<(usize, usize, HogMap)>,
    segmentation: &Segmentation,
    (w, h): (usize, usize),
    deadline: Deadline,
) -> Result<Vec<Level>, VisionError> {
    hogs.into_par_iter()
        .map(|(lw, lh, hog)| {
            if deadline.passed() {
                return Err(VisionError::DeadlineExceeded);
            }
            let cell_segments =
                segmentation.cell_labels(lw, lh, hog.width(), hog.height(), CELL_SIZE);
            Ok(Level {
                scale_x: lw as f64 / w as f64,
                scale_y: lh as f64 / h as f64,
                hog,
                cell_segments,
            })
        })
        .collect()
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;

    #[test]
    fn default_gives_eleven_levels_on_vga() {
        let p = PyramidParams::default();
        let s = p.scales();
        assert_eq!(s.len(), 11);
        assert!((s[0] - 1.0).abs() < 1e-12 && (s[10] - 0.5).abs() < 1e-12);
        let img = ColorImage::new(64, 48, vec![10.0; 64 * 48 * 3]).unwrap();
        let pyr = FeaturePyramid::build(&img, &p, &SegmentParams::default()).unwrap();
        assert_eq!(pyr.levels.len(), 11);
        assert_eq!(
            (pyr.levels[0].hog.width(), pyr.levels[0].hog.height()),
            (8, 6)
        );
        for l in &pyr.levels {
            assert_eq!(l.cell_segments.len(), l.hog.width() * l.hog.height());
        }
    }

    #[test]
    fn every_stage_gives_up_at_the_deadline() {
        let img = crate::vision::image::noise_image(300, 200, 4);
        let passed = Deadline::at(Instant::now());
        let far = Deadline::at(Instant::now() + std::time::Duration::from_secs(3600));
        let p = PyramidParams::default();
        let seg = SegmentParams::default();
        assert!(matches!(
            FeaturePyramid::build_until(&img, &p, &seg, passed),
            Err(VisionError::DeadlineExceeded)
        ));
        assert!(matches!(
            crate::vision::hog::hog_until(&img, passed),
            Err(VisionError::DeadlineExceeded)
        ));
        assert!(matches!(
            segment_until(&img, &seg, passed),
            Err(VisionError::DeadlineExceeded)
        ));
        // A deadline far off changes nothing.
        assert_eq!(
            crate::vision::hog::hog_until(&img, far).unwrap(),
            crate::vision::hog::hog(&img)
        );
        assert_eq!(
            segment_until(&img, &seg, far).unwrap().labels(),
            crate::vision::segment::segment(&img, &seg)
                .unwrap()
                .labels()
        );
    }

    #[test]
    fn a_pyramid_built_beside_another_is_the_one_built_alone() {
        let img = std::sync::Arc::new(crate::vision::image::noise_image(160, 120, 5));
        let seg = SegmentParams::default();
        let hog = PyramidParams::default();
        let other = PyramidParams {
            levels_per_octave: 3,
            ..hog
        };
        let settings = [(hog, seg), (other, seg)];
        let all = FeaturePyramid::build_all(&img, &settings, Deadline::NONE).unwrap();
        let alone = FeaturePyramid::build(&img, &other, &seg).unwrap();
        let beside = &all[1];
        assert_eq!((beside.params, beside.seg_params), (other, seg));
        assert_eq!(beside.levels.len(), alone.levels.len());
        for (a, b) in beside.levels.iter().zip(&alone.levels) {
            assert_eq!(a.hog, b.hog);
            assert_eq!(a.cell_segments, b.cell_segments);
            assert_eq!((a.scale_x, a.scale_y), (b.scale_x, b.scale_y));
        }
        assert_eq!(beside.segmentation.labels(), alone.segmentation.labels());
        // The segmentation is shared, not computed again.
        assert_eq!(beside.timing.segmentation_ms, 0.0);
        // Only the settings that are not the pyramid's own are built.
        let others = all[0].build_others(&settings, Deadline::NONE).unwrap();
        assert_eq!(others.len(), 1);
        assert_eq!(others[0].params, other);
        // A pyramid without its pixels cannot.
        let lean = all[0].clone().lean().unwrap();
        assert!(lean.build_beside(&other, Deadline::NONE).is_err());
    }

    #[test]
    fn every_nth_level_is_computed_and_the_rest_resampled_from_above() {
        let img = crate::vision::image::noise_image(200, 150, 7);
        let exact = PyramidParams::default();
        let fast = PyramidParams {
            computed_every: 5,
            ..exact
        };
        let all = feature_levels(&img, &exact, Deadline::NONE).unwrap();
        let some = feature_levels(&img, &fast, Deadline::NONE).unwrap();
        assert_eq!(all.len(), 11);
        assert_eq!(some.len(), all.len());
        for (l, (a, b)) in all.iter().zip(&some).enumerate() {
            assert_eq!((a.0, a.1), (b.0, b.1));
            assert_eq!((a.2.width(), a.2.height()), (b.2.width(), b.2.height()));
            if l % 5 == 0 {
                assert_eq!(a.2, b.2, "level {l} is computed");
            } else {
                let sw = all[l - l % 5].0;
                let want = resample_cells(&all[l - l % 5].2, a.0, a.1, sw as f64 / a.0 as f64);
                assert_eq!(b.2, want.unwrap(), "level {l}");
            }
        }
        // A backend that computed every level gets the same cells.
        let maps = all.into_iter().map(|(_, _, m)| m).collect();
        let same = approximate_levels((200, 150), &fast, maps, Deadline::NONE).unwrap();
        assert!(same.iter().zip(&some).all(|(a, b)| *a == b.2));
        assert!(PyramidParams {
            computed_every: 0,
            ..exact
        }
        .validate()
        .is_err());
    }

    #[test]
    fn resampled_cells_keep_a_uniform_map_and_at_ratio_one_copy_it() {
        let (w, h) = (9, 7);
        let data: Vec<f32> = (0..w * h * HOG_STRIDE).map(|i| (i % 97) as f32).collect();
        let map = HogMap::from_raw(w, h, data).unwrap();
        assert_eq!(
            resample_cells(&map, w * CELL_SIZE, h * CELL_SIZE, 1.0).unwrap(),
            map
        );
        let mut flat = vec![0.0; w * h * HOG_STRIDE];
        for cell in flat.chunks_exact_mut(HOG_STRIDE) {
            for (k, v) in cell.iter_mut().enumerate() {
                *v = k as f32 * 0.5 - 3.0;
            }
        }
        let flat = HogMap::from_raw(w, h, flat).unwrap();
        // 72 x 56 pixels down to 50 x 40: 6 x 5 cells, each the same.
        let small = resample_cells(&flat, 50, 40, 72.0 / 50.0).unwrap();
        assert_eq!((small.width(), small.height()), (6, 5));
        for y in 0..5 {
            for x in 0..6 {
                for (a, b) in small.cell(x, y).iter().zip(flat.cell(0, 0)) {
                    assert!((a - b).abs() < 1e-5);
                }
            }
        }
    }

    #[test]
    fn invalid_settings_are_refused() {
        let bad = [
            PyramidParams {
                levels_per_octave: 0,
                ..Default::default()
            },
            PyramidParams {
                min_scale: 0.0,
                ..Default::default()
            },
            PyramidParams {
                min_scale: 2.0,
                max_scale: 1.0,
                ..Default::default()
            },
            PyramidParams {
                max_scale: f32::NAN,
                ..Default::default()
            },
            PyramidParams {
                levels_per_octave: 64,
                min_scale: 0.01,
                max_scale: 4.0,
                ..Default::default()
            },
        ];
        for p in bad {
            assert!(p.validate().is_err(), "{p:?}");
        }
    }
}
