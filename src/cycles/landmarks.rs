//! Landmark lower bounds for the incremental basis's shortest-path queries (A* with landmarks
//! and the triangle inequality, "ALT": Goldberg & Harrelson, 2005).
//!
//! For a landmark `l` and the least-σ² distances `d_l(·)` from it, the triangle inequality gives
//! for any nodes v, t
//!
//! ```text
//! d(v, t) ≥ h_t(v) = max_l |d_l(t) − d_l(v)|,
//! ```
//!
//! a lower bound on the distance still to go, and a consistent one
//! (`h_t(u) ≤ w(u, v) + h_t(v)` for every edge, since `|d_l(u) − d_l(v)| ≤ w(u, v)`). A search
//! from s to t that settles nodes by `g(v) + h_t(v)` instead of `g(v)` (A*) settles each node
//! once at its least distance, and only the nodes with `g + h_t` below `d(s, t)`: the ones
//! roughly between s and t instead of a ball around s. A loop closure between two far places
//! (a false one, or a large loop) then costs a corridor of the map rather than half of it.
//!
//! The distances are kept **exact** as the graph grows (the bound is only valid for distances
//! of the graph queried or of a supergraph of it): an edge (a, b, w) whose `d_l(a) + w` is
//! below `d_l(b)` lowers `d_l(b)`, and the decrease spreads by a Dijkstra search limited to the
//! nodes it lowers (a new node: one step; a loop closure: the region it shortens). A query
//! that avoids an edge searches a subgraph, whose distances are at least these: the bound
//! still holds. The graph never loses an edge (an eviction rebuilds the estimator from
//! scratch). Landmarks are kept only once the owner wants them ([`Landmarks::want`]: the
//! incremental basis does when its searches often cross the map), and then as the graph
//! grows — the first at [`FIRST_LANDMARK_AT`] nodes, one more at each doubling, up to
//! [`MAX_LANDMARKS`] (when they are wanted late, the ones the graph's size calls for at the
//! edges that follow, one per edge) — each the node farthest from the landmarks so far (from
//! the newest node for the first), which puts them on the map's periphery; a new one costs one
//! search of the whole graph.
//!
//! Measured before writing this (a Python prototype on M3500 streamed in robot order, a search
//! from the newest node to a random older one at a fifth of the arrivals, five landmarks):
//! 4.3× fewer settled nodes, for 117 000 node updates to keep the distances, a tenth of what
//! the searches saved.

use std::cmp::Reverse;
use std::collections::BinaryHeap;

use super::dijkstra::{Adjacency, Dijkstra};

/// Most landmarks (the bound costs one lookup each per node reached; a node's distances fill
/// one cache line).
pub(crate) const MAX_LANDMARKS: usize = 8;

/// Nodes before the first landmark (below, a search is cheap anyway).
pub(crate) const FIRST_LANDMARK_AT: usize = 256;

/// Landmarks are wanted once at least this many searches have grown past their plain start
/// (see [`Landmarks::note_far_search`]), and at least one per [`FAR_SEARCH_NODES`] nodes of
/// the graph: their upkeep costs every edge, and only a stream whose searches often cross the
/// map repays it. Measured (2026-12-03, `so2lin stream FILE --json`, robot order): M3500 + 1000
/// false edges reach it at 920–1 080 nodes, the simulated worlds of 10 000 and 40 000 poses at
/// 4 000 and 16 800, w20000 at 6 700; city10000, M3500, intel and ais2klinik never (city10000
/// had its 64th such search at 4 520 nodes; with landmarks kept from there its stream took 9 %
/// longer).
const FAR_SEARCHES_FOR_LANDMARKS: usize = 64;

/// See [`FAR_SEARCHES_FOR_LANDMARKS`].
const FAR_SEARCH_NODES: usize = 32;

