//! A forward solve spread over steps: new right-hand sides for every row of R, computed a few
//! rows at a time while rows keep being rotated into R.
//!
//! Recomputing right-hand sides `from..K` from the rows (`Rᵀ d = g`, `g = Σ_r a_r β_r`, after
//! the rows' β were rewritten: a re-linearisation) is one right-looking forward solve over all
//! of R. Done a block of positions at a time, with R changing in between, it keeps, for the
//! positions `k < p` already solved, their new values `d'_k`, and for the others the part of
//! g not yet eliminated, `h = g_{≥p} − R_{<p,≥p}ᵀ d'_{<p}`:
//!
//! ```text
//! advance:        d'_p = h_p / R_pp,   h_j −= R_pj d'_p  (j in row p),   p += 1
//! a row (a, β'):  its rotations at rows k < p turn (d'_k, β') as they turn (d_k, β);
//!                 the row reaches position p or beyond as (w, β'_rem): h += w β'_rem
//! ```
//!
//! The second line keeps the invariant: the rotations at rows before p are orthogonal, so
//! `R'_{<p}ᵀ d'_{<p} + w β'_rem = R_{<p}ᵀ d'_{<p} + a β'`, and with `g' = g + a β'` the
//! uneliminated part moves by `w β'_rem`; rotations among the rows from p on change
//! `R_{≥p}` only, which the later blocks read as it is then. When p reaches the end, `d'` is
//! `R⁻ᵀ g` for the R of that moment — what one forward solve then would give, up to rounding
//! — and replaces d's right-hand sides `from..K`. Until then d answers with the rows' old β.
//!
//! g itself is gathered over steps first, a block of rows per step ([`SqrtInfo::spread_begin`]):
//! gathered at once, in the step that began the spread, its pass over every row made that step
//! the slowest of its neighbours (a median 0.12 ms on city10000, 36 of its 93 such steps among
//! the slowest 1 %; 1.5 ms on a 100 000-pose world). While g is gathered p = 0, so a row rotated
//! in meanwhile reaches position 0 whole, with no rotation before: `h += a β'`, its own share of
//! g. The gather walks the rows there were at its start, those added since come in that way,
//! and when it is done `h = g` and the solve begins. Gathering takes a median 7 steps of the 19
//! a spread takes on city10000 (2 of 5 on M3500, 4 of 16 on the 100 000-pose world).
//!
//! A row's rotations are replayed on `d'` when it is kept (a tried row taken back never
//! reaches it); a shift of the last row's β (`shift_last_row`) moves `d'` through the same
//! gains and `h` through the row as it crossed p. What the spread does not follow — a removed
//! row, a shift of another row's β in these right-hand sides, a shift after p moved — marks it
//! stale, and its owner starts it again from the rows.

use super::{Lanes, PREFETCH_AHEAD, SqrtInfo, gather, lane};
use std::ops::Range;

/// Positions solved per step: a spread ends after about this many steps (fewer when the
/// factor is small: [`MIN_BLOCK`]).
pub(super) const SPREAD_STEPS: usize = 16;

/// Values of R eliminated per step at least.
const MIN_BLOCK: usize = 4096;

/// A row gathered into g counts as this many values of R eliminated. Measured with scratch
/// timers (`so2lin stream FILE --json`, robot order, 2026-12-07): a row took 4.6 ns on
/// city10000 against 2.6 ns per value of the solve, and 11.5–13.7 ns against 3.0–3.4 ns on a
/// 100 000-pose world, whose g and order no longer fit in the caches (its rows' writes into g
/// scatter, the solve reads R in order). In that world's last fifth, a median gathering block
/// took 0.31 ms against 0.30 ms for a block of its solve (at 3, 0.44 against 0.27 ms); on
/// city10000 7 against 12 µs.
const GATHER_COST: usize = 4;

/// The state of a spread forward solve (module docs).
#[derive(Clone, Debug)]
pub(super) struct Spread<const K: usize, const L: usize> {
    /// The right-hand sides it computes: `from..K`.
    from: usize,
    /// Positions before p are solved.
    p: usize,
    /// The new right-hand sides of the positions before p.
    d_new: Vec<[f64; K]>,
    /// For the positions from p on: the part of g not yet eliminated.
    h: Vec<[f64; K]>,
    /// The owner's rows `gathered..rows` are still to be gathered into h (module docs).
    gathered: usize,
    rows: usize,
    /// The rotations of the row being rotated in at rows before p: `(k, c, s)`.
    log: Vec<(u32, [f64; L], [f64; L])>,
    /// That row as it reached position p or beyond (all its positions from p on), and the
    /// product of the cosines of the rotations before.
    crossing: Vec<(u32, [f64; L])>,
    crossing_gain: [f64; L],
    /// Whether the row being rotated in has reached p (`crossing` is kept, nothing more is
    /// logged).
    crossed: bool,
    /// The β of a tried row not yet kept (taken in at `keep_row`).
    pending: Option<[f64; K]>,
    /// `log` and `crossing` belong to the last row taken in, at the current p.
    follows_last: bool,
    /// Changed in a way it does not follow: to start again.
    stale: bool,
}

