//! The image side of the edge correspondences: colour gradients of the
//! image, and the search along an edge sample's normal for the strongest
//! image edges of compatible orientation (several hypotheses per sample,
//! as Choi and Christensen).

use nalgebra::Vector2;

use super::distance::pixel_index;
use super::edges::EdgeSample;
use super::params::{IrlsParams, MAX_RANGE};
use crate::vision::image::ColorImage;

/// A 3x3 binomial blur and then Sobel derivatives of one plane (each
/// normalised to intensity per pixel).
fn sobel(plane: &[f32], w: usize, h: usize) -> (Vec<f32>, Vec<f32>) {
    let at = |v: &[f32], x: isize, y: isize| {
        let x = x.clamp(0, w as isize - 1) as usize;
        let y = y.clamp(0, h as isize - 1) as usize;
        v[y * w + x]
    };
    let mut blur = vec![0.0f32; w * h];
    for y in 0..h as isize {
        for x in 0..w as isize {
            let mut s = 0.0;
            for (dy, wy) in [(-1, 1.0), (0, 2.0), (1, 1.0)] {
                for (dx, wx) in [(-1, 1.0), (0, 2.0), (1, 1.0)] {
                    s += wx * wy * at(plane, x + dx, y + dy);
                }
            }
            blur[y as usize * w + x as usize] = s / 16.0;
        }
    }
    let mut gx = vec![0.0f32; w * h];
    let mut gy = vec![0.0f32; w * h];
    for y in 0..h as isize {
        for x in 0..w as isize {
            let p = |dx, dy| at(&blur, x + dx, y + dy);
            let i = y as usize * w + x as usize;
            gx[i] = ((p(1, -1) + 2.0 * p(1, 0) + p(1, 1))
                - (p(-1, -1) + 2.0 * p(-1, 0) + p(-1, 1)))
                / 8.0;
            gy[i] = ((p(-1, 1) + 2.0 * p(0, 1) + p(1, 1))
                - (p(-1, -1) + 2.0 * p(0, -1) + p(1, -1)))
                / 8.0;
        }
    }
    (gx, gy)
}

/// Image gradients: per pixel the strongest colour channel's Sobel
/// gradient, after a 3x3 binomial blur (see [`Gradients::new`]).
pub struct Gradients {
    pub(super) width: usize,
    pub(super) height: usize,
    gx: Vec<f32>,
    gy: Vec<f32>,
}

impl Gradients {
    /// The Sobel gradient of each colour channel (after a 3x3 binomial
    /// blur), and at each pixel the channel whose gradient is the
    /// strongest: an outline between two colours of equal brightness is
    /// an edge, which the grey image does not show.
    pub fn new(img: &ColorImage) -> Self {
        let (w, h) = (img.width(), img.height());
        let planes: Vec<(Vec<f32>, Vec<f32>)> = (0..3)
            .map(|c| {
                let plane: Vec<f32> = img.data().iter().skip(c).step_by(3).copied().collect();
                sobel(&plane, w, h)
            })
            .collect();
        let (gx, gy): (Vec<f32>, Vec<f32>) = (0..w * h)
            .map(|i| {
                let strength = |c: usize| planes[c].0[i].powi(2) + planes[c].1[i].powi(2);
                let best = (1..3).fold(0, |b, c| if strength(c) > strength(b) { c } else { b });
                (planes[best].0[i], planes[best].1[i])
            })
            .unzip();
        Self {
            width: w,
            height: h,
            gx,
            gy,
        }
    }

    /// The gradient at the pixel containing `p`, if inside the image.
    fn at(&self, p: &Vector2<f64>) -> Option<Vector2<f64>> {
        let i = pixel_index(p, self.width, self.height)?;
        Some(Vector2::new(f64::from(self.gx[i]), f64::from(self.gy[i])))
    }
}

/// Edge hypotheses kept per sample.
pub(super) const HYPOTHESES: usize = 3;

