//! Boykov-Kolmogorov max-flow (PAMI 2004): two search trees grown from the
//! terminals, augmenting along the paths where they meet, and trees reused
//! between augmentations through orphan adoption. The graph is reset and
//! rebuilt between box locations without giving its memory back.
//!
//! Terminal capacities follow Kolmogorov's `add_tweights`: only their
//! difference is stored and the smaller one is added to the flow, so negative
//! terminal weights are allowed. Edge capacities must be non-negative.

use std::collections::VecDeque;

/// Adds terminal capacities to a node's residual terminal capacity
/// `tr_cap` (> 0 from the source, < 0 to the sink): only their difference
/// is kept, and the smaller, which every cut pays, is returned as flow.
pub(crate) fn add_terminal_caps(tr_cap: &mut f64, cap_source: f64, cap_sink: f64) -> f64 {
    let delta = *tr_cap;
    let (mut cs, mut ct) = (cap_source, cap_sink);
    if delta > 0.0 {
        cs += delta;
    } else {
        ct -= delta;
    }
    *tr_cap = cs - ct;
    cs.min(ct)
}

const NONE: u32 = u32::MAX;
const TERMINAL: u32 = u32::MAX - 1;
const ORPHAN: u32 = u32::MAX - 2;
const INFINITE_D: u32 = u32::MAX;

#[derive(Clone, Copy, Debug)]
struct Node {
    first: u32,
    parent: u32,
    ts: u32,
    dist: u32,
    is_sink: bool,
    active: bool,
    /// Residual terminal capacity: > 0 from the source, < 0 to the sink.
    tr_cap: f64,
}

#[derive(Clone, Copy, Debug)]
struct Arc {
    head: u32,
    next: u32,
    r_cap: f64,
}

/// A reusable s-t graph. Arcs come in pairs: arc `a` and its sister `a ^ 1`.
#[derive(Debug, Default)]
pub struct Graph {
    nodes: Vec<Node>,
    arcs: Vec<Arc>,
    flow: f64,
    active: VecDeque<u32>,
    orphans: VecDeque<u32>,
    time: u32,
}

impl Graph {
    pub fn new() -> Self {
        Self::default()
    }

    /// Removes every node and arc, keeping the allocations.
    pub fn reset(&mut self) {
        self.nodes.clear();
        self.arcs.clear();
        self.active.clear();
        self.orphans.clear();
        self.flow = 0.0;
        self.time = 0;
    }

    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// Adds `n` nodes; returns the index of the first.
    pub fn add_nodes(&mut self, n: usize) -> usize {
        let first = self.nodes.len();
        self.nodes.extend(std::iter::repeat_n(
            Node {
                first: NONE,
                parent: NONE,
                ts: 0,
                dist: 0,
                is_sink: false,
                active: false,
                tr_cap: 0.0,
            },
            n,
        ));
        first
    }

    /// Adds terminal capacities: `cap_source` is paid when `i` ends on the
    /// sink side, `cap_sink` when it ends on the source side. Either may be
    /// negative.
    pub fn add_tweights(&mut self, i: usize, cap_source: f64, cap_sink: f64) {
        self.flow += add_terminal_caps(&mut self.nodes[i].tr_cap, cap_source, cap_sink);
    }

    /// Adds the arc `i -> j` with capacity `cap` and `j -> i` with `rev_cap`
    /// (both clamped at zero).
    pub fn add_edge(&mut self, i: usize, j: usize, cap: f64, rev_cap: f64) {
        if i == j {
            return;
        }
        let a = self.arcs.len() as u32;
        self.arcs.push(Arc {
            head: j as u32,
            next: self.nodes[i].first,
            r_cap: cap.max(0.0),
        });
        self.arcs.push(Arc {
            head: i as u32,
            next: self.nodes[j].first,
            r_cap: rev_cap.max(0.0),
        });
        self.nodes[i].first = a;
        self.nodes[j].first = a + 1;
    }

