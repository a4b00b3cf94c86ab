//! From cycle integers γ to edge wraps k (method [§5](crate::method#5-wraps-and-orientations)).
//!
//! Order the edges as tree edges then chords, `C = [C_T C_L]`; then `k = [0; C_L⁻¹ γ]` solves
//! `C k = γ`, and every solution gives the same orientations modulo 2π (paper Prop. 1).
//! `C_L⁻¹ γ` is integral for every integer γ iff `|det C_L| = 1`, and `|det C_L|` is the same
//! for every spanning tree (see `cycles::integral`).
//!
//! **Triangular bases** (fundamental, incremental, and every basis arranged by
//! [`CycleBasis::ordered`](crate::cycles::CycleBasis::ordered) that peels completely): cycle t
//! holds its chord as `terms[0]` with sign +1 and otherwise only tree edges and chords of
//! earlier cycles, so `C_L` is unit lower triangular and
//!
//! ```text
//! k_{chord(t)} = γ_t − Σ_{e ∈ c_t, e ≠ chord(t)} (±1) k_e        (forward substitution),
//! ```
//!
//! integral by construction.
//!
//! **Any other basis** (e.g. a minimum basis with a non-triangular core): the cycles are
//! peeled into a core and a triangular part; the core is eliminated exactly over the integers
//! (unimodular row operations), which gives `|det C_L|`; k is solved on the core's pivot
//! columns, then by forward substitution through the peeled cycles (dividing by the ±1 sign of
//! each designated edge). When `|det C_L| > 1`, a γ whose k would be fractional is reported as
//! [`WrapError::Fractional`], never rounded.

use crate::cycles::Cycle;
use crate::cycles::integral::{Designated, IntegerError, IntegerLu, peel};

