//! MCAP logs of online runs: record every step, replay it bit for bit.
//!
//! A log is one MCAP file (zstd chunks) with JSON messages, each channel carrying its JSON
//! Schema (`jsonschema` encoding):
//!
//! | topic | content |
//! |---|---|
//! | `/so2lin/edge` | every input edge exactly as given: ids, dx, dy, dθ, the information matrix |
//! | `/so2lin/step` | every step's outcome (the online [`Step`](crate::online::Step)) and its latency in ns |
//! | `/so2lin/estimate` | orientation snapshots every N steps ([`LogOptions::snapshot_every`]) and at the end |
//! | `/so2lin/log` | human-readable events as `foxglove.Log` |
//! | `/graph` | `foxglove.SceneUpdate`: odometry and loop-closure edges as line lists, ambiguous loops highlighted (with each snapshot) |
//! | `/poses` | `foxglove.PosesInFrame` in frame `map`: the current poses ([`OnlineEstimator::poses`]: orientations with least-squares positions), with each snapshot |
//! | `/pose` | `foxglove.PoseInFrame` in frame `map`: the newest node's pose ([`OnlineEstimator::newest`]), every step |
//! | `/so2lin/maintenance` | what [`OnlineEstimator::maintain`] did between two steps ([`Recorder::maintain`]): a renewal of the estimate's factor or a re-linearisation of its position rows, the number of steps before it, the factor's variables and nonzeros |
//!
//! A metadata record `so2lin` holds the version, configuration, source and
//! [`SCHEMA_VERSION`]. The log time of a step's messages (`log_time`, `publish_time` and every
//! Foxglove `timestamp`) is the step's time: the caller's ([`Recorder::add_edge_at`]) or the
//! wall clock ([`Recorder::add_edge`]); `so2lin stream --log` and `demo` give step k the time
//! start + k·0.1 s (`--step-time`), so a playback shows the map growing at ten steps a second.
//! Messages carry their step index, which orders them on reading. A writer thread ([`Recorder`]) serialises and compresses off the estimator's
//! thread; it closes and flushes a chunk after every loop closure, at least every
//! [`LogOptions::flush_every`] steps and [`LogOptions::flush_interval_ms`] after a step reached
//! it, and never lets more than [`LogOptions::max_backlog`] steps wait for a flush, so a log
//! cut at any byte (a robot losing power) holds every step flushed before the cut: [`read_log`] reads linearly, stops at the first
//! damaged record and reports the log as cut.
//!
//! Replay ([`replay`]) rebuilds the estimator from the metadata, feeds the recorded edges and
//! compares every new step with the recorded one: its outcome (all fields but the latency), the
//! newest pose after it (`/pose`, read as the recorder read it) and every snapshot taken after it
//! (the orientations of `/so2lin/estimate` and the poses of `/poses`); the times are recorded
//! data, not compared. What `/so2lin/maintenance` records is done again after the same step (a
//! renewal changes the answers' last bits, a re-linearisation the fast positions), the
//! snapshots taken before it compared before it, and what it did compared. JSON numbers are written in shortest round-trip form, so equality is bit
//! equality of the floats.

use std::collections::BTreeMap;
use std::io::{Seek, Write};

use serde_json::{Value, json};

use crate::graph::{Edge, Information, Pose2};
use crate::online::{OnlineConfig, OnlineEstimator};
use crate::screening::ScreeningConfig;

/// Version of the so2lin channels' message layout. 2: step messages carry the newest pose after
/// the step in full precision (`newest`); a log of version 1 replays and verifies too, its
/// newest poses compared as `/pose` displays them. 3: the channel `/so2lin/maintenance`
/// (what [`OnlineEstimator::maintain`] did between steps, which a replay must do too); logs of
/// versions 1 and 2 have none and replay as before.
pub const SCHEMA_VERSION: &str = "3";

/// Recording options. Defaults ([`LogOptions::default`]): a snapshot every 100 steps; a flush
/// (the open chunk closed and written to the sink) after every loop closure, at least every 64
/// steps and at most 10 ms after a step reached the writer; at most 256 steps not yet flushed.
///
/// **What a crash can lose** (`kill -9`, a robot losing power after the OS wrote the file):
/// at most [`max_backlog`](Self::max_backlog) steps, always — a step that would make more
/// steps unflushed waits for the writer's next flush, and that wait is the only cost the log
/// can put on a step (it ends at the writer's next flush: at most `flush_every` steps of
/// serialising and one chunk's compression away, unless the writer thread gets no CPU). In
/// time: a step is in the file about [`flush_interval_ms`](Self::flush_interval_ms) (plus the
/// writer's 1 ms poll) after it was recorded when the writer keeps up, and within the time the
/// writer takes for `max_backlog` steps when it does not. The README gives measured figures
/// (`cargo bench --bench log_kill`).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct LogOptions {
    /// Snapshot (`/so2lin/estimate`, `/graph`, `/poses`) every this many steps (0: only at
    /// the end). Default 100.
    pub snapshot_every: usize,
    /// Flush (close the chunk) at least every this many steps. Default 64.
    pub flush_every: usize,
    /// Also flush after every loop closure (steps that queue up behind the writer share one
    /// flush). Default true.
    pub flush_on_loop_closure: bool,
    /// Flush once the oldest step not yet flushed reached the writer this many milliseconds
    /// ago (wall clock). Default 10.
    pub flush_interval_ms: u64,
    /// At most this many steps recorded and not yet flushed (at least 1): a step beyond waits
    /// for the writer's next flush. Default 256.
    pub max_backlog: usize,
}

