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
//! **Replays.** When the estimator evicts a loop closure it replays the stream without it
//! into a fresh estimator, whose estimate nobody reads within the replay. When the estimate is
//! read every step the replay keeps the factors through it all the same, to screen the
//! replayed loop closures with them as live steps do (module `online::predict`; faster than
//! through P_UU on large worlds: module `online::rebuild`, "the builder's pace"). Otherwise
//! (and in the in-step replays the tests compare with) the replay defers them: its operations
//! go to the systems' rows only ([`Op::Defer`]), and the factors are built once at the
//! replay's end ([`Op::Rebuild`]: a fill-reducing order with the newest node last, every
//! position row at the headings of that moment, as a renewal does), instead of being kept
//! through every replayed step. On M3500 + 1000 false loop closures (`so2lin stream`, robot
//! order, the newest pose read after every step) this took the worst step (a replay) from
//! 110–140 ms to 52–72 ms. Since 2026-12-06 the replay's factors are not built from nothing
//! when it replaces an estimator whose rows differ from its own in a few loop closures (the
//! evicted, the re-admitted: [`Estimate::inherit`], [`Laplacian::adopt`]): the replaced
//! factor takes the difference by rotations and down-dates and one forward solve, and keeps
//! its order until its next renewal. On M3500 + 1000 false loop closures (random seeds 2–5, 7,
//! 8, clustered 4; `so2lin stream FILE --json`: robot order, the newest pose read after every
//! step; three runs each, medians) the worst step, an eviction's, fell by 0.4–2.2 ms
//! (9.7–17.2 → 8.8–15.0 ms), the p99 and the steps' time within the runs' noise, while the
//! estimate's work over the stream rose by 7–19 % (the replaced order kept until the next
//! renewal, where a rebuild gave a fresh one).
//!
//! **Positions** (the linear estimate's model: headings treated as exact): the position row of
//! an edge uses the tail's heading as estimated right after the edge's step — read at the newer
//! end of the edge, O(1) in the factor, and carried across the edge by its unwrapped
//! measurement — and the isotropic part of the translation information,
//! `w = (Ω_t,xx + Ω_t,yy)/2` (exact when it is isotropic). So the fast answers
//! ([`Estimate::pose`]) lag the heading corrections that later loop closures make to old nodes,
//! like iSAM2's with a relinearisation threshold. Every position row is re-linearised at the
//! current headings whenever a renewal of the position factor's order starts (the renewed
//! factor takes them; its builder solves those headings from the factor it built, so the step
//! that starts a renewal pays no back-substitution), and from the step at which a bound on how
//! far the headings have moved since the rows were linearised passes [`HEADING_LAG`], over
//! the next steps ([`Estimate::relinearise_over_steps`]): the headings solved a block of the
//! factor per step (a back-substitution spread over steps, each block reading the factor of
//! its own step: module `estimate::incremental::back`), then the rows' position measurements
//! at them written into the rows a block per step,
//! then the factor's right-hand sides recomputed from them (their information `Σ a β` gathered
//! a block of rows per step, then one forward solve a block of positions per step, while rows
//! keep being rotated in: [`Laplacian::relinearise`], module `estimate::incremental::spread`);
//! on city10000 the three take a median 3.5, 7 and 24 steps, on M3500 0 (the headings in the
//! step that starts it), 3 and 7 (scratch counters, 2026-12-07). Each block is sized by
//! its step's own work on the factor, up to 1.25 times its share at a light step (an odometry
//! row) and only its least block at a loop closure's heavy one
//! (`estimate::incremental::levelled`), so that no step pays for a whole pass over the factor,
//! and the heaviest steps pay little: each
//! heading row added, or measurement moved, changes the headings by a potential driven between
//! its two ends, which by the maximum principle moves no node by more than it moves the edge's
//! own difference `θ_b − θ_a` — known from the rotations (`(δ − (θ̂_b − θ̂_a))(1 − Πc²)`,
//! [`Laplacian::moved`]); the bound adds these up (and after a re-linearisation over steps it
//! starts from its growth since the first of them, which bounds how far the headings its
//! blocks solved are from the current ones). Both are step-scheduled events, so the
//! answers do not depend on what was read when. [`Estimate::poses`] is the exact answer on
//! demand, without changing the factor: every position row at the current headings (one forward
//! and one back-substitution; a 2×2-block system solved from scratch when the translation
//! information is not isotropic).
//!
//! **One factor for both.** The orientation and position systems share their graph, so one
//! [`Laplacian`] with three right-hand sides (heading; x, y) holds both: each edge's row is
//! rotated in once, along one path, and one renewal builder runs. The position right-hand side
//! of an edge is known only after its heading row and the step's wraps are applied (it reads
//! the new heading); it enters as a shift of that row's right-hand side, through the gains its
//! rotations recorded ([`crate::estimate::incremental::SqrtInfo::shift_last_row`]), O(path)
//! without a second walk. While every edge's position weight is the same multiple λ of its
//! orientation weight (isotropic translation information, `w_pos = λ/σ_θ²`: city10000 and the
//! simulated worlds) the two systems' square-root factors are the same R up to the scale `√λ`
//! and the positions' solution does not depend on λ: the factor has one lane, every row
//! weighted like the heading, and position variances are its variances divided by λ. At the
//! first edge that breaks the proportion (or is anisotropic: M3500, INTEL) it is widened, once,
//! to two lanes (R as it is for the headings; R and d times `√λ` for the positions), each row
//! then carrying its heading weight in lane 0 and its position weight in lane 1. Two factors
//! with two builders, as this was before (2026-12-05), walked every path twice: M3500 took
//! 0.071–0.074 s of steps against 0.058–0.060 s with the lanes, p99 125–131 against 125–130 µs,
//! worst step over 2 ms in one run of 38 each (`so2lin stream M3500.g2o --json`, robot order,
//! the newest pose read after every step; medians of three batches of alternating runs).

use super::laplacian::{Laplacian, RenewalEvent};
use super::snapshot::Chunked;
use crate::estimate::EstimateError;
use crate::graph::{Edge, Pose2, PoseGraph};

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
    /// From here on the changes go to the systems' rows only, without factor work, until
    /// [`Op::Rebuild`]: a replay of the stream, whose answers nobody reads in between.
    Defer,
    /// Build the factors of the whole systems at once ([`Laplacian::rebuild`]), or derive them
    /// from the factors inherited from the estimate this one replaces ([`Laplacian::adopt`]),
    /// every position row at the headings of that moment (as a renewal does).
    Rebuild,
}

/// Relative difference below which two edges' position-to-heading weight ratios count as
/// equal (the shared factor stays).
const RATIO_TOLERANCE: f64 = 1e-12;

/// The factor of the two systems (see the module docs): right-hand side 0 the headings, 1
/// and 2 the positions.
enum Factors {
    /// One lane, every row weighted by its heading weight; `ratio` is λ (position weight over
    /// heading weight, the same for every edge so far; None before the first edge).
    Shared {
        both: Box<Laplacian<3>>,
        ratio: Option<f64>,
    },
    /// Two lanes: the headings' weights in lane 0, the positions' in lane 1.
    Lanes { both: Box<Laplacian<3, 2>> },
}

/// `$body` with `$f` the factor, whichever kind it is: the two kinds are driven alike (they
/// differ in their lanes only).
macro_rules! with_factor {
    ($factors:expr, $f:ident => $body:expr) => {
        match $factors {
            Factors::Shared { both: $f, .. } => $body,
            Factors::Lanes { both: $f } => $body,
        }
    };
}

impl Default for Factors {
    fn default() -> Self {
        Factors::Shared {
            both: Box::default(),
            ratio: None,
        }
    }
}

