//! A weighted-Laplacian least-squares problem kept factored as edges arrive: the orientation
//! estimate a robot reads after every step, and the positions given the orientations.
//!
//! Both are scalar problems on one weighted graph Laplacian (`K` right-hand sides in `L`
//! lanes: systems on the same graph with other weights, factored in one order, module
//! `estimate::incremental`),
//!
//! ```text
//! min_x Σ_e w_e ‖x_b − x_a − y_e‖²,
//! orientations (K = 1):  y_e = δ_e − 2π k_e,   w_e = 1/σ_e²,
//! positions    (K = 2):  y_e = R(θ_a) t_e,     w_e = the translation information,
//! ```
//!
//! with one anchor per connected component (its first node, x = 0, as in
//! [`OrientationEstimator`](crate::estimate::OrientationEstimator)). It is kept as a square-root
//! information factor `R x = d` ([`SqrtInfo`]): every edge is the row
//! `√w_e (x_b − x_a) = √w_e y_e`, every anchor a prior row `√w x_a = 0` (which leaves the
//! anchored solution unchanged: the Laplacian part is invariant to a shift of a component; its
//! weight is that of the component's first edge, so the common mode is as well determined as
//! the differences). The events that change it:
//!
//! - a new node: a variable appended at the end of the order (so the newest node is read in
//!   O(1): `θ_n = d_n / R_nn`);
//! - a new edge (tree edge or chord): its row, rotated in along the elimination-tree path of
//!   its older end;
//! - two components joined: the later anchor's prior row is removed (a down-date);
//! - an edge whose `y_e` changed (a chord's wrap after a re-screening, a heading that moved):
//!   only its right-hand side moves (for the edge just added, by the gains its rotations
//!   recorded: how the shared factor of [`super::estimate`] takes an edge's position
//!   right-hand side after its heading row).
//!
//! [`Laplacian::widen`] turns a one-lane system into one of several lanes, the weights of each
//! scaled (how a factor shared by headings and positions takes them in two lanes when their
//! weights stop being proportional).
//!
//! **Renewing the order without a stall.** New nodes are appended at the end, so revisits of old
//! places make R fill in, and the nodes appended since the last renewal form a chain that every
//! loop closure to an older node walks. When R's nonzeros per row have grown by half (by a fifth
//! from 20 000 variables: [`FILL_RATIO_LARGE`]), or an eighth of the nodes were appended, since the
//! last renewal, a new factor is built **beside** the live one on another thread: approximate
//! minimum-degree order with the newest node last (the graph as it was at that step; from 20 000
//! variables four levels of nested dissection above it, [`dissected_order`], the separators
//! computed afresh only once the graph has grown by a quarter and the nodes added since placed in
//! the last renewal's tree otherwise, a renewal that splits afresh due [`SPLIT_BUILD`] times
//! later), the normal
//! equations factored at once by a sparse Cholesky ([`SqrtInfo::factored`], supernodal on large
//! factors; rows rotated in when extreme weights defeat it). Every later change (node, row, removed
//! prior, moved right-hand side) is sent to the builder, a step's changes together at its end
//! (one lock and one wake-up: `strace -f -c` of `so2lin stream M3500.g2o --json` counted 7 251
//! futex calls against 13 942 when each change went alone), which applies
//! them to its factor as they come, so the live factor's steps replay nothing
//! ([`super::renewal`]). The new factor is
//! collected once the live factor has done [`work_per_nonzero`] units of its own work
//! ([`SqrtInfo::take_work`]; 96 up to M3500's 3 500 nodes, growing to 144 at 5 500, 120 from
//! 20 000) per nonzero the renewed factor is expected to have (the last renewal's fill per row
//! times the variables), and at least [`MIN_DELAY`] steps after the start — counts, not clocks, so
//! the run stays deterministic whatever the threads' timing; the step waits only if the builder is
//! still busy then — and swapped in. Every answer in between comes from the live factor: exact at
//! every step.

use super::renewal::{Beside, Due, Worker};
use crate::estimate::incremental::{
    Dissection, Lanes, Leftover, SqrtInfo, dissected_order, fill_reducing_order, lane,
};
use crate::graph::UnionFind;
use std::sync::Arc;

/// Renew the order when R's nonzeros per row exceed this multiple of the last renewal's
/// ([`fill_ratio`]: below [`LARGE_FACTOR`] variables).
const FILL_RATIO: f64 = 1.5;
/// [`FILL_RATIO`] from [`LARGE_FACTOR`] variables on: a renewal starts sooner after the last one
/// was collected. On large worlds the renewals' builder sat idle for most of the time between them
/// (on the 100 000-pose world, collected 100–200 nodes after they started, then about 900 nodes
/// before the next began), while the loop closures' work grew with the age of the order (mean 187 k
/// entries in the first 100 steps after a collection, 364 k after 800, 794 k beyond 900; the
/// slowest 1 % of the steps, 1 619 of 1 685, all beyond 900). Measured (`so2lin stream FILE
/// --json`, robot order, the newest pose read after every step, the renewals supernodal where they
/// pay, alternating runs, 2026-12-05; at 1.2 against 1.5): the 100 000-pose world p99 4.5–5.5
/// against 7.0–7.8 ms, worst step 27–28 against 40–54 ms, 82–99 against 112–136 s of steps (two
/// runs against four); a 30 000-pose world p99 1.68 against 1.87 ms, 7.1 against 7.9 s (six runs);
/// but a 10 000-pose world 578 against 538 µs (eight), city10000 239 against 218 µs (ten) and
/// M3500 120 against 126 µs (twelve): within their noise, so the smaller factors keep 1.5.
const FILL_RATIO_LARGE: f64 = 1.2;
/// Variables from which [`FILL_RATIO_LARGE`] and [`LARGE_SIZE`] apply, and renewals order by
/// nested dissection ([`BuildOrder::Dissected`]). Below it dissection did not pay (`so2lin stream
/// M3500.g2o --json`, robot order, the newest pose read after every step, 2026-12-05): from 256
/// variables the estimate's work was 39.5 M values against 33.5 M for minimum degree alone (its
/// fresh splits, due twice as late, come at nearly every renewal of a small graph), p99 167
/// against 148 µs; with fresh splits due as the others 32.0 M, p99 144 µs but a worst step of
/// 2.1 ms (three runs each); city10000 changed by 6 % or less and its builds took longer.
const LARGE_FACTOR: usize = 20_000;

/// [`work_per_nonzero`]'s size factor from [`LARGE_FACTOR`] variables (1.5 below, from 5 500):
/// large factors' renewals are collected sooner. Their builds cost less per nonzero than the
/// rule's `^0.8` assumed once the largest are supernodal ([`SqrtInfo::factored`]), and with
/// renewals starting sooner ([`FILL_RATIO_LARGE`]) each build has fewer changes to catch up.
/// Measured (`so2lin stream FILE --json`, robot order, the newest pose read after every step,
/// alternating runs, 2026-12-05; at 1.25 against 1.5): the 100 000-pose world p99 4.0–4.7
/// against 4.5–5.4 ms (medians 4.4 and 4.9), worst step 25–28 against 34–39 ms, 71–83 against
/// 80–92 s of steps, 4–17 waits against 4–21 (four runs against five); a 30 000-pose world
/// (simplicial builds) p99 1.45 against 1.60 ms, 6.2 against 6.6 s, 4.5 waits against 9.5 (six
/// runs each). At 1.0 the 100 000-pose world's builder fell behind: 41–44 waits, a worst step
/// of 68 ms in one of two runs (p99 3.9–4.0 ms).
const LARGE_SIZE: f64 = 1.25;

