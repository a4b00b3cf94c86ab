//! The online estimator (METHOD.md §7): tree, cycle basis, γ model and screening grown one
//! edge at a time.
//!
//! Each edge either reaches a new node or joins two components (a **tree edge**: no new
//! cycle), or closes exactly one new cycle: the edge plus the least-σ² path between its ends
//! in the graph so far ([`IncrementalBasis`]). The new cycle adds one row to μ and P_γ
//! ([`GammaModel::push_cycle`]) and is screened at once, conditioned on every determined cycle
//! through the append-only Cholesky factor ([`crate::gamma::Conditioner`]):
//!
//! ```text
//! y = L⁻¹ P_{U,new},   mean = μ_new + yᵀz,   var = P_new,new − ‖y‖²,   Γ = Z ∩ [mean ± q·sd].
//! ```
//!
//! A single candidate determines the cycle (a row is appended to L). When a cycle is
//! determined, the ambiguous cycles that share information with it directly — a nonzero
//! `(P_γ)_ij`, i.e. a common edge — are re-screened with fresh conditional moments, and a
//! re-screen that leaves one candidate determines that cycle too (and so on). Ambiguous cycles
//! correlated only indirectly are left as they are until a neighbour is determined (their
//! stored moments are then conditioned on fewer cycles: wider, never overconfident), which
//! keeps a step's cost local; `finish` re-screens every one of them exactly. [`OnlineEstimator::finish`] runs the batch
//! pipeline's fixed-point first screening and second screening on the current state — the
//! same [`Screener`] code.
//!
//! Orientations are cached: an odometry step to a new node extends the cached estimate in O(1)
//! (`θ_new = θ_i + δ` is exact for a leaf), and a new cycle invalidates it; the next query
//! solves the anchored Laplacian once ([`OrientationEstimator`]). Between determinations the
//! ambiguous cycles' chords use their most likely integer (the rounded conditional mean).

use serde::Serialize;

use crate::batch::{self, BatchResult};
use crate::cycles::{BasisKind, Cycle, CycleBasis, IncrementalBasis};
use crate::estimate::{EstimateError, OrientationEstimator};
use std::collections::{BTreeMap, VecDeque};

use crate::gamma::{GammaModel, Moments};
use crate::graph::{Edge, GraphError, Information, NodeId, NodePolicy, Pose2, PoseGraph};
use crate::screening::{
    ConfigError, Hypothesis, Interval, Screener, ScreeningConfig, rounding_success,
};
use crate::wraps::WrapSolver;

/// Settings of the online estimator.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct OnlineConfig {
    /// Screening settings (α, degrees of freedom, family-wise, hypothesis cap). Family-wise,
    /// cycle t is tested at [`ScreeningConfig::online_level`]`(t)` (α-spending).
    pub screening: ScreeningConfig,
}

/// What a step decided about a cycle.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Decision {
    /// One candidate: the cycle's integer is fixed.
    Determined,
    /// Several candidates.
    Ambiguous,
    /// The confidence interval held no integer: kept ambiguous with the two nearest.
    Inconsistent,
}

impl Decision {
    fn of(iv: Interval, determined: bool) -> Self {
        if determined {
            Decision::Determined
        } else if iv.inconsistent {
            Decision::Inconsistent
        } else {
            Decision::Ambiguous
        }
    }
}

/// The screening of the new cycle closed by a step.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct CycleStep {
    /// Cycle id (0-based, in order of closing).
    pub cycle: usize,
    /// Conditional mean of γ given the determined cycles.
    pub mean: f64,
    /// Conditional standard deviation.
    pub sd: f64,
    /// Candidate integers `lo..=hi`.
    pub candidates: Interval,
    /// The decision.
    pub decision: Decision,
}

/// An earlier ambiguous cycle re-screened because a determination shared information with it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Rescreen {
    /// Cycle id.
    pub cycle: usize,
    /// Candidates before the step.
    pub before: Interval,
    /// Candidates after it.
    pub after: Interval,
    /// Decision after it.
    pub decision: Decision,
    /// Whether the candidates or decision changed.
    pub changed: bool,
}

/// What one edge did.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum StepKind {
    /// A tree edge: reached a new node, or joined two components.
    Tree {
        /// The edge created a node.
        new_node: bool,
        /// The edge joined two components.
        joined_components: bool,
    },
    /// A chord: closed a new cycle.
    Cycle(CycleStep),
}

