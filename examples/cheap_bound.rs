//! Feasibility of a cheaper exact pre-filter for stage 1 (the speed work): as
//! HOG features are non-negative, every cell's best unary
//! `min(v.h, o.h + r)` is at least `min(v, o).h + min(r, 0)` (elementwise
//! minimum of the object and occlusion filters), so one correlation with a
//! single filter per cell bounds the chain bound from below (a Potts weight
//! of at least 0; a negative one is added per chain edge). Prints how many positions
//! and how many 16-position blocks this cheap bound lets through, against
//! the exact chain bound, on CMU_KO8 photographs.
//!
//! `cargo run --release --example cheap_bound -- [MODEL] [N_IMAGES]`

use sdhop::vision::detect::{chain_pair_weight, dense_bounds, scan_range};
use sdhop::vision::hog::{HOG_DIM, HOG_STRIDE};
use sdhop::vision::pyramid::FeaturePyramid;

mod common;

fn main() {
    let (name, model, files, n_img) = common::model_and_images();
    let cut = -model.meta.detection.threshold;
    let trunc = model.meta.detection.max_truncation;
    let (mut total, mut pass_exact, mut pass_cheap) = (0usize, 0usize, 0usize);
    let (mut blocks, mut blocks_exact, mut blocks_cheap) = (0usize, 0usize, 0usize);
    let mut negative_h = 0usize;
    for f in files.iter().take(n_img) {
        let img = sdhop::data::load_image(f).unwrap();
        let pyr =
            FeaturePyramid::build(&img, &model.meta.pyramid, &model.meta.segmentation).unwrap();
        let exact = dense_bounds(&pyr, &model.views, trunc);
        for (li, level) in pyr.levels.iter().enumerate() {
            let (mw, mh) = (level.hog.width(), level.hog.height());
            for y in 0..mh {
                for x in 0..mw {
                    negative_h += level.hog.cell(x, y)[..HOG_DIM]
                        .iter()
                        .filter(|&&v| v < 0.0)
                        .count();
                }
            }
            for (vi, v) in model.views.iter().enumerate() {
                let Some(lb) = exact.levels[li][vi].as_ref() else {
                    continue;
                };
                let Some((_, _, _, _, min_inside)) = scan_range(mw, mh, v.rows, v.cols, trunc)
                else {
                    continue;
                };
                let n = v.rows * v.cols;
                let m: Vec<f32> = (0..n * HOG_DIM)
                    .map(|k| {
                        let (i, d) = (k / HOG_DIM, k % HOG_DIM);
                        v.w_vis[i * HOG_STRIDE + d].min(v.w_occ[i * HOG_STRIDE + d])
                    })
                    .collect();
                let pair = f64::from(chain_pair_weight(v));
                let pair_part = if pair < 0.0 {
                    pair * (v.rows * (v.cols - 1) + v.cols * (v.rows - 1)) as f64
                } else {
                    0.0
                };
                let rneg: f64 = v.w_prior.iter().map(|&r| f64::from(r.min(0.0))).sum();
                let hop_min = f64::from(v.w_hop[0].min(v.w_hop[v.w_hop.len() - 1]));
                for yy in 0..lb.ny {
                    let (mut any_e, mut any_c, mut in_block) = (false, false, 0);
                    for xx in 0..lb.nx {
                        let (x0, y0) = (lb.x_lo + xx as isize, lb.y_lo + yy as isize);
                        let ov = common::overlap;
                        let inside = ov(x0, v.cols, mw) * ov(y0, v.rows, mh);
                        if inside >= min_inside {
                            total += 1;
                            let mut sum = rneg + pair_part;
                            for ty in 0..v.rows {
                                for tx in 0..v.cols {
                                    let (cx, cy) = (x0 + tx as isize, y0 + ty as isize);
                                    if cx < 0 || cy < 0 || cx as usize >= mw || cy as usize >= mh {
                                        continue;
                                    }
                                    let h = level.hog.cell(cx as usize, cy as usize);
                                    let i = ty * v.cols + tx;
                                    sum += m[i * HOG_DIM..(i + 1) * HOG_DIM]
                                        .iter()
                                        .zip(h)
                                        .map(|(a, b)| f64::from(a * b))
                                        .sum::<f64>();
                                }
                            }
                            let hop = if hop_min >= 0.0 {
                                hop_min
                            } else {
                                hop_min * inside as f64
                            };
                            let base = hop
                                + f64::from(v.w_trunc) * (n - inside) as f64
                                + f64::from(v.bias);
                            let e = f64::from(lb.values[yy * lb.nx + xx]);
                            assert!(
                                sum <= e + 1e-3 * (1.0 + e.abs()),
                                "cheap {sum} above exact {e}"
                            );
                            let pe = base + e <= cut + 1e-4 * (1.0 + cut.abs());
                            let pc = base + sum <= cut + 1e-4 * (1.0 + cut.abs());
                            pass_exact += usize::from(pe);
                            pass_cheap += usize::from(pc);
                            any_e |= pe;
                            any_c |= pc;
                        }
                        in_block += 1;
                        if in_block == 16 || xx + 1 == lb.nx {
                            blocks += 1;
                            blocks_exact += usize::from(any_e);
                            blocks_cheap += usize::from(any_c);
                            (any_e, any_c, in_block) = (false, false, 0);
                        }
                    }
                }
            }
        }
    }
    println!(
        "{name}: {total} positions; exact bound passes {pass_exact} ({:.2}%), cheap bound {pass_cheap} ({:.2}%); 16-position blocks {blocks}: exact {blocks_exact} ({:.1}%), cheap {blocks_cheap} ({:.1}%); negative HOG values {negative_h}",
        100.0 * pass_exact as f64 / total as f64,
        100.0 * pass_cheap as f64 / total as f64,
        100.0 * blocks_exact as f64 / blocks as f64,
        100.0 * blocks_cheap as f64 / blocks as f64,
    );
}
