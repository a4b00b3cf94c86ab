//! What a replay reuses from the estimator it replaces: the cycle each quarantined loop
//! closure failed on when it arrived.
//!
//! An eviction rebuilds the estimator by replaying every arrival without the evicted edge, and
//! every loop closure quarantined so far arrives again: with the evicted edge gone it may pass
//! now. Its cycle is the least-σ² path between its ends in the graph of that moment, a search
//! that crosses the map for a random false edge (on M3500 + 1000 of them, about 1 400 nodes
//! settled per arrival, most of a replay's time). The search need not be run again when the
//! replay's graph at that arrival is a **subgraph** of the replaced estimator's graph at the same
//! arrival (it only lacks edges: evicted, or kept in quarantine) and still holds every edge of
//! the path found then: that path was a least-σ² path in the larger graph, so it is one in the
//! smaller. The replay's graph stops being a subgraph at the first edge it takes in that the
//! replaced estimator had not taken in by then (a loop closure that failed through the evicted
//! edge passes now); from there on every arrival searches as usual. Among paths of equal σ²
//! the one reused may differ from the one a search would pick: the test and the basis are as
//! valid, and the run as deterministic. So may a path the aimed search found (past a few
//! hundred settled nodes, a path at most twice the least σ², module `cycles`): reused, it is
//! still within that factor of the least path of the smaller graph (whose least is no
//! shorter), as a new search's would be.

use std::collections::BTreeMap;
use std::sync::Arc;

use crate::cycles::{Cycle, SignedEdge};

/// No entry (an input not in the graph).
const NONE: u32 = u32::MAX;

/// What an estimator records for a replay of itself.
#[derive(Clone, Debug, Default)]
pub(crate) struct Paths {
    /// For each input index: the arrival count at which it entered the graph (NONE: not in
    /// it) and its graph edge index.
    entered: Vec<(u32, u32)>,
    /// The cycle each quarantined loop closure failed on at its arrival, by input index; its
    /// path's edges by input index (term 0, the chord, is renumbered when it is reused).
    /// Shared: the copies of the estimator a checkpoint takes ([`super::checkpoint`]) copy
    /// pointers, not the paths (a random false edge's crosses the map: hundreds of edges).
    failed: BTreeMap<usize, Arc<Cycle>>,
}

impl Paths {
    /// Room for `inputs` more inputs without growing.
    pub fn try_reserve(&mut self, inputs: usize) -> Result<(), std::collections::TryReserveError> {
        self.entered.try_reserve(inputs)?;
        Ok(())
    }

    /// Input `input` entered the graph as edge `edge` when `at` arrivals had been given.
    pub fn entered(&mut self, input: usize, edge: usize, at: usize) {
        if self.entered.len() <= input {
            self.entered.resize(input + 1, (NONE, NONE));
        }
        self.entered[input] = (at as u32, edge as u32);
        self.failed.remove(&input);
    }

    /// The graph edge of input `input`, if it is in the graph.
    fn edge_of(&self, input: usize) -> Option<u32> {
        self.entered
            .get(input)
            .map(|&(_, e)| e)
            .filter(|&e| e != NONE)
    }

    /// Loop closure `input` failed on `cycle` at its arrival; `input_of` maps graph edges to
    /// input indices.
    pub fn failed(&mut self, input: usize, cycle: &Cycle, input_of: &[u32]) {
        let mut by_input = cycle.clone();
        for t in &mut by_input.terms[1..] {
            t.edge = input_of[t.edge as usize];
        }
        self.failed.insert(input, Arc::new(by_input));
    }
}

/// The replaced estimator's [`Paths`] as a replay goes (see the module docs).
#[derive(Debug)]
pub(crate) struct Hints {
    replaced: Paths,
    /// The replay's graph took in an edge the replaced one had not by then.
    diverged: bool,
}

impl Hints {
    /// Hints from the estimator being replaced.
    pub fn new(replaced: Paths) -> Self {
        Self {
            replaced,
            diverged: false,
        }
    }

    /// The replay takes input `input` into its graph when `at` arrivals have been given.
    pub fn entered(&mut self, input: usize, at: usize) {
        let then = self.replaced.entered.get(input).map_or(NONE, |&(t, _)| t);
        if then == NONE || then as usize > at {
            self.diverged = true;
        }
    }

