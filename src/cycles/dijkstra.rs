//! Dijkstra's shortest paths on an undirected multigraph given as adjacency lists of
//! `(neighbour, edge id)`, with positive edge weights — the one implementation used by the
//! incremental basis (a path between the ends of a new chord), the exact MCB (shortest-path
//! trees from the roots, bounded by a radius) and the spanner of the approximate MCB
//! (a bounded point-to-point query).
//!
//! Written here rather than taken from petgraph because callers need: a graph that grows
//! between calls (the online basis), early stops (target settled, radius exceeded), work
//! arrays reused across calls (a generation stamp instead of clearing: a call costs only what
//! it explores), the settle order (for labels along the tree) and edge ids of the predecessor
//! (parallel edges are distinct edges).
//!
//! Ties: the queue pops the smallest distance first and, among equal distances, the earliest
//! pushed; node indices never break ties, so the result depends only on the adjacency order.
//! Cost of a call: `O(E_v log E_v)` for the `E_v` edges incident to the settled nodes.

use std::cmp::Ordering;
use std::collections::BinaryHeap;

use smallvec::SmallVec;

use super::SignedEdge;

/// Adjacency lists: for each node, `(neighbour, edge id)`.
pub(crate) type Adjacency = Vec<Vec<(u32, u32)>>;

/// Queue entry `(distance, push sequence, node)`, ordered so that `BinaryHeap` pops the
/// smallest distance first and, among equal distances, the earliest pushed.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Entry(f64, u64, u32);
impl Eq for Entry {}
impl Ord for Entry {
    fn cmp(&self, other: &Self) -> Ordering {
        other.0.total_cmp(&self.0).then(other.1.cmp(&self.1))
    }
}
impl PartialOrd for Entry {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

/// Reusable Dijkstra work arrays. After [`run`](Self::run), `dist`/`pred` are valid for the
/// nodes reported by [`settled`](Self::settled), in [`order`](Self::order).
#[derive(Clone, Debug, Default)]
pub(crate) struct Dijkstra {
    dist: Vec<f64>,
    pred: Vec<(u32, u32)>,
    stamp: Vec<u32>,
    done: Vec<u32>,
    generation: u32,
    heap: BinaryHeap<Entry>,
    order: Vec<u32>,
}

impl Dijkstra {
    /// Work arrays for `n` nodes (grown on demand by [`run`](Self::run)).
    pub(crate) fn new(n: usize) -> Self {
        let mut d = Self::default();
        d.grow(n);
        d
    }

    fn grow(&mut self, n: usize) {
        if self.dist.len() < n {
            self.dist.resize(n, 0.0);
            self.pred.resize(n, (0, 0));
            self.stamp.resize(n, 0);
            self.done.resize(n, 0);
        }
    }

    /// Shortest paths from `src` over `adj` with edge weights `w`. Stops when `target` is
    /// settled, or before settling a node farther than `radius` (settled nodes all have
    /// `dist ≤ radius`). Returns whether `target` was settled.
    pub(crate) fn run(
        &mut self,
        adj: &[Vec<(u32, u32)>],
        w: &[f64],
        src: usize,
        target: Option<usize>,
        radius: f64,
    ) -> bool {
        self.grow(adj.len());
        self.generation = self.generation.wrapping_add(1);
        if self.generation == 0 {
            self.stamp.iter_mut().for_each(|s| *s = 0);
            self.done.iter_mut().for_each(|s| *s = 0);
            self.generation = 1;
        }
        let g = self.generation;
        self.heap.clear();
        self.order.clear();
        self.stamp[src] = g;
        self.dist[src] = 0.0;
        let mut seq = 0u64;
        self.heap.push(Entry(0.0, seq, src as u32));
        while let Some(Entry(d, _, v)) = self.heap.pop() {
            let v = v as usize;
            if self.done[v] == g {
                continue;
            }
            if d > radius {
                break;
            }
            self.done[v] = g;
            self.order.push(v as u32);
            if target == Some(v) {
                return true;
            }
            for &(x, e) in &adj[v] {
                let x = x as usize;
                let nd = d + w[e as usize];
                if self.stamp[x] != g || nd < self.dist[x] {
                    self.stamp[x] = g;
                    self.dist[x] = nd;
                    self.pred[x] = (v as u32, e);
                    seq += 1;
                    self.heap.push(Entry(nd, seq, x as u32));
                }
            }
        }
        false
    }

    /// Whether `v` was settled by the last run.
    pub(crate) fn settled(&self, v: usize) -> bool {
        self.done.get(v) == Some(&self.generation)
    }

    /// Distance of a settled node.
    pub(crate) fn dist(&self, v: usize) -> f64 {
        self.dist[v]
    }

    /// `(parent node, edge to it)` of a settled node other than the source.
    pub(crate) fn pred(&self, v: usize) -> (u32, u32) {
        self.pred[v]
    }

    /// Nodes settled by the last run, in settle order (the source first).
    pub(crate) fn order(&self) -> &[u32] {
        &self.order
    }

    /// Append the tree path `src → … → dst` of the last run (source `src`, `dst` settled) as
    /// signed edges in traversal order; `ends` orients the edges.
    pub(crate) fn path(
        &self,
        ends: &[(u32, u32)],
        src: usize,
        dst: usize,
        out: &mut SmallVec<[SignedEdge; 8]>,
    ) {
        let start = out.len();
        let mut v = dst;
        while v != src {
            let (u, e) = self.pred[v];
            // Traversing u → v: along the edge if it is stored as (u, v).
            out.push(SignedEdge::new(e as usize, ends[e as usize].0 == u));
            v = u as usize;
        }
        out[start..].reverse();
    }
}
