//! The batch pipeline of the paper (method [§2](crate::method#2-cycles)–[§6](crate::method#6-which-cycle-basis), [§8](crate::method#8-success-probability)): basis → γ model → first screening
//! (iterated) → second screening (iterated) → hypotheses with χ², p-value and the
//! success-rate bound; then, per hypothesis, poses ([`solve`]): wraps → orientations θ* →
//! least-squares positions → SE(2) refinement. It is the reference the online estimator is checked against, and it is
//! only a driver: every formula lives in [`crate::cycles`], [`crate::gamma`],
//! [`crate::screening`], [`crate::wraps`] and [`crate::estimate`].
//!
//! **Robust poses** against false loop closures (the DCS kernel, the quarantine stream, the
//! leave-out test): [`robust`], re-exported here.

use std::time::Instant;

use crate::cycles::{BasisKind, CycleBasis, McbError};
use crate::estimate::{EstimateError, OrientationEstimator};
use crate::gamma::{GammaModel, SingularError};
use crate::graph::{GraphError, NodeId, Pose2, PoseGraph};
use crate::refine::{RefineConfig, Refined};
use crate::screening::{ConfigError, Hypothesis, Screened, Screener, ScreeningConfig};
use crate::wraps::{WrapError, WrapSolver};

pub use crate::screening::{InconsistentCycle, Iteration, SecondOutcome};

mod leave_out;
pub mod robust;

pub(crate) use leave_out::{GROUP_SPAN, place, place_of, same_place};
pub use robust::{RobustConfig, quarantined, solve_robust};

/// What to run. Defaults: the incremental basis and [`ScreeningConfig::default`]
/// (deserialised fields left out take these).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct BatchConfig {
    /// Cycle basis.
    pub basis: BasisKind,
    /// Screening settings.
    pub screening: ScreeningConfig,
}

impl Default for BatchConfig {
    fn default() -> Self {
        Self {
            basis: BasisKind::Incremental,
            screening: ScreeningConfig::default(),
        }
    }
}

/// Everything the pipeline produced.
#[derive(Clone, Debug)]
pub struct BatchResult {
    /// Number of edges of the graph.
    pub edges: usize,
    /// The basis used.
    pub basis: CycleBasis,
    /// The γ model of that basis.
    pub model: GammaModel,
    /// The screening result.
    pub screened: Screened,
    /// `C k = γ` for this basis, analysed once (integrality included).
    pub solver: WrapSolver,
    /// Set when the requested basis could not be used and the incremental basis replaced it
    /// (a minimum basis that is not integral, method [§5](crate::method#5-wraps-and-orientations)).
    pub fallback: Option<BasisFallback>,
    /// Time to build the basis (including a fallback and the integrality check).
    pub basis_seconds: f64,
    /// Time for the γ model and both screenings.
    pub screening_seconds: f64,
}

impl std::ops::Deref for BatchResult {
    type Target = Screened;
    fn deref(&self) -> &Screened {
        &self.screened
    }
}

impl BatchResult {
    /// The wraps k of every edge for a hypothesis (`k = [0; C_L⁻¹ γ]`).
    pub fn wraps(&self, h: &Hypothesis) -> Result<Vec<i64>, WrapError> {
        self.solver
            .wraps(&self.basis.cycles, &self.screened.gamma(h))
    }
}

/// The poses of one hypothesis.
#[derive(Clone, Debug)]
pub struct Solution {
    /// The wraps k of every edge.
    pub wraps: Vec<i64>,
    /// `Σ_e (θ_j − θ_i − δ_e + 2πk_e)² / σ_e²` of θ* (the hypothesis' χ²).
    pub chi2_orientation: f64,
    /// θ* with the least-squares positions.
    pub linear: Vec<Pose2>,
    /// SE(2) cost `Σ eᵀΩe` of [`linear`](Self::linear).
    pub cost_linear: f64,
    /// The refinement from [`linear`](Self::linear) (its cost after each accepted step), on
    /// the edges not [`rejected`](Self::rejected).
    pub refined: Refined,
    /// Loop closures rejected by the robust kernel ([`solve_robust`]; empty for [`solve`]).
    pub rejected: Vec<RejectedEdge>,
    /// The noise scales of the online quarantine that [`solve_robust`] runs first (None for
    /// [`solve`] or with the quarantine off).
    pub noise_scales: Option<crate::online::NoiseScales>,
    /// The noise scale the loop closures' leave-out drops showed in the last pass
    /// (`Δ_(k) / χ²_1⁻¹(0.99)`, [`robust`] docs); the leave-out test used the smaller of it and
    /// the larger of [`noise_scales`](Self::noise_scales). None when the test did not run or
    /// had fewer than 854 loop closures.
    pub drop_scale: Option<f64>,
    /// Wall time of this solution.
    pub seconds: f64,
}

