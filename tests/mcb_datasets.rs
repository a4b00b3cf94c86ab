//! Minimum cycle bases on the benchmark datasets: the MCB is the lightest basis, the
//! approximation keeps its bound, both are integral bases whose wraps reproduce γ, and
//! screening M3500b/c with the MCB gives the paper's outcome.
//!
//! `cargo test --release --test mcb_datasets -- --nocapture` prints the table.

mod common;

use so2lin::batch::{BatchConfig, SecondOutcome, screen};
use so2lin::cycles::{BasisKind, CycleBasis, approx};
use so2lin::io::{ReadOptions, read_graph};
use so2lin::screening::ScreeningConfig;
use so2lin::wraps::gamma_of;

#[test]
#[cfg_attr(
    so2lin_no_datasets,
    ignore = "benchmark datasets not found (set SO2LIN_DATASETS)"
)]
fn mcb_is_lightest_and_approximation_within_bound_on_every_dataset() {
    let Some((dir, names)) = common::dataset_names() else {
        return;
    };
    let mut checked = 0;
    for name in names {
        let (g, _) = read_graph(dir.join(&name), ReadOptions::default()).unwrap();
        if g.edge_count() > 25_000 {
            eprintln!("{name}: {} edges > 25 000, skipped", g.edge_count());
            continue;
        }
        let sigma2: Vec<f64> = g.edges().iter().map(|e| e.sigma2()).collect();
        let cycles = g.stats().cycles;
        let mcb = CycleBasis::build(&g, BasisKind::Mcb);
        assert_eq!(mcb.kind, BasisKind::Mcb, "{name}");
        let w_mcb = mcb.weight(&sigma2);
        let tol = 1e-9 * w_mcb.max(1e-300);
        let mut row = format!("{name:<30} mcb {w_mcb:>12.4}");
        for kind in [
            BasisKind::Odometric,
            BasisKind::Mst,
            BasisKind::Incremental,
            BasisKind::McbApprox,
            BasisKind::Mcb,
        ] {
            let b = if kind == BasisKind::Mcb {
                mcb.clone()
            } else {
                CycleBasis::build(&g, kind)
            };
            assert_eq!(b.cycles.len(), cycles, "{name} {kind:?}");
            let w = b.weight(&sigma2);
            assert!(
                w >= w_mcb - tol,
                "{name}: {kind:?} weighs {w} < MCB {w_mcb}"
            );
            if kind == BasisKind::McbApprox {
                let k = f64::from(2 * approx::DEFAULT_K - 1);
                assert!(w <= k * w_mcb + tol, "{name}: approx {w} > {k} × {w_mcb}");
            }
            row += &format!("  {kind:?} ×{:.4}", w / w_mcb);
            // An integral basis, and k from γ reproduces γ (γ of the zero-free wraps
            // `k_e = e mod 3 − 1`, an arbitrary integer vector).
            for c in &b.cycles {
                assert!(c.is_closed(g.endpoints()), "{name} {kind:?}");
            }
            let solver = b.wrap_solver(g.edge_count()).unwrap();
            assert!(
                solver.is_integral(),
                "{name} {kind:?}: |det| {}",
                solver.abs_det()
            );
            let truth: Vec<i64> = (0..g.edge_count() as i64).map(|e| e % 3 - 1).collect();
            let gamma = gamma_of(&b.cycles, &truth);
            let k = solver.wraps(&b.cycles, &gamma).unwrap();
            assert_eq!(gamma_of(&b.cycles, &k), gamma, "{name} {kind:?}");
        }
        eprintln!("{row}");
        checked += 1;
    }
    assert!(checked >= 18, "only {checked} datasets checked");
}

#[test]
#[cfg_attr(
    so2lin_no_datasets,
    ignore = "benchmark datasets not found (set SO2LIN_DATASETS)"
)]
fn screening_m3500b_and_m3500c_with_the_mcb() {
    // The paper (Table IV, MCB): one hypothesis on M3500b, two on M3500c.
    for (name, want) in [("M3500b.g2o", 1), ("M3500c.g2o", 2)] {
        let Some(path) = common::dataset(name) else {
            return;
        };
        let (g, _) = read_graph(&path, ReadOptions::default()).unwrap();
        for basis in [BasisKind::Mcb, BasisKind::McbApprox] {
            let cfg = BatchConfig {
                basis,
                screening: ScreeningConfig::paper(),
            };
            let r = screen(&g, &cfg).unwrap();
            assert_eq!(r.basis.kind, basis, "{name}: no fallback");
            assert!(r.fallback.is_none());
            assert_eq!(r.outcome, SecondOutcome::Complete, "{name} {basis:?}");
            eprintln!(
                "{name} {basis:?}: first screening {:?} %, second {:?} %, {} hypotheses",
                r.first
                    .iter()
                    .map(|i| i.determined_percent)
                    .collect::<Vec<_>>(),
                r.second
                    .iter()
                    .map(|i| i.determined_percent)
                    .collect::<Vec<_>>(),
                r.hypotheses.len()
            );
            assert_eq!(r.hypotheses.len(), want, "{name} {basis:?}");
            // The best hypothesis' wraps reproduce its γ.
            let h = &r.hypotheses[0];
            let k = r.wraps(h).unwrap();
            assert_eq!(gamma_of(&r.basis.cycles, &k), r.gamma(h));
        }
    }
}
