//! Quarantine and re-admission (method §11): a loop closure whose cycle fails its angle or
//! translation test when it arrives is held out of the graph, the basis, the conditioning and
//! the estimate, and re-tested through the path a new loop closure would take once the number
//! of cycles ℓ has grown:
//!
//! ```text
//! ℓ_retest = max(2ℓ, ℓ + 32),   or max(8ℓ, ℓ + 32) when it failed by far (χ² > 8 × threshold),
//! ```
//!
//! so each held edge costs O(log ℓ) re-tests, each a search of the graph. At most
//! [`RETESTS_PER_STEP`] are re-tested in one step, the earliest due first: the others wait for
//! the next steps, so that a step never does more than its own edge's work and one re-test's.
//! A re-test is at the
//! per-cycle level α (stricter than the family-wise α_t of arrivals), or at its arrival's level
//! when the failed test's noise scale has since risen above 1 (module docs of
//! [`crate::online`]: re-admission).

use super::{ANGLE_TEST, OnlineEstimator, Rescreen, Step, StepKind};
use crate::batch::RejectedEdge;
use crate::graph::Edge;

/// A quarantined loop closure.
#[derive(Clone, Copy, Debug)]
pub(super) struct Held {
    pub(super) edge: Edge,
    pub(super) rejected: RejectedEdge,
    /// The cycle count of its next re-test.
    pub(super) due: usize,
    /// Whether it was evicted (accepted, then quarantined): a replay keeps it in quarantine
    /// until its re-test (re-tested at its arrival, it would pass as it first did, and be
    /// accepted again).
    pub(super) evicted: bool,
    /// The level of the test it failed at its arrival (the per-cycle α for an evicted edge).
    pub(super) level: f64,
    /// The noise scale of that test when it failed ([`OnlineEstimator::test_scale`]).
    pub(super) scale: f64,
    /// Whether it failed its arrival's test by far ([`failed_by_far`]): its re-tests are 8×
    /// the cycles apart, not 2×.
    pub(super) far: bool,
}

/// The cycle count at which a loop closure quarantined when `cycles` had closed is re-tested:
/// twice as many, and at least 32 more; eight times as many when it failed by far (its χ²
/// above [`FAR`] times the threshold: a random false edge, whose re-tests would cost one
/// search of the graph each for nothing; a genuine edge that failed by far because its path
/// ran through an accepted false edge is replayed when the examination evicts that edge).
pub(super) fn retest_after(cycles: usize, far: bool) -> usize {
    let factor = if far { 8 } else { 2 };
    cycles.saturating_mul(factor).max(cycles + 32)
}

/// Whether a rejection's χ² (the angle residual squared) was above [`FAR`] times its
/// threshold.
pub(super) fn failed_by_far(rejected: &RejectedEdge) -> bool {
    let ratio = rejected.statistic / rejected.threshold;
    if rejected.test == ANGLE_TEST {
        ratio * ratio > FAR
    } else {
        translation_by_far(rejected.statistic, rejected.threshold)
    }
}

/// Whether a translation statistic `tested` fails its `threshold` by far ([`failed_by_far`]).
pub(super) fn translation_by_far(tested: f64, threshold: f64) -> bool {
    tested / threshold > FAR
}

/// A test failed by far: its χ² (the angle residual squared) above this multiple of the
/// threshold ([`retest_after`]). The clean w20000.txt's long loops (5 000–10 000 poses) fail
/// at 4.0–5.7× when they arrive on paths longer than the graph later offers, and pass on the
/// final graph: at 4 they waited for 8× the cycles, which that file never reaches, and 164 of
/// them ended its stream held; at 8 all come back. Of the false edges held at the end of 24
/// streams of M3500 with 1000 false edges, 91 % had failed above 8× (their costly re-tests
/// stay rare), and those streams' decisions did not change.
const FAR: f64 = 8.0;

