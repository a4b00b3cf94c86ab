//! The γ model: the cycle integers as a Gaussian (method [§2](crate::method#2-cycles), [§3](crate::method#3-first-screening), [§7](crate::method#7-online-estimation)).
//!
//! For a cycle basis `C`, `γ = C k ∈ Z^ℓ` and `γ ~ N(μ, P_γ)` with
//!
//! ```text
//! μ = C δ / 2π,        P_γ = C P Cᵀ / 4π²,   (P_γ)_st = Σ_{e ∈ c_s ∩ c_t} (±1)(±1) σ_e² / 4π²,
//! ```
//!
//! nonzero only where cycles share edges. [`GammaModel`] stores μ and a **sparse** symmetric
//! P_γ and grows by one row per cycle (the batch pipeline appends all cycles of a basis, the
//! online estimator one per loop closure — the same code).
//!
//! [`Conditioner`] conditions γ on a set U of determined integers `u_U`:
//!
//! ```text
//! mean_i = μ_i + P_iU P_UU⁻¹ (u_U − μ_U),      var_i = P_ii − P_iU P_UU⁻¹ P_Ui,
//! ```
//!
//! with an **append-only** sparse Cholesky factor `L` of `P_UU` (rows appended in the order
//! cycles are determined) and `z = L⁻¹ (u_U − μ_U)`: for a cycle i,
//! `y = L⁻¹ P_{U,i}` (sparse triangular solve), `mean = μ_i + yᵀz`, `var = P_ii − ‖y‖²`; when
//! i is determined with value u, `(yᵀ, √var)` becomes a new row of L and `(u − mean)/√var`
//! a new entry of z. No inverse is ever formed. Appending in the order cycles are determined
//! (chronological, online) lets L fill in (measured: city10000 reaches > 1000 nonzeros per row
//! after 4000 cycles, against 17 per row in a fill-reducing order), so the owner may call
//! [`Conditioner::reorder`] now and then to rebuild L in a fill-reducing order (approximate
//! minimum degree); the moments are order-independent. The diagonal of L
//! holds the sequential conditional standard deviations (the integer-bootstrapping `s_i` of
//! method [§8](crate::method#8-success-probability)), and `‖z‖² = (u − μ)ᵀ P_UU⁻¹ (u − μ)`.

use std::f64::consts::TAU;

use smallvec::SmallVec;

use crate::cycles::Cycle;

/// `4π²`.
const FOUR_PI2: f64 = TAU * TAU;

/// μ and the sparse symmetric P_γ of a growing set of cycles.
#[derive(Clone, Debug, Default)]
pub struct GammaModel {
    mu: Vec<f64>,
    /// Row i of P_γ: `(column, value)` sorted by column, diagonal included.
    rows: Vec<Vec<(u32, f64)>>,
    /// For each edge, the cycles through it with the edge's sign in them.
    edge_cycles: Vec<SmallVec<[(u32, i8); 4]>>,
    /// Dense accumulator and its touched list (scratch for [`push_cycle`](Self::push_cycle)).
    acc: Vec<f64>,
    touched: Vec<u32>,
}

impl GammaModel {
    /// An empty model.
    pub fn new() -> Self {
        Self::default()
    }

    /// Room for `cycles` more cycles and `edges` more edges without growing its arrays.
    pub fn try_reserve(
        &mut self,
        cycles: usize,
        edges: usize,
    ) -> Result<(), std::collections::TryReserveError> {
        self.mu.try_reserve(cycles)?;
        self.rows.try_reserve(cycles)?;
        self.acc.try_reserve(cycles)?;
        self.edge_cycles.try_reserve(edges)?;
        Ok(())
    }

    /// Build the model of a whole basis: `σ²` and `δ` per edge, cycles in basis order.
    pub fn from_cycles(cycles: &[Cycle], sigma2: &[f64], delta: &[f64]) -> Self {
        let mut m = Self::new();
        for c in cycles {
            m.push_cycle(c, sigma2, delta);
        }
        m
    }

    /// Number of cycles ℓ.
    pub fn len(&self) -> usize {
        self.mu.len()
    }

    /// Whether there are no cycles.
    pub fn is_empty(&self) -> bool {
        self.mu.is_empty()
    }