/// How much later a renewal that splits its graph afresh ([`BuildOrder::Dissected`] without a
/// tree) is due, as a factor on the work due: its separators cost about as much again as the
/// rest of its build (about 200 ms against 100 ms for the minimum degree on the 100 000-pose
/// world). Measured (`so2lin stream FILE --json`, robot order, the newest pose read after every
/// step, two runs each alternating, 2026-12-05), on the 100 000-pose world: at 2 the worst step
/// 41–42 ms with 12 waits, at 1 53–72 ms with 20–22 (p99 3.9 ms and 3.6–4.1 ms).
const SPLIT_BUILD: f64 = 2.0;

/// The fill growth per row that starts a renewal of a factor of `n` variables.
fn fill_ratio(n: usize) -> f64 {
    if n >= LARGE_FACTOR {
        FILL_RATIO_LARGE
    } else {
        FILL_RATIO
    }
}

/// Renew when more than `1/APPENDED_FRACTION` of the nodes were appended since the last
/// renewal.
const APPENDED_FRACTION: usize = 8;
/// Below this many variables the order is never renewed.
const MIN_VARIABLES: usize = 256;
/// Steps between starting a renewal and collecting it, at least.
pub(crate) const MIN_DELAY: u64 = 32;
/// Work of the live factor ([`SqrtInfo::take_work`], entries visited) between starting a
/// renewal and collecting it, per nonzero expected in the renewed factor. Measured on M3500,
/// city10000 and a 10 000-pose simulated world: a build (its fill-reducing order included)
/// takes 70–150 ns per nonzero of the factor it builds, the live factor 2–6 ns per entry
/// visited, and the screening's builder may share the builder's core. Counting the live
/// factor's work instead of steps keeps the collection in step with the builder when the live
/// steps grow slow (a delay in steps let a 10 000-pose world's live factor fill for hundreds
/// of milliseconds while its steps slowed down, and the builders of M3500 were waited for at
/// 50 of its 5 453 steps, up to 2.4 ms). 96 rather than 64 since the screening takes its
/// moments from this factor (module `online::predict`): with no P_UU solve between rotations
/// the live factor does this work sooner, and at 64 the collections waited (the 100 000-pose
/// world's worst step 158–173 ms in 35–38 waits, against 29–92 ms in 5 at 96; M3500's over 2 ms
/// in 6 of 14 runs, against 1 of 12; `so2lin stream FILE --json`, robot order, the newest pose
/// read after every step), at a cost of 5–20 % in p99 and stream time. Since rows are rotated
/// over contiguous values (module `estimate::incremental`, 2026-12-04) the live factor does a
/// unit of work a third faster, and on the larger graphs the builders fell behind: city10000
/// waited at 34–38 collections (worst step 3.6–4.1 ms) against 2–4 before, and at 144 units
/// per nonzero at 5–7 (1.1–1.5 ms, p99 0.72× before). M3500's builds keep up at 96 (p99 0.88×
/// before; at 144 its p99 was 1.07×: the live factor fills for longer). So the constant grows
/// with the factor, [`work_per_nonzero`].
const WORK_PER_NONZERO: f64 = 96.0;

/// [`WORK_PER_NONZERO`] for a factor of `n` variables: × `(n / 3 500)^0.8`, between 1 (M3500's
/// size and below) and 1.5 (from about 5 500 variables). A build's cost per nonzero grows with
/// the factor (its order's and the caches'), the live factor's work per unit of time falls.
/// (With `^0.4`, 1.5 from 10 000 variables: city10000 waited at 17–19 collections against 10
/// with `^0.8`, four alternating runs.) From [`LARGE_FACTOR`] variables, [`LARGE_SIZE`].
fn work_per_nonzero(n: usize, lanes: usize) -> f64 {
    let size = if n >= LARGE_FACTOR {
        LARGE_SIZE
    } else {
        (n as f64 / 3_500.0).powf(0.8).clamp(1.0, 1.5)
    };
    WORK_PER_NONZERO * size * (1.0 + size * EXTRA_LANE_BUILD * lanes.saturating_sub(1) as f64)
}

/// What each lane beyond the first adds to a renewal's build, relative to the live work of
/// that lane (which [`SqrtInfo::take_work`] counts per value, so a two-lane factor's work
/// comes twice as fast), at M3500's size; it grows with the factor as the build's cost per
/// nonzero does ([`work_per_nonzero`]'s size factor): a build of two lanes makes one order and
/// one symbolic factorization for both, but twice the numeric work, and rotates two lanes. Measured
/// (`so2lin stream FILE --json`, robot order, the newest pose read after every step,
/// alternating runs, 2026-12-05): on M3500 at 0 its collections waited for the builder and
/// the worst step was 2.4–3.1 ms in a slow hour (1.4–1.9 ms in a quiet one); at 0.15
/// 1.1–2.6 ms; at 0.3 0.9–1.2 ms (0.45–0.86), against 0.5–0.65 ms for the two one-lane
/// factors this replaced. On ais2klinik (15 115 poses) a flat 0.3 left the worst step at
/// 2.7–8.5 ms (over 2 ms in 7 of 8 runs, against 3 of 8 for the two factors); grown with the
/// size, 1.4–3.5 ms (1 of 8), p99 289–291 against 345–358 µs.
const EXTRA_LANE_BUILD: f64 = 0.3;

/// A change to the system, sent to a renewal's builder so that it keeps its copy up to date
/// itself (the live factor's steps replay nothing).
pub(crate) enum Msg<const K: usize, const L: usize> {
    /// A new variable.
    Variable(u32),
    /// An anchor's prior row added.
    Prior((usize, [f64; L])),
    /// An anchor's prior row removed.
    Unprior((usize, [f64; L])),
    /// An edge: its ends, √w (per lane) and y.
    Edge(u32, u32, [f64; L], [f64; K]),
    /// Edge e's y is now this.
    SetY(u32, [f64; K]),
    /// Every edge's y is now this (a re-linearisation: [`Laplacian::relinearise`]).
    Relinearised(Vec<[f64; K]>),
}

/// What [`Laplacian::after_step`] did with the factor's renewal.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum RenewalEvent {
    /// A renewal started: its snapshot takes the rows as re-linearised then.
    Started,
    /// A renewal was swapped in: the live rows are now its snapshot's, with every change since.
    Collected,
}

/// What a renewal's builder returns: its factor, the right-hand sides it holds, and the
/// dissection its order came from (large factors).
type Built<const K: usize, const L: usize> = (SqrtInfo<K, L>, Vec<[f64; K]>, Option<Dissection>);

/// A renewal builder's state: its factor, its copy of the rows, its dissection.
type Building<const K: usize, const L: usize> = (SqrtInfo<K, L>, Rows<K, L>, Option<Dissection>);

/// A job that rewrites (some of) the measurements `y` of a renewal's snapshot, run by the
/// builder.
pub(crate) type Relinearise<const K: usize> = Box<dyn FnOnce(&mut [[f64; K]]) + Send>;