    /// The cycle loop closure `input` failed on at its arrival in the replaced estimator, with
    /// the replay's edge indices (`own`) and its chord numbered `chord`, while the replay's
    /// graph is a subgraph of the replaced one's and holds every edge of its path.
    pub fn cycle(&self, input: usize, own: &Paths, chord: usize) -> Option<Cycle> {
        if self.diverged {
            return None;
        }
        let mut cycle = Cycle::clone(self.replaced.failed.get(&input)?);
        cycle.terms[0] = SignedEdge::new(chord, true);
        for t in &mut cycle.terms[1..] {
            t.edge = own.edge_of(t.edge as usize)?;
        }
        Some(cycle)
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::graph::{Edge, Information};
    use crate::sim::{OutlierConfig, OutlierKind, SimConfig, inject_outliers, simulate};

    fn cycle(edges: &[u32]) -> Cycle {
        Cycle {
            terms: edges
                .iter()
                .map(|&e| SignedEdge { edge: e, sign: 1 })
                .collect(),
        }
    }

    #[test]
    fn a_failed_path_is_reused_while_the_replay_only_lacks_edges() {
        // Replaced estimator: inputs 0, 1, 2 entered at their arrivals as edges 0, 1, 2;
        // input 3 failed on the cycle [chord, edge 0, edge 2]; input 4 was readmitted at
        // arrival 6.
        let mut replaced = Paths::default();
        for i in 0..3 {
            replaced.entered(i, i, i);
        }
        replaced.failed(3, &cycle(&[3, 0, 2]), &[0, 1, 2]);
        replaced.entered(4, 3, 6);
        let mut hints = Hints::new(replaced);
        // The replay lacks input 1 (evicted): inputs 0 and 2 are its edges 0 and 1.
        let mut own = Paths::default();
        for (input, edge) in [(0, 0), (2, 1)] {
            hints.entered(input, input);
            own.entered(input, edge, input);
        }
        let reused = hints
            .cycle(3, &own, 2)
            .expect("a subgraph holding the path");
        assert_eq!(reused.terms.as_slice(), cycle(&[2, 0, 1]).terms.as_slice());
        // A path through an edge the replay lacks is not reused.
        let mut without_2 = Paths::default();
        without_2.entered(0, 0, 0);
        assert!(hints.cycle(3, &without_2, 1).is_none());
        // Input 4 taken in at arrival 6 as before: still a subgraph; earlier, not.
        hints.entered(4, 6);
        assert!(hints.cycle(3, &own, 2).is_some());
        hints.entered(4, 5);
        assert!(hints.cycle(3, &own, 2).is_none());
    }

    /// A simulated 1 000-pose world (seed `700 + seed`) with 40 random false loop closures and
    /// every edge's declared noise 16 times too wide, so that evictions happen; with `own`,
    /// each edge's noise is scaled by its own factor in [1, 1.01) as well (unique least-σ²
    /// paths). The edges in file order, and the false edges' indices.
    pub(crate) fn wide_outlier_world(seed: u64, own: bool) -> (Vec<Edge>, Vec<usize>) {
        let world = simulate(&SimConfig::new(1000, 700 + seed)).unwrap();
        let bad = inject_outliers(
            &world.graph,
            &OutlierConfig {
                count: 40,
                kind: OutlierKind::Random,
                seed,
            },
        )
        .unwrap();
        let mut state = seed;
        let edges = (bad.graph.edges().iter())
            .map(|e| {
                state = state
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                let factor = if own {
                    1.0 + (state >> 11) as f64 / (1u64 << 53) as f64 / 100.0
                } else {
                    1.0
                };
                let wide = Information(e.information().0.map(|v| v / (16.0 * factor)));
                Edge::new(e.from(), e.to(), e.measurement(), wide).unwrap()
            })
            .collect();
        (edges, bad.false_edges.iter().map(|f| f.edge).collect())
    }

    /// Streams whose evictions replay (simulated worlds, declared noise 16× too wide, 40 random
    /// false loop closures) decide the same, to the bit, whether their replays reuse the
    /// failed paths or search every cycle again — where the least-σ² path is unique: every
    /// edge's declared noise is scaled by its own factor in [1, 1.01) (the simulator gives
    /// every edge the same noise, so paths of equal σ² abound, and which of them a search picks
    /// depends on how it searches: module docs) and every arrival's search exact (the aimed
    /// one takes a path at most twice the least, which a search of the replay's smaller graph
    /// need not repeat: reusing it keeps that bound, but not the bits).
    #[test]
    fn a_replay_that_reuses_paths_decides_as_one_that_searches() {
        use crate::online::{OnlineConfig, OnlineEstimator};
        crate::cycles::EXACT_ARRIVAL_SEARCHES.with(|e| e.set(true));
        let mut replays = 0;
        for seed in 0..4u64 {
            let (edges, _) = wide_outlier_world(seed, true);
            let run = |reuse: bool| {
                let mut est = OnlineEstimator::new(OnlineConfig::default()).unwrap();
                est.reuse_paths = reuse;
                for edge in crate::online::robot_order(&edges) {
                    est.add_edge(edge).unwrap();
                }
                est
            };
            let (mut reused, mut searched) = (run(true), run(false));
            replays += usize::from(reused.replay_work > 0);
            assert_eq!(reused.replay_work, searched.replay_work, "seed {seed}");
            let bits = |est: &OnlineEstimator| -> Vec<(usize, u64)> {
                (est.rejected().iter())
                    .map(|r| (r.edge, r.statistic.to_bits()))
                    .collect()
            };
            assert_eq!(bits(&reused), bits(&searched), "seed {seed}");
            assert_eq!(reused.gamma(), searched.gamma(), "seed {seed}");
            let theta = |est: &mut OnlineEstimator| -> Vec<u64> {
                est.orientations()
                    .unwrap()
                    .iter()
                    .map(|t| t.to_bits())
                    .collect()
            };
            assert_eq!(theta(&mut reused), theta(&mut searched), "seed {seed}");
        }
        assert!(
            replays > 0,
            "no world evicted anything: the test would test nothing"
        );
    }
}
