//! Boykov-Kolmogorov max-flow ([`super::maxflow`]) specialised to the
//! 4-connected pixel grids of the mask refinement: a node's four arcs are
//! implicit (right, down, left, up), stored beside its terminal capacity,
//! so the search walks neighbours by index arithmetic instead of arc lists
//! and a node's state fits one cache line. The cut is the same as the
//! general graph's: the nodes reachable from the source in the residual
//! graph, which every maximum flow leaves the same.

use std::collections::VecDeque;

use super::maxflow::add_terminal_caps;

/// Directions of a node's arcs; the sister of arc `(i, d)` is
/// `(neighbour(i, d), opposite(d))`.
const RIGHT: u8 = 0;
const DOWN: u8 = 1;
const LEFT: u8 = 2;
const UP: u8 = 3;
/// Parent codes beyond the four directions.
const TERMINAL: u8 = 4;
const ORPHAN: u8 = 5;
const NONE: u8 = 6;
const INFINITE_D: u32 = u32::MAX;

#[inline]
fn opposite(d: u8) -> u8 {
    (d + 2) & 3
}

#[derive(Clone, Copy, Debug)]
struct Node {
    /// Residual terminal capacity: > 0 from the source, < 0 to the sink.
    tr_cap: f64,
    /// Residual capacity of the arc toward each neighbour (by direction).
    cap: [f64; 4],
    ts: u32,
    dist: u32,
    /// The direction of the arc to the parent, or a code above 3.
    parent: u8,
    is_sink: bool,
    active: bool,
    /// Bit `d` set where the neighbour in direction `d` exists.
    dirs: u8,
}

/// A reusable s-t graph over a `w x h` grid of nodes (index `y * w + x`),
/// each joined to its 4 neighbours.
#[derive(Debug, Default)]
pub struct GridGraph {
    w: usize,
    nodes: Vec<Node>,
    flow: f64,
    active: VecDeque<u32>,
    orphans: VecDeque<u32>,
    time: u32,
}

impl GridGraph {
    pub fn new() -> Self {
        Self::default()
    }

    /// A `w x h` grid with every capacity zero, keeping the allocations.
    pub fn reset(&mut self, w: usize, h: usize) {
        self.w = w;
        self.nodes.clear();
        self.nodes.reserve(w * h);
        for y in 0..h {
            for x in 0..w {
                let dirs = u8::from(x + 1 < w) << RIGHT
                    | u8::from(y + 1 < h) << DOWN
                    | u8::from(x > 0) << LEFT
                    | u8::from(y > 0) << UP;
                self.nodes.push(Node {
                    tr_cap: 0.0,
                    cap: [0.0; 4],
                    ts: 0,
                    dist: 0,
                    parent: NONE,
                    is_sink: false,
                    active: false,
                    dirs,
                });
            }
        }
        self.active.clear();
        self.orphans.clear();
        self.flow = 0.0;
        self.time = 0;
    }

    /// Adds terminal capacities, as [`super::maxflow::Graph::add_tweights`]:
    /// `cap_source` is paid when `i` ends on the sink side, `cap_sink` when
    /// it ends on the source side.
    pub fn add_tweights(&mut self, i: usize, cap_source: f64, cap_sink: f64) {
        self.flow += add_terminal_caps(&mut self.nodes[i].tr_cap, cap_source, cap_sink);
    }

    /// Adds capacity `cap` to the arc from `i` to its right neighbour and
    /// `rev_cap` to the reverse arc (both clamped at zero); nothing where
    /// `i` is on the grid's right edge.
    pub fn add_right(&mut self, i: usize, cap: f64, rev_cap: f64) {
        self.add_pair(i, RIGHT, cap, rev_cap);
    }

    /// As [`GridGraph::add_right`], to the neighbour below.
    pub fn add_down(&mut self, i: usize, cap: f64, rev_cap: f64) {
        self.add_pair(i, DOWN, cap, rev_cap);
    }

    fn add_pair(&mut self, i: usize, d: u8, cap: f64, rev_cap: f64) {
        if self.nodes[i].dirs >> d & 1 == 0 {
            return;
        }
        let j = self.neighbour(i as u32, d) as usize;
        self.nodes[i].cap[d as usize] += cap.max(0.0);
        self.nodes[j].cap[opposite(d) as usize] += rev_cap.max(0.0);
    }

