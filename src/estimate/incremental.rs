//! An incremental square-root information solver: the factor a robot keeps between steps.
//!
//! A linear least-squares problem `min Σ_r (a_rᵀ x − b_r)²` (rows `a_r` sparse, `K`
//! right-hand sides) is kept as `R x = d` with R upper triangular (`RᵀR = AᵀA`,
//! `Rᵀd = Aᵀb`) in a variable order of our choosing, one row of R per variable:
//!
//! - **a new row** `(a, β)` is rotated into R by Givens rotations
//!   (`ρ = hypot(R_kk, w_k)`, `c = R_kk/ρ`, `s = w_k/ρ`; `R_k ← c R_k + s w`, `w ← c w − s R_k`,
//!   and likewise `d_k`, `β`) along the elimination-tree path from the row's first variable to
//!   the root: a row near the end of the order touches a few rows of R only. Row k is
//!   rotated in place when the row's remaining positions are its own, or lie beyond its last
//!   (fill from a newer node's column, appended); otherwise it is rebuilt by a merge. A row
//!   of R keeps its positions and its values apart: the in-place rotation is one loop over
//!   contiguous values, and the row being rotated goes on with row k's pattern without
//!   copying it (about a third less time per entry than interleaved `(position, value)`
//!   pairs, which the rotation had to merge one by one; module `rotate`);
//! - **a removed row** is the same with hyperbolic rotations (`ρ = sqrt(R_kk² − w_k²)`);
//! - **a changed right-hand side** of a row (a wrap that changed) moves d only:
//!   `d ← d + R⁻ᵀ a Δβ`, one sparse forward solve along the same path; for the last row
//!   added (while no row was added or removed since), `d_k += g_k Δβ` with the gains
//!   `g_k = s_k Π_{j<k} c_j` its rotations recorded, without walking R again
//!   ([`SqrtInfo::shift_last_row`]);
//! - **a new variable** is appended at the end of the order with an empty row;
//! - **new right-hand sides for every row** (the rows' β rewritten: a re-linearisation) are one
//!   forward solve `Rᵀ d = Σ a β` ([`SqrtInfo::reset_rhs_in`]), or the same spread over steps
//!   a block of positions at a time while rows keep being rotated in (module `spread`); and
//!   a back-substitution the same way (module `back`).
//!
//! **Lanes.** A factor may hold `L` systems whose rows are the same up to their coefficients
//! (one graph, other weights): one order and one pattern, every entry of R holding a value per
//! lane (`[f64; L]`). A rotation takes a `(c, s)` per lane and turns every lane of a row of R in
//! the same pass over its positions, so the path is walked once for all of them; right-hand
//! side q belongs to lane `min(q, L − 1)`. An entry is absent only when it is zero in every lane
//! (the patterns stay one). [`SqrtInfo::take_work`] counts values, entries times lanes.
//!
//! Reading: `x = R⁻¹ d` by back-substitution. The last variable is `d_n / R_nn` (O(1)); one
//! variable costs its elimination-tree path to the root; all of them one back-substitution.
//! A marginal variance is `‖R⁻ᵀ e_v‖²` (one forward solve along the path). No update factors
//! a matrix from scratch: that is [`SqrtInfo::factored`] alone (module `factored`: a new
//! fill-reducing order, by a sparse Cholesky of the normal equations, up-looking or
//! supernodal), which the owner runs beside the live factor (a
//! renewal) or once at the end of a replay whose answers nobody read.
//!
//! Written by hand because no maintained crate offers a sparse QR/Cholesky factor that can be
//! grown, down-dated and read in place one row at a time (faer's sparse Cholesky refactors).

mod back;
mod dissection;
mod factored;
mod rotate;
mod spread;

pub(crate) use dissection::{Dissection, dissected_order};
pub(crate) use factored::{amd_order, fill_reducing_order};
use rotate::{Undo, align};
use spread::Spread;

/// The off-diagonal entries of a row of R (or of a row being rotated in): positions
/// ascending, and their values apart from them, so that a rotation's arithmetic runs over
/// contiguous values (which the compiler vectorises) and a pattern is compared as one slice.
#[derive(Clone, Debug, PartialEq)]
struct Row<const L: usize = 1> {
    pos: Vec<u32>,
    val: Vec<[f64; L]>,
}

impl<const L: usize> Default for Row<L> {
    fn default() -> Self {
        Self {
            pos: Vec::new(),
            val: Vec::new(),
        }
    }
}

impl<const L: usize> Row<L> {
    #[inline]
    fn len(&self) -> usize {
        self.pos.len()
    }

    #[inline]
    fn clear(&mut self) {
        self.pos.clear();
        self.val.clear();
    }

    #[inline]
    fn push(&mut self, p: u32, v: [f64; L]) {
        self.pos.push(p);
        self.val.push(v);
    }

    /// Entry `i` as `(position, value)`.
    #[inline]
    fn get(&self, i: usize) -> Option<(u32, [f64; L])> {
        Some((*self.pos.get(i)?, self.val[i]))
    }

    /// The first position (a row of R: its elimination-tree parent).
    #[inline]
    fn first(&self) -> Option<u32> {
        self.pos.first().copied()
    }

    /// `(position, value)` pairs in order.
    fn iter(&self) -> impl Iterator<Item = (u32, [f64; L])> + '_ {
        self.pos.iter().copied().zip(self.val.iter().copied())
    }

    /// Ask the CPU to load the row's first entries into its cache, ahead of a pass over R
    /// that reaches it a few rows later ([`PREFETCH_AHEAD`]). Each row's positions and values
    /// are heap blocks of their own, in no order the hardware can guess, so a whole pass (a
    /// back-substitution, a forward solve) otherwise waits for each row's memory in turn.
    /// Every orientation of city10000 at its end (10 000 nodes, 204 000 nonzeros; the median
    /// of 100, a throwaway example, 2026-12-07): 275–305 µs against 392–399 without, from a
    /// cold cache (as after a step's other work); 159–162 against 169–171 µs in a warm one. A
    /// hint: it changes no value.
    #[inline(always)]
    fn prefetch(&self) {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
            let (pos, val) = (
                self.pos.as_ptr().cast::<i8>(),
                self.val.as_ptr().cast::<i8>(),
            );
            // SAFETY: a prefetch reads nothing the program sees and never faults, whatever the
            // address (an empty row's dangling pointer included); these are the row's own.
            unsafe {
                _mm_prefetch::<_MM_HINT_T0>(pos);
                _mm_prefetch::<_MM_HINT_T0>(val);
                _mm_prefetch::<_MM_HINT_T0>(val.wrapping_add(64));
            }
        }
    }

    /// `Σ_j r_j x_j` over the row's entries for `M` right-hand sides at once (lane `lanes[m]`
    /// of the values, `x(j)[m]`), the sum of a back-substitution, in the row's order. Every
    /// back-substitution sums a row here, so a variable's value is the same bits whichever of
    /// them gives it (a whole one, [`SqrtInfo::solve_columns`], or along its path,
    /// [`SqrtInfo::value`]). (Four interleaved partial sums, which overlap the additions'
    /// latency, made a whole back-substitution 6 % faster but M3500's steps, whose paths' rows
    /// are short, slower: p99 84.3 against 80.4 µs, six alternating runs each, 2026-12-07.)
    #[inline(always)]
    fn dot<const M: usize>(&self, lanes: [usize; M], x: impl Fn(usize) -> [f64; M]) -> [f64; M] {
        let mut s = [0.0; M];
        for (&j, v) in self.pos.iter().zip(&self.val) {
            let xj = x(j as usize);
            for m in 0..M {
                s[m] += v[lanes[m]] * xj[m];
            }
        }
        s
    }
}