/// Exact least-σ² distances from a few landmarks, kept as the graph grows (module docs).
#[derive(Clone, Debug, Default)]
pub(crate) struct Landmarks {
    /// `dist[v * MAX_LANDMARKS + l]`: distance from landmark l to node v (∞: not reached);
    /// empty until landmarks are wanted.
    dist: Vec<f64>,
    /// Landmarks in use.
    count: usize,
    /// Nodes with an edge (the graph's size for the schedule: a caller may reserve every node
    /// ahead, as the batch replay of a file does).
    nodes: usize,
    /// Node count at which the next landmark is added.
    next_at: usize,
    /// Landmarks are kept ([`Self::want`]).
    wanted: bool,
    /// Searches that grew past their plain start while no landmark was wanted.
    far_searches: usize,
    /// Scratch of the decrease searches.
    heap: BinaryHeap<Reverse<(u64, u32)>>,
    /// The target's distances from the landmarks the query in progress uses (those reaching
    /// its source and target); NaN for the others, which [`Self::bound`] then skips without a
    /// branch.
    target: [f64; MAX_LANDMARKS],
}

impl Landmarks {
    /// Number of landmarks in use.
    pub fn count(&self) -> usize {
        self.count
    }

    /// Make room for nodes `0..n` (not reached from any landmark yet), once landmarks are
    /// wanted (no memory before: most streams never want them).
    pub fn reserve_nodes(&mut self, n: usize) {
        if self.wanted && self.dist.len() < n * MAX_LANDMARKS {
            self.dist.resize(n * MAX_LANDMARKS, f64::INFINITY);
        }
    }

    /// Room for `additional` more nodes' distances without growing (address space only until
    /// landmarks are wanted).
    pub fn try_reserve(
        &mut self,
        additional: usize,
    ) -> Result<(), std::collections::TryReserveError> {
        self.dist
            .try_reserve(additional.saturating_mul(MAX_LANDMARKS))?;
        Ok(())
    }

    fn row(&self, v: usize) -> &[f64] {
        &self.dist[v * MAX_LANDMARKS..v * MAX_LANDMARKS + self.count]
    }

    /// Edge a — b of weight `w` was added to `adj`: lower the distances it shortens, then add
    /// a landmark if the graph has grown to the next size (`n` nodes; `search` is scratch for
    /// its search of the whole graph).
    pub fn edge_added(
        &mut self,
        adj: &Adjacency,
        w: &[f64],
        (a, b, wab): (usize, usize, f64),
        search: &mut Dijkstra,
    ) {
        // A new node (this edge its only one): its distances, and nothing else moves.
        let leaf = [(b, a), (a, b)]
            .into_iter()
            .find(|&(v, _)| adj[v].len() == 1 && adj[v][0].0 as usize != v);
        self.nodes += usize::from(adj[a].len() == 1) + usize::from(adj[b].len() == 1);
        for l in 0..self.count {
            let (da, db) = (
                self.dist[a * MAX_LANDMARKS + l],
                self.dist[b * MAX_LANDMARKS + l],
            );
            if let Some((v, u)) = leaf {
                let du = self.dist[u * MAX_LANDMARKS + l];
                let dv = &mut self.dist[v * MAX_LANDMARKS + l];
                *dv = dv.min(du + wab);
            } else if da + wab < db {
                self.lower(adj, w, l, b, da + wab);
            } else if db + wab < da {
                self.lower(adj, w, l, a, db + wab);
            }
        }
        let n = self.nodes;
        if !self.wanted {
            return;
        }
        if self.next_at == 0 {
            self.next_at = FIRST_LANDMARK_AT;
        }
        // One at a time: the schedule's next size reached adds one landmark at this edge; a
        // graph that wanted them late, and so is past several sizes, gets the others at the
        // edges that follow, one each (each costs a search of the whole graph: added all at
        // once they made a 100 000-pose world's slowest step with `maintain`, 24 ms for
        // five).
        if n >= self.next_at && self.count < MAX_LANDMARKS {
            self.reserve_nodes(adj.len());
            self.next_at = self.next_at.saturating_mul(2);
            self.add_landmark(adj, w, b, search);
        }
    }