    #[inline]
    fn neighbour(&self, i: u32, d: u8) -> u32 {
        match d {
            RIGHT => i + 1,
            DOWN => i + self.w as u32,
            LEFT => i - 1,
            _ => i - self.w as u32,
        }
    }

    /// True when node `i` is on the source side of the minimum cut found by
    /// the last [`GridGraph::maxflow`] (the nodes reachable from the source).
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

    /// Pushes flow along every path `source -> i -> j -> sink` of one arc
    /// (as [`super::maxflow::Graph`] does before its search).
    fn push_short_paths(&mut self) {
        for i in 0..self.nodes.len() {
            for d in 0..4u8 {
                let ni = self.nodes[i];
                if ni.tr_cap <= 0.0 {
                    break;
                }
                if ni.dirs >> d & 1 == 0 || ni.cap[d as usize] <= 0.0 {
                    continue;
                }
                let j = self.neighbour(i as u32, d) as usize;
                let need = -self.nodes[j].tr_cap;
                if need > 0.0 {
                    let f = ni.tr_cap.min(ni.cap[d as usize]).min(need);
                    self.nodes[i].cap[d as usize] -= f;
                    self.nodes[j].cap[opposite(d) as usize] += f;
                    self.nodes[i].tr_cap -= f;
                    self.nodes[j].tr_cap += f;
                    self.flow += f;
                }
            }
        }
    }

    /// Computes the maximum flow (including the constant collected by
    /// [`GridGraph::add_tweights`]).
    pub fn maxflow(&mut self) -> f64 {
        self.push_short_paths();
        self.active.clear();
        self.orphans.clear();
        self.time = 0;
        for i in 0..self.nodes.len() {
            let n = &mut self.nodes[i];
            n.active = false;
            n.ts = 0;
            if n.tr_cap == 0.0 {
                n.parent = NONE;
                continue;
            }
            n.is_sink = n.tr_cap < 0.0;
            n.parent = TERMINAL;
            n.dist = 1;
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
            if let Some((m, d)) = meet {
                // Keep growing from `i` next round.
                self.nodes[i as usize].active = true;
                current = Some(i);
                self.augment(m, d);
                while let Some(o) = self.orphans.pop_front() {
                    self.process_orphan(o);
                }
            }
        }
        self.flow
    }

