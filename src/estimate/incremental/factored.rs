//! A factor built at once, beside the live one: the renewal of [`SqrtInfo`]'s order.
//!
//! Given a fill-reducing order (approximate minimum degree of the graph, with the newest
//! variables last: [`fill_reducing_order`]) and the rows `a_r` with right-hand sides `β_r`,
//!
//! ```text
//! AᵀA = L Lᵀ   (in that order, a sparse Cholesky),   R = Lᵀ,   Rᵀ d = Aᵀβ,
//! ```
//!
//! one symbolic analysis (faer's elimination tree and column counts) for every lane, then an
//! up-looking simplicial Cholesky of all lanes at once written straight into R's rows
//! ([`SqrtInfo::rows_up_looking`]), or faer's supernodal one per lane (dense blocks of columns
//! with a common pattern) where the flops per nonzero of L make the blocks pay
//! ([`supernodal_pays`]). Rows are rotated in instead only by the caller, when the Cholesky meets
//! a non-positive pivot.

use super::{Lanes, Row, SqrtInfo, is_zero};

impl<const K: usize, const L: usize> SqrtInfo<K, L> {
    /// The factor of the rows given, in the variable order `order`, computed at once: the
    /// normal equations `AᵀA` in that order factored by a sparse Cholesky (simplicial, or where
    /// its flops per nonzero make dense blocks pay faer's supernodal one: [`supernodal_pays`]),
    /// `R = Lᵀ`, then d by one forward solve. Far cheaper than rotating every row in; `None`
    /// when the Cholesky meets a non-positive pivot (extreme weights: the caller rotates the
    /// rows in instead, which is the better-conditioned QR).
    pub fn factored<const N: usize, C: Lanes<L>>(
        order: &[usize],
        rows: impl Iterator<Item = ([(usize, C); N], [f64; K])> + Clone,
    ) -> Option<Self> {
        Self::factored_by(order, rows, Cholesky::Auto)
    }

    /// [`Self::factored`] by the given kind of Cholesky factorization.
    pub(super) fn factored_by<const N: usize, C: Lanes<L>>(
        order: &[usize],
        rows: impl Iterator<Item = ([(usize, C); N], [f64; K])> + Clone,
        cholesky: Cholesky,
    ) -> Option<Self> {
        use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
        use faer::sparse::SymbolicSparseColMatRef;
        use faer::sparse::linalg::cholesky::{simplicial, supernodal};
        let mut f = Self::new();
        for &v in order {
            f.push_variable(v);
        }
        let n = order.len();
        // The upper triangle of AᵀA in positions, column by column: the diagonal summed apart,
        // the entries above it sorted (stably: repeats — parallel edges — summed in the rows'
        // order), every diagonal present. The products are listed as they come, then counted
        // into their columns (stable) and each column sorted by row: faer's triplet sort took
        // a third of this function's time, and a small vector per column (spilling to the heap
        // past four entries) 0.33 against 0.26 ms on M3500.
        let mut diag = vec![[0.0; L]; n];
        let mut products: Vec<(u32, u32, [f64; L])> = Vec::new();
        let mut col_ptr = vec![0usize; n + 1];
        for (entries, _) in rows.clone() {
            for &(u, a) in &entries {
                for &(v, b) in &entries {
                    let (pu, pv) = (f.pos_of[u], f.pos_of[v]);
                    let (a, b) = (a.lanes(), b.lanes());
                    if is_zero(&a) || is_zero(&b) {
                        continue;
                    }
                    let ab: [f64; L] = std::array::from_fn(|l| a[l] * b[l]);
                    if pu == pv {
                        for (d, x) in diag[pu as usize].iter_mut().zip(ab) {
                            *d += x;
                        }
                    } else if pu < pv {
                        products.push((pv, pu, ab));
                        col_ptr[pv as usize + 1] += 1;
                    }
                }
            }
        }
        for c in 0..n {
            col_ptr[c + 1] += col_ptr[c];
        }
        let mut by_column = vec![(0u32, [0.0; L]); products.len()];
        let mut next = col_ptr.clone();
        for &(c, r, x) in &products {
            by_column[next[c as usize]] = (r, x);
            next[c as usize] += 1;
        }
        drop(products);
        let mut row_idx: Vec<usize> = Vec::with_capacity(by_column.len() + n);
        // The lanes' values apart (faer takes one slice per matrix).
        let mut a_values: [Vec<f64>; L] =
            std::array::from_fn(|_| Vec::with_capacity(by_column.len() + n));
        for p in 0..n {
            let col = &mut by_column[col_ptr[p]..col_ptr[p + 1]];
            col.sort_by_key(|&(r, _)| r);
            col_ptr[p] = row_idx.len();
            let start = row_idx.len();
            for &(r, x) in col.iter() {
                let r = r as usize;
                if row_idx.len() > start && row_idx.last() == Some(&r) {
                    for (values, x) in a_values.iter_mut().zip(x) {
                        if let Some(last) = values.last_mut() {
                            *last += x;
                        }
                    }
                } else {
                    row_idx.push(r);
                    for (values, x) in a_values.iter_mut().zip(x) {
                        values.push(x);
                    }
                }
            }
            row_idx.push(p);
            for (values, x) in a_values.iter_mut().zip(diag[p]) {
                values.push(x);
            }
        }
        col_ptr[n] = row_idx.len();
        drop(by_column);
        let pattern = SymbolicSparseColMatRef::new_checked(n, n, &col_ptr, None, &row_idx);
        let nnz = row_idx.len();
        let mut mem = MemBuffer::try_new(StackReq::any_of(&[
            simplicial::prefactorize_symbolic_cholesky_scratch::<usize>(n, nnz),
            supernodal::factorize_supernodal_symbolic_cholesky_scratch::<usize>(n),
        ]))
        .ok()?;
        let stack = MemStack::new(&mut mem);
        let (mut etree, mut counts) = (vec![0isize; n], vec![0usize; n]);
        let tree =
            simplicial::prefactorize_symbolic_cholesky(&mut etree, &mut counts, pattern, stack);
        let normal = NormalEquations {
            pattern,
            values: &a_values,
            tree,
            counts: &counts,
        };
        let supernodal = match cholesky {
            Cholesky::Auto => supernodal_pays(&counts),
            Cholesky::Simplicial => false,
            Cholesky::Supernodal => true,
        };
        if supernodal {
            f.rows_supernodal(normal, stack)?;
        } else {
            f.rows_up_looking(normal)?;
        }
        if f.diag
            .iter()
            .flatten()
            .any(|&r| !(r > 0.0 && r.is_finite()))
        {
            return None;
        }
        f.reset_rhs(rows);
        Some(f)
    }
}