/// Why no wraps.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum WrapError {
    /// The cycles are not linearly independent.
    #[error("the cycles are linearly dependent (cycle {cycle}): not a basis")]
    Dependent {
        /// A cycle of the dependent set.
        cycle: usize,
    },
    /// The exact elimination, or the wraps of a γ, overflowed 64-bit integers.
    #[error("integer overflow computing wraps (64-bit integers)")]
    Overflow,
    /// γ has no integer k (the basis is not integral).
    #[error("C k = γ has no integer solution (cycle {cycle}): the basis is not integral")]
    Fractional {
        /// The cycle whose equation did not divide exactly.
        cycle: usize,
    },
    /// A cycle is empty or names an edge outside `0..edges`.
    #[error("cycle {cycle} is empty or names an edge outside 0..{edges}")]
    Edge {
        /// The cycle.
        cycle: usize,
        /// Number of edges.
        edges: usize,
    },
    /// The cycles given to [`WrapSolver::wraps`] are not as many as those it analysed.
    #[error("{got} cycles given, the solver analysed {want}")]
    Cycles {
        /// Cycles given.
        got: usize,
        /// Cycles analysed.
        want: usize,
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

impl From<IntegerError> for WrapError {
    fn from(e: IntegerError) -> Self {
        match e {
            IntegerError::Dependent { cycle } => Self::Dependent { cycle },
            IntegerError::Overflow => Self::Overflow,
            IntegerError::Fractional { cycle } => Self::Fractional { cycle },
        }
    }
}

/// The non-triangular part of a general basis.
#[derive(Clone, Debug)]
struct General {
    core: IntegerLu,
    peeled: Vec<Designated>,
}

/// Recovers k from γ for a basis: forward substitution when it is triangular as given, the
/// exact peel-and-eliminate solver otherwise.
#[derive(Clone, Debug)]
pub struct WrapSolver {
    edges: usize,
    cycles: usize,
    general: Option<General>,
}

/// Every cycle non-empty, every edge in `0..edges`.
fn check_edges(cycles: &[Cycle], edges: usize) -> Result<(), WrapError> {
    match cycles
        .iter()
        .position(|c| c.terms.is_empty() || c.terms.iter().any(|t| t.edge as usize >= edges))
    {
        Some(cycle) => Err(WrapError::Edge { cycle, edges }),
        None => Ok(()),
    }
}

/// Whether `cycles` are triangular as given: distinct chords `terms[0]` with sign +1, and no
/// cycle uses the chord of a later one.
fn is_triangular(cycles: &[Cycle], edges: usize) -> bool {
    const NONE: usize = usize::MAX;
    let mut owner = vec![NONE; edges];
    for (t, c) in cycles.iter().enumerate() {
        let Some(first) = c.terms.first() else {
            return false;
        };
        let chord = first.edge as usize;
        if first.sign != 1 || owner[chord] != NONE {
            return false;
        }
        owner[chord] = t;
    }
    cycles.iter().enumerate().all(|(t, c)| {
        c.terms[1..].iter().all(|term| {
            let o = owner[term.edge as usize];
            o == NONE || o < t
        })
    })
}

impl WrapSolver {
    /// Analyse `cycles` over `edges` edges: fails only if they are not independent (or the
    /// exact elimination overflows).
    pub fn new(cycles: &[Cycle], edges: usize) -> Result<Self, WrapError> {
        check_edges(cycles, edges)?;
        let general = if is_triangular(cycles, edges) {
            None
        } else {
            let (core, peeled) = peel(cycles, edges);
            let core = IntegerLu::new(cycles, &core)?;
            Some(General { core, peeled })
        };
        Ok(Self {
            edges,
            cycles: cycles.len(),
            general,
        })
    }

    /// `|det C_L|` (the same for every spanning tree): 1 for an integral basis.
    pub fn abs_det(&self) -> u128 {
        self.general.as_ref().map_or(1, |g| g.core.abs_det())
    }

    /// Whether every integer γ has integer wraps (`|det C_L| = 1`).
    pub fn is_integral(&self) -> bool {
        self.abs_det() == 1
    }

    /// Number of cycles in the non-triangular core (0 when every cycle peels off).
    pub fn core_len(&self) -> usize {
        self.general.as_ref().map_or(0, |g| g.core.len())
    }

    /// Whether the basis is triangular as given (forward substitution only).
    pub fn is_triangular(&self) -> bool {
        self.general.is_none()
    }

    /// An integer k with `C k = γ`: `k = [0; C_L⁻¹ γ]` for the basis' chords (tree edges 0).
    /// `cycles` must be the cycles the solver was built from.
    pub fn wraps(&self, cycles: &[Cycle], gamma: &[i64]) -> Result<Vec<i64>, WrapError> {
        if cycles.len() != self.cycles {
            return Err(WrapError::Cycles {
                got: cycles.len(),
                want: self.cycles,
            });
        }
        check_edges(cycles, self.edges)?;
        if gamma.len() != cycles.len() {
            return Err(WrapError::Length {
                got: gamma.len(),
                want: cycles.len(),
            });
        }
        let mut k = vec![0i64; self.edges];
        let Some(general) = &self.general else {
            for (c, &g) in cycles.iter().zip(gamma) {
                let rest = signed_sum(c.terms[1..].iter(), &k)?;
                k[c.chord() as usize] = g.checked_sub(rest).ok_or(WrapError::Overflow)?;
            }
            return Ok(k);
        };
        general.core.solve(gamma, &mut k)?;
        for d in &general.peeled {
            let c = &cycles[d.cycle as usize];
            let rest = signed_sum(c.terms.iter().filter(|t| t.edge != d.edge), &k)?;
            // sign = ±1, so dividing is multiplying.
            let v = gamma[d.cycle as usize]
                .checked_sub(rest)
                .ok_or(WrapError::Overflow)?;
            k[d.edge as usize] = if d.sign < 0 {
                v.checked_neg().ok_or(WrapError::Overflow)?
            } else {
                v
            };
        }
        Ok(k)
    }
}

/// `Σ ±k_e` over `terms`, checked for overflow.
fn signed_sum<'a>(
    mut terms: impl Iterator<Item = &'a crate::cycles::SignedEdge>,
    k: &[i64],
) -> Result<i64, WrapError> {
    terms.try_fold(0i64, |acc, t| {
        let x = k[t.edge as usize];
        if t.sign < 0 {
            acc.checked_sub(x)
        } else {
            acc.checked_add(x)
        }
        .ok_or(WrapError::Overflow)
    })
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
    fn reordered_basis_takes_the_general_path() {
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
        assert!(WrapSolver::new(&cycles, 4).unwrap().is_triangular());
        cycles.swap(0, 1);
        let solver = WrapSolver::new(&cycles, 4).unwrap();
        assert!(!solver.is_triangular());
        assert!(solver.is_integral());
        for gamma in [[1, 2], [-3, 0], [0, 5]] {
            let k = solver.wraps(&cycles, &gamma).unwrap();
            assert_eq!(gamma_of(&cycles, &k), gamma);
        }
        assert!(matches!(
            solver.wraps(&cycles, &[1]),
            Err(WrapError::Length { got: 1, want: 2 })
        ));
        // A dependent set is refused.
        let twice = vec![cycles[0].clone(), cycles[0].clone()];
        assert!(matches!(
            WrapSolver::new(&twice, 4),
            Err(WrapError::Dependent { .. })
        ));
    }

    #[test]
    fn foreign_cycles_are_errors_not_panics() {
        let w = simulate(&SimConfig::new(60, 2)).unwrap();
        let m = w.graph.edge_count();
        let b = CycleBasis::build(&w.graph, BasisKind::Incremental);
        // An edge beyond the graph.
        assert_eq!(
            WrapSolver::new(&b.cycles, m - 1).err(),
            Some(WrapError::Edge {
                cycle: b
                    .cycles
                    .iter()
                    .position(|c| c.terms.iter().any(|t| t.edge as usize == m - 1))
                    .unwrap(),
                edges: m - 1
            })
        );
        let solver = WrapSolver::new(&b.cycles, m).unwrap();
        let gamma = vec![0; b.cycles.len()];
        // Fewer cycles than analysed.
        assert_eq!(
            solver.wraps(&b.cycles[1..], &gamma[1..]).err(),
            Some(WrapError::Cycles {
                got: b.cycles.len() - 1,
                want: b.cycles.len()
            })
        );
        // Same count, an edge out of range.
        let mut bad = b.cycles.clone();
        bad[0].terms[0].edge = m as u32;
        assert!(matches!(
            solver.wraps(&bad, &gamma),
            Err(WrapError::Edge { cycle: 0, .. })
        ));
    }
}
