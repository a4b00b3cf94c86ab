//! The batch pipeline: estimates against dense references and GTSAM, χ² identities, and the
//! paper's datasets.

mod common;

use nalgebra::{DMatrix, DVector};
use so2lin::batch::{BatchConfig, SecondOutcome, screen};
use so2lin::cycles::BasisKind;
use so2lin::estimate::OrientationEstimator;
use so2lin::graph::PoseGraph;
use so2lin::io::{ReadOptions, read_graph};
use so2lin::screening::ScreeningConfig;
use so2lin::sim::{SimConfig, simulate};
use std::f64::consts::TAU;

const BASES: [BasisKind; 3] = [BasisKind::Odometric, BasisKind::Mst, BasisKind::Incremental];

fn config(basis: BasisKind) -> BatchConfig {
    BatchConfig {
        basis,
        screening: ScreeningConfig::default(),
    }
}

/// Dense reference θ* = (Ā P⁻¹ Āᵀ)⁻¹ Ā P⁻¹ (δ − 2πk), anchor node 0.
fn dense_theta(g: &PoseGraph, k: &[i64]) -> Vec<f64> {
    let n = g.node_count() - 1;
    let mut lap = DMatrix::<f64>::zeros(n, n);
    let mut rhs = DVector::<f64>::zeros(n);
    for (e, (&(a, b), edge)) in g.endpoints().iter().zip(g.edges()).enumerate() {
        let w = 1.0 / edge.sigma2();
        let y = w * (edge.delta() - TAU * k[e] as f64);
        let (va, vb) = (a.checked_sub(1), b.checked_sub(1));
        if let Some(i) = va {
            lap[(i, i)] += w;
            rhs[i] -= y;
        }
        if let Some(j) = vb {
            lap[(j, j)] += w;
            rhs[j] += y;
        }
        if let (Some(i), Some(j)) = (va, vb) {
            lap[(i, j)] -= w;
            lap[(j, i)] -= w;
        }
    }
    let x = lap.cholesky().expect("connected graph").solve(&rhs);
    std::iter::once(0.0).chain(x.iter().copied()).collect()
}

#[test]
fn orientations_match_dense_reference_and_chi2_identity() {
    for seed in 0..6 {
        let mut c = SimConfig::new(40 + 20 * seed as usize, seed);
        c.sigma_theta = 0.02 + 0.04 * seed as f64;
        let w = simulate(&c).unwrap();
        let est = OrientationEstimator::new(&w.graph).unwrap();
        for basis in BASES {
            let r = screen(&w.graph, &config(basis)).unwrap();
            assert!(!r.hypotheses.is_empty());
            for h in r.hypotheses.iter().take(4) {
                let k = r.wraps(h).unwrap();
                let theta = est.orientations(&k);
                let reference = dense_theta(&w.graph, &k);
                for (a, b) in theta.iter().zip(&reference) {
                    assert!((a - b).abs() < 1e-9, "seed {seed} {basis:?}: {a} vs {b}");
                }
                // χ² of the estimate equals (γ − μ)ᵀ P_γ⁻¹ (γ − μ).
                let cost = est.cost(&theta, &k);
                assert!(
                    (cost - h.chi2).abs() <= 1e-8 * h.chi2.max(1.0),
                    "seed {seed} {basis:?}: cost {cost} vs γ-form {}",
                    h.chi2
                );
            }
        }
    }
}

#[test]
fn marginal_variance_matches_dense_inverse() {
    let w = simulate(&SimConfig::new(30, 4)).unwrap();
    let est = OrientationEstimator::new(&w.graph).unwrap();
    let g = &w.graph;
    let n = g.node_count() - 1;
    let mut lap = DMatrix::<f64>::zeros(n, n);
    for (&(a, b), e) in g.endpoints().iter().zip(g.edges()) {
        let w = 1.0 / e.sigma2();
        for (x, y, v) in [(a, a, w), (b, b, w), (a, b, -w), (b, a, -w)] {
            if x > 0 && y > 0 {
                lap[(x - 1, y - 1)] += v;
            }
        }
    }
    let inv = lap.try_inverse().unwrap();
    assert_eq!(est.variance(0), 0.0);
    for v in 1..=n {
        assert!((est.variance(v) - inv[(v - 1, v - 1)]).abs() < 1e-12);
    }
}

