//! The SD-HOP energy of eq. (4) at one box location, its joint feature
//! vector (section 2.2), and its exact minimisation by s-t min-cut with the
//! lower-linear-envelope construction of `hop-graph.md`.
//!
//! Labels: `true` = visible (1), `false` = occluded (0). The energy is
//! `sum_i F_i v_i + (B_i + R_i)(1 - v_i) + W * #(4-neighbour label changes)
//!  + sum_c psi_c(S_c) + w_trunc * c(p) + bias`, where `psi_c` is the linear
//! interpolation of `w_hop` at the normalised count `t_c = K S_c / M_c`.
//!
//! Why one file of about 880 lines: the energy, its joint feature vector,
//! the graph construction and the bounds must agree term by term, and a
//! third of the file is the tests that check them against brute force.

use super::hog::{HOG_DIM, HOG_STRIDE, INSENSITIVE_BINS, SENSITIVE_BINS};
use super::maxflow::Graph;
use super::VisionError;

/// No clique: a cell outside the image.
pub const NO_CLIQUE: u32 = u32::MAX;

/// Round-off below which a curvature `(D^2 w)_k` counts as zero.
pub const CURVATURE_EPS: f64 = 1e-9;

/// `(D^2 w)_k = -w_{k-1} + 2 w_k - w_{k+1}` for `k = 1..K-1`.
pub fn hop_curvature(w_hop: &[f64]) -> Vec<f64> {
    (1..w_hop.len().saturating_sub(1))
        .map(|k| -w_hop[k - 1] + 2.0 * w_hop[k] - w_hop[k + 1])
        .collect()
}

/// Checks what the min-cut construction needs of the CRF weights:
/// `K + 1 >= 2` HOP weights, `W >= 0` and `D^2 w_hop >= -tolerance`.
fn check_graph_weights(w_hop: &[f64], pairwise: f64, tolerance: f64) -> Result<(), VisionError> {
    if w_hop.len() < 2 {
        return Err(VisionError::InvalidParameter(
            "w_hop needs K + 1 >= 2 values".into(),
        ));
    }
    if pairwise < 0.0 {
        return Err(VisionError::InvalidParameter(format!(
            "pairwise weight W must be >= 0, got {pairwise}"
        )));
    }
    if let Some(c) = hop_curvature(w_hop).iter().find(|&&c| c < -tolerance) {
        return Err(VisionError::InvalidParameter(format!(
            "w_hop must be concave (D^2 w >= 0), found curvature {c}"
        )));
    }
    Ok(())
}

/// The interpolation feature `theta_c` of a clique of size `m` with `s`
/// visible cells, accumulated into `out` (length `K + 1`).
pub fn hop_theta_add(s: usize, m: usize, out: &mut [f64]) {
    let k_max = out.len() - 1;
    if m == 0 {
        return;
    }
    // t = K s / m, floor by integer division so knots are exact.
    let num = k_max * s;
    let k = num / m;
    let phi = (num - k * m) as f64 / m as f64;
    out[k] += 1.0 - phi;
    if k < k_max {
        out[k + 1] += phi;
    }
}

/// `psi_c(S) = w_hop . theta_c`.
pub fn hop_value(w_hop: &[f64], s: usize, m: usize) -> f64 {
    let mut theta = vec![0.0; w_hop.len()];
    hop_theta_add(s, m, &mut theta);
    w_hop.iter().zip(&theta).map(|(w, t)| w * t).sum()
}

/// Which 4-neighbour pairs of a box carry the Potts term.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PairwiseMode {
    /// Every 4-connected pair (SD-HOP).
    #[default]
    Grid,
    /// Only pairs that run along an image edge, as in Gao, Packer and
    /// Koller 2011 (the ablation of the paper): both cells lie on an edge
    /// ([`edge_direction`]) whose direction is the direction of the pair.
    Edges,
}

/// Smallest dominant contrast-insensitive orientation value of a cell that
/// counts as lying on an edge.
pub const EDGE_STRENGTH: f32 = 0.1;

/// Direction of the edge a cell lies on, from its HOG features: `1` when
/// the edge runs horizontally (the dominant gradient is within 30 degrees of
/// vertical), `2` when it runs vertically (gradient within 20 degrees of
/// horizontal), `0` for no edge (weak or diagonal gradients).
pub fn edge_direction(phi: &[f32]) -> u8 {
    let unsigned = &phi[SENSITIVE_BINS..SENSITIVE_BINS + INSENSITIVE_BINS];
    let (mut best, mut bin) = (0.0f32, 0usize);
    for (b, &v) in unsigned.iter().enumerate() {
        if v > best {
            best = v;
            bin = b;
        }
    }
    if best < EDGE_STRENGTH {
        return 0;
    }
    match bin {
        3..=6 => 1,
        0 | 1 | 8 => 2,
        _ => 0,
    }
}

