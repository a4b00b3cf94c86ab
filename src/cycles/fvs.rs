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

/// Nodes meeting every cycle of the multigraph `(nodes, ends)` (no self-loops), ascending.
pub(crate) fn feedback_vertex_set(nodes: usize, ends: &[(u32, u32)]) -> Vec<u32> {
    let mut edges: Vec<(u32, u32)> = ends.to_vec();
    let mut alive = vec![true; edges.len()];
    let mut inc: Vec<Vec<u32>> = vec![Vec::new(); nodes];
    for (e, &(a, b)) in ends.iter().enumerate() {
        inc[a as usize].push(e as u32);
        inc[b as usize].push(e as u32);
    }
    let mut deg: Vec<u32> = inc.iter().map(|l| l.len() as u32).collect();
    let mut removed = vec![false; nodes];
    let mut heap: BinaryHeap<(u32, Reverse<u32>)> =
        (0..nodes).map(|v| (deg[v], Reverse(v as u32))).collect();
    let mut small: Vec<u32> = (0..nodes as u32)
        .rev()
        .filter(|&v| deg[v as usize] <= 2)
        .collect();
    let mut fvs = Vec::new();

    // Delete node v with its edges (rule 1, or v taken into the set).
    let remove = |v: usize,
                  edges: &[(u32, u32)],
                  alive: &mut [bool],
                  inc: &[Vec<u32>],
                  deg: &mut [u32],
                  removed: &mut [bool],
                  small: &mut Vec<u32>,
                  heap: &mut BinaryHeap<(u32, Reverse<u32>)>| {
        removed[v] = true;
        for &e in &inc[v] {
            if !alive[e as usize] {
                continue;
            }
            alive[e as usize] = false;
            let (a, b) = edges[e as usize];
            let u = if a as usize == v { b } else { a } as usize;
            deg[u] -= 1;
            if !removed[u] {
                if deg[u] <= 2 {
                    small.push(u as u32);
                }
                heap.push((deg[u], Reverse(u as u32)));
            }
        }
        deg[v] = 0;
    };

    loop {
        while let Some(v) = small.pop() {
            let v = v as usize;
            if removed[v] {
                continue;
            }
            if deg[v] <= 1 {
                remove(
                    v,
                    &edges,
                    &mut alive,
                    &inc,
                    &mut deg,
                    &mut removed,
                    &mut small,
                    &mut heap,
                );
                continue;
            }
            if deg[v] != 2 {
                continue;
            }
            let two: Vec<u32> = inc[v]
                .iter()
                .copied()
                .filter(|&e| alive[e as usize])
                .collect();
            let other = |e: u32| {
                let (a, b) = edges[e as usize];
                if a as usize == v { b } else { a }
            };
            let (a, b) = (other(two[0]), other(two[1]));
            if a == b {
                fvs.push(a);
                remove(
                    a as usize,
                    &edges,
                    &mut alive,
                    &inc,
                    &mut deg,
                    &mut removed,
                    &mut small,
                    &mut heap,
                );
            } else {
                alive[two[0] as usize] = false;
                alive[two[1] as usize] = false;
                removed[v] = true;
                deg[v] = 0;
                let id = edges.len() as u32;
                edges.push((a, b));
                alive.push(true);
                inc[a as usize].push(id);
                inc[b as usize].push(id);
            }
        }
        // The largest remaining degree (stale heap entries are skipped).
        let mut pick = None;
        while let Some((d, Reverse(v))) = heap.pop() {
            if !removed[v as usize] && deg[v as usize] == d {
                pick = Some(v);
                break;
            }
        }
        let Some(v) = pick else { break };
        fvs.push(v);
        remove(
            v as usize,
            &edges,
            &mut alive,
            &inc,
            &mut deg,
            &mut removed,
            &mut small,
            &mut heap,
        );
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
