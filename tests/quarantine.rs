//! Online quarantine of false loop closures (`OnlineConfig::quarantine`, method §11): a loop
//! closure whose cycle fails its angle or SE(2) translation test at arrival is kept out of the
//! graph, the basis, the conditioning and the estimate, listed by `rejected()`, and re-tested
//! later.

use so2lin::graph::{Edge, PoseGraph};
use so2lin::online::{OnlineConfig, OnlineEstimator, StepKind};
use so2lin::screening::ScreeningConfig;
use so2lin::sim::{OutlierConfig, OutlierKind, SimConfig, inject_outliers, simulate};

fn run(edges: &[Edge], config: OnlineConfig) -> (OnlineEstimator, Vec<so2lin::online::Step>) {
    let mut est = OnlineEstimator::new(config).unwrap();
    let steps = edges.iter().map(|e| est.add_edge(*e).unwrap()).collect();
    (est, steps)
}

/// Orientations, exact poses, γ and wraps of a run.
type Observed = (Vec<f64>, Vec<(f64, f64, f64)>, Vec<i64>, Vec<i64>);

/// Everything a caller reads from a run: orientations, exact poses, γ, wraps.
fn observe(est: &mut OnlineEstimator) -> Observed {
    let theta = est.orientations().unwrap().to_vec();
    let poses = est
        .poses()
        .unwrap()
        .iter()
        .map(|p| (p.x, p.y, p.theta))
        .collect();
    (theta, poses, est.gamma(), est.wraps().unwrap())
}

/// Random false loop closures on simulated worlds: the quarantined set is the false set in
/// (nearly) every world, and when it is exactly the false set the run is **bit for bit** the
/// run of the clean edges alone — nothing of a quarantined edge reached the basis, the
/// conditioning or the estimate.
#[test]
fn quarantined_false_edges_leave_no_trace() {
    let (mut caught, mut injected, mut wrong, mut exact) = (0, 0, 0, 0);
    for seed in 0..12u64 {
        let world = simulate(&SimConfig::new(600, 40 + seed)).unwrap();
        let bad = inject_outliers(
            &world.graph,
            &OutlierConfig {
                count: 10,
                kind: OutlierKind::Random,
                seed,
            },
        )
        .unwrap();
        let (mut est, steps) = run(bad.graph.edges(), OnlineConfig::default());
        let rejected: Vec<usize> = est.rejected().iter().map(|r| r.edge).collect();
        let falses: Vec<usize> = bad.false_edges.iter().map(|f| f.edge).collect();
        injected += falses.len();
        caught += rejected.iter().filter(|e| falses.contains(e)).count();
        wrong += rejected.iter().filter(|e| !falses.contains(e)).count();
        // Bookkeeping: every input edge is in the graph or in quarantine, once.
        assert_eq!(est.graph().edge_count() + rejected.len(), est.arrivals());
        let mut seen: Vec<usize> = (0..est.graph().edge_count())
            .map(|e| est.input_index(e).unwrap())
            .chain(rejected.iter().copied())
            .collect();
        seen.sort_unstable();
        assert_eq!(seen, (0..est.arrivals()).collect::<Vec<_>>());
        // Steps report what rejected() holds.
        let q: usize = steps.iter().map(|s| s.quarantined.len()).sum();
        let r: usize = steps.iter().map(|s| s.readmitted.len()).sum();
        assert_eq!(q - r, rejected.len(), "seed {seed}");
        // A quarantined arrival is listed first; an eviction at the same step (and what its
        // rebuild quarantined) follows.
        for s in &steps {
            if s.kind == StepKind::Quarantined {
                assert_eq!(s.quarantined[0].edge, s.edge);
            }
            for q in &s.quarantined {
                assert!(q.statistic > q.threshold, "{q:?}");
            }
        }
        if rejected == falses && r == 0 {
            exact += 1;
            let clean: Vec<Edge> = bad
                .graph
                .edges()
                .iter()
                .enumerate()
                .filter(|(e, _)| !bad.is_false(*e))
                .map(|(_, e)| *e)
                .collect();
            let (mut reference, _) = run(&clean, OnlineConfig::default());
            assert_eq!(
                observe(&mut est),
                observe(&mut reference),
                "seed {seed}: the quarantined run differs from the clean run"
            );
            assert_eq!(est.counters().cycles, reference.counters().cycles);
        }
    }
    println!("caught {caught}/{injected}, {wrong} genuine quarantined, {exact}/12 exact");
    assert!(caught * 100 >= injected * 90, "recall {caught}/{injected}");
    assert!(wrong <= 1, "{wrong} genuine edges quarantined");
    assert!(
        exact >= 6,
        "only {exact} runs quarantined exactly the false edges"
    );
}

