//! A seeded Manhattan-world simulator with ground truth (the kind of world behind M3500).
//!
//! A robot lives on an integer grid of `world_size × world_size` cells. At each step it
//! may turn by ±π/2 (probability `turn_probability`, or when the next cell would leave the
//! world), then moves one unit forward. Pose `i+1` is reached from pose `i` by the true
//! relative pose `z = (R(θ_i)ᵀ (p_{i+1} − p_i), θ_{i+1} − θ_i)`. Each earlier pose (other than
//! the previous one) within `closure_radius` of the new pose closes a loop with probability
//! `loop_closure_probability`. Every measurement gets independent Gaussian noise:
//!
//! ```text
//! dx, dy += N(0, σ_xy²),     δ_e = wrap(θ_j − θ_i + ε_e),   ε_e ~ N(0, σ_θ²),
//! ```
//!
//! with `wrap` into (−π, π], as a robot reports angles. True headings are also in (−π, π].
//! The true wrap of each edge is therefore the integer of method [§1](crate::method#1-model),
//! `k_e = (δ_e − ε_e − (θ_j − θ_i)) / 2π`, recorded with the noise in [`GroundTruth`].
//!
//! **False loop closures** ([`inject_outliers`], method [§11](crate::method#11-false-loop-closures), the Vertigo protocol of
//! Sünderhauf & Protzel): K false edges are added to any graph, either between K random node
//! pairs (`random`), or in groups of 10 between two regions, edge k of a group joining the k-th
//! nodes after two random starts and all edges of a group sharing one measurement
//! (`clustered`; the last group is shorter when 10 does not divide K). A measurement is drawn
//! as `(x, y, θ)` with x, y uniform in [−10, 10) and θ uniform in (−π, π]; its information is
//! that of a genuine loop closure drawn uniformly (of the first edge when the graph has
//! none). Nodes are taken in ascending id order; paired ids differ by more than 1 (no false
//! edge looks like odometry) and every false edge is new. Each false edge goes right after
//! the edge that introduces its later node (first appearance in edge order), which is the
//! moment a robot could produce it: robot order.
//!
//! Determinism: the stream of numbers comes from ChaCha8 seeded with the seed (stream 0 for
//! worlds, stream 1 for outliers), uniform variates from the top 53 bits, normal variates by
//! Box–Muller with the pure-Rust `libm` functions, so the same seed gives bit-identical worlds
//! on every platform.

use rand_chacha::ChaCha8Rng;
use rand_chacha::rand_core::{Rng, SeedableRng};
use serde::Serialize;
use std::f64::consts::{FRAC_PI_2, PI, TAU};

use crate::graph::{Edge, GraphError, NodeId, NodePolicy, Pose2, PoseGraph};

/// Simulator parameters ([`SimConfig::new`] gives the defaults for a size and seed; a
/// deserialised one names every field).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, serde::Deserialize)]
pub struct SimConfig {
    /// Number of poses (nodes).
    pub poses: usize,
    /// Seed of the random stream.
    pub seed: u64,
    /// Probability that an eligible earlier pose gets a loop closure.
    pub loop_closure_probability: f64,
    /// Distance (grid units) within which earlier poses are eligible for a loop closure.
    pub closure_radius: f64,
    /// Probability of a random turn at each step.
    pub turn_probability: f64,
    /// Side of the square world, in grid cells.
    pub world_size: i64,
    /// Standard deviation of the angle noise (radians).
    pub sigma_theta: f64,
    /// Standard deviation of the translation noise (grid units).
    pub sigma_xy: f64,
}

impl SimConfig {
    /// Defaults resembling M3500 (σ_θ = 0.05 rad, σ_xy = 0.05; world side ≈ √poses / 2).
    pub fn new(poses: usize, seed: u64) -> Self {
        Self {
            poses,
            seed,
            loop_closure_probability: 0.06,
            closure_radius: 1.0,
            turn_probability: 0.3,
            world_size: ((poses as f64).sqrt() / 2.0).round().max(3.0) as i64,
            sigma_theta: 0.05,
            sigma_xy: 0.05,
        }
    }
}

