//! Reading and writing pose graphs: g2o (`VERTEX_SE2`, `EDGE_SE2`) and TORO (`VERTEX2`,
//! `EDGE2`, `EQUIV`).
//!
//! Each edge line gives `i j dx dy dθ` and six information entries. Their order is
//! g2o `I11 I12 I13 I22 I23 I33` (upper triangle of Ω in (x, y, θ) order) or TORO
//! `Ixx Ixy Iyy Itt Ixt Iyt`. **The tag alone does not decide** (`w20000.txt` uses `EDGE2`
//! with g2o-ordered numbers, see `datasets/SOURCES.md`), so with [`InfoOrder::Auto`] the
//! order is detected: an edge whose entries are positive definite in exactly one order
//! decides it for the whole file; edges read before a decision (entries positive definite in
//! both orders) are held back and interpreted once the order is known (or in the tag's order
//! at end of file). The caller can force an order instead.
//!
//! Other rules:
//! - `δ = dθ` is kept as written, also outside (−π, π]. Edges with `i > j` keep their direction.
//! - Subnormal information entries (the ~6.95e-310 garbage in `FRH.g2o`) are read as 0.
//! - `EQUIV a b` (TORO node equivalence) is **reported, not merged**: it is returned as a
//!   [`Record::Equiv`] and listed in [`ReadSummary::equivalences`]. Merging would turn the
//!   measured edges that such files also carry between the two nodes (`w100.graph` has
//!   `21→1` beside `EQUIV 21 1`) into self-loops and silently drop measurements; a caller
//!   that wants merged nodes can relabel with the list.
//! - Unknown tags (landmarks, 3D, `FIX`, …) are skipped and counted per tag; `#` comments
//!   and blank lines are ignored.
//! - Every malformed line is a [`ReadError`] with file, line number and what was wrong.
//! - A line may hold at most [`MAX_LINE_BYTES`] (1 MiB) bytes: a longer one (a binary file, a
//!   corrupted or hostile file, `/dev/zero`) is [`LineError::TooLong`] after reading at most
//!   that much, so memory stays bounded whatever the input.
//! - An MCAP log given as a graph is [`LineError::McapLog`], not a line of garbage.
//!
//! [`Reader`] is an iterator of [`Record`]s in file order (how the online estimator and the
//! `stream` command consume a file); [`read_graph`] collects one into a [`PoseGraph`].

use std::collections::{BTreeMap, VecDeque};
use std::fs::File;
use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;

use crate::graph::{Edge, GraphError, Information, NodeId, NodePolicy, Pose2, PoseGraph};

/// The longest line a graph file may have, in bytes (1 MiB; the longest line of a valid file
/// is about 200 bytes).
pub const MAX_LINE_BYTES: usize = 1 << 20;

/// The 8 bytes every MCAP file starts with (the last one is a newline, so a graph reader sees
/// them as line 1).
const MCAP_MAGIC: &[u8] = b"\x89MCAP0\r\n";

/// Order of the six information entries on an edge line.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum InfoOrder {
    /// Detect from positive definiteness (see the module docs).
    #[default]
    Auto,
    /// `I11 I12 I13 I22 I23 I33`.
    G2o,
    /// `Ixx Ixy Iyy Itt Ixt Iyt`.
    Toro,
}

impl InfoOrder {
    /// Reorder six raw entries into g2o order.
    fn to_g2o(self, v: [f64; 6]) -> [f64; 6] {
        match self {
            InfoOrder::Toro => [v[0], v[1], v[4], v[2], v[5], v[3]],
            _ => v,
        }
    }
}

/// Options for reading a graph file.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct ReadOptions {
    /// Information-matrix order (default: detect).
    pub order: InfoOrder,
    /// Whether edges may name nodes without a vertex line (default: yes; several
    /// benchmark files have no vertex lines at all).
    pub nodes: NodePolicy,
}

