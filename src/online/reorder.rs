//! Renewing the factor of P_UU, `P_UU = L Lᵀ` over the determined cycles, in a fill-reducing
//! order without a stall. Appending a row per determined cycle in the order they are
//! determined lets L fill in (conditioning a new cycle solves `L y = P_U,new`, whose cost is
//! the entries of L it reaches), while the conditional moments `mean = μ + yᵀz`,
//! `var = P − ‖y‖²` do not depend on the order. So when L's fill per row has grown by half,
//! L is rebuilt in approximate-minimum-degree order:
//!
//! - **in the step**, when the rebuild is expected to cost at most [`REORDER_IN_STEP_WORK`]
//!   (counted work: about 1.5 ms on the development machine, M3500's factors but its last);
//! - otherwise **beside** the live one on the worker thread (module `renewal`), sent every later
//!   cycle and determination, and collected at a count of the live factor's work fixed in
//!   advance, so that no step waits for a large rebuild.
//!
//! Why not always beside: on the development machine (two virtual cores) the steps around a
//! builder running beside them were slower and their latencies noisy, and the factor renewed
//! beside fills on meanwhile (a renewal is collected 100–150 steps after it starts on M3500).
//! The noise was traced only in part: frees on the worker of memory the steps allocate (they
//! share the allocator's locks) account for some of it, and a busy thread that allocates
//! nothing of ours did not slow the steps (`benches/MEASUREMENTS.md`). Measured on clean M3500
//! in robot order with the screening alone, p99 of a step against the single-threaded build
//! before issue 11 (which rebuilt in the step, 2–3 ms): 1.83× and 1.87× with every renewal
//! beside, 1.15× and 1.20× with the small ones in the step (two batches of nine alternating
//! runs; the worst step 0.8–1.3 ms against 1.5 ms). The rebuild in the step decides as the
//! renewal beside does (the same cycles and values; the conditional moments agree to
//! rounding).

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
/// A renewal of the P_UU factor expected to cost at most this much work (the units of
/// [`Conditioner::take_work`], its order counted by `ORDER_WORK_PER_NONZERO`) is built in the
/// step that starts it instead of beside it ([`OnlineEstimator::maybe_reorder`]). On the
/// development machine that is a rebuild of up to about 1.5 ms (M3500: 1 227 determined cycles,
/// 1.3 ms, of which 0.7 ms the order; its last renewal, 1 546 cycles and 1.8 ms, is built
/// beside), below the 2 ms bound on M3500's worst step.
pub(super) const REORDER_IN_STEP_WORK: f64 = 500_000.0;

impl OnlineEstimator {
    /// Renew the factor of P_UU in a fill-reducing order when appending in chronological
    /// order has made it much denser than a reordered one would be (amortised: its fill per
    /// row must grow by half first). Conditional moments do not depend on the order. A rebuild
    /// expected to cost at most [`Self::reorder_in_step_work`] (by default
    /// [`REORDER_IN_STEP_WORK`]) is done here ([`Self::reorder_in_step`]). A larger one is
    /// built **beside** the live one on another thread, from a snapshot of the
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
        let per_row = self.live_fill_per_row();
        let base = if self.fill_after_reorder.is_finite() {
            self.fill_after_reorder
        } else {
            1.0
        };
        if per_row <= REORDER_FILL_RATIO * base.max(1.0) {
            return;
        }
        // The builder's work in the live factor's units.
        let expected = self.expected_rebuild_work(rows);
        let determined = self.screener.cond.determined();
        if expected <= self.reorder_in_step_work {
            self.reorder_in_step(&determined);
            return;
        }
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
        self.cond_work += self.screener.cond.take_work();
        let worker = &mut self.worker;
        match renewal::Beside::start(worker, "so2lin-reorder", build, apply, finish) {
            Some(build) => {
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
            None => self.renewal_failed(),
        }
    }

    /// The work a rebuild of the P_UU factor over `rows` determined cycles is expected to
    /// cost, in the live factor's units ([`Conditioner::take_work`]): its solves, expected from
    /// the last renewal's per determined cycle (at least one solve of the live fill per row),
    /// and the fill-reducing order it computes first, about as long per nonzero of P_γ as
    /// [`ORDER_WORK_PER_NONZERO`] entries of a solve (measured on city10000: 10.8 ms for
    /// 115 000 nonzeros, against 5 ns per entry).
    pub(super) fn expected_rebuild_work(&self, rows: usize) -> f64 {
        rows as f64 * self.rebuild_work_per_row.max(self.live_fill_per_row())
            + ORDER_WORK_PER_NONZERO * self.model.nnz() as f64
    }

    /// A renewal could not be made (no worker thread, or a rebuild that failed: it cannot for
    /// cycles the live factor holds): the live factor goes on, and the next attempt waits
    /// until its fill per row has grown by half again, instead of repeating at every step.
    fn renewal_failed(&mut self) {
        self.fill_after_reorder = self.live_fill_per_row();
    }

