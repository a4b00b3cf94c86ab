//! Renewing the factor of P_UU, `P_UU = L Lᵀ` over the determined cycles, in a fill-reducing
//! order without a stall. Appending a row per determined cycle in the order they are
//! determined lets L fill in (conditioning a new cycle solves `L y = P_U,new`, whose cost is
//! the entries of L it reaches), while the conditional moments `mean = μ + yᵀz`,
//! `var = P − ‖y‖²` do not depend on the order. So when L's fill per row has grown by half,
//! L is rebuilt in approximate-minimum-degree order beside the live one on the worker thread
//! (module `renewal`), sent every later cycle and determination, and collected at a count of
//! the live factor's work fixed in advance.

use super::{OnlineEstimator, laplacian, renewal};
use crate::gamma::{Conditioner, GammaModel};

/// A renewal of the P_UU factor built beside the live one ([`OnlineEstimator::maybe_reorder`]).
pub(super) struct CondRenewal {
    /// When it is collected (the live work counted by [`Conditioner::take_work`]).
    due: renewal::Due,
    build: renewal::Beside<(Conditioner, GammaModel), (Conditioner, GammaModel), CondMsg>,
    /// Cycles of the model sent to the builder.
    cycles_sent: usize,
    /// Determinations (positions in the live factor's order) sent to the builder.
    determined_sent: usize,
}

/// What a renewal's builder of the P_UU factor is told as the live estimator goes on.
pub(super) enum CondMsg {
    /// A new cycle: μ_t and its row of P_γ.
    Cycle(f64, Vec<(u32, f64)>),
    /// Cycle c determined with this value.
    Determine(u32, i64),
}

/// Below this many determined cycles L is never reordered (chronological fill is cheap).
const REORDER_MIN_ROWS: usize = 256;
/// Reorder when L's nonzeros per row exceed this multiple of the last reordered factor's.
const REORDER_FILL_RATIO: f64 = 1.5;
/// A renewal of the P_UU factor is collected once the live factor has done this many times
/// the work its builder is expected to do (the builder may share its core with the
/// estimate's).
const REORDER_WORK_MARGIN: f64 = 1.5;
/// The P_UU builder's fill-reducing order, in entries of a solve per nonzero of P_γ.
const ORDER_WORK_PER_NONZERO: f64 = 20.0;

