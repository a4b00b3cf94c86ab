//! The pose-graph model (method [§1](crate::method#1-model)).
//!
//! A pose graph has nodes with optional initial poses and directed edges `e = (i, j)`, each
//! carrying a measured relative pose `(dx, dy, dθ)` and its 3×3 information matrix `Ω`
//! in `(x, y, θ)` order. The orientation part of the model is
//!
//! ```text
//! δ_e = θ_j − θ_i + ε_e  (mod 2π),   ε_e ~ N(0, σ_e²),   σ_e² = (Ω⁻¹)_θθ,
//! ```
//!
//! the marginal variance of the angle (equal to `1/Ω_θθ` when Ω is diagonal). `δ_e` is kept
//! exactly as given: any real number, not reduced to (−π, π].
//!
//! Node ids are arbitrary `u64` values (not assumed dense or ordered); the graph maps them to
//! dense indices `0..n` in order of first appearance, which is deterministic for a given
//! input order. Parallel edges (several edges between the same pair of nodes) are legal and
//! are indexed by edge id, never by node pair.

use std::collections::HashMap;

use serde::{Deserialize, Serialize};

/// Wrap an angle into (−π, π] (the one implementation; the simulator re-exports it).
///
/// ```
/// use so2lin::graph::wrap_angle;
/// assert_eq!(wrap_angle(std::f64::consts::PI), std::f64::consts::PI);
/// assert!((wrap_angle(-std::f64::consts::PI) - std::f64::consts::PI).abs() < 1e-15);
/// assert!((wrap_angle(7.0) - (7.0 - std::f64::consts::TAU)).abs() < 1e-15);
/// ```
pub fn wrap_angle(a: f64) -> f64 {
    use std::f64::consts::{PI, TAU};
    let w = a - TAU * libm::floor((a + PI) / TAU);
    if w <= -PI { w + TAU } else { w }
}

/// The largest |dθ| an edge may have, in radians: 2π·2²⁰ (about 6.6·10⁶ rad, a million turns).
///
/// Wraps and cycle integers are computed in f64 and i64 from sums of dθ/2π over cycles; up to
/// this size the sum of a cycle of a million edges stays below 2⁴⁰ turns, where f64 still
/// resolves a turn to better than 10⁻³ and no integer arithmetic can overflow. A larger dθ
/// carries no usable information about its wrap and is rejected.
pub const MAX_ABS_DELTA: f64 = std::f64::consts::TAU * (1u64 << 20) as f64;

/// The largest ratio between the angle information (1/σ²) of two edges of one graph that the
/// orientation system is solved reliably at in double precision (10¹⁵, about 1/ε of f64);
/// beyond it factorisations may fail. See [`PoseGraph::information_spread`].
pub const MAX_INFORMATION_SPREAD: f64 = 1e15;

/// A node id as written in a file or given by a caller. Not assumed dense or ordered.
pub type NodeId = u64;

/// A planar pose or relative pose `(x, y, θ)`, θ in radians (any real number).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose2 {
    /// x coordinate.
    pub x: f64,
    /// y coordinate.
    pub y: f64,
    /// Orientation in radians.
    pub theta: f64,
}

impl Pose2 {
    /// A pose from its three components.
    pub const fn new(x: f64, y: f64, theta: f64) -> Self {
        Self { x, y, theta }
    }

    fn is_finite(&self) -> bool {
        self.x.is_finite() && self.y.is_finite() && self.theta.is_finite()
    }

    /// `self ⊕ z`: the pose reached from `self` by the relative pose `z` (angles add, not
    /// wrapped). Trigonometry from `libm`, so results are the same on every platform.
    pub fn compose(self, z: Pose2) -> Pose2 {
        let (s, c) = libm::sincos(self.theta);
        Pose2::new(
            self.x + c * z.x - s * z.y,
            self.y + s * z.x + c * z.y,
            self.theta + z.theta,
        )
    }

    /// `self⁻¹`, the relative pose back.
    pub fn inverse(self) -> Pose2 {
        let (s, c) = libm::sincos(self.theta);
        Pose2::new(
            -(c * self.x + s * self.y),
            s * self.x - c * self.y,
            -self.theta,
        )
    }

