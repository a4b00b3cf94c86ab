//! The batch pipeline of the paper (method [§2](crate::method#2-cycles)–[§6](crate::method#6-which-cycle-basis), [§8](crate::method#8-success-probability)): basis → γ model → first screening
//! (iterated) → second screening (iterated) → hypotheses with χ², p-value and the
//! success-rate bound; then, per hypothesis, poses ([`solve`]): wraps → orientations θ* →
//! least-squares positions → SE(2) refinement. It is the reference the online estimator is checked against, and it is
//! only a driver: every formula lives in [`crate::cycles`], [`crate::gamma`],
//! [`crate::screening`], [`crate::wraps`] and [`crate::estimate`].
//!
//! **Robust poses** ([`solve_robust`]): false loop closures (method [§11](crate::method#11-false-loop-closures)) are met with the
//! dynamic covariance scaling kernel (DCS, Agarwal et al. 2013) on loop closures (edges whose
//! ids differ by more than 1; odometry keeps its weight): a loop closure with statistic χ²_e
//! has its information scaled by
//!
//! ```text
//! s_e² = min(1, 2Φ / (Φ + χ²_e))²,      Φ = χ²_d⁻¹(1 − α / (2 m_L))
//! ```
//!
//! (m_L loop closures, α [`RobustConfig::alpha`]): Φ is the family-wise (Bonferroni) quantile,
//! so on data that follow the declared noise no genuine loop closure is down-weighted with
//! probability ≥ 1 − α/2. A pass has three stages; the first two are
//! iterated to fixed weights (iteratively reweighted least squares, at most
//! [`RobustConfig::rounds`] rounds):
//! 1. orientations, d = 1, `χ²_e = wrap(θ_j − θ_i − δ_e)² / σ_e²`, the wraps re-read from the
//!    current θ (`k_e = round((δ_e − θ_j + θ_i) / 2π)`), started from the hypothesis' θ*;
//! 2. the SE(2) cost, d = 3, `χ²_e = e_eᵀ Ω_e e_e`: least-squares positions from stage 1,
//!    Levenberg–Marquardt with the stage-1 weights, then reweighted Levenberg–Marquardt;
//! 3. loop closures with `χ²_e > Φ` at the result are **rejected**; if none is, the **leave-out
//!    test**: a false edge the map bent to fit has a small residual but a large cost drop when
//!    it is left out, `Δ_G = min F − min F_{without G}` (χ²_{3|G|} for genuine edges in the
//!    linear-Gaussian model). Δ_G is computed linearised for every loop closure alone and for
//!    every *place group* (loop closures whose two ends are each within 10 node indices of
//!    another's, transitively: one revisit, or a group of false edges sharing a measurement,
//!    which hold each other up and drop little one at a time) by
//!    [`crate::refine::leave_out_drops`] (sparse forward solves, no dense inverse), and
//!    compared with `s · χ²_{3|G|}⁻¹(1 − α/(2N))` (N candidates; s the smaller of two bounds
//!    of the data's noise: the larger of the two noise scales the quarantine estimated, 1
//!    without it, and — with 854 loop closures or more — the scale the drops themselves show,
//!    `Δ_(k) / χ²_1⁻¹(0.99)`, `Δ_(k)` an upper confidence bound of their 99th percentile
//!    (`drop_scale`: it bounds the largest of the three components' variance scales, which
//!    benchmark files declare wrong by different factors; the quarantine's angle scale stops
//!    at 0.25, while M3500's drops show about 0.05); declared noise 4–30× too wide would
//!    otherwise hide every bent edge). Beyond it, the largest drop *per edge left out* first (of
//!    a false edge and the genuine edges it contradicts, leaving out either resolves the
//!    conflict; the fewer edges explain it) is verified by refining without it, and rejected
//!    when the refined drop also exceeds the threshold; repeated, at most 8 groups a pass.
//!
//! Before the first pass ([`RobustConfig::quarantine`], on by default) the graph is streamed
//! through the online estimator in robot order with quarantine on (family-wise at α, angle and
//! SE(2) translation closure of each new cycle, [`crate::online`]): the loop closures it
//! quarantines are rejected (tests `cycle_angle`, `cycle_translation`) and the passes start
//! from the graph without them. Tested cycle by cycle as they close, a false loop closure is
//! met before any later cycle is routed through it; the passes then catch what slipped through.
//!
//! After a pass that rejected edges, the graph without them is screened again and solved from
//! its own θ* by a new pass (at most five passes). When the passes rejected loop closures the
//! stream had accepted, the stream's quarantine was decided with them in the graph: genuine
//! loop closures whose cycles ran through them failed (two false edges can cover for each
//! other online, each one's contradictors failing through the other). So the stream runs again
//! without them, and without the loop closures it had quarantined at the same places (within
//! 10 node indices at both ends: the other members of a group of false edges, held out while
//! one of them stood), and the passes start over from its result (at most twice). Then every rejected loop closure (by the
//! quarantine or by a pass) whose `χ²_e ≤ s·Φ` (d = 3) at the robust poses is restored (a
//! genuine edge quarantined online because its cycle then ran through a false edge fits the
//! solution, and so does one an early pass rejected at poses the later passes corrected);
//! the final poses are the plain refinement on the edges kept: on clean data, the ordinary
//! least-squares optimum.
//!
//! Orientations and positions are linear given the wraps, so every round is re-weighted sparse
//! solves.