/// The share of its usual block that a pass spread over steps (modules `spread` and `back`,
/// and the rows of a re-linearisation, module `online::estimate`) takes at a step whose own
/// work on the factor (its rotations) was `own` entries of R, against that usual block, `base`
/// entries: up to [`LIGHT_SHARE`] times as much at a light step (an odometry row, a few dozen
/// entries), falling with the step's own work to nothing beyond the least block
/// ([`MIN_LEVELLED`]; for a re-linearisation's rows, a quarter of their least block) at a step
/// whose rotations visit [`LIGHT_SHARE`] times the block or more (a heavy loop closure):
/// `max(0, LIGHT_SHARE − own/base)`. The slowest steps are loop closures',
/// and a block added to them adds to the p99. Counted work, so the same steps in every run,
/// and the same with one lane or two (entries, not values). Until 2026-12-07 (forty-third
/// session) a heavy step took a quarter of the block: of city10000's 160 slowest loop
/// closures, 66 carried a re-linearisation's block. With nothing (`so2lin stream FILE --json`,
/// robot order, the newest pose read after every step, alternating, twelve rounds): city10000
/// p99 median 93.9 against 99.8 µs (seven lower; worst step 3.19–5.64 against 3.78–8.04 ms),
/// M3500 74.9 against 77.8 µs (eight lower; worst step 1.64–3.95 against 1.42–4.40 ms); the
/// fast pose's mean distance to the exact one 0.048 m on M3500 and 0.104 m on city10000
/// (0.0476 and 0.103 before; `cargo run --release --example fast_pose_lag -- FILE`).
pub(crate) fn levelled(own: u64, base: usize) -> f64 {
    (LIGHT_SHARE - own as f64 / base.max(1) as f64).max(0.0)
}

/// The share of its usual block a pass takes at the lightest steps ([`levelled`]). A pass
/// reads R at about 2.5 ns a value (its values gathered by position), where a rotation
/// takes about 1 ns, so a light step's double block (2, until 2026-12-07) made it as slow as
/// the slowest 1 %: on city10000 28 of the 206 slowest steps were odometry steps carrying a
/// block of the headings' back-substitution (44–66 k values, 0.13–0.25 ms). Measured (`so2lin
/// stream FILE --json`, robot order, the newest pose read after every step, alternating runs,
/// 2026-12-07; 1.25 against 2): city10000 p99 median 123.0 against 129.6 µs (seven runs
/// each; worst step 3.53–3.87 against 3.46–5.36 ms), M3500 98.5 against 103.3 µs (eight;
/// worst step 1.06–2.84 against 1.53–3.98 ms); the fast pose lands its re-linearisation a few
/// steps later, its mean distance to the exact one 0.047 against 0.046 m on M3500 and 0.103
/// against 0.101 m on city10000 (sampled every 25 steps). At 1 the p99 gained no more (123.6
/// and 100.0 µs) and M3500's fast pose was 0.054 m away.
const LIGHT_SHARE: f64 = 1.25;

/// Entries of R a block of a pass spread over steps reads at least, however heavy its step
/// ([`levelled`]).
const MIN_LEVELLED: usize = 4096;

/// How many rows ahead a pass over R prefetches ([`Row::prefetch`]).
const PREFETCH_AHEAD: usize = 8;

/// No position (variable unknown).
const NONE: u32 = u32::MAX;

/// The lane of right-hand side `q` in a factor of `L` lanes: the first `L − 1` right-hand
/// sides have a lane each, the others share the last (with `L = 2` and three right-hand
/// sides: the headings in lane 0, both position components in lane 1).
#[inline(always)]
pub(crate) const fn lane<const L: usize>(q: usize) -> usize {
    if q < L { q } else { L - 1 }
}

/// `g += Σ_r a_r β_r` in the right-hand sides `columns`, by position (`pos_of` maps a variable
/// to its position): the information a forward solve `Rᵀ d = g` starts from, gathered at once
/// ([`SqrtInfo::reset_rhs_in`]) or a block of rows per step (module `spread`).
fn gather<const K: usize, const L: usize, const N: usize, C: Lanes<L>>(
    pos_of: &[u32],
    g: &mut [[f64; K]],
    columns: std::ops::Range<usize>,
    rows: impl IntoIterator<Item = ([(usize, C); N], [f64; K])>,
) {
    // (Internal iteration: a chained or flattened source runs as loops over its parts.)
    rows.into_iter().for_each(|(entries, beta)| {
        for (v, a) in entries {
            let p = pos_of[v] as usize;
            let a = a.lanes();
            for q in columns.clone() {
                g[p][q] += a[lane::<L>(q)] * beta[q];
            }
        }
    });
}

/// A row's coefficient on one variable, per lane: a plain `f64` for a factor of one lane.
pub(crate) trait Lanes<const L: usize>: Copy {
    /// The coefficient in each lane.
    fn lanes(self) -> [f64; L];
}

impl Lanes<1> for f64 {
    #[inline(always)]
    fn lanes(self) -> [f64; 1] {
        [self]
    }
}

impl<const L: usize> Lanes<L> for [f64; L] {
    #[inline(always)]
    fn lanes(self) -> [f64; L] {
        self
    }
}

/// Whether every lane of an entry is zero (the entry is absent).
#[inline(always)]
fn is_zero<const L: usize>(v: &[f64; L]) -> bool {
    v.iter().all(|&x| x == 0.0)
}

/// The removed row made the factor indefinite: it was not (numerically) part of the problem.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
#[error("removing a row made the information matrix indefinite (position {position})")]
pub(crate) struct Indefinite {
    /// Position of the failing pivot.
    pub position: usize,
}

/// Scratch of [`SqrtInfo::whiten3`] (kept zeroed between calls).
#[derive(Clone, Debug, Default)]
pub(crate) struct WhitenScratch {
    w: Vec<[f64; 3]>,
    mark: Vec<bool>,
    reach: Vec<u32>,
}

/// `R x = d` with `K` right-hand sides in `L` lanes (see the module docs).
#[derive(Clone, Debug)]
pub(crate) struct SqrtInfo<const K: usize, const L: usize = 1> {
    pos_of: Vec<u32>,
    var_at: Vec<u32>,
    diag: Vec<[f64; L]>,
    /// Off-diagonal entries of each row of R, positions ascending and greater than the row's
    /// own.
    rows: Vec<Row<L>>,
    d: Vec<[f64; K]>,
    nnz: usize,
    /// Entries of R read or written by rotations and forward solves ([`Self::take_work`]).
    work: u64,
    // Scratch (kept to avoid allocations per step).
    w: Row<L>,
    w_next: Row<L>,
    spare_row: Row<L>,
    /// A row being rotated in, its values placed at the positions of the row of R it meets.
    aligned: Vec<[f64; L]>,
    x: Vec<f64>,
    path: Vec<u32>,
    /// `(position, g)` for the last row added: `d_k` moves by `g Δβ` when that row's
    /// right-hand side moves by `Δβ` (see [`Self::shift_last_row`]).
    gains: Vec<(u32, [f64; L])>,
    /// Whether `gains` still describe R (no row added or removed since).
    gains_valid: bool,
    /// What a tentative row changed ([`Self::try_row`]), to put back on [`Self::undo_row`].
    undo: Option<Box<Undo<K, L>>>,
    /// Whether the rotation in progress records into `undo`.
    recording: bool,
    /// A forward solve of new right-hand sides spread over steps (module `spread`).
    spread: Option<Box<Spread<K, L>>>,
    /// The last spread's state, ended: its arrays for the next (module `spread`).
    spread_spare: Option<Box<Spread<K, L>>>,
    /// A back-substitution spread over steps (module `back`).
    back: Option<Box<back::Back>>,
}

/// What rotating a row `aᵀx = β` into R leaves ([`SqrtInfo::try_row`]): the part of each
/// right-hand side no rotation absorbed, `(β − aᵀx̂)·Πc`, and `Πc`, the product of the
/// rotations' cosines, `1/√(1 + ‖R⁻ᵀa‖²)` (x̂ the solution before the row), per lane.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Leftover<const K: usize, const L: usize = 1> {
    pub residual: [f64; K],
    pub cosines: [f64; L],
}

