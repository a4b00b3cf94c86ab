//! The (2k−1)-approximate minimum cycle basis of Kavitha, Mehlhorn and Michail
//! ("New approximation algorithms for minimum cycle bases of graphs", STACS 2007 /
//! Algorithmica 2011); with k = 2 it is the paper's MCB_a (method [§6](crate::method#6-which-cycle-basis)).
//!
//! After the same reduction as the exact MCB (blocks, contracted chains; `reduce`),
//! in each block:
//! 1. a greedy (2k−1)-spanner S (Althöfer et al.): edges by increasing weight (ties by id);
//!    `e = (a, b)` joins S unless S already holds an `a–b` path of weight `≤ (2k−1)·w_e`
//!    (a Dijkstra bounded by that radius, stopped at b);
//! 2. an exact MCB of S ([`super::mcb`], which reduces S again);
//! 3. for every edge `e = (a, b)` not in S, the cycle `e` + the least-weight `b → a` path in S.
//!
//! The cycles of step 3 each own an edge no other cycle uses, so together with an MCB of S
//! they form a basis, and its weight is at most `(2k−1)` times the MCB weight. S has
//! `O(n^{1+1/k})` edges, so the exact part is much smaller than the graph. Cost: one bounded
//! Dijkstra per edge for S, the exact MCB of S, one point-to-point Dijkstra per non-spanner
//! edge.

use std::time::Instant;

use smallvec::SmallVec;

use super::Cycle;
use super::SignedEdge;
use super::dijkstra::{Adjacency, Dijkstra};
use super::mcb::{McbError, check, checked, mcb};
use super::reduce::reduce;

/// The paper's MCB_a: k = 2, a 3-spanner.
pub const DEFAULT_K: u32 = 2;

/// A (2k−1)-approximate minimum cycle basis of the multigraph (same conventions as
/// [`super::mcb::minimum_cycle_basis`]); `k ≥ 1`.
pub fn approximate_minimum_cycle_basis(
    nodes: usize,
    ends: &[(usize, usize)],
    weights: &[f64],
    k: u32,
    deadline: Option<Instant>,
) -> Result<Vec<Cycle>, McbError> {
    let ends = checked(nodes, ends, weights)?;
    approximate(nodes, &ends, weights, k, deadline)
}

/// [`approximate_minimum_cycle_basis`] on checked input.
pub(crate) fn approximate(
    nodes: usize,
    ends: &[(u32, u32)],
    w: &[f64],
    k: u32,
    deadline: Option<Instant>,
) -> Result<Vec<Cycle>, McbError> {
    if k == 0 {
        return Err(McbError::Stretch { k });
    }
    let stretch = f64::from(2 * k - 1);
    let reduced = reduce(nodes, ends, w);
    let mut out = reduced.cycles;
    let mut search = Dijkstra::default();
    for b in &reduced.blocks {
        check(deadline)?;
        let mut order: Vec<usize> = (0..b.ends.len()).collect();
        order.sort_by(|&p, &q| b.w[p].total_cmp(&b.w[q]).then(p.cmp(&q)));
        let mut adj: Adjacency = vec![SmallVec::new(); b.nodes];
        let mut in_s = vec![false; b.ends.len()];
        for e in order {
            let (x, y) = b.ends[e];
            if !search.run(&adj, &b.w, x as usize, Some(y as usize), stretch * b.w[e]) {
                in_s[e] = true;
                adj[x as usize].push((y, e as u32));
                adj[y as usize].push((x, e as u32));
            }
        }
        // Exact MCB of the spanner, in spanner edge numbers.
        let s_edges: Vec<u32> = (0..b.ends.len() as u32)
            .filter(|&e| in_s[e as usize])
            .collect();
        let s_ends: Vec<(u32, u32)> = s_edges.iter().map(|&e| b.ends[e as usize]).collect();
        let s_w: Vec<f64> = s_edges.iter().map(|&e| b.w[e as usize]).collect();
        for c in mcb(b.nodes, &s_ends, &s_w, deadline)? {
            let terms: SmallVec<[SignedEdge; 8]> = c
                .terms
                .iter()
                .map(|t| SignedEdge {
                    edge: s_edges[t.edge as usize],
                    sign: t.sign,
                })
                .collect();
            out.push(b.expand(&terms));
        }
        // Each non-spanner edge with its least-weight spanner path back.
        for e in (0..b.ends.len()).filter(|&e| !in_s[e]) {
            check(deadline)?;
            let (x, y) = b.ends[e];
            search.run(&adj, &b.w, y as usize, Some(x as usize), f64::INFINITY);
            let mut terms: SmallVec<[SignedEdge; 8]> = SmallVec::new();
            terms.push(SignedEdge::new(e, true));
            search.path(&b.ends, y as usize, x as usize, &mut terms);
            out.push(b.expand(&terms));
        }
    }
    Ok(out)
}
