//! Every benchmark file reads with the counts of `datasets/SOURCES.md`.

mod common;

use so2lin::io::{InfoOrder, ReadOptions, read_graph};

/// (file, nodes, edges, odometric, loop closures, cycles, parallel edges, EQUIV lines)
type Row = (
    &'static str,
    usize,
    usize,
    usize,
    usize,
    usize,
    usize,
    usize,
);
const COUNTS: [Row; 19] = [
    ("intel.g2o", 1728, 2512, 1727, 785, 785, 0, 0),
    ("MIT.g2o", 808, 827, 807, 20, 20, 0, 0),
    ("CSAIL.g2o", 1045, 1172, 1044, 128, 128, 1, 0),
    ("manhattan.g2o", 3500, 5453, 3499, 1954, 1954, 0, 0),
    ("city10000.g2o", 10000, 20687, 9999, 10688, 10688, 0, 0),
    ("ais2klinik.g2o", 15115, 16727, 15113, 1614, 1613, 0, 0),
    ("FR079.g2o", 989, 1217, 988, 229, 229, 0, 0),
    ("FRH.g2o", 1316, 2820, 1315, 1505, 1505, 0, 0),
    ("M3500.g2o", 3500, 5453, 3499, 1954, 1954, 0, 0),
    ("M3500a.g2o", 3500, 5453, 3499, 1954, 1954, 0, 0),
    ("M3500b.g2o", 3500, 5453, 3499, 1954, 1954, 0, 0),
    ("M3500c.g2o", 3500, 5453, 3499, 1954, 1954, 0, 0),
    (
        "manhattanOlson3500.g2o",
        3500,
        5598,
        3499,
        2099,
        2099,
        145,
        0,
    ),
    ("noisyToyGraph.txt", 4, 5, 3, 2, 2, 0, 0),
    ("orientationsNoisyToyGraph.txt", 4, 5, 3, 2, 2, 0, 0),
    ("optimizedNoisyToyGraph.txt", 4, 5, 3, 2, 2, 0, 0),
    ("pose2example.txt", 11, 12, 10, 2, 2, 0, 0),
    ("w100.graph", 100, 300, 99, 201, 201, 0, 40),
    ("w20000.txt", 20061, 26831, 20060, 6771, 6771, 0, 0),
];

#[test]
#[cfg_attr(
    so2lin_no_datasets,
    ignore = "benchmark datasets not found (set SO2LIN_DATASETS)"
)]
fn counts_match_sources_md() {
    if common::datasets_dir().is_none() {
        return;
    }
    for (name, nodes, edges, odo, lc, cycles, parallel, equiv) in COUNTS {
        let Some(path) = common::dataset(name) else {
            continue;
        };
        let (g, summary) =
            read_graph(&path, ReadOptions::default()).unwrap_or_else(|e| panic!("{name}: {e}"));
        let s = g.stats();
        assert_eq!(
            (
                s.nodes,
                s.edges,
                s.odometric_edges,
                s.loop_closures,
                s.cycles,
                s.components
            ),
            (nodes, edges, odo, lc, cycles, 1),
            "{name}"
        );
        assert_eq!(s.parallel_edges, parallel, "{name}: parallel edges");
        assert_eq!(summary.equivalences.len(), equiv, "{name}: EQUIV lines");
        assert!(
            summary.skipped.is_empty(),
            "{name}: skipped {:?}",
            summary.skipped
        );
    }
}

fn sigma2_all(name: &str) -> Option<Vec<f64>> {
    let path = common::dataset(name)?;
    let (g, _) = read_graph(&path, ReadOptions::default()).unwrap();
    Some(g.edges().iter().map(|e| e.sigma2()).collect())
}

