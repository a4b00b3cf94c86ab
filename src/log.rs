//! MCAP logs of online runs: record every step, replay it bit for bit.
//!
//! A log is one MCAP file (zstd chunks) with JSON messages, each channel carrying its JSON
//! Schema (`jsonschema` encoding):
//!
//! | topic | content |
//! |---|---|
//! | `/so2lin/edge` | every input edge exactly as given: ids, dx, dy, dθ, the information matrix |
//! | `/so2lin/step` | every step's outcome (the online [`Step`]) and its latency in ns |
//! | `/so2lin/estimate` | orientation snapshots every N steps and at the end |
//! | `/so2lin/log` | human-readable events as `foxglove.Log` |
//! | `/graph` | `foxglove.SceneUpdate`: odometry and loop-closure edges as line lists, ambiguous loops highlighted (with each snapshot) |
//! | `/poses` | `foxglove.PosesInFrame` in frame `map`: odometry composed with the current orientations (with each snapshot) |
//!
//! A metadata record `so2lin` holds the version, configuration, source and
//! [`SCHEMA_VERSION`]. Log time is the step index (edges carry no timestamps), so a log plays
//! back in order. The writer closes and flushes a chunk after every loop closure and at
//! least every [`LogOptions::flush_every`] steps, so a log cut at any byte (a robot losing
//! power) still holds every step flushed before the cut: [`read_log`] reads linearly, stops at
//! the first damaged record and reports the log as cut.
//!
//! Replay ([`replay`]) rebuilds the estimator from the metadata, feeds the recorded edges and
//! compares every new step with the recorded one (all fields but the latency): JSON numbers are
//! written in shortest round-trip form, so equality is bit equality of the floats.

use std::collections::BTreeMap;
use std::io::{Seek, Write};
use std::path::Path;

use serde_json::{Value, json};

use crate::graph::{Edge, Information, Pose2};
use crate::online::{OnlineConfig, OnlineEstimator, Step, StepKind};
use crate::screening::ScreeningConfig;

/// Version of the so2lin channels' message layout.
pub const SCHEMA_VERSION: &str = "1";

/// Recording options.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LogOptions {
    /// Orientation snapshot every this many steps (0: only at the end).
    pub snapshot_every: usize,
    /// Flush (close the chunk) at least every this many steps; loop closures always flush.
    pub flush_every: usize,
}

impl Default for LogOptions {
    fn default() -> Self {
        Self {
            snapshot_every: 5000,
            flush_every: 64,
        }
    }
}

/// A failure to write or read a log.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    /// File system.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The error.
        source: std::io::Error,
    },
    /// The MCAP layer.
    #[error("MCAP: {0}")]
    Mcap(#[from] mcap::McapError),
    /// Not a so2lin log, or a malformed message.
    #[error("not a valid so2lin log: {0}")]
    Format(String),
}

/// Something a recorder can write into.
pub trait Sink: Write + Seek + Send {}
impl<T: Write + Seek + Send> Sink for T {}

const EDGE_SCHEMA: &str = r##"{"$schema":"https://json-schema.org/draft/2020-12/schema","title":"so2lin.Edge","type":"object","required":["step","from","to","dx","dy","dtheta","information"],"properties":{"step":{"type":"integer","minimum":0},"from":{"type":"integer","minimum":0},"to":{"type":"integer","minimum":0},"dx":{"type":"number"},"dy":{"type":"number"},"dtheta":{"type":"number"},"information":{"description":"upper triangle of the 3x3 information matrix, g2o order I11 I12 I13 I22 I23 I33","type":"array","items":{"type":"number"},"minItems":6,"maxItems":6}},"additionalProperties":false}"##;

const STEP_SCHEMA: &str = r##"{"$schema":"https://json-schema.org/draft/2020-12/schema","title":"so2lin.Step","type":"object","required":["step","latency_ns","edge","kind","rescreened"],"$defs":{"interval":{"type":"object","required":["lo","hi","inconsistent"],"properties":{"lo":{"type":"integer"},"hi":{"type":"integer"},"inconsistent":{"type":"boolean"}}},"decision":{"enum":["determined","ambiguous","inconsistent"]}},"properties":{"step":{"type":"integer","minimum":0},"latency_ns":{"type":"integer","minimum":0},"edge":{"type":"integer","minimum":0},"kind":{"oneOf":[{"type":"object","required":["kind","new_node","joined_components"],"properties":{"kind":{"const":"tree"},"new_node":{"type":"boolean"},"joined_components":{"type":"boolean"}}},{"type":"object","required":["kind","cycle","mean","sd","candidates","decision"],"properties":{"kind":{"const":"cycle"},"cycle":{"type":"integer","minimum":0},"mean":{"type":"number"},"sd":{"type":"number"},"candidates":{"$ref":"#/$defs/interval"},"decision":{"$ref":"#/$defs/decision"}}}]},"rescreened":{"type":"array","items":{"type":"object","required":["cycle","before","after","decision","changed"],"properties":{"cycle":{"type":"integer"},"before":{"$ref":"#/$defs/interval"},"after":{"$ref":"#/$defs/interval"},"decision":{"$ref":"#/$defs/decision"},"changed":{"type":"boolean"}}}}}}"##;

