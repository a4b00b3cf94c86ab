//! Work counted, not timed (`so2lin::work`): a stream's work per step is the same in every run,
//! whatever the renewal threads' timing, and stays within what it was when this test was
//! written (a guard against an algorithm that quietly does more: latencies on a shared
//! machine move by 2× from day to day, counts do not).

use so2lin::graph::Edge;
use so2lin::online::{OnlineConfig, OnlineEstimator, robot_order};
use so2lin::sim::{OutlierConfig, OutlierKind, SimConfig, inject_outliers, simulate};
use so2lin::work::{Work, on_this_thread};

/// A 3 500-pose simulated world (robot order), with `outliers` random false loop closures.
fn world(outliers: usize) -> Vec<Edge> {
    let g = simulate(&SimConfig::new(3500, 7)).unwrap().graph;
    let g = if outliers == 0 {
        g
    } else {
        let config = OutlierConfig {
            count: outliers,
            kind: OutlierKind::Random,
            seed: 7,
        };
        inject_outliers(&g, &config).unwrap().graph
    };
    robot_order(g.edges())
}

/// Stream `edges` with the defaults, the newest pose read after every step (as `so2lin
/// stream` does), on the calling thread: the work of each step.
fn stream(edges: &[Edge]) -> Vec<Work> {
    let mut est = OnlineEstimator::new(OnlineConfig::default()).unwrap();
    edges
        .iter()
        .map(|&e| {
            let before = on_this_thread();
            est.add_edge(e).unwrap();
            est.newest().unwrap();
            on_this_thread().since(before)
        })
        .collect()
}

fn total(steps: &[Work]) -> Work {
    steps.iter().fold(Work::default(), |t, w| Work {
        search_nodes: t.search_nodes + w.search_nodes,
        estimate_entries: t.estimate_entries + w.estimate_entries,
        conditioning_entries: t.conditioning_entries + w.conditioning_entries,
    })
}

/// The same stream twice, the second on a new thread while this one keeps a core busy (the
/// renewal builders then run at another pace): every step's counts are equal.
#[test]
fn the_counts_do_not_depend_on_the_threads_timing() {
    for outliers in [0, 100] {
        let edges = world(outliers);
        let first = stream(&edges);
        let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let second = {
            let (edges, done) = (edges.clone(), done.clone());
            std::thread::spawn(move || {
                let steps = stream(&edges);
                done.store(true, std::sync::atomic::Ordering::Relaxed);
                steps
            })
        };
        let mut spin = 0u64;
        while !done.load(std::sync::atomic::Ordering::Relaxed) {
            spin = std::hint::black_box(spin.wrapping_add(1));
        }
        let second = second.join().unwrap();
        assert_eq!(first.len(), second.len());
        for (k, (a, b)) in first.iter().zip(&second).enumerate() {
            assert_eq!(a, b, "{outliers} false edges, step {k}");
        }
        let t = total(&first);
        println!("{outliers} false edges: {t:?}");
        assert!(t.estimate_entries > 0 && t.search_nodes > 0);
    }
}

/// Totals of the two streams above when this test was written, and the slack allowed: a
/// change that makes a stream do more than this much more work fails here, and one that makes
/// it do less should lower the figures (the test prints them).
#[test]
fn the_work_stays_within_its_recorded_bounds() {
    const SLACK: f64 = 1.10;
    // Measured on 2026-12-03 (search nodes, estimate entries, conditioning entries).
    let recorded = [
        (0, [188_384u64, 71_224_897, 0]),
        (100, [309_008u64, 70_083_382, 4_156]),
    ];
    for (outliers, [search, estimate, conditioning]) in recorded {
        let t = total(&stream(&world(outliers)));
        println!("{outliers} false edges: {t:?}");
        let within = |got: u64, bound: u64| got as f64 <= SLACK * bound as f64;
        assert!(
            within(t.search_nodes, search),
            "search nodes {} > {search}",
            t.search_nodes
        );
        assert!(
            within(t.estimate_entries, estimate),
            "estimate entries {} > {estimate}",
            t.estimate_entries
        );
        assert!(
            within(t.conditioning_entries, conditioning),
            "conditioning entries {} > {conditioning}",
            t.conditioning_entries
        );
    }
}