impl<const K: usize, const L: usize> Leftover<K, L> {
    /// How far the row moved its own prediction `aᵀx̂`, per right-hand side, over `scale`:
    /// `(β − aᵀx̂)(1 − Πc²)/scale` (`1 − Πc² = ‖R⁻ᵀa‖²/(1 + ‖R⁻ᵀa‖²)`, the gain of the
    /// prediction toward the row). For a Laplacian edge row `√w (x_b − x_a) = √w y` with
    /// `scale = √w`, the change of `x̂_b − x̂_a`. Zero when the row's last rotation met an
    /// empty row (`Πc = 0`: a new variable takes the row, nothing else moves).
    pub fn moved_prediction(&self, scale: [f64; L]) -> [f64; K] {
        let gain = self.gain();
        std::array::from_fn(|q| {
            let l = lane::<L>(q);
            if self.cosines[l] == 0.0 {
                0.0
            } else {
                (self.residual[q] / self.cosines[l]) * gain[l] / scale[l]
            }
        })
    }

    /// `1 − Πc²` per lane: how much of a later shift `Δβ` of the row's right-hand side moves
    /// its own prediction (`aᵀ(RᵀR)⁻¹a` with the row in).
    pub fn gain(&self) -> [f64; L] {
        self.cosines.map(|c| 1.0 - c * c)
    }
}

impl<const K: usize, const L: usize> Default for SqrtInfo<K, L> {
    fn default() -> Self {
        Self {
            pos_of: Vec::new(),
            var_at: Vec::new(),
            diag: Vec::new(),
            rows: Vec::new(),
            d: Vec::new(),
            nnz: 0,
            work: 0,
            w: Row::default(),
            w_next: Row::default(),
            spare_row: Row::default(),
            aligned: Vec::new(),
            x: Vec::new(),
            path: Vec::new(),
            gains: Vec::new(),
            gains_valid: false,
            undo: None,
            recording: false,
            spread: None,
            spread_spare: None,
            back: None,
        }
    }
}

impl<const K: usize, const L: usize> SqrtInfo<K, L> {
    /// No variables.
    pub fn new() -> Self {
        Self::default()
    }

    /// Number of variables.
    pub fn len(&self) -> usize {
        self.diag.len()
    }

    /// Room for `additional` more variables without growing its arrays.
    pub fn try_reserve(
        &mut self,
        additional: usize,
    ) -> Result<(), std::collections::TryReserveError> {
        let n = self.diag.len().saturating_add(additional);
        // Variable ids index `pos_of`: room up to the same count.
        self.pos_of
            .try_reserve(n.saturating_sub(self.pos_of.len()))?;
        self.var_at.try_reserve(additional)?;
        self.diag.try_reserve(additional)?;
        self.rows.try_reserve(additional)?;
        self.d.try_reserve(additional)?;
        self.x.try_reserve(n.saturating_sub(self.x.len()))?;
        Ok(())
    }

    /// How many variables it holds without growing its arrays.
    pub fn capacity(&self) -> usize {
        (self.var_at.capacity())
            .min(self.diag.capacity())
            .min(self.rows.capacity())
            .min(self.d.capacity())
    }

    /// Values of R (entries times lanes) visited by the row updates since the last call (then
    /// zero): a deterministic measure of the time this factor's updates took (a rotation or
    /// forward solve costs in proportion to the entries of the rows on its path).
    pub fn take_work(&mut self) -> u64 {
        std::mem::take(&mut self.work)
    }

    /// A block of a pass spread over steps whose usual block is `base` entries, at a step
    /// whose own work on the factor was `own` values: its share ([`Self::levelled_share`]) of
    /// `base`, at least [`MIN_LEVELLED`] entries.
    pub(crate) fn levelled_block(&self, base: usize, own: u64) -> usize {
        ((base as f64 * self.levelled_share(base, own)) as usize).max(MIN_LEVELLED)
    }

    /// [`levelled`] for a step whose own work on the factor was `own` values (entries times
    /// lanes), against a usual block of `base` entries.
    pub(crate) fn levelled_share(&self, base: usize, own: u64) -> f64 {
        levelled(own / L as u64, base)
    }

    /// Nonzeros of R (diagonal included).
    pub fn nnz(&self) -> usize {
        self.nnz + self.diag.len()
    }

    /// Variable `v`'s position in the order (tests).
    #[cfg(test)]
    pub(crate) fn position_of(&self, v: usize) -> u32 {
        self.pos_of[v]
    }

    /// Append variable `v` (the next unused id is expected, but any id works) at the end of the
    /// order, with an empty row.
    pub fn push_variable(&mut self, v: usize) {
        if self.pos_of.len() <= v {
            self.pos_of.resize(v + 1, NONE);
        }
        self.pos_of[v] = self.var_at.len() as u32;
        self.var_at.push(v as u32);
        self.diag.push([0.0; L]);
        self.rows.push(Row::default());
        self.d.push([0.0; K]);
        self.x.push(0.0);
        self.spread_push();
    }

    /// Move the right-hand side of the last row added by `Δβ`, when no row was added or
    /// removed since: `d_k += g_k Δβ` on that row's path, with `g_k = s_k Π_{j<k} c_j` from
    /// its rotations (the rotation is linear in `(d, β)`, so this is what rotating the row in
    /// with `β + Δβ` would have given; it equals [`Self::shift_rhs`], `R⁻ᵀ a Δβ`, without
    /// walking the path again). False (nothing done) when the gains are stale.
    pub fn shift_last_row(&mut self, delta: [f64; K]) -> bool {
        if !self.gains_valid {
            return false;
        }
        self.spread_shift_last(delta);
        for &(k, g) in &self.gains {
            let dk = &mut self.d[k as usize];
            for q in 0..K {
                dk[q] += g[lane::<L>(q)] * delta[q];
            }
        }
        true
    }

    /// Change the right-hand side of an existing row `a` by `Δβ`: `d ← d + R⁻ᵀ a Δβ`.
    pub fn shift_rhs<C: Lanes<L>>(&mut self, entries: &[(usize, C)], delta: [f64; K]) {
        self.spread_shift_other(delta);
        self.forward(entries, |dk, y| {
            for (q, (dq, &sq)) in dk.iter_mut().zip(&delta).enumerate() {
                *dq += y[lane::<L>(q)] * sq;
            }
        });
    }

    /// Forward solve `Rᵀ y = a` on the positions it reaches (the elimination-tree paths of a's
    /// variables), in increasing order: `visit(d_k, y_k)` for each of them.
    fn forward<C: Lanes<L>>(
        &mut self,
        entries: &[(usize, C)],
        mut visit: impl FnMut(&mut [f64; K], [f64; L]),
    ) {
        self.load(entries);
        let work_before = self.work;
        let mut w = std::mem::take(&mut self.w);
        let mut next = std::mem::take(&mut self.w_next);
        let mut head = 0;
        loop {
            while head < w.len() && is_zero(&w.val[head]) {
                head += 1;
            }
            if head >= w.len() {
                break;
            }
            let (k, ak) = (w.pos[head] as usize, w.val[head]);
            self.work += (L * (1 + self.rows[k].len() + w.len() - head)) as u64;
            let diag = self.diag[k];
            let y: [f64; L] = std::array::from_fn(|l| ak[l] / diag[l]);
            visit(&mut self.d[k], y);
            // a_j -= R_kj y for j in row k, merged with the rest of w.
            next.clear();
            let row = &self.rows[k];
            let rest = (&w.pos[head + 1..], &w.val[head + 1..]);
            if let Some((xs, inside)) = align(row, rest, &mut self.aligned) {
                // On row k's pattern, exact zeros included: the loop skips them as pivots and
                // the merge below drops them (as a rotation carries them, module `rotate`).
                next.pos.extend_from_slice(&row.pos);
                next.val.extend(
                    (row.val.iter().zip(xs))
                        .map(|(a, x)| std::array::from_fn(|l| x[l] - a[l] * y[l])),
                );
                for (&p, x) in rest.0[inside..].iter().zip(&rest.1[inside..]) {
                    if !is_zero(x) {
                        next.push(p, *x);
                    }
                }
            } else {
                let (mut i, mut j) = (0, head + 1);
                while i < row.len() || j < w.len() {
                    let (p, v) = match (row.get(i), w.get(j)) {
                        (Some((pa, a)), Some((pb, b))) if pa == pb => {
                            i += 1;
                            j += 1;
                            (pa, std::array::from_fn(|l| b[l] - a[l] * y[l]))
                        }
                        (Some((pa, a)), Some((pb, _))) if pa < pb => {
                            i += 1;
                            (pa, std::array::from_fn(|l| -a[l] * y[l]))
                        }
                        (Some(_), Some((pb, b))) => {
                            j += 1;
                            (pb, b)
                        }
                        (Some((pa, a)), None) => {
                            i += 1;
                            (pa, std::array::from_fn(|l| -a[l] * y[l]))
                        }
                        (None, Some((pb, b))) => {
                            j += 1;
                            (pb, b)
                        }
                        (None, None) => unreachable!(),
                    };
                    if !is_zero(&v) {
                        next.push(p, v);
                    }
                }
            }
            std::mem::swap(&mut w, &mut next);
            head = 0;
        }
        self.w = w;
        self.w_next = next;
        crate::work::estimated(self.work - work_before);
    }

