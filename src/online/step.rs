//! What a step of the online estimator reports: the kind of edge (tree edge, cycle, or a loop
//! closure put in quarantine), for a cycle its conditional moments and the decision of its
//! screening (one candidate integer: determined; several: ambiguous; none: inconsistent), the
//! ambiguous cycles it re-screened, the loop closures it quarantined and re-admitted; the
//! counters of a run; and the noise scales the quarantine estimated (module
//! [`crate::closure`]).

use serde::Serialize;

use crate::batch::RejectedEdge;
use crate::screening::Interval;

/// What a step decided about a cycle.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Decision {
    /// One candidate: the cycle's integer is fixed.
    Determined,
    /// Several candidates.
    Ambiguous,
    /// The confidence interval held no integer: kept ambiguous with the two nearest.
    Inconsistent,
}

impl Decision {
    pub(super) fn of(iv: Interval, determined: bool) -> Self {
        if determined {
            Decision::Determined
        } else if iv.inconsistent {
            Decision::Inconsistent
        } else {
            Decision::Ambiguous
        }
    }
}

/// The screening of the new cycle closed by a step.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct CycleStep {
    /// Cycle id (0-based, in order of closing).
    pub cycle: usize,
    /// Conditional mean of γ given the determined cycles.
    pub mean: f64,
    /// Conditional standard deviation.
    pub sd: f64,
    /// Candidate integers `lo..=hi`.
    pub candidates: Interval,
    /// The decision.
    pub decision: Decision,
}

/// An earlier ambiguous cycle re-screened because a determination shared information with it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Rescreen {
    /// Cycle id.
    pub cycle: usize,
    /// Candidates before the step.
    pub before: Interval,
    /// Candidates after it.
    pub after: Interval,
    /// Decision after it.
    pub decision: Decision,
    /// Whether the candidates or decision changed.
    pub changed: bool,
}

/// What one edge did.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum StepKind {
    /// A tree edge: reached a new node, or joined two components.
    Tree {
        /// The edge created a node.
        new_node: bool,
        /// The edge joined two components.
        joined_components: bool,
    },
    /// A chord: closed a new cycle.
    Cycle(CycleStep),
    /// A loop closure whose cycle failed its test: quarantined (see [`Step::quarantined`]),
    /// not added to the graph.
    Quarantined,
}

/// The outcome of [`OnlineEstimator::add_edge`](super::OnlineEstimator::add_edge).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Step {
    /// Index of the edge (0-based, in order of arrival).
    pub edge: usize,
    /// Tree edge or new cycle.
    pub kind: StepKind,
    /// Earlier cycles re-screened by this step, ascending.
    pub rescreened: Vec<Rescreen>,
    /// The edges quarantined by this step: the arriving loop closure, with its test; after an
    /// eviction, the evicted edges and any other the rebuild quarantined.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub quarantined: Vec<RejectedEdge>,
    /// Input indices of quarantined edges re-admitted at this step (by a re-test, or by the
    /// rebuild after an eviction), ascending.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub readmitted: Vec<usize>,
}

/// What [`OnlineEstimator::maintain`](super::OnlineEstimator::maintain) did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Maintenance {
    /// The estimate's factor was renewed.
    pub renewed: bool,
    /// Every position row was re-linearised at the current headings (with a renewal, or alone).
    pub relinearised: bool,
    /// The factor's variables (nodes) after it, when it did either (0 otherwise).
    pub variables: usize,
    /// The factor's nonzeros off the diagonal after it, when it did either (0 otherwise).
    pub nonzeros: usize,
}

/// Counters of a run.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Counters {
    /// Edges accepted (added to the graph).
    pub steps: usize,
    /// Loop closures in quarantine now.
    pub quarantined: usize,
    /// Quarantined loop closures re-admitted so far.
    pub readmitted: usize,
    /// Tree edges among them.
    pub tree_edges: usize,
    /// Cycles closed.
    pub cycles: usize,
    /// Cycles determined.
    pub determined: usize,
    /// Cycles ambiguous now.
    pub ambiguous: usize,
    /// Cycles found inconsistent so far.
    pub inconsistent: usize,
    /// Re-screens of ambiguous cycles.
    pub rescreens: usize,
    /// Times the factor of P_UU was rebuilt in a fill-reducing order.
    pub reorders: usize,
    /// Times the orientation factor's order was renewed (built beside the live factor).
    pub estimate_renewals: usize,
    /// Steps that had to wait for a renewal's builder thread (0 when it keeps up).
    pub renewal_waits: usize,
    /// Steps that swapped in an eviction's rebuild (module `online::rebuild`) and found its
    /// builder still replaying, so waited for it (0 when the builder keeps up: when the edges
    /// come slowly enough for the replays' length).
    pub rebuild_waits: usize,
    /// Times every position row was re-linearised because the headings had moved by more
    /// than the bound on the fast answers' heading lag (1 rad; module `online::estimate`)
    /// since the rows were (counted at the step that rewrites the rows, at headings solved
    /// over the steps before). Like `estimate_renewals`, it counts the
    /// estimate's work applied so far, which the next read (or loop closure, while the
    /// estimate is read every step) brings up to date. The live steps' only: an eviction's
    /// rebuild, swapped in, goes on from the count of the estimator it replaces (its builder's
    /// own are not counted: none in the replay, all rows once at its end, and those of the
    /// arrivals it takes until the swap).
    pub estimate_relinearisations: usize,
    /// Times [`OnlineEstimator::maintain`](super::OnlineEstimator::maintain) renewed the
    /// estimate's factor (on the caller's thread, between steps).
    pub maintenance_renewals: usize,
    /// Times the estimator was rebuilt by a replay of the stream: evictions, and the one
    /// re-test from the start of a stream that quarantined a loop closure (module
    /// `online::checkpoint`).
    pub rebuilds: usize,
    /// Those that replayed from a checkpoint instead of from the first arrival.
    pub rebuilds_from_checkpoint: usize,
    /// Arrivals the rebuilds replayed, in all.
    pub replayed_arrivals: usize,
}

/// The noise scales the quarantine uses
/// ([`OnlineEstimator::noise_scales`](super::OnlineEstimator::noise_scales)), estimated from
/// the accepted cycles ([`closure::Scale`](crate::closure::Scale)). They multiply the declared
/// variances in the quarantine's tests only; the screening that determines γ keeps the
/// declared noise.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct NoiseScales {
    /// s_θ: the angle variances' factor (1 before 50 samples).
    pub angle: f64,
    /// Cycle tests s_θ was estimated from: the angle residuals of cycles with a sharp angle
    /// (conditional sd < 0.1) that did not fail by far, at arrival and at re-tests.
    pub angle_samples: usize,
    /// s: the translation closures' factor (1 before 50 samples).
    pub translation: f64,
    /// Translation closures s was estimated from (those that did not fail by far).
    pub translation_samples: usize,
}

impl NoiseScales {
    /// The larger of the two scales: the noise `solve`'s SE(2) tests assume, so that neither
    /// component is tested tighter than its own.
    pub fn larger(&self) -> f64 {
        self.angle.max(self.translation)
    }
}
