//! The recorder: the estimator's thread hands every step to a writer thread, which serialises
//! the messages, fills zstd chunks and writes the file — the SLAM loop pays for a copy of the
//! step and a queue push, not for JSON, compression or I/O (the design of a bag recorder).
//!
//! **Flush policy** (crash safety). The writer takes what is queued every millisecond (at once
//! on [`Recorder::sync`], `finish` and a full backlog), writes it, and closes the open chunk —
//! compressed, written to the sink, the sink flushed — when the batch held a loop closure
//! (unless [`LogOptions::flush_on_loop_closure`] is off), after at most
//! [`LogOptions::flush_every`] steps, once the oldest unflushed step reached the writer
//! [`LogOptions::flush_interval_ms`] ago, when the estimator waits for it, on `sync` and at the
//! end. Loop closures of one batch share one flush (group commit), so a writer that falls
//! behind catches up instead of compressing a tiny chunk per step. **The backlog is bounded**:
//! at most [`LogOptions::max_backlog`] steps are recorded and not yet flushed; a step beyond
//! waits for the next flush ([`Recorder::backpressure`] counts those waits). A log cut at any
//! byte holds every step whose chunk was closed before the cut, so a crash loses at most
//! `max_backlog` steps; `sync` waits until everything recorded so far is flushed.
//!
//! **Recording observes steps**: the estimator knows nothing of MCAP. [`Recorder::add_edge`]
//! (or [`Recorder::add_edge_at`] with the caller's timestamp) adds the edge to the estimator,
//! times the step, reads the newest pose ([`OnlineEstimator::newest`], `/pose` every step) and
//! hands everything to the writer; `log_time`, `publish_time` and every Foxglove `timestamp`
//! of the step's messages are the step's time.
//!
//! **Snapshots** (`/so2lin/estimate`, `/graph`, `/poses`, every
//! [`LogOptions::snapshot_every`] steps and at the end) are the exact poses of
//! [`OnlineEstimator::poses`], read from the maintained factors (one forward and one
//! back-substitution, no factorisation); the writer serialises them. A snapshot that cannot be
//! computed is reported on `/so2lin/log` and never costs a step.
//!
//! Chunks are written whole (assembled in memory, never a placeholder header patched later),
//! so a file cut at any byte — a crash in the middle of a write included — reads as complete
//! chunks and a cut.
//!
//! The messages and their order do not depend on the writer's timing; only the chunk
//! boundaries can, so replays are identical while the files' bytes may differ (the recorded
//! latencies differ anyway).

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::mpsc::{SyncSender, sync_channel};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serde_json::Value;

use super::foxglove::{self, LogLine, PoseInFrame, PosesInFrame, SceneUpdate, Stamp, Style};
use super::queue::Queue;
use super::{
    EDGE_SCHEMA, ESTIMATE_SCHEMA, LogError, LogOptions, MAINTENANCE_SCHEMA, SCHEMA_VERSION,
    STEP_SCHEMA, Sink,
};
use crate::graph::{Edge, NodeId, NodePolicy, Pose2, PoseGraph};
use crate::online::{Decision, OnlineConfig, OnlineError, OnlineEstimator, Step, StepKind};

/// Writes an online run to MCAP (flush policy and threads: [`crate::log`]).
pub struct Recorder {
    queue: Arc<Queue<Record>>,
    /// False once the writer stopped or a snapshot failed.
    live: bool,
    worker: Option<JoinHandle<Result<u64, LogError>>>,
    failure: Arc<Mutex<Option<String>>>,
    options: LogOptions,
    steps: u64,
    backpressure: Backpressure,
}

/// How often recording made a step wait for the writer (the bounded backlog,
/// [`LogOptions::max_backlog`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct Backpressure {
    /// Steps whose recording waited for the writer's flush.
    pub steps_waited: u64,
    /// The longest such wait, ns.
    pub longest_wait_ns: u64,
    /// All waits together, ns.
    pub total_wait_ns: u64,
}

