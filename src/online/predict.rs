//! Screening a new cycle with the estimate's factor (method [§10](crate::method#10-the-estimate-online)):
//! one factor for the estimate and the screening while no cycle is ambiguous.
//!
//! When every accepted loop closure's cycle is determined, the headings' factor `R` (rows
//! `√w_e (θ_j − θ_i) = √w_e (δ_e − 2π k_e)`, `w_e = 1/σ_e²`) holds exactly the information of
//! the determined cycles' integers, and conditioning the new cycle t (chord e = a → b, sign
//! `s` in t, the rest of its path `P` with known wraps) on them is predicting e from `R`:
//!
//! ```text
//! mean_t = s (δ_e − (θ̂_b − θ̂_a)) / 2π + Σ_{f ∈ P} s_f k_f,
//! var_t  = (σ_e² + Var(θ̂_b − θ̂_a)) / 4π²,
//! ```
//!
//! equal to the P_UU conditioning of [`crate::gamma`] (measured: within 1e-12 over the 10 085
//! cycles of city10000). Rotating e's row `√w (e_b − e_a)ᵀθ = √w δ_e` into `R` gives both:
//! the rotations leave `√w (δ_e − (θ̂_b − θ̂_a)) Πc` of its right-hand side, with
//! `1/Πc² = 1 + w Var(θ̂_b − θ̂_a)` (Πc the product of their cosines). The estimate rotates that
//! row in anyway, so the screening costs no solve of its own: the row is kept with its wrap
//! when t is determined (its right-hand side moved by `−2π k_e √w` through the rotations'
//! gains), and taken back otherwise, exactly ([`crate::estimate`]'s tentative rows).
//!
//! A caller that does not read the estimate after every step says so
//! ([`OnlineConfig::estimate_every_step`](super::OnlineConfig::estimate_every_step) off): the
//! factor is then not kept through the steps and every cycle goes through P_UU, which alone
//! is cheaper than the rotations (M3500 screened in 0.027 s of steps against 0.092 s).
//!
//! With the prediction, the P_UU factor is not needed for the new cycle: the cycles determined this way wait
//! in a backlog, appended to P_UU (or P_UU rebuilt in a fill-reducing order, when they are
//! more than an eighth of its cycles, or when appending them costs several times what the
//! rebuild is expected to: [`with_backlog`]) before anything uses it: a cycle that must be
//! screened by P_UU (some cycle is ambiguous, so its chord is in `R` with a guessed wrap; the factors are deferred, within a
//! replay that builds them after it, module `rebuild`; or the new edge would widen a shared
//! factor to two lanes), the second screening, `finish`.
//! The success bound takes the backlog's conditional deviations as they were when determined.
//! On city10000 in robot order, the newest pose read after every step, this took the steps
//! from 1.50–1.54 s to 1.10–1.20 s and the worst step from 4.1–5.6 ms to 1.3–2.0 ms (no P_UU
//! renewal is waited for when P_UU does not grow; measured before the estimate's renewals were
//! collected later; `benches/MEASUREMENTS.md`, "Measured on 2026-12-03").

use std::f64::consts::TAU;

use super::OnlineEstimator;
use crate::cycles::Cycle;
use crate::gamma::{Conditioner, GammaModel, Moments};
use crate::graph::Edge;
use crate::screening::Screener;

impl OnlineEstimator {
    /// Conditional moments of the new cycle t (chord `edge`, a → b, term 0 of `cycle`) given
    /// the determined cycles, from the estimate's factor (module docs: one factor), with the
    /// chord's heading row rotated in tentatively ([`Estimate::try_chord`](super::estimate::Estimate::try_chord)): `None` when P_UU
    /// must give them (an ambiguous cycle's chord is in the factor with a guessed wrap, the
    /// factors are deferred, or the edge would widen the factor).
    pub(super) fn predict(
        &mut self,
        cycle: &Cycle,
        edge: &Edge,
        a: usize,
        b: usize,
    ) -> Option<Moments> {
        if !self.predicts || !self.ambiguous.is_empty() {
            return None;
        }
        let p = self.estimate.try_chord(&self.graph, edge, a, b)?;
        let rest = self.path_wraps(cycle);
        self.predicted += 1;
        let sign = f64::from(cycle.terms[0].sign);
        Some(Moments {
            mean: sign * p.innovation / TAU + rest as f64,
            var: p.variance / (TAU * TAU),
        })
    }

    /// Append the cycles determined from predictions ([`Self::backlog`]) to the P_UU factor,
    /// in their order, before it is used.
    pub(super) fn sync_conditioner(&mut self) {
        if self.backlog.is_empty() {
            return;
        }
        let backlog = std::mem::take(&mut self.backlog);
        let rows = self.screener.cond.len() + backlog.len();
        let bound = APPEND_BOUND_MARGIN * self.expected_rebuild_work(rows);
        let fresh = with_backlog(&mut self.screener, &self.model, &backlog, bound);
        if let Some(fresh) = fresh {
            // A renewal in progress describes the replaced factor.
            self.renewal = None;
            self.install_conditioner(fresh);
        }
    }
}

