//! Rotating a row into R: Givens rotations along the row's elimination-tree path.
//!
//! A row `(w, β)` meets row k of R at its first nonzero position k:
//!
//! ```text
//! ρ = hypot(R_kk, w_k),  c = R_kk/ρ,  s = w_k/ρ,
//! R_k ← c R_k + s w,     w ← c w − s R_k,     d_k ← c d_k + s β,     β ← c β − s d_k,
//! ```
//!
//! which zeroes `w_k`; the row goes on to its next nonzero position, up the elimination-tree
//! path, until it is empty. A removed row is the same with hyperbolic rotations
//! (`ρ = sqrt(R_kk² − w_k²)`, `c = ρ/R_kk`, `s = w_k/R_kk`). What is left of β is the row's
//! prediction error times the product of the cosines (`residual = (β − aᵀx̂)·Πc`), and
//! `1/Πc² = 1 + aᵀ(RᵀR)⁻¹a` is that error's variance in units of the row's ([`Leftover`]).
//!
//! Row k is rotated in place when the row's remaining positions lie in row k's pattern or
//! beyond its last position ([`align`] places them; fill beyond the last is appended),
//! otherwise row k is rebuilt by a merge. The row goes on with row k's pattern; where a
//! rotation cancelled exactly it carries a zero, which later rotations skip as a pivot and
//! never store as fill (until 2026-12-07 a second pass over each rotated row looked for such
//! zeros to drop them: a sixteenth of city10000's robot thread, `perf`). A tentative row
//! ([`SqrtInfo::try_row`]) records each rotation it makes — row k's old length (or, after a
//! merge, its old positions), its diagonal `r` and right-hand side, and the row's pivot `w_k`
//! — and [`SqrtInfo::undo_row`] turns the rotations back, last first, each with the `(c, s)`
//! it had, `c = r/ρ`, `s = w_k/ρ` from the diagonal `ρ` the rotation left (no later rotation
//! of the same row turns row k again: its positions only grow), the same bits: with `w'` the
//! row after the rotation at k (zero after the last one),
//!
//! ```text
//! R_k ← c R_k − s w',     w ← s R_k + c w'     (on row k's pattern; w_k from the record),
//! ```
//!
//! row k's pattern cut back to its old one (the fill's entries are zero up to rounding), its
//! diagonal and right-hand side put back as recorded. The rotations are orthogonal, so the
//! rows come back to within a few units of rounding of their old values (not bit for bit),
//! and the forward pass copies no row's values: that copy was a sixth of a loop closure's
//! rotations, and most tried rows are kept.

use super::{Indefinite, Lanes, Leftover, NONE, Row, SqrtInfo, is_zero, lane};

/// What a tentative row ([`SqrtInfo::try_row`]) needs to be turned back: per row of R it
/// rotated, a [`Rotated`] record; and the factor-wide counts and gains.
#[derive(Clone, Debug)]
pub(super) struct Undo<const K: usize, const L: usize> {
    rows: Vec<Rotated<K, L>>,
    /// The positions of the rows rebuilt by a merge, one range per such record (a row rotated
    /// in place only gained positions at its end: its old length restores its pattern).
    positions: Vec<u32>,
    nnz: usize,
    work: u64,
    gains: Vec<(u32, [f64; L])>,
    gains_valid: bool,
    /// A tried row is pending (neither kept nor undone).
    active: bool,
}

impl<const K: usize, const L: usize> Default for Undo<K, L> {
    fn default() -> Self {
        Self {
            rows: Vec::new(),
            positions: Vec::new(),
            nnz: 0,
            work: 0,
            gains: Vec::new(),
            gains_valid: false,
            active: false,
        }
    }
}

/// One rotation of a tentative row: the row of R it turned (position k) as the row found it —
/// its length, where its positions start in the [`Undo`] record if a merge rebuilt it, its
/// diagonal and right-hand side — and the row's pivot value `w_k`, from which and the two
/// diagonals the rotation's `(c, s)` follow ([`Rotated::turned`]).
#[derive(Clone, Copy, Debug)]
struct Rotated<const K: usize, const L: usize> {
    k: u32,
    /// [`NONE`] when the row was rotated in place (its old pattern is its first `len`).
    positions: u32,
    len: u32,
    diag: [f64; L],
    d: [f64; K],
    pivot: [f64; L],
}

