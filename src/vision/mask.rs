//! Binary pixel masks: the raw cell mask of a detection drawn in image
//! pixels, its refinement by image segments (paper section 3.3), and COCO
//! uncompressed run-length encoding.

use serde::{Deserialize, Serialize};

/// A binary mask over an image, row-major, one byte per pixel (0 or 1).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Mask {
    pub width: usize,
    pub height: usize,
    pub data: Vec<u8>,
}

impl Mask {
    pub fn new(width: usize, height: usize) -> Self {
        Self {
            width,
            height,
            data: vec![0; width * height],
        }
    }

    #[inline]
    pub fn get(&self, x: usize, y: usize) -> bool {
        self.data[y * self.width + x] != 0
    }

    #[inline]
    pub fn set(&mut self, x: usize, y: usize, v: bool) {
        self.data[y * self.width + x] = u8::from(v);
    }

    /// The mask mirrored left to right.
    pub fn mirrored(&self) -> Self {
        let mut data = Vec::with_capacity(self.data.len());
        for line in self.data.chunks_exact(self.width.max(1)) {
            data.extend(line.iter().rev());
        }
        Self {
            width: self.width,
            height: self.height,
            data,
        }
    }

    pub fn area(&self) -> usize {
        self.data.iter().filter(|&&v| v != 0).count()
    }

    /// The tight box `(x0, y0, x1, y1)` (exclusive ends) of the mask's
    /// pixels; `None` when it is empty.
    pub fn tight_box(&self) -> Option<(usize, usize, usize, usize)> {
        let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
        for y in 0..self.height {
            for x in 0..self.width {
                if self.get(x, y) {
                    x0 = x0.min(x);
                    y0 = y0.min(y);
                    x1 = x1.max(x + 1);
                    y1 = y1.max(y + 1);
                }
            }
        }
        (x0 != usize::MAX).then_some((x0, y0, x1, y1))
    }

    /// Intersection over union with another mask of the same size (1 when
    /// both are empty).
    pub fn iou(&self, other: &Mask) -> f64 {
        let mut inter = 0usize;
        let mut union = 0usize;
        for (a, b) in self.data.iter().zip(&other.data) {
            let (a, b) = (*a != 0, *b != 0);
            inter += usize::from(a && b);
            union += usize::from(a || b);
        }
        if union == 0 {
            1.0
        } else {
            inter as f64 / union as f64
        }
    }

    /// COCO uncompressed RLE: column-major run lengths, starting with a run
    /// of zeros (possibly empty).
    pub fn to_rle(&self) -> Rle {
        let (w, h) = (self.width, self.height);
        let mut counts = Vec::new();
        let mut current = 0u8;
        let mut run = 0u32;
        // Appends `n` pixels of value `v` in column-major order.
        let mut feed = |v: u8, n: usize| {
            if n == 0 {
                return;
            }
            if v != current {
                counts.push(run);
                run = 0;
                current = v;
            }
            run += n as u32;
        };
        // Only the columns and rows of the set pixels' bounding box need
        // reading; the pixels around it are zeros, fed as whole runs.
        if let Some((bx0, by0, bx1, by1)) = self.bounds() {
            feed(0, bx0 * h);
            for x in bx0..=bx1 {
                feed(0, by0);
                for y in by0..=by1 {
                    feed(u8::from(self.get(x, y)), 1);
                }
                feed(0, h - 1 - by1);
            }
            feed(0, (w - 1 - bx1) * h);
        } else {
            feed(0, w * h);
        }
        counts.push(run);
        Rle {
            size: [h, w],
            counts,
        }
    }

    /// The inclusive bounding box `(x0, y0, x1, y1)` of the set pixels, if
    /// any.
    pub fn bounds(&self) -> Option<(usize, usize, usize, usize)> {
        let w = self.width;
        if w == 0 {
            return None;
        }
        let mut b: Option<(usize, usize, usize, usize)> = None;
        for (y, row) in self.data.chunks_exact(w).enumerate() {
            let Some(first) = row.iter().position(|&v| v != 0) else {
                continue;
            };
            let last = row.iter().rposition(|&v| v != 0).unwrap_or(first);
            b = Some(match b {
                None => (first, y, last, y),
                Some((x0, y0, x1, _)) => (x0.min(first), y0, x1.max(last), y),
            });
        }
        b
    }

    /// Decodes a COCO uncompressed RLE; `None` when the counts do not cover
    /// exactly `h * w` pixels.
    pub fn from_rle(rle: &Rle) -> Option<Self> {
        let [h, w] = rle.size;
        let total: u64 = rle.counts.iter().map(|&c| u64::from(c)).sum();
        if total != (h as u64) * (w as u64) {
            return None;
        }
        let mut m = Mask::new(w, h);
        let mut p = 0usize;
        for (k, &c) in rle.counts.iter().enumerate() {
            for _ in 0..c {
                if k % 2 == 1 {
                    let (x, y) = (p / h, p % h);
                    m.set(x, y, true);
                }
                p += 1;
            }
        }
        Some(m)
    }
}

