//! MCAP logs: record while streaming, replay bit for bit, survive being cut anywhere.

mod common;

use std::io::{Cursor, Seek, SeekFrom, Write};

use so2lin::graph::Edge;
use so2lin::log::{LogOptions, Recorder, read_log, replay};
use so2lin::online::{OnlineConfig, OnlineEstimator, StepKind, robot_order};
use so2lin::sim::{SimConfig, simulate};

use common::SharedSink as Shared;

/// Record a run; returns the log bytes and, for every step the documented flush policy
/// flushes (every loop closure, and at least every `flush_every` steps), the sink length
/// right after it (`None` for steps not flushed yet).
fn record(edges: &[Edge], options: LogOptions) -> (Vec<u8>, Vec<Option<usize>>) {
    record_with(edges, options, OnlineConfig::default())
}

/// [`record`] with `config`.
fn record_with(
    edges: &[Edge],
    options: LogOptions,
    config: OnlineConfig,
) -> (Vec<u8>, Vec<Option<usize>>) {
    let sink = Shared::default();
    let mut est = OnlineEstimator::new(config).unwrap();
    let mut rec = Recorder::new(Box::new(sink.clone()), &config, "test", options).unwrap();
    let mut lengths = Vec::new();
    let mut since = 0;
    for e in edges {
        let step = rec.add_edge(&mut est, *e).unwrap();
        since += 1;
        let flushed = (options.flush_on_loop_closure && matches!(step.kind, StepKind::Cycle(_)))
            || since >= options.flush_every;
        if flushed {
            since = 0;
            // The writer thread flushes on its own; wait for it to reach this step.
            rec.sync().unwrap();
        }
        lengths.push(flushed.then(|| sink.len()));
    }
    assert_eq!(rec.finish(&mut est).unwrap(), edges.len() as u64);
    (sink.bytes(), lengths)
}

fn assert_replays(name: &str, edges: &[Edge]) {
    assert_replays_with(name, edges, OnlineConfig::default());
}

/// [`assert_replays`] of a run with `config`: the replay must rebuild it from the log.
fn assert_replays_with(name: &str, edges: &[Edge], config: OnlineConfig) {
    let (bytes, _) = record_with(edges, LogOptions::default(), config);
    let log = read_log(&bytes).unwrap();
    assert_eq!(log.config().unwrap(), config, "{name}: settings recorded");
    assert!(log.truncated.is_none(), "{name}: {:?}", log.truncated);
    assert_eq!(
        log.edges.as_slice(),
        edges,
        "{name}: edges recorded exactly"
    );
    let r = replay(&log, true).unwrap();
    assert_eq!(r.steps, edges.len());
    assert!(r.divergence.is_none(), "{name}: {:?}", r.divergence);
}

#[test]
fn datasets_and_simulated_worlds_replay_without_divergence() {
    for seed in 0..6 {
        let w = simulate(&SimConfig {
            sigma_theta: 0.04 * (seed + 1) as f64,
            ..SimConfig::new(800, seed)
        })
        .unwrap();
        assert_replays(&format!("sim {seed}"), w.graph.edges());
        // Screened through P_UU alone (moments not bit-identical to the default's): the
        // replay must take the setting from the log to reproduce them.
        let lazy = OnlineConfig {
            estimate_every_step: false,
            ..OnlineConfig::default()
        };
        assert_replays_with(&format!("sim {seed}, lazy"), w.graph.edges(), lazy);
        // Renewals swapped in sooner (at other steps, so other bits): the replay takes the
        // delay from the log too.
        let sooner = OnlineConfig {
            renewal_delay: 0.25,
            ..OnlineConfig::default()
        };
        assert_replays_with(&format!("sim {seed}, sooner"), w.graph.edges(), sooner);
    }
    for name in ["intel.g2o", "M3500b.g2o"] {
        let Some(path) = common::dataset(name) else {
            return;
        };
        let edges: Vec<Edge> = common::edges_of(&path);
        assert_replays(name, &edges);
    }
}

#[test]
fn a_log_cut_anywhere_replays_every_flushed_step() {
    for flush_on_loop_closure in [true, false] {
        cut_anywhere(LogOptions {
            snapshot_every: 100,
            flush_every: 16,
            flush_on_loop_closure,
            ..LogOptions::default()
        });
    }
}