/// What the recorder hands to the writer thread.
enum Record {
    Step {
        edge: Edge,
        /// Boxed: a step with its lists is much larger than the other records.
        step: Box<Step>,
        latency_ns: u64,
        time_ns: u64,
        /// The newest node and its pose after the step.
        newest: Option<(NodeId, Pose2)>,
        /// When the step was handed over (the flush interval counts from here).
        handed: Instant,
    },
    Snapshot(Snapshot),
    /// [`OnlineEstimator::maintain`] renewed the estimate's factor, or re-linearised its
    /// position rows, after the steps so far: whether it renewed, the factor's variables and
    /// nonzeros.
    Maintained(bool, usize, usize),
    /// A snapshot that could not be computed: said on `/so2lin/log`.
    Failed(String),
    Sync(SyncSender<()>),
    Finish(Option<Snapshot>),
}

/// A snapshot (`/so2lin/estimate`, `/graph`, `/poses`): the exact poses, and the chords of the
/// ambiguous cycles; the writer serialises it with its replica of the graph.
struct Snapshot {
    poses: Vec<Pose2>,
    /// Input indices of the chords of the ambiguous cycles, ascending.
    flagged: Vec<usize>,
    /// Input indices of the quarantined loop closures, ascending.
    rejected: Vec<usize>,
}

impl Snapshot {
    fn of(est: &mut OnlineEstimator) -> Result<Self, OnlineError> {
        let mut flagged: Vec<usize> = est
            .ambiguous()
            .iter()
            .filter_map(|&c| est.input_index(est.cycles()[c].chord() as usize))
            .collect();
        flagged.sort_unstable();
        Ok(Self {
            poses: est.poses()?,
            flagged,
            rejected: est.rejected().iter().map(|r| r.edge).collect(),
        })
    }
}

/// The serialised `/so2lin/estimate`, `/graph` and `/poses` messages of a snapshot.
struct Encoded([Vec<u8>; 3]);

/// Serialise a snapshot: the orientations, the graph's edges by style, the poses.
fn encode(
    step: u64,
    time_ns: u64,
    graph: &PoseGraph,
    poses: &[Pose2],
    flagged: &[usize],
    rejected: &[usize],
) -> Result<Encoded, LogError> {
    let theta: Vec<f64> = poses.iter().map(|p| p.theta).collect();
    let pos: Vec<(f64, f64)> = poses.iter().map(|p| (p.x, p.y)).collect();
    let nodes: Vec<u64> = graph.nodes().iter().map(|n| n.id).collect();
    let mut segments: [Vec<(usize, usize)>; 4] = Default::default();
    for (e, (&ends, edge)) in graph.endpoints().iter().zip(graph.edges()).enumerate() {
        let style = if rejected.binary_search(&e).is_ok() {
            Style::Rejected
        } else if flagged.binary_search(&e).is_ok() {
            Style::Flagged
        } else if edge.is_odometric() {
            Style::Odometry
        } else {
            Style::LoopClosure
        };
        segments[style as usize].push(ends);
    }
    #[derive(serde::Serialize)]
    struct EstimateMsg<'a> {
        step: u64,
        nodes: &'a [u64],
        theta: &'a [f64],
    }
    fn json<T: serde::Serialize>(v: &T) -> Result<Vec<u8>, LogError> {
        serde_json::to_vec(v).map_err(|e| LogError::Format(e.to_string()))
    }
    Ok(Encoded([
        json(&EstimateMsg {
            step,
            nodes: &nodes,
            theta: &theta,
        })?,
        json(&SceneUpdate::graph(time_ns, &segments, &pos))?,
        json(&PosesInFrame::new(time_ns, &pos, &theta))?,
    ]))
}

