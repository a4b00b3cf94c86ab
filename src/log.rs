//! MCAP logs of online runs: record every step, replay it bit for bit.
//!
//! A log is one MCAP file (zstd chunks) with JSON messages, each channel carrying its JSON
//! Schema (`jsonschema` encoding):
//!
//! | topic | content |
//! |---|---|
//! | `/so2lin/edge` | every input edge exactly as given: ids, dx, dy, dθ, the information matrix |
//! | `/so2lin/step` | every step's outcome (the online [`Step`](crate::online::Step)) and its latency in ns |
//! | `/so2lin/estimate` | orientation snapshots every N steps and at the end |
//! | `/so2lin/log` | human-readable events as `foxglove.Log` |
//! | `/graph` | `foxglove.SceneUpdate`: odometry and loop-closure edges as line lists, ambiguous loops highlighted (with each snapshot) |
//! | `/poses` | `foxglove.PosesInFrame` in frame `map`: the current poses ([`OnlineEstimator::poses`]: orientations with least-squares positions), with each snapshot |
//!
//! A metadata record `so2lin` holds the version, configuration, source and
//! [`SCHEMA_VERSION`]. Log time is the step index (edges carry no timestamps), so a log plays
//! back in order. A writer thread ([`Recorder`]) serialises and compresses off the estimator's
//! thread; it closes and flushes a chunk after every loop closure and at least every
//! [`LogOptions::flush_every`] steps, so a log cut at any byte (a robot losing power) still
//! holds every step flushed before the cut: [`read_log`] reads linearly, stops at the first
//! damaged record and reports the log as cut.
//!
//! Replay ([`replay`]) rebuilds the estimator from the metadata, feeds the recorded edges and
//! compares every new step with the recorded one (all fields but the latency): JSON numbers are
//! written in shortest round-trip form, so equality is bit equality of the floats.

use std::collections::BTreeMap;
use std::io::{Seek, Write};

use serde_json::{Value, json};

use crate::graph::{Edge, Information, Pose2};
use crate::online::{OnlineConfig, OnlineEstimator};
use crate::screening::ScreeningConfig;

/// Version of the so2lin channels' message layout.
pub const SCHEMA_VERSION: &str = "1";

/// Recording options.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LogOptions {
    /// Orientation snapshot every this many steps (0: only at the end).
    pub snapshot_every: usize,
    /// Flush (close the chunk) at least every this many steps.
    pub flush_every: usize,
    /// Also flush after every loop closure (steps that queue up behind the writer share one
    /// flush).
    pub flush_on_loop_closure: bool,
}

impl Default for LogOptions {
    fn default() -> Self {
        Self {
            snapshot_every: 5000,
            flush_every: 64,
            flush_on_loop_closure: true,
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

pub(crate) const EDGE_SCHEMA: &str = r##"{"$schema":"https://json-schema.org/draft/2020-12/schema","title":"so2lin.Edge","type":"object","required":["step","from","to","dx","dy","dtheta","information"],"properties":{"step":{"type":"integer","minimum":0},"from":{"type":"integer","minimum":0},"to":{"type":"integer","minimum":0},"dx":{"type":"number"},"dy":{"type":"number"},"dtheta":{"type":"number"},"information":{"description":"upper triangle of the 3x3 information matrix, g2o order I11 I12 I13 I22 I23 I33","type":"array","items":{"type":"number"},"minItems":6,"maxItems":6}},"additionalProperties":false}"##;

pub(crate) const STEP_SCHEMA: &str = r##"{"$schema":"https://json-schema.org/draft/2020-12/schema","title":"so2lin.Step","type":"object","required":["step","latency_ns","edge","kind","rescreened"],"$defs":{"interval":{"type":"object","required":["lo","hi","inconsistent"],"properties":{"lo":{"type":"integer"},"hi":{"type":"integer"},"inconsistent":{"type":"boolean"}}},"decision":{"enum":["determined","ambiguous","inconsistent"]}},"properties":{"step":{"type":"integer","minimum":0},"latency_ns":{"type":"integer","minimum":0},"edge":{"type":"integer","minimum":0},"kind":{"oneOf":[{"type":"object","required":["kind","new_node","joined_components"],"properties":{"kind":{"const":"tree"},"new_node":{"type":"boolean"},"joined_components":{"type":"boolean"}}},{"type":"object","required":["kind","cycle","mean","sd","candidates","decision"],"properties":{"kind":{"const":"cycle"},"cycle":{"type":"integer","minimum":0},"mean":{"type":"number"},"sd":{"type":"number"},"candidates":{"$ref":"#/$defs/interval"},"decision":{"$ref":"#/$defs/decision"}}}]},"rescreened":{"type":"array","items":{"type":"object","required":["cycle","before","after","decision","changed"],"properties":{"cycle":{"type":"integer"},"before":{"$ref":"#/$defs/interval"},"after":{"$ref":"#/$defs/interval"},"decision":{"$ref":"#/$defs/decision"},"changed":{"type":"boolean"}}}}}}"##;

pub(crate) const ESTIMATE_SCHEMA: &str = r##"{"$schema":"https://json-schema.org/draft/2020-12/schema","title":"so2lin.Estimate","type":"object","required":["step","nodes","theta"],"properties":{"step":{"type":"integer","minimum":0},"nodes":{"type":"array","items":{"type":"integer","minimum":0}},"theta":{"description":"orientation of each node, radians, unwrapped, anchors 0","type":"array","items":{"type":"number"}}}}"##;

mod foxglove;
mod queue;
mod record;

pub use record::Recorder;
use record::step_json;

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
        Ok(OnlineConfig { screening })
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
            let replayed = step_json(k as u64, &step)?;
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