    /// `self⁻¹ ⊕ b`: the pose `b` in the frame of `self` (angle difference not wrapped).
    pub fn between(self, b: Pose2) -> Pose2 {
        let (s, c) = libm::sincos(self.theta);
        let (dx, dy) = (b.x - self.x, b.y - self.y);
        Pose2::new(c * dx + s * dy, -s * dx + c * dy, b.theta - self.theta)
    }
}

/// With the `nalgebra` feature: a pose as an isometry (rotation by θ, then translation).
#[cfg(feature = "nalgebra")]
impl From<Pose2> for nalgebra::Isometry2<f64> {
    fn from(p: Pose2) -> Self {
        nalgebra::Isometry2::new(nalgebra::Vector2::new(p.x, p.y), p.theta)
    }
}

/// With the `nalgebra` feature: an isometry as a pose, θ = its rotation angle in (−π, π].
#[cfg(feature = "nalgebra")]
impl From<nalgebra::Isometry2<f64>> for Pose2 {
    fn from(i: nalgebra::Isometry2<f64>) -> Self {
        Pose2::new(i.translation.x, i.translation.y, i.rotation.angle())
    }
}

/// The 3×3 symmetric information matrix of an edge, in `(x, y, θ)` order, stored as its
/// upper triangle in g2o order: `[I11, I12, I13, I22, I23, I33]`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Information(pub [f64; 6]);

impl Information {
    /// A diagonal information matrix `diag(ixx, iyy, itt)`.
    pub const fn diagonal(ixx: f64, iyy: f64, itt: f64) -> Self {
        Self([ixx, 0.0, 0.0, iyy, 0.0, itt])
    }

    /// The information stored by a symmetric matrix's upper triangle (its lower one is not
    /// read): the inverse of [`Self::matrix`].
    ///
    /// ```
    /// use so2lin::graph::Information;
    /// let i = Information([44.4, 1.1, 0.3, 376.0, 0.7, 9807.0]);
    /// assert_eq!(Information::from_symmetric(i.matrix()), i);
    /// ```
    pub fn from_symmetric(m: [[f64; 3]; 3]) -> Self {
        Self([m[0][0], m[0][1], m[0][2], m[1][1], m[1][2], m[2][2]])
    }

    /// The full symmetric matrix, row-major.
    pub fn matrix(&self) -> [[f64; 3]; 3] {
        let [a, b, c, d, e, f] = self.0;
        [[a, b, c], [b, d, e], [c, e, f]]
    }

    /// The Cholesky factor `L` (lower triangular, `Ω = L Lᵀ`) if Ω is positive definite.
    ///
    /// Written by hand: a fixed 3×3 factorisation is six lines and needs no linear-algebra
    /// crate in the hot path of file reading.
    pub fn cholesky(&self) -> Option<[[f64; 3]; 3]> {
        let m = self.matrix();
        let mut l = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..=i {
                let s: f64 = (0..j).map(|k| l[i][k] * l[j][k]).sum();
                if i == j {
                    let d = m[i][i] - s;
                    // NaN is not finite, so this also rejects NaN.
                    if !d.is_finite() || d <= 0.0 {
                        return None;
                    }
                    l[i][i] = d.sqrt();
                } else {
                    l[i][j] = (m[i][j] - s) / l[j][j];
                }
            }
        }
        Some(l)
    }

    /// Whether Ω is symmetric positive definite (it is symmetric by construction).
    pub fn is_positive_definite(&self) -> bool {
        self.cholesky().is_some()
    }

    /// The information of the translation alone, `(Σ_tt)⁻¹ = Ω_tt − Ω_tθ Ω_θθ⁻¹ Ω_θt` (the
    /// Schur complement of the angle; `Σ = Ω⁻¹`): the weight of a translation measurement
    /// whose angle error is marginalised out. `Ω_tt` when Ω is diagonal.
    pub fn translation_information(&self) -> [[f64; 2]; 2] {
        let [a, b, c, d, e, f] = self.0;
        [
            [a - c * c / f, b - c * e / f],
            [b - c * e / f, d - e * e / f],
        ]
    }

    /// The angle variance `σ² = (Ω⁻¹)_θθ`, if Ω is positive definite.
    ///
    /// With `Ω = L Lᵀ`, `(Ω⁻¹)_θθ = ‖L⁻¹ e₃‖² = 1 / L₃₃²`: the inverse of the Schur
    /// complement of the (x, y) block, which is `1/Ω_θθ` when Ω is diagonal.
    pub fn angle_variance(&self) -> Option<f64> {
        let l = self.cholesky()?;
        let v = 1.0 / (l[2][2] * l[2][2]);
        (v.is_finite() && v > 0.0).then_some(v)
    }
}