impl Recorder {
    /// Start a log in a file.
    pub fn create(
        path: &Path,
        config: &OnlineConfig,
        source: &str,
        options: LogOptions,
    ) -> Result<Self, LogError> {
        let file = std::fs::File::create(path).map_err(|source| LogError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::new(
            Box::new(std::io::BufWriter::new(file)),
            config,
            source,
            options,
        )
    }

    /// Start a log in any seekable sink: writes the header, schemas, channels and metadata,
    /// then hands the file to the writer thread.
    pub fn new(
        sink: Box<dyn Sink>,
        config: &OnlineConfig,
        source: &str,
        options: LogOptions,
    ) -> Result<Self, LogError> {
        let opts = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            // Chunks are small (one per loop closure): compress on the writer thread itself,
            // without a worker-pool handoff per chunk.
            .compression_threads(0)
            // Each chunk is assembled in memory and written whole when it is closed. (With
            // seeking, mcap writes a placeholder chunk header first, streams the data after
            // it and patches the header at the end: a crash in between leaves a header that
            // claims an impossible length, which reads as corruption, not as a cut.)
            .disable_seeking(true)
            .compression_level(1)
            .profile("")
            .library(format!("so2lin {}", env!("CARGO_PKG_VERSION")));
        let mut mcap = opts.create(sink)?;
        let mut channels = [0u16; 8];
        let defs = [
            ("so2lin.Edge", EDGE_SCHEMA, "/so2lin/edge"),
            ("so2lin.Step", STEP_SCHEMA, "/so2lin/step"),
            ("so2lin.Estimate", ESTIMATE_SCHEMA, "/so2lin/estimate"),
            ("foxglove.Log", foxglove::LOG_SCHEMA, "/so2lin/log"),
            ("foxglove.SceneUpdate", foxglove::SCENE_SCHEMA, "/graph"),
            ("foxglove.PosesInFrame", foxglove::POSES_SCHEMA, "/poses"),
            ("foxglove.PoseInFrame", foxglove::POSE_SCHEMA, "/pose"),
            (
                "so2lin.Maintenance",
                MAINTENANCE_SCHEMA,
                "/so2lin/maintenance",
            ),
        ];
        for (k, (name, schema, topic)) in defs.into_iter().enumerate() {
            let id = mcap.add_schema(name, "jsonschema", schema.as_bytes())?;
            channels[k] = mcap.add_channel(id, topic, "json", &BTreeMap::new())?;
        }
        let s = config.screening;
        let metadata: BTreeMap<String, String> = [
            ("so2lin_version", env!("CARGO_PKG_VERSION").to_owned()),
            ("schema_version", SCHEMA_VERSION.to_owned()),
            ("source", source.to_owned()),
            ("basis", "incremental".to_owned()),
            ("alpha", format!("{:?}", s.alpha)),
            ("dof", s.dof.to_string()),
            ("family_wise", s.family_wise.to_string()),
            ("max_hypotheses", s.max_hypotheses.to_string()),
            ("quarantine", config.quarantine.to_string()),
            ("evict", config.evict.to_string()),
            (
                "estimate_every_step",
                config.estimate_every_step.to_string(),
            ),
            ("renewal_delay", format!("{:?}", config.renewal_delay)),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_owned(), v))
        .collect();
        mcap.write_metadata(&mcap::records::Metadata {
            name: "so2lin".into(),
            metadata,
        })?;
        mcap.flush()?;
        let writer = Writer {
            mcap,
            graph: PoseGraph::new(),
            channels,
            options,
            steps: 0,
            since_flush: 0,
            oldest: None,
            time_ns: 0,
            pending: false,
            buf: Vec::with_capacity(1024),
        };
        let queue = Arc::new(Queue::new(options.max_backlog));
        let failure = Arc::new(Mutex::new(None));
        let (fail, q) = (Arc::clone(&failure), Arc::clone(&queue));
        let worker = std::thread::Builder::new()
            .name("so2lin-log".into())
            .spawn(move || {
                let result = writer.run(&q);
                if let Err(e) = &result {
                    if let Ok(mut f) = fail.lock() {
                        *f = Some(describe(e));
                    }
                    q.gone();
                }
                result
            })
            .map_err(|source| LogError::Io {
                path: "log writer thread".into(),
                source,
            })?;
        Ok(Self {
            queue,
            live: true,
            worker: Some(worker),
            failure,
            options,
            steps: 0,
            backpressure: Backpressure::default(),
        })
    }