    /// Append a cycle: `μ_t = (Cδ)_t / 2π` and row t of P_γ. Returns t.
    pub fn push_cycle(&mut self, cycle: &Cycle, sigma2: &[f64], delta: &[f64]) -> usize {
        let t = self.mu.len();
        self.mu.push(cycle.signed_sum(delta) / TAU);
        self.acc.resize(t + 1, 0.0);
        let mut diag = 0.0;
        for term in &cycle.terms {
            let e = term.edge as usize;
            if self.edge_cycles.len() <= e {
                self.edge_cycles.resize(e + 1, SmallVec::new());
            }
            let w = sigma2[e] / FOUR_PI2;
            diag += w;
            for &(c, s) in &self.edge_cycles[e] {
                if self.acc[c as usize] == 0.0 {
                    self.touched.push(c);
                }
                self.acc[c as usize] += f64::from(s * term.sign) * w;
            }
        }
        self.touched.sort_unstable();
        self.touched.dedup();
        let mut row = Vec::with_capacity(self.touched.len() + 1);
        for &c in &self.touched {
            let v = std::mem::take(&mut self.acc[c as usize]);
            if v != 0.0 {
                row.push((c, v));
                self.rows[c as usize].push((t as u32, v));
            }
        }
        self.touched.clear();
        row.push((t as u32, diag));
        self.rows.push(row);
        for term in &cycle.terms {
            self.edge_cycles[term.edge as usize].push((t as u32, term.sign));
        }
        t
    }

    /// A copy of μ and P_γ without the index from edges to cycles ([`push_cycle`]'s, which a
    /// renewal's builder never uses): what a renewal of the P_UU factor starts from.
    ///
    /// [`push_cycle`]: Self::push_cycle
    pub fn rows_only(&self) -> Self {
        Self {
            mu: self.mu.clone(),
            rows: self.rows.clone(),
            ..Self::default()
        }
    }

    /// Append cycle t from its μ_t and its row of P_γ as another model computed it
    /// ([`push_cycle`](Self::push_cycle)): the entries for cycles ≤ t, ascending, its variance
    /// last. Keeps a copy (a renewal's builder) in step with the live model; a copy grown this
    /// way takes rows only. Entries for later cycles are ignored.
    pub fn push_row(&mut self, mu: f64, row: &[(u32, f64)]) -> usize {
        let t = self.mu.len();
        self.mu.push(mu);
        let row: Vec<(u32, f64)> = row
            .iter()
            .copied()
            .filter(|&(c, _)| c as usize <= t)
            .collect();
        for &(c, v) in &row {
            if (c as usize) < t {
                self.rows[c as usize].push((t as u32, v));
            }
        }
        self.rows.push(row);
        t
    }

    /// Remove the last cycle (undo [`push_cycle`](Self::push_cycle) of `cycle`, the same
    /// cycle): the online estimator tests a new loop closure's cycle and takes it back when the
    /// loop closure is quarantined. It must not have been determined.
    pub fn pop_cycle(&mut self, cycle: &Cycle) {
        let Some(row) = self.rows.pop() else { return };
        let last = self.mu.len() as u32 - 1;
        for &(c, _) in &row {
            if c != last {
                // Column `last` is the largest, so it is the last entry of every row it is in.
                self.rows[c as usize].pop();
            }
        }
        self.mu.pop();
        for term in &cycle.terms {
            self.edge_cycles[term.edge as usize].pop();
        }
    }

    /// μ.
    pub fn mu(&self) -> &[f64] {
        &self.mu
    }

    /// Row i of P_γ, sorted by column, diagonal included.
    pub fn row(&self, i: usize) -> &[(u32, f64)] {
        &self.rows[i]
    }

    /// `(P_γ)_ii`.
    pub fn variance(&self, i: usize) -> f64 {
        self.entry(i, i)
    }

    /// `(P_γ)_ij` (0 where the cycles share no edge).
    pub fn entry(&self, i: usize, j: usize) -> f64 {
        let row = &self.rows[i];
        row.binary_search_by_key(&(j as u32), |x| x.0)
            .map_or(0.0, |k| row[k].1)
    }

    /// Number of stored nonzeros of P_γ (both triangles).
    pub fn nnz(&self) -> usize {
        self.rows.iter().map(Vec::len).sum()
    }