/// Pair flags of [`BoxProblem::pairs`]: the pair with the right neighbour,
/// the pair with the neighbour below.
pub const PAIR_RIGHT: u8 = 1;
pub const PAIR_DOWN: u8 = 2;

/// The CRF over the cells of one box: unaries, Potts weight, cliques and HOP
/// weights. Buffers are reused between locations.
#[derive(Clone, Debug, Default)]
pub struct BoxProblem {
    pub rows: usize,
    pub cols: usize,
    /// Cost of labelling cell `i` visible (`F_i`, plus any loss terms).
    pub u1: Vec<f64>,
    /// Cost of labelling cell `i` occluded (`B_i + R_i`, plus any loss terms).
    pub u0: Vec<f64>,
    /// Potts weight `W >= 0`.
    pub pairwise: f64,
    /// Which pairs carry the Potts term, per cell ([`PAIR_RIGHT`] |
    /// [`PAIR_DOWN`]); empty means every 4-connected pair.
    pub pairs: Vec<u8>,
    /// Clique of every cell (`0..n_cliques`) or [`NO_CLIQUE`].
    pub clique_of: Vec<u32>,
    pub n_cliques: usize,
    /// `w_HOP`, `K + 1` values with `D^2 w >= 0`.
    pub w_hop: Vec<f64>,
    /// Constant term `C(y)` (truncation cost and bias, plus any loss constant).
    pub constant: f64,
    // Scratch.
    diffs: Vec<f64>,
    sizes: Vec<u32>,
    members_start: Vec<u32>,
    members: Vec<u32>,
}

impl BoxProblem {
    /// An empty problem of the given shape with zero terms.
    pub fn new(rows: usize, cols: usize, w_hop: Vec<f64>) -> Self {
        let n = rows * cols;
        Self {
            rows,
            cols,
            u1: vec![0.0; n],
            u0: vec![0.0; n],
            pairwise: 0.0,
            clique_of: vec![NO_CLIQUE; n],
            n_cliques: 0,
            w_hop,
            constant: 0.0,
            ..Default::default()
        }
    }