/// A renewal of a Laplacian's factor in progress.
type Renewal<const K: usize, const L: usize> = Beside<Building<K, L>, Built<K, L>, Msg<K, L>>;

/// How a build orders the variables.
enum BuildOrder {
    /// Approximate minimum degree ([`fill_reducing_order`]).
    MinimumDegree,
    /// Nested dissection ([`dissected_order`]): the variables placed in the given tree, or a
    /// fresh split.
    Dissected(Option<Arc<Dissection>>),
}

/// The data a factor is built from (a snapshot goes to the builder thread).
#[derive(Clone)]
struct Rows<const K: usize, const L: usize> {
    ends: Vec<(u32, u32)>,
    /// `√w_e` of every edge, per lane.
    sqrt_w: Vec<[f64; L]>,
    /// `y_e` of every edge.
    y: Vec<[f64; K]>,
}

impl<const K: usize, const L: usize> Default for Rows<K, L> {
    fn default() -> Self {
        Self {
            ends: Vec::new(),
            sqrt_w: Vec::new(),
            y: Vec::new(),
        }
    }
}

impl<const K: usize, const L: usize> Rows<K, L> {
    fn entries(&self, e: usize) -> [(usize, [f64; L]); 2] {
        let (a, b) = self.ends[e];
        let s = self.sqrt_w[e];
        [(a as usize, s.map(|s| -s)), (b as usize, s)]
    }

    fn rhs(&self, e: usize) -> [f64; K] {
        std::array::from_fn(|q| self.sqrt_w[e][lane::<L>(q)] * self.y[e][q])
    }

    /// How edge e's right-hand side moves when its measurement goes from `old` to `new`.
    fn shift(&self, e: usize, old: [f64; K], new: [f64; K]) -> [f64; K] {
        std::array::from_fn(|q| self.sqrt_w[e][lane::<L>(q)] * (new[q] - old[q]))
    }
}

/// The incrementally factored Laplacian system (see the module docs).
pub(crate) struct Laplacian<const K: usize, const L: usize = 1> {
    factor: SqrtInfo<K, L>,
    rows: Rows<K, L>,
    components: UnionFind,
    /// Anchor (least node index) of each union-find root.
    anchor: Vec<usize>,
    /// The weight of each node's anchor prior (0: none). The prior takes the square-root
    /// weight of the component's first edge, so the component's common mode is as well
    /// determined as its differences (a weak prior would collect the rounding errors there).
    prior: Vec<[f64; L]>,
    /// The prior weight each node was (or would be) given as an anchor.
    first_weight: Vec<[f64; L]>,
    fill_after_renewal: f64,
    /// Nodes at the last renewal (its snapshot).
    nodes_at_renewal: usize,
    renewal: Option<(Renewal<K, L>, Due)>,
    /// Changes for the renewal's builder not handed over yet ([`Self::post`]).
    outbox: Vec<Msg<K, L>>,
    /// The live factor's work so far ([`SqrtInfo::take_work`]).
    work: u64,
    /// The thread that builds renewals and frees retired factors.
    worker: Worker,
    steps: u64,
    /// The edge whose row was the last one rotated into the factor, while no row was added
    /// or removed since (its right-hand side moves by [`SqrtInfo::shift_last_row`]).
    last_edge: Option<usize>,
    /// Changes go to the rows only, the factor is built at [`Self::rebuild`] (a replay).
    deferred: bool,
    /// The right-hand sides from this one on lag the rows' measurements (re-linearised, see
    /// [`Self::relinearise`]) until the next [`Self::after_step`] recomputes them.
    stale_rhs: Option<usize>,
    /// A bound on how far any node's anchored value has moved, per right-hand side, since
    /// [`Self::set_moved`] last set it ([`Self::moved`]).
    moved: [f64; K],
    /// The [`Leftover`] of the row tried last ([`Self::try_edge`]).
    tried: Option<Leftover<K, L>>,
    /// The last row added ([`Self::last_edge`]): how far it has moved its own difference
    /// `x_b − x_a` (signed, per right-hand side) and its [`Leftover::gain`], so that a later
    /// shift of its right-hand side (the wrap a kept loop closure takes) counts net.
    last_moved: ([f64; K], [f64; L]),
    /// The dissection of the last renewal ordered by one ([`BuildOrder::Dissected`]), in which
    /// the next places the nodes added since.
    dissection: Option<Arc<Dissection>>,
    /// Renewals from this many variables order by nested dissection ([`LARGE_FACTOR`]).
    dissect_from: usize,
    /// The work a renewal is collected after, as a multiple of [`work_per_nonzero`]'s
    /// ([`Self::set_renewal_delay`]).
    renewal_delay: f64,
    /// Renewals completed.
    pub renewals: usize,
    /// Steps that waited for a renewal's builder.
    pub waits: usize,
}

impl<const K: usize, const L: usize> Default for Laplacian<K, L> {
    fn default() -> Self {
        Self {
            factor: SqrtInfo::new(),
            rows: Rows::default(),
            components: UnionFind::new(0),
            anchor: Vec::new(),
            prior: Vec::new(),
            first_weight: Vec::new(),
            fill_after_renewal: 0.0,
            nodes_at_renewal: 0,
            renewal: None,
            outbox: Vec::new(),
            work: 0,
            worker: Worker::default(),
            steps: 0,
            last_edge: None,
            dissection: None,
            dissect_from: LARGE_FACTOR,
            renewal_delay: 1.0,
            deferred: false,
            stale_rhs: None,
            moved: [0.0; K],
            tried: None,
            last_moved: ([0.0; K], [0.0; L]),
            renewals: 0,
            waits: 0,
        }
    }
}

impl<const K: usize, const L: usize> Laplacian<K, L> {
    /// Number of nodes.
    pub fn len(&self) -> usize {
        self.anchor.len()
    }

    /// Room for `nodes` more nodes and `edges` more edges without growing its arrays; a
    /// renewal's factor is built with the same room.
    pub fn try_reserve(
        &mut self,
        nodes: usize,
        edges: usize,
    ) -> Result<(), std::collections::TryReserveError> {
        self.rows.ends.try_reserve(edges)?;
        self.rows.sqrt_w.try_reserve(edges)?;
        self.rows.y.try_reserve(edges)?;
        self.components.try_reserve(nodes)?;
        self.anchor.try_reserve(nodes)?;
        self.prior.try_reserve(nodes)?;
        self.first_weight.try_reserve(nodes)?;
        self.factor.try_reserve(nodes)?;
        Ok(())
    }

    /// The room [`Self::try_reserve`] left: (nodes, edges).
    pub fn room(&self) -> (usize, usize) {
        let edges = (self.rows.ends.capacity())
            .min(self.rows.sqrt_w.capacity())
            .min(self.rows.y.capacity());
        let nodes = (self.factor.capacity())
            .min(self.prior.capacity())
            .min(self.first_weight.capacity());
        (
            nodes.saturating_sub(self.len()),
            edges.saturating_sub(self.rows.ends.len()),
        )
    }

    /// Tell a renewal's builder (if any) about a change: queued here, and handed over with
    /// the step's others at its end ([`Self::post`]).
    fn send(&mut self, msg: Msg<K, L>) {
        if self.renewal.is_some() {
            self.outbox.push(msg);
        }
    }