const ESTIMATE_SCHEMA: &str = r##"{"$schema":"https://json-schema.org/draft/2020-12/schema","title":"so2lin.Estimate","type":"object","required":["step","nodes","theta"],"properties":{"step":{"type":"integer","minimum":0},"nodes":{"type":"array","items":{"type":"integer","minimum":0}},"theta":{"description":"orientation of each node, radians, unwrapped, anchors 0","type":"array","items":{"type":"number"}}}}"##;

/// The official `foxglove.Log` JSON Schema (foxglove/schemas, `schemas/jsonschema/Log.json`).
const FOXGLOVE_LOG_SCHEMA: &str = include_str!("log/foxglove_Log.json");

/// The official `foxglove.SceneUpdate` JSON Schema (foxglove/schemas).
const FOXGLOVE_SCENE_SCHEMA: &str = include_str!("log/foxglove_SceneUpdate.json");
/// The official `foxglove.PosesInFrame` JSON Schema (foxglove/schemas).
const FOXGLOVE_POSES_SCHEMA: &str = include_str!("log/foxglove_PosesInFrame.json");

/// Writes an online run to MCAP.
pub struct Recorder {
    writer: mcap::Writer<Box<dyn Sink>>,
    channels: [u16; 6],
    options: LogOptions,
    steps: u64,
    since_flush: usize,
    error: Option<String>,
}