/// One meaningful line of a graph file.
#[derive(Clone, Debug, PartialEq)]
pub enum Record {
    /// A vertex with its initial pose.
    Vertex {
        /// Node id.
        id: NodeId,
        /// Initial pose.
        pose: Pose2,
        /// 1-based line number.
        line: usize,
    },
    /// A validated edge.
    Edge {
        /// The edge.
        edge: Edge,
        /// 1-based line number.
        line: usize,
    },
    /// A TORO `EQUIV a b` line.
    Equiv {
        /// First node.
        a: NodeId,
        /// Second node.
        b: NodeId,
        /// 1-based line number.
        line: usize,
    },
}

/// What was wrong with a line.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum LineError {
    /// The underlying reader failed.
    #[error("I/O error: {0}")]
    Io(String),
    /// The line is not valid UTF-8.
    #[error("line is not valid UTF-8")]
    NotUtf8,
    /// The line is longer than [`MAX_LINE_BYTES`].
    #[error("line is longer than {max} bytes: not a graph file")]
    TooLong {
        /// The limit, [`MAX_LINE_BYTES`].
        max: usize,
    },
    /// The file is an MCAP log, not a graph file.
    #[error(
        "this is an MCAP log, not a graph file: read it with so2lin::log::read_log (`so2lin replay` or `so2lin plot`)"
    )]
    McapLog,
    /// The path is a directory.
    #[error("is a directory, not a graph file")]
    Directory,
    /// Wrong number of fields for the tag.
    #[error("{tag} needs {expected} fields after the tag, found {found}")]
    FieldCount {
        /// The line's tag.
        tag: String,
        /// Fields required.
        expected: usize,
        /// Fields present.
        found: usize,
    },
    /// A field that is not a number.
    #[error("field {field} ({name}) is not a number: {text:?}")]
    BadNumber {
        /// 1-based field index after the tag.
        field: usize,
        /// What the field is.
        name: &'static str,
        /// The text found.
        text: String,
    },
    /// A node id that is not a non-negative integer.
    #[error("field {field} is not a valid node id (non-negative integer): {text:?}")]
    BadId {
        /// 1-based field index after the tag.
        field: usize,
        /// The text found.
        text: String,
    },
    /// The information entries are positive definite in neither g2o nor TORO order.
    #[error("information matrix {raw:?} is positive definite in neither g2o nor TORO order")]
    NoValidOrder {
        /// The six raw entries as written.
        raw: [f64; 6],
    },
    /// The edge or node failed validation.
    #[error(transparent)]
    Graph(#[from] GraphError),
}

/// A reading error: file, 1-based line number, and what was wrong. Displayed as
/// `file:line: what`, or `file: what` for errors not tied to a line.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{file}{}: {kind}", if *line > 0 { format!(":{line}") } else { String::new() })]
pub struct ReadError {
    /// File name (or a label for in-memory input).
    pub file: String,
    /// 1-based line number (0 for errors not tied to a line, such as failing to open).
    pub line: usize,
    /// What was wrong.
    pub kind: LineError,
}

/// What a whole read found besides the records.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct ReadSummary {
    /// Lines skipped, by tag (unknown tags: landmarks, 3D, …); tags are cut to 40 characters,
    /// and beyond 256 distinct tags the rest are counted under `(other tags)`.
    pub skipped: BTreeMap<String, usize>,
    /// The information order used for edges (None when the file has no edges).
    pub order: Option<InfoOrder>,
    /// `EQUIV a b` pairs, in file order.
    pub equivalences: Vec<(NodeId, NodeId)>,
    /// Number of vertex lines.
    pub vertices: usize,
    /// Number of edge lines.
    pub edges: usize,
    /// The 1-based line of every edge of the graph, by edge index (filled by [`read_graph`]
    /// and [`read_graph_from`]).
    #[serde(skip)]
    pub edge_lines: Vec<usize>,
}

/// An edge line parsed but not yet interpreted (its information order may be undecided).
#[derive(Clone, Debug)]
struct RawEdge {
    from: NodeId,
    to: NodeId,
    pose: Pose2,
    raw: [f64; 6],
    tag_order: InfoOrder,
    line: usize,
}

enum Pending {
    Record(Record),
    Edge(RawEdge),
}