/// Which sparse Cholesky factorization [`SqrtInfo::factored`] computes R with (the two
/// named ones forced by tests only).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(not(test), allow(dead_code))]
pub(super) enum Cholesky {
    /// Supernodal when [`supernodal_pays`], simplicial otherwise.
    Auto,
    /// Row by row of L, every lane at once ([`SqrtInfo::rows_up_looking`]).
    Simplicial,
    /// By dense blocks of columns with a common pattern (faer's supernodal `LLᵀ`).
    Supernodal,
}

/// The normal equations `AᵀA` of [`SqrtInfo::factored`]: their upper triangle by columns (every
/// diagonal present, rows ascending) and its values, one slice per lane; and their elimination
/// tree and the column counts of L (diagonal included).
#[derive(Clone, Copy)]
struct NormalEquations<'a, const L: usize> {
    pattern: faer::sparse::SymbolicSparseColMatRef<'a, usize>,
    values: &'a [Vec<f64>; L],
    tree: faer::sparse::linalg::cholesky::simplicial::EliminationTreeRef<'a, usize>,
    counts: &'a [usize],
}

/// Flops of the factorization per nonzero of L beyond which [`SqrtInfo::factored`] factors
/// supernodally: faer's own rule for choosing (its high-level symbolic Cholesky with the
/// automatic threshold), the flops counted from the column counts as faer counts them. The
/// dense blocks pay where the top of the elimination tree is dense. Measured on each graph's
/// final factor (three right-hand sides, one lane, the whole of [`SqrtInfo::factored`] after
/// the order, one thread, 2026-12-05): the up-looking factorization against the supernodal one
/// took 1.0 against 2.1 ms on M3500 (7.4 flops per nonzero), 2.4 against 5.0 ms on ais2klinik
/// (3.3), 5.2 against 7.8 ms on city10000 (15.7); 14.5 against 9.6 ms on a 10 000-pose simulated
/// world (51), 84 against 40 ms on a 30 000-pose one (79) and 540–564 against 223–224 ms on the
/// 100 000-pose one (126).
const SUPERNODAL_FLOPS_PER_NONZERO: f64 = 40.0;

