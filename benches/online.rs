//! Online estimator latency (`cargo bench --bench online`).
//!
//! - `stream/<input>`: every edge of a file through `add_edge` **in robot order**
//!   ([`robot_order`]), with the newest pose read after every step ([`OnlineEstimator::newest`])
//!   as a robot would (M3500 and city10000 when the datasets are present, simulated worlds
//!   always; `M3500+1000` is M3500 with 1000 random false loop closures injected as
//!   `so2lin inject --outliers 1000 --seed 1` does); `stream/<input>_logged` the same with an
//!   MCAP recorder attached (writing to memory); `stream/M3500+1000_seed<S>_screening`: M3500
//!   with 1000 random false loop closures (`--seed S`, 1–7) through the screening alone, no
//!   estimate kept or read (`so2lin stream FILE --estimate none`), issue 11's cost.
//! - `step/sim<N>/{odometry,loop_closure}`: one more step on a simulated world of N poses
//!   already streamed: an odometry step to a new pose, or a loop closure re-observing the
//!   latest odometry edge (a local loop). The state keeps growing across iterations, as on a
//!   robot.
//! - `query/M3500/orientations_after_loop_closure`: M3500's last loop closure (determined)
//!   followed by `orientations()` (one back-substitution in the maintained factor);
//!   `poses_after_loop_closure` the same with `poses()` (one forward and one
//!   back-substitution); `newest_after_odometry`: an odometry step followed by `newest()`.

/// The allocator of the `so2lin` tool (mimalloc, without transparent huge pages), so that the
/// benchmark measures the steps as `so2lin stream` does: with glibc's malloc the renewal
/// builder and the robot's thread wait for each other's arena locks (module `so2lin::online`).
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

use std::hint::black_box;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use criterion::{BatchSize, Criterion, criterion_group, criterion_main};
use so2lin::graph::{Edge, Pose2};
use so2lin::io::{InfoOrder, Reader};
use so2lin::log::{LogOptions, Recorder};
use so2lin::online::{OnlineConfig, OnlineEstimator, robot_order};
use so2lin::sim::{OutlierConfig, OutlierKind, SimConfig, inject_outliers, simulate};

/// `$SO2LIN_DATASETS`, else `../shared/datasets` beside the repository.
fn dataset_dir() -> PathBuf {
    std::env::var_os("SO2LIN_DATASETS")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/datasets"))
}

fn dataset(name: &str) -> Option<Vec<Edge>> {
    let mut reader = Reader::open(dataset_dir().join(name), InfoOrder::Auto).ok()?;
    let edges = reader.edges().collect::<Result<Vec<_>, _>>().ok()?;
    Some(robot_order(&edges))
}

/// A dataset with `k` random false loop closures (the Vertigo protocol of `so2lin inject`,
/// `--seed seed`), in robot order.
fn corrupted(name: &str, k: usize, seed: u64) -> Option<Vec<Edge>> {
    let (graph, _) = so2lin::io::read_graph(dataset_dir().join(name), Default::default()).ok()?;
    let config = OutlierConfig {
        count: k,
        kind: OutlierKind::Random,
        seed,
    };
    let bad = inject_outliers(&graph, &config).ok()?;
    Some(robot_order(bad.graph.edges()))
}

fn simulated(poses: usize) -> Vec<Edge> {
    simulate(&SimConfig::new(poses, 1))
        .expect("valid config")
        .graph
        .edges()
        .to_vec()
}

/// Every edge through `add_edge` with no estimate kept or read: the screening and the
/// quarantine alone.
fn screened(edges: &[Edge]) -> OnlineEstimator {
    let config = OnlineConfig {
        estimate_every_step: false,
        ..OnlineConfig::default()
    };
    let mut est = OnlineEstimator::new(config).expect("valid config");
    for e in edges {
        est.add_edge(*e).expect("valid edge");
    }
    est
}

/// Every edge through `add_edge`, reading the newest pose after each (as a robot does).
fn streamed(edges: &[Edge]) -> OnlineEstimator {
    let mut est = OnlineEstimator::new(OnlineConfig::default()).expect("valid config");
    for e in edges {
        est.add_edge(*e).expect("valid edge");
        black_box(est.newest().expect("reads"));
    }
    est
}