    pub fn len(&self) -> usize {
        self.rows * self.cols
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Checks `W >= 0`, `D^2 w_hop >= 0`, shapes and finiteness.
    pub fn validate(&self) -> Result<(), VisionError> {
        let n = self.len();
        if self.u1.len() != n
            || self.u0.len() != n
            || self.clique_of.len() != n
            || !(self.pairs.is_empty() || self.pairs.len() == n)
        {
            return Err(VisionError::InvalidParameter(
                "box problem buffers disagree".into(),
            ));
        }
        let finite = self
            .u1
            .iter()
            .chain(&self.u0)
            .chain(&self.w_hop)
            .all(|v| v.is_finite())
            && self.pairwise.is_finite()
            && self.constant.is_finite();
        if !finite {
            return Err(VisionError::NonFinite("energy terms"));
        }
        check_graph_weights(&self.w_hop, self.pairwise, CURVATURE_EPS)?;
        if self
            .clique_of
            .iter()
            .any(|&c| c != NO_CLIQUE && c as usize >= self.n_cliques)
        {
            return Err(VisionError::InvalidParameter(
                "clique index out of range".into(),
            ));
        }
        Ok(())
    }

    /// Adds a Hamming loss against `truth`: `weight` per disagreeing cell.
    pub fn add_hamming_loss(&mut self, truth: &[bool], weight: f64) {
        for (i, &t) in truth.iter().enumerate() {
            if t {
                self.u0[i] -= weight;
            } else {
                self.u1[i] -= weight;
            }
        }
    }

    /// Whether the pair of cell `i` in direction `flag` carries the Potts
    /// term.
    #[inline]
    fn pair_on(&self, i: usize, flag: u8) -> bool {
        self.pairs.is_empty() || self.pairs[i] & flag != 0
    }

    /// Number of neighbour pairs carrying the Potts term with different
    /// labels.
    pub fn label_changes(&self, v: &[bool]) -> usize {
        let mut n = 0;
        for y in 0..self.rows {
            for x in 0..self.cols {
                let i = y * self.cols + x;
                if x + 1 < self.cols && v[i] != v[i + 1] && self.pair_on(i, PAIR_RIGHT) {
                    n += 1;
                }
                if y + 1 < self.rows && v[i] != v[i + self.cols] && self.pair_on(i, PAIR_DOWN) {
                    n += 1;
                }
            }
        }
        n
    }

    /// The HOP statistic `theta_HOP = sum_c theta_c` of a labelling.
    pub fn hop_statistic(&self, v: &[bool]) -> Vec<f64> {
        let mut sizes = vec![0usize; self.n_cliques];
        let mut on = vec![0usize; self.n_cliques];
        for (i, &c) in self.clique_of.iter().enumerate() {
            if c != NO_CLIQUE {
                sizes[c as usize] += 1;
                on[c as usize] += usize::from(v[i]);
            }
        }
        let mut theta = vec![0.0; self.w_hop.len()];
        for (s, m) in on.iter().zip(&sizes) {
            hop_theta_add(*s, *m, &mut theta);
        }
        theta
    }

    /// The energy of a labelling, evaluated term by term.
    pub fn energy(&self, v: &[bool]) -> f64 {
        let unary: f64 = (0..self.len())
            .map(|i| if v[i] { self.u1[i] } else { self.u0[i] })
            .sum();
        let hop: f64 = self
            .hop_statistic(v)
            .iter()
            .zip(&self.w_hop)
            .map(|(t, w)| t * w)
            .sum();
        unary + self.pairwise * self.label_changes(v) as f64 + hop + self.constant
    }

    /// A lower bound on the minimum energy: every cell's best unary, every
    /// clique's smallest potential (`min(w_0, w_K)` by concavity), `W >= 0`.
    pub fn lower_bound(&self) -> f64 {
        let unary: f64 = self.u1.iter().zip(&self.u0).map(|(a, b)| a.min(*b)).sum();
        let k = self.w_hop.len() - 1;
        unary + self.n_cliques as f64 * self.w_hop[0].min(self.w_hop[k]) + self.constant
    }

    /// A lower bound on the minimum energy that keeps the Potts terms: the
    /// unary and pairwise energy is split into one chain per row and one per
    /// column of the box, each taking half of every unary and the Potts
    /// terms of its own pairs; the chains are minimised exactly by dynamic
    /// programming, and the sum of their minima is at most the minimum of
    /// their sum. Cliques add their smallest potential (`min(w_0, w_K)` by
    /// concavity). Equals [`BoxProblem::lower_bound`] when `W = 0`.
    pub fn lower_bound_chains(&self) -> f64 {
        let (rows, cols) = (self.rows, self.cols);
        let k = self.w_hop.len() - 1;
        let w = self.pairwise;
        let mut total = self.constant + self.n_cliques as f64 * self.w_hop[0].min(self.w_hop[k]);
        // One chain: `cells` in order, `flag` the pair flag linking each
        // cell to the next.
        let chain = |cells: &mut dyn Iterator<Item = usize>, flag: u8| -> f64 {
            let (mut s0, mut s1) = (0.0f64, 0.0f64);
            let mut prev: Option<usize> = None;
            for i in cells {
                let (u0, u1) = (0.5 * self.u0[i], 0.5 * self.u1[i]);
                match prev {
                    None => (s0, s1) = (u0, u1),
                    Some(p) => {
                        let wp = if self.pair_on(p, flag) { w } else { 0.0 };
                        (s0, s1) = (u0 + s0.min(s1 + wp), u1 + s1.min(s0 + wp));
                    }
                }
                prev = Some(i);
            }
            s0.min(s1)
        };
        for y in 0..rows {
            total += chain(&mut (0..cols).map(|x| y * cols + x), PAIR_RIGHT);
        }
        for x in 0..cols {
            total += chain(&mut (0..rows).map(|y| y * cols + x), PAIR_DOWN);
        }
        total
    }

    /// The exact minimum of the energy without its pairwise term, a lower
    /// bound on the minimum because `W >= 0`. Without pairwise terms the
    /// energy splits into independent cliques, and for a clique the best
    /// labelling with `s` visible cells takes the `s` cells whose visible
    /// label costs least relative to the occluded one, so the minimum is a
    /// sort and a scan over `s`.
    pub fn lower_bound_without_pairwise(&mut self) -> f64 {
        self.gather_cliques();
        let k = self.w_hop.len() - 1;
        let mut total = self.constant;
        for (i, &c) in self.clique_of.iter().enumerate() {
            if c == NO_CLIQUE {
                total += self.u1[i].min(self.u0[i]);
            }
        }
        for c in 0..self.n_cliques {
            let lo = self.members_start[c] as usize;
            let hi = self.members_start[c + 1] as usize;
            let m = hi - lo;
            if m == 0 {
                continue;
            }
            self.diffs.clear();
            let mut base = 0.0;
            for &i in &self.members[lo..hi] {
                let i = i as usize;
                base += self.u0[i];
                self.diffs.push(self.u1[i] - self.u0[i]);
            }
            self.diffs.sort_unstable_by(f64::total_cmp);
            let mut best = f64::INFINITY;
            let mut prefix = 0.0;
            for s in 0..=m {
                if s > 0 {
                    prefix += self.diffs[s - 1];
                }
                let num = k * s;
                let kk = num / m;
                let phi = (num - kk * m) as f64 / m as f64;
                let hop = if kk < k {
                    (1.0 - phi) * self.w_hop[kk] + phi * self.w_hop[kk + 1]
                } else {
                    self.w_hop[k]
                };
                best = best.min(base + prefix + hop);
            }
            total += best;
        }
        total
    }

    /// Groups cells by clique (counting sort into the scratch buffers).
    fn gather_cliques(&mut self) {
        let nc = self.n_cliques;
        self.sizes.clear();
        self.sizes.resize(nc, 0);
        for &c in &self.clique_of {
            if c != NO_CLIQUE {
                self.sizes[c as usize] += 1;
            }
        }
        self.members_start.clear();
        self.members_start.resize(nc + 1, 0);
        for c in 0..nc {
            self.members_start[c + 1] = self.members_start[c] + self.sizes[c];
        }
        self.members.clear();
        self.members.resize(self.members_start[nc] as usize, 0);
        let mut fill: Vec<u32> = self.members_start[..nc].to_vec();
        for (i, &c) in self.clique_of.iter().enumerate() {
            if c != NO_CLIQUE {
                self.members[fill[c as usize] as usize] = i as u32;
                fill[c as usize] += 1;
            }
        }
    }

    /// Minimises the energy exactly by min-cut (the construction of
    /// `hop-graph.md`, source side = visible). Writes the labelling into `v`
    /// and returns its energy. Assumes [`BoxProblem::validate`] holds.
    pub fn solve(&mut self, graph: &mut Graph, v: &mut Vec<bool>) -> f64 {
        self.solve_below(graph, v, f64::INFINITY)
            .unwrap_or(f64::INFINITY)
    }

    /// Like [`BoxProblem::solve`], but returns `None` without finishing as
    /// soon as the minimum is known to exceed `limit` (the flow found so far
    /// plus the constant already does); `v` is then not a labelling.
    pub fn solve_below(&mut self, graph: &mut Graph, v: &mut Vec<bool>, limit: f64) -> Option<f64> {
        let n = self.len();
        let k = self.w_hop.len() - 1;
        let kf = k as f64;
        let curv: Vec<f64> = hop_curvature(&self.w_hop)
            .into_iter()
            .map(|c| if c > CURVATURE_EPS { c } else { 0.0 })
            .collect();
        let first_slope = self.w_hop[1] - self.w_hop[0];
        let clique_constant = self.w_hop[k] - kf * first_slope;
        self.gather_cliques();
        graph.reset();
        graph.add_nodes(n);
        let mut constant = self.constant;
        for i in 0..n {
            let mut u1 = self.u1[i];
            let c = self.clique_of[i];
            if c != NO_CLIQUE {
                u1 += kf / f64::from(self.sizes[c as usize]) * first_slope;
            }
            graph.add_tweights(i, self.u0[i], u1);
        }
        if self.pairwise > 0.0 {
            for y in 0..self.rows {
                for x in 0..self.cols {
                    let i = y * self.cols + x;
                    if x + 1 < self.cols && self.pair_on(i, PAIR_RIGHT) {
                        graph.add_edge(i, i + 1, self.pairwise, self.pairwise);
                    }
                    if y + 1 < self.rows && self.pair_on(i, PAIR_DOWN) {
                        graph.add_edge(i, i + self.cols, self.pairwise, self.pairwise);
                    }
                }
            }
        }
        for c in 0..self.n_cliques {
            let m = self.sizes[c];
            if m == 0 {
                continue;
            }
            constant += clique_constant;
            let lo = self.members_start[c] as usize;
            let hi = self.members_start[c + 1] as usize;
            for (kk, &d2) in curv.iter().enumerate() {
                if d2 == 0.0 {
                    continue;
                }
                let knot = kk + 1;
                let z = graph.add_nodes(1);
                graph.add_tweights(z, (kf - knot as f64) * d2, 0.0);
                let cap = kf / f64::from(m) * d2;
                for &i in &self.members[lo..hi] {
                    graph.add_edge(z, i as usize, cap, 0.0);
                }
            }
        }
        let flow = graph.maxflow_until(limit - constant)?;
        v.clear();
        v.extend((0..n).map(|i| graph.is_source_side(i)));
        Some(flow + constant)
    }
}

/// Weights of one viewpoint: the blocks of `w` in the order of the joint
/// feature, `[w_vis, w_occ, w_prior, w_trunc, W, w_hop, bias]`.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewWeights {
    /// Template height in cells.
    pub rows: usize,
    /// Template width in cells.
    pub cols: usize,
    /// Object filter, `rows * cols * HOG_STRIDE` (pad entries zero).
    pub w_vis: Vec<f32>,
    /// Occlusion filter, same layout.
    pub w_occ: Vec<f32>,
    /// Prior cost of each cell being occluded, `rows * cols`.
    pub w_prior: Vec<f32>,
    /// Cost per cell outside the image.
    pub w_trunc: f32,
    /// Potts weight `W`.
    pub w_pair: f32,
    /// Which neighbour pairs carry `W`.
    pub pair_mode: PairwiseMode,
    /// Higher-order weights, `K + 1`.
    pub w_hop: Vec<f32>,
    pub bias: f32,
}

