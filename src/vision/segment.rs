//! Felzenszwalb-Huttenlocher graph-based over-segmentation (IJCV 2004), and
//! the assignment of segments to the HOG cells of every pyramid level.
//!
//! The image is smoothed by a Gaussian, an 8-connected grid graph is built
//! with Euclidean colour distances as weights, edges are sorted (a stable
//! radix sort, so the result is deterministic), and components are merged
//! while the edge weight is no larger than both components' internal
//! difference plus `k / size`. Components smaller than `min_size` are then
//! merged along the remaining edges in the same order.

use serde::{Deserialize, Serialize};

use super::image::{ColorImage, CHANNELS};
use super::{Deadline, VisionError};

/// Parameters of the over-segmentation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SegmentParams {
    /// Gaussian pre-smoothing standard deviation in pixels (0 = none).
    pub sigma: f32,
    /// Scale of the merge threshold (larger means larger segments).
    pub k: f32,
    /// Minimum segment size in pixels (1 keeps every segment).
    pub min_size: usize,
    /// Segment an image this many times smaller (area-averaged), then give
    /// every pixel the label of its low-resolution pixel: a speed knob. 1 =
    /// full resolution. `sigma` and `min_size` stay in full-resolution pixels.
    #[serde(default = "one")]
    pub downsample: usize,
}

fn one() -> usize {
    1
}

impl Default for SegmentParams {
    fn default() -> Self {
        Self {
            sigma: 0.8,
            k: 300.0,
            min_size: 50,
            downsample: 2,
        }
    }
}

impl SegmentParams {
    pub fn validate(&self) -> Result<(), VisionError> {
        if !self.sigma.is_finite() || self.sigma < 0.0 || self.sigma > 20.0 {
            return Err(VisionError::InvalidParameter(format!(
                "segmentation sigma must be in [0, 20], got {}",
                self.sigma
            )));
        }
        if !self.k.is_finite() || self.k < 0.0 {
            return Err(VisionError::InvalidParameter(format!(
                "segmentation k must be finite and >= 0, got {}",
                self.k
            )));
        }
        if !(1..=8).contains(&self.downsample) {
            return Err(VisionError::InvalidParameter(format!(
                "segmentation downsample must be in 1..=8, got {}",
                self.downsample
            )));
        }
        if self.min_size == 0 {
            return Err(VisionError::InvalidParameter(
                "segmentation min_size must be >= 1".into(),
            ));
        }
        Ok(())
    }
}

/// A label per pixel, labels `0..count` numbered in raster order of first
/// appearance.
#[derive(Clone, Debug, PartialEq)]
pub struct Segmentation {
    width: usize,
    height: usize,
    labels: Vec<u32>,
    count: usize,
}