/// A loop closure the robust kernel rejected.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct RejectedEdge {
    /// 0-based index in the input order (the graph's edge order; online, the order of arrival).
    pub edge: usize,
    /// Source node id.
    pub from: NodeId,
    /// Target node id.
    pub to: NodeId,
    /// The test: `"se2_chi2"` (the edge's `e_eᵀ Ω_e e_e` at the robust solution, 3 dof),
    /// `"leave_out"` (statistic: the cost drop of leaving the edge's group out, threshold
    /// `s · χ²_{3|G|}⁻¹`, [`robust`] docs), or
    /// the online tests of its cycle at arrival, `"cycle_angle"` (statistic: the distance of
    /// the conditional mean of γ to the nearest integer in σ; threshold q) and
    /// `"cycle_translation"` (statistic: χ²₂ of the translation closure, the larger of its two
    /// ends, or the first end's alone when that already fails every test: a lower bound,
    /// [`crate::closure::translation_closure_unless_first_fails`]).
    pub test: &'static str,
    /// The statistic χ²_e.
    pub statistic: f64,
    /// The threshold Φ it exceeded.
    pub threshold: f64,
}

impl RejectedEdge {
    /// Edge `e` of `graph` rejected by `test`.
    fn of(graph: &PoseGraph, e: usize, test: &'static str, statistic: f64, threshold: f64) -> Self {
        let edge = &graph.edges()[e];
        Self {
            edge: e,
            from: edge.from(),
            to: edge.to(),
            test,
            statistic,
            threshold,
        }
    }
}

/// Why poses could not be computed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SolveError {
    /// γ → k failed.
    #[error(transparent)]
    Wraps(#[from] WrapError),
    /// A linear system failed.
    #[error(transparent)]
    Estimate(#[from] EstimateError),
    /// A reweighted edge failed validation (an information matrix scaled out of range).
    #[error(transparent)]
    Graph(#[from] GraphError),
    /// Bad robust settings.
    #[error("invalid robust setting: alpha = {0} must be in (0, 1)")]
    RobustAlpha(f64),
    /// Screening the graph without the rejected edges failed.
    #[error("screening without the rejected loop closures: {0}")]
    Screening(Box<BatchError>),
    /// The quarantine pass (the graph streamed through the online estimator) failed.
    #[error("quarantine pass: {0}")]
    Quarantine(String),
    /// Screening the graph without the rejected edges left no hypothesis.
    #[error("screening without the rejected loop closures left no hypothesis")]
    NoHypothesis,
}

impl From<BatchError> for SolveError {
    fn from(e: BatchError) -> Self {
        SolveError::Screening(Box::new(e))
    }
}

/// Poses for a hypothesis of a screened graph: wraps, θ* (with the graph's factored
/// orientation system `orient`), least-squares positions, and `refine` on the SE(2) cost.
pub fn solve(
    graph: &PoseGraph,
    result: &BatchResult,
    orient: &OrientationEstimator,
    h: &Hypothesis,
    refine: &RefineConfig,
) -> Result<Solution, SolveError> {
    let t = Instant::now();
    let wraps = result.wraps(h)?;
    let theta = orient.orientations(&wraps);
    let chi2_orientation = orient.cost(&theta, &wraps);
    let linear = orient.poses(graph, &theta)?;
    let cost_linear = refine.residual.cost(graph, &linear);
    let refined = crate::refine::refine(graph, &linear, refine)?;
    Ok(Solution {
        wraps,
        chi2_orientation,
        linear,
        cost_linear,
        refined,
        rejected: Vec::new(),
        noise_scales: None,
        drop_scale: None,
        seconds: t.elapsed().as_secs_f64(),
    })
}

/// A basis cycle whose SE(2) translation closure failed its test ([`translation_failures`]).
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct TranslationFailure {
    /// Cycle index in the basis.
    pub cycle: usize,
    /// Its edges (indices in the graph).
    pub edges: Vec<usize>,
    /// `χ²_2` of the closure divided by the noise scale ([`crate::closure`]).
    pub chi2: f64,
    /// The threshold it exceeded ([`crate::closure::threshold`] at `level`).
    pub threshold: f64,
    /// The level of the test.
    pub level: f64,
}

impl std::fmt::Display for TranslationFailure {
    /// `cycle 402 failed its translation closure test at level 2.6e-6: χ² 31.2 > 25.7`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "cycle {} failed its translation closure test at level {:.1e}: χ² {:.1} > {:.1}",
            self.cycle, self.level, self.chi2, self.threshold
        )
    }
}

