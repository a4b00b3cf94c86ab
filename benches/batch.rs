//! Each stage of the batch pipeline (`screen --basis incremental`) on M3500 and INTEL when
//! the datasets are present, on a simulated 3500-pose world otherwise.
//!
//! `cargo bench --bench batch`

use std::hint::black_box;
use std::path::PathBuf;

use criterion::{Criterion, criterion_group, criterion_main};
use so2lin::batch::{BatchConfig, screen};
use so2lin::cycles::{BasisKind, CycleBasis};
use so2lin::estimate::OrientationEstimator;
use so2lin::graph::PoseGraph;
use so2lin::io::{ReadOptions, read_graph_from, write_g2o};
use so2lin::screening::ScreeningConfig;
use so2lin::sim::{SimConfig, simulate};

/// (name, file bytes) of the benchmark inputs.
fn inputs() -> Vec<(String, Vec<u8>)> {
    let dir = std::env::var_os("SO2LIN_DATASETS")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/datasets"));
    let found: Vec<(String, Vec<u8>)> = ["M3500.g2o", "intel.g2o"]
        .iter()
        .filter_map(|n| std::fs::read(dir.join(n)).ok().map(|b| (n.to_string(), b)))
        .collect();
    if !found.is_empty() {
        return found;
    }
    eprintln!(
        "datasets not found in {}: benchmarking a simulated world",
        dir.display()
    );
    let world = simulate(&SimConfig::new(3500, 1)).expect("valid config");
    let mut bytes = Vec::new();
    write_g2o(&mut bytes, &world.graph, None).expect("in-memory write");
    vec![("sim3500".into(), bytes)]
}

fn read(bytes: &[u8]) -> PoseGraph {
    read_graph_from(bytes, "bench", ReadOptions::default())
        .expect("valid input")
        .0
}

fn bench(c: &mut Criterion) {
    let paper = BatchConfig {
        basis: BasisKind::Incremental,
        screening: ScreeningConfig::paper(),
    };
    for (name, bytes) in inputs() {
        let graph = read(&bytes);
        let result = screen(&graph, &paper).expect("screens");
        let k = result.wraps(&result.hypotheses[0]).expect("integral");
        c.bench_function(&format!("{name}/read"), |b| {
            b.iter(|| read(black_box(&bytes)))
        });
        c.bench_function(&format!("{name}/basis_incremental"), |b| {
            b.iter(|| CycleBasis::build(black_box(&graph), BasisKind::Incremental))
        });
        c.bench_function(&format!("{name}/basis_and_screening"), |b| {
            b.iter(|| screen(black_box(&graph), &paper).map(|r| r.determined))
        });
        c.bench_function(&format!("{name}/estimate"), |b| {
            b.iter(|| OrientationEstimator::new(black_box(&graph)).map(|e| e.orientations(&k)))
        });
        c.bench_function(&format!("{name}/whole_screen_command"), |b| {
            b.iter(|| {
                let g = read(black_box(&bytes));
                let r = screen(&g, &paper).expect("screens");
                let k = r.wraps(&r.hypotheses[0]).expect("integral");
                OrientationEstimator::new(&g).map(|e| e.orientations(&k))
            })
        });
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