    /// Grows the tree of `i`; returns the arc `(node, direction)` from the
    /// source tree to the sink tree where the trees meet, if they do.
    fn grow(&mut self, i: u32) -> Option<(u32, u8)> {
        let ni = self.nodes[i as usize];
        for d in 0..4u8 {
            if ni.dirs >> d & 1 == 0 {
                continue;
            }
            let j = self.neighbour(i, d);
            let nj = self.nodes[j as usize];
            let cap = if ni.is_sink {
                nj.cap[opposite(d) as usize]
            } else {
                ni.cap[d as usize]
            };
            if cap <= 0.0 {
                continue;
            }
            if nj.parent == NONE {
                let n = &mut self.nodes[j as usize];
                n.is_sink = ni.is_sink;
                n.parent = opposite(d);
                n.ts = ni.ts;
                n.dist = ni.dist + 1;
                self.activate(j);
            } else if nj.is_sink != ni.is_sink {
                return Some(if ni.is_sink { (j, opposite(d)) } else { (i, d) });
            } else if nj.ts <= ni.ts && nj.dist > ni.dist {
                let n = &mut self.nodes[j as usize];
                n.parent = opposite(d);
                n.ts = ni.ts;
                n.dist = ni.dist + 1;
            }
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

    /// Pushes the bottleneck along the path through the middle arc `(m, dm)`.
    fn augment(&mut self, m: u32, dm: u8) {
        let head = self.neighbour(m, dm);
        let mut bottleneck = self.nodes[m as usize].cap[dm as usize];
        // Source tree: from the middle arc's tail up to the source.
        let mut i = m;
        loop {
            let d = self.nodes[i as usize].parent;
            if d == TERMINAL {
                break;
            }
            let p = self.neighbour(i, d);
            bottleneck = bottleneck.min(self.nodes[p as usize].cap[opposite(d) as usize]);
            i = p;
        }
        bottleneck = bottleneck.min(self.nodes[i as usize].tr_cap);
        // Sink tree.
        let mut i = head;
        loop {
            let d = self.nodes[i as usize].parent;
            if d == TERMINAL {
                break;
            }
            bottleneck = bottleneck.min(self.nodes[i as usize].cap[d as usize]);
            i = self.neighbour(i, d);
        }
        bottleneck = bottleneck.min(-self.nodes[i as usize].tr_cap);

        self.nodes[head as usize].cap[opposite(dm) as usize] += bottleneck;
        self.nodes[m as usize].cap[dm as usize] -= bottleneck;
        let mut i = m;
        loop {
            let d = self.nodes[i as usize].parent;
            if d == TERMINAL {
                break;
            }
            let p = self.neighbour(i, d);
            self.nodes[i as usize].cap[d as usize] += bottleneck;
            let back = &mut self.nodes[p as usize].cap[opposite(d) as usize];
            *back -= bottleneck;
            if *back <= 0.0 {
                self.set_orphan_front(i);
            }
            i = p;
        }
        self.nodes[i as usize].tr_cap -= bottleneck;
        if self.nodes[i as usize].tr_cap <= 0.0 {
            self.set_orphan_front(i);
        }
        let mut i = head;
        loop {
            let d = self.nodes[i as usize].parent;
            if d == TERMINAL {
                break;
            }
            let p = self.neighbour(i, d);
            self.nodes[p as usize].cap[opposite(d) as usize] += bottleneck;
            let fwd = &mut self.nodes[i as usize].cap[d as usize];
            *fwd -= bottleneck;
            if *fwd <= 0.0 {
                self.set_orphan_front(i);
            }
            i = p;
        }
        self.nodes[i as usize].tr_cap += bottleneck;
        if self.nodes[i as usize].tr_cap >= 0.0 {
            self.set_orphan_front(i);
        }
        self.flow += bottleneck;
    }

    /// Distance from `start` to its tree's terminal, or `INFINITE_D` when it
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
            j = self.neighbour(j, nj.parent);
        }
        let mut j = start;
        let mut dd = d;
        while self.nodes[j as usize].ts != time {
            let n = &mut self.nodes[j as usize];
            n.ts = time;
            n.dist = dd;
            dd -= 1;
            let p = n.parent;
            j = self.neighbour(j, p);
        }
        d
    }

    /// The capacity along which `i` could receive (source tree) or send
    /// (sink tree) flow through its neighbour `j` in direction `d`.
    #[inline]
    fn tree_cap(&self, i: u32, j: u32, d: u8, sink: bool) -> f64 {
        if sink {
            self.nodes[i as usize].cap[d as usize]
        } else {
            self.nodes[j as usize].cap[opposite(d) as usize]
        }
    }