    /// A fill-reducing order of the cycles in `set` (ascending), for appending them to a
    /// [`Conditioner`]: approximate minimum degree (faer) on the pattern of `P_γ` restricted to
    /// the set. Conditioning is order-independent; only the fill of L (speed) changes.
    pub fn fill_reducing_order(&self, set: &[usize]) -> Vec<usize> {
        let k = set.len();
        let mut local = vec![u32::MAX; self.len()];
        for (p, &c) in set.iter().enumerate() {
            local[c] = p as u32;
        }
        let mut col_ptr = Vec::with_capacity(k + 1);
        let mut row_idx = Vec::new();
        col_ptr.push(0usize);
        for &c in set {
            row_idx.extend(
                self.rows[c]
                    .iter()
                    .map(|&(j, _)| local[j as usize])
                    .filter(|&l| l != u32::MAX)
                    .map(|l| l as usize),
            );
            col_ptr.push(row_idx.len());
        }
        match crate::estimate::incremental::amd_order(&col_ptr, &row_idx) {
            Some(perm) => perm.iter().map(|&p| set[p]).collect(),
            None => set.to_vec(),
        }
    }

    /// Nonzeros of the principal submatrix on `set` (given as a membership mask).
    pub fn nnz_within(&self, member: &[bool]) -> usize {
        (0..self.rows.len())
            .filter(|&i| member[i])
            .map(|i| {
                self.rows[i]
                    .iter()
                    .filter(|&&(j, _)| member[j as usize])
                    .count()
            })
            .sum()
    }
}

/// Conditional mean and variance of one γ_i given the determined set.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Moments {
    /// Conditional mean.
    pub mean: f64,
    /// Conditional variance.
    pub var: f64,
}

impl Moments {
    /// Conditional standard deviation.
    pub fn sd(&self) -> f64 {
        self.var.max(0.0).sqrt()
    }
}

/// Conditioning failed: the conditional variance of a cycle is not positive, i.e. `P_UU` with
/// that cycle added is numerically singular.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
#[error("cycle {cycle}: conditional variance {var:e} is not positive (P_γ numerically singular)")]
pub struct SingularError {
    /// The cycle.
    pub cycle: usize,
    /// Its conditional variance.
    pub var: f64,
}

const NONE: u32 = u32::MAX;

/// Gaussian conditioning of γ on determined integers, with an append-only sparse Cholesky
/// factor of `P_UU` (see the module docs).
#[derive(Clone, Debug, Default)]
pub struct Conditioner {
    /// Position in U of each cycle (NONE if not determined).
    pos: Vec<u32>,
    /// Cycle at each position.
    cycle_at: Vec<u32>,
    /// Determined value at each position.
    value: Vec<i64>,
    /// Strictly-lower entries of each column of L: `(row position, value)`, rows increasing.
    cols: Vec<Vec<(u32, f64)>>,
    /// Diagonal of L: conditional standard deviations in determination order.
    diag: Vec<f64>,
    /// Nonzeros of L (diagonal included).
    nnz: usize,
    /// `z = L⁻¹ (u_U − μ_U)`.
    z: Vec<f64>,
    /// Elimination tree: first off-diagonal row of each column (NONE for none yet).
    parent: Vec<u32>,
    /// Entries of L visited by the triangular solves ([`Self::take_work`]).
    work: u64,
    // Scratch for the sparse triangular solve.
    y: Vec<f64>,
    mark: Vec<bool>,
    pattern: Vec<u32>,
    stack: Vec<u32>,
    path: Vec<u32>,
}

impl Conditioner {
    /// Nothing determined.
    pub fn new() -> Self {
        Self::default()
    }

    /// Entries of L visited by the sparse triangular solves since the last call (then zero):
    /// a deterministic measure of the time the conditioning took (a solve costs in proportion
    /// to the entries of the columns it reaches), by which a renewal beside it is scheduled.
    pub fn take_work(&mut self) -> u64 {
        std::mem::take(&mut self.work)
    }

    /// Entries of L visited by the triangular solves since the last [`Self::take_work`],
    /// without taking them.
    pub fn work(&self) -> u64 {
        self.work
    }

    /// Number of determined cycles |U|.
    pub fn len(&self) -> usize {
        self.diag.len()
    }

