//! The outlier benchmark (METHOD.md §11): false loop closures injected by the Vertigo protocol
//! (`sim::inject_outliers`, `so2lin simulate --outliers`, `so2lin inject`), and the robust
//! kernel of `batch::solve_robust` against them.
//!
//! "Reaches the outlier-free solution" means: the solution's SE(2) cost on the clean graph is
//! within 1 % of the clean graph's own optimum (the criterion).

mod common;

use std::process::Command;

use so2lin::batch::{BatchConfig, RobustConfig, screen, solve, solve_robust};
use so2lin::estimate::OrientationEstimator;
use so2lin::graph::PoseGraph;
use so2lin::refine::{RefineConfig, cost};
use so2lin::sim::{OutlierConfig, OutlierKind, SimConfig, inject_outliers, simulate};

/// The plain solution of the best hypothesis (clean optimum).
fn plain(g: &PoseGraph) -> so2lin::batch::Solution {
    let r = screen(g, &BatchConfig::default()).unwrap();
    let orient = OrientationEstimator::new(g).unwrap();
    solve(g, &r, &orient, &r.hypotheses[0], &RefineConfig::default()).unwrap()
}

fn robust(g: &PoseGraph) -> so2lin::batch::Solution {
    let r = screen(g, &BatchConfig::default()).unwrap();
    let orient = OrientationEstimator::new(g).unwrap();
    let cfg = RobustConfig::default();
    solve_robust(
        g,
        &r,
        &orient,
        &r.hypotheses[0],
        &RefineConfig::default(),
        &cfg,
    )
    .unwrap()
}

/// `g` with `count` false loop closures of `kind` (seed `seed`).
fn corrupted(g: &PoseGraph, count: usize, kind: OutlierKind, seed: u64) -> so2lin::sim::Corrupted {
    inject_outliers(g, &OutlierConfig { count, kind, seed }).unwrap()
}

/// The loop closures (indices in `c.graph`) the default online estimator quarantines when
/// `c.graph` is streamed in robot order.
fn stream_rejected(c: &so2lin::sim::Corrupted) -> Vec<usize> {
    use so2lin::online::{OnlineConfig, OnlineEstimator, robot_order_indices};
    let mut est = OnlineEstimator::new(OnlineConfig::default()).unwrap();
    let order = robot_order_indices(c.graph.edges());
    for &i in &order {
        est.add_edge(c.graph.edges()[i]).unwrap();
    }
    est.rejected().iter().map(|r| order[r.edge]).collect()
}

/// Stream `file` with `count` false loop closures of `kind` for each of `seeds` (robot order,
/// the defaults) and require precision and recall ≥ 0.99 of the quarantined set (printed).
fn assert_stream_catches(file: &str, count: usize, kind: OutlierKind, seeds: &[u64]) {
    let Some(path) = common::dataset(file) else {
        return;
    };
    let (g, _) = so2lin::io::read_graph(&path, Default::default()).unwrap();
    for &seed in seeds {
        let c = corrupted(&g, count, kind, seed);
        let rejected = stream_rejected(&c);
        let caught = rejected.iter().filter(|&&e| c.is_false(e)).count();
        let precision = caught as f64 / rejected.len() as f64;
        let recall = caught as f64 / c.false_edges.len() as f64;
        println!(
            "{file} + {count} {kind:?} seed {seed}: precision {precision:.3} ({caught}/{}), \
             recall {recall:.3}",
            rejected.len()
        );
        assert!(
            precision >= 0.99 && recall >= 0.99,
            "{file} {kind:?} seed {seed}: precision {precision}, recall {recall}"
        );
    }
}

/// On 200 clean worlds the kernel raises no more rejections than α allows, and where it
/// rejects nothing it returns the plain optimum.
#[test]
fn the_kernel_leaves_clean_worlds_alone() {
    let mut rejected_worlds = 0;
    let worlds = 200u64;
    for seed in 0..worlds {
        let w = simulate(&SimConfig::new(400, 300 + seed)).unwrap();
        let r = robust(&w.graph);
        if !r.rejected.is_empty() {
            rejected_worlds += 1;
            println!("seed {}: {:?}", 300 + seed, r.rejected);
        }
        // The plain optimum is compared on a tenth of the worlds (it costs a second solve).
        if r.rejected.is_empty() && seed % 20 == 0 {
            let p = plain(&w.graph);
            let (a, b) = (p.refined.cost(), r.refined.cost());
            assert!((a - b).abs() <= 1e-6 * a, "seed {seed}: {a} vs {b}");
        }
    }
    // Every test of `solve` (quarantine, residual, leave-out) is family-wise at α = 0.01 per
    // world: about 2 worlds in 200 may have a rejection; 7 or more has probability 0.005.
    // Measured: 1 (seed 473: one loop closure quarantined online; its last re-test, at the
    // per-cycle level, still failed: cycle_angle 3.81 σ against 2.58).
    println!("{rejected_worlds} of {worlds} clean worlds had a rejection");
    assert!(
        rejected_worlds <= 6,
        "{rejected_worlds} of {worlds} clean worlds had rejections"
    );
}

