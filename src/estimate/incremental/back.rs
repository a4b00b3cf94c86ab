//! A back-substitution spread over steps: every variable's value for one right-hand side,
//! computed a block of positions at a time while rows keep being rotated into R.
//!
//! `R x = d` is solved from the last position down, `x_p = (d_p − Σ_{j>p} R_pj x_j) / R_pp`.
//! Done a block of positions per step, each block reads R and d as they are at its own step,
//! and the values it already has for the positions above it (solved at earlier steps). So the
//! answer is not the solution of one moment's system: position p gets the value that the
//! system of its block's step gives it, *given* the values its ancestors (the positions of
//! its row) took at their own steps. For a Laplacian that conditional value is a weighted
//! average of the ancestors' values plus what the right-hand side drives (eliminating the
//! positions below p leaves a Laplacian, whose weights are positive and sum to at most 1, the
//! rest going to an anchor's prior), so by the maximum principle it is off the solution of its
//! step by at most the most an ancestor's value is off the solution of that step. By
//! induction from the last position down, every value is off the solution of its own step,
//! and so of the last block's, by at most the sum over the steps in between of the most any
//! value moved in a step — what a bound that adds up each step's movement counts. Its owner
//! counts that as lag (module `online::estimate`: a re-linearisation of the position rows,
//! whose headings come from here).
//!
//! Variables appended while it runs take the last positions, above every position still to be
//! solved: each block first solves any new ones (their rows read only each other), since a row
//! still to be solved may have gained an entry at them. A factor replaced (a renewal swapped
//! in, a rebuild) drops the solve with its state.

use super::{PREFETCH_AHEAD, SqrtInfo, lane};

/// Positions solved per step: a solve ends after about this many steps (fewer when the factor
/// is small: [`MIN_BLOCK`]).
pub(crate) const BACK_STEPS: usize = 8;

/// Values of R a block reads at least (about 25 µs), so that a small factor's headings take a
/// step or two.
const MIN_BLOCK: usize = 32768;

/// The state of a spread back-substitution (module docs).
#[derive(Clone, Debug)]
pub(super) struct Back {
    /// The right-hand side solved.
    q: usize,
    /// Values by position: those from `next` up are solved.
    x: Vec<f64>,
    /// The positions below this one are still to be solved.
    next: usize,
}

impl<const K: usize, const L: usize> SqrtInfo<K, L> {
    /// Start solving right-hand side `q` a block per step ([`Self::back_advance`]), dropping a
    /// solve in progress.
    pub fn back_start(&mut self, q: usize) {
        let n = self.len();
        // Room for the variables the factor has room for (reserved by its owner), so that
        // none appended while the solve runs makes a step copy the values.
        let mut x = Vec::with_capacity(self.capacity().max(n));
        x.resize(n, 0.0);
        self.back = Some(Box::new(Back {
            q: q.min(K - 1),
            x,
            next: n,
        }));
    }

    /// Solve the next block of positions (about a [`BACK_STEPS`]-th of R, more at a step
    /// whose own work `own` was light and less at a heavy one, [`super::levelled`]; after the
    /// variables appended since the last block): whether the solve is complete, None when no
    /// solve is in progress (none started, or the factor was replaced since).
    pub fn back_advance(&mut self, own: u64) -> Option<bool> {
        self.back_advance_by(self.levelled_block(self.back_base(), own))
    }

    /// The share of its usual block a block of [`Self::back_advance`] takes after a step whose
    /// own work was `own` ([`super::levelled`]).
    pub fn back_share(&self, own: u64) -> f64 {
        self.levelled_share(self.back_base(), own)
    }

    /// The usual block of [`Self::back_advance`]: a [`BACK_STEPS`]-th of R, at least
    /// [`MIN_BLOCK`] entries.
    fn back_base(&self) -> usize {
        ((self.len() + self.nnz) / BACK_STEPS).max(MIN_BLOCK)
    }

    /// [`Self::back_advance`] by a block of at least `budget` values of R.
    pub(crate) fn back_advance_by(&mut self, budget: usize) -> Option<bool> {
        let mut b = self.back.take()?;
        let n = self.len();
        let l = lane::<L>(b.q);
        let mut done = 0;
        let solve = |p: usize, x: &[f64]| {
            let [s] = self.rows[p].dot([l], |j| [x[j]]);
            (self.d[p][b.q] - s) / self.diag[p][l]
        };
        // Appended variables first: they are above every position, and rows below may hold
        // them by fill.
        let appended = b.x.len();
        if appended < n {
            b.x.resize(n, 0.0);
            for p in (appended..n).rev() {
                b.x[p] = solve(p, &b.x);
                done += 1 + self.rows[p].len();
            }
        }
        while b.next > 0 && done < budget {
            let p = b.next - 1;
            if let Some(ahead) = p.checked_sub(PREFETCH_AHEAD) {
                self.rows[ahead].prefetch();
            }
            b.x[p] = solve(p, &b.x);
            done += 1 + self.rows[p].len();
            b.next = p;
        }
        crate::work::estimated(done as u64);
        let complete = b.next == 0;
        self.back = Some(b);
        Some(complete)
    }

    /// The values of a complete solve, by variable (None: none complete); the solve ends.
    pub fn back_take(&mut self) -> Option<Vec<f64>> {
        if self
            .back
            .as_ref()
            .is_none_or(|b| b.next > 0 || b.x.len() < self.len())
        {
            return None;
        }
        let b = self.back.take()?;
        let mut out = vec![0.0; self.pos_of.len()];
        for (p, &v) in self.var_at.iter().enumerate() {
            out[v as usize] = b.x[p];
        }
        Some(out)
    }

    /// Drop a solve in progress.
    pub fn back_cancel(&mut self) {
        self.back = None;
    }
}