/// Why an edge or node was rejected.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum GraphError {
    /// An edge from a node to itself.
    #[error("edge {from}→{to} is a self-loop")]
    SelfLoop {
        /// The node.
        from: NodeId,
        /// Same as `from`.
        to: NodeId,
    },
    /// A measurement or information entry that is NaN or infinite.
    #[error("edge {from}→{to}: {what} is not finite")]
    NonFinite {
        /// Source node.
        from: NodeId,
        /// Target node.
        to: NodeId,
        /// Which number.
        what: &'static str,
    },
    /// The information matrix is not symmetric positive definite, so σ² is not finite and > 0.
    #[error("edge {from}→{to}: information matrix {info:?} is not positive definite")]
    NotPositiveDefinite {
        /// Source node.
        from: NodeId,
        /// Target node.
        to: NodeId,
        /// The offending upper triangle, g2o order.
        info: [f64; 6],
    },
    /// The caller required known nodes and this one was never added.
    #[error("edge {from}→{to}: unknown node {node}")]
    UnknownNode {
        /// Source node.
        from: NodeId,
        /// Target node.
        to: NodeId,
        /// The unknown endpoint.
        node: NodeId,
    },
    /// |dθ| above [`MAX_ABS_DELTA`]: its wraps cannot be computed.
    #[error(
        "edge {from}→{to}: dθ = {delta:e} rad is beyond ±2π·2²⁰ (a million turns): its wraps cannot be computed"
    )]
    AngleTooLarge {
        /// Source node.
        from: NodeId,
        /// Target node.
        to: NodeId,
        /// The measured angle.
        delta: f64,
    },
    /// A node pose with a non-finite component.
    #[error("node {node}: pose is not finite")]
    NonFinitePose {
        /// The node.
        node: NodeId,
    },
    /// A node added twice with different initial poses.
    #[error("node {node} is defined twice with different poses")]
    DuplicateNode {
        /// The node.
        node: NodeId,
    },
}

/// A validated measurement edge `from → to`.
///
/// Construct with [`Edge::new`]; the angle variance σ² is derived once and cached.
/// Deserialising validates like [`Edge::new`] (a `sigma2` field, if present, is ignored).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "EdgeFields")]
pub struct Edge {
    from: NodeId,
    to: NodeId,
    measurement: Pose2,
    information: Information,
    sigma2: f64,
}

/// The fields an edge is deserialised from, validated by [`Edge::new`].
#[derive(Deserialize)]
struct EdgeFields {
    from: NodeId,
    to: NodeId,
    measurement: Pose2,
    information: Information,
}

impl TryFrom<EdgeFields> for Edge {
    type Error = GraphError;
    fn try_from(f: EdgeFields) -> Result<Self, GraphError> {
        Edge::new(f.from, f.to, f.measurement, f.information)
    }
}

impl Edge {
    /// Validate and build an edge: no self-loop, finite numbers, Ω positive definite.
    pub fn new(
        from: NodeId,
        to: NodeId,
        measurement: Pose2,
        information: Information,
    ) -> Result<Self, GraphError> {
        if from == to {
            return Err(GraphError::SelfLoop { from, to });
        }
        if !measurement.is_finite() {
            return Err(GraphError::NonFinite {
                from,
                to,
                what: "measurement",
            });
        }
        if measurement.theta.abs() > MAX_ABS_DELTA {
            return Err(GraphError::AngleTooLarge {
                from,
                to,
                delta: measurement.theta,
            });
        }
        if information.0.iter().any(|v| !v.is_finite()) {
            return Err(GraphError::NonFinite {
                from,
                to,
                what: "information matrix",
            });
        }
        let sigma2 = information
            .angle_variance()
            .ok_or(GraphError::NotPositiveDefinite {
                from,
                to,
                info: information.0,
            })?;
        Ok(Self {
            from,
            to,
            measurement,
            information,
            sigma2,
        })
    }