    /// The right-hand side d (to save and restore around a temporary [`Self::reset_rhs`]).
    pub fn rhs(&self) -> &[[f64; K]] {
        &self.d
    }

    /// Restore a right-hand side saved by [`Self::rhs`].
    pub fn set_rhs(&mut self, d: Vec<[f64; K]>) {
        if d.len() == self.d.len() {
            self.d = d;
        }
    }

    /// Every variable's value, indexed by variable (one back-substitution).
    #[cfg(test)]
    pub fn solve(&self, rhs: usize) -> Vec<f64> {
        let [x] = self.solve_columns([rhs]);
        x
    }

    /// Every variable's value for the right-hand sides `columns`, indexed by variable: one
    /// back-substitution for all of them (R read once; each column summed as a
    /// back-substitution of that column alone sums it, [`Row::dot`]: the same bits).
    pub fn solve_columns<const M: usize>(&self, columns: [usize; M]) -> [Vec<f64>; M] {
        let n = self.len();
        crate::work::estimated((M * (n + self.nnz)) as u64);
        let mut x = vec![[0.0; M]; n];
        let lanes = columns.map(lane::<L>);
        for p in (0..n).rev() {
            if let Some(ahead) = p.checked_sub(PREFETCH_AHEAD) {
                self.rows[ahead].prefetch();
            }
            let s = self.rows[p].dot(lanes, |j| x[j]);
            for m in 0..M {
                x[p][m] = (self.d[p][columns[m]] - s[m]) / self.diag[p][lanes[m]];
            }
        }
        std::array::from_fn(|m| {
            let mut out = vec![0.0; self.pos_of.len()];
            for (p, &v) in self.var_at.iter().enumerate() {
                out[v as usize] = x[p][m];
            }
            out
        })
    }

    /// One variable's value for every right-hand side: back-substitution along its
    /// elimination-tree path (O(1) for the last variable).
    pub fn value(&mut self, v: usize) -> [f64; K] {
        let p = self.path_of(v);
        let mut out = [0.0; K];
        for (q, o) in out.iter_mut().enumerate() {
            *o = self.back_along_path(p, q);
        }
        out
    }

    /// One variable's value for right-hand side `q` only.
    pub fn value_of(&mut self, v: usize, q: usize) -> f64 {
        let p = self.path_of(v);
        self.back_along_path(p, q)
    }

    /// The elimination-tree path of variable v into `self.path`; its position.
    fn path_of(&mut self, v: usize) -> usize {
        let p = self.pos_of[v] as usize;
        self.path.clear();
        let mut k = p;
        loop {
            self.path.push(k as u32);
            match self.rows[k].first() {
                Some(parent) => k = parent as usize,
                None => break,
            }
        }
        p
    }

    /// Back-substitution of right-hand side q along `self.path` (from [`Self::path_of`]):
    /// the value at position p, its first element.
    fn back_along_path(&mut self, p: usize, q: usize) -> f64 {
        let mut visited = 0;
        let l = lane::<L>(q);
        for &k in self.path.iter().rev() {
            let k = k as usize;
            visited += 1 + self.rows[k].len();
            let [s] = self.rows[k].dot([l], |j| [self.x[j]]);
            self.x[k] = (self.d[k][q] - s) / self.diag[k][l];
        }
        crate::work::estimated(visited as u64);
        self.x[p]
    }

    /// Variance of the combination `aᵀx`: `aᵀ(AᵀA)⁻¹a = ‖R⁻ᵀ a‖²` (one forward solve along
    /// the paths of a's variables; `a = e_v` gives a marginal variance).
    pub fn marginal<C: Lanes<L>>(&mut self, entries: &[(usize, C)]) -> [f64; L] {
        let mut sum = [0.0; L];
        self.forward(entries, |_, y| {
            for (s, y) in sum.iter_mut().zip(y) {
                *s += y * y;
            }
        });
        sum
    }

    /// Recompute d from scratch for the rows given (`Rᵀ d = Σ_r a_r β_r`): one forward solve.
    /// Resynchronises d after many right-hand-side shifts.
    pub fn reset_rhs<const N: usize, C: Lanes<L>>(
        &mut self,
        rows: impl IntoIterator<Item = ([(usize, C); N], [f64; K])>,
    ) {
        self.reset_rhs_from(0, rows);
    }

    /// [`Self::reset_rhs`] for the right-hand sides `from..K` only (the others are kept): the
    /// positions of a factor shared with the headings, re-linearised.
    pub fn reset_rhs_from<const N: usize, C: Lanes<L>>(
        &mut self,
        from: usize,
        rows: impl IntoIterator<Item = ([(usize, C); N], [f64; K])>,
    ) {
        self.reset_rhs_in(from..K, rows);
    }

    /// `g = Σ_r a_r β_r` in the right-hand sides `columns`, by position (zero in the others):
    /// what a forward solve `Rᵀ d = g` starts from.
    fn information<const N: usize, C: Lanes<L>>(
        &self,
        columns: std::ops::Range<usize>,
        rows: impl IntoIterator<Item = ([(usize, C); N], [f64; K])>,
    ) -> Vec<[f64; K]> {
        let mut g = vec![[0.0; K]; self.len()];
        gather(&self.pos_of, &mut g, columns, rows);
        g
    }

    /// [`Self::reset_rhs`] for the right-hand sides `columns` only (the others are kept).
    pub fn reset_rhs_in<const N: usize, C: Lanes<L>>(
        &mut self,
        columns: std::ops::Range<usize>,
        rows: impl IntoIterator<Item = ([(usize, C); N], [f64; K])>,
    ) {
        let (from, to) = (columns.start.min(K), columns.end.min(K));
        let n = self.len();
        crate::work::estimated((n + self.nnz) as u64);
        let mut g = self.information(from..to, rows);
        for k in 0..n {
            let mut dk = g[k];
            for (q, v) in dk.iter_mut().enumerate().take(to).skip(from) {
                *v /= self.diag[k][lane::<L>(q)];
            }
            if let Some(ahead) = self.rows.get(k + PREFETCH_AHEAD) {
                ahead.prefetch();
            }
            let row = &self.rows[k];
            for (&j, a) in row.pos.iter().zip(&row.val) {
                let gj = &mut g[j as usize];
                // Every q, unrolled (K and the lanes known), the kept ones skipped.
                for q in 0..K {
                    if q >= from && q < to {
                        gj[q] -= a[lane::<L>(q)] * dk[q];
                    }
                }
            }
            self.d[k][from..to].copy_from_slice(&dk[from..to]);
        }
    }
}