/// The factored orientation and position systems with their pending operations.
#[derive(Default)]
pub(crate) struct Estimate {
    factors: Factors,
    /// Some edge's translation information is not isotropic.
    anisotropic: bool,
    pending: Vec<Op>,
    /// The weights of a loop closure tried ([`Self::try_chord`]) and not yet kept or undone.
    tried: Option<(f64, f64, bool)>,
    /// The factors of the estimate this one replaces ([`Self::inherit`]), until the deferred
    /// factors are built ([`Op::Rebuild`]).
    inherited: Option<Factors>,
    /// The headings' bound [`Laplacian::moved`] when the renewal of the factor holding the
    /// positions started (its rows re-linearised then).
    moved_at_renewal: f64,
    /// Re-linearisations of every position row because the headings moved by more than
    /// [`HEADING_LAG`] ([`Self::after_step`]), by the live steps: a rebuilt estimator swapped
    /// in takes the count of the one it replaces (its builder's own are not counted).
    pub relinearisations: usize,
    /// The positions factor's live work at the last of them ([`RELINEARISE_WORK_PER_NONZERO`]).
    work_at_relinearisation: u64,
    /// The steps re-linearise no position row ([`Self::hold_positions`]: a replay, whose
    /// positions nobody reads before its end).
    positions_held: bool,
    /// The headings' sines and cosines for the position rows.
    trig: Trig,
    /// A re-linearisation of the position rows in progress ([`Self::after_step`]).
    relin: Option<Relin>,
    /// The block of rows' new position measurements the one in progress writes in a step,
    /// computed here first and then copied into the rows (kept for its room): computing them
    /// straight into the rows' chunks made those steps slower (city10000, two traced runs
    /// each: a median 92–95 µs against 62–68 µs two steps before the last block).
    relin_rows: Vec<[f64; 2]>,
    /// Each position row's edge's older end and measurement, copied from the graph as a
    /// renewal's job first needs them ([`tails_snapshot`]): each edge once, and a renewal's
    /// job shares the chunks rather than copying them all in the step that starts it.
    tails: Chunked<(usize, Pose2)>,
}

/// A re-linearisation of the position rows made over steps ([`Estimate::after_step`]):
/// `moved` is the headings' bound [`Laplacian::moved`] at its first step, `edges` the position
/// rows then (the later ones are written at the headings of their own steps).
enum Relin {
    /// The headings solved a block of the factor's positions per step
    /// ([`Laplacian::back_start`]).
    Headings { moved: f64, edges: usize },
    /// The rows' position measurements `R(θ_a) t_e` at those headings `theta`, written into the
    /// factor's rows a block per step from row `next` on ([`Laplacian::measurements_mut`]); the
    /// last block hands them to the factor ([`Laplacian::relinearise`]). Until 2026-12-07 the
    /// blocks went to a buffer that the last step then wrote over every row: that rewrite took
    /// a median 32 µs on city10000 and up to 0.18 ms (scratch timers), and its step was among
    /// the slowest 1 % 10–20 times a run.
    Rows {
        theta: Vec<f64>,
        next: usize,
        moved: f64,
        edges: usize,
    },
}

/// Blocks of rows a re-linearisation writes ([`Relin::Rows`]), one a step (fewer when there
/// are few rows: [`MIN_ROW_BLOCK`]).
const ROW_STEPS: usize = 4;

/// Rows a re-linearisation writes per step at least. At 4 096 M3500's 5 453 rows were written
/// in one or two steps of about 60 µs (15–30 ns a row), 5 of its 54 slowest; at 1 024
/// (alternating runs, `so2lin stream M3500.g2o --json`, robot order, the newest pose read after
/// every step, 2026-12-07) its p99 median was 98.8 against 103.9 µs, lower in seven of eight
/// rounds (worst step 1.35–3.41 against 1.38–3.62 ms), the fast pose 0.0476 against 0.0473 m
/// from the exact one on average; city10000, whose first 16 000 rows it also bounds, within the
/// noise (eleven rounds: median 129.2 against 126.0 µs, five lower; worst step 3.26–5.96
/// against 3.52–4.95 ms). Larger files write a quarter of their rows a step ([`ROW_STEPS`]),
/// above this. A heavy step, whose share of a block is nothing
/// ([`crate::estimate::incremental::levelled`]), writes a quarter of this, so that a run of
/// loop closures does not stall the rows.
const MIN_ROW_BLOCK: usize = 1024;

/// Live work (entries of the factor visited by the steps' rotations and solves, counted)
/// between two re-linearisations for the bound [`HEADING_LAG`], per nonzero of the factor: a
/// re-linearisation costs a few passes over the factor (a back-substitution, the rows, a
/// forward solve), so this keeps it to a few percent of the steps' own work however large the
/// world and however often the bound is passed (a 10 000-pose simulated world passed it 363
/// times in 16 600 steps). Less [`RELINEARISE_ALLOWANCE`]: a small factor is re-linearised
/// whenever the bound is passed (MIT's 808 poses do little live work between their large
/// corrections).
const RELINEARISE_WORK_PER_NONZERO: f64 = 32.0;

/// Work granted to every re-linearisation ahead (see [`RELINEARISE_WORK_PER_NONZERO`]): about
/// a millisecond of the live factor's steps.
const RELINEARISE_ALLOWANCE: u64 = 1 << 20;

/// The bound on how far the headings may have moved since the position rows were
/// linearised (rad) beyond which every position row is re-linearised at the current headings
/// (module docs: positions; the factor takes them over the next steps). The bound
/// adds up every row's movement, so it is loose; measured (`so2lin stream FILE --json`, robot
/// order, the newest pose read, against no such bound): at 1 rad the newest pose's distance to the exact one, sampled every 25
/// steps, went on MIT from 35 m on average (89 m at worst) to 2.3 m (5.6), on M3500 from
/// 0.24 m (1.3) to 0.05 m (0.43) at a cost of 0.100 → 0.108 s of steps and p99 188 → 207 µs
/// (49 re-linearisations), on city10000 from 0.18 m to 0.10 m for no measurable time (92);
/// at 0.2 rad M3500 took 0.22 s (242), at 0.05 rad 0.50 s (725). Re-linearisations are also
/// spaced by the live work ([`RELINEARISE_WORK_PER_NONZERO`]).
pub(crate) const HEADING_LAG: f64 = 1.0;

/// The share of [`HEADING_LAG`] beyond which [`Estimate::maintain`] (a caller's idle time)
/// re-linearises every position row, before a step has to: with the caller maintaining after
/// every step, the steps then re-linearise nothing. Measured (`so2lin stream FILE --json
/// --maintain`, robot order, the newest pose read after every step, back to back, alternating,
/// 2026-12-05): M3500 p99 47.4 µs (44.4–54.8) at 1/2 and 49.5 (45.1–55.6) at 1/4 against 65.7
/// (58.1–75.5) leaving them to the steps, the worst step 0.36, 0.35 and 0.36 ms (medians;
/// eight runs each; 74 and 172 re-linearisations between steps, 21 on the steps otherwise);
/// city10000 71.4–74.4 and 71.6–73.0 against 76.7–80.4 µs, worst 0.70–0.84, 0.67–0.70 and
/// 0.76–1.01 ms (three runs each). The same share of the work that spaces the steps'
/// re-linearisations ([`RELINEARISE_WORK_PER_NONZERO`]) spaces these: unspaced, a 30 000-pose
/// world spent 9.1 s of maintenance against 4.4 s without re-linearising between steps (p99
/// 335 against 329 µs, worst 6.8 against 7.0 ms); spaced, 5.4–5.6 s, p99 288–303 µs (worst
/// 7.6 ms in the run that kept it), 4 re-linearisations left to the steps (two runs); the
/// 100 000-pose world's maintenance took 96 s unspaced against 18 s without (worst step 25.3
/// against 36.5 ms, one run each).
const MAINTAIN_LAG: f64 = 0.5;