fn cut_anywhere(options: LogOptions) {
    let w = simulate(&SimConfig::new(600, 21)).unwrap();
    let edges = w.graph.edges();
    let (bytes, lengths) = record(edges, options);
    // Steps up to k are in the file once the flush at step k reached the sink.
    let flushed_by = |cut: usize| {
        (0..edges.len())
            .filter(|&k| lengths[k].is_some_and(|l| l <= cut))
            .map(|k| k + 1)
            .max()
            .unwrap_or(0)
    };
    let mut seen = 0;
    for i in 0..50 {
        let cut = 9 + (bytes.len() - 10) * i / 49;
        let log = match read_log(&bytes[..cut]) {
            Ok(log) => log,
            // Cut before the metadata record: nothing was recorded yet.
            Err(e) => {
                assert_eq!(flushed_by(cut), 0, "cut {cut}: {e}");
                continue;
            }
        };
        let want = flushed_by(cut);
        // Every step flushed before the cut is there (a chunk still open at the cut may
        // have reached the file too if it was written before the next flush).
        assert!(
            log.steps.len() >= want,
            "cut at {cut}: read {} < flushed {want}",
            log.steps.len()
        );
        assert!(cut == bytes.len() || log.truncated.is_some());
        let r = replay(&log, true).unwrap();
        assert!(r.divergence.is_none());
        assert_eq!(r.steps, log.steps.len());
        seen = seen.max(r.steps);
    }
    assert_eq!(seen, edges.len());
}

#[test]
fn corrupt_and_foreign_files_are_errors() {
    assert!(read_log(b"").is_err());
    assert!(read_log(b"EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n").is_err());
    let w = simulate(&SimConfig::new(100, 3)).unwrap();
    let (mut bytes, _) = record(w.graph.edges(), LogOptions::default());
    // Flip bytes in the middle: whatever survives must replay or fail cleanly, never panic.
    for k in (20..bytes.len()).step_by(97) {
        bytes[k] ^= 0x5a;
        if let Ok(log) = read_log(&bytes) {
            let _ = replay(&log, true);
        }
    }
}

/// A file that cannot grow beyond `limit` bytes.
struct Failing {
    file: Cursor<Vec<u8>>,
    limit: u64,
}

impl Write for Failing {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        if self.file.position() + buf.len() as u64 > self.limit {
            return Err(std::io::Error::other("disk full"));
        }
        self.file.write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Seek for Failing {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        self.file.seek(pos)
    }
}

#[test]
fn a_failing_sink_is_reported_and_never_fails_a_step() {
    let w = simulate(&SimConfig::new(300, 5)).unwrap();
    let config = OnlineConfig::default();
    let mut plain = OnlineEstimator::new(config).unwrap();
    let mut logged = OnlineEstimator::new(config).unwrap();
    let sink = Failing {
        file: Cursor::new(Vec::new()),
        limit: 20_000,
    };
    let mut rec = Recorder::new(Box::new(sink), &config, "test", LogOptions::default()).unwrap();
    for e in w.graph.edges() {
        let a = plain.add_edge(*e).unwrap();
        let b = rec.add_edge(&mut logged, *e).unwrap();
        assert_eq!(a, b);
    }
    let sync = rec.sync();
    assert!(sync.is_err());
    let err = rec.error().unwrap();
    assert!(err.contains("disk full"), "{err}");
    assert!(rec.finish(&mut logged).is_err());
    assert_eq!(
        plain.orientations().unwrap(),
        logged.orientations().unwrap()
    );
}

#[test]
fn a_recorder_dropped_without_finish_leaves_a_complete_file() {
    let w = simulate(&SimConfig::new(200, 8)).unwrap();
    let sink = Shared::default();
    let config = OnlineConfig::default();
    let mut est = OnlineEstimator::new(config).unwrap();
    let mut rec =
        Recorder::new(Box::new(sink.clone()), &config, "t", LogOptions::default()).unwrap();
    for e in w.graph.edges() {
        rec.add_edge(&mut est, *e).unwrap();
    }
    drop(rec);
    let log = read_log(&sink.bytes()).unwrap();
    assert!(log.truncated.is_none(), "{:?}", log.truncated);
    assert_eq!(log.steps.len(), w.graph.edge_count());
}