/// Streaming reader: an iterator of [`Record`]s in file order.
///
/// After the last item, [`summary`](Reader::summary) tells what was skipped and which
/// information order was used. After an error the iterator ends.
pub struct Reader<R> {
    src: R,
    file: String,
    forced: InfoOrder,
    decided: Option<InfoOrder>,
    line: usize,
    buf: Vec<u8>,
    pending: VecDeque<Pending>,
    ready: VecDeque<Result<Record, ReadError>>,
    summary: ReadSummary,
    done: bool,
}

impl Reader<BufReader<File>> {
    /// Open a file for streaming.
    pub fn open(path: impl AsRef<Path>, order: InfoOrder) -> Result<Self, ReadError> {
        let path = path.as_ref();
        let file = open_file(path)?;
        Ok(Reader::new(
            BufReader::new(file),
            path.display().to_string(),
            order,
        ))
    }
}

/// Open a graph file for reading: a directory or a file that cannot be opened is a
/// [`ReadError`] at line 0.
pub fn open_file(path: &Path) -> Result<File, ReadError> {
    let err = |kind| ReadError {
        file: path.display().to_string(),
        line: 0,
        kind,
    };
    let file = File::open(path).map_err(|e| err(LineError::Io(e.to_string())))?;
    match file.metadata() {
        Ok(m) if m.is_dir() => Err(err(LineError::Directory)),
        _ => Ok(file),
    }
}

impl<R: BufRead> Reader<R> {
    /// Stream records from any buffered source; `file` names it in errors.
    pub fn new(src: R, file: impl Into<String>, order: InfoOrder) -> Self {
        let decided = (order != InfoOrder::Auto).then_some(order);
        Self {
            src,
            file: file.into(),
            forced: order,
            decided,
            line: 0,
            buf: Vec::new(),
            pending: VecDeque::new(),
            ready: VecDeque::new(),
            summary: ReadSummary::default(),
            done: false,
        }
    }

    /// Skipped tags, order used, equivalences and counts so far (complete after the last item).
    pub fn summary(&self) -> &ReadSummary {
        &self.summary
    }