/// Without quarantine the same false edges are added (the old behaviour), and the estimate is
/// corrupted: the check above could fail.
#[test]
fn without_quarantine_false_edges_are_added() {
    let world = simulate(&SimConfig::new(600, 41)).unwrap();
    let bad = inject_outliers(
        &world.graph,
        &OutlierConfig {
            count: 10,
            kind: OutlierKind::Random,
            seed: 1,
        },
    )
    .unwrap();
    let config = OnlineConfig {
        quarantine: false,
        ..OnlineConfig::default()
    };
    let (est, steps) = run(bad.graph.edges(), config);
    assert!(est.rejected().is_empty());
    assert_eq!(est.graph().edge_count(), bad.graph.edge_count());
    assert!(steps.iter().all(|s| s.quarantined.is_empty()));
}

/// Re-admission: at a loose per-cycle level (α = 0.05, not family-wise) many genuine loop
/// closures fail at arrival by chance; of those re-tested by the end (the cycles have doubled
/// since), most come back.
/// A re-admitted edge is in the graph and no longer in `rejected()`.
#[test]
fn genuine_edges_quarantined_by_chance_are_readmitted() {
    let world = simulate(&SimConfig::new(1500, 7)).unwrap();
    let config = OnlineConfig {
        screening: ScreeningConfig {
            alpha: 0.05,
            ..ScreeningConfig::default()
        }
        .per_cycle(),
        quarantine: true,
        evict: false,
        ..OnlineConfig::default()
    };
    // Step by step, with the number of cycles closed when each edge was quarantined.
    let mut est = OnlineEstimator::new(config).unwrap();
    let mut steps = Vec::new();
    let mut held_at = Vec::new();
    for e in world.graph.edges() {
        let s = est.add_edge(*e).unwrap();
        for r in &s.quarantined {
            held_at.push((r.edge, est.counters().cycles));
        }
        steps.push(s);
    }
    let readmitted: Vec<usize> = steps.iter().flat_map(|s| s.readmitted.clone()).collect();
    // Re-tested by the end: quarantined when the cycles were at most half (and 32 fewer than)
    // the final count.
    let last = est.counters().cycles;
    let due: Vec<usize> = held_at
        .iter()
        .filter(|&&(_, c)| 2 * c <= last && c + 32 <= last)
        .map(|&(e, _)| e)
        .collect();
    let back = due.iter().filter(|e| readmitted.contains(e)).count();
    println!(
        "quarantined {}, re-tested by the end {}, re-admitted {} of them ({} in all), left {}",
        held_at.len(),
        due.len(),
        back,
        readmitted.len(),
        est.rejected().len()
    );
    assert!(due.len() > 20, "{}", due.len());
    assert!(back * 2 > due.len(), "{back} of {}", due.len());
    assert_eq!(est.counters().readmitted, readmitted.len());
    let in_graph: Vec<usize> = (0..est.graph().edge_count())
        .map(|e| est.input_index(e).unwrap())
        .collect();
    for e in &readmitted {
        assert!(
            in_graph.contains(e),
            "re-admitted edge {e} not in the graph"
        );
        assert!(est.rejected().iter().all(|r| r.edge != *e));
    }
    // The estimator's graph is a valid graph of the accepted edges.
    let mut g = PoseGraph::new();
    for e in est.graph().edges() {
        g.add_edge(*e, so2lin::NodePolicy::CreateUnknown).unwrap();
    }
    assert_eq!(g.node_count(), est.graph().node_count());
}