/// COCO uncompressed RLE (`size` is `[height, width]`).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Rle {
    pub size: [usize; 2],
    pub counts: Vec<u32>,
}

/// COCO compressed RLE: the run lengths as the `counts` string of
/// pycocotools (`frPyObjects` and `decode` read it as it is).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CompressedRle {
    pub size: [usize; 2],
    pub counts: String,
}

impl Rle {
    /// The compressed form, as pycocotools' `rleToString` writes it: each
    /// count (from the third on, less the count two before it) in 5-bit
    /// groups, low first, each group a character from 48 on with bit 5
    /// saying that more follow, the last group's bit 4 its sign.
    pub fn compress(&self) -> CompressedRle {
        let mut out = String::new();
        for (i, &c) in self.counts.iter().enumerate() {
            let mut x = i64::from(c);
            if i > 2 {
                x -= i64::from(self.counts[i - 2]);
            }
            loop {
                let mut g = (x & 0x1f) as u8;
                x >>= 5;
                let more = if g & 0x10 != 0 { x != -1 } else { x != 0 };
                if more {
                    g |= 0x20;
                }
                out.push(char::from(g + 48));
                if !more {
                    break;
                }
            }
        }
        CompressedRle {
            size: self.size,
            counts: out,
        }
    }
}

impl CompressedRle {
    /// The run lengths back (pycocotools' `rleFrString`); `None` for a
    /// string that is not a valid encoding.
    pub fn decompress(&self) -> Option<Rle> {
        let bytes = self.counts.as_bytes();
        let mut counts: Vec<u32> = Vec::new();
        let mut p = 0;
        while p < bytes.len() {
            let (mut x, mut k) = (0i64, 0u32);
            loop {
                let c = i64::from(bytes.get(p)?.checked_sub(48)?);
                if c > 0x3f || k > 12 {
                    return None;
                }
                x |= (c & 0x1f) << (5 * k);
                p += 1;
                k += 1;
                if c & 0x20 == 0 {
                    if c & 0x10 != 0 {
                        x |= -1i64 << (5 * k);
                    }
                    break;
                }
            }
            let m = counts.len();
            if m > 2 {
                x += i64::from(counts[m - 2]);
            }
            counts.push(u32::try_from(x).ok()?);
        }
        Some(Rle {
            size: self.size,
            counts,
        })
    }
}

/// Geometry of a box on a pyramid level, to draw cell labels in pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CellGrid {
    /// Top-left cell of the box on the level (may be negative).
    pub cell_x: isize,
    pub cell_y: isize,
    pub rows: usize,
    pub cols: usize,
    /// Level size over image size.
    pub scale_x: f64,
    pub scale_y: f64,
    pub cell_size: usize,
}

impl CellGrid {
    /// The box in image pixels `(x, y, width, height)`.
    pub fn pixel_box(&self) -> (f64, f64, f64, f64) {
        let cs = self.cell_size as f64;
        (
            self.cell_x as f64 * cs / self.scale_x,
            self.cell_y as f64 * cs / self.scale_y,
            self.cols as f64 * cs / self.scale_x,
            self.rows as f64 * cs / self.scale_y,
        )
    }

    /// Pixel range `[x0, x1) x [y0, y1)` of the box clipped to the image.
    pub fn pixel_range(&self, width: usize, height: usize) -> (usize, usize, usize, usize) {
        let (x, y, w, h) = self.pixel_box();
        let clip = |v: f64, hi: usize| v.round().clamp(0.0, hi as f64) as usize;
        (
            clip(x, width),
            clip(y, height),
            clip(x + w, width),
            clip(y + h, height),
        )
    }

    /// The box cell containing pixel `(px, py)`, if any.
    #[inline]
    pub fn cell_of(&self, px: usize, py: usize) -> Option<usize> {
        let cs = self.cell_size as f64;
        let cx = ((px as f64 + 0.5) * self.scale_x / cs).floor() as isize - self.cell_x;
        let cy = ((py as f64 + 0.5) * self.scale_y / cs).floor() as isize - self.cell_y;
        (cx >= 0 && cy >= 0 && (cx as usize) < self.cols && (cy as usize) < self.rows)
            .then(|| cy as usize * self.cols + cx as usize)
    }
}