/// `replay --verify` checks the estimate, not only the steps' outcomes: the newest pose after
/// every step (in full precision in the step message, and as displayed on `/pose`) and every
/// snapshot's orientations and poses. A log with any one of them changed — by one unit in the
/// last place for the full-precision values — diverges at that step, on that channel.
#[test]
fn a_replay_checks_the_newest_poses_and_the_snapshots() {
    let w = simulate(&SimConfig::new(600, 5)).unwrap();
    let options = LogOptions {
        snapshot_every: 50,
        ..LogOptions::default()
    };
    let (bytes, _) = record(w.graph.edges(), options);
    let log = read_log(&bytes).unwrap();
    let r = replay(&log, true).unwrap();
    assert!(r.divergence.is_none(), "{:?}", r.divergence);
    let n = log.steps.len();
    assert_eq!(log.newest.len(), n, "a /pose message every step");
    assert!(log.steps.iter().all(|s| s["newest"]["theta"].is_f64()));
    assert_eq!(
        log.estimates.len(),
        n / 50 + 1,
        "snapshots every 50 steps and at the end"
    );
    assert_eq!(log.poses.len(), log.estimates.len());
    let next_up = |v: &mut serde_json::Value| {
        let x = v.as_f64().unwrap();
        *v = serde_json::json!(f64::from_bits(x.to_bits() + 1));
    };
    let up = |x: &mut f64| *x = f64::from_bits(x.to_bits() + 1);
    let up32 = |x: &mut f32| *x = f32::from_bits(x.to_bits() + 1);
    let k = n / 2;
    let (at, _) = log.estimates[3];
    type Tamper<'a> = Box<dyn Fn(&mut so2lin::log::LogContents) + 'a>;
    let tampered: [(&str, usize, Tamper); 5] = [
        (
            "/so2lin/step",
            k,
            Box::new(|l| next_up(&mut l.steps[k]["newest"]["x"])),
        ),
        (
            "/so2lin/step",
            k,
            Box::new(|l| next_up(&mut l.steps[k]["newest"]["theta"])),
        ),
        (
            "/pose",
            k,
            Box::new(|l| up32(&mut l.newest.get_mut(&(k as u64)).unwrap()[1])),
        ),
        (
            "/so2lin/estimate",
            at as usize - 1,
            Box::new(|l| up(&mut l.estimates[3].1[7])),
        ),
        (
            "/poses",
            at as usize - 1,
            Box::new(|l| up32(&mut l.poses[3].1[7][0])),
        ),
    ];
    // A log of schema version 1 (steps without the newest pose) verifies against `/pose`.
    let mut older = read_log(&bytes).unwrap();
    for s in &mut older.steps {
        s.as_object_mut().unwrap().remove("newest");
    }
    assert!(replay(&older, true).unwrap().divergence.is_none());
    up32(&mut older.newest.get_mut(&(k as u64)).unwrap()[0]);
    let d = replay(&older, true).unwrap().divergence.unwrap();
    assert_eq!((d.channel, d.step), ("/pose", k));
    for (channel, step, tamper) in tampered {
        let mut bad = read_log(&bytes).unwrap();
        tamper(&mut bad);
        let d = replay(&bad, true).unwrap().divergence;
        let d = d.unwrap_or_else(|| panic!("{channel} changed at step {step}: not found"));
        assert_eq!((d.channel, d.step), (channel, step));
    }
}

/// `/poses` holds `OnlineEstimator::poses()` of the step it was taken at (periodic snapshots
/// and the final one, all from the maintained factors).
#[test]
fn pose_snapshots_are_the_estimators_poses() {
    let mut c = SimConfig::new(500, 12);
    c.sigma_theta = 0.1;
    let w = simulate(&c).unwrap();
    let sink = Shared::default();
    let config = OnlineConfig::default();
    let options = LogOptions {
        snapshot_every: 150,
        ..LogOptions::default()
    };
    let mut est = OnlineEstimator::new(config).unwrap();
    let mut rec = Recorder::new(Box::new(sink.clone()), &config, "t", options).unwrap();
    let mut expected = Vec::new();
    for (k, e) in w.graph.edges().iter().enumerate() {
        rec.add_edge(&mut est, *e).unwrap();
        if (k + 1) % 150 == 0 {
            expected.push(est.poses().unwrap());
        }
    }
    expected.push(est.poses().unwrap());
    rec.finish(&mut est).unwrap();
    let bytes = sink.bytes();
    let mut recorded = Vec::new();
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        if m.channel.topic == "/poses" {
            let v: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
            recorded.push(v["poses"].as_array().unwrap().clone());
        }
    }
    assert_eq!(recorded.len(), expected.len());
    for (got, want) in recorded.iter().zip(&expected) {
        assert_eq!(got.len(), want.len());
        for (g, p) in got.iter().zip(want) {
            let x = g["position"]["x"].as_f64().unwrap();
            let y = g["position"]["y"].as_f64().unwrap();
            let qz = g["orientation"]["z"].as_f64().unwrap();
            // Display channels: millimetres (and 1e-6 for quaternions), single precision.
            assert!((x - p.x).abs() <= 6e-4 + 1e-6 * p.x.abs(), "{x} vs {}", p.x);
            assert!((y - p.y).abs() <= 6e-4 + 1e-6 * p.y.abs(), "{y} vs {}", p.y);
            assert!((qz - (0.5 * p.theta).sin()).abs() <= 1e-6);
        }
    }
}

