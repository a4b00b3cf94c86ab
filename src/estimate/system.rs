//! Sparse normal equations of a pose graph, shared by the orientation, position and refinement
//! solvers.
//!
//! Every edge `e = (a, b)` contributes a residual `r_e` (dimension `r`) with Jacobians `J_a`,
//! `J_b` (each `r × d`, `d` unknowns per node) and weight `W_e` (`r × r`, symmetric):
//!
//! ```text
//! H = Σ_e Jᵀ W_e J,   g = Σ_e Jᵀ W_e r_e,   J = [… J_a … J_b …],   (H + λ diag H) Δ = −g.
//! ```
//!
//! `H` has the sparsity of the graph (a `d × d` block per node and per adjacent pair); one
//! node per connected component is the **anchor** (gauge) and has no unknowns. The pattern is
//! built once; each assembly only adds values into their precomputed slots, and the AMD
//! ordering and symbolic Cholesky factorisation (faer) are computed at the first
//! factorisation and reused by every later one (refinement iterations change values only).

use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use faer::{Col, Side};

use super::EstimateError;
use crate::graph::PoseGraph;

/// No unknowns: the node is its component's anchor.
pub(crate) const ANCHOR: usize = usize::MAX;

/// Anchors (the first node, in index order, of each connected component) and the index of
/// every other node among the unknowns.
#[derive(Clone, Debug)]
pub(crate) struct Anchored {
    /// Unknown index of each node, [`ANCHOR`] for anchors.
    pub var_of: Vec<usize>,
    /// The anchor of each component.
    pub anchors: Vec<usize>,
    /// Number of non-anchor nodes.
    pub free: usize,
}

impl Anchored {
    pub fn new(graph: &PoseGraph) -> Self {
        let (label, count) = graph.components();
        let mut anchors = vec![ANCHOR; count];
        for (v, &c) in label.iter().enumerate() {
            if anchors[c] == ANCHOR {
                anchors[c] = v;
            }
        }
        let mut var_of = vec![ANCHOR; graph.node_count()];
        let mut free = 0;
        for (v, slot) in var_of.iter_mut().enumerate() {
            if anchors[label[v]] != v {
                *slot = free;
                free += 1;
            }
        }
        Self {
            var_of,
            anchors,
            free,
        }
    }
}

impl Anchored {
    /// The right-hand side `Σ_e y_e (u_b − u_a)` of a scalar Laplacian system (edge e from a
    /// to b, anchors dropped).
    pub fn scatter(&self, ends: &[(usize, usize)], y: impl Fn(usize) -> f64) -> Col<f64> {
        let mut rhs = Col::<f64>::zeros(self.free);
        for (e, &(a, b)) in ends.iter().enumerate() {
            let y = y(e);
            if self.var_of[b] != ANCHOR {
                rhs[self.var_of[b]] += y;
            }
            if self.var_of[a] != ANCHOR {
                rhs[self.var_of[a]] -= y;
            }
        }
        rhs
    }

    /// Unknown `i` of node `v` in a solution with `d` unknowns per node (0 for an anchor).
    pub fn value(&self, x: &Col<f64>, v: usize, d: usize, i: usize) -> f64 {
        match self.var_of[v] {
            ANCHOR => 0.0,
            u => x[d * u + i],
        }
    }
}

/// `H` and `g` of a graph for `D` unknowns per node, with a cached symbolic factorisation.
/// Cloning keeps the pattern and the symbolic factorisation (shared), so a clone assembles
/// and factors other values of the same graph without a new ordering.
#[derive(Clone)]
pub(crate) struct NormalEquations<const D: usize> {
    var_of: Vec<usize>,
    ends: Vec<(usize, usize)>,
    pattern: SymbolicSparseColMat<usize>,
    /// Value slot of each edge's four blocks (aa, ab, ba, bb), `D·D` entries each, row-major;
    /// `usize::MAX` where a node is an anchor.
    slots: Vec<usize>,
    /// Slot of each unknown's diagonal entry.
    diagonal: Vec<usize>,
    values: Vec<f64>,
    rhs: Vec<f64>,
    symbolic: Option<SymbolicLlt<usize>>,
}

const NONE: usize = usize::MAX;