/// The SE(2) translation closure test of every basis cycle ([`crate::closure`]; statistic
/// divided by the noise scale [`crate::closure::Scale`] of all the cycles), family-wise
/// like the angle tests: each cycle at the per-cycle level of `config`
/// ([`ScreeningConfig::level`]`(ℓ)`: α/(2ℓ) by default), so the ℓ translation tests spend α/2
/// on data that follow the declared noise. Returns the cycles that fail, ascending.
pub fn translation_failures(
    graph: &PoseGraph,
    basis: &CycleBasis,
    config: &ScreeningConfig,
) -> Vec<TranslationFailure> {
    let level = config.level(basis.cycles.len());
    let limit = crate::closure::threshold(level);
    // Each edge's closure noise once (a cycle is closed from both ends, and an edge lies on
    // many cycles).
    let noise: Vec<Option<crate::closure::EdgeNoise>> = graph
        .edges()
        .iter()
        .map(crate::closure::EdgeNoise::of)
        .collect();
    let chi2: Vec<Option<f64>> = basis
        .cycles
        .iter()
        .map(|c| {
            crate::closure::translation_closure_at_both_ends(&c.terms, &|e| noise[e], 1.0)
                .map(|x| x.chi2)
        })
        .collect();
    let mut scale = crate::closure::Scale::default();
    for &x in chi2.iter().flatten() {
        scale.push(x);
    }
    let s = scale.value();
    basis
        .cycles
        .iter()
        .zip(&chi2)
        .enumerate()
        .filter_map(|(cycle, (c, &x))| {
            let tested = x? / s;
            crate::closure::fails(tested, limit).then(|| TranslationFailure {
                cycle,
                edges: c.terms.iter().map(|t| t.edge as usize).collect(),
                chi2: tested,
                threshold: limit,
                level,
            })
        })
        .collect()
}

/// The requested basis was replaced by the incremental basis.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct BasisFallback {
    /// The basis asked for.
    pub requested: BasisKind,
    /// Why it was not used, e.g. `|det C_L| = 3: not integral`.
    pub reason: String,
}

/// A basis with its wrap solver, and why the requested one was replaced, if it was.
pub type IntegralBasis = (CycleBasis, WrapSolver, Option<BasisFallback>);

/// Build the requested basis; a basis that is not integral (or not a basis) is replaced by
/// the incremental basis, which always is, so no γ can give fractional wraps.
pub fn integral_basis(graph: &PoseGraph, kind: BasisKind) -> Result<IntegralBasis, WrapError> {
    usable_or_incremental(graph, kind, CycleBasis::try_build(graph, kind, None))
}

/// The basis if it was built and is integral, else the incremental basis and why.
fn usable_or_incremental(
    graph: &PoseGraph,
    kind: BasisKind,
    built: Result<CycleBasis, McbError>,
) -> Result<IntegralBasis, WrapError> {
    let reason = match built {
        Err(e) => e.to_string(),
        Ok(basis) => match basis.wrap_solver(graph.edge_count()) {
            Ok(s) if s.is_integral() => return Ok((basis, s, None)),
            Ok(s) => format!("|det C_L| = {}: not integral", s.abs_det()),
            Err(e) => e.to_string(),
        },
    };
    let fallback = BasisFallback {
        requested: kind,
        reason,
    };
    let basis = CycleBasis::incremental(graph);
    let solver = basis.wrap_solver(graph.edge_count())?;
    Ok((basis, solver, Some(fallback)))
}

