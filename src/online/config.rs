//! Settings of the online estimator ([`OnlineConfig`]) and why it refuses an input or a query
//! ([`OnlineError`]); a refused edge leaves the estimator unchanged.

use serde::Serialize;

#[cfg(doc)]
use super::OnlineEstimator;

use crate::estimate::EstimateError;
use crate::gamma::SingularError;
use crate::graph::{GraphError, NodeId};
use crate::screening::{ConfigError, ScreeningConfig};
use crate::wraps::WrapError;

/// Settings of the online estimator (deserialised fields left out take their defaults).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, serde::Deserialize)]
#[serde(default)]
pub struct OnlineConfig {
    /// Screening settings (α, degrees of freedom, family-wise, hypothesis cap). Family-wise,
    /// cycle t is tested at [`ScreeningConfig::online_level`]`(t)` (α-spending).
    pub screening: ScreeningConfig,
    /// Quarantine a loop closure whose cycle fails its angle or translation test when it
    /// arrives (module docs). On by default; off, every edge is added (the cycle is then
    /// kept ambiguous with its two nearest integers) and no translation test is run.
    pub quarantine: bool,
    /// With quarantine and the family-wise setting: also evict accepted loop closures that the
    /// cycles failing through them incriminate (the path-triggered examination, module docs),
    /// rebuilding the estimator by a replay without them. On by default: on INTEL with 100
    /// random false loop closures (3 seeds) it took the quarantined set's precision from 0.82
    /// to 1.00. The replay runs beside the live estimator and is swapped in 32 arrivals (or an
    /// eighth of those it replays) after the eviction (module `online::rebuild`); clean data
    /// never pays for it.
    pub evict: bool,
    /// The caller reads the estimate after every step, as a robot does (on by default): the
    /// estimate's factor is then brought up to date inside each step, and while no cycle is
    /// ambiguous the screening takes a new cycle's moments from it instead of from P_UU
    /// (module `online::predict`). Off, for a caller that reads rarely or never (the
    /// screening alone, a replay that checks decisions): the estimate's changes wait until
    /// it is read (then applied at once, the same answers) and every cycle is conditioned
    /// through P_UU, 2–3× cheaper per step when nothing is read (`so2lin stream FILE --json
    /// --estimate none`, robot order, 2026-12-03: M3500 0.027 s of steps against 0.092 s,
    /// city10000 0.73 s against 1.30 s). The decisions are the same either way; the cycles'
    /// moments agree to about 1e-12, not bit for bit, so a log replays with the setting it
    /// was recorded with.
    pub estimate_every_step: bool,
    /// How long a renewal of the estimate's factor (a fresh order, built beside the live
    /// factor on another thread) is built before it is swapped in, as a multiple of the
    /// default (1.0): the live factor's work it waits for. The default suits edges fed back to
    /// back (a file streamed as fast as the steps go), where a build spans hundreds of steps and
    /// sooner would make steps wait for the builder. A front end that sends edges at its
    /// sensors' rate leaves the builder time between them: a smaller value swaps fresher
    /// factors in, whose loop closures cost less. Measured (`so2lin stream M3500.g2o --json
    /// --rate 1000`, robot order, the newest pose read after every step, three runs each,
    /// 2026-12-05): 1/6 took the p99 from 403–433 to 312–360 µs and the estimate's work from
    /// 33.5 M to 21.1 M values, with no step waiting (worst step 1.0–2.7 ms against 1.0–1.1);
    /// back to back, every collection waited and the worst step reached 2.3 ms (delays of 1/2
    /// and 1/3 waited as well: `benches/MEASUREMENTS.md`, twenty-fourth session). Counted in
    /// work, not time, so the answers do not depend on the threads' timing; a log replays with
    /// the value it was recorded with. Finite and positive.
    pub renewal_delay: f64,
}

impl Default for OnlineConfig {
    /// The default screening, quarantine on, evictions on, the estimate read every step.
    fn default() -> Self {
        Self {
            screening: ScreeningConfig::default(),
            quarantine: true,
            evict: true,
            estimate_every_step: true,
            renewal_delay: 1.0,
        }
    }
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
    /// [`OnlineEstimator::reserve`]: the allocator refused the room asked for (nothing else
    /// changed; the estimator works on without it).
    #[error("cannot reserve room for {nodes} nodes and {edges} edges: the allocator refused")]
    Reserve {
        /// Nodes asked for.
        nodes: usize,
        /// Edges asked for.
        edges: usize,
    },
    /// Bad settings.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// [`OnlineConfig::renewal_delay`] is not a finite positive number.
    #[error("renewal_delay must be a finite number > 0 (got {0})")]
    RenewalDelay(f64),
    /// [`OnlineEstimator::poses`]: the exact positions' linear system (the 2×2-block system
    /// of anisotropic translation information) could not be factored or solved.
    #[error("poses: {0}")]
    Poses(#[from] EstimateError),
    /// [`OnlineEstimator::finish`]: P_γ is numerically singular at the named cycle (the
    /// second screening's conditioning).
    #[error("finish: {0}")]
    Singular(#[from] SingularError),
    /// [`OnlineEstimator::finish`]: the wraps of the named cycle could not be computed from
    /// the basis.
    #[error("finish: {0}")]
    Wraps(#[from] WrapError),
    /// A loop closure between two nodes of one component found no path between them in the
    /// basis graph (an internal inconsistency; the edge is refused, nothing changes).
    #[error("loop closure {from} → {to}: no path between its nodes in the basis graph")]
    NoCycle {
        /// The edge's first node.
        from: NodeId,
        /// The edge's second node.
        to: NodeId,
    },
}