    /// Only the edges, in file order (vertices and equivalences are consumed silently but
    /// still counted in the summary).
    pub fn edges(&mut self) -> impl Iterator<Item = Result<Edge, ReadError>> + '_ {
        self.filter_map(|r| match r {
            Ok(Record::Edge { edge, .. }) => Some(Ok(edge)),
            Ok(_) => None,
            Err(e) => Some(Err(e)),
        })
    }

    fn err(&self, line: usize, kind: LineError) -> ReadError {
        ReadError {
            file: self.file.clone(),
            line,
            kind,
        }
    }

    /// Interpret a raw edge in a given order.
    fn finish_edge(&mut self, raw: &RawEdge, order: InfoOrder) -> Result<Record, ReadError> {
        self.summary.order.get_or_insert(order);
        let info = Information(order.to_g2o(raw.raw));
        Edge::new(raw.from, raw.to, raw.pose, info)
            .map(|edge| Record::Edge {
                edge,
                line: raw.line,
            })
            .map_err(|e| self.err(raw.line, e.into()))
    }

    /// Move held-back items to the output, interpreting edges in `order` (or their tag's).
    fn release_pending(&mut self, order: Option<InfoOrder>) {
        while let Some(p) = self.pending.pop_front() {
            let out = match p {
                Pending::Record(r) => Ok(r),
                Pending::Edge(raw) => self.finish_edge(&raw, order.unwrap_or(raw.tag_order)),
            };
            self.ready.push_back(out);
        }
    }

    fn handle_edge(&mut self, raw: RawEdge) {
        let order = match self.decided {
            Some(o) => Some(o),
            None => {
                let g = Information(InfoOrder::G2o.to_g2o(raw.raw)).is_positive_definite();
                let t = Information(InfoOrder::Toro.to_g2o(raw.raw)).is_positive_definite();
                match (g, t) {
                    (true, false) => Some(InfoOrder::G2o),
                    (false, true) => Some(InfoOrder::Toro),
                    (true, true) => None,
                    (false, false) => {
                        self.release_pending(None);
                        let e = self.err(raw.line, LineError::NoValidOrder { raw: raw.raw });
                        self.ready.push_back(Err(e));
                        return;
                    }
                }
            }
        };
        match order {
            Some(o) => {
                self.decided = Some(o);
                self.release_pending(Some(o));
                let r = self.finish_edge(&raw, o);
                self.ready.push_back(r);
            }
            None => self.pending.push_back(Pending::Edge(raw)),
        }
    }

    fn emit(&mut self, r: Record) {
        if self.pending.is_empty() {
            self.ready.push_back(Ok(r));
        } else {
            self.pending.push_back(Pending::Record(r));
        }
    }

    /// Read one physical line and queue what it yields. Returns false at end of input.
    fn step(&mut self) -> bool {
        self.buf.clear();
        // Read at most one byte more than a line may hold: memory stays bounded on any input.
        let limit = MAX_LINE_BYTES as u64 + 1;
        match (&mut self.src).take(limit).read_until(b'\n', &mut self.buf) {
            Ok(0) => return false,
            Ok(_) if self.buf.len() > MAX_LINE_BYTES => {
                self.line += 1;
                let e = self.err(
                    self.line,
                    LineError::TooLong {
                        max: MAX_LINE_BYTES,
                    },
                );
                self.ready.push_back(Err(e));
                return true;
            }
            Ok(_) if self.line == 0 && self.buf == MCAP_MAGIC => {
                self.line += 1;
                let e = self.err(self.line, LineError::McapLog);
                self.ready.push_back(Err(e));
                return true;
            }
            Ok(_) => {}
            Err(e) => {
                self.line += 1;
                let e = self.err(self.line, LineError::Io(e.to_string()));
                self.ready.push_back(Err(e));
                return true;
            }
        }
        self.line += 1;
        let line = self.line;
        let text = match std::str::from_utf8(&self.buf) {
            Ok(t) => t.to_owned(),
            Err(_) => {
                let e = self.err(line, LineError::NotUtf8);
                self.ready.push_back(Err(e));
                return true;
            }
        };
        match parse_line(&text, line) {
            Ok(Parsed::Nothing) => {}
            Ok(Parsed::Skipped(tag)) => {
                // Bounded bookkeeping: tags are cut to 40 characters and at most
                // MAX_SKIPPED_TAGS distinct tags are listed, the rest counted together.
                let known = self.summary.skipped.len() < MAX_SKIPPED_TAGS
                    || self.summary.skipped.contains_key(&tag);
                let key = if known { tag } else { OTHER_TAGS.to_owned() };
                *self.summary.skipped.entry(key).or_default() += 1
            }
            Ok(Parsed::Record(r)) => {
                match &r {
                    Record::Vertex { .. } => self.summary.vertices += 1,
                    Record::Equiv { a, b, .. } => self.summary.equivalences.push((*a, *b)),
                    Record::Edge { .. } => {}
                }
                self.emit(r)
            }
            Ok(Parsed::Edge(raw)) => {
                self.summary.edges += 1;
                let raw = RawEdge {
                    tag_order: if self.forced == InfoOrder::Auto {
                        raw.tag_order
                    } else {
                        self.forced
                    },
                    ..raw
                };
                self.handle_edge(raw)
            }
            Err(kind) => {
                self.release_pending(None);
                let e = self.err(line, kind);
                self.ready.push_back(Err(e));
            }
        }
        true
    }
}

impl<R: BufRead> Iterator for Reader<R> {
    type Item = Result<Record, ReadError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if let Some(item) = self.ready.pop_front() {
                if item.is_err() {
                    self.done = true;
                    self.ready.clear();
                    self.pending.clear();
                }
                return Some(item);
            }
            if self.done {
                return None;
            }
            if !self.step() {
                // End of input: undecided edges take their tag's order.
                self.release_pending(None);
                self.done = true;
                if self.ready.is_empty() {
                    return None;
                }
            }
        }
    }
}

enum Parsed {
    Nothing,
    Skipped(String),
    Record(Record),
    Edge(RawEdge),
}

const EDGE_NAMES: [&str; 11] = [
    "from", "to", "dx", "dy", "dtheta", "info1", "info2", "info3", "info4", "info5", "info6",
];

