//! The scale-space pyramid: HOG features and segment-per-cell maps at every
//! level, plus the pixel-level over-segmentation of the input image.

use std::time::Instant;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::cells::{FeatureKind, LearnedCells, STRIP_PIXELS};
use super::hog::{HogMap, CELL_SIZE};
use super::image::ColorImage;
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
}

impl Default for PyramidParams {
    /// 11 levels from full size down to half size, HOG cells.
    fn default() -> Self {
        Self {
            levels_per_octave: 10,
            max_scale: 1.0,
            min_scale: 0.5,
            features: FeatureKind::Hog,
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
            && self.max_scale <= 4.0;
        if !ok {
            return Err(VisionError::InvalidParameter(format!(
                "pyramid needs 1 <= levels_per_octave <= 64 and 0 < min_scale <= max_scale <= 4, got {self:?}"
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
        let levels = hogs
            .into_par_iter()
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
            .collect::<Result<_, _>>()?;
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
/// before each level).
pub fn feature_levels(
    img: &ColorImage,
    params: &PyramidParams,
    deadline: Deadline,
) -> Result<Vec<(usize, usize, HogMap)>, VisionError> {
    let (w, h) = (img.width(), img.height());
    level_sizes(w, h, params)
        .into_par_iter()
        .map(|(lw, lh)| {
            if deadline.passed() {
                return Err(VisionError::DeadlineExceeded);
            }
            // A large level of learned cells, strip by strip.
            if params.features.in_strips(lw * lh) {
                let cells = LearnedCells::builtin()?;
                return Ok((
                    lw,
                    lh,
                    cells.level_cells_until(img, (lw, lh), STRIP_PIXELS, deadline)?,
                ));
            }
            // The full-size level reads the image itself.
            if (lw, lh) == (w, h) {
                return Ok((lw, lh, params.features.cells_until(img, deadline)?));
            }
            // HOG levels as ever; learned cells see upsampled levels
            // interpolated, not in blocks.
            let resized = params.features.resize_until(img, lw, lh, deadline)?;
            if deadline.passed() {
                return Err(VisionError::DeadlineExceeded);
            }
            Ok((lw, lh, params.features.cells_until(&resized, deadline)?))
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