/// The truth behind a simulated graph.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GroundTruth {
    /// True pose of every node (node id = index), heading in (−π, π].
    pub poses: Vec<Pose2>,
    /// True wrap k_e of every edge (edge order of the graph).
    pub wraps: Vec<i64>,
    /// Noise added to every edge's measurement (dx, dy, ε).
    pub noise: Vec<Pose2>,
}

/// A simulated world: the measured graph (initial poses composed from odometry) and its truth.
#[derive(Clone, Debug)]
pub struct SimWorld {
    /// Configuration used.
    pub config: SimConfig,
    /// The measured pose graph, edges in time order (odometry step, then its loop closures).
    pub graph: PoseGraph,
    /// Ground truth.
    pub truth: GroundTruth,
}

/// Why a configuration cannot be simulated.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SimError {
    /// A parameter out of range.
    #[error("invalid simulator parameter {name} = {value}: {why}")]
    Parameter {
        /// Parameter name.
        name: &'static str,
        /// Its value.
        value: f64,
        /// The allowed range.
        why: &'static str,
    },
    /// A generated edge failed validation (cannot happen with valid parameters).
    #[error(transparent)]
    Graph(#[from] GraphError),
}

/// Wrap an angle into (−π, π] ([`crate::graph::wrap_angle`], re-exported).
pub use crate::graph::wrap_angle;

/// The simulator's random draws (also the crate's tests' deterministic noise).
pub(crate) struct Noise(ChaCha8Rng);