    /// True when node `i` is on the source side of the minimum cut found by
    /// the last [`Graph::maxflow`] (the nodes reachable from the source).
    pub fn is_source_side(&self, i: usize) -> bool {
        let n = &self.nodes[i];
        n.parent != NONE && !n.is_sink
    }

    #[inline]
    fn activate(&mut self, i: u32) {
        let n = &mut self.nodes[i as usize];
        if !n.active {
            n.active = true;
            self.active.push_back(i);
        }
    }

    fn next_active(&mut self) -> Option<u32> {
        while let Some(i) = self.active.pop_front() {
            let n = &mut self.nodes[i as usize];
            n.active = false;
            if n.parent != NONE {
                return Some(i);
            }
        }
        None
    }

    /// Computes the maximum flow (including the constant collected by
    /// [`Graph::add_tweights`]).
    pub fn maxflow(&mut self) -> f64 {
        self.maxflow_until(f64::INFINITY).unwrap_or(f64::INFINITY)
    }

    /// Pushes flow along every path `source -> i -> j -> sink` of one arc,
    /// as much as each takes, in one pass over the arcs. Any flow is a valid
    /// start for the search trees, and these short paths are most of what
    /// the graphs of `energy` carry (a clique node feeding its cells, a
    /// cell feeding a neighbour), so the trees have far less left to find.
    fn push_short_paths(&mut self) {
        for i in 0..self.nodes.len() {
            let mut a = self.nodes[i].first;
            while a != NONE && self.nodes[i].tr_cap > 0.0 {
                let arc = self.arcs[a as usize];
                let j = arc.head as usize;
                let need = -self.nodes[j].tr_cap;
                if arc.r_cap > 0.0 && need > 0.0 {
                    let d = self.nodes[i].tr_cap.min(arc.r_cap).min(need);
                    self.arcs[a as usize].r_cap -= d;
                    self.arcs[(a ^ 1) as usize].r_cap += d;
                    self.nodes[i].tr_cap -= d;
                    self.nodes[j].tr_cap += d;
                    self.flow += d;
                }
                a = arc.next;
            }
        }
    }

    /// Like [`Graph::maxflow`], but gives up and returns `None` as soon as
    /// the flow exceeds `limit`: the maximum flow, never below any flow
    /// found on the way, then exceeds it too. The cut is not valid then.
    pub fn maxflow_until(&mut self, limit: f64) -> Option<f64> {
        self.push_short_paths();
        if self.flow > limit {
            return None;
        }
        self.active.clear();
        self.orphans.clear();
        self.time = 0;
        for i in 0..self.nodes.len() {
            let n = &mut self.nodes[i];
            n.active = false;
            n.ts = 0;
            if n.tr_cap > 0.0 {
                n.is_sink = false;
                n.parent = TERMINAL;
                n.dist = 1;
            } else if n.tr_cap < 0.0 {
                n.is_sink = true;
                n.parent = TERMINAL;
                n.dist = 1;
            } else {
                n.parent = NONE;
                continue;
            }
            self.activate(i as u32);
        }

        let mut current: Option<u32> = None;
        loop {
            let i = match current.take() {
                Some(i) if self.nodes[i as usize].parent != NONE => {
                    self.nodes[i as usize].active = false;
                    i
                }
                Some(i) => {
                    self.nodes[i as usize].active = false;
                    match self.next_active() {
                        Some(j) => j,
                        None => break,
                    }
                }
                None => match self.next_active() {
                    Some(j) => j,
                    None => break,
                },
            };
            let meet = self.grow(i);
            self.time = self.time.wrapping_add(1);
            if let Some(a) = meet {
                // Keep growing from `i` next round.
                self.nodes[i as usize].active = true;
                current = Some(i);
                self.augment(a);
                if self.flow > limit {
                    return None;
                }
                self.adopt();
            }
        }
        Some(self.flow)
    }

