//! Where each block of a model's weights sits in the structural SVM's
//! training vector, and the weights written back from that vector (the
//! HOP weights made exactly concave in `f32`).

use crate::vision::energy::{joint_feature_len, PairwiseMode, ViewWeights};
use crate::vision::hog::{HOG_DIM, HOG_STRIDE};

/// Positions of the blocks of one model's training vector.
#[derive(Clone, Debug)]
pub struct Layout {
    /// `(rows, cols)` per viewpoint.
    pub shapes: Vec<(usize, usize)>,
    pub k: usize,
    pub pair_mode: PairwiseMode,
    /// False: the plain-HOG ablation (see [`super::TrainParams::occlusion`]).
    pub occlusion: bool,
    offsets: Vec<usize>,
    pub len: usize,
}

impl Layout {
    pub fn new(shapes: Vec<(usize, usize)>, k: usize, pair_mode: PairwiseMode) -> Self {
        let mut offsets = Vec::new();
        let mut len = 0;
        for &(r, c) in &shapes {
            offsets.push(len);
            len += joint_feature_len(r * c, k);
        }
        Self {
            shapes,
            k,
            pair_mode,
            occlusion: true,
            offsets,
            len,
        }
    }

    pub(super) fn n(&self, view: usize) -> usize {
        self.shapes[view].0 * self.shapes[view].1
    }

    /// Index of `W` of a viewpoint.
    pub(super) fn pair_index(&self, view: usize) -> usize {
        let n = self.n(view);
        self.offsets[view] + 2 * n * HOG_DIM + n + 1
    }

    /// Index of the first HOP parameter `a`; then `b`, then `c_1..c_{K-1}`.
    pub(super) fn hop_index(&self, view: usize) -> usize {
        self.pair_index(view) + 1
    }

    /// The coordinates constrained to be non-negative: `W` and the HOP
    /// curvatures `c_j` of every viewpoint.
    pub fn nonneg(&self) -> Vec<usize> {
        let mut out = Vec::new();
        for v in 0..self.shapes.len() {
            out.push(self.pair_index(v));
            out.extend((2..=self.k).map(|j| self.hop_index(v) + j));
        }
        out
    }

    /// Writes a viewpoint's joint feature (HOP block in the training
    /// parametrisation) into `out` with weight `scale`.
    pub(super) fn add_psi(
        &self,
        view: usize,
        psi: &[f64],
        scale: f64,
        out: &mut [f64],
        hop: bool,
        pair: bool,
    ) {
        let o = self.offsets[view];
        let h = self.hop_index(view) - o;
        let k = self.k;
        for (j, &v) in psi[..h].iter().enumerate() {
            if j == self.pair_index(view) - o && !pair {
                continue;
            }
            out[o + j] += scale * v;
        }
        if hop {
            let theta = &psi[h..h + k + 1];
            let sum: f64 = theta.iter().sum();
            let first: f64 = theta.iter().enumerate().map(|(i, t)| i as f64 * t).sum();
            out[o + h] += scale * sum;
            out[o + h + 1] += scale * first;
            for j in 1..k {
                let cj: f64 = (j + 1..=k).map(|kk| (kk - j) as f64 * theta[kk]).sum();
                out[o + h + 1 + j] -= scale * cj;
            }
        }
        out[o + h + k + 1] += scale * psi[h + k + 1];
    }

    /// The detector weights of a training vector. `W >= 0` and
    /// `D^2 w_HOP >= 0` hold exactly in the `f32` values.
    pub fn to_views(&self, w: &[f64]) -> Vec<ViewWeights> {
        (0..self.shapes.len())
            .map(|v| {
                let (rows, cols) = self.shapes[v];
                let n = rows * cols;
                let o = self.offsets[v];
                let mut vw = ViewWeights::zeros(rows, cols, self.k);
                vw.pair_mode = self.pair_mode;
                for i in 0..n {
                    for d in 0..HOG_DIM {
                        vw.w_vis[i * HOG_STRIDE + d] = w[o + i * HOG_DIM + d] as f32;
                        vw.w_occ[i * HOG_STRIDE + d] = w[o + (n + i) * HOG_DIM + d] as f32;
                    }
                    vw.w_prior[i] = w[o + 2 * n * HOG_DIM + i] as f32;
                    if !self.occlusion {
                        vw.w_prior[i] = PLAIN_HOG_PRIOR;
                        for d in 0..HOG_DIM {
                            vw.w_occ[i * HOG_STRIDE + d] = 0.0;
                        }
                    }
                }
                vw.w_trunc = w[o + 2 * n * HOG_DIM + n] as f32;
                vw.w_pair = w[self.pair_index(v)].max(0.0) as f32;
                let h = self.hop_index(v);
                vw.w_hop = exact_concave(w[h], w[h + 1], &w[h + 2..h + 1 + self.k]);
                vw.bias = w[h + self.k + 1] as f32;
                vw
            })
            .collect()
    }
}