/// Bring the P_UU factor of `screener` up to date with the cycles determined from the
/// estimate's predictions (`backlog`, in their order): appended when they are few against
/// the cycles it holds, otherwise a factor of all of them in a fill-reducing order, returned
/// (appending many in chronological order fills L, which is why L is renewed: module docs).
/// The appends stop once their solves have visited more than `bound` entries of L (a step
/// passes [`APPEND_BOUND_MARGIN`] times what a rebuild of all of them is expected to cost),
/// and the factor is rebuilt instead (once: a rebuild that fails, there or before the appends,
/// leaves the rest to be appended). Where P_γ couples the cycles densely a solve reaches nearly the whole factor, and appending one
/// cycle to one of 13 400 visited about 0.57 M entries on a 100 000-pose world with 500 false
/// loop closures, against 34.7 M for rebuilding all 14 760 (`benches/MEASUREMENTS.md`,
/// thirty-sixth session) — a backlog just under the eighth would have cost a step seconds.
/// A determination cannot fail here (its conditional variance holds its chord's σ²/4π²); if
/// one did, the cycles after it would be appended as P_UU decides them.
pub(super) fn with_backlog(
    screener: &mut Screener,
    model: &GammaModel,
    backlog: &[(u32, i64, f64)],
    bound: f64,
) -> Option<Conditioner> {
    if backlog.is_empty() {
        return None;
    }
    let rebuilt = |screener: &Screener, rest: &[(u32, i64, f64)]| {
        let mut all = screener.cond.determined();
        all.extend(rest.iter().map(|&(c, v, _)| (c as usize, v)));
        Conditioner::rebuilt(model, &all, 0).ok()
    };
    let mut bound = bound;
    if backlog.len() > screener.cond.len() / BACKLOG_REBUILD_FRACTION {
        match rebuilt(screener, backlog) {
            Some(fresh) => return Some(fresh),
            // (A rebuild that failed is not tried again at the bound.)
            None => bound = f64::INFINITY,
        }
    }
    let start = screener.cond.work();
    for (k, &(c, v, _)) in backlog.iter().enumerate() {
        if screener.cond.work().saturating_sub(start) as f64 > bound {
            if let Some(fresh) = rebuilt(screener, &backlog[k..]) {
                return Some(fresh);
            }
            // (A rebuild that failed is not tried again at every later append.)
            bound = f64::INFINITY;
        }
        let _ = screener.determine(model, c as usize, v);
    }
    None
}

/// A step's appends of the backlog stop once they have cost this many times what a rebuild is
/// expected to ([`OnlineEstimator::expected_rebuild_work`]): the expectation runs low where
/// the factor is dense (5.77 M expected against 34.66 M counted on the 100 000-pose world
/// with 500 false loop closures, `--seed 2`), and below it appending is left as it was.
const APPEND_BOUND_MARGIN: f64 = 8.0;

/// [`with_backlog`] rebuilds P_UU when the backlog exceeds the factor's rows over this.
const BACKLOG_REBUILD_FRACTION: usize = 8;

#[cfg(test)]
pub(super) mod tests {
    use super::with_backlog;
    use crate::gamma::Conditioner;
    use crate::graph::{Edge, Information};
    use crate::online::{OnlineConfig, OnlineEstimator, Step, StepKind, robot_order};
    use crate::sim::{OutlierConfig, OutlierKind, SimConfig, inject_outliers, simulate};

    /// Edges of a world in robot order, with the declared information divided by `widen`.
    fn stream(edges: &[Edge], widen: f64) -> Vec<Edge> {
        let wide = |e: &Edge| {
            let info = Information(e.information().0.map(|v| v / widen));
            Edge::new(e.from(), e.to(), e.measurement(), info).unwrap()
        };
        robot_order(&edges.iter().map(wide).collect::<Vec<_>>())
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() <= 1e-9 * a.abs().max(b.abs()).max(1.0)
    }

    /// The same step up to the moments' rounding (1e-9): the same decisions, re-screens and
    /// quarantines (module `reorder`'s tests use it too).
    pub(in crate::online) fn same_step(a: &Step, b: &Step) -> bool {
        let kinds = match (&a.kind, &b.kind) {
            (StepKind::Cycle(x), StepKind::Cycle(y)) => {
                (x.cycle, x.candidates, x.decision) == (y.cycle, y.candidates, y.decision)
                    && close(x.mean, y.mean)
                    && close(x.sd, y.sd)
            }
            (x, y) => x == y,
        };
        let rejected = |s: &Step| -> Vec<(usize, &str)> {
            s.quarantined.iter().map(|r| (r.edge, r.test)).collect()
        };
        kinds
            && (a.edge, &a.rescreened, &a.readmitted) == (b.edge, &b.rescreened, &b.readmitted)
            && rejected(a) == rejected(b)
            && (a.quarantined.iter().zip(&b.quarantined))
                .all(|(x, y)| close(x.statistic, y.statistic))
    }

