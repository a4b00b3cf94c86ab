//! Exact minimum cycle basis (MCB) of an undirected multigraph with positive edge weights
//! (method [§6](crate::method#6-which-cycle-basis): with weights σ², the MCB minimises `tr P_γ`).
//!
//! **Reduction.** The graph is split into biconnected blocks and every chain of degree-2
//! nodes is contracted into one edge (`reduce`); a block that is a single cycle is
//! its own MCB. What follows runs on each contracted block (`n` nodes, `m` edges,
//! `ℓ = m − n + 1`), and the cycles are expanded back at the end.
//!
//! **de Pina's scheme** (de Pina 1995; Kavitha, Mehlhorn, Michail, Paluch 2008). Fix a
//! spanning tree (the minimum one); a cycle is a vector over GF(2) in *chord coordinates*
//! (which chords it uses). Support vectors `S_0 … S_{ℓ−1}` start as the unit vectors. Phase
//! `i` takes as `C_i` a least-weight cycle with `⟨C_i, S_i⟩ = 1` (odd intersection), then makes
//! every later support orthogonal to it: `S_j ← S_j + S_i` for `j > i` with `⟨C_i, S_j⟩ = 1`.
//! The `C_i` form an MCB (the matrix `⟨C_i, S_j⟩` is unit triangular, so they are independent;
//! and an exchange argument bounds each `w(C_i)` by a distinct MCB cycle). `S_j` only ever
//! involves coordinates `≤ j`, so it is stored bit-packed in `⌈(j+1)/64⌉` words: memory
//! `ℓ²/128` bytes, never a dense `m × m` matrix.
//!
//! **Candidates** (Horton 1987; Mehlhorn, Michail, "Minimum cycle bases: faster and simpler",
//! 2009). The least-weight odd cycle is found among Horton candidates `C(v, e)`: for a root
//! `v`, the shortest-path tree `T_v`, and an edge `e = (x, y)` not in `T_v` whose ends lie in
//! different subtrees of `v`, `C(v, e) = P(v, x) + e + P(y, v)`, of weight
//! `d(v, x) + w_e + d(v, y)`. Roots are a feedback vertex set (`fvs`), so every cycle
//! passes through a root. Why this suffices: let `C` be a least-weight odd cycle and `v` a root
//! on it; then `C = Σ_{e ∈ C} C_v(e)` over GF(2) (the tree paths cancel pairwise), and each term
//! weighs at most `w(C)`; one term is odd, and if its two paths shared a first edge, removing
//! the shared part would leave a *lighter* odd cycle, so it is a proper candidate of weight
//! `w(C)`. Candidates are de-duplicated (the same cycle from several roots), sorted **once**
//! by (weight, edge set), and indexed by chord coordinate; phase `i` scans, for each
//! coordinate in the support of `S_i`, that coordinate's candidates in sorted order, testing
//! parity with the bit-packed `S_i` (an odd cycle must use a chord of the support), and keeps
//! the first odd one. Ties therefore break by the sorted order: the result is deterministic.
//!
//! **Radius.** Every `C_i` weighs at most the heaviest MCB cycle, so candidates heavier than a
//! radius `R` are not generated (bounded Dijkstra: only nodes within `R` of the root are
//! settled). If a phase finds no odd candidate of weight `≤ R`, the least odd cycle is heavier
//! than `R` (its Horton representative would be there); `R` doubles and the candidates are
//! regenerated — finished phases stay valid. A bounded search is a prefix of the full one, so
//! the order of candidates, hence the result, does not depend on `R`.
//!
//! **Order of phases.** Any order of the chord coordinates is correct; chords are processed
//! by the weight of the lightest candidate through them, so early phases pick light local
//! cycles and the supports stay sparse.
//!
//! **Complexity.** Reduction `O(n + m)`; candidates: one bounded Dijkstra per root,
//! `O(f · m log m)` for `f` roots, `K` candidates of total length `L`; phases: the scans plus
//! `O(ℓ · |C_i|)` parity tests and at most `ℓ` word-XORs of `⌈i/64⌉` words each per phase,
//! `O(ℓ³/64)` in the worst case, far less on pose graphs (supports stay sparse). Memory
//! `O(L + ℓ²/64)` words.

use std::time::Instant;

use smallvec::SmallVec;

use super::dijkstra::Dijkstra;
use super::fvs::feedback_vertex_set;
use super::reduce::{Block, reduce};
use super::{Cycle, SignedEdge};
use crate::graph::UnionFind;