impl Segmentation {
    /// Builds a segmentation from raw labels, renumbering them in raster order.
    pub fn from_labels(width: usize, height: usize, raw: &[u32]) -> Result<Self, VisionError> {
        if raw.len() != width * height {
            return Err(VisionError::BufferSize {
                expected: width * height,
                actual: raw.len(),
            });
        }
        let mut map = std::collections::HashMap::new();
        let labels = raw
            .iter()
            .map(|&r| {
                let n = map.len() as u32;
                *map.entry(r).or_insert(n)
            })
            .collect();
        Ok(Self {
            width,
            height,
            labels,
            count: map.len(),
        })
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    /// The segment count alone, without the per-pixel labels (an empty
    /// `0 x 0` map): for pyramids kept only for training (see
    /// [`crate::vision::pyramid::FeaturePyramid::lean`]).
    pub fn without_labels(&self) -> Self {
        Self {
            width: 0,
            height: 0,
            labels: Vec::new(),
            count: self.count,
        }
    }

    /// Number of segments.
    pub fn count(&self) -> usize {
        self.count
    }

    /// Labels, row-major.
    pub fn labels(&self) -> &[u32] {
        &self.labels
    }

    #[inline]
    pub fn label(&self, x: usize, y: usize) -> u32 {
        self.labels[y * self.width + x]
    }

    /// Segment of every HOG cell of a pyramid level whose image is
    /// `level_w x level_h` pixels with `cells_w x cells_h` cells of
    /// `cell_size` pixels: the segment covering most of the cell's pixels,
    /// where a level pixel takes the label of the nearest image pixel (ties go
    /// to the lower label).
    pub fn cell_labels(
        &self,
        level_w: usize,
        level_h: usize,
        cells_w: usize,
        cells_h: usize,
        cell_size: usize,
    ) -> Vec<u32> {
        let sx = self.width as f64 / level_w as f64;
        let sy = self.height as f64 / level_h as f64;
        let col: Vec<usize> = (0..cells_w * cell_size)
            .map(|x| (((x as f64 + 0.5) * sx) as usize).min(self.width - 1))
            .collect();
        let rows: Vec<usize> = (0..cells_h * cell_size)
            .map(|y| (((y as f64 + 0.5) * sy) as usize).min(self.height - 1))
            .collect();
        let mut out = vec![0u32; cells_w * cells_h];
        let mut counts: Vec<(u32, u32)> = Vec::with_capacity(cell_size * cell_size);
        for cy in 0..cells_h {
            for cx in 0..cells_w {
                counts.clear();
                // Neighbouring pixels mostly share a segment: the entry of
                // the previous pixel's label is tried first.
                let mut last = usize::MAX;
                for &iy in &rows[cy * cell_size..(cy + 1) * cell_size] {
                    let row = &self.labels[iy * self.width..(iy + 1) * self.width];
                    for &ix in &col[cx * cell_size..(cx + 1) * cell_size] {
                        let l = row[ix];
                        if let Some(e) = counts.get_mut(last).filter(|e| e.0 == l) {
                            e.1 += 1;
                            continue;
                        }
                        last = match counts.iter().position(|(k, _)| *k == l) {
                            Some(i) => {
                                counts[i].1 += 1;
                                i
                            }
                            None => {
                                counts.push((l, 1));
                                counts.len() - 1
                            }
                        };
                    }
                }
                let mut best = (u32::MAX, 0u32);
                for &(l, c) in &counts {
                    if c > best.1 || (c == best.1 && l < best.0) {
                        best = (l, c);
                    }
                }
                out[cy * cells_w + cx] = best.0;
            }
        }
        out
    }
}

/// Union-find with union by rank and path halving.
struct DisjointSets {
    parent: Vec<u32>,
    rank: Vec<u8>,
    size: Vec<u32>,
}

impl DisjointSets {
    fn new(n: usize) -> Self {
        Self {
            parent: (0..n as u32).collect(),
            rank: vec![0; n],
            size: vec![1; n],
        }
    }

    #[inline]
    fn find(&mut self, mut x: u32) -> u32 {
        while self.parent[x as usize] != x {
            let p = self.parent[x as usize];
            self.parent[x as usize] = self.parent[p as usize];
            x = p;
        }
        x
    }

