//! The online estimator ends where the batch pipeline ends, and refuses bad input without a
//! trace.

mod common;

use proptest::prelude::*;
use so2lin::batch::{BatchConfig, screen, screen_spending};
use so2lin::cycles::BasisKind;
use so2lin::estimate::OrientationEstimator;
use so2lin::graph::{Edge, Information, NodeId, Pose2, PoseGraph};
use so2lin::io::{ReadOptions, read_graph};
use so2lin::online::{Counters, OnlineConfig, OnlineError, OnlineEstimator};
use so2lin::screening::ScreeningConfig;
use so2lin::sim::{SimConfig, simulate};

/// Stream `edges`, finish, and compare with the batch pipeline on `graph` (same edges, same
/// order, every cycle at the same level: the online α-spending levels when family-wise):
/// identical wraps of the best hypothesis, orientations equal to 1e-9 (both anchored at
/// the batch graph's first node). Returns (online determined, batch determined), or `None` when
/// the online estimator quarantined a loop closure (quarantine is on, as by default: on clean
/// data a genuine edge is quarantined with probability ≤ α, and the two paths then have
/// different bases; callers bound how often).
fn compare(
    name: &str,
    graph: &PoseGraph,
    edges: &[Edge],
    cfg: ScreeningConfig,
) -> Option<(usize, usize)> {
    let batch = screen_spending(
        graph,
        &BatchConfig {
            basis: BasisKind::Incremental,
            screening: cfg,
        },
    )
    .unwrap();
    let mut est = OnlineEstimator::new(OnlineConfig {
        screening: cfg,
        ..OnlineConfig::default()
    })
    .unwrap();
    for e in edges {
        est.add_edge(*e).unwrap();
    }
    if est.counters().quarantined + est.counters().readmitted > 0 {
        println!("{name}: quarantined {:?}", est.rejected());
        return None;
    }
    let online = est.finish().unwrap();
    assert_eq!(
        online.basis.cycles, batch.basis.cycles,
        "{name}: same incremental basis"
    );
    let (hb, ho) = (&batch.hypotheses[0], &online.hypotheses[0]);
    let kb = batch.wraps(hb).unwrap();
    let ko = online.wraps(ho).unwrap();
    assert_eq!(kb, ko, "{name}: wraps of the best hypothesis");
    assert!(
        (hb.chi2 - ho.chi2).abs() <= 1e-6 * hb.chi2.max(1.0),
        "{name}: χ² {} vs {}",
        hb.chi2,
        ho.chi2
    );
    let tb = OrientationEstimator::new(graph).unwrap().orientations(&kb);
    let g = est.graph();
    let to = OrientationEstimator::new(g).unwrap().orientations(&ko);
    let anchor: NodeId = graph.nodes()[0].id;
    let shift = to[g.node_index(anchor).unwrap()];
    for (v, node) in graph.nodes().iter().enumerate() {
        let Some(w) = g.node_index(node.id) else {
            continue;
        };
        assert!(
            (tb[v] - (to[w] - shift)).abs() < 1e-9,
            "{name}: node {} {} vs {}",
            node.id,
            tb[v],
            to[w] - shift
        );
    }
    Some((online.determined, batch.determined))
}

#[test]
#[cfg_attr(
    so2lin_no_datasets,
    ignore = "benchmark datasets not found (set SO2LIN_DATASETS)"
)]
fn datasets_stream_to_the_batch_answer() {
    let Some((dir, names)) = common::dataset_names() else {
        return;
    };
    let mut compared = 0;
    for name in names {
        let path = dir.join(&name);
        let (graph, _) = read_graph(&path, ReadOptions::default()).unwrap();
        if graph.edge_count() > 25_000 {
            continue;
        }
        let edges: Vec<Edge> = common::edges_of(&path);
        assert_eq!(
            edges.as_slice(),
            graph.edges(),
            "{name}: streaming and whole-file reads agree"
        );
        // No loop closure of a clean dataset is quarantined (tests/statistics.rs), except for
        // a while on manhattan.g2o, whose declared angle information is too tight for its
        // measurements (χ²/ℓ = 1.59): two loop closures are quarantined before its angle
        // scale is established and re-admitted after, so they join the basis later there.
        let Some((on, ba)) = compare(&name, &graph, &edges, ScreeningConfig::default()) else {
            assert_eq!(
                name, "manhattan.g2o",
                "{name}: a loop closure was quarantined"
            );
            compared += 1;
            continue;
        };
        // The online path tests each cycle once conditioned on every earlier determination
        // (and re-tests ambiguous ones as determinations arrive), the batch path tests all
        // cycles unconditionally at its first iteration: the sets may differ by a few cycles
        // near the decision boundary; the best hypothesis may not.
        println!("{name}: determined online {on}, batch {ba}");
        compared += 1;
    }
    assert!(compared >= 18, "only {compared} datasets compared");
}