/// A sample and its image matches: signed distances along the normal of
/// the strongest compatible edges (the strongest first). Each Gauss-Newton
/// step uses the one nearest to the model's current projection (multiple
/// hypotheses, as Choi and Christensen): a strong edge of the clutter
/// next to the object's own edge does not capture the sample for good.
#[derive(Clone, Copy, Debug)]
pub(super) struct Match {
    pub(super) sample: EdgeSample,
    /// Match position minus sample position, along the normal (pixels).
    pub(super) offsets: [f64; HYPOTHESES],
    pub(super) count: usize,
}

/// The gradient along the sample's normal at `t` pixels along it, where the
/// gradient is strong enough and within the angle of the normal (else 0).
fn edge_strength(g: &Gradients, s: &EdgeSample, p: &IrlsParams, cos_max: f64, t: f64) -> f64 {
    match g.at(&(s.pixel + s.normal * t)) {
        Some(v) => {
            let along = v.dot(&s.normal).abs();
            let m = v.norm();
            if m >= p.min_gradient && along >= cos_max * m {
                along
            } else {
                0.0
            }
        }
        None => 0.0,
    }
}

/// The sub-pixel offset (within half a pixel) of a peak of strength `v0`
/// between neighbours `vm` and `vp`: the vertex of the parabola through
/// the three (none where they do not curve down).
fn subpixel(vm: f64, v0: f64, vp: f64) -> f64 {
    let denom = vm - 2.0 * v0 + vp;
    if denom < -1e-12 {
        (0.5 * (vm - vp) / denom).clamp(-0.5, 0.5)
    } else {
        0.0
    }
}

