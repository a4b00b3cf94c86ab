//! Orientation and position estimates for a hypothesis (method [§5](crate::method#5-wraps-and-orientations), [§8](crate::method#8-success-probability); the positions follow
//! the paper's reference \[2\], LAGO).
//!
//! **Orientations.** For wraps k, the maximum-likelihood orientations are
//!
//! ```text
//! θ* = (Ā P⁻¹ Āᵀ)⁻¹ Ā P⁻¹ (δ − 2πk),      P_θ = (Ā P⁻¹ Āᵀ)⁻¹,
//! ```
//!
//! where `Ā P⁻¹ Āᵀ` is the weighted graph Laplacian (weights 1/σ_e²) with the anchors' rows
//! and columns removed (one anchor per connected component, θ = 0). It is sparse and SPD; it
//! is factored once by a sparse Cholesky (faer, AMD ordering) and each hypothesis is one
//! solve. Marginal variances are one solve per requested node (never a dense inverse). The
//! cost of an estimate is `χ² = Σ_e (θ_j − θ_i − δ_e + 2πk_e)² / σ_e²`, which equals
//! `(γ − μ)ᵀ P_γ⁻¹ (γ − μ)` for `γ = Ck` (method [§2](crate::method#2-cycles)).
//!
//! **Positions.** With the orientations fixed at θ*, each edge's measured translation `t_e`
//! (in the frame of its tail `i`) becomes a linear measurement of `p_j − p_i = R(θ*_i) t_e`;
//! the positions minimise
//!
//! ```text
//! Σ_e (p_j − p_i − R(θ*_i) t_e)ᵀ R(θ*_i) Ω_t,e R(θ*_i)ᵀ (p_j − p_i − R(θ*_i) t_e),
//! Ω_t,e = Ω_tt − Ω_tθ Ω_θθ⁻¹ Ω_θt   (the translation's marginal information),
//! ```
//!
//! a sparse 2n × 2n SPD system (anchors at the origin). Covariance approximation: θ* is treated
//! as exact (the rotated translation keeps the measured covariance rotated into the world
//! frame; the angle uncertainty it would add, first order in σ_θ·|t|, is neglected) and the
//! translation's correlation with the angle measurement is marginalised out. This is the linear
//! initial guess; [`crate::refine`] then minimises the full SE(2) cost from it.

use std::f64::consts::TAU;

use faer::Col;
use faer::sparse::linalg::solvers::Llt;

use crate::graph::{Pose2, PoseGraph};
use crate::tree::SpanningTree;

pub(crate) mod incremental;
mod system;

pub(crate) use system::{ANCHOR, Anchored, NormalEquations, solve};

/// A linear system could not be built or factored.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum EstimateError {
    /// An argument has the wrong length for the graph or system it is used with.
    #[error("linear system: {what}: expected {expected}, got {got}")]
    Size {
        /// What was counted (e.g. "initial poses for the graph's nodes").
        what: &'static str,
        /// The count the graph or system has.
        expected: usize,
        /// The count given.
        got: usize,
    },
    /// The sparse Cholesky factorisation met a non-positive pivot: the normal equations are
    /// not positive definite in double precision.
    #[error(
        "linear system: the normal equations ({unknowns} unknowns) are not positive definite \
         (pivot {pivot} in the solver's fill-reducing order): an edge's information is \
         degenerate, or the information spans more than double precision can factor"
    )]
    NotPositiveDefinite {
        /// Number of unknowns of the system.
        unknowns: usize,
        /// The failing pivot, in the factorisation's (permuted) order.
        pivot: usize,
    },
    /// The factorisation could not allocate or index its system.
    #[error(
        "linear system: the sparse factorisation of {unknowns} unknowns ran out of memory or index range"
    )]
    Resources {
        /// Number of unknowns of the system.
        unknowns: usize,
    },
}

impl EstimateError {
    /// `Err(Size)` unless `got == expected`.
    pub(crate) fn check_size(what: &'static str, expected: usize, got: usize) -> Result<(), Self> {
        if got == expected {
            Ok(())
        } else {
            Err(Self::Size {
                what,
                expected,
                got,
            })
        }
    }

