//! Distances to a visibility mask, to test at once whether a point lies
//! in the mask grown by any margin (the refinement's search range
//! shrinks, its margin stays).

use nalgebra::Vector2;

use crate::vision::mask::Mask;

/// The row-major index of the pixel containing `p` in a `width` x
/// `height` grid, if inside it.
pub(super) fn pixel_index(p: &Vector2<f64>, width: usize, height: usize) -> Option<usize> {
    if p.x < 0.0 || p.y < 0.0 {
        return None;
    }
    let (x, y) = (p.x as usize, p.y as usize);
    (x < width && y < height).then(|| y * width + x)
}

/// The chessboard (L-infinity) distance of every pixel to the nearest pixel
/// of a mask: a pixel lies in the mask grown by `r` (square neighbourhood)
/// exactly when its distance is at most `r`. One map answers every growth
/// the refinement asks (the search range shrinks, the margin stays).
pub struct MaskDistance {
    width: usize,
    height: usize,
    /// Saturates at `u16::MAX` (no mask pixel, or farther).
    dist: Vec<u16>,
}

impl MaskDistance {
    /// Two raster passes with unit steps to all 8 neighbours, which is
    /// exact for the chessboard distance.
    pub fn new(m: &Mask) -> Self {
        let (w, h) = (m.width, m.height);
        let mut d = vec![u16::MAX; w * h];
        for y in 0..h {
            for x in 0..w {
                if m.get(x, y) {
                    d[y * w + x] = 0;
                }
            }
        }
        let step = |v: u16| v.saturating_add(1);
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let mut v = d[i];
                if x > 0 {
                    v = v.min(step(d[i - 1]));
                }
                if y > 0 {
                    v = v.min(step(d[i - w]));
                    if x > 0 {
                        v = v.min(step(d[i - w - 1]));
                    }
                    if x + 1 < w {
                        v = v.min(step(d[i - w + 1]));
                    }
                }
                d[i] = v;
            }
        }
        for y in (0..h).rev() {
            for x in (0..w).rev() {
                let i = y * w + x;
                let mut v = d[i];
                if x + 1 < w {
                    v = v.min(step(d[i + 1]));
                }
                if y + 1 < h {
                    v = v.min(step(d[i + w]));
                    if x + 1 < w {
                        v = v.min(step(d[i + w + 1]));
                    }
                    if x > 0 {
                        v = v.min(step(d[i + w - 1]));
                    }
                }
                d[i] = v;
            }
        }
        Self {
            width: w,
            height: h,
            dist: d,
        }
    }

    /// The distance of pixel `(x, y)` to the mask (saturated; outside
    /// the grid: the largest).
    pub fn distance(&self, x: usize, y: usize) -> usize {
        if x < self.width && y < self.height {
            usize::from(self.dist[y * self.width + x])
        } else {
            usize::MAX
        }
    }

    /// Whether the pixel containing `p` lies in the mask grown by `r`.
    pub fn within(&self, p: &Vector2<f64>, r: usize) -> bool {
        pixel_index(p, self.width, self.height).is_some_and(|i| usize::from(self.dist[i]) <= r)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::rng::SplitMix64;

    #[test]
    fn mask_distance_equals_the_square_neighbourhood_test() {
        let mut rng = SplitMix64::new(3);
        let (w, h) = (37, 23);
        let mut m = Mask::new(w, h);
        for _ in 0..12 {
            m.set(rng.range_usize(0, w), rng.range_usize(0, h), true);
        }
        let d = MaskDistance::new(&m);
        for r in [0, 1, 3, 30] {
            for y in 0..h {
                for x in 0..w {
                    let near = (y.saturating_sub(r)..(y + r + 1).min(h)).any(|yy| {
                        (x.saturating_sub(r)..(x + r + 1).min(w)).any(|xx| m.get(xx, yy))
                    });
                    let p = Vector2::new(x as f64 + 0.5, y as f64 + 0.5);
                    assert_eq!(d.within(&p, r), near, "r {r}, ({x}, {y})");
                }
            }
        }
        // No mask pixel: nothing is near it.
        let none = MaskDistance::new(&Mask::new(5, 4));
        assert!(!none.within(&Vector2::new(1.0, 1.0), 1000));
        assert!(!d.within(&Vector2::new(-0.5, 1.0), 1000));
    }
}
