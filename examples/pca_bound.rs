//! Feasibility of a cheaper exact stage-1 bound (the speed work): the chain bound
//! with each cell's filter responses replaced by their projection on the
//! top `k` principal directions of the model's filter cells minus the
//! Cauchy-Schwarz bound of the residual (`|w_res . h_res| <= |w_res| |h_res|`),
//! a lower bound on the exact chain bound. Prints, per `k`, how many
//! positions each bound lets through to stage 2 on CMU_KO8 photographs.
//!
//! `cargo run --release --example pca_bound -- [MODEL] [N_IMAGES]`

use nalgebra::{DMatrix, SymmetricEigen};
use sdhop::vision::detect::{chain_pair_weight, dense_bounds, scan_range};
use sdhop::vision::hog::{HOG_DIM, HOG_STRIDE};
use sdhop::vision::pyramid::FeaturePyramid;

mod common;

fn main() {
    let (_, model, files, n_img) = common::model_and_images();
    let cut = -model.meta.detection.threshold;
    let trunc = model.meta.detection.max_truncation;
    // Principal directions of all filter cells of all views.
    let mut s = DMatrix::<f64>::zeros(HOG_DIM, HOG_DIM);
    for v in &model.views {
        for i in 0..v.rows * v.cols {
            for w in [&v.w_vis, &v.w_occ] {
                let c = &w[i * HOG_STRIDE..i * HOG_STRIDE + HOG_DIM];
                for a in 0..HOG_DIM {
                    for b in 0..HOG_DIM {
                        s[(a, b)] += f64::from(c[a]) * f64::from(c[b]);
                    }
                }
            }
        }
    }
    let eig = SymmetricEigen::new(s);
    let mut order: Vec<usize> = (0..HOG_DIM).collect();
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let total: f64 = eig.eigenvalues.iter().sum();
    for k in [4usize, 8, 12, 16] {
        let basis: Vec<Vec<f64>> = order[..k]
            .iter()
            .map(|&j| eig.eigenvectors.column(j).iter().copied().collect())
            .collect();
        let kept: f64 = order[..k].iter().map(|&j| eig.eigenvalues[j]).sum();
        let project = |h: &[f32]| -> (Vec<f64>, f64) {
            let c: Vec<f64> = basis
                .iter()
                .map(|b| b.iter().zip(h).map(|(x, y)| x * f64::from(*y)).sum())
                .collect();
            let mut r2 = 0.0;
            for d in 0..HOG_DIM {
                let rec: f64 = basis.iter().zip(&c).map(|(b, ci)| b[d] * ci).sum();
                r2 += (f64::from(h[d]) - rec).powi(2);
            }
            (c, r2.max(0.0).sqrt())
        };
        let (mut total_pos, mut pass_exact, mut pass_pca, mut worst, mut slack) =
            (0usize, 0usize, 0usize, f64::MIN, 0.0f64);
        for f in files.iter().take(n_img) {
            let img = sdhop::data::load_image(f).unwrap();
            let pyr =
                FeaturePyramid::build(&img, &model.meta.pyramid, &model.meta.segmentation).unwrap();
            let exact = dense_bounds(&pyr, &model.views, trunc);
            for (li, level) in pyr.levels.iter().enumerate() {
                let (mw, mh) = (level.hog.width(), level.hog.height());
                let cells: Vec<(Vec<f64>, f64)> = (0..mh)
                    .flat_map(|y| (0..mw).map(move |x| (x, y)))
                    .map(|(x, y)| project(level.hog.cell(x, y)))
                    .collect();
                for (vi, v) in model.views.iter().enumerate() {
                    let Some(lb) = exact.levels[li][vi].as_ref() else {
                        continue;
                    };
                    let Some((_, _, _, _, min_inside)) = scan_range(mw, mh, v.rows, v.cols, trunc)
                    else {
                        continue;
                    };
                    let n = v.rows * v.cols;
                    let wp: Vec<(Vec<f64>, f64, Vec<f64>, f64)> = (0..n)
                        .map(|i| {
                            let (a, na) =
                                project(&v.w_vis[i * HOG_STRIDE..i * HOG_STRIDE + HOG_DIM]);
                            let (b, nb) =
                                project(&v.w_occ[i * HOG_STRIDE..i * HOG_STRIDE + HOG_DIM]);
                            (a, na, b, nb)
                        })
                        .collect();
                    let pair = f64::from(chain_pair_weight(v));
                    let hop_min = f64::from(v.w_hop[0].min(v.w_hop[v.w_hop.len() - 1]));
                    for yy in 0..lb.ny {
                        for xx in 0..lb.nx {
                            let (x0, y0) = (lb.x_lo + xx as isize, lb.y_lo + yy as isize);
                            let ov = common::overlap;
                            let inside = ov(x0, v.cols, mw) * ov(y0, v.rows, mh);
                            if inside < min_inside {
                                continue;
                            }
                            total_pos += 1;
                            // Lower-bounded unaries (0 outside the map).
                            let mut u = vec![(0.0f64, 0.0f64); n];
                            for ty in 0..v.rows {
                                for tx in 0..v.cols {
                                    let i = ty * v.cols + tx;
                                    let (x, y) = (x0 + tx as isize, y0 + ty as isize);
                                    let (f, g) = if x >= 0
                                        && y >= 0
                                        && (x as usize) < mw
                                        && (y as usize) < mh
                                    {
                                        let (c, r) = &cells[y as usize * mw + x as usize];
                                        let (a, na, b, nb) = &wp[i];
                                        let fa: f64 = a.iter().zip(c).map(|(p, q)| p * q).sum();
                                        let gb: f64 = b.iter().zip(c).map(|(p, q)| p * q).sum();
                                        (fa - na * r, gb - nb * r)
                                    } else {
                                        (0.0, 0.0)
                                    };
                                    u[i] = (0.5 * (g + f64::from(v.w_prior[i])), 0.5 * f);
                                }
                            }
                            let chain = |idx: &mut dyn Iterator<Item = usize>| {
                                let mut s: Option<(f64, f64)> = None;
                                for i in idx {
                                    let (u0, u1) = u[i];
                                    s = Some(match s {
                                        None => (u0, u1),
                                        Some((s0, s1)) => {
                                            (u0 + s0.min(s1 + pair), u1 + s1.min(s0 + pair))
                                        }
                                    });
                                }
                                s.map_or(0.0, |(a, b)| a.min(b))
                            };
                            let mut sum = 0.0;
                            for ty in 0..v.rows {
                                sum += chain(&mut (0..v.cols).map(|tx| ty * v.cols + tx));
                            }
                            for tx in 0..v.cols {
                                sum += chain(&mut (0..v.rows).map(|ty| ty * v.cols + tx));
                            }
                            let e = f64::from(lb.values[yy * lb.nx + xx]);
                            worst = worst.max(sum - e);
                            slack += e - sum;
                            let hop = if hop_min >= 0.0 {
                                hop_min
                            } else {
                                hop_min * inside as f64
                            };
                            let base = hop
                                + f64::from(v.w_trunc) * (n - inside) as f64
                                + f64::from(v.bias);
                            pass_exact += usize::from(base + e <= cut + 1e-4 * (1.0 + cut.abs()));
                            pass_pca += usize::from(base + sum <= cut + 1e-4 * (1.0 + cut.abs()));
                        }
                    }
                }
            }
        }
        println!(
            "k {k:>2} ({:.0}% of the filter energy): {total_pos} positions, exact bound passes {pass_exact} ({:.2}%), PCA bound passes {pass_pca} ({:.2}%); mean slack {:.3}, PCA - exact at most {worst:.2e}",
            100.0 * kept / total,
            100.0 * pass_exact as f64 / total_pos as f64,
            100.0 * pass_pca as f64 / total_pos as f64,
            slack / total_pos as f64
        );
    }
}