    /// An edge with diagonal information `diag(1/σ_xy², 1/σ_xy², 1/σ_θ²)`.
    pub fn with_sigmas(
        from: NodeId,
        to: NodeId,
        measurement: Pose2,
        sigma_xy: f64,
        sigma_theta: f64,
    ) -> Result<Self, GraphError> {
        let ixy = 1.0 / (sigma_xy * sigma_xy);
        Self::new(
            from,
            to,
            measurement,
            Information::diagonal(ixy, ixy, 1.0 / (sigma_theta * sigma_theta)),
        )
    }

    /// Source node id.
    pub fn from(&self) -> NodeId {
        self.from
    }
    /// Target node id.
    pub fn to(&self) -> NodeId {
        self.to
    }
    /// Measured relative pose of `to` in the frame of `from`.
    pub fn measurement(&self) -> Pose2 {
        self.measurement
    }
    /// The measured relative angle δ_e (as given, not wrapped).
    pub fn delta(&self) -> f64 {
        self.measurement.theta
    }
    /// The information matrix Ω.
    pub fn information(&self) -> Information {
        self.information
    }
    /// The angle variance σ² = (Ω⁻¹)_θθ.
    pub fn sigma2(&self) -> f64 {
        self.sigma2
    }
    /// Whether the edge joins consecutive ids (|i − j| = 1), the convention for odometry.
    pub fn is_odometric(&self) -> bool {
        self.from.abs_diff(self.to) == 1
    }

    /// The same measurement written the other way, `to → from`: the inverse relative pose
    /// `Z⁻¹` and the information of the same noise seen from the other end.
    ///
    /// With the noise a right perturbation (`Z ⊕ ε`, g2o's convention),
    /// `(Z ⊕ ε)⁻¹ = Z⁻¹ ⊕ ε'` with `ε' = −Ad(Z) ε`, `Ad(Z) = [[R(θ), J t], [0, 1]]`,
    /// `J t = (t_y, −t_x)`: so `Σ' = Ad Σ Adᵀ` and `Ω' = Ad⁻ᵀ Ω Ad⁻¹`. The translation's
    /// information gains cross terms with the angle (its noise gains `J t ε_θ`), and the
    /// angle variance is unchanged (kept to the bit: the estimate of the headings is the same
    /// whichever way an edge is written). `e.reversed().reversed()` is `e` up to rounding.
    ///
    /// ```
    /// use so2lin::graph::{Edge, Information, Pose2};
    /// let e = Edge::new(3, 7, Pose2::new(1.0, 0.5, 0.3), Information::diagonal(100.0, 100.0, 400.0))?;
    /// let r = e.reversed();
    /// assert_eq!((r.from(), r.to()), (7, 3));
    /// assert_eq!(r.sigma2(), e.sigma2());
    /// let back = r.reversed();
    /// assert!((back.measurement().x - 1.0).abs() < 1e-12);
    /// assert!((back.information().0[0] - 100.0).abs() < 1e-9);
    /// # Ok::<(), so2lin::graph::GraphError>(())
    /// ```
    pub fn reversed(&self) -> Edge {
        let z = self.measurement;
        let (s, c) = libm::sincos(z.theta);
        // Ad⁻¹ = [[Rᵀ, −Rᵀ J t], [0, 1]].
        let (jx, jy) = (z.y, -z.x);
        let inv = [
            [c, s, -(c * jx + s * jy)],
            [-s, c, -(-s * jx + c * jy)],
            [0.0, 0.0, 1.0],
        ];
        let m = self.information.matrix();
        // Ω' = (Ad⁻¹)ᵀ Ω Ad⁻¹.
        let mut w = [[0.0; 3]; 3];
        for (i, row) in w.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v = (0..3)
                    .flat_map(|k| (0..3).map(move |l| (k, l)))
                    .map(|(k, l)| inv[k][i] * m[k][l] * inv[l][j])
                    .sum();
            }
        }
        Edge {
            from: self.to,
            to: self.from,
            measurement: z.inverse(),
            information: Information::from_symmetric(w),
            sigma2: self.sigma2,
        }
    }
}

