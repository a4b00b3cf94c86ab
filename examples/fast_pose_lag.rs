//! How far the fast newest pose a robot reads after every step (`OnlineEstimator::newest`,
//! O(1)) is from the exact pose of the same linear estimate (`poses()`, every position row at
//! the current headings).
//!
//! ```text
//! cargo run --release --example fast_pose_lag -- FILE [every]
//! ```
//!
//! Streams the file's edges in robot order, reads the newest pose after every step and, every
//! `every` steps (default 25), compares it with the exact one: prints the mean and the largest
//! distance, and how many times every position row was re-linearised because the headings had
//! moved too far since (the bound of the `online::estimate` module docs).

use std::process::ExitCode;

use so2lin::io::{InfoOrder, Reader};
use so2lin::online::{OnlineConfig, OnlineEstimator, robot_order};

fn run(path: &str, every: usize) -> Result<(), String> {
    let mut reader = Reader::open(std::path::Path::new(path), InfoOrder::Auto)
        .map_err(|e| format!("{path}: {e}"))?;
    let edges = reader
        .edges()
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| format!("{path}: {e}"))?;
    let mut est = OnlineEstimator::new(OnlineConfig::default()).map_err(|e| e.to_string())?;
    let (mut sum, mut worst, mut checks) = (0.0, 0.0_f64, 0);
    for (i, e) in robot_order(&edges).iter().enumerate() {
        est.add_edge(*e).map_err(|e| e.to_string())?;
        let Some((id, fast)) = est.newest().map_err(|e| e.to_string())? else {
            continue;
        };
        if i % every != 0 {
            continue;
        }
        let Some(v) = est.graph().node_index(id) else {
            continue;
        };
        let exact = est.poses().map_err(|e| e.to_string())?[v];
        let d = (fast.x - exact.x).hypot(fast.y - exact.y);
        sum += d;
        worst = worst.max(d);
        checks += 1;
    }
    let c = est.counters();
    println!(
        "{path}: {checks} checks (every {every} steps, robot order): the fast newest pose is \
         {:.3} m from the exact one on average, {worst:.3} m at worst; {} re-linearisations, \
         {} renewals",
        sum / checks.max(1) as f64,
        c.estimate_relinearisations,
        c.estimate_renewals
    );
    Ok(())
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1) else {
        eprintln!("usage: fast_pose_lag FILE [every]");
        return ExitCode::FAILURE;
    };
    let every = match args.get(2).map(|s| s.parse::<usize>()) {
        None => 25,
        Some(Ok(n)) if n > 0 => n,
        Some(_) => {
            eprintln!("every: a positive number of steps");
            return ExitCode::FAILURE;
        }
    };
    match run(path, every) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("{e}");
            ExitCode::FAILURE
        }
    }
}