    /// Joins two roots; returns the new root.
    #[inline]
    fn join(&mut self, a: u32, b: u32) -> u32 {
        let (ra, rb) = (self.rank[a as usize], self.rank[b as usize]);
        let (root, child) = if ra > rb { (a, b) } else { (b, a) };
        if ra == rb {
            self.rank[root as usize] += 1;
        }
        self.parent[child as usize] = root;
        self.size[root as usize] += self.size[child as usize];
        root
    }
}

/// Separable Gaussian smoothing of every channel, edges clamped.
pub fn gaussian_blur(img: &ColorImage, sigma: f32) -> ColorImage {
    // Nothing gives up without a deadline.
    blur_checked(img, sigma, &|| Ok(())).unwrap_or_else(|_| img.clone())
}

/// [`gaussian_blur`] that stops with `check`'s error, looked at every 64
/// rows of each pass.
fn blur_checked(
    img: &ColorImage,
    sigma: f32,
    check: &dyn Fn() -> Result<(), VisionError>,
) -> Result<ColorImage, VisionError> {
    if sigma <= 0.0 {
        return Ok(img.clone());
    }
    let radius = (4.0 * sigma).ceil() as isize;
    let mut kernel: Vec<f32> = (-radius..=radius)
        .map(|i| (-(i * i) as f32 / (2.0 * sigma * sigma)).exp())
        .collect();
    let sum: f32 = kernel.iter().sum();
    kernel.iter_mut().for_each(|k| *k /= sum);
    let (w, h) = (img.width(), img.height());
    let src = img.data();
    let mut tmp = vec![0.0f32; src.len()];
    for y in 0..h {
        if y % 64 == 0 {
            check()?;
        }
        for x in 0..w {
            let mut acc = [0.0f32; CHANNELS];
            for (k, &kv) in kernel.iter().enumerate() {
                let xx = (x as isize + k as isize - radius).clamp(0, w as isize - 1) as usize;
                let p = (y * w + xx) * CHANNELS;
                for c in 0..CHANNELS {
                    acc[c] += kv * src[p + c];
                }
            }
            tmp[(y * w + x) * CHANNELS..(y * w + x + 1) * CHANNELS].copy_from_slice(&acc);
        }
    }
    let row = w * CHANNELS;
    let mut out = vec![0.0f32; src.len()];
    for y in 0..h {
        if y % 64 == 0 {
            check()?;
        }
        let dst = &mut out[y * row..(y + 1) * row];
        for (k, &kv) in kernel.iter().enumerate() {
            let yy = (y as isize + k as isize - radius).clamp(0, h as isize - 1) as usize;
            for (d, s) in dst.iter_mut().zip(&tmp[yy * row..(yy + 1) * row]) {
                *d += kv * s;
            }
        }
    }
    // Dimensions are unchanged and samples stay finite.
    Ok(ColorImage::new(w, h, out).unwrap_or_else(|_| img.clone()))
}

/// Neighbour offsets of the 8-connected graph (each undirected edge once).
const DIRS: [(isize, isize); 4] = [(1, 0), (0, 1), (1, 1), (1, -1)];

/// Stable LSD radix sort of `(key << 32) | payload` values by key.
#[cfg(test)]
fn radix_sort_by_key(items: &mut Vec<u64>) {
    // Nothing gives up without a deadline.
    let _ = radix_sort_checked(items, &|| Ok(()));
}

/// [`radix_sort_by_key`] that stops with `check`'s error, looked at
/// before each pass (a pass over 16 M edges is tens of milliseconds).
fn radix_sort_checked(
    items: &mut Vec<u64>,
    check: &dyn Fn() -> Result<(), VisionError>,
) -> Result<(), VisionError> {
    let mut buf = vec![0u64; items.len()];
    const BITS: u32 = 11;
    const BUCKETS: usize = 1 << BITS;
    for pass in 0..3u32 {
        check()?;
        let shift = 32 + pass * BITS;
        let mut count = vec![0usize; BUCKETS + 1];
        for &v in items.iter() {
            count[((v >> shift) as usize & (BUCKETS - 1)) + 1] += 1;
        }
        if count[1] == items.len() && pass > 0 {
            // Every key has this digit zero: nothing to reorder.
            continue;
        }
        for i in 0..BUCKETS {
            count[i + 1] += count[i];
        }
        for &v in items.iter() {
            let d = (v >> shift) as usize & (BUCKETS - 1);
            buf[count[d]] = v;
            count[d] += 1;
        }
        std::mem::swap(items, &mut buf);
    }
    Ok(())
}

/// Segments an image.
pub fn segment(img: &ColorImage, params: &SegmentParams) -> Result<Segmentation, VisionError> {
    segment_until(img, params, Deadline::NONE)
}

/// Edges (or pixel rows, times four) between two looks at the deadline:
/// about a millisecond of work.
const DEADLINE_EDGES: usize = 1 << 18;

/// [`segment`] that gives up with [`VisionError::DeadlineExceeded`] once
/// `deadline` has passed (looked at between the steps and every
/// [`DEADLINE_EDGES`] edges within them).
pub fn segment_until(
    img: &ColorImage,
    params: &SegmentParams,
    deadline: Deadline,
) -> Result<Segmentation, VisionError> {
    params.validate()?;
    let f = params.downsample;
    let check = || {
        if deadline.passed() {
            Err(VisionError::DeadlineExceeded)
        } else {
            Ok(())
        }
    };
    if f == 1 {
        return segment_full(img, params, &check);
    }
    let (w, h) = (img.width(), img.height());
    let (sw, sh) = (w.div_ceil(f), h.div_ceil(f));
    let small = img.resize_area_until(sw, sh, deadline)?;
    let p = SegmentParams {
        sigma: params.sigma / f as f32,
        min_size: params.min_size.div_ceil(f * f),
        downsample: 1,
        ..*params
    };
    let s = segment_full(&small, &p, &check)?;
    let mut raw: Vec<u32> = Vec::with_capacity(w * h);
    for y in 0..h {
        if y % 256 == 0 {
            check()?;
        }
        let sy = (y / f).min(sh - 1);
        raw.extend((0..w).map(|x| s.label((x / f).min(sw - 1), sy)));
    }
    check()?;
    compact(w, h, raw)
}

fn segment_full(
    img: &ColorImage,
    params: &SegmentParams,
    check: &dyn Fn() -> Result<(), VisionError>,
) -> Result<Segmentation, VisionError> {
    check()?;
    let smooth = blur_checked(img, params.sigma, check)?;
    let (w, h) = (smooth.width(), smooth.height());
    let n = w * h;
    if n > (u32::MAX / 4) as usize {
        return Err(VisionError::ImageTooLarge {
            width: w,
            height: h,
        });
    }
    let d = smooth.data();
    // Edge id = pixel * 4 + direction; key = bits of the non-negative weight.
    let mut edges: Vec<u64> = Vec::with_capacity(n * 4);
    let rows_per_check = (DEADLINE_EDGES / (4 * w)).max(1);
    for y in 0..h {
        if y % rows_per_check == 0 {
            check()?;
        }
        for x in 0..w {
            let p = y * w + x;
            for (k, &(dx, dy)) in DIRS.iter().enumerate() {
                let (nx, ny) = (x as isize + dx, y as isize + dy);
                if nx < 0 || ny < 0 || nx >= w as isize || ny >= h as isize {
                    continue;
                }
                let q = ny as usize * w + nx as usize;
                let mut s = 0.0f32;
                for c in 0..CHANNELS {
                    let diff = d[p * CHANNELS + c] - d[q * CHANNELS + c];
                    s += diff * diff;
                }
                let key = s.sqrt().to_bits() as u64;
                edges.push((key << 32) | (p * 4 + k) as u64);
            }
        }
    }
    radix_sort_checked(&mut edges, check)?;
    check()?;
    // Neighbour offsets per direction: no division when decoding an edge.
    let offsets: [isize; 4] = DIRS.map(|(dx, dy)| dy * w as isize + dx);
    let endpoints = |e: u64| -> (u32, u32, f32) {
        let id = (e & 0xFFFF_FFFF) as usize;
        let p = id >> 2;
        let q = (p as isize + offsets[id & 3]) as usize;
        (p as u32, q as u32, f32::from_bits((e >> 32) as u32))
    };
    let mut sets = DisjointSets::new(n);
    let mut thresh = vec![params.k; n];
    for (i, &e) in edges.iter().enumerate() {
        if i % DEADLINE_EDGES == 0 {
            check()?;
        }
        let (p, q, wgt) = endpoints(e);
        let a = sets.find(p);
        let b = sets.find(q);
        if a != b && wgt <= thresh[a as usize] && wgt <= thresh[b as usize] {
            let r = sets.join(a, b);
            thresh[r as usize] = wgt + params.k / sets.size[r as usize] as f32;
        }
    }
    if params.min_size > 1 {
        for (i, &e) in edges.iter().enumerate() {
            if i % DEADLINE_EDGES == 0 {
                check()?;
            }
            let (p, q, _) = endpoints(e);
            let a = sets.find(p);
            let b = sets.find(q);
            if a != b
                && ((sets.size[a as usize] as usize) < params.min_size
                    || (sets.size[b as usize] as usize) < params.min_size)
            {
                sets.join(a, b);
            }
        }
    }
    let raw: Vec<u32> = (0..n as u32).map(|p| sets.find(p)).collect();
    compact(w, h, raw)
}

/// Renumbers root labels into `0..count` in raster order (linear time).
fn compact(w: usize, h: usize, raw: Vec<u32>) -> Result<Segmentation, VisionError> {
    let mut map = vec![u32::MAX; raw.len()];
    let mut next = 0u32;
    let labels = raw
        .iter()
        .map(|&r| {
            let m = &mut map[r as usize];
            if *m == u32::MAX {
                *m = next;
                next += 1;
            }
            *m
        })
        .collect();
    Ok(Segmentation {
        width: w,
        height: h,
        labels,
        count: next as usize,
    })
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;

    /// The majority segment of every cell, against a direct count with a
    /// map (ties to the lower label), on random piecewise label maps at
    /// several level sizes.
    #[test]
    fn cell_labels_match_a_direct_majority_count() {
        let mut rng = crate::vision::rng::SplitMix64::new(21);
        let (w, h) = (97, 61);
        let raw: Vec<u32> = (0..w * h)
            .map(|p| {
                let (x, y) = (p % w, p / w);
                ((x / 7 + y / 5) % 6) as u32 + u32::from(rng.next_f64() < 0.2) * 7
            })
            .collect();
        let s = Segmentation::from_labels(w, h, &raw).unwrap();
        for (lw, lh) in [(97, 61), (160, 100), (64, 40), (33, 20)] {
            let (cw, ch) = (lw / 8, lh / 8);
            let got = s.cell_labels(lw, lh, cw, ch, 8);
            let (sx, sy) = (w as f64 / lw as f64, h as f64 / lh as f64);
            for cy in 0..ch {
                for cx in 0..cw {
                    let mut n = std::collections::BTreeMap::new();
                    for py in cy * 8..cy * 8 + 8 {
                        for px in cx * 8..cx * 8 + 8 {
                            let ix = (((px as f64 + 0.5) * sx) as usize).min(w - 1);
                            let iy = (((py as f64 + 0.5) * sy) as usize).min(h - 1);
                            *n.entry(s.label(ix, iy)).or_insert(0u32) += 1;
                        }
                    }
                    // Ascending labels: the first of the largest count.
                    let best = n.iter().fold(
                        (u32::MAX, 0),
                        |b, (&l, &c)| {
                            if c > b.1 {
                                (l, c)
                            } else {
                                b
                            }
                        },
                    );
                    assert_eq!(got[cy * cw + cx], best.0, "{lw}x{lh} cell {cx},{cy}");
                }
            }
        }
    }

    fn blocks(w: usize, h: usize) -> ColorImage {
        // Four flat quadrants of very different colours.
        let mut d = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let q = (x >= w / 2) as usize + 2 * (y >= h / 2) as usize;
                let c = [
                    [250.0, 10.0, 10.0],
                    [10.0, 250.0, 10.0],
                    [10.0, 10.0, 250.0],
                    [250.0, 250.0, 10.0],
                ][q];
                d.extend_from_slice(&c);
            }
        }
        ColorImage::new(w, h, d).unwrap()
    }

    #[test]
    fn flat_quadrants_give_four_segments() {
        let img = blocks(40, 30);
        let s = segment(
            &img,
            &SegmentParams {
                sigma: 0.0,
                k: 10.0,
                min_size: 1,
                downsample: 1,
            },
        )
        .unwrap();
        assert_eq!(s.count(), 4);
        assert_eq!(s.label(0, 0), 0);
        assert_eq!(s.label(39, 0), 1);
        assert_eq!(s.label(0, 29), 2);
        assert_eq!(s.label(39, 29), 3);
        // Smoothing blurs the borders; min_size merges the thin strips away.
        let s2 = segment(
            &img,
            &SegmentParams {
                sigma: 0.8,
                k: 10.0,
                min_size: 100,
                downsample: 1,
            },
        )
        .unwrap();
        assert_eq!(s2.count(), 4);
    }

    #[test]
    fn deterministic_and_min_size_respected() {
        let mut rng = crate::vision::rng::SplitMix64::new(9);
        let data: Vec<f32> = (0..50 * 40 * 3)
            .map(|_| (rng.next_f64() * 255.0) as f32)
            .collect();
        let img = ColorImage::new(50, 40, data).unwrap();
        let p = SegmentParams {
            sigma: 0.5,
            k: 200.0,
            min_size: 30,
            downsample: 1,
        };
        let a = segment(&img, &p).unwrap();
        let b = segment(&img, &p).unwrap();
        assert_eq!(a, b);
        let mut sizes = vec![0usize; a.count()];
        a.labels().iter().for_each(|&l| sizes[l as usize] += 1);
        assert!(sizes.iter().all(|&s| s >= 30), "{sizes:?}");
    }

    #[test]
    fn single_pixel_segments_are_fine() {
        let mut rng = crate::vision::rng::SplitMix64::new(3);
        let data: Vec<f32> = (0..9 * 7 * 3)
            .map(|_| (rng.next_f64() * 255.0) as f32)
            .collect();
        let img = ColorImage::new(9, 7, data).unwrap();
        let s = segment(
            &img,
            &SegmentParams {
                sigma: 0.0,
                k: 0.0,
                min_size: 1,
                downsample: 1,
            },
        )
        .unwrap();
        // k = 0 merges only identical neighbours: random colours stay apart.
        assert_eq!(s.count(), 63);
        let cells = s.cell_labels(9, 7, 1, 0, 8);
        assert!(cells.is_empty());
    }

    #[test]
    fn invalid_params_are_refused() {
        let img = blocks(8, 8);
        for p in [
            SegmentParams {
                sigma: -1.0,
                ..Default::default()
            },
            SegmentParams {
                k: f32::NAN,
                ..Default::default()
            },
            SegmentParams {
                min_size: 0,
                ..Default::default()
            },
        ] {
            assert!(matches!(
                segment(&img, &p),
                Err(VisionError::InvalidParameter(_))
            ));
        }
    }

    #[test]
    fn radix_sort_is_stable_and_sorted() {
        let mut rng = crate::vision::rng::SplitMix64::new(5);
        let mut v: Vec<u64> = (0..5000u64)
            .map(|i| ((rng.next_u64() % 3000) << 32) | i)
            .collect();
        let mut expect = v.clone();
        expect.sort_by_key(|e| (e >> 32, e & 0xFFFF_FFFF));
        radix_sort_by_key(&mut v);
        assert_eq!(v, expect);
    }

    #[test]
    fn cells_take_the_majority_segment() {
        // Left 5 columns label 0, the rest label 1, 16x8 image: 2 cells.
        let raw: Vec<u32> = (0..8)
            .flat_map(|_| (0..16).map(|x| u32::from(x >= 5)))
            .collect();
        let s = Segmentation::from_labels(16, 8, &raw).unwrap();
        assert_eq!(s.cell_labels(16, 8, 2, 1, 8), vec![0, 1]);
        // At half resolution one cell covers the whole image: label 1 wins 11:5.
        assert_eq!(s.cell_labels(8, 4, 1, 0, 8), Vec::<u32>::new());
        assert_eq!(s.cell_labels(8, 8, 1, 1, 8), vec![1]);
    }

    /// Felzenszwalb-Huttenlocher as first written here: edges pixel by
    /// pixel, a comparison sort by (weight, id), the small-component pass
    /// over every edge.
    fn segment_reference(img: &ColorImage, params: &SegmentParams) -> Vec<u32> {
        let smooth = gaussian_blur(img, params.sigma);
        let (w, h) = (smooth.width(), smooth.height());
        let d = smooth.data();
        let mut edges: Vec<(f32, usize, usize)> = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let p = y * w + x;
                for &(dx, dy) in DIRS.iter() {
                    let (nx, ny) = (x as isize + dx, y as isize + dy);
                    if nx < 0 || ny < 0 || nx >= w as isize || ny >= h as isize {
                        continue;
                    }
                    let q = ny as usize * w + nx as usize;
                    let mut s = 0.0f32;
                    for c in 0..CHANNELS {
                        let diff = d[p * CHANNELS + c] - d[q * CHANNELS + c];
                        s += diff * diff;
                    }
                    edges.push((s.sqrt(), p, q));
                }
            }
        }
        // Stable: equal weights keep their pixel-then-direction order.
        edges.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut sets = DisjointSets::new(w * h);
        let mut thresh = vec![params.k; w * h];
        for &(wgt, p, q) in &edges {
            let (a, b) = (sets.find(p as u32), sets.find(q as u32));
            if a != b && wgt <= thresh[a as usize] && wgt <= thresh[b as usize] {
                let r = sets.join(a, b);
                thresh[r as usize] = wgt + params.k / sets.size[r as usize] as f32;
            }
        }
        for &(_, p, q) in &edges {
            let (a, b) = (sets.find(p as u32), sets.find(q as u32));
            if a != b
                && ((sets.size[a as usize] as usize) < params.min_size
                    || (sets.size[b as usize] as usize) < params.min_size)
            {
                sets.join(a, b);
            }
        }
        let raw: Vec<u32> = (0..(w * h) as u32).map(|p| sets.find(p)).collect();
        compact(w, h, raw).unwrap().labels
    }

    #[test]
    fn segmentation_equals_the_reference_implementation() {
        let mut rng = crate::vision::rng::SplitMix64::new(8);
        for (w, h) in [(61, 47), (1, 9), (9, 1), (2, 2), (40, 33)] {
            // Blocks of colour with noise: ties and many small pieces.
            let data: Vec<f32> = (0..w * h * CHANNELS)
                .map(|i| {
                    let p = i / CHANNELS;
                    let block = ((p % w) / 7 + (p / w) / 5) % 3;
                    (block * 80) as f32 + rng.range_usize(0, 4) as f32 * 10.0
                })
                .collect();
            let img = ColorImage::new(w, h, data).unwrap();
            for (k, min_size) in [(300.0, 50), (50.0, 5), (10.0, 1)] {
                let params = SegmentParams {
                    sigma: 0.5,
                    k,
                    min_size,
                    downsample: 1,
                };
                let got = segment(&img, &params).unwrap();
                assert_eq!(
                    got.labels,
                    segment_reference(&img, &params),
                    "{w}x{h}, k {k}, min_size {min_size}"
                );
            }
        }
    }
}