/// The outcome of [`OnlineEstimator::add_edge`].
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Step {
    /// Index of the edge (0-based, in order of arrival).
    pub edge: usize,
    /// Tree edge or new cycle.
    pub kind: StepKind,
    /// Earlier cycles re-screened by this step, ascending.
    pub rescreened: Vec<Rescreen>,
}

/// Counters of a run.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Counters {
    /// Edges accepted.
    pub steps: usize,
    /// Tree edges among them.
    pub tree_edges: usize,
    /// Cycles closed.
    pub cycles: usize,
    /// Cycles determined.
    pub determined: usize,
    /// Cycles ambiguous now.
    pub ambiguous: usize,
    /// Cycles found inconsistent so far.
    pub inconsistent: usize,
    /// Re-screens of ambiguous cycles.
    pub rescreens: usize,
    /// Times the factor of P_UU was rebuilt in a fill-reducing order.
    pub reorders: usize,
}

/// Why an input or query was refused. A refused edge leaves the estimator unchanged.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum OnlineError {
    /// The edge failed validation.
    #[error(transparent)]
    Edge(#[from] GraphError),
    /// More edges than the estimator indexes (2³² − 1).
    #[error("too many edges: the estimator indexes at most {0}")]
    Capacity(usize),
    /// Bad settings.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// A numerical failure while screening or estimating.
    #[error("numerical failure: {0}")]
    Numerical(String),
}

impl From<EstimateError> for OnlineError {
    fn from(e: EstimateError) -> Self {
        OnlineError::Numerical(e.to_string())
    }
}

/// The online estimator.
///
/// ```
/// use so2lin::online::{OnlineConfig, OnlineEstimator};
/// use so2lin::graph::Pose2;
///
/// let mut est = OnlineEstimator::new(OnlineConfig::default()).unwrap();
/// let step = |i: u64, j: u64, dtheta: f64| (i, j, Pose2::new(1.0, 0.0, dtheta));
/// for (i, j, z) in [step(0, 1, 1.57), step(1, 2, 1.57), step(2, 3, 1.57), step(3, 0, 1.57)] {
///     est.add_measurement(i, j, z, 0.05, 0.01).unwrap();
/// }
/// assert_eq!(est.counters().determined, 1);
/// let heading = est.orientation(3).unwrap().unwrap();
/// assert!((heading - 3.0 * 1.5708).abs() < 0.01);
/// ```
pub struct OnlineEstimator {
    config: OnlineConfig,
    graph: PoseGraph,
    sigma2: Vec<f64>,
    delta: Vec<f64>,
    basis: IncrementalBasis,
    cycles: Vec<Cycle>,
    model: GammaModel,
    screener: Screener,
    /// Ambiguous cycles with their conditional moments at their last screening.
    ambiguous: BTreeMap<usize, Moments>,
    counters: Counters,
    theta: Vec<f64>,
    theta_valid: bool,
    solver: Option<OrientationEstimator>,
    /// Nonzeros per row of L right after the last reordering.
    fill_after_reorder: f64,
    /// MCAP recorder, when attached.
    recorder: Option<Box<crate::log::Recorder>>,
}

/// Below this many determined cycles L is never reordered (chronological fill is cheap).
const REORDER_MIN_ROWS: usize = 256;
/// Reorder when L's nonzeros per row exceed this multiple of the last reordered factor's.
const REORDER_FILL_RATIO: f64 = 1.5;

impl OnlineEstimator {
    /// A new estimator with no nodes.
    pub fn new(config: OnlineConfig) -> Result<Self, OnlineError> {
        config.screening.validate()?;
        Ok(Self {
            config,
            graph: PoseGraph::new(),
            sigma2: Vec::new(),
            delta: Vec::new(),
            basis: IncrementalBasis::new(),
            cycles: Vec::new(),
            model: GammaModel::new(),
            screener: Screener::new(),
            ambiguous: BTreeMap::new(),
            counters: Counters::default(),
            theta: Vec::new(),
            theta_valid: true,
            solver: None,
            fill_after_reorder: f64::INFINITY,
            recorder: None,
        })
    }

    /// The settings.
    pub fn config(&self) -> &OnlineConfig {
        &self.config
    }