impl ViewWeights {
    /// All-zero weights (a flat HOP) for a template of `rows x cols` cells.
    pub fn zeros(rows: usize, cols: usize, k: usize) -> Self {
        let n = rows * cols;
        Self {
            rows,
            cols,
            w_vis: vec![0.0; n * HOG_STRIDE],
            w_occ: vec![0.0; n * HOG_STRIDE],
            w_prior: vec![0.0; n],
            w_trunc: 0.0,
            w_pair: 0.0,
            pair_mode: PairwiseMode::Grid,
            w_hop: vec![0.0; k + 1],
            bias: 0.0,
        }
    }

    pub fn cells(&self) -> usize {
        self.rows * self.cols
    }

    /// Length of the joint feature vector of this viewpoint.
    pub fn feature_len(&self) -> usize {
        joint_feature_len(self.cells(), self.w_hop.len() - 1)
    }

    /// Checks shapes, finiteness, `W >= 0` and `D^2 w_hop >= 0`.
    pub fn validate(&self) -> Result<(), VisionError> {
        let n = self.cells();
        if n == 0 {
            return Err(VisionError::InvalidParameter(
                "template has no cells".into(),
            ));
        }
        if self.w_vis.len() != n * HOG_STRIDE
            || self.w_occ.len() != n * HOG_STRIDE
            || self.w_prior.len() != n
        {
            return Err(VisionError::InvalidParameter(
                "weight blocks disagree with the template size".into(),
            ));
        }
        let all = self
            .w_vis
            .iter()
            .chain(&self.w_occ)
            .chain(&self.w_prior)
            .chain(&self.w_hop)
            .chain([&self.w_trunc, &self.w_pair, &self.bias]);
        if !all.into_iter().all(|v| v.is_finite()) {
            return Err(VisionError::NonFinite("weights"));
        }
        // Stored as f32: allow their round-off in the curvature.
        let hop: Vec<f64> = self.w_hop.iter().map(|&v| f64::from(v)).collect();
        check_graph_weights(&hop, f64::from(self.w_pair), 1e-6)
    }