    /// Hand the step's changes to the renewal's builder at once: one lock, and one wake-up
    /// when it waits for them, per step rather than per change (a wake-up is a system call,
    /// and the builder's thread woke for each). A builder that is gone abandons the renewal
    /// (the live factor goes on).
    fn post(&mut self) {
        if self.outbox.is_empty() {
            return;
        }
        if let Some((r, _)) = &self.renewal
            && !r.send_all(self.outbox.drain(..))
        {
            self.drop_renewal();
        }
    }

    /// Abandon the renewal in progress (if any) and the changes queued for it.
    fn drop_renewal(&mut self) {
        self.renewal = None;
        self.outbox.clear();
    }

    /// A new node (index = current count).
    pub fn add_node(&mut self) -> usize {
        let v = self.components.push();
        self.anchor.push(v);
        self.prior.push([0.0; L]);
        self.first_weight.push([0.0; L]);
        if !self.deferred {
            self.factor.push_variable(v);
            self.send(Msg::Variable(v as u32));
        }
        v
    }

    /// Number of edges.
    pub fn edge_count(&self) -> usize {
        self.rows.ends.len()
    }

    /// A new edge from node a to b with weight w (per lane) and measurement y.
    pub fn add_edge(&mut self, a: usize, b: usize, w: impl Lanes<L>, y: [f64; K]) {
        let e = self.push_row(a, b, w, y);
        let (ra, rb) = (self.components.find(a), self.components.find(b));
        let (aa, ab) = (self.anchor[ra], self.anchor[rb]);
        let (winner, loser) = (aa.min(ab), aa.max(ab));
        let live = !self.deferred;
        if self.prior[winner] == [0.0; L] {
            self.first_weight[winner] = self.rows.sqrt_w[e];
            self.prior[winner] = self.rows.sqrt_w[e];
            let prior = (winner, self.prior[winner]);
            if live {
                self.factor.add_row(&[prior], [0.0; K]);
                self.send(Msg::Prior(prior));
            }
        }
        if live {
            let left = self.factor.add_row(&self.rows.entries(e), self.rows.rhs(e));
            self.note_row(left, e);
            self.last_edge = Some(e);
            self.send(Msg::Edge(a as u32, b as u32, self.rows.sqrt_w[e], y));
        }
        if ra != rb {
            self.components.union(a, b);
            let r = self.components.find(a);
            self.anchor[r] = winner;
            let p = self.prior[loser];
            if p != [0.0; L] {
                self.prior[loser] = [0.0; L];
            }
            if p != [0.0; L] && live {
                // The joined component's values are now relative to another anchor. (The joining
                // row's own movement covers that shift, measured; not relied upon.)
                self.moved = [f64::INFINITY; K];
                self.last_edge = None;
                self.send(Msg::Unprior((loser, p)));
                if self.factor.remove_row(&[(loser, p)], [0.0; K]).is_err() {
                    // Numerically the prior was the only information left: rebuild now.
                    self.drop_renewal();
                    let n = self.len();
                    self.factor =
                        build(&self.rows, &self.prior, n, None, BuildOrder::MinimumDegree).0;
                }
            }
        }
    }

    /// Add edge a → b like [`Self::add_edge`], tentatively: its row is rotated in and the
    /// [`Leftover`] returned, to be kept ([`Self::keep_edge`]) or taken back
    /// ([`Self::undo_edge`]) before any other change. `None` (nothing done) unless the factor is
    /// live and a and b are already joined with their component anchored: a loop closure.
    pub fn try_edge(
        &mut self,
        a: usize,
        b: usize,
        w: impl Lanes<L>,
        y: [f64; K],
    ) -> Option<Leftover<K, L>> {
        let root = self.components.find(a);
        if self.deferred
            || root != self.components.find(b)
            || self.prior[self.anchor[root]] == [0.0; L]
        {
            return None;
        }
        let e = self.push_row(a, b, w, y);
        let left = self.factor.try_row(&self.rows.entries(e), self.rows.rhs(e));
        self.tried = Some(left);
        Some(left)
    }

    /// Record edge a → b's row (weight w, measurement y) among the rows; its index.
    fn push_row(&mut self, a: usize, b: usize, w: impl Lanes<L>, y: [f64; K]) -> usize {
        self.rows.ends.push((a as u32, b as u32));
        self.rows.sqrt_w.push(w.lanes().map(f64::sqrt));
        self.rows.y.push(y);
        self.rows.ends.len() - 1
    }

    /// Keep the edge of the last [`Self::try_edge`].
    pub fn keep_edge(&mut self) {
        self.factor.keep_row();
        let e = self.rows.ends.len() - 1;
        if let Some(left) = self.tried.take() {
            self.note_row(left, e);
        }
        self.last_edge = Some(e);
        let (a, b) = self.rows.ends[e];
        self.send(Msg::Edge(a, b, self.rows.sqrt_w[e], self.rows.y[e]));
    }

    /// Take back the edge of the last [`Self::try_edge`]: the system as before it.
    pub fn undo_edge(&mut self) {
        self.tried = None;
        self.factor.undo_row();
        self.rows.ends.pop();
        self.rows.sqrt_w.pop();
        self.rows.y.pop();
    }

    /// Set the measurement of edge e (only its right-hand side moves).
    pub fn set_y(&mut self, e: usize, y: [f64; K]) {
        let old = self.rows.y[e];
        if old == y {
            return;
        }
        self.rows.y[e] = y;
        if self.deferred {
            return;
        }
        let shift = self.rows.shift(e, old, y);
        if self.last_edge == Some(e) && self.factor.shift_last_row(shift) {
            // The last row's difference moves by gain·Δy: counted net of what the row moved.
            let (signed, gain) = self.last_moved;
            for q in 0..K {
                let now = signed[q] + gain[lane::<L>(q)] * (y[q] - old[q]);
                self.moved[q] += now.abs() - signed[q].abs();
                self.last_moved.0[q] = now;
            }
        } else {
            // Its difference moves by w·Var·Δy, w·Var < 1 with its row in.
            self.factor.shift_rhs(&self.rows.entries(e), shift);
            for q in 0..K {
                self.moved[q] += (y[q] - old[q]).abs();
            }
        }
        self.send(Msg::SetY(e as u32, y));
    }

    /// Add the change of edge e's difference `x_b − x_a` that its new row made to the bound
    /// [`Self::moved`]: the change of the solution caused by one row (or one moved
    /// measurement) is a potential driven between a and b (harmonic elsewhere, each
    /// component held at its anchor), so by the maximum principle no node's anchored value
    /// moves by more than `|Δ(x_b − x_a)|`.
    fn note_row(&mut self, left: Leftover<K, L>, e: usize) {
        let change = left.moved_prediction(self.rows.sqrt_w[e]);
        for (m, c) in self.moved.iter_mut().zip(change) {
            *m += c.abs();
        }
        self.last_moved = (change, left.gain());
    }

    /// A bound on how far any node's anchored value (right-hand side q) has moved since
    /// [`Self::set_moved`] (infinite after two components joined).
    pub fn moved(&self, q: usize) -> f64 {
        self.moved[q]
    }