impl Default for LogOptions {
    fn default() -> Self {
        Self {
            snapshot_every: 100,
            flush_every: 64,
            flush_on_loop_closure: true,
            flush_interval_ms: 10,
            max_backlog: 256,
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
    /// The MCAP layer failed while writing.
    #[error("MCAP: {0}")]
    Mcap(String),
    /// The file is damaged: a CRC mismatch, an impossible length, undecodable compressed data,
    /// or a malformed record or message.
    #[error("corrupt log near byte {offset}: {what} ({intact_steps} steps before it are intact)")]
    Corrupt {
        /// How far reading got, in bytes from the start of the file.
        offset: u64,
        /// What was wrong.
        what: String,
        /// Complete steps read before the damage.
        intact_steps: usize,
    },
    /// Not a so2lin log, or a malformed message.
    #[error("not a valid so2lin log: {0}")]
    Format(String),
}

#[doc(hidden)]
impl From<mcap::McapError> for LogError {
    /// The error and its chain of causes as one message (the `mcap` crate's type stays out of
    /// the public API).
    fn from(e: mcap::McapError) -> Self {
        let mut text = e.to_string();
        let mut cause = std::error::Error::source(&e);
        while let Some(c) = cause {
            text = format!("{text}: {c}");
            cause = c.source();
        }
        LogError::Mcap(text)
    }
}

/// Something a recorder can write into.
pub trait Sink: Write + Seek + Send {}
impl<T: Write + Seek + Send> Sink for T {}

pub(crate) const EDGE_SCHEMA: &str = r##"{"$schema":"https://json-schema.org/draft/2020-12/schema","title":"so2lin.Edge","type":"object","required":["step","from","to","dx","dy","dtheta","information"],"properties":{"step":{"type":"integer","minimum":0},"from":{"type":"integer","minimum":0},"to":{"type":"integer","minimum":0},"dx":{"type":"number"},"dy":{"type":"number"},"dtheta":{"type":"number"},"information":{"description":"upper triangle of the 3x3 information matrix, g2o order I11 I12 I13 I22 I23 I33","type":"array","items":{"type":"number"},"minItems":6,"maxItems":6}},"additionalProperties":false}"##;

pub(crate) const STEP_SCHEMA: &str = r##"{"$schema":"https://json-schema.org/draft/2020-12/schema","title":"so2lin.Step","type":"object","required":["step","latency_ns","edge","kind","rescreened"],"$defs":{"interval":{"type":"object","required":["lo","hi","inconsistent"],"properties":{"lo":{"type":"integer"},"hi":{"type":"integer"},"inconsistent":{"type":"boolean"}}},"decision":{"enum":["determined","ambiguous","inconsistent"]}},"properties":{"step":{"type":"integer","minimum":0},"latency_ns":{"type":"integer","minimum":0},"edge":{"type":"integer","minimum":0},"kind":{"oneOf":[{"type":"object","required":["kind","new_node","joined_components"],"properties":{"kind":{"const":"tree"},"new_node":{"type":"boolean"},"joined_components":{"type":"boolean"}}},{"type":"object","required":["kind","cycle","mean","sd","candidates","decision"],"properties":{"kind":{"const":"cycle"},"cycle":{"type":"integer","minimum":0},"mean":{"type":"number"},"sd":{"type":"number"},"candidates":{"$ref":"#/$defs/interval"},"decision":{"$ref":"#/$defs/decision"}}},{"type":"object","required":["kind"],"properties":{"kind":{"const":"quarantined"}}}]},"rescreened":{"type":"array","items":{"type":"object","required":["cycle","before","after","decision","changed"],"properties":{"cycle":{"type":"integer"},"before":{"$ref":"#/$defs/interval"},"after":{"$ref":"#/$defs/interval"},"decision":{"$ref":"#/$defs/decision"},"changed":{"type":"boolean"}}}},"quarantined":{"description":"the loop closure quarantined at this step (absent when none)","type":"array","items":{"type":"object","required":["edge","from","to","test","statistic","threshold"],"properties":{"edge":{"type":"integer","minimum":0},"from":{"type":"integer","minimum":0},"to":{"type":"integer","minimum":0},"test":{"enum":["cycle_angle","cycle_translation"]},"statistic":{"type":"number"},"threshold":{"type":"number"}}}},"readmitted":{"description":"input indices of quarantined loop closures re-admitted at this step (absent when none)","type":"array","items":{"type":"integer","minimum":0}},"newest":{"description":"the newest node and its pose after the step, in full precision (absent when there is none)","type":"object","required":["node","x","y","theta"],"properties":{"node":{"type":"integer","minimum":0},"x":{"type":"number"},"y":{"type":"number"},"theta":{"type":"number"}},"additionalProperties":false}}}"##;

pub(crate) const MAINTENANCE_SCHEMA: &str = r##"{"$schema":"https://json-schema.org/draft/2020-12/schema","title":"so2lin.Maintenance","description":"OnlineEstimator::maintain renewed the estimate's factor, or re-linearised its position rows, between two steps","type":"object","required":["step","renewed","variables","nonzeros"],"properties":{"step":{"description":"the number of steps before it","type":"integer","minimum":0},"renewed":{"description":"a renewal (false: a re-linearisation alone)","type":"boolean"},"variables":{"type":"integer","minimum":0},"nonzeros":{"type":"integer","minimum":0}},"additionalProperties":false}"##;

pub(crate) const ESTIMATE_SCHEMA: &str = r##"{"$schema":"https://json-schema.org/draft/2020-12/schema","title":"so2lin.Estimate","type":"object","required":["step","nodes","theta"],"properties":{"step":{"type":"integer","minimum":0},"nodes":{"type":"array","items":{"type":"integer","minimum":0}},"theta":{"description":"orientation of each node, radians, unwrapped, anchors 0","type":"array","items":{"type":"number"}}}}"##;

mod foxglove;
mod queue;
mod record;

use record::step_json;
pub use record::{Backpressure, Recorder};

/// What [`OnlineEstimator::maintain`] did between two steps, as recorded: a renewal of the
/// estimate's factor, or a re-linearisation of its position rows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Maintained {
    /// The number of steps before it.
    pub steps: u64,
    /// The snapshots recorded before it ([`LogContents::estimates`] and
    /// [`LogContents::poses`]: how many of each), which a replay compares before it.
    pub snapshots_before: (usize, usize),
    /// A renewal (false: a re-linearisation alone).
    pub renewed: bool,
    /// Variables and nonzeros of the factor after it.
    pub factor: (usize, usize),
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
    /// The newest pose after each step as `/pose` shows it (x, y, and the yaw quaternion's z
    /// and w, rounded, single precision), by step index.
    pub newest: BTreeMap<u64, [f32; 4]>,
    /// Each snapshot's orientations (`/so2lin/estimate`), with the number of steps before it,
    /// in step order.
    pub estimates: Vec<(u64, Vec<f64>)>,
    /// Each snapshot's poses as `/poses` shows them (as [`Self::newest`]), with the number of
    /// steps before it, in step order.
    pub poses: Vec<(u64, Vec<[f32; 4]>)>,
    /// What [`OnlineEstimator::maintain`] did between steps (`/so2lin/maintenance`), in the
    /// order recorded.
    pub maintenance: Vec<Maintained>,
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
        // Logs written before quarantine existed lack the key: they ran without it.
        let quarantine = match self.metadata.get("quarantine") {
            None => false,
            Some(v) => v.parse().map_err(|_| parse_err("quarantine"))?,
        };
        // Logs written before evictions existed lack the key: they ran without them.
        let evict = match self.metadata.get("evict") {
            None => false,
            Some(v) => v.parse().map_err(|_| parse_err("evict"))?,
        };
        // Logs written before the setting existed lack the key: they were recorded reading
        // the newest pose every step (the recorder does).
        let estimate_every_step = match self.metadata.get("estimate_every_step") {
            None => true,
            Some(v) => v.parse().map_err(|_| parse_err("estimate_every_step"))?,
        };
        // Logs written before the setting existed lack the key: they ran with the default.
        let renewal_delay = match self.metadata.get("renewal_delay") {
            None => 1.0,
            Some(v) => v.parse().map_err(|_| parse_err("renewal_delay"))?,
        };
        Ok(OnlineConfig {
            screening,
            quarantine,
            evict,
            estimate_every_step,
            renewal_delay,
        })
    }
}

