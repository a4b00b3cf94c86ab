//! Integrality of a cycle basis: `|det C_L|` exactly, and an exact integer solver for
//! `C k = γ` (method [§5](crate::method#5-wraps-and-orientations)), used by [`crate::wraps::WrapSolver`].
//!
//! **Invariance.** `C = Z F_T` for any spanning tree T, with `F_T` the fundamental basis of T
//! (a network matrix, totally unimodular) and `Z` integral, so by Cauchy–Binet every nonzero
//! `ℓ × ℓ` minor of C — `det C_L` for any tree, or any nonsingular set of ℓ edge columns — has
//! the same absolute value `|det Z|`, the index of the lattice spanned by the cycles in the
//! integer cycle lattice. The basis is **integral** (every integer γ has an integer k) iff it
//! is 1. So no spanning tree is needed: columns are chosen where elimination is cheapest.
//!
//! **Peeling** (the triangular part). An edge that lies in exactly one remaining cycle is that
//! cycle's designated edge; the cycle is removed (`O(total length)` with a queue). A designated
//! edge lies only in its own cycle and in cycles removed before it, so in *reverse* peel order
//! each cycle uses its designated edge and otherwise only edges designated *earlier* or never
//! designated, and no core cycle (never removed) uses a designated edge, so
//! `C = [[C_core, 0], [*, T]]` (core cycles first) with `T` triangular with ±1 diagonal, and
//! `|det C_L| = |det C_core|`. Fundamental and incremental bases peel completely; on pose
//! graphs the MCB does too, or leaves a small core.
//!
//! **Core** (the rest): fraction-free integer elimination with unimodular row operations only
//! (add an integer multiple of a row; Euclid steps `gcd` on two rows), pivots of value ±1
//! preferred, so `|det| = Π |pivots|` exactly. Entries are `i64` with checked arithmetic
//! (an overflow is reported, never wrapped). The row operations are recorded and replayed on
//! γ; back substitution divides exactly or reports a fractional solution. Cost
//! `O(K² · r)` for a core of K cycles with rows of length r after fill.

use smallvec::SmallVec;

use super::Cycle;

/// A cycle's designated edge and its sign in the cycle.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Designated {
    /// The cycle (index in the basis).
    pub cycle: u32,
    /// The edge no later cycle uses.
    pub edge: u32,
    /// Its sign in the cycle (±1).
    pub sign: i8,
}

/// Peeling: `(core cycles ascending, peeled cycles in triangular order with their designated
/// edges)`; see the module docs.
pub(crate) fn peel(cycles: &[Cycle], edges: usize) -> (Vec<u32>, Vec<Designated>) {
    // Cycles through each edge (CSR).
    let mut count = vec![0u32; edges];
    for c in cycles {
        for t in &c.terms {
            count[t.edge as usize] += 1;
        }
    }
    let mut start = vec![0usize; edges + 1];
    for e in 0..edges {
        start[e + 1] = start[e] + count[e] as usize;
    }
    let mut fill = start.clone();
    let mut through = vec![0u32; start[edges]];
    for (t, c) in cycles.iter().enumerate() {
        for term in &c.terms {
            let e = term.edge as usize;
            through[fill[e]] = t as u32;
            fill[e] += 1;
        }
    }
    let mut removed = vec![false; cycles.len()];
    let mut queue: std::collections::VecDeque<u32> = (0..edges as u32)
        .filter(|&e| count[e as usize] == 1)
        .collect();
    let mut order = Vec::with_capacity(cycles.len());
    while let Some(e) = queue.pop_front() {
        if count[e as usize] != 1 {
            continue;
        }
        let Some(&t) = through[start[e as usize]..start[e as usize + 1]]
            .iter()
            .find(|&&t| !removed[t as usize])
        else {
            continue;
        };
        removed[t as usize] = true;
        let c = &cycles[t as usize];
        let sign = c.terms.iter().find(|x| x.edge == e).map_or(1, |x| x.sign);
        order.push(Designated {
            cycle: t,
            edge: e,
            sign,
        });
        for term in &c.terms {
            let f = term.edge as usize;
            count[f] -= 1;
            if count[f] == 1 {
                queue.push_back(f as u32);
            }
        }
    }
    let core = (0..cycles.len() as u32)
        .filter(|&t| !removed[t as usize])
        .collect();
    // The designated edge of s lies only in s and in cycles peeled before s; reversed, every
    // cycle uses only designated edges of cycles before it (lower triangular).
    order.reverse();
    (core, order)
}

