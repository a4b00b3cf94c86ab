//! The SE(2) translation closure of a cycle (method [§11](crate::method#11-false-loop-closures)): a
//! χ² test with 2 degrees of freedom that catches false loop closures whose angle passes.
//!
//! Composing the measurements `Z_e = (t_e, δ_e)` around a cycle (`Z_e` along an edge, `Z_e⁻¹`
//! against it) from the frame of its first node gives the identity on clean data, up to noise.
//! Rotations are 2π-periodic, so the **translation** of the composition,
//!
//! ```text
//! r = Σ_i R(φ_{i−1}) t'_i,     φ_i = Σ_{k ≤ i} δ'_k,     (t'_i, δ'_i) = Z_i or Z_i⁻¹,
//! ```
//!
//! needs no wrap: it is a function of the measurements alone. Its covariance is propagated to
//! first order from each edge's covariance `Σ_e = Ω_e⁻¹` (g2o's convention: the noise is a
//! right perturbation `Z_e ⊕ ε_e`). A perturbation `η` inserted where the running pose is
//! `P = (p, φ)` (after `Z_e` along the edge, before `Z_e⁻¹` against it) moves the closure by
//!
//! ```text
//! δr = R(φ) η_t + J (r − p) η_θ,     J = [[0, −1], [1, 0]],
//! ```
//!
//! so `Cov(r) = Σ_e G_e Σ_e G_eᵀ` with `G_e = [R(φ) | J(r − p)]` (edges independent), and
//!
//! ```text
//! χ²_t = rᵀ Cov(r)⁻¹ r  ~  χ²_2,     P(χ²_2 > x) = e^{−x/2},  threshold −2 ln(level).
//! ```
//!
//! The angle noise enters through the lever arms `r − p`, so the test is valid on its own (it
//! is the marginal of the translation, not conditioned on the angle test). Linearisation is the
//! only approximation: at the benchmark files' noise (σ_θ ≤ 0.1 rad, loops of a few edges) it is
//! far below the statistic's spread.

use crate::cycles::SignedEdge;
use crate::graph::{Edge, Pose2};

/// The translation closure of one cycle and its test statistic.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Closure {
    /// The closure translation r in the frame of the cycle's first node.
    pub residual: [f64; 2],
    /// Its covariance (first order).
    pub covariance: [[f64; 2]; 2],
    /// `rᵀ Cov(r)⁻¹ r` (infinite if the covariance is singular and r ≠ 0).
    pub chi2: f64,
}

/// `χ²_2⁻¹(1 − level) = −2 ln(level)`: the threshold of the translation test at `level`.
pub fn threshold(level: f64) -> f64 {
    -2.0 * level.ln()
}

/// `P(χ²_2 > x) = e^{−x/2}`.
pub fn p_value(chi2: f64) -> f64 {
    (-0.5 * chi2).exp()
}

/// `Ω⁻¹` of an edge (symmetric 3×3 by cofactors); `None` if Ω is singular.
fn covariance(e: &Edge) -> Option<[[f64; 3]; 3]> {
    let m = e.information().matrix();
    let c = |i: usize, j: usize| {
        let (r0, r1) = ((i + 1) % 3, (i + 2) % 3);
        let (c0, c1) = ((j + 1) % 3, (j + 2) % 3);
        m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0]
    };
    let det = m[0][0] * c(0, 0) + m[0][1] * c(0, 1) + m[0][2] * c(0, 2);
    if !(det.is_finite() && det > 0.0) {
        return None;
    }
    let mut s = [[0.0; 3]; 3];
    for (i, row) in s.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = c(j, i) / det;
        }
    }
    Some(s)
}