impl Estimate {
    /// An empty estimate whose factor's renewals are collected after `renewal_delay` times
    /// the default work ([`crate::online::OnlineConfig::renewal_delay`]).
    pub fn new(renewal_delay: f64) -> Self {
        let mut e = Self::default();
        with_factor!(&mut e.factors, both => both.set_renewal_delay(renewal_delay));
        e
    }
}

/// A loop closure's prediction by the headings' factor ([`Estimate::try_chord`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Prediction {
    /// `δ − (θ̂_b − θ̂_a)`: the measurement, unwrapped by no turn, minus its prediction.
    pub innovation: f64,
    /// `σ² + Var(θ̂_b − θ̂_a)`: the innovation's variance.
    pub variance: f64,
}

/// `R(θ) t`: a relative translation in the world frame of a tail with heading θ.
pub(crate) fn rotate(theta: f64, z: Pose2) -> [f64; 2] {
    rotated(theta.sin_cos(), z)
}

/// [`rotate`] given θ's `(sin, cos)`.
#[inline]
fn rotated((s, c): (f64, f64), z: Pose2) -> [f64; 2] {
    [c * z.x - s * z.y, s * z.x + c * z.y]
}

/// An edge's position weight (the isotropic part of its translation information) and
/// whether its translation information is isotropic.
fn position_weight(edge: &Edge) -> (f64, bool) {
    let o = edge.information().translation_information();
    (
        0.5 * (o[0][0] + o[1][1]),
        o[0][1] == 0.0 && o[0][0] == o[1][1],
    )
}

/// Spacing of the grid of headings whose sines and cosines [`Trig`] keeps (rad). A power of
/// two, so that a grid point `k·GRID` nearest to θ, and θ's distance to it, are exact.
const GRID: f64 = 1.0 / 64.0;

/// `(sin θ, cos θ)` from those of the grid point `g = k·GRID` next to θ towards 0, which
/// `near` holds as `[g, sin g, cos g]` (computed now when it holds another point): the grid
/// point's rotated by `δ = θ − g` (exact, `|δ| < GRID`), whose sine and cosine are their Taylor
/// polynomials to `δ⁷` and `δ⁸` (the first terms left out, `δ⁹/9!` and `δ¹⁰/10!`, are below
/// 2e-22 there). Within a few units in the last place of `f64::sin_cos`, and a function of θ
/// alone: the same bits whatever `near` held before, so a re-linearisation's rows do not
/// depend on which headings were seen before (a log's replay, a rebuild from a checkpoint and
/// a renewal's builder write the same bits). (`k` by truncation, not `round`: without SSE4.1,
/// the baseline of x86-64, `round` is a call.)
#[inline]
fn sin_cos_near(theta: f64, near: &mut [f64; 3]) -> (f64, f64) {
    let g = ((theta / GRID) as i64) as f64 * GRID;
    let d = theta - g;
    // (A heading too large for k, or not finite: libm's own.)
    if d.is_nan() || d.abs() >= GRID {
        return theta.sin_cos();
    }
    if g != near[0] {
        let (s, c) = g.sin_cos();
        *near = [g, s, c];
    }
    let d2 = d * d;
    let sin_d = d + d * d2 * (-1.0 / 6.0 + d2 * (1.0 / 120.0 - d2 * (1.0 / 5040.0)));
    let cos_d = 1.0 + d2 * (-0.5 + d2 * (1.0 / 24.0 + d2 * (-1.0 / 720.0 + d2 * (1.0 / 40320.0))));
    let [_, s, c] = *near;
    (s * cos_d + c * sin_d, c * cos_d - s * sin_d)
}

/// The sines and cosines of every node's heading, as a re-linearisation of the position rows
/// needs them ([`write_relinearised`]), through [`sin_cos_near`]: each node keeps its nearest
/// grid point's, which changes only when its heading moved by about `GRID` since, so most of
/// them are two short polynomials instead of two calls to libm's `sin` and `cos` (10 000
/// headings: 16 µs against 90 µs, a throwaway benchmark, 2026-12-07). Wrote by hand: a
/// rotation by a small angle, which no crate's `sin_cos` does.
#[derive(Default)]
pub(crate) struct Trig {
    /// Each node's nearest grid point, its sine and cosine (NaN: none yet).
    near: Vec<[f64; 3]>,
    /// The last answer of [`Self::of`] (kept for its room).
    out: Vec<(f64, f64)>,
}

impl Trig {
    /// `(sin θ_v, cos θ_v)` of every node v.
    fn of(&mut self, theta: &[f64]) -> &[(f64, f64)] {
        self.near.resize(theta.len(), [f64::NAN; 3]);
        self.out.clear();
        (self.out).extend((theta.iter().zip(&mut self.near)).map(|(&t, n)| sin_cos_near(t, n)));
        &self.out
    }

    /// `(sin θ, cos θ)` of node v's heading θ.
    fn at(&mut self, v: usize, theta: f64) -> (f64, f64) {
        if self.near.len() <= v {
            self.near.resize(v + 1, [f64::NAN; 3]);
        }
        sin_cos_near(theta, &mut self.near[v])
    }

    /// Room for `nodes` nodes in all.
    fn try_reserve(&mut self, nodes: usize) -> Result<(), std::collections::TryReserveError> {
        (self.near).try_reserve(nodes.saturating_sub(self.near.len()))?;
        (self.out).try_reserve(nodes.saturating_sub(self.out.len()))
    }
}

/// Write `R(θ_a) t_e` (every edge's position measurement at the headings θ, given as each
/// node's `(sin θ, cos θ)`: [`Trig::of`]) into components `first` and `first + 1` of the
/// first `edges` measurements `y`, from `tails` (each edge's older end and measurement). The
/// sine and cosine are taken once per node, not per edge: the same values, computed fewer
/// times (M3500 has 1.6 edges per node, city10000 2.1).
fn write_relinearised<const K: usize>(
    y: &mut Chunked<[f64; K]>,
    sin_cos: &[(f64, f64)],
    tails: impl Iterator<Item = (usize, Pose2)>,
    first: usize,
) {
    for (ye, (a, z)) in y.iter_mut().zip(tails) {
        let [px, py] = rotated(sin_cos[a], z);
        ye[first] = px;
        ye[first + 1] = py;
    }
}

/// The edges' older ends and measurements, of the edges `edges` (those the graph has).
fn tails(
    graph: &PoseGraph,
    edges: std::ops::Range<usize>,
) -> impl Iterator<Item = (usize, Pose2)> + '_ {
    let end = edges.end.min(graph.edge_count());
    let edges = edges.start.min(end)..end;
    (graph.endpoints()[edges.clone()]
        .iter()
        .zip(&graph.edges()[edges]))
    .map(|(&(a, _), e)| (a, e.measurement()))
}

/// The tails of the first `edges` edges (the rows' order: [`tails`]) as a copy that shares
/// `store`'s chunks: the edges `store` lacks are copied into it first (the graph only grows
/// while an estimate lives, so each edge is copied once), and the snapshot costs a pointer
/// per chunk of them (module `online::snapshot`). Copying them all in the step that starts
/// a renewal took 0.09–0.44 ms on city10000 and 1.3–3.4 ms on a 100 000-pose world.
fn tails_snapshot(
    store: &mut Chunked<(usize, Pose2)>,
    graph: &PoseGraph,
    edges: usize,
) -> Chunked<(usize, Pose2)> {
    // (A store that is not this graph's prefix, checked at its last edge, starts again.)
    if let Some(last) = store.len().checked_sub(1)
        && tails(graph, last..last + 1).next().as_ref() != store.get(last)
    {
        *store = Chunked::default();
    }
    for tail in tails(graph, store.len()..edges) {
        store.push(tail);
    }
    store.clone()
}