/// Searches along the sample's normal for the strongest compatible edges
/// (local maxima of the gradient along the normal, up to [`HYPOTHESES`]),
/// each with a parabolic sub-pixel refinement; ties go to the nearer one.
pub(super) fn search(
    g: &Gradients,
    s: &EdgeSample,
    p: &IrlsParams,
) -> Option<([f64; HYPOTHESES], usize)> {
    let range = p.search_range.round() as i64;
    let cos_max = p.max_angle_degrees.to_radians().cos();
    let strength = |t: f64| edge_strength(g, s, p, cos_max, t);
    // The profile along the normal, on the stack (the range is at most
    // MAX_RANGE: `IrlsParams::validate`).
    let mut values = [0.0f64; 2 * MAX_RANGE + 3];
    let n = (2 * range + 3) as usize;
    for (i, v) in values[..n].iter_mut().enumerate() {
        *v = strength((i as i64 - range - 1) as f64);
    }
    let at = |t: i64| values[(t + range + 1) as usize];
    // The strongest local maxima, strongest first (nearer first among
    // equals, then the earlier), kept by insertion.
    let mut peaks = [(0.0f64, 0i64); HYPOTHESES];
    let mut found = 0;
    for t in -range..=range {
        let v = at(t);
        let peak = v > 0.0
            && v >= at(t - 1)
            && v >= at(t + 1)
            && !(v == at(t - 1) && t > 0)
            && !(v == at(t + 1) && t < 0);
        if !peak {
            continue;
        }
        let better = |q: &(f64, i64)| v > q.0 || (v == q.0 && t.abs() < q.1.abs());
        // `found` never exceeds HYPOTHESES.
        let Some(pos) = (0..found)
            .find(|&i| better(&peaks[i]))
            .or((found < HYPOTHESES).then_some(found))
        else {
            continue;
        };
        let last = found.min(HYPOTHESES - 1);
        for i in (pos..last).rev() {
            peaks[i + 1] = peaks[i];
        }
        peaks[pos] = (v, t);
        found = (found + 1).min(HYPOTHESES);
    }
    if found == 0 {
        return None;
    }
    // Only edges of comparable strength compete with the strongest.
    let floor = 0.5 * peaks[0].0;
    let peaks = &peaks[..peaks[..found].iter().take_while(|p| p.0 >= floor).count()];
    let mut out = [0.0; HYPOTHESES];
    let count = peaks.len();
    for (o, &(v0, t)) in out.iter_mut().zip(peaks) {
        *o = t as f64 + subpixel(at(t - 1), v0, at(t + 1));
    }
    Some((out, count))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::rng::SplitMix64;
    use nalgebra::Vector3;

    /// The search by its definition: every local maximum, sorted by
    /// strength (nearer, then earlier, first among equals), those under
    /// half the strongest dropped, the first HYPOTHESES kept.
    fn search_reference(g: &Gradients, s: &EdgeSample, p: &IrlsParams) -> Vec<f64> {
        let range = p.search_range.round() as i64;
        let cos_max = p.max_angle_degrees.to_radians().cos();
        let strength = |t: i64| edge_strength(g, s, p, cos_max, t as f64);
        let mut peaks: Vec<(f64, i64)> = (-range..=range)
            .filter(|&t| {
                let v = strength(t);
                v > 0.0
                    && v >= strength(t - 1)
                    && v >= strength(t + 1)
                    && !(v == strength(t - 1) && t > 0)
                    && !(v == strength(t + 1) && t < 0)
            })
            .map(|t| (strength(t), t))
            .collect();
        peaks.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.abs().cmp(&b.1.abs())));
        let floor = peaks.first().map_or(0.0, |p| 0.5 * p.0);
        peaks
            .iter()
            .filter(|p| p.0 >= floor)
            .take(HYPOTHESES)
            .map(|&(v0, t)| t as f64 + subpixel(strength(t - 1), v0, strength(t + 1)))
            .collect()
    }

    #[test]
    fn an_outline_between_colours_of_equal_brightness_is_an_edge() {
        // Red left, green right, both of grey level 40: the grey image has
        // no edge there, the colour gradient does.
        let (w, h) = (32, 16);
        let data: Vec<f32> = (0..w * h)
            .flat_map(|i| {
                if i % w < w / 2 {
                    [120.0, 0.0, 0.0]
                } else {
                    [0.0, 120.0, 0.0]
                }
            })
            .collect();
        let img = ColorImage::new(w, h, data).unwrap();
        let g = Gradients::new(&img);
        let at_edge = g.at(&Vector2::new(16.0, 8.0)).unwrap();
        assert!(
            at_edge.x.abs() > 20.0 && at_edge.y.abs() < 1e-3,
            "{at_edge:?}"
        );
        let flat = g.at(&Vector2::new(4.0, 8.0)).unwrap();
        assert!(flat.norm() < 1e-3, "{flat:?}");
    }

    #[test]
    fn search_keeps_the_strongest_peaks_as_defined() {
        let mut rng = SplitMix64::new(17);
        let (w, h) = (64, 48);
        // Blocks of grey levels, noise only on the right half: exact
        // block steps make peaks of equal strength (ties to order).
        let data: Vec<f32> = (0..w * h)
            .flat_map(|i| {
                let (x, y) = (i % w, i / w);
                let block = ((x / 5) * 31 + (y / 7) * 17) % 9;
                let v = (block * 28) as f32;
                [v, v, v].map(|c| (x, c))
            })
            .map(|(x, v)| {
                if x >= w / 2 {
                    v + (rng.next_f64() * 3.0) as f32
                } else {
                    v
                }
            })
            .collect();
        let g = Gradients::new(&ColorImage::new(w, h, data).unwrap());
        let mut compared = 0;
        for i in 0..400 {
            let angle = rng.range_f64(0.0, std::f64::consts::TAU);
            let s = EdgeSample {
                point: Vector3::zeros(),
                pixel: Vector2::new(rng.range_f64(0.0, w as f64), rng.range_f64(0.0, h as f64)),
                normal: Vector2::new(angle.cos(), angle.sin()),
            };
            let p = IrlsParams {
                search_range: [1.0, 3.0, 7.5, 30.0][i % 4],
                ..IrlsParams::default()
            };
            let want = search_reference(&g, &s, &p);
            let got = search(&g, &s, &p).map_or(Vec::new(), |(o, n)| o[..n].to_vec());
            assert_eq!(got, want, "sample {s:?}, range {}", p.search_range);
            compared += usize::from(want.len() > 1);
        }
        // Enough samples had several hypotheses to compare their order.
        assert!(compared > 20, "{compared}");
    }
}
