//! The Foxglove messages of a log (`foxglove.Log`, `foxglove.SceneUpdate`,
//! `foxglove.PosesInFrame`), serialised straight from borrowed data: a snapshot of a large
//! graph writes its lines and poses without building an intermediate JSON tree.
//!
//! The schemas are the official JSON Schemas of foxglove/schemas, embedded verbatim. These
//! channels are for viewing: coordinates are rounded to 10⁻³ (a millimetre in metre units) and
//! quaternion components to 10⁻⁶, in single precision — short numbers make a snapshot of a
//! large graph half as long to write and compress; the exact orientations are on
//! `/so2lin/estimate`.

use serde::Serialize;

/// The official `foxglove.Log` JSON Schema (foxglove/schemas, `schemas/jsonschema/Log.json`).
pub(super) const LOG_SCHEMA: &str = include_str!("foxglove_Log.json");
/// The official `foxglove.SceneUpdate` JSON Schema (foxglove/schemas).
pub(super) const SCENE_SCHEMA: &str = include_str!("foxglove_SceneUpdate.json");
/// The official `foxglove.PosesInFrame` JSON Schema (foxglove/schemas).
pub(super) const POSES_SCHEMA: &str = include_str!("foxglove_PosesInFrame.json");
/// `foxglove.PoseInFrame` (the official JSON Schema).
pub(super) const POSE_SCHEMA: &str = include_str!("foxglove_PoseInFrame.json");

/// `foxglove.Time` (log time is the step index: `sec` = step).
#[derive(Clone, Copy, Serialize)]
pub(super) struct Stamp {
    sec: u64,
    nsec: u32,
}

impl Stamp {
    /// A time in nanoseconds since the Unix epoch (the log time of the message).
    pub(super) fn at(ns: u64) -> Self {
        Self {
            sec: ns / 1_000_000_000,
            nsec: (ns % 1_000_000_000) as u32,
        }
    }
}

/// `foxglove.Log`.
#[derive(Serialize)]
pub(super) struct LogLine<'a> {
    pub timestamp: Stamp,
    pub level: u8,
    pub message: &'a str,
    pub name: &'a str,
    pub file: &'a str,
    pub line: u32,
}

#[derive(Clone, Copy, Serialize)]
struct Point {
    x: f32,
    y: f32,
    z: f32,
}

/// `v` rounded to a multiple of `1/scale`, in single precision.
fn rounded(v: f64, scale: f64) -> f32 {
    ((v * scale).round() / scale) as f32
}

impl Point {
    fn planar((x, y): (f64, f64)) -> Self {
        Self {
            x: rounded(x, 1e3),
            y: rounded(y, 1e3),
            z: 0.0,
        }
    }
}

#[derive(Clone, Copy, Serialize)]
struct Quaternion {
    x: f32,
    y: f32,
    z: f32,
    w: f32,
}

impl Quaternion {
    /// Rotation by `theta` about z.
    fn yaw(theta: f64) -> Self {
        let (s, c) = (0.5 * theta).sin_cos();
        Self {
            x: 0.0,
            y: 0.0,
            z: rounded(s, 1e6),
            w: rounded(c, 1e6),
        }
    }
}

/// A planar pose as `/pose` and `/poses` show it: the position's x and y, and the yaw
/// quaternion's z and w, each rounded and in single precision as written.
pub(super) fn displayed((x, y): (f64, f64), theta: f64) -> [f32; 4] {
    let (p, q) = (Point::planar((x, y)), Quaternion::yaw(theta));
    [p.x, p.y, q.z, q.w]
}

#[derive(Clone, Copy, Serialize)]
struct Pose {
    position: Point,
    orientation: Quaternion,
}

#[derive(Clone, Copy, Serialize)]
struct Color {
    r: f64,
    g: f64,
    b: f64,
    a: f64,
}

/// An empty list of any of the schema's object types.
const NONE: [(); 0] = [];

/// Segments as endpoint index pairs, with the positions they index.
type Segments<'a> = (&'a [(usize, usize)], &'a [(f64, f64)]);

/// `foxglove.LinePrimitive` of type LINE_LIST (2): consecutive point pairs are segments.
#[derive(Serialize)]
struct LineList<'a> {
    #[serde(rename = "type")]
    kind: u8,
    pose: Pose,
    thickness: f64,
    scale_invariant: bool,
    #[serde(serialize_with = "segments")]
    points: Segments<'a>,
    color: Color,
    colors: [(); 0],
    indices: [(); 0],
}

/// Serialise segments `(a, b)` as the points `pos[a], pos[b], …`.
fn segments<S: serde::Serializer>((ends, pos): &Segments<'_>, s: S) -> Result<S::Ok, S::Error> {
    s.collect_seq(
        ends.iter()
            .flat_map(|&(a, b)| [Point::planar(pos[a]), Point::planar(pos[b])]),
    )
}

#[derive(Serialize)]
struct SceneEntity<'a> {
    timestamp: Stamp,
    frame_id: &'a str,
    id: &'a str,
    lifetime: Stamp,
    frame_locked: bool,
    metadata: [(); 0],
    arrows: [(); 0],
    cubes: [(); 0],
    spheres: [(); 0],
    cylinders: [(); 0],
    lines: Vec<LineList<'a>>,
    triangles: [(); 0],
    texts: [(); 0],
    models: [(); 0],
}

/// `foxglove.SceneUpdate`.
#[derive(Serialize)]
pub(super) struct SceneUpdate<'a> {
    deletions: [(); 0],
    entities: [SceneEntity<'a>; 1],
}