impl OnlineEstimator {
    /// Renew the factor of P_UU in a fill-reducing order when appending in chronological
    /// order has made it much denser than a reordered one would be (amortised: its fill per
    /// row must grow by half first). Conditional moments do not depend on the order. The new
    /// factor is built **beside** the live one on another thread, from a snapshot of the
    /// determined cycles, collected once the live factor has done [`REORDER_WORK_MARGIN`]
    /// times the work the builder is expected to do, and at least a number of steps later
    /// (counts, so the run is deterministic whatever the threads' timing; a step waits only if
    /// the builder is still busy then). The builder is sent every later cycle and
    /// determination and applies them itself, so the swap costs nothing: no step rebuilds or
    /// replays the factor.
    pub(super) fn maybe_reorder(&mut self) {
        if self.renewal.is_some() {
            return;
        }
        let rows = self.screener.cond.len();
        if rows < REORDER_MIN_ROWS {
            return;
        }
        let per_row = self.screener.cond.factor_nnz() as f64 / rows as f64;
        let base = if self.fill_after_reorder.is_finite() {
            self.fill_after_reorder
        } else {
            1.0
        };
        if per_row <= REORDER_FILL_RATIO * base.max(1.0) {
            return;
        }
        let determined = self.screener.cond.determined();
        let model = self.model.rows_only();
        // The rebuilt factor is small (fill-reducing order) while the live one keeps filling:
        // collect it as soon as the builder can be done. That is counted in the live factor's
        // own work (below), so a collection does not come later in time as the live steps grow
        // slower; and at least per_row steps after the start: rebuilding costs about rows · f²
        // for a fresh fill of f ≤ per_row per row, a step's solve up to rows · per_row (the
        // bound that matters when P_γ is dense: complete graphs, per_row ≈ rows/2).
        let delay = laplacian::MIN_DELAY.max(per_row.ceil() as u64);
        let build = move || {
            let fresh = Conditioner::rebuilt(&model, &determined, 0).ok()?;
            Some((fresh, model))
        };
        // Keep up with the live model and determinations until collected.
        let apply = |(fresh, model): &mut (Conditioner, GammaModel), msg: CondMsg| {
            match msg {
                CondMsg::Cycle(mu, row) => {
                    model.push_row(mu, &row);
                }
                CondMsg::Determine(c, v) => {
                    fresh.determine(model, c as usize, v).ok()?;
                }
            }
            Some(())
        };
        // The builder's copy of the model comes back to be freed on the worker: its row per
        // cycle cost the collecting step 0.33 ms to free on city10000, about 8 ms on a
        // 100 000-pose world.
        let finish = |built: (Conditioner, GammaModel)| built;
        // The builder's work in the live factor's units: its solves, expected from the last
        // one's per determined cycle (at least one solve of the current fill per row), and the
        // fill-reducing order it computes first, about as long per nonzero of P_γ as
        // ORDER_WORK_PER_NONZERO entries of a solve (measured on city10000: 10.8 ms for 115 000
        // nonzeros, against 5 ns per entry).
        let expected = rows as f64 * self.rebuild_work_per_row.max(per_row)
            + ORDER_WORK_PER_NONZERO * self.model.nnz() as f64;
        self.cond_work += self.screener.cond.take_work();
        let worker = &mut self.worker;
        if let Some(build) = renewal::Beside::start(worker, "so2lin-reorder", build, apply, finish)
        {
            self.renewal = Some(CondRenewal {
                due: renewal::Due {
                    step: self.counters.steps as u64 + delay,
                    work: self.cond_work + (REORDER_WORK_MARGIN * expected) as u64,
                },
                build,
                cycles_sent: self.model.len(),
                determined_sent: rows,
            });
        }
    }

    /// Advance a renewal of the P_UU factor (see [`Self::maybe_reorder`]): tell the builder
    /// about this step's cycle and determinations, and at its step collect it and swap it in.
    pub(super) fn advance_reorder(&mut self) {
        let Some(r) = &mut self.renewal else { return };
        let live = &self.screener.cond;
        let mut sent = true;
        for t in r.cycles_sent..self.model.len() {
            let msg = CondMsg::Cycle(self.model.mu()[t], self.model.row(t).to_vec());
            sent &= r.build.send(msg);
        }
        r.cycles_sent = self.model.len();
        for &c in &live.order()[r.determined_sent..] {
            let v = live.value(c as usize).unwrap_or(0);
            sent &= r.build.send(CondMsg::Determine(c, v));
        }
        r.determined_sent = live.len();
        if !sent {
            self.renewal = None;
            return;
        }
        self.cond_work += self.screener.cond.take_work();
        if !r.due.reached(self.counters.steps as u64, self.cond_work) {
            return;
        }
        let Some(r) = self.renewal.take() else { return };
        let Some((mut fresh, snapshot)) = r.build.collect(&mut self.cond_waits) else {
            return;
        };
        self.worker.retire("so2lin-reorder", snapshot);
        // The builder's own work (its build and the changes it applied).
        self.rebuild_work_per_row = fresh.take_work() as f64 / fresh.len().max(1) as f64;
        self.install_conditioner(fresh);
    }

    /// Swap in a P_UU factor rebuilt in a fill-reducing order (a renewal's, or the catch-up of
    /// module `predict`): the old one is freed on the worker, and the fill the next renewal is
    /// measured against is this one's.
    pub(super) fn install_conditioner(&mut self, fresh: Conditioner) {
        let old = std::mem::replace(&mut self.screener.cond, fresh);
        self.worker.retire("so2lin-reorder", old);
        let rows = self.screener.cond.len().max(1);
        self.fill_after_reorder = self.screener.cond.factor_nnz() as f64 / rows as f64;
        self.counters.reorders += 1;
    }
}