/// Whether a factor with these column counts (of L, diagonal included) is factored
/// supernodally ([`SUPERNODAL_FLOPS_PER_NONZERO`]).
pub(super) fn supernodal_pays(counts: &[usize]) -> bool {
    let (mut flops, mut nnz) = (0.0, 0.0);
    for &c in counts {
        let c = c as f64;
        flops += c + c * (c + 1.0) / 2.0;
        nnz += c;
    }
    flops > SUPERNODAL_FLOPS_PER_NONZERO * nnz
}

impl<const K: usize, const L: usize> SqrtInfo<K, L> {
    /// R's rows and diagonal from a simplicial Cholesky of the normal equations, every lane in
    /// one pass and written straight into R's rows. Up-looking (row k of L at a time, as
    /// CSparse's `cs_chol`): the pattern of row k of L is the reach of column k of `AᵀA` in the
    /// elimination tree, and its values solve `L₀₀ l = a` over that reach,
    ///
    /// ```text
    /// l_kj = (a_jk − Σ_{i<j} L_ji l_ki) / L_jj   (j in the reach, descendants first),
    /// L_kk = √(a_kk − Σ_j l_kj²),
    /// ```
    ///
    /// each `l_kj` appended to row j of R (column j of L), so the rows come out sorted with no
    /// copy. Written here rather than taken from faer's simplicial Cholesky, which factors one
    /// matrix per call into its own column storage: on M3500's renewals (two lanes, 2 400–3 200
    /// variables) its two numeric passes and the copy into rows took 1.2–1.3 ms of a 3–3.5 ms
    /// build. None when a pivot is not positive and finite.
    fn rows_up_looking(&mut self, normal: NormalEquations<'_, L>) -> Option<()> {
        let n = self.len();
        let parent = normal.tree.into_inner();
        let (col_ptr, row_idx) = (normal.pattern.col_ptr(), normal.pattern.row_idx());
        for (row, &count) in self.rows.iter_mut().zip(normal.counts) {
            row.clear();
            row.pos.reserve_exact(count.saturating_sub(1));
            row.val.reserve_exact(count.saturating_sub(1));
        }
        // The solve's dense scratch, zero outside the current row's reach.
        let mut x = vec![[0.0; L]; n];
        let mut mark = vec![usize::MAX; n];
        // The reach of row k (`reach[top..]`, descendants before ancestors), and one path.
        let mut reach = vec![0usize; n];
        let mut path: Vec<usize> = Vec::new();
        let mut nnz = 0;
        for k in 0..n {
            mark[k] = k;
            let mut top = n;
            let mut dk = [0.0; L];
            let (start, end) = (col_ptr[k], col_ptr[k + 1]);
            for (t, &i) in (start..end).zip(&row_idx[start..end]) {
                let a: [f64; L] = std::array::from_fn(|l| normal.values[l][t]);
                if i == k {
                    dk = a;
                    continue;
                }
                x[i] = a;
                // Up the tree from i to the reach found so far (k itself at the latest).
                let mut j = i;
                while mark[j] != k {
                    path.push(j);
                    mark[j] = k;
                    j = usize::try_from(parent[j]).ok()?;
                }
                // This path's nodes are descendants of those already in the reach: before them.
                while let Some(j) = path.pop() {
                    top -= 1;
                    reach[top] = j;
                }
            }
            for &j in &reach[top..] {
                let xj = std::mem::replace(&mut x[j], [0.0; L]);
                let dj = self.diag[j];
                let lkj: [f64; L] = std::array::from_fn(|l| xj[l] / dj[l]);
                let row = &mut self.rows[j];
                for (&p, v) in row.pos.iter().zip(&row.val) {
                    let xp = &mut x[p as usize];
                    for l in 0..L {
                        xp[l] -= v[l] * lkj[l];
                    }
                }
                for l in 0..L {
                    dk[l] -= lkj[l] * lkj[l];
                }
                if !is_zero(&lkj) {
                    row.push(k as u32, lkj);
                    nnz += 1;
                }
            }
            if !dk.iter().all(|&d| d > 0.0 && d.is_finite()) {
                return None;
            }
            self.diag[k] = dk.map(f64::sqrt);
        }
        self.nnz += nnz;
        Some(())
    }