const EDGE: usize = 0;
const STEP: usize = 1;
const ESTIMATE: usize = 2;
const LOG: usize = 3;
const GRAPH: usize = 4;
const POSES: usize = 5;

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

    /// Start a log in any seekable sink.
    pub fn new(
        sink: Box<dyn Sink>,
        config: &OnlineConfig,
        source: &str,
        options: LogOptions,
    ) -> Result<Self, LogError> {
        let opts = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            // Chunks are small (one per loop closure): compress on this thread, without a
            // worker pool handoff per chunk.
            .compression_threads(0)
            .compression_level(1)
            .profile("")
            .library(format!("so2lin {}", env!("CARGO_PKG_VERSION")));
        let mut writer = opts.create(sink)?;
        let mut channels = [0u16; 6];
        let defs = [
            ("so2lin.Edge", EDGE_SCHEMA, "/so2lin/edge"),
            ("so2lin.Step", STEP_SCHEMA, "/so2lin/step"),
            ("so2lin.Estimate", ESTIMATE_SCHEMA, "/so2lin/estimate"),
            ("foxglove.Log", FOXGLOVE_LOG_SCHEMA, "/so2lin/log"),
            ("foxglove.SceneUpdate", FOXGLOVE_SCENE_SCHEMA, "/graph"),
            ("foxglove.PosesInFrame", FOXGLOVE_POSES_SCHEMA, "/poses"),
        ];
        for (k, (name, schema, topic)) in defs.into_iter().enumerate() {
            let id = writer.add_schema(name, "jsonschema", schema.as_bytes())?;
            channels[k] = writer.add_channel(id, topic, "json", &BTreeMap::new())?;
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
            ("expected_cycles", config.expected_cycles.to_string()),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_owned(), v))
        .collect();
        writer.write_metadata(&mcap::records::Metadata {
            name: "so2lin".into(),
            metadata,
        })?;
        writer.flush()?;
        Ok(Self {
            writer,
            channels,
            options,
            steps: 0,
            since_flush: 0,
            error: None,
        })
    }

    fn put(&mut self, channel: usize, value: &Value) -> Result<(), LogError> {
        let data = serde_json::to_vec(value).map_err(|e| LogError::Format(e.to_string()))?;
        let header = mcap::records::MessageHeader {
            channel_id: self.channels[channel],
            sequence: self.steps as u32,
            log_time: self.steps,
            publish_time: self.steps,
        };
        self.writer.write_to_known_channel(&header, &data)?;
        Ok(())
    }

    fn log_line(&mut self, level: u8, message: String) -> Result<(), LogError> {
        let v = json!({
            "timestamp": {"sec": self.steps, "nsec": 0},
            "level": level,
            "message": message,
            "name": "so2lin",
            "file": "",
            "line": 0
        });
        self.put(LOG, &v)
    }

    /// Record one step: its input edge, its outcome with the latency, events, and a snapshot
    /// when due. Errors are kept (see [`error`](Self::error)); recording never fails a step.
    pub fn record(&mut self, edge: &Edge, step: &Step, latency_ns: u64, est: &mut OnlineEstimator) {
        if self.error.is_some() {
            return;
        }
        if let Err(e) = self.try_record(edge, step, latency_ns, est) {
            self.error = Some(e.to_string());
        }
    }

    fn try_record(
        &mut self,
        edge: &Edge,
        step: &Step,
        latency_ns: u64,
        est: &mut OnlineEstimator,
    ) -> Result<(), LogError> {
        self.put(EDGE, &edge_json(self.steps, edge))?;
        self.put(STEP, &step_json(self.steps, step, latency_ns))?;
        if let StepKind::Cycle(c) = &step.kind {
            use crate::online::Decision;
            match c.decision {
                Decision::Ambiguous => self.log_line(
                    3,
                    format!(
                        "cycle {} (edge {}→{}) is ambiguous: γ ∈ {}..={}",
                        c.cycle,
                        edge.from(),
                        edge.to(),
                        c.candidates.lo,
                        c.candidates.hi
                    ),
                )?,
                Decision::Inconsistent => self.log_line(
                    3,
                    format!(
                        "cycle {} (edge {}→{}) is inconsistent: no integer within its interval",
                        c.cycle,
                        edge.from(),
                        edge.to()
                    ),
                )?,
                Decision::Determined => {}
            }
        }
        for r in step.rescreened.iter().filter(|r| r.changed) {
            self.log_line(
                2,
                format!("cycle {} re-screened: {:?}", r.cycle, r.decision),
            )?;
        }
        self.steps += 1;
        self.since_flush += 1;
        if self.options.snapshot_every > 0 && self.steps % self.options.snapshot_every as u64 == 0 {
            self.snapshot(est)?;
        }
        if matches!(step.kind, StepKind::Cycle(_)) || self.since_flush >= self.options.flush_every {
            self.writer.flush()?;
            self.since_flush = 0;
        }
        Ok(())
    }

    fn snapshot(&mut self, est: &mut OnlineEstimator) -> Result<(), LogError> {
        let theta = est
            .orientations()
            .map_err(|e| LogError::Format(e.to_string()))?
            .to_vec();
        let nodes: Vec<u64> = est.graph().nodes().iter().map(|n| n.id).collect();
        self.put(
            ESTIMATE,
            &json!({"step": self.steps, "nodes": nodes, "theta": theta}),
        )?;
        let pos = crate::estimate::composed_positions(est.graph(), &theta);
        let flagged: std::collections::BTreeSet<usize> = est
            .ambiguous()
            .iter()
            .map(|&c| est.cycles()[c].chord() as usize)
            .collect();
        self.put(GRAPH, &scene_json(self.steps, est, &pos, &flagged))?;
        self.put(POSES, &poses_json(self.steps, &pos, &theta))
    }

    /// The first recording error, if any.
    pub fn error(&self) -> Option<&str> {
        self.error.as_deref()
    }

    /// Write the final snapshot and the summary, and close the file.
    pub fn finish(mut self, est: &mut OnlineEstimator) -> Result<u64, LogError> {
        if let Some(e) = self.error.take() {
            return Err(LogError::Format(e));
        }
        self.snapshot(est)?;
        self.writer.finish()?;
        Ok(self.steps)
    }
}

fn stamp(step: u64) -> Value {
    json!({"sec": step, "nsec": 0})
}

fn point(p: (f64, f64)) -> Value {
    json!({"x": p.0, "y": p.1, "z": 0.0})
}

fn quaternion(theta: f64) -> Value {
    let (s, c) = (0.5 * theta).sin_cos();
    json!({"x": 0.0, "y": 0.0, "z": s, "w": c})
}