#[test]
#[cfg_attr(
    so2lin_no_datasets,
    ignore = "benchmark datasets not found (set SO2LIN_DATASETS)"
)]
fn m3500_noisy_variants_angle_variance() {
    for (name, itt, order) in [
        ("M3500a.g2o", 30.90, InfoOrder::Toro),
        ("M3500b.g2o", 16.04, InfoOrder::Toro),
        ("M3500c.g2o", 8.90, InfoOrder::Toro),
    ] {
        let Some(path) = common::dataset(name) else {
            return;
        };
        let (g, summary) = read_graph(&path, ReadOptions::default()).unwrap();
        assert_eq!(summary.order, Some(order), "{name}");
        // Odometric edges carry the isotropic noise of the SOURCES.md table.
        let odo: Vec<f64> = g
            .edges()
            .iter()
            .filter(|e| e.is_odometric())
            .map(|e| e.sigma2())
            .collect();
        for s2 in odo {
            let rel = (s2 - 1.0 / itt).abs() / (1.0 / itt);
            assert!(
                rel < 5e-3,
                "{name}: σ² = {s2}, expected 1/{itt} to 3 digits"
            );
        }
    }
}

#[test]
#[cfg_attr(
    so2lin_no_datasets,
    ignore = "benchmark datasets not found (set SO2LIN_DATASETS)"
)]
fn w20000_is_edge2_in_g2o_order() {
    let Some(path) = common::dataset("w20000.txt") else {
        return;
    };
    let (g, summary) = read_graph(&path, ReadOptions::default()).unwrap();
    assert_eq!(summary.order, Some(InfoOrder::G2o));
    for e in g.edges() {
        assert!(e.information().is_positive_definite());
        assert!((e.sigma2() - 0.2).abs() < 1e-12, "Itt = 5 → σ² = 0.2");
    }
    // Forcing TORO order makes its matrices singular: a clear error on line 1.
    let err = read_graph(
        &path,
        ReadOptions {
            order: InfoOrder::Toro,
            ..Default::default()
        },
    )
    .unwrap_err();
    assert_eq!(err.line, 1);
    assert!(err.to_string().contains("not positive definite"), "{err}");
}

#[test]
#[cfg_attr(
    so2lin_no_datasets,
    ignore = "benchmark datasets not found (set SO2LIN_DATASETS)"
)]
fn frh_denormals_read_as_zero_and_olson_angles_kept() {
    if let Some(s2) = sigma2_all("FRH.g2o") {
        assert!(s2.iter().all(|v| v.is_finite() && *v > 0.0));
        let path = common::dataset("FRH.g2o").unwrap();
        let (g, _) = read_graph(&path, ReadOptions::default()).unwrap();
        assert!(g.edges().iter().all(|e| e.information().0[2] == 0.0));
    }
    if let Some(path) = common::dataset("manhattanOlson3500.g2o") {
        let (g, _) = read_graph(&path, ReadOptions::default()).unwrap();
        let outside = g
            .edges()
            .iter()
            .filter(|e| e.delta().abs() > std::f64::consts::PI)
            .count();
        assert_eq!(outside, 854, "angles outside [-π, π] are kept as written");
    }
}

#[test]
#[cfg_attr(
    so2lin_no_datasets,
    ignore = "benchmark datasets not found (set SO2LIN_DATASETS)"
)]
fn mit_reversed_edges_keep_direction() {
    let Some(path) = common::dataset("MIT.g2o") else {
        return;
    };
    let (g, _) = read_graph(&path, ReadOptions::default()).unwrap();
    let reversed = g.edges().iter().filter(|e| e.from() > e.to()).count();
    assert_eq!(reversed, 20);
}

/// With `SO2LIN_REQUIRE_DATASETS=1` a build without the datasets fails here, with the reason;
/// otherwise their tests are reported as ignored (see `build.rs`).
#[test]
fn datasets_are_present_when_required() {
    let required = std::env::var("SO2LIN_REQUIRE_DATASETS").is_ok_and(|v| v == "1");
    let built_without = cfg!(so2lin_no_datasets);
    if required && built_without {
        panic!(
            "SO2LIN_REQUIRE_DATASETS=1 but the datasets were not found when the tests were built \
             (set SO2LIN_DATASETS to their folder)"
        );
    }
    if required {
        assert!(common::datasets_dir().is_some());
    }
}