/// [`write_relinearised`] of the first `edges` rows as a job for a renewal's builder, which
/// gives it the headings; `tails` from [`tails_snapshot`].
fn relinearise<const K: usize>(
    tails: Chunked<(usize, Pose2)>,
    edges: usize,
    first: usize,
) -> impl FnOnce(&mut Chunked<[f64; K]>, &[f64]) + Send + 'static {
    move |y: &mut Chunked<[f64; K]>, theta: &[f64]| {
        let tails = tails.iter().copied().take(edges);
        write_relinearised(y, Trig::default().of(theta), tails, first)
    }
}

/// Keep the headings' bound [`Laplacian::moved`] as the lag of the position rows across a
/// renewal of the factor (`event`): recorded when the renewal starts, and when it is swapped
/// in the bound is what the headings moved since that start or since a re-linearisation in
/// between (which sets `at_start` to 0), the rows' latest (bounds add up).
fn track_lag<const L: usize>(
    both: &mut Laplacian<3, L>,
    event: Option<RenewalEvent>,
    at_start: &mut f64,
) {
    match event {
        Some(RenewalEvent::Started) => *at_start = both.moved(0),
        // Infinite at the start (components joined, not re-linearised since): it stays so.
        Some(RenewalEvent::Collected) if at_start.is_finite() => {
            both.set_moved(0, (both.moved(0) - *at_start).max(0.0));
        }
        _ => {}
    }
}

impl Factors {
    /// Keep the shared factor if edge (heading weight `w`, position weight `w_pos`,
    /// `isotropic`) keeps the weights proportional; widen it to two lanes otherwise.
    fn admit(&mut self, w: f64, w_pos: f64, isotropic: bool) {
        // Equal up to the rounding of σ² (weights proportional in the file give ratios a few
        // ulps apart): the positions' weights then differ from λ/σ² by that relative amount,
        // which moves the solution by as little.
        if self.keeps(w, w_pos, isotropic) {
            if let Factors::Shared { ratio, .. } = self {
                *ratio = Some(w_pos / w);
            }
            return;
        }
        let Factors::Shared { both, ratio } = self else {
            return;
        };
        let scale = ratio.map_or(1.0, f64::sqrt);
        let (nodes, edges) = both.room();
        let mut wide = both.widen([1.0, scale]);
        // The room reserved stays (a widened copy is exactly as long as the shared factor).
        // (Refused, the widened factor grows as it would have.)
        let _ = wide.try_reserve(nodes, edges);
        *self = Factors::Lanes {
            both: Box::new(wide),
        };
    }

    /// Whether an edge with these weights keeps a shared factor shared ([`Self::admit`]).
    fn keeps(&self, w: f64, w_pos: f64, isotropic: bool) -> bool {
        let Factors::Shared { ratio, .. } = self else {
            return true;
        };
        let r = w_pos / w;
        isotropic
            && r > 0.0
            && r.is_finite()
            && ratio.is_none_or(|l| (l - r).abs() <= RATIO_TOLERANCE * l)
    }

    /// Edge a → b's row (heading weight `w`, position weight `w_pos`, heading measurement
    /// `y`; the positions' right-hand sides 0 until its position row).
    fn add_edge(&mut self, (a, b): (usize, usize), (w, w_pos): (f64, f64), y: f64) {
        let y = [y, 0.0, 0.0];
        match self {
            Factors::Shared { both, .. } => both.add_edge(a, b, w, y),
            Factors::Lanes { both } => both.add_edge(a, b, [w, w_pos], y),
        }
    }

    /// [`Self::add_edge`] tentatively ([`Laplacian::try_edge`]): the residual and the product
    /// of the cosines it leaves in the headings' lane.
    fn try_edge(
        &mut self,
        (a, b): (usize, usize),
        (w, w_pos): (f64, f64),
        y: f64,
    ) -> Option<(f64, f64)> {
        let y = [y, 0.0, 0.0];
        match self {
            Factors::Shared { both, .. } => {
                (both.try_edge(a, b, w, y)).map(|l| (l.residual[0], l.cosines[0]))
            }
            Factors::Lanes { both } => {
                (both.try_edge(a, b, [w, w_pos], y)).map(|l| (l.residual[0], l.cosines[0]))
            }
        }
    }

    /// Orientation of node v.
    fn orientation(&mut self, v: usize) -> f64 {
        with_factor!(self, both => both.value_of(v, 0))
    }

    /// Every orientation (one back-substitution).
    fn orientations(&mut self) -> Vec<f64> {
        with_factor!(self, both => both.all(0))
    }

    /// Whether changes are deferred ([`Op::Defer`]).
    fn deferred(&self) -> bool {
        with_factor!(self, both => both.deferred())
    }

    /// [`Op::Defer`].
    fn defer(&mut self) {
        with_factor!(self, both => both.defer())
    }

    /// [`Op::Rebuild`]: the factor (from `old`'s when they match, [`Laplacian::adopt`]), then
    /// every position row at its headings (their sines and cosines by `trig`).
    fn rebuild(&mut self, graph: &PoseGraph, old: Option<Factors>, trig: &mut Trig) {
        if !self.deferred() {
            return;
        }
        let edges = self.position_rows();
        let adopted = match (&mut *self, old) {
            (Factors::Shared { both, .. }, Some(Factors::Shared { both: old, .. })) => {
                both.adopt(old)
            }
            (Factors::Lanes { both }, Some(Factors::Lanes { both: old })) => both.adopt(old),
            (_, None) => false,
            // Lanes on one side only: freed on the worker, not in this step.
            (_, Some(old)) => {
                with_factor!(self, both => both.retire(old));
                false
            }
        };
        if !adopted {
            with_factor!(self, both => both.rebuild());
        }
        self.relinearise_positions(graph, edges, trig);
        // The rebuild's answers are read now (nothing lags a rebuild).
        with_factor!(self, both => both.flush_rhs());
    }

    /// The bound on how far the headings moved since the position rows were linearised
    /// ([`Laplacian::moved`]).
    fn headings_moved(&self) -> f64 {
        with_factor!(self, both => both.moved(0))
    }

    /// The factor's work and nonzeros ([`Laplacian::work_and_nnz`]).
    fn positions_work(&self) -> (u64, usize) {
        with_factor!(self, both => both.work_and_nnz())
    }

    /// Every position row (of the first `edges`) at the current headings, the factor's order
    /// and values kept; the headings' bound back to 0. Written here from the graph (no copy
    /// of the tails: this runs on the step), their sines and cosines by `trig`.
    fn relinearise_positions(&mut self, graph: &PoseGraph, edges: usize, trig: &mut Trig) {
        with_factor!(self, both => {
            let sin_cos = trig.of(&both.all(0));
            both.relinearise(|y| write_relinearised(y, sin_cos, tails(graph, 0..edges), 1), 1);
            both.set_moved(0, 0.0);
        })
    }

    /// Number of position rows.
    fn position_rows(&self) -> usize {
        with_factor!(self, both => both.edge_count())
    }
}

impl Estimate {
    /// Queue an operation.
    pub fn push(&mut self, op: Op) {
        self.pending.push(op);
    }

    /// Whether the factors are still to be built: deferred ([`Op::Defer`], applied or
    /// pending) or an [`Op::Rebuild`] pending — what [`Self::inherit`] would serve.
    fn builds_later(&self) -> bool {
        self.factors.deferred()
            || (self.pending.iter()).any(|op| matches!(op, Op::Defer | Op::Rebuild))
    }

    /// Renewals completed and steps that waited for a renewal's builder.
    pub fn renewals(&self) -> (usize, usize) {
        with_factor!(&self.factors, both => (both.renewals, both.waits))
    }

    /// Renewals made on the caller's thread ([`Self::maintain`]).
    pub fn renewed_now(&self) -> usize {
        with_factor!(&self.factors, both => both.renewed_now)
    }