    /// The backlog's appends stop at their bound and the factor is rebuilt from every
    /// determined cycle instead (module docs): with no bound every cycle is appended; with a
    /// bound of nothing the first is appended and the rest go to a rebuild holding all of
    /// them; both hold the same cycles (χ² to 1e-9). Fails if the bound is not checked, or
    /// if the rebuild leaves a cycle of the backlog out.
    #[test]
    fn appending_the_backlog_stops_at_its_bound() {
        let world = simulate(&SimConfig::new(1500, 33)).unwrap();
        let config = OnlineConfig {
            estimate_every_step: false,
            ..OnlineConfig::default()
        };
        let mut est = OnlineEstimator::new(config).unwrap();
        for edge in stream(world.graph.edges(), 1.0) {
            est.add_edge(edge).unwrap();
        }
        let all = est.screener.cond.determined();
        // A backlog of a tenth: under the eighth from which it is rebuilt at once.
        let split = all.len() * 9 / 10;
        assert!(split > 200 && (all.len() - split) * 8 < split);
        let backlog: Vec<(u32, i64, f64)> = (all[split..].iter())
            .map(|&(c, v)| (c as u32, v, 0.0))
            .collect();
        let screener = || {
            let mut s = est.screener.without_conditioner();
            s.cond = Conditioner::rebuilt(&est.model, &all[..split], 0).unwrap();
            s
        };
        let mut appended = screener();
        assert!(with_backlog(&mut appended, &est.model, &backlog, f64::INFINITY).is_none());
        assert_eq!(appended.cond.len(), all.len());
        let mut bounded = screener();
        let fresh = with_backlog(&mut bounded, &est.model, &backlog, 0.0)
            .expect("rebuilt once the first append passed the bound");
        assert_eq!(bounded.cond.len(), split + 1);
        assert_eq!(fresh.len(), all.len());
        let (a, b) = (appended.cond.chi2(), fresh.chi2());
        assert!(close(a, b), "χ² {a} against {b}");
    }

    /// Streams screened by the estimate's prediction decide as those screened by P_UU, step
    /// by step (moments within 1e-9): a clean world, a noisy one whose ambiguous cycles send
    /// the screening back and forth between the two, and worlds with false loop closures
    /// whose evictions replay (declared noise 16× too wide).
    #[test]
    fn screening_by_prediction_decides_as_p_uu() {
        let clean = simulate(&SimConfig::new(800, 31)).unwrap();
        let noisy = simulate(&SimConfig {
            sigma_theta: 0.25,
            ..SimConfig::new(600, 32)
        })
        .unwrap();
        let mut worlds = vec![
            ("clean", stream(clean.graph.edges(), 1.0)),
            ("noisy", stream(noisy.graph.edges(), 1.0)),
        ];
        for (seed, kind) in [(1, OutlierKind::Random), (2, OutlierKind::Clustered)] {
            let world = simulate(&SimConfig::new(1000, 700 + seed)).unwrap();
            let bad = inject_outliers(
                &world.graph,
                &OutlierConfig {
                    count: 40,
                    kind,
                    seed,
                },
            )
            .unwrap();
            worlds.push(("outliers", stream(bad.graph.edges(), 16.0)));
        }
        let mut switched = false;
        for (name, edges) in worlds {
            let run = |estimate_every_step: bool| {
                let mut est = OnlineEstimator::new(OnlineConfig {
                    estimate_every_step,
                    ..OnlineConfig::default()
                })
                .unwrap();
                let mut steps = Vec::new();
                for &edge in &edges {
                    steps.push(est.add_edge(edge).unwrap());
                    // What a robot reads: the newest pose (the route must not depend on it).
                    est.newest().unwrap();
                }
                (est, steps)
            };
            let ((mut a, sa), (mut b, sb)) = (run(true), run(false));
            assert!(a.predicted > 0 && b.predicted == 0, "{name}");
            switched |= a.predicted < a.counters().cycles;
            for (x, y) in sa.iter().zip(&sb) {
                assert!(same_step(x, y), "{name}: {x:?} against {y:?}");
            }
            assert_eq!(a.gamma(), b.gamma(), "{name}");
            // P_UU's renewals differ (it grows less), and the waits depend on the threads.
            let counts = |e: &OnlineEstimator| {
                let c = e.counters();
                let screening = (c.cycles, c.determined, c.ambiguous, c.inconsistent);
                (c.steps, c.quarantined, c.readmitted, c.rescreens, screening)
            };
            assert_eq!(counts(&a), counts(&b), "{name}");
            let (ta, tb) = (
                a.orientations().unwrap().to_vec(),
                b.orientations().unwrap().to_vec(),
            );
            assert!(ta.iter().zip(&tb).all(|(x, y)| close(*x, *y)), "{name}");
            let (ha, hb) = (a.hypotheses().unwrap(), b.hypotheses().unwrap());
            assert_eq!(ha.len(), hb.len(), "{name}");
            assert!(
                (ha.iter().zip(&hb)).all(|(x, y)| x.values == y.values && close(x.chi2, y.chi2))
            );
        }
        assert!(
            switched,
            "no stream screened by P_UU after a prediction: the switch is untested"
        );
    }
}