/// `foxglove.SceneUpdate`: odometry edges (grey) and loop closures (blue) as line lists, the
/// chords of ambiguous cycles (red, thicker) highlighted, in frame `map`.
fn scene_json(
    step: u64,
    est: &OnlineEstimator,
    pos: &[(f64, f64)],
    flagged: &std::collections::BTreeSet<usize>,
) -> Value {
    let g = est.graph();
    let mut sets: [Vec<Value>; 3] = Default::default();
    for (e, (&(a, b), edge)) in g.endpoints().iter().zip(g.edges()).enumerate() {
        let k = if flagged.contains(&e) {
            2
        } else if edge.is_odometric() {
            0
        } else {
            1
        };
        sets[k].push(point(pos[a]));
        sets[k].push(point(pos[b]));
    }
    let colors = [
        (0.6, 0.6, 0.6, 1.0),
        (0.2, 0.4, 1.0, 0.8),
        (1.0, 0.1, 0.1, 1.0),
    ];
    let thickness = [0.05, 0.03, 0.12];
    let lines: Vec<Value> = sets
        .into_iter()
        .enumerate()
        .map(|(k, points)| {
            let (r, gr, b, a) = colors[k];
            json!({"type": 2, "pose": {"position": point((0.0, 0.0)), "orientation": quaternion(0.0)},
                   "thickness": thickness[k], "scale_invariant": false, "points": points,
                   "color": {"r": r, "g": gr, "b": b, "a": a}, "colors": [], "indices": []})
        })
        .collect();
    json!({"deletions": [], "entities": [{
        "timestamp": stamp(step), "frame_id": "map", "id": "so2lin-graph",
        "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": false, "metadata": [],
        "arrows": [], "cubes": [], "spheres": [], "cylinders": [], "lines": lines,
        "triangles": [], "texts": [], "models": []
    }]})
}

/// `foxglove.PosesInFrame`: every pose in frame `map`.
fn poses_json(step: u64, pos: &[(f64, f64)], theta: &[f64]) -> Value {
    let poses: Vec<Value> = pos
        .iter()
        .zip(theta)
        .map(|(&p, &t)| json!({"position": point(p), "orientation": quaternion(t)}))
        .collect();
    json!({"timestamp": stamp(step), "frame_id": "map", "poses": poses})
}

fn edge_json(step: u64, e: &Edge) -> Value {
    let m = e.measurement();
    json!({"step": step, "from": e.from(), "to": e.to(), "dx": m.x, "dy": m.y, "dtheta": m.theta,
           "information": e.information().0})
}

fn step_json(step: u64, s: &Step, latency_ns: u64) -> Value {
    let mut v = serde_json::to_value(s).unwrap_or(Value::Null);
    if let Value::Object(map) = &mut v {
        map.insert("step".into(), json!(step));
        map.insert("latency_ns".into(), json!(latency_ns));
    }
    v
}

/// What [`read_log`] found.
#[derive(Debug)]
pub struct LogContents {
    /// The `so2lin` metadata record.
    pub metadata: BTreeMap<String, String>,
    /// Recorded edges, in step order.
    pub edges: Vec<Edge>,
    /// Recorded steps (JSON, latency included), in step order.
    pub steps: Vec<Value>,
    /// Whether the file ended early (no end magic / damaged last chunk).
    pub truncated: Option<String>,
}

impl LogContents {
    /// The online configuration recorded in the metadata.
    pub fn config(&self) -> Result<OnlineConfig, LogError> {
        let get = |k: &str| {
            self.metadata
                .get(k)
                .ok_or_else(|| LogError::Format(format!("metadata lacks {k}")))
        };
        let parse_err = |k: &str| LogError::Format(format!("metadata {k} is malformed"));
        let screening = ScreeningConfig {
            alpha: get("alpha")?.parse().map_err(|_| parse_err("alpha"))?,
            dof: get("dof")?.parse().map_err(|_| parse_err("dof"))?,
            family_wise: get("family_wise")?
                .parse()
                .map_err(|_| parse_err("family_wise"))?,
            max_hypotheses: get("max_hypotheses")?
                .parse()
                .map_err(|_| parse_err("max_hypotheses"))?,
        };
        let expected_cycles = get("expected_cycles")?
            .parse()
            .map_err(|_| parse_err("expected_cycles"))?;
        Ok(OnlineConfig {
            screening,
            expected_cycles,
        })
    }
}