/// Simulated worlds (noise as declared) with K false loop closures: the robust solution is
/// the outlier-free one in at least 5 of 6 worlds for each setting (measured: 6 of 6), and
/// over all runs at least 95 % of the rejected edges are false.
#[test]
fn the_kernel_reaches_the_outlier_free_solution_on_simulated_worlds() {
    let mut ok = [0usize; 3];
    let mut runs = [0usize; 3];
    let (mut rejected_all, mut rejected_false) = (0usize, 0usize);
    for seed in 0..6u64 {
        let w = simulate(&SimConfig::new(400, 700 + seed)).unwrap();
        let clean = plain(&w.graph).refined.cost();
        for (slot, (k, kind)) in [
            (1, OutlierKind::Random),
            (10, OutlierKind::Random),
            (10, OutlierKind::Clustered),
        ]
        .into_iter()
        .enumerate()
        {
            let c = corrupted(&w.graph, k, kind, seed);
            let r = robust(&c.graph);
            let on_clean = cost(&w.graph, &r.refined.poses);
            let success = on_clean <= 1.01 * clean;
            let false_rejected = r.rejected.iter().filter(|x| c.is_false(x.edge)).count();
            rejected_all += r.rejected.len();
            rejected_false += false_rejected;
            println!(
                "seed {seed} K = {k} {kind:?}: clean-graph cost {on_clean:.1} vs {clean:.1}; rejected {} ({false_rejected} false of {k})",
                r.rejected.len()
            );
            runs[slot] += 1;
            ok[slot] += usize::from(success);
        }
    }
    println!(
        "reached the outlier-free solution: K=1 random {}/{}, K=10 random {}/{}, K=10 clustered {}/{}",
        ok[0], runs[0], ok[1], runs[1], ok[2], runs[2]
    );
    assert!(ok.iter().all(|&k| k >= 5), "{ok:?} of {runs:?}");
    assert!(
        rejected_false as f64 >= 0.95 * rejected_all as f64,
        "{rejected_false} of {rejected_all} rejected are false"
    );
}

