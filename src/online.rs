//! The online estimator (method [§7](crate::method#7-online-estimation), [§10](crate::method#10-the-estimate-online)): tree, cycle basis, γ model and screening grown one
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
//! A single candidate determines the cycle (a row is appended to L). While no cycle is
//! ambiguous the same moments come from the estimate's factor instead (module `predict`):
//! rotating the new loop closure's heading row into it leaves the loop closure's prediction
//! error and its variance, the row is kept when the cycle is determined, and L receives the
//! cycles determined that way only when it is next used. When a cycle is
//! determined, the ambiguous cycles that share information with it directly — a nonzero
//! `(P_γ)_ij`, i.e. a common edge — are re-screened with fresh conditional moments, and a
//! re-screen that leaves one candidate determines that cycle too (and so on). Ambiguous cycles
//! correlated only indirectly are left as they are until a neighbour is determined (their
//! stored moments are then conditioned on fewer cycles: wider, never overconfident), which
//! keeps a step's cost local; `finish` re-screens every one of them exactly. [`OnlineEstimator::finish`] runs the batch
//! pipeline's fixed-point first screening and second screening on the current state — the
//! same [`Screener`] code.
//!
//! **Quarantine** (on by default, [`OnlineConfig::quarantine`]; method
//! [§11](crate::method#11-false-loop-closures)): a loop closure is tested *before* it is added.
//! Its cycle is found by [`IncrementalBasis::probe`] and tested twice at the cycle's level α_t:
//! the SE(2) translation closure ([`crate::closure`], at both ends of the chord, the larger
//! `χ²_t / s > −4 ln(α_t/2)`, s the noise scale
//! estimated from the accepted cycles, [`closure::Scale`]; the edges' angle variances times the
//! angle noise scale s_θ) and the angle: the distance r of γ's conditional mean to the nearest
//! integer, in conditional sd, fails when `r / √s_θ > q_t` (with s_θ = 1: the screening's
//! interval holding no integer). s_θ is estimated like s ([`closure::Scale::angle`]) from `r²`
//! of the accepted cycles whose conditional sd is below 0.1 (their nearest integer is their
//! value). The scales calibrate the quarantine's tests only: the screening that determines γ
//! keeps the declared noise, so the integer guarantee is untouched. A scale above 1 (the
//! declared noise too tight, as the median of the accepted cycles shows) widens the tests: a
//! cycle whose interval holds no integer in the declared noise but passes in the noise the data
//! show is accepted (inconsistent, as with quarantine off), its loop closure kept. A loop closure failing either is
//! **quarantined**: never added to the graph, the basis (no later cycle is routed through it),
//! the γ model, the conditioning or the estimate; it is kept with its test, statistic and
//! threshold ([`OnlineEstimator::rejected`], [`Step::quarantined`]). On data that follow the
//! declared noise, the angle tests spend α/2 (the α-spending sequence) and the translation tests
//! another α/2 at the same levels (with the margin of [`crate::closure`], checked empirically),
//! so the probability that any genuine edge is quarantined is ≤ α (the scales, estimated from
//! the data's tails, keep this empirically: `tests/statistics.rs`).
//!
//! **Evictions** ([`OnlineConfig::evict`], on by default; family-wise setting only): before 50
//! cycles no scale is estimated (s = s_θ = 1, the declared noise), and a false loop closure
//! closing a long cycle can pass its tests at any time (a long cycle's covariance hides it);
//! once in, the genuine loop closures after it are routed through it and fail.
//! **Path-triggered examination**: each failed cycle (failing at the family-wise level) counts
//! against the accepted loop closures on its path; at 3 failures (then 6, 12, …) such an edge
//! e is examined. It is **evicted** when its own cycle on the least-σ² path avoiding it (the
//! graph has grown since e was accepted: the path may be shorter, the test sharper) fails at
//! the family-wise level of its cycle, or when one of the last 4 loop closures that failed
//! through e passes (at the per-cycle level α) on the path avoiding e and that cycle is
//! doubtful (beyond the per-cycle threshold), or when two of them pass — each on a path at
//! most 4 times as long (`Σ σ²`) as e's own, the loop e closes (a longer path passes only
//! because its covariance is wider, and the search for it crosses the map); a loop closure
//! whose failed cycle's path through e was already longer than that is not asked (its loop is
//! not e's: on M3500 + 1000 false edges 94 % of the queries were such, and none of them
//! incriminated a false edge). "Avoiding e" avoids e's place too: the accepted loop closures
//! whose two ends are each within 10 node indices of e's (a clustered group of false edges
//! sharing one measurement holds itself up otherwise: M3500 + 1000 clustered seed 4 held 107
//! genuine loop closures behind a pair of them; module `evict`), and an eviction keeps the
//! quarantined loop closures of e's place out through its replay. The second clause is
//! for a false edge whose own cycle has no power (the path avoiding it is long, its covariance
//! wide): on M3500 + 1000 false edges, seeds 4 and 5, six such edges stayed in and 250 and 125
//! genuine loop closures were quarantined through them (precision 0.80, 0.89). A third clause,
//! **outvoted**: two of those loop closures, each a sharper test than e's own cycle (its failed
//! path through e shorter than e's own), agree with each other on the cycle they close together
//! through paths avoiding e's place — the loop closures of a return to a place agree among
//! themselves even when every path between the places runs through one false edge or another —
//! unless the two stretches of odometry joining them have the same length (members of a
//! clustered group share one measurement and agree as true loop closures do; module `evict`).
//! On M3500 + 1000 false edges, random seeds 1–80, it took the genuine loop closures held at the
//! end from 372 to 160 and the runs below 0.95 precision from 3 to 1; clustered seeds 1–40,
//! 30 → 31 and none. An eviction
//! quarantines e and **rebuilds** the estimator by replaying the arrivals in input order
//! without it (the current scales standing in for the replay's own until it has 50 cycles):
//! from the start at the first rebuild, O(m) for that one step, and from then on from the
//! latest checkpoint before e's arrival (module `checkpoint`: a copy of the state kept every
//! quarter of the arrivals, and one just before a doubtful loop closure — a long cycle, or a
//! translation statistic above half its threshold — is accepted; a stream that has
//! quarantined something is rebuilt from the start once, early, as soon as its translation closures give a noise scale, so that its first
//! cycles are re-tested at it); none of this on clean data (no clean benchmark file of
//! ≤ 25 000 edges quarantines or evicts anything). The replay reuses what it can: a quarantined loop closure arriving again takes
//! the cycle it failed on before while the replay's graph is a subgraph of the replaced one's
//! (module `replay`: no search across the map), and the estimate's factors are built once at
//! the replay's end instead of through every replayed step (M3500 + 1000 false edges, the
//! newest pose read after every step: worst step, a replay, 120–168 ms before both, 39–49 ms
//! after) — since 2026-12-06 derived from the replaced estimator's factors, which differ from
//! them in a few rows (module `online/estimate.rs`). Since 2026-12-06 the rebuild is made **beside
//! the live estimator** (module `rebuild`): the eviction's step hands the replay to a builder
//! thread and goes on; every later arrival goes to the builder too, and the rebuilt estimator, its
//! estimate's factors built by the builder, is swapped in 32 arrivals later (or an eighth of the
//! arrivals it replays, if more: a count, so the run does not depend on the threads' timing) —
//! until then the answers, and [`OnlineEstimator::rejected`], are those of the live estimator,
//! which still holds the evicted edges ([`OnlineEstimator::evicting`] names them), and
//! [`OnlineEstimator::settle`] swaps a rebuild in progress in at once and examines the suspects
//! still due (a stream's end). The
//! warm-up replay (above) is made the same way, and kept only if it changed a loop closure's
//! state. On M3500 with 1 000 false loop closures at 1 000 edges a second no step waits for the
//! rebuild; back to back, or when the replays are long (a 100 000-pose world with 500 false loop
//! closures, whose late evictions replay 20 000–167 000 arrivals: one swap of 25 for 3.4 s at
//! 200 edges a second in one of two runs), the swap's step waits for what the builder has left
//! (module `rebuild`). An evicted edge is re-tested like a
//! quarantined one, counting from its eviction, and later replays keep it in quarantine until then
//! (re-tested at its arrival, it would pass as it first did and be accepted again). At the step
//! that swaps a rebuild in, [`Step::quarantined`] lists the evicted edges (and any other edge the
//! rebuild quarantined), [`Step::readmitted`] the held edges the rebuild accepted, and the step's
//! `kind` and `rescreened` describe the live estimator's step (cycle ids may have changed). An
//! earlier audit that re-tested every accepted cycle at each doubling of the cycle count evicted
//! genuine loop closures of the clean CSAIL and
//! ais2klinik files and was removed.
//!
//! **Re-admission**: a quarantined loop closure is re-tested, through the same path a new
//! loop closure takes (a new probe, so a shorter path that appeared since is used), when the
//! number of cycles has doubled since its last test (and grown by at least 32), or grown
//! eightfold when it failed by far (χ² above 8× the threshold: a random false edge, whose
//! re-tests cost a search of the graph each): O(log ℓ) tests
//! per edge, at most one a step (the earliest due first; a re-admission closes a cycle, which
//! may bring other dates, and a thousand re-tests in one step would stall the robot). The
//! re-test is at the per-cycle level α, not the family-wise α_t — stricter, so a false edge rarely slips in by being tried again, while a genuine edge quarantined by a path
//! through an accepted false edge that has since been bypassed passes. One exception: when the
//! failed test's noise scale has risen above 1 (and above its value at the failure) since, the
//! data have shown the declared noise too tight, and the edge is re-tested at the level it
//! failed at, in the noise they show (manhattan.g2o: two loop closures failed at 74 and 277
//! cycles, before its angle scale of 1.29 was established; at the per-cycle level they stayed
//! out for good). Re-testing every edge at its arrival's level let a false edge of a simulated
//! world back in (`tests/quarantine.rs`). A re-admitted edge is added as a new edge is ([`Step::readmitted`]);
//! [`OnlineEstimator::graph`] holds the accepted edges in the order they were added and
//! [`OnlineEstimator::input_index`] maps them to input order. With quarantine off no
//! translation test is run and every edge is added (an inconsistent cycle is kept ambiguous).
//!
//! **The estimate** (modules `online/estimate.rs`, `online/laplacian.rs`): orientations and positions are kept as sparse
//! square-root information factors grown by the same events as the basis — a new node (appended
//! last, so the newest node is read in O(1)), a new edge (Givens rotations along the elimination
//! tree path of its older end), a chord whose wrap moved after a re-screen (right-hand side
//! only), two components joined (the later anchor's prior row down-dated). Between
//! determinations the ambiguous cycles' chords use their most likely integer (the rounded
//! conditional mean, clamped to the candidates); the wraps follow γ by forward substitution
//! (`k_chord = γ_t − Σ_rest ±k_e`), re-done only for the cycles a step changed and the later
//! cycles through a chord whose wrap moved. Reads never factor: [`OnlineEstimator::newest`]
//! and [`OnlineEstimator::orientation`] back-substitute along one path,
//! [`OnlineEstimator::orientations`] and [`OnlineEstimator::poses`] over the whole factor.
//!
//! **No stalls**: the estimate's factors, and the factor of P_UU (when it grows: module
//! `predict`) once its rebuild is expected to cost more than about 1.5 ms, are renewed in a
//! fill-reducing order on a worker thread, which is sent every later change and applies it
//! itself; the new factor is collected once the live factor has done as much work (entries
//! of the factor visited, counted) as the builder is expected to need, and swapped in
//! (`online/renewal.rs`), so no step replays a large factor, and results do not depend on the
//! threads' timing. A step rebuilds P_UU's factor itself when the rebuild is small (counted
//! work, about 1.5 ms or less on the development machine: a builder beside the steps costs
//! them more than that there, `online/reorder.rs`), or when the screening returns to it from
//! predictions with a long backlog (module `predict`). Nor does a step copy a growing array
//! when the caller reserved room for the stream ([`OnlineEstimator::reserve`]).
//!
//! **The allocator matters.** The worker frees memory the robot's thread allocated (the
//! snapshot a renewal starts from, retired factors), and the robot's thread grows and frees
//! rows the worker allocated. With glibc's malloc both then take the same arena locks: on
//! M3500 (`so2lin stream`, robot order) the robot's thread slept on them about 70 times a
//! stream, and the worker was off its core for most of a build's wall time, so collections
//! waited for it. A program embedding the estimator should use a thread-caching allocator that
//! frees another thread's memory without a lock, as the `so2lin` tool does (mimalloc, without
//! transparent huge pages, whose first touch zeroes 2 MiB inside a step: 5–6 ms on the
//! development VM). With it, M3500's steps took 0.059 s in all against 0.072 s, and its worst step
//! 2.2 ms against 5.6 ms (medians of eight alternating runs of `so2lin stream`, robot order).
//!
//! **Idle time** ([`OnlineEstimator::maintain`]): a caller with time between steps (a robot
//! waiting for its next sensor reading) lets the estimator renew the estimate's factor then, on
//! its own thread, as soon as [`MAINTAIN_APPENDED`] nodes were appended since the factor's
//! order was made. A renewal beside the steps is collected only after the live factor has done
//! a build's worth of work, with the nodes appended meanwhile at the end of its order, which
//! every loop closure to an older node walks; renewed between steps the factor is fresh when
//! the next step arrives. The steps then do a half to a quarter of the work. In between it
//! re-linearises the position rows before a step would have to.

