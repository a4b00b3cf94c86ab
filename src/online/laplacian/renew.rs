//! Renewing a [`Laplacian`]'s factor without a stall: when a renewal starts, what its builder
//! does, and when the new factor is swapped in (the builder's thread and the hand-over of its
//! state: [`crate::online::renewal`]).
//!
//! New nodes are appended at the end, so revisits of old places make R fill in, and the nodes
//! appended since the last renewal form a chain that every loop closure to an older node walks. When R's nonzeros per row have grown by half (by a fifth
//! from 20 000 variables: [`FILL_RATIO_LARGE`]), or an eighth of the nodes were appended, since the
//! last renewal, a new factor is built **beside** the live one on another thread: approximate
//! minimum-degree order with the newest node last (the graph as it was at that step; from 20 000
//! variables four levels of nested dissection above it, [`dissected_order`], the separators
//! computed afresh only once the graph has grown by a quarter and the nodes added since placed in
//! the last renewal's tree otherwise, a renewal that splits afresh due [`SPLIT_BUILD`] times
//! later), from a snapshot of the rows and priors that shares their chunks (module
//! [`crate::online::snapshot`]: the step that starts it copies a pointer per 1 024 rows, not the
//! rows; such a step took 0.19–0.57 ms on city10000 and 2.0–7.1 ms on a 100 000-pose world
//! while it copied them), the normal
//! equations factored at once by a sparse Cholesky ([`SqrtInfo::factored`], supernodal on large
//! factors; rows rotated in when extreme weights defeat it). Every later change (node, row, removed
//! prior, moved right-hand side) is sent to the builder, a step's changes together at its end
//! (one lock and one wake-up: `strace -f -c` of `so2lin stream M3500.g2o --json` counted 7 251
//! futex calls against 13 942 when each change went alone), which applies
//! them to its factor as they come, so the live factor's steps replay nothing
//! ([`crate::online::renewal`]). The new factor is
//! collected once the live factor has done [`work_per_nonzero`] units of its own work
//! ([`SqrtInfo::take_work`]; 96 up to M3500's 3 500 nodes, growing to 144 at 5 500, 120 from
//! 20 000) per nonzero the renewed factor is expected to have (the last renewal's fill per row
//! times the variables), and at least [`MIN_DELAY`] steps after the start — counts, not clocks, so
//! the run stays deterministic whatever the threads' timing; the step waits only if the builder is
//! still busy then — and swapped in. Every answer in between comes from the live factor: exact at
//! every step.
//!
//! A caller with idle time between steps renews on its own thread instead
//! ([`Laplacian::renew_now`], driven by [`crate::online::OnlineEstimator::maintain`]): the same
//! build from the graph as it is then, swapped in at once, so the factor's order has no nodes
//! appended after its snapshot.

use super::{Laplacian, Rows, reset_rhs};
use crate::estimate::incremental::{Dissection, SqrtInfo, dissected_order, fill_reducing_order};
use crate::online::renewal::{Beside, Due};
use crate::online::snapshot::Chunked;
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
pub(super) const LARGE_FACTOR: usize = 20_000;

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
    /// Edge e's y is now this in the components marked (the others as the builder has them:
    /// a wrap moves the heading only, and the builder's positions may be re-linearised).
    SetY(u32, [f64; K], [bool; K]),
    /// Every edge's y is now this (a re-linearisation: [`Laplacian::relinearise`]).
    Relinearised(Chunked<[f64; K]>),
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
type Built<const K: usize, const L: usize> =
    (SqrtInfo<K, L>, Chunked<[f64; K]>, Option<Dissection>);

/// A renewal builder's state: its factor, its copy of the rows, its dissection.
type Building<const K: usize, const L: usize> = (SqrtInfo<K, L>, Rows<K, L>, Option<Dissection>);

/// A job that rewrites the measurements `y` of a renewal's snapshot from right-hand side 1 on,
/// given the snapshot's solution of right-hand side 0 (indexed by node: the headings), run by
/// the builder: it solves that from the factor it built, so that the robot's step that starts
/// a renewal pays no back-substitution. (Not made relative to the anchors as
/// [`Laplacian::all`] reads the live factor: an anchor's prior holds it at 0 to rounding, and
/// a solution from another factor differs in its last bits anyway.)
pub(super) type Relinearise<const K: usize> =
    Box<dyn FnOnce(&mut Chunked<[f64; K]>, &[f64]) + Send>;

/// A renewal of a Laplacian's factor in progress.
pub(super) type Renewal<const K: usize, const L: usize> =
    Beside<Building<K, L>, Built<K, L>, Msg<K, L>>;