/// Read a log linearly, tolerating a cut: everything before the first damaged record is
/// returned, and `truncated` says why reading stopped.
pub fn read_log(bytes: &[u8]) -> Result<LogContents, LogError> {
    use mcap::read::Options;
    let mut metadata = None;
    let mut truncated = None;
    if bytes.len() < 8 || &bytes[..8] != mcap::MAGIC {
        return Err(LogError::Format("not an MCAP file (bad magic)".into()));
    }
    let records =
        mcap::read::LinearReader::new_with_options(bytes, Options::IgnoreEndMagic.into())?;
    for r in records {
        match r {
            Ok(mcap::records::Record::Metadata(m)) if m.name == "so2lin" => {
                metadata = Some(m.metadata);
                break;
            }
            Ok(_) => {}
            Err(_) => break,
        }
    }
    let metadata = metadata.ok_or_else(|| LogError::Format("no so2lin metadata record".into()))?;
    let (mut edges, mut steps) = (Vec::new(), Vec::new());
    let stream = mcap::MessageStream::new_with_options(bytes, Options::IgnoreEndMagic.into())?;
    for m in stream {
        let m = match m {
            Ok(m) => m,
            Err(e) => {
                truncated = Some(e.to_string());
                break;
            }
        };
        let parse = || -> Result<Value, LogError> {
            serde_json::from_slice(&m.data).map_err(|e| LogError::Format(e.to_string()))
        };
        match m.channel.topic.as_str() {
            "/so2lin/edge" => edges.push((m.log_time, edge_from_json(&parse()?)?)),
            "/so2lin/step" => steps.push((m.log_time, parse()?)),
            _ => {}
        }
    }
    if truncated.is_none() && !bytes.ends_with(mcap::MAGIC) {
        truncated = Some("the file does not end with the MCAP magic".into());
    }
    // Keep only steps whose edge and outcome were both recorded, in step order.
    edges.sort_by_key(|x| x.0);
    steps.sort_by_key(|x| x.0);
    let n = edges.len().min(steps.len());
    for (k, ((te, _), (ts, _))) in edges.iter().zip(&steps).take(n).enumerate() {
        if *te != k as u64 || *ts != k as u64 {
            return Err(LogError::Format(format!("step {k} is missing")));
        }
    }
    Ok(LogContents {
        metadata,
        edges: edges.into_iter().take(n).map(|x| x.1).collect(),
        steps: steps.into_iter().take(n).map(|x| x.1).collect(),
        truncated,
    })
}

fn edge_from_json(v: &Value) -> Result<Edge, LogError> {
    let num = |k: &str| {
        v[k].as_f64()
            .ok_or_else(|| LogError::Format(format!("edge lacks {k}")))
    };
    let id = |k: &str| {
        v[k].as_u64()
            .ok_or_else(|| LogError::Format(format!("edge lacks {k}")))
    };
    let info: Vec<f64> = v["information"]
        .as_array()
        .map(|a| a.iter().filter_map(Value::as_f64).collect())
        .unwrap_or_default();
    let info: [f64; 6] = info
        .try_into()
        .map_err(|_| LogError::Format("edge information needs 6 numbers".into()))?;
    Edge::new(
        id("from")?,
        id("to")?,
        Pose2::new(num("dx")?, num("dy")?, num("dtheta")?),
        Information(info),
    )
    .map_err(|e| LogError::Format(e.to_string()))
}

/// The first difference between a replayed step and the recorded one.
#[derive(Clone, Debug, PartialEq)]
pub struct Divergence {
    /// Step index.
    pub step: usize,
    /// Recorded (without latency).
    pub recorded: Value,
    /// Replayed.
    pub replayed: Value,
}

/// Result of a replay.
pub struct Replay {
    /// Steps replayed.
    pub steps: usize,
    /// Latency of every replayed step, ns.
    pub latency_ns: Vec<u64>,
    /// First divergence (with verification).
    pub divergence: Option<Divergence>,
    /// Why the log ended early, if it did.
    pub truncated: Option<String>,
    /// The estimator after the replay.
    pub estimator: OnlineEstimator,
}

/// Rebuild the run from a log; with `verify`, compare every step with the recorded one and stop
/// at the first divergence.
pub fn replay(log: &LogContents, verify: bool) -> Result<Replay, LogError> {
    let config = log.config()?;
    let mut est = OnlineEstimator::new(config).map_err(|e| LogError::Format(e.to_string()))?;
    let mut latency_ns = Vec::with_capacity(log.edges.len());
    let mut divergence = None;
    for (k, (edge, recorded)) in log.edges.iter().zip(&log.steps).enumerate() {
        let t = std::time::Instant::now();
        let step = est
            .add_edge(*edge)
            .map_err(|e| LogError::Format(format!("step {k}: {e}")))?;
        latency_ns.push(t.elapsed().as_nanos() as u64);
        if verify {
            let replayed = step_json(k as u64, &step, 0);
            let mut recorded = recorded.clone();
            if let Value::Object(map) = &mut recorded {
                map.insert("latency_ns".into(), json!(0));
            }
            if replayed != recorded {
                divergence = Some(Divergence {
                    step: k,
                    recorded,
                    replayed,
                });
                break;
            }
        }
    }
    Ok(Replay {
        steps: latency_ns.len(),
        latency_ns,
        divergence,
        truncated: log.truncated.clone(),
        estimator: est,
    })
}
