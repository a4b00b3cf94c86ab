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
//! **Renewing the order without a stall** (module `renew`): new nodes are appended at the end,
//! so R fills as the robot revisits old places; a factor in a new order is built beside the live
//! one on another thread, kept up to date with every change, and swapped in at a point of the
//! run fixed in advance.

mod renew;

use renew::{BuildOrder, LARGE_FACTOR, Msg, Renewal, build};
pub(crate) use renew::{MIN_DELAY, RenewalEvent};

use super::renewal::{Due, Worker};
use super::snapshot::Chunked;
use crate::estimate::incremental::{Dissection, Lanes, Leftover, SqrtInfo, lane};
use crate::graph::UnionFind;
use std::sync::Arc;

/// [`Laplacian::adopt`] derives a factor from another when at most this fraction of the rows
/// (and at least [`ADOPT_MIN_CHANGES`]) differ — rows and priors added or removed, nodes new —
/// and builds it whole otherwise: each difference is a rotation along a path, and down-dated
/// rows lose precision as they add up.
const ADOPT_CHANGES_FRACTION: usize = 16;
/// See [`ADOPT_CHANGES_FRACTION`].
const ADOPT_MIN_CHANGES: usize = 32;

/// Edge a → b's row `√w (x_b − x_a)`: its entries.
#[inline]
fn row_entries<const L: usize>((a, b): (u32, u32), s: [f64; L]) -> [(usize, [f64; L]); 2] {
    [(a as usize, s.map(|s| -s)), (b as usize, s)]
}

/// An edge's row's right-hand side `√w y`, per right-hand side (its lane's weight).
#[inline]
fn row_rhs<const K: usize, const L: usize>(s: [f64; L], y: [f64; K]) -> [f64; K] {
    std::array::from_fn(|q| s[lane::<L>(q)] * y[q])
}

/// The data a factor is built from (a snapshot goes to the builder thread), kept as shared
/// chunks ([`Chunked`]): a renewal's snapshot, or a re-linearisation's rows handed to its
/// builder, costs a pointer per chunk on the robot's thread, and a write into a shared chunk
/// copies that chunk.
#[derive(Clone)]
struct Rows<const K: usize, const L: usize> {
    ends: Chunked<(u32, u32)>,
    /// `√w_e` of every edge, per lane.
    sqrt_w: Chunked<[f64; L]>,
    /// `y_e` of every edge.
    y: Chunked<[f64; K]>,
}

impl<const K: usize, const L: usize> Default for Rows<K, L> {
    fn default() -> Self {
        Self {
            ends: Chunked::default(),
            sqrt_w: Chunked::default(),
            y: Chunked::default(),
        }
    }
}

impl<const K: usize, const L: usize> Rows<K, L> {
    fn entries(&self, e: usize) -> [(usize, [f64; L]); 2] {
        row_entries(self.ends[e], self.sqrt_w[e])
    }

    fn rhs(&self, e: usize) -> [f64; K] {
        row_rhs(self.sqrt_w[e], self.y[e])
    }

    /// Every edge's `(entries, rhs)` in order (what [`Self::entries`] and [`Self::rhs`] give
    /// edge by edge), walking the three arrays a chunk at a time, side by side (their chunks
    /// have the same lengths): zipping their element iterators took 175 µs over city10000's
    /// 20 000 rows, against 109–112 µs this way (`benches/MEASUREMENTS.md`, forty-first
    /// session).
    fn each(&self) -> impl Iterator<Item = ([(usize, [f64; L]); 2], [f64; K])> + Clone + '_ {
        self.each_in(0..self.ends.len())
    }

    /// [`Self::each`] for the edges `range` only.
    fn each_in(
        &self,
        range: std::ops::Range<usize>,
    ) -> impl Iterator<Item = ([(usize, [f64; L]); 2], [f64; K])> + Clone + '_ {
        let slices = (self.ends.slices_in(range.clone()))
            .zip(self.sqrt_w.slices_in(range.clone()))
            .zip(self.y.slices_in(range));
        slices.flat_map(|((ends, sqrt_w), y)| {
            (ends.iter().zip(sqrt_w).zip(y))
                .map(|((&ends, &s), &y)| (row_entries(ends, s), row_rhs(s, y)))
        })
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
    /// Shared chunks, as the rows: a renewal's snapshot takes them at a pointer per chunk.
    prior: Chunked<[f64; L]>,
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
    /// Its work in the last step ([`Self::step_share`]).
    own_work: u64,
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
    /// The work a renewal is collected after, as a multiple of the default (module `renew`,
    /// `work_per_nonzero`; [`Self::set_renewal_delay`]).
    renewal_delay: f64,
    /// Renewals completed.
    pub renewals: usize,
    /// Steps that waited for a renewal's builder.
    pub waits: usize,
    /// Renewals on the caller's thread ([`Self::renew_now`]).
    pub renewed_now: usize,
}

