//! Orientation estimate for a hypothesis (METHOD.md §5, §8).
//!
//! For wraps k, the maximum-likelihood orientations are
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
//! `(γ − μ)ᵀ P_γ⁻¹ (γ − μ)` for `γ = Ck` (METHOD.md §2).

use std::f64::consts::TAU;

use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::Llt;
use faer::sparse::{SparseColMat, Triplet};
use faer::{Col, Side};

use crate::graph::PoseGraph;

/// The Laplacian could not be factored.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("orientation system: {0}")]
pub struct EstimateError(pub String);

const ANCHOR: usize = usize::MAX;

/// Factored orientation system of a graph.
pub struct OrientationEstimator {
    var_of: Vec<usize>,
    ends: Vec<(usize, usize)>,
    weight: Vec<f64>,
    delta: Vec<f64>,
    llt: Option<Llt<usize, f64>>,
    anchors: Vec<usize>,
}

impl OrientationEstimator {
    /// Build and factor the anchored Laplacian; anchors are the first node (index order) of
    /// each connected component.
    pub fn new(graph: &PoseGraph) -> Result<Self, EstimateError> {
        let (label, count) = graph.components();
        let mut anchors = vec![ANCHOR; count];
        for (v, &c) in label.iter().enumerate() {
            if anchors[c] == ANCHOR {
                anchors[c] = v;
            }
        }
        let mut var_of = vec![0; graph.node_count()];
        let mut n = 0;
        for (v, slot) in var_of.iter_mut().enumerate() {
            if anchors[label[v]] == v {
                *slot = ANCHOR;
            } else {
                *slot = n;
                n += 1;
            }
        }
        let ends = graph.endpoints().to_vec();
        let weight: Vec<f64> = graph.edges().iter().map(|e| 1.0 / e.sigma2()).collect();
        let delta = graph.edges().iter().map(|e| e.delta()).collect();
        let mut trip = Vec::with_capacity(4 * ends.len());
        for (&(a, b), &w) in ends.iter().zip(&weight) {
            let (va, vb) = (var_of[a], var_of[b]);
            if va != ANCHOR {
                trip.push(Triplet::new(va, va, w));
            }
            if vb != ANCHOR {
                trip.push(Triplet::new(vb, vb, w));
            }
            if va != ANCHOR && vb != ANCHOR {
                trip.push(Triplet::new(va, vb, -w));
                trip.push(Triplet::new(vb, va, -w));
            }
        }
        let llt = if n == 0 {
            None
        } else {
            let lap = SparseColMat::<usize, f64>::try_new_from_triplets(n, n, &trip)
                .map_err(|e| EstimateError(format!("{e:?}")))?;
            Some(
                lap.sp_cholesky(Side::Lower)
                    .map_err(|e| EstimateError(format!("{e:?}")))?,
            )
        };
        Ok(Self {
            var_of,
            ends,
            weight,
            delta,
            llt,
            anchors,
        })
    }

    /// The anchor node of each component.
    pub fn anchors(&self) -> &[usize] {
        &self.anchors
    }

    /// θ* for wraps k (one entry per node, anchors 0; unwrapped).
    pub fn orientations(&self, wraps: &[i64]) -> Vec<f64> {
        let nodes = self.var_of.len();
        let Some(llt) = &self.llt else {
            return vec![0.0; nodes];
        };
        let n = self.var_of.iter().filter(|&&v| v != ANCHOR).count();
        let mut rhs = Col::<f64>::zeros(n);
        for (e, &(a, b)) in self.ends.iter().enumerate() {
            let y = self.weight[e] * (self.delta[e] - TAU * wraps[e] as f64);
            if self.var_of[b] != ANCHOR {
                rhs[self.var_of[b]] += y;
            }
            if self.var_of[a] != ANCHOR {
                rhs[self.var_of[a]] -= y;
            }
        }
        let x = llt.solve(&rhs);
        self.var_of
            .iter()
            .map(|&v| if v == ANCHOR { 0.0 } else { x[v] })
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

    /// Marginal variance `(P_θ)_vv` of node v (0 for an anchor): one sparse solve.
    pub fn variance(&self, node: usize) -> f64 {
        let (Some(llt), Some(&v)) = (&self.llt, self.var_of.get(node)) else {
            return 0.0;
        };
        if v == ANCHOR {
            return 0.0;
        }
        let n = self.var_of.iter().filter(|&&x| x != ANCHOR).count();
        let mut e = Col::<f64>::zeros(n);
        e[v] = 1.0;
        llt.solve(&e)[v]
    }
}

/// Positions composed from the measured translations along a spanning forest (breadth first
/// from each component's first node, edges in insertion order), rotated by the given
/// orientations: `p_j = p_i + R(θ_i) t_ij`. The anchors sit at the origin. This is the
/// "odometry composed with the current orientations" view; it is not a least-squares
/// position estimate.
pub fn composed_positions(graph: &PoseGraph, theta: &[f64]) -> Vec<(f64, f64)> {
    let n = graph.node_count();
    let mut adj: Vec<Vec<usize>> = vec![Vec::new(); n];
    for (e, &(a, b)) in graph.endpoints().iter().enumerate() {
        adj[a].push(e);
        adj[b].push(e);
    }
    let mut pos = vec![(0.0, 0.0); n];
    let mut seen = vec![false; n];
    let mut queue = std::collections::VecDeque::new();
    for root in 0..n {
        if seen[root] {
            continue;
        }
        seen[root] = true;
        queue.push_back(root);
        while let Some(v) = queue.pop_front() {
            for &e in &adj[v] {
                let (a, b) = graph.endpoints()[e];
                let w = if a == v { b } else { a };
                if seen[w] {
                    continue;
                }
                seen[w] = true;
                let m = graph.edges()[e].measurement();
                let (s, c) = theta[a].sin_cos();
                let (tx, ty) = (c * m.x - s * m.y, s * m.x + c * m.y);
                pos[w] = if w == b {
                    (pos[a].0 + tx, pos[a].1 + ty)
                } else {
                    (pos[b].0 - tx, pos[b].1 - ty)
                };
                queue.push_back(w);
            }
        }
    }
    pos
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{SimConfig, simulate};

    #[test]
    fn composed_positions_follow_the_truth_for_tiny_noise() {
        let mut c = SimConfig::new(200, 4);
        c.sigma_xy = 1e-7;
        c.sigma_theta = 1e-7;
        let w = simulate(&c).unwrap();
        let theta: Vec<f64> = w.truth.poses.iter().map(|p| p.theta).collect();
        let pos = composed_positions(&w.graph, &theta);
        let p0 = w.truth.poses[0];
        for (p, t) in pos.iter().zip(&w.truth.poses) {
            assert!((p.0 - (t.x - p0.x)).abs() < 1e-4 && (p.1 - (t.y - p0.y)).abs() < 1e-4);
        }
    }
}