fn bench_stream(c: &mut Criterion) {
    let mut inputs = vec![
        ("sim1000".to_owned(), simulated(1000)),
        ("sim10000".to_owned(), simulated(10_000)),
    ];
    for name in ["M3500.g2o", "city10000.g2o"] {
        if let Some(edges) = dataset(name) {
            inputs.push((name.trim_end_matches(".g2o").to_owned(), edges));
        }
    }
    // Issue 11's cost: M3500 with 1000 false loop closures, quarantine and evictions on.
    if let Some(edges) = corrupted("M3500.g2o", 1000, 1) {
        inputs.push(("M3500+1000".to_owned(), edges));
    }
    let mut group = c.benchmark_group("stream");
    group.sample_size(10);
    for (name, edges) in &inputs {
        group.bench_function(name.as_str(), |b| {
            b.iter(|| streamed(black_box(edges)).counters())
        });
    }
    // Issue 11's cost as it states it: the screening alone (no estimate kept or read, as
    // `so2lin stream FILE --estimate none`), M3500 + 1000 random false loop closures, the
    // seeds the README's cost paragraph reports.
    for seed in 1..=7 {
        if let Some(edges) = corrupted("M3500.g2o", 1000, seed) {
            group.bench_function(format!("M3500+1000_seed{seed}_screening"), |b| {
                b.iter(|| screened(black_box(&edges)).counters())
            });
        }
    }
    // Recording overhead: the same stream with an MCAP recorder writing to memory.
    for (name, edges) in inputs
        .iter()
        .filter(|(n, _)| n == "M3500" || n == "sim1000")
    {
        group.bench_function(format!("{name}_logged"), |b| {
            b.iter(|| {
                let config = OnlineConfig::default();
                let mut est = OnlineEstimator::new(config).expect("valid config");
                let sink = Box::new(std::io::Cursor::new(Vec::new()));
                let mut rec = Recorder::new(sink, &config, "bench", LogOptions::default())
                    .expect("in memory");
                for (k, e) in edges.iter().enumerate() {
                    rec.add_edge_at(&mut est, *e, k as u64 * 100_000_000)
                        .expect("valid edge");
                    black_box(est.newest().expect("reads"));
                }
                rec.finish(&mut est).expect("in memory")
            })
        });
    }
    group.finish();
}

/// Time `iters` steps made by `step` on a growing estimator.
fn grow(
    est: &mut OnlineEstimator,
    iters: u64,
    mut step: impl FnMut(&mut OnlineEstimator),
) -> Duration {
    let start = Instant::now();
    for _ in 0..iters {
        step(est);
    }
    start.elapsed()
}

fn bench_steps(c: &mut Criterion) {
    let mut group = c.benchmark_group("step");
    group.sample_size(20);
    for poses in [1_000usize, 10_000, 100_000] {
        let edges = simulated(poses);
        let mut est = streamed(&edges);
        let mut next = poses as u64;
        let z = Pose2::new(1.0, 0.0, 0.01);
        group.bench_function(format!("sim{poses}/odometry"), |b| {
            b.iter_custom(|iters| {
                grow(&mut est, iters, |e| {
                    let edge = Edge::with_sigmas(next - 1, next, z, 0.05, 0.05).expect("valid");
                    e.add_edge(edge).expect("accepted");
                    next += 1;
                })
            })
        });
        group.bench_function(format!("sim{poses}/loop_closure"), |b| {
            b.iter_custom(|iters| {
                grow(&mut est, iters, |e| {
                    // Odometry to a new pose, then (timed together) a loop closure to the pose
                    // before: a new local cycle of two edges.
                    let edge = Edge::with_sigmas(next - 1, next, z, 0.05, 0.05).expect("valid");
                    e.add_edge(edge).expect("accepted");
                    let lc = Edge::with_sigmas(next - 1, next, z, 0.05, 0.05).expect("valid");
                    e.add_edge(lc).expect("accepted");
                    next += 1;
                })
            })
        });
    }
    group.finish();
}

fn bench_queries(c: &mut Criterion) {
    let edges = dataset("M3500.g2o").unwrap_or_else(|| simulated(3500));
    // The stream up to (not including) its last loop closure, and that loop closure.
    let Some(cut) = edges.iter().rposition(|e| !e.is_odometric()) else {
        return;
    };
    let (prefix, closure) = (&edges[..cut], edges[cut]);
    let mut group = c.benchmark_group("query/M3500");
    group.sample_size(20);
    // A query right after a loop closure: back-substitutions in the maintained factors.
    type Query = fn(&mut OnlineEstimator) -> usize;
    let queries: [(&str, Query); 2] = [
        ("orientations_after_loop_closure", |est| {
            est.orientations().map(|t| t.len()).expect("solves")
        }),
        ("poses_after_loop_closure", |est| {
            est.poses().map(|p| p.len()).expect("solves")
        }),
    ];
    for (name, query) in queries {
        group.bench_function(name, |b| {
            b.iter_batched(
                || {
                    let mut est = streamed(prefix);
                    est.orientations().expect("solves");
                    est
                },
                |mut est| {
                    est.add_edge(closure).expect("accepted");
                    query(&mut est)
                },
                BatchSize::PerIteration,
            )
        });
    }
    let mut est = streamed(&edges);
    est.orientations().expect("solves");
    let mut prev = edges
        .iter()
        .map(|e| e.from().max(e.to()))
        .max()
        .unwrap_or(0);
    let z = Pose2::new(1.0, 0.0, 0.0);
    group.bench_function("newest_after_odometry", |b| {
        b.iter(|| {
            let odo = Edge::with_sigmas(prev, prev + 1, z, 0.05, 0.05).expect("valid");
            est.add_edge(odo).expect("accepted");
            prev += 1;
            est.newest().expect("reads")
        })
    });
    group.finish();
}

criterion_group!(benches, bench_stream, bench_steps, bench_queries);
criterion_main!(benches);