impl Noise {
    /// Draws from `seed`.
    pub(crate) fn seeded(seed: u64) -> Self {
        Self(ChaCha8Rng::seed_from_u64(seed))
    }
    fn uniform(&mut self) -> f64 {
        (self.0.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
    /// A standard normal draw.
    pub(crate) fn normal(&mut self) -> f64 {
        // Box–Muller; 1 − u is in (0, 1], so the logarithm is finite.
        let u = 1.0 - self.uniform();
        let v = self.uniform();
        libm::sqrt(-2.0 * libm::log(u)) * libm::cos(TAU * v)
    }
}

fn check(name: &'static str, value: f64, ok: bool, why: &'static str) -> Result<(), SimError> {
    if ok {
        Ok(())
    } else {
        Err(SimError::Parameter { name, value, why })
    }
}

/// Simulate a world.
pub fn simulate(config: &SimConfig) -> Result<SimWorld, SimError> {
    let c = config;
    let p = c.loop_closure_probability;
    check("poses", c.poses as f64, c.poses >= 1, "at least 1")?;
    check(
        "loop_closure_probability",
        p,
        (0.0..=1.0).contains(&p),
        "in [0, 1]",
    )?;
    let t = c.turn_probability;
    check("turn_probability", t, (0.0..=1.0).contains(&t), "in [0, 1]")?;
    let r = c.closure_radius;
    check(
        "closure_radius",
        r,
        r.is_finite() && r >= 0.0,
        "finite, ≥ 0",
    )?;
    check(
        "world_size",
        c.world_size as f64,
        (2..=1 << 20).contains(&c.world_size),
        "2..2^20",
    )?;
    for (name, s) in [("sigma_theta", c.sigma_theta), ("sigma_xy", c.sigma_xy)] {
        check(name, s, s.is_finite() && s > 0.0, "finite, > 0")?;
    }

    let mut rng = Noise::seeded(c.seed);
    let size = c.world_size;
    // Cells of the grid → poses that visited them (for loop-closure candidates).
    let mut visits: Vec<Vec<usize>> = vec![Vec::new(); (size * size) as usize];
    let reach = c.closure_radius.floor() as i64;
    let mut cells: Vec<(i64, i64)> = Vec::with_capacity(c.poses);
    let mut dirs: Vec<i64> = Vec::with_capacity(c.poses); // heading in quarter turns, mod 4
    let mut graph = PoseGraph::new();
    let mut truth = GroundTruth {
        poses: Vec::new(),
        wraps: Vec::new(),
        noise: Vec::new(),
    };
    let mut estimate = Pose2::default(); // odometry-composed initial pose

    let start = (size / 2, size / 2);
    cells.push(start);
    dirs.push(0);
    visits[(start.1 * size + start.0) as usize].push(0);
    truth.poses.push(true_pose(start, 0));
    graph.add_node(0, Some(estimate))?;

    for i in 1..c.poses {
        let (cell, dir) = (cells[i - 1], dirs[i - 1]);
        let mut new_dir = dir;
        if rng.uniform() < c.turn_probability {
            new_dir += if rng.uniform() < 0.5 { 1 } else { 3 };
        }
        // Turn until the next cell is inside the world (left first, then right, then back).
        let inside = |d: i64| {
            let (x, y) = step(cell, d);
            (0..size).contains(&x) && (0..size).contains(&y)
        };
        if !inside(new_dir) {
            new_dir = [dir + 1, dir + 3, dir + 2]
                .into_iter()
                .find(|&d| inside(d))
                .unwrap_or(dir);
        }
        let new_dir = new_dir.rem_euclid(4);
        let next = step(cell, new_dir);
        cells.push(next);
        dirs.push(new_dir);
        truth.poses.push(true_pose(next, new_dir));

        let odo = add_measurement(&mut graph, &mut truth, &mut rng, c, i - 1, i)?;
        estimate = compose(estimate, odo);
        graph.add_node(i as u64, Some(estimate))?;

        // Loop closures to earlier poses near the new one, in a fixed scan order.
        let mut candidates = Vec::new();
        for dy in -reach..=reach {
            for dx in -reach..=reach {
                let (x, y) = (next.0 + dx, next.1 + dy);
                if !(0..size).contains(&x) || !(0..size).contains(&y) {
                    continue;
                }
                if ((dx * dx + dy * dy) as f64).sqrt() > c.closure_radius {
                    continue;
                }
                candidates.extend(visits[(y * size + x) as usize].iter().copied());
            }
        }
        candidates.sort_unstable();
        for j in candidates {
            if j + 1 < i && rng.uniform() < p {
                add_measurement(&mut graph, &mut truth, &mut rng, c, j, i)?;
            }
        }
        visits[(next.1 * size + next.0) as usize].push(i);
    }
    Ok(SimWorld {
        config: *c,
        graph,
        truth,
    })
}

fn step((x, y): (i64, i64), dir: i64) -> (i64, i64) {
    match dir.rem_euclid(4) {
        0 => (x + 1, y),
        1 => (x, y + 1),
        2 => (x - 1, y),
        _ => (x, y - 1),
    }
}

fn true_pose((x, y): (i64, i64), dir: i64) -> Pose2 {
    Pose2::new(x as f64, y as f64, wrap_angle(dir as f64 * FRAC_PI_2))
}

/// `a ⊕ z` with the heading wrapped (the simulated robot's pose).
pub fn compose(a: Pose2, z: Pose2) -> Pose2 {
    let p = a.compose(z);
    Pose2::new(p.x, p.y, wrap_angle(p.theta))
}

/// Add a noisy measurement `from → to` with its ground truth; returns the measurement.
fn add_measurement(
    graph: &mut PoseGraph,
    truth: &mut GroundTruth,
    rng: &mut Noise,
    c: &SimConfig,
    from: usize,
    to: usize,
) -> Result<Pose2, SimError> {
    let z = truth.poses[from].between(truth.poses[to]);
    let noise = Pose2::new(
        c.sigma_xy * rng.normal(),
        c.sigma_xy * rng.normal(),
        c.sigma_theta * rng.normal(),
    );
    let delta = wrap_angle(z.theta + noise.theta);
    let wrap = ((delta - noise.theta - z.theta) / TAU).round() as i64;
    let m = Pose2::new(z.x + noise.x, z.y + noise.y, delta);
    let edge = Edge::with_sigmas(from as u64, to as u64, m, c.sigma_xy, c.sigma_theta)?;
    graph.add_edge(edge, NodePolicy::CreateUnknown)?;
    truth.wraps.push(wrap);
    truth.noise.push(noise);
    Ok(m)
}

/// How false loop closures are placed (module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum OutlierKind {
    /// Independent random node pairs.
    Random,
    /// Groups of 10 consecutive edges between two regions, sharing one measurement.
    Clustered,
}

/// Nodes per group of clustered false edges.
pub const CLUSTER_SIZE: usize = 10;

/// The outlier benchmark's settings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct OutlierConfig {
    /// Number of false edges K.
    pub count: usize,
    /// Random pairs or clustered groups.
    pub kind: OutlierKind,
    /// Seed of the random stream.
    pub seed: u64,
}

