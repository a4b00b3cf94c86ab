//! Each stage of the batch pipeline (`screen --basis incremental`) on M3500 and INTEL when
//! the datasets are present, on a simulated 3500-pose world otherwise; and the whole `solve`
//! (read, screen, orientations, positions, refinement to convergence; plain and robust) on M3500 and city10000.
//!
//! `cargo bench --bench batch`

use std::hint::black_box;
use std::path::PathBuf;

use criterion::{Criterion, criterion_group, criterion_main};
use so2lin::batch::{BatchConfig, RobustConfig, screen, solve, solve_robust};
use so2lin::cycles::{BasisKind, CycleBasis};
use so2lin::estimate::OrientationEstimator;
use so2lin::graph::PoseGraph;
use so2lin::io::{ReadOptions, read_graph_from, write_g2o};
use so2lin::refine::RefineConfig;
use so2lin::screening::ScreeningConfig;
use so2lin::sim::{SimConfig, simulate};

/// (name, file bytes) of those of `names` found in the datasets folder.
fn datasets(names: &[&str]) -> Vec<(String, Vec<u8>)> {
    let dir = std::env::var_os("SO2LIN_DATASETS")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/datasets"));
    names
        .iter()
        .filter_map(|n| std::fs::read(dir.join(n)).ok().map(|b| (n.to_string(), b)))
        .collect()
}

/// (name, file bytes) of the benchmark inputs.
fn inputs() -> Vec<(String, Vec<u8>)> {
    let found = datasets(&["M3500.g2o", "intel.g2o"]);
    if !found.is_empty() {
        return found;
    }
    eprintln!(
        "datasets not found (SO2LIN_DATASETS or ../shared/datasets): benchmarking a simulated world"
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

/// The whole `solve` command: read, screen, θ*, positions, refinement to convergence (the
/// defaults); `solve/robust/…` with the robust kernel, as `so2lin solve` runs by default.
fn bench_solve(c: &mut Criterion) {
    let mut inputs = datasets(&["M3500.g2o", "city10000.g2o"]);
    if inputs.is_empty() {
        inputs = self::inputs();
    }
    let mut group = c.benchmark_group("solve");
    group.sample_size(10);
    let refine = RefineConfig::default();
    for (name, bytes) in &inputs {
        group.bench_function(name.as_str(), |b| {
            b.iter(|| {
                let g = read(black_box(bytes));
                let r = screen(&g, &BatchConfig::default()).expect("screens");
                let orient = OrientationEstimator::new(&g).expect("factors");
                solve(&g, &r, &orient, &r.hypotheses[0], &refine)
                    .expect("solves")
                    .refined
                    .cost()
            })
        });
        group.bench_function(format!("robust/{name}"), |b| {
            b.iter(|| {
                let g = read(black_box(bytes));
                let r = screen(&g, &BatchConfig::default()).expect("screens");
                let orient = OrientationEstimator::new(&g).expect("factors");
                let robust = RobustConfig::default();
                solve_robust(&g, &r, &orient, &r.hypotheses[0], &refine, &robust)
                    .expect("solves")
                    .refined
                    .cost()
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench, bench_solve);
criterion_main!(benches);
