//! What the online estimator answers between steps: the graph and its quarantine, the noise
//! scales, the cycles and their integers γ, the wraps, and the estimate. The estimate is read
//! from the maintained square-root factors `R x = d` without factoring anything: one node's
//! value by back-substitution along its elimination-tree path (`x_n = d_n / R_nn` for the
//! newest node, last in the order), every node's by one back-substitution, a node's marginal
//! covariance by one forward solve (`Var(aᵀx) = ‖R⁻ᵀa‖²`); [`OnlineEstimator::finish`] runs the
//! batch pipeline's screenings on the current state.

use super::{Counters, NoiseScales, OnlineError, OnlineEstimator, predict};
use crate::batch::{self, BatchResult, RejectedEdge};
use crate::closure;
use crate::cycles::{BasisKind, Cycle, CycleBasis};
use crate::gamma::Moments;
use crate::graph::{NodeId, Pose2, PoseGraph};
use crate::screening::{Hypothesis, rounding_success};

impl OnlineEstimator {
    /// Counters of the run so far. Those of the estimate's factor (renewals, the steps that
    /// waited for one, re-linearisations, renewals in idle time) are read as they are now, so
    /// after a step's read ([`Self::newest`], [`Self::pose`], ...) they include what that read
    /// applied; the others are those of the last [`Self::add_edge`].
    pub fn counters(&self) -> Counters {
        let mut counters = self.counters;
        self.estimate_counters(&mut counters);
        counters
    }

    /// The graph so far: the accepted edges, in the order they were added (quarantined loop
    /// closures are not in it; a re-admitted one is added when it is re-admitted).
    /// [`Self::input_index`] maps its edges to input order.
    pub fn graph(&self) -> &PoseGraph {
        &self.graph
    }

    /// The input index (0-based, in order of arrival) of edge `e` of [`Self::graph`]; the
    /// identity while nothing was quarantined.
    pub fn input_index(&self, e: usize) -> Option<usize> {
        self.input_of.get(e).map(|&i| i as usize)
    }

    /// Number of edges given so far, accepted or quarantined.
    pub fn arrivals(&self) -> usize {
        self.arrivals
    }

    /// A rebuild in progress (module `online::rebuild`): the arrival count after which the
    /// rebuilt estimator is swapped in, and the input indices of the accepted loop closures
    /// it evicts, ascending — still in the graph and in every answer until then (or until
    /// [`Self::settle`]); none for the warm-up replay, which re-tests the stream so far at its
    /// noise scales. None when no rebuild is in progress.
    pub fn evicting(&self) -> Option<(usize, Vec<usize>)> {
        let (at, mut evicted) = self.rebuilding.as_ref()?.evicting();
        // (Not those of its place already held: they stay held through the rebuild.)
        evicted.retain(|i| !self.held.contains_key(i));
        Some((at, evicted))
    }

    /// The loop closures in quarantine now, by input index: each with the test it failed, its
    /// statistic and the threshold it exceeded (at its last test). An eviction in progress
    /// ([`Self::evicting`]) adds its edges when its rebuild is swapped in.
    pub fn rejected(&self) -> Vec<RejectedEdge> {
        self.held.values().map(|h| h.rejected).collect()
    }

    /// The noise scale s of the translation closures ([`closure::Scale`]): a closure's χ²₂
    /// is tested as `χ²₂ / s`.
    pub fn translation_scale(&self) -> f64 {
        match self.warm {
            Some((t, _)) if self.scale.len() < closure::SCALE_MIN_CYCLES => t,
            _ => self.scale.value(),
        }
    }

    /// Both noise scales with the number of samples each was estimated from.
    pub fn noise_scales(&self) -> NoiseScales {
        NoiseScales {
            angle: self.angle_scale(),
            angle_samples: self.angle_scale.len(),
            translation: self.translation_scale(),
            translation_samples: self.scale.len(),
        }
    }

    /// The angle noise scale s_θ ([`closure::Scale::angle`]): the quarantine's angle test and
    /// the translation closures' heading noise use the declared angle variances times s_θ.
    pub fn angle_scale(&self) -> f64 {
        match self.warm {
            Some((_, a)) if self.angle_scale.len() < closure::SCALE_MIN_CYCLES => a,
            _ => self.angle_scale.value(),
        }
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
        (0..self.model.len()).map(|i| self.best_gamma(i)).collect()
    }

    /// Current best wraps k of every edge of [`Self::graph`] (zero on tree edges; quarantined
    /// loop closures are not in it): `C k = γ` for [`Self::gamma`].
    pub fn wraps(&self) -> Result<Vec<i64>, OnlineError> {
        Ok(self.wrap.clone())
    }

    /// Current orientations of all nodes (dense index order; anchors 0; unwrapped): one
    /// back-substitution in the maintained factor (no factorisation).
    pub fn orientations(&mut self) -> Result<&[f64], OnlineError> {
        self.theta = self.estimate.orientations(&self.graph);
        self.refresh_counters();
        Ok(&self.theta)
    }