/// σ_θ up to 0.2 rad; above, see `extreme_noise_paths_may_differ_and_online_is_not_worse`.
#[test]
fn simulated_worlds_stream_to_the_batch_answer() {
    let (mut differ, mut quarantined) = (0, 0);
    for seed in 0..120u64 {
        let mut c = SimConfig::new(200 + (seed as usize * 37) % 1300, seed);
        c.sigma_theta = [0.01, 0.05, 0.1, 0.15, 0.2][seed as usize % 5];
        let w = simulate(&c).unwrap();
        match compare(
            &format!("seed {seed}"),
            &w.graph,
            w.graph.edges(),
            ScreeningConfig::default(),
        ) {
            Some((on, ba)) => differ += usize::from(on != ba),
            None => quarantined += 1,
        }
    }
    println!(
        "determined sets of different size in {differ} of 120 worlds; {quarantined} worlds with a quarantined loop closure"
    );
    // Family-wise at α = 0.01 per world: 4 of 120 would be a 1-in-30 event at rate α.
    assert!(
        quarantined <= 4,
        "{quarantined} clean worlds quarantined an edge"
    );
}

/// Why the two paths can end differently at extreme noise. Both make irrevocable per-cycle
/// decisions at level α, but they condition differently: the online path tests each new
/// cycle given every earlier determination (it cannot see the future), the batch path tests
/// every cycle unconditionally at its first iteration. At σ_θ = 0.3 rad (M3500c's level, loops
/// of 4 edges have γ deviations of 0.1) each path occasionally fixes a wrong integer, and not
/// the same one; neither is then exact. This test measures how often, and checks that the
/// online answer is the truth at least as often as the batch one (it conditions on more).
#[test]
fn extreme_noise_paths_may_differ_and_online_is_not_worse() {
    let (mut differ, mut batch_ok, mut online_ok) = (0, 0, 0);
    for seed in 0..60u64 {
        let mut c = SimConfig::new(200 + (seed as usize * 37) % 1300, seed);
        c.sigma_theta = 0.3;
        let w = simulate(&c).unwrap();
        let batch = screen_spending(&w.graph, &BatchConfig::default()).unwrap();
        // The screening paths compared: quarantine off (at σ_θ = 0.3 rad the translation
        // closure of long cycles is far from Gaussian, and a quarantined edge changes the basis).
        let mut est = OnlineEstimator::new(OnlineConfig {
            quarantine: false,
            ..OnlineConfig::default()
        })
        .unwrap();
        for e in w.graph.edges() {
            est.add_edge(*e).unwrap();
        }
        let online = est.finish().unwrap();
        let truth = so2lin::wraps::gamma_of(&batch.basis.cycles, &w.truth.wraps);
        let gb = batch.gamma(&batch.hypotheses[0]);
        let go = online.gamma(&online.hypotheses[0]);
        differ += usize::from(gb != go);
        batch_ok += usize::from(gb == truth);
        online_ok += usize::from(go == truth);
    }
    println!(
        "σ_θ = 0.3: best differs in {differ}/60 worlds; best = truth: batch {batch_ok}, online {online_ok}"
    );
    assert!(
        online_ok >= batch_ok,
        "online {online_ok} < batch {batch_ok}"
    );
}