use std::time::Instant;

use crate::cycles::{BasisKind, CycleBasis, McbError};
use crate::estimate::{EstimateError, OrientationEstimator};
use crate::gamma::{GammaModel, SingularError};
use crate::graph::{Edge, GraphError, Information, NodeId, NodePolicy, Pose2, PoseGraph};
use crate::refine::{RefineConfig, Refined};
use crate::screening::{
    ConfigError, Hypothesis, Screened, Screener, ScreeningConfig, chi2_quantile,
};
use crate::wraps::{WrapError, WrapSolver};

pub use crate::screening::{InconsistentCycle, Iteration, SecondOutcome};

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
    /// (`Δ_(k) / χ²_1⁻¹(0.99)`, module docs); the leave-out test used the smaller of it and
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
    /// `s · χ²_{3|G|}⁻¹`, module docs), or
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

/// Settings of [`solve_robust`].
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct RobustConfig {
    /// Family-wise level of the loop-closure test (module docs). Default 0.01.
    pub alpha: f64,
    /// Most reweighting rounds per stage. Default 20.
    pub rounds: usize,
    /// Stream the graph through the online estimator first (robot order, quarantine on, at
    /// `alpha`) and leave its quarantined loop closures out (module docs). Default on.
    pub quarantine: bool,
}