    fn send(&mut self, record: Record, urgent: bool) {
        let step = matches!(record, Record::Step { .. });
        if !self.live {
            return;
        }
        match self.queue.push(record, urgent, step) {
            // A writer that is gone stopped on an error, kept in `failure`.
            None => self.live = false,
            Some(None) => {}
            Some(Some(wait)) => {
                let ns = u64::try_from(wait.as_nanos()).unwrap_or(u64::MAX);
                let b = &mut self.backpressure;
                b.steps_waited += 1;
                b.longest_wait_ns = b.longest_wait_ns.max(ns);
                b.total_wait_ns = b.total_wait_ns.saturating_add(ns);
            }
        }
    }

    /// How often recording made a step wait for the writer so far.
    pub fn backpressure(&self) -> Backpressure {
        self.backpressure
    }

    /// Add an edge to the estimator and record the step, at the wall-clock time (ns since the
    /// Unix epoch). A refused edge is not recorded and leaves the estimator unchanged.
    pub fn add_edge(&mut self, est: &mut OnlineEstimator, edge: Edge) -> Result<Step, OnlineError> {
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64);
        self.add_edge_at(est, edge, now)
    }

    /// [`add_edge`](Self::add_edge) at the caller's time (ns since the Unix epoch, e.g. the
    /// sensor time of the measurement): the log time of the step's messages. Times are
    /// recorded data, so a replay stays exact whatever they are.
    pub fn add_edge_at(
        &mut self,
        est: &mut OnlineEstimator,
        edge: Edge,
        time_ns: u64,
    ) -> Result<Step, OnlineError> {
        let start = std::time::Instant::now();
        let step = est.add_edge(edge)?;
        let latency_ns = start.elapsed().as_nanos() as u64;
        self.record(&edge, &step, latency_ns, time_ns, est);
        Ok(step)
    }

    /// Record one step made by the caller: its input edge, its outcome with the latency, the
    /// newest pose, and a snapshot when due. Errors are kept (see [`error`](Self::error));
    /// recording never fails a step.
    pub fn record(
        &mut self,
        edge: &Edge,
        step: &Step,
        latency_ns: u64,
        time_ns: u64,
        est: &mut OnlineEstimator,
    ) {
        if !self.live {
            return;
        }
        let newest = est.newest().ok().flatten();
        let record = Record::Step {
            edge: *edge,
            step: Box::new(step.clone()),
            latency_ns,
            time_ns,
            newest,
            handed: Instant::now(),
        };
        self.send(record, false);
        self.steps += 1;
        let every = self.options.snapshot_every as u64;
        if every > 0 && self.steps.is_multiple_of(every) {
            match Snapshot::of(est) {
                Ok(s) => self.send(Record::Snapshot(s), false),
                Err(e) => self.send(Record::Failed(e.to_string()), false),
            }
        }
    }

    /// [`OnlineEstimator::maintain`], recorded when it did something (a renewal of the
    /// estimate's factor, or a re-linearisation of its position rows), so that a replay does
    /// it at the same point (the answers after it differ from a run without it).
    pub fn maintain(&mut self, est: &mut OnlineEstimator) -> crate::online::Maintenance {
        let done = est.maintain();
        if done.relinearised {
            let record = Record::Maintained(done.renewed, done.variables, done.nonzeros);
            self.send(record, false);
        }
        done
    }

    /// Block until every step recorded so far is written and its chunk flushed to the sink.
    pub fn sync(&mut self) -> Result<(), LogError> {
        let (reply, done) = sync_channel(1);
        self.send(Record::Sync(reply), true);
        done.recv().map_err(|_| {
            LogError::Format(
                self.error()
                    .unwrap_or_else(|| "the log writer stopped".into()),
            )
        })
    }

    /// The first recording error, if any.
    pub fn error(&self) -> Option<String> {
        self.failure.lock().ok().and_then(|f| f.clone())
    }

    /// Write the final snapshot and the summary, close the file, and return the number of
    /// steps recorded.
    pub fn finish(mut self, est: &mut OnlineEstimator) -> Result<u64, LogError> {
        match Snapshot::of(est) {
            Ok(s) => self.send(Record::Finish(Some(s)), true),
            Err(e) => {
                self.send(Record::Failed(e.to_string()), false);
                self.send(Record::Finish(None), true);
            }
        }
        self.queue.close();
        let result = match self.worker.take().map(JoinHandle::join) {
            Some(Ok(r)) => r,
            Some(Err(_)) => Err(LogError::Format("the log writer thread panicked".into())),
            None => Err(LogError::Format("the log writer is gone".into())),
        };
        match self.error() {
            Some(e) => Err(LogError::Format(e)),
            None => result,
        }
    }
}