    /// Set the bound [`Self::moved`] of right-hand side q (0 when the owner re-linearised
    /// with the values of now).
    pub fn set_moved(&mut self, q: usize, bound: f64) {
        self.moved[q] = bound;
        // The last row's movement is in the bound as set: a later shift of its right-hand
        // side adds its own (no more than the net, by the triangle inequality).
        self.last_moved.0[q] = 0.0;
    }

    /// Edge e's measurement.
    pub fn y(&self, e: usize) -> [f64; K] {
        self.rows.y[e]
    }

    /// Every node's values for the right-hand sides `columns`, with the measurements
    /// rewritten by `relinearise`, leaving the system as it was: one forward and one
    /// back-substitution per column.
    pub fn all_for<const M: usize>(
        &mut self,
        relinearise: impl FnOnce(&mut [[f64; K]]),
        columns: [usize; M],
    ) -> [Vec<f64>; M] {
        let saved_y = self.rows.y.clone();
        relinearise(&mut self.rows.y);
        let saved_d = self.factor.rhs().to_vec();
        reset_rhs(&mut self.factor, &self.rows, 0);
        let out = self.all_columns(columns);
        self.rows.y = saved_y;
        self.factor.set_rhs(saved_d);
        out
    }

    /// Value of node v: back-substitution along its elimination-tree path (O(1) for the
    /// last node of the order, the newest).
    pub fn value(&mut self, v: usize) -> [f64; K] {
        self.factor.value(v)
    }

    /// Value of node v for right-hand side q only.
    pub fn value_of(&mut self, v: usize, q: usize) -> f64 {
        self.factor.value_of(v, q)
    }

    /// Values of every node for right-hand side q: one back-substitution (each relative to
    /// its anchor, which removes the rounding of the common mode).
    pub fn all(&mut self, q: usize) -> Vec<f64> {
        let [x] = self.all_columns([q]);
        x
    }

    /// [`Self::all`] for the right-hand sides `columns`, in one back-substitution.
    pub fn all_columns<const M: usize>(&mut self, columns: [usize; M]) -> [Vec<f64>; M] {
        let mut xs = self.factor.solve_columns(columns);
        let anchors: Vec<usize> = (0..self.len())
            .map(|v| self.anchor[self.components.find(v)])
            .collect();
        for x in &mut xs {
            for (v, &a) in anchors.iter().enumerate() {
                if a != v {
                    x[v] -= x[a];
                }
            }
            for (xv, &p) in x.iter_mut().zip(&self.prior) {
                if p != [0.0; L] {
                    *xv = 0.0;
                }
            }
        }
        xs
    }

    /// Marginal variance of node v in the anchored system: `Var(θ_v − θ_anchor)` (0 for an
    /// anchor), exact with the anchor's prior (the prior only adds a common shift).
    pub fn variance(&mut self, v: usize) -> [f64; L] {
        let r = self.components.find(v);
        let a = self.anchor[r];
        if a == v {
            return [0.0; L];
        }
        self.factor.marginal(&[(v, [1.0; L]), (a, [-1.0; L])])
    }

    /// From now on, changes go to the rows only (no factor work, no renewal) until
    /// [`Self::rebuild`]: a replay of many steps whose answers nobody reads in between.
    pub fn defer(&mut self) {
        self.drop_renewal();
        self.deferred = true;
    }

    /// Whether changes are deferred ([`Self::defer`]).
    pub fn deferred(&self) -> bool {
        self.deferred
    }

    /// Build the factor of the whole system at once, in a fill-reducing order with the newest
    /// node last (as a renewal does, on this thread), and apply changes to it from now on. The
    /// order is minimum degree's at any size: this runs in a step (a replay's end), where a
    /// split's separators would add to it; later renewals of a large factor dissect.
    pub fn rebuild(&mut self) {
        let n = self.len();
        let last = n.checked_sub(1);
        self.install(build(&self.rows, &self.prior, n, last, BuildOrder::MinimumDegree).0);
        self.nodes_at_renewal = n;
        self.deferred = false;
    }

    /// Swap in a factor built in a new order (a renewal's, or a rebuild's): its build's work is
    /// not the live factor's, its fill per row is the next renewal's reference, and the old
    /// factor is freed on the worker (a factor's thousands of rows cost a step about a
    /// millisecond to free).
    fn install(&mut self, mut fresh: SqrtInfo<K, L>) {
        fresh.take_work();
        // Its right-hand sides are its rows' (a build's, or a renewal's that was sent every
        // re-linearisation).
        self.stale_rhs = None;
        self.fill_after_renewal = fresh.nnz() as f64 / self.len().max(1) as f64;
        self.last_edge = None;
        let old = std::mem::replace(&mut self.factor, fresh);
        if old.len() > 0 {
            self.worker.retire("so2lin-renew", old);
        }
    }

    /// Rewrite the rows' measurements by `relinearise`, and the factor's right-hand sides
    /// `from..K` with them at the end of the next step ([`Self::after_step`]: a forward
    /// solve, so that no step pays for both it and the back-substitution that gave the
    /// headings); until then the factor answers with the rows as they were. The factor's
    /// order and values stay.
    pub fn relinearise(&mut self, relinearise: impl FnOnce(&mut [[f64; K]]), from: usize) {
        relinearise(&mut self.rows.y);
        let from = from.min(K);
        self.stale_rhs = Some(self.stale_rhs.map_or(from, |f| f.min(from)));
        self.last_edge = None;
        // A renewal in progress takes them too (or it would bring back its snapshot's).
        if self.renewal.is_some() {
            self.send(Msg::Relinearised(self.rows.y.clone()));
        }
    }

    /// Recompute the right-hand sides a [`Self::relinearise`] left lagging, now.
    pub fn flush_rhs(&mut self) {
        if let Some(from) = self.stale_rhs.take() {
            // The last row's gains stay valid: d is the same linear function of the rows'
            // right-hand sides, recomputed.
            reset_rhs(&mut self.factor, &self.rows, from);
        }
    }

    /// Collect later renewals after `delay` times the default work ([`work_per_nonzero`]):
    /// sooner below 1 (a caller whose edges arrive slowly enough for the builder).
    pub fn set_renewal_delay(&mut self, delay: f64) {
        self.renewal_delay = delay;
    }

    /// Take the live factor's work since the last call into this system's count.
    fn step_work(&mut self) {
        self.work += self.factor.take_work();
    }

    /// The live factor's work so far ([`SqrtInfo::take_work`]) and its nonzeros.
    pub fn work_and_nnz(&self) -> (u64, usize) {
        (self.work, self.factor.nnz())
    }

    /// Whether a renewal is in progress.
    #[cfg(test)]
    pub fn renewing(&self) -> bool {
        self.renewal.is_some()
    }