    /// Grows the tree of `i`; returns the arc (source tree -> sink tree) where
    /// the trees meet, if they do.
    fn grow(&mut self, i: u32) -> Option<u32> {
        let ni = self.nodes[i as usize];
        let mut a = ni.first;
        while a != NONE {
            let arc = self.arcs[a as usize];
            let cap = if ni.is_sink {
                self.arcs[(a ^ 1) as usize].r_cap
            } else {
                arc.r_cap
            };
            if cap > 0.0 {
                let j = arc.head;
                let nj = self.nodes[j as usize];
                if nj.parent == NONE {
                    let n = &mut self.nodes[j as usize];
                    n.is_sink = ni.is_sink;
                    n.parent = a ^ 1;
                    n.ts = ni.ts;
                    n.dist = ni.dist + 1;
                    self.activate(j);
                } else if nj.is_sink != ni.is_sink {
                    return Some(if ni.is_sink { a ^ 1 } else { a });
                } else if nj.ts <= ni.ts && nj.dist > ni.dist {
                    let n = &mut self.nodes[j as usize];
                    n.parent = a ^ 1;
                    n.ts = ni.ts;
                    n.dist = ni.dist + 1;
                }
            }
            a = arc.next;
        }
        None
    }

    fn set_orphan_front(&mut self, i: u32) {
        self.nodes[i as usize].parent = ORPHAN;
        self.orphans.push_front(i);
    }

    fn set_orphan_rear(&mut self, i: u32) {
        self.nodes[i as usize].parent = ORPHAN;
        self.orphans.push_back(i);
    }

    fn augment(&mut self, middle: u32) {
        let mut bottleneck = self.arcs[middle as usize].r_cap;
        // Source tree: from the tail of the middle arc up to the source.
        let mut i = self.arcs[(middle ^ 1) as usize].head;
        loop {
            let a = self.nodes[i as usize].parent;
            if a == TERMINAL {
                break;
            }
            bottleneck = bottleneck.min(self.arcs[(a ^ 1) as usize].r_cap);
            i = self.arcs[a as usize].head;
        }
        bottleneck = bottleneck.min(self.nodes[i as usize].tr_cap);
        // Sink tree.
        let mut i = self.arcs[middle as usize].head;
        loop {
            let a = self.nodes[i as usize].parent;
            if a == TERMINAL {
                break;
            }
            bottleneck = bottleneck.min(self.arcs[a as usize].r_cap);
            i = self.arcs[a as usize].head;
        }
        bottleneck = bottleneck.min(-self.nodes[i as usize].tr_cap);

        self.arcs[(middle ^ 1) as usize].r_cap += bottleneck;
        self.arcs[middle as usize].r_cap -= bottleneck;
        let mut i = self.arcs[(middle ^ 1) as usize].head;
        loop {
            let a = self.nodes[i as usize].parent;
            if a == TERMINAL {
                break;
            }
            self.arcs[a as usize].r_cap += bottleneck;
            self.arcs[(a ^ 1) as usize].r_cap -= bottleneck;
            if self.arcs[(a ^ 1) as usize].r_cap <= 0.0 {
                self.set_orphan_front(i);
            }
            i = self.arcs[a as usize].head;
        }
        self.nodes[i as usize].tr_cap -= bottleneck;
        if self.nodes[i as usize].tr_cap <= 0.0 {
            self.set_orphan_front(i);
        }
        let mut i = self.arcs[middle as usize].head;
        loop {
            let a = self.nodes[i as usize].parent;
            if a == TERMINAL {
                break;
            }
            self.arcs[(a ^ 1) as usize].r_cap += bottleneck;
            self.arcs[a as usize].r_cap -= bottleneck;
            if self.arcs[a as usize].r_cap <= 0.0 {
                self.set_orphan_front(i);
            }
            i = self.arcs[a as usize].head;
        }
        self.nodes[i as usize].tr_cap += bottleneck;
        if self.nodes[i as usize].tr_cap >= 0.0 {
            self.set_orphan_front(i);
        }
        self.flow += bottleneck;
    }