impl Default for RobustConfig {
    fn default() -> Self {
        Self {
            alpha: 0.01,
            rounds: 20,
            quarantine: true,
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

/// `min(1, 2Φ/(Φ + χ²))²`, the DCS scale of the information.
fn dcs_weight(chi2: f64, phi: f64) -> f64 {
    let s = (2.0 * phi / (phi + chi2)).min(1.0);
    if s.is_finite() { s * s } else { 0.0 }
}

/// Weights of [`reweighted`] that keep `m` edges but those `left_out`.
fn kept(m: usize, left_out: impl Iterator<Item = usize>) -> Vec<f64> {
    let mut keep = vec![1.0; m];
    for e in left_out {
        keep[e] = 0.0;
    }
    keep
}

/// The graph with each edge's information scaled by its weight; an edge of weight 0 is left
/// out. Nodes keep their order, so node indices are those of `graph`.
fn reweighted(graph: &PoseGraph, weight: &[f64]) -> Result<PoseGraph, GraphError> {
    let mut g = PoseGraph::new();
    for n in graph.nodes() {
        g.add_node(n.id, n.initial)?;
    }
    for (e, &w) in graph.edges().iter().zip(weight) {
        if w == 1.0 {
            g.add_edge(*e, NodePolicy::RequireKnown)?;
        } else if w > 0.0 {
            let info = Information(e.information().0.map(|v| v * w));
            let scaled = Edge::new(e.from(), e.to(), e.measurement(), info)?;
            g.add_edge(scaled, NodePolicy::RequireKnown)?;
        }
    }
    Ok(g)
}

/// Poses for a hypothesis with the DCS kernel on loop closures (module docs): the rejected
/// loop closures are listed, and the refinement is the plain one on the others. When a pass
/// rejects edges, the graph without them is screened again (family-wise at
/// [`RobustConfig::alpha`], incremental basis) and solved from its own θ* by another pass, up to
/// five passes, until a pass rejects nothing; when the passes rejected loop closures the
/// quarantine's stream had accepted, the stream runs again without them (at most
/// twice).
pub fn solve_robust(
    graph: &PoseGraph,
    result: &BatchResult,
    orient: &OrientationEstimator,
    h: &Hypothesis,
    refine: &RefineConfig,
    robust: &RobustConfig,
) -> Result<Solution, SolveError> {
    if !(robust.alpha > 0.0 && robust.alpha < 1.0) {
        return Err(SolveError::RobustAlpha(robust.alpha));
    }
    let t = Instant::now();
    let edges = graph.edges();
    let m_l = edges.iter().filter(|e| !e.is_odometric()).count().max(1) as f64;
    let level = 1.0 - robust.alpha / (2.0 * m_l);
    let phi = (chi2_quantile(1.0, level), chi2_quantile(3.0, level));
    let screening = BatchConfig {
        basis: BasisKind::Incremental,
        screening: ScreeningConfig {
            alpha: robust.alpha,
            ..ScreeningConfig::default()
        },
    };
    let theta_h = orient.orientations(&result.wraps(h)?);
    // The graph without the rejected edges, re-screened, and its own θ*.
    let without = |rejected: &[RejectedEdge], alive: &mut Vec<usize>| {
        let keep = kept(edges.len(), rejected.iter().map(|r| r.edge));
        alive.retain(|&e| keep[e] == 1.0);
        let g = reweighted(graph, &keep)?;
        let r = screen(&g, &screening)?;
        let best = r.hypotheses.first().ok_or(SolveError::NoHypothesis)?;
        let theta0 = OrientationEstimator::new(&g)?.orientations(&r.wraps(best)?);
        Ok::<_, SolveError>((g, theta0))
    };
    // The loop closures the passes rejected (the stream had accepted them).
    let mut excluded: Vec<RejectedEdge> = Vec::new();
    let mut restreams = 0;
    let (mut rejected, noise_scales, first, x, mut g, drop_scale) = loop {
        let mut theta0 = theta_h.clone();
        let mut alive: Vec<usize> = (0..edges.len()).collect();
        let mut g = graph.clone();
        let (mut rejected, noise_scales) = if robust.quarantine {
            let (r, s) = quarantine_run(graph, robust.alpha, &excluded)?;
            (r, Some(s))
        } else {
            (Vec::new(), None)
        };
        rejected.extend_from_slice(&excluded);
        rejected.sort_by_key(|r| r.edge);
        if !rejected.is_empty() {
            (g, theta0) = without(&rejected, &mut alive)?;
        }
        // The leave-out test in the noise the data show (module docs).
        let scale = noise_scales.map_or(1.0, |s| s.larger());
        let mut first = None;
        let mut x;
        let mut pass = 0;
        let mut found = Vec::new();
        let mut shown;
        loop {
            pass += 1;
            let p = robust_pass(&g, &theta0, refine, robust, phi, scale)?;
            x = p.poses;
            shown = p.drop_scale;
            first.get_or_insert((p.chi2_orientation, p.linear));
            if p.rejected.is_empty() || pass == 5 {
                break;
            }
            let new = p.rejected.into_iter().map(|r| RejectedEdge {
                edge: alive[r.edge],
                ..r
            });
            let before = found.len();
            found.extend(new);
            rejected.extend_from_slice(&found[before..]);
            rejected.sort_by_key(|r| r.edge);
            (g, theta0) = without(&rejected, &mut alive)?;
        }
        // Loop closures the stream accepted and the passes rejected: the stream's quarantine
        // decisions were made with them in the graph (genuine loop closures failing through
        // them), so the stream runs again without them (module docs).
        if found.is_empty() || !robust.quarantine || restreams == RESTREAMS {
            break (rejected, noise_scales, first, x, g, shown);
        }
        // With the quarantined loop closures of the same places: the members of a group of
        // false edges that the stream held out while one of them stood.
        let out_already = kept(edges.len(), excluded.iter().chain(&found).map(|r| r.edge));
        let places: Vec<(usize, usize)> = found.iter().map(|r| place(graph, r.edge)).collect();
        let held: Vec<RejectedEdge> = rejected
            .iter()
            .filter(|r| {
                out_already[r.edge] == 1.0
                    && places.iter().any(|&p| same_place(p, place(graph, r.edge)))
            })
            .copied()
            .collect();
        excluded.extend(found);
        excluded.extend(held);
        excluded.sort_by_key(|r| r.edge);
        restreams += 1;
    };
    let scale = noise_scales.map_or(1.0, |s| s.larger());
    // Rejected loop closures whose SE(2) χ²_e at the robust solution is within Φ are
    // restored (module docs): the online tests saw them through cycles that the solution no
    // longer needs, and an earlier pass through poses that later passes corrected.
    let chi2: Vec<f64> = refine.residual.edge_costs(graph, &x).collect();
    let before = rejected.len();
    rejected.retain(|r| chi2[r.edge].is_nan() || chi2[r.edge] > scale * phi.1);
    if rejected.len() < before {
        g = reweighted(graph, &kept(edges.len(), rejected.iter().map(|r| r.edge)))?;
    }
    let mut refined = crate::refine::refine(&g, &x, refine)?;
    // Loop closures the leave-out test rejected are put back one at a time, and kept when the
    // cost now rises by no more than the threshold they failed (module docs): the test may
    // have met them while false edges still bent their place, and one that is the only
    // support of a stretch of the map fits the solution without it badly (its χ²_e stays
    // large) although it contradicts nothing.
    let retests: Vec<RejectedEdge> = rejected
        .iter()
        .filter(|r| r.test == "leave_out")
        .copied()
        .collect();
    for r in retests {
        let others = rejected.iter().map(|q| q.edge).filter(|&e| e != r.edge);
        let g_r = reweighted(graph, &kept(edges.len(), others))?;
        let with = crate::refine::refine(&g_r, &refined.poses, refine)?;
        if with.cost() - refined.cost() <= r.threshold {
            rejected.retain(|q| q.edge != r.edge);
            refined = with;
        }
    }
    let (chi2_orientation, linear) = first.unwrap_or_default();
    let cost_linear = refine.residual.cost(graph, &linear);
    Ok(Solution {
        wraps: wraps_of(
            graph,
            &refined.poses.iter().map(|p| p.theta).collect::<Vec<_>>(),
        ),
        chi2_orientation,
        linear,
        cost_linear,
        refined,
        rejected,
        noise_scales,
        drop_scale,
        seconds: t.elapsed().as_secs_f64(),
    })
}

/// The loop closures the online estimator quarantines when `graph` is streamed in robot order
/// with the default screening at level `alpha` (indices in `graph`'s edge order, ascending):
/// what [`solve_robust`] leaves out before its first pass.
pub fn quarantined(graph: &PoseGraph, alpha: f64) -> Result<Vec<RejectedEdge>, SolveError> {
    quarantine_run(graph, alpha, &[]).map(|(rejected, _)| rejected)
}

/// [`quarantined`] with the noise scales the stream ended with.
/// The edges `excluded` are left out of the stream (and are not in the result).
fn quarantine_run(
    graph: &PoseGraph,
    alpha: f64,
    excluded: &[RejectedEdge],
) -> Result<(Vec<RejectedEdge>, crate::online::NoiseScales), SolveError> {
    let config = crate::online::OnlineConfig {
        screening: ScreeningConfig {
            alpha,
            ..ScreeningConfig::default()
        },
        quarantine: true,
        // Only the decisions are read: no estimate is kept through the stream.
        estimate_every_step: false,
        ..crate::online::OnlineConfig::default()
    };
    let numerical = |e: crate::online::OnlineError| SolveError::Quarantine(e.to_string());
    let mut est = crate::online::OnlineEstimator::new(config).map_err(numerical)?;
    let mut out_of_stream = vec![false; graph.edge_count()];
    for r in excluded {
        out_of_stream[r.edge] = true;
    }
    let mut order = crate::online::robot_order_indices(graph.edges());
    order.retain(|&i| !out_of_stream[i]);
    for &i in &order {
        est.add_edge(graph.edges()[i]).map_err(numerical)?;
    }
    let mut out: Vec<RejectedEdge> = est
        .rejected()
        .into_iter()
        .map(|r| RejectedEdge {
            edge: order[r.edge],
            ..r
        })
        .collect();
    out.sort_by_key(|r| r.edge);
    Ok((out, est.noise_scales()))
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

/// Times [`solve_robust`] streams the graph again without the loop closures its passes
/// rejected.
const RESTREAMS: usize = 2;
/// Candidates verified by a refinement without them, per leave-out round ([`leave_out`]).
const LEAVE_OUT_TRIES: usize = 5;
/// Most groups rejected by leaving them out, per pass ([`leave_out`]).
const LEAVE_OUT_ROUNDS: usize = 8;
/// Loop closures whose ends are both within this many node indices of another's are in one
/// place group ([`place_groups`]).
pub(crate) const GROUP_SPAN: usize = 10;

/// The place of edge e: its two node indices, smaller first.
pub(crate) fn place(graph: &PoseGraph, e: usize) -> (usize, usize) {
    let (a, b) = graph.endpoints()[e];
    place_of(a, b)
}

/// The place of an edge between node indices a and b: smaller first.
pub(crate) fn place_of(a: usize, b: usize) -> (usize, usize) {
    (a.min(b), a.max(b))
}

/// Whether two places ([`place`]) are one: both ends within [`GROUP_SPAN`] node indices.
pub(crate) fn same_place((a, b): (usize, usize), (c, d): (usize, usize)) -> bool {
    a.abs_diff(c) <= GROUP_SPAN && b.abs_diff(d) <= GROUP_SPAN
}

/// Loop closures `lcs` (edge indices) grouped by place: `(a, b)` and `(a′, b′)` (node indices,
/// `a < b`) with `|a − a′| ≤ GROUP_SPAN` and `|b − b′| ≤ GROUP_SPAN` are in one group,
/// transitively (a run of loop closures of one revisit, or a group of false ones sharing a
/// measurement). Groups in order of their first edge, edges ascending.
fn place_groups(graph: &PoseGraph, lcs: &[usize]) -> Vec<Vec<usize>> {
    let ends: Vec<(usize, usize)> = lcs.iter().map(|&e| place(graph, e)).collect();
    let mut order: Vec<usize> = (0..lcs.len()).collect();
    order.sort_by_key(|&i| (ends[i], i));
    let mut parent: Vec<usize> = (0..lcs.len()).collect();
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    for (k, &i) in order.iter().enumerate() {
        for &j in order[..k].iter().rev() {
            if ends[j].0 + GROUP_SPAN < ends[i].0 {
                break;
            }
            if same_place(ends[j], ends[i]) {
                let (ri, rj) = (root(&mut parent, i), root(&mut parent, j));
                parent[ri.max(rj)] = ri.min(rj);
            }
        }
    }
    let mut groups: std::collections::BTreeMap<usize, Vec<usize>> = Default::default();
    for (i, &e) in lcs.iter().enumerate() {
        let r = root(&mut parent, i);
        groups.entry(r).or_default().push(e);
    }
    let mut out: Vec<Vec<usize>> = groups
        .into_values()
        .map(|mut g| {
            g.sort_unstable();
            g
        })
        .collect();
    out.sort_by_key(|g| g[0]);
    out
}

/// What [`leave_out`] returns: the poses without the rejected groups, the rejected edges,
/// and the scale the drops showed in its last round ([`drop_scale`]).
type LeftOut = (Vec<Pose2>, Vec<RejectedEdge>, Option<f64>);

/// Stage 3's leave-out test (module docs), greedy: every loop closure of `graph` (weights `w`,
/// poses `x` at their minimum) and every place group of two or more is a candidate; its
/// linearised drop Δ_G ([`crate::refine::leave_out_drops`]) is compared with
/// `s · χ²_{3|G|}⁻¹(1 − α / (2N))` (N candidates, `s` the noise scale); the candidates beyond it,
/// most significant first, are verified by refining without them, and the first whose actual
/// drop exceeds the threshold is rejected. Repeated (at most [`LEAVE_OUT_ROUNDS`] groups) until
/// no candidate is verified. Returns the poses without the rejected groups and the rejected
/// edges with their group's drop.
fn leave_out(
    graph: &PoseGraph,
    w: &[f64],
    mut x: Vec<Pose2>,
    inner: &RefineConfig,
    alpha: f64,
    scale: f64,
) -> Result<LeftOut, SolveError> {
    let edges = graph.edges();
    let mut w = w.to_vec();
    let mut rejected = Vec::new();
    let mut shown = None;
    // The graph of the edges of nonzero weight, and their indices in `graph`.
    let live = |w: &[f64]| -> Result<(PoseGraph, Vec<usize>), SolveError> {
        let alive = (0..edges.len()).filter(|&e| w[e] > 0.0).collect();
        Ok((reweighted(graph, w)?, alive))
    };
    let (mut g, mut alive) = live(&w)?;
    'rounds: for _ in 0..LEAVE_OUT_ROUNDS {
        let lcs: Vec<usize> = (0..alive.len())
            .filter(|&l| !edges[alive[l]].is_odometric())
            .collect();
        let places = place_groups(&g, &lcs);
        let drops = crate::refine::leave_out_drops(&g, &x, inner.residual, &places)?;
        // Candidates: every loop closure alone, and every place group of two or more.
        let mut groups: Vec<(Vec<usize>, f64)> = Vec::new();
        for (p, place) in places.iter().enumerate() {
            groups.extend(
                place
                    .iter()
                    .zip(&drops.edges[p])
                    .map(|(&l, &d)| (vec![l], d)),
            );
            if place.len() > 1 {
                groups.push((place.clone(), drops.groups[p]));
            }
        }
        let level = 1.0 - alpha / (2.0 * groups.len().max(1) as f64);
        shown = drop_scale(&drops.edges);
        let scale = scale.min(shown.unwrap_or(f64::INFINITY));
        let threshold = |g: &[usize]| scale * chi2_quantile(3.0 * g.len() as f64, level);
        // The largest drop per edge left out first: of a false edge and the genuine ones it
        // contradicts, leaving out either resolves the conflict, and the fewer edges explain it.
        let mut candidates: Vec<(f64, usize)> = groups
            .iter()
            .enumerate()
            .filter(|(_, (g, d))| *d > threshold(g))
            .map(|(i, (g, d))| (d / g.len() as f64, i))
            .collect();
        candidates.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        let with = inner.residual.cost(&g, &x);
        for &(_, i) in candidates.iter().take(LEAVE_OUT_TRIES) {
            let mut w_i = w.clone();
            let group = &groups[i].0;
            for &l in group {
                w_i[alive[l]] = 0.0;
            }
            let (g_i, alive_i) = live(&w_i)?;
            // Poses of g_i's nodes are x (nodes keep their order).
            let r = crate::refine::refine(&g_i, &x, inner)?;
            let drop = with - r.cost();
            if drop > threshold(group) {
                let t = threshold(group);
                rejected.extend(
                    group
                        .iter()
                        .map(|&l| RejectedEdge::of(graph, alive[l], "leave_out", drop, t)),
                );
                (w, g, alive, x) = (w_i, g_i, alive_i, r.poses);
                continue 'rounds;
            }
        }
        break;
    }
    rejected.sort_by_key(|r| r.edge);
    Ok((x, rejected, shown))
}

/// The noise scale the loop closures' own leave-out drops show, from above:
/// `ŝ = Δ_(k) / χ²_1⁻¹(0.99)`, `Δ_(k)` the k-th largest single-edge drop with
/// `k = ⌊N/100 − 2.58 √(N/100)⌋` (an upper 99.5 % confidence bound of their 99th percentile:
/// the number of N draws above it is Binomial(N, 0.01)); None when k < 1, i.e. with fewer
/// than 854 loop closures (their 99th percentile is not known well enough from above).
///
/// Why it bounds the scale: with the edges' whitened residual components' true variances
/// `λ_i` times the declared ones, a drop is `Δ_e = Σ_i λ_i z_i²` (z standard normal, at most
/// three components, which may be scaled differently: benchmark files declare their angle and
/// translation noise wrong by different factors), so `Δ_e ≥ λ_max z_max²` and
/// `Q_0.99(Δ) ≥ λ_max χ²_1⁻¹(0.99)`; a threshold `ŝ χ²_{3|G|}⁻¹(1 − α/2N)` with `ŝ ≥ λ_max` is
/// then passed by data that follow the (rescaled) model with probability ≥ 1 − α/2N per
/// candidate. An order statistic: each of fewer than k false edges still in the graph moves it
/// up by one place among the genuine drops, not by its size.
fn drop_scale(drops: &[Vec<f64>]) -> Option<f64> {
    let mut all: Vec<f64> = drops
        .iter()
        .flatten()
        .copied()
        .filter(|d| d.is_finite())
        .collect();
    let expected = all.len() as f64 / 100.0;
    let k = (expected - 2.58 * expected.sqrt()).floor();
    if k < 1.0 {
        return None;
    }
    let k = k as usize;
    let (_, q, _) = all.select_nth_unstable_by(k - 1, |a, b| b.total_cmp(a));
    (*q > 0.0).then(|| *q / crate::closure::Q99_1)
}

/// One robust pass (stages 1–3 of the module docs) from orientations θ₀.
struct Pass {
    /// The robust poses.
    poses: Vec<Pose2>,
    /// Loop closures of the pass' graph rejected (edge indices in the pass' graph).
    rejected: Vec<RejectedEdge>,
    /// Orientation χ² after stage 1 (every edge at full weight).
    chi2_orientation: f64,
    /// Least-squares positions after stage 1.
    linear: Vec<Pose2>,
    /// The scale the leave-out drops showed ([`drop_scale`]; None when the test did not run
    /// or had too few loop closures).
    drop_scale: Option<f64>,
}

fn robust_pass(
    graph: &PoseGraph,
    theta0: &[f64],
    refine: &RefineConfig,
    robust: &RobustConfig,
    (phi_1, phi_3): (f64, f64),
    scale: f64,
) -> Result<Pass, SolveError> {
    let edges = graph.edges();
    let ends = graph.endpoints();
    let loop_closure: Vec<bool> = edges.iter().map(|e| !e.is_odometric()).collect();
    let settled = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-3);
    let weights_of = |stat: &dyn Fn(usize) -> f64, phi: f64| -> Vec<f64> {
        (0..edges.len())
            .map(|e| {
                if loop_closure[e] {
                    dcs_weight(stat(e), phi)
                } else {
                    1.0
                }
            })
            .collect()
    };
    // Stage 1: orientations.
    let mut theta = theta0.to_vec();
    let mut w = vec![1.0; edges.len()];
    let mut g_w = graph.clone();
    for _ in 0..robust.rounds {
        let residual = |e: usize| {
            let (a, b) = ends[e];
            crate::graph::wrap_angle(theta[b] - theta[a] - edges[e].delta())
        };
        let next = weights_of(&|e| residual(e).powi(2) / edges[e].sigma2(), phi_1);
        if settled(&next, &w) {
            break;
        }
        w = next;
        g_w = reweighted(graph, &w)?;
        theta = OrientationEstimator::new(&g_w)?.orientations(&wraps_of(graph, &theta));
    }
    let chi2_orientation = OrientationEstimator::new(graph)?.cost(&theta, &wraps_of(graph, &theta));
    // Stage 2: SE(2) with least-squares positions from stage 1.
    let linear = crate::estimate::poses(&g_w, &theta)?;
    let inner = RefineConfig {
        iterations: refine.iterations.min(20),
        ..*refine
    };
    // First with the weights of stage 1 (a linear start can be far from the minimum, and
    // the kernel would then down-weight genuine edges), then reweighted.
    let mut x = crate::refine::refine(&g_w, &linear, &inner)?.poses;
    let mut w2 = vec![f64::NAN; edges.len()];
    for _ in 0..robust.rounds {
        let chi2: Vec<f64> = refine.residual.edge_costs(graph, &x).collect();
        let next = weights_of(&|e| chi2[e], phi_3);
        if settled(&next, &w2) {
            break;
        }
        w2 = next;
        x = crate::refine::refine(&reweighted(graph, &w2)?, &x, &inner)?.poses;
    }
    let chi2: Vec<f64> = refine.residual.edge_costs(graph, &x).collect();
    let mut shown = None;
    let mut rejected: Vec<RejectedEdge> = (0..edges.len())
        .filter(|&e| loop_closure[e] && chi2[e] > phi_3)
        .map(|e| RejectedEdge::of(graph, e, "se2_chi2", chi2[e], phi_3))
        .collect();
    if rejected.is_empty() {
        let w_all: Vec<f64> = if w2.first().is_none_or(|w| w.is_nan()) {
            vec![1.0; edges.len()]
        } else {
            w2
        };
        (x, rejected, shown) = leave_out(graph, &w_all, x, &inner, robust.alpha, scale)?;
    }
    Ok(Pass {
        poses: x,
        rejected,
        chi2_orientation,
        linear,
        drop_scale: shown,
    })
}

/// The wraps that bring every edge's angle residual into (−π, π] at orientations θ.
fn wraps_of(graph: &PoseGraph, theta: &[f64]) -> Vec<i64> {
    graph
        .edges()
        .iter()
        .zip(graph.endpoints())
        .map(|(e, &(a, b))| {
            ((e.delta() - theta[b] + theta[a]) / std::f64::consts::TAU).round() as i64
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

    /// Place groups: loop closures whose two ends are each within GROUP_SPAN node indices of
    /// another's are grouped transitively, in order of first edge; others stay alone.
    #[test]
    fn place_groups_join_nearby_loop_closures() {
        let mut g = PoseGraph::new();
        let info = Information::diagonal(1.0, 1.0, 1.0);
        let z = Pose2::new(1.0, 0.0, 0.0);
        for i in 0..100u64 {
            g.add_edge(Edge::new(i, i + 1, z, info).unwrap(), Default::default())
                .unwrap();
        }
        let lc = [(0, 50), (5, 55), (12, 64), (30, 90), (80, 20)];
        for (a, b) in lc {
            g.add_edge(Edge::new(a, b, z, info).unwrap(), Default::default())
                .unwrap();
        }
        let lcs: Vec<usize> = (100..105).collect();
        // (0,50)–(5,55)–(12,64) chain (each step ≤ 10 in both ends); (80,20) is (20,80),
        // 10 from (30,90) in both ends.
        assert_eq!(
            place_groups(&g, &lcs),
            vec![vec![100, 101, 102], vec![103, 104]]
        );
        assert_eq!(place_groups(&g, &[100, 103]), vec![vec![100], vec![103]]);
    }
    use crate::cycles::{Cycle, SignedEdge};
    use crate::graph::{Edge, NodePolicy, Pose2};

    /// Drops `λ_θ z₁² + λ_t (z₂² + z₃²)` of n loop closures (angle and translation scaled
    /// differently, as the benchmark files are), the simulator's deterministic normal draws.
    fn drops(n: usize, (la, lt): (f64, f64), noise: &mut crate::sim::Noise) -> Vec<Vec<f64>> {
        (0..n)
            .map(|_| {
                let (a, x, y) = (noise.normal(), noise.normal(), noise.normal());
                vec![la * a * a + lt * (x * x + y * y)]
            })
            .collect()
    }

    /// The drops' scale bounds the largest component's scale from above, sharply; a few
    /// false edges left in the graph do not move it; too few loop closures give none; and
    /// the threshold it sets lets clean data through at the family-wise level.
    #[test]
    fn the_drop_scale_bounds_the_noise_from_above() {
        let mut noise = crate::sim::Noise::seeded(7);
        let (la, lt) = (0.3, 0.02);
        let d = drops(2000, (la, lt), &mut noise);
        let s = drop_scale(&d).unwrap();
        assert!(s >= la && s <= 2.0 * la, "{s}");
        let mut dirty = d.clone();
        dirty.extend((0..5).map(|i| vec![100.0 + i as f64]));
        let t = drop_scale(&dirty).unwrap();
        assert!(t >= s && t <= 1.25 * s, "{s} {t}");
        assert_eq!(drop_scale(&d[..853]), None);
        assert!(drop_scale(&d[..854]).is_some());
        // 100 clean files of 2000 loop closures at α = 0.01: a file with any drop beyond the
        // threshold is a false alarm (expected at most α of them).
        let alpha = 0.01;
        let alarms = (0..100)
            .filter(|_| {
                let d = drops(2000, (la, lt), &mut noise);
                let limit = drop_scale(&d).unwrap() * chi2_quantile(3.0, 1.0 - alpha / 4000.0);
                d.iter().flatten().any(|&x| x > limit)
            })
            .count();
        println!("{alarms} of 100 clean files with a drop beyond the threshold");
        assert!(alarms <= 4, "{alarms} of 100");
    }

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