/// How many times its file size a log's records may expand when decompressed: the bound on
/// every record and chunk [`read_log`] decompresses (at least [`MIN_RECORD_LIMIT`]). A length
/// field beyond it is reported as corruption before anything is allocated for it. so2lin's own
/// logs expand about 4–8× (JSON in zstd level 1).
pub const MAX_EXPANSION: usize = 64;

/// The smallest record bound, for tiny files: 1 MiB.
pub const MIN_RECORD_LIMIT: usize = 1 << 20;

/// The bound on any one record or decompressed chunk of a log of `file_len` bytes:
/// `max(file_len · MAX_EXPANSION, MIN_RECORD_LIMIT)`.
pub fn record_limit(file_len: usize) -> usize {
    file_len.saturating_mul(MAX_EXPANSION).max(MIN_RECORD_LIMIT)
}

/// Read a log linearly, tolerating a cut: everything before the cut is returned, and
/// `truncated` says why reading stopped.
///
/// Every chunk's CRC is checked before any of its records is used, and the data section's CRC
/// at its end; every record and decompressed chunk is bounded by [`record_limit`] of the
/// file's length, so a damaged length field is an error, never an allocation. A file that ends
/// inside a record is a cut ([`LogContents::truncated`]); any other damage (a CRC mismatch, an
/// impossible length, undecodable compressed data, a malformed record or message) is
/// [`LogError::Corrupt`], naming where reading stopped and how many steps before it were
/// intact.
pub fn read_log(bytes: &[u8]) -> Result<LogContents, LogError> {
    use mcap::records::Record;
    use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};

    if bytes.len() < 8 || &bytes[..8] != mcap::MAGIC {
        return Err(LogError::Format("not an MCAP file (bad magic)".into()));
    }
    let options = LinearReaderOptions::default()
        .with_skip_end_magic(true)
        .with_prevalidate_chunk_crcs(true)
        .with_validate_data_section_crc(true)
        .with_record_length_limit(record_limit(bytes.len()));
    let mut reader = LinearReader::new_with_options(options);
    reader
        .add_decompressor(BoundedZstd::new(bytes.len()))
        .map_err(LogError::from)?;
    let mut rest = bytes;
    let mut metadata = None;
    let mut topics: BTreeMap<u16, String> = BTreeMap::new();
    let (mut edges, mut steps) = (Vec::new(), Vec::new());
    let (mut newest, mut estimates, mut poses) = (BTreeMap::new(), Vec::new(), Vec::new());
    let mut maintenance = Vec::new();
    let mut truncated = None;
    // Corruption found while reading: (offset reached, what).
    let mut corrupt: Option<(usize, String)> = None;
    while let Some(event) = reader.next_event() {
        let offset = bytes.len() - rest.len();
        let record = match event {
            Ok(LinearReadEvent::ReadRequest(need)) => {
                let n = need.min(rest.len());
                reader.insert(n).copy_from_slice(&rest[..n]);
                reader.notify_read(n);
                rest = &rest[n..];
                continue;
            }
            // Only the records a so2lin log is read from are parsed, and only once every
            // length inside them fits the record (the parser would allocate from it).
            Ok(LinearReadEvent::Record { opcode, .. }) if !PARSED.contains(&opcode) => continue,
            Ok(LinearReadEvent::Record { opcode, data }) => {
                match fields_fit(opcode, data)
                    .and_then(|()| mcap::parse_record(opcode, data).map_err(|e| e.to_string()))
                {
                    Ok(r) => r,
                    Err(e) => {
                        corrupt = Some((
                            offset,
                            format!("malformed record (opcode {opcode:#04x}): {e}"),
                        ));
                        break;
                    }
                }
            }
            Err(mcap::McapError::UnexpectedEof) => {
                truncated = Some("the file ends inside a record".to_owned());
                break;
            }
            Err(e) => {
                corrupt = Some((offset, e.to_string()));
                break;
            }
        };
        match record {
            Record::Metadata(m) if m.name == "so2lin" => {
                metadata.get_or_insert(m.metadata);
            }
            Record::Channel(c) => {
                topics.insert(c.id, c.topic);
            }
            Record::Message { header, data } => {
                let Some(topic) = topics.get(&header.channel_id) else {
                    corrupt = Some((
                        offset,
                        format!("message on unknown channel {}", header.channel_id),
                    ));
                    break;
                };
                let parsed = match topic.as_str() {
                    "/so2lin/edge" => parse_json(&data).and_then(|v| {
                        edges.push((step_of(&v)?, edge_from_json(&v)?));
                        Ok(())
                    }),
                    "/so2lin/step" => parse_json(&data).and_then(|v| {
                        steps.push((step_of(&v)?, v));
                        Ok(())
                    }),
                    // The Foxglove messages carry their step in the header's sequence.
                    "/pose" => parse_json(&data).and_then(|v| {
                        let pose = displayed_pose(&v["pose"])?;
                        newest.entry(u64::from(header.sequence)).or_insert(pose);
                        Ok(())
                    }),
                    "/so2lin/estimate" => parse_json(&data).and_then(|v| {
                        let theta = (v["theta"].as_array())
                            .ok_or_else(|| LogError::Format("an estimate without theta".into()))?;
                        let theta = theta.iter().map(number).collect::<Result<_, _>>()?;
                        estimates.push((step_of(&v)?, theta));
                        Ok(())
                    }),
                    "/so2lin/maintenance" => parse_json(&data).and_then(|v| {
                        let count = |k: &str| {
                            (v[k].as_u64().and_then(|x| usize::try_from(x).ok())).ok_or_else(|| {
                                LogError::Format(format!("a maintenance without {k}"))
                            })
                        };
                        let renewed = (v["renewed"].as_bool()).ok_or_else(|| {
                            LogError::Format("a maintenance without renewed".into())
                        })?;
                        maintenance.push(Maintained {
                            steps: step_of(&v)?,
                            snapshots_before: (estimates.len(), poses.len()),
                            renewed,
                            factor: (count("variables")?, count("nonzeros")?),
                        });
                        Ok(())
                    }),
                    "/poses" => parse_json(&data).and_then(|v| {
                        let all = (v["poses"].as_array())
                            .ok_or_else(|| LogError::Format("poses without poses".into()))?;
                        let all = all.iter().map(displayed_pose).collect::<Result<_, _>>()?;
                        poses.push((u64::from(header.sequence), all));
                        Ok(())
                    }),
                    _ => Ok(()),
                };
                if let Err(e) = parsed {
                    corrupt = Some((offset, format!("{topic} message {}: {e}", header.sequence)));
                    break;
                }
            }
            Record::DataEnd(_) => break,
            _ => {}
        }
    }
    if truncated.is_none() && corrupt.is_none() && !bytes.ends_with(mcap::MAGIC) {
        truncated = Some("the file does not end with the MCAP magic".into());
    }
    // Keep only steps whose edge and outcome were both recorded, in step order.
    edges.sort_by_key(|x| x.0);
    steps.sort_by_key(|x| x.0);
    let n = edges.len().min(steps.len());
    let missing = edges
        .iter()
        .zip(&steps)
        .take(n)
        .enumerate()
        .find(|(k, ((te, _), (ts, _)))| *te != *k as u64 || *ts != *k as u64)
        .map(|(k, _)| k);
    if let Some((offset, what)) = corrupt {
        let intact = missing.unwrap_or(n);
        return Err(LogError::Corrupt {
            offset: offset as u64,
            what,
            intact_steps: intact,
        });
    }
    if let Some(k) = missing {
        return Err(LogError::Format(format!("step {k} is missing")));
    }
    let metadata = metadata.ok_or_else(|| LogError::Format("no so2lin metadata record".into()))?;
    Ok(LogContents {
        metadata,
        edges: edges.into_iter().take(n).map(|x| x.1).collect(),
        steps: steps.into_iter().take(n).map(|x| x.1).collect(),
        newest,
        estimates: sorted(estimates),
        poses: sorted(poses),
        maintenance,
        truncated,
    })
}

