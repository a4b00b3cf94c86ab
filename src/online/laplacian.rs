//! A weighted-Laplacian least-squares problem kept factored as edges arrive: the orientation
//! estimate a robot reads after every step, and the positions given the orientations.
//!
//! Both are `K` scalar problems sharing one weighted graph Laplacian,
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
//!   only its right-hand side moves.
//!
//! **Renewing the order without a stall.** New nodes are appended at the end, so revisits of
//! old places make R fill in, and the nodes appended since the last renewal form a chain that
//! every loop closure to an older node walks. When R's nonzeros per row have grown by half, or
//! an eighth of the nodes were appended, since the last renewal, a new factor is built
//! **beside** the live one on another thread, in approximate minimum-degree order with the
//! newest node last (the graph as it was at that step). It is collected a fixed number of
//! steps later ([`DELAY_PER_ROW`] steps per nonzero of R, at least
//! [`MIN_DELAY`]: a step count, so the run stays deterministic whatever the threads' timing;
//! the step waits only if the builder is still busy then). The events since the snapshot are
//! then replayed into it, at most [`REPLAY_PER_STEP`] per step, and once it has caught up, d is
//! recomputed from the current measurements (one forward solve) and the new factor replaces
//! the old.
//! Every answer in between comes from the live factor: exact at every step.

use std::thread::JoinHandle;

use crate::estimate::incremental::{SqrtInfo, fill_reducing_order};
use crate::graph::UnionFind;

/// Renew the order when R's nonzeros per row exceed this multiple of the last renewal's.
const FILL_RATIO: f64 = 1.5;
/// Renew when more than `1/APPENDED_FRACTION` of the nodes were appended since the last
/// renewal.
const APPENDED_FRACTION: usize = 8;
/// Below this many variables the order is never renewed.
const MIN_VARIABLES: usize = 256;
/// Steps between starting a renewal and collecting it, at least.
pub(crate) const MIN_DELAY: u64 = 32;
/// Steps between starting a renewal and collecting it, per nonzero of R (the builder's work
/// grows with the factor).
pub(crate) const DELAY_PER_ROW: f64 = 0.002;
/// Events replayed into a renewed factor per step.
pub(crate) const REPLAY_PER_STEP: usize = 32;

#[derive(Clone, Copy, Debug)]
enum Event {
    Variable(u32),
    Prior(u32),
    Unprior(u32),
    Row(u32),
}

struct Renewal<const K: usize> {
    build: Beside<SqrtInfo<K>>,
    events: Vec<Event>,
    replayed: usize,
}

/// A factor built beside the live one on another thread and collected at a step fixed when it
/// was started (shared by the estimate's factors and the factor of P_γ, so the run does not
/// depend on the threads' timing).
pub(crate) struct Beside<T> {
    handle: Option<JoinHandle<Option<T>>>,
    fresh: Option<T>,
    ready_at: u64,
}

impl<T: Send + 'static> Beside<T> {
    /// Start `job` on a thread named `name`, to be collected at step `ready_at`. None when no
    /// thread can be started: the live factor goes on, and the owner may try again later.
    pub fn start(
        name: &str,
        ready_at: u64,
        job: impl FnOnce() -> Option<T> + Send + 'static,
    ) -> Option<Self> {
        let handle = std::thread::Builder::new()
            .name(name.into())
            .spawn(job)
            .ok()?;
        Some(Self {
            handle: Some(handle),
            fresh: None,
            ready_at,
        })
    }

    /// At step `step`: the built factor once its step has come (joining the builder, and
    /// counting in `waits` a step that found it still busy), `Ok(None)` before, `Err(())` if
    /// the build failed.
    pub fn poll(&mut self, step: u64, waits: &mut usize) -> Result<Option<&mut T>, ()> {
        if self.fresh.is_none() {
            if step < self.ready_at {
                return Ok(None);
            }
            let h = self.handle.take().ok_or(())?;
            if !h.is_finished() {
                *waits += 1;
            }
            self.fresh = Some(h.join().ok().flatten().ok_or(())?);
        }
        Ok(self.fresh.as_mut())
    }

    /// The built factor (after [`Self::poll`] gave it).
    pub fn take(self) -> Option<T> {
        self.fresh
    }
}

/// The data a factor is built from (a snapshot goes to the builder thread).
#[derive(Clone)]
struct Rows<const K: usize> {
    ends: Vec<(u32, u32)>,
    sqrt_w: Vec<f64>,
    /// `y_e` of every edge.
    y: Vec<[f64; K]>,
}

impl<const K: usize> Default for Rows<K> {
    fn default() -> Self {
        Self {
            ends: Vec::new(),
            sqrt_w: Vec::new(),
            y: Vec::new(),
        }
    }
}

impl<const K: usize> Rows<K> {
    fn entries(&self, e: usize) -> [(usize, f64); 2] {
        let (a, b) = self.ends[e];
        let s = self.sqrt_w[e];
        [(a as usize, -s), (b as usize, s)]
    }