impl<const K: usize, const L: usize> Spread<K, L> {
    /// The row being rotated in meets row k: whether k lies before p (then its rotation is
    /// logged: [`Self::log`]). At the first k from p on, the row's entries (`positions` and
    /// `values`, from its head on) and the product `gain` of the cosines so far are kept.
    pub(super) fn meet(
        &mut self,
        k: usize,
        (positions, values): (&[u32], &[[f64; L]]),
        gain: [f64; L],
    ) -> bool {
        if self.crossed {
            return false;
        }
        if k < self.p {
            return true;
        }
        self.crossed = true;
        self.crossing_gain = gain;
        self.crossing.extend(
            (positions.iter().copied().zip(values.iter().copied()))
                .filter(|(_, v)| v.iter().any(|&x| x != 0.0)),
        );
        false
    }

    /// Log the rotation `(c, s)` at row k (before p).
    pub(super) fn log(&mut self, k: usize, c: [f64; L], s: [f64; L]) {
        self.log.push((k as u32, c, s));
    }
}

impl<const K: usize, const L: usize> SqrtInfo<K, L> {
    /// Begin a spread forward solve of right-hand sides `from..K` from the owner's first `rows`
    /// rows (their g gathered first, over the next [`Self::spread_advance`]s: module docs),
    /// replacing any in progress.
    pub fn spread_begin(&mut self, from: usize, rows: usize) {
        let n = self.len();
        let from = from.min(K);
        // Room for the variables the factor has room for (reserved by its owner), so that none
        // appended while the spread runs makes a step copy its arrays: with exactly n, the
        // first odometry step after a spread began copied both into fresh memory (city10000:
        // 0.13–0.42 ms, 8 or 9 of the slowest 1 % of its steps). Zeroed by the allocator, the
        // room's pages are touched only when used.
        let room = self.capacity().max(n);
        let zeroed = || {
            let mut v = vec![[0.0; K]; room];
            v.truncate(n);
            v
        };
        // The arrays of the last spread (one in progress, or ended) serve again: allocated
        // afresh, zeroing them cost the step that began a spread a median 26 µs on city10000
        // and up to 0.47 ms (scratch timers, 2026-12-07). d' needs no zeros (each position is
        // written before it is read); h is zero before that spread's p (its solve zeroes each
        // position it eliminates, and no row reaches a position before p), so only h[p..]
        // is zeroed here: nothing when that spread ended.
        let mut sp = match self.spread.take().or_else(|| self.spread_spare.take()) {
            Some(mut sp) => {
                let from_p = sp.p.min(sp.h.len());
                crate::work::estimated((sp.h.len() - from_p) as u64);
                sp.h[from_p..].fill([0.0; K]);
                for v in [&mut sp.h, &mut sp.d_new] {
                    v.truncate(n);
                    v.resize(n, [0.0; K]);
                    // (Refused, it grows as it would have.)
                    let _ = v.try_reserve(room - n);
                }
                sp
            }
            None => {
                crate::work::estimated(n as u64);
                Box::new(Spread {
                    from,
                    p: 0,
                    d_new: zeroed(),
                    h: zeroed(),
                    gathered: 0,
                    rows,
                    log: Vec::new(),
                    crossing: Vec::new(),
                    crossing_gain: [1.0; L],
                    crossed: false,
                    pending: None,
                    follows_last: false,
                    stale: false,
                })
            }
        };
        // (A fresh one holds these already; one taken again is reset.)
        sp.from = from;
        sp.p = 0;
        sp.gathered = 0;
        sp.rows = rows;
        sp.log.clear();
        sp.crossing.clear();
        sp.crossing_gain = [1.0; L];
        sp.crossed = false;
        sp.pending = None;
        sp.follows_last = false;
        sp.stale = false;
        self.spread = Some(sp);
    }

    /// Whether a spread of right-hand sides `from..K` is in progress and follows R.
    pub fn spreading(&self, from: usize) -> bool {
        self.spread
            .as_ref()
            .is_some_and(|s| !s.stale && s.from == from.min(K))
    }

    /// Drop the spread in progress, if any (its arrays kept for the next).
    pub fn spread_cancel(&mut self) {
        if let Some(sp) = self.spread.take() {
            self.spread_spare = Some(sp);
        }
    }