/// Quarantined loop closures re-tested in one step, at most ([`OnlineEstimator::retest_due`]):
/// the earliest due first, the rest at the steps that follow. A re-test is a loop closure's
/// step — a search, the screening, the estimate's rotations — and every re-admission closes a
/// cycle, which brings the next held edge's date: on the clean w20000.txt, 1 040 loop
/// closures quarantined while its translation scale was rising came due in one step (arrival
/// 16 135), which re-admitted 1 039 of them and took 0.2 s (`so2lin stream w20000.txt
/// --json`: robot order, the newest pose read after every step). One a step: the same
/// decisions to the edge (1 219 re-admitted in all, none held at the end; every file of the
/// benchmark folder and twelve of M3500 + 1 000 false loop closures likewise), that stream's
/// worst step 5.5–5.9 ms instead of 0.2 s (its warm-up replay, or a long loop's translation
/// closure), its p99 up by an eighth to a half (a loop closure's work more in each of a thousand
/// steps: what a stall costs when it is spread). A held edge is re-tested O(log ℓ) times, at
/// dates that at least double, and at most one edge is held per arrival, so the backlog a
/// burst leaves drains at one a step unless most arrivals are held and fail again and again;
/// an edge whose date has come but whose re-test waits is still held (listed by
/// [`OnlineEstimator::rejected`]), at the end of a stream too.
pub(super) const RETESTS_PER_STEP: usize = 1;

impl OnlineEstimator {
    /// `edge` quarantined after failing `rejected` (its test at `level`), re-tested at cycle
    /// count `due`, with the failed test's current noise scale.
    pub(super) fn held(
        &self,
        edge: Edge,
        rejected: RejectedEdge,
        due: usize,
        evicted: bool,
        level: f64,
    ) -> Held {
        Held {
            edge,
            rejected,
            due,
            evicted,
            level,
            scale: self.test_scale(rejected.test),
            far: failed_by_far(&rejected),
        }
    }

    /// The noise scale a quarantine test divides its statistic by: the angle scale for
    /// [`ANGLE_TEST`], the translation scale for [`TRANSLATION_TEST`](super::TRANSLATION_TEST).
    pub(super) fn test_scale(&self, test: &str) -> f64 {
        if test == ANGLE_TEST {
            self.angle_scale()
        } else {
            self.translation_scale()
        }
    }

    /// Quarantine a loop closure that failed its test at arrival; it is re-tested when the
    /// cycles have doubled ([`Self::retest_due`]).
    pub(super) fn hold(&mut self, edge: Edge, rejected: RejectedEdge, level: f64) -> Step {
        let due = retest_after(self.counters.cycles, failed_by_far(&rejected));
        self.hold_until(self.held(edge, rejected, due, false, level))
    }

    /// Quarantine `held` ([`Self::hold`], or a replay keeping an evicted edge).
    pub(super) fn hold_until(&mut self, held: Held) -> Step {
        let rejected = held.rejected;
        self.keep_held(held);
        Step {
            edge: rejected.edge,
            kind: StepKind::Quarantined,
            rescreened: Vec::new(),
            quarantined: vec![rejected],
            readmitted: Vec::new(),
        }
    }

    /// Keep `held` in quarantine until its re-test ([`Held::due`]), indexed by that date.
    pub(super) fn keep_held(&mut self, held: Held) {
        let input = held.rejected.edge;
        self.due.insert((held.due, input));
        self.held.insert(input, held);
    }