    fn rhs(&self, e: usize) -> [f64; K] {
        self.y[e].map(|y| self.sqrt_w[e] * y)
    }
}

/// The incrementally factored Laplacian system (see the module docs).
pub(crate) struct Laplacian<const K: usize> {
    factor: SqrtInfo<K>,
    rows: Rows<K>,
    components: UnionFind,
    /// Anchor (least node index) of each union-find root.
    anchor: Vec<usize>,
    /// The weight of each node's anchor prior (0: none). The prior takes the square-root
    /// weight of the component's first edge, so the component's common mode is as well
    /// determined as its differences (a weak prior would collect the rounding errors there).
    prior: Vec<f64>,
    /// The prior weight each node was (or would be) given as an anchor.
    first_weight: Vec<f64>,
    fill_after_renewal: f64,
    /// Nodes at the last renewal (its snapshot).
    nodes_at_renewal: usize,
    renewal: Option<Renewal<K>>,
    steps: u64,
    /// Renewals completed.
    pub renewals: usize,
    /// Steps that waited for a renewal's builder.
    pub waits: usize,
}

impl<const K: usize> Default for Laplacian<K> {
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
            steps: 0,
            renewals: 0,
            waits: 0,
        }
    }
}

impl<const K: usize> Laplacian<K> {
    /// Number of nodes.
    pub fn len(&self) -> usize {
        self.anchor.len()
    }

    fn log(&mut self, e: Event) {
        if let Some(r) = &mut self.renewal {
            r.events.push(e);
        }
    }

    /// A new node (index = current count).
    pub fn add_node(&mut self) -> usize {
        let v = self.components.push();
        self.anchor.push(v);
        self.prior.push(0.0);
        self.first_weight.push(0.0);
        self.factor.push_variable(v);
        self.log(Event::Variable(v as u32));
        v
    }

    /// Number of edges.
    pub fn edge_count(&self) -> usize {
        self.rows.ends.len()
    }

    /// A new edge from node a to b with weight w and measurement y.
    pub fn add_edge(&mut self, a: usize, b: usize, w: f64, y: [f64; K]) {
        let e = self.rows.ends.len();
        self.rows.ends.push((a as u32, b as u32));
        self.rows.sqrt_w.push(w.sqrt());
        self.rows.y.push(y);
        let (ra, rb) = (self.components.find(a), self.components.find(b));
        let (aa, ab) = (self.anchor[ra], self.anchor[rb]);
        let (winner, loser) = (aa.min(ab), aa.max(ab));
        if self.prior[winner] == 0.0 {
            self.first_weight[winner] = self.rows.sqrt_w[e];
            self.prior[winner] = self.rows.sqrt_w[e];
            self.factor
                .add_row(&[(winner, self.prior[winner])], [0.0; K]);
            self.log(Event::Prior(winner as u32));
        }
        self.factor.add_row(&self.rows.entries(e), self.rows.rhs(e));
        self.log(Event::Row(e as u32));
        if ra != rb {
            self.components.union(a, b);
            let r = self.components.find(a);
            self.anchor[r] = winner;
            let p = self.prior[loser];
            if p != 0.0 {
                self.prior[loser] = 0.0;
                self.log(Event::Unprior(loser as u32));
                if self.factor.remove_row(&[(loser, p)], [0.0; K]).is_err() {
                    // Numerically the prior was the only information left: rebuild now.
                    self.renewal = None;
                    self.factor = build(&self.rows, &self.prior, self.len(), None);
                }
            }
        }
    }

    /// Set the measurement of edge e (only its right-hand side moves).
    pub fn set_y(&mut self, e: usize, y: [f64; K]) {
        let old = self.rows.y[e];
        if old == y {
            return;
        }
        self.rows.y[e] = y;
        let s = self.rows.sqrt_w[e];
        let shift: [f64; K] = std::array::from_fn(|q| s * (y[q] - old[q]));
        self.factor.shift_rhs(&self.rows.entries(e), shift);
    }

    /// Every node's values (per right-hand side) for other measurements `y`, leaving the
    /// factor as it was: one forward and one back-substitution.
    pub fn all_for(&mut self, y: Vec<[f64; K]>) -> [Vec<f64>; K] {
        let saved_y = std::mem::replace(&mut self.rows.y, y);
        let saved_d = self.factor.rhs().to_vec();
        reset_rhs(&mut self.factor, &self.rows);
        let out = std::array::from_fn(|q| self.all(q));
        self.rows.y = saved_y;
        self.factor.set_rhs(saved_d);
        out
    }

    /// Set every edge's measurement and recompute d at once (one forward solve): cheaper
    /// than shifting when most right-hand sides move.
    pub fn reset_y(&mut self, y: Vec<[f64; K]>) {
        self.rows.y = y;
        reset_rhs(&mut self.factor, &self.rows);
    }

    /// Value of node v: back-substitution along its elimination-tree path (O(1) for the
    /// last node of the order, the newest).
    pub fn value(&mut self, v: usize) -> [f64; K] {
        self.factor.value(v)
    }

