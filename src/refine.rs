//! Refinement of a pose graph on SE(2): Levenberg–Marquardt on the full cost
//!
//! ```text
//! F(x) = Σ_e e_eᵀ Ω_e e_e,     e_e = t2v(Z_e⁻¹ (X_i⁻¹ X_j))      (g2o's EdgeSE2 error; F is g2o's χ²)
//! e_t = R_zᵀ (R_iᵀ (t_j − t_i) − t_z),   e_θ = wrap(θ_j − θ_i − θ_z),
//! ∂e_t/∂t_j = R_zᵀR_iᵀ = −∂e_t/∂t_i,   ∂e_t/∂θ_i = R_zᵀ (dR_iᵀ/dθ) (t_j − t_i),   ∂e_θ/∂θ_j = 1 = −∂e_θ/∂θ_i.
//! ```
//!
//! Each iteration solves `(H + λ diag H) Δ = −g` ([`crate::estimate`]'s sparse normal
//! equations, one anchor pose per component held fixed) and keeps the step only if F
//! decreases; λ starts at 0 (Gauss–Newton), grows ×10 on a rejected step and shrinks ×10 on
//! an accepted one. It stops after the configured number of linear solves or when an accepted
//! step lowers F by less than the configured relative amount. Written here, compactly, rather
//! than pulling in a factor-graph framework: the whole method is the Jacobian above plus the
//! shared sparse Cholesky.

use crate::estimate::{Anchored, EstimateError, NormalEquations, solve};
use crate::graph::{Pose2, PoseGraph};
use crate::sim::wrap_angle;

/// When to stop.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct RefineConfig {
    /// At most this many linear solves.
    pub iterations: usize,
    /// Stop once an accepted step lowers the cost by less than this fraction.
    pub relative_decrease: f64,
}

impl Default for RefineConfig {
    fn default() -> Self {
        Self {
            iterations: 5,
            relative_decrease: 1e-6,
        }
    }
}

/// What a refinement did.
#[derive(Clone, Debug, PartialEq)]
pub struct Refined {
    /// The refined poses.
    pub poses: Vec<Pose2>,
    /// The cost before refining, then after every accepted step.
    pub costs: Vec<f64>,
    /// Linear solves made (accepted and rejected steps).
    pub iterations: usize,
    /// Whether it stopped on the relative-decrease criterion (rather than the iteration cap).
    pub converged: bool,
}

impl Refined {
    /// The final cost.
    pub fn cost(&self) -> f64 {
        self.costs.last().copied().unwrap_or(0.0)
    }
}

/// Error of one edge and its Jacobians w.r.t. `(x_i, y_i, θ_i)` and `(x_j, y_j, θ_j)`.
fn linearise(z: Pose2, xi: Pose2, xj: Pose2) -> ([f64; 3], [[f64; 3]; 3], [[f64; 3]; 3]) {
    let (si, ci) = (libm::sin(xi.theta), libm::cos(xi.theta));
    let (sz, cz) = (libm::sin(z.theta), libm::cos(z.theta));
    let (dx, dy) = (xj.x - xi.x, xj.y - xi.y);
    // R_iᵀ d and its derivative in θ_i.
    let (lx, ly) = (ci * dx + si * dy, -si * dx + ci * dy);
    let (dlx, dly) = (-si * dx + ci * dy, -ci * dx - si * dy);
    let (ux, uy) = (lx - z.x, ly - z.y);
    let e = [
        cz * ux + sz * uy,
        -sz * ux + cz * uy,
        wrap_angle(xj.theta - xi.theta - z.theta),
    ];
    // M = R_zᵀ R_iᵀ.
    let m = [
        [cz * ci - sz * si, cz * si + sz * ci],
        [-sz * ci - cz * si, -sz * si + cz * ci],
    ];
    let dth = [cz * dlx + sz * dly, -sz * dlx + cz * dly];
    let ja = [
        [-m[0][0], -m[0][1], dth[0]],
        [-m[1][0], -m[1][1], dth[1]],
        [0.0, 0.0, -1.0],
    ];
    let jb = [
        [m[0][0], m[0][1], 0.0],
        [m[1][0], m[1][1], 0.0],
        [0.0, 0.0, 1.0],
    ];
    (e, ja, jb)
}

/// `Σ_e e_eᵀ Ω_e e_e` (g2o's χ²) of poses `x` (one per node, dense index order).
pub fn cost(graph: &PoseGraph, x: &[Pose2]) -> f64 {
    graph
        .edges()
        .iter()
        .zip(graph.endpoints())
        .map(|(edge, &(a, b))| {
            let (e, _, _) = linearise(edge.measurement(), x[a], x[b]);
            let o = edge.information().matrix();
            (0..3)
                .map(|i| (0..3).map(|j| e[i] * o[i][j] * e[j]).sum::<f64>())
                .sum::<f64>()
        })
        .sum()
}