/// Every step's messages carry the caller's time (log time, publish time and Foxglove
/// timestamps agree), the newest pose goes out every step on `/pose`, snapshots come every
/// `snapshot_every` steps, and the log still replays exactly.
#[test]
fn caller_times_and_the_newest_pose_are_in_every_step() {
    let w = simulate(&SimConfig::new(300, 3)).unwrap();
    let sink = Shared::default();
    let config = OnlineConfig::default();
    let options = LogOptions::default();
    let mut est = OnlineEstimator::new(config).unwrap();
    let mut rec = Recorder::new(Box::new(sink.clone()), &config, "t", options).unwrap();
    let t0 = 1_700_000_000_000_000_000u64;
    let mut newest = Vec::new();
    for (k, e) in w.graph.edges().iter().enumerate() {
        rec.add_edge_at(&mut est, *e, t0 + k as u64 * 100_000_000)
            .unwrap();
        newest.push(est.newest().unwrap().unwrap().1);
    }
    rec.finish(&mut est).unwrap();
    let bytes = sink.bytes();
    let (mut poses, mut snapshots) = (0usize, 0usize);
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        assert_eq!(m.log_time, m.publish_time);
        assert!(m.log_time >= t0 && m.log_time < t0 + 1000 * 100_000_000);
        let v: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
        let stamp = v
            .get("timestamp")
            .or_else(|| v["entities"][0].get("timestamp"));
        if let Some(s) = stamp {
            let ns = s["sec"].as_u64().unwrap() * 1_000_000_000 + s["nsec"].as_u64().unwrap();
            assert_eq!(ns, m.log_time, "{}", m.channel.topic);
        }
        if m.channel.topic == "/pose" {
            let k = ((m.log_time - t0) / 100_000_000) as usize;
            let p = &v["pose"]["position"];
            // Display channels carry f32 coordinates.
            assert!((p["x"].as_f64().unwrap() - newest[k].x).abs() < 1e-3);
            poses += 1;
        }
        if m.channel.topic == "/poses" {
            snapshots += 1;
        }
    }
    assert_eq!(poses, w.graph.edge_count());
    assert_eq!(snapshots, w.graph.edge_count() / options.snapshot_every + 1);
    let log = read_log(&bytes).unwrap();
    let replay = so2lin::log::replay(&log, true).unwrap();
    assert_eq!(replay.steps, w.graph.edge_count());
}

/// A valid graph whose angle information alternates 1e12 and 1e-12 (issue: the writer's
/// snapshot solve failed at a snapshot and every later step was dropped): every step is
/// recorded and replays, whatever the snapshots do, and a snapshot that cannot be computed
/// would be said on `/so2lin/log`, never cost a step.
#[test]
fn extreme_information_never_costs_a_step() {
    let w = simulate(&SimConfig::new(400, 9)).unwrap();
    let edges: Vec<Edge> = w
        .graph
        .edges()
        .iter()
        .enumerate()
        .map(|(k, e)| {
            let info = so2lin::graph::Information::diagonal(
                100.0,
                100.0,
                if k % 2 == 0 { 1e12 } else { 1e-12 },
            );
            Edge::new(e.from(), e.to(), e.measurement(), info).unwrap()
        })
        .collect();
    let options = LogOptions {
        snapshot_every: 7,
        ..LogOptions::default()
    };
    let (bytes, _) = record(&edges, options);
    let log = read_log(&bytes).unwrap();
    assert!(log.truncated.is_none(), "{:?}", log.truncated);
    assert_eq!(log.steps.len(), edges.len());
    let replay = so2lin::log::replay(&log, true).unwrap();
    assert!(replay.divergence.is_none());
    assert_eq!(replay.steps, edges.len());
}

