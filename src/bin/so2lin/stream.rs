//! `so2lin stream`: feed a file's edges through the online estimator, timing every step.

use std::path::Path;
use std::time::Instant;

use serde_json::{Value, json};

use so2lin::estimate::OrientationEstimator;
use so2lin::io::InfoOrder;
use so2lin::log::{LogOptions, Recorder};
use so2lin::online::{OnlineConfig, OnlineEstimator, StepKind, robot_order_indices};

/// In which order the edges reach the estimator.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum EdgeOrder {
    /// As a robot produces them: an edge arrives when its later node appears.
    Robot,
    /// As the file lists them.
    File,
}

/// What the robot reads after every step (its cost is inside the step's latency).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum EstimateQuery {
    /// Nothing: the screening alone (the estimate is not kept up to date through the stream,
    /// and every cycle is conditioned through P_UU; with --log the recorder reads the newest
    /// pose, so it is).
    None,
    /// The newest node's pose.
    Newest,
    /// Every node's exact pose.
    All,
}

/// Options of the `stream` command.
pub struct StreamArgs<'a> {
    pub file: &'a Path,
    pub info_order: InfoOrder,
    pub edge_order: EdgeOrder,
    pub estimate: EstimateQuery,
    pub config: OnlineConfig,
    pub orientations: Option<&'a Path>,
    pub log: Option<&'a Path>,
    pub log_options: LogOptions,
    /// Log time between steps (the file's edges carry no timestamps).
    pub step_time_ns: u64,
    /// Edges per second, as a robot's front end sends them (None: back to back).
    pub rate: Option<f64>,
    /// Reserve the file's node and edge counts before the first step (`reserved` in the
    /// output says whether the room was had).
    pub reserve: bool,
    /// Call `OnlineEstimator::maintain` after every step, untimed by the steps.
    pub maintain: bool,
    /// Write one line per step here ([`Trace`]).
    pub trace: Option<&'a Path>,
    pub json: bool,
}

/// `--trace FILE`: one CSV line per step, in the order the steps ran — which steps were slow
/// and what they did. Columns: the step's index, the edge's index in the file (0-based, in the
/// file's order: the index `rejected_edges` gives), its kind (`tree`, `cycle`, `quarantined`),
/// its time in ns (the add_edge and the read `--estimate` asks for, as in `latency_us`), its
/// counted work (search nodes settled, estimate factor entries, P_UU factor entries: the same
/// in every run), whether an eviction's rebuild was in progress beside the estimator after
/// it (`OnlineEstimator::evicting`: its swap is a later step), and what the estimate's factor
/// did in it, from the step's change in `Counters`: `renewed` (a renewal of its order
/// collected), `renewal_waited` (the step waited for that renewal's builder) and
/// `relinearised` (every position row rewritten at the headings: the last step of a
/// re-linearisation, whose headings were solved a block of the factor per step over the steps
/// before (about 4 on city10000) and its rows' measurements over about 7; the factor's
/// right-hand sides follow over about the next 24 steps on city10000, their information
/// gathered a block of rows a step, then a forward solve a block of positions a step;
/// the blocks are counted in their steps' work), and the robot thread's CPU time in the step in
/// ns ([`thread_cpu_ns`]; empty where the clock is not read): `ns` less `cpu_ns` is the time the
/// thread was off its core in the step.
/// `OnlineEstimator::counters` reads these after the step's read, which applies them.
struct Trace {
    out: std::io::BufWriter<std::fs::File>,
    path: std::path::PathBuf,
}

impl Trace {
    const HEADER: &'static str = "step,edge,kind,ns,search_nodes,estimate_entries,conditioning_entries,rebuilding,renewed,renewal_waited,relinearised,cpu_ns";

    fn create(path: &Path) -> Result<Self, String> {
        let file =
            std::fs::File::create(path).map_err(|e| format!("--trace {}: {e}", path.display()))?;
        let mut trace = Self {
            out: std::io::BufWriter::new(file),
            path: path.to_path_buf(),
        };
        trace.line(format_args!("{}", Self::HEADER))?;
        Ok(trace)
    }