/// Two edges whose angle information differs by more than [`MAX_INFORMATION_SPREAD`]
/// ([`PoseGraph::information_spread`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct InformationSpread {
    /// Index of the edge of largest angle information.
    pub high: usize,
    /// Index of the edge of smallest angle information.
    pub low: usize,
    /// The ratio of the two informations.
    pub ratio: f64,
}

/// A node of the graph.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Node {
    /// The node's id.
    pub id: NodeId,
    /// Initial pose (e.g. from a file's vertex line), if known.
    pub initial: Option<Pose2>,
}

/// Whether an edge may introduce nodes that were not added before.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum NodePolicy {
    /// An edge to an unseen node creates it (files without vertex lines, online use).
    #[default]
    CreateUnknown,
    /// An edge to an unseen node is an error.
    RequireKnown,
}

/// A pose graph: nodes indexed densely in order of first appearance, edges in insertion order.
#[derive(Clone, Debug, Default)]
pub struct PoseGraph {
    nodes: Vec<Node>,
    index: HashMap<NodeId, usize>,
    edges: Vec<Edge>,
    ends: Vec<(usize, usize)>,
}

impl PoseGraph {
    /// Room for `nodes` more nodes and `edges` more edges without growing its arrays (see
    /// [`crate::online::OnlineEstimator::reserve`]: a growing array is copied in one step).
    pub fn try_reserve(
        &mut self,
        nodes: usize,
        edges: usize,
    ) -> Result<(), std::collections::TryReserveError> {
        self.nodes.try_reserve(nodes)?;
        self.index.try_reserve(nodes)?;
        self.edges.try_reserve(edges)?;
        self.ends.try_reserve(edges)?;
        Ok(())
    }

    /// An empty graph.
    pub fn new() -> Self {
        Self::default()
    }

    /// Add a node, or set the initial pose of a node created earlier by an edge.
    /// Adding the same node twice with the same pose is accepted; with another pose it is an error.
    pub fn add_node(&mut self, id: NodeId, initial: Option<Pose2>) -> Result<usize, GraphError> {
        if let Some(p) = initial
            && !p.is_finite()
        {
            return Err(GraphError::NonFinitePose { node: id });
        }
        if let Some(&k) = self.index.get(&id) {
            let node = &mut self.nodes[k];
            match (node.initial, initial) {
                (Some(a), Some(b)) if a != b => return Err(GraphError::DuplicateNode { node: id }),
                (None, Some(_)) => node.initial = initial,
                _ => {}
            }
            return Ok(k);
        }
        Ok(self.push_node(id, initial))
    }

    fn push_node(&mut self, id: NodeId, initial: Option<Pose2>) -> usize {
        let k = self.nodes.len();
        self.nodes.push(Node { id, initial });
        self.index.insert(id, k);
        k
    }

    /// Add a validated edge; returns its edge index. With [`NodePolicy::RequireKnown`] an edge
    /// to an unknown node is rejected and the graph is unchanged.
    pub fn add_edge(&mut self, edge: Edge, policy: NodePolicy) -> Result<usize, GraphError> {
        if policy == NodePolicy::RequireKnown {
            for node in [edge.from, edge.to] {
                if !self.index.contains_key(&node) {
                    return Err(GraphError::UnknownNode {
                        from: edge.from,
                        to: edge.to,
                        node,
                    });
                }
            }
        }
        let a = self.index_or_insert(edge.from);
        let b = self.index_or_insert(edge.to);
        self.edges.push(edge);
        self.ends.push((a, b));
        Ok(self.edges.len() - 1)
    }

    fn index_or_insert(&mut self, id: NodeId) -> usize {
        match self.index.get(&id) {
            Some(&k) => k,
            None => self.push_node(id, None),
        }
    }