impl<const K: usize> SqrtInfo<K> {
    /// `Y = R⁻ᵀ [a₀ a₁ a₂]` for three rows on the same variables, as (position, row of Y)
    /// pairs, positions ascending: `YᵀY' = Aᵀ(AᵀA)⁻¹A'` for two such. A forward solve over the
    /// reach of the rows' variables (the union of their elimination-tree paths: the positions
    /// of row k of R are ancestors of k) in a dense scratch, costing the entries of R on those
    /// rows only.
    pub fn whiten3<const N: usize>(
        &self,
        rows: &[[(usize, f64); N]; 3],
        s: &mut WhitenScratch,
    ) -> Vec<(u32, [f64; 3])> {
        let n = self.len();
        s.w.resize(n, [0.0; 3]);
        s.mark.resize(n, false);
        s.reach.clear();
        for (q, row) in rows.iter().enumerate() {
            for &(v, a) in row {
                if a == 0.0 {
                    continue;
                }
                let mut k = self.pos_of[v] as usize;
                s.w[k][q] += a;
                while !s.mark[k] {
                    s.mark[k] = true;
                    s.reach.push(k as u32);
                    match self.rows[k].first() {
                        Some(parent) => k = parent as usize,
                        None => break,
                    }
                }
            }
        }
        s.reach.sort_unstable();
        let mut y = Vec::with_capacity(s.reach.len());
        for &k in &s.reach {
            let k = k as usize;
            let yk = s.w[k].map(|v| v / self.diag[k][0]);
            s.w[k] = [0.0; 3];
            s.mark[k] = false;
            for (j, a) in self.rows[k].iter() {
                let wj = &mut s.w[j as usize];
                for q in 0..3 {
                    wj[q] -= a[0] * yk[q];
                }
            }
            y.push((k as u32, yk));
        }
        y
    }

    /// The same rows in `M` lanes, lane m weighted by `scale[m]²` (R and the right-hand sides
    /// of lane m scaled by `scale[m]`): how a factor shared by systems whose weights were
    /// proportional becomes one factor of lanes when the proportion breaks.
    pub fn widen<const M: usize>(&self, scale: [f64; M]) -> SqrtInfo<K, M> {
        let mut f = SqrtInfo::<K, M>::new();
        f.pos_of.clone_from(&self.pos_of);
        f.var_at.clone_from(&self.var_at);
        f.diag = self.diag.iter().map(|&[r]| scale.map(|m| m * r)).collect();
        f.rows = self
            .rows
            .iter()
            .map(|row| Row {
                pos: row.pos.clone(),
                val: row.val.iter().map(|&[v]| scale.map(|m| m * v)).collect(),
            })
            .collect();
        f.d = self
            .d
            .iter()
            .map(|dk| std::array::from_fn(|q| scale[lane::<M>(q)] * dk[q]))
            .collect();
        f.nnz = self.nnz;
        f.x = vec![0.0; self.x.len()];
        // A rotation's cosines and sines do not change when both rows scale alike.
        f.gains = self.gains.iter().map(|&(k, [g])| (k, [g; M])).collect();
        f.gains_valid = self.gains_valid;
        f
    }
}

#[cfg(test)]
mod tests {
    use super::factored::{Cholesky, supernodal_pays};
    use super::*;

    /// `H x = g` by Gaussian elimination (H SPD: no pivoting), for checking.
    fn dense_solve(mut h: Vec<Vec<f64>>, mut x: Vec<f64>) -> Vec<f64> {
        let n = x.len();
        for k in 0..n {
            let pivot = h[k].clone();
            for i in k + 1..n {
                let f = h[i][k] / pivot[k];
                for (hij, pkj) in h[i].iter_mut().zip(&pivot).skip(k) {
                    *hij -= f * pkj;
                }
                x[i] -= f * x[k];
            }
        }
        for k in (0..n).rev() {
            let s: f64 = (k + 1..n).map(|j| h[k][j] * x[j]).sum();
            x[k] = (x[k] - s) / h[k][k];
        }
        x
    }

    /// Dense normal equations: the diagonal of their inverse and their solution.
    fn dense(n: usize, rows: &[(Vec<(usize, f64)>, f64)]) -> (Vec<Vec<f64>>, Vec<f64>) {
        let mut h = vec![vec![0.0; n]; n];
        let mut g = vec![0.0; n];
        for (a, b) in rows {
            for &(i, x) in a {
                g[i] += x * b;
                for &(j, y) in a {
                    h[i][j] += x * y;
                }
            }
        }
        let inv_diag = (0..n)
            .map(|v| {
                let mut e = vec![0.0; n];
                e[v] = 1.0;
                dense_solve(h.clone(), e)[v]
            })
            .collect();
        (vec![inv_diag], dense_solve(h, g))
    }