impl<const K: usize, const L: usize> Rotated<K, L> {
    /// The rotation's `(c, s)` per lane, given the diagonal `rho` it left at k: what
    /// [`SqrtInfo::rotate`] computed, the same bits (`c = r/ρ`, `s = w_k/ρ`; a lane without a
    /// pivot did not turn). Only an update's rotations are recorded (a tried row is never a
    /// downdate, whose `(c, s)` are `ρ/r` and `w_k/r`), which `rotate` asserts.
    fn turned(&self, rho: [f64; L]) -> ([f64; L], [f64; L]) {
        let turned = |l: usize| self.pivot[l] != 0.0;
        (
            std::array::from_fn(|l| {
                if turned(l) {
                    self.diag[l] / rho[l]
                } else {
                    1.0
                }
            }),
            std::array::from_fn(|l| {
                if turned(l) {
                    self.pivot[l] / rho[l]
                } else {
                    0.0
                }
            }),
        )
    }
}

impl<const K: usize, const L: usize> SqrtInfo<K, L> {
    /// The row `Σ a_v x_v` into `self.w`, at its variables' positions (repeats summed),
    /// positions ascending.
    pub(super) fn load<C: Lanes<L>>(&mut self, entries: &[(usize, C)]) {
        self.w.clear();
        for &(v, a) in entries {
            let p = self.pos_of[v];
            debug_assert!(p != NONE, "unknown variable {v}");
            let a = a.lanes();
            match self.w.pos.iter().position(|&q| q == p) {
                Some(i) => {
                    for (x, a) in self.w.val[i].iter_mut().zip(a) {
                        *x += a;
                    }
                }
                None => self.w.push(p, a),
            }
        }
        // A handful of entries: sorted by insertion.
        for i in 1..self.w.len() {
            let mut j = i;
            while j > 0 && self.w.pos[j - 1] > self.w.pos[j] {
                self.w.pos.swap(j - 1, j);
                self.w.val.swap(j - 1, j);
                j -= 1;
            }
        }
    }

    /// Add the row `Σ a_v x_v = β` (Givens rotations): what the rotations leave.
    pub fn add_row<C: Lanes<L>>(
        &mut self,
        entries: &[(usize, C)],
        beta: [f64; K],
    ) -> Leftover<K, L> {
        self.load(entries);
        // Cannot fail for an update.
        let (residual, cosines) = self.rotate(beta, false).unwrap_or(([0.0; K], [1.0; L]));
        self.spread_take(beta, false);
        Leftover { residual, cosines }
    }

    /// Add the row `Σ a_v x_v = β` like [`Self::add_row`], keeping what it overwrites until
    /// [`Self::keep_row`] or [`Self::undo_row`] (no other change in between). Returns the
    /// [`Leftover`]: the row's prediction error and variance come with the rotations that add
    /// it (`β − aᵀx̂ = residual/Πc`, `1 + aᵀ(RᵀR)⁻¹a = 1/Πc²`), so a caller can judge the row
    /// before keeping it, at the cost of a small record per rotation ([`Rotated`]).
    pub fn try_row<C: Lanes<L>>(
        &mut self,
        entries: &[(usize, C)],
        beta: [f64; K],
    ) -> Leftover<K, L> {
        let mut undo = self.undo.take().unwrap_or_default();
        undo.rows.clear();
        undo.positions.clear();
        undo.nnz = self.nnz;
        undo.work = self.work;
        undo.gains.clone_from(&self.gains);
        undo.gains_valid = self.gains_valid;
        undo.active = true;
        self.undo = Some(undo);
        self.load(entries);
        let (residual, cosines) = self.rotate_recording(beta);
        self.spread_take(beta, true);
        Leftover { residual, cosines }
    }

