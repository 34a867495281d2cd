//! The 1-slack structural SVM QP over the working set, solved in its dual
//! with clarabel.
//!
//! Primal: `min_w,xi 1/2 |w|^2 + C xi` s.t. `g_j . w >= b_j - xi` for every
//! cutting plane `j` and `w_k >= 0` for the constrained coordinates `k`
//! (the Potts weight and the HOP curvatures, see [`super::Layout`]).
//! Dual: `max_{alpha, mu >= 0, sum alpha <= C} b . alpha - 1/2 |G alpha +
//! mu|^2`, with `w = G alpha + mu` (mu only on the constrained coordinates).
//! Its size is the number of planes plus the constrained coordinates, so it
//! stays small however long `w` is.

use clarabel::algebra::CscMatrix;
use clarabel::solver::{
    DefaultSettings, DefaultSolver, IPSolver, NonnegativeConeT, SolverStatus, SupportedConeT,
};

use super::TrainError;

/// One cutting plane: `g . w >= b - xi`.
#[derive(Clone, Debug)]
pub struct Plane {
    pub g: Vec<f64>,
    pub b: f64,
}

/// The working set and its Gram matrix.
#[derive(Default)]
pub struct WorkingSet {
    pub planes: Vec<Plane>,
    gram: Vec<Vec<f64>>,
    /// How often each plane was active (alpha > 0) since it was added.
    idle: Vec<usize>,
}

/// The QP's solution.
#[derive(Clone, Debug)]
pub struct QpSolution {
    pub w: Vec<f64>,
    /// Slack of the working set: `max_j (b_j - g_j . w)`, at least 0.
    pub xi: f64,
    /// Primal objective `1/2 |w|^2 + C xi`.
    pub objective: f64,
}