/// Why the pipeline stopped.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum BatchError {
    /// Bad settings.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// P_γ numerically singular.
    #[error(transparent)]
    Singular(#[from] SingularError),
    /// The basis has no wrap solver (never for the incremental basis of a valid graph).
    #[error(transparent)]
    Wraps(#[from] WrapError),
}

/// Screen a γ model to the end from the screener's current state: the first screening to its
/// fixed point (from scratch when nothing is determined yet), then the second; cycle i is
/// tested at half-width factor `q(i)`. Shared by [`screen`] and the online estimator's `finish`.
pub(crate) fn run_screening(
    model: &GammaModel,
    mut screener: Screener,
    cfg: &ScreeningConfig,
    q: &dyn Fn(usize) -> f64,
    cycles: &CycleBasis,
) -> Result<Screened, SingularError> {
    let qs: Vec<f64> = (0..model.len()).map(q).collect();
    let q = |i: usize| qs[i];
    let edges = |i: usize| {
        cycles.cycles[i]
            .terms
            .iter()
            .map(|t| t.edge as usize)
            .collect()
    };
    screener.grow(model.len());
    let mut first = Vec::new();
    screener.first_screening(model, &q, &edges, &mut first)?;
    screener.finish(model, cfg, &q, &edges, first)
}

/// Run the whole pipeline on a graph. Family-wise (the default), every cycle is tested at
/// α/(2ℓ) (Bonferroni, [`ScreeningConfig::level`]).
pub fn screen(graph: &PoseGraph, config: &BatchConfig) -> Result<BatchResult, BatchError> {
    screen_with(graph, config, false)
}

/// The pipeline with the online estimator's levels: cycle t (in basis order, which for the
/// incremental basis is the order the cycles close in) at
/// [`ScreeningConfig::online_level`]`(t)`. A batch run and a finished online run on the same
/// edges then test every cycle at the same level (used to compare the two).
pub fn screen_spending(graph: &PoseGraph, config: &BatchConfig) -> Result<BatchResult, BatchError> {
    screen_with(graph, config, true)
}

fn screen_with(
    graph: &PoseGraph,
    config: &BatchConfig,
    spending: bool,
) -> Result<BatchResult, BatchError> {
    config.screening.validate()?;
    let t0 = Instant::now();
    let (basis, solver, fallback) = integral_basis(graph, config.basis)?;
    let basis_seconds = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let sigma2: Vec<f64> = graph.edges().iter().map(|e| e.sigma2()).collect();
    let delta: Vec<f64> = graph.edges().iter().map(|e| e.delta()).collect();
    let model = GammaModel::from_cycles(&basis.cycles, &sigma2, &delta);
    let s = config.screening;
    let bonferroni = s.quantile(model.len());
    let q = |t: usize| {
        if spending {
            s.online_quantile(t)
        } else {
            bonferroni
        }
    };
    let screened = run_screening(&model, Screener::new(), &s, &q, &basis)?;
    Ok(BatchResult {
        edges: graph.edge_count(),
        basis,
        model,
        screened,
        solver,
        fallback,
        basis_seconds,
        screening_seconds: t1.elapsed().as_secs_f64(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::cycles::{Cycle, SignedEdge};
    use crate::graph::{Edge, NodePolicy, Pose2};

    #[test]
    fn a_non_integral_basis_falls_back_to_the_incremental_one() {
        // K4 (edges 01 02 03 12 13 23) and its three Hamiltonian cycles: |det C_L| = 2.
        let mut g = PoseGraph::new();
        for (a, b) in [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)] {
            let e = Edge::with_sigmas(a, b, Pose2::default(), 1.0, 0.1).unwrap();
            g.add_edge(e, NodePolicy::CreateUnknown).unwrap();
        }
        let s = |e: usize, along: bool| SignedEdge::new(e, along);
        let cycles = [
            [s(0, true), s(3, true), s(5, true), s(2, false)],
            [s(0, true), s(4, true), s(5, false), s(1, false)],
            [s(1, true), s(3, false), s(4, true), s(2, false)],
        ]
        .map(|t| Cycle {
            terms: t.into_iter().collect(),
        });
        let hand = CycleBasis {
            kind: BasisKind::Mcb,
            cycles: cycles.to_vec(),
        };
        let (basis, _, fallback) = usable_or_incremental(&g, BasisKind::Mcb, Ok(hand)).unwrap();
        assert_eq!(basis.kind, BasisKind::Incremental);
        let f = fallback.unwrap();
        assert_eq!(f.requested, BasisKind::Mcb);
        assert!(f.reason.contains("|det C_L| = 2"), "{}", f.reason);
        // The real minimum basis of K4 (three triangles) is integral and kept.
        let (basis, _, fallback) = integral_basis(&g, BasisKind::Mcb).unwrap();
        assert_eq!((basis.kind, fallback), (BasisKind::Mcb, None));
        let (_, _, fallback) =
            usable_or_incremental(&g, BasisKind::McbApprox, Err(McbError::Deadline)).unwrap();
        assert!(fallback.unwrap().reason.contains("budget"));
    }
}