/// The crash bound: after every recorded step, the bytes already in the sink (what a
/// `kill -9` would leave) hold all but at most `max_backlog` of the steps — whatever the
/// writer's speed, because a step beyond waits for the writer's flush. Here only that bound
/// makes the writer flush (no loop-closure flushes, `flush_every` and the interval out of
/// reach), so the old writer, which flushed every `flush_every` steps, fails at step 9.
#[test]
fn a_crash_loses_at_most_max_backlog_steps() {
    const MAX: usize = 8;
    let w = simulate(&SimConfig::new(300, 13)).unwrap();
    let edges = w.graph.edges();
    let options = LogOptions {
        snapshot_every: 50,
        flush_every: 10_000,
        flush_on_loop_closure: false,
        flush_interval_ms: 1_000_000,
        max_backlog: MAX,
    };
    let sink = Shared::default();
    let config = OnlineConfig::default();
    let mut est = OnlineEstimator::new(config).unwrap();
    let mut rec = Recorder::new(Box::new(sink.clone()), &config, "t", options).unwrap();
    for (k, e) in edges.iter().enumerate() {
        rec.add_edge(&mut est, *e).unwrap();
        let log = read_log(&sink.bytes()).unwrap();
        assert!(
            (k + 1).saturating_sub(log.steps.len()) <= MAX,
            "after step {k}: {} steps in the file",
            log.steps.len()
        );
        let r = replay(&log, true).unwrap();
        assert!(r.divergence.is_none());
    }
    // Only the bound flushed, so steps did wait for it.
    let b = rec.backpressure();
    assert!(b.steps_waited >= (edges.len() / MAX - 1) as u64, "{b:?}");
    assert_eq!(rec.finish(&mut est).unwrap(), edges.len() as u64);
}

/// The time bound: a step no other rule would flush (no loop closure, far fewer than
/// `flush_every` steps, no `sync`) reaches the sink once it is `flush_interval_ms` old. The
/// test waits for that condition (failing only if it never comes within a minute); the old
/// writer never flushed these steps before `finish`.
#[test]
fn an_idle_writer_flushes_within_the_interval() {
    let options = LogOptions {
        flush_every: 10_000,
        max_backlog: 10_000,
        flush_interval_ms: 5,
        ..LogOptions::default()
    };
    let sink = Shared::default();
    let config = OnlineConfig::default();
    let mut est = OnlineEstimator::new(config).unwrap();
    let mut rec = Recorder::new(Box::new(sink.clone()), &config, "t", options).unwrap();
    let info = so2lin::graph::Information::diagonal(100.0, 100.0, 1000.0);
    for k in 0..3u64 {
        let e = Edge::new(k, k + 1, so2lin::graph::Pose2::new(1.0, 0.0, 0.1), info).unwrap();
        assert!(matches!(
            rec.add_edge(&mut est, e).unwrap().kind,
            StepKind::Tree { .. }
        ));
    }
    let start = std::time::Instant::now();
    let steps = loop {
        let n = read_log(&sink.bytes()).unwrap().steps.len();
        if n == 3 || start.elapsed().as_secs() >= 60 {
            break n;
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    };
    assert_eq!(steps, 3, "the steps never reached the sink");
    rec.finish(&mut est).unwrap();
}

/// A run with quarantined loop closures replays bit for bit (the quarantine is in the metadata
/// and every step), its `/so2lin/step` messages carry `quarantined`, and the last `/graph`
/// draws each quarantined edge in its own line list (the fourth), by its input index.
#[test]
fn quarantined_edges_are_recorded_replayed_and_drawn() {
    use so2lin::sim::{OutlierConfig, OutlierKind, inject_outliers};
    let w = simulate(&SimConfig::new(400, 21)).unwrap();
    let bad = inject_outliers(
        &w.graph,
        &OutlierConfig {
            count: 10,
            kind: OutlierKind::Random,
            seed: 3,
        },
    )
    .unwrap();
    let edges = bad.graph.edges();
    let (bytes, _) = record(edges, LogOptions::default());
    let log = read_log(&bytes).unwrap();
    assert_eq!(
        log.metadata.get("quarantine").map(String::as_str),
        Some("true")
    );
    let r = replay(&log, true).unwrap();
    assert!(r.divergence.is_none(), "{:?}", r.divergence);
    let mut est = r.estimator;
    let rejected: Vec<usize> = est.rejected().iter().map(|x| x.edge).collect();
    assert!(!rejected.is_empty(), "nothing quarantined");
    let in_steps: Vec<u64> = log
        .steps
        .iter()
        .filter_map(|s| s["quarantined"][0]["edge"].as_u64())
        .collect();
    assert!(rejected.iter().all(|&e| in_steps.contains(&(e as u64))));
    // The final /graph: the fourth line list holds both ends of every quarantined edge.
    let mut last_graph = None;
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        if m.channel.topic == "/graph" {
            last_graph = Some(serde_json::from_slice::<serde_json::Value>(&m.data).unwrap());
        }
    }
    let g = last_graph.expect("a /graph snapshot");
    let lines = &g["entities"][0]["lines"];
    assert_eq!(
        lines[3]["points"].as_array().map(Vec::len),
        Some(2 * rejected.len())
    );
    let poses = est.poses().unwrap();
    let first = &lines[3]["points"][0];
    let a = est.graph().node_index(edges[rejected[0]].from()).unwrap();
    assert!((first["x"].as_f64().unwrap() - poses[a].x).abs() < 1e-3);
}