impl<const K: usize, const L: usize> Default for Laplacian<K, L> {
    fn default() -> Self {
        Self {
            factor: SqrtInfo::new(),
            rows: Rows::default(),
            components: UnionFind::new(0),
            anchor: Vec::new(),
            prior: Chunked::default(),
            first_weight: Vec::new(),
            fill_after_renewal: 0.0,
            nodes_at_renewal: 0,
            renewal: None,
            outbox: Vec::new(),
            work: 0,
            own_work: 0,
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
            renewed_now: 0,
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
        self.send(Msg::SetY(
            e as u32,
            y,
            std::array::from_fn(|q| y[q] != old[q]),
        ));
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
        relinearise: impl FnOnce(&mut Chunked<[f64; K]>),
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
        self.anchored(&mut xs);
        xs
    }

    /// Start solving right-hand side q for every node a block of positions per step
    /// ([`Self::back_advance`]; module `estimate::incremental::back`: each block reads the
    /// factor of its own step), dropping one in progress.
    pub fn back_start(&mut self, q: usize) {
        self.factor.back_start(q);
    }

    /// Solve the next block (sized by the last step's own work, [`Self::step_share`]): whether
    /// the solve is complete; None when none is in progress (none started, or the factor was
    /// replaced since: a renewal swapped in, a rebuild).
    pub fn back_advance(&mut self) -> Option<bool> {
        self.factor.back_advance(self.own_work)
    }

    /// Every node's value of a complete spread solve, as [`Self::all`] gives them (each
    /// relative to its anchor); None when none is complete. The solve ends.
    pub fn back_take(&mut self) -> Option<Vec<f64>> {
        let mut xs = [self.factor.back_take()?];
        self.anchored(&mut xs);
        let [x] = xs;
        Some(x)
    }

    /// Drop a spread solve in progress ([`Self::back_start`]).
    pub fn back_cancel(&mut self) {
        self.factor.back_cancel();
    }

    /// Every node's values relative to its anchor's (an anchor's, with its prior, 0).
    fn anchored<const M: usize>(&mut self, xs: &mut [Vec<f64>; M]) {
        // (An anchor is its own: its value is read before any is changed.)
        for v in 0..self.len() {
            let a = self.anchor[self.components.find(v)];
            if a != v {
                for x in xs.iter_mut() {
                    x[v] -= x[a];
                }
            }
        }
        for x in xs {
            for (xv, &p) in x.iter_mut().zip(self.prior.iter()) {
                if p != [0.0; L] {
                    *xv = 0.0;
                }
            }
        }
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

    /// [`Self::rebuild`] from `old`'s factor instead of a new build: `old` is the system this
    /// one replaces (an estimator rebuilt by a replay, whose rows differ from the replaced
    /// one's in a few loop closures: the evicted ones, those re-admitted). The rows and anchor
    /// priors only this system has are rotated into `old`'s factor, then those only `old` has
    /// are down-dated (rows matched by their ends and weights), and the right-hand sides are
    /// recomputed from this system's rows (one forward solve): a few paths and one pass over
    /// the factor instead of a whole build in the replay's step. The factor keeps `old`'s order
    /// and renewal schedule, and its worker thread is taken over (in any case). The
    /// right-hand sides but the first lag the rows until the next [`Self::flush_rhs`] (a
    /// replay's rebuild re-linearises them first). False, this system's rows and factor
    /// unchanged, when more rows differ than [`ADOPT_CHANGES_FRACTION`] allows or a down-date
    /// fails; the caller then rebuilds.
    pub fn adopt(&mut self, mut old: Box<Self>) -> bool {
        // (The replaced system's worker goes on serving this one; `old` is freed on it.)
        self.worker = std::mem::take(&mut old.worker);
        old.drop_renewal();
        let adopted = self.deferred
            && !old.deferred
            && old.tried.is_none()
            && old.len() <= self.len()
            && self.adopted(&mut old);
        self.worker.retire("so2lin-renew", old);
        adopted
    }

    /// Free `value` on this system's worker thread, not on the caller's.
    pub fn retire<T: Send + 'static>(&mut self, value: T) {
        self.worker.retire("so2lin-renew", value);
    }

    /// [`Self::adopt`] once the two systems are known to be comparable.
    fn adopted(&mut self, old: &mut Self) -> bool {
        // A row as compared: its ends and its weights' bits.
        let key = |rows: &Rows<K, L>, e: usize| (rows.ends[e], rows.sqrt_w[e].map(f64::to_bits));
        // The two systems hold the same rows in the same order up to the replay's first
        // arrival (its checkpoint's graph, or the replay from the start's first difference):
        // that prefix is matched in place, the rest sorted.
        let common = (0..self.rows.ends.len().min(old.rows.ends.len()))
            .find(|&e| key(&self.rows, e) != key(&old.rows, e))
            .unwrap_or(self.rows.ends.len().min(old.rows.ends.len()));
        // (key, index) of the rows after it, sorted: equal rows side by side.
        let keyed = |rows: &Rows<K, L>| {
            let mut keys: Vec<(_, u32)> = (common..rows.ends.len())
                .map(|e| (key(rows, e), e as u32))
                .collect();
            keys.sort_unstable();
            keys
        };
        let (mine, theirs) = (keyed(&self.rows), keyed(&old.rows));
        let (mut added, mut removed) = (Vec::new(), Vec::new());
        let (mut i, mut j) = (0, 0);
        while i < mine.len() || j < theirs.len() {
            match (mine.get(i), theirs.get(j)) {
                (Some(a), Some(b)) if a.0 == b.0 => (i, j) = (i + 1, j + 1),
                (Some(a), Some(b)) if a.0 > b.0 => {
                    removed.push(b.1 as usize);
                    j += 1;
                }
                (Some(a), _) => {
                    added.push(a.1 as usize);
                    i += 1;
                }
                (None, Some(b)) => {
                    removed.push(b.1 as usize);
                    j += 1;
                }
                (None, None) => break,
            }
        }
        let n = self.len();
        let priors = |p: &Chunked<[f64; L]>, v: usize| p.get(v).copied().unwrap_or([0.0; L]);
        let moved_priors: Vec<usize> = (0..n)
            .filter(|&v| priors(&self.prior, v) != priors(&old.prior, v))
            .collect();
        let changes = added.len() + removed.len() + moved_priors.len() + (n - old.len());
        if changes > ADOPT_MIN_CHANGES.max(self.rows.ends.len() / ADOPT_CHANGES_FRACTION) {
            return false;
        }
        let mut factor = std::mem::take(&mut old.factor);
        for v in old.len()..n {
            factor.push_variable(v);
        }
        // Information in first, then out: the down-dates meet the larger factor.
        for &v in &moved_priors {
            let p = self.prior[v];
            if p != [0.0; L] {
                factor.add_row(&[(v, p)], [0.0; K]);
            }
        }
        for &e in &added {
            factor.add_row(&self.rows.entries(e), [0.0; K]);
        }
        for &v in &moved_priors {
            let p = priors(&old.prior, v);
            if p != [0.0; L] && factor.remove_row(&[(v, p)], [0.0; K]).is_err() {
                return false;
            }
        }
        for &e in &removed {
            if factor.remove_row(&old.rows.entries(e), [0.0; K]).is_err() {
                return false;
            }
        }
        // The headings' right-hand side now; the others lag until the next flush
        // ([`Self::flush_rhs`]: a replay's rebuild re-linearises them first, and computing
        // them here too was a second pass).
        factor.reset_rhs_in(0..1, self.rows.each());
        factor.take_work();
        self.factor = factor;
        self.stale_rhs = (K > 1).then_some(1);
        // The replaced factor's schedule: its renewal in progress was dropped, and the next
        // step starts one if it is due.
        self.fill_after_renewal = old.fill_after_renewal;
        self.nodes_at_renewal = old.nodes_at_renewal;
        self.dissection = old.dissection.take();
        self.last_edge = None;
        self.deferred = false;
        true
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
        let mut old = std::mem::replace(&mut self.factor, fresh);
        self.factor.take_scratch_of(&mut old);
        if old.len() > 0 {
            self.worker.retire("so2lin-renew", old);
        }
    }

    /// Rewrite the rows' measurements by `relinearise`, and the factor's right-hand sides
    /// `from..K` with them over the next steps ([`Self::after_step`]: their information
    /// gathered a block of rows each, then a forward solve a block of positions each, about a
    /// `SPREAD_STEPS`-th of the factor per step, so that no step pays for a whole pass over
    /// the rows or the factor, nor for both it and the back-substitution that gave the
    /// headings: module `estimate::incremental::spread`); until it ends the factor answers
    /// with the rows as they were. The factor's order and values stay.
    pub fn relinearise(&mut self, relinearise: impl FnOnce(&mut Chunked<[f64; K]>), from: usize) {
        relinearise(&mut self.rows.y);
        // A spread in progress solved for the rows' old measurements.
        self.factor.spread_cancel();
        let from = from.min(K);
        self.stale_rhs = Some(self.stale_rhs.map_or(from, |f| f.min(from)));
        self.last_edge = None;
        // A renewal in progress takes them too (or it would bring back its snapshot's).
        if self.renewal.is_some() {
            self.send(Msg::Relinearised(self.rows.y.clone()));
        }
    }

    /// The measurements of rows `range`, to rewrite ahead of a [`Self::relinearise`] that
    /// takes them as they are (a re-linearisation a block of rows per step, module
    /// `online::estimate`). Neither the factor nor a renewal's builder is told until that
    /// call: meanwhile the rows hold measurements of two linearisations, which only a
    /// renewal's start (whose builder rewrites every row) and [`Self::all_for`] (which
    /// rewrites every row, then puts them back) read — and a spread of right-hand sides, so
    /// none may be in progress ([`Self::rhs_lagging`]).
    pub fn measurements_mut(
        &mut self,
        range: std::ops::Range<usize>,
    ) -> impl Iterator<Item = &mut [f64; K]> + '_ {
        self.rows.y.slices_in_mut(range).flatten()
    }