    /// Take over `old`'s scratch buffers (the row being rotated, its next state, the aligned
    /// values, the spare row, the tried row's undo record), emptied, their capacity kept, when
    /// this factor replaces `old` (a renewal swapped in). A fresh factor's buffers start empty
    /// and grow by doubling in the steps after the swap, each growth a copy into memory the
    /// allocator must first fault in: the undo record of a heavy loop closure holds a record
    /// per rotation (a thousand and more on city10000); when it held every rotated row's values,
    /// about a megabyte, that growth took 2 % of city10000's robot thread's samples (`perf`;
    /// `benches/MEASUREMENTS.md`, thirty-first session).
    /// A pending tried row's record is not taken (its factor must still undo it).
    pub(crate) fn take_scratch_of(&mut self, old: &mut Self) {
        fn emptied<T>(mine: &mut Vec<T>, theirs: &mut Vec<T>) {
            if theirs.capacity() > mine.capacity() {
                std::mem::swap(mine, theirs);
            }
            mine.clear();
        }
        for (mine, theirs) in [
            (&mut self.w, &mut old.w),
            (&mut self.w_next, &mut old.w_next),
            (&mut self.spare_row, &mut old.spare_row),
        ] {
            emptied(&mut mine.pos, &mut theirs.pos);
            emptied(&mut mine.val, &mut theirs.val);
        }
        emptied(&mut self.aligned, &mut old.aligned);
        if self.spread.is_none() && self.spread_spare.is_none() {
            self.spread_spare = old.spread_spare.take().or_else(|| old.spread.take());
        }
        emptied(&mut self.path, &mut old.path);
        let room = |u: &Option<Box<Undo<K, L>>>| u.as_ref().map_or(0, |u| u.rows.capacity());
        let idle = |u: &Option<Box<Undo<K, L>>>| u.as_ref().is_none_or(|u| !u.active);
        if idle(&self.undo) && idle(&old.undo) && room(&old.undo) > room(&self.undo) {
            std::mem::swap(&mut self.undo, &mut old.undo);
            if let Some(u) = &mut self.undo {
                u.rows.clear();
                u.positions.clear();
                u.gains.clear();
            }
        }
    }

    /// The scratch buffers' room, in values and rotation records (tests of
    /// [`Self::take_scratch_of`]'s callers).
    #[cfg(test)]
    pub(crate) fn scratch_room(&self) -> usize {
        self.w.val.capacity()
            + self.w_next.val.capacity()
            + self.undo.as_ref().map_or(0, |u| u.rows.capacity())
    }

    /// Keep the row of the last [`Self::try_row`].
    pub fn keep_row(&mut self) {
        self.spread_keep();
        if let Some(u) = &mut self.undo {
            u.rows.clear();
            u.positions.clear();
            u.active = false;
        }
    }

    /// Take back the row of the last [`Self::try_row`]: its rotations turned back, last first
    /// (module doc). Every row it touched gets its old pattern, diagonal and right-hand side
    /// exactly, and its old values to within rounding; the gains, counts and work are as
    /// before it. Nothing when no tried row is pending (kept, or already taken back).
    pub fn undo_row(&mut self) {
        let Some(mut u) = self.undo.take_if(|u| u.active) else {
            return;
        };
        self.spread_undo();
        // The row as it was after the rotation being turned back: nothing after the last one.
        let mut after = std::mem::take(&mut self.w);
        let mut before = std::mem::take(&mut self.w_next);
        after.clear();
        for r in u.rows.iter().rev() {
            let k = r.k as usize;
            let (c, s) = r.turned(self.diag[k]);
            let row = &mut self.rows[k];
            before.clear();
            before.push(r.k, r.pivot);
            // `after` lies on row k's pattern but for entries that are rounding (a position the
            // row never had, turned back), which are dropped.
            let mut t = 0;
            for (p, v) in row.pos.iter().zip(row.val.iter_mut()) {
                while t < after.len() && after.pos[t] < *p {
                    t += 1;
                }
                let x = if t < after.len() && after.pos[t] == *p {
                    after.val[t]
                } else {
                    [0.0; L]
                };
                let mut back = [0.0; L];
                for l in 0..L {
                    (v[l], back[l]) = unturn((c[l], s[l]), v[l], x[l]);
                }
                before.push(*p, back);
            }
            let len = r.len as usize;
            if r.positions == NONE {
                row.pos.truncate(len);
                row.val.truncate(len);
            } else {
                let start = r.positions as usize;
                keep_positions(row, &u.positions[start..start + len]);
            }
            self.diag[k] = r.diag;
            self.d[k] = r.d;
            std::mem::swap(&mut after, &mut before);
        }
        after.clear();
        before.clear();
        self.w = after;
        self.w_next = before;
        self.nnz = u.nnz;
        // Work counts what stays: a renewal is due after the same work with or without it.
        self.work = u.work;
        std::mem::swap(&mut self.gains, &mut u.gains);
        self.gains_valid = u.gains_valid;
        u.rows.clear();
        u.positions.clear();
        u.active = false;
        self.undo = Some(u);
    }