    /// Whether [`Self::maintain`] would renew the factor or re-linearise its position rows
    /// (the pending operations applied): the variables of the factor.
    pub fn maintenance_due(&mut self, graph: &PoseGraph, appended: usize) -> Option<usize> {
        let due = self.renewal_due(graph, appended) || self.relinearisation_due();
        due.then(|| with_factor!(&self.factors, both => both.len()))
    }

    /// Whether a renewal pays (the pending operations applied): `appended` nodes or more at the
    /// end of the factor's order.
    fn renewal_due(&mut self, graph: &PoseGraph, appended: usize) -> bool {
        self.apply_pending(graph);
        with_factor!(&self.factors, both => both.renewal_pays(appended))
    }

    /// Whether the headings moved by more than [`MAINTAIN_LAG`] of [`HEADING_LAG`] since the
    /// position rows were linearised, and the live factor has done that share of the work that
    /// pays for a re-linearisation since the last ([`Self::relinearisation_paid`]): both before
    /// a step's own re-linearisation would be due, so a caller who maintains after every step
    /// leaves the steps none.
    fn relinearisation_due(&self) -> bool {
        !self.factors.deferred()
            && self.factors.headings_moved() > MAINTAIN_LAG * HEADING_LAG
            && self.relinearisation_paid(MAINTAIN_LAG)
    }

    /// Whether the live factor has done `share` of [`RELINEARISE_WORK_PER_NONZERO`] units of
    /// work per nonzero since the last re-linearisation, less [`RELINEARISE_ALLOWANCE`]: what
    /// spaces re-linearisations on large worlds, on the steps (`share` 1) and between them.
    fn relinearisation_paid(&self, share: f64) -> bool {
        let (work, nnz) = self.factors.positions_work();
        work.saturating_sub(self.work_at_relinearisation) + RELINEARISE_ALLOWANCE
            >= (share * RELINEARISE_WORK_PER_NONZERO * nnz as f64) as u64
    }

    /// A caller's idle time: the pending operations applied, then, if at least `appended`
    /// nodes were appended to the factor's order since it was made, the factor renewed now on
    /// this thread with every position row at the current headings (as a renewal's builder
    /// does: [`Laplacian::renew_now`]); otherwise, if the headings moved by more than
    /// [`MAINTAIN_LAG`] of [`HEADING_LAG`], every position row re-linearised (rows and
    /// right-hand sides at once). Whether it renewed, and the factor's variables and nonzeros;
    /// None when it did neither.
    pub fn maintain(&mut self, graph: &PoseGraph, appended: usize) -> Option<(bool, usize, usize)> {
        let renew = self.renewal_due(graph, appended);
        if !renew && !self.relinearisation_due() {
            return None;
        }
        if renew {
            self.relin_cancel();
            let edges = self.factors.position_rows();
            let tails = tails_snapshot(&mut self.tails, graph, edges);
            with_factor!(&mut self.factors, both => {
                both.renew_now(Some(Box::new(relinearise::<3>(tails, edges, 1))));
                // The rows are at the headings of now, and nothing lags them.
                both.set_moved(0, 0.0);
            });
            self.relinearised();
        } else {
            self.relinearise_now(graph);
        }
        let (variables, nonzeros) =
            with_factor!(&self.factors, both => (both.len(), both.work_and_nnz().1));
        Some((renew, variables, nonzeros))
    }

    /// Hold the position rows' re-linearisations ([`Self::after_step`]) until
    /// [`Self::release_positions`]: a replay's steps (module `online::rebuild`, "the builder's
    /// pace"). Its positions are read by nobody before the replay ends, and the steps'
    /// re-linearisations — a back-substitution, the rows, a forward solve, every 140 arrivals
    /// on a 50 000-pose world — were a fifth of a builder's time (`perf`, that world with 250
    /// false loop closures, back to back; `benches/MEASUREMENTS.md`, thirty-fourth session). The headings, and so every decision, do not depend on them.
    pub fn hold_positions(&mut self) {
        self.positions_held = true;
    }

    /// The end of [`Self::hold_positions`]: when the factors are built (not deferred), every
    /// position row re-linearised now at the current headings (rows and right-hand sides at
    /// once), as the replay's steps would have left them at the latest; a deferred estimate's
    /// build does it ([`Op::Rebuild`]).
    pub fn release_positions(&mut self, graph: &PoseGraph) {
        if !std::mem::take(&mut self.positions_held) || self.builds_later() {
            return;
        }
        self.apply_pending(graph);
        self.relinearise_now(graph);
    }

    /// Every position row re-linearised at the current headings, rows and the factor's
    /// right-hand sides at once (nothing left for a step): a caller's idle time
    /// ([`Self::maintain`]) and the end of a replay ([`Self::release_positions`]).
    fn relinearise_now(&mut self, graph: &PoseGraph) {
        self.relin_cancel();
        let edges = self.factors.position_rows();
        self.factors
            .relinearise_positions(graph, edges, &mut self.trig);
        with_factor!(&mut self.factors, both => both.flush_rhs());
        self.relinearised();
    }

    /// The re-linearisations' schedule counts from here: the live work spacing them
    /// ([`Self::relinearisation_paid`]) and the heading lag of a renewal in progress.
    fn relinearised(&mut self) {
        self.work_at_relinearisation = self.factors.positions_work().0;
        self.moved_at_renewal = 0.0;
    }

    /// Whether the steps' re-linearisations are held ([`Self::hold_positions`]).
    #[cfg(test)]
    pub fn positions_held(&self) -> bool {
        self.positions_held
    }

    /// Whether the two systems share one factor (every edge so far has proportional weights).
    #[cfg(test)]
    pub fn shared(&self) -> bool {
        matches!(self.factors, Factors::Shared { .. })
    }

    /// The headings' prediction of a loop closure a → b (`edge`, not yet in `graph`), from its
    /// heading row rotated in tentatively with no wrap (`y = δ`): the rotations leave
    /// `√w (δ − (θ̂_b − θ̂_a)) Πc` with `1/Πc² = 1 + w Var(θ̂_b − θ̂_a)`, `w = 1/σ²`. The row
    /// must then be kept ([`Self::keep_chord`], its wrap set by an [`Op::Wrap`]) or taken back
    /// ([`Self::undo_chord`]) before anything else. `None` (nothing done) when the factors are
    /// deferred, or the edge would widen a shared factor.
    pub fn try_chord(
        &mut self,
        graph: &PoseGraph,
        edge: &Edge,
        a: usize,
        b: usize,
    ) -> Option<Prediction> {
        // Not `sync`: within a deferral (a replay) the factors stay unbuilt.
        self.apply_pending(graph);
        let w = edge.sigma2().recip();
        let (w_pos, isotropic) = position_weight(edge);
        if self.factors.deferred() || !self.factors.keeps(w, w_pos, isotropic) {
            return None;
        }
        let (residual, cosines) = self.factors.try_edge((a, b), (w, w_pos), edge.delta())?;
        self.tried = Some((w, w_pos, isotropic));
        Some(Prediction {
            innovation: residual / (w.sqrt() * cosines),
            variance: edge.sigma2() / (cosines * cosines),
        })
    }

    /// Take over `old`'s factors (the estimate of the estimator a replay replaces): this
    /// estimate, deferred, builds its factors from them when they match
    /// ([`Laplacian::adopt`]), instead of from nothing — or from those `old` inherited, if it
    /// was itself a replay's not read since. Nothing when `old` has a loop closure tried and
    /// not yet kept or undone, or when this estimate builds no factors later (a rebuild beside
    /// built its own: module `online::rebuild`; `old`'s would be held for nothing).
    pub fn inherit(&mut self, old: &mut Estimate) {
        if old.tried.is_some() || !self.builds_later() {
            return;
        }
        self.inherited = if old.factors.deferred() {
            old.inherited.take()
        } else {
            Some(std::mem::take(&mut old.factors))
        };
    }