    /// Whether the right-hand sides lag the rows' measurements (a [`Self::relinearise`]
    /// whose spread forward solve has not ended).
    pub fn rhs_lagging(&self) -> bool {
        self.stale_rhs.is_some()
    }

    /// Advance the spread forward solve of the right-hand sides a [`Self::relinearise`] left
    /// lagging by one block (starting it, or starting it again when something it does not
    /// follow changed the factor); they are current when it ends.
    fn advance_rhs(&mut self) {
        let Some(from) = self.stale_rhs else {
            return;
        };
        if !self.factor.spreading(from) {
            (self.factor).spread_begin(from, self.rows.ends.len());
        }
        let rows = &self.rows;
        if self.factor.spread_advance(|range| rows.each_in(range)) {
            self.stale_rhs = None;
        }
    }

    /// Recompute the right-hand sides a [`Self::relinearise`] left lagging, now.
    pub fn flush_rhs(&mut self) {
        self.factor.spread_cancel();
        if let Some(from) = self.stale_rhs.take() {
            // The last row's gains stay valid: d is the same linear function of the rows'
            // right-hand sides, recomputed.
            reset_rhs(&mut self.factor, &self.rows, from);
        }
    }

    /// Take the live factor's work since the last call into this system's count (and as the
    /// step's own, [`Self::step_share`]).
    fn step_work(&mut self) {
        self.own_work = self.factor.take_work();
        self.work += self.own_work;
    }

