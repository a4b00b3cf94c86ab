//! Minimum cycle bases on the benchmark datasets: exact MCB of INTEL, M3500 and city10000,
//! the 3-approximation (k = 2) of M3500 and INTEL. Skipped (with a message) when the datasets
//! are absent.
//!
//! `cargo bench --bench mcb`

use std::hint::black_box;
use std::path::PathBuf;
use std::time::Duration;

use criterion::{Criterion, criterion_group, criterion_main};
use so2lin::cycles::{BasisKind, CycleBasis};
use so2lin::graph::PoseGraph;
use so2lin::io::{ReadOptions, read_graph};

fn dataset(name: &str) -> Option<PoseGraph> {
    let dir = std::env::var_os("SO2LIN_DATASETS")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/datasets"));
    match read_graph(dir.join(name), ReadOptions::default()) {
        Ok((g, _)) => Some(g),
        Err(e) => {
            eprintln!("skipping {name}: {e}");
            None
        }
    }
}

fn bench(c: &mut Criterion) {
    for name in ["intel.g2o", "M3500.g2o"] {
        let Some(g) = dataset(name) else { continue };
        c.bench_function(&format!("{name}/mcb"), |b| {
            b.iter(|| CycleBasis::build(black_box(&g), BasisKind::Mcb))
        });
        c.bench_function(&format!("{name}/mcb_approx"), |b| {
            b.iter(|| CycleBasis::build(black_box(&g), BasisKind::McbApprox))
        });
    }
    if let Some(g) = dataset("city10000.g2o") {
        let mut group = c.benchmark_group("city10000.g2o");
        group
            .sample_size(10)
            .measurement_time(Duration::from_secs(40));
        group.bench_function("mcb", |b| {
            b.iter(|| CycleBasis::build(black_box(&g), BasisKind::Mcb))
        });
        group.bench_function("mcb_approx", |b| {
            b.iter(|| CycleBasis::build(black_box(&g), BasisKind::McbApprox))
        });
        group.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