/// Why the integer elimination failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum IntegerError {
    /// The cycles are linearly dependent (not a basis).
    #[error("the cycles are linearly dependent (cycle {cycle})")]
    Dependent {
        /// A cycle in the dependent set.
        cycle: usize,
    },
    /// An entry exceeded the 64-bit range during elimination.
    #[error("integer overflow in the exact elimination")]
    Overflow,
    /// The solution of `C k = γ` is not integral.
    #[error(
        "C k = γ has no integer solution for this γ (cycle {cycle}): the basis is not integral"
    )]
    Fractional {
        /// Basis index of the cycle whose equation failed to divide exactly.
        cycle: usize,
    },
}

type Row = SmallVec<[(u32, i64); 8]>;

/// A recorded unimodular row operation.
#[derive(Clone, Copy, Debug)]
enum Op {
    /// `row[t] += f · row[s]`.
    AddMul { t: u32, s: u32, f: i64 },
    /// `(row[a], row[b]) ← (p·row[a] + q·row[b], r·row[a] + s·row[b])` with `ps − qr = ±1`.
    Mix { a: u32, b: u32, m: [i64; 4] },
}

/// Exact integer elimination of a set of cycles (rows) over edge columns.
#[derive(Clone, Debug)]
pub(crate) struct IntegerLu {
    /// Basis index of each local row.
    cycle: Vec<u32>,
    ops: Vec<Op>,
    /// `(row, column)` of each pivot, in elimination order.
    pivots: Vec<(u32, u32)>,
    /// The eliminated rows.
    rows: Vec<Row>,
    /// `Π |pivot|`.
    abs_det: u128,
}

fn ck(x: Option<i64>) -> Result<i64, IntegerError> {
    x.ok_or(IntegerError::Overflow)
}

/// `a·x + b·y` for sparse rows, dropping zeros.
fn combine(a: i64, x: &Row, b: i64, y: &Row) -> Result<Row, IntegerError> {
    let mut out = Row::new();
    let (mut i, mut j) = (0, 0);
    while i < x.len() || j < y.len() {
        let (c, v) = match (x.get(i), y.get(j)) {
            (Some(&(cx, vx)), Some(&(cy, _))) if cx < cy => {
                i += 1;
                (cx, ck(a.checked_mul(vx))?)
            }
            (Some(&(cx, _)), Some(&(cy, vy))) if cy < cx => {
                j += 1;
                (cy, ck(b.checked_mul(vy))?)
            }
            (Some(&(cx, vx)), Some(&(_, vy))) => {
                i += 1;
                j += 1;
                (
                    cx,
                    ck(ck(a.checked_mul(vx))?.checked_add(ck(b.checked_mul(vy))?))?,
                )
            }
            (Some(&(cx, vx)), None) => {
                i += 1;
                (cx, ck(a.checked_mul(vx))?)
            }
            (None, Some(&(cy, vy))) => {
                j += 1;
                (cy, ck(b.checked_mul(vy))?)
            }
            (None, None) => break,
        };
        if v != 0 {
            out.push((c, v));
        }
    }
    Ok(out)
}

fn entry(row: &Row, c: u32) -> i64 {
    row.binary_search_by_key(&c, |x| x.0)
        .map_or(0, |k| row[k].1)
}

