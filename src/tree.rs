//! Spanning trees and forests (method [§5](crate::method#5-wraps-and-orientations)–[§6](crate::method#6-which-cycle-basis)).
//!
//! A spanning tree `T` splits the edges into `n − c` tree edges and `ℓ = m − n + c` chords;
//! each chord closes one fundamental cycle (the chord plus the tree path between its ends).
//! Two trees of the paper are built here:
//!
//! - `T_o`, the **odometric tree**: the edges `(i, i+1)` (consecutive ids, either direction)
//!   where present, taken first in file order; nodes they miss are attached by the earliest edge
//!   (file order) that reaches them (ais2klinik lacks `7289→7290`).
//! - `T_m`, the **minimum spanning tree** w.r.t. the weights `w_e = σ_e²` (Kruskal; ties broken
//!   by edge index, so the result is deterministic).
//!
//! Disconnected graphs give forests: one root (anchor, θ = 0) per component, the component's
//! first node in index order.

use crate::graph::{PoseGraph, UnionFind};

/// Steps `(node, edge to its parent)` up a tree.
pub type TreePath = Vec<(usize, usize)>;

/// A spanning forest with parent pointers and depths.
#[derive(Clone, Debug, PartialEq)]
pub struct SpanningTree {
    /// `(parent node, edge to parent)` per node; `None` for roots.
    pub parent: Vec<Option<(usize, usize)>>,
    /// Depth of each node below its root.
    pub depth: Vec<u32>,
    /// The root (anchor) of every component, in increasing node index.
    pub roots: Vec<usize>,
    /// Whether each edge is a tree edge.
    pub in_tree: Vec<bool>,
}

impl SpanningTree {
    /// Kruskal over edges in the given preference order: an edge joining two components
    /// becomes a tree edge.
    pub fn from_preference(graph: &PoseGraph, order: impl IntoIterator<Item = usize>) -> Self {
        let n = graph.node_count();
        let ends = graph.endpoints();
        let mut uf = UnionFind::new(n);
        let mut in_tree = vec![false; ends.len()];
        for e in order {
            let (a, b) = ends[e];
            if uf.union(a, b) {
                in_tree[e] = true;
            }
        }
        Self::from_tree_edges(graph, in_tree)
    }

    /// Build parents and depths from a set of tree edges (must be a forest spanning each
    /// component, as produced by [`from_preference`](Self::from_preference)).
    fn from_tree_edges(graph: &PoseGraph, in_tree: Vec<bool>) -> Self {
        let n = graph.node_count();
        let ends = graph.endpoints();
        let mut adj: Vec<Vec<(usize, usize)>> = vec![Vec::new(); n];
        for (e, &(a, b)) in ends.iter().enumerate() {
            if in_tree[e] {
                adj[a].push((b, e));
                adj[b].push((a, e));
            }
        }
        let mut parent = vec![None; n];
        let mut depth = vec![0u32; n];
        let mut seen = vec![false; n];
        let mut roots = Vec::new();
        let mut queue = std::collections::VecDeque::new();
        for r in 0..n {
            if seen[r] {
                continue;
            }
            roots.push(r);
            seen[r] = true;
            queue.push_back(r);
            while let Some(v) = queue.pop_front() {
                for &(w, e) in &adj[v] {
                    if !seen[w] {
                        seen[w] = true;
                        parent[w] = Some((v, e));
                        depth[w] = depth[v] + 1;
                        queue.push_back(w);
                    }
                }
            }
        }
        Self {
            parent,
            depth,
            roots,
            in_tree,
        }
    }

    /// The odometric tree `T_o`.
    pub fn odometric(graph: &PoseGraph) -> Self {
        let edges = graph.edges();
        let odo = (0..edges.len()).filter(|&e| edges[e].is_odometric());
        let rest = (0..edges.len()).filter(|&e| !edges[e].is_odometric());
        Self::from_preference(graph, odo.chain(rest))
    }