/// Draws the cell labels of a box as a pixel mask over the image.
pub fn raw_mask(grid: &CellGrid, labels: &[bool], width: usize, height: usize) -> Mask {
    let mut m = Mask::new(width, height);
    let (x0, y0, x1, y1) = grid.pixel_range(width, height);
    for y in y0..y1 {
        for x in x0..x1 {
            if let Some(i) = grid.cell_of(x, y) {
                if labels[i] {
                    m.set(x, y, true);
                }
            }
        }
    }
    m
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;

    #[test]
    fn compressed_rle_round_trips_and_matches_pycocotools() {
        // pycocotools: encode(np.asfortranarray(m)) of a 4x4 mask with
        // column 1 rows 1..3 and column 3 set gives b'5252' (runs 5, 2, 5,
        // 4; the fourth written less the second).
        let rle = Rle {
            size: [4, 4],
            counts: vec![5, 2, 5, 4],
        };
        let c = rle.compress();
        assert_eq!(c.counts, "5252");
        assert_eq!(c.decompress().unwrap(), rle);
        let mut rng = crate::vision::rng::SplitMix64::new(5);
        for _ in 0..200 {
            let n = (rng.next_u64() % 40) as usize;
            let counts: Vec<u32> = (0..n)
                .map(|_| {
                    (rng.next_u64() % [3, 40, 5000, 2_000_000][(rng.next_u64() % 4) as usize])
                        as u32
                })
                .collect();
            let rle = Rle {
                size: [1, 1],
                counts,
            };
            assert_eq!(rle.compress().decompress().unwrap(), rle);
        }
        for bad in ["/", "\u{7f}", "o"] {
            let c = CompressedRle {
                size: [1, 1],
                counts: bad.to_string(),
            };
            assert_eq!(c.decompress(), None, "{bad:?}");
        }
    }

    #[test]
    fn rle_is_column_major_and_round_trips() {
        let mut m = Mask::new(3, 2);
        m.set(0, 1, true);
        m.set(1, 0, true);
        m.set(1, 1, true);
        // Column-major: (0,0)=0 (0,1)=1 (1,0)=1 (1,1)=1 (2,0)=0 (2,1)=0.
        let rle = m.to_rle();
        assert_eq!(rle.size, [2, 3]);
        assert_eq!(rle.counts, vec![1, 3, 2]);
        assert_eq!(Mask::from_rle(&rle).unwrap(), m);
        let mut full = Mask::new(2, 2);
        full.data.iter_mut().for_each(|v| *v = 1);
        assert_eq!(full.to_rle().counts, vec![0, 4]);
        assert!(Mask::from_rle(&Rle {
            size: [2, 2],
            counts: vec![1, 1]
        })
        .is_none());
    }

    #[test]
    fn cells_map_to_pixels() {
        let grid = CellGrid {
            cell_x: -1,
            cell_y: 0,
            rows: 1,
            cols: 2,
            scale_x: 0.5,
            scale_y: 0.5,
            cell_size: 8,
        };
        // Box covers pixels x in [-16, 16), y in [0, 16).
        assert_eq!(grid.pixel_box(), (-16.0, 0.0, 32.0, 16.0));
        let m = raw_mask(&grid, &[true, false], 20, 20);
        // Cell 0 is outside the image; cell 1 covers x 0..16 but is occluded.
        assert_eq!(m.area(), 0);
        let m = raw_mask(&grid, &[false, true], 20, 20);
        assert_eq!(m.area(), 16 * 16);
        assert!(m.get(15, 15) && !m.get(16, 0) && !m.get(0, 16));
    }

    /// The column-major run lengths read pixel by pixel, as `to_rle` was
    /// first written.
    fn rle_direct(m: &Mask) -> Vec<u32> {
        let (mut counts, mut current, mut run) = (Vec::new(), 0u8, 0u32);
        for x in 0..m.width {
            for y in 0..m.height {
                let v = u8::from(m.get(x, y));
                if v != current {
                    counts.push(run);
                    run = 0;
                    current = v;
                }
                run += 1;
            }
        }
        counts.push(run);
        counts
    }

    #[test]
    fn rle_from_the_bounding_box_equals_the_direct_scan() {
        let mut rng = crate::vision::rng::SplitMix64::new(11);
        for t in 0..200 {
            let (w, h) = (1 + t % 13, 1 + (t / 13) % 11);
            let mut m = Mask::new(w, h);
            // Empty, full, single pixels and random blobs.
            match t % 4 {
                0 => {}
                1 => m.data.fill(1),
                2 => {
                    let (x, y) = (rng.range_usize(0, w), rng.range_usize(0, h));
                    m.set(x, y, true);
                }
                _ => {
                    for v in m.data.iter_mut() {
                        *v = u8::from(rng.range_usize(0, 3) == 0);
                    }
                }
            }
            assert_eq!(m.to_rle().counts, rle_direct(&m), "{w}x{h}, case {}", t % 4);
            let b = m.bounds();
            assert_eq!(b.is_none(), m.data.iter().all(|&v| v == 0));
        }
    }
}