    /// Remove a row previously added (hyperbolic rotations). On failure the factor is left
    /// partly updated; the owner rebuilds it.
    pub fn remove_row<C: Lanes<L>>(
        &mut self,
        entries: &[(usize, C)],
        beta: [f64; K],
    ) -> Result<(), Indefinite> {
        self.load(entries);
        self.rotate(beta, true).map(|_| ())
    }

    /// Rotate the row in `self.w` (positions) with right-hand side `beta` into R.
    /// [`Self::rotate`] of an update, recording every row it changes in `self.undo`: the
    /// leftover right-hand side and the product of the cosines.
    fn rotate_recording(&mut self, beta: [f64; K]) -> ([f64; K], [f64; L]) {
        self.recording = self.undo.is_some();
        let out = self.rotate(beta, false).unwrap_or(([0.0; K], [1.0; L]));
        self.recording = false;
        out
    }

    /// Rotate the row in `self.w` (right-hand side β) into R (a hyperbolic downdate when
    /// `downdate`): the leftover right-hand side and the product of the cosines.
    fn rotate(
        &mut self,
        mut beta: [f64; K],
        downdate: bool,
    ) -> Result<([f64; K], [f64; L]), Indefinite> {
        let work_before = self.work;
        // The undo record derives an update's rotations only ([`Rotated::turned`]).
        debug_assert!(!(self.recording && downdate));
        self.spread_begin_row(downdate);
        let mut w = std::mem::take(&mut self.w);
        let mut next = std::mem::take(&mut self.w_next);
        // `Some(j)`: the row's positions are row j of R's (`w.pos` unused), its values `w.val`
        // — what an in-place rotation leaves, so that its pattern is never copied.
        let mut pattern_of: Option<usize> = None;
        let mut head = 0;
        self.gains.clear();
        self.gains_valid = !downdate;
        // The part of the row's right-hand side still to rotate, per unit of β (updates).
        let mut gain = [1.0; L];
        let result = loop {
            while head < w.val.len() && is_zero(&w.val[head]) {
                head += 1;
            }
            if head >= w.val.len() {
                break Ok((beta, gain));
            }
            let wk = w.val[head];
            let k = match pattern_of {
                Some(j) => self.rows[j].pos[head],
                None => w.pos[head],
            } as usize;
            // A spread forward solve logs the rotations before its position and keeps the row
            // as it reaches it (module `spread`).
            let log_spread = match self.spread.as_deref_mut() {
                Some(sp) if !downdate => {
                    let positions = match pattern_of {
                        Some(j) => &self.rows[j].pos[head..],
                        None => &w.pos[head..],
                    };
                    sp.meet(k, (positions, &w.val[head..]), gain)
                }
                _ => false,
            };
            self.work += (L * (1 + self.rows[k].len() + w.val.len() - head)) as u64;
            let (mut c, mut s) = ([1.0; L], [0.0; L]);
            let mut indefinite = false;
            let r = self.diag[k];
            if !downdate && (0..L).all(|l| wk[l] != 0.0 && r[l].abs().max(wk[l].abs()) < 1e150) {
                // Every lane turns, no square near overflow: the lanes at once (what the loop
                // below computes, lane by lane).
                let rho: [f64; L] = std::array::from_fn(|l| (r[l] * r[l] + wk[l] * wk[l]).sqrt());
                c = std::array::from_fn(|l| r[l] / rho[l]);
                s = std::array::from_fn(|l| wk[l] / rho[l]);
                self.diag[k] = rho;
            } else {
                for l in 0..L {
                    let (r, wk) = (self.diag[k][l], wk[l]);
                    if wk == 0.0 {
                        // This lane has no entry here (another has): nothing turns.
                        continue;
                    }
                    let (cl, sl, rho) = if downdate {
                        let rho2 = r * r - wk * wk;
                        if rho2 <= 0.0 || !rho2.is_finite() {
                            indefinite = true;
                            break;
                        }
                        let rho = rho2.sqrt();
                        (rho / r, wk / r, rho)
                    } else {
                        // hypot only where the squares could overflow (it is several times slower).
                        let rho = if r.abs().max(wk.abs()) < 1e150 {
                            (r * r + wk * wk).sqrt()
                        } else {
                            r.hypot(wk)
                        };
                        (r / rho, wk / rho, rho)
                    };
                    (c[l], s[l]) = (cl, sl);
                    self.diag[k][l] = rho;
                }
            }
            if indefinite {
                break Err(Indefinite { position: k });
            }
            if self.recording
                && let Some(u) = &mut self.undo
            {
                // Row k as the row found it (it is turned below), and the rotation.
                u.rows.push(Rotated {
                    k: k as u32,
                    positions: NONE,
                    len: self.rows[k].len() as u32,
                    diag: r,
                    d: self.d[k],
                    pivot: wk,
                });
            }
            if log_spread && let Some(sp) = self.spread.as_deref_mut() {
                sp.log(k, c, s);
            }
            if !downdate {
                self.gains
                    .push((k as u32, std::array::from_fn(|l| s[l] * gain[l])));
                for l in 0..L {
                    gain[l] *= c[l];
                }
            }
            next.clear();
            let in_place = if downdate {
                None
            } else {
                // Row k and the row's pattern (row j of R, j < k, or its own).
                let (below, above) = self.rows.split_at_mut(k);
                let rest_pos = match pattern_of {
                    Some(j) => &below[j].pos[head + 1..],
                    None => &w.pos[head + 1..],
                };
                rotate_in_place(
                    &mut above[0],
                    (c, s),
                    (rest_pos, &w.val[head + 1..]),
                    &mut next.val,
                    &mut self.aligned,
                )
            };
            if let Some(fill) = in_place {
                self.nnz += fill;
                pattern_of = Some(k);
            } else {
                if let Some(j) = pattern_of.take() {
                    w.pos.clear();
                    w.pos.extend_from_slice(&self.rows[j].pos);
                }
                // Fill inside row k (or a downdate): row k rebuilt by a merge with the row.
                let old = std::mem::take(&mut self.rows[k]);
                if self.recording
                    && let Some(u) = &mut self.undo
                    && let Some(r) = u.rows.last_mut()
                {
                    r.positions = u.positions.len() as u32;
                    u.positions.extend_from_slice(&old.pos);
                }
                let mut row = std::mem::take(&mut self.spare_row);
                row.clear();
                let (mut i, mut j) = (0, head + 1);
                while i < old.len() || j < w.len() {
                    let (p, rkj, wj) = match (old.get(i), w.get(j)) {
                        (Some((pa, a)), Some((pb, b))) if pa == pb => {
                            i += 1;
                            j += 1;
                            (pa, a, b)
                        }
                        (Some((pa, a)), Some((pb, _))) if pa < pb => {
                            i += 1;
                            (pa, a, [0.0; L])
                        }
                        (Some(_), Some((pb, b))) => {
                            j += 1;
                            if is_zero(&b) {
                                continue;
                            }
                            (pb, [0.0; L], b)
                        }
                        (Some((pa, a)), None) => {
                            i += 1;
                            (pa, a, [0.0; L])
                        }
                        (None, Some((pb, b))) => {
                            j += 1;
                            if is_zero(&b) {
                                // A zero the row carries (module doc): no fill.
                                continue;
                            }
                            (pb, [0.0; L], b)
                        }
                        (None, None) => unreachable!(),
                    };
                    let (mut rn, mut wn) = ([0.0; L], [0.0; L]);
                    for l in 0..L {
                        (rn[l], wn[l]) = turn(downdate, (c[l], s[l]), rkj[l], wj[l]);
                    }
                    row.push(p, rn);
                    if !is_zero(&wn) {
                        next.push(p, wn);
                    }
                }
                self.nnz = self.nnz + row.len() - old.len();
                self.rows[k] = row;
                self.spare_row = old;
            }
            let dk = &mut self.d[k];
            for q in 0..K {
                let l = lane::<L>(q);
                (dk[q], beta[q]) = turn(downdate, (c[l], s[l]), dk[q], beta[q]);
            }
            std::mem::swap(&mut w, &mut next);
            head = 0;
        };
        w.clear();
        self.w = w;
        self.w_next = next;
        crate::work::estimated(self.work - work_before);
        self.gains_valid &= result.is_ok();
        result
    }
}