/// The cost of labelling a cell occluded in a plain-HOG model (no
/// occlusion reasoning): far above any filter response, so that every
/// min-cut labels every cell visible.
pub const PLAIN_HOG_PRIOR: f32 = 1e3;

/// `w_k = a + b k - sum_{j<k} (k - j) c_j` for `k = 0..=K`, with `c_j`
/// clamped at 0, as `f32` values whose curvature is exactly `c_j >= 0`:
/// everything is rounded to a common power-of-two grid fine enough for
/// 24-bit mantissas, then computed in integers.
pub fn exact_concave(a: f64, b: f64, c: &[f64]) -> Vec<f32> {
    let k = c.len() + 1;
    let real: Vec<f64> = (0..=k)
        .map(|kk| {
            a + b * kk as f64
                - (1..kk)
                    .map(|j| (kk - j) as f64 * c[j - 1].max(0.0))
                    .sum::<f64>()
        })
        .collect();
    let big = real
        .iter()
        .chain([&a, &b])
        .chain(c)
        .fold(1e-30f64, |m, v| m.max(v.abs()));
    // Every |value| / grid < 2^22 (headroom for the sums below 2^24).
    let grid = 2f64.powi(big.log2().ceil() as i32 - 22);
    let q = |v: f64| (v / grid).round() as i64;
    let (qa, qb) = (q(a), q(b));
    let qc: Vec<i64> = c.iter().map(|&v| q(v.max(0.0)).max(0)).collect();
    (0..=k)
        .map(|kk| {
            let s = qa + qb * kk as i64 - (1..kk).map(|j| (kk - j) as i64 * qc[j - 1]).sum::<i64>();
            (s as f64 * grid) as f32
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::energy::hop_curvature;
    use crate::vision::rng::SplitMix64;

    #[test]
    fn exact_concave_weights_have_non_negative_curvature() {
        let mut rng = SplitMix64::new(9);
        for _ in 0..2000 {
            let k = rng.range_usize(1, 8);
            let scale = 10f64.powf(rng.range_f64(-4.0, 3.0));
            let c: Vec<f64> = (0..k - 1)
                .map(|_| {
                    if rng.next_f64() < 0.4 {
                        0.0
                    } else {
                        rng.range_f64(-0.2, 1.0) * scale
                    }
                })
                .collect();
            let w = exact_concave(
                rng.range_f64(-1.0, 1.0) * scale,
                rng.range_f64(-1.0, 1.0) * scale,
                &c,
            );
            let w64: Vec<f64> = w.iter().map(|&v| f64::from(v)).collect();
            for (j, d2) in hop_curvature(&w64).into_iter().enumerate() {
                assert!(d2 >= 0.0, "curvature {d2} at {j} of {w:?}");
                // Close to the requested curvature.
                assert!((d2 - c[j].max(0.0)).abs() <= 1e-5 * scale.max(1e-30) * 8.0);
            }
        }
    }

    /// The training parametrisation reproduces `w_hop . theta`.
    #[test]
    fn hop_reparametrisation_preserves_the_energy() {
        let layout = Layout::new(vec![(1, 1)], 4, PairwiseMode::Grid);
        let mut rng = SplitMix64::new(2);
        for _ in 0..100 {
            let mut w = vec![0.0; layout.len];
            for v in w.iter_mut() {
                *v = rng.range_f64(-1.0, 1.0);
            }
            let h = layout.hop_index(0);
            for j in 2..=4 {
                w[h + j] = w[h + j].abs();
            }
            let views = layout.to_views(&w);
            let mut psi = vec![0.0; joint_feature_len(1, 4)];
            let hp = 2 * HOG_DIM + 1 + 2;
            for t in &mut psi[hp..hp + 5] {
                *t = rng.range_f64(0.0, 3.0);
            }
            let mut train_psi = vec![0.0; layout.len];
            layout.add_psi(0, &psi, 1.0, &mut train_psi, true, true);
            let direct: f64 = views[0]
                .w_hop
                .iter()
                .zip(&psi[hp..hp + 5])
                .map(|(a, b)| f64::from(*a) * b)
                .sum();
            let via: f64 = (0..5).map(|j| w[h + j] * train_psi[h + j]).sum();
            // f32 weights: round-off relative to the size of the energy.
            assert!(
                (direct - via).abs() < 1e-5 * (1.0 + direct.abs()),
                "{direct} vs {via}"
            );
        }
    }
}
