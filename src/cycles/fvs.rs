//! A feedback vertex set (a set of nodes meeting every cycle) of a multigraph, for the roots
//! of the Horton candidates of the exact MCB ([`super::mcb`]).
//!
//! Greedy with the classic reduction rules, applied until none applies, then the node of
//! largest remaining degree is taken (ties: smallest index), and so on:
//! - a node of degree ≤ 1 lies on no cycle: delete it;
//! - a node of degree 2 with two different neighbours `a`, `b`: every cycle through it passes
//!   through `a` and `b`; bypass it by an edge `a–b`;
//! - a node of degree 2 whose two edges go to the same neighbour `a` (a 2-cycle): take `a`.
//!
//! The set is not minimum (that is NP-hard) but small on pose graphs; any feedback vertex set
//! makes the MCB exact, its size only sets the number of shortest-path trees. `O(m log m)`.

use std::cmp::Reverse;
use std::collections::BinaryHeap;

/// The shrinking multigraph of the reduction rules.
struct Residual {
    edges: Vec<(u32, u32)>,
    alive: Vec<bool>,
    inc: Vec<Vec<u32>>,
    deg: Vec<u32>,
    removed: Vec<bool>,
    /// Nodes whose degree dropped to ≤ 2 (to look at again).
    small: Vec<u32>,
    /// (degree, node) of every node, with stale entries skipped on pop.
    heap: BinaryHeap<(u32, Reverse<u32>)>,
}

impl Residual {
    fn new(nodes: usize, ends: &[(u32, u32)]) -> Self {
        let mut inc: Vec<Vec<u32>> = vec![Vec::new(); nodes];
        for (e, &(a, b)) in ends.iter().enumerate() {
            inc[a as usize].push(e as u32);
            inc[b as usize].push(e as u32);
        }
        let deg: Vec<u32> = inc.iter().map(|l| l.len() as u32).collect();
        let heap = (0..nodes).map(|v| (deg[v], Reverse(v as u32))).collect();
        let small = (0..nodes as u32)
            .rev()
            .filter(|&v| deg[v as usize] <= 2)
            .collect();
        Self {
            edges: ends.to_vec(),
            alive: vec![true; ends.len()],
            inc,
            deg,
            removed: vec![false; nodes],
            small,
            heap,
        }
    }

    /// The other end of edge `e` at node `v`.
    fn other(&self, e: u32, v: usize) -> u32 {
        let (a, b) = self.edges[e as usize];
        if a as usize == v { b } else { a }
    }

    /// Delete node v with its edges (rule 1, or v taken into the set).
    fn remove(&mut self, v: usize) {
        self.removed[v] = true;
        for i in 0..self.inc[v].len() {
            let e = self.inc[v][i];
            if !self.alive[e as usize] {
                continue;
            }
            self.alive[e as usize] = false;
            let u = self.other(e, v) as usize;
            self.deg[u] -= 1;
            if !self.removed[u] {
                if self.deg[u] <= 2 {
                    self.small.push(u as u32);
                }
                self.heap.push((self.deg[u], Reverse(u as u32)));
            }
        }
        self.deg[v] = 0;
    }

    /// Rule 3 for a degree-2 node v: bypass it by an edge `a–b`, or take `a` when both edges
    /// go to `a`; returns the node taken.
    fn bypass(&mut self, v: usize) -> Option<u32> {
        let two: Vec<u32> = self.inc[v]
            .iter()
            .copied()
            .filter(|&e| self.alive[e as usize])
            .collect();
        let (a, b) = (self.other(two[0], v), self.other(two[1], v));
        if a == b {
            self.remove(a as usize);
            return Some(a);
        }
        self.alive[two[0] as usize] = false;
        self.alive[two[1] as usize] = false;
        self.removed[v] = true;
        self.deg[v] = 0;
        let id = self.edges.len() as u32;
        self.edges.push((a, b));
        self.alive.push(true);
        self.inc[a as usize].push(id);
        self.inc[b as usize].push(id);
        None
    }

    /// The node of largest remaining degree (ties: smallest index).
    fn largest(&mut self) -> Option<u32> {
        while let Some((d, Reverse(v))) = self.heap.pop() {
            if !self.removed[v as usize] && self.deg[v as usize] == d {
                return Some(v);
            }
        }
        None
    }
}

/// Nodes meeting every cycle of the multigraph `(nodes, ends)` (no self-loops), ascending.
pub(crate) fn feedback_vertex_set(nodes: usize, ends: &[(u32, u32)]) -> Vec<u32> {
    let mut g = Residual::new(nodes, ends);
    let mut fvs = Vec::new();
    loop {
        while let Some(v) = g.small.pop() {
            let v = v as usize;
            if g.removed[v] {
                continue;
            }
            match g.deg[v] {
                0 | 1 => g.remove(v),
                2 => fvs.extend(g.bypass(v)),
                _ => {}
            }
        }
        let Some(v) = g.largest() else { break };
        fvs.push(v);
        g.remove(v as usize);
    }
    fvs.sort_unstable();
    fvs
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::UnionFind;

    fn is_fvs(nodes: usize, ends: &[(u32, u32)], fvs: &[u32]) -> bool {
        let mut uf = UnionFind::new(nodes);
        ends.iter()
            .filter(|(a, b)| !fvs.contains(a) && !fvs.contains(b))
            .all(|&(a, b)| uf.union(a as usize, b as usize))
    }

    #[test]
    fn hits_every_cycle() {
        // K4 plus a parallel edge and a pendant path.
        let ends = [
            (0, 1),
            (0, 2),
            (0, 3),
            (1, 2),
            (1, 3),
            (2, 3),
            (2, 3),
            (3, 4),
            (4, 5),
        ];
        let f = feedback_vertex_set(6, &ends);
        assert!(is_fvs(6, &ends, &f), "{f:?}");
        assert!(f.len() <= 2, "{f:?}");
        // A single cycle needs one node; a 2-cycle too.
        assert_eq!(feedback_vertex_set(3, &[(0, 1), (1, 2), (2, 0)]).len(), 1);
        assert_eq!(feedback_vertex_set(2, &[(0, 1), (1, 0)]).len(), 1);
        // 5×5 grid.
        let mut g = Vec::new();
        for r in 0..5u32 {
            for c in 0..5u32 {
                let v = 5 * r + c;
                if c < 4 {
                    g.push((v, v + 1));
                }
                if r < 4 {
                    g.push((v, v + 5));
                }
            }
        }
        let f = feedback_vertex_set(25, &g);
        assert!(is_fvs(25, &g, &f));
    }
}