/// How a build orders the variables.
pub(super) enum BuildOrder {
    /// Approximate minimum degree ([`fill_reducing_order`]).
    MinimumDegree,
    /// Nested dissection ([`dissected_order`]): the variables placed in the given tree, or a
    /// fresh split.
    Dissected(Option<Arc<Dissection>>),
}

impl<const K: usize, const L: usize> Laplacian<K, L> {
    /// Tell a renewal's builder (if any) about a change: queued here, and handed over with
    /// the step's others at its end ([`Self::post`]).
    pub(super) fn send(&mut self, msg: Msg<K, L>) {
        if self.renewal.is_some() {
            self.outbox.push(msg);
        }
    }

    /// Hand the step's changes to the renewal's builder at once: one lock, and one wake-up
    /// when it waits for them, per step rather than per change (a wake-up is a system call,
    /// and the builder's thread woke for each). A builder that is gone abandons the renewal
    /// (the live factor goes on).
    pub(super) fn post(&mut self) {
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
    pub(super) fn drop_renewal(&mut self) {
        self.renewal = None;
        self.outbox.clear();
    }

    /// Whether [`Self::renew_now`] is worth a caller's idle time: the factor is large enough to
    /// be renewed at all, and at least `appended` nodes were appended at the end of its order
    /// since it was made (the chain every loop closure to an older node walks).
    pub fn renewal_pays(&self, appended: usize) -> bool {
        let n = self.len();
        !self.deferred && n >= MIN_VARIABLES && n - self.nodes_at_renewal.min(n) >= appended
    }

    /// The order a renewal of `n` variables builds in: nested dissection from
    /// [`LARGE_FACTOR`] variables (in the last renewal's tree while it is not stale), minimum
    /// degree below.
    fn renewal_order(&self, n: usize) -> BuildOrder {
        if n >= self.dissect_from {
            BuildOrder::Dissected(self.dissection.clone().filter(|t| !t.stale(n)))
        } else {
            BuildOrder::MinimumDegree
        }
    }

    /// A renewal now, on the calling thread (a caller's idle time between steps): any renewal
    /// in progress is dropped, the factor is built as a renewal's builder builds it (a
    /// fill-reducing order with the newest node last, from the graph as it is now), the job
    /// `relinearise` rewrites the rows' right-hand sides 1.. from its headings, and it is
    /// swapped in. The old factor is freed here too, not on the worker (nothing runs beside
    /// the next step).
    pub fn renew_now(&mut self, relinearise: Option<Relinearise<K>>) {
        // (Right-hand sides lagging a re-linearisation need no flush: the new factor's come
        // from the rows. Changes queued for the builder go with it.)
        self.drop_renewal();
        let n = self.len();
        let order = self.renewal_order(n);
        let room = self.factor.capacity();
        let (f, tree) = renewed(&mut self.rows, &self.prior, n, order, relinearise, room);
        if let Some(tree) = tree {
            self.dissection = Some(Arc::new(tree));
        }
        drop(std::mem::replace(&mut self.factor, SqrtInfo::new()));
        self.install(f);
        self.nodes_at_renewal = n;
        self.renewed_now += 1;
    }

    /// Collect later renewals after `delay` times the default work ([`work_per_nonzero`]):
    /// sooner below 1 (a caller whose edges arrive slowly enough for the builder).
    pub fn set_renewal_delay(&mut self, delay: f64) {
        self.renewal_delay = delay;
    }

    /// Called once per step, after its events: starts or completes a renewal. A renewal's
    /// snapshot takes the right-hand sides 1.. computed by the job `relinearise` gives (None:
    /// the current ones) from the snapshot's solution of right-hand side 0, both on the
    /// builder's thread; they become the live ones when the renewal is swapped in.
    pub fn after_step(
        &mut self,
        relinearise: impl FnOnce() -> Option<Relinearise<K>>,
    ) -> Option<RenewalEvent> {
        self.steps += 1;
        if self.deferred {
            return None;
        }
        self.advance_rhs();
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
        let relinearise = relinearise();
        let prior = self.prior.clone();
        // The builder's work grows with the size of the factor it builds (about the last
        // renewal's fill per row), not with the live factor's fill, which is what grows
        // without bound between renewals.
        let expected_nnz = self.fill_after_renewal.max(2.0) * n as f64;
        // The renewed factor and right-hand sides get the live ones' room (reserved on the
        // builder, so that the first node or edge after the swap does not copy them in a step).
        let room = self.factor.capacity();
        let y_room = self.rows.y.capacity();
        let order = self.renewal_order(n);
        // A fresh split computes its separators too.
        let split = if matches!(order, BuildOrder::Dissected(None)) {
            SPLIT_BUILD
        } else {
            1.0
        };
        let build = move || {
            let (f, tree) = renewed(&mut rows, &prior, n, order, relinearise, room);
            // (Refused, the renewed rows grow as they would have.)
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
                Msg::SetY(e, y, changed) => {
                    let e = e as usize;
                    let old = *rows.y.get(e)?;
                    let y = std::array::from_fn(|q| if changed[q] { y[q] } else { old[q] });
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

/// A renewal's factor of `rows` (the newest of the `n` nodes last, in `order`), as a builder
/// and [`Laplacian::renew_now`] make it: if `relinearise` is given, the headings solved from
/// the new factor, the rows' right-hand sides 1.. rewritten from them and the factor's
/// recomputed (a forward solve); the factor given `room` (the live one's capacity, so that
/// the first change after the swap does not copy it). With the dissection the order came from.
fn renewed<const K: usize, const L: usize>(
    rows: &mut Rows<K, L>,
    prior: &Chunked<[f64; L]>,
    n: usize,
    order: BuildOrder,
    relinearise: Option<Relinearise<K>>,
    room: usize,
) -> (SqrtInfo<K, L>, Option<Dissection>) {
    let (mut f, tree) = build(rows, prior, n, n.checked_sub(1), order);
    if let Some(job) = relinearise {
        let [x] = f.solve_columns([0]);
        job(&mut rows.y, &x);
        reset_rhs(&mut f, rows, 1);
    }
    // (Refused, the renewed factor grows as it would have.)
    let _ = f.try_reserve(room.saturating_sub(f.len()));
    (f, tree)
}

/// A factor of the whole system in a fill-reducing order (`last` at the end), and the
/// dissection the order came from ([`BuildOrder::Dissected`]).
pub(super) fn build<const K: usize, const L: usize>(
    rows: &Rows<K, L>,
    prior: &Chunked<[f64; L]>,
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
    let edges = rows.each();
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
            let event = l.after_step(|| None);
            assert_eq!(event.is_some(), l.renewing(), "started: {event:?}");
            assert!(l.len() <= MIN_VARIABLES + 1, "no renewal started");
        }
        for _ in 0..2 * MIN_DELAY {
            assert_eq!(l.after_step(|| None), None);
        }
        assert!(
            l.renewing() && l.renewals == 0,
            "collected without the work due"
        );
        // Loop closures to the first node: the live factor's own work, until the due.
        let mut closures = 0;
        while l.renewals == 0 {
            let v = l.len() - 1;
            // Tried and kept, as a stream's loop closures are (their undo record grows).
            if l.try_edge(0, v, 1.0, [0.1 * v as f64]).is_some() {
                l.keep_edge();
            } else {
                l.add_edge(0, v, 1.0, [0.1 * v as f64]);
            }
            closures += 1;
            let room = l.factor.scratch_room();
            let event = l.after_step(|| None);
            // The renewed factor took the live one's scratch (not grown again after the swap).
            assert!(l.factor.scratch_room() >= room.max(1), "{event:?}");
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

    /// A renewal now (a caller's idle time) drops the renewal in progress beside, builds the
    /// factor with no node appended after its order, and answers as the live factor did; it
    /// is due again only once enough nodes were appended since.
    #[test]
    fn a_renewal_now_replaces_the_one_beside() {
        // A node with its odometry edge, and every fifth one a loop closure 20 nodes back.
        let grow = |l: &mut Laplacian<1>, loops: bool| {
            let v = l.add_node();
            l.add_edge(v - 1, v, 4.0, [0.1]);
            if loops && v.is_multiple_of(5) && v > 20 {
                l.add_edge(v - 20, v, 1.0, [2.05]);
            }
        };
        let mut l = Laplacian::<1>::default();
        l.add_node();
        while !l.renewing() {
            grow(&mut l, true);
            l.after_step(|| None);
        }
        // Three nodes appended since the renewal beside started (its snapshot).
        let loops_until = l.len();
        for _ in 0..3 {
            grow(&mut l, false);
            l.after_step(|| None);
        }
        assert!(l.renewing());
        let before = l.all(0);
        assert!(l.renewal_pays(3) && !l.renewal_pays(4));
        l.renew_now(None);
        assert!(!l.renewing(), "the renewal beside is dropped");
        assert_eq!((l.renewed_now, l.renewals), (1, 0));
        assert!(!l.renewal_pays(1), "nothing appended since");
        for (a, b) in l.all(0).iter().zip(&before) {
            assert!((a - b).abs() < 1e-9, "{a} vs {b}");
        }
        // The chain appended since the renewal is empty: a loop closure from the newest node
        // to the first walks the fresh order, less than the live factor's before it did.
        let mut old = Laplacian::<1>::default();
        old.add_node();
        // The same graph, every node appended in arrival order.
        for _ in 1..l.len() {
            let loops = old.len() < loops_until;
            grow(&mut old, loops);
        }
        let n = l.len() - 1;
        let (_, a) = old.work_and_nnz();
        let (_, b) = l.work_and_nnz();
        assert!(b < a, "fresh order {b} nonzeros against {a} appended");
        l.add_edge(0, n, 1.0, [0.5]);
        let v = l.add_node();
        l.add_edge(v - 1, v, 4.0, [0.1]);
        assert!(!l.renewal_pays(2) && l.renewal_pays(1));
    }

    /// A renewal re-linearises its snapshot on the builder, from the headings the builder
    /// solves from its new factor: once swapped in, the factor answers as one whose rows were
    /// re-linearised on the step at the snapshot's headings (read from the live factor) and
    /// then renewed — also when an old edge's wrap moves while it is built (the builder keeps
    /// its re-linearised position for that edge: the live factor's is older). And the
    /// re-linearisation matters: without it the positions differ.
    #[test]
    fn a_renewal_relinearises_its_snapshot_on_the_builder() {
        // Each edge's tail and translation (the position columns are rewritten from them).
        let mut tails: Vec<(usize, f64)> = Vec::new();
        let job = |tails: Vec<(usize, f64)>| {
            move |y: &mut Chunked<[f64; 3]>, theta: &[f64]| {
                for (r, &(a, t)) in y.iter_mut().zip(&tails) {
                    let (s, c) = theta[a].sin_cos();
                    (r[1], r[2]) = (c * t, s * t);
                }
            }
        };
        let (mut on_builder, mut on_step, mut never) = (
            Laplacian::<3>::default(),
            Laplacian::<3>::default(),
            Laplacian::<3>::default(),
        );
        let mut add = |ls: [&mut Laplacian<3>; 3], a: usize, b: usize, w: f64, y: [f64; 3]| {
            tails.push((a, y[1]));
            for l in ls {
                l.add_edge(a, b, w, y);
            }
            tails.clone()
        };
        for l in [&mut on_builder, &mut on_step, &mut never] {
            l.add_node();
        }
        let (mut started, mut wrapped) = (false, false);
        let mut v = 0;
        while on_builder.renewals == 0 {
            v += 1;
            for l in [&mut on_builder, &mut on_step, &mut never] {
                l.add_node();
            }
            let ls = [&mut on_builder, &mut on_step, &mut never];
            let mut copied = add(ls, v - 1, v, 4.0, [0.02, 1.0, 0.0]);
            if v % 5 == 0 && v > 30 {
                // Loop closures whose headings disagree with the chain's.
                let ls = [&mut on_builder, &mut on_step, &mut never];
                copied = add(ls, v - 30, v, 1.0, [0.5, 7.0, 0.0]);
            }
            if started && !wrapped {
                // An old edge's wrap moves while the renewal is built (as a re-screen moves a
                // chord's): its heading only, its position measurement as each factor has it.
                for l in [&mut on_builder, &mut on_step, &mut never] {
                    let [h, px, py] = l.y(5);
                    l.set_y(5, [h + 0.3, px, py]);
                }
                wrapped = true;
            }
            let on_builder_event = on_builder
                .after_step(|| (!started).then(|| Box::new(job(copied.clone())) as Relinearise<3>));
            if on_builder_event == Some(RenewalEvent::Started) {
                started = true;
                let theta = on_step.all(0);
                let rewrite = job(copied);
                on_step.relinearise(|y| rewrite(y, &theta), 1);
            }
            assert_eq!(on_step.after_step(|| None), on_builder_event, "at node {v}");
            never.after_step(|| None);
            assert!(v < 10_000, "no renewal collected");
        }
        assert!(on_step.renewals == 1 && never.renewals == 1);
        let close = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9);
        for q in 0..3 {
            assert!(close(&on_builder.all(q), &on_step.all(q)), "column {q}");
        }
        assert!(
            !close(&on_builder.all(1), &never.all(1)),
            "the re-linearisation moved nothing"
        );
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
                l.after_step(|| None);
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
                l.rows.ends.chunk_addresses(),
                l.rows.sqrt_w.chunk_addresses(),
                l.prior.chunk_addresses(),
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
            l.after_step(|| None);
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
            dissected.after_step(|| None);
            plain.after_step(|| None);
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
}
