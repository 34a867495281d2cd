//! Response transfer between the detectors of several objects (paper,
//! section 2.5 and Algorithm 1): the detectors run one after another, and
//! where an earlier object's detection marked cells visible, a later
//! detector's occlusion response is replaced by the earlier object's
//! collected object-filter response. An occlusion there is then decided
//! between two objects' filters rather than against a generic occlusion
//! filter: a detection of one object explains the occlusion of another
//! that it covers.
//!
//! Where the paper replaces the occlusion response by the collected
//! object response outright, here it is capped by it and by 0: the
//! occlusion response of a claimed cell is `min(B, max(C, 0))`. A
//! transferred response explains an occlusion (removes the occlusion
//! filter's objection) but never rewards one: with the paper's
//! replacement, on the synthetic test scenes a box made only of another
//! object's cells became the best detection (score 59 against the object's
//! 62, every cell hidden), since a well-matched object's responses are far
//! below 0. Our detectors of different objects are trained apart, so
//! their responses are not made comparable by joint training as the
//! paper's are.
//!
//! The claimed cells are kept per pyramid level (a cell is claimed when
//! most of its pixels lie in the earlier detection's visible mask), with
//! the mean object response per visible cell of that detection: the
//! detections of different objects sit on different levels, so the
//! per-cell responses of one do not line up with the cells of another.
//!
//! Exactness: a transferred response can lower a location's energy below
//! the stage-1 bound, so every location whose box meets a claimed cell is
//! visited whatever its stage-1 bound (the stage-2 bounds and the min-cut
//! see the transferred responses): the detections are still exactly those
//! of solving every location.

use super::super::mask::Mask;
use super::super::pyramid::FeaturePyramid;
use super::CELL_SIZE;

/// The claimed cells of every level and their collected responses.
#[derive(Clone, Debug, Default)]
pub struct Transfer {
    levels: Vec<LevelClaims>,
}

#[derive(Clone, Debug, Default)]
struct LevelClaims {
    width: usize,
    height: usize,
    /// The collected response per cell (NaN where unclaimed).
    response: Vec<f32>,
    /// Summed-area table of the claimed cells, `(width + 1) x (height + 1)`.
    integral: Vec<u32>,
}

impl Transfer {
    /// No claimed cell, for the levels of `pyr`.
    pub fn new(pyr: &FeaturePyramid) -> Self {
        Self {
            levels: pyr
                .levels
                .iter()
                .map(|l| {
                    let (w, h) = (l.hog.width(), l.hog.height());
                    LevelClaims {
                        width: w,
                        height: h,
                        response: vec![f32::NAN; w * h],
                        integral: vec![0; (w + 1) * (h + 1)],
                    }
                })
                .collect(),
        }
    }

    /// Whether no cell is claimed.
    pub fn is_empty(&self) -> bool {
        self.levels
            .iter()
            .all(|l| l.integral.last().is_none_or(|&v| v == 0))
    }

    /// Claims, on every level, the cells with more than half of their
    /// pixels in `visible` (the image's size), with the collected response
    /// `response` (later claims replace earlier ones, as the label map of
    /// Algorithm 1 keeps the last object).
    pub fn claim(&mut self, pyr: &FeaturePyramid, visible: &Mask, response: f32) {
        if !response.is_finite() {
            return;
        }
        let (iw, ih) = (visible.width, visible.height);
        // Summed-area table of the mask.
        let mut sat = vec![0u32; (iw + 1) * (ih + 1)];
        for y in 0..ih {
            let mut row = 0u32;
            for x in 0..iw {
                row += u32::from(visible.get(x, y));
                sat[(y + 1) * (iw + 1) + x + 1] = sat[y * (iw + 1) + x + 1] + row;
            }
        }
        let count = |x0: usize, y0: usize, x1: usize, y1: usize| -> u32 {
            sat[y1 * (iw + 1) + x1] + sat[y0 * (iw + 1) + x0]
                - sat[y0 * (iw + 1) + x1]
                - sat[y1 * (iw + 1) + x0]
        };
        for (claims, level) in self.levels.iter_mut().zip(&pyr.levels) {
            let cs = CELL_SIZE as f64;
            for cy in 0..claims.height {
                let y0 = ((cy as f64 * cs / level.scale_y).round() as usize).min(ih);
                let y1 = (((cy + 1) as f64 * cs / level.scale_y).round() as usize).min(ih);
                for cx in 0..claims.width {
                    let x0 = ((cx as f64 * cs / level.scale_x).round() as usize).min(iw);
                    let x1 = (((cx + 1) as f64 * cs / level.scale_x).round() as usize).min(iw);
                    let area = (x1 - x0) * (y1 - y0);
                    if area > 0 && 2 * count(x0, y0, x1, y1) as usize > area {
                        claims.response[cy * claims.width + cx] = response;
                    }
                }
            }
            let w = claims.width;
            for y in 0..claims.height {
                let mut row = 0u32;
                for x in 0..w {
                    row += u32::from(!claims.response[y * w + x].is_nan());
                    claims.integral[(y + 1) * (w + 1) + x + 1] =
                        claims.integral[y * (w + 1) + x + 1] + row;
                }
            }
        }
    }

    /// The collected response of cell `(x, y)` of `level`, if claimed.
    pub fn at(&self, level: usize, x: usize, y: usize) -> Option<f32> {
        let l = self.levels.get(level)?;
        (x < l.width && y < l.height)
            .then(|| l.response[y * l.width + x])
            .filter(|v| !v.is_nan())
    }

    /// Whether the box of `cols x rows` cells at `(x, y)` on `level` meets
    /// a claimed cell.
    pub fn meets(&self, level: usize, x: isize, y: isize, cols: usize, rows: usize) -> bool {
        let Some(l) = self.levels.get(level) else {
            return false;
        };
        let clip = |v: isize, hi: usize| v.clamp(0, hi as isize) as usize;
        let (x0, x1) = (clip(x, l.width), clip(x + cols as isize, l.width));
        let (y0, y1) = (clip(y, l.height), clip(y + rows as isize, l.height));
        if x0 >= x1 || y0 >= y1 {
            return false;
        }
        let w = l.width + 1;
        l.integral[y1 * w + x1] + l.integral[y0 * w + x0]
            > l.integral[y0 * w + x1] + l.integral[y1 * w + x0]
    }
}