/// Snapshots in step order (stable: two at one step keep the order they were written in).
fn sorted<T>(mut snapshots: Vec<(u64, T)>) -> Vec<(u64, T)> {
    snapshots.sort_by_key(|s| s.0);
    snapshots
}

/// A number of a message (`null`: how JSON writes a value that is not finite).
fn number(v: &Value) -> Result<f64, LogError> {
    match v {
        Value::Null => Ok(f64::NAN),
        _ => v
            .as_f64()
            .ok_or_else(|| LogError::Format(format!("{v} where a number belongs"))),
    }
}

/// A Foxglove pose as displayed (x, y, the quaternion's z and w), each number read as the
/// single-precision value it was written from (its shortest decimal form, parsed as `f32`).
fn displayed_pose(pose: &Value) -> Result<[f32; 4], LogError> {
    let field = |outer: &str, inner: &str| -> Result<f32, LogError> {
        let v = &pose[outer][inner];
        let x = number(v)?;
        // The shortest form of an f32, read back as an f64, prints as that same form.
        Ok(if x.is_finite() {
            x.to_string().parse::<f32>().unwrap_or(x as f32)
        } else {
            x as f32
        })
    };
    Ok([
        field("position", "x")?,
        field("position", "y")?,
        field("orientation", "z")?,
        field("orientation", "w")?,
    ])
}