/// Why a minimum cycle basis was not computed.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum McbError {
    /// An edge weight is not positive and finite.
    #[error("edge {edge} has weight {weight}: weights must be positive and finite")]
    Weight {
        /// The edge.
        edge: usize,
        /// Its weight.
        weight: f64,
    },
    /// An edge joins a node to itself.
    #[error("edge {edge} is a self-loop")]
    SelfLoop {
        /// The edge.
        edge: usize,
    },
    /// Not one weight per edge.
    #[error("{ends} edges but {weights} weights")]
    Length {
        /// Edges given.
        ends: usize,
        /// Weights given.
        weights: usize,
    },
    /// An edge names a node outside `0..nodes`.
    #[error("edge {edge} names a node outside 0..{nodes}")]
    Node {
        /// The edge.
        edge: usize,
        /// Number of nodes.
        nodes: usize,
    },
    /// The approximation parameter k must be at least 1.
    #[error("k = {k}: the spanner stretch 2k − 1 needs k ≥ 1")]
    Stretch {
        /// The k given.
        k: u32,
    },
    /// The deadline passed before the basis was complete.
    #[error("time budget exhausted")]
    Deadline,
    /// A phase found no odd cycle among all candidates (a bug: never expected).
    #[error("internal error: no cycle with odd intersection in phase {phase}")]
    Internal {
        /// The phase.
        phase: usize,
    },
}

/// Check a weighted multigraph and convert its ends to `u32`.
pub(crate) fn checked(
    nodes: usize,
    ends: &[(usize, usize)],
    weights: &[f64],
) -> Result<Vec<(u32, u32)>, McbError> {
    if ends.len() != weights.len() {
        return Err(McbError::Length {
            ends: ends.len(),
            weights: weights.len(),
        });
    }
    ends.iter()
        .zip(weights)
        .enumerate()
        .map(|(edge, (&(a, b), &weight))| {
            if !(weight.is_finite() && weight > 0.0) {
                Err(McbError::Weight { edge, weight })
            } else if a >= nodes || b >= nodes {
                Err(McbError::Node { edge, nodes })
            } else if a == b {
                Err(McbError::SelfLoop { edge })
            } else {
                Ok((a as u32, b as u32))
            }
        })
        .collect()
}

/// Fails with [`McbError::Deadline`] once `deadline` has passed.
pub(crate) fn check(deadline: Option<Instant>) -> Result<(), McbError> {
    match deadline {
        Some(d) if Instant::now() > d => Err(McbError::Deadline),
        _ => Ok(()),
    }
}

/// An exact minimum cycle basis of the multigraph with `nodes` nodes, edges `ends` (indexed
/// by position; parallel edges allowed) and positive `weights`: `m − n + c` closed signed
/// cycles (any starting edge and orientation), block by block.
pub fn minimum_cycle_basis(
    nodes: usize,
    ends: &[(usize, usize)],
    weights: &[f64],
    deadline: Option<Instant>,
) -> Result<Vec<Cycle>, McbError> {
    let ends = checked(nodes, ends, weights)?;
    mcb(nodes, &ends, weights, deadline)
}

/// [`minimum_cycle_basis`] on checked input.
pub(crate) fn mcb(
    nodes: usize,
    ends: &[(u32, u32)],
    w: &[f64],
    deadline: Option<Instant>,
) -> Result<Vec<Cycle>, McbError> {
    let reduced = reduce(nodes, ends, w);
    let mut out = reduced.cycles;
    for block in &reduced.blocks {
        for c in block_mcb(block, deadline)? {
            out.push(block.expand(&c));
        }
    }
    Ok(out)
}

const NONE: u32 = u32::MAX;

/// De-duplicated candidates sorted by (weight, edge set), with their chord coordinates.
#[derive(Default)]
struct Candidates {
    weight: Vec<f64>,
    /// Edges of candidate k: `edges[start[k]..start[k + 1]]`, ascending.
    start: Vec<usize>,
    edges: Vec<u32>,
    /// Chord coordinates of candidate k: `coords[cstart[k]..cstart[k + 1]]`, ascending.
    cstart: Vec<usize>,
    coords: Vec<u32>,
    /// For each coordinate, the candidates using it, ascending.
    by_coord: Vec<Vec<u32>>,
}

impl Candidates {
    fn edges(&self, k: usize) -> &[u32] {
        &self.edges[self.start[k]..self.start[k + 1]]
    }
    fn coords(&self, k: usize) -> &[u32] {
        &self.coords[self.cstart[k]..self.cstart[k + 1]]
    }
}