    fn line(&mut self, line: std::fmt::Arguments<'_>) -> Result<(), String> {
        use std::io::Write;
        writeln!(self.out, "{line}").map_err(|e| format!("--trace {}: {e}", self.path.display()))
    }

    fn finish(mut self) -> Result<(), String> {
        use std::io::Write;
        self.out
            .flush()
            .map_err(|e| format!("--trace {}: {e}", self.path.display()))
    }
}

/// What `--maintain` cost between the steps.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct MaintenanceCost {
    /// Calls that renewed the estimate's factor.
    pub renewals: usize,
    /// Calls that re-linearised every position row without a renewal.
    pub relinearisations: usize,
    /// Time in all calls, seconds.
    pub seconds: f64,
    /// The longest call, ms.
    pub worst_ms: f64,
}

/// p50, p90, p99, max, mean of latencies in µs.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct Latency {
    pub p50: f64,
    pub p90: f64,
    pub p99: f64,
    pub max: f64,
    pub mean: f64,
    pub count: usize,
}

/// Nearest-rank percentile `p` of a sorted, non-empty sample.
fn rank(sorted: &[u64], p: f64) -> u64 {
    sorted[(((p * sorted.len() as f64).ceil() as usize).max(1) - 1).min(sorted.len() - 1)]
}

/// p50, p90, p99, max and total of one kind of work per step ([`so2lin::work`]).
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct WorkPerStep {
    pub p50: u64,
    pub p90: u64,
    pub p99: u64,
    pub max: u64,
    pub total: u64,
}

impl WorkPerStep {
    /// Nearest-rank percentiles of a sample of counts.
    pub fn of(mut counts: Vec<u64>) -> Self {
        if counts.is_empty() {
            return Self::default();
        }
        counts.sort_unstable();
        Self {
            p50: rank(&counts, 0.50),
            p90: rank(&counts, 0.90),
            p99: rank(&counts, 0.99),
            max: counts[counts.len() - 1],
            total: counts.iter().sum(),
        }
    }
}

impl Latency {
    /// Nearest-rank percentiles of a sample (ns in, µs out).
    pub fn of(mut ns: Vec<u64>) -> Self {
        if ns.is_empty() {
            return Self::default();
        }
        ns.sort_unstable();
        let rank = |p: f64| rank(&ns, p);
        let us = |x: u64| x as f64 / 1e3;
        Self {
            p50: us(rank(0.50)),
            p90: us(rank(0.90)),
            p99: us(rank(0.99)),
            max: us(ns[ns.len() - 1]),
            mean: ns.iter().sum::<u64>() as f64 / ns.len() as f64 / 1e3,
            count: ns.len(),
        }
    }
}

/// The calling thread's CPU time in ns (Linux: `CLOCK_THREAD_CPUTIME_ID`; None elsewhere or
/// when refused). A step's wall time less its CPU time is the time the robot's thread was off
/// its core inside the step: waiting for a builder, or preempted — by the OS, or, on a virtual
/// machine, by the host, which steals the virtual core (on the development VM, two busy
/// threads each lost their core for 1–40 ms several times a second, one busy thread never for
/// more than 0.3 ms; `benches/MEASUREMENTS.md`, fortieth session). The clock is read outside the
/// step's timed window (about 0.5 µs a read there: a system call).
pub fn thread_cpu_ns() -> Option<u64> {
    #[cfg(target_os = "linux")]
    {
        let mut t = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: clock_gettime writes only the timespec we pass by pointer.
        let ok = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) } == 0;
        let secs = u64::try_from(t.tv_sec).ok()?;
        let nanos = u64::try_from(t.tv_nsec).ok()?;
        ok.then(|| secs.saturating_mul(1_000_000_000).saturating_add(nanos))
    }
    #[cfg(not(target_os = "linux"))]
    None
}