    /// The minimum spanning tree `T_m` for weights σ². Weights within about 1e-9 of each other
    /// (relative) count as equal and go by edge index: σ² is computed from the information
    /// matrix, and the same noise written the other way (`Edge::reversed`, then read back
    /// through `Edge::new`) may give σ² one rounding apart — which, among equal odometry
    /// weights, picked another tree, another basis, and on ambiguous data another estimate.
    pub fn minimum(graph: &PoseGraph) -> Self {
        let edges = graph.edges();
        let mut order: Vec<usize> = (0..edges.len()).collect();
        order.sort_by_cached_key(|&e| (weight_key(edges[e].sigma2()), e));
        Self::from_preference(graph, order)
    }

    /// Chord edge indices (edges not in the tree), in increasing order.
    pub fn chords(&self) -> Vec<usize> {
        (0..self.in_tree.len())
            .filter(|&e| !self.in_tree[e])
            .collect()
    }

    /// Tree path from `a` up to the lowest common ancestor of `a` and `b`, and from `b` up to
    /// it: two lists of `(node, edge to its parent)` steps.
    pub fn paths_to_lca(&self, mut a: usize, mut b: usize) -> (TreePath, TreePath) {
        let (mut up_a, mut up_b) = (Vec::new(), Vec::new());
        // A node deeper than another always has a parent.
        while self.depth[a] > self.depth[b] {
            let Some((p, e)) = self.parent[a] else { break };
            up_a.push((a, e));
            a = p;
        }
        while self.depth[b] > self.depth[a] {
            let Some((p, e)) = self.parent[b] else { break };
            up_b.push((b, e));
            b = p;
        }
        while a != b {
            match (self.parent[a], self.parent[b]) {
                (Some((pa, ea)), Some((pb, eb))) => {
                    up_a.push((a, ea));
                    up_b.push((b, eb));
                    a = pa;
                    b = pb;
                }
                // Different components: no path (callers only ask within a component).
                _ => break,
            }
        }
        (up_a, up_b)
    }
}

/// A weight σ² > 0 on a logarithmic grid of relative step 2⁻³⁰ (about 1e-9): weights one
/// rounding apart share a key (but at a grid boundary, about one pair in 10⁶).
fn weight_key(sigma2: f64) -> i64 {
    (sigma2.log2() * (1u64 << 30) as f64).round() as i64
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::{Edge, NodePolicy, Pose2};

    fn graph(edges: &[(u64, u64, f64)]) -> PoseGraph {
        let mut g = PoseGraph::new();
        for &(a, b, s) in edges {
            let e = Edge::with_sigmas(a, b, Pose2::default(), 1.0, s).unwrap();
            g.add_edge(e, NodePolicy::CreateUnknown).unwrap();
        }
        g
    }

    #[test]
    fn odometric_tree_prefers_consecutive_ids_and_patches_gaps() {
        // 0-1-2 chain, 3-4 chain, gap 2→3 missing; joined by the loop closures 0→3, 1→4.
        let g = graph(&[
            (0, 1, 0.1),
            (1, 2, 0.1),
            (0, 3, 0.1),
            (3, 4, 0.1),
            (1, 4, 0.1),
        ]);
        let t = SpanningTree::odometric(&g);
        assert_eq!(t.in_tree, vec![true, true, true, true, false]);
        assert_eq!(t.roots, vec![0]);
        assert_eq!(t.chords(), vec![4]);
    }

    #[test]
    fn minimum_tree_and_forest() {
        let g = graph(&[(0, 1, 0.3), (1, 2, 0.1), (0, 2, 0.2), (5, 6, 1.0)]);
        let t = SpanningTree::minimum(&g);
        assert_eq!(t.in_tree, vec![false, true, true, true]);
        assert_eq!(t.roots.len(), 2);
        let (a, b) = t.paths_to_lca(1, 0);
        assert_eq!(a.len() + b.len(), 2);
    }
}
