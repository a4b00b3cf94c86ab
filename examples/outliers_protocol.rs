//! The outlier protocol of issue 11 (method §11, Vertigo): inject K false loop closures into a
//! dataset (`sim::inject_outliers`, as `so2lin inject`), then
//!
//! - **stream** it as `so2lin stream` does by default (robot order, quarantine on, the newest
//!   pose read after every step): precision and recall of the quarantined set against the
//!   injected one, and the streaming time;
//! - **solve** it as `so2lin solve` does by default (family-wise screening, best hypothesis,
//!   `batch::solve_robust` with its defaults): success when the solution's SE(2) cost on the
//!   clean graph is within 1 % of the clean graph's own optimum (solved the same way).
//!
//! Prints one Markdown row per (file, kind, K) with the counts pooled over the seeds.
//!
//! ```text
//! cargo run --release --example outliers_protocol -- DATASET_DIR [FILE…] [--seeds N] [--k K,K,…]
//! ```
//!
//! Defaults: M3500, intel and city10000; K = 1, 10, 100 (and 1000 on M3500); 3 seeds.

use std::path::PathBuf;
use std::time::Instant;

use so2lin::batch::{BatchConfig, RobustConfig, screen, solve_robust};
use so2lin::estimate::OrientationEstimator;
use so2lin::graph::{Pose2, PoseGraph};
use so2lin::online::{OnlineConfig, OnlineEstimator, robot_order_indices};
use so2lin::refine::{RefineConfig, cost};
use so2lin::sim::{OutlierConfig, OutlierKind, inject_outliers};

/// The refined poses of `so2lin solve`'s default pipeline.
fn solve(g: &PoseGraph) -> Result<Vec<Pose2>, String> {
    let r = screen(g, &BatchConfig::default()).map_err(|e| e.to_string())?;
    let h = r.hypotheses.first().ok_or("no hypothesis")?;
    let orient = OrientationEstimator::new(g).map_err(|e| e.to_string())?;
    let s = solve_robust(
        g,
        &r,
        &orient,
        h,
        &RefineConfig::default(),
        &RobustConfig::default(),
    )
    .map_err(|e| e.to_string())?;
    Ok(s.refined.poses)
}

/// The quarantined edges (indices in `g`) of `so2lin stream`'s default run, and its seconds.
fn stream(g: &PoseGraph) -> Result<(Vec<usize>, f64), String> {
    let order = robot_order_indices(g.edges());
    let t = Instant::now();
    let mut est = OnlineEstimator::new(OnlineConfig::default()).map_err(|e| e.to_string())?;
    for &i in &order {
        est.add_edge(g.edges()[i]).map_err(|e| e.to_string())?;
        est.newest().map_err(|e| e.to_string())?;
    }
    let seconds = t.elapsed().as_secs_f64();
    Ok((
        est.rejected().iter().map(|r| order[r.edge]).collect(),
        seconds,
    ))
}

fn main() -> Result<(), String> {
    let mut args = std::env::args().skip(1);
    let dir = PathBuf::from(
        args.next()
            .ok_or("usage: DATASET_DIR [FILE…] [--seeds N]")?,
    );
    let (mut files, mut seeds, mut ks) = (Vec::new(), 3u64, None);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--seeds" => {
                seeds = args
                    .next()
                    .and_then(|s| s.parse().ok())
                    .ok_or("--seeds N")?
            }
            "--k" => {
                ks = Some(
                    args.next()
                        .ok_or("--k K,K")?
                        .split(',')
                        .map(|k| k.parse::<usize>().map_err(|e| e.to_string()))
                        .collect::<Result<Vec<_>, _>>()?,
                )
            }
            f => files.push(f.to_owned()),
        }
    }
    if files.is_empty() {
        files = vec![
            "M3500.g2o".into(),
            "intel.g2o".into(),
            "city10000.g2o".into(),
        ];
    }
    println!(
        "| file | kind | K | runs | solve: outlier-free solution | stream: precision | stream: recall | stream seconds (mean) |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for file in &files {
        let (clean, _) = so2lin::io::read_graph(dir.join(file), Default::default())
            .map_err(|e| e.to_string())?;
        let optimum = cost(&clean, &solve(&clean)?);
        let mut kset = ks.clone().unwrap_or_else(|| vec![1, 10, 100]);
        if ks.is_none() && file.starts_with("M3500") {
            kset.push(1000);
        }
        for kind in [OutlierKind::Random, OutlierKind::Clustered] {
            for &k in &kset {
                let (mut ok, mut runs, mut tp, mut flagged, mut injected, mut secs) =
                    (0, 0, 0, 0, 0, 0.0);
                for seed in 1..=seeds {
                    let bad = inject_outliers(
                        &clean,
                        &OutlierConfig {
                            count: k,
                            kind,
                            seed,
                        },
                    )
                    .map_err(|e| e.to_string())?;
                    let (rejected, s) = stream(&bad.graph)?;
                    secs += s;
                    tp += rejected.iter().filter(|&&e| bad.is_false(e)).count();
                    flagged += rejected.len();
                    injected += bad.false_edges.len();
                    runs += 1;
                    let poses = solve(&bad.graph);
                    let success = poses.map(|p| {
                        let on_clean: Vec<Pose2> = clean
                            .nodes()
                            .iter()
                            .map(|n| bad.graph.node_index(n.id).map_or(Pose2::default(), |v| p[v]))
                            .collect();
                        let c = cost(&clean, &on_clean);
                        eprintln!("{file} {kind:?} K={k} seed {seed}: cost {c:.6e} vs optimum {optimum:.6e}, stream caught {}/{} ({} flagged)", rejected.iter().filter(|&&e| bad.is_false(e)).count(), bad.false_edges.len(), rejected.len());
                        c <= 1.01 * optimum
                    });
                    ok += usize::from(success.unwrap_or(false));
                }
                let ratio = |a: usize, b: usize| {
                    if b == 0 {
                        "–".to_owned()
                    } else {
                        format!("{:.3} ({a}/{b})", a as f64 / b as f64)
                    }
                };
                println!(
                    "| {file} | {} | {k} | {runs} | {ok}/{runs} | {} | {} | {:.3} |",
                    match kind {
                        OutlierKind::Random => "random",
                        OutlierKind::Clustered => "clustered",
                    },
                    ratio(tp, flagged),
                    ratio(tp, injected),
                    secs / runs as f64
                );
            }
        }
    }
    Ok(())
}
