//! Reduction of a weighted multigraph before a minimum cycle basis is computed: split it into
//! biconnected blocks, then contract every chain of degree-2 nodes of a block into one
//! weighted edge; expand cycles back at the end.
//!
//! - Every cycle lies inside one block, and the cycle space is the direct sum of the blocks'
//!   cycle spaces, so an MCB of the graph is the union of MCBs of its blocks (bridges carry no
//!   cycle). Blocks are found with Hopcroft–Tarjan's low-point DFS (iterative, with an edge
//!   stack; parallel edges are told apart by edge id, so only the very edge used to enter a
//!   node is skipped), `O(n + m)`.
//! - In a block, a node of degree 2 lies on a chain between two branch nodes (degree ≥ 3): a
//!   cycle uses either all or none of a chain's edges, so the chain is one edge of weight
//!   `Σ w` (the contracted graph has the same cycle space and cycle weights, with far fewer
//!   nodes: pose graphs are mostly odometry chains). A block without branch nodes is a single
//!   cycle, which is its own MCB. `O(block size)`.
//!
//! Hand-written rather than petgraph's `biconnected_components` because the contraction, the
//! expansion and the edge ids (parallel edges) are needed anyway, and the traversal is short.

use smallvec::SmallVec;

use super::dijkstra::Adjacency;
use super::{Cycle, SignedEdge};

/// One biconnected block with its degree-2 chains contracted.
#[derive(Clone, Debug, Default)]
pub(crate) struct Block {
    /// Number of (branch) nodes.
    pub nodes: usize,
    /// Contracted edges `(a, b)`.
    pub ends: Vec<(u32, u32)>,
    /// Weight of each contracted edge (sum over its chain, in chain order).
    pub w: Vec<f64>,
    /// Adjacency `(neighbour, edge)` of the contracted graph, edges in increasing id.
    pub adj: Adjacency,
    /// Chain of contracted edge `e`: `chain[start[e]..start[e + 1]]`, the original signed edges
    /// walked from `ends[e].0` to `ends[e].1`.
    start: Vec<usize>,
    chain: Vec<SignedEdge>,
}

impl Block {
    /// Cycle rank `m − n + 1` of the block.
    pub(crate) fn rank(&self) -> usize {
        (self.ends.len() + 1).saturating_sub(self.nodes)
    }

    /// Expand a closed walk of contracted signed edges into original signed edges.
    pub(crate) fn expand(&self, terms: &[SignedEdge]) -> Cycle {
        let mut out = SmallVec::new();
        for t in terms {
            let e = t.edge as usize;
            let chain = &self.chain[self.start[e]..self.start[e + 1]];
            if t.sign > 0 {
                out.extend_from_slice(chain);
            } else {
                out.extend(chain.iter().rev().map(|c| SignedEdge {
                    edge: c.edge,
                    sign: -c.sign,
                }));
            }
        }
        Cycle { terms: out }
    }
}

/// The reduced graph: contracted blocks that hold a branch node, and the cycles that need
/// no search (blocks that are single cycles).
#[derive(Clone, Debug, Default)]
pub(crate) struct Reduced {
    /// Blocks to search.
    pub blocks: Vec<Block>,
    /// Blocks that are a single cycle (in every MCB).
    pub cycles: Vec<Cycle>,
}

/// Edge lists (ids) of the biconnected blocks with at least two edges, in DFS order.
pub(crate) fn blocks(nodes: usize, ends: &[(u32, u32)]) -> Vec<Vec<u32>> {
    const NONE: u32 = u32::MAX;
    let mut adj: Adjacency = vec![SmallVec::new(); nodes];
    for (e, &(a, b)) in ends.iter().enumerate() {
        adj[a as usize].push((b, e as u32));
        adj[b as usize].push((a, e as u32));
    }
    let mut disc = vec![0u32; nodes];
    let mut low = vec![0u32; nodes];
    let mut time = 0u32;
    let mut edge_stack: Vec<u32> = Vec::new();
    let mut frames: Vec<(u32, u32, usize)> = Vec::new();
    let mut out = Vec::new();
    for r in 0..nodes {
        if disc[r] != 0 {
            continue;
        }
        time += 1;
        disc[r] = time;
        low[r] = time;
        frames.push((r as u32, NONE, 0));
        while let Some(top) = frames.last_mut() {
            let (v, pe, i) = (top.0 as usize, top.1, top.2);
            if let Some(&(x, e)) = adj[v].get(i) {
                top.2 += 1;
                let x = x as usize;
                if e == pe {
                    continue;
                }
                if disc[x] == 0 {
                    edge_stack.push(e);
                    time += 1;
                    disc[x] = time;
                    low[x] = time;
                    frames.push((x as u32, e, 0));
                } else if disc[x] < disc[v] {
                    edge_stack.push(e);
                    low[v] = low[v].min(disc[x]);
                }
                continue;
            }
            frames.pop();
            if let Some(&(u, _, _)) = frames.last() {
                let u = u as usize;
                low[u] = low[u].min(low[v]);
                if low[v] >= disc[u] {
                    let mut block = Vec::new();
                    while let Some(f) = edge_stack.pop() {
                        block.push(f);
                        if f == pe {
                            break;
                        }
                    }
                    if block.len() > 1 {
                        block.sort_unstable();
                        out.push(block);
                    }
                }
            }
        }
    }
    out
}