    /// Gather the next block of rows, then solve the next block of positions (together about
    /// a [`SPREAD_STEPS`]-th of R, more at a step whose own rotations so far were light and
    /// less at a heavy one: [`super::levelled`]); at the end, the new right-hand sides replace
    /// d's and the spread is over. `rows(range)` gives the owner's rows `range` (their entries
    /// and β, as for [`Self::reset_rhs_in`]). Whether it is over (true when none was in
    /// progress).
    pub fn spread_advance<I, const N: usize, C: Lanes<L>>(
        &mut self,
        rows: impl FnOnce(Range<usize>) -> I,
    ) -> bool
    where
        I: IntoIterator<Item = ([(usize, C); N], [f64; K])>,
    {
        let n = self.len();
        let base = ((n + self.nnz) / SPREAD_STEPS).max(MIN_BLOCK);
        let budget = self.levelled_block(base, self.work);
        let Some(sp) = self.spread.as_mut() else {
            return true;
        };
        let from = sp.from;
        let mut done = 0;
        if sp.gathered < sp.rows {
            let block = sp.gathered..sp.rows.min(sp.gathered + budget.div_ceil(GATHER_COST));
            done += block.len() * GATHER_COST;
            sp.gathered = block.end;
            gather(&self.pos_of, &mut sp.h, from..K, rows(block));
        }
        while sp.gathered == sp.rows && sp.p < n && done < budget {
            let k = sp.p;
            // (Zeroed for the next spread, which takes h[..p] as zeros: module docs.)
            let mut dk = std::mem::replace(&mut sp.h[k], [0.0; K]);
            let diag = self.diag[k];
            for (q, x) in dk.iter_mut().enumerate().skip(from) {
                *x /= diag[lane::<L>(q)];
            }
            if let Some(ahead) = self.rows.get(k + PREFETCH_AHEAD) {
                ahead.prefetch();
            }
            let row = &self.rows[k];
            for (&j, a) in row.pos.iter().zip(&row.val) {
                let hj = &mut sp.h[j as usize];
                for q in from..K {
                    hj[q] -= a[lane::<L>(q)] * dk[q];
                }
            }
            sp.d_new[k] = dk;
            done += 1 + row.len();
            sp.p += 1;
        }
        // A shift of the last row after this would split its path at another p.
        sp.follows_last = false;
        crate::work::estimated(done as u64);
        if sp.p < n {
            return false;
        }
        for (d, new) in self.d.iter_mut().zip(&sp.d_new) {
            d[from..].copy_from_slice(&new[from..]);
        }
        self.spread_cancel();
        true
    }

    /// A new variable at the end of the order.
    pub(super) fn spread_push(&mut self) {
        if let Some(sp) = &mut self.spread {
            sp.d_new.push([0.0; K]);
            sp.h.push([0.0; K]);
        }
    }

    /// A rotation begins (`downdate`: a removed row, which the spread does not follow).
    pub(super) fn spread_begin_row(&mut self, downdate: bool) {
        if let Some(sp) = &mut self.spread {
            sp.log.clear();
            sp.crossing.clear();
            sp.crossing_gain = [1.0; L];
            sp.crossed = false;
            sp.follows_last = false;
            sp.stale |= downdate;
        }
    }

    /// The row just rotated in is kept with right-hand side `beta` (now, or at `keep_row`
    /// when `tried`).
    pub(super) fn spread_take(&mut self, beta: [f64; K], tried: bool) {
        let Some(sp) = &mut self.spread else {
            return;
        };
        if tried {
            sp.pending = Some(beta);
            return;
        }
        let from = sp.from;
        let mut b = beta;
        for &(k, c, s) in &sp.log {
            let dk = &mut sp.d_new[k as usize];
            for q in from..K {
                let l = lane::<L>(q);
                (dk[q], b[q]) = (c[l] * dk[q] + s[l] * b[q], c[l] * b[q] - s[l] * dk[q]);
            }
        }
        for &(j, v) in &sp.crossing {
            let hj = &mut sp.h[j as usize];
            for q in from..K {
                hj[q] += v[lane::<L>(q)] * b[q];
            }
        }
        sp.follows_last = true;
    }

    /// A tried row is kept.
    pub(super) fn spread_keep(&mut self) {
        if let Some(beta) = self.spread.as_mut().and_then(|sp| sp.pending.take()) {
            self.spread_take(beta, false);
        }
    }

    /// A tried row is taken back (it never reached the spread).
    pub(super) fn spread_undo(&mut self) {
        if let Some(sp) = &mut self.spread {
            sp.pending = None;
            sp.follows_last = false;
        }
    }