    /// Whether nothing is determined.
    pub fn is_empty(&self) -> bool {
        self.diag.is_empty()
    }

    /// The determined value of cycle i, if any.
    pub fn value(&self, i: usize) -> Option<i64> {
        match self.pos.get(i) {
            Some(&p) if p != NONE => Some(self.value[p as usize]),
            _ => None,
        }
    }

    /// Cycles in determination order.
    pub fn order(&self) -> &[u32] {
        &self.cycle_at
    }

    /// Conditional standard deviations `s_i` in determination order (diagonal of L).
    pub fn conditional_sds(&self) -> &[f64] {
        &self.diag
    }

    /// `‖z‖² = (u_U − μ_U)ᵀ P_UU⁻¹ (u_U − μ_U)`, the χ² of the determined part.
    pub fn chi2(&self) -> f64 {
        self.z.iter().map(|v| v * v).sum()
    }

    /// Nonzeros of L (diagonal included), kept as a counter: O(1).
    pub fn factor_nnz(&self) -> usize {
        self.nnz
    }

    /// Solve `y = L⁻¹ P_{U,i}` into the scratch (`self.y` on `self.pattern`).
    ///
    /// Up-looking sparse triangular solve (Davis, "Direct Methods for Sparse Linear
    /// Systems", §4.1 `cs_ereach`): the nonzero pattern of y is the union of the elimination
    /// tree paths from the right-hand side's nonzeros, collected in topological order, so the
    /// numeric pass touches only the columns it needs.
    fn solve(&mut self, model: &GammaModel, i: usize) {
        let n = self.diag.len();
        if self.y.len() < n {
            self.y.resize(n, 0.0);
            self.mark.resize(n, false);
        }
        // Reach in the elimination tree, as a stack whose top part is in topological order.
        if self.stack.len() < n {
            self.stack.resize(n, 0);
        }
        let mut top = n;
        for &(c, v) in model.row(i) {
            let Some(&p) = self.pos.get(c as usize) else {
                continue;
            };
            if p == NONE {
                continue;
            }
            self.y[p as usize] = v;
            let mut j = p;
            self.path.clear();
            while j != NONE && !self.mark[j as usize] {
                self.mark[j as usize] = true;
                self.path.push(j);
                j = self.parent[j as usize];
            }
            while let Some(j) = self.path.pop() {
                top -= 1;
                self.stack[top] = j;
            }
        }
        self.pattern.clear();
        self.pattern.extend_from_slice(&self.stack[top..]);
        // Borrowed apart, so that the inner loop keeps y's buffer in registers (through
        // `self` it was reloaded at every entry: a write to y might have moved it, as far as
        // the compiler could tell).
        let (y, cols, diag) = (&mut self.y[..], &self.cols, &self.diag);
        let mut work = 0;
        for &p in &self.pattern {
            let p = p as usize;
            let col = &cols[p];
            work += 1 + col.len() as u64;
            let yp = y[p] / diag[p];
            y[p] = yp;
            if yp != 0.0 {
                for &(r, l) in col {
                    y[r as usize] -= l * yp;
                }
            }
        }
        self.work += work;
        crate::work::conditioned(work);
    }

    fn moments_from_scratch(&self, model: &GammaModel, i: usize) -> Moments {
        let (mut dot, mut norm2) = (0.0, 0.0);
        for &p in &self.pattern {
            let yp = self.y[p as usize];
            dot += yp * self.z[p as usize];
            norm2 += yp * yp;
        }
        Moments {
            mean: model.mu()[i] + dot,
            var: model.variance(i) - norm2,
        }
    }

    fn clear_scratch(&mut self) {
        for &p in &self.pattern {
            self.y[p as usize] = 0.0;
            self.mark[p as usize] = false;
        }
        self.pattern.clear();
    }

    /// Conditional mean and variance of γ_i given the determined set.
    pub fn moments(&mut self, model: &GammaModel, i: usize) -> Moments {
        self.solve(model, i);
        let m = self.moments_from_scratch(model, i);
        self.clear_scratch();
        m
    }

