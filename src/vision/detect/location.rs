//! One location: its CRF (the unaries of the object and occlusion filters,
//! the cliques of the image segments in the box, the pairwise terms) and
//! its min-cut, after the stage-2 bounds of exact pruning.

use super::*;

impl Detector<'_> {
    /// Stage 2b and the min-cut at one candidate. `None` when pruned.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn solve(
        &self,
        pyr: &FeaturePyramid,
        cand: &Candidate,
        cut: f64,
        prune: bool,
        aug: Option<&dyn LossAugment>,
        s: &mut Scratch,
    ) -> Option<Solved> {
        self.fill_problem(pyr, &cand.location(), s, None);
        if let Some(a) = aug {
            let location = cand.location();
            a.augment(location.view, &self.grid(pyr, &location), &mut s.problem);
        }
        let p = &mut s.problem;
        if prune {
            let lb = p.lower_bound_chains();
            if lb - margin(lb) > cut {
                return None;
            }
            let lb = p.lower_bound_without_pairwise();
            if lb - margin(lb) > cut {
                return None;
            }
        }
        let limit = if prune {
            cut + margin(cut)
        } else {
            f64::INFINITY
        };
        let energy = p.solve_below(&mut s.graph, &mut s.labels, limit)?;
        Some(Solved {
            cand: *cand,
            energy,
            cells: s.labels.clone(),
        })
    }

    /// The geometry of a location's box.
    pub fn grid(&self, pyr: &FeaturePyramid, loc: &Location) -> CellGrid {
        let w = self.views[loc.view].w;
        let level = &pyr.levels[loc.level];
        CellGrid {
            cell_x: loc.x,
            cell_y: loc.y,
            rows: w.rows,
            cols: w.cols,
            scale_x: level.scale_x,
            scale_y: level.scale_y,
            cell_size: CELL_SIZE,
        }
    }

    /// Every location of every level and viewpoint with at most
    /// `max_truncation` of its cells outside the image.
    pub fn locations(&self, pyr: &FeaturePyramid, max_truncation: f64) -> Vec<Location> {
        let mut out = Vec::new();
        for (li, level) in pyr.levels.iter().enumerate() {
            for (vi, view) in self.views.iter().enumerate() {
                let (rows, cols) = (view.w.rows, view.w.cols);
                let n = rows * cols;
                let (mw, mh) = (level.hog.width(), level.hog.height());
                let min_inside = (((1.0 - max_truncation) * n as f64).ceil() as usize).max(1);
                let (x_lo, x_hi) = positions(mw, cols, min_inside.div_ceil(rows).max(1));
                let (y_lo, y_hi) = positions(mh, rows, min_inside.div_ceil(cols).max(1));
                for y in y_lo..=y_hi {
                    for x in x_lo..=x_hi {
                        if overlap(x, cols, mw) * overlap(y, rows, mh) >= min_inside {
                            out.push(Location {
                                level: li,
                                view: vi,
                                y,
                                x,
                            });
                        }
                    }
                }
            }
        }
        out
    }

    /// The CRF of a location (unaries, cliques, constant) into
    /// `s.problem`; also the cells' HOG features when `features` is given.
    /// Returns the number of cells outside the image.
    pub(super) fn fill_problem(
        &self,
        pyr: &FeaturePyramid,
        loc: &Location,
        s: &mut Scratch,
        mut features: Option<&mut Vec<[f32; HOG_DIM]>>,
    ) -> usize {
        let view = &self.views[loc.view];
        let w = view.w;
        let level = &pyr.levels[loc.level];
        let (rows, cols) = (w.rows, w.cols);
        let (mw, mh) = (level.hog.width(), level.hog.height());
        if s.problem.rows != rows || s.problem.cols != cols || s.problem.w_hop != view.w_hop {
            s.problem = BoxProblem::new(rows, cols, view.w_hop.clone());
        }
        if let Some(f) = features.as_deref_mut() {
            f.clear();
        }
        let nseg = pyr.segmentation.count();
        if s.seg_stamp.len() < nseg {
            s.seg_stamp.resize(nseg, 0);
            s.seg_local.resize(nseg, 0);
        }
        s.generation = s.generation.wrapping_add(1);
        if s.generation == 0 {
            s.seg_stamp.iter_mut().for_each(|v| *v = 0);
            s.generation = 1;
        }
        let p = &mut s.problem;
        p.pairwise = f64::from(w.w_pair);
        let edges = w.pair_mode == PairwiseMode::Edges;
        if edges {
            p.pairs.clear();
            p.pairs.resize(rows * cols, 0);
            s.edge_dirs.clear();
            s.edge_dirs.resize(rows * cols, 0);
        } else {
            p.pairs.clear();
        }
        let mut n_cliques = 0u32;
        let mut truncated = 0usize;
        for ty in 0..rows {
            for tx in 0..cols {
                let i = ty * cols + tx;
                let (cx, cy) = (loc.x + tx as isize, loc.y + ty as isize);
                let prior = f64::from(w.w_prior[i]);
                if cx < 0 || cy < 0 || cx as usize >= mw || cy as usize >= mh {
                    p.u1[i] = 0.0;
                    p.u0[i] = prior;
                    p.clique_of[i] = NO_CLIQUE;
                    truncated += 1;
                    if let Some(f) = features.as_deref_mut() {
                        f.push([0.0; HOG_DIM]);
                    }
                    continue;
                }
                let (cx, cy) = (cx as usize, cy as usize);
                let phi = level.hog.cell_padded(cx, cy);
                if edges {
                    s.edge_dirs[i] = edge_direction(phi);
                }
                if let Some(f) = features.as_deref_mut() {
                    let mut c = [0.0f32; HOG_DIM];
                    c.copy_from_slice(&phi[..HOG_DIM]);
                    f.push(c);
                }
                let f = &w.w_vis[i * HOG_STRIDE..(i + 1) * HOG_STRIDE];
                let b = &w.w_occ[i * HOG_STRIDE..(i + 1) * HOG_STRIDE];
                p.u1[i] = f64::from(dot(f, phi));
                // Response transfer: where another object's detection
                // claimed the cell, the occlusion is explained by it: the
                // occlusion filter's response counts no more than its
                // collected object response, and never more than 0 (see
                // `transfer.rs` for why it is capped and not replaced).
                let occ = match self.transfer.and_then(|t| t.at(loc.level, cx, cy)) {
                    Some(c) => dot(b, phi).min(c.max(0.0)),
                    None => dot(b, phi),
                };
                p.u0[i] = f64::from(occ) + prior;
                let seg = level.cell_segments[cy * mw + cx] as usize;
                if s.seg_stamp[seg] != s.generation {
                    s.seg_stamp[seg] = s.generation;
                    s.seg_local[seg] = n_cliques;
                    n_cliques += 1;
                }
                p.clique_of[i] = s.seg_local[seg];
            }
        }
        p.n_cliques = n_cliques as usize;
        p.constant = f64::from(w.w_trunc) * truncated as f64 + f64::from(w.bias);
        if edges {
            // A pair runs along an edge when both cells lie on an edge in
            // the pair's direction (cells outside the image lie on none).
            for i in 0..rows * cols {
                let d = s.edge_dirs[i];
                if i % cols + 1 < cols && d == 1 && s.edge_dirs[i + 1] == 1 {
                    p.pairs[i] |= PAIR_RIGHT;
                }
                if i + cols < rows * cols && d == 2 && s.edge_dirs[i + cols] == 2 {
                    p.pairs[i] |= PAIR_DOWN;
                }
            }
        }
        truncated
    }

    /// The CRF of a location, the HOG features of its cells (zero outside
    /// the image) and its number of cells outside the image: what
    /// [`super::energy::joint_feature`] needs.
    pub fn problem_at(
        &self,
        pyr: &FeaturePyramid,
        loc: &Location,
    ) -> (BoxProblem, Vec<[f32; HOG_DIM]>, usize) {
        let mut s = Scratch::default();
        let mut feats = Vec::new();
        let truncated = self.fill_problem(pyr, loc, &mut s, Some(&mut feats));
        (s.problem, feats, truncated)
    }
}
