//! The estimate a robot reads: orientations and positions kept factored as edges arrive
//! ([`Laplacian`]), brought up to date when they are read.
//!
//! Each step hands its changes to the estimate as operations — new nodes, the new edge's
//! orientation row `√w_e (θ_b − θ_a) = √w_e (δ_e − 2πk_e)`, the wraps that moved (right-hand
//! sides only), the new edge's position row `p_b − p_a = R(θ_a) t_e`, the end of the step —
//! and the factors apply them at the next read, in the same order. A robot that reads after
//! every step pays for them inside that step; a caller that never reads (a batch replay, the
//! screening alone) pays nothing. The operations carry every value that could change later
//! (the wraps of the moment), and the factors' renewals are scheduled by the steps applied, so
//! the answer is the same bits whenever it is read.
//!
//! **Positions** (the linear estimate's model: headings treated as exact): the position row of
//! an edge uses the tail's heading as estimated right after the edge's step — read at the newer
//! end of the edge, O(1) in the factor, and carried across the edge by its unwrapped
//! measurement — and the isotropic part of the translation information,
//! `w = (Ω_t,xx + Ω_t,yy)/2` (exact when it is isotropic). So the fast answers
//! ([`Estimate::pose`]) lag the heading corrections that later loop closures make to old nodes,
//! like iSAM2 with a relinearisation threshold; every position row is re-linearised at the
//! current headings whenever a renewal of the position factor's order starts (the renewed
//! factor takes them; a step-scheduled event, so the answers do not depend on what was read
//! when). [`Estimate::poses`] is the exact answer on
//! demand, without changing the factor: every position row at the current headings (one forward
//! and one back-substitution; a 2×2-block system solved from scratch when the translation
//! information is not isotropic).

use super::laplacian::Laplacian;
use crate::estimate::EstimateError;
use crate::graph::{Pose2, PoseGraph};

/// One change to the factored estimate.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Op {
    /// A new node.
    Node,
    /// The orientation row of edge `e` from a to b, with its unwrapped measurement.
    Edge { e: u32, a: u32, b: u32, y: f64 },
    /// Edge `e`'s unwrapped measurement is now `y` (its wrap moved).
    Wrap { e: u32, y: f64 },
    /// The position row of edge `e` (from a to b; `y` its unwrapped measurement then).
    Position { e: u32, a: u32, b: u32, y: f64 },
    /// End of a step.
    Step,
}

/// The factored orientation and position systems with their pending operations.
#[derive(Default)]
pub(crate) struct Estimate {
    heads: Laplacian<1>,
    positions: Laplacian<2>,
    /// Some edge's translation information is not isotropic.
    anisotropic: bool,
    pending: Vec<Op>,
}

/// `R(θ) t`: a relative translation in the world frame of a tail with heading θ.
pub(crate) fn rotate(theta: f64, z: Pose2) -> [f64; 2] {
    let (s, c) = theta.sin_cos();
    [c * z.x - s * z.y, s * z.x + c * z.y]
}

impl Estimate {
    /// Queue an operation.
    pub fn push(&mut self, op: Op) {
        self.pending.push(op);
    }

    /// Renewals completed and steps that waited for a renewal's builder.
    pub fn renewals(&self) -> (usize, usize) {
        (
            self.heads.renewals + self.positions.renewals,
            self.heads.waits + self.positions.waits,
        )
    }

    /// Apply the pending operations (in order).
    pub fn sync(&mut self, graph: &PoseGraph) {
        let pending = std::mem::take(&mut self.pending);
        for &op in &pending {
            match op {
                Op::Node => {
                    self.heads.add_node();
                    self.positions.add_node();
                }
                Op::Edge { e, a, b, y } => {
                    let w = graph.edges()[e as usize].sigma2().recip();
                    self.heads.add_edge(a as usize, b as usize, w, [y]);
                }
                Op::Wrap { e, y } => self.heads.set_y(e as usize, [y]),
                Op::Position { e, a, b, y } => {
                    let edge = &graph.edges()[e as usize];
                    let o = edge.information().translation_information();
                    self.anisotropic |= o[0][1] != 0.0 || o[0][0] != o[1][1];
                    let theta_a = if a > b {
                        self.heads.value(a as usize)[0]
                    } else {
                        self.heads.value(b as usize)[0] - y
                    };
                    let w = 0.5 * (o[0][0] + o[1][1]);
                    let t = rotate(theta_a, edge.measurement());
                    self.positions.add_edge(a as usize, b as usize, w, t);
                }
                Op::Step => {
                    // One builder at a time (heads first).
                    let free = !self.positions.renewing();
                    self.heads.after_step(free, || None);
                    // A renewal of the position factor takes every position row at the
                    // current headings.
                    let free = !self.heads.renewing();
                    let (heads, edges) = (&mut self.heads, self.positions.edge_count());
                    self.positions.after_step(free, || {
                        // The headings here (one back-substitution); the rows on the builder.
                        let theta = heads.all(0);
                        let tails: Vec<(usize, Pose2)> = graph
                            .endpoints()
                            .iter()
                            .zip(graph.edges())
                            .take(edges)
                            .map(|(&(a, _), e)| (a, e.measurement()))
                            .collect();
                        Some(Box::new(move || {
                            tails.iter().map(|&(a, z)| rotate(theta[a], z)).collect()
                        }))
                    });
                }
            }
        }
        self.pending = pending;
        self.pending.clear();
    }

    /// Orientation of node v (O(1) for the newest).
    pub fn orientation(&mut self, graph: &PoseGraph, v: usize) -> f64 {
        self.sync(graph);
        self.heads.value(v)[0]
    }

    /// Every orientation: one back-substitution.
    pub fn orientations(&mut self, graph: &PoseGraph) -> Vec<f64> {
        self.sync(graph);
        self.heads.all(0)
    }

    /// The fast pose of node v (see the module docs; O(1) for the newest).
    pub fn pose(&mut self, graph: &PoseGraph, v: usize) -> Pose2 {
        self.sync(graph);
        let [x, y] = self.positions.value(v);
        Pose2::new(x, y, self.heads.value(v)[0])
    }

    /// Every pose, exact (see the module docs).
    pub fn poses(&mut self, graph: &PoseGraph) -> Result<Vec<Pose2>, EstimateError> {
        self.sync(graph);
        let theta = self.heads.all(0);
        if self.anisotropic {
            return crate::estimate::poses(graph, &theta);
        }
        let y = relinearised(&mut self.heads, graph, self.positions.edge_count());
        let [x, y] = self.positions.all_for(y);
        Ok((0..theta.len())
            .map(|v| Pose2::new(x[v], y[v], theta[v]))
            .collect())
    }

    /// Variance of node v's orientation relative to its anchor.
    pub fn orientation_variance(&mut self, graph: &PoseGraph, v: usize) -> f64 {
        self.sync(graph);
        self.heads.variance(v)
    }

    /// Variance of each coordinate of node v's position relative to its anchor (isotropic
    /// weights).
    pub fn position_variance(&mut self, graph: &PoseGraph, v: usize) -> f64 {
        self.sync(graph);
        self.positions.variance(v)
    }
}

/// The first `edges` position rows at the current headings.
fn relinearised(heads: &mut Laplacian<1>, graph: &PoseGraph, edges: usize) -> Vec<[f64; 2]> {
    let theta = heads.all(0);
    graph
        .endpoints()
        .iter()
        .zip(graph.edges())
        .take(edges)
        .map(|(&(a, _), e)| rotate(theta[a], e.measurement()))
        .collect()
}