    /// Determine cycle i with value u: append its row to L and its entry to z. Returns the
    /// moments it had just before. On error nothing changes.
    pub fn determine(
        &mut self,
        model: &GammaModel,
        i: usize,
        u: i64,
    ) -> Result<Moments, SingularError> {
        self.solve(model, i);
        let m = self.moments_from_scratch(model, i);
        self.append_solved(model, i, u, m)?;
        Ok(m)
    }

    /// Test-and-determine with one solve: compute the moments of cycle i, ask `choose` for a
    /// value, and when it gives one, determine the cycle from the same solve (as
    /// [`determine`](Self::determine) would, without solving twice). Returns the moments and
    /// the value determined, if any; on error nothing changes.
    pub fn decide(
        &mut self,
        model: &GammaModel,
        i: usize,
        choose: impl FnOnce(Moments) -> Option<i64>,
    ) -> (Moments, Result<Option<i64>, SingularError>) {
        self.solve(model, i);
        let m = self.moments_from_scratch(model, i);
        match choose(m) {
            Some(u) => (m, self.append_solved(model, i, u, m).map(|()| Some(u))),
            None => {
                self.clear_scratch();
                (m, Ok(None))
            }
        }
    }

    /// Append cycle i with value u from the solve in the scratch (`m` its moments).
    fn append_solved(
        &mut self,
        model: &GammaModel,
        i: usize,
        u: i64,
        m: Moments,
    ) -> Result<(), SingularError> {
        // Relative guard: a variance lost to cancellation is not a variance.
        if m.var.is_nan() || m.var <= model.variance(i) * 1e-12 {
            self.clear_scratch();
            return Err(SingularError {
                cycle: i,
                var: m.var,
            });
        }
        let q = self.diag.len() as u32;
        let s = m.var.sqrt();
        // Store the whole structural pattern (exact zeros too), so that the elimination
        // tree (first off-diagonal of each column) stays the structural one.
        for k in 0..self.pattern.len() {
            let p = self.pattern[k] as usize;
            self.cols[p].push((q, self.y[p]));
            self.nnz += 1;
            if self.parent[p] == NONE {
                self.parent[p] = q;
            }
        }
        self.clear_scratch();
        if self.pos.len() <= i {
            self.pos.resize(i + 1, NONE);
        }
        self.pos[i] = q;
        self.cycle_at.push(i as u32);
        self.value.push(u);
        self.cols.push(Vec::new());
        self.nnz += 1;
        self.parent.push(NONE);
        self.diag.push(s);
        self.z.push((u as f64 - m.mean) / s);
        Ok(())
    }

    /// Rebuild L in a fill-reducing order of the determined cycles (same values), with the
    /// `recent` highest-numbered cycles ordered last (each part by approximate minimum
    /// degree). The conditional moments do not depend on the order, so every query answers
    /// as before (to rounding); z, the factor and the sequential deviations are those of the
    /// new order. Keeping the newest cycles at the end of the elimination order keeps the
    /// rows appended afterwards — new loops, mostly next to recent ones — short (the idea of
    /// iSAM2's constrained ordering). On error nothing changes.
    pub fn reorder(&mut self, model: &GammaModel, recent: usize) -> Result<(), SingularError> {
        *self = Self::rebuilt(model, &self.determined(), recent)?;
        Ok(())
    }

    /// The determined cycles with their values, in determination order.
    pub fn determined(&self) -> Vec<(usize, i64)> {
        self.cycle_at
            .iter()
            .zip(&self.value)
            .map(|(&c, &v)| (c as usize, v))
            .collect()
    }

    /// A factor of the given determined cycles in a fill-reducing order, with the `recent`
    /// highest-numbered ones last ([`Self::reorder`]); `model` needs only the rows of those
    /// cycles, so a snapshot of it can be rebuilt on another thread.
    pub fn rebuilt(
        model: &GammaModel,
        determined: &[(usize, i64)],
        recent: usize,
    ) -> Result<Self, SingularError> {
        let mut sorted = determined.to_vec();
        sorted.sort_unstable();
        let set: Vec<usize> = sorted.iter().map(|&(c, _)| c).collect();
        let split = set.len().saturating_sub(recent);
        let mut order = model.fill_reducing_order(&set[..split]);
        order.extend(model.fill_reducing_order(&set[split..]));
        let mut fresh = Conditioner::new();
        for i in order {
            let v = sorted
                .binary_search_by_key(&i, |&(c, _)| c)
                .map_or(0, |p| sorted[p].1);
            fresh.determine(model, i, v)?;
        }
        Ok(fresh)
    }