/// An error with its chain of causes ("MCAP: I/O error …: disk full").
fn describe(e: &LogError) -> String {
    let mut text = e.to_string();
    let mut cause = std::error::Error::source(e);
    while let Some(c) = cause {
        let more = c.to_string();
        if !text.contains(&more) {
            text = format!("{text}: {more}");
        }
        cause = c.source();
    }
    text
}

impl Drop for Recorder {
    /// Without [`finish`](Recorder::finish), the writer still flushes what it holds and writes
    /// the summary (no final snapshot).
    fn drop(&mut self) {
        self.queue.close();
        if let Some(w) = self.worker.take() {
            let _ = w.join();
        }
    }
}

const EDGE: usize = 0;
const STEP: usize = 1;
const ESTIMATE: usize = 2;
const LOG: usize = 3;
const GRAPH: usize = 4;
const POSES: usize = 5;
const POSE: usize = 6;
const MAINTENANCE: usize = 7;

/// The writer thread's state.
struct Writer {
    mcap: mcap::Writer<Box<dyn Sink>>,
    /// The recorded edges in input order (quarantined ones included; the same dense node
    /// indices as the estimator's graph, since a quarantined loop closure creates no node).
    graph: PoseGraph,
    channels: [u16; 8],
    options: LogOptions,
    steps: u64,
    /// Steps written since the last flush.
    since_flush: usize,
    /// When the oldest of them was handed over.
    oldest: Option<Instant>,
    /// Time of the current step (ns since the Unix epoch).
    time_ns: u64,
    /// A loop closure is waiting for its flush.
    pending: bool,
    /// Reused serialisation buffer.
    buf: Vec<u8>,
}