impl IntegerLu {
    /// Eliminate the given cycles of the basis (rows) over their edges.
    pub(crate) fn new(all: &[Cycle], which: &[u32]) -> Result<Self, IntegerError> {
        let mut rows: Vec<Row> = which
            .iter()
            .map(|&t| {
                let mut r: Row = all[t as usize]
                    .terms
                    .iter()
                    .map(|x| (x.edge, i64::from(x.sign)))
                    .collect();
                r.sort_unstable_by_key(|x| x.0);
                r
            })
            .collect();
        let n = rows.len();
        let mut active = vec![true; n];
        let mut ops = Vec::new();
        let mut pivots = Vec::with_capacity(n);
        let mut abs_det: u128 = 1;
        for _ in 0..n {
            // Pivot: the first ±1 entry of the shortest active row; else the smallest entry.
            let mut best: Option<(u32, u32, i64, usize)> = None;
            for (r, row) in rows.iter().enumerate() {
                if !active[r] {
                    continue;
                }
                let Some(&(c, v)) = row.iter().min_by_key(|x| x.1.unsigned_abs()) else {
                    return Err(IntegerError::Dependent {
                        cycle: which[r] as usize,
                    });
                };
                let key = (v.unsigned_abs() != 1, row.len());
                if best.is_none_or(|(_, _, bv, bl)| key < (bv.unsigned_abs() != 1, bl)) {
                    best = Some((r as u32, c, v, row.len()));
                }
            }
            let Some((p, c, _, _)) = best else { break };
            // Clear column c from every other active row with unimodular operations.
            for r in 0..n as u32 {
                if r == p || !active[r as usize] {
                    continue;
                }
                loop {
                    let a = entry(&rows[r as usize], c);
                    if a == 0 {
                        break;
                    }
                    let pv = entry(&rows[p as usize], c);
                    if a % pv == 0 {
                        let f = -(a / pv);
                        rows[r as usize] = combine(1, &rows[r as usize], f, &rows[p as usize])?;
                        ops.push(Op::AddMul { t: r, s: p, f });
                    } else {
                        // Euclid step: (row_p, row_r) ← (row_r − q·row_p, row_p), a
                        // unimodular 2×2 operation; the pivot slot p keeps the remainder.
                        let q = a / pv;
                        let new_p = combine(1, &rows[r as usize], -q, &rows[p as usize])?;
                        let old_p = std::mem::replace(&mut rows[p as usize], new_p);
                        rows[r as usize] = old_p;
                        ops.push(Op::Mix {
                            a: p,
                            b: r,
                            m: [-q, 1, 1, 0],
                        });
                    }
                }
            }
            let pv = entry(&rows[p as usize], c);
            abs_det = abs_det
                .checked_mul(u128::from(pv.unsigned_abs()))
                .ok_or(IntegerError::Overflow)?;
            active[p as usize] = false;
            pivots.push((p, c));
        }
        Ok(Self {
            cycle: which.to_vec(),
            ops,
            pivots,
            rows,
            abs_det,
        })
    }

    /// Number of eliminated cycles.
    pub(crate) fn len(&self) -> usize {
        self.cycle.len()
    }

    /// `Π |pivot|`: the absolute determinant of the eliminated system.
    pub(crate) fn abs_det(&self) -> u128 {
        self.abs_det
    }

    /// Solve the rows' equations `Σ_e c_e k_e = γ_t` for the eliminated rows, writing k on the
    /// pivot columns (other columns are left as they are in `k`, which must be zero there).
    /// `gamma` is indexed by basis cycle.
    pub(crate) fn solve(&self, gamma: &[i64], k: &mut [i64]) -> Result<(), IntegerError> {
        let mut rhs: Vec<i64> = self.cycle.iter().map(|&t| gamma[t as usize]).collect();
        for op in &self.ops {
            match *op {
                Op::AddMul { t, s, f } => {
                    rhs[t as usize] =
                        ck(rhs[t as usize].checked_add(ck(f.checked_mul(rhs[s as usize]))?))?;
                }
                Op::Mix { a, b, m } => {
                    let (x, y) = (rhs[a as usize], rhs[b as usize]);
                    let nx = ck(ck(m[0].checked_mul(x))?.checked_add(ck(m[1].checked_mul(y))?))?;
                    let ny = ck(ck(m[2].checked_mul(x))?.checked_add(ck(m[3].checked_mul(y))?))?;
                    rhs[a as usize] = nx;
                    rhs[b as usize] = ny;
                }
            }
        }
        for &(r, c) in self.pivots.iter().rev() {
            let row = &self.rows[r as usize];
            let mut acc = rhs[r as usize];
            let mut pv = 0;
            for &(col, v) in row {
                if col == c {
                    pv = v;
                } else {
                    acc = ck(acc.checked_sub(ck(v.checked_mul(k[col as usize]))?))?;
                }
            }
            // i64::MIN / −1 overflows: checked.
            if pv == 0 || ck(acc.checked_rem(pv))? != 0 {
                return Err(IntegerError::Fractional {
                    cycle: self.cycle[r as usize] as usize,
                });
            }
            k[c as usize] = ck(acc.checked_div(pv))?;
        }
        Ok(())
    }
}