    /// The typed error of a failed sparse Cholesky of `unknowns` unknowns.
    pub(crate) fn from_llt(unknowns: usize, e: faer::sparse::linalg::LltError) -> Self {
        match e {
            faer::sparse::linalg::LltError::Numeric(
                faer::linalg::cholesky::llt::factor::LltError::NonPositivePivot { index },
            ) => Self::NotPositiveDefinite {
                unknowns,
                pivot: index,
            },
            faer::sparse::linalg::LltError::Generic(_) => Self::Resources { unknowns },
        }
    }
}

/// Factored orientation system of a graph.
pub struct OrientationEstimator {
    anchored: Anchored,
    /// The Laplacian's pattern and symbolic factorisation, reused by [`Self::poses`].
    system: NormalEquations<1>,
    ends: Vec<(usize, usize)>,
    weight: Vec<f64>,
    delta: Vec<f64>,
    llt: Option<Llt<usize, f64>>,
}

impl OrientationEstimator {
    /// Build and factor the anchored Laplacian; anchors are the first node (index order) of
    /// each connected component.
    pub fn new(graph: &PoseGraph) -> Result<Self, EstimateError> {
        let anchored = Anchored::new(graph);
        let weight: Vec<f64> = graph.edges().iter().map(|e| 1.0 / e.sigma2()).collect();
        let mut ne = NormalEquations::<1>::new(graph, &anchored)?;
        for (e, &w) in weight.iter().enumerate() {
            ne.add(e, &[[-1.0]], &[[1.0]], &[[w]], &[0.0]);
        }
        Ok(Self {
            llt: ne.factor(0.0)?,
            system: ne,
            anchored,
            ends: graph.endpoints().to_vec(),
            weight,
            delta: graph.edges().iter().map(|e| e.delta()).collect(),
        })
    }

    /// The anchor node of each component.
    pub fn anchors(&self) -> &[usize] {
        &self.anchored.anchors
    }

    /// θ* for wraps k (one entry per node, anchors 0; unwrapped).
    pub fn orientations(&self, wraps: &[i64]) -> Vec<f64> {
        let rhs = self.anchored.scatter(&self.ends, |e| {
            self.weight[e] * (self.delta[e] - TAU * wraps[e] as f64)
        });
        let x = solve(self.llt.as_ref(), &rhs);
        (0..self.anchored.var_of.len())
            .map(|v| self.anchored.value(&x, v, 1, 0))
            .collect()
    }

    /// `Σ_e (θ_j − θ_i − δ_e + 2πk_e)² / σ_e²`.
    pub fn cost(&self, theta: &[f64], wraps: &[i64]) -> f64 {
        self.ends
            .iter()
            .enumerate()
            .map(|(e, &(a, b))| {
                let r = theta[b] - theta[a] - self.delta[e] + TAU * wraps[e] as f64;
                r * r * self.weight[e]
            })
            .sum()
    }

    /// Poses for orientations θ of the graph this system was built from: θ with the
    /// least-squares [`positions`], reusing this system's ordering when the translation
    /// information is isotropic.
    pub fn poses(&self, graph: &PoseGraph, theta: &[f64]) -> Result<Vec<Pose2>, EstimateError> {
        EstimateError::check_size(
            "poses: graph nodes for the system's nodes",
            self.anchored.var_of.len(),
            graph.node_count(),
        )?;
        EstimateError::check_size(
            "poses: graph edges for the system's edges",
            self.ends.len(),
            graph.edge_count(),
        )?;
        EstimateError::check_size(
            "poses: orientations for the graph's nodes",
            graph.node_count(),
            theta.len(),
        )?;
        let pos = positions_with(graph, theta, &self.anchored, Some(&self.system))?;
        Ok(with_headings(pos, theta))
    }

    /// Marginal variance `(P_θ)_vv` of node v (0 for an anchor): one sparse solve.
    pub fn variance(&self, node: usize) -> f64 {
        let Some(&v) = self.anchored.var_of.get(node) else {
            return 0.0;
        };
        if v == ANCHOR || self.llt.is_none() {
            return 0.0;
        }
        let mut e = Col::<f64>::zeros(self.anchored.free);
        e[v] = 1.0;
        solve(self.llt.as_ref(), &e)[v]
    }
}