/// Horton candidates of weight `≤ radius` from every root, de-duplicated and sorted.
/// `coord[e]` is the chord coordinate of edge e (NONE for tree edges).
fn candidates(
    b: &Block,
    roots: &[u32],
    radius: f64,
    coord: &[u32],
    search: &mut Dijkstra,
    deadline: Option<Instant>,
) -> Result<Candidates, McbError> {
    let mut branch = vec![NONE; b.nodes];
    let mut pos = vec![0u32; b.nodes];
    // Raw candidates: sorted edge lists in one arena.
    let mut raw_start = vec![0usize];
    let mut raw: Vec<u32> = Vec::new();
    for &v in roots {
        check(deadline)?;
        let v = v as usize;
        search.run(&b.adj, &b.w, v, None, radius);
        for (k, &u) in search.order().iter().enumerate() {
            let u = u as usize;
            pos[u] = k as u32;
            branch[u] = if k == 0 {
                NONE
            } else {
                let p = search.pred(u).0 as usize;
                if p == v { u as u32 } else { branch[p] }
            };
        }
        for &x in search.order() {
            let x = x as usize;
            for &(y, e) in &b.adj[x] {
                let y = y as usize;
                if !search.settled(y) || pos[y] <= pos[x] || branch[x] == branch[y] {
                    continue;
                }
                if search.pred(y).1 == e {
                    continue;
                }
                let weight = search.dist(x) + b.w[e as usize] + search.dist(y);
                if weight > radius {
                    continue;
                }
                let first = raw.len();
                raw.push(e);
                for mut u in [x, y] {
                    while u != v {
                        let (p, f) = search.pred(u);
                        raw.push(f);
                        u = p as usize;
                    }
                }
                raw[first..].sort_unstable();
                raw_start.push(raw.len());
            }
        }
    }
    let count = raw_start.len() - 1;
    let edges_of = |k: usize| &raw[raw_start[k]..raw_start[k + 1]];
    // Canonical weight: summed in edge order, so equal cycles get equal weights.
    let canon: Vec<f64> = (0..count)
        .map(|k| edges_of(k).iter().map(|&e| b.w[e as usize]).sum())
        .collect();
    let mut order: Vec<u32> = (0..count as u32).collect();
    order.sort_unstable_by(|&p, &q| {
        let (p, q) = (p as usize, q as usize);
        canon[p]
            .total_cmp(&canon[q])
            .then_with(|| edges_of(p).cmp(edges_of(q)))
    });
    order.dedup_by(|p, q| edges_of(*p as usize) == edges_of(*q as usize));
    let mut c = Candidates {
        start: vec![0],
        cstart: vec![0],
        by_coord: vec![Vec::new(); b.rank()],
        ..Candidates::default()
    };
    for (k, &r) in order.iter().enumerate() {
        let r = r as usize;
        c.weight.push(canon[r]);
        c.edges.extend_from_slice(edges_of(r));
        c.start.push(c.edges.len());
        let first = c.coords.len();
        c.coords.extend(
            edges_of(r)
                .iter()
                .map(|&e| coord[e as usize])
                .filter(|&x| x != NONE),
        );
        c.coords[first..].sort_unstable();
        for &x in &c.coords[first..] {
            c.by_coord[x as usize].push(k as u32);
        }
        c.cstart.push(c.coords.len());
    }
    Ok(c)
}

/// Bit `i` of a packed vector.
fn bit(s: &[u64], i: u32) -> bool {
    s.get(i as usize / 64)
        .is_some_and(|w| (w >> (i % 64)) & 1 == 1)
}

/// Parity of `⟨C, S⟩` for a cycle with chord coordinates `coords`.
fn odd(coords: &[u32], s: &[u64]) -> bool {
    coords.iter().filter(|&&x| bit(s, x)).count() % 2 == 1
}

/// The first (least) candidate with odd intersection with `s`, if any.
fn least_odd(c: &Candidates, s: &[u64]) -> Option<usize> {
    let mut best = u32::MAX;
    for (wi, &word) in s.iter().enumerate() {
        let mut word = word;
        while word != 0 {
            let x = wi * 64 + word.trailing_zeros() as usize;
            word &= word - 1;
            for &k in &c.by_coord[x] {
                if k >= best {
                    break;
                }
                if odd(c.coords(k as usize), s) {
                    best = k;
                    break;
                }
            }
        }
    }
    (best != u32::MAX).then_some(best as usize)
}