    /// Number of nodes.
    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }
    /// Number of edges.
    pub fn edge_count(&self) -> usize {
        self.edges.len()
    }
    /// Nodes in index order.
    pub fn nodes(&self) -> &[Node] {
        &self.nodes
    }
    /// Edges in insertion order.
    pub fn edges(&self) -> &[Edge] {
        &self.edges
    }
    /// Dense endpoint indices `(from, to)` of every edge, parallel to [`edges`](Self::edges).
    pub fn endpoints(&self) -> &[(usize, usize)] {
        &self.ends
    }
    /// Dense index of a node id.
    pub fn node_index(&self, id: NodeId) -> Option<usize> {
        self.index.get(&id).copied()
    }

    /// The edges of largest and smallest angle information 1/σ² and the ratio between them, if
    /// the ratio exceeds [`MAX_INFORMATION_SPREAD`]: a diagnosis for a linear system that failed
    /// to factor (both edges are valid on their own).
    pub fn information_spread(&self) -> Option<InformationSpread> {
        let by = |cmp: fn(f64, f64) -> bool| {
            let mut best: Option<usize> = None;
            for (e, edge) in self.edges.iter().enumerate() {
                if best.is_none_or(|b| cmp(1.0 / edge.sigma2, 1.0 / self.edges[b].sigma2)) {
                    best = Some(e);
                }
            }
            best
        };
        let (high, low) = (by(|a, b| a > b)?, by(|a, b| a < b)?);
        let info = |e: usize| 1.0 / self.edges[e].sigma2;
        let ratio = info(high) / info(low);
        (ratio > MAX_INFORMATION_SPREAD).then_some(InformationSpread { high, low, ratio })
    }

    /// Connected components: a component label (0-based, in order of first node) per node,
    /// and the number of components.
    pub fn components(&self) -> (Vec<usize>, usize) {
        let mut uf = UnionFind::new(self.nodes.len());
        for &(a, b) in &self.ends {
            uf.union(a, b);
        }
        let mut label = vec![usize::MAX; self.nodes.len()];
        let mut root_label = vec![usize::MAX; self.nodes.len()];
        let mut count = 0;
        for (v, l) in label.iter_mut().enumerate() {
            let r = uf.find(v);
            if root_label[r] == usize::MAX {
                root_label[r] = count;
                count += 1;
            }
            *l = root_label[r];
        }
        (label, count)
    }

    /// Number of edges whose unordered node pair was already joined by an earlier edge.
    pub fn parallel_edge_count(&self) -> usize {
        let mut seen = std::collections::HashSet::with_capacity(self.ends.len());
        self.ends
            .iter()
            .filter(|&&(a, b)| !seen.insert((a.min(b), a.max(b))))
            .count()
    }

    /// Summary statistics (the `info` command).
    pub fn stats(&self) -> GraphStats {
        let (_, components) = self.components();
        let odometric = self.edges.iter().filter(|e| e.is_odometric()).count();
        let mut s: Vec<f64> = self.edges.iter().map(|e| e.sigma2.sqrt()).collect();
        s.sort_by(f64::total_cmp);
        let sigma_theta = (!s.is_empty()).then(|| SigmaStats {
            min: s[0],
            median: if s.len() % 2 == 1 {
                s[s.len() / 2]
            } else {
                0.5 * (s[s.len() / 2 - 1] + s[s.len() / 2])
            },
            max: s[s.len() - 1],
        });
        GraphStats {
            nodes: self.nodes.len(),
            edges: self.edges.len(),
            odometric_edges: odometric,
            loop_closures: self.edges.len() - odometric,
            cycles: self.edges.len() + components - self.nodes.len(),
            components,
            parallel_edges: self.parallel_edge_count(),
            sigma_theta,
        }
    }
}

/// Min / median / max of σ_θ over the edges.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct SigmaStats {
    /// Smallest σ_θ.
    pub min: f64,
    /// Median σ_θ.
    pub median: f64,
    /// Largest σ_θ.
    pub max: f64,
}