fn parse_line(text: &str, line: usize) -> Result<Parsed, LineError> {
    let mut fields = text.split_ascii_whitespace();
    let Some(tag) = fields.next() else {
        return Ok(Parsed::Nothing);
    };
    if tag.starts_with('#') {
        return Ok(Parsed::Nothing);
    }
    let rest: Vec<&str> = fields.collect();
    let count = |expected: usize| {
        if rest.len() == expected {
            Ok(())
        } else {
            Err(LineError::FieldCount {
                tag: short(tag),
                expected,
                found: rest.len(),
            })
        }
    };
    match tag {
        "VERTEX_SE2" | "VERTEX2" => {
            count(4)?;
            let id = parse_id(rest[0], 1)?;
            let v = [
                parse_num(rest[1], 2, "x")?,
                parse_num(rest[2], 3, "y")?,
                parse_num(rest[3], 4, "theta")?,
            ];
            let pose = Pose2::new(v[0], v[1], v[2]);
            if v.iter().any(|x| !x.is_finite()) {
                return Err(GraphError::NonFinitePose { node: id }.into());
            }
            Ok(Parsed::Record(Record::Vertex { id, pose, line }))
        }
        "EDGE_SE2" | "EDGE2" => {
            count(11)?;
            let from = parse_id(rest[0], 1)?;
            let to = parse_id(rest[1], 2)?;
            let mut v = [0.0; 9];
            for (k, x) in v.iter_mut().enumerate() {
                *x = parse_num(rest[k + 2], k + 3, EDGE_NAMES[k + 2])?;
            }
            let mut raw = [v[3], v[4], v[5], v[6], v[7], v[8]];
            for x in &mut raw {
                if x.is_subnormal() {
                    *x = 0.0;
                }
            }
            let tag_order = if tag == "EDGE2" {
                InfoOrder::Toro
            } else {
                InfoOrder::G2o
            };
            let pose = Pose2::new(v[0], v[1], v[2]);
            // Report non-finite numbers as such, before any order detection.
            for (what, ok) in [
                ("measurement", v[..3].iter().all(|x| x.is_finite())),
                ("information matrix", raw.iter().all(|x| x.is_finite())),
            ] {
                if !ok {
                    return Err(GraphError::NonFinite { from, to, what }.into());
                }
            }
            Ok(Parsed::Edge(RawEdge {
                from,
                to,
                pose,
                raw,
                tag_order,
                line,
            }))
        }
        "EQUIV" => {
            count(2)?;
            let a = parse_id(rest[0], 1)?;
            let b = parse_id(rest[1], 2)?;
            Ok(Parsed::Record(Record::Equiv { a, b, line }))
        }
        other => Ok(Parsed::Skipped(short(other))),
    }
}

/// At most this many distinct skipped tags are listed in [`ReadSummary::skipped`].
const MAX_SKIPPED_TAGS: usize = 256;
/// The key counting skipped lines beyond [`MAX_SKIPPED_TAGS`] distinct tags.
const OTHER_TAGS: &str = "(other tags)";

/// A field quoted in a message or used as a key: at most 40 characters.
fn short(text: &str) -> String {
    match text.char_indices().nth(40) {
        Some((end, _)) => format!("{}…", &text[..end]),
        None => text.to_owned(),
    }
}

fn parse_id(text: &str, field: usize) -> Result<NodeId, LineError> {
    text.parse().map_err(|_| LineError::BadId {
        field,
        text: short(text),
    })
}

fn parse_num(text: &str, field: usize, name: &'static str) -> Result<f64, LineError> {
    text.parse().map_err(|_| LineError::BadNumber {
        field,
        name,
        text: short(text),
    })
}

/// Read a whole graph file.
pub fn read_graph(
    path: impl AsRef<Path>,
    options: ReadOptions,
) -> Result<(PoseGraph, ReadSummary), ReadError> {
    let reader = Reader::open(path, options.order)?;
    collect_graph(reader, options.nodes)
}

/// Read a whole graph from any buffered source; `name` labels it in errors.
pub fn read_graph_from<R: BufRead>(
    src: R,
    name: &str,
    options: ReadOptions,
) -> Result<(PoseGraph, ReadSummary), ReadError> {
    collect_graph(Reader::new(src, name, options.order), options.nodes)
}