/// `so2lin simulate --outliers` lists its false edges; `so2lin inject` adds K more to a file.
#[test]
fn cli_simulate_and_inject_write_the_false_edges() {
    let dir = std::env::temp_dir().join(format!("so2lin-outliers-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let bin = env!("CARGO_BIN_EXE_so2lin");
    let world = dir.join("w.g2o");
    let st = Command::new(bin)
        .args([
            "simulate",
            "--poses",
            "300",
            "--seed",
            "2",
            "--outliers",
            "12",
        ])
        .args(["--outlier-kind", "clustered", "--out"])
        .arg(&world)
        .status()
        .unwrap();
    assert!(st.success());
    let truth: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("w.truth.json")).unwrap()).unwrap();
    let listed = truth["false_edges"].as_array().unwrap();
    assert_eq!(listed.len(), 12);
    let (g, _) = so2lin::io::read_graph(&world, Default::default()).unwrap();
    for f in listed {
        let e = g.edges()[f["edge"].as_u64().unwrap() as usize];
        assert_eq!(e.from(), f["from"].as_u64().unwrap());
        assert_eq!(e.to(), f["to"].as_u64().unwrap());
    }
    // Genuine edges are the simulated world's, in order.
    let w = simulate(&SimConfig::new(300, 2)).unwrap();
    assert_eq!(g.edge_count(), w.graph.edge_count() + 12);
    let out = dir.join("w5.g2o");
    let tj = dir.join("w5.json");
    let st = Command::new(bin)
        .arg("inject")
        .arg(&world)
        .args([
            "--outliers",
            "5",
            "--kind",
            "random",
            "--seed",
            "4",
            "--out",
        ])
        .arg(&out)
        .arg("--truth")
        .arg(&tj)
        .status()
        .unwrap();
    assert!(st.success());
    let (g5, _) = so2lin::io::read_graph(&out, Default::default()).unwrap();
    assert_eq!(g5.edge_count(), g.edge_count() + 5);
    let t5: serde_json::Value = serde_json::from_slice(&std::fs::read(&tj).unwrap()).unwrap();
    assert_eq!(t5["false_edges"].as_array().unwrap().len(), 5);
    // Same as the library on the same graph (one implementation).
    let lib = inject_outliers(
        &g,
        &OutlierConfig {
            count: 5,
            kind: OutlierKind::Random,
            seed: 4,
        },
    )
    .unwrap();
    assert_eq!(lib.graph.edges(), g5.edges());
    let bad = Command::new(bin)
        .arg("inject")
        .arg(&world)
        .args(["--outliers", "5", "--kind", "sideways", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(!bad.status.success());
    std::fs::remove_dir_all(&dir).ok();
}

/// M3500 with one injected random false loop closure (datasets required). Seed 1 is a case
/// the residual test alone missed (the map bends to fit the false edge: cost on the clean
/// graph +61 %); the leave-one-out test catches it.
#[test]
fn m3500_with_one_false_loop_closure() {
    let Some(path) = common::dataset("M3500.g2o") else {
        return;
    };
    let (g, _) = so2lin::io::read_graph(&path, Default::default()).unwrap();
    let clean = plain(&g);
    assert!(clean.rejected.is_empty());
    let r0 = robust(&g);
    assert!(r0.rejected.is_empty(), "clean M3500: {:?}", r0.rejected);
    assert!((r0.refined.cost() - clean.refined.cost()).abs() <= 1e-6 * clean.refined.cost());
    // The leave-out test's scale from the drops of M3500's 1 954 loop closures is reported,
    // and sharper than the quarantine's (angle scale at its floor 0.25; measured 0.048).
    let shown = r0.drop_scale.expect("M3500 has enough loop closures");
    let quarantine = r0.noise_scales.map(|s| s.larger()).unwrap();
    assert!(shown > 0.0 && shown < quarantine, "{shown} {quarantine}");
    let c = inject_outliers(
        &g,
        &OutlierConfig {
            count: 1,
            kind: OutlierKind::Random,
            seed: 1,
        },
    )
    .unwrap();
    let r = robust(&c.graph);
    let on_clean = cost(&g, &r.refined.poses);
    println!(
        "M3500 + 1 false edge: clean-graph cost {on_clean:.2} vs {:.2}; rejected {:?}",
        clean.refined.cost(),
        r.rejected.iter().map(|x| x.edge).collect::<Vec<_>>()
    );
    assert!(on_clean <= 1.01 * clean.refined.cost());
    assert!(r.rejected.iter().all(|x| c.is_false(x.edge)));
}

/// The kernel rejects nothing on clean benchmark files and leaves their optimum unchanged
/// (datasets required).
#[test]
fn the_kernel_leaves_clean_datasets_alone() {
    for name in [
        "intel.g2o",
        "MIT.g2o",
        "CSAIL.g2o",
        "FR079.g2o",
        "M3500b.g2o",
    ] {
        let Some(path) = common::dataset(name) else {
            return;
        };
        let (g, _) = so2lin::io::read_graph(&path, Default::default()).unwrap();
        let p = plain(&g);
        let r = robust(&g);
        assert!(r.rejected.is_empty(), "{name}: {:?}", r.rejected);
        let (a, b) = (p.refined.cost(), r.refined.cost());
        assert!((a - b).abs() <= 1e-6 * a, "{name}: {a} vs {b}");
    }
}

/// INTEL with 10 and 100 random false loop closures (seeds 1–3, datasets required), streamed
/// with the default online estimator in robot order: the quarantined set's precision and
/// recall. The path-triggered evictions (on by default) took the precision at K = 100 from
/// 0.82 to 1.00 (measured 298/298 quarantined edges false, 298 of 300 false edges caught);
/// this guards ≥ 0.95 for both, pooled over the seeds.
#[test]
fn intel_stream_quarantines_random_false_edges() {
    let Some(path) = common::dataset("intel.g2o") else {
        return;
    };
    let (g, _) = so2lin::io::read_graph(&path, Default::default()).unwrap();
    for k in [10, 100] {
        let (mut caught, mut flagged, mut injected) = (0, 0, 0);
        for seed in 1..=3u64 {
            let c = corrupted(&g, k, OutlierKind::Random, seed);
            let rejected = stream_rejected(&c);
            caught += rejected.iter().filter(|&&e| c.is_false(e)).count();
            flagged += rejected.len();
            injected += c.false_edges.len();
        }
        let (precision, recall) = (
            caught as f64 / flagged as f64,
            caught as f64 / injected as f64,
        );
        println!(
            "INTEL K = {k}: precision {precision:.3} ({caught}/{flagged}), recall {recall:.3} ({caught}/{injected})"
        );
        assert!(
            precision >= 0.95 && recall >= 0.95,
            "K = {k}: {precision} {recall}"
        );
    }
}

/// `solve`'s default pipeline reaches the outlier-free solution on the four protocol runs that
/// the earlier leave-one-out (the five largest residuals only) missed (datasets required):
/// INTEL + 100 random (seed 1: one false edge the map bent to fit, residual χ² 0.32, 13th
/// largest) and + 100 clustered (seed 1: two groups whose edges each drop the cost by 1–22 but
/// together by 751), M3500 + 1000 random (seed 1: a bent false edge; seed 2: a false edge the
/// stream accepted again after evicting it, with 107 genuine contradictors quarantined through
/// it, see `m3500_stream_keeps_evicted_edges_out_through_later_replays`). And five runs of
/// M3500 with 1000 false edges that the leave-out test then missed: random seeds 4 and 6 (one
/// and two false edges the stream accepted, leave-out drops 2.7, 4.1 and 4.3 against the
/// threshold of about 7.2 from the quarantine's angle scale, 0.25 at its floor; the drops' own
/// scale gives 1.4–1.6, the largest genuine drop being 0.5–0.7), random seed 7 and clustered
/// seeds 4 and 7 (false edges covering for each other online, 107–155 genuine loop closures
/// quarantined through them: found by the passes, then the stream runs again without them;
/// clustered seed 7 also puts back a genuine loop closure the leave-out test met beside false
/// edges, which the solution without it fitted at χ²_e 21.7). Every rejected edge is false
/// except at most one genuine edge per run.
#[test]
fn solve_finds_bent_false_edges_and_groups() {
    for (name, k, kind, seed) in [
        ("intel.g2o", 100, OutlierKind::Random, 1),
        ("intel.g2o", 100, OutlierKind::Clustered, 1),
        ("M3500.g2o", 1000, OutlierKind::Random, 1),
        ("M3500.g2o", 1000, OutlierKind::Random, 2),
        ("M3500.g2o", 1000, OutlierKind::Random, 4),
        ("M3500.g2o", 1000, OutlierKind::Random, 6),
        ("M3500.g2o", 1000, OutlierKind::Random, 7),
        ("M3500.g2o", 1000, OutlierKind::Clustered, 4),
        ("M3500.g2o", 1000, OutlierKind::Clustered, 7),
    ] {
        let Some(path) = common::dataset(name) else {
            return;
        };
        let (g, _) = so2lin::io::read_graph(&path, Default::default()).unwrap();
        let optimum = plain(&g).refined.cost();
        let c = corrupted(&g, k, kind, seed);
        let r = robust(&c.graph);
        let on_clean = cost(&g, &r.refined.poses);
        let genuine = r.rejected.iter().filter(|x| !c.is_false(x.edge)).count();
        let missed = c.false_edges.len() - (r.rejected.len() - genuine);
        println!(
            "{name} + {k} {kind:?} seed {seed}: clean-graph cost {on_clean:.2} vs {optimum:.2}; {missed} false edges accepted, {genuine} genuine rejected"
        );
        assert!(on_clean <= 1.01 * optimum, "{name} {kind:?} seed {seed}");
        assert_eq!(missed, 0, "{name} {kind:?} seed {seed}");
        assert!(genuine <= 1, "{name} {kind:?} seed {seed}");
    }
}

/// M3500 + 1000 random false loop closures (seeds 1, 2, 4, 5; datasets required), streamed with the
/// defaults in robot order: the quarantined set's precision and recall ≥ 0.99 each. Seed 2
/// guards the replay that keeps an evicted edge in quarantine: a later eviction replayed the
/// stream and re-tested the earlier-evicted false edge at its arrival, where it passed as it
/// first had, so it was accepted again and 107 genuine loop closures were quarantined through
/// it (precision 0.903, 994/1101); keeping it held until its re-test date gives 1000/1000.
/// Seeds 4 and 5 guard the two-blamer examination: six false edges each, whose own cycles on
/// the paths avoiding them had no power, stayed in while only the last loop closure failing
/// through them (usually another false one) was asked (precision 0.799 and 0.889).
#[test]
fn m3500_stream_keeps_evicted_edges_out_through_later_replays() {
    assert_stream_catches("M3500.g2o", 1000, OutlierKind::Random, &[1, 2, 4, 5]);
}

/// A loop closure that failed through an accepted one blames it only when it passes on a
/// path not much longer than the suspect's own (4 times at most): on M3500 + 1000 clustered
/// false edges, seed 7, passes on paths 5–118 times as long evicted 47 genuine loop closures
/// (stream precision 0.865, 996 of 1 151) before that bound; with it, none (and the searches
/// that crossed the map for them stop at the bound). INTEL + 100 clustered seed 1, whose false
/// edges are blamed on paths up to 3.6 times their own, keeps its recall (13 of its false
/// edges stayed in with a bound of 2).
#[test]
fn the_stream_blames_through_the_loop_a_suspect_closes() {
    assert_stream_catches("M3500.g2o", 1000, OutlierKind::Clustered, &[7]);
    assert_stream_catches("intel.g2o", 100, OutlierKind::Clustered, &[1]);
}

/// False edges at different places can cover for each other: avoiding one, the failed loop
/// closures' paths go through another and fail again, so none of them passes without the
/// suspect. They still agree among themselves (a return to a place), and two of them, each a
/// sharper test than the suspect's own cycle, that agree outvote it — unless the stretches of
/// odometry joining them have the same length, which members of a clustered group (one shared
/// measurement) also agree on. On M3500 + 1000 false edges: random seeds 41 and 47 held 113 and
/// 107 genuine loop closures without the vote (precision 0.898, 0.903), none with it (0.998,
/// 1.000); clustered seed 14 lost genuine ones to a vote of group members without the legs'
/// condition (0.981), none with it (1.000).
#[test]
fn the_stream_outvotes_false_edges_that_cover_for_each_other() {
    assert_stream_catches("M3500.g2o", 1000, OutlierKind::Random, &[41, 47]);
    assert_stream_catches("M3500.g2o", 1000, OutlierKind::Clustered, &[14]);
}

/// A false loop closure accepted in the heading spread of the angle scale's floor (0.25, kept
/// for long loops) can be many of the data's own standard deviations off in angle: the
/// examination tests its own cycle's angle at the data's own scale. On M3500 + 1000 false
/// edges, random seeds 7, 108 and 133 and clustered seed 49 each held the 107 genuine loop
/// closures of a return to the map's start, which failed through such an edge (1690 → 1012
/// on random seed 7: 0.738 rad off on a twelve-edge cycle, 2.85 σ at the floor, about 9 σ at
/// M3500's own angle scale 0.0246), precision 0.903 each without the angle test; 1.000,
/// 0.999, 1.000 and 1.000 with it (and with the closure tested at both ends).
#[test]
fn the_examination_tests_its_own_cycle_angle_at_the_data_scale() {
    assert_stream_catches("M3500.g2o", 1000, OutlierKind::Random, &[7, 108, 133]);
    assert_stream_catches("M3500.g2o", 1000, OutlierKind::Clustered, &[49]);
}

/// A clustered group of false loop closures shares one measurement, so its members hold each
/// other up: examined alone, a member's own cycle and the failed loop closures' paths go
/// through a sibling, on which they pass or fail as if the member were genuine. The stream
/// examines a suspect without the accepted loop closures of its place (both ends within 10
/// poses of its own). On M3500 + 1000 clustered false edges, seeds 4, 9 and 10 held 107, 110
/// and 17 genuine loop closures at the end of their streams when a suspect was examined
/// alone (a pair or more of one group accepted together; precision 0.90, 0.90, 0.98), none
/// but 2 with its place.
#[test]
fn the_stream_examines_a_suspect_without_its_place() {
    assert_stream_catches("M3500.g2o", 1000, OutlierKind::Clustered, &[4, 9, 10]);
}

/// The members of a clustered group are not mutually consistent (they share one measurement,
/// not the odometry between them): while one is accepted the others fail through it, and a
/// replay that evicts it used to re-test them at their arrival and accept the next, one
/// eviction per member. An eviction keeps the quarantined loop closures of the evicted edge's
/// place in quarantine through its replay. On M3500 + 1000 clustered false edges, seeds 12
/// and 13 held 23 and 108 genuine loop closures at the end without it (precision 0.978 and
/// 0.902; 32 and 10 rebuilds), 8 and none with it (8 and 5 rebuilds).
#[test]
fn an_eviction_keeps_the_quarantined_place_mates_out() {
    assert_stream_catches("M3500.g2o", 1000, OutlierKind::Clustered, &[12, 13]);
}