    /// Current poses of all nodes (dense index order), **exact**: the current orientations
    /// with their least-squares positions (anchors at the origin), as
    /// [`OrientationEstimator::poses`](crate::estimate::OrientationEstimator::poses) would
    /// give. With isotropic translation information (most SLAM data) every position row is
    /// taken at the current headings in the maintained factor — one forward and one
    /// back-substitution, no factorisation, the factor left as it was; otherwise the
    /// 2×2-block system is solved from scratch.
    pub fn poses(&mut self) -> Result<Vec<Pose2>, OnlineError> {
        let poses = self.estimate.poses(&self.graph)?;
        self.refresh_counters();
        Ok(poses)
    }

    /// Current orientation of a node (None for an unknown node): back-substitution along the
    /// node's path in the factor (O(1) for the newest node).
    pub fn orientation(&mut self, node: NodeId) -> Result<Option<f64>, OnlineError> {
        let Some(v) = self.graph.node_index(node) else {
            return Ok(None);
        };
        Ok(Some(self.estimate.orientation(&self.graph, v)))
    }

    /// Current pose of a node (None for an unknown node), read from the maintained factors
    /// along the node's path (O(1) for the newest node). The heading is exact. The position
    /// rows use the tail's heading **as estimated when the edge arrived** (all of them are
    /// re-linearised at the then current headings whenever a renewal of the position factor
    /// starts, and used from its swap on),
    /// and the isotropic part of the translation information: like iSAM2 with a
    /// re-linearisation threshold, the fast answer lags heading corrections that loop closures
    /// make to old nodes; [`Self::poses`] is the exact answer on demand.
    pub fn pose(&mut self, node: NodeId) -> Result<Option<Pose2>, OnlineError> {
        let Some(v) = self.graph.node_index(node) else {
            return Ok(None);
        };
        Ok(Some(self.estimate.pose(&self.graph, v)))
    }

    /// The newest node (the last one an edge created) and its pose ([`Self::pose`]).
    pub fn newest(&mut self) -> Result<Option<(NodeId, Pose2)>, OnlineError> {
        let Some(node) = self.graph.nodes().last().map(|n| n.id) else {
            return Ok(None);
        };
        Ok(self.pose(node)?.map(|p| (node, p)))
    }

    /// All poses as `(node id, pose)` pairs, exact ([`Self::poses`]).
    pub fn poses_by_id(&mut self) -> Result<Vec<(NodeId, Pose2)>, OnlineError> {
        let poses = self.poses()?;
        Ok(self.graph.nodes().iter().map(|n| n.id).zip(poses).collect())
    }

    /// Marginal variance of a node's orientation relative to its component's anchor (None
    /// for an unknown node): one forward solve in the maintained factor.
    pub fn variance(&mut self, node: NodeId) -> Result<Option<f64>, OnlineError> {
        let Some(v) = self.graph.node_index(node) else {
            return Ok(None);
        };
        Ok(Some(self.estimate.orientation_variance(&self.graph, v)))
    }

    /// Marginal covariance of a node's pose `(x, y, θ)` relative to its component's anchor,
    /// from the maintained factors (None for an unknown node). The positions are conditioned
    /// on the headings (the linear estimate's model), so the covariance is block-diagonal: the
    /// position block `σ²_p I` from the position factor (isotropic weights), `σ²_θ` from the
    /// orientation factor.
    pub fn covariance(&mut self, node: NodeId) -> Result<Option<[[f64; 3]; 3]>, OnlineError> {
        let Some(v) = self.graph.node_index(node) else {
            return Ok(None);
        };
        let p = self.estimate.position_variance(&self.graph, v);
        let t = self.estimate.orientation_variance(&self.graph, v);
        Ok(Some([[p, 0.0, 0.0], [0.0, p, 0.0], [0.0, 0.0, t]]))
    }

    /// Integer-bootstrapping lower bound on the probability that the current γ is right:
    /// the determined cycles' sequential conditional deviations, and each ambiguous cycle's
    /// deviation given the determined set (larger than its sequential one, so the product
    /// stays a lower bound).
    pub fn success_probability_lower_bound(&self) -> f64 {
        let sds = self.screener.cond.conditional_sds().iter().copied();
        let backlog = self.backlog.iter().map(|&(_, _, sd)| sd);
        let amb = self.ambiguous.values().map(Moments::sd);
        sds.chain(backlog)
            .chain(amb)
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
        let mut screener = self.screener.clone();
        // No bound on the appends: this is no step a robot waits for.
        if let Some(fresh) =
            predict::with_backlog(&mut screener, &self.model, &self.backlog, f64::INFINITY)
        {
            screener.cond = fresh;
        }
        let screened = batch::run_screening(
            &self.model,
            screener,
            &self.config.screening,
            &|t| self.config.screening.online_quantile(t),
            &basis,
        )?;
        let solver = basis.wrap_solver(self.graph.edge_count())?;
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