/// Least-squares positions for fixed orientations θ (see the module docs); anchors at the
/// origin.
///
/// When every edge's translation information is isotropic (`Ω_t = w I`, as in most SLAM
/// data), `R Ω_t Rᵀ = w I` and the problem splits exactly into x and y with one shared
/// weighted Laplacian: one n × n factorisation and two solves instead of a 2n × 2n system.
pub fn positions(graph: &PoseGraph, theta: &[f64]) -> Result<Vec<(f64, f64)>, EstimateError> {
    positions_with(graph, theta, &Anchored::new(graph), None)
}

/// [`positions`], reusing a Laplacian pattern and ordering of the same graph when given.
fn positions_with(
    graph: &PoseGraph,
    theta: &[f64],
    anchored: &Anchored,
    laplacian: Option<&NormalEquations<1>>,
) -> Result<Vec<(f64, f64)>, EstimateError> {
    let rotated = |edge: &crate::graph::Edge, a: usize| {
        let m = edge.measurement();
        let (s, c) = theta[a].sin_cos();
        ([c * m.x - s * m.y, s * m.x + c * m.y], [[c, -s], [s, c]])
    };
    let isotropic = graph.edges().iter().all(|e| {
        let o = e.information().translation_information();
        o[0][1] == 0.0 && o[0][0] == o[1][1]
    });
    let nodes = anchored.var_of.len();
    if isotropic {
        let mut ne = match laplacian {
            Some(l) => l.clone(),
            None => NormalEquations::<1>::new(graph, anchored)?,
        };
        ne.clear();
        let mut weighted = Vec::with_capacity(graph.edge_count());
        for (e, (edge, &(a, _))) in graph.edges().iter().zip(graph.endpoints()).enumerate() {
            let w = edge.information().translation_information()[0][0];
            ne.add(e, &[[-1.0]], &[[1.0]], &[[w]], &[0.0]);
            let (t, _) = rotated(edge, a);
            weighted.push([w * t[0], w * t[1]]);
        }
        let llt = ne.factor(0.0)?;
        let [x, y] = [0, 1].map(|i| {
            solve(
                llt.as_ref(),
                &anchored.scatter(graph.endpoints(), |e| weighted[e][i]),
            )
        });
        return Ok((0..nodes)
            .map(|v| (anchored.value(&x, v, 1, 0), anchored.value(&y, v, 1, 0)))
            .collect());
    }
    let mut ne = NormalEquations::<2>::new(graph, anchored)?;
    const MINUS: [[f64; 2]; 2] = [[-1.0, 0.0], [0.0, -1.0]];
    const PLUS: [[f64; 2]; 2] = [[1.0, 0.0], [0.0, 1.0]];
    for (e, (edge, &(a, _))) in graph.edges().iter().zip(graph.endpoints()).enumerate() {
        let (t, r) = rotated(edge, a);
        let o = edge.information().translation_information();
        // W = R Ω_t Rᵀ.
        let w: [[f64; 2]; 2] = std::array::from_fn(|i| {
            std::array::from_fn(|j| {
                (0..2)
                    .map(|k| (0..2).map(|l| r[i][k] * o[k][l] * r[j][l]).sum::<f64>())
                    .sum()
            })
        });
        // Residual at p = 0.
        ne.add(e, &MINUS, &PLUS, &w, &[-t[0], -t[1]]);
    }
    let llt = ne.factor(0.0)?;
    let x = solve(llt.as_ref(), &ne.rhs());
    Ok((0..nodes)
        .map(|v| (anchored.value(&x, v, 2, 0), anchored.value(&x, v, 2, 1)))
        .collect())
}

/// Poses from orientations θ: θ with the least-squares [`positions`].
pub fn poses(graph: &PoseGraph, theta: &[f64]) -> Result<Vec<Pose2>, EstimateError> {
    Ok(with_headings(positions(graph, theta)?, theta))
}

fn with_headings(pos: Vec<(f64, f64)>, theta: &[f64]) -> Vec<Pose2> {
    pos.into_iter()
        .zip(theta)
        .map(|((x, y), &t)| Pose2::new(x, y, t))
        .collect()
}