    /// Validate and add a measurement with isotropic noise (σ_xy, σ_θ).
    pub fn add_measurement(
        &mut self,
        from: NodeId,
        to: NodeId,
        z: Pose2,
        sigma_xy: f64,
        sigma_theta: f64,
    ) -> Result<Step, OnlineError> {
        self.add_edge(Edge::with_sigmas(from, to, z, sigma_xy, sigma_theta)?)
    }

    /// Validate and add a measurement with a full information matrix.
    pub fn add_measurement_info(
        &mut self,
        from: NodeId,
        to: NodeId,
        z: Pose2,
        info: Information,
    ) -> Result<Step, OnlineError> {
        self.add_edge(Edge::new(from, to, z, info)?)
    }

    /// Record every following step to an MCAP log ([`crate::log`]). Without a recorder
    /// `add_edge` does no recording work at all.
    pub fn attach_recorder(&mut self, recorder: crate::log::Recorder) {
        self.recorder = Some(Box::new(recorder));
    }

    /// The attached recorder (to [`sync`](crate::log::Recorder::sync) it or read its error).
    pub fn recorder_mut(&mut self) -> Option<&mut crate::log::Recorder> {
        self.recorder.as_deref_mut()
    }

    /// Take the recorder back (to finish the log).
    pub fn detach_recorder(&mut self) -> Option<crate::log::Recorder> {
        self.recorder.take().map(|r| *r)
    }

    /// Add an edge (validated by construction). Edges to unseen nodes create them; an edge
    /// between two components joins them. With a recorder attached, the edge, the step and
    /// its latency are logged.
    pub fn add_edge(&mut self, edge: Edge) -> Result<Step, OnlineError> {
        let Some(mut recorder) = self.recorder.take() else {
            return self.add_edge_inner(edge);
        };
        let start = std::time::Instant::now();
        let step = self.add_edge_inner(edge);
        let ns = start.elapsed().as_nanos() as u64;
        if let Ok(s) = &step {
            recorder.record(&edge, s, ns, self);
        }
        self.recorder = Some(recorder);
        step
    }

    fn add_edge_inner(&mut self, edge: Edge) -> Result<Step, OnlineError> {
        let e = self.graph.edge_count();
        if e >= u32::MAX as usize {
            return Err(OnlineError::Capacity(u32::MAX as usize));
        }
        let nodes_before = self.graph.node_count();
        // Cannot fail with CreateUnknown; mapped rather than unwrapped all the same.
        self.graph.add_edge(edge, NodePolicy::CreateUnknown)?;
        let (a, b) = self.graph.endpoints()[e];
        self.sigma2.push(edge.sigma2());
        self.delta.push(edge.delta());
        self.counters.steps += 1;
        self.solver = None;
        let Some(cycle) = self.basis.add_edge(a, b, edge.sigma2()) else {
            self.counters.tree_edges += 1;
            let new_node = self.graph.node_count() > nodes_before;
            self.extend_estimate(a, b, nodes_before);
            return Ok(Step {
                edge: e,
                kind: StepKind::Tree {
                    new_node,
                    joined_components: !new_node,
                },
                rescreened: Vec::new(),
            });
        };
        self.theta_valid = false;
        self.counters.cycles += 1;
        let t = self.model.push_cycle(&cycle, &self.sigma2, &self.delta);
        self.cycles.push(cycle);
        self.screener.grow(t + 1);
        let cycles = &self.cycles;
        let (m, iv, determined) = self.screener.screen(
            &self.model,
            t,
            self.config.screening.online_quantile(t),
            || edges_of(&cycles[t]),
        );
        let mut rescreened = Vec::new();
        if determined {
            self.propagate(t, &mut rescreened);
            self.maybe_reorder();
        } else {
            self.ambiguous.insert(t, m);
        }
        self.refresh_counters();
        Ok(Step {
            edge: e,
            kind: StepKind::Cycle(CycleStep {
                cycle: t,
                mean: m.mean,
                sd: m.sd(),
                candidates: iv,
                decision: Decision::of(iv, determined),
            }),
            rescreened,
        })
    }