    /// Called once per step, after its events: starts or completes a renewal. A renewal's
    /// snapshot takes the right-hand sides computed by the job `relinearise` gives (None: the
    /// current ones), run on the builder's thread; they become the live ones when the renewal
    /// is swapped in.
    pub fn after_step(
        &mut self,
        relinearise: impl FnOnce(&mut Self) -> Option<Relinearise<K>>,
    ) -> Option<RenewalEvent> {
        self.steps += 1;
        if self.deferred {
            return None;
        }
        self.flush_rhs();
        self.step_work();
        self.post();
        if self.renewal.is_some() {
            return self.complete_renewal().then_some(RenewalEvent::Collected);
        }
        let n = self.len();
        if n < MIN_VARIABLES {
            return None;
        }
        // Nodes appended since the last renewal form a chain at the end of the order that
        // every loop closure to an older node walks: renew when it is an eighth of the graph,
        // or when the fill per row has grown by half (a fifth on large factors).
        let per_row = self.factor.nnz() as f64 / n as f64;
        let appended = n - self.nodes_at_renewal;
        if per_row <= fill_ratio(n) * self.fill_after_renewal.max(1.0)
            && appended <= MIN_VARIABLES.max(n / APPENDED_FRACTION)
        {
            return None;
        }
        let mut rows = self.rows.clone();
        let relinearise = relinearise(self);
        let prior = self.prior.clone();
        let newest = n - 1;
        // The builder's work grows with the size of the factor it builds (about the last
        // renewal's fill per row), not with the live factor's fill, which is what grows
        // without bound between renewals.
        let expected_nnz = self.fill_after_renewal.max(2.0) * n as f64;
        // The renewed factor and right-hand sides get the live ones' room (reserved on the
        // builder, so that the first node or edge after the swap does not copy them in a step).
        let room = self.factor.capacity();
        let y_room = self.rows.y.capacity();
        let order = if n >= self.dissect_from {
            BuildOrder::Dissected(self.dissection.clone().filter(|t| !t.stale(n)))
        } else {
            BuildOrder::MinimumDegree
        };
        // A fresh split computes its separators too.
        let split = if matches!(order, BuildOrder::Dissected(None)) {
            SPLIT_BUILD
        } else {
            1.0
        };
        let build = move || {
            if let Some(job) = relinearise {
                job(&mut rows.y);
            }
            let (mut f, tree) = build(&rows, &prior, n, Some(newest), order);
            // (Refused, the renewed factor grows as it would have.)
            let _ = f.try_reserve(room.saturating_sub(f.len()));
            let _ = rows.y.try_reserve(y_room.saturating_sub(rows.y.len()));
            Some((f, rows, tree))
        };
        // Keep up with the live system until collected.
        let apply = |(f, rows, _): &mut Building<K, L>, msg: Msg<K, L>| {
            match msg {
                Msg::Variable(v) => f.push_variable(v as usize),
                Msg::Prior(p) => {
                    f.add_row(&[p], [0.0; K]);
                }
                Msg::Unprior(p) => f.remove_row(&[p], [0.0; K]).ok()?,
                Msg::Edge(a, b, s, y) => {
                    rows.ends.push((a, b));
                    rows.sqrt_w.push(s);
                    rows.y.push(y);
                    let e = rows.ends.len() - 1;
                    f.add_row(&rows.entries(e), rows.rhs(e));
                }
                Msg::Relinearised(y) => {
                    if y.len() != rows.y.len() {
                        return None;
                    }
                    rows.y = y;
                    reset_rhs(f, rows, 0);
                }
                Msg::SetY(e, y) => {
                    let e = e as usize;
                    let old = *rows.y.get(e)?;
                    rows.y[e] = y;
                    let shift = rows.shift(e, old, y);
                    // The last edge's row is the last row added unless a prior's was removed
                    // since (which makes the gains stale).
                    if e + 1 != rows.ends.len() || !f.shift_last_row(shift) {
                        f.shift_rhs(&rows.entries(e), shift);
                    }
                }
            }
            Some(())
        };
        let finish = |(f, rows, tree): Building<K, L>| (f, rows.y, tree);
        let due = Due {
            step: self.steps + MIN_DELAY,
            // Saturating: a caller's delay may be any finite positive number.
            work: self.work.saturating_add(
                (expected_nnz * split * work_per_nonzero(n, L) * self.renewal_delay) as u64,
            ),
        };
        let worker = &mut self.worker;
        let renewal = Beside::start(worker, "so2lin-renew", build, apply, finish)?;
        self.nodes_at_renewal = n;
        self.renewal = Some((renewal, due));
        Some(RenewalEvent::Started)
    }

    /// At the renewal's step: collect the builder (which has applied every change since its
    /// snapshot) and swap its factor in; the old one is freed on the worker.
    /// Whether it was swapped in.
    fn complete_renewal(&mut self) -> bool {
        let Some((_, due)) = &self.renewal else {
            return false;
        };
        if !due.reached(self.steps, self.work) {
            return false;
        }
        let Some((r, _)) = self.renewal.take() else {
            return false;
        };
        let Some((fresh, y, tree)) = r.collect(&mut self.waits) else {
            return false;
        };
        if y.len() != self.rows.y.len() {
            return false;
        }
        if let Some(tree) = tree {
            self.dissection = Some(Arc::new(tree));
        }
        // The builder's array, with the live one's room.
        self.rows.y = y;
        self.install(fresh);
        self.renewals += 1;
        true
    }
}

impl<const K: usize> Laplacian<K> {
    /// The same system in `M` lanes, lane m's weights multiplied by `scale[m]²` (R, d and the
    /// priors by `scale[m]`): how a factor shared by systems whose weights were proportional
    /// becomes a factor of lanes when an edge breaks the proportion. No renewal in progress
    /// (one is started afresh later); the counters go on.
    pub fn widen<const M: usize>(&self, scale: [f64; M]) -> Laplacian<K, M> {
        let lanes = |&[s]: &[f64; 1]| scale.map(|m| m * s);
        Laplacian {
            factor: self.factor.widen(scale),
            rows: Rows {
                ends: self.rows.ends.clone(),
                sqrt_w: self.rows.sqrt_w.iter().map(lanes).collect(),
                y: self.rows.y.clone(),
            },
            components: self.components.clone(),
            anchor: self.anchor.clone(),
            prior: self.prior.iter().map(lanes).collect(),
            first_weight: self.first_weight.iter().map(lanes).collect(),
            fill_after_renewal: self.fill_after_renewal,
            nodes_at_renewal: self.nodes_at_renewal,
            work: self.work,
            steps: self.steps,
            last_edge: self.last_edge,
            deferred: self.deferred,
            stale_rhs: self.stale_rhs,
            moved: self.moved,
            last_moved: (self.last_moved.0, scale.map(|_| self.last_moved.1[0])),
            dissection: self.dissection.clone(),
            dissect_from: self.dissect_from,
            renewal_delay: self.renewal_delay,
            renewals: self.renewals,
            waits: self.waits,
            ..Laplacian::default()
        }
    }
}

/// d of a factor, its right-hand sides `from..K`, from the rows' current ones (priors have 0).
fn reset_rhs<const K: usize, const L: usize>(
    f: &mut SqrtInfo<K, L>,
    rows: &Rows<K, L>,
    from: usize,
) {
    f.reset_rhs_from(
        from,
        (0..rows.ends.len()).map(|e| (rows.entries(e), rows.rhs(e))),
    );
}

