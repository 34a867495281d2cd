//! Tests of the parent module.

use super::*;
use crate::vision::rng::SplitMix64;

/// Every instruction-set path of the dense bound gives bit-identical
/// values, on rows of positions that are not a multiple of the lanes and
/// hang off the map.
#[test]
fn dense_row_paths_are_bit_identical() {
    let mut rng = SplitMix64::new(17);
    let (mw, mh) = (23, 11);
    let data: Vec<f32> = (0..mw * mh * HOG_STRIDE)
        .map(|_| rng.range_f64(0.0, 0.3) as f32)
        .collect();
    let hog = HogMap::from_raw(mw, mh, data).unwrap();
    let mut w = ViewWeights::zeros(5, 4, 4);
    for v in w.w_vis.iter_mut().chain(w.w_occ.iter_mut()) {
        *v = rng.range_f64(-0.5, 0.5) as f32;
    }
    for v in &mut w.w_prior {
        *v = rng.range_f64(-0.2, 0.2) as f32;
    }
    w.w_pair = 0.05;
    let map = PlanarMap::new(&hog, w.cols, w.rows);
    let (x_lo, x_hi, y_lo, y_hi, _) = scan_range(mw, mh, w.rows, w.cols, 0.5).unwrap();
    let nx = (x_hi - x_lo + 1) as usize;
    assert!(nx % LANES != 0);
    let mut s = DenseScratch::default();
    for y in y_lo..=y_hi {
        let mut portable = vec![0.0f32; nx];
        dense_row_body::<HOG_DIM>(
            &map,
            &BoundFilter::full(&w),
            0.05,
            x_lo,
            y,
            &mut portable,
            &mut s,
        );
        let mut dispatched = vec![0.0f32; nx];
        dense_row(&map, &w, 0.05, x_lo, y, &mut dispatched, &mut s);
        assert_eq!(
            portable,
            dispatched,
            "row {y} on {:?}",
            crate::vision::simd::level()
        );
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
            {
                let mut out = vec![0.0f32; nx];
                // SAFETY: the features were detected at run time.
                unsafe {
                    dense_row_avx2::<HOG_DIM>(
                        &map,
                        &BoundFilter::full(&w),
                        0.05,
                        x_lo,
                        y,
                        &mut out,
                        &mut s,
                    )
                };
                assert_eq!(portable, out, "AVX2, row {y}");
                if crate::vision::simd::level() == crate::vision::simd::Simd::Avx512 {
                    // SAFETY: as above.
                    unsafe {
                        dense_row_avx512::<HOG_DIM>(
                            &map,
                            &BoundFilter::full(&w),
                            0.05,
                            x_lo,
                            y,
                            &mut out,
                            &mut s,
                        )
                    };
                    assert_eq!(portable, out, "AVX-512, row {y}");
                }
            }
        }
    }
}

/// The dense bound equals the row-and-column chain bound computed one
/// position at a time (f64, zero features off the map), on maps whose
/// rows give one, two and three blocks of positions.
#[test]
fn dense_row_matches_a_scalar_chain_bound() {
    let mut rng = SplitMix64::new(29);
    for mw in [9usize, 23, 57] {
        let mh = 9;
        let data: Vec<f32> = (0..mw * mh * HOG_STRIDE)
            .map(|_| rng.range_f64(0.0, 0.3) as f32)
            .collect();
        let hog = HogMap::from_raw(mw, mh, data).unwrap();
        let mut w = ViewWeights::zeros(4, 5, 4);
        for v in w.w_vis.iter_mut().chain(w.w_occ.iter_mut()) {
            *v = rng.range_f64(-0.5, 0.5) as f32;
        }
        for v in &mut w.w_prior {
            *v = rng.range_f64(-0.2, 0.2) as f32;
        }
        let pair = 0.07f32;
        let map = PlanarMap::new(&hog, w.cols, w.rows);
        let (x_lo, x_hi, y_lo, y_hi, _) = scan_range(mw, mh, w.rows, w.cols, 0.5).unwrap();
        let nx = (x_hi - x_lo + 1) as usize;
        let mut s = DenseScratch::default();
        for y in y_lo..=y_hi {
            let mut got = vec![0.0f32; nx];
            dense_row(&map, &w, pair, x_lo, y, &mut got, &mut s);
            for (k, &g) in got.iter().enumerate() {
                let x = x_lo + k as isize;
                let unary = |tx: usize, ty: usize| -> (f64, f64) {
                    let (cx, cy) = (x + tx as isize, y + ty as isize);
                    let i = ty * w.cols + tx;
                    let (mut f, mut o) = (0.0, 0.0);
                    if cx >= 0 && cy >= 0 && (cx as usize) < mw && (cy as usize) < mh {
                        let h = hog.cell(cx as usize, cy as usize);
                        for (d, &hd) in h.iter().enumerate().take(HOG_DIM) {
                            f += f64::from(w.w_vis[i * HOG_STRIDE + d] * hd);
                            o += f64::from(w.w_occ[i * HOG_STRIDE + d] * hd);
                        }
                    }
                    (0.5 * (o + f64::from(w.w_prior[i])), 0.5 * f)
                };
                let chain = |cells: Vec<(f64, f64)>| {
                    let p = f64::from(pair);
                    let mut st = cells[0];
                    for &(u0, u1) in &cells[1..] {
                        st = (u0 + st.0.min(st.1 + p), u1 + st.1.min(st.0 + p));
                    }
                    st.0.min(st.1)
                };
                let mut want = 0.0;
                for ty in 0..w.rows {
                    want += chain((0..w.cols).map(|tx| unary(tx, ty)).collect());
                }
                for tx in 0..w.cols {
                    want += chain((0..w.rows).map(|ty| unary(tx, ty)).collect());
                }
                assert!(
                    (f64::from(g) - want).abs() < 1e-4 * (1.0 + want.abs()),
                    "map {mw}, position ({x}, {y}): {g} against {want}"
                );
            }
        }
    }
}