/// Split into blocks and contract chains. `w` must be positive.
pub(crate) fn reduce(nodes: usize, ends: &[(u32, u32)], w: &[f64]) -> Reduced {
    const NONE: u32 = u32::MAX;
    let mut out = Reduced::default();
    // Per-block local node numbers, reset after each block.
    let mut local = vec![NONE; nodes];
    // Each edge lies in exactly one block: one flag per edge serves all blocks.
    let mut used = vec![false; ends.len()];
    for block in blocks(nodes, ends) {
        let mut members: Vec<u32> = Vec::new();
        for &e in &block {
            let (a, b) = ends[e as usize];
            for v in [a, b] {
                if local[v as usize] == NONE {
                    local[v as usize] = members.len() as u32;
                    members.push(v);
                }
            }
        }
        let mut adj: Vec<SmallVec<[(u32, u32); 4]>> = vec![SmallVec::new(); members.len()];
        for &e in &block {
            let (a, b) = ends[e as usize];
            let (la, lb) = (local[a as usize], local[b as usize]);
            adj[la as usize].push((lb, e));
            adj[lb as usize].push((la, e));
        }
        let along = |e: u32, from: u32| {
            SignedEdge::new(e as usize, local[ends[e as usize].0 as usize] == from)
        };
        // Walk from local node `from` along edge `e` through degree-2 nodes to a branch node.
        let walk = |from: u32, e: u32, used: &mut Vec<bool>, chain: &mut Vec<SignedEdge>| {
            let (mut cur, mut via) = (from, e);
            loop {
                used[via as usize] = true;
                chain.push(along(via, cur));
                let (a, b) = ends[via as usize];
                let (la, lb) = (local[a as usize], local[b as usize]);
                cur = if la == cur { lb } else { la };
                if adj[cur as usize].len() != 2 || cur == from {
                    return cur;
                }
                let next = adj[cur as usize]
                    .iter()
                    .find(|&&(_, f)| f != via)
                    .map_or(via, |&(_, f)| f);
                if next == via {
                    return cur;
                }
                via = next;
            }
        };
        let branch: Vec<u32> = (0..members.len() as u32)
            .filter(|&v| adj[v as usize].len() != 2)
            .collect();
        if branch.is_empty() {
            let mut chain = Vec::new();
            walk(0, adj[0][0].1, &mut used, &mut chain);
            out.cycles.push(Cycle {
                terms: chain.into_iter().collect(),
            });
        } else {
            let mut cid = vec![NONE; members.len()];
            for (i, &v) in branch.iter().enumerate() {
                cid[v as usize] = i as u32;
            }
            let mut b = Block {
                nodes: branch.len(),
                adj: vec![SmallVec::new(); branch.len()],
                start: vec![0],
                ..Block::default()
            };
            for &v in &branch {
                for &(_, e) in &adj[v as usize] {
                    if used[e as usize] {
                        continue;
                    }
                    let mut chain = Vec::new();
                    let end = walk(v, e, &mut used, &mut chain);
                    let weight: f64 = chain.iter().map(|t| w[t.edge as usize]).sum();
                    if end == v {
                        // A chain back to its start (not possible inside a biconnected block
                        // with a branch node, kept for robustness): a cycle of its own.
                        out.cycles.push(Cycle {
                            terms: chain.into_iter().collect(),
                        });
                        continue;
                    }
                    let (ca, cb) = (cid[v as usize], cid[end as usize]);
                    let id = b.ends.len() as u32;
                    b.ends.push((ca, cb));
                    b.w.push(weight);
                    b.adj[ca as usize].push((cb, id));
                    b.adj[cb as usize].push((ca, id));
                    b.chain.extend(chain);
                    b.start.push(b.chain.len());
                }
            }
            if b.rank() > 0 {
                out.blocks.push(b);
            }
        }
        for v in members {
            local[v as usize] = NONE;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blocks_split_at_cut_vertices_and_keep_parallel_edges() {
        // Triangle 0-1-2, bridge 2-3, a 2-cycle 3=4 (parallel edges), a square 4-5-6-7.
        let ends = [
            (0, 1),
            (1, 2),
            (2, 0),
            (2, 3),
            (3, 4),
            (4, 3),
            (4, 5),
            (5, 6),
            (6, 7),
            (7, 4),
        ];
        let mut b = blocks(8, &ends);
        b.sort();
        assert_eq!(b, vec![vec![0, 1, 2], vec![4, 5], vec![6, 7, 8, 9]]);
        let r = reduce(8, &ends, &[1.0; 10]);
        assert!(r.blocks.is_empty());
        assert_eq!(r.cycles.len(), 3);
    }

    #[test]
    fn chains_contract_and_expand() {
        // Theta graph: branch nodes 0 and 3, chains 0-1-3, 0-2-3 and the edge 0-3.
        let ends = [(0, 1), (1, 3), (2, 0), (2, 3), (0, 3)];
        let w = [1.0, 2.0, 3.0, 4.0, 5.0];
        let r = reduce(4, &ends, &w);
        assert_eq!(r.blocks.len(), 1);
        let b = &r.blocks[0];
        assert_eq!((b.nodes, b.ends.len(), b.rank()), (2, 3, 2));
        let mut ws = b.w.clone();
        ws.sort_by(f64::total_cmp);
        assert_eq!(ws, vec![3.0, 5.0, 7.0]);
        // Contracted edges 0 (0→1→3) and 1 (0→2→3) as a cycle: 0 forward, 1 backward.
        let c = b.expand(&[SignedEdge::new(0, true), SignedEdge::new(1, false)]);
        let ends_usize: Vec<(usize, usize)> = ends
            .iter()
            .map(|&(a, b)| (a as usize, b as usize))
            .collect();
        assert!(c.is_closed(&ends_usize));
        assert_eq!(c.len(), 4);
    }
}
