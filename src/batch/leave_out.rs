//! The leave-out test of the robust passes ([`super::robust`], stage 3): a false loop closure
//! the map bent to fit has a small residual but a large cost drop when left out,
//!
//! ```text
//! Δ_G = min F − min F_{without G}   (χ²_{3|G|} for genuine edges, linear-Gaussian model),
//! ```
//!
//! computed linearised for every loop closure alone and for every place group (loop closures
//! whose two ends are each within [`GROUP_SPAN`] node indices of another's, transitively) and
//! compared with `s · χ²_{3|G|}⁻¹(1 − α/(2N))` (N candidates; s the data's noise scale, bounded
//! by the quarantine's and by the drops' own 99th percentile, [`drop_scale`]). The largest drop
//! per edge left out is verified by refining without it.

use super::robust::reweighted;
use super::{RejectedEdge, SolveError};
use crate::graph::{Pose2, PoseGraph};
use crate::refine::RefineConfig;
use crate::screening::chi2_quantile;

/// Candidates verified by a refinement without them, per leave-out round ([`leave_out`]).
const LEAVE_OUT_TRIES: usize = 5;
/// Most groups rejected by leaving them out, per pass ([`leave_out`]).
const LEAVE_OUT_ROUNDS: usize = 8;
/// Loop closures whose ends are both within this many node indices of another's are in one
/// place group ([`place_groups`]).
pub(crate) const GROUP_SPAN: usize = 10;

/// The place of edge e: its two node indices, smaller first.
pub(crate) fn place(graph: &PoseGraph, e: usize) -> (usize, usize) {
    let (a, b) = graph.endpoints()[e];
    place_of(a, b)
}

/// The place of an edge between node indices a and b: smaller first.
pub(crate) fn place_of(a: usize, b: usize) -> (usize, usize) {
    (a.min(b), a.max(b))
}

/// Whether two places ([`place`]) are one: both ends within [`GROUP_SPAN`] node indices.
pub(crate) fn same_place((a, b): (usize, usize), (c, d): (usize, usize)) -> bool {
    a.abs_diff(c) <= GROUP_SPAN && b.abs_diff(d) <= GROUP_SPAN
}

/// Loop closures `lcs` (edge indices) grouped by place: `(a, b)` and `(a′, b′)` (node indices,
/// `a < b`) with `|a − a′| ≤ GROUP_SPAN` and `|b − b′| ≤ GROUP_SPAN` are in one group,
/// transitively (a run of loop closures of one revisit, or a group of false ones sharing a
/// measurement). Groups in order of their first edge, edges ascending.
fn place_groups(graph: &PoseGraph, lcs: &[usize]) -> Vec<Vec<usize>> {
    let ends: Vec<(usize, usize)> = lcs.iter().map(|&e| place(graph, e)).collect();
    let mut order: Vec<usize> = (0..lcs.len()).collect();
    order.sort_by_key(|&i| (ends[i], i));
    let mut parent: Vec<usize> = (0..lcs.len()).collect();
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    for (k, &i) in order.iter().enumerate() {
        for &j in order[..k].iter().rev() {
            if ends[j].0 + GROUP_SPAN < ends[i].0 {
                break;
            }
            if same_place(ends[j], ends[i]) {
                let (ri, rj) = (root(&mut parent, i), root(&mut parent, j));
                parent[ri.max(rj)] = ri.min(rj);
            }
        }
    }
    let mut groups: std::collections::BTreeMap<usize, Vec<usize>> = Default::default();
    for (i, &e) in lcs.iter().enumerate() {
        let r = root(&mut parent, i);
        groups.entry(r).or_default().push(e);
    }
    let mut out: Vec<Vec<usize>> = groups
        .into_values()
        .map(|mut g| {
            g.sort_unstable();
            g
        })
        .collect();
    out.sort_by_key(|g| g[0]);
    out
}

/// What [`leave_out`] returns: the poses without the rejected groups, the rejected edges,
/// and the scale the drops showed in its last round ([`drop_scale`]).
type LeftOut = (Vec<Pose2>, Vec<RejectedEdge>, Option<f64>);