/// The step index a message carries.
fn step_of(v: &Value) -> Result<u64, LogError> {
    v.get("step")
        .and_then(Value::as_u64)
        .ok_or_else(|| LogError::Format("a message without its step index".into()))
}

/// zstd chunk decoding whose window (what the decoder allocates, in zstd's own C code, for a
/// frame) is bounded by [`record_limit`] of the file: mcap's built-in decoder accepts any window
/// up to 128 MiB that a frame header asks for.
struct BoundedZstd {
    stream: Option<zstd::zstd_safe::DStream<'static>>,
    need: usize,
    window_log: u32,
}

impl BoundedZstd {
    fn new(file_len: usize) -> Self {
        let limit = record_limit(file_len);
        // The smallest power of two ≥ the limit, within zstd's range [2^10, 2^27].
        let window_log = limit.next_power_of_two().trailing_zeros().clamp(10, 27);
        Self {
            stream: None,
            need: 0,
            window_log,
        }
    }
}

fn zstd_result(r: zstd::zstd_safe::SafeResult) -> Result<usize, mcap::McapError> {
    r.map_err(|code| {
        mcap::McapError::DecompressionError(zstd::zstd_safe::get_error_name(code).into())
    })
}

impl mcap::sans_io::decompressor::Decompressor for BoundedZstd {
    fn next_read_size(&self) -> usize {
        self.need
    }