    /// [`Self::rows_up_looking`] by a supernodal Cholesky: supernode s holds columns
    /// `begin..end` of L as one dense column-major block, rows `begin..end` then its pattern
    /// below them; column j of the block (its entries below the diagonal that are not zero:
    /// the supernodes are relaxed, padded with explicit zeros) is row j of R.
    fn rows_supernodal(
        &mut self,
        normal: NormalEquations<'_, L>,
        stack: &mut faer::dyn_stack::MemStack,
    ) -> Option<()> {
        use faer::dyn_stack::{MemBuffer, MemStack};
        use faer::linalg::cholesky::llt::factor::LltRegularization;
        use faer::sparse::linalg::SymbolicSupernodalParams;
        use faer::sparse::linalg::cholesky::supernodal;
        use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
        let symbolic = supernodal::factorize_supernodal_symbolic_cholesky(
            normal.pattern,
            normal.tree,
            normal.counts,
            stack,
            SymbolicSupernodalParams::default(),
        )
        .ok()?;
        // The numeric factorization reads the lower triangle: the upper one transposed (each
        // column's rows ascending, its diagonal first).
        let n = self.len();
        let (col_ptr, row_idx) = (normal.pattern.col_ptr(), normal.pattern.row_idx());
        let nnz = row_idx.len();
        let mut lower_ptr = vec![0usize; n + 1];
        for &r in row_idx {
            lower_ptr[r + 1] += 1;
        }
        for c in 0..n {
            lower_ptr[c + 1] += lower_ptr[c];
        }
        let mut next = lower_ptr[..n].to_vec();
        let mut lower_idx = vec![0usize; nnz];
        let mut lower_values: [Vec<f64>; L] = std::array::from_fn(|_| vec![0.0; nnz]);
        for c in 0..n {
            for t in col_ptr[c]..col_ptr[c + 1] {
                let r = row_idx[t];
                let o = next[r];
                lower_idx[o] = c;
                for (lower, upper) in lower_values.iter_mut().zip(normal.values) {
                    lower[o] = upper[t];
                }
                next[r] += 1;
            }
        }
        let lower = SymbolicSparseColMatRef::new_checked(n, n, &lower_ptr, None, &lower_idx);
        let par = faer::Par::Seq;
        let mut mem = MemBuffer::try_new(supernodal::factorize_supernodal_numeric_llt_scratch::<
            usize,
            f64,
        >(&symbolic, par, Default::default()))
        .ok()?;
        let stack = MemStack::new(&mut mem);
        let mut values: [Vec<f64>; L] = std::array::from_fn(|_| vec![0.0; symbolic.len_val()]);
        for (values, lower_values) in values.iter_mut().zip(&lower_values) {
            supernodal::factorize_supernodal_numeric_llt(
                values,
                SparseColMatRef::new(lower, lower_values),
                LltRegularization::default(),
                &symbolic,
                par,
                stack,
                Default::default(),
            )
            .ok()?;
        }
        let (begin, end, at) = (
            symbolic.supernode_begin(),
            symbolic.supernode_end(),
            symbolic.col_ptr_for_val(),
        );
        for s in 0..symbolic.n_supernodes() {
            let below = symbolic.supernode(s).pattern();
            let (first, width) = (begin[s], end[s] - begin[s]);
            let height = width + below.len();
            for c in 0..width {
                let column = at[s] + c * height;
                let value =
                    |r: usize| -> [f64; L] { std::array::from_fn(|l| values[l][column + r]) };
                let j = first + c;
                self.diag[j] = value(c);
                let mut row = Row {
                    pos: Vec::with_capacity(height - c - 1),
                    val: Vec::with_capacity(height - c - 1),
                };
                let positions = (first + c + 1..first + width).chain(below.iter().copied());
                for (r, p) in (c + 1..height).zip(positions) {
                    let v = value(r);
                    if !is_zero(&v) {
                        row.push(p as u32, v);
                    }
                }
                debug_assert!(row.pos.windows(2).all(|p| p[0] < p[1]), "row {j} unsorted");
                self.nnz += row.len();
                self.rows[j] = row;
            }
        }
        Some(())
    }
}