    /// From the next edge on, keep landmarks (none are kept until they are wanted: their
    /// upkeep costs every edge, and a stream whose searches stay local never needs them).
    pub fn want(&mut self) {
        self.wanted = true;
    }

    /// A search grew past its plain start while no landmark is kept: count it, and want
    /// landmarks once such searches are frequent ([`FAR_SEARCHES_FOR_LANDMARKS`]).
    pub fn note_far_search(&mut self) {
        self.far_searches += 1;
        let far = self.far_searches;
        if far >= FAR_SEARCHES_FOR_LANDMARKS && far * FAR_SEARCH_NODES >= self.nodes {
            self.want();
        }
    }

    /// Lower landmark l's distance of node v to `d` and spread the decrease (a search that
    /// settles only the nodes whose distance drops).
    fn lower(&mut self, adj: &Adjacency, w: &[f64], l: usize, v: usize, d: f64) {
        self.dist[v * MAX_LANDMARKS + l] = d;
        self.heap.clear();
        self.heap.push(Reverse((d.to_bits(), v as u32)));
        let mut settled = 0;
        while let Some(Reverse((bits, x))) = self.heap.pop() {
            let (dx, x) = (f64::from_bits(bits), x as usize);
            if dx > self.dist[x * MAX_LANDMARKS + l] {
                continue;
            }
            settled += 1;
            for &(y, e) in &adj[x] {
                let nd = dx + w[e as usize];
                let slot = &mut self.dist[y as usize * MAX_LANDMARKS + l];
                if nd < *slot {
                    *slot = nd;
                    self.heap.push(Reverse((nd.to_bits(), y)));
                }
            }
        }
        crate::work::searched(settled);
    }

    /// A new landmark: the node farthest from the landmarks so far (ties: the lowest index),
    /// or from `newest` for the first; its distances by one search of the whole graph.
    fn add_landmark(&mut self, adj: &Adjacency, w: &[f64], newest: usize, search: &mut Dijkstra) {
        let far = |search: &Dijkstra| {
            let mut best = (f64::NEG_INFINITY, newest);
            for &v in search.order() {
                let d = search.dist(v as usize);
                if d > best.0 {
                    best = (d, v as usize);
                }
            }
            best.1
        };
        let landmark = if self.count == 0 {
            search.run(adj, w, newest, None, f64::INFINITY);
            far(search)
        } else {
            let mut best = (f64::NEG_INFINITY, newest);
            for v in 0..adj.len() {
                let nearest = self.row(v).iter().copied().fold(f64::INFINITY, f64::min);
                if nearest.is_finite() && nearest > best.0 {
                    best = (nearest, v);
                }
            }
            best.1
        };
        search.run(adj, w, landmark, None, f64::INFINITY);
        let l = self.count;
        self.count += 1;
        for &v in search.order() {
            self.dist[v as usize * MAX_LANDMARKS + l] = search.dist(v as usize);
        }
    }

    /// Prepare the bound from `source` toward `target` ([`Self::bound`]): the landmarks that
    /// reach both, with the target's distances. (Only the two with the largest bound at the
    /// source was tried: slower, the bound weaker.)
    pub fn aim(&mut self, source: usize, target: usize) {
        self.target = [f64::NAN; MAX_LANDMARKS];
        for l in 0..self.count {
            let (ds, dt) = (
                self.dist[source * MAX_LANDMARKS + l],
                self.dist[target * MAX_LANDMARKS + l],
            );
            if ds.is_finite() && dt.is_finite() {
                self.target[l] = dt;
            }
        }
    }