    /// Conditional means and covariance of the undetermined cycles `set` (dense, row-major
    /// `|set| × |set|`): `Q_ij = P_ij − y_iᵀ y_j` with `y_i = L⁻¹ P_{U,i}`.
    pub fn joint(&mut self, model: &GammaModel, set: &[usize]) -> (Vec<f64>, Vec<f64>) {
        let k = set.len();
        let mut ys: Vec<Vec<(u32, f64)>> = Vec::with_capacity(k);
        let mut means = Vec::with_capacity(k);
        for &i in set {
            self.solve(model, i);
            means.push(self.moments_from_scratch(model, i).mean);
            self.pattern.sort_unstable();
            ys.push(
                self.pattern
                    .iter()
                    .map(|&p| (p, self.y[p as usize]))
                    .collect(),
            );
            self.clear_scratch();
        }
        let mut q = vec![0.0; k * k];
        for a in 0..k {
            for b in 0..=a {
                let v = model.entry(set[a], set[b]) - sparse_dot(&ys[a], &ys[b]);
                q[a * k + b] = v;
                q[b * k + a] = v;
            }
        }
        (means, q)
    }
}

fn sparse_dot(a: &[(u32, f64)], b: &[(u32, f64)]) -> f64 {
    let (mut i, mut j, mut s) = (0, 0, 0.0);
    while i < a.len() && j < b.len() {
        match a[i].0.cmp(&b[j].0) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                s += a[i].1 * b[j].1;
                i += 1;
                j += 1;
            }
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cycles::{BasisKind, CycleBasis};
    use crate::sim::{SimConfig, simulate};
    use nalgebra::{DMatrix, DVector};

    fn model(poses: usize, seed: u64) -> (GammaModel, Vec<Cycle>) {
        let w = simulate(&SimConfig::new(poses, seed)).unwrap();
        let g = &w.graph;
        let s2: Vec<f64> = g.edges().iter().map(|e| e.sigma2()).collect();
        let d: Vec<f64> = g.edges().iter().map(|e| e.delta()).collect();
        let b = CycleBasis::build(g, BasisKind::Odometric);
        // Dense reference of P_γ = C P Cᵀ / 4π².
        let (l, m) = (b.cycles.len(), g.edge_count());
        let mut c = DMatrix::<f64>::zeros(l, m);
        for (t, cy) in b.cycles.iter().enumerate() {
            for term in &cy.terms {
                c[(t, term.edge as usize)] = f64::from(term.sign);
            }
        }
        let p = DMatrix::from_diagonal(&DVector::from_vec(s2.clone()));
        let dense = &c * p * c.transpose() / FOUR_PI2;
        let gm = GammaModel::from_cycles(&b.cycles, &s2, &d);
        for i in 0..l {
            for j in 0..l {
                assert!((gm.entry(i, j) - dense[(i, j)]).abs() < 1e-14);
            }
        }
        (gm, b.cycles)
    }

    #[test]
    fn conditioning_matches_dense_schur_complement() {
        let (gm, _) = model(120, 3);
        let l = gm.len();
        let mut p = DMatrix::<f64>::zeros(l, l);
        for i in 0..l {
            for &(j, v) in gm.row(i) {
                p[(i, j as usize)] = v;
            }
        }
        let mut cond = Conditioner::new();
        // Determine every other cycle with arbitrary integers, in a scrambled order.
        let det: Vec<usize> = (0..l).rev().filter(|i| i % 2 == 0).collect();
        for (k, &i) in det.iter().enumerate() {
            cond.determine(&gm, i, (k % 3) as i64 - 1).unwrap();
        }
        let u: Vec<usize> = det.clone();
        let a: Vec<usize> = (0..l).filter(|i| i % 2 == 1).collect();
        let puu = p.select_rows(&u).select_columns(&u);
        let pau = p.select_rows(&a).select_columns(&u);
        let diff = DVector::from_iterator(
            u.len(),
            u.iter()
                .enumerate()
                .map(|(k, &i)| ((k % 3) as f64 - 1.0) - gm.mu()[i]),
        );
        let chol = puu.clone().cholesky().unwrap();
        let mean_ref = &pau * chol.solve(&diff);
        let var_ref = &p.select_rows(&a).select_columns(&a) - &pau * chol.solve(&pau.transpose());
        for (k, &i) in a.iter().enumerate() {
            let m = cond.moments(&gm, i);
            assert!(
                (m.mean - gm.mu()[i] - mean_ref[k]).abs() < 1e-10,
                "mean of {i}"
            );
            assert!((m.var - var_ref[(k, k)]).abs() < 1e-12, "var of {i}");
        }
        let (_, q) = cond.joint(&gm, &a);
        for x in 0..a.len() {
            for y in 0..a.len() {
                assert!((q[x * a.len() + y] - var_ref[(x, y)]).abs() < 1e-12);
            }
        }
        let recount = cond.diag.len() + cond.cols.iter().map(Vec::len).sum::<usize>();
        assert_eq!(cond.factor_nnz(), recount);
        let chi2_ref = diff.dot(&chol.solve(&diff));
        assert!((cond.chi2() - chi2_ref).abs() < 1e-9 * chi2_ref.max(1.0));
        assert_eq!(cond.value(det[0]), Some(-1));
        assert_eq!(cond.value(a[0]), None);
    }

    /// A factor rebuilt at once in a fill-reducing order holds what determining the cycles one
    /// by one does: the same moments for every other cycle, the same χ², a structural pattern
    /// whose elimination tree serves later determinations (checked against one determined
    /// after the rebuild), and the same values. It fails where the one-by-one path fails.
    #[test]
    fn a_rebuilt_factor_conditions_as_the_incremental_one() {
        let (gm, _) = model(150, 5);
        let l = gm.len();
        let det: Vec<usize> = (0..l).filter(|i| i % 3 != 1).collect();
        let mut one_by_one = Conditioner::new();
        for &i in &det {
            one_by_one.determine(&gm, i, (i % 5) as i64 - 2).unwrap();
        }
        let mut rebuilt = Conditioner::rebuilt(&gm, &one_by_one.determined(), 0).unwrap();
        assert_ne!(rebuilt.order(), one_by_one.order(), "a new order");
        assert!((rebuilt.chi2() - one_by_one.chi2()).abs() < 1e-9 * one_by_one.chi2().max(1.0));
        let close = |a: Moments, b: Moments| {
            (a.mean - b.mean).abs() < 1e-10 && (a.var - b.var).abs() < 1e-12 * b.var.max(1.0)
        };
        let rest: Vec<usize> = (0..l).filter(|i| i % 3 == 1).collect();
        for &i in &rest {
            assert!(
                close(rebuilt.moments(&gm, i), one_by_one.moments(&gm, i)),
                "{i}"
            );
        }
        // Determinations after the rebuild use its elimination tree.
        for &i in &rest[..rest.len() / 2] {
            let a = rebuilt.determine(&gm, i, 1).unwrap();
            let b = one_by_one.determine(&gm, i, 1).unwrap();
            assert!(close(a, b), "{i}");
        }
        for &i in &rest[rest.len() / 2..] {
            assert!(
                close(rebuilt.moments(&gm, i), one_by_one.moments(&gm, i)),
                "{i}"
            );
            assert_eq!(rebuilt.value(i), None);
        }
        assert_eq!(rebuilt.value(det[3]), Some((det[3] % 5) as i64 - 2));
        let recount = rebuilt.diag.len() + rebuilt.cols.iter().map(Vec::len).sum::<usize>();
        assert_eq!(rebuilt.factor_nnz(), recount);
        // A cycle listed twice is singular, as determining it twice is.
        let mut twice = one_by_one.determined();
        twice.push(twice[0]);
        assert!(Conditioner::rebuilt(&gm, &twice, 0).is_err());
    }

    #[test]
    fn singular_determination_is_rejected_without_change() {
        let (gm, _) = model(60, 4);
        let mut cond = Conditioner::new();
        cond.determine(&gm, 0, 0).unwrap();
        let before = (cond.len(), cond.chi2());
        // Determining the same cycle twice: conditional variance 0.
        assert!(cond.determine(&gm, 0, 1).is_err());
        assert_eq!((cond.len(), cond.chi2()), before);
    }
}