    /// After cycle `first` is determined: re-screen the ambiguous cycles sharing an edge with
    /// it (fresh moments), determine those left with one candidate, and continue from them.
    fn propagate(&mut self, first: usize, out: &mut Vec<Rescreen>) {
        let mut queue = VecDeque::from([first]);
        while let Some(c) = queue.pop_front() {
            let neighbours: Vec<usize> = self
                .model
                .row(c)
                .iter()
                .map(|&(j, _)| j as usize)
                .filter(|j| self.ambiguous.contains_key(j))
                .collect();
            for i in neighbours {
                let before = self.screener.interval(i);
                let cycles = &self.cycles;
                let (m, after, determined) = self.screener.screen(
                    &self.model,
                    i,
                    self.config.screening.online_quantile(i),
                    || edges_of(&cycles[i]),
                );
                self.counters.rescreens += 1;
                if determined {
                    self.ambiguous.remove(&i);
                    queue.push_back(i);
                } else {
                    self.ambiguous.insert(i, m);
                }
                let decision = Decision::of(after, determined);
                match out.iter_mut().find(|x| x.cycle == i) {
                    Some(x) => {
                        x.after = after;
                        x.decision = decision;
                        x.changed = x.before != after || determined;
                    }
                    None => out.push(Rescreen {
                        cycle: i,
                        before,
                        after,
                        decision,
                        changed: before != after || determined,
                    }),
                }
            }
        }
        out.sort_by_key(|x| x.cycle);
    }

    /// Rebuild the factor of P_UU in a fill-reducing order when appending in chronological
    /// order has made it much denser than a reordered one would be (amortised: its fill per row must
    /// grow by half first). Conditional moments are unchanged.
    fn maybe_reorder(&mut self) {
        let rows = self.screener.cond.len();
        if rows < REORDER_MIN_ROWS {
            return;
        }
        let per_row = self.screener.cond.factor_nnz() as f64 / rows as f64;
        let base = if self.fill_after_reorder.is_finite() {
            self.fill_after_reorder
        } else {
            1.0
        };
        if per_row <= REORDER_FILL_RATIO * base.max(1.0) {
            return;
        }
        if self.screener.cond.reorder(&self.model, 0).is_err() {
            return;
        }
        self.fill_after_reorder = self.screener.cond.factor_nnz() as f64 / rows as f64;
        self.counters.reorders += 1;
    }

    /// Extend the cached estimate after a tree edge: exact O(1) for a new leaf.
    fn extend_estimate(&mut self, a: usize, b: usize, nodes_before: usize) {
        let n = self.graph.node_count();
        if !self.theta_valid {
            return;
        }
        let d = *self.delta.last().unwrap_or(&0.0);
        match (a >= nodes_before, b >= nodes_before) {
            (false, true) => self.theta.push(self.theta[a] + d),
            (true, false) => self.theta.push(self.theta[b] - d),
            // Both new: a new component anchored at a.
            (true, true) => self.theta.extend([0.0, d]),
            // Two components joined: the anchor of one changes; recompute on demand.
            (false, false) => self.theta_valid = false,
        }
        debug_assert!(!self.theta_valid || self.theta.len() == n);
    }

    fn refresh_counters(&mut self) {
        self.counters.determined = self.screener.cond.len();
        self.counters.ambiguous = self.ambiguous.len();
        self.counters.inconsistent = self.screener.inconsistent_count();
    }

    /// Counters of the run so far.
    pub fn counters(&self) -> Counters {
        self.counters
    }

    /// The graph so far.
    pub fn graph(&self) -> &PoseGraph {
        &self.graph
    }

    /// The cycles closed so far (the incremental basis), in order.
    pub fn cycles(&self) -> &[Cycle] {
        &self.cycles
    }

    /// Ids of the ambiguous cycles, ascending.
    pub fn ambiguous(&self) -> Vec<usize> {
        self.ambiguous.keys().copied().collect()
    }

    /// Current best γ: determined values, and the rounded conditional mean (clamped to the
    /// candidates) of each ambiguous cycle.
    pub fn gamma(&self) -> Vec<i64> {
        let mut g: Vec<i64> = (0..self.model.len())
            .map(|i| self.screener.cond.value(i).unwrap_or(0))
            .collect();
        for (&i, m) in &self.ambiguous {
            let iv = self.screener.interval(i);
            g[i] = (m.mean.round() as i64).clamp(iv.lo, iv.hi);
        }
        g
    }