#[test]
fn paper_preset_and_family_wise_also_agree() {
    let w = simulate(&SimConfig {
        sigma_theta: 0.2,
        ..SimConfig::new(1500, 77)
    })
    .unwrap();
    // The paper's per-cycle level quarantines ~α·ℓ genuine edges: compared without quarantine.
    let paper = ScreeningConfig::paper();
    let batch = screen_spending(
        &w.graph,
        &BatchConfig {
            basis: BasisKind::Incremental,
            screening: paper,
        },
    )
    .unwrap();
    let mut est = OnlineEstimator::new(OnlineConfig {
        screening: paper,
        quarantine: false,
        ..OnlineConfig::default()
    })
    .unwrap();
    for e in w.graph.edges() {
        est.add_edge(*e).unwrap();
    }
    let online = est.finish().unwrap();
    assert_eq!(
        batch.wraps(&batch.hypotheses[0]).unwrap(),
        online.wraps(&online.hypotheses[0]).unwrap()
    );
    // Family-wise: both sides at the online α-spending levels (see `compare`).
    compare(
        "family-wise",
        &w.graph,
        w.graph.edges(),
        ScreeningConfig::default(),
    )
    .expect("nothing quarantined");
}

/// The batch default (Bonferroni over the known ℓ) and the online default (α-spending) are
/// both family-wise; on clean worlds they end at the same best hypothesis.
#[test]
fn bonferroni_batch_and_spending_online_agree_on_clean_worlds() {
    for seed in 0..20u64 {
        let w = simulate(&SimConfig::new(300 + 40 * seed as usize, 500 + seed)).unwrap();
        let batch = screen(&w.graph, &BatchConfig::default()).unwrap();
        let mut est = OnlineEstimator::new(OnlineConfig::default()).unwrap();
        for e in w.graph.edges() {
            est.add_edge(*e).unwrap();
        }
        let online = est.finish().unwrap();
        assert_eq!(
            batch.wraps(&batch.hypotheses[0]).unwrap(),
            online.wraps(&online.hypotheses[0]).unwrap(),
            "seed {seed}"
        );
    }
}

/// Everything a caller can observe.
fn snapshot(est: &mut OnlineEstimator) -> (String, Vec<f64>, Vec<i64>, Vec<usize>, f64) {
    // The read first: the estimate's counters count the work applied, which a read brings up
    // to date.
    let theta = est.orientations().unwrap().to_vec();
    // Whether a step waited for a builder thread is the threads' timing, not an answer.
    let counters = Counters {
        renewal_waits: 0,
        rebuild_waits: 0,
        ..est.counters()
    };
    (
        format!("{counters:?}"),
        theta,
        est.gamma(),
        est.ambiguous(),
        est.success_probability_lower_bound(),
    )
}