/// The values of `rest` (a row being rotated in or solved for, after its pivot) at the positions
/// of `row` (a row of R), zero where `rest` has none, and how many of `rest`'s entries lie
/// within `row`'s range (the others lie beyond its last position: fill from a newer node's
/// column). `None` when `rest` has a position within that range that `row` lacks (fill inside
/// the row: the caller merges). The common case: after its first entry a row's pattern lies in
/// its parent's, so the row being rotated in carries row k's pattern, or part of it.
pub(super) fn align<'a, const L: usize>(
    row: &Row<L>,
    (rest_pos, rest_val): (&[u32], &'a [[f64; L]]),
    aligned: &'a mut Vec<[f64; L]>,
) -> Option<(&'a [[f64; L]], usize)> {
    let l = row.len();
    // Row k's pattern exactly (then whatever follows lies beyond its last position).
    if rest_pos.len() >= l && same(&rest_pos[..l], &row.pos) {
        return Some((&rest_val[..l], l));
    }
    aligned.clear();
    // Row k's pattern less its first position (the row met row k's first position, its
    // parent, as a zero): a third of the rows rotated on M3500, where a merge would branch at
    // every entry.
    if l > 1 && rest_pos.len() >= l - 1 && same(&rest_pos[..l - 1], &row.pos[1..]) {
        aligned.push([0.0; L]);
        aligned.extend_from_slice(&rest_val[..l - 1]);
        return Some((aligned, l - 1));
    }
    let last = row.pos.last().copied().unwrap_or(0);
    aligned.resize(l, [0.0; L]);
    let mut t = 0;
    let mut inside = 0;
    for (&p, &x) in rest_pos.iter().zip(rest_val) {
        if l == 0 || p > last {
            break;
        }
        while row.pos[t] < p {
            t += 1;
        }
        if row.pos[t] != p {
            return None;
        }
        aligned[t] = x;
        t += 1;
        inside += 1;
    }
    Some((aligned, inside))
}