    /// Keep the loop closure of the last [`Self::try_chord`].
    pub fn keep_chord(&mut self) {
        let Some((w, w_pos, isotropic)) = self.tried.take() else {
            return;
        };
        self.factors.admit(w, w_pos, isotropic);
        with_factor!(&mut self.factors, both => both.keep_edge())
    }

    /// Take back the loop closure of the last [`Self::try_chord`].
    pub fn undo_chord(&mut self) {
        if self.tried.take().is_none() {
            return;
        }
        with_factor!(&mut self.factors, both => both.undo_edge())
    }

    /// Apply the pending operations (in order).
    pub fn sync(&mut self, graph: &PoseGraph) {
        self.apply_pending(graph);
        // A read within a deferral (the estimator's replays read nothing) builds the factors
        // then rather than reading unbuilt ones.
        self.factors
            .rebuild(graph, self.inherited.take(), &mut self.trig);
    }

    /// Apply the pending operations (in order), deferred ones to the rows only.
    fn apply_pending(&mut self, graph: &PoseGraph) {
        let pending = std::mem::take(&mut self.pending);
        for &op in &pending {
            match op {
                Op::Node => {
                    with_factor!(&mut self.factors, both => both.add_node());
                }
                Op::Edge { e, a, b, y } => {
                    let edge = &graph.edges()[e as usize];
                    let w = edge.sigma2().recip();
                    let (w_pos, isotropic) = position_weight(edge);
                    self.factors.admit(w, w_pos, isotropic);
                    // The position components come with the position row.
                    let (a, b) = (a as usize, b as usize);
                    self.factors.add_edge((a, b), (w, w_pos), y);
                }
                Op::Wrap { e, y } => with_factor!(&mut self.factors, both => {
                    let [_, px, py] = both.y(e as usize);
                    both.set_y(e as usize, [y, px, py]);
                }),
                Op::Position { e, a, b, y } => {
                    let edge = &graph.edges()[e as usize];
                    let (_, isotropic) = position_weight(edge);
                    self.anisotropic |= !isotropic;
                    if self.factors.deferred() {
                        // Its measurement comes with the rebuild, at the headings then.
                        continue;
                    }
                    let theta_a = if a > b {
                        self.factors.orientation(a as usize)
                    } else {
                        self.factors.orientation(b as usize) - y
                    };
                    let [px, py] = rotate(theta_a, edge.measurement());
                    with_factor!(&mut self.factors, both => {
                        let [heading, ..] = both.y(e as usize);
                        both.set_y(e as usize, [heading, px, py]);
                    })
                }
                Op::Step => self.after_step(graph),
                Op::Defer => {
                    self.relin_cancel();
                    self.factors.defer()
                }
                Op::Rebuild => self
                    .factors
                    .rebuild(graph, self.inherited.take(), &mut self.trig),
            }
        }
        self.pending = pending;
        self.pending.clear();
    }

    /// End of a step: renewals start or complete. A renewal of the factor takes every
    /// position row at the current headings (solved and written on its builder). Once the
    /// headings' bound passes [`HEADING_LAG`], a re-linearisation of the position rows starts
    /// and goes on over the next steps ([`Self::relinearise_over_steps`]).
    fn after_step(&mut self, graph: &PoseGraph) {
        let edges = self.factors.position_rows();
        let deferred = self.factors.deferred();
        let at_start = &mut self.moved_at_renewal;
        let store = &mut self.tails;
        let collected = with_factor!(&mut self.factors, both => {
            let event = both.after_step(|| {
                // The headings and the rows from them on the builder.
                let tails = tails_snapshot(store, graph, edges);
                Some(Box::new(relinearise::<3>(tails, edges, 1)))
            });
            track_lag(both, event, at_start);
            matches!(event, Some(RenewalEvent::Collected))
        });
        // A renewal swapped in brought rows at its snapshot's headings, and the bound from
        // there: a re-linearisation in progress is older.
        if deferred || self.positions_held || collected {
            self.relin_cancel();
            if deferred || self.positions_held {
                return;
            }
        }
        if self.relin.is_none() {
            if self.factors.headings_moved() <= HEADING_LAG || !self.relinearisation_paid(1.0) {
                return;
            }
            let moved = self.factors.headings_moved();
            with_factor!(&mut self.factors, both => both.back_start(0));
            self.relin = Some(Relin::Headings { moved, edges });
        }
        self.relinearise_over_steps(graph);
    }

    /// One step of the re-linearisation in progress: a block of the headings'
    /// back-substitution (module `estimate::incremental::back`, about an eighth of the
    /// factor), or, once they are solved, a block of the rows' position measurements (about a
    /// quarter of them) written into the factor's rows, the last handing them over; the factor's
    /// right-hand sides follow over the next steps ([`Laplacian::relinearise`]). Each block
    /// by the step's own work ([`Laplacian::step_share`]: more at a light step, less at a
    /// heavy one). So no step pays for a whole pass over the factor. The headings' blocks
    /// read the factor of their own steps, so the headings are those of the first block's
    /// step up to what the headings moved since (module `back`'s maximum principle), and the
    /// rows' lag after it is the bound's growth since that step. A renewal collected in
    /// between drops it (its rows are at its snapshot's headings, and the bound restarts
    /// there); a later step starts another if the bound is still passed.
    fn relinearise_over_steps(&mut self, graph: &PoseGraph) {
        match self.relin.take() {
            None => {}
            Some(Relin::Headings { moved, edges }) => {
                match with_factor!(&mut self.factors, both => both.back_advance()) {
                    // The factor was replaced (widened): a later step starts again.
                    None => {}
                    Some(false) => self.relin = Some(Relin::Headings { moved, edges }),
                    Some(true) => {
                        if let Some(theta) =
                            with_factor!(&mut self.factors, both => both.back_take())
                        {
                            self.relin = Some(Relin::Rows {
                                theta,
                                next: 0,
                                moved,
                                edges,
                            });
                        }
                    }
                }
            }
            Some(Relin::Rows {
                theta,
                next,
                moved,
                edges,
            }) => {
                // The rows are rewritten in place, a block per step: not while a spread still
                // gathers them for an earlier re-linearisation (none begins once the first
                // block is written; in practice none is in progress here).
                if next == 0 && with_factor!(&self.factors, both => both.rhs_lagging()) {
                    self.relin = Some(Relin::Rows {
                        theta,
                        next,
                        moved,
                        edges,
                    });
                    return;
                }
                let share = with_factor!(&self.factors, both => both.step_share());
                let block = ((edges / ROW_STEPS).max(MIN_ROW_BLOCK) as f64 * share)
                    .max((MIN_ROW_BLOCK / 4) as f64);
                let end = edges.min(next + block as usize);
                self.relin_rows.clear();
                for (a, z) in tails(graph, next..end) {
                    self.relin_rows.push(rotated(self.trig.at(a, theta[a]), z));
                }
                let rows = &self.relin_rows;
                with_factor!(&mut self.factors, both => {
                    for (y, &[px, py]) in both.measurements_mut(next..end).zip(rows) {
                        y[1] = px;
                        y[2] = py;
                    }
                });
                if end < edges {
                    self.relin = Some(Relin::Rows {
                        theta,
                        next: end,
                        moved,
                        edges,
                    });
                    return;
                }
                // Every row written: the factor's right-hand sides follow.
                let lag = (self.factors.headings_moved() - moved).max(0.0);
                with_factor!(&mut self.factors, both => {
                    both.relinearise(|_| {}, 1);
                    both.set_moved(0, lag);
                });
                self.relinearisations += 1;
                // (A renewal in progress takes these rows too: its bound counts from here.)
                self.relinearised();
            }
        }
    }

    /// Drop a re-linearisation in progress ([`Self::relinearise_over_steps`]).
    fn relin_cancel(&mut self) {
        if self.relin.take().is_some() {
            with_factor!(&mut self.factors, both => both.back_cancel());
        }
    }

