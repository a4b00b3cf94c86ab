//! From cycle integers γ to edge wraps k (METHOD.md §5).
//!
//! Order the edges as tree edges then chords, `C = [C_T C_L]`; then `k = [0; C_L⁻¹ γ]` solves
//! `C k = γ`, and every solution gives the same orientations modulo 2π (paper Prop. 1).
//! `C_L⁻¹ γ` is integral for every integer γ iff `det C_L = ±1`. The bases of
//! [`crate::cycles`] are triangular — cycle t holds its chord with sign +1 and otherwise only
//! tree edges and chords of earlier cycles — so `C_L` is unit lower triangular and
//!
//! ```text
//! k_{chord(t)} = γ_t − Σ_{e ∈ c_t, e ≠ chord(t)} (±1) k_e        (forward substitution),
//! ```
//!
//! integral by construction. [`WrapSolver::new`] checks the triangular structure and refuses a
//! basis without it (a general `C_L` needs an integrality check per γ).

use crate::cycles::Cycle;

/// The basis is not triangular in its chords.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum WrapError {
    /// Cycle `cycle` uses edge `edge`, the chord of a later cycle (or a chord twice).
    #[error(
        "cycle {cycle} uses edge {edge}, the chord of a later or the same cycle: C_L is not triangular"
    )]
    NotTriangular {
        /// The cycle.
        cycle: usize,
        /// The edge.
        edge: usize,
    },
    /// γ has the wrong length.
    #[error("γ has {got} entries, the basis has {want} cycles")]
    Length {
        /// Entries given.
        got: usize,
        /// Cycles in the basis.
        want: usize,
    },
}

/// Recovers k from γ for a triangular basis.
#[derive(Clone, Debug)]
pub struct WrapSolver {
    edges: usize,
}

impl WrapSolver {
    /// Check that `cycles` (over `edges` edges) is triangular in its chords.
    pub fn new(cycles: &[Cycle], edges: usize) -> Result<Self, WrapError> {
        const NONE: usize = usize::MAX;
        let mut owner = vec![NONE; edges];
        for (t, c) in cycles.iter().enumerate() {
            let chord = c.chord() as usize;
            if owner[chord] != NONE {
                return Err(WrapError::NotTriangular {
                    cycle: t,
                    edge: chord,
                });
            }
            owner[chord] = t;
        }
        for (t, c) in cycles.iter().enumerate() {
            for term in &c.terms[1..] {
                let o = owner[term.edge as usize];
                if o != NONE && o >= t {
                    return Err(WrapError::NotTriangular {
                        cycle: t,
                        edge: term.edge as usize,
                    });
                }
            }
        }
        Ok(Self { edges })
    }

    /// `k = [0; C_L⁻¹ γ]`: zero on tree edges, forward substitution on the chords.
    pub fn wraps(&self, cycles: &[Cycle], gamma: &[i64]) -> Result<Vec<i64>, WrapError> {
        if gamma.len() != cycles.len() {
            return Err(WrapError::Length {
                got: gamma.len(),
                want: cycles.len(),
            });
        }
        let mut k = vec![0i64; self.edges];
        for (c, &g) in cycles.iter().zip(gamma) {
            let rest: i64 = c.terms[1..]
                .iter()
                .map(|t| i64::from(t.sign) * k[t.edge as usize])
                .sum();
            k[c.chord() as usize] = g - rest;
        }
        Ok(k)
    }
}

/// `γ = C k`.
pub fn gamma_of(cycles: &[Cycle], k: &[i64]) -> Vec<i64> {
    cycles
        .iter()
        .map(|c| {
            c.terms
                .iter()
                .map(|t| i64::from(t.sign) * k[t.edge as usize])
                .sum()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cycles::{BasisKind, CycleBasis};
    use crate::sim::{SimConfig, simulate};

    #[test]
    fn wraps_reproduce_gamma_and_truth() {
        let w = simulate(&SimConfig::new(250, 11)).unwrap();
        for kind in [BasisKind::Odometric, BasisKind::Mst, BasisKind::Incremental] {
            let b = CycleBasis::build(&w.graph, kind);
            let solver = WrapSolver::new(&b.cycles, w.graph.edge_count()).unwrap();
            let gamma = gamma_of(&b.cycles, &w.truth.wraps);
            let k = solver.wraps(&b.cycles, &gamma).unwrap();
            assert_eq!(gamma_of(&b.cycles, &k), gamma, "{kind:?}");
        }
    }

    #[test]
    fn non_triangular_basis_is_refused() {
        use crate::cycles::IncrementalBasis;
        // Triangle 0→1→2 closed by 2→0 (cycle 0), then a parallel 0→2 whose cheapest path
        // back is the chord 2→0 of cycle 0.
        let mut inc = IncrementalBasis::new();
        let mut cycles: Vec<_> = [(0, 1), (1, 2), (2, 0), (0, 2)]
            .iter()
            .filter_map(|&(a, b)| inc.add_edge(a, b, 1.0))
            .collect();
        assert_eq!(cycles.len(), 2);
        assert!(cycles[1].terms.iter().any(|t| t.edge == 2));
        assert!(WrapSolver::new(&cycles, 4).is_ok());
        cycles.swap(0, 1);
        assert!(matches!(
            WrapSolver::new(&cycles, 4),
            Err(WrapError::NotTriangular { cycle: 0, edge: 2 })
        ));
        let solver = WrapSolver::new(&cycles[1..], 4).unwrap();
        assert!(matches!(
            solver.wraps(&cycles[1..], &[1, 2]),
            Err(WrapError::Length { got: 2, want: 1 })
        ));
    }
}