impl Writer {
    /// Take records until the queue closes or `Finish` arrives; after each batch, flush for
    /// the loop closures in it (group commit).
    fn run(mut self, queue: &Queue<Record>) -> Result<u64, LogError> {
        let mut batch = Vec::new();
        let interval = Duration::from_millis(self.options.flush_interval_ms);
        loop {
            let deadline = self.oldest.map(|t| t + interval);
            let closed = queue.take(&mut batch, deadline);
            for record in batch.drain(..) {
                match record {
                    Record::Step {
                        edge,
                        step,
                        latency_ns,
                        time_ns,
                        newest,
                        handed,
                    } => {
                        self.oldest.get_or_insert(handed);
                        self.step(&edge, &step, latency_ns, time_ns, newest)?;
                        // The interval is checked once per batch (below): a writer that is
                        // behind writes whole chunks, not one per step.
                        if self.since_flush >= self.options.flush_every.max(1) {
                            self.flush(queue)?;
                        }
                    }
                    Record::Snapshot(s) => self.snapshot(s)?,
                    Record::Maintained(renewed, variables, nonzeros) => {
                        let msg = MaintenanceMsg {
                            step: self.steps,
                            renewed,
                            variables,
                            nonzeros,
                        };
                        self.put(MAINTENANCE, &msg)?;
                    }
                    Record::Failed(e) => self.log_line(4, &format!("snapshot not written: {e}"))?,
                    Record::Sync(reply) => {
                        self.flush(queue)?;
                        // The caller may have stopped waiting; nothing to do then.
                        let _ = reply.send(());
                    }
                    Record::Finish(s) => {
                        if let Some(s) = s {
                            self.snapshot(s)?;
                        }
                        self.mcap.finish()?;
                        return Ok(self.steps);
                    }
                }
            }
            let overdue = self.oldest.is_some_and(|t| t.elapsed() >= interval);
            if self.pending || overdue || (self.since_flush > 0 && queue.producer_waiting()) {
                self.flush(queue)?;
            }
            if closed {
                self.mcap.finish()?;
                return Ok(self.steps);
            }
        }
    }

    /// Close the open chunk and flush the sink: the steps written since the last flush are
    /// durable.
    fn flush(&mut self, queue: &Queue<Record>) -> Result<(), LogError> {
        self.mcap.flush()?;
        queue.durable(self.since_flush);
        self.since_flush = 0;
        self.oldest = None;
        self.pending = false;
        Ok(())
    }

    /// Serialise `value` into the reused buffer and write it as one message on `channel`.
    fn put<T: serde::Serialize + ?Sized>(
        &mut self,
        channel: usize,
        value: &T,
    ) -> Result<(), LogError> {
        let mut buf = std::mem::take(&mut self.buf);
        buf.clear();
        let written = serde_json::to_writer(&mut buf, value)
            .map_err(|e| LogError::Format(e.to_string()))
            .and_then(|()| self.write(channel, &buf));
        self.buf = buf;
        written
    }

    /// Write one message on `channel` at the current log time.
    fn write(&mut self, channel: usize, data: &[u8]) -> Result<(), LogError> {
        let header = mcap::records::MessageHeader {
            channel_id: self.channels[channel],
            sequence: self.steps as u32,
            log_time: self.time_ns,
            publish_time: self.time_ns,
        };
        self.mcap.write_to_known_channel(&header, data)?;
        Ok(())
    }

    fn log_line(&mut self, level: u8, message: &str) -> Result<(), LogError> {
        let line = LogLine {
            timestamp: Stamp::at(self.time_ns),
            level,
            message,
            name: "so2lin",
            file: "",
            line: 0,
        };
        self.put(LOG, &line)
    }

    fn step(
        &mut self,
        edge: &Edge,
        step: &Step,
        latency_ns: u64,
        time_ns: u64,
        newest: Option<(NodeId, Pose2)>,
    ) -> Result<(), LogError> {
        self.time_ns = time_ns;
        self.graph
            .add_edge(*edge, NodePolicy::CreateUnknown)
            .map_err(|e| LogError::Format(e.to_string()))?;
        self.put(EDGE, &EdgeMsg::new(self.steps, edge))?;
        if let Some((_, p)) = newest {
            self.put(POSE, &PoseInFrame::new(time_ns, p.x, p.y, p.theta))?;
        }
        let msg = StepMsg {
            step: self.steps,
            latency_ns,
            outcome: step,
            newest: newest.map(NewestMsg::from),
        };
        self.put(STEP, &msg)?;
        if let StepKind::Cycle(c) = &step.kind {
            let (from, to) = (edge.from(), edge.to());
            match c.decision {
                Decision::Ambiguous => self.log_line(
                    3,
                    &format!(
                        "cycle {} (edge {from}→{to}) is ambiguous: γ ∈ {}..={}",
                        c.cycle, c.candidates.lo, c.candidates.hi
                    ),
                )?,
                Decision::Inconsistent => self.log_line(
                    3,
                    &format!(
                        "cycle {} (edge {from}→{to}) is inconsistent: no integer within its interval",
                        c.cycle
                    ),
                )?,
                Decision::Determined => {}
            }
        }
        for r in &step.quarantined {
            self.log_line(
                3,
                &format!(
                    "edge {} ({}→{}) quarantined: {} statistic {:.3} above {:.3}",
                    r.edge, r.from, r.to, r.test, r.statistic, r.threshold
                ),
            )?;
        }
        for &e in &step.readmitted {
            self.log_line(2, &format!("edge {e} re-admitted from quarantine"))?;
        }
        for r in step.rescreened.iter().filter(|r| r.changed) {
            self.log_line(
                2,
                &format!("cycle {} re-screened: {:?}", r.cycle, r.decision),
            )?;
        }
        self.steps += 1;
        self.since_flush += 1;
        if self.options.flush_on_loop_closure && matches!(step.kind, StepKind::Cycle(_)) {
            self.pending = true;
        }
        Ok(())
    }

