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
//! The true wrap of each edge is therefore the integer of METHOD.md §1,
//! `k_e = (δ_e − ε_e − (θ_j − θ_i)) / 2π`, recorded with the noise in [`GroundTruth`].
//!
//! Determinism: the stream of numbers comes from ChaCha8 seeded with the seed, uniform
//! variates from the top 53 bits, normal variates by Box–Muller with the pure-Rust `libm`
//! functions, so the same seed gives bit-identical worlds on every platform.

use rand_chacha::ChaCha8Rng;
use rand_chacha::rand_core::{Rng, SeedableRng};
use serde::Serialize;
use std::f64::consts::{FRAC_PI_2, PI, TAU};

use crate::graph::{Edge, GraphError, NodePolicy, Pose2, PoseGraph};

/// Simulator parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
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

/// Wrap an angle into (−π, π].
pub fn wrap_angle(a: f64) -> f64 {
    let w = a - TAU * libm::floor((a + PI) / TAU);
    if w <= -PI { w + TAU } else { w }
}

struct Noise(ChaCha8Rng);

impl Noise {
    fn uniform(&mut self) -> f64 {
        (self.0.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
    fn normal(&mut self) -> f64 {
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

    let mut rng = Noise(ChaCha8Rng::seed_from_u64(c.seed));
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
