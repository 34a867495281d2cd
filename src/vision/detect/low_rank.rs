//! Stage 1's low-rank bound (see [`super::bounds`]): one orthonormal basis
//! of the HOG dimensions serves every component of a model, so that the
//! feature maps are projected once and each component's dense bound reads
//! `LOW_RANK + 1` planes instead of the full HOG.

use super::*;

/// Rank of the shared basis of stage 1's low-rank bound.
pub const LOW_RANK: usize = 10;
/// Feature planes of the low-rank bound: the basis and the norm.
pub(super) const LOW_RANK_DIMS: usize = LOW_RANK + 1;

/// An orthonormal basis of the HOG dimensions that best represents the
/// filters of a model's components (the leading eigenvectors of the second
/// moments of all their cells' object and occlusion filters): one
/// projection of the feature maps serves every component's bound.
#[derive(Clone, Debug, PartialEq)]
pub struct LowRankBasis {
    pub(super) vectors: Vec<[f32; HOG_DIM]>,
}

/// One component's filters in the basis, with each cell's residual norm
/// as the weight of the norm plane (negated): `w . f >= (B^T w) . (B^T f) -
/// |w - B B^T w| |f|`, so the chain bound over these unaries is a lower
/// bound of the full one.
#[derive(Clone, Debug, PartialEq)]
pub struct LowRankFilter {
    pub(super) vis: Vec<f32>,
    pub(super) occ: Vec<f32>,
}

impl LowRankBasis {
    /// The basis of `views`' filters.
    pub fn new(views: &[ViewWeights]) -> Self {
        let mut m = nalgebra::SMatrix::<f64, HOG_DIM, HOG_DIM>::zeros();
        for w in views {
            for cell in w.w_vis.chunks(HOG_STRIDE).chain(w.w_occ.chunks(HOG_STRIDE)) {
                let v = nalgebra::SVector::<f64, HOG_DIM>::from_iterator(
                    cell[..HOG_DIM].iter().map(|&x| f64::from(x)),
                );
                m += v * v.transpose();
            }
        }
        let eig = m.symmetric_eigen();
        let mut order: Vec<usize> = (0..HOG_DIM).collect();
        order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
        let vectors = order[..LOW_RANK]
            .iter()
            .map(|&k| {
                let mut b = [0.0f32; HOG_DIM];
                for (d, x) in b.iter_mut().enumerate() {
                    *x = eig.eigenvectors[(d, k)] as f32;
                }
                b
            })
            .collect();
        Self { vectors }
    }

    /// `w`'s filters in this basis.
    pub fn filter(&self, w: &ViewWeights) -> LowRankFilter {
        let project = |f: &[f32]| -> Vec<f32> {
            let mut out = Vec::with_capacity(w.cells() * LOW_RANK_DIMS);
            for cell in f.chunks(HOG_STRIDE) {
                let c: Vec<f64> = cell[..HOG_DIM].iter().map(|&x| f64::from(x)).collect();
                let mut resid = c.clone();
                for b in &self.vectors {
                    let a: f64 = b.iter().zip(&c).map(|(&x, y)| f64::from(x) * y).sum();
                    out.push(a as f32);
                    for (r, &x) in resid.iter_mut().zip(b) {
                        *r -= a * f64::from(x);
                    }
                }
                let e = resid.iter().map(|r| r * r).sum::<f64>().sqrt();
                // Rounded up for the f32 arithmetic of the bound.
                out.push(-((e * (1.0 + 1e-4) + 1e-6) as f32));
            }
            out
        };
        LowRankFilter {
            vis: project(&w.w_vis),
            occ: project(&w.w_occ),
        }
    }
}

/// Stage 1's low-rank bound of a model: the basis of its components'
/// filters and each component's filters in it.
#[derive(Clone, Debug, PartialEq)]
pub struct LowRank {
    pub(super) basis: LowRankBasis,
    pub(super) filters: Vec<LowRankFilter>,
}

impl LowRank {
    pub fn new(views: &[ViewWeights]) -> Self {
        let basis = LowRankBasis::new(views);
        let filters = views.iter().map(|w| basis.filter(w)).collect();
        Self { basis, filters }
    }
}