    /// Nonzeros per row of the live factor of P_UU.
    fn live_fill_per_row(&self) -> f64 {
        self.screener.cond.factor_nnz() as f64 / self.screener.cond.len().max(1) as f64
    }

    /// Rebuild the factor of P_UU in a fill-reducing order here, in the step (a small one:
    /// [`REORDER_IN_STEP_WORK`]). The old factor is freed here too (on the worker its frees
    /// contended with this thread's allocations: module docs).
    fn reorder_in_step(&mut self, determined: &[(usize, i64)]) {
        let Ok(mut fresh) = Conditioner::rebuilt(&self.model, determined, 0) else {
            self.renewal_failed();
            return;
        };
        self.rebuild_work_per_row = fresh.take_work() as f64 / fresh.len().max(1) as f64;
        self.screener.cond = fresh;
        self.after_reorder();
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
            self.renewal_failed();
            return;
        }
        self.cond_work += self.screener.cond.take_work();
        if !r.due.reached(self.counters.steps as u64, self.cond_work) {
            return;
        }
        let Some(r) = self.renewal.take() else { return };
        let Some((mut fresh, snapshot)) = r.build.collect(&mut self.cond_waits) else {
            self.renewal_failed();
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
        self.after_reorder();
    }

    /// The fill the next renewal is measured against is the new factor's; one more reorder.
    fn after_reorder(&mut self) {
        self.fill_after_reorder = self.live_fill_per_row();
        self.counters.reorders += 1;
    }
}

#[cfg(test)]
mod tests {
    use crate::gamma::Conditioner;
    use crate::online::predict::tests::same_step;
    use crate::online::{OnlineConfig, OnlineEstimator, robot_order};
    use crate::sim::{SimConfig, simulate};

    /// The factor of P_UU renewed in the step (every renewal), beside it (every renewal) or by
    /// the default rule decides every step alike, ends with the same determined cycles, and
    /// holds what a factor rebuilt from nothing holds (its χ² and a new cycle's moments to
    /// 1e-9): the two paths are one renewal, and the rule choosing between them changes
    /// neither a decision nor an answer. The screening alone (no estimate read: every cycle
    /// conditioned through P_UU, as `so2lin stream --estimate none` runs).
    #[test]
    fn renewals_in_the_step_or_beside_it_decide_alike() {
        let world = simulate(&SimConfig::new(2500, 41)).unwrap();
        let edges = robot_order(world.graph.edges());
        let run = |in_step_work: f64| {
            let config = OnlineConfig {
                estimate_every_step: false,
                ..OnlineConfig::default()
            };
            let mut est = OnlineEstimator::new(config).unwrap();
            est.reorder_in_step_work = in_step_work;
            let steps: Vec<_> = edges.iter().map(|&e| est.add_edge(e).unwrap()).collect();
            (est, steps)
        };
        let (beside, steps_beside) = run(0.0);
        let (in_step, steps_in_step) = run(f64::INFINITY);
        let (default, steps_default) = run(super::REORDER_IN_STEP_WORK);
        for (name, est) in [("beside", &beside), ("in the step", &in_step)] {
            assert!(
                est.counters().reorders >= 3,
                "{name}: {} renewals",
                est.counters().reorders
            );
        }
        assert_eq!(in_step.cond_waits, 0, "no builder waited for in the step");
        for (k, ((b, i), d)) in (steps_beside.iter().zip(&steps_in_step))
            .zip(&steps_default)
            .enumerate()
        {
            assert!(same_step(b, i) && same_step(b, d), "step {k}");
        }
        let mut sets: Vec<Vec<(usize, i64)>> = [&beside, &in_step, &default]
            .iter()
            .map(|e| e.screener.cond.determined())
            .collect();
        for s in &mut sets {
            s.sort_unstable();
        }
        assert!(sets[0].len() > 256 && sets[0] == sets[1] && sets[0] == sets[2]);
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-9 * a.abs().max(b.abs()).max(1.0);
        let model = &in_step.model;
        let mut fresh = Conditioner::rebuilt(model, &sets[0], 0).unwrap();
        let undetermined: Vec<usize> = (0..model.len())
            .filter(|&c| sets[0].binary_search_by_key(&c, |&(d, _)| d).is_err())
            .collect();
        for est in [&beside, &in_step, &default] {
            let mut live = est.screener.cond.clone();
            assert!(close(live.chi2(), fresh.chi2()));
            for &c in undetermined.iter().take(20) {
                let (m, f) = (live.moments(model, c), fresh.moments(model, c));
                assert!(close(m.mean, f.mean) && close(m.var, f.var), "cycle {c}");
            }
        }
    }
}