/// The graph with every information matrix divided by `factor` (declared variances `factor`
/// times wider than the noise drawn), as in the benchmark files (method §11: 6–22× too wide).
fn declared_wider(g: &PoseGraph, factor: f64) -> PoseGraph {
    let mut out = PoseGraph::new();
    for e in g.edges() {
        let info = so2lin::graph::Information(e.information().0.map(|v| v / factor));
        let wide = Edge::new(e.from(), e.to(), e.measurement(), info).unwrap();
        out.add_edge(wide, so2lin::NodePolicy::CreateUnknown)
            .unwrap();
    }
    out
}

/// Declared noise 16× wider than the data's in variance and random false loop closures from
/// the first cycles on (before 50 cycles no noise scale is estimated, and a false edge
/// closing a long cycle passes both tests at the declared noise): the angle noise scale
/// sharpens the angle test and the translation closures' heading noise. With the defaults
/// (evictions by the path-triggered examination on) the pooled precision and recall are
/// 1.000 and 0.947 (2026-12-04, thirteenth session, since the translation closure is tested
/// at both ends of its chord: false edges accepted per world 1, 11, 1, 0, 3, 0, 1, 0); 0.979
/// and 0.872 before that (seeds 1 and 5 accepted 13 and 20 of 40: false edges accepted among
/// the first cycles widened both noise scales, the angle scale to 1), 0.942 and 0.716 before
/// the examination's angle test, 0.907 / 0.641 without evictions. The recall is still short
/// of the 0.95 (seed 1). This guards what is reached, and a clean copy of each world
/// quarantines nothing.
#[test]
fn random_false_edges_are_caught_when_the_declared_noise_is_too_wide() {
    let config = OnlineConfig::default();
    let (mut caught, mut flagged, mut injected) = (0, 0, 0);
    for seed in 0..8u64 {
        let world = simulate(&SimConfig::new(1000, 700 + seed)).unwrap();
        let wide = declared_wider(&world.graph, 16.0);
        let (clean, _) = run(wide.edges(), config);
        assert!(
            clean.rejected().is_empty(),
            "seed {seed}: {:?}",
            clean.rejected()
        );
        // The scales see the 16× too-wide declared variances: the translation scale near
        // 1/16, the angle scale at its floor.
        let s = clean.noise_scales();
        println!("seed {seed}: noise scales {s:?}");
        assert!(
            s.translation_samples >= 50 && s.angle_samples >= 50,
            "{s:?}"
        );
        assert!(s.translation > 1.0 / 64.0 && s.translation < 0.25, "{s:?}");
        assert_eq!(s.angle, so2lin::closure::ANGLE_SCALE_FLOOR, "{s:?}");
        let bad = inject_outliers(
            &wide,
            &OutlierConfig {
                count: 40,
                kind: OutlierKind::Random,
                seed,
            },
        )
        .unwrap();
        let (est, _) = run(bad.graph.edges(), config);
        let rejected: Vec<usize> = est.rejected().iter().map(|r| r.edge).collect();
        let tp = rejected.iter().filter(|&&e| bad.is_false(e)).count();
        println!(
            "seed {seed}: {tp} of {} false edges quarantined, {} genuine",
            bad.false_edges.len(),
            rejected.len() - tp
        );
        caught += tp;
        flagged += rejected.len();
        injected += bad.false_edges.len();
    }
    let (precision, recall) = (
        caught as f64 / flagged as f64,
        caught as f64 / injected as f64,
    );
    println!("precision {precision:.3}, recall {recall:.3}");
    assert!(precision >= 0.95 && recall >= 0.85, "{precision} {recall}");
}