    /// Room for `nodes` more nodes and `edges` more edges without growing the factor's arrays
    /// ([`crate::online::OnlineEstimator::reserve`]).
    pub fn try_reserve(
        &mut self,
        nodes: usize,
        edges: usize,
    ) -> Result<(), std::collections::TryReserveError> {
        with_factor!(&mut self.factors, both => both.try_reserve(nodes, edges))?;
        let len = with_factor!(&self.factors, both => both.len());
        let rows = self.factors.position_rows() + edges;
        (self.relin_rows).try_reserve(rows.saturating_sub(self.relin_rows.len()))?;
        (self.tails).try_reserve(rows.saturating_sub(self.tails.len()))?;
        self.trig.try_reserve(len + nodes)
    }

    /// Orientation of node v (O(1) for the newest).
    pub fn orientation(&mut self, graph: &PoseGraph, v: usize) -> f64 {
        self.sync(graph);
        self.factors.orientation(v)
    }

    /// Every orientation: one back-substitution.
    pub fn orientations(&mut self, graph: &PoseGraph) -> Vec<f64> {
        self.sync(graph);
        self.factors.orientations()
    }

    /// The fast pose of node v (see the module docs; O(1) for the newest).
    pub fn pose(&mut self, graph: &PoseGraph, v: usize) -> Pose2 {
        self.sync(graph);
        let [theta, x, y] = with_factor!(&mut self.factors, both => both.value(v));
        Pose2::new(x, y, theta)
    }

    /// Every pose, exact (see the module docs).
    pub fn poses(&mut self, graph: &PoseGraph) -> Result<Vec<Pose2>, EstimateError> {
        self.sync(graph);
        let theta = self.factors.orientations();
        if self.anisotropic {
            return crate::estimate::poses(graph, &theta);
        }
        let edges = self.factors.position_rows();
        let [x, y] = with_factor!(&mut self.factors, both => both.all_for(
            |y| write_relinearised(y, self.trig.of(&theta), tails(graph, 0..edges), 1),
            [1, 2],
        ));
        Ok((0..theta.len())
            .map(|v| Pose2::new(x[v], y[v], theta[v]))
            .collect())
    }

    /// Variance of node v's orientation relative to its anchor.
    pub fn orientation_variance(&mut self, graph: &PoseGraph, v: usize) -> f64 {
        self.sync(graph);
        with_factor!(&mut self.factors, both => both.variance(v)[0])
    }