impl<const D: usize> NormalEquations<D> {
    /// The pattern of `H` for the graph's edges.
    pub fn new(graph: &PoseGraph, anchored: &Anchored) -> Result<Self, EstimateError> {
        let var_of = anchored.var_of.clone();
        let ends = graph.endpoints().to_vec();
        let dim = anchored.free * D;
        let unknown = |v: usize, i: usize| (var_of[v] != ANCHOR).then(|| var_of[v] * D + i);
        // Block column of each free node: itself and its free neighbours, ascending (unknown
        // indices increase with node index), each expanded to D rows.
        let mut adjacent: Vec<Vec<usize>> = vec![Vec::new(); anchored.free];
        for &(a, b) in &ends {
            if var_of[a] != ANCHOR && var_of[b] != ANCHOR {
                adjacent[var_of[a]].push(var_of[b]);
                adjacent[var_of[b]].push(var_of[a]);
            }
        }
        let mut col_ptr = Vec::with_capacity(dim + 1);
        let mut row_idx = Vec::new();
        col_ptr.push(0);
        for (v, near) in adjacent.iter_mut().enumerate() {
            near.push(v);
            near.sort_unstable();
            near.dedup();
            for _ in 0..D {
                row_idx.extend(near.iter().flat_map(|&u| (0..D).map(move |i| u * D + i)));
                col_ptr.push(row_idx.len());
            }
        }
        let pattern = SymbolicSparseColMat::new_checked(dim, dim, col_ptr, None, row_idx);
        let slot = |r: usize, c: usize| {
            let (start, end) = (pattern.col_ptr()[c], pattern.col_ptr()[c + 1]);
            let rows = &pattern.row_idx()[start..end];
            rows.binary_search(&r).map(|k| start + k).unwrap_or(NONE)
        };
        let mut slots = Vec::with_capacity(4 * D * D * ends.len());
        for &(a, b) in &ends {
            for (p, q) in [(a, a), (a, b), (b, a), (b, b)] {
                for i in 0..D {
                    for j in 0..D {
                        slots.push(match (unknown(p, i), unknown(q, j)) {
                            (Some(r), Some(c)) => slot(r, c),
                            _ => NONE,
                        });
                    }
                }
            }
        }
        let diagonal = (0..dim).map(|i| slot(i, i)).collect();
        let nnz = pattern.row_idx().len();
        Ok(Self {
            var_of,
            ends,
            pattern,
            slots,
            diagonal,
            values: vec![0.0; nnz],
            rhs: vec![0.0; dim],
            symbolic: None,
        })
    }

    /// Number of unknowns.
    pub fn dim(&self) -> usize {
        self.rhs.len()
    }

    /// Start a new assembly.
    pub fn clear(&mut self) {
        self.values.fill(0.0);
        self.rhs.fill(0.0);
    }

    /// Add edge `e`'s term: residual `res` (length `R`), Jacobians `ja`, `jb` (`R × D`,
    /// row-major) and weight `w` (`R × R`, symmetric, row-major).
    // Index loops over the fixed-size blocks read as the matrix products they are.
    #[allow(clippy::needless_range_loop)]
    pub fn add<const R: usize>(
        &mut self,
        e: usize,
        ja: &[[f64; D]; R],
        jb: &[[f64; D]; R],
        w: &[[f64; R]; R],
        res: &[f64; R],
    ) {
        // W J_x and W r.
        let wj = |j: &[[f64; D]; R]| -> [[f64; D]; R] {
            let mut out = [[0.0; D]; R];
            for (k, row) in out.iter_mut().enumerate() {
                for (c, x) in row.iter_mut().enumerate() {
                    *x = (0..R).map(|l| w[k][l] * j[l][c]).sum();
                }
            }
            out
        };
        let (wja, wjb) = (wj(ja), wj(jb));
        let blocks = [(ja, &wja), (ja, &wjb), (jb, &wja), (jb, &wjb)];
        let base = 4 * D * D * e;
        for (k, (jl, wjr)) in blocks.into_iter().enumerate() {
            for i in 0..D {
                for j in 0..D {
                    let s = self.slots[base + k * D * D + i * D + j];
                    if s != NONE {
                        self.values[s] += (0..R).map(|l| jl[l][i] * wjr[l][j]).sum::<f64>();
                    }
                }
            }
        }
        let (a, b) = self.ends[e];
        let wr: [f64; R] = std::array::from_fn(|k| (0..R).map(|l| w[k][l] * res[l]).sum());
        for (v, j) in [(a, ja), (b, jb)] {
            if self.var_of[v] != ANCHOR {
                for i in 0..D {
                    self.rhs[self.var_of[v] * D + i] -=
                        (0..R).map(|l| j[l][i] * wr[l]).sum::<f64>();
                }
            }
        }
    }

    /// Factor `H + λ diag(H)` (the AMD ordering and symbolic factorisation are computed once).
    pub fn factor(&mut self, lambda: f64) -> Result<Option<Llt<usize, f64>>, EstimateError> {
        if self.dim() == 0 {
            return Ok(None);
        }
        // The damped copy only when damping: H itself stays for the next λ.
        let damped;
        let values = if lambda > 0.0 {
            let mut v = self.values.clone();
            for &s in &self.diagonal {
                v[s] += lambda * self.values[s];
            }
            damped = v;
            &damped
        } else {
            &self.values
        };
        let symbolic = match &self.symbolic {
            Some(s) => s.clone(),
            None => {
                let s = SymbolicLlt::try_new(self.pattern.as_ref(), Side::Lower).map_err(|_| {
                    EstimateError::Resources {
                        unknowns: self.dim(),
                    }
                })?;
                self.symbolic = Some(s.clone());
                s
            }
        };
        let h = SparseColMatRef::new(self.pattern.as_ref(), values);
        Llt::try_new_with_symbolic(symbolic, h, Side::Lower)
            .map(Some)
            .map_err(|e| EstimateError::from_llt(self.dim(), e))
    }

    /// `−g`, the right-hand side of the step equations.
    pub fn rhs(&self) -> Col<f64> {
        Col::from_fn(self.dim(), |i| self.rhs[i])
    }
}

/// Solve with a factorisation (None: no unknowns).
pub(crate) fn solve(llt: Option<&Llt<usize, f64>>, rhs: &Col<f64>) -> Col<f64> {
    match llt {
        Some(l) => l.solve(rhs),
        None => Col::zeros(0),
    }
}