    fn decompress(
        &mut self,
        src: &[u8],
        dst: &mut [u8],
    ) -> Result<mcap::sans_io::decompressor::DecompressResult, mcap::McapError> {
        use zstd::zstd_safe::{DParameter, DStream, InBuffer, OutBuffer};
        if self.stream.is_none() {
            let mut stream = DStream::create();
            zstd_result(stream.init())?;
            zstd_result(stream.set_parameter(DParameter::WindowLogMax(self.window_log)))?;
            self.stream = Some(stream);
        }
        let Some(stream) = self.stream.as_mut() else {
            return Err(mcap::McapError::DecompressionError("no zstd stream".into()));
        };
        let mut input = InBuffer::around(src);
        let mut output = OutBuffer::around(dst);
        self.need = zstd_result(stream.decompress_stream(&mut output, &mut input))?;
        Ok(mcap::sans_io::decompressor::DecompressResult {
            consumed: input.pos,
            wrote: output.pos(),
        })
    }

    fn reset(&mut self) -> Result<(), mcap::McapError> {
        self.need = 0;
        if let Some(stream) = self.stream.as_mut() {
            zstd_result(stream.reset(zstd::zstd_safe::ResetDirective::SessionOnly))?;
        }
        Ok(())
    }

    fn name(&self) -> &'static str {
        "zstd"
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mcap::sans_io::decompressor::Decompressor;

    fn frame(window_log: u32, data: &[u8]) -> Vec<u8> {
        let mut enc = zstd::stream::Encoder::new(Vec::new(), 1).unwrap();
        enc.include_contentsize(false).unwrap();
        enc.window_log(window_log).unwrap();
        enc.long_distance_matching(true).unwrap();
        std::io::Write::write_all(&mut enc, data).unwrap();
        enc.finish().unwrap()
    }

    #[test]
    fn zstd_windows_beyond_the_record_limit_are_refused() {
        let data = b"so2lin so2lin so2lin so2lin".repeat(100);
        // A 10 kB file: records up to 1 MiB, window up to 2^20.
        let mut d = BoundedZstd::new(10_000);
        assert_eq!(d.window_log, 20);
        let mut out = vec![0; data.len()];
        let small = frame(20, &data);
        let r = d.decompress(&small, &mut out).unwrap();
        assert_eq!(&out[..r.wrote], &data[..]);
        // A frame asking for a 128 MiB window is an error before zstd allocates it.
        d.reset().unwrap();
        let big = frame(27, &data);
        let e = d.decompress(&big, &mut out).unwrap_err();
        assert!(
            e.to_string().contains("Frame requires too much memory"),
            "{e}"
        );
    }
}

/// Opcodes of the records [`read_log`] parses: channel, message, metadata, data end.
const PARSED: [u8; 4] = [0x04, 0x05, 0x0C, 0x0F];

/// Whether every length-prefixed field of a channel or metadata record fits in the record
/// (the others have no such field).
fn fields_fit(opcode: u8, data: &[u8]) -> Result<(), String> {
    struct Cursor<'a>(&'a [u8]);
    impl Cursor<'_> {
        fn skip(&mut self, n: usize) -> Result<(), String> {
            match self.0.get(n..) {
                Some(rest) => {
                    self.0 = rest;
                    Ok(())
                }
                None => Err(format!("a field of {n} bytes with {} left", self.0.len())),
            }
        }
        fn len(&mut self) -> Result<usize, String> {
            let bytes: [u8; 4] = self
                .0
                .get(..4)
                .and_then(|b| b.try_into().ok())
                .ok_or("a length cut short")?;
            self.0 = &self.0[4..];
            Ok(u32::from_le_bytes(bytes) as usize)
        }
        fn string(&mut self) -> Result<(), String> {
            let n = self.len()?;
            self.skip(n)
        }
        fn string_map(&mut self) -> Result<(), String> {
            let n = self.len()?;
            let mut inner = Cursor(
                self.0
                    .get(..n)
                    .ok_or_else(|| format!("a map of {n} bytes with {} left", self.0.len()))?,
            );
            while !inner.0.is_empty() {
                inner.string()?;
                inner.string()?;
            }
            self.skip(n)
        }
    }
    let mut c = Cursor(data);
    let checked = match opcode {
        // Channel: id, schema id, topic, message encoding, metadata.
        0x04 => c
            .skip(4)
            .and_then(|()| c.string())
            .and_then(|()| c.string())
            .and_then(|()| c.string_map()),
        // Metadata: name, metadata.
        0x0C => c.string().and_then(|()| c.string_map()),
        _ => Ok(()),
    };
    checked.map_err(|e| format!("record (opcode {opcode:#04x}) claims {e}"))
}