    fn adopt(&mut self) {
        while let Some(i) = self.orphans.pop_front() {
            self.process_orphan(i);
        }
    }

    /// Distance from `j` to its tree's terminal, or `INFINITE_D` when `j`
    /// hangs from an orphan. Marks the walked path with the current time.
    fn origin_distance(&mut self, start: u32) -> u32 {
        let time = self.time;
        let mut j = start;
        let mut d: u32 = 0;
        loop {
            let nj = self.nodes[j as usize];
            if nj.ts == time {
                d += nj.dist;
                break;
            }
            d += 1;
            if nj.parent == TERMINAL {
                let n = &mut self.nodes[j as usize];
                n.ts = time;
                n.dist = 1;
                break;
            }
            if nj.parent == ORPHAN || nj.parent == NONE {
                return INFINITE_D;
            }
            j = self.arcs[nj.parent as usize].head;
        }
        // Mark the path with distances.
        let mut j = start;
        let mut dd = d;
        while self.nodes[j as usize].ts != time {
            let n = &mut self.nodes[j as usize];
            n.ts = time;
            n.dist = dd;
            dd -= 1;
            j = self.arcs[n.parent as usize].head;
        }
        d
    }

    fn process_orphan(&mut self, i: u32) {
        let sink = self.nodes[i as usize].is_sink;
        let mut best_arc = NONE;
        let mut d_min = INFINITE_D;
        let mut a0 = self.nodes[i as usize].first;
        while a0 != NONE {
            let arc = self.arcs[a0 as usize];
            // Capacity along which `i` could receive (source tree) or send
            // (sink tree) flow through this neighbour.
            let cap = if sink {
                arc.r_cap
            } else {
                self.arcs[(a0 ^ 1) as usize].r_cap
            };
            if cap > 0.0 {
                let j = arc.head;
                let nj = self.nodes[j as usize];
                if nj.is_sink == sink && nj.parent != NONE {
                    let d = self.origin_distance(j);
                    if d < d_min {
                        best_arc = a0;
                        d_min = d;
                    }
                }
            }
            a0 = arc.next;
        }
        if best_arc != NONE {
            let time = self.time;
            let n = &mut self.nodes[i as usize];
            n.parent = best_arc;
            n.ts = time;
            n.dist = d_min + 1;
            return;
        }
        // No parent: `i` becomes free; its children become orphans and its
        // tree neighbours that could reach it become active.
        self.nodes[i as usize].parent = NONE;
        let mut a0 = self.nodes[i as usize].first;
        while a0 != NONE {
            let arc = self.arcs[a0 as usize];
            let j = arc.head;
            let nj = self.nodes[j as usize];
            if nj.is_sink == sink && nj.parent != NONE {
                let cap = if sink {
                    arc.r_cap
                } else {
                    self.arcs[(a0 ^ 1) as usize].r_cap
                };
                if cap > 0.0 {
                    self.activate(j);
                }
                if nj.parent != TERMINAL
                    && nj.parent != ORPHAN
                    && self.arcs[nj.parent as usize].head == i
                {
                    self.set_orphan_rear(j);
                }
            }
            a0 = arc.next;
        }
    }
}