use smallvec::SmallVec;

mod checkpoint;
mod chord;
mod config;
mod estimate;
mod evict;
mod laplacian;
mod order;
mod predict;
mod quarantine;
mod read;
mod rebuild;
mod renewal;
mod reorder;
mod replay;
mod snapshot;
mod step;

pub use config::{OnlineConfig, OnlineError};
pub use order::{robot_order, robot_order_indices};
pub use step::{Counters, CycleStep, Decision, Maintenance, NoiseScales, Rescreen, Step, StepKind};

/// Nodes appended to the estimate's factor since its order was made from which
/// [`OnlineEstimator::maintain`] renews it (or the graph's nodes over [`MAINTAIN_FRACTION`],
/// if more). Measured (`so2lin stream FILE --json --maintain`, robot order, the newest pose
/// read after every step, back to back, 2026-12-05, before the maintenance re-linearised
/// between renewals): every 24, 48 or 96 nodes, M3500's p99
/// was 53–64, 62–66 and 90–103 µs (worst step 0.32–0.47, 0.35–0.48 and 0.67–1.19 ms) for
/// 0.21–0.24, 0.11 and 0.05–0.06 s of maintenance (three runs each); city10000's 81–86, 72–80
/// and 85–105 µs (worst 0.69–0.83, 0.70–0.77 and 1.78–2.23 ms) for 2.1–2.2, 1.1 and 0.5–0.6 s
/// (two).
pub const MAINTAIN_APPENDED: usize = 48;