/// Whether two equally long position lists are equal: one pass without an early exit, which
/// the compiler vectorises (the rows are a few dozen entries; a `memcmp` call cost more).
#[inline]
fn same(a: &[u32], b: &[u32]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// Rotate row k of R in place with the row being rotated in (`rest`: its entries after row k's
/// pivot) when [`align`] finds no fill inside row k: row k ← c·row k + s·rest and `next` ←
/// c·rest − s·row k on row k's pattern (a loop over contiguous values), the positions of
/// `rest` beyond row k's last appended to row k (`next` gets their values too): afterwards
/// `next` holds the row's values on row k's whole pattern (a value may be an exact zero, where
/// the rotation cancelled: the rotations that follow skip it as a pivot, and no row of R gains
/// an entry from it). Returns the number of entries appended to row k; `None`, with nothing
/// changed, when there is fill inside the row.
fn rotate_in_place<const L: usize>(
    row: &mut Row<L>,
    (c, s): ([f64; L], [f64; L]),
    (rest_pos, rest_val): (&[u32], &[[f64; L]]),
    next: &mut Vec<[f64; L]>,
    aligned: &mut Vec<[f64; L]>,
) -> Option<usize> {
    let (xs, inside) = align(row, (rest_pos, rest_val), aligned)?;
    next.clear();
    next.extend(row.val.iter_mut().zip(xs).map(|(r, x)| {
        let mut wn = [0.0; L];
        for l in 0..L {
            (r[l], wn[l]) = turn(false, (c[l], s[l]), r[l], x[l]);
        }
        wn
    }));
    let before = row.len();
    for (&p, x) in rest_pos[inside..].iter().zip(&rest_val[inside..]) {
        if is_zero(x) {
            // A zero the row carries: no fill.
            continue;
        }
        // Fill beyond row k's last position: row k's entry there is 0.
        let (mut rn, mut wn) = ([0.0; L], [0.0; L]);
        for l in 0..L {
            (rn[l], wn[l]) = turn(false, (c[l], s[l]), 0.0, x[l]);
        }
        row.push(p, rn);
        next.push(wn);
    }
    Some(row.len() - before)
}

/// Keep the entries of `row` at `positions` (a subset of its own, ascending), in order.
fn keep_positions<const L: usize>(row: &mut Row<L>, positions: &[u32]) {
    let mut o = 0;
    for t in 0..row.len() {
        if o < positions.len() && row.pos[t] == positions[o] {
            row.val[o] = row.val[t];
            o += 1;
        }
    }
    debug_assert_eq!(
        o,
        positions.len(),
        "a merge's old pattern lies in its new one"
    );
    row.pos.clear();
    row.pos.extend_from_slice(positions);
    row.val.truncate(o);
}

/// [`turn`] of an update turned back: (row k's entry, the row's entry after the rotation) →
/// (row k's entry, the row's entry) before it.
#[inline(always)]
fn unturn((c, s): (f64, f64), rk: f64, w: f64) -> (f64, f64) {
    (c * rk - s * w, s * rk + c * w)
}

/// One Givens rotation (a hyperbolic one when `downdate`) of a pair: (row k's entry, the row's
/// entry) → their rotated values.
#[inline(always)]
fn turn(downdate: bool, (c, s): (f64, f64), rkj: f64, wj: f64) -> (f64, f64) {
    if downdate {
        let rn = (rkj - s * wj) / c;
        (rn, c * wj - s * rn)
    } else {
        (c * rkj + s * wj, c * wj - s * rkj)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimate::incremental::tests::{assert_taken_back, chain_with_closures, lcg};

    /// [`align`] against a plain lookup, on random rows and random rests: rests on the row's
    /// whole pattern, on it less its first position (the fast path; a row of one position
    /// included, where a rest before it is fill), on any subset, with entries beyond the
    /// row's last, and with fill inside (`None`).
    #[test]
    fn align_places_a_rest_on_the_rows_pattern() {
        let mut state = 7u64;
        let mut aligned = Vec::new();
        let mut cases = [0usize; 4];
        for trial in 0..4_000 {
            let l = 1 + trial % 9;
            let mut pos: Vec<u32> = Vec::new();
            let mut p = 1 + (lcg(&mut state) * 3.0) as u32;
            for _ in 0..l {
                pos.push(p);
                p += 1 + (lcg(&mut state) * 3.0) as u32;
            }
            let row = Row::<2> {
                val: pos.iter().map(|&q| [f64::from(q), -f64::from(q)]).collect(),
                pos: pos.clone(),
            };
            let kind = trial % 4;
            let mut rest: Vec<u32> = match kind {
                0 => pos.clone(),
                1 => pos[1..].to_vec(),
                _ => pos
                    .iter()
                    .copied()
                    .filter(|_| lcg(&mut state) < 0.6)
                    .collect(),
            };
            if kind == 3 {
                // A position between or before the row's: fill inside (unless it lands on one).
                rest.push((lcg(&mut state) * f64::from(p)) as u32);
            }
            for b in 0..(lcg(&mut state) * 3.0) as u32 {
                rest.push(p + b);
            }
            rest.sort_unstable();
            rest.dedup();
            let vals: Vec<[f64; 2]> = rest.iter().map(|&q| [f64::from(q) + 0.5, 1.0]).collect();
            let last = pos[l - 1];
            let fill = rest.iter().any(|&q| q <= last && !pos.contains(&q));
            let got = align(&row, (&rest, &vals), &mut aligned).map(|(xs, n)| (xs.to_vec(), n));
            if fill {
                assert!(
                    got.is_none(),
                    "fill inside the row not seen: {pos:?} {rest:?}"
                );
                cases[3] += 1;
                continue;
            }
            let want: Vec<[f64; 2]> = pos
                .iter()
                .map(|q| {
                    rest.iter()
                        .position(|r| r == q)
                        .map_or([0.0; 2], |t| vals[t])
                })
                .collect();
            let inside = rest.iter().filter(|&&q| q <= last).count();
            assert_eq!(got, Some((want, inside)), "row {pos:?}, rest {rest:?}");
            cases[kind.min(2)] += 1;
        }
        assert!(cases.iter().all(|&c| c > 100), "cases {cases:?}");
    }

    /// A chain of `n` variables with random loop closures, each tried then kept, so that the
    /// scratch buffers and the undo record have grown.
    fn grown(n: usize, seed: u64) -> SqrtInfo<2> {
        chain_with_closures(n, 60, &mut { seed }, true)
    }

    /// A factor that replaces another takes its scratch buffers emptied, with their capacity
    /// (so that the steps after a renewal's swap do not grow them again), and computes the
    /// same bits as without them: tried rows kept and taken back, rows added. A tried row still
    /// pending in the old factor keeps its record there.
    #[test]
    fn a_replacing_factor_takes_the_old_ones_scratch() {
        let mut old = grown(60, 3);
        let undo_room = old.undo.as_ref().map_or(0, |u| u.rows.capacity());
        let w_room = old.w.val.capacity().max(old.w_next.val.capacity());
        assert!(
            undo_room > 60 && w_room > 2,
            "{undo_room} {w_room}: nothing grew"
        );
        let fresh = grown(40, 5);
        let (mut with, mut without) = (fresh.clone(), fresh);
        with.take_scratch_of(&mut old);
        let u = with.undo.as_ref().expect("the undo record taken");
        assert!(u.rows.capacity() >= undo_room && !u.active);
        assert!(u.rows.is_empty() && u.positions.is_empty());
        assert!(with.w.val.capacity().max(with.w_next.val.capacity()) >= w_room);
        assert!(with.w.len() == 0 && with.w_next.len() == 0 && with.aligned.is_empty());
        let mut s = 9u64;
        for k in 0..30 {
            let (a, b) = ((k * 7) % 40, (k * 13 + 5) % 40);
            if a == b {
                continue;
            }
            let row = [(a, -1.5), (b, 1.5)];
            let beta = [lcg(&mut s), lcg(&mut s)];
            let (l1, l2) = (with.try_row(&row, beta), without.try_row(&row, beta));
            assert_eq!(l1, l2);
            if k % 3 == 0 {
                with.undo_row();
                without.undo_row();
            } else {
                with.keep_row();
                without.keep_row();
            }
            assert_eq!(
                (&with.rows, &with.diag, &with.d),
                (&without.rows, &without.diag, &without.d)
            );
        }
        // A pending tried row stays with its factor.
        let mut pending = grown(30, 7);
        let before = pending.clone();
        let _ = pending.try_row(&[(1, -1.0), (28, 1.0)], [0.3, 0.1]);
        let mut other = grown(20, 8);
        other.take_scratch_of(&mut pending);
        assert!(pending.undo.as_ref().is_some_and(|u| u.active));
        assert!(other.undo.as_ref().is_none_or(|u| !u.active));
        pending.undo_row();
        assert_taken_back(&pending, &before);
    }
}