/// A run given idle time between steps (`Recorder::maintain` after every step) replays bit for
/// bit: each renewal or re-linearisation the maintenance made is recorded on
/// `/so2lin/maintenance`, the replay makes it at the same point, and the snapshots taken after
/// the same step are compared with the estimator as it was when each was taken (before the
/// maintenance, or after it for the final one). A log without those records, or with one a
/// step late, diverges.
#[test]
fn maintenance_between_steps_is_recorded_and_replayed() {
    let w = simulate(&SimConfig::new(900, 6)).unwrap();
    let edges = robot_order(w.graph.edges());
    let options = LogOptions {
        snapshot_every: 5,
        ..LogOptions::default()
    };
    let config = OnlineConfig::default();
    let sink = Shared::default();
    let mut est = OnlineEstimator::new(config).unwrap();
    let mut rec = Recorder::new(Box::new(sink.clone()), &config, "test", options).unwrap();
    let mut made = Vec::new();
    for (k, e) in edges.iter().enumerate() {
        rec.add_edge(&mut est, *e).unwrap();
        let done = rec.maintain(&mut est);
        if done.relinearised {
            made.push((k as u64 + 1, done.renewed, (done.variables, done.nonzeros)));
        }
    }
    // The last step's maintenance comes before the final snapshot.
    let again = est.maintain();
    assert!(!again.relinearised, "nothing due twice in a row");
    rec.finish(&mut est).unwrap();
    let bytes = sink.bytes();
    let log = read_log(&bytes).unwrap();
    let renewals = made.iter().filter(|m| m.1).count();
    assert!(renewals >= 8 && made.len() > renewals, "{made:?}");
    assert_eq!(est.counters().maintenance_renewals, renewals);
    let recorded: Vec<_> = (log.maintenance.iter())
        .map(|m| (m.steps, m.renewed, m.factor))
        .collect();
    assert_eq!(recorded, made);
    // Some renewals follow a step whose snapshot was taken before them.
    assert!(
        (log.maintenance.iter()).any(|m| log.estimates.iter().any(|(at, _)| *at == m.steps)),
        "no snapshot at a maintained step"
    );
    let r = replay(&log, true).unwrap();
    assert!(r.divergence.is_none(), "{:?}", r.divergence);
    assert_eq!(r.estimator.counters().maintenance_renewals, renewals);
    let first = log.maintenance[0].steps as usize;
    let mut bare = read_log(&bytes).unwrap();
    bare.maintenance.clear();
    let d = replay(&bare, true).unwrap().divergence;
    let d = d.expect("a log without its maintenance records diverges");
    assert!(d.step + 1 >= first, "{d:?}");
    let mut late = read_log(&bytes).unwrap();
    late.maintenance[0].steps += 1;
    let d = replay(&late, true).unwrap().divergence;
    let d = d.expect("a maintenance record a step late diverges");
    assert!(d.step + 1 >= first, "{d:?}");
}