/// On large graphs [`OnlineEstimator::maintain`] renews once the nodes appended since the
/// factor's order was made are this fraction of all of them: a build costs about a
/// microsecond per node or more, and the steps gain no more from renewing sooner. Measured on
/// a 30 000-pose simulated world (`so2lin simulate --poses 30000`, as [`MAINTAIN_APPENDED`]):
/// every 48 nodes p99 338 µs and 13.7 s of maintenance, from n/256 329 µs and 8.2 s, from
/// n/128 329 µs and 4.4 s, the worst step 6.9–7.0 ms in all three (one run each; without
/// maintenance 1.37 ms and 11.7 ms); city10000 from n/128 71–72 µs against 71–73 every 48
/// nodes, worst 0.69–0.79 against 0.66 ms (two runs each).
pub const MAINTAIN_FRACTION: usize = 128;

use estimate::{Estimate, Op};
use evict::Suspect;
use quarantine::Held;
use reorder::CondRenewal;

use crate::cycles::{Cycle, IncrementalBasis};
use std::collections::{BTreeMap, BTreeSet};

use crate::closure;
use crate::gamma::{GammaModel, Moments};
use crate::graph::{Edge, Information, NodeId, NodePolicy, Pose2, PoseGraph};
use crate::screening::Screener;

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
    /// What the translation closures read of each edge of the graph.
    noise: Vec<Option<closure::EdgeNoise>>,
    basis: IncrementalBasis,
    cycles: Vec<Cycle>,
    model: GammaModel,
    screener: Screener,
    /// Ambiguous cycles with their conditional moments at their last screening.
    ambiguous: BTreeMap<usize, Moments>,
    /// The counts as of the last step; those of the estimate's factor are not kept here but
    /// read from it ([`Self::estimate_counters`]).
    counters: Counters,
    /// The factored orientations and positions (the estimate read after every step).
    estimate: Estimate,
    /// Current best γ of every cycle ([`Self::gamma`]), kept up to date step by step.
    gamma: Vec<i64>,
    /// Current wraps of every edge (forward substitution of `gamma` over the cycles).
    wrap: Vec<i64>,
    /// The cycle each edge closed (NONE for tree edges).
    chord_cycle: Vec<u32>,
    /// For each chord, the later cycles through it (their wraps depend on its wrap).
    users: Vec<SmallVec<[u32; 2]>>,
    /// Scratch for [`Self::orientations`].
    theta: Vec<f64>,
    /// Nonzeros per row of L right after the last reordering.
    fill_after_reorder: f64,
    /// A renewal of L in progress.
    renewal: Option<CondRenewal>,
    /// The thread that builds renewals of L and frees retired ones.
    worker: renewal::Worker,
    /// Steps that waited for a renewal of L.
    cond_waits: usize,
    /// Steps that waited for a rebuild's builder ([`Counters::rebuild_waits`]), over the
    /// estimators this one replaced.
    rebuild_waits: usize,
    /// The live P_UU factor's work so far ([`crate::gamma::Conditioner::take_work`]).
    cond_work: u64,
    /// The last renewal builder's work per determined cycle (the same units; 0 before one).
    rebuild_work_per_row: f64,
    /// Edges given so far (accepted or quarantined): the next input index.
    arrivals: usize,
    /// Input index of each edge of the graph.
    input_of: Vec<u32>,
    /// When each input entered the graph, and the cycles quarantined loop closures failed
    /// on at their arrival: what a replay of this estimator reuses ([`replay`]).
    paths: replay::Paths,
    /// Within a replay: the replaced estimator's [`replay::Paths`].
    hints: Option<replay::Hints>,
    /// Whether a replay of this estimator reuses them (off only to test that it decides as a
    /// replay that searches every cycle again).
    reuse_paths: bool,
    /// Quarantined loop closures by input index.
    held: BTreeMap<usize, Held>,
    /// Their re-test schedule: (cycle count at which to re-test, input index).
    due: BTreeSet<(usize, usize)>,
    /// The translation closures' noise scale, from the accepted cycles.
    scale: closure::Scale,
    /// The angle noise scale s_θ, from the accepted cycles' angle residuals.
    angle_scale: closure::Scale,
    /// The scales (translation, angle) carried over a rebuild: used while the live ones have
    /// fewer than [`closure::SCALE_MIN_CYCLES`] statistics.
    warm: Option<(f64, f64)>,
    /// Accepted loop closures (graph edge index) on the paths of cycles that failed since
    /// they were last examined: (failures, failures at which to examine them next).
    suspects: BTreeMap<usize, Suspect>,
    /// The suspects whose failures have reached their bar (examined at the end of a step, so
    /// a step does not scan every suspect).
    suspects_due: BTreeSet<usize>,
    /// Arrivals replayed by rebuilds so far (each replays the arrivals since its checkpoint):
    /// kept within [`evict::REPLAY_BUDGET`] times the arrivals.
    replay_work: usize,
    /// Set while the estimator is being rebuilt by a replay: no examination (no
    /// nested rebuild); the suspects it counts are examined once, by the builder a few
    /// arrivals before the swap ([`rebuild`], "the examination before a swap"), or by the
    /// step after the swap (a replay in the step).
    replaying: bool,
    /// Whether new cycles are screened with the estimate's prediction when it holds exactly
    /// the determined cycles' information ([`OnlineConfig::estimate_every_step`]).
    predicts: bool,
    /// Cycles determined from the estimate's prediction and not yet appended to the P_UU
    /// factor, in the order determined: (cycle, value, conditional sd of γ).
    backlog: Vec<(u32, i64, f64)>,
    /// New cycles screened by prediction so far.
    predicted: usize,
    /// Copies of the screening state an eviction's replay may start from
    /// ([`checkpoint`]), oldest first.
    checkpoints: Vec<checkpoint::Checkpoint>,
    /// Arrivals between two checkpoints, at least ([`checkpoint::MIN_INTERVAL`]; tests set
    /// it lower to replay from many checkpoints in small worlds).
    checkpoint_interval: usize,
    /// Whether copies are taken before doubtful loop closures
    /// ([`checkpoint::doubtful`]; tests turn them off to compare).
    doubtful_checkpoints: bool,
    /// Renewals of the P_UU factor expected to cost at most this much work are built in the
    /// step ([`reorder::REORDER_IN_STEP_WORK`]; tests set 0 or ∞ to take one path only).
    reorder_in_step_work: f64,
    /// The node and edge counts the caller reserved room up to ([`Self::reserve`]): a
    /// rebuild's replacement gets the same room.
    room_for: (usize, usize),
    /// An eviction's rebuild in progress beside this estimator ([`rebuild`]).
    rebuilding: Option<rebuild::Rebuilding>,
    /// The thread that replays rebuilds ([`rebuild`]).
    replayer: renewal::Worker,
    /// Whether an eviction's rebuild is made beside the live estimator and swapped in later
    /// ([`rebuild`]; off only to test that it decides as a rebuild in the step).
    rebuilds_beside: bool,
    /// Whether a rebuild's replay screens the loop closures it replays with the estimate's
    /// factor when the estimate is read every step ([`rebuild`], "the builder's pace"; off
    /// only to test that it decides as a replay screening through P_UU).
    replays_predict: bool,
    /// Within a rebuild's replay: the arrival count, a few arrivals before the swap, at which
    /// its builder examines the suspects due ([`rebuild`], "the examination before a swap");
    /// None otherwise.
    examine_at: Option<usize>,
    /// The loop closures that examination found to evict, with its scales: evicted by the
    /// step that swaps this estimator in.
    examined: Option<(BTreeMap<usize, Held>, (f64, f64))>,
}