/// Which line list an edge is drawn in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Style {
    /// Odometry (grey).
    Odometry = 0,
    /// Loop closure (blue).
    LoopClosure = 1,
    /// Chord of an ambiguous or inconsistent cycle (red, thick).
    Flagged = 2,
    /// Quarantined loop closure (orange, thin, half transparent): not in the estimate.
    Rejected = 3,
}

impl<'a> SceneUpdate<'a> {
    /// The graph in frame `map`: `segments[s]` holds the endpoint pairs drawn in style `s`.
    pub(super) fn graph(
        time_ns: u64,
        segments: &'a [Vec<(usize, usize)>; 4],
        pos: &'a [(f64, f64)],
    ) -> Self {
        const COLORS: [(f64, f64, f64, f64); 4] = [
            (0.6, 0.6, 0.6, 1.0),
            (0.2, 0.4, 1.0, 0.8),
            (1.0, 0.1, 0.1, 1.0),
            (1.0, 0.6, 0.0, 0.5),
        ];
        const THICKNESS: [f64; 4] = [0.05, 0.03, 0.12, 0.02];
        let lines = segments
            .iter()
            .enumerate()
            .map(|(k, ends)| {
                let (r, g, b, a) = COLORS[k];
                LineList {
                    kind: 2,
                    pose: Pose {
                        position: Point::planar((0.0, 0.0)),
                        orientation: Quaternion::yaw(0.0),
                    },
                    thickness: THICKNESS[k],
                    scale_invariant: false,
                    points: (ends, pos),
                    color: Color { r, g, b, a },
                    colors: NONE,
                    indices: NONE,
                }
            })
            .collect();
        Self {
            deletions: NONE,
            entities: [SceneEntity {
                timestamp: Stamp::at(time_ns),
                frame_id: "map",
                id: "so2lin-graph",
                lifetime: Stamp::at(0),
                frame_locked: false,
                metadata: NONE,
                arrows: NONE,
                cubes: NONE,
                spheres: NONE,
                cylinders: NONE,
                lines,
                triangles: NONE,
                texts: NONE,
                models: NONE,
            }],
        }
    }
}

/// `foxglove.PosesInFrame` in frame `map`.
#[derive(Serialize)]
pub(super) struct PosesInFrame<'a> {
    timestamp: Stamp,
    frame_id: &'a str,
    #[serde(serialize_with = "poses")]
    poses: (&'a [(f64, f64)], &'a [f64]),
}

impl<'a> PosesInFrame<'a> {
    /// Positions with headings.
    pub(super) fn new(time_ns: u64, pos: &'a [(f64, f64)], theta: &'a [f64]) -> Self {
        Self {
            timestamp: Stamp::at(time_ns),
            frame_id: "map",
            poses: (pos, theta),
        }
    }
}

/// `foxglove.PoseInFrame` in frame `map`: one pose (the newest node's, every step).
#[derive(Serialize)]
pub(super) struct PoseInFrame<'a> {
    timestamp: Stamp,
    frame_id: &'a str,
    pose: Pose,
}

impl PoseInFrame<'_> {
    /// A planar pose at a time.
    pub(super) fn new(time_ns: u64, x: f64, y: f64, theta: f64) -> Self {
        Self {
            timestamp: Stamp::at(time_ns),
            frame_id: "map",
            pose: Pose {
                position: Point::planar((x, y)),
                orientation: Quaternion::yaw(theta),
            },
        }
    }
}

fn poses<S: serde::Serializer>(
    (pos, theta): &(&[(f64, f64)], &[f64]),
    s: S,
) -> Result<S::Ok, S::Error> {
    s.collect_seq(pos.iter().zip(*theta).map(|(&p, &t)| Pose {
        position: Point::planar(p),
        orientation: Quaternion::yaw(t),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scene_lines_hold_both_endpoints_of_every_segment() {
        let pos = [(0.0, 0.0), (1.0, 0.0), (1.0, 2.0)];
        let segs = [vec![(0, 1), (1, 2)], vec![(2, 0)], vec![], vec![(0, 2)]];
        let v = serde_json::to_value(SceneUpdate::graph(7_250_000_000, &segs, &pos))
            .expect("serialisable");
        let lines = &v["entities"][0]["lines"];
        assert_eq!(lines[0]["points"].as_array().map(Vec::len), Some(4));
        assert_eq!(lines[1]["points"][0]["x"], 1.0);
        assert_eq!(lines[1]["points"][0]["y"], 2.0);
        assert_eq!(lines[2]["points"].as_array().map(Vec::len), Some(0));
        // Quarantined loop closures: their own list, thinner than the others.
        assert_eq!(lines[3]["points"].as_array().map(Vec::len), Some(2));
        assert!(lines[3]["thickness"].as_f64() < lines[1]["thickness"].as_f64());
        assert_eq!(v["entities"][0]["timestamp"]["sec"], 7);
        assert_eq!(v["entities"][0]["timestamp"]["nsec"], 250_000_000);
        assert_eq!(v["entities"][0]["arrows"], serde_json::json!([]));
    }

    #[test]
    fn poses_carry_yaw_quaternions() {
        let v = serde_json::to_value(PosesInFrame::new(1, &[(1.0, 2.0)], &[std::f64::consts::PI]))
            .expect("serialisable");
        let q = &v["poses"][0]["orientation"];
        assert!((q["z"].as_f64().unwrap_or(0.0) - 1.0).abs() < 1e-12);
        assert_eq!(v["frame_id"], "map");
    }
}