/// A factor of the whole system in a fill-reducing order (`last` at the end), and the
/// dissection the order came from ([`BuildOrder::Dissected`]).
fn build<const K: usize, const L: usize>(
    rows: &Rows<K, L>,
    prior: &[[f64; L]],
    n: usize,
    last: Option<usize>,
    ordering: BuildOrder,
) -> (SqrtInfo<K, L>, Option<Dissection>) {
    let ends: Vec<(usize, usize)> = rows
        .ends
        .iter()
        .map(|&(a, b)| (a as usize, b as usize))
        .collect();
    let last: Vec<usize> = last.into_iter().collect();
    let (order, tree) = match ordering {
        BuildOrder::MinimumDegree => (fill_reducing_order(n, &ends, &last), None),
        BuildOrder::Dissected(tree) => {
            let (order, tree) = dissected_order(n, &ends, &last, tree.as_deref());
            (order, Some(tree))
        }
    };
    let priors = prior
        .iter()
        .enumerate()
        .take(n)
        .filter(|&(_, &p)| p != [0.0; L])
        .map(|(v, &p)| ([(v, p), (v, [0.0; L])], [0.0; K]));
    let edges = (0..rows.ends.len()).map(|e| (rows.entries(e), rows.rhs(e)));
    if let Some(f) = SqrtInfo::factored(&order, priors.clone().chain(edges.clone())) {
        return (f, tree);
    }
    // Extreme weights: rotate the rows in (QR, better conditioned than the normal equations).
    let mut f = SqrtInfo::new();
    for v in order {
        f.push_variable(v);
    }
    for (entries, rhs) in priors.chain(edges) {
        f.add_row(&entries, rhs);
    }
    (f, tree)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A renewal is collected once the live factor's work reaches its due (and `MIN_DELAY`
    /// steps have passed): steps without work leave it pending.
    #[test]
    fn a_renewal_is_due_by_work() {
        let mut l = Laplacian::<1>::default();
        l.add_node();
        while !l.renewing() {
            let v = l.add_node();
            l.add_edge(v - 1, v, 4.0, [0.1]);
            let event = l.after_step(|_| None);
            assert_eq!(event.is_some(), l.renewing(), "started: {event:?}");
            assert!(l.len() <= MIN_VARIABLES + 1, "no renewal started");
        }
        for _ in 0..2 * MIN_DELAY {
            assert_eq!(l.after_step(|_| None), None);
        }
        assert!(
            l.renewing() && l.renewals == 0,
            "collected without the work due"
        );
        // Loop closures to the first node: the live factor's own work, until the due.
        let mut closures = 0;
        while l.renewals == 0 {
            let v = l.len() - 1;
            l.add_edge(0, v, 1.0, [0.1 * v as f64]);
            closures += 1;
            let event = l.after_step(|_| None);
            assert_eq!(event.is_some(), l.renewals == 1, "{event:?}");
            assert!(closures < 10_000, "not collected with the work due");
        }
        assert!(closures > 1, "collected before the work was due");
        assert!(
            !l.renewing() && l.renewals == 1,
            "not collected with the work due"
        );
        // The renewed factor gives the same answer.
        let x = l.all(0);
        let last = x.len() - 1;
        assert!((x[last] - 0.1 * last as f64).abs() < 1e-9, "{}", x[last]);
    }

    /// Any finite positive renewal delay is taken as given: a huge one leaves every renewal
    /// pending (its due saturates rather than wrapping round to a due already reached), a
    /// tiny one collects each as soon as [`MIN_DELAY`] steps have passed.
    #[test]
    fn extreme_renewal_delays_saturate() {
        let run = |delay: f64| {
            let mut l = Laplacian::<1>::default();
            l.set_renewal_delay(delay);
            l.add_node();
            for v in 1..2_000 {
                l.add_node();
                l.add_edge(v - 1, v, 4.0, [0.1]);
                if v % 3 == 0 {
                    l.add_edge(v / 2, v, 1.0, [0.05 * v as f64]);
                }
                l.after_step(|_| None);
            }
            l.renewals
        };
        assert_eq!(
            run(1e300),
            0,
            "a renewal collected before its (unreachable) due"
        );
        assert!(run(1e-300) > run(1.0), "a tiny delay collects sooner");
    }

    /// Room reserved for the nodes and edges to come: the rows' arrays never move, and every
    /// renewal's factor and right-hand sides come with the live ones' room (reserved on the
    /// builder), so no step copies an array to grow it. Without the builder's reserve, the
    /// swapped-in arrays hold their own count rounded up to a power of two, less than the room.
    #[test]
    fn reserved_room_outlives_renewals() {
        let n = 2_000;
        let mut l = Laplacian::<1>::default();
        l.try_reserve(3 * n, 6 * n).expect("room for a small world");
        let rows = |l: &Laplacian<1>| {
            (
                l.rows.ends.as_ptr(),
                l.rows.sqrt_w.as_ptr(),
                l.prior.as_ptr(),
            )
        };
        let before = rows(&l);
        l.add_node();
        for v in 1..n {
            l.add_node();
            l.add_edge(v - 1, v, 4.0, [0.1]);
            if v % 3 == 0 {
                l.add_edge(v / 2, v, 1.0, [0.05 * v as f64]);
            }
            l.after_step(|_| None);
        }
        assert!(l.renewals >= 2, "renewals {}", l.renewals);
        assert_eq!(rows(&l), before, "a reserved array grew");
        // The right-hand sides come from the builder, with the room.
        assert!(l.rows.y.capacity() >= 6 * n, "{}", l.rows.y.capacity());
        assert!(
            l.factor.capacity() >= 3 * n,
            "the renewed factor holds {} variables without growing",
            l.factor.capacity()
        );
        let (nodes, edges) = l.room();
        assert!(nodes >= 2 * n && edges >= 4 * n, "room {nodes}, {edges}");
    }

    /// Renewals from `dissect_from` variables order by nested dissection: the first splits the
    /// graph, the later ones place the nodes added since in its tree until the graph has grown
    /// by a quarter, then split it afresh. Every answer is that of renewals by minimum degree
    /// alone (a boustrophedon over a 60 × 60 grid, each node closing a loop to its neighbour in
    /// the row before, and every third to an older node further away).
    #[test]
    #[cfg(feature = "metis")]
    fn dissected_renewals_answer_as_minimum_degree_ones() {
        let w = 60;
        let index = |r: usize, c: usize| r * w + if r.is_multiple_of(2) { c } else { w - 1 - c };
        let mut dissected = Laplacian::<2> {
            dissect_from: 400,
            ..Laplacian::default()
        };
        let mut plain = Laplacian::<2> {
            dissect_from: usize::MAX,
            ..Laplacian::default()
        };
        let mut bases = Vec::new();
        let (mut placed, mut dissected_renewals) = (0, 0);
        let mut last: Option<Arc<Dissection>> = None;
        for l in [&mut dissected, &mut plain] {
            l.add_node();
        }
        for v in 1..w * w {
            let (r, c) = (
                v / w,
                if (v / w).is_multiple_of(2) {
                    v % w
                } else {
                    w - 1 - v % w
                },
            );
            for l in [&mut dissected, &mut plain] {
                l.add_node();
                l.add_edge(v - 1, v, 4.0, [0.01 * (v % 7) as f64, 1.0]);
                if r > 0 {
                    let y = [0.05 * ((v * 13) % 5) as f64 - 0.1, 0.5];
                    l.add_edge(index(r - 1, c), v, 2.0, y);
                }
                if v.is_multiple_of(3) {
                    // A long loop closure now and then: work for the live factor.
                    l.add_edge((v * 7919 + v * v) % (v - 1), v, 1.0, [0.02, -1.0]);
                }
            }
            let renewals = dissected.renewals;
            dissected.after_step(|_| None);
            plain.after_step(|_| None);
            if dissected.renewals > renewals
                && let Some(tree) = dissected.dissection.as_ref()
                && !last.as_ref().is_some_and(|l| Arc::ptr_eq(l, tree))
            {
                last = Some(Arc::clone(tree));
                dissected_renewals += 1;
                if bases.last() != Some(&tree.base()) {
                    bases.push(tree.base());
                } else {
                    placed += 1;
                }
            }
            let (a, b) = (dissected.value(v), plain.value(v));
            assert!(
                (a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9,
                "node {v}: {a:?} against {b:?}"
            );
            if v.is_multiple_of(100) {
                for q in 0..2 {
                    let (a, b) = (dissected.all(q), plain.all(q));
                    let gap = a
                        .iter()
                        .zip(&b)
                        .map(|(x, y)| (x - y).abs())
                        .fold(0.0, f64::max);
                    assert!(gap < 1e-9, "node {v}, column {q}: {gap}");
                }
            }
        }
        eprintln!(
            "{} renewals, {dissected_renewals} dissected, splits at {bases:?}, {placed} placed",
            dissected.renewals
        );
        assert!(bases.len() >= 2, "split {} times", bases.len());
        assert!(placed >= 1, "no renewal placed nodes in a kept tree");
        assert!(
            bases.windows(2).all(|b| b[1] as f64 > 1.25 * b[0] as f64),
            "split before the graph grew by a quarter: {bases:?}"
        );
        assert!(plain.dissection.is_none());
    }

    /// A re-linearisation rewrites the rows at once and their right-hand sides at the end of
    /// the next step: in between the factor answers as before it (the headings' column
    /// untouched throughout), after it as a re-linearisation applied at once — with rows
    /// rotated in between, and for a factor widened to two lanes while it lags.
    #[test]
    fn a_relinearisation_lands_at_the_next_step() {
        let build = || {
            let mut l = Laplacian::<3>::default();
            l.add_node();
            for v in 1..300usize {
                l.add_node();
                l.add_edge(v - 1, v, 4.0, [0.01, 1.0, 0.0]);
                if v % 7 == 0 && v > 20 {
                    l.add_edge(v - 20, v, 2.0, [0.25, 0.5, 19.0]);
                }
            }
            l
        };
        // Every position measurement turned by 0.3 rad.
        let job = || -> Relinearise<3> {
            Box::new(|y: &mut [[f64; 3]]| {
                for r in y.iter_mut() {
                    let (s, c) = 0.3f64.sin_cos();
                    let [x, y] = [r[1], r[2]];
                    (r[1], r[2]) = (c * x - s * y, s * x + c * y);
                }
            })
        };
        let close = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9);
        let (mut now, mut later) = (build(), build());
        let before: Vec<Vec<f64>> = (0..3).map(|q| later.all(q)).collect();
        now.relinearise(job(), 1);
        now.flush_rhs();
        later.relinearise(job(), 1);
        for (q, b) in before.iter().enumerate() {
            assert!(close(&later.all(q), b), "column {q} moved before the step");
        }
        // A row rotated in before the step ends, in both.
        for l in [&mut now, &mut later] {
            let v = l.add_node();
            l.add_edge(v - 1, v, 4.0, [0.01, 1.0, 0.0]);
            l.add_edge(v - 150, v, 2.0, [0.5, 3.0, -2.0]);
        }
        // Widened to two lanes while lagging: the wide factor takes the lag with it.
        let (mut now2, mut later2) = (now.widen([1.0, 2.0]), later.widen([1.0, 2.0]));
        now.after_step(|_| None);
        later.after_step(|_| None);
        now2.after_step(|_| None);
        later2.after_step(|_| None);
        for q in 0..3 {
            assert!(close(&later.all(q), &now.all(q)), "column {q}");
        }
        for q in 0..3 {
            assert!(close(&later2.all(q), &now2.all(q)), "wide column {q}");
            assert!(close(&later2.all(q), &later.all(q)), "wide column {q}");
        }
        assert!(
            !close(&later.all(1), &before[1]),
            "the positions did not move"
        );
    }

    /// [`Laplacian::moved`] bounds how far every node's anchored value has moved since it was
    /// set to 0: through new chains, loop closures added or tried and kept or undone, moved
    /// measurements of the last row (net, through its gains) and of older rows, and components
    /// that join. And the bound is not vacuous: it is reached (to rounding).
    #[test]
    fn the_moved_bound_bounds_every_nodes_movement() {
        let mut state = 0x2545_f491_4f6c_dd1d_u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut l = Laplacian::<2>::default();
        let mut base = Vec::new();
        let mut worst_ratio: f64 = 0.0;
        let mut largest: f64 = 0.0;
        l.add_node();
        for step in 0..1500 {
            let n = l.len();
            let r = next();
            if r < 0.45 || n < 4 {
                // A new node on the chain (or, now and then, the start of a second chain).
                let v = l.add_node();
                let from = if step % 400 == 399 { None } else { Some(v - 1) };
                if let Some(u) = from {
                    l.add_edge(u, v, 1.0 + next(), [next() - 0.5, next()]);
                }
            } else if r < 0.75 {
                // A loop closure between two older nodes of the first chain, its measurement
                // off by up to half a unit.
                let (a, b) = ((next() * n as f64) as usize, n - 1);
                if a == b {
                    continue;
                }
                let y = [next() - 0.5, next() * 3.0];
                // Between two components: they join (the bound is infinite).
                let join = l.components.find(a) != l.components.find(b);
                if join || next() < 0.5 {
                    l.add_edge(a, b, 4.0 * next() + 0.5, y);
                } else if l.try_edge(a, b, 2.0, y).is_some() {
                    if next() < 0.7 {
                        l.keep_edge();
                    } else {
                        l.undo_edge();
                    }
                }
            } else if r < 0.9 && l.edge_count() > 0 {
                // A measurement moved: the last row's (a wrap taken) or an older one's.
                let e = if next() < 0.5 {
                    l.edge_count() - 1
                } else {
                    (next() * l.edge_count() as f64) as usize
                };
                let [y0, y1] = l.y(e);
                let jump = if next() < 0.2 {
                    std::f64::consts::TAU
                } else {
                    0.2
                };
                l.set_y(e, [y0 + jump * (next() - 0.5), y1 + next() - 0.5]);
            } else {
                // Settle: the owner re-linearised with the values of now.
                base = (0..2).map(|q| l.all(q)).collect();
                l.set_moved(0, 0.0);
                l.set_moved(1, 0.0);
                continue;
            }
            if base.is_empty() {
                continue;
            }
            for (q, before) in base.iter().enumerate() {
                let now = l.all(q);
                let moved = (before.iter().zip(&now))
                    .map(|(x, y)| (x - y).abs())
                    .fold(0.0, f64::max);
                let bound = l.moved(q);
                assert!(
                    moved <= bound + 1e-9,
                    "step {step}, rhs {q}: {moved} > {bound}"
                );
                if bound.is_finite() && bound > 0.0 {
                    worst_ratio = worst_ratio.max(moved / bound);
                }
                largest = largest.max(moved);
            }
        }
        eprintln!("largest movement {largest}, tightest ratio {worst_ratio}");
        assert!(
            largest > 1.0 && worst_ratio > 0.99,
            "{largest} {worst_ratio}"
        );
    }
}