    /// The share of its usual block that a pass spread over steps takes after the last step
    /// ([`crate::estimate::incremental::levelled`], by that step's own work on the factor):
    /// what [`Self::back_advance`] takes, for other passes to take alike.
    pub fn step_share(&self) -> f64 {
        self.factor.back_share(self.own_work)
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
            renewed_now: self.renewed_now,
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
    f.reset_rhs_from(from, rows.each());
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A replay's system, deferred, built from the factor of the system it replaces
    /// ([`Laplacian::adopt`]): a loop closure the replaced one had is gone (evicted), one it
    /// lacked is in (re-admitted), a wrap moved, two nodes and a new component (its anchor's
    /// prior) are new. The answers equal a whole build's to 1e-9, in the replaced factor's
    /// order; a system that differs in too many rows is not adopted (the caller rebuilds).
    #[test]
    fn a_replays_system_adopts_the_replaced_factor() {
        let chain = |l: &mut Laplacian<3>, n: usize| {
            l.add_node();
            for v in 1..n {
                l.add_node();
                l.add_edge(v - 1, v, 4.0, [0.01, 1.0, 0.0]);
            }
        };
        let mut old = Laplacian::<3>::default();
        chain(&mut old, 300);
        for v in (40..300).step_by(9) {
            old.add_edge(v - 35, v, 2.0, [0.3, 0.5, 30.0]);
        }
        // The replaced system: one false loop closure among them.
        old.add_edge(10, 290, 2.0, [3.0, 1.0, 1.0]);
        let replay = |readmitted: bool| {
            let mut l = Laplacian::<3>::default();
            l.defer();
            chain(&mut l, 302);
            for v in (40..300).step_by(9) {
                let wrap = if v == 103 {
                    0.3 - std::f64::consts::TAU
                } else {
                    0.3
                };
                l.add_edge(v - 35, v, 2.0, [wrap, 0.5, 30.0]);
            }
            if readmitted {
                l.add_edge(50, 250, 3.0, [0.7, 2.0, -1.0]);
            }
            // Two nodes of a new component.
            l.add_node();
            l.add_node();
            l.add_edge(302, 303, 5.0, [0.1, 1.0, 1.0]);
            l
        };
        let mut built = replay(true);
        built.rebuild();
        let mut adopted = replay(true);
        let order: Vec<u32> = (0..300).map(|v| old.factor.position_of(v)).collect();
        assert!(adopted.adopt(Box::new(old)));
        assert!(!adopted.deferred());
        // The headings' column is exact now, the positions' after the flush a rebuild makes.
        let headings = adopted.all(0);
        adopted.flush_rhs();
        assert_eq!(headings, adopted.all(0));
        for q in 0..3 {
            let (a, b) = (adopted.all(q), built.all(q));
            assert_eq!(a.len(), 304);
            for (x, y) in a.iter().zip(&b) {
                assert!((x - y).abs() < 1e-9, "column {q}: {x} vs {y}");
            }
        }
        // The replaced factor's order (its nodes where they were), not a new build's.
        let kept: Vec<u32> = (0..300).map(|v| adopted.factor.position_of(v)).collect();
        let fresh: Vec<u32> = (0..300).map(|v| built.factor.position_of(v)).collect();
        assert_eq!(kept, order);
        assert_ne!(fresh, order);
        // Too many rows apart: not adopted, nothing of the replay's system changed.
        let mut other = Laplacian::<3>::default();
        chain(&mut other, 250);
        let mut far = replay(false);
        assert!(!far.adopt(Box::new(other)));
        assert!(far.deferred());
    }

    /// A chain of `n` nodes with a loop closure of `span` nodes at every `every`-th node from
    /// `span` on.
    fn chain_with_closures(n: usize, every: usize, span: usize) -> Laplacian<3> {
        let mut l = Laplacian::<3>::default();
        l.add_node();
        for v in 1..n {
            l.add_node();
            l.add_edge(v - 1, v, 4.0, [0.01, 1.0, 0.0]);
            if v % every == 0 && v > span {
                l.add_edge(v - span, v, 2.0, [0.25, 0.5, 19.0]);
            }
        }
        l
    }

    /// A re-linearisation's job: every position measurement turned by 0.3 rad.
    fn turned(y: &mut Chunked<[f64; 3]>) {
        let (s, c) = 0.3f64.sin_cos();
        for r in y.iter_mut() {
            let [x, y] = [r[1], r[2]];
            (r[1], r[2]) = (c * x - s * y, s * x + c * y);
        }
    }

    /// A back-substitution spread over steps gives the bits of one at once when nothing
    /// changes in between; while rows are rotated in and nodes appended between its blocks,
    /// every value is off the solution of the last block's step by at most the sum of the
    /// most any value moved in each step (module `estimate::incremental::back`), and it does
    /// read the factors of the steps (it is not the first step's solution). A factor replaced
    /// drops it.
    #[test]
    fn a_back_substitution_spread_over_steps_is_within_the_movement_of_its_steps() {
        let mut l = chain_with_closures(3000, 5, 290);
        l.set_renewal_delay(f64::INFINITY);
        // Nothing changes: the same bits.
        l.back_start(0);
        let mut blocks = 0;
        while l.factor.back_advance_by(3000) == Some(false) {
            blocks += 1;
        }
        assert!(blocks >= 5, "{blocks} blocks");
        let (spread, whole) = (l.back_take().expect("complete"), l.all(0));
        assert!(
            spread
                .iter()
                .zip(&whole)
                .all(|(a, b)| a.to_bits() == b.to_bits())
        );
        assert!(l.back_take().is_none(), "taken once");
        // Loop closures that turn the headings, and new nodes, between the blocks.
        l.back_start(0);
        let mut solutions = vec![l.all(0)];
        for step in 0.. {
            let v = l.add_node();
            l.add_edge(v - 1, v, 4.0, [0.01, 1.0, 0.0]);
            // Loop closures 0.05 rad off the headings' prediction: each moves them a little.
            let now = l.all(0);
            let off_by = |a: usize, delta: f64| [now[v] - now[a] + delta, 0.0, 0.0];
            match step % 3 {
                0 => l.add_edge(v - 900 - step, v, 2.0, off_by(v - 900 - step, -0.05)),
                1 => {
                    assert!(
                        l.try_edge(v - 2500, v, 2.0, off_by(v - 2500, 0.05))
                            .is_some()
                    );
                    l.keep_edge();
                }
                _ => {}
            }
            l.after_step(|| None);
            let done = l.factor.back_advance_by(3000);
            solutions.push(l.all(0));
            if done == Some(true) {
                assert!(step >= 5, "{step} steps");
                break;
            }
            assert_eq!(done, Some(false));
        }
        let spread = l.back_take().expect("complete");
        let last = solutions.last().expect("a step");
        let moved: f64 = (solutions.windows(2))
            .map(|w| (w[0].iter().zip(&w[1])).fold(0.0_f64, |m, (a, b)| m.max((a - b).abs())))
            .sum();
        let off = (spread.iter().zip(last)).fold(0.0_f64, |m, (a, b)| m.max((a - b).abs()));
        let off_first =
            (spread.iter().zip(&solutions[0])).fold(0.0_f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(moved > 0.05, "the headings moved by {moved} only");
        assert!(off <= moved + 1e-9, "{off} off, {moved} moved");
        assert!(
            off_first > 1e-3,
            "the first step's solution ({off_first} off)"
        );
        assert_eq!(spread.len(), last.len(), "the appended nodes solved");
        // A replaced factor drops it.
        l.back_start(0);
        l.rebuild();
        assert_eq!(l.back_advance(), None);
        assert!(l.back_take().is_none());
    }

    /// A re-linearisation rewrites the rows at once and their right-hand sides at the end of
    /// the next step when the factor is small (one block of the spread forward solve: a
    /// larger one is the next test's): in between the factor answers as before it (the
    /// headings' column untouched throughout), after it as a re-linearisation applied at once
    /// — with rows rotated in between, and for a factor widened to two lanes while it lags.
    #[test]
    fn a_relinearisation_lands_at_the_next_step() {
        let build = || chain_with_closures(300, 7, 20);
        let job = || turned;
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
        now.after_step(|| None);
        later.after_step(|| None);
        now2.after_step(|| None);
        later2.after_step(|| None);
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

    /// A re-linearisation's right-hand sides computed a block of positions per step, while
    /// every kind of change goes on (new nodes and chains, loop closures added, tried and kept,
    /// tried and taken back, the last row's measurement moved; an older row's moved, or the
    /// last row's after the solve moved on, which start it again; a widening to two lanes) end equal to those of one forward solve
    /// made at once before the same changes; and they take several steps, during which the
    /// answers are the old rows' (the positions do not move until the end).
    #[test]
    fn a_relinearisation_spread_over_steps_ends_where_one_at_once_does() {
        let build = || {
            let mut l = chain_with_closures(3000, 5, 290);
            // No renewal collected: the spread, not a renewed factor, brings the new sides.
            l.set_renewal_delay(f64::INFINITY);
            l
        };
        let job = || turned;
        let close = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9);
        // One step's changes, the same in both; `step` picks which.
        fn changes<const L: usize>(l: &mut Laplacian<3, L>, step: usize, w: [f64; L]) {
            if step == 6 {
                // The last row's measurement, after the spread moved on: it starts again.
                let e = l.edge_count() - 1;
                let y = l.y(e);
                l.set_y(e, [y[0], y[1] + 1.0, y[2]]);
            }
            let v = l.add_node();
            l.add_edge(v - 1, v, w, [0.02, 1.0, 0.1]);
            match if step == 2 { 4 } else { step % 4 } {
                0 => l.add_edge(v - 700, v, w, [0.1, 2.0, -3.0]),
                1 => {
                    assert!(l.try_edge(v - 1200, v, w, [0.3, 0.0, 0.0]).is_some());
                    l.keep_edge();
                    // Its position row, through its gains.
                    l.set_y(l.edge_count() - 1, [0.3, -4.0, 2.5]);
                }
                2 => {
                    assert!(l.try_edge(v - 40, v, w, [1.0, 5.0, 5.0]).is_some());
                    l.undo_edge();
                }
                3 => {
                    l.add_edge(v - 2500, v, w, [0.05, 0.0, 0.0]);
                    l.set_y(l.edge_count() - 1, [0.05, 7.0, -1.0]);
                }
                _ => {
                    // An older row's position measurement: the spread starts again.
                    let e = l.edge_count() - 10;
                    let y = l.y(e);
                    l.set_y(e, [y[0], y[1] + 0.5, y[2]]);
                }
            }
        }
        for widen_at in [None, Some(4)] {
            let (mut now, mut later, mut plain) = (build(), build(), build());
            let before = later.all(1);
            now.relinearise(job(), 1);
            now.flush_rhs();
            later.relinearise(job(), 1);
            let (mut now2, mut later2) = (None, None);
            let mut steps = 0;
            for step in 0..60 {
                if Some(step) == widen_at {
                    now2 = Some(now.widen([1.0, 2.0]));
                    later2 = Some(later.widen([1.0, 2.0]));
                }
                match (&mut now2, &mut later2) {
                    (Some(n), Some(l)) => {
                        changes(n, step, [1.5, 0.7]);
                        changes(l, step, [1.5, 0.7]);
                        n.after_step(|| None);
                        l.after_step(|| None);
                        if l.stale_rhs.is_none() {
                            break;
                        }
                    }
                    _ => {
                        changes(&mut now, step, [1.5]);
                        changes(&mut later, step, [1.5]);
                        // Until the end the answers are those of the rows before.
                        changes(&mut plain, step, [1.5]);
                        assert!(close(&later.all(1), &plain.all(1)), "moved early");
                        plain.after_step(|| None);
                        now.after_step(|| None);
                        later.after_step(|| None);
                        if later.stale_rhs.is_none() {
                            break;
                        }
                    }
                }
                steps += 1;
            }
            assert!(steps >= 5, "spread over {steps} steps only");
            let renewals = later2.as_ref().map_or(later.renewals, |l| l.renewals);
            assert_eq!(renewals, 0);
            let (a, b): (Vec<Vec<f64>>, Vec<Vec<f64>>) = match (now2, later2) {
                (Some(mut n), Some(mut l)) => (
                    (0..3).map(|q| n.all(q)).collect(),
                    (0..3).map(|q| l.all(q)).collect(),
                ),
                _ => (
                    (0..3).map(|q| now.all(q)).collect(),
                    (0..3).map(|q| later.all(q)).collect(),
                ),
            };
            for q in 0..3 {
                assert!(close(&a[q], &b[q]), "column {q}, widened at {widen_at:?}");
            }
            assert!(!close(&b[1], &before), "the positions did not move");
        }
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