#[test]
#[cfg_attr(
    so2lin_no_datasets,
    ignore = "benchmark datasets not found (set SO2LIN_DATASETS)"
)]
fn gtsam_lago_toy_graph_orientations() {
    let Some(path) = common::dataset("noisyToyGraph.txt") else {
        return;
    };
    let (g, _) = read_graph(&path, ReadOptions::default()).unwrap();
    let r = screen(&g, &config(BasisKind::Incremental)).unwrap();
    assert_eq!(r.hypotheses.len(), 1);
    let k = r.wraps(&r.hypotheses[0]).unwrap();
    assert_ne!(
        k.iter().filter(|&&x| x != 0).count(),
        0,
        "edge 2→0 needs a 2π correction"
    );
    let theta = OrientationEstimator::new(&g).unwrap().orientations(&k);
    for (got, want) in theta.iter().zip([0.0, 1.565449, 3.134143, 4.710123]) {
        assert!((got - want).abs() < 1e-4, "{got} vs {want}");
    }
}

#[test]
#[cfg_attr(
    so2lin_no_datasets,
    ignore = "benchmark datasets not found (set SO2LIN_DATASETS)"
)]
fn m3500_paper_preset_reproduces_the_mcb_row() {
    let Some(path) = common::dataset("M3500.g2o") else {
        return;
    };
    let (g, _) = read_graph(&path, ReadOptions::default()).unwrap();
    let cfg = BatchConfig {
        basis: BasisKind::Incremental,
        screening: ScreeningConfig::paper(),
    };
    let r = screen(&g, &cfg).unwrap();
    assert_eq!(r.first.len(), 2, "{:?}", r.first);
    assert!(
        (r.first[0].determined_percent - 99.95).abs() < 0.005,
        "{:?}",
        r.first[0]
    );
    assert_eq!(r.first[0].determined + r.first[1].determined, 1954);
    assert_eq!(r.hypotheses.len(), 1);
    assert!((r.basis.mean_length() - 6.8).abs() < 0.05);
}

#[test]
#[cfg_attr(
    so2lin_no_datasets,
    ignore = "benchmark datasets not found (set SO2LIN_DATASETS)"
)]
fn paper_datasets_all_bases_finish() {
    // (file, hypotheses expected with the incremental basis; the paper's MCB outcome)
    let cases = [
        ("intel.g2o", 1),
        ("MIT.g2o", 1),
        ("M3500.g2o", 1),
        ("M3500a.g2o", 1),
        ("M3500b.g2o", 1),
        ("M3500c.g2o", 2),
    ];
    for (name, want) in cases {
        let Some(path) = common::dataset(name) else {
            return;
        };
        let (g, _) = read_graph(&path, ReadOptions::default()).unwrap();
        for basis in BASES {
            let cfg = BatchConfig {
                basis,
                screening: ScreeningConfig::paper(),
            };
            let r = screen(&g, &cfg).unwrap();
            let total: usize = r.first.iter().chain(&r.second).map(|i| i.determined).sum();
            assert_eq!(total, r.determined, "{name} {basis:?}");
            assert_eq!(r.determined + r.ambiguous.len(), r.model.len());
            match r.outcome {
                SecondOutcome::Complete => assert!(!r.hypotheses.is_empty()),
                SecondOutcome::TooMany(_) | SecondOutcome::NoneInside => {
                    assert_eq!(r.hypotheses.len(), 1, "fallback answer")
                }
            }
            if basis == BasisKind::Incremental {
                assert_eq!(r.hypotheses.len(), want, "{name}");
                assert_eq!(r.outcome, SecondOutcome::Complete);
            }
        }
    }
}