/// Stage 3's leave-out test (module docs; stage 3 of [`super::robust`]), greedy: every loop closure of `graph` (weights `w`,
/// poses `x` at their minimum) and every place group of two or more is a candidate; its
/// linearised drop Δ_G ([`crate::refine::leave_out_drops`]) is compared with
/// `s · χ²_{3|G|}⁻¹(1 − α / (2N))` (N candidates, `s` the noise scale); the candidates beyond it,
/// most significant first, are verified by refining without them, and the first whose actual
/// drop exceeds the threshold is rejected. Repeated (at most [`LEAVE_OUT_ROUNDS`] groups) until
/// no candidate is verified. Returns the poses without the rejected groups and the rejected
/// edges with their group's drop.
pub(super) fn leave_out(
    graph: &PoseGraph,
    w: &[f64],
    mut x: Vec<Pose2>,
    inner: &RefineConfig,
    alpha: f64,
    scale: f64,
) -> Result<LeftOut, SolveError> {
    let edges = graph.edges();
    let mut w = w.to_vec();
    let mut rejected = Vec::new();
    let mut shown = None;
    // The graph of the edges of nonzero weight, and their indices in `graph`.
    let live = |w: &[f64]| -> Result<(PoseGraph, Vec<usize>), SolveError> {
        let alive = (0..edges.len()).filter(|&e| w[e] > 0.0).collect();
        Ok((reweighted(graph, w)?, alive))
    };
    let (mut g, mut alive) = live(&w)?;
    'rounds: for _ in 0..LEAVE_OUT_ROUNDS {
        let lcs: Vec<usize> = (0..alive.len())
            .filter(|&l| !edges[alive[l]].is_odometric())
            .collect();
        let places = place_groups(&g, &lcs);
        let drops = crate::refine::leave_out_drops(&g, &x, inner.residual, &places)?;
        // Candidates: every loop closure alone, and every place group of two or more.
        let mut groups: Vec<(Vec<usize>, f64)> = Vec::new();
        for (p, place) in places.iter().enumerate() {
            groups.extend(
                place
                    .iter()
                    .zip(&drops.edges[p])
                    .map(|(&l, &d)| (vec![l], d)),
            );
            if place.len() > 1 {
                groups.push((place.clone(), drops.groups[p]));
            }
        }
        let level = 1.0 - alpha / (2.0 * groups.len().max(1) as f64);
        shown = drop_scale(&drops.edges);
        let scale = scale.min(shown.unwrap_or(f64::INFINITY));
        let threshold = |g: &[usize]| scale * chi2_quantile(3.0 * g.len() as f64, level);
        // The largest drop per edge left out first: of a false edge and the genuine ones it
        // contradicts, leaving out either resolves the conflict, and the fewer edges explain it.
        let mut candidates: Vec<(f64, usize)> = groups
            .iter()
            .enumerate()
            .filter(|(_, (g, d))| *d > threshold(g))
            .map(|(i, (g, d))| (d / g.len() as f64, i))
            .collect();
        candidates.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        let with = inner.residual.cost(&g, &x);
        for &(_, i) in candidates.iter().take(LEAVE_OUT_TRIES) {
            let mut w_i = w.clone();
            let group = &groups[i].0;
            for &l in group {
                w_i[alive[l]] = 0.0;
            }
            let (g_i, alive_i) = live(&w_i)?;
            // Poses of g_i's nodes are x (nodes keep their order).
            let r = crate::refine::refine(&g_i, &x, inner)?;
            let drop = with - r.cost();
            if drop > threshold(group) {
                let t = threshold(group);
                rejected.extend(
                    group
                        .iter()
                        .map(|&l| RejectedEdge::of(graph, alive[l], "leave_out", drop, t)),
                );
                (w, g, alive, x) = (w_i, g_i, alive_i, r.poses);
                continue 'rounds;
            }
        }
        break;
    }
    rejected.sort_by_key(|r| r.edge);
    Ok((x, rejected, shown))
}