    /// The weights as one flat vector in joint-feature order.
    pub fn to_vector(&self) -> Vec<f64> {
        let mut w = Vec::with_capacity(self.feature_len());
        let strip = |f: &[f32], w: &mut Vec<f64>| {
            for cell in f.chunks(HOG_STRIDE) {
                w.extend(cell[..HOG_DIM].iter().map(|&v| f64::from(v)));
            }
        };
        strip(&self.w_vis, &mut w);
        strip(&self.w_occ, &mut w);
        w.extend(self.w_prior.iter().map(|&v| f64::from(v)));
        w.push(f64::from(self.w_trunc));
        w.push(f64::from(self.w_pair));
        w.extend(self.w_hop.iter().map(|&v| f64::from(v)));
        w.push(f64::from(self.bias));
        w
    }
}

/// Length of one viewpoint's joint feature vector for `n` cells and `K`.
pub fn joint_feature_len(n: usize, k: usize) -> usize {
    2 * n * HOG_DIM + n + 1 + 1 + (k + 1) + 1
}

/// The joint feature `Psi(x, y)` of one viewpoint: the HOG features of the
/// box cells (zero outside the image), a labelling, the cells' cliques and the
/// number of cells outside the image.
pub fn joint_feature(
    features: &[[f32; HOG_DIM]],
    v: &[bool],
    problem: &BoxProblem,
    truncated_cells: usize,
) -> Vec<f64> {
    let n = v.len();
    let k = problem.w_hop.len() - 1;
    let mut psi = vec![0.0; joint_feature_len(n, k)];
    for (i, f) in features.iter().enumerate() {
        let base = if v[i] { i * HOG_DIM } else { (n + i) * HOG_DIM };
        for (d, &x) in f.iter().enumerate() {
            psi[base + d] = f64::from(x);
        }
    }
    let mut o = 2 * n * HOG_DIM;
    for (i, &vi) in v.iter().enumerate() {
        psi[o + i] = if vi { 0.0 } else { 1.0 };
    }
    o += n;
    psi[o] = truncated_cells as f64;
    psi[o + 1] = problem.label_changes(v) as f64;
    o += 2;
    for (j, t) in problem.hop_statistic(v).into_iter().enumerate() {
        psi[o + j] = t;
    }
    psi[o + k + 1] = 1.0;
    psi
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;
    use crate::vision::rng::SplitMix64;
    use proptest::prelude::*;

    /// A random concave `w_hop` (non-increasing differences), K + 1 values.
    fn concave(rng: &mut SplitMix64, k: usize) -> Vec<f64> {
        let mut diffs: Vec<f64> = (0..k).map(|_| rng.range_f64(-3.0, 3.0)).collect();
        diffs.sort_by(|a, b| b.total_cmp(a));
        if rng.next_f64() < 0.2 {
            // Straight stretches: repeated differences (zero curvature).
            let d = diffs[0];
            diffs.iter_mut().take(k / 2 + 1).for_each(|x| *x = d);
        }
        let mut w = vec![rng.range_f64(-2.0, 2.0)];
        for d in diffs {
            let last = *w.last().unwrap();
            w.push(last + d);
        }
        w
    }

    /// Random connected-ish segments: region growing from random seeds,
    /// optionally leaving some cells outside the image (no clique).
    fn random_problem(rng: &mut SplitMix64, rows: usize, cols: usize) -> BoxProblem {
        let n = rows * cols;
        let k = if rng.next_f64() < 0.7 {
            4
        } else {
            rng.range_usize(1, 7)
        };
        let mut p = BoxProblem::new(rows, cols, concave(rng, k));
        let scale = if rng.next_f64() < 0.5 { 0.125 } else { 1.0 };
        for i in 0..n {
            p.u1[i] = rng.range_f64(-3.0, 3.0) * scale;
            p.u0[i] = rng.range_f64(-3.0, 3.0) * scale;
        }
        p.pairwise = if rng.next_f64() < 0.2 {
            0.0
        } else {
            rng.range_f64(0.0, 1.5) * scale
        };
        p.w_hop.iter_mut().for_each(|w| *w *= scale);
        p.constant = rng.range_f64(-1.0, 1.0);
        if rng.next_f64() < 0.3 {
            // Potts terms on some pairs only (the edge-pairwise ablation).
            p.pairs = (0..n).map(|_| rng.range_usize(0, 4) as u8).collect();
        }
        let seeds = rng.range_usize(1, 5.min(n) + 1);
        let mut lab = vec![u32::MAX; n];
        let mut order: Vec<usize> = (0..n).collect();
        for s in 0..seeds {
            let i = rng.range_usize(0, n);
            lab[i] = s as u32;
        }
        // Grow: repeatedly give unlabelled cells the label of a labelled neighbour.
        while lab.contains(&u32::MAX) {
            for i in 0..n {
                let j = rng.range_usize(0, n);
                order.swap(i, j);
            }
            for &i in &order {
                if lab[i] != u32::MAX {
                    continue;
                }
                let (y, x) = (i / cols, i % cols);
                let nb = [
                    (x > 0).then(|| i - 1),
                    (x + 1 < cols).then(|| i + 1),
                    (y > 0).then(|| i - cols),
                    (y + 1 < rows).then(|| i + cols),
                ];
                if let Some(j) = nb.iter().flatten().find(|&&j| lab[j] != u32::MAX) {
                    lab[i] = lab[*j];
                }
            }
        }
        // Some cells outside the image: no clique.
        let outside = rng.next_f64() < 0.3;
        let cut = rng.range_usize(0, cols);
        for i in 0..n {
            if outside && i % cols < cut {
                lab[i] = u32::MAX;
            }
        }
        // Renumber cliques densely.
        let mut map = std::collections::HashMap::new();
        for i in 0..n {
            if lab[i] != u32::MAX {
                let next = map.len() as u32;
                p.clique_of[i] = *map.entry(lab[i]).or_insert(next);
            }
        }
        p.n_cliques = map.len();
        p
    }

    fn brute_force(p: &BoxProblem) -> f64 {
        let n = p.len();
        (0..1u32 << n)
            .map(|m| {
                let v: Vec<bool> = (0..n).map(|i| m >> i & 1 == 1).collect();
                p.energy(&v)
            })
            .fold(f64::INFINITY, f64::min)
    }

    #[test]
    fn worked_example_of_hop_graph_md() {
        // Section 5 of hop-graph.md: 2x3 box, one clique, W = 1/4.
        let mut p = BoxProblem::new(2, 3, vec![0.0, 3.0, 4.0, 3.0, 0.0]);
        p.u1 = vec![-2.0, 0.5, 3.0, -2.0, -0.75, 4.0];
        p.u0 = vec![1.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        p.pairwise = 0.25;
        p.clique_of = vec![0; 6];
        p.n_cliques = 1;
        p.validate().unwrap();
        let mut g = Graph::new();
        let mut v = Vec::new();
        let e = p.solve(&mut g, &mut v);
        assert!((e - (-5.0 / 12.0)).abs() < 1e-12, "{e}");
        assert_eq!(v, vec![true, true, false, true, true, false]);
        assert!((hop_value(&p.w_hop, 2, 6) - 10.0 / 3.0).abs() < 1e-12);
        // Loss-augmented against v_hat = (1,0,0,1,1,0): -7/12.
        let truth = [true, false, false, true, true, false];
        p.add_hamming_loss(&truth, 1.0 / 6.0);
        let e = p.solve(&mut g, &mut v);
        assert!((e - (-7.0 / 12.0)).abs() < 1e-12, "{e}");
        assert_eq!(v, vec![true, true, false, true, true, false]);
    }

    #[test]
    fn edge_direction_follows_the_dominant_gradient() {
        let mut phi = [0.0f32; HOG_DIM];
        assert_eq!(edge_direction(&phi), 0, "flat cell");
        // Gradient along +y (bin 4.5 of 9): a horizontal edge.
        phi[SENSITIVE_BINS + 4] = 0.3;
        assert_eq!(edge_direction(&phi), 1);
        // Gradient along x: a vertical edge.
        phi[SENSITIVE_BINS] = 0.4;
        assert_eq!(edge_direction(&phi), 2);
        // Diagonal, or too weak.
        let mut d = [0.0f32; HOG_DIM];
        d[SENSITIVE_BINS + 2] = 0.3;
        assert_eq!(edge_direction(&d), 0);
        d[SENSITIVE_BINS + 2] = 0.0;
        d[SENSITIVE_BINS] = EDGE_STRENGTH * 0.5;
        assert_eq!(edge_direction(&d), 0);
    }

    #[test]
    fn theta_interpolates_at_knots() {
        let mut t = vec![0.0; 5];
        hop_theta_add(3, 6, &mut t);
        assert_eq!(t, vec![0.0, 0.0, 1.0, 0.0, 0.0]);
        let mut t = vec![0.0; 5];
        hop_theta_add(1, 6, &mut t);
        assert!((t[0] - 1.0 / 3.0).abs() < 1e-15 && (t[1] - 2.0 / 3.0).abs() < 1e-15);
        let mut t = vec![0.0; 5];
        hop_theta_add(6, 6, &mut t);
        assert_eq!(t, vec![0.0, 0.0, 0.0, 0.0, 1.0]);
    }

    #[test]
    fn non_concave_or_negative_weights_are_refused() {
        let mut p = BoxProblem::new(1, 2, vec![0.0, -1.0, 0.0]);
        assert!(p.validate().is_err());
        p.w_hop = vec![0.0, 1.0, 0.0];
        p.pairwise = -0.1;
        assert!(p.validate().is_err());
        p.pairwise = 0.1;
        p.u1[0] = f64::NAN;
        assert!(matches!(p.validate(), Err(VisionError::NonFinite(_))));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(1500))]

        /// The min-cut labelling's energy is the exhaustive minimum, plain and
        /// loss-augmented, for boxes of up to 16 cells.
        #[test]
        fn min_cut_equals_exhaustive_minimum(seed in any::<u64>()) {
            let mut rng = SplitMix64::new(seed);
            let (rows, cols) = loop {
                let r = rng.range_usize(1, 5);
                let c = rng.range_usize(1, 5);
                if r * c <= 16 { break (r, c); }
            };
            let mut p = random_problem(&mut rng, rows, cols);
            p.validate().unwrap();
            let mut g = Graph::new();
            let mut v = Vec::new();
            for round in 0..2 {
                if round == 1 {
                    let truth: Vec<bool> = (0..p.len()).map(|_| rng.next_f64() < 0.5).collect();
                    p.add_hamming_loss(&truth, 1.0 / p.len() as f64);
                }
                let e = p.solve(&mut g, &mut v);
                let best = brute_force(&p);
                let direct = p.energy(&v);
                prop_assert!((e - best).abs() < 1e-9, "round {}: cut {} vs brute {}", round, e, best);
                prop_assert!((direct - best).abs() < 1e-9, "round {}: labelling energy {} vs {}", round, direct, best);
                prop_assert!(p.lower_bound() <= best + 1e-9);
                let chains = p.lower_bound_chains();
                prop_assert!(chains <= best + 1e-9, "chain bound {} above {}", chains, best);
                prop_assert!(p.lower_bound() <= chains + 1e-9);
                let tight = p.lower_bound_without_pairwise();
                prop_assert!(tight <= best + 1e-9, "bound {} above {}", tight, best);
                prop_assert!(p.lower_bound() <= tight + 1e-9);
                let mut q = p.clone();
                q.pairwise = 0.0;
                let exact = brute_force(&q);
                prop_assert!((q.lower_bound_without_pairwise() - exact).abs() < 1e-9);
            }
        }

        /// `w . Psi(x, y) == E(x, y)` for any labelling.
        #[test]
        fn weights_dot_joint_feature_is_energy(seed in any::<u64>()) {
            let mut rng = SplitMix64::new(seed);
            let (rows, cols) = (rng.range_usize(1, 6), rng.range_usize(1, 6));
            let n = rows * cols;
            let k = rng.range_usize(1, 6);
            let mut w = ViewWeights::zeros(rows, cols, k);
            for cell in 0..n {
                for d in 0..HOG_DIM {
                    w.w_vis[cell * HOG_STRIDE + d] = rng.range_f64(-1.0, 1.0) as f32;
                    w.w_occ[cell * HOG_STRIDE + d] = rng.range_f64(-1.0, 1.0) as f32;
                }
                w.w_prior[cell] = rng.range_f64(-1.0, 1.0) as f32;
            }
            w.w_trunc = rng.range_f64(-1.0, 1.0) as f32;
            w.w_pair = rng.range_f64(0.0, 1.0) as f32;
            w.w_hop = concave(&mut rng, k).into_iter().map(|x| x as f32).collect();
            w.bias = rng.range_f64(-1.0, 1.0) as f32;
            // Features, some cells outside (zero features, no clique).
            let mut p = random_problem(&mut rng, rows, cols);
            p.w_hop = w.w_hop.iter().map(|&x| f64::from(x)).collect();
            p.pairwise = f64::from(w.w_pair);
            let feats: Vec<[f32; HOG_DIM]> = (0..n).map(|i| {
                let mut f = [0.0f32; HOG_DIM];
                if p.clique_of[i] != NO_CLIQUE {
                    f.iter_mut().for_each(|x| *x = rng.next_f64() as f32 * 0.4);
                }
                f
            }).collect();
            let truncated = p.clique_of.iter().filter(|&&c| c == NO_CLIQUE).count();
            for i in 0..n {
                let dot = |f: &[f32]| -> f64 {
                    (0..HOG_DIM).map(|d| f64::from(f[i * HOG_STRIDE + d]) * f64::from(feats[i][d])).sum()
                };
                p.u1[i] = dot(&w.w_vis);
                p.u0[i] = dot(&w.w_occ) + f64::from(w.w_prior[i]);
            }
            p.constant = f64::from(w.w_trunc) * truncated as f64 + f64::from(w.bias);
            let wv = w.to_vector();
            for _ in 0..8 {
                let v: Vec<bool> = (0..n).map(|_| rng.next_f64() < 0.5).collect();
                let psi = joint_feature(&feats, &v, &p, truncated);
                prop_assert_eq!(psi.len(), wv.len());
                let dot: f64 = psi.iter().zip(&wv).map(|(a, b)| a * b).sum();
                let e = p.energy(&v);
                prop_assert!((dot - e).abs() < 1e-9 * (1.0 + e.abs()), "{} vs {}", dot, e);
            }
        }
    }
}