/// Refine `initial` (one pose per node; each component's anchor, its first node, stays fixed).
pub fn refine(
    graph: &PoseGraph,
    initial: &[Pose2],
    config: &RefineConfig,
) -> Result<Refined, EstimateError> {
    if initial.len() != graph.node_count() {
        return Err(EstimateError(format!(
            "{} initial poses for {} nodes",
            initial.len(),
            graph.node_count()
        )));
    }
    let anchored = Anchored::new(graph);
    let mut ne = NormalEquations::<3>::new(graph, &anchored)?;
    let mut x = initial.to_vec();
    let mut c = cost(graph, &x);
    let mut costs = vec![c];
    let (mut lambda, mut iterations, mut converged) = (0.0f64, 0, false);
    let mut assembled = false;
    while iterations < config.iterations && ne.dim() > 0 {
        if !assembled {
            ne.clear();
            for (e, (edge, &(a, b))) in graph.edges().iter().zip(graph.endpoints()).enumerate() {
                let (err, ja, jb) = linearise(edge.measurement(), x[a], x[b]);
                ne.add(e, &ja, &jb, &edge.information().matrix(), &err);
            }
            assembled = true;
        }
        iterations += 1;
        let Ok(llt) = ne.factor(lambda) else {
            lambda = if lambda == 0.0 { 1e-4 } else { lambda * 10.0 };
            continue;
        };
        let step = solve(llt.as_ref(), &ne.rhs());
        let trial: Vec<Pose2> = x
            .iter()
            .enumerate()
            .map(|(v, p)| {
                let d = |i| anchored.value(&step, v, 3, i);
                Pose2::new(p.x + d(0), p.y + d(1), p.theta + d(2))
            })
            .collect();
        let ct = cost(graph, &trial);
        if ct.is_finite() && ct <= c {
            let decrease = if c > 0.0 { (c - ct) / c } else { 0.0 };
            x = trial;
            c = ct;
            costs.push(c);
            assembled = false;
            lambda = if lambda > 1e-9 { lambda / 10.0 } else { 0.0 };
            if decrease < config.relative_decrease {
                converged = true;
                break;
            }
        } else {
            lambda = if lambda == 0.0 { 1e-4 } else { lambda * 10.0 };
        }
    }
    Ok(Refined {
        poses: x,
        costs,
        iterations,
        converged,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{SimConfig, simulate};

    /// Finite differences of the error agree with the analytic Jacobians.
    #[test]
    fn jacobians_match_finite_differences() {
        let z = Pose2::new(0.7, -0.3, 2.9);
        let xi = Pose2::new(1.0, 2.0, -2.5);
        let xj = Pose2::new(1.4, 1.1, 0.9);
        let (_, ja, jb) = linearise(z, xi, xj);
        let h = 1e-6;
        for k in 0..3 {
            let bump = |p: Pose2, s: f64| {
                let mut v = [p.x, p.y, p.theta];
                v[k] += s;
                Pose2::new(v[0], v[1], v[2])
            };
            let (ep, _, _) = linearise(z, bump(xi, h), xj);
            let (em, _, _) = linearise(z, bump(xi, -h), xj);
            let (fp, _, _) = linearise(z, xi, bump(xj, h));
            let (fm, _, _) = linearise(z, xi, bump(xj, -h));
            for r in 0..3 {
                assert!(
                    ((ep[r] - em[r]) / (2.0 * h) - ja[r][k]).abs() < 1e-6,
                    "a {r} {k}"
                );
                assert!(
                    ((fp[r] - fm[r]) / (2.0 * h) - jb[r][k]).abs() < 1e-6,
                    "b {r} {k}"
                );
            }
        }
    }

    #[test]
    fn the_truth_costs_about_the_noise_and_refinement_never_increases_the_cost() {
        let w = simulate(&SimConfig::new(300, 3)).unwrap();
        let p0 = w.truth.poses[0];
        let truth: Vec<Pose2> = w.truth.poses.iter().map(|t| p0.between(*t)).collect();
        let c = cost(&w.graph, &truth);
        // E[χ²] = 3 m for correctly weighted noise.
        let m = w.graph.edge_count() as f64;
        assert!(c > 2.0 * m && c < 4.0 * m, "{c} vs 3m = {}", 3.0 * m);
        let r = refine(&w.graph, &truth, &RefineConfig::default()).unwrap();
        assert!(r.costs.windows(2).all(|p| p[1] <= p[0]));
        assert!(r.cost() < c);
    }
}