/// The noise scale the loop closures' own leave-out drops show, from above:
/// `ŝ = Δ_(k) / χ²_1⁻¹(0.99)`, `Δ_(k)` the k-th largest single-edge drop with
/// `k = ⌊N/100 − 2.58 √(N/100)⌋` (an upper 99.5 % confidence bound of their 99th percentile:
/// the number of N draws above it is Binomial(N, 0.01)); None when k < 1, i.e. with fewer
/// than 854 loop closures (their 99th percentile is not known well enough from above).
///
/// Why it bounds the scale: with the edges' whitened residual components' true variances
/// `λ_i` times the declared ones, a drop is `Δ_e = Σ_i λ_i z_i²` (z standard normal, at most
/// three components, which may be scaled differently: benchmark files declare their angle and
/// translation noise wrong by different factors), so `Δ_e ≥ λ_max z_max²` and
/// `Q_0.99(Δ) ≥ λ_max χ²_1⁻¹(0.99)`; a threshold `ŝ χ²_{3|G|}⁻¹(1 − α/2N)` with `ŝ ≥ λ_max` is
/// then passed by data that follow the (rescaled) model with probability ≥ 1 − α/2N per
/// candidate. An order statistic: each of fewer than k false edges still in the graph moves it
/// up by one place among the genuine drops, not by its size.
fn drop_scale(drops: &[Vec<f64>]) -> Option<f64> {
    let mut all: Vec<f64> = drops
        .iter()
        .flatten()
        .copied()
        .filter(|d| d.is_finite())
        .collect();
    let expected = all.len() as f64 / 100.0;
    let k = (expected - 2.58 * expected.sqrt()).floor();
    if k < 1.0 {
        return None;
    }
    let k = k as usize;
    let (_, q, _) = all.select_nth_unstable_by(k - 1, |a, b| b.total_cmp(a));
    (*q > 0.0).then(|| *q / crate::closure::Q99_1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::{Edge, Information};

    /// Place groups: loop closures whose two ends are each within GROUP_SPAN node indices of
    /// another's are grouped transitively, in order of first edge; others stay alone.
    #[test]
    fn place_groups_join_nearby_loop_closures() {
        let mut g = PoseGraph::new();
        let info = Information::diagonal(1.0, 1.0, 1.0);
        let z = Pose2::new(1.0, 0.0, 0.0);
        for i in 0..100u64 {
            g.add_edge(Edge::new(i, i + 1, z, info).unwrap(), Default::default())
                .unwrap();
        }
        let lc = [(0, 50), (5, 55), (12, 64), (30, 90), (80, 20)];
        for (a, b) in lc {
            g.add_edge(Edge::new(a, b, z, info).unwrap(), Default::default())
                .unwrap();
        }
        let lcs: Vec<usize> = (100..105).collect();
        // (0,50)–(5,55)–(12,64) chain (each step ≤ 10 in both ends); (80,20) is (20,80),
        // 10 from (30,90) in both ends.
        assert_eq!(
            place_groups(&g, &lcs),
            vec![vec![100, 101, 102], vec![103, 104]]
        );
        assert_eq!(place_groups(&g, &[100, 103]), vec![vec![100], vec![103]]);
    }

    /// Drops `λ_θ z₁² + λ_t (z₂² + z₃²)` of n loop closures (angle and translation scaled
    /// differently, as the benchmark files are), the simulator's deterministic normal draws.
    fn drops(n: usize, (la, lt): (f64, f64), noise: &mut crate::sim::Noise) -> Vec<Vec<f64>> {
        (0..n)
            .map(|_| {
                let (a, x, y) = (noise.normal(), noise.normal(), noise.normal());
                vec![la * a * a + lt * (x * x + y * y)]
            })
            .collect()
    }

    /// The drops' scale bounds the largest component's scale from above, sharply; a few
    /// false edges left in the graph do not move it; too few loop closures give none; and
    /// the threshold it sets lets clean data through at the family-wise level.
    #[test]
    fn the_drop_scale_bounds_the_noise_from_above() {
        let mut noise = crate::sim::Noise::seeded(7);
        let (la, lt) = (0.3, 0.02);
        let d = drops(2000, (la, lt), &mut noise);
        let s = drop_scale(&d).unwrap();
        assert!(s >= la && s <= 2.0 * la, "{s}");
        let mut dirty = d.clone();
        dirty.extend((0..5).map(|i| vec![100.0 + i as f64]));
        let t = drop_scale(&dirty).unwrap();
        assert!(t >= s && t <= 1.25 * s, "{s} {t}");
        assert_eq!(drop_scale(&d[..853]), None);
        assert!(drop_scale(&d[..854]).is_some());
        // 100 clean files of 2000 loop closures at α = 0.01: a file with any drop beyond the
        // threshold is a false alarm (expected at most α of them).
        let alpha = 0.01;
        let alarms = (0..100)
            .filter(|_| {
                let d = drops(2000, (la, lt), &mut noise);
                let limit = drop_scale(&d).unwrap() * chi2_quantile(3.0, 1.0 - alpha / 4000.0);
                d.iter().flatten().any(|&x| x > limit)
            })
            .count();
        println!("{alarms} of 100 clean files with a drop beyond the threshold");
        assert!(alarms <= 4, "{alarms} of 100");
    }
}