/// The slowest step: its index, wall time and the robot thread's CPU time in it.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct WorstStep {
    /// Index of the step (0-based, in the order streamed).
    pub step: usize,
    /// Its wall time, ms (the `max` of `latency_us`).
    pub ms: f64,
    /// The robot thread's CPU time in it, ms (None where the clock is not read): the rest is
    /// time off the core, waiting for a builder or preempted.
    pub cpu_ms: Option<f64>,
}

/// Peak resident set size of this process, from the OS (Linux: VmHWM), in bytes.
pub fn peak_rss_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

pub fn run(args: StreamArgs) -> Result<(), String> {
    let start = Instant::now();
    let mut est = OnlineEstimator::new(args.config).map_err(|e| e.to_string())?;
    // Skipped lines are reported and a file without a 2D edge is an error, as for every
    // command.
    let (graph, _) = crate::files::load(args.file, args.info_order)?;
    let edges = graph.edges().to_vec();
    let nodes = graph.node_count();
    drop(graph);
    // File index of the k-th edge streamed (rejected edges are reported in file order).
    let file_index: Vec<usize> = match args.edge_order {
        EdgeOrder::Robot => robot_order_indices(&edges),
        EdgeOrder::File => (0..edges.len()).collect(),
    };
    let edges: Vec<_> = file_index.iter().map(|&i| edges[i]).collect();
    // The file's size is known: its arrays are reserved before the first step, as a front end
    // that knows its mission's size would (`OnlineEstimator::reserve`).
    // Refused, the stream goes on without it (the estimator is unchanged) and says so.
    let reserved = args.reserve
        && match est.reserve(nodes, edges.len()) {
            Ok(()) => true,
            Err(e) => {
                eprintln!("warning: {e}; streaming without the room");
                false
            }
        };
    let mut recorder = match args.log {
        Some(path) => {
            let source = args.file.display().to_string();
            Some(
                Recorder::create(path, &args.config, &source, args.log_options)
                    .map_err(|e| e.to_string())?,
            )
        }
        None => None,
    };
    let t0 = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64);
    let bar = crate::files::progress_bar(edges.len() as u64 * 64, "streaming");
    let (mut all, mut tree, mut cyc) = (Vec::new(), Vec::new(), Vec::new());
    // Work per step (search nodes, estimate entries, conditioning entries): counted, so the
    // same on every machine (module `so2lin::work`).
    let mut work: [Vec<u64>; 3] = Default::default();
    let mut sink = 0.0;
    // With a rate, edge k arrives k/rate after the first; the stream sleeps until then, and
    // records how far a step started after its edge's arrival (the steps before it overran).
    let paced = Instant::now();
    let mut max_lag = std::time::Duration::ZERO;
    let mut maintenance = MaintenanceCost::default();
    let mut trace = args.trace.map(Trace::create).transpose()?;
    let mut counted = est.counters();
    // The robot thread's CPU time per step (None where the clock was not read), beside `all`.
    let mut cpu: Vec<Option<u64>> = Vec::new();
    for (k, &edge) in edges.iter().enumerate() {
        if let Some(hz) = args.rate {
            let arrival = std::time::Duration::from_secs_f64(k as f64 / hz);
            let now = paced.elapsed();
            match arrival.checked_sub(now) {
                Some(wait) => std::thread::sleep(wait),
                None => max_lag = max_lag.max(now - arrival),
            }
        }
        let w0 = so2lin::work::on_this_thread();
        let c0 = thread_cpu_ns();
        let t = Instant::now();
        let step = est.add_edge(edge).map_err(|e| e.to_string())?;
        match args.estimate {
            EstimateQuery::None => {}
            EstimateQuery::Newest => {
                if let Some((_, p)) = est.newest().map_err(|e| e.to_string())? {
                    sink += p.x;
                }
            }
            EstimateQuery::All => {
                let poses = est.poses().map_err(|e| e.to_string())?;
                sink += poses.last().map_or(0.0, |p| p.x);
            }
        }
        let ns = t.elapsed().as_nanos() as u64;
        let cpu_ns = c0.zip(thread_cpu_ns()).map(|(a, b)| b.saturating_sub(a));
        let w = so2lin::work::on_this_thread().since(w0);
        work[0].push(w.search_nodes);
        work[1].push(w.estimate_entries);
        work[2].push(w.conditioning_entries);
        if let Some(rec) = recorder.as_mut() {
            let time = t0.saturating_add((k as u64).saturating_mul(args.step_time_ns));
            rec.record(&edge, &step, ns, time, &mut est);
        }
        if args.maintain {
            let t = Instant::now();
            let done = match recorder.as_mut() {
                Some(rec) => rec.maintain(&mut est),
                None => est.maintain(),
            };
            let spent = t.elapsed();
            maintenance.renewals += usize::from(done.renewed);
            maintenance.relinearisations += usize::from(done.relinearised && !done.renewed);
            maintenance.seconds += spent.as_secs_f64();
            maintenance.worst_ms = maintenance.worst_ms.max(spent.as_secs_f64() * 1e3);
        }
        if let Some(t) = trace.as_mut() {
            let kind = match step.kind {
                StepKind::Tree { .. } => "tree",
                StepKind::Cycle(_) => "cycle",
                StepKind::Quarantined => "quarantined",
            };
            let now = est.counters();
            t.line(format_args!(
                "{k},{},{kind},{ns},{},{},{},{},{},{},{},{}",
                file_index[k],
                w.search_nodes,
                w.estimate_entries,
                w.conditioning_entries,
                u8::from(est.evicting().is_some()),
                now.estimate_renewals
                    .saturating_sub(counted.estimate_renewals),
                now.renewal_waits.saturating_sub(counted.renewal_waits),
                (now.estimate_relinearisations).saturating_sub(counted.estimate_relinearisations),
                cpu_ns.map_or(String::new(), |c| c.to_string()),
            ))?;
            counted = now;
        }
        cpu.push(cpu_ns);
        all.push(ns);
        match step.kind {
            StepKind::Tree { .. } => tree.push(ns),
            StepKind::Cycle(_) | StepKind::Quarantined => cyc.push(ns),
        }
        if all.len() % 1024 == 0 {
            bar.set_position(all.len() as u64 * 64);
        }
    }
    bar.finish_and_clear();
    std::hint::black_box(sink);
    if let Some(t) = trace {
        t.finish()?;
    }
    let backpressure = recorder.as_ref().map(Recorder::backpressure);
    if let Some(rec) = recorder {
        rec.finish(&mut est).map_err(|e| e.to_string())?;
        if let (Some(path), Some(b)) = (args.log, backpressure) {
            eprintln!(
                "log written to {} ({} waited for the log writer's flush, longest {:.2} ms; at most {} steps were unflushed at any time)",
                path.display(),
                crate::report::plural(b.steps_waited as usize, "step", "steps"),
                b.longest_wait_ns as f64 / 1e6,
                args.log_options.max_backlog.max(1),
            );
        }
    }
    let stream_s = start.elapsed().as_secs_f64();
    // An eviction's rebuild still in progress beside the estimator is swapped in: the summary
    // gives the decisions on every arrival (after the log, which records steps only).
    est.settle();
    let t = Instant::now();
    let result = est.finish().map_err(|e| e.to_string())?;
    let finish_s = t.elapsed().as_secs_f64();
    if let Some(path) = args.orientations {
        let best = result.hypotheses.first().ok_or("no hypothesis")?;
        let k = result.wraps(best).map_err(|e| e.to_string())?;
        let theta = OrientationEstimator::new(est.graph())
            .map_err(|e| e.to_string())?
            .orientations(&k);
        crate::screen::write_orientations(path, est.graph(), &theta)?;
    }
    let c = est.counters();
    let rejected: Vec<_> = est
        .rejected()
        .into_iter()
        .map(|mut r| {
            r.edge = file_index[r.edge];
            r
        })
        .collect();
    let steps_s = all.iter().sum::<u64>() as f64 / 1e9;
    // The slowest step (the first, on a tie) with its CPU time.
    let worst = all
        .iter()
        .enumerate()
        .rev()
        .max_by_key(|&(_, &ns)| ns)
        .map(|(k, &ns)| WorstStep {
            step: k,
            ms: ns as f64 / 1e6,
            cpu_ms: cpu[k].map(|c| c as f64 / 1e6),
        });
    let lat = [
        ("all", Latency::of(all)),
        ("tree", Latency::of(tree)),
        ("cycle", Latency::of(cyc)),
    ];
    let [search, estimate, conditioning] = work.map(WorkPerStep::of);
    // CPU times only when every step has one (a clock that failed once would skew them).
    let cpu = cpu
        .into_iter()
        .collect::<Option<Vec<u64>>>()
        .filter(|c| !c.is_empty())
        .map(Latency::of);
    let total = start.elapsed().as_secs_f64();
    let rss = peak_rss_bytes();
    if args.json {
        let latency: serde_json::Map<String, Value> =
            lat.iter().map(|(k, l)| (k.to_string(), json!(l))).collect();
        let hypotheses: Vec<Value> = result
            .hypotheses
            .iter()
            .map(|h| json!({"chi2": h.chi2, "p_value": h.p_value}))
            .collect();
        let v = json!({
            "file": args.file.display().to_string(),
            "config": args.config,
            "edge_order": args.edge_order,
            "estimate": args.estimate,
            "rate_hz": args.rate,
            "reserved": reserved,
            "max_lag_ms": args.rate.map(|_| max_lag.as_secs_f64() * 1e3),
            "estimate_renewals": c.estimate_renewals,
            "renewal_waits": c.renewal_waits,
            "rebuild_waits": c.rebuild_waits,
            "estimate_relinearisations": c.estimate_relinearisations,
            "maintenance": args.maintain.then_some(maintenance),
            "steps": c.steps,
            "nodes": est.graph().node_count(),
            "cycles": c.cycles,
            "determined": c.determined,
            "ambiguous": c.ambiguous,
            "inconsistent": c.inconsistent,
            "quarantined": c.quarantined,
            "readmitted": c.readmitted,
            "rejected_edges": rejected,
            "noise_scales": est.noise_scales(),
            "rescreens": c.rescreens,
            "reorders": c.reorders,
            "rebuilds": c.rebuilds,
            "rebuilds_from_checkpoint": c.rebuilds_from_checkpoint,
            "replayed_arrivals": c.replayed_arrivals,
            "latency_us": latency,
            "cpu_us": cpu,
            "worst_step": worst,
            "work_per_step": {
                "search_nodes": search,
                "estimate_entries": estimate,
                "conditioning_entries": conditioning,
            },
            "stream_seconds": stream_s,
            "steps_seconds": steps_s,
            "finish_seconds": finish_s,
            "total_seconds": total,
            "peak_rss_bytes": rss,
            "log_backpressure": backpressure,
            "outcome": result.outcome,
            "hypotheses": hypotheses,
            "success_probability_lower_bound": result.success_lower_bound,
        });
        println!("{v}");
        return Ok(());
    }
    println!(
        "{}: {} streamed, {} accepted ({} tree edges, {} cycles), {} in quarantine, {}",
        args.file.display(),
        crate::report::plural(est.arrivals(), "edge", "edges"),
        c.steps,
        c.tree_edges,
        c.cycles,
        c.quarantined,
        crate::report::plural(est.graph().node_count(), "node", "nodes"),
    );
    let read = match args.estimate {
        EstimateQuery::None => "no estimate read",
        EstimateQuery::Newest => "the newest pose read after every step",
        EstimateQuery::All => "every pose read after every step",
    };
    let order = match args.edge_order {
        EdgeOrder::Robot => "robot order",
        EdgeOrder::File => "file order",
    };
    let pace = match args.rate {
        Some(hz) => format!(
            "edges at {hz} Hz, at most {:.3} ms behind their arrival",
            max_lag.as_secs_f64() * 1e3
        ),
        None => "edges back to back".to_owned(),
    };
    let room = if reserved {
        "the file's counts reserved"
    } else {
        "nothing reserved"
    };
    println!("latency per step in µs ({order}, {read}, {pace}, {room}):");
    println!("                              p50       p90       p99     worst      mean");
    for (name, l) in &lat {
        println!(
            "  {name:<6} ({:>6} steps) {:>9.2} {:>9.2} {:>9.2} {:>9.2} {:>9.2}",
            l.count, l.p50, l.p90, l.p99, l.max, l.mean
        );
    }
    if let Some(l) = cpu {
        println!(
            "  cpu    ({:>6} steps) {:>9.2} {:>9.2} {:>9.2} {:>9.2} {:>9.2}   (all steps, on the CPU: the robot thread's CPU time)",
            l.count, l.p50, l.p90, l.p99, l.max, l.mean
        );
    }
    if let Some(w) = worst {
        match w.cpu_ms {
            Some(c) => println!(
                "  the worst step, #{}: {:.3} ms, {:.3} ms of it on the CPU ({:.3} ms off it: waiting for a builder, or preempted)",
                w.step,
                w.ms,
                c,
                (w.ms - c).max(0.0)
            ),
            None => println!("  the worst step, #{}: {:.3} ms", w.step, w.ms),
        }
    }
    println!("work per step (counted: the same in every run, on any machine):");
    println!("                                  p50       p90       p99     worst        total");
    for (name, w) in [
        ("search nodes settled", search),
        ("estimate factor entries", estimate),
        ("P_UU factor entries", conditioning),
    ] {
        println!(
            "  {name:<26} {:>9} {:>9} {:>9} {:>9} {:>12}",
            w.p50, w.p90, w.p99, w.max, w.total
        );
    }
    println!(
        "online: {} determined, {} ambiguous, {} inconsistent, {} re-screens, {} factor reorders, {} estimate renewals, {} waited for a renewal's builder (of either factor), {} for an eviction's rebuild, {} re-linearisations of the positions",
        c.determined,
        c.ambiguous,
        c.inconsistent,
        c.rescreens,
        c.reorders,
        c.estimate_renewals,
        crate::report::plural(c.renewal_waits, "step", "steps"),
        c.rebuild_waits,
        c.estimate_relinearisations
    );
    if args.maintain {
        println!(
            "maintenance between the steps (not in their latency): {} of the estimate's factor and {} of its positions alone, {:.4} s in all, the longest call {:.2} ms",
            crate::report::plural(maintenance.renewals, "renewal", "renewals"),
            crate::report::plural(
                maintenance.relinearisations,
                "re-linearisation",
                "re-linearisations"
            ),
            maintenance.seconds,
            maintenance.worst_ms,
        );
    }
    if c.rebuilds > 0 {
        println!(
            "rebuilds: {} ({} from a checkpoint), {} arrivals replayed",
            c.rebuilds, c.rebuilds_from_checkpoint, c.replayed_arrivals
        );
    }
    let second =
        crate::report::second_screening_words(&result, args.config.screening.joint_level())
            .unwrap_or_else(|| "second screening complete".into());
    println!(
        "finish: {} determined, {} ambiguous, {} ({second})",
        result.determined,
        result.ambiguous.len(),
        crate::report::plural(result.hypotheses.len(), "hypothesis", "hypotheses"),
    );
    for (k, h) in result.hypotheses.iter().take(10).enumerate() {
        println!("  #{:<3} χ² = {:<12.4} p = {:.4}", k + 1, h.chi2, h.p_value);
    }
    crate::report::print_rejected(&rejected, "quarantined (kept out of the estimate)");
    crate::report::print_noise_scales(&est.noise_scales());
    if c.readmitted > 0 {
        println!(
            "{} re-admitted after a later re-test",
            crate::report::plural(c.readmitted, "loop closure", "loop closures")
        );
    }
    println!(
        "success probability ≥ {:.6} (integer bootstrapping; assumes the declared noise; {})",
        result.success_lower_bound,
        crate::report::accepted_words(c.steps, rejected.len())
    );
    let rss = rss.map_or("n/a".to_owned(), |b| format!("{:.1} MB", b as f64 / 1e6));
    println!(
        "seconds: stream {stream_s:.4}, finish {finish_s:.4}, total {total:.4}; peak RSS {rss}"
    );
    Ok(())
}