    /// Variance of each coordinate of node v's position relative to its anchor (isotropic
    /// weights).
    pub fn position_variance(&mut self, graph: &PoseGraph, v: usize) -> f64 {
        self.sync(graph);
        match &mut self.factors {
            // The shared factor weighs the positions' rows by 1/λ of their weights.
            Factors::Shared { both, ratio } => both.variance(v)[0] / ratio.unwrap_or(1.0),
            Factors::Lanes { both } => both.variance(v)[1],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The headings' sines and cosines by their grid points are libm's to a few units in the
    /// last place, and the same bits whatever the memo held before.
    #[test]
    fn sines_and_cosines_from_the_grid_are_libms_and_do_not_depend_on_the_memo() {
        let mut s = 3u64;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut theta: Vec<f64> = (0..20_000)
            .map(|i| match i % 4 {
                0 => 2000.0 * (next() - 0.5),
                1 => 0.1 * (next() - 0.5),
                // On a grid point and next to it.
                2 => (next() * 1000.0).floor() * GRID,
                _ => (next() * 1000.0).floor() * GRID - 1e-17,
            })
            .collect();
        theta.extend([0.0, -0.0, GRID, -GRID, 1e-300, 3.0e15, -7.5e17, 1e300]);
        let mut fresh = Trig::default();
        let first = fresh.of(&theta).to_vec();
        for (&t, &(s, c)) in theta.iter().zip(&first) {
            let (ls, lc) = t.sin_cos();
            assert!(
                (s - ls).abs() <= 4e-16 && (c - lc).abs() <= 4e-16,
                "{t}: {s} {c}"
            );
        }
        // A memo that held other headings (moved by up to two grid steps): the same bits.
        let mut used = Trig::default();
        let moved: Vec<f64> = theta
            .iter()
            .map(|t| t + 2.0 * GRID * (next() - 0.5))
            .collect();
        used.of(&moved);
        let again = used.of(&theta);
        assert!(
            first
                .iter()
                .zip(again)
                .all(|(a, b)| { (a.0.to_bits(), a.1.to_bits()) == (b.0.to_bits(), b.1.to_bits()) })
        );
        let (s, c) = sin_cos_near(f64::NAN, &mut [f64::NAN; 3]);
        assert!(s.is_nan() && c.is_nan());
        let (s, c) = sin_cos_near(f64::INFINITY, &mut [f64::NAN; 3]);
        assert!(s.is_nan() && c.is_nan());
    }
    use crate::graph::{Information, NodePolicy};
    use crate::online::snapshot;

    impl Estimate {
        /// A factor of two lanes from the start (what the shared factor must equal).
        fn lanes() -> Self {
            Estimate {
                factors: Factors::Lanes {
                    both: Box::default(),
                },
                ..Estimate::default()
            }
        }
    }

    fn lcg(state: &mut u64) -> f64 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*state >> 11) as f64) / ((1u64 << 53) as f64)
    }

    /// A renewal's job reads each row's tail and translation from a store that copies each
    /// edge of the graph once and hands out copies sharing its chunks: what it hands out is
    /// the graph's, also across chunk boundaries, and a store that is not the graph's prefix
    /// (another graph) starts again.
    #[test]
    fn the_tails_store_is_the_graphs() {
        let info = |_: usize| Information::diagonal(30.0, 30.0, 4.0);
        let (mut graph, mut other) = (PoseGraph::new(), PoseGraph::new());
        let mut store = Chunked::default();
        let expected = |g: &PoseGraph, n: usize| tails(g, 0..n).collect::<Vec<_>>();
        let got = |c: &Chunked<(usize, Pose2)>| c.iter().copied().collect::<Vec<_>>();
        let edges = world(2_000, info);
        let mut seen = 0;
        for (i, edge) in edges.iter().enumerate() {
            graph.add_edge(*edge, NodePolicy::CreateUnknown).unwrap();
            if i % 397 == 0 {
                let snapshot = tails_snapshot(&mut store, &graph, i + 1);
                assert_eq!(got(&snapshot), expected(&graph, i + 1), "edge {i}");
                seen += 1;
            }
        }
        assert!(seen > 3 && store.len() > snapshot::CHUNK);
        // Another graph: its first edges' measurements differ.
        for edge in &edges[..10] {
            let e = Edge::new(edge.from(), edge.to(), Pose2::new(1.0, 2.0, 0.5), info(0));
            other
                .add_edge(e.unwrap(), NodePolicy::CreateUnknown)
                .unwrap();
        }
        let snapshot = tails_snapshot(&mut store, &other, 10);
        assert_eq!(got(&snapshot), expected(&other, 10));
    }

    /// Edges in robot order over `n` nodes: odometry, and a loop closure to an older node
    /// every third node; edge i has the information `info(i)`.
    fn world(n: u64, info: impl Fn(usize) -> Information) -> Vec<Edge> {
        let mut s = 5u64;
        let mut edges = Vec::new();
        for v in 1..n {
            let mut to_older = vec![v - 1];
            if v % 3 == 0 && v > 40 {
                to_older.push((lcg(&mut s) * (v - 10) as f64) as u64);
            }
            for u in to_older {
                let z = Pose2::new(lcg(&mut s) - 0.5, lcg(&mut s) - 0.5, lcg(&mut s) - 0.5);
                edges.push(Edge::new(u, v, z, info(edges.len())).unwrap());
            }
        }
        edges
    }

    /// Add step i's edge to `graph` and return the step's operations (with a wrap moved on
    /// some older edge every few steps; `s` the generator's state).
    fn step_ops(graph: &mut PoseGraph, i: usize, edge: Edge, s: &mut u64) -> Vec<Op> {
        let before = graph.node_count();
        let e = graph.add_edge(edge, NodePolicy::CreateUnknown).unwrap();
        let (a, b) = graph.endpoints()[e];
        let (e32, a, b) = (e as u32, a as u32, b as u32);
        let y = edge.delta();
        let mut ops: Vec<Op> = (before..graph.node_count()).map(|_| Op::Node).collect();
        ops.push(Op::Edge { e: e32, a, b, y });
        if i.is_multiple_of(7) && e > 0 {
            let c = (lcg(s) * e as f64) as usize;
            let y = graph.edges()[c].delta() - std::f64::consts::TAU;
            ops.push(Op::Wrap { e: c as u32, y });
        }
        ops.extend([Op::Position { e: e32, a, b, y }, Op::Step]);
        ops
    }

    /// Stream the edges into every estimate and compare each with the first after every
    /// step.
    fn stream(edges: &[Edge], ests: &mut [Estimate]) {
        let mut graph = PoseGraph::new();
        let mut s = 11u64;
        for (i, edge) in edges.iter().enumerate() {
            let ops = step_ops(&mut graph, i, *edge, &mut s);
            for est in ests.iter_mut() {
                for &op in &ops {
                    est.push(op);
                }
            }
            let (first, rest) = ests.split_first_mut().unwrap();
            let newest = graph.node_count() - 1;
            let want = first.pose(&graph, newest);
            for est in rest {
                // The fast positions are re-linearised whenever the factor is renewed (at
                // different steps with one lane or two): equal until the first renewal.
                let got = est.pose(&graph, newest);
                let close = |a: f64, b: f64| (a - b).abs() < 1e-9;
                let fast_equal = first.renewals().0 + est.renewals().0 > 0
                    || close(got.x, want.x) && close(got.y, want.y);
                assert!(
                    fast_equal && close(got.theta, want.theta),
                    "step {i}: {got:?} vs {want:?}"
                );
                if i % 50 == 0 || i + 1 == edges.len() {
                    let v = (lcg(&mut s) * newest as f64) as usize;
                    let pairs = [
                        (est.orientation(&graph, v), first.orientation(&graph, v)),
                        (
                            est.orientation_variance(&graph, v),
                            first.orientation_variance(&graph, v),
                        ),
                        (
                            est.position_variance(&graph, v),
                            first.position_variance(&graph, v),
                        ),
                    ];
                    for (g, w) in pairs {
                        assert!(
                            (g - w).abs() < 1e-9 * w.abs().max(1.0),
                            "{i} {v}: {g} vs {w}"
                        );
                    }
                    let (all, want_all) =
                        (est.poses(&graph).unwrap(), first.poses(&graph).unwrap());
                    for (g, w) in all.iter().zip(&want_all) {
                        assert!(close(g.x, w.x) && close(g.y, w.y) && close(g.theta, w.theta));
                    }
                }
            }
        }
    }

    /// Position weights 3× the heading weights on every edge (two kinds of edges): one
    /// shared factor all along (renewals included), with the answers of a factor of two
    /// lanes.
    #[test]
    fn a_shared_factor_equals_a_factor_of_two_lanes() {
        let info = |i: usize| {
            let (t, xy) = if i.is_multiple_of(5) {
                (4.0, 12.0)
            } else {
                (50.0, 150.0)
            };
            Information::diagonal(xy, xy, t)
        };
        let edges = world(700, info);
        let mut ests = [Estimate::lanes(), Estimate::default()];
        stream(&edges, &mut ests);
        assert!(ests[1].shared() && !ests[0].shared());
        assert!(ests[1].renewals().0 > 0, "the shared factor was renewed");
    }

    /// The first edge whose weights break the proportion widens the shared factor to two
    /// lanes, which go on with the answers of two lanes from the start; an anisotropic edge
    /// widens it too.
    #[test]
    fn a_shared_factor_widens_at_the_first_disproportionate_edge() {
        for (at, odd) in [
            (400, Information::diagonal(30.0, 30.0, 4.0)),
            (350, Information([30.0, 2.0, 0.0, 31.0, 0.0, 10.0])),
        ] {
            let info = |i: usize| {
                if i == at {
                    odd
                } else {
                    Information::diagonal(150.0, 150.0, 50.0)
                }
            };
            let edges = world(600, info);
            let mut ests = [Estimate::lanes(), Estimate::default()];
            stream(&edges, &mut ests);
            assert!(!ests[1].shared());
            // And it was shared until that edge.
            let mut ests = [Estimate::lanes(), Estimate::default()];
            stream(&edges[..at], &mut ests);
            assert!(ests[1].shared());
        }
    }

    /// A replay defers the factors' work ([`Op::Defer`]) and builds them at its end
    /// ([`Op::Rebuild`]): the answers then equal those of the factors kept through every
    /// step (exact poses, orientations, variances), the fast poses are the exact ones (every
    /// position row at the headings of the rebuild), and later steps go on incrementally —
    /// with one shared factor, two lanes, and a shared factor that widens within the replay.
    #[test]
    fn a_replay_builds_its_factors_at_its_end() {
        let shared = |_: usize| Information::diagonal(150.0, 150.0, 50.0);
        let splits = |i: usize| {
            if i == 300 {
                Information::diagonal(30.0, 30.0, 4.0)
            } else {
                shared(i)
            }
        };
        for (edges, two) in [
            (world(600, shared), false),
            (world(600, shared), true),
            (world(600, splits), false),
        ] {
            let fresh = || {
                if two {
                    Estimate::lanes()
                } else {
                    Estimate::default()
                }
            };
            let (mut live, mut replayed) = (fresh(), fresh());
            replayed.push(Op::Defer);
            let mut graph = PoseGraph::new();
            let mut s = 11u64;
            let (replay, after) = edges.split_at(500);
            for (i, edge) in replay.iter().enumerate() {
                for op in step_ops(&mut graph, i, *edge, &mut s) {
                    live.push(op);
                    replayed.push(op);
                }
                // The live one is read after every step (as a robot does).
                live.pose(&graph, graph.node_count() - 1);
            }
            replayed.push(Op::Rebuild);
            let close = |a: f64, b: f64| (a - b).abs() < 1e-9 * a.abs().max(1.0);
            let exact = replayed.poses(&graph).unwrap();
            for (v, p) in exact.iter().enumerate() {
                let fast = replayed.pose(&graph, v);
                assert!(close(fast.x, p.x) && close(fast.y, p.y) && close(fast.theta, p.theta));
            }
            for (g, w) in exact.iter().zip(&live.poses(&graph).unwrap()) {
                assert!(close(g.x, w.x) && close(g.y, w.y) && close(g.theta, w.theta));
            }
            // Later steps: incremental again, with the answers of the live factors.
            for (i, edge) in after.iter().enumerate() {
                for op in step_ops(&mut graph, 500 + i, *edge, &mut s) {
                    live.push(op);
                    replayed.push(op);
                }
                let v = graph.node_count() - 1;
                assert!(close(
                    replayed.orientation(&graph, v),
                    live.orientation(&graph, v)
                ));
            }
            let v = graph.node_count() / 2;
            assert!(close(
                replayed.orientation_variance(&graph, v),
                live.orientation_variance(&graph, v)
            ));
            assert!(close(
                replayed.position_variance(&graph, v),
                live.position_variance(&graph, v)
            ));
            for (g, w) in (replayed.poses(&graph).unwrap().iter()).zip(&live.poses(&graph).unwrap())
            {
                assert!(close(g.x, w.x) && close(g.y, w.y) && close(g.theta, w.theta));
            }
            assert_eq!(replayed.shared(), live.shared());
        }
    }
}