    /// Re-test the quarantined loop closures whose time has come (module docs: re-admission),
    /// through the path a new loop closure takes, at the level of [`Held::level`], at most
    /// [`RETESTS_PER_STEP`] of them (the earliest due first; the rest stay due). Re-admitted
    /// edges and the cycles their determination re-screened are added to `step`.
    pub(super) fn retest_due(&mut self, step: &mut Step) {
        let mut retests = 0;
        while let Some(&(due, input)) = self.due.first() {
            if due > self.counters.cycles || retests == RETESTS_PER_STEP {
                break;
            }
            self.due.pop_first();
            let Some(held) = self.held.remove(&input) else {
                continue;
            };
            let Some((a, b)) = self.ends(&held.edge) else {
                continue;
            };
            retests += 1;
            // At the per-cycle level α; at the arrival's level when the data have shown the
            // declared noise too tight since (the failed test's scale risen above 1 and above
            // what it was): the failure may be the noise model's, not the edge's (module docs).
            let scale = self.test_scale(held.rejected.test);
            let level = if scale > held.scale.max(1.0) {
                held.level
            } else {
                self.config.screening.alpha
            };
            // A re-test that fails internally leaves the edge in quarantine: this step's own
            // edge is already in, and nothing of the held edge's is lost.
            let retest = self
                .add_chord(input, held.edge, a, b, level)
                .unwrap_or(Err(held.rejected));
            match retest {
                Ok(s) => {
                    self.counters.readmitted += 1;
                    step.readmitted.push(input);
                    for r in s.rescreened {
                        match step.rescreened.iter_mut().find(|x| x.cycle == r.cycle) {
                            Some(x) => {
                                *x = Rescreen {
                                    before: x.before,
                                    ..r
                                }
                            }
                            None => step.rescreened.push(r),
                        }
                    }
                    step.rescreened.sort_by_key(|x| x.cycle);
                }
                Err(rejected) => {
                    // Re-tested after as many cycles as its arrival's failure set: a failure
                    // by far at the strict per-cycle level is not one at its own level.
                    let due = retest_after(self.counters.cycles, held.far);
                    // An evicted edge that fails its re-test stays an evicted edge.
                    self.keep_held(Held {
                        rejected,
                        due,
                        scale: self.test_scale(rejected.test),
                        ..held
                    });
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{Held, RETESTS_PER_STEP};
    use crate::batch::RejectedEdge;
    use crate::estimate::OrientationEstimator;
    use crate::online::{ANGLE_TEST, OnlineConfig, OnlineEstimator, robot_order_indices};
    use crate::sim::{SimConfig, simulate};

    /// Genuine loop closures of a simulated world put in quarantine as they arrive, all due
    /// for their re-test at the same cycle count: they come back one per step (the first
    /// step at their date re-admits one, not all), every one of them by the end, and the
    /// orientations equal the batch estimate of the accepted graph after every step. Fails
    /// if a step re-tests more than [`RETESTS_PER_STEP`] (the old loop re-admitted all six at
    /// once).
    #[test]
    fn due_retests_come_one_per_step() {
        const HELD: usize = 6;
        let world = simulate(&SimConfig::new(400, 5)).unwrap();
        let edges = world.graph.edges();
        let order = robot_order_indices(edges);
        let mut est = OnlineEstimator::new(OnlineConfig::default()).unwrap();
        let (mut held, mut date) = (Vec::new(), None);
        let mut per_step = Vec::new();
        for &i in &order {
            let edge = edges[i];
            let chord = matches!(est.ends(&edge), Some((a, b)) if est.basis.connected(a, b));
            if chord && est.counters.cycles >= 20 && held.len() < HELD {
                // Held as a failed arrival would be, due a few cycles on (the same date for all).
                let due = *date.get_or_insert(est.counters.cycles + 5);
                let rejected = RejectedEdge {
                    edge: est.arrivals,
                    from: edge.from(),
                    to: edge.to(),
                    test: ANGLE_TEST,
                    statistic: 1.0,
                    threshold: 0.5,
                };
                held.push(est.arrivals);
                let level = est.config.screening.alpha;
                let h: Held = est.held(edge, rejected, due, false, level);
                est.hold_until(h);
                est.arrivals += 1;
                est.refresh_counters();
                continue;
            }
            let step = est.add_edge(edge).unwrap();
            per_step.push(step.readmitted.len());
            let want = OrientationEstimator::new(est.graph())
                .unwrap()
                .orientations(&est.wraps().unwrap());
            for (a, b) in est.orientations().unwrap().iter().zip(&want) {
                assert!((a - b).abs() < 1e-9, "{a} vs {b}");
            }
        }
        assert_eq!(held.len(), HELD, "too few loop closures in the world");
        // (step, re-admissions) of the steps that re-admitted any.
        let back: Vec<(usize, usize)> = (per_step.iter().enumerate())
            .filter(|&(_, &n)| n > 0)
            .map(|(i, &n)| (i, n))
            .collect();
        assert!(back.iter().all(|&(_, n)| n <= RETESTS_PER_STEP), "{back:?}");
        assert_eq!(back.len(), HELD, "{back:?}");
        assert!(back.windows(2).all(|w| w[1].0 == w[0].0 + 1), "{back:?}");
        assert_eq!(est.counters().readmitted, HELD);
        assert!(est.rejected().is_empty(), "{:?}", est.rejected());
    }
}