    /// The last row's β moved by `delta` (its gains valid): `d'` by the gains at rows before
    /// p, `h` by the row as it crossed p.
    pub(super) fn spread_shift_last(&mut self, delta: [f64; K]) {
        let Some(sp) = &mut self.spread else {
            return;
        };
        let from = sp.from;
        if delta[from..].iter().all(|&x| x == 0.0) {
            return;
        }
        if let Some(b) = &mut sp.pending {
            // The rotations are linear in β: taken in later with β + Δβ.
            for q in from..K {
                b[q] += delta[q];
            }
            return;
        }
        if !sp.follows_last {
            sp.stale = true;
            return;
        }
        for &(k, g) in &self.gains {
            if (k as usize) < sp.p {
                let dk = &mut sp.d_new[k as usize];
                for q in from..K {
                    dk[q] += g[lane::<L>(q)] * delta[q];
                }
            }
        }
        for &(j, v) in &sp.crossing {
            let hj = &mut sp.h[j as usize];
            for q in from..K {
                let l = lane::<L>(q);
                hj[q] += v[l] * sp.crossing_gain[l] * delta[q];
            }
        }
    }

    /// Some row's β moved by `delta` by a forward solve along its path: followed only where
    /// the spread's right-hand sides do not move.
    pub(super) fn spread_shift_other(&mut self, delta: [f64; K]) {
        if let Some(sp) = &mut self.spread
            && delta[sp.from..].iter().any(|&x| x != 0.0)
        {
            sp.stale = true;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A spread holds room for the variables its factor has room for: variables appended while
    /// it runs do not move its arrays (a step would copy them), and it still ends with the
    /// right-hand sides of one forward solve made at once. The next spread takes the same
    /// arrays, after one that ended (h left zero) and after one dropped half way (h zeroed
    /// again), and ends equal to a solve at once as well.
    #[test]
    fn variables_appended_during_a_spread_do_not_move_its_arrays() {
        let mut f = SqrtInfo::<2, 1>::new();
        f.try_reserve(3200).unwrap();
        type Rows = Vec<([(usize, f64); 2], [f64; 2])>;
        let mut rows: Rows = Vec::new();
        let add = |f: &mut SqrtInfo<2, 1>, rows: &mut Rows, a: usize, b: usize, beta: [f64; 2]| {
            let row = [(a, -1.0), (b, 1.0)];
            f.add_row(&row, beta);
            rows.push((row, beta));
        };
        f.push_variable(0);
        f.add_row(&[(0, 1.0)], [0.0; 2]);
        for v in 1..3000 {
            f.push_variable(v);
            add(&mut f, &mut rows, v - 1, v, [0.1, v as f64]);
        }
        f.spread_begin(1, rows.len());
        let at = |f: &SqrtInfo<2, 1>| {
            let sp = f.spread.as_ref().expect("spreading");
            (sp.h.as_ptr(), sp.d_new.as_ptr())
        };
        let before = at(&f);
        let mut steps = 0;
        for v in 3000..3200 {
            f.push_variable(v);
            add(&mut f, &mut rows, v - 1, v, [0.1, v as f64]);
            if v % 7 == 0 {
                add(&mut f, &mut rows, v - 150, v, [0.3, 2.0]);
            }
            assert_eq!(at(&f), before, "moved at variable {v}");
            let done = f.spread_advance(|range| rows[range].to_vec());
            steps += 1;
            if done {
                break;
            }
        }
        assert!(steps > 1, "a spread of one step");
        let equal_to_once = |f: &mut SqrtInfo<2, 1>, rows: &Rows| {
            let spread: Vec<f64> = f.d.iter().map(|d| d[1]).collect();
            let mut once = f.clone();
            once.reset_rhs_from(1, rows.iter().copied());
            let off =
                (spread.iter().zip(&once.d)).fold(0.0_f64, |m, (a, b)| m.max((a - b[1]).abs()));
            assert!(off < 1e-9, "{off}");
        };
        equal_to_once(&mut f, &rows);
        // New measurements (re-linearisations), solved in the first spread's arrays by a
        // spread that runs to its end, then one dropped after a step and one to the end.
        for (round, drop_after) in [None, Some(1), None].into_iter().enumerate() {
            for (i, (_, beta)) in rows.iter_mut().enumerate() {
                beta[1] = ((i + round) % 13) as f64 - 6.0;
            }
            f.spread_begin(1, rows.len());
            assert_eq!(at(&f), before, "new arrays");
            for step in 0.. {
                if Some(step) == drop_after {
                    f.spread_cancel();
                    break;
                }
                if f.spread_advance(|range| rows[range].to_vec()) {
                    equal_to_once(&mut f, &rows);
                    break;
                }
            }
        }
    }
}