fn bad_edge(kind: u8, from: NodeId, to: NodeId) -> Result<so2lin::online::Step, OnlineError> {
    let z = Pose2::new(1.0, 0.0, 0.3);
    let ok = Information::diagonal(100.0, 100.0, 400.0);
    match kind % 5 {
        0 => Err(OnlineError::from(Edge::new(from, from, z, ok).unwrap_err())),
        1 => Err(OnlineError::from(
            Edge::new(from, to, Pose2::new(f64::NAN, 0.0, 0.0), ok).unwrap_err(),
        )),
        2 => Err(OnlineError::from(
            Edge::new(from, to, z, Information::diagonal(1.0, 1.0, -1.0)).unwrap_err(),
        )),
        3 => Err(OnlineError::from(
            Edge::new(
                from,
                to,
                z,
                Information([1.0, 0.0, 0.0, 1.0, 0.0, f64::INFINITY]),
            )
            .unwrap_err(),
        )),
        _ => Err(OnlineError::from(
            Edge::new(from, to, z, Information::diagonal(1.0, 1.0, 0.0)).unwrap_err(),
        )),
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]

    #[test]
    fn rejected_edges_change_nothing(seed in any::<u64>(), poses in 30usize..200,
                                     bad in proptest::collection::vec((any::<u8>(), any::<prop::sample::Index>()), 1..20)) {
        let w = simulate(&SimConfig::new(poses, seed)).unwrap();
        let edges = w.graph.edges();
        let mut clean = OnlineEstimator::new(OnlineConfig::default()).unwrap();
        let mut dirty = OnlineEstimator::new(OnlineConfig::default()).unwrap();
        let mut at: Vec<usize> = bad.iter().map(|(_, i)| i.index(edges.len())).collect();
        at.sort_unstable();
        let mut next_bad = 0;
        for (k, e) in edges.iter().enumerate() {
            while next_bad < at.len() && at[next_bad] == k {
                // Query both at the same moments: cached estimates then share their history.
                let reference = snapshot(&mut clean);
                let before = snapshot(&mut dirty);
                prop_assert_eq!(&before, &reference);
                let (kind, _) = bad[next_bad];
                // Through the estimator's own validating entry points.
                let r = match kind % 5 {
                    0 => dirty.add_measurement(e.from(), e.from(), e.measurement(), 0.1, 0.1),
                    1 => dirty.add_measurement(e.from(), e.to(), Pose2::new(0.0, f64::INFINITY, 0.0), 0.1, 0.1),
                    2 => dirty.add_measurement(e.from(), e.to(), e.measurement(), 0.1, 0.0),
                    3 => dirty.add_measurement_info(e.from(), e.to(), e.measurement(), Information::diagonal(1.0, 1.0, f64::NAN)),
                    _ => bad_edge(kind, e.from(), e.to()),
                };
                prop_assert!(r.is_err());
                prop_assert_eq!(snapshot(&mut dirty), before);
                next_bad += 1;
            }
            prop_assert_eq!(clean.add_edge(*e).unwrap(), dirty.add_edge(*e).unwrap());
        }
        prop_assert_eq!(snapshot(&mut clean), snapshot(&mut dirty));
    }
}

#[test]
fn odometry_extends_the_cached_estimate_exactly() {
    let w = simulate(&SimConfig::new(400, 12)).unwrap();
    let mut est = OnlineEstimator::new(OnlineConfig::default()).unwrap();
    for e in w.graph.edges() {
        est.add_edge(*e).unwrap();
        if e.is_odometric() {
            // Cached O(1) extension versus a fresh solve of the same state.
            let cached = est.orientation(e.to()).unwrap().unwrap();
            let k = est.wraps().unwrap();
            let fresh = OrientationEstimator::new(est.graph())
                .unwrap()
                .orientations(&k);
            let v = est.graph().node_index(e.to()).unwrap();
            assert!((cached - fresh[v]).abs() < 1e-9, "{cached} vs {}", fresh[v]);
        }
    }
}

#[test]
fn components_join_and_unknown_nodes_are_created() {
    // The translations below do not close around the loop (only the angles do): without
    // quarantine, so that the loop closure is added whatever its translation.
    let mut est = OnlineEstimator::new(OnlineConfig {
        quarantine: false,
        ..OnlineConfig::default()
    })
    .unwrap();
    let z = |t: f64| Pose2::new(1.0, 0.0, t);
    // Two separate chains with sparse ids, then a bridge, then a loop.
    est.add_measurement(1000, 7, z(0.5), 0.1, 0.01).unwrap();
    est.add_measurement(42, 99, z(-0.2), 0.1, 0.01).unwrap();
    assert_eq!(est.orientation(99).unwrap(), Some(-0.2));
    let s = est.add_measurement(7, 42, z(0.1), 0.1, 0.01).unwrap();
    assert!(matches!(
        s.kind,
        so2lin::online::StepKind::Tree {
            new_node: false,
            joined_components: true
        }
    ));
    let s = est.add_measurement(99, 1000, z(-0.4), 0.1, 0.01).unwrap();
    let so2lin::online::StepKind::Cycle(c) = s.kind else {
        panic!("expected a cycle")
    };
    assert_eq!(c.candidates.single(), Some(0));
    assert_eq!(est.orientation(12345).unwrap(), None);
    // 0.5 + 0.1 − 0.2 − 0.4 = 0: consistent loop; θ_99 = 0.5 + 0.1 − 0.2 from the anchor 1000.
    let t = est.orientation(99).unwrap().unwrap();
    assert!((t - 0.4).abs() < 1e-9, "{t}");
    assert!(est.variance(99).unwrap().unwrap() > 0.0);
}