fn parse_json(data: &[u8]) -> Result<Value, LogError> {
    serde_json::from_slice(data).map_err(|e| LogError::Format(e.to_string()))
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
    /// What differs: the step's outcome (`/so2lin/step`), the newest pose after it (`/pose`),
    /// or a snapshot taken after it (`/so2lin/estimate`: orientations, `/poses`: poses).
    pub channel: &'static str,
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

/// Compare step `k` as replayed (`step`, and the estimator after it) with the recording: its
/// outcome and the newest pose after it (read as the recorder read it). Reads change no later
/// answer (the estimate is the same bits whenever it is read), and the recorder read the same
/// things at the same steps.
fn verify_step(
    log: &LogContents,
    k: usize,
    step: &crate::online::Step,
    recorded: &Value,
    est: &mut OnlineEstimator,
) -> Result<Option<Divergence>, LogError> {
    let newest = est.newest().ok().flatten();
    let mut replayed = step_json(k as u64, step, newest)?;
    let mut recorded = recorded.clone();
    if let (Value::Object(rec), Value::Object(rep)) = (&mut recorded, &mut replayed) {
        rec.insert("latency_ns".into(), json!(0));
        // Logs written before steps carried the newest pose have it on `/pose` only.
        if !rec.contains_key("newest") {
            rep.remove("newest");
        }
    }
    if recorded != replayed {
        return Ok(Some(diverged(k, "/so2lin/step", recorded, replayed)));
    }
    let shown = newest.map(|(_, p)| foxglove::displayed((p.x, p.y), p.theta));
    let was = log.newest.get(&(k as u64)).copied();
    if first_difference(was.as_slice(), shown.as_slice(), same_pose).is_some() {
        return Ok(Some(diverged(k, "/pose", json!(was), json!(shown))));
    }
    Ok(None)
}

/// A divergence at step `k`.
fn diverged(k: usize, channel: &'static str, recorded: Value, replayed: Value) -> Divergence {
    Divergence {
        step: k,
        channel,
        recorded,
        replayed,
    }
}

/// Equal as `/pose` and `/poses` show them.
fn same_pose(a: &[f32; 4], b: &[f32; 4]) -> bool {
    first_difference(a, b, same_f32).is_none()
}

/// Compare the recorded snapshots `estimates` and `poses` (taken after step `k`) with the
/// replayed estimator's exact poses now.
fn verify_snapshots(
    k: usize,
    estimates: &[(u64, Vec<f64>)],
    snapshots: &[(u64, Vec<[f32; 4]>)],
    est: &mut OnlineEstimator,
) -> Option<Divergence> {
    if estimates.is_empty() && snapshots.is_empty() {
        return None;
    }
    // (Poses the replay cannot compute differ from any recorded snapshot.)
    let poses = est.poses().unwrap_or_default();
    let theta: Vec<f64> = poses.iter().map(|p| p.theta).collect();
    let shown: Vec<[f32; 4]> = (poses.iter())
        .map(|p| foxglove::displayed((p.x, p.y), p.theta))
        .collect();
    for (_, was) in estimates {
        if let Some((i, was, now)) = first_difference(was, &theta, |a, b| same_f64(*a, *b)) {
            let (was, now) = (was_at(i, was), was_at(i, now));
            return Some(diverged(k, "/so2lin/estimate", was, now));
        }
    }
    for (_, was) in snapshots {
        if let Some((i, was, now)) = first_difference(was, &shown, same_pose) {
            return Some(diverged(k, "/poses", was_at(i, was), was_at(i, now)));
        }
    }
    None
}

/// After step `k` has been replayed (and verified): what [`OnlineEstimator::maintain`] was
/// recorded doing after it, each done again, and with `verify` the
/// snapshots taken after the step compared in between, each with the estimator as it was when
/// it was taken. `next` is the first maintenance not yet replayed (advanced past these).
fn after_step(
    log: &LogContents,
    k: usize,
    est: &mut OnlineEstimator,
    next: &mut usize,
    verify: bool,
) -> Option<Divergence> {
    let after = k as u64 + 1;
    let (estimates, snapshots) = (taken_at(&log.estimates, after), taken_at(&log.poses, after));
    // Where the snapshots after this step start in the log's lists.
    let first = (
        log.estimates.len() - taken_from(&log.estimates, after),
        log.poses.len() - taken_from(&log.poses, after),
    );
    let (mut e, mut p) = (0, 0);
    while let Some(m) = log.maintenance.get(*next).filter(|m| m.steps <= after) {
        *next += 1;
        if m.steps < after {
            continue;
        }
        if verify {
            let (e_to, p_to) = (
                m.snapshots_before
                    .0
                    .saturating_sub(first.0)
                    .clamp(e, estimates.len()),
                m.snapshots_before
                    .1
                    .saturating_sub(first.1)
                    .clamp(p, snapshots.len()),
            );
            let d = verify_snapshots(k, &estimates[e..e_to], &snapshots[p..p_to], est);
            if d.is_some() {
                return d;
            }
            (e, p) = (e_to, p_to);
        }
        let done = est.maintain();
        let made = (done.relinearised).then_some((done.renewed, (done.variables, done.nonzeros)));
        if verify && made != Some((m.renewed, m.factor)) {
            let recorded = json!({ "renewed": m.renewed, "factor": m.factor });
            let replayed = json!({ "done": made });
            return Some(diverged(k, "/so2lin/maintenance", recorded, replayed));
        }
    }
    if verify {
        return verify_snapshots(k, &estimates[e..], &snapshots[p..], est);
    }
    None
}

/// How many snapshots of `s` (in step order) were taken after `steps` steps or later.
fn taken_from<T>(s: &[(u64, T)], steps: u64) -> usize {
    s.len() - s.partition_point(|(at, _)| *at < steps)
}

/// The snapshots of `s` (in step order) taken after `steps` steps.
fn taken_at<T>(s: &[(u64, T)], steps: u64) -> &[(u64, T)] {
    let from = s.partition_point(|(at, _)| *at < steps);
    // (`max`: a caller's list out of order finds nothing rather than panicking.)
    let to = s.partition_point(|(at, _)| *at <= steps).max(from);
    &s[from..to]
}

/// Equal to the bit, a NaN equal to any NaN (written as `null`, read back as NaN).
fn same_f64(a: f64, b: f64) -> bool {
    a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())
}