    /// Current best wraps k of every edge (zero on tree edges).
    pub fn wraps(&self) -> Result<Vec<i64>, OnlineError> {
        WrapSolver::new(&self.cycles, self.graph.edge_count())
            .and_then(|s| s.wraps(&self.cycles, &self.gamma()))
            .map_err(|e| OnlineError::Numerical(e.to_string()))
    }

    fn ensure_solver(&mut self) -> Result<&OrientationEstimator, OnlineError> {
        if self.solver.is_none() {
            self.solver = Some(OrientationEstimator::new(&self.graph)?);
        }
        // Just set above when it was missing.
        self.solver
            .as_ref()
            .ok_or_else(|| OnlineError::Numerical("no solver".into()))
    }

    /// Current orientations of all nodes (dense index order; anchors 0; unwrapped): cached,
    /// one sparse solve after a new cycle.
    pub fn orientations(&mut self) -> Result<&[f64], OnlineError> {
        if !self.theta_valid {
            let k = self.wraps()?;
            self.theta = self.ensure_solver()?.orientations(&k);
            self.theta_valid = true;
        }
        Ok(&self.theta)
    }

    /// Current poses of all nodes (dense index order): the current orientations with their
    /// least-squares positions ([`OrientationEstimator::poses`]; anchors at the origin).
    /// Computed on demand: one sparse solve (two, with the orientation system, after a new
    /// cycle).
    pub fn poses(&mut self) -> Result<Vec<crate::graph::Pose2>, OnlineError> {
        let theta = self.orientations()?.to_vec();
        self.ensure_solver()?;
        match &self.solver {
            Some(solver) => Ok(solver.poses(&self.graph, &theta)?),
            None => Err(OnlineError::Numerical("no solver".into())),
        }
    }

    /// Current orientation of a node (None for an unknown node).
    pub fn orientation(&mut self, node: NodeId) -> Result<Option<f64>, OnlineError> {
        let Some(v) = self.graph.node_index(node) else {
            return Ok(None);
        };
        Ok(self.orientations()?.get(v).copied())
    }

    /// Marginal variance of a node's orientation (None for an unknown node).
    pub fn variance(&mut self, node: NodeId) -> Result<Option<f64>, OnlineError> {
        let Some(v) = self.graph.node_index(node) else {
            return Ok(None);
        };
        Ok(Some(self.ensure_solver()?.variance(v)))
    }

    /// Integer-bootstrapping lower bound on the probability that the current γ is right:
    /// the determined cycles' sequential conditional deviations, and each ambiguous cycle's
    /// deviation given the determined set (larger than its sequential one, so the product
    /// stays a lower bound).
    pub fn success_probability_lower_bound(&self) -> f64 {
        let sds = self.screener.cond.conditional_sds().iter().copied();
        let amb = self.ambiguous.values().map(Moments::sd);
        sds.chain(amb)
            .map(|s| rounding_success(s).ln())
            .sum::<f64>()
            .exp()
    }

    /// Run the fixed-point first screening and the second screening on the current state
    /// (the batch pipeline's code) without changing the estimator, and return the same kind of
    /// result as [`batch::screen`].
    pub fn finish(&self) -> Result<BatchResult, OnlineError> {
        let basis = CycleBasis {
            kind: BasisKind::Incremental,
            cycles: self.cycles.clone(),
        };
        let screened = batch::run_screening(
            &self.model,
            self.screener.clone(),
            &self.config.screening,
            &|t| self.config.screening.online_quantile(t),
            &basis,
        )
        .map_err(|e| OnlineError::Numerical(e.to_string()))?;
        let solver = basis
            .wrap_solver(self.graph.edge_count())
            .map_err(|e| OnlineError::Numerical(e.to_string()))?;
        Ok(BatchResult {
            edges: self.graph.edge_count(),
            basis,
            model: self.model.clone(),
            screened,
            solver,
            fallback: None,
            basis_seconds: 0.0,
            screening_seconds: 0.0,
        })
    }

    /// The surviving hypotheses of the current ambiguous set (second screening), best first.
    pub fn hypotheses(&self) -> Result<Vec<Hypothesis>, OnlineError> {
        Ok(self.finish()?.screened.hypotheses)
    }
}

fn edges_of(c: &Cycle) -> Vec<usize> {
    c.terms.iter().map(|t| t.edge as usize).collect()
}