fn collect_graph<R: BufRead>(
    mut reader: Reader<R>,
    policy: NodePolicy,
) -> Result<(PoseGraph, ReadSummary), ReadError> {
    let mut graph = PoseGraph::new();
    let mut edge_lines = Vec::new();
    while let Some(record) = reader.next() {
        let (result, line) = match record? {
            Record::Vertex { id, pose, line } => (graph.add_node(id, Some(pose)).map(drop), line),
            Record::Edge { edge, line } => {
                edge_lines.push(line);
                (graph.add_edge(edge, policy).map(drop), line)
            }
            Record::Equiv { .. } => continue,
        };
        result.map_err(|e| reader.err(line, e.into()))?;
    }
    let mut summary = reader.summary.clone();
    summary.edge_lines = edge_lines;
    Ok((graph, summary))
}

/// Write a graph in g2o format: one `VERTEX_SE2` per node that has a pose, then every edge
/// unchanged as `EDGE_SE2` (g2o information order), in insertion order.
///
/// `poses` (indexed by dense node index, e.g. estimated poses) replaces the initial poses;
/// without it, nodes with no initial pose get no vertex line. Numbers are written in Rust's
/// shortest round-trip form, so reading the file back gives bit-identical edges.
pub fn write_g2o<W: Write>(
    mut w: W,
    graph: &PoseGraph,
    poses: Option<&[Pose2]>,
) -> std::io::Result<()> {
    for (k, node) in graph.nodes().iter().enumerate() {
        let pose = match poses {
            Some(p) => p.get(k).copied(),
            None => node.initial,
        };
        if let Some(p) = pose {
            writeln!(
                w,
                "VERTEX_SE2 {} {:?} {:?} {:?}",
                node.id, p.x, p.y, p.theta
            )?;
        }
    }
    for e in graph.edges() {
        let m = e.measurement();
        let i = e.information().0;
        writeln!(
            w,
            "EDGE_SE2 {} {} {:?} {:?} {:?} {:?} {:?} {:?} {:?} {:?} {:?}",
            e.from(),
            e.to(),
            m.x,
            m.y,
            m.theta,
            i[0],
            i[1],
            i[2],
            i[3],
            i[4],
            i[5]
        )?;
    }
    w.flush()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read(text: &str) -> Result<(PoseGraph, ReadSummary), ReadError> {
        read_graph_from(text.as_bytes(), "mem", ReadOptions::default())
    }

    #[test]
    fn toro_and_g2o_orders() {
        let toro = "EDGE2 0 1 1 0 0.1 10 0 20 30 0 0\n";
        let (g, s) = read(toro).unwrap();
        assert_eq!(s.order, Some(InfoOrder::Toro));
        assert_eq!(
            g.edges()[0].information().0,
            [10.0, 0.0, 0.0, 20.0, 0.0, 30.0]
        );
        // w20000 style: EDGE2 tag with g2o-ordered numbers.
        let w = "EDGE2 0 1 1 0 0.1 3.16228 0 0 3.16228 0 5\n";
        let (g, s) = read(w).unwrap();
        assert_eq!(s.order, Some(InfoOrder::G2o));
        assert!((g.edges()[0].sigma2() - 0.2).abs() < 1e-15);
        // Forced order that makes the matrix singular is an error naming the line.
        let e = read_graph_from(
            w.as_bytes(),
            "w.txt",
            ReadOptions {
                order: InfoOrder::Toro,
                ..Default::default()
            },
        )
        .unwrap_err();
        assert_eq!(e.line, 1);
        assert!(e.to_string().starts_with("w.txt:1: edge 0→1"), "{e}");
    }

    #[test]
    fn ambiguous_lines_wait_for_the_deciding_line() {
        // First edge is positive definite in both orders; the second decides TORO.
        let text = "EDGE2 0 1 0 0 0 4 1 4 4 1 1\nVERTEX2 5 0 0 0\nEDGE2 1 2 0 0 0 1 0 1 1 0 0\n";
        let mut r = Reader::new(text.as_bytes(), "t", InfoOrder::Auto);
        let recs: Vec<Record> = r.by_ref().map(|x| x.unwrap()).collect();
        assert!(matches!(recs[0], Record::Edge { line: 1, .. }));
        assert!(matches!(recs[1], Record::Vertex { line: 2, .. }));
        let Record::Edge { edge, .. } = &recs[0] else {
            unreachable!()
        };
        // TORO: Ixx=4 Ixy=1 Iyy=4 Itt=4 Ixt=1 Iyt=1 → g2o [4,1,1,4,1,4].
        assert_eq!(edge.information().0, [4.0, 1.0, 1.0, 4.0, 1.0, 4.0]);
        assert_eq!(r.summary().order, Some(InfoOrder::Toro));
    }

    #[test]
    fn quirks_equiv_skipped_reversed_denormal() {
        let text = "# comment\n\nVERTEX2 0 0 0 0\nEQUIV 3 0\nLANDMARK 1 2\nLANDMARK 3\n\
                    EDGE_SE2 4 0 1 0 7.5 1 0 6.95335e-310 1 0 2\r\nVERTEX_SE3:QUAT 1 2\n";
        let (g, s) = read(text).unwrap();
        assert_eq!(s.equivalences, vec![(3, 0)]);
        assert_eq!(s.skipped.get("LANDMARK"), Some(&2));
        assert_eq!(s.skipped.get("VERTEX_SE3:QUAT"), Some(&1));
        let e = g.edges()[0];
        assert_eq!((e.from(), e.to(), e.delta()), (4, 0, 7.5));
        assert_eq!(e.information().0[2], 0.0);
        assert_eq!(g.node_count(), 2);
    }

    #[test]
    fn malformed_lines_name_file_and_line() {
        let cases = [
            ("VERTEX_SE2 0 0 0\n", "needs 4 fields"),
            ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0\n", "needs 11 fields"),
            ("EDGE_SE2 0 x 1 0 0 1 0 0 1 0 1\n", "not a valid node id"),
            ("EDGE_SE2 -1 2 1 0 0 1 0 0 1 0 1\n", "not a valid node id"),
            (
                "EDGE_SE2 0 1 1 0 abc 1 0 0 1 0 1\n",
                "(dtheta) is not a number",
            ),
            (
                "EDGE_SE2 0 1 1 0 nan 1 0 0 1 0 1\n",
                "measurement is not finite",
            ),
            (
                "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 inf\n",
                "information matrix is not finite",
            ),
            ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 -1\n", "positive definite"),
            ("EDGE_SE2 0 0 1 0 0 1 0 0 1 0 1\n", "self-loop"),
            ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 0 1 0 0\n", "defined twice"),
        ];
        for (text, want) in cases {
            let body = format!("VERTEX_SE2 9 0 0 0\n{text}");
            let e = read(&body).unwrap_err();
            assert!(e.line >= 2, "{e}");
            let msg = e.to_string();
            assert!(msg.starts_with("mem:"), "{msg}");
            assert!(msg.contains(want), "{msg} should contain {want}");
        }
        let e = read_graph_from(
            &b"VERTEX_SE2 0 0 0 0\n\xff\xfe\n"[..],
            "bin",
            Default::default(),
        )
        .unwrap_err();
        assert_eq!((e.line, e.kind), (2, LineError::NotUtf8));
    }

    #[test]
    fn require_known_nodes() {
        let text = "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n";
        let opts = ReadOptions {
            nodes: NodePolicy::RequireKnown,
            ..Default::default()
        };
        let e = read_graph_from(text.as_bytes(), "k", opts).unwrap_err();
        assert_eq!(e.line, 2);
        assert!(e.to_string().contains("unknown node 1"));
    }

    #[test]
    fn writer_round_trip_is_exact() {
        let text = "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 0.1 1e-300 4.79 44.72136 0.1 0 44.72136 0 3.3\n\
                    EDGE_SE2 1 0 0.3 0 -7 1 0 0 1 0 1\n";
        let (g, _) = read(text).unwrap();
        let mut out = Vec::new();
        write_g2o(&mut out, &g, None).unwrap();
        let (g2, s2) = read_graph_from(&out[..], "out", Default::default()).unwrap();
        assert_eq!(g.edges(), g2.edges());
        assert_eq!(s2.order, Some(InfoOrder::G2o));
    }
}