/// A fill-reducing order of the variables `0..n` of a graph with the given edges (approximate
/// minimum degree, faer), with the variables in `last` appended at the end in that order.
pub(crate) fn fill_reducing_order(
    n: usize,
    edges: &[(usize, usize)],
    last: &[usize],
) -> Vec<usize> {
    let p = FreePattern::new(n, edges, last);
    let mut order: Vec<usize> = match amd_order(&p.col_ptr, &p.row_idx) {
        Some(perm) => perm.iter().map(|&i| p.free[i]).collect(),
        None => p.free.clone(),
    };
    order.extend_from_slice(last);
    order
}

/// The graph of the variables `0..n` not in `last` (the free ones), numbered by their rank
/// among them: a symmetric pattern by columns, each with its diagonal, rows ascending, no
/// repeats (the form faer's minimum degree takes).
pub(crate) struct FreePattern {
    /// The free variables, ascending: local index → variable.
    pub free: Vec<usize>,
    /// Column starts (one past the last at the end).
    pub col_ptr: Vec<usize>,
    /// Rows of each column.
    pub row_idx: Vec<usize>,
}

impl FreePattern {
    /// The pattern of the graph on `0..n` with the given edges, the variables in `last` left
    /// out.
    pub fn new(n: usize, edges: &[(usize, usize)], last: &[usize]) -> Self {
        let mut is_last = vec![false; n];
        for &v in last {
            is_last[v] = true;
        }
        let mut local = vec![usize::MAX; n];
        let mut free = Vec::new();
        for v in 0..n {
            if !is_last[v] {
                local[v] = free.len();
                free.push(v);
            }
        }
        let k = free.len();
        // Counted into place rather than collected into a list per node.
        let mut col_ptr = vec![0usize; k + 1];
        let pairs = || {
            edges.iter().filter_map(|&(a, b)| {
                let (la, lb) = (local[a], local[b]);
                (la != usize::MAX && lb != usize::MAX && la != lb).then_some((la, lb))
            })
        };
        for (la, lb) in pairs() {
            col_ptr[la + 1] += 1;
            col_ptr[lb + 1] += 1;
        }
        for c in 0..k {
            col_ptr[c + 1] += col_ptr[c] + 1;
        }
        let mut row_idx = vec![0usize; col_ptr[k]];
        let mut next: Vec<usize> = col_ptr[..k].to_vec();
        for c in 0..k {
            row_idx[next[c]] = c;
            next[c] += 1;
        }
        for (la, lb) in pairs() {
            row_idx[next[la]] = lb;
            next[la] += 1;
            row_idx[next[lb]] = la;
            next[lb] += 1;
        }
        // Sort each column and drop repeats (parallel edges), compacting in place.
        let mut write = 0;
        let mut start = 0;
        for c in 0..k {
            let end = col_ptr[c + 1];
            row_idx[start..end].sort_unstable();
            col_ptr[c] = write;
            let mut last = usize::MAX;
            for i in start..end {
                let r = row_idx[i];
                if r != last {
                    row_idx[write] = r;
                    write += 1;
                    last = r;
                }
            }
            start = end;
        }
        col_ptr[k] = write;
        row_idx.truncate(write);
        Self {
            free,
            col_ptr,
            row_idx,
        }
    }

    /// Number of free variables.
    pub fn len(&self) -> usize {
        self.free.len()
    }

    /// The local neighbours of local variable `i`, itself included.
    pub fn column(&self, i: usize) -> &[usize] {
        &self.row_idx[self.col_ptr[i]..self.col_ptr[i + 1]]
    }
}

/// Approximate minimum degree (faer) of a symmetric pattern given by columns (`col_ptr`,
/// `row_idx`, rows ascending): the permutation, or None if faer refuses it. The one place
/// both the orientation factor and the factor of P_γ get their fill-reducing orders.
pub(crate) fn amd_order(col_ptr: &[usize], row_idx: &[usize]) -> Option<Vec<usize>> {
    use faer::dyn_stack::{MemBuffer, MemStack};
    use faer::sparse::SymbolicSparseColMatRef;
    use faer::sparse::linalg::amd;
    let k = col_ptr.len().checked_sub(1)?;
    let pattern = SymbolicSparseColMatRef::new_checked(k, k, col_ptr, None, row_idx);
    let (mut perm, mut perm_inv) = (vec![0usize; k], vec![0usize; k]);
    let mut mem = MemBuffer::new(amd::order_scratch::<usize>(k, row_idx.len()));
    amd::order(
        &mut perm,
        &mut perm_inv,
        pattern,
        amd::Control::default(),
        MemStack::new(&mut mem),
    )
    .ok()
    .map(|_| perm)
}