/// The low-rank bound is a lower bound of the full one at every
/// position (the min-cut stage then decides as before), and tight
/// where the filters lie in the basis.
#[test]
fn low_rank_bounds_stay_below_the_full_ones() {
    let mut rng = SplitMix64::new(23);
    let (mw, mh) = (29, 13);
    let data: Vec<f32> = (0..mw * mh * HOG_STRIDE)
        .map(|_| rng.range_f64(0.0, 0.3) as f32)
        .collect();
    let hog = HogMap::from_raw(mw, mh, data).unwrap();
    let mut views = Vec::new();
    for (rows, cols) in [(5, 4), (3, 6), (4, 4)] {
        let mut w = ViewWeights::zeros(rows, cols, 4);
        for v in w.w_vis.iter_mut().chain(w.w_occ.iter_mut()) {
            *v = rng.range_f64(-0.5, 0.5) as f32;
        }
        for c in w
            .w_vis
            .chunks_mut(HOG_STRIDE)
            .chain(w.w_occ.chunks_mut(HOG_STRIDE))
        {
            c[HOG_DIM..].iter_mut().for_each(|v| *v = 0.0);
        }
        for v in &mut w.w_prior {
            *v = rng.range_f64(-0.2, 0.2) as f32;
        }
        w.w_pair = 0.05;
        views.push(w);
    }
    let lr = LowRank::new(&views);
    let pad = 6;
    let map = PlanarMap::new(&hog, pad, pad);
    let low = PlanarMap::projected(&hog, &lr.basis, pad, pad);
    let mut s = DenseScratch::default();
    let mut looser = 0.0f64;
    let mut n = 0usize;
    for (vi, w) in views.iter().enumerate() {
        let (x_lo, x_hi, y_lo, y_hi, _) = scan_range(mw, mh, w.rows, w.cols, 0.5).unwrap();
        let nx = (x_hi - x_lo + 1) as usize;
        let f = BoundFilter::low_rank(w, &lr.filters[vi]);
        for y in y_lo..=y_hi {
            let mut full = vec![0.0f32; nx];
            dense_row(&map, w, 0.05, x_lo, y, &mut full, &mut s);
            let mut cheap = vec![0.0f32; nx];
            dense_row_with::<LOW_RANK_DIMS>(&low, &f, 0.05, x_lo, y, &mut cheap, &mut s);
            for (a, b) in full.iter().zip(&cheap) {
                assert!(b <= a, "low-rank {b} above full {a}");
                looser += f64::from(a - b);
                n += 1;
            }
        }
    }
    assert!(n > 100 && looser > 0.0);
    // Filters inside a 10-dimensional subspace: the bound is exact up
    // to rounding.
    let basis = lr.basis.vectors.clone();
    let mut w = views[0].clone();
    for c in w
        .w_vis
        .chunks_mut(HOG_STRIDE)
        .chain(w.w_occ.chunks_mut(HOG_STRIDE))
    {
        let a: Vec<f32> = (0..LOW_RANK)
            .map(|_| rng.range_f64(-0.5, 0.5) as f32)
            .collect();
        for d in 0..HOG_DIM {
            c[d] = (0..LOW_RANK).map(|k| a[k] * basis[k][d]).sum();
        }
    }
    let f = lr.basis.filter(&w);
    let bf = BoundFilter::low_rank(&w, &f);
    let (x_lo, x_hi, y_lo, _, _) = scan_range(mw, mh, w.rows, w.cols, 0.5).unwrap();
    let nx = (x_hi - x_lo + 1) as usize;
    let mut full = vec![0.0f32; nx];
    dense_row(&map, &w, 0.05, x_lo, y_lo + 2, &mut full, &mut s);
    let mut cheap = vec![0.0f32; nx];
    dense_row_with::<LOW_RANK_DIMS>(&low, &bf, 0.05, x_lo, y_lo + 2, &mut cheap, &mut s);
    for (a, b) in full.iter().zip(&cheap) {
        assert!(*b <= *a + 1e-5 && *a - *b < 1e-2, "{a} {b}");
    }
}