    fn process_orphan(&mut self, i: u32) {
        let ni = self.nodes[i as usize];
        let sink = ni.is_sink;
        let mut best = NONE;
        let mut d_min = INFINITE_D;
        for d in 0..4u8 {
            if ni.dirs >> d & 1 == 0 {
                continue;
            }
            let j = self.neighbour(i, d);
            if self.tree_cap(i, j, d, sink) <= 0.0 {
                continue;
            }
            let nj = self.nodes[j as usize];
            if nj.is_sink == sink && nj.parent != NONE {
                let dist = self.origin_distance(j);
                if dist < d_min {
                    best = d;
                    d_min = dist;
                }
            }
        }
        if best != NONE {
            let time = self.time;
            let n = &mut self.nodes[i as usize];
            n.parent = best;
            n.ts = time;
            n.dist = d_min + 1;
            return;
        }
        // No parent: `i` becomes free; its children become orphans and its
        // tree neighbours that could reach it become active.
        self.nodes[i as usize].parent = NONE;
        for d in 0..4u8 {
            if ni.dirs >> d & 1 == 0 {
                continue;
            }
            let j = self.neighbour(i, d);
            let nj = self.nodes[j as usize];
            if nj.is_sink != sink || nj.parent == NONE {
                continue;
            }
            if self.tree_cap(i, j, d, sink) > 0.0 {
                self.activate(j);
            }
            if nj.parent < TERMINAL && self.neighbour(j, nj.parent) == i {
                self.set_orphan_rear(j);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::maxflow::Graph;
    use crate::vision::rng::SplitMix64;

    /// Draws a capacity: zeros, quarter integers (exact in floating point,
    /// so both graphs' cuts must agree node by node) or arbitrary values.
    fn draw(rng: &mut SplitMix64, exact: bool) -> f64 {
        match rng.range_usize(0, 5) {
            0 => 0.0,
            _ if exact => rng.range_usize(0, 24) as f64 * 0.25,
            _ => rng.next_f64() * 6.0,
        }
    }

    /// The same grid in both graphs; returns their flows and cuts.
    fn both(rng: &mut SplitMix64, w: usize, h: usize, exact: bool) -> [(f64, Vec<bool>); 2] {
        let mut g = Graph::new();
        let mut q = GridGraph::new();
        g.add_nodes(w * h);
        q.reset(w, h);
        for i in 0..w * h {
            let (s, t) = (draw(rng, exact) - 1.0, draw(rng, exact));
            g.add_tweights(i, s, t);
            q.add_tweights(i, s, t);
            let (x, y) = (i % w, i / w);
            if x + 1 < w {
                let (c, r) = (draw(rng, exact), draw(rng, exact));
                g.add_edge(i, i + 1, c, r);
                q.add_right(i, c, r);
            }
            if y + 1 < h {
                let (c, r) = (draw(rng, exact), draw(rng, exact));
                g.add_edge(i, i + w, c, r);
                q.add_down(i, c, r);
            }
        }
        let fg = g.maxflow();
        let fq = q.maxflow();
        [
            (fg, (0..w * h).map(|i| g.is_source_side(i)).collect()),
            (fq, (0..w * h).map(|i| q.is_source_side(i)).collect()),
        ]
    }

    #[test]
    fn the_grid_cut_is_the_general_graphs_node_by_node() {
        let mut rng = SplitMix64::new(3);
        for t in 0..600 {
            let (w, h) = (rng.range_usize(1, 30), rng.range_usize(1, 30));
            let [(fg, sg), (fq, sq)] = both(&mut rng, w, h, true);
            assert_eq!(fg, fq, "case {t}: {w}x{h}");
            assert_eq!(sg, sq, "case {t}: {w}x{h}");
        }
    }

    #[test]
    fn the_grid_flow_is_the_general_graphs_on_arbitrary_capacities() {
        let mut rng = SplitMix64::new(8);
        for t in 0..300 {
            let (w, h) = (rng.range_usize(1, 40), rng.range_usize(1, 40));
            let [(fg, _), (fq, _)] = both(&mut rng, w, h, false);
            assert!(
                (fg - fq).abs() <= 1e-9 * (1.0 + fg.abs()),
                "case {t}: {fg} vs {fq}"
            );
        }
    }

    #[test]
    fn arcs_off_the_grid_are_ignored_and_memory_is_reused() {
        let mut q = GridGraph::new();
        q.reset(2, 1);
        q.add_right(1, 5.0, 5.0);
        q.add_down(0, 5.0, 5.0);
        q.add_tweights(0, 3.0, 0.0);
        q.add_tweights(1, 0.0, 2.0);
        // Without an arc between them each node takes its own side.
        assert_eq!(q.maxflow(), 0.0);
        assert!(q.is_source_side(0) && !q.is_source_side(1));
        q.reset(2, 1);
        q.add_right(0, 5.0, 5.0);
        q.add_tweights(0, 3.0, 0.0);
        q.add_tweights(1, 0.0, 2.0);
        assert_eq!(q.maxflow(), 2.0);
        // The arc carries node 0's flow to node 1: both on the source side.
        assert!(q.is_source_side(0) && q.is_source_side(1));
        q.reset(0, 0);
        assert_eq!(q.maxflow(), 0.0);
    }
}