/// Dead reckoning: the measured relative poses composed along the odometric spanning tree
/// ([`SpanningTree::odometric`]) from each component's anchor at the origin — the start of
/// an iterative solver that knows nothing of the loops.
pub fn odometry_poses(graph: &PoseGraph) -> Vec<Pose2> {
    let tree = SpanningTree::odometric(graph);
    let mut order: Vec<usize> = (0..graph.node_count()).collect();
    order.sort_by_key(|&v| tree.depth[v]);
    let mut pose = vec![Pose2::default(); graph.node_count()];
    for v in order {
        if let Some((p, e)) = tree.parent[v] {
            let z = graph.edges()[e].measurement();
            let (a, _) = graph.endpoints()[e];
            pose[v] = pose[p].compose(if a == p { z } else { z.inverse() });
        }
    }
    pose
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{SimConfig, simulate};

    /// Failures are typed: a size mismatch names what was counted, and a system whose
    /// information spans more than double precision can factor is `NotPositiveDefinite`,
    /// not a solver's debug text.
    #[test]
    fn failures_are_typed() {
        let w = simulate(&SimConfig::new(200, 4)).unwrap();
        let est = OrientationEstimator::new(&w.graph).unwrap();
        let err = est.poses(&w.graph, &[0.0; 3]).unwrap_err();
        assert_eq!(
            err,
            EstimateError::Size {
                what: "poses: orientations for the graph's nodes",
                expected: w.graph.node_count(),
                got: 3
            }
        );
        let mut g = PoseGraph::new();
        for (k, e) in w.graph.edges().iter().enumerate() {
            let info = if k % 2 == 0 { 1e12 } else { 1e-12 };
            let e = crate::graph::Edge::new(
                e.from(),
                e.to(),
                e.measurement(),
                crate::graph::Information::diagonal(1.0, 1.0, info),
            )
            .unwrap();
            g.add_edge(e, crate::graph::NodePolicy::CreateUnknown)
                .unwrap();
        }
        match OrientationEstimator::new(&g) {
            Err(e @ EstimateError::NotPositiveDefinite { unknowns, .. }) => {
                assert_eq!(unknowns, g.node_count() - 1);
                assert!(!e.to_string().contains("NonPositivePivot"), "{e}");
            }
            other => panic!("{:?}", other.map(|_| ())),
        }
    }

    /// The isotropic shortcut and the general 2 × 2-block system agree: a graph made
    /// anisotropic by a negligible off-diagonal term takes the general path.
    #[test]
    fn isotropic_and_general_position_systems_agree() {
        let w = simulate(&SimConfig::new(300, 6)).unwrap();
        let theta = OrientationEstimator::new(&w.graph)
            .unwrap()
            .orientations(&vec![0; w.graph.edge_count()]);
        let mut aniso = PoseGraph::new();
        for e in w.graph.edges() {
            let mut info = e.information();
            info.0[1] = 1e-12;
            let e2 = crate::graph::Edge::new(e.from(), e.to(), e.measurement(), info).unwrap();
            aniso.add_edge(e2, Default::default()).unwrap();
        }
        let a = positions(&w.graph, &theta).unwrap();
        let b = positions(&aniso, &theta).unwrap();
        for (p, q) in a.iter().zip(&b) {
            assert!((p.0 - q.0).abs() < 1e-8 && (p.1 - q.1).abs() < 1e-8);
        }
    }

    #[test]
    fn positions_and_odometry_follow_the_truth_for_tiny_noise() {
        let mut c = SimConfig::new(200, 4);
        c.sigma_xy = 1e-7;
        c.sigma_theta = 1e-7;
        let w = simulate(&c).unwrap();
        let theta: Vec<f64> = w.truth.poses.iter().map(|p| p.theta).collect();
        let p0 = w.truth.poses[0];
        let pos = positions(&w.graph, &theta).unwrap();
        let odo = odometry_poses(&w.graph);
        // The truth relative to node 0, in node 0's frame (the anchor's frame).
        for ((p, o), t) in pos.iter().zip(&odo).zip(&w.truth.poses) {
            let rel = p0.between(*t);
            let (s, c) = p0.theta.sin_cos();
            let world = (c * rel.x - s * rel.y, s * rel.x + c * rel.y);
            assert!((p.0 - world.0).abs() < 1e-4 && (p.1 - world.1).abs() < 1e-4);
            assert!((o.x - rel.x).abs() < 1e-4 && (o.y - rel.y).abs() < 1e-4);
        }
    }
}