/// The clique count is the number of distinct segments among each box's
/// cells inside the map, at every position a scan reaches (boxes hanging
/// over every border included), and never above the O(1) bound.
#[test]
fn clique_counts_are_the_distinct_segments_of_each_box() {
    let (mw, mh) = (13usize, 9usize);
    let mut rng = SplitMix64::new(5);
    // Blocky segments, so that boxes hold a few each.
    let seg: Vec<u32> = (0..mw * mh)
        .map(|i| ((i % mw) / 3 + 5 * ((i / mw) / 2)) as u32 + (rng.next_u64() % 2) as u32 * 40)
        .collect();
    let upper = CliqueCounter::new(&seg, mw, mh);
    let mut exact = CliqueCount::default();
    for (rows, cols) in [(1, 1), (3, 4), (5, 2), (9, 13), (11, 15)] {
        for y in -(rows as isize) + 1..mh as isize {
            for x in -(cols as isize) + 1..mw as isize {
                let mut seen = std::collections::HashSet::new();
                let (x0, x1) = (x.max(0), (x + cols as isize).min(mw as isize));
                let (y0, y1) = (y.max(0), (y + rows as isize).min(mh as isize));
                for yy in y0..y1 {
                    for xx in x0..x1 {
                        seen.insert(seg[yy as usize * mw + xx as usize]);
                    }
                }
                let n = exact.count(&seg, (mw, mh), (rows, cols), (x, y));
                assert_eq!(n as usize, seen.len(), "{rows}x{cols} at ({x}, {y})");
                let b = upper.bound(x0 as usize, x1 as usize, y0 as usize, y1 as usize);
                assert!(n as usize <= b);
            }
        }
    }
    // In any order (the count keeps the last box's cells: a step along the
    // same rows updates them, any other query counts afresh).
    let mut exact = CliqueCount::default();
    for _ in 0..3000 {
        let (rows, cols) = (
            1 + (rng.next_u64() % 11) as usize,
            1 + (rng.next_u64() % 15) as usize,
        );
        let x = (rng.next_u64() % (mw + cols) as u64) as isize - cols as isize + 1;
        let y = (rng.next_u64() % (mh + rows) as u64) as isize - rows as isize + 1;
        let (x0, x1) = (x.max(0), (x + cols as isize).min(mw as isize));
        let (y0, y1) = (y.max(0), (y + rows as isize).min(mh as isize));
        let mut seen = std::collections::HashSet::new();
        for yy in y0..y1 {
            for xx in x0..x1 {
                seen.insert(seg[yy as usize * mw + xx as usize]);
            }
        }
        let n = exact.count(&seg, (mw, mh), (rows, cols), (x, y));
        assert_eq!(n as usize, seen.len(), "{rows}x{cols} at ({x}, {y})");
        // And the next position along the row, as a scan asks.
        let n = exact.count(&seg, (mw, mh), (rows, cols), (x + 1, y));
        let (x0, x1) = ((x + 1).max(0), (x + 1 + cols as isize).min(mw as isize));
        let mut seen = std::collections::HashSet::new();
        for yy in y0..y1 {
            for xx in x0..x1 {
                seen.insert(seg[yy as usize * mw + xx as usize]);
            }
        }
        assert_eq!(n as usize, seen.len(), "{rows}x{cols} at ({}, {y})", x + 1);
    }
}
