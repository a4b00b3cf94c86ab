//! What `kill -9` during a logged run loses (`cargo bench --bench log_kill [-- FILE] [--runs N]`).
//!
//! The bench runs itself as a child process that streams FILE (default M3500.g2o from the
//! datasets folder) in robot order exactly as `so2lin stream FILE --log LOG` does — each edge
//! through `add_edge`, the newest pose read, the step recorded with the default
//! [`LogOptions`] — except that every step is stamped with the wall clock, and that after
//! recording step k the child writes k to its stdout (a pipe the parent reads and timestamps).
//! The parent first times one whole run, then kills N children (default 30) with SIGKILL at
//! uniformly random times (a fixed seed) during their runs, reads each log with
//! [`read_log`], and prints per run and in the worst case:
//!
//! - **lost steps**: steps the child had recorded before the kill minus steps in the log;
//! - **lost time**: how long before the kill the oldest lost step was recorded.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use rand_chacha::ChaCha8Rng;
use rand_chacha::rand_core::{Rng, SeedableRng};
use so2lin::graph::Edge;
use so2lin::io::{InfoOrder, Reader};
use so2lin::log::{LogOptions, Recorder, read_log};
use so2lin::online::{OnlineConfig, OnlineEstimator, robot_order};

const CHILD: &str = "SO2LIN_LOG_KILL_CHILD";

fn edges(path: &Path) -> Vec<Edge> {
    let mut reader = Reader::open(path, InfoOrder::Auto).expect("readable graph file");
    let edges = reader
        .edges()
        .collect::<Result<Vec<_>, _>>()
        .expect("valid edges");
    robot_order(&edges)
}

fn wall_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// The child: stream and record, reporting every recorded step on stdout.
fn child(file: &Path, log: &Path) {
    let edges = edges(file);
    let config = OnlineConfig::default();
    let mut est = OnlineEstimator::new(config).expect("default config");
    let mut rec = Recorder::create(
        log,
        &config,
        &file.display().to_string(),
        LogOptions::default(),
    )
    .expect("log file");
    let mut out = std::io::stdout().lock();
    for (k, &edge) in edges.iter().enumerate() {
        let t = Instant::now();
        let step = est.add_edge(edge).expect("valid edge");
        let _ = est.newest();
        let ns = t.elapsed().as_nanos() as u64;
        rec.record(&edge, &step, ns, wall_ns(), &mut est);
        out.write_all(&(k as u32).to_le_bytes()).expect("pipe");
        out.flush().expect("pipe");
    }
    let b = rec.backpressure();
    rec.finish(&mut est).expect("log finished");
    eprintln!("child: {} steps, backpressure {b:?}", edges.len());
}

struct Run {
    recorded: usize,
    in_log: usize,
    lost_ms: f64,
    kill_ms: f64,
}

/// One child, killed `kill_after` after its first step (never, if `None`).
fn run(file: &Path, log: &Path, kill_after: Option<Duration>) -> (Run, Duration) {
    let mut child = Command::new(std::env::current_exe().expect("own path"))
        .env(CHILD, log)
        .arg(file)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("child");
    let mut pipe = child.stdout.take().expect("piped stdout");
    let reader = std::thread::spawn(move || {
        let mut seen = Vec::new();
        let mut word = [0u8; 4];
        while pipe.read_exact(&mut word).is_ok() {
            seen.push(Instant::now());
        }
        seen
    });
    // The first step starts the clock (loading the file is not part of the run).
    let first = loop {
        if let Ok(Some(_)) = child.try_wait() {
            break Instant::now();
        }
        let size = std::fs::metadata(log).map_or(0, |m| m.len());
        if size > 0 {
            break Instant::now();
        }
        std::thread::sleep(Duration::from_micros(200));
    };
    let mut killed = None;
    if let Some(after) = kill_after {
        std::thread::sleep(after);
        killed = Some(Instant::now());
        let _ = child.kill();
    }
    let _ = child.wait();
    let seen = reader.join().expect("reader");
    let end = killed.unwrap_or_else(Instant::now);
    let bytes = std::fs::read(log).expect("log written");
    let in_log = read_log(&bytes).map_or(0, |l| l.steps.len());
    let recorded = seen.len();
    let lost_ms = match seen.get(in_log) {
        Some(t) if in_log < recorded => end.duration_since(*t).as_secs_f64() * 1e3,
        _ => 0.0,
    };
    let kill_ms = end.duration_since(first).as_secs_f64() * 1e3;
    (
        Run {
            recorded,
            in_log,
            lost_ms,
            kill_ms,
        },
        end.duration_since(first),
    )
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let file = args
        .iter()
        .find(|a| !a.starts_with("--") && Path::new(a).is_file())
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            std::env::var_os("SO2LIN_DATASETS")
                .map(PathBuf::from)
                .unwrap_or_else(|| {
                    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/datasets")
                })
                .join("M3500.g2o")
        });
    if let Some(log) = std::env::var_os(CHILD) {
        child(&file, Path::new(&log));
        return;
    }
    let runs: usize = args
        .iter()
        .position(|a| a == "--runs")
        .and_then(|k| args.get(k + 1)?.parse().ok())
        .unwrap_or(30);
    if !file.is_file() {
        eprintln!("log_kill: {} not found; skipped", file.display());
        return;
    }
    let log = std::env::temp_dir().join(format!("so2lin-log-kill-{}.mcap", std::process::id()));
    let _ = std::fs::remove_file(&log);
    let (full, length) = run(&file, &log, None);
    assert_eq!(
        full.in_log, full.recorded,
        "an unkilled run logs every step"
    );
    println!(
        "{}: {} steps, run {:.0} ms without a kill (default LogOptions: {:?})",
        file.display(),
        full.recorded,
        length.as_secs_f64() * 1e3,
        LogOptions::default()
    );
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let (mut worst_steps, mut worst_ms) = (0, 0.0f64);
    for r in 0..runs {
        let _ = std::fs::remove_file(&log);
        let u = (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        let after = length.mul_f64(0.02 + 0.96 * u);
        let (k, _) = run(&file, &log, Some(after));
        let lost = k.recorded - k.in_log.min(k.recorded);
        worst_steps = worst_steps.max(lost);
        worst_ms = worst_ms.max(k.lost_ms);
        println!(
            "run {r:>2}: killed at {:>7.1} ms after step {:>5}: {:>5} in the log, lost {lost:>3} steps, the oldest recorded {:.2} ms before the kill",
            k.kill_ms, k.recorded, k.in_log, k.lost_ms
        );
    }
    let _ = std::fs::remove_file(&log);
    println!(
        "worst of {runs} kills: {worst_steps} steps lost, the oldest recorded {worst_ms:.2} ms before the kill"
    );
}
