//! Robust poses ([`solve_robust`]): false loop closures (method [§11](crate::method#11-false-loop-closures)) are met with the
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

use super::leave_out::leave_out;
use super::{
    BatchConfig, BatchResult, RejectedEdge, Solution, SolveError, place, same_place, screen,
};
use crate::cycles::BasisKind;
use crate::estimate::OrientationEstimator;
use crate::graph::{Edge, GraphError, Information, NodePolicy, Pose2, PoseGraph};
use crate::refine::RefineConfig;
use crate::screening::{Hypothesis, ScreeningConfig, chi2_quantile};

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
pub(super) fn reweighted(graph: &PoseGraph, weight: &[f64]) -> Result<PoseGraph, GraphError> {
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

/// Times [`solve_robust`] streams the graph again without the loop closures its passes
/// rejected.
const RESTREAMS: usize = 2;

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
    /// The scale the leave-out drops showed (`drop_scale` of [`super::leave_out`]; None when
    /// the test did not run or had too few loop closures).
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