/// The translation closure of a cycle given as signed edges in traversal order; `edge(e)`
/// returns edge e's measurement and information. `None` if an edge's information is singular.
pub fn translation_closure(terms: &[SignedEdge], edge: &dyn Fn(usize) -> Edge) -> Option<Closure> {
    // Running poses where each edge's noise enters (module docs).
    let mut pose = Pose2::default();
    let mut frames = Vec::with_capacity(terms.len());
    for t in terms {
        let z = edge(t.edge as usize).measurement();
        if t.sign > 0 {
            pose = pose.compose(z);
            frames.push(pose);
        } else {
            frames.push(pose);
            pose = pose.compose(z.inverse());
        }
    }
    let r = [pose.x, pose.y];
    let mut cov = [[0.0; 2]; 2];
    for (t, p) in terms.iter().zip(&frames) {
        let s = covariance(&edge(t.edge as usize))?;
        let (sn, cs) = (libm::sin(p.theta), libm::cos(p.theta));
        // G = [R(φ) | J (r − p)], 2×3.
        let lever = [-(r[1] - p.y), r[0] - p.x];
        let g = [[cs, -sn, lever[0]], [sn, cs, lever[1]]];
        for a in 0..2 {
            for b in 0..2 {
                let mut v = 0.0;
                for i in 0..3 {
                    for j in 0..3 {
                        v += g[a][i] * s[i][j] * g[b][j];
                    }
                }
                cov[a][b] += v;
            }
        }
    }
    let det = cov[0][0] * cov[1][1] - cov[0][1] * cov[1][0];
    let chi2 = if det > 0.0 && det.is_finite() {
        (cov[1][1] * r[0] * r[0] - 2.0 * cov[0][1] * r[0] * r[1] + cov[0][0] * r[1] * r[1]) / det
    } else if r == [0.0, 0.0] {
        0.0
    } else {
        f64::INFINITY
    };
    Some(Closure {
        residual: r,
        covariance: cov,
        chi2,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::Information;

    fn edge(from: u64, to: u64, z: Pose2) -> Edge {
        Edge::new(from, to, z, Information::diagonal(100.0, 100.0, 400.0)).unwrap()
    }

    /// A square driven around exactly closes; shifting one translation by 1 m gives
    /// χ² = 1 / Var of that direction, and the covariance matches a Monte-Carlo estimate.
    #[test]
    fn square_closes_and_covariance_matches_sampling() {
        use rand_chacha::ChaCha8Rng;
        use rand_chacha::rand_core::{Rng, SeedableRng};
        let h = std::f64::consts::FRAC_PI_2;
        let z = [
            Pose2::new(2.0, 0.0, h),
            Pose2::new(2.0, 0.0, h),
            Pose2::new(2.0, 0.0, h),
        ];
        // Edges 0→1, 1→2, 2→3 along; chord 0→3 traversed along, then back against the path.
        let chord = Pose2::new(0.0, -2.0, -h);
        let edges = [
            edge(0, 1, z[0]),
            edge(1, 2, z[1]),
            edge(2, 3, z[2]),
            edge(0, 3, chord),
        ];
        let terms = [
            SignedEdge::new(3, true),
            SignedEdge::new(2, false),
            SignedEdge::new(1, false),
            SignedEdge::new(0, false),
        ];
        let c = translation_closure(&terms, &|e| edges[e]).unwrap();
        assert!(c.residual[0].abs() < 1e-12 && c.residual[1].abs() < 1e-12);
        assert!(c.chi2 < 1e-20);
        // Monte Carlo with the edges' noise (right perturbations, σ_t = 0.1, σ_θ = 0.05).
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut gauss = || {
            let u1 = (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64 + 1e-300;
            let u2 = (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        };
        let n = 40_000;
        let mut acc = [[0.0; 2]; 2];
        for _ in 0..n {
            let noisy: Vec<Edge> = edges
                .iter()
                .map(|e| {
                    let eps = Pose2::new(0.1 * gauss(), 0.1 * gauss(), 0.05 * gauss());
                    edge(e.from(), e.to(), e.measurement().compose(eps))
                })
                .collect();
            let r = translation_closure(&terms, &|e| noisy[e]).unwrap().residual;
            for a in 0..2 {
                for b in 0..2 {
                    acc[a][b] += r[a] * r[b] / n as f64;
                }
            }
        }
        for a in 0..2 {
            for b in 0..2 {
                let want = c.covariance[a][b];
                assert!(
                    (acc[a][b] - want).abs() < 0.05 * c.covariance[a][a].max(c.covariance[b][b]),
                    "Cov[{a}][{b}]: sampled {} vs propagated {want}",
                    acc[a][b]
                );
            }
        }
        // A 1 m error on the chord's translation.
        let bad = [
            edges[0],
            edges[1],
            edges[2],
            edge(0, 3, Pose2::new(1.0, -2.0, -h)),
        ];
        let b = translation_closure(&terms, &|e| bad[e]).unwrap();
        assert!(b.chi2 > threshold(1e-6), "{}", b.chi2);
        assert!((p_value(threshold(1e-3)) - 1e-3).abs() < 1e-15);
    }
}