/// [`same_f64`] in single precision (widening keeps bits apart and NaNs NaN).
fn same_f32(a: &f32, b: &f32) -> bool {
    same_f64(f64::from(*a), f64::from(*b))
}

/// The first index where `was` and `now` differ under `eq` (their lengths, if one is the
/// other's start), with the two entries there (`None` past an end).
fn first_difference<'a, T>(
    was: &'a [T],
    now: &'a [T],
    eq: impl Fn(&T, &T) -> bool,
) -> Option<(usize, Option<&'a T>, Option<&'a T>)> {
    let i = (0..was.len().max(now.len()))
        .find(|&i| !matches!((was.get(i), now.get(i)), (Some(a), Some(b)) if eq(a, b)))?;
    Some((i, was.get(i), now.get(i)))
}

/// One entry of a snapshot, for a divergence: its index and value (null past the end).
fn was_at<T: serde::Serialize>(i: usize, v: Option<&T>) -> Value {
    json!({ "index": i, "value": v })
}

/// Rebuild the run from a log; with `verify`, compare every step with the recorded one — its
/// outcome, the newest pose after it and the snapshots taken after it — and stop at the first
/// divergence.
pub fn replay(log: &LogContents, verify: bool) -> Result<Replay, LogError> {
    let config = log.config()?;
    let mut est = OnlineEstimator::new(config).map_err(|e| LogError::Format(e.to_string()))?;
    // The log's size is known, as the stream's file was (`OnlineEstimator::reserve`).
    let nodes: std::collections::BTreeSet<_> =
        log.edges.iter().flat_map(|e| [e.from(), e.to()]).collect();
    // Refused, the replay goes on without it (its arrays grow as they would have).
    let _ = est.reserve(nodes.len(), log.edges.len());
    let mut latency_ns = Vec::with_capacity(log.edges.len());
    let mut divergence = None;
    // The first recorded maintenance not replayed yet.
    let mut next = 0;
    for (k, (edge, recorded)) in log.edges.iter().zip(&log.steps).enumerate() {
        let t = std::time::Instant::now();
        let step = est
            .add_edge(*edge)
            .map_err(|e| LogError::Format(format!("step {k}: {e}")))?;
        latency_ns.push(t.elapsed().as_nanos() as u64);
        if verify {
            divergence = verify_step(log, k, &step, recorded, &mut est)?;
        }
        if divergence.is_none() {
            divergence = after_step(log, k, &mut est, &mut next, verify);
        }
        if divergence.is_some() {
            break;
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