    /// Values of every node for right-hand side q: one back-substitution (each relative to
    /// its anchor, which removes the rounding of the common mode).
    pub fn all(&mut self, q: usize) -> Vec<f64> {
        let mut x = self.factor.solve(q);
        for v in 0..x.len() {
            let r = self.components.find(v);
            let a = self.anchor[r];
            if a != v {
                x[v] -= x[a];
            }
        }
        for (xv, &p) in x.iter_mut().zip(&self.prior) {
            if p != 0.0 {
                *xv = 0.0;
            }
        }
        x
    }

    /// Marginal variance of node v in the anchored system: `Var(θ_v − θ_anchor)` (0 for an
    /// anchor), exact with the anchor's prior (the prior only adds a common shift).
    pub fn variance(&mut self, v: usize) -> f64 {
        let r = self.components.find(v);
        let a = self.anchor[r];
        if a == v {
            return 0.0;
        }
        self.factor.marginal(&[(v, 1.0), (a, -1.0)])
    }

    /// Called once per step, after its events: starts, advances or completes a renewal.
    pub fn after_step(&mut self) {
        self.steps += 1;
        if self.renewal.is_some() {
            self.advance_renewal();
            return;
        }
        let n = self.len();
        if n < MIN_VARIABLES {
            return;
        }
        // Nodes appended since the last renewal form a chain at the end of the order that
        // every loop closure to an older node walks: renew when it is an eighth of the graph,
        // or when the fill per row has grown by half.
        let per_row = self.factor.nnz() as f64 / n as f64;
        let appended = n - self.nodes_at_renewal;
        if per_row <= FILL_RATIO * self.fill_after_renewal.max(1.0)
            && appended <= MIN_VARIABLES.max(n / APPENDED_FRACTION)
        {
            return;
        }
        let rows = self.rows.clone();
        let prior = self.prior.clone();
        let newest = n - 1;
        let delay = MIN_DELAY.max((self.factor.nnz() as f64 * DELAY_PER_ROW) as u64);
        let job = move || Some(build(&rows, &prior, n, Some(newest)));
        let Some(build) = Beside::start("so2lin-renew", self.steps + delay, job) else {
            return;
        };
        self.nodes_at_renewal = n;
        self.renewal = Some(Renewal {
            build,
            events: Vec::new(),
            replayed: 0,
        });
    }

    fn advance_renewal(&mut self) {
        let Some(r) = &mut self.renewal else { return };
        let fresh = match r.build.poll(self.steps, &mut self.waits) {
            Ok(Some(f)) => f,
            Ok(None) => return,
            Err(()) => {
                self.renewal = None;
                return;
            }
        };
        let end = (r.replayed + REPLAY_PER_STEP).min(r.events.len());
        for ev in &r.events[r.replayed..end] {
            match *ev {
                Event::Variable(v) => fresh.push_variable(v as usize),
                Event::Prior(v) => {
                    fresh.add_row(&[(v as usize, self.first_weight[v as usize])], [0.0; K])
                }
                Event::Row(e) => fresh.add_row(&self.rows.entries(e as usize), [0.0; K]),
                Event::Unprior(v) => {
                    let p = self.first_weight[v as usize];
                    if fresh.remove_row(&[(v as usize, p)], [0.0; K]).is_err() {
                        self.renewal = None;
                        return;
                    }
                }
            }
        }
        r.replayed = end;
        if r.replayed < r.events.len() {
            return;
        }
        let Some(mut fresh) = self.renewal.take().and_then(|r| r.build.take()) else {
            return;
        };
        reset_rhs(&mut fresh, &self.rows);
        self.fill_after_renewal = fresh.nnz() as f64 / self.len().max(1) as f64;
        self.factor = fresh;
        self.renewals += 1;
    }
}

/// d of a factor from the rows' current right-hand sides (priors have 0).
fn reset_rhs<const K: usize>(f: &mut SqrtInfo<K>, rows: &Rows<K>) {
    f.reset_rhs((0..rows.ends.len()).map(|e| (rows.entries(e), rows.rhs(e))));
}

/// A factor of the whole system in a fill-reducing order (`last` at the end).
fn build<const K: usize>(
    rows: &Rows<K>,
    prior: &[f64],
    n: usize,
    last: Option<usize>,
) -> SqrtInfo<K> {
    let ends: Vec<(usize, usize)> = rows
        .ends
        .iter()
        .map(|&(a, b)| (a as usize, b as usize))
        .collect();
    let last: Vec<usize> = last.into_iter().collect();
    let order = fill_reducing_order(n, &ends, &last);
    let mut f = SqrtInfo::new();
    for v in order {
        f.push_variable(v);
    }
    for (v, &p) in prior.iter().enumerate().take(n) {
        if p != 0.0 {
            f.add_row(&[(v, p)], [0.0; K]);
        }
    }
    for e in 0..rows.ends.len() {
        f.add_row(&rows.entries(e), rows.rhs(e));
    }
    f
}