    /// `h(v) = max_l |d_l(target) − d_l(v)|` over the active landmarks of the last
    /// [`Self::aim`] that reach v (0 when none does).
    pub fn bound(&self, v: usize) -> f64 {
        let start = v * MAX_LANDMARKS;
        let Some(row) = (self.dist.get(start..start + MAX_LANDMARKS))
            .and_then(|r| <&[f64; MAX_LANDMARKS]>::try_from(r).ok())
        else {
            return 0.0;
        };
        // Every landmark slot at once, unrolled (no branch on which are active: a NaN
        // difference never compares greater); the maximum is exact, so the order does not
        // matter.
        let mut h = 0.0f64;
        for (&dt, &dv) in self.target.iter().zip(row) {
            let d = (dt - dv).abs();
            h = if d > h { d } else { h };
        }
        if h.is_finite() {
            return h;
        }
        // An active landmark that does not reach v (never for a node connected to the
        // source, which the landmark reaches): skipped.
        let mut h = 0.0f64;
        for (&dt, &dv) in self.target.iter().zip(row) {
            if dv.is_finite() && !dt.is_nan() {
                h = h.max((dt - dv).abs());
            }
        }
        h
    }

    /// Landmark l's distance to v (tests).
    #[cfg(test)]
    pub fn distance(&self, l: usize, v: usize) -> f64 {
        self.dist[v * MAX_LANDMARKS + l]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cycles::SignedEdge;
    use smallvec::SmallVec;

    fn lcg(state: &mut u64) -> u64 {
        *state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        *state >> 33
    }

    /// The weight of `path` (signed edges, `ends` their end nodes), asserting that it walks
    /// from `s` to `t`.
    fn walked(path: &[SignedEdge], ends: &[(u32, u32)], w: &[f64], s: usize, t: usize) -> f64 {
        let (mut at, mut weight) = (s as u32, 0.0);
        for term in path {
            let (a, b) = ends[term.edge as usize];
            let (from, to) = if term.sign > 0 { (a, b) } else { (b, a) };
            assert_eq!(from, at);
            at = to;
            weight += w[term.edge as usize];
        }
        assert_eq!(at, t as u32);
        weight
    }

    /// A graph being grown: its adjacency, weights and landmarks, and the search scratch.
    #[derive(Default)]
    struct Growing {
        adj: Adjacency,
        w: Vec<f64>,
        lm: Landmarks,
        search: Dijkstra,
    }

    impl Growing {
        /// Add edge a — b of weight x (nodes created as needed); its id.
        fn add(&mut self, a: usize, b: usize, x: f64) -> u32 {
            if !self.lm.wanted {
                self.lm.want();
                self.lm.reserve_nodes(self.adj.len());
            }
            while self.adj.len() <= a.max(b) {
                self.adj.push(SmallVec::new());
            }
            self.lm.reserve_nodes(self.adj.len());
            let e = self.w.len() as u32;
            self.w.push(x);
            self.adj[a].push((b as u32, e));
            self.adj[b].push((a as u32, e));
            let Self { adj, w, lm, search } = self;
            lm.edge_added(adj, w, (a, b, x), search);
            e
        }
    }

    /// `check` run from landmark l of `g` (the node at distance 0) over the whole graph.
    fn search_from_landmark(g: &Growing, l: usize, check: &mut Dijkstra) {
        let src = (0..g.adj.len())
            .find(|&u| g.lm.distance(l, u) == 0.0)
            .expect("a landmark at distance 0");
        check.run(&g.adj, &g.w, src, None, f64::INFINITY);
    }

    /// A graph grown edge by edge — a chain with new nodes, loop closures of random weights
    /// (some far, some parallel), a second component joined later — keeps every landmark's
    /// distances equal to a search of the whole graph after every edge, and the bound below
    /// the least distance between random pairs.
    #[test]
    fn landmark_distances_stay_exact_as_the_graph_grows() {
        let mut state = 7;
        let mut g = Growing::default();
        let mut check = Dijkstra::default();
        let n = 1_400;
        for v in 1..n {
            // The second component (nodes from 900) starts on its own and is joined at 1 200.
            let from = if v == 900 { None } else { Some(v - 1) };
            if let Some(u) = from {
                let x = 0.5 + (lcg(&mut state) % 100) as f64 / 50.0;
                g.add(u, v, x);
            }
            if v == 1_200 {
                g.add(10, 950, 1.0);
            }
            let lo = if (900..1_200).contains(&v) { 900 } else { 0 };
            if v > lo + 20 && lcg(&mut state).is_multiple_of(3) {
                let u = lo + (lcg(&mut state) as usize) % (v - lo - 1);
                let x = 0.1 + (lcg(&mut state) % 100) as f64 / 20.0;
                g.add(u, v, x);
            }
            if v % 97 == 0 || v == n - 1 {
                assert!(g.lm.count() <= MAX_LANDMARKS);
                // The bound is the triangle inequality's over the landmarks that reach the
                // source and the target (while there are two components, some do not: they
                // count for nothing), skipping those that do not reach the node.
                for _ in 0..50 {
                    let mut node = || (lcg(&mut state) as usize) % g.adj.len();
                    let (s, t, u) = (node(), node(), node());
                    g.lm.aim(s, t);
                    let d = |l: usize, x: usize| g.lm.distance(l, x);
                    let reference = (0..g.lm.count())
                        .filter(|&l| d(l, s).is_finite() && d(l, t).is_finite())
                        .filter(|&l| d(l, u).is_finite())
                        .map(|l| (d(l, t) - d(l, u)).abs())
                        .fold(0.0, f64::max);
                    assert_eq!(
                        g.lm.bound(u),
                        reference,
                        "node count {v}: {s} -> {t} at {u}"
                    );
                }
                for l in 0..g.lm.count() {
                    search_from_landmark(&g, l, &mut check);
                    for u in 0..g.adj.len() {
                        let exact = if check.settled(u) {
                            check.dist(u)
                        } else {
                            f64::INFINITY
                        };
                        let kept = g.lm.distance(l, u);
                        assert!(
                            kept == exact || (kept - exact).abs() <= 1e-9 * exact,
                            "node count {v}, landmark {l}, node {u}: kept {kept}, exact {exact}"
                        );
                    }
                }
            }
        }
        assert!(g.lm.count() >= 3, "landmarks: {}", g.lm.count());
        for _ in 0..200 {
            let (s, t) = (
                (lcg(&mut state) as usize) % g.adj.len(),
                (lcg(&mut state) as usize) % g.adj.len(),
            );
            check.run(&g.adj, &g.w, t, Some(s), f64::INFINITY);
            let exact = if check.settled(s) {
                check.dist(s)
            } else {
                f64::INFINITY
            };
            g.lm.aim(s, t);
            assert!(
                g.lm.bound(s) <= exact + 1e-9,
                "bound {} above {exact}",
                g.lm.bound(s)
            );
        }
    }

    /// Landmarks wanted late — the graph already past three sizes of the schedule (256, 512
    /// and 1 024 nodes) — come one per edge at the edges that follow, not all at one edge
    /// (each costs a search of the whole graph), and each has its exact distances.
    #[test]
    fn landmarks_wanted_late_come_one_per_edge() {
        let mut g = Growing::default();
        let mut state = 11;
        // A chain of 1 100 nodes with loop closures, grown while no landmark is wanted.
        for v in 1..1_100usize {
            for (u, x) in [(v - 1, 1.0), ((lcg(&mut state) as usize) % v, 5.0)] {
                while g.adj.len() <= v {
                    g.adj.push(SmallVec::new());
                }
                let e = g.w.len() as u32;
                g.w.push(x);
                g.adj[u].push((v as u32, e));
                g.adj[v].push((u as u32, e));
                let Growing { adj, w, lm, search } = &mut g;
                lm.edge_added(adj, w, (u, v, x), search);
            }
        }
        assert_eq!(g.lm.count(), 0);
        let mut counts = Vec::new();
        for k in 0..4 {
            g.add(k, 1_099 - k, 2.0);
            counts.push(g.lm.count());
        }
        assert_eq!(counts, [1, 2, 3, 3]);
        let mut check = Dijkstra::default();
        for l in 0..g.lm.count() {
            search_from_landmark(&g, l, &mut check);
            for u in 0..g.adj.len() {
                assert_eq!(g.lm.distance(l, u), check.dist(u), "landmark {l}, node {u}");
            }
        }
    }

    /// A* with the landmark bound finds what Dijkstra finds: the same least distance to the
    /// target, within a radius exactly when Dijkstra does, by a path that walks from the source
    /// to the target with that weight; and it settles fewer nodes across a map. So does a
    /// search begun plain and aimed where it stopped (`resume_toward`).
    #[test]
    fn aimed_searches_find_the_least_weight_path() {
        let mut state = 11;
        let mut g = Growing::default();
        let mut ends = Vec::new();
        // A 40 × 40 grid of random weights (equal ones often: ties), grown row by row.
        let side = 40;
        for v in 0..side * side {
            let mut neighbours = Vec::new();
            if v % side > 0 {
                neighbours.push(v - 1);
            }
            if v >= side {
                neighbours.push(v - side);
            }
            for u in neighbours {
                let x = if lcg(&mut state).is_multiple_of(2) {
                    1.0
                } else {
                    0.5 + (lcg(&mut state) % 8) as f64 / 4.0
                };
                g.add(u, v, x);
                ends.push((u as u32, v as u32));
            }
        }
        let Growing { adj, w, mut lm, .. } = g;
        assert!(lm.count() >= 3);
        let (mut plain, mut aimed) = (Dijkstra::default(), Dijkstra::default());
        let mut resumed = Dijkstra::default();
        let (mut settled_plain, mut settled_aimed) = (0, 0);
        for q in 0..300 {
            let (s, t) = (
                (lcg(&mut state) as usize) % adj.len(),
                (lcg(&mut state) as usize) % adj.len(),
            );
            let radius = if q % 3 == 0 {
                (lcg(&mut state) % 60) as f64
            } else {
                f64::INFINITY
            };
            let one = plain.run(&adj, &w, s, Some(t), radius);
            lm.aim(s, t);
            // A* from the start.
            let two = aimed.run_settling(&adj, &w, (s, Some(t)), radius, 0) == Some(true)
                || aimed.resume_toward(&adj, &w, t, radius, |v| lm.bound(v));
            assert_eq!(one, two, "{s} -> {t} within {radius}");
            // Plain for the first few nodes, then aimed from where it stopped.
            let most = (lcg(&mut state) % 200) as usize;
            let three = match resumed.run_settling(&adj, &w, (s, Some(t)), radius, most) {
                Some(found) => found,
                None => resumed.resume_toward(&adj, &w, t, radius, |v| lm.bound(v)),
            };
            assert_eq!(
                one, three,
                "{s} -> {t} within {radius}, resumed after {most}"
            );
            if three && s != t {
                let exact = plain.dist(t);
                assert!((resumed.dist(t) - exact).abs() <= 1e-12 * exact);
                let mut path = SmallVec::new();
                resumed.path(&ends, s, t, &mut path);
                let weight = walked(&path, &ends, &w, s, t);
                assert!((weight - exact).abs() <= 1e-9 * exact);
            }
            settled_plain += plain.order().len();
            settled_aimed += aimed.order().len();
            if !two || s == t {
                continue;
            }
            let exact = plain.dist(t);
            assert!(
                (aimed.dist(t) - exact).abs() <= 1e-12 * exact,
                "{} vs {exact}",
                aimed.dist(t)
            );
            let mut path = SmallVec::new();
            aimed.path(&ends, s, t, &mut path);
            let weight = walked(&path, &ends, &w, s, t);
            assert!((weight - exact).abs() <= 1e-9 * exact);
        }
        assert!(
            2 * settled_aimed < settled_plain,
            "aimed {settled_aimed} against {settled_plain} settled"
        );
    }
}