    pub(super) fn lcg(state: &mut u64) -> f64 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*state >> 11) as f64) / ((1u64 << 53) as f64)
    }

    /// The supernodal and the simplicial Cholesky give the same factor: the same pattern (the
    /// supernodes' padding dropped), the same values and right-hand sides to rounding, on a
    /// grid of two lanes in a fill-reducing order whose top is dense (a 30 × 30 grid's
    /// separators); and after it both take a row alike.
    #[test]
    fn supernodal_and_simplicial_factors_agree() {
        let side = 30;
        let n = side * side;
        let mut state = 7u64;
        let edges = dissection::grid(side, side);
        type Rows = Vec<([(usize, [f64; 2]); 2], [f64; 3])>;
        let mut rows: Rows = vec![([(0, [1.0, 2.0]), (0, [0.0; 2])], [0.0; 3])];
        for &(a, b) in &edges {
            let w = [0.5 + lcg(&mut state), 0.5 + 3.0 * lcg(&mut state)];
            let y = [lcg(&mut state), lcg(&mut state), lcg(&mut state)];
            rows.push(([(a, w.map(|w| -w)), (b, w)], y.map(|y| y * w[0])));
        }
        let order = fill_reducing_order(n, &edges, &[n - 1]);
        let by = |cholesky| {
            SqrtInfo::<3, 2>::factored_by(&order, rows.iter().copied(), cholesky).unwrap()
        };
        let (mut simplicial, mut supernodal) = (by(Cholesky::Simplicial), by(Cholesky::Supernodal));
        let close = |a: [f64; 2], b: [f64; 2]| {
            (0..2).all(|l| (a[l] - b[l]).abs() <= 1e-12 * (1.0 + a[l].abs()))
        };
        assert_eq!(simplicial.nnz, supernodal.nnz);
        assert!(
            simplicial.nnz > 10 * n,
            "a dense enough top: {}",
            simplicial.nnz
        );
        for k in 0..n {
            assert_eq!(simplicial.rows[k].pos, supernodal.rows[k].pos, "row {k}");
            assert!(close(simplicial.diag[k], supernodal.diag[k]), "row {k}");
            for (a, b) in simplicial.rows[k].val.iter().zip(&supernodal.rows[k].val) {
                assert!(close(*a, *b), "row {k}");
            }
            let (a, b) = (simplicial.d[k], supernodal.d[k]);
            assert!((0..3).all(|q| (a[q] - b[q]).abs() <= 1e-10 * (1.0 + a[q].abs())));
        }
        let row = [(3, [1.0, 0.5]), (n - 2, [-1.0, -0.5])];
        let (a, b) = (
            simplicial.add_row(&row, [0.3; 3]),
            supernodal.add_row(&row, [0.3; 3]),
        );
        for q in 0..3 {
            assert!((a.residual[q] - b.residual[q]).abs() < 1e-10);
        }
        let (x, y) = (
            simplicial.solve_columns([0, 1, 2]),
            supernodal.solve_columns([0, 1, 2]),
        );
        for q in 0..3 {
            for v in 0..n {
                assert!((x[q][v] - y[q][v]).abs() < 1e-9, "{q} {v}");
            }
        }
    }

    /// The choice of factorization follows the flops per nonzero of L: a chain's factor
    /// (two per column) is simplicial, a dense one of 200 columns supernodal (about 68 flops per
    /// nonzero; 100 columns make 35).
    #[test]
    fn supernodal_pays_where_the_factor_is_dense() {
        assert!(!supernodal_pays(&[2; 1000]));
        let dense: Vec<usize> = (1..=200).rev().collect();
        assert!(supernodal_pays(&dense));
    }

    /// A factor of two lanes (the same rows, each lane with its own coefficients) is two
    /// factors of one lane: the same solutions, variances, predictions and leftovers through
    /// rows added, tried and taken back, shifted and removed, and built at once.
    #[test]
    fn two_lanes_are_two_factors() {
        let n = 40;
        let mut s = 7u64;
        let mut wide = SqrtInfo::<3, 2>::new();
        let mut one = SqrtInfo::<1>::new();
        let mut two = SqrtInfo::<2>::new();
        for v in 0..n {
            wide.push_variable(v);
            one.push_variable(v);
            two.push_variable(v);
        }
        // Row `(a, b)` with weight ratio `1 + 3·u` between the lanes.
        type Rows = Vec<([(usize, [f64; 2]); 2], [f64; 3])>;
        let mut rows: Rows = Vec::new();
        let add = |a: usize, b: usize, s: &mut u64, rows: &mut Rows| {
            let (w0, w1) = (0.5 + lcg(s), (0.5 + lcg(s)) * (1.0 + 3.0 * lcg(s)));
            let entries = [(a, [-w0, -w1]), (b, [w0, w1])];
            let beta = [lcg(s), lcg(s), lcg(s)];
            rows.push((entries, beta));
            entries
        };
        let check = |wide: &mut SqrtInfo<3, 2>, one: &mut SqrtInfo<1>, two: &mut SqrtInfo<2>| {
            let close = |x: &[f64], y: &[f64]| x.iter().zip(y).all(|(a, b)| (a - b).abs() < 1e-10);
            assert!(close(&wide.solve(0), &one.solve(0)));
            // One back-substitution for several columns: each column's bits.
            let [x0, x1, x2] = wide.solve_columns([0, 1, 2]);
            assert_eq!([x0, x1, x2], [wide.solve(0), wide.solve(1), wide.solve(2)]);
            assert!(close(&wide.solve(1), &two.solve(0)) && close(&wide.solve(2), &two.solve(1)));
            for v in [3, 17, n - 1] {
                let [v0, v1] = wide.marginal(&[(v, [1.0; 2])]);
                let ([u0], [u1]) = (one.marginal(&[(v, 1.0)]), two.marginal(&[(v, 1.0)]));
                assert!((v0 - u0).abs() < 1e-10 && (v1 - u1).abs() < 1e-10);
            }
        };
        let split = |entries: &[(usize, [f64; 2]); 2], l: usize| entries.map(|(v, a)| (v, a[l]));
        let prior = [(0, [2.0, 3.0])];
        wide.add_row(&prior, [0.0; 3]);
        one.add_row(&[(0, 2.0)], [0.0]);
        two.add_row(&[(0, 3.0)], [0.0; 2]);
        for b in 1..n {
            let mut ends = vec![(b - 1, b)];
            if b % 4 == 0 && b > 8 {
                ends.push(((lcg(&mut s) * (b - 4) as f64) as usize, b));
            }
            for (a, b) in ends {
                let e = add(a, b, &mut s, &mut rows);
                let beta = rows[rows.len() - 1].1;
                let left = wide.add_row(&e, beta);
                let l1 = one.add_row(&split(&e, 0), [beta[0]]);
                let l2 = two.add_row(&split(&e, 1), [beta[1], beta[2]]);
                let close = |a: f64, b: f64| (a - b).abs() < 1e-10;
                assert!(
                    close(left.residual[0], l1.residual[0])
                        && close(left.cosines[0], l1.cosines[0])
                );
                assert!(
                    close(left.residual[2], l2.residual[1])
                        && close(left.cosines[1], l2.cosines[0])
                );
            }
        }
        check(&mut wide, &mut one, &mut two);
        // The last row's right-hand side shifted, by its gains and by a forward solve.
        assert!(wide.shift_last_row([0.3, -0.2, 0.5]));
        assert!(one.shift_last_row([0.3]) && two.shift_last_row([-0.2, 0.5]));
        let (e, _) = rows[5];
        wide.shift_rhs(&e, [0.1, 0.2, -0.3]);
        one.shift_rhs(&split(&e, 0), [0.1]);
        two.shift_rhs(&split(&e, 1), [0.2, -0.3]);
        check(&mut wide, &mut one, &mut two);
        // A loop closure tried and taken back: bit for bit.
        let e = [(2, [-1.5, -4.0]), (n - 2, [1.5, 4.0])];
        let before = wide.clone();
        let left = wide.try_row(&e, [0.2, 0.1, -0.1]);
        let [l0] = one.clone().try_row(&split(&e, 0), [0.2]).cosines;
        let [l1] = two.clone().try_row(&split(&e, 1), [0.1, -0.1]).cosines;
        assert!((left.cosines[0] - l0).abs() < 1e-12 && (left.cosines[1] - l1).abs() < 1e-12);
        wide.undo_row();
        assert_taken_back(&wide, &before);
        // A row removed (hyperbolic rotations).
        let (e, beta) = rows[9];
        wide.remove_row(&e, beta).unwrap();
        one.remove_row(&split(&e, 0), [beta[0]]).unwrap();
        two.remove_row(&split(&e, 1), [beta[1], beta[2]]).unwrap();
        check(&mut wide, &mut one, &mut two);
        // Built at once from the rows left (one order, one structure, a Cholesky per lane).
        rows.remove(9);
        let order: Vec<usize> = (0..n).rev().collect();
        let priors = [([(0, [2.0, 3.0]), (0, [0.0; 2])], [0.0; 3])];
        let all = || priors.iter().chain(&rows).copied();
        let mut wide = SqrtInfo::<3, 2>::factored(&order, all()).unwrap();
        let mut one =
            SqrtInfo::<1>::factored(&order, all().map(|(e, b)| (split(&e, 0), [b[0]]))).unwrap();
        let mut two =
            SqrtInfo::<2>::factored(&order, all().map(|(e, b)| (split(&e, 1), [b[1], b[2]])))
                .unwrap();
        one.shift_rhs(&split(&rows[5].0, 0), [0.1]);
        two.shift_rhs(&split(&rows[5].0, 1), [0.2, -0.3]);
        wide.shift_rhs(&rows[5].0, [0.1, 0.2, -0.3]);
        check(&mut wide, &mut one, &mut two);
    }

    /// Growing, down-dating and shifting agree with dense normal equations.
    #[test]
    fn incremental_rows_match_dense_least_squares() {
        let mut s = 7u64;
        let n = 30;
        let mut f = SqrtInfo::<1>::new();
        // A shuffled order of variables.
        let mut vars: Vec<usize> = (0..n).collect();
        for i in (1..n).rev() {
            let j = (lcg(&mut s) * (i + 1) as f64) as usize;
            vars.swap(i, j);
        }
        for &v in &vars {
            f.push_variable(v);
        }
        let mut rows: Vec<(Vec<(usize, f64)>, f64)> = Vec::new();
        // A prior on variable 0 and a chain, then random extra rows.
        rows.push((vec![(0, 1.0)], 0.0));
        for v in 1..n {
            let w = 0.5 + lcg(&mut s);
            rows.push((vec![(v - 1, -w), (v, w)], lcg(&mut s) - 0.5));
        }
        for _ in 0..40 {
            let a = (lcg(&mut s) * n as f64) as usize;
            let b = (lcg(&mut s) * n as f64) as usize;
            if a != b {
                let w = 0.5 + lcg(&mut s);
                rows.push((vec![(a, -w), (b, w)], 3.0 * (lcg(&mut s) - 0.5)));
            }
        }
        for (a, b) in &rows {
            f.add_row(a, [*b]);
        }
        let check = |f: &mut SqrtInfo<1>, rows: &[(Vec<(usize, f64)>, f64)]| {
            let (var, x) = dense(n, rows);
            let all = f.solve(0);
            // Rows long enough for every part of a row's sum ([`Row::dot`]).
            assert!(f.rows.iter().any(|r| r.len() >= 9));
            for v in 0..n {
                assert!((all[v] - x[v]).abs() < 1e-9, "{v}: {} vs {}", all[v], x[v]);
                // Along its path or in a whole back-substitution: the same bits.
                assert_eq!(f.value(v)[0].to_bits(), all[v].to_bits(), "{v}");
                assert!((f.value(v)[0] - x[v]).abs() < 1e-9);
                assert!((f.marginal(&[(v, 1.0)])[0] - var[0][v]).abs() < 1e-9);
            }
        };
        check(&mut f, &rows);
        // Shift the right-hand side of a row.
        let (a, b) = rows[35].clone();
        f.shift_rhs(&a, [0.7]);
        rows[35].1 = b + 0.7;
        check(&mut f, &rows);
        // Remove a row.
        let (a, b) = rows.remove(40);
        f.remove_row(&a, [b]).unwrap();
        check(&mut f, &rows);
        // Recompute d from the rows: same solution.
        let pad = |a: &Vec<(usize, f64)>| match a.as_slice() {
            [x] => [*x, (x.0, 0.0)],
            [x, y, ..] => [*x, *y],
            [] => [(0, 0.0); 2],
        };
        f.reset_rhs(rows.iter().map(|(a, b)| (pad(a), [*b])));
        check(&mut f, &rows);
        // The same rows factored at once (Cholesky), in the same order: the same answers, and
        // it grows and down-dates like the rotated one.
        let mut g = SqrtInfo::<1>::factored(&vars, rows.iter().map(|(a, b)| (pad(a), [*b])))
            .expect("positive definite");
        assert_eq!(g.var_at, f.var_at);
        check(&mut g, &rows);
        let extra = (vec![(3, -1.5), (17, 1.5)], 0.25);
        g.add_row(&extra.0, [extra.1]);
        rows.push(extra);
        check(&mut g, &rows);
        let (a, b) = rows.pop().expect("the extra row");
        g.remove_row(&a, [b]).unwrap();
        check(&mut g, &rows);
    }

    /// Moving the last row's right-hand side by its rotations' gains is moving it by a
    /// forward solve; a removed row makes the gains stale. Splitting right-hand sides off
    /// with a scale is the factor of the rows weighted by the scale squared.
    #[test]
    fn the_last_rows_gains_shift_its_right_hand_side() {
        type Row = ([(usize, f64); 2], [f64; 2]);
        let rows: Vec<Row> = (0..40)
            .map(|i| {
                let (a, b) = (i % 12, (i * 7 + 3) % 12);
                let w = 1.0 + (i % 5) as f64;
                ([(a, -w), (b, w)], [0.1 * i as f64, 1.0 - 0.05 * i as f64])
            })
            .filter(|([(a, _), (b, _)], _)| a != b)
            .collect();
        let mut f = SqrtInfo::<2>::new();
        let mut g = SqrtInfo::<2>::new();
        for v in 0..12 {
            f.push_variable(v);
            g.push_variable(v);
        }
        for v in 0..12 {
            f.add_row(&[(v, 1.0)], [0.0; 2]);
            g.add_row(&[(v, 1.0)], [0.0; 2]);
        }
        for (a, b) in &rows {
            f.add_row(a, *b);
            g.add_row(a, *b);
        }
        let (last, beta) = rows[rows.len() - 1];
        assert!(f.shift_last_row([0.5, -2.0]));
        g.shift_rhs(&last, [0.5, -2.0]);
        for q in 0..2 {
            for (x, y) in f.solve(q).iter().zip(g.solve(q)) {
                assert!((x - y).abs() < 1e-12, "{x} vs {y}");
            }
        }
        // Widened to two lanes, the second weighted 9×: the same solution, a ninth of the
        // variance in that lane, and the gains still shift the last row.
        let mut wide = f.widen([1.0, 3.0]);
        for q in 0..2 {
            for (x, y) in wide.solve(q).iter().zip(f.solve(q)) {
                assert!((x - y).abs() < 1e-12, "{x} vs {y}");
            }
        }
        let [v0, v1] = wide.marginal(&[(5, [1.0; 2])]);
        let [v] = f.marginal(&[(5, 1.0)]);
        assert!((v0 - v).abs() < 1e-12 && (9.0 * v1 - v).abs() < 1e-12);
        let mut g = f.clone();
        assert!(wide.shift_last_row([0.25, 1.0]) && g.shift_last_row([0.25, 1.0 / 3.0]));
        for q in 0..2 {
            for (x, y) in wide.solve(q).iter().zip(g.solve(q)) {
                assert!((x - y).abs() < 1e-12, "{x} vs {y}");
            }
        }
        f.remove_row(&last, [beta[0] + 0.5, beta[1] - 2.0]).unwrap();
        assert!(!f.shift_last_row([1.0, 1.0]));
    }

    /// A tried row leaves the prediction error and variance of the row before it
    /// (`residual/Πc = β − aᵀx̂`, `1/Πc² − 1 = ‖R⁻ᵀa‖²`); taken back, the factor is the one
    /// before, bit for bit (rows it filled included), and its gains still shift the row added
    /// before it; kept, it is the factor `add_row` gives.
    #[test]
    fn a_tried_row_predicts_and_is_taken_back_exactly() {
        let mut s = 11u64;
        let n = 25;
        let mut f = chain_with_closures(n, 15, &mut s, false);
        // A loop closure across the chain: its row meets fill on its path.
        let row = [(2, -3.0), (n - 3, 3.0)];
        let beta = [0.4, -1.1];
        let x0 = f.solve(0);
        let predicted = 3.0 * (x0[n - 3] - x0[2]);
        let [var] = f.marginal(&row);
        let before = f.clone();
        let left = f.try_row(&row, beta);
        let [cosines] = left.cosines;
        assert!(cosines > 0.0 && cosines < 1.0);
        let error = left.residual[0] / cosines;
        assert!((error - (beta[0] - predicted)).abs() < 1e-12, "{error}");
        let ratio = 1.0 / (cosines * cosines) - 1.0;
        assert!(
            (ratio - var).abs() < 1e-12 * var.max(1.0),
            "{ratio} vs {var}"
        );
        f.undo_row();
        assert_taken_back(&f, &before);
        assert_eq!(
            (f.nnz, &f.gains, f.gains_valid),
            (before.nnz, &before.gains, true)
        );
        assert_eq!(f.work, before.work);
        // Tried and kept: what add_row gives (on the factor as it was, bit for bit).
        let mut f = before.clone();
        let mut g = before.clone();
        g.add_row(&row, beta);
        let _ = f.try_row(&row, beta);
        f.keep_row();
        assert_eq!((&f.rows, &f.diag, &f.d), (&g.rows, &g.diag, &g.d));
        // A kept row is not taken back by a stray undo.
        f.undo_row();
        assert_eq!(
            (&f.rows, &f.diag, &f.d, f.nnz),
            (&g.rows, &g.diag, &g.d, g.nnz)
        );
        assert!(f.shift_last_row([1.0, 0.0]) && g.shift_last_row([1.0, 0.0]));
        assert_eq!(f.d, g.d);
    }

    /// `f` is `before` taken back ([`SqrtInfo::undo_row`]): every row of R with its old
    /// pattern, diagonal and right-hand side bit for bit, its values within rounding (1e-13 of
    /// the row's largest entry or diagonal), and the same count of nonzeros.
    pub(super) fn assert_taken_back<const K: usize, const L: usize>(
        f: &SqrtInfo<K, L>,
        before: &SqrtInfo<K, L>,
    ) {
        assert_eq!(
            (&f.diag, &f.d, f.nnz),
            (&before.diag, &before.d, before.nnz)
        );
        assert_eq!(f.rows.len(), before.rows.len());
        for (k, (r, b)) in f.rows.iter().zip(&before.rows).enumerate() {
            assert_eq!(r.pos, b.pos, "row {k}'s pattern");
            for l in 0..L {
                let scale = b
                    .val
                    .iter()
                    .fold(before.diag[k][l].abs(), |m, v| m.max(v[l].abs()));
                for (x, y) in r.val.iter().zip(&b.val) {
                    assert!(
                        (x[l] - y[l]).abs() <= 1e-13 * scale,
                        "row {k}, lane {l}: {} against {}",
                        x[l],
                        y[l]
                    );
                }
            }
        }
    }

    /// Tried rows taken back over and over leave a factor that answers as the one that never
    /// tried them: random loop closures on a chain, two lanes (some rows with a lane at zero,
    /// which that lane's rotations leave alone), each tried and taken back before the next is
    /// kept; the solution, a marginal and the rows' patterns then match the factor that only
    /// added the kept ones.
    #[test]
    fn rows_taken_back_over_and_over_leave_the_answers() {
        let mut s = 5u64;
        let n = 120;
        let mut f = SqrtInfo::<3, 2>::new();
        let mut g = SqrtInfo::<3, 2>::new();
        for v in 0..n {
            f.push_variable(v);
            g.push_variable(v);
        }
        let mut both = |row: &[(usize, [f64; 2])], beta: [f64; 3]| {
            f.add_row(row, beta);
            g.add_row(row, beta);
        };
        both(&[(0, [1.0, 1.0])], [0.0; 3]);
        for v in 1..n {
            both(
                &[(v - 1, [-1.0, -2.0]), (v, [1.0, 2.0])],
                [lcg(&mut s), lcg(&mut s), 0.1],
            );
        }
        let mut undone = 0;
        for t in 0..400 {
            let (a, b) = (
                (lcg(&mut s) * n as f64) as usize,
                (lcg(&mut s) * n as f64) as usize,
            );
            if a == b {
                continue;
            }
            let lanes = if t % 5 == 0 { [0.0, 3.0] } else { [1.5, 0.5] };
            let row = [(a, lanes.map(|x| -x)), (b, lanes)];
            let beta = [lcg(&mut s), lcg(&mut s), lcg(&mut s)];
            if t % 3 == 0 {
                let before = f.clone();
                let _ = f.try_row(&row, beta);
                f.undo_row();
                assert_taken_back(&f, &before);
                undone += 1;
            } else {
                let _ = f.try_row(&row, beta);
                f.keep_row();
                g.add_row(&row, beta);
            }
        }
        assert!(undone > 100);
        assert_eq!(
            f.rows.iter().map(|r| &r.pos).collect::<Vec<_>>(),
            g.rows.iter().map(|r| &r.pos).collect::<Vec<_>>()
        );
        for q in 0..3 {
            let (x, y) = (f.solve(q), g.solve(q));
            for v in 0..n {
                assert!(
                    (x[v] - y[v]).abs() < 1e-9,
                    "rhs {q}, variable {v}: {} against {}",
                    x[v],
                    y[v]
                );
            }
        }
        let probe = [(3, [1.0, 1.0]), (n - 7, [-1.0, -1.0])];
        let (a, b) = (f.marginal(&probe), g.marginal(&probe));
        assert!(
            (0..2).all(|l| (a[l] - b[l]).abs() < 1e-9 * b[l].max(1.0)),
            "{a:?} against {b:?}"
        );
    }

    /// A chain of `n` variables (a prior on the first) and up to `closures` random loop
    /// closures between them, added, or tried and kept (`tried`: the undo record grows).
    pub(super) fn chain_with_closures(
        n: usize,
        closures: usize,
        s: &mut u64,
        tried: bool,
    ) -> SqrtInfo<2> {
        let mut f = SqrtInfo::<2>::new();
        for v in 0..n {
            f.push_variable(v);
        }
        f.add_row(&[(0, 1.0)], [0.0; 2]);
        for v in 1..n {
            f.add_row(&[(v - 1, -1.0), (v, 1.0)], [lcg(s), lcg(s)]);
        }
        for _ in 0..closures {
            let (a, b) = ((lcg(s) * n as f64) as usize, (lcg(s) * n as f64) as usize);
            if a == b {
                continue;
            }
            let row = [(a, -2.0), (b, 2.0)];
            let beta = [lcg(s), lcg(s)];
            if tried {
                let _ = f.try_row(&row, beta);
                f.keep_row();
            } else {
                f.add_row(&row, beta);
            }
        }
        f
    }

    /// A zero pivot (a variable no row touches) makes the Cholesky give up, not panic.
    #[test]
    fn factored_refuses_a_singular_system() {
        let rows = [
            ([(0, 1.0), (1, -1.0)], [0.5]),
            ([(0, 1.0), (0, 0.0)], [0.0]),
        ];
        assert!(SqrtInfo::<1>::factored(&[0, 1, 2], rows.into_iter()).is_none());
    }

    /// The ways a row being rotated in meets a row of R — fill beyond its last position, a
    /// position inside it that it lacks (a merge), part of its pattern, exactly its pattern,
    /// and an exact cancellation (the zeros dropped) — each give the dense least-squares
    /// answer, and a tried row through each is taken back ([`assert_taken_back`]).
    #[test]
    fn every_way_a_row_meets_r_agrees_with_dense_least_squares() {
        let n = 6;
        let mut f = SqrtInfo::<1>::new();
        for v in 0..n {
            f.push_variable(v);
        }
        let mut rows: Vec<(Vec<(usize, f64)>, f64)> = Vec::new();
        let add = |f: &mut SqrtInfo<1>, rows: &mut Vec<_>, a: Vec<(usize, f64)>, b: f64| {
            let before = f.clone();
            let _ = f.try_row(&a, [b]);
            f.undo_row();
            assert_taken_back(f, &before);
            // Then added to the factor as it was, bit for bit, for the dense comparison below.
            *f = before;
            f.add_row(&a, [b]);
            rows.push((a, b));
        };
        add(&mut f, &mut rows, vec![(0, 1.0)], 0.3);
        // Beyond row 0's last position (it has none): appended.
        add(&mut f, &mut rows, vec![(0, -1.0), (3, 1.0)], 0.5);
        assert_eq!(f.rows[0].pos, [3]);
        // Position 2 inside row 0's range, which it lacks: merged.
        add(&mut f, &mut rows, vec![(0, -1.0), (2, 0.5), (3, 1.0)], 0.1);
        assert_eq!(f.rows[0].pos, [2, 3]);
        // Part of row 0's pattern, then exactly it.
        add(&mut f, &mut rows, vec![(0, 0.7), (3, -0.4)], -0.2);
        add(&mut f, &mut rows, vec![(0, 0.3), (2, 0.9), (3, -1.2)], 0.8);
        assert_eq!(f.rows[0].pos, [2, 3]);
        // Row 0 of R itself: every entry of the row being rotated cancels exactly.
        let r0: Vec<(usize, f64)> = std::iter::once((0, f.diag[0][0]))
            .chain(f.rows[0].iter().map(|(p, [v])| (p as usize, v)))
            .collect();
        let nnz = f.nnz;
        add(&mut f, &mut rows, r0.clone(), 0.0);
        assert_eq!(f.nnz, nnz, "the cancelled row filled nothing");
        // Row 0 of R again but for its last entry: the first rotation (c = s) cancels every
        // entry but that one, and the row goes on carrying exact zeros, which are skipped as
        // pivots and stored nowhere.
        let mut partly = r0;
        if let Some(last) = partly.last_mut() {
            last.1 += 0.5;
        }
        add(&mut f, &mut rows, partly, 0.2);
        assert_eq!(f.nnz, nnz, "the carried zeros filled nothing");
        assert!(
            f.rows.iter().all(|r| r.val.iter().all(|v| !is_zero(v))),
            "a zero stored in R"
        );
        for v in 1..n {
            add(
                &mut f,
                &mut rows,
                vec![(v - 1, -1.0), (v, 1.0)],
                0.1 * v as f64,
            );
        }
        let (var, x) = dense(n, &rows);
        let all = f.solve(0);
        for v in 0..n {
            assert!((all[v] - x[v]).abs() < 1e-9, "{v}: {} vs {}", all[v], x[v]);
            assert!((f.marginal(&[(v, 1.0)])[0] - var[0][v]).abs() < 1e-9);
        }
    }

    #[test]
    fn fill_reducing_order_is_a_permutation_with_last_at_the_end() {
        let edges: Vec<(usize, usize)> = (1..50)
            .map(|v| (v - 1, v))
            .chain([(0, 49), (10, 30)])
            .collect();
        let o = fill_reducing_order(50, &edges, &[49]);
        assert_eq!(o.len(), 50);
        assert_eq!(*o.last().unwrap(), 49);
        let mut s = o.clone();
        s.sort_unstable();
        assert_eq!(s, (0..50).collect::<Vec<_>>());
    }
}