/// One inserted false edge.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct FalseEdge {
    /// Its index in the corrupted graph's edge order (0-based).
    pub edge: usize,
    /// Source node id.
    pub from: NodeId,
    /// Target node id.
    pub to: NodeId,
    /// Group (clustered) or edge (random) number, 0-based.
    pub group: usize,
}

/// A graph with false loop closures inserted.
#[derive(Clone, Debug)]
pub struct Corrupted {
    /// The corrupted graph (same nodes, genuine edges in their order, false edges inserted).
    pub graph: PoseGraph,
    /// The false edges, ascending by index.
    pub false_edges: Vec<FalseEdge>,
    /// For every edge of `graph`, its index in the input graph (`None` for a false edge).
    pub source_edge: Vec<Option<usize>>,
}

impl Corrupted {
    /// Whether edge e of the corrupted graph is false.
    pub fn is_false(&self, e: usize) -> bool {
        self.source_edge.get(e).is_some_and(Option::is_none)
    }
}

/// Insert false loop closures into a graph (module docs).
pub fn inject_outliers(graph: &PoseGraph, config: &OutlierConfig) -> Result<Corrupted, SimError> {
    let k = config.count;
    let mut ids: Vec<NodeId> = graph.nodes().iter().map(|n| n.id).collect();
    ids.sort_unstable();
    let group = match config.kind {
        OutlierKind::Random => 1,
        OutlierKind::Clustered => CLUSTER_SIZE,
    };
    // Two starts whose groups are disjoint and not adjacent: 2·group + 2 nodes at least.
    let needed = 2 * group + 2;
    if k > 0 && ids.len() < needed {
        return Err(SimError::Parameter {
            name: "outliers",
            value: k as f64,
            why: "the graph needs at least 4 nodes (random) or 22 nodes (clustered)",
        });
    }
    let mut rng = Noise::seeded(config.seed);
    rng.0.set_stream(1);
    let genuine: Vec<&Edge> = graph.edges().iter().filter(|e| !e.is_odometric()).collect();
    let mut existing: std::collections::HashSet<(NodeId, NodeId)> = graph
        .edges()
        .iter()
        .map(|e| (e.from().min(e.to()), e.from().max(e.to())))
        .collect();
    let index = |rng: &mut Noise, n: usize| ((rng.uniform() * n as f64) as usize).min(n - 1);
    let mut made: Vec<(usize, Edge)> = Vec::with_capacity(k);
    let mut g = 0;
    let mut attempts = 0usize;
    while made.len() < k {
        attempts += 1;
        if attempts > 1000 * (k + 10) {
            return Err(SimError::Parameter {
                name: "outliers",
                value: k as f64,
                why: "too many for this graph: no more new node pairs found",
            });
        }
        let len = group.min(k - made.len());
        let last = ids.len() - len;
        let (a, b) = (index(&mut rng, last + 1), index(&mut rng, last + 1));
        // Disjoint, non-adjacent ranges a..a+len and b..b+len.
        if a.abs_diff(b) <= len {
            continue;
        }
        let pairs: Vec<(NodeId, NodeId)> = (0..len).map(|i| (ids[a + i], ids[b + i])).collect();
        let key = |(p, q): (NodeId, NodeId)| (p.min(q), p.max(q));
        if pairs
            .iter()
            .any(|&pq| pq.0.abs_diff(pq.1) <= 1 || existing.contains(&key(pq)))
        {
            continue;
        }
        let z = Pose2::new(
            20.0 * rng.uniform() - 10.0,
            20.0 * rng.uniform() - 10.0,
            PI - TAU * rng.uniform(),
        );
        let info = if genuine.is_empty() {
            graph.edges().first().map(|e| e.information())
        } else {
            Some(genuine[index(&mut rng, genuine.len())].information())
        };
        let Some(info) = info else {
            return Err(SimError::Parameter {
                name: "outliers",
                value: k as f64,
                why: "the graph has no edge to take the information from",
            });
        };
        for pq in pairs {
            existing.insert(key(pq));
            made.push((g, Edge::new(pq.0, pq.1, z, info)?));
        }
        g += 1;
    }
    // Robot order: after the edge that introduces the later of the two nodes.
    let mut first_seen: std::collections::HashMap<NodeId, usize> = Default::default();
    for (e, edge) in graph.edges().iter().enumerate() {
        first_seen.entry(edge.from()).or_insert(e);
        first_seen.entry(edge.to()).or_insert(e);
    }
    let slot = |id: NodeId| first_seen.get(&id).copied().unwrap_or(0);
    let mut after: Vec<(usize, usize, Edge)> = made
        .into_iter()
        .map(|(grp, e)| (slot(e.from()).max(slot(e.to())), grp, e))
        .collect();
    after.sort_by_key(|x| x.0); // stable: generation order within a slot
    let mut out = PoseGraph::new();
    for n in graph.nodes() {
        out.add_node(n.id, n.initial)?;
    }
    let mut false_edges = Vec::with_capacity(k);
    let mut source_edge = Vec::with_capacity(graph.edge_count() + k);
    let mut next = after.iter().peekable();
    for (e, edge) in graph.edges().iter().enumerate() {
        out.add_edge(*edge, NodePolicy::RequireKnown)?;
        source_edge.push(Some(e));
        while let Some(&&(_, grp, f)) = next.peek().filter(|x| x.0 == e) {
            let idx = out.add_edge(f, NodePolicy::RequireKnown)?;
            false_edges.push(FalseEdge {
                edge: idx,
                from: f.from(),
                to: f.to(),
                group: grp,
            });
            source_edge.push(None);
            next.next();
        }
    }
    Ok(Corrupted {
        graph: out,
        false_edges,
        source_edge,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrap_angle_range() {
        for a in [-10.0, -PI, -3.0, 0.0, PI, 3.2, 7.0, 100.0] {
            let w = wrap_angle(a);
            assert!(w > -PI && w <= PI, "{a} → {w}");
            assert!((((a - w) / TAU) - ((a - w) / TAU).round()).abs() < 1e-12);
        }
        assert_eq!(wrap_angle(-PI), PI);
    }

    #[test]
    fn truth_matches_noiseless_measurements() {
        let w = simulate(&SimConfig::new(400, 7)).unwrap();
        let g = &w.graph;
        assert_eq!(g.node_count(), 400);
        assert!(
            g.edge_count() > 450,
            "too few loop closures: {}",
            g.edge_count()
        );
        assert!(
            w.truth.wraps.iter().any(|&k| k != 0),
            "no edge wraps: weak test world"
        );
        for (k, e) in g.edges().iter().enumerate() {
            let (i, j) = (e.from() as usize, e.to() as usize);
            let (ti, tj) = (w.truth.poses[i], w.truth.poses[j]);
            let n = w.truth.noise[k];
            // Angle: θ_j − θ_i = δ − ε − 2πk exactly (to rounding).
            let lhs = tj.theta - ti.theta;
            let rhs = e.delta() - n.theta - TAU * w.truth.wraps[k] as f64;
            assert!((lhs - rhs).abs() < 1e-12, "edge {k}: {lhs} vs {rhs}");
            // Translation: measurement − noise is the true relative translation.
            let z = ti.between(tj);
            let m = e.measurement();
            assert!((m.x - n.x - z.x).abs() < 1e-12 && (m.y - n.y - z.y).abs() < 1e-12);
            if e.is_odometric() {
                assert!(
                    (z.x.hypot(z.y) - 1.0).abs() < 1e-12,
                    "odometry is a unit step"
                );
            }
        }
    }

    #[test]
    fn same_seed_same_world_other_seed_other_world() {
        let a = simulate(&SimConfig::new(300, 42)).unwrap();
        let b = simulate(&SimConfig::new(300, 42)).unwrap();
        let c = simulate(&SimConfig::new(300, 43)).unwrap();
        assert_eq!(a.graph.edges(), b.graph.edges());
        assert_eq!(a.truth, b.truth);
        assert_ne!(a.graph.edges(), c.graph.edges());
    }

    #[test]
    fn rejects_bad_parameters() {
        let mut c = SimConfig::new(10, 1);
        c.sigma_theta = 0.0;
        assert!(matches!(
            simulate(&c),
            Err(SimError::Parameter {
                name: "sigma_theta",
                ..
            })
        ));
        let mut c = SimConfig::new(10, 1);
        c.loop_closure_probability = 1.5;
        assert!(simulate(&c).is_err());
    }
}

#[cfg(test)]
mod outlier_tests {
    use super::*;

    #[test]
    fn random_and_clustered_outliers_follow_the_protocol() {
        let w = simulate(&SimConfig::new(300, 4)).unwrap();
        let g = &w.graph;
        for kind in [OutlierKind::Random, OutlierKind::Clustered] {
            let cfg = OutlierConfig {
                count: 25,
                kind,
                seed: 9,
            };
            let c = inject_outliers(g, &cfg).unwrap();
            assert_eq!(c.graph.edge_count(), g.edge_count() + 25);
            assert_eq!(c.false_edges.len(), 25);
            assert_eq!(c.graph.node_count(), g.node_count());
            // Genuine edges keep their order; false edges are marked.
            let genuine: Vec<Edge> = (0..c.graph.edge_count())
                .filter(|&e| !c.is_false(e))
                .map(|e| c.graph.edges()[e])
                .collect();
            assert_eq!(genuine.as_slice(), g.edges());
            let mut first_seen = std::collections::HashMap::new();
            for (e, edge) in c.graph.edges().iter().enumerate() {
                if !c.is_false(e) {
                    first_seen.entry(edge.from()).or_insert(e);
                    first_seen.entry(edge.to()).or_insert(e);
                }
            }
            for f in &c.false_edges {
                let e = c.graph.edges()[f.edge];
                assert!(!e.is_odometric());
                let z = e.measurement();
                assert!(z.x.abs() <= 10.0 && z.y.abs() <= 10.0);
                assert!(z.theta > -PI && z.theta <= PI);
                // Right after the genuine edge introducing its later node (or another false
                // edge inserted there).
                let later = first_seen[&e.from()].max(first_seen[&e.to()]);
                assert!(f.edge > later);
                assert!((later + 1..f.edge).all(|x| c.is_false(x)));
            }
            let groups = c.false_edges.iter().map(|f| f.group).max().unwrap() + 1;
            match kind {
                OutlierKind::Random => assert_eq!(groups, 25),
                OutlierKind::Clustered => {
                    assert_eq!(groups, 3);
                    // One measurement per group; consecutive node pairs.
                    for grp in 0..groups {
                        let mut es: Vec<Edge> = c
                            .false_edges
                            .iter()
                            .filter(|f| f.group == grp)
                            .map(|f| c.graph.edges()[f.edge])
                            .collect();
                        es.sort_by_key(|e| e.from());
                        assert!(
                            es.windows(2)
                                .all(|p| p[0].measurement() == p[1].measurement()
                                    && p[1].from() == p[0].from() + 1
                                    && p[1].to() == p[0].to() + 1)
                        );
                    }
                }
            }
            // Deterministic.
            let again = inject_outliers(g, &cfg).unwrap();
            assert_eq!(again.graph.edges(), c.graph.edges());
        }
        let tiny = simulate(&SimConfig::new(3, 1)).unwrap();
        let cfg = OutlierConfig {
            count: 1,
            kind: OutlierKind::Random,
            seed: 1,
        };
        assert!(matches!(
            inject_outliers(&tiny.graph, &cfg),
            Err(SimError::Parameter {
                name: "outliers",
                ..
            })
        ));
    }
}