/// An MCB of one contracted block, as closed walks of signed block edges.
fn block_mcb(
    b: &Block,
    deadline: Option<Instant>,
) -> Result<Vec<SmallVec<[SignedEdge; 8]>>, McbError> {
    let rank = b.rank();
    let roots = feedback_vertex_set(b.nodes, &b.ends);
    // Chords of the minimum spanning tree (Kruskal, ties by edge id).
    let mut by_weight: Vec<usize> = (0..b.ends.len()).collect();
    by_weight.sort_by(|&p, &q| b.w[p].total_cmp(&b.w[q]).then(p.cmp(&q)));
    let mut uf = UnionFind::new(b.nodes);
    let chords: Vec<usize> = by_weight
        .into_iter()
        .filter(|&e| !uf.union(b.ends[e].0 as usize, b.ends[e].1 as usize))
        .collect();
    let total: f64 = b.w.iter().sum();
    let mut sorted_w = b.w.clone();
    sorted_w.sort_by(f64::total_cmp);
    // Start with a radius of a few typical edges; doubled on demand.
    let mut radius = 4.0 * sorted_w[sorted_w.len() / 2];
    let mut search = Dijkstra::new(b.nodes);

    // Phase order: chords by the weight of their lightest candidate (then by edge id).
    let mut coord = vec![NONE; b.ends.len()];
    for (x, &e) in chords.iter().enumerate() {
        coord[e] = x as u32;
    }
    let first = candidates(b, &roots, radius, &coord, &mut search, deadline)?;
    let mut key = vec![(f64::INFINITY, 0usize); rank];
    for (x, &e) in chords.iter().enumerate() {
        key[x] = (
            first.by_coord[x]
                .first()
                .map_or(f64::INFINITY, |&k| first.weight[k as usize]),
            e,
        );
    }
    let mut phase: Vec<usize> = (0..rank).collect();
    phase.sort_by(|&p, &q| key[p].0.total_cmp(&key[q].0).then(key[p].1.cmp(&key[q].1)));
    for (i, &x) in phase.iter().enumerate() {
        coord[chords[x]] = i as u32;
    }
    let mut cands = candidates(b, &roots, radius, &coord, &mut search, deadline)?;

    // Support vectors: S_j has bits 0..=j only.
    let mut support: Vec<Vec<u64>> = (0..rank)
        .map(|j| {
            let mut s = vec![0u64; j / 64 + 1];
            s[j / 64] = 1 << (j % 64);
            s
        })
        .collect();
    let mut chosen: Vec<Vec<u32>> = Vec::with_capacity(rank);
    for i in 0..rank {
        check(deadline)?;
        let k = loop {
            if let Some(k) = least_odd(&cands, &support[i]) {
                break k;
            }
            if radius == f64::INFINITY {
                // Not expected: S_i ≠ 0, so some fundamental cycle is odd, and with an
                // unbounded radius every Horton candidate is present.
                return Err(McbError::Internal { phase: i });
            }
            // Past the total weight every simple cycle fits: go unbounded (no rounding doubt).
            radius = if 2.0 * radius >= total {
                f64::INFINITY
            } else {
                2.0 * radius
            };
            cands = candidates(b, &roots, radius, &coord, &mut search, deadline)?;
        };
        let ci: Vec<u32> = cands.coords(k).to_vec();
        let (head, tail) = support.split_at_mut(i + 1);
        let si = &head[i];
        for (off, sj) in tail.iter_mut().enumerate() {
            let j = (i + 1 + off) as u32;
            let parity = ci.iter().filter(|&&x| x <= j && bit(sj, x)).count() % 2;
            if parity == 1 {
                for (a, &bw) in sj.iter_mut().zip(si) {
                    *a ^= bw;
                }
            }
        }
        chosen.push(cands.edges(k).to_vec());
    }
    Ok(chosen.iter().map(|c| walk(b, c)).collect())
}

/// A simple cycle given by its edge set, as a closed walk of signed edges starting along its
/// first edge.
pub(crate) fn walk(b: &Block, edges: &[u32]) -> SmallVec<[SignedEdge; 8]> {
    walk_ends(&b.ends, edges)
}

/// [`walk`] over any edge list.
pub(crate) fn walk_ends(ends: &[(u32, u32)], edges: &[u32]) -> SmallVec<[SignedEdge; 8]> {
    let mut at: Vec<(u32, u32)> = edges
        .iter()
        .flat_map(|&e| {
            let (a, b) = ends[e as usize];
            [(a, e), (b, e)]
        })
        .collect();
    at.sort_unstable();
    let mut out = SmallVec::new();
    let Some(&e0) = edges.first() else {
        return out;
    };
    let (mut node, mut via) = (ends[e0 as usize].1, e0);
    out.push(SignedEdge::new(e0 as usize, true));
    while out.len() < edges.len() {
        let lo = at.partition_point(|&(v, _)| v < node);
        let Some(&(_, next)) = at[lo..]
            .iter()
            .take_while(|&&(v, _)| v == node)
            .find(|&&(_, f)| f != via)
        else {
            break;
        };
        let (a, b) = ends[next as usize];
        out.push(SignedEdge::new(next as usize, a == node));
        node = if a == node { b } else { a };
        via = next;
    }
    out
}