/// A plain Edmonds-Karp max-flow on a dense capacity matrix, used as a
/// reference in tests. `cap[u][v]` with node 0 the source and node 1 the sink.
pub fn edmonds_karp(cap: &[Vec<f64>]) -> f64 {
    let n = cap.len();
    let mut r: Vec<Vec<f64>> = cap.to_vec();
    let mut flow = 0.0;
    loop {
        let mut prev = vec![usize::MAX; n];
        prev[0] = 0;
        let mut q = VecDeque::from([0usize]);
        while let Some(u) = q.pop_front() {
            for v in 0..n {
                if prev[v] == usize::MAX && r[u][v] > 1e-12 {
                    prev[v] = u;
                    q.push_back(v);
                }
            }
        }
        if prev[1] == usize::MAX {
            return flow;
        }
        let mut b = f64::INFINITY;
        let mut v = 1;
        while v != 0 {
            b = b.min(r[prev[v]][v]);
            v = prev[v];
        }
        let mut v = 1;
        while v != 0 {
            r[prev[v]][v] -= b;
            r[v][prev[v]] += b;
            v = prev[v];
        }
        flow += b;
    }
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;
    use crate::vision::rng::SplitMix64;

    /// A random graph: terminal weights and arcs. Capacities are drawn from a
    /// mixture of zeros, tiny values and ordinary ones.
    struct Instance {
        n: usize,
        tw: Vec<(f64, f64)>,
        edges: Vec<(usize, usize, f64, f64)>,
    }

    fn draw_cap(rng: &mut SplitMix64) -> f64 {
        match rng.range_usize(0, 6) {
            0 => 0.0,
            1 => rng.next_f64() * 1e-9,
            2 => rng.range_usize(0, 5) as f64,
            _ => rng.next_f64() * 10.0,
        }
    }

    fn random_instance(rng: &mut SplitMix64, n: usize, density: f64) -> Instance {
        let tw = (0..n)
            .map(|_| {
                let s = draw_cap(rng) - if rng.next_f64() < 0.2 { 3.0 } else { 0.0 };
                (s, draw_cap(rng))
            })
            .collect();
        let mut edges = Vec::new();
        for i in 0..n {
            for j in i + 1..n {
                if rng.next_f64() < density {
                    edges.push((i, j, draw_cap(rng), draw_cap(rng)));
                }
            }
        }
        Instance { n, tw, edges }
    }

    fn build(g: &mut Graph, inst: &Instance) {
        g.reset();
        g.add_nodes(inst.n);
        for (i, &(s, t)) in inst.tw.iter().enumerate() {
            g.add_tweights(i, s, t);
        }
        for &(i, j, c, r) in &inst.edges {
            g.add_edge(i, j, c, r);
        }
    }

    /// Cost of a labelling (true = source side) including the terminal weights.
    fn cut_cost(inst: &Instance, side: &[bool]) -> f64 {
        let mut c = 0.0;
        for (i, &(s, t)) in inst.tw.iter().enumerate() {
            c += if side[i] { t } else { s };
        }
        for &(i, j, cij, cji) in &inst.edges {
            if side[i] && !side[j] {
                c += cij;
            }
            if side[j] && !side[i] {
                c += cji;
            }
        }
        c
    }

    fn brute_force(inst: &Instance) -> f64 {
        (0..1u32 << inst.n)
            .map(|m| {
                let side: Vec<bool> = (0..inst.n).map(|i| m >> i & 1 == 1).collect();
                cut_cost(inst, &side)
            })
            .fold(f64::INFINITY, f64::min)
    }

    fn dense(inst: &Instance) -> (Vec<Vec<f64>>, f64) {
        let n = inst.n + 2;
        let mut cap = vec![vec![0.0; n]; n];
        let mut constant = 0.0;
        for (i, &(s, t)) in inst.tw.iter().enumerate() {
            let m = s.min(t);
            constant += m;
            cap[0][i + 2] += s - m;
            cap[i + 2][1] += t - m;
        }
        for &(i, j, c, r) in &inst.edges {
            cap[i + 2][j + 2] += c;
            cap[j + 2][i + 2] += r;
        }
        (cap, constant)
    }

    #[test]
    fn matches_brute_force_on_small_graphs() {
        let mut rng = SplitMix64::new(42);
        let mut g = Graph::new();
        for t in 0..3000 {
            let n = 1 + t % 11;
            let density = rng.next_f64();
            let inst = random_instance(&mut rng, n, density);
            build(&mut g, &inst);
            let flow = g.maxflow();
            let best = brute_force(&inst);
            assert!(
                (flow - best).abs() <= 1e-9 * (1.0 + best.abs()),
                "case {t}: {flow} vs {best}"
            );
            let side: Vec<bool> = (0..n).map(|i| g.is_source_side(i)).collect();
            let c = cut_cost(&inst, &side);
            assert!(
                (c - best).abs() <= 1e-9 * (1.0 + best.abs()),
                "case {t}: cut {c} vs {best}"
            );
        }
    }

    #[test]
    fn stopping_at_a_limit_is_exact() {
        // Below the maximum flow it must give up; at or above it, it must
        // return the same flow as an unlimited run.
        let mut rng = SplitMix64::new(11);
        let mut g = Graph::new();
        for t in 0..2000 {
            let density = rng.next_f64();
            let inst = random_instance(&mut rng, 1 + t % 11, density);
            let best = brute_force(&inst);
            let eps = 1e-9 * (1.0 + best.abs());
            let below = best - eps - rng.next_f64() * 5.0;
            build(&mut g, &inst);
            assert_eq!(
                g.maxflow_until(below),
                None,
                "case {t}: limit {below} < {best}"
            );
            build(&mut g, &inst);
            let above = best + eps + rng.next_f64() * 5.0;
            let f = g
                .maxflow_until(above)
                .expect("limit above the maximum flow");
            assert!((f - best).abs() <= eps, "case {t}: {f} vs {best}");
        }
    }

    #[test]
    fn matches_edmonds_karp_on_larger_graphs() {
        let mut rng = SplitMix64::new(7);
        let mut g = Graph::new();
        for t in 0..1500 {
            let n = 12 + rng.range_usize(0, 60);
            let density = rng.range_f64(0.02, 0.3);
            let inst = random_instance(&mut rng, n, density);
            build(&mut g, &inst);
            let flow = g.maxflow();
            let (cap, constant) = dense(&inst);
            let ek = edmonds_karp(&cap) + constant;
            assert!(
                (flow - ek).abs() <= 1e-7 * (1.0 + ek.abs()),
                "case {t}: {flow} vs {ek}"
            );
            let side: Vec<bool> = (0..n).map(|i| g.is_source_side(i)).collect();
            let c = cut_cost(&inst, &side);
            assert!(
                (c - ek).abs() <= 1e-7 * (1.0 + ek.abs()),
                "case {t}: cut {c} vs {ek}"
            );
        }
    }

    #[test]
    fn grid_graphs_reuse_memory() {
        // 4-connected grids like the detector's, rebuilt many times.
        let mut rng = SplitMix64::new(11);
        let mut g = Graph::new();
        for t in 0..300 {
            let (w, h) = (rng.range_usize(1, 9), rng.range_usize(1, 9));
            let n = w * h;
            let tw = (0..n)
                .map(|_| (rng.range_f64(-2.0, 2.0), rng.range_f64(-2.0, 2.0)))
                .collect();
            let mut edges = Vec::new();
            let pw = rng.next_f64();
            for y in 0..h {
                for x in 0..w {
                    if x + 1 < w {
                        edges.push((y * w + x, y * w + x + 1, pw, pw));
                    }
                    if y + 1 < h {
                        edges.push((y * w + x, (y + 1) * w + x, pw, pw));
                    }
                }
            }
            let inst = Instance { n, tw, edges };
            build(&mut g, &inst);
            let flow = g.maxflow();
            let (cap, constant) = dense(&inst);
            let ek = edmonds_karp(&cap) + constant;
            assert!((flow - ek).abs() <= 1e-9 * (1.0 + ek.abs()), "case {t}");
        }
    }

    #[test]
    fn empty_graph_has_zero_flow() {
        let mut g = Graph::new();
        assert_eq!(g.maxflow(), 0.0);
        g.add_nodes(1);
        g.add_tweights(0, 2.0, 5.0);
        assert_eq!(g.maxflow(), 2.0);
        assert!(!g.is_source_side(0));
    }
}