/// Cycles whose conditional sd of γ is below this feed the angle noise scale: their nearest
/// integer is their value (a genuine residual of half a turn would be 5 sd away).
const ANGLE_SCALE_MAX_SD: f64 = 0.1;

/// Name of the angle test in [`RejectedEdge::test`](crate::batch::RejectedEdge::test): the
/// statistic is the residual in σ.
pub const ANGLE_TEST: &str = "cycle_angle";
/// Name of the translation test in [`RejectedEdge::test`](crate::batch::RejectedEdge::test):
/// the statistic is χ²₂.
pub const TRANSLATION_TEST: &str = "cycle_translation";

impl std::fmt::Debug for OnlineEstimator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OnlineEstimator")
            .field("config", &self.config)
            .field("nodes", &self.graph.node_count())
            .field("edges", &self.graph.edge_count())
            .field("counters", &self.counters())
            .finish_non_exhaustive()
    }
}

impl OnlineEstimator {
    /// A new estimator with no nodes.
    pub fn new(config: OnlineConfig) -> Result<Self, OnlineError> {
        config.screening.validate()?;
        let delay = config.renewal_delay;
        if !(delay.is_finite() && delay > 0.0) {
            return Err(OnlineError::RenewalDelay(delay));
        }
        Ok(Self {
            config,
            graph: PoseGraph::new(),
            sigma2: Vec::new(),
            delta: Vec::new(),
            noise: Vec::new(),
            basis: IncrementalBasis::new(),
            cycles: Vec::new(),
            model: GammaModel::new(),
            screener: Screener::new(),
            ambiguous: BTreeMap::new(),
            counters: Counters::default(),
            estimate: Estimate::new(config.renewal_delay),
            gamma: Vec::new(),
            wrap: Vec::new(),
            chord_cycle: Vec::new(),
            users: Vec::new(),
            theta: Vec::new(),
            fill_after_reorder: f64::INFINITY,
            renewal: None,
            worker: renewal::Worker::default(),
            cond_waits: 0,
            rebuild_waits: 0,
            cond_work: 0,
            rebuild_work_per_row: 0.0,
            arrivals: 0,
            input_of: Vec::new(),
            paths: replay::Paths::default(),
            hints: None,
            reuse_paths: true,
            held: BTreeMap::new(),
            due: BTreeSet::new(),
            scale: closure::Scale::default(),
            angle_scale: closure::Scale::angle(),
            warm: None,
            suspects: BTreeMap::new(),
            suspects_due: BTreeSet::new(),
            replay_work: 0,
            replaying: false,
            predicts: config.estimate_every_step,
            backlog: Vec::new(),
            predicted: 0,
            checkpoints: Vec::new(),
            checkpoint_interval: checkpoint::MIN_INTERVAL,
            doubtful_checkpoints: true,
            reorder_in_step_work: reorder::REORDER_IN_STEP_WORK,
            room_for: (0, 0),
            rebuilding: None,
            replayer: renewal::Worker::default(),
            rebuilds_beside: true,
            replays_predict: true,
            examine_at: None,
            examined: None,
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

    /// Make room for `nodes` more nodes and `edges` more edges, so that the estimator's arrays
    /// do not grow while they arrive. An array that grows is copied, in one step, into memory
    /// the system has not handed out yet (each page's first touch a fault): the arrays indexed
    /// by edge double together, at edge 1 025, 2 049, 4 097, … Measured (`so2lin stream FILE`
    /// with and without `--no-reserve`, robot order, the newest pose read after every step,
    /// three runs each, 2026-12-05): M3500's 4 097th step took 0.51–0.82 ms without room and
    /// 6–13 µs with it, its 1 025th 0.15–0.20 ms against 3–4 µs; city10000's 8 193rd 0.78–0.87
    /// ms against 52–54 µs, its 16 385th 1.9–2.4 ms against 1 µs. A front end that knows its
    /// mission's size (or a bound on it) reserves it once, before the first edge, as a
    /// real-time loop preallocates: the room costs address space, not memory, until edges fill
    /// it (the system maps the pages as they are first written, a few at a step). The answers
    /// are the same bits with or without it, and an estimator that replaces this one in a
    /// rebuild (a replay after an eviction) gets the same room. `so2lin stream` reserves the
    /// file's counts unless `--no-reserve`.
    ///
    /// Errors: [`OnlineError::Capacity`] for more edges than the estimator indexes, and
    /// [`OnlineError::Reserve`] when the allocator refuses the room; either way the estimator
    /// is otherwise unchanged and works on without it.
    pub fn reserve(&mut self, nodes: usize, edges: usize) -> Result<(), OnlineError> {
        if edges > u32::MAX as usize {
            return Err(OnlineError::Capacity(u32::MAX as usize));
        }
        // A connected graph has edges − nodes + 1 cycles; more edges between fewer nodes
        // grow the per-cycle arrays later.
        let cycles = edges.saturating_sub(nodes) + 1;
        let mut room = || -> Result<(), std::collections::TryReserveError> {
            self.graph.try_reserve(nodes, edges)?;
            self.sigma2.try_reserve(edges)?;
            self.delta.try_reserve(edges)?;
            self.noise.try_reserve(edges)?;
            self.wrap.try_reserve(edges)?;
            self.chord_cycle.try_reserve(edges)?;
            self.users.try_reserve(edges)?;
            self.input_of.try_reserve(edges)?;
            self.paths.try_reserve(edges)?;
            self.theta.try_reserve(nodes)?;
            self.basis.try_reserve(nodes, edges)?;
            self.cycles.try_reserve(cycles)?;
            self.gamma.try_reserve(cycles)?;
            self.model.try_reserve(cycles, edges)?;
            self.screener.try_reserve(cycles)?;
            self.estimate.try_reserve(nodes, edges)
        };
        // A refusal leaves some arrays with more room than before, nothing else changed.
        room().map_err(|_| OnlineError::Reserve { nodes, edges })?;
        let (n, m) = self.room_for;
        self.room_for = (
            n.max(self.graph.node_count().saturating_add(nodes)),
            m.max(self.graph.edge_count().saturating_add(edges)),
        );
        Ok(())
    }

    /// Room up to `(nodes, edges)` in all ([`Self::reserve`]), if any was asked for: an
    /// estimator that replaces this one in a rebuild keeps the caller's room.
    pub(super) fn keep_room(&mut self, (nodes, edges): (usize, usize)) {
        if (nodes, edges) == (0, 0) {
            return;
        }
        // Refused, the arrays grow as they would have.
        let _ = self.reserve(
            nodes.saturating_sub(self.graph.node_count()),
            edges.saturating_sub(self.graph.edge_count()),
        );
    }

    /// Add an edge (validated by construction). Edges to unseen nodes create them; an edge
    /// between two components joins them. A refused edge leaves the estimator unchanged.
    /// Recording is an observer of steps: see [`crate::log::Recorder::add_edge`].
    pub fn add_edge(&mut self, edge: Edge) -> Result<Step, OnlineError> {
        self.add_edge_inner(edge)
    }

    /// Use idle time between steps (a robot waiting for its next sensor reading) to keep the
    /// estimate fast: if at least [`MAINTAIN_APPENDED`] nodes (and a [`MAINTAIN_FRACTION`]th
    /// of the graph's) were appended to the estimate's factor since its order was made, the
    /// factor is renewed now, on this thread — the
    /// renewal a builder thread would otherwise make beside the steps, and collect later with
    /// the nodes appended meanwhile at the end of its order — with every position row taken
    /// at the current headings. The steps after it walk a fresh factor, and any renewal in
    /// progress beside is dropped. Otherwise, once the headings have moved half as far as the
    /// bound at which a step would re-linearise the position rows, they are re-linearised now
    /// (a back-substitution and a forward solve), so that no step has to. It blocks for one
    /// sparse factorization in a fill-reducing order when a renewal is due (the longest call:
    /// 3–5 ms on M3500's 3 500 nodes, 13–20 ms on city10000's 10 000, about 0.1 s on a
    /// 30 000-pose world on the development machine), less for a re-linearisation, and costs
    /// nothing otherwise: a caller with a deadline asks [`Self::maintenance_due`] first.
    /// The answers stay exact; a renewal changes their last bits and a re-linearisation the
    /// fast positions, so a log records what it did ([`crate::log::Recorder::maintain`]) and a
    /// replay does it at the same points.
    ///
    /// ```
    /// use so2lin::online::{OnlineConfig, OnlineEstimator, robot_order};
    /// use so2lin::sim::{SimConfig, simulate};
    ///
    /// let world = simulate(&SimConfig::new(600, 1)).expect("a simulated world");
    /// let mut est = OnlineEstimator::new(OnlineConfig::default())?;
    /// for edge in robot_order(world.graph.edges()) {
    ///     est.add_edge(edge)?;
    ///     let (_node, _pose) = est.newest()?.expect("a node");
    ///     // ... and while waiting for the next reading:
    ///     est.maintain();
    /// }
    /// assert!(est.counters().maintenance_renewals > 0);
    /// # Ok::<(), so2lin::online::OnlineError>(())
    /// ```
    pub fn maintain(&mut self) -> Maintenance {
        let built = self.estimate.maintain(&self.graph, self.maintain_after());
        self.refresh_counters();
        match built {
            Some((renewed, variables, nonzeros)) => Maintenance {
                renewed,
                relinearised: true,
                variables,
                nonzeros,
            },
            None => Maintenance::default(),
        }
    }

    /// Whether [`Self::maintain`] would renew the estimate's factor (or re-linearise its
    /// position rows) now, and if so the nodes of the factor: a renewal costs about as much as
    /// the last one per node (it grows with the graph; a re-linearisation less), so a caller
    /// with a deadline can tell whether it fits before the next reading:
    /// `if est.maintenance_due().is_some_and(|n| n as f64 * per_node < time_left)
    /// { est.maintain(); }`, with `per_node` the last call's time over its
    /// [`Maintenance::variables`] (the `robot_loop` example).
    pub fn maintenance_due(&mut self) -> Option<usize> {
        self.estimate
            .maintenance_due(&self.graph, self.maintain_after())
    }

    /// Nodes appended since the factor's order was made from which [`Self::maintain`] renews.
    fn maintain_after(&self) -> usize {
        MAINTAIN_APPENDED.max(self.graph.node_count() / MAINTAIN_FRACTION)
    }

    /// The translation closure of a cycle whose terms are graph edges and, numbered from the
    /// graph's edge count on, the edges `new` (not in the graph: a loop closure being tested),
    /// from the closure noise kept per edge, at both ends of its chord — the second end left
    /// out when the first already fails every test the caller puts to it, `decided(χ²)`
    /// ([`closure::translation_closure_unless_first_fails`]).
    fn closure_with(
        &self,
        terms: &[crate::cycles::SignedEdge],
        new: &[Option<closure::EdgeNoise>],
        angle_scale: f64,
        decided: &dyn Fn(f64) -> bool,
    ) -> Option<closure::Closure> {
        let n = self.noise.len();
        let of = |i: usize| match i.checked_sub(n) {
            Some(k) => new.get(k).copied().flatten(),
            None => self.noise[i],
        };
        closure::translation_closure_unless_first_fails(terms, &of, angle_scale, decided)
    }

    /// The node indices of an edge's two ends, if both are in the graph.
    fn ends(&self, edge: &Edge) -> Option<(usize, usize)> {
        Some((
            self.graph.node_index(edge.from())?,
            self.graph.node_index(edge.to())?,
        ))
    }

    fn add_edge_inner(&mut self, edge: Edge) -> Result<Step, OnlineError> {
        let input = self.arrivals;
        if input >= u32::MAX as usize {
            return Err(OnlineError::Capacity(u32::MAX as usize));
        }
        let mut step = match self.ends(&edge) {
            Some((a, b)) if self.basis.connected(a, b) => {
                let level = self.config.screening.online_level(self.model.len());
                match self.add_chord(input, edge, a, b, level)? {
                    Ok(step) => step,
                    Err(rejected) => self.hold(edge, rejected, level),
                }
            }
            _ => self.add_tree_edge(input, edge)?,
        };
        self.arrivals += 1;
        self.retest_due(&mut step);
        self.examine_suspects(&mut step);
        self.warm_up(&mut step);
        self.advance_rebuild(edge, &mut step);
        self.refresh_counters();
        self.checkpoint_if_due();
        Ok(step)
    }

    /// A tree edge: a new node, or two components joined.
    fn add_tree_edge(&mut self, input: usize, edge: Edge) -> Result<Step, OnlineError> {
        let e = self.graph.edge_count();
        let nodes_before = self.graph.node_count();
        // Cannot fail with CreateUnknown; mapped rather than unwrapped all the same.
        self.graph.add_edge(edge, NodePolicy::CreateUnknown)?;
        let (a, b) = self.graph.endpoints()[e];
        for _ in nodes_before..self.graph.node_count() {
            self.estimate.push(Op::Node);
        }
        self.sigma2.push(edge.sigma2());
        self.delta.push(edge.delta());
        self.noise.push(closure::EdgeNoise::of(&edge));
        self.accept(input);
        self.basis.commit(a, b, edge.sigma2(), false);
        self.counters.tree_edges += 1;
        let new_node = self.graph.node_count() > nodes_before;
        self.push_edge(e, a, b, &[], false);
        self.after_step();
        Ok(Step {
            edge: input,
            kind: StepKind::Tree {
                new_node,
                joined_components: !new_node,
            },
            rescreened: Vec::new(),
            quarantined: Vec::new(),
            readmitted: Vec::new(),
        })
    }

    /// The per-edge state of an accepted edge (σ² and δ already pushed).
    fn accept(&mut self, input: usize) {
        self.paths
            .entered(input, self.input_of.len(), self.arrivals);
        if let Some(h) = &mut self.hints {
            h.entered(input, self.arrivals);
        }
        self.input_of.push(input as u32);
        self.wrap.push(0);
        self.chord_cycle.push(NONE);
        self.users.push(SmallVec::new());
        self.counters.steps += 1;
    }

    /// `δ_e − 2π k_e`: the unwrapped measurement of edge e.
    fn wrapped(&self, e: usize) -> f64 {
        self.delta[e] - std::f64::consts::TAU * self.wrap[e] as f64
    }

    /// Hand a step's edge to the estimate: its orientation row (with its wrap), the rows
    /// whose wrap moved, its position row, the end of the step.
    /// A chord whose heading row is in already (kept after its prediction, with no wrap)
    /// gets its wrap.
    fn push_edge(&mut self, e: usize, a: usize, b: usize, changed: &[usize], admitted: bool) {
        let (e32, a, b) = (e as u32, a as u32, b as u32);
        let y = self.wrapped(e);
        if admitted {
            self.estimate.push(Op::Wrap { e: e32, y });
        } else {
            self.estimate.push(Op::Edge { e: e32, a, b, y });
        }
        for &c in changed {
            if c != e {
                let y = self.wrapped(c);
                self.estimate.push(Op::Wrap { e: c as u32, y });
            }
        }
        self.estimate.push(Op::Position { e: e32, a, b, y });
        self.estimate.push(Op::Step);
    }

    /// End of a step: the P_UU factor's renewal advances (the counters are refreshed once,
    /// at the end of [`Self::add_edge`]).
    fn after_step(&mut self) {
        self.advance_reorder();
    }

    fn refresh_counters(&mut self) {
        self.counters.quarantined = self.held.len();
        self.counters.determined = self.screener.cond.len() + self.backlog.len();
        self.counters.ambiguous = self.ambiguous.len();
        self.counters.inconsistent = self.screener.inconsistent_count();
        self.counters.rebuild_waits = self.rebuild_waits;
        self.counters.replayed_arrivals = self.replay_work;
    }

    /// The counters of the estimate's factor as they are now (a read applies the steps'
    /// operations to it after [`Self::add_edge`] returned): derived whenever they are read
    /// ([`Self::counters`]), never stored.
    fn estimate_counters(&self, counters: &mut Counters) {
        let (renewals, waits) = self.estimate.renewals();
        counters.estimate_renewals = renewals;
        counters.renewal_waits = waits + self.cond_waits;
        counters.estimate_relinearisations = self.estimate.relinearisations;
        counters.maintenance_renewals = self.estimate.renewed_now();
    }
}

/// No cycle.
const NONE: u32 = u32::MAX;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{SimConfig, simulate};

    /// Stream `edges` through an estimator prepared by `setup` and a plain one side by side:
    /// the newest pose after every step, the quarantine and the final poses are the same bits.
    /// `check(k, est)` looks at the prepared one before edge k and once more at the end
    /// (k = edges.len()).
    fn beside_a_plain_one(
        edges: &[Edge],
        setup: impl FnOnce(&mut OnlineEstimator),
        mut check: impl FnMut(usize, &mut OnlineEstimator),
    ) {
        let mut est = OnlineEstimator::new(OnlineConfig::default()).expect("default config");
        let mut plain = OnlineEstimator::new(OnlineConfig::default()).expect("default config");
        setup(&mut est);
        for (k, e) in edges.iter().enumerate() {
            check(k, &mut est);
            est.add_edge(*e).expect("a valid edge");
            plain.add_edge(*e).expect("a valid edge");
            assert_eq!(est.newest().ok(), plain.newest().ok(), "step {k}");
        }
        check(edges.len(), &mut est);
        assert_eq!(est.rejected(), plain.rejected());
        assert_eq!(est.poses().ok(), plain.poses().ok());
    }

    /// The arrays that grow with every edge (a few of them).
    fn arrays(e: &OnlineEstimator) -> [usize; 7] {
        [
            e.graph.edges().as_ptr() as usize,
            e.sigma2.as_ptr() as usize,
            e.noise.as_ptr() as usize,
            e.wrap.as_ptr() as usize,
            e.users.as_ptr() as usize,
            e.input_of.as_ptr() as usize,
            e.gamma.as_ptr() as usize,
        ]
    }

    /// With room reserved for a whole stream, the arrays that grow with every edge never move
    /// (no step copies one), and the answers are the same bits as without the room.
    #[test]
    fn reserved_arrays_do_not_move() {
        let w = simulate(&SimConfig::new(2_500, 5)).expect("a world");
        let edges = robot_order(w.graph.edges());
        let room = |e: &mut OnlineEstimator| {
            e.reserve(w.graph.node_count(), edges.len())
                .expect("room for a small world")
        };
        let mut before = None;
        beside_a_plain_one(&edges, room, |k, est| {
            let now = arrays(est);
            assert_eq!(
                *before.get_or_insert(now),
                now,
                "a reserved array moved at {k}"
            );
            if k == edges.len() {
                assert!(est.counters().estimate_renewals >= 2);
            }
        });
    }

    /// An estimator that replaces this one in a rebuild (a stream with false loop closures:
    /// the re-test from the start, evictions) keeps the caller's room: between rebuilds no
    /// array moves, and the answers are the same bits as without the room.
    #[test]
    fn the_room_outlives_rebuilds() {
        use crate::sim::{OutlierConfig, OutlierKind, inject_outliers};
        let w = simulate(&SimConfig::new(1_500, 11)).expect("a world");
        // Rebuilt at arrivals 383 and 438: the second replaces the estimator before its arrays
        // pass 512, 1 024 and 2 048 edges (without the room kept, they moved at 519).
        let outliers = OutlierConfig {
            count: 50,
            kind: OutlierKind::Random,
            seed: 1,
        };
        let bad = inject_outliers(&w.graph, &outliers).expect("false edges");
        let edges = bad.graph.edges();
        let room = |e: &mut OnlineEstimator| {
            e.reserve(bad.graph.node_count(), edges.len())
                .expect("room for a small world")
        };
        let (mut rebuilds, mut before) = (0, None);
        beside_a_plain_one(edges, room, |_, est| {
            if est.counters().rebuilds != rebuilds {
                rebuilds = est.counters().rebuilds;
                before = None;
            }
            let now = arrays(est);
            assert_eq!(
                *before.get_or_insert(now),
                now,
                "an array moved after rebuild {rebuilds}"
            );
        });
        assert!(rebuilds >= 2, "no rebuild replaced the estimator");
    }

    /// Room that cannot be had is a typed error, and the estimator answers on as before.
    #[test]
    fn room_refused_is_an_error_and_changes_nothing() {
        let w = simulate(&SimConfig::new(300, 2)).expect("a world");
        let edges = robot_order(w.graph.edges());
        beside_a_plain_one(
            &edges,
            |_| {},
            |k, est| {
                if k == 100 {
                    assert!(matches!(
                        est.reserve(10, u32::MAX as usize + 1),
                        Err(OnlineError::Capacity(_))
                    ));
                    let err = est.reserve(usize::MAX / 2, 10).expect_err("too much room");
                    assert!(matches!(err, OnlineError::Reserve { .. }), "{err}");
                    assert!(err.to_string().contains("cannot reserve room"), "{err}");
                }
            },
        );
    }
}