/// Counts describing a graph.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct GraphStats {
    /// Number of nodes n.
    pub nodes: usize,
    /// Number of edges m.
    pub edges: usize,
    /// Edges with |i − j| = 1.
    pub odometric_edges: usize,
    /// All other edges.
    pub loop_closures: usize,
    /// Cycle-space dimension ℓ = m − n + c.
    pub cycles: usize,
    /// Connected components c.
    pub components: usize,
    /// Edges repeating an earlier edge's node pair.
    pub parallel_edges: usize,
    /// σ_θ statistics (absent for a graph without edges).
    pub sigma_theta: Option<SigmaStats>,
}

/// Disjoint sets with path halving and union by size, growable one element at a time
/// (the online estimator adds nodes as edges arrive, which petgraph's fixed-size
/// `UnionFind` does not support).
#[derive(Clone, Debug, Default)]
pub struct UnionFind {
    parent: Vec<usize>,
    size: Vec<usize>,
}

impl UnionFind {
    /// Room for `additional` more sets without growing.
    pub fn try_reserve(
        &mut self,
        additional: usize,
    ) -> Result<(), std::collections::TryReserveError> {
        self.parent.try_reserve(additional)?;
        self.size.try_reserve(additional)?;
        Ok(())
    }

    /// `n` singleton sets.
    pub fn new(n: usize) -> Self {
        Self {
            parent: (0..n).collect(),
            size: vec![1; n],
        }
    }
    /// Add a singleton set; returns its element.
    pub fn push(&mut self) -> usize {
        self.parent.push(self.parent.len());
        self.size.push(1);
        self.parent.len() - 1
    }
    /// Number of elements.
    pub fn len(&self) -> usize {
        self.parent.len()
    }
    /// Whether there are no elements.
    pub fn is_empty(&self) -> bool {
        self.parent.is_empty()
    }
    /// Representative of `x`'s set.
    pub fn find(&mut self, mut x: usize) -> usize {
        while self.parent[x] != x {
            self.parent[x] = self.parent[self.parent[x]];
            x = self.parent[x];
        }
        x
    }
    /// Merge the sets of `a` and `b`; false if they were already one set.
    pub fn union(&mut self, a: usize, b: usize) -> bool {
        let (mut ra, mut rb) = (self.find(a), self.find(b));
        if ra == rb {
            return false;
        }
        if self.size[ra] < self.size[rb] {
            std::mem::swap(&mut ra, &mut rb);
        }
        self.parent[rb] = ra;
        self.size[ra] += self.size[rb];
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn e(from: NodeId, to: NodeId) -> Edge {
        Edge::with_sigmas(from, to, Pose2::new(1.0, 0.0, 0.1), 0.1, 0.05).unwrap()
    }

    #[test]
    fn absurd_angles_are_rejected_and_spread_is_named() {
        let info = Information::diagonal(1.0, 1.0, 1.0);
        for delta in [1e300, -1e300, MAX_ABS_DELTA * 1.0001] {
            let err = Edge::new(0, 1, Pose2::new(0.0, 0.0, delta), info).unwrap_err();
            assert!(matches!(err, GraphError::AngleTooLarge { .. }), "{err}");
        }
        assert!(Edge::new(0, 1, Pose2::new(0.0, 0.0, MAX_ABS_DELTA), info).is_ok());
        let mut g = PoseGraph::new();
        g.add_edge(e(0, 1), NodePolicy::CreateUnknown).unwrap();
        assert_eq!(g.information_spread(), None);
        let strong = Edge::new(
            1,
            2,
            Pose2::default(),
            Information::diagonal(1.0, 1.0, 1e20),
        );
        g.add_edge(strong.unwrap(), NodePolicy::CreateUnknown)
            .unwrap();
        let s = g.information_spread().unwrap();
        assert_eq!((s.high, s.low), (1, 0));
        assert!(s.ratio > 1e16);
    }

    #[test]
    fn edges_deserialise_validated() {
        let good = e(3, 4);
        let text = serde_json::to_string(&good).unwrap();
        assert_eq!(serde_json::from_str::<Edge>(&text).unwrap(), good);
        let self_loop = text.replace("\"to\":4", "\"to\":3");
        let err = serde_json::from_str::<Edge>(&self_loop).unwrap_err();
        assert!(err.to_string().contains("self-loop"), "{err}");
    }

    #[cfg(feature = "nalgebra")]
    #[test]
    fn isometry_round_trip() {
        let p = Pose2::new(1.5, -2.0, 0.7);
        let iso: nalgebra::Isometry2<f64> = p.into();
        let q = p.compose(Pose2::new(0.3, 0.4, -0.2));
        let moved = iso * nalgebra::Isometry2::from(Pose2::new(0.3, 0.4, -0.2));
        let back = Pose2::from(moved);
        assert!((back.x - q.x).abs() < 1e-12 && (back.y - q.y).abs() < 1e-12);
        assert!((back.theta - q.theta).abs() < 1e-12);
        assert_eq!(Pose2::from(iso), p);
    }

    #[test]
    fn angle_variance_diagonal_and_full() {
        let d = Information::diagonal(4.0, 9.0, 30.9);
        assert!((d.angle_variance().unwrap() - 1.0 / 30.9).abs() < 1e-15);
        // Full matrix: compare with the cofactor formula (Ω⁻¹)_33 = (a d − b²)/det Ω.
        let i = Information([44.4, 1.1, 0.3, 376.0, 0.7, 9807.0]);
        let [a, b, c, d, e, f] = i.0;
        let det = a * (d * f - e * e) - b * (b * f - e * c) + c * (b * e - d * c);
        let want = (a * d - b * b) / det;
        let got = i.angle_variance().unwrap();
        assert!(
            (got - want).abs() < 1e-15 * want.abs().max(1.0),
            "{got} vs {want}"
        );
    }

    #[test]
    fn rejects_bad_edges() {
        let p = Pose2::new(0.0, 0.0, 0.0);
        let ok = Information::diagonal(1.0, 1.0, 1.0);
        assert!(matches!(
            Edge::new(3, 3, p, ok),
            Err(GraphError::SelfLoop { .. })
        ));
        assert!(matches!(
            Edge::new(0, 1, Pose2::new(f64::NAN, 0.0, 0.0), ok),
            Err(GraphError::NonFinite { .. })
        ));
        assert!(matches!(
            Edge::new(
                0,
                1,
                p,
                Information([1.0, 0.0, 0.0, 1.0, 0.0, f64::INFINITY])
            ),
            Err(GraphError::NonFinite { .. })
        ));
        for bad in [
            Information::diagonal(1.0, 1.0, 0.0),
            Information::diagonal(1.0, 1.0, -2.0),
            Information::diagonal(-1.0, 1.0, 1.0),
            Information([1.0, 2.0, 0.0, 1.0, 0.0, 1.0]),
        ] {
            assert!(matches!(
                Edge::new(0, 1, p, bad),
                Err(GraphError::NotPositiveDefinite { .. })
            ));
        }
    }

    #[test]
    fn sparse_ids_parallel_edges_components() {
        let mut g = PoseGraph::new();
        g.add_edge(e(100, 7), NodePolicy::CreateUnknown).unwrap();
        g.add_edge(e(7, 100), NodePolicy::CreateUnknown).unwrap();
        g.add_edge(e(5, 6), NodePolicy::CreateUnknown).unwrap();
        assert_eq!(g.node_index(100), Some(0));
        assert_eq!(g.node_index(6), Some(3));
        let s = g.stats();
        assert_eq!(
            (s.nodes, s.edges, s.components, s.cycles, s.parallel_edges),
            (4, 3, 2, 1, 1)
        );
        assert_eq!((s.odometric_edges, s.loop_closures), (1, 2));
    }

    #[test]
    fn require_known_leaves_graph_unchanged() {
        let mut g = PoseGraph::new();
        g.add_node(0, Some(Pose2::default())).unwrap();
        let err = g.add_edge(e(0, 1), NodePolicy::RequireKnown).unwrap_err();
        assert_eq!(
            err,
            GraphError::UnknownNode {
                from: 0,
                to: 1,
                node: 1
            }
        );
        assert_eq!((g.node_count(), g.edge_count()), (1, 0));
        assert!(matches!(
            g.add_node(0, Some(Pose2::new(1.0, 0.0, 0.0))),
            Err(GraphError::DuplicateNode { node: 0 })
        ));
    }
}