    fn snapshot(&mut self, s: Snapshot) -> Result<(), LogError> {
        if s.poses.len() != self.graph.node_count() {
            return self.log_line(
                4,
                "snapshot not written: it does not match the recorded graph",
            );
        }
        let [estimate, graph, poses] = encode(
            self.steps,
            self.time_ns,
            &self.graph,
            &s.poses,
            &s.flagged,
            &s.rejected,
        )?
        .0;
        self.write(ESTIMATE, &estimate)?;
        self.write(GRAPH, &graph)?;
        self.write(POSES, &poses)
    }
}

/// A `/so2lin/maintenance` message: what [`OnlineEstimator::maintain`] did after `step` steps
/// (a renewal, or a re-linearisation of the position rows) and the size of the factor.
#[derive(serde::Serialize)]
struct MaintenanceMsg {
    step: u64,
    renewed: bool,
    variables: usize,
    nonzeros: usize,
}

/// A `/so2lin/edge` message.
#[derive(serde::Serialize)]
struct EdgeMsg {
    step: u64,
    from: u64,
    to: u64,
    dx: f64,
    dy: f64,
    dtheta: f64,
    information: [f64; 6],
}

impl EdgeMsg {
    fn new(step: u64, e: &Edge) -> Self {
        let m = e.measurement();
        Self {
            step,
            from: e.from(),
            to: e.to(),
            dx: m.x,
            dy: m.y,
            dtheta: m.theta,
            information: e.information().0,
        }
    }
}

/// A `/so2lin/step` message: the step's outcome with its index and latency, and the newest
/// pose after it.
#[derive(serde::Serialize)]
struct StepMsg<'a> {
    step: u64,
    latency_ns: u64,
    #[serde(flatten)]
    outcome: &'a Step,
    #[serde(skip_serializing_if = "Option::is_none")]
    newest: Option<NewestMsg>,
}

/// The newest pose in a step message, in full precision (`/pose` carries it as Foxglove's
/// single-precision fields, for display).
#[derive(serde::Serialize)]
struct NewestMsg {
    node: NodeId,
    x: f64,
    y: f64,
    theta: f64,
}

impl From<(NodeId, Pose2)> for NewestMsg {
    fn from((node, p): (NodeId, Pose2)) -> Self {
        Self {
            node,
            x: p.x,
            y: p.y,
            theta: p.theta,
        }
    }
}

/// The step message as JSON with latency 0 (how replay compares steps).
pub(super) fn step_json(
    step: u64,
    s: &Step,
    newest: Option<(NodeId, Pose2)>,
) -> Result<Value, LogError> {
    let msg = StepMsg {
        step,
        latency_ns: 0,
        outcome: s,
        newest: newest.map(NewestMsg::from),
    };
    serde_json::to_value(&msg).map_err(|e| LogError::Format(e.to_string()))
}