fn dotv(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

impl WorkingSet {
    pub fn add(&mut self, p: Plane) {
        let row: Vec<f64> = self.planes.iter().map(|q| dotv(&q.g, &p.g)).collect();
        for (r, v) in self.gram.iter_mut().zip(&row) {
            r.push(*v);
        }
        let mut own = row;
        own.push(dotv(&p.g, &p.g));
        self.gram.push(own);
        self.planes.push(p);
        self.idle.push(0);
    }

    /// Slack of the working set at `w`.
    pub fn slack(&self, w: &[f64]) -> f64 {
        self.planes
            .iter()
            .map(|p| p.b - dotv(&p.g, w))
            .fold(0.0, f64::max)
    }

    /// Drops planes that stayed inactive for `patience` solves.
    fn prune(&mut self, patience: usize) {
        let keep: Vec<bool> = self.idle.iter().map(|&i| i < patience).collect();
        if keep.iter().all(|&k| k) {
            return;
        }
        let mut k = keep.iter();
        self.planes.retain(|_| *k.next().unwrap_or(&true));
        let mut k = keep.iter();
        self.idle.retain(|_| *k.next().unwrap_or(&true));
        let mut rows: Vec<Vec<f64>> = Vec::new();
        for (r, &kr) in self.gram.iter().zip(&keep) {
            if kr {
                rows.push(
                    r.iter()
                        .zip(&keep)
                        .filter(|(_, &kc)| kc)
                        .map(|(v, _)| *v)
                        .collect(),
                );
            }
        }
        self.gram = rows;
    }

    /// Solves the QP for regularisation `c` with `w_k >= 0` for every `k` in
    /// `nonneg`; the returned `w` satisfies those constraints exactly.
    pub fn solve(&mut self, c: f64, nonneg: &[usize]) -> Result<QpSolution, TrainError> {
        let m = self.planes.len();
        let r = nonneg.len();
        let n = m + r;
        let dim = self.planes.first().map_or(0, |p| p.g.len());
        // H = [G^T G, G_N^T; G_N, I] (upper triangle, column by column).
        let mut colptr = vec![0usize];
        let mut rowval = Vec::new();
        let mut nzval = Vec::new();
        for j in 0..n {
            for i in 0..=j {
                let v = match (i < m, j < m) {
                    (true, true) => self.gram[i][j],
                    (true, false) => self.planes[i].g[nonneg[j - m]],
                    (false, false) => f64::from(u8::from(i == j)),
                    (false, true) => 0.0,
                };
                if v != 0.0 {
                    rowval.push(i);
                    nzval.push(v);
                }
            }
            colptr.push(rowval.len());
        }
        let p = CscMatrix::new(n, n, colptr, rowval, nzval);
        let mut q: Vec<f64> = self.planes.iter().map(|p| -p.b).collect();
        q.resize(n, 0.0);
        // -z <= 0 (n rows) and sum alpha <= C (one row).
        let mut colptr = vec![0usize];
        let mut rowval = Vec::new();
        let mut nzval = Vec::new();
        for j in 0..n {
            rowval.push(j);
            nzval.push(-1.0);
            if j < m {
                rowval.push(n);
                nzval.push(1.0);
            }
            colptr.push(rowval.len());
        }
        let a = CscMatrix::new(n + 1, n, colptr, rowval, nzval);
        let mut b = vec![0.0; n];
        b.push(c);
        let cones: [SupportedConeT<f64>; 1] = [NonnegativeConeT(n + 1)];
        let settings = DefaultSettings {
            verbose: false,
            tol_gap_abs: 1e-9,
            tol_gap_rel: 1e-9,
            ..DefaultSettings::default()
        };
        let mut solver = DefaultSolver::new(&p, &q, &a, &b, &cones, settings)
            .map_err(|e| TrainError::Qp(e.to_string()))?;
        solver.solve();
        match solver.solution.status {
            SolverStatus::Solved | SolverStatus::AlmostSolved => {}
            s => return Err(TrainError::Qp(format!("clarabel stopped: {s:?}"))),
        }
        let z = &solver.solution.x;
        let mut w = vec![0.0; dim];
        for (j, plane) in self.planes.iter().enumerate() {
            let a = z[j].max(0.0);
            if a > 1e-9 * c.max(1.0) {
                self.idle[j] = 0;
                for (wi, gi) in w.iter_mut().zip(&plane.g) {
                    *wi += a * gi;
                }
            } else {
                self.idle[j] += 1;
            }
        }
        for (k, &idx) in nonneg.iter().enumerate() {
            w[idx] += z[m + k].max(0.0);
        }
        // Exact feasibility of the saved weights: the interior-point solution
        // is feasible only to its tolerance.
        for &idx in nonneg {
            w[idx] = w[idx].max(0.0);
        }
        let xi = self.slack(&w);
        let objective = 0.5 * dotv(&w, &w) + c * xi;
        self.prune(50);
        Ok(QpSolution { w, xi, objective })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 2-d problem solved by hand: planes g = (1, 0), b = 1 and
    /// g = (0, 1), b = 1 with C large: w = (1, 1), xi = 0.
    #[test]
    fn separable_planes_give_the_hard_margin_solution() {
        let mut ws = WorkingSet::default();
        ws.add(Plane {
            g: vec![1.0, 0.0],
            b: 1.0,
        });
        ws.add(Plane {
            g: vec![0.0, 1.0],
            b: 1.0,
        });
        let s = ws.solve(100.0, &[]).unwrap();
        assert!(
            (s.w[0] - 1.0).abs() < 1e-6 && (s.w[1] - 1.0).abs() < 1e-6,
            "{:?}",
            s.w
        );
        assert!(s.xi < 1e-6);
        // With C small the slack takes over: w = C * sum of active g / ...
        let s = ws.solve(0.5, &[]).unwrap();
        // Optimum: alpha splits C between the planes: w = (0.25, 0.25)...
        // check optimality via the objective against a grid search instead.
        let obj =
            |w: [f64; 2]| 0.5 * (w[0] * w[0] + w[1] * w[1]) + 0.5 * (1.0 - w[0].min(w[1])).max(0.0);
        let mut best = f64::INFINITY;
        for i in 0..=100 {
            for j in 0..=100 {
                best = best.min(obj([i as f64 / 100.0, j as f64 / 100.0]));
            }
        }
        assert!(s.objective <= best + 1e-6, "{} vs {}", s.objective, best);
    }

    /// A plane that pushes a constrained coordinate negative: the solution
    /// keeps it at exactly zero.
    #[test]
    fn nonnegative_coordinates_stay_feasible() {
        let mut ws = WorkingSet::default();
        ws.add(Plane {
            g: vec![-1.0, 1.0],
            b: 1.0,
        });
        let s = ws.solve(10.0, &[0]).unwrap();
        assert!(s.w[0] >= 0.0 && s.w[0] < 1e-6, "{:?}", s.w);
        assert!((s.w[1] - 1.0).abs() < 1e-6, "{:?}", s.w);
        let free = ws.solve(10.0, &[]).unwrap();
        assert!(free.w[0] < -0.4, "{:?}", free.w);
    }
}
