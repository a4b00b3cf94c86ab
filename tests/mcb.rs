//! Minimum cycle bases against an independent brute force, integrality and wraps of general
//! bases, and the approximation bound.
//!
//! The brute force is written only here: it enumerates every simple cycle of a small
//! multigraph (as an edge bitmask), sorts them by weight and keeps each one independent over
//! GF(2) of those kept (matroid greedy) — an MCB by definition.

use proptest::prelude::*;
use so2lin::cycles::approx::approximate_minimum_cycle_basis;
use so2lin::cycles::mcb::minimum_cycle_basis;
use so2lin::cycles::{BasisKind, Cycle, CycleBasis, SignedEdge};
use so2lin::wraps::{WrapError, WrapSolver, gamma_of};

/// A small multigraph: `n` nodes, edges `(a, b)` with `a ≠ b`, positive weights.
#[derive(Clone, Debug)]
struct Graph {
    n: usize,
    ends: Vec<(usize, usize)>,
    w: Vec<f64>,
}

/// Every simple cycle as `(weight, edge mask)`: DFS from each start node s through nodes
/// larger than s only, closing back at s; each cycle is found in both directions and kept once.
fn simple_cycles(g: &Graph) -> Vec<(f64, u64)> {
    let mut adj = vec![Vec::new(); g.n];
    for (e, &(a, b)) in g.ends.iter().enumerate() {
        adj[a].push((b, e));
        adj[b].push((a, e));
    }
    let mut found = std::collections::BTreeSet::new();
    fn dfs(
        adj: &[Vec<(usize, usize)>],
        s: usize,
        v: usize,
        on_path: &mut Vec<bool>,
        mask: u64,
        last: Option<usize>,
        found: &mut std::collections::BTreeSet<u64>,
    ) {
        for &(x, e) in &adj[v] {
            if Some(e) == last {
                continue;
            }
            if x == s {
                found.insert(mask | 1 << e);
            } else if x > s && !on_path[x] {
                on_path[x] = true;
                dfs(adj, s, x, on_path, mask | 1 << e, Some(e), found);
                on_path[x] = false;
            }
        }
    }
    let mut on_path = vec![false; g.n];
    for s in 0..g.n {
        on_path[s] = true;
        dfs(&adj, s, s, &mut on_path, 0, None, &mut found);
        on_path[s] = false;
    }
    found
        .into_iter()
        .map(|m| {
            let w = (0..g.ends.len())
                .filter(|e| m >> e & 1 == 1)
                .map(|e| g.w[e])
                .sum();
            (w, m)
        })
        .collect()
}

/// GF(2) elimination basis over u64 masks: inserts if independent.
#[derive(Default)]
struct Gf2 {
    rows: Vec<u64>,
}
impl Gf2 {
    fn insert(&mut self, mut x: u64) -> bool {
        for &r in &self.rows {
            x = x.min(x ^ r);
        }
        if x == 0 {
            return false;
        }
        self.rows.push(x);
        self.rows.sort_unstable_by(|a, b| b.cmp(a));
        true
    }
}

/// Brute-force MCB weight and the cycle-space dimension.
fn brute_force(g: &Graph) -> (f64, usize) {
    let mut cycles = simple_cycles(g);
    cycles.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut basis = Gf2::default();
    let mut weight = 0.0;
    for (w, m) in cycles {
        if basis.insert(m) {
            weight += w;
        }
    }
    (weight, basis.rows.len())
}

fn mask(c: &Cycle) -> u64 {
    c.terms.iter().fold(0, |m, t| m ^ 1 << t.edge)
}

fn components(g: &Graph) -> usize {
    let mut uf = so2lin::graph::UnionFind::new(g.n);
    g.ends.iter().filter(|&&(a, b)| uf.union(a, b)).count();
    (0..g.n).filter(|&v| uf.find(v) == v).count()
}

/// Closed, simple as a set, rank ℓ over GF(2), ℓ = m − n + c.
fn assert_basis(g: &Graph, cycles: &[Cycle]) {
    let l = g.ends.len() + components(g) - g.n;
    assert_eq!(cycles.len(), l, "{g:?}");
    let mut gf2 = Gf2::default();
    for c in cycles {
        assert!(c.is_closed(&g.ends), "not closed: {c:?} in {g:?}");
        assert_eq!(mask(c).count_ones() as usize, c.len(), "edge repeated");
        assert!(gf2.insert(mask(c)), "dependent: {g:?}");
    }
}

fn weight(g: &Graph, cycles: &[Cycle]) -> f64 {
    cycles.iter().map(|c| c.weight(&g.w)).sum()
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-9 * a.abs().max(b.abs()).max(1.0)
}

/// The whole check on one graph: exact MCB = brute force; approximations within (2k−1);
/// integrality and wraps of both.
fn check(g: &Graph) {
    let (want, rank) = brute_force(g);
    let got = minimum_cycle_basis(g.n, &g.ends, &g.w, None).unwrap();
    assert_basis(g, &got);
    assert_eq!(got.len(), rank);
    assert!(
        close(weight(g, &got), want),
        "MCB weight {} vs brute force {want} on {g:?}",
        weight(g, &got)
    );
    for k in 1..=3u32 {
        let a = approximate_minimum_cycle_basis(g.n, &g.ends, &g.w, k, None).unwrap();
        assert_basis(g, &a);
        let bound = f64::from(2 * k - 1) * want;
        assert!(
            weight(g, &a) <= bound + 1e-9 * bound.max(1.0),
            "k = {k}: {g:?}"
        );
    }
    check_wraps(g, &got);
}

/// Wraps from the basis (as computed, and as arranged by `CycleBasis::ordered`) satisfy
/// `C k = γ` for γ of random integer k, whenever the basis is integral.
fn check_wraps(g: &Graph, cycles: &[Cycle]) {
    let m = g.ends.len();
    let ordered = CycleBasis::ordered(BasisKind::Mcb, cycles.to_vec(), m);
    for basis in [cycles, ordered.cycles.as_slice()] {
        let solver = WrapSolver::new(basis, m).unwrap();
        assert_eq!(solver.abs_det(), dense_abs_det(g, basis), "{g:?}");
        let truth: Vec<i64> = (0..m as i64).map(|e| (e * 7 + 3) % 5 - 2).collect();
        let gamma = gamma_of(basis, &truth);
        if solver.is_integral() {
            let k = solver.wraps(basis, &gamma).unwrap();
            assert_eq!(gamma_of(basis, &k), gamma);
        }
    }
    let solver = WrapSolver::new(&ordered.cycles, m).unwrap();
    assert!(solver.is_triangular() || solver.core_len() > 0);
}

/// `|det C_L|` for the chords of a BFS spanning forest, by dense fraction-free (Bareiss)
/// elimination in i128 — independent of the crate's sparse peel-and-eliminate code.
fn dense_abs_det(g: &Graph, cycles: &[Cycle]) -> u128 {
    let mut uf = so2lin::graph::UnionFind::new(g.n);
    let chords: Vec<usize> = (0..g.ends.len())
        .filter(|&e| !uf.union(g.ends[e].0, g.ends[e].1))
        .collect();
    let l = chords.len();
    let mut a = vec![vec![0i128; l]; l];
    for (r, c) in cycles.iter().enumerate() {
        for t in &c.terms {
            if let Some(j) = chords.iter().position(|&e| e == t.edge as usize) {
                a[r][j] += i128::from(t.sign);
            }
        }
    }
    let mut prev = 1i128;
    let mut sign = 1i128;
    for k in 0..l {
        if a[k][k] == 0 {
            let Some(p) = (k + 1..l).find(|&p| a[p][k] != 0) else {
                return 0;
            };
            a.swap(k, p);
            sign = -sign;
        }
        for i in k + 1..l {
            for j in k + 1..l {
                a[i][j] = (a[i][j] * a[k][k] - a[i][k] * a[k][j]) / prev;
            }
        }
        prev = a[k][k];
    }
    if l == 0 {
        1
    } else {
        (sign * a[l - 1][l - 1]).unsigned_abs()
    }
}

/// A connected multigraph: a random tree, then extra edges (parallel ones allowed).
fn graphs() -> impl Strategy<Value = Graph> {
    (2usize..=10)
        .prop_flat_map(|n| {
            let tree = proptest::collection::vec(0usize..1000, n - 1);
            let extra = proptest::collection::vec((0usize..n, 1usize..n), 0..=(2 * n).min(12));
            let tied = any::<bool>();
            (Just(n), tree, extra, tied)
        })
        .prop_flat_map(|(n, tree, extra, tied)| {
            let mut ends: Vec<(usize, usize)> = tree
                .iter()
                .enumerate()
                .map(|(i, &r)| (r % (i + 1), i + 1))
                .collect();
            ends.extend(extra.iter().map(|&(a, d)| (a, (a + d) % n)));
            let m = ends.len();
            // Small integer weights make many ties (non-unique shortest paths); real ones not.
            let w = if tied {
                proptest::collection::vec((1u32..=3).prop_map(f64::from), m).boxed()
            } else {
                proptest::collection::vec(0.01f64..10.0, m).boxed()
            };
            (Just(n), Just(ends), w)
        })
        .prop_map(|(n, ends, w)| Graph { n, ends, w })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(1500))]
    #[test]
    fn random_multigraphs_match_brute_force(g in graphs()) {
        check(&g);
    }
}

fn unit(n: usize, ends: Vec<(usize, usize)>) -> Graph {
    let w = vec![1.0; ends.len()];
    Graph { n, ends, w }
}

/// Deterministic varied weights (a fixed LCG), so exhaustive families also see no ties.
fn varied(mut g: Graph, seed: u64) -> Graph {
    let mut s = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    for w in &mut g.w {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        *w = 0.1 + (s >> 40) as f64 / (1u64 << 24) as f64;
    }
    g
}

#[test]
fn every_connected_graph_on_up_to_five_nodes() {
    let mut checked = 0;
    for n in 2..=5usize {
        let pairs: Vec<(usize, usize)> = (0..n)
            .flat_map(|a| (a + 1..n).map(move |b| (a, b)))
            .collect();
        for bits in 0u32..1 << pairs.len() {
            let ends: Vec<(usize, usize)> = pairs
                .iter()
                .enumerate()
                .filter(|(i, _)| bits >> i & 1 == 1)
                .map(|(_, &p)| p)
                .collect();
            let g = unit(n, ends);
            if components(&g) != 1 {
                continue;
            }
            check(&g);
            check(&varied(g, u64::from(bits)));
            checked += 1;
        }
    }
    // Connected labelled graphs on 2..=5 nodes: 1 + 4 + 38 + 728.
    assert_eq!(checked, 771);
}

#[test]
fn named_families() {
    let complete = |n: usize| {
        let ends = (0..n)
            .flat_map(|a| (a + 1..n).map(move |b| (a, b)))
            .collect();
        unit(n, ends)
    };
    let wheel = |n: usize| {
        let mut ends: Vec<(usize, usize)> = (1..n).map(|i| (0, i)).collect();
        ends.extend((1..n).map(|i| (i, if i + 1 < n { i + 1 } else { 1 })));
        unit(n, ends)
    };
    let grid = |r: usize, c: usize| {
        let mut ends = Vec::new();
        for i in 0..r {
            for j in 0..c {
                let v = i * c + j;
                if j + 1 < c {
                    ends.push((v, v + 1));
                }
                if i + 1 < r {
                    ends.push((v, v + c));
                }
            }
        }
        unit(r * c, ends)
    };
    // Two nodes joined by j parallel edges; a triangle with every edge doubled.
    let bundle = |j: usize| unit(2, vec![(0, 1); j]);
    let doubled = unit(3, vec![(0, 1), (1, 0), (1, 2), (2, 1), (2, 0), (0, 2)]);
    let petersen = {
        let mut ends: Vec<(usize, usize)> = (0..5).map(|i| (i, (i + 1) % 5)).collect();
        ends.extend((0..5).map(|i| (i, i + 5)));
        ends.extend((0..5).map(|i| (i + 5, (i + 2) % 5 + 5)));
        unit(10, ends)
    };
    let k33 = unit(
        6,
        (0..3).flat_map(|a| (3..6).map(move |b| (a, b))).collect(),
    );
    let mut all = vec![doubled, petersen, k33, grid(3, 3), grid(2, 5)];
    all.extend((3..=7).map(complete));
    all.extend((4..=9).map(wheel));
    all.extend((2..=6).map(bundle));
    for (i, g) in all.into_iter().enumerate() {
        check(&g);
        check(&varied(g, i as u64));
    }
}

/// K4 with its three Hamiltonian cycles: independent over Q, `|det C_L| = 2` — not integral.
#[test]
fn hand_made_non_integral_basis() {
    // a=01 b=02 c=03 d=12 e=13 f=23
    let g = unit(4, vec![(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]);
    let s = |e: usize, along: bool| SignedEdge::new(e, along);
    let cycles: Vec<Cycle> = [
        vec![s(0, true), s(3, true), s(5, true), s(2, false)], // 0→1→2→3→0
        vec![s(0, true), s(4, true), s(5, false), s(1, false)], // 0→1→3→2→0
        vec![s(1, true), s(3, false), s(4, true), s(2, false)], // 0→2→1→3→0
    ]
    .into_iter()
    .map(|t| Cycle {
        terms: t.into_iter().collect(),
    })
    .collect();
    for c in &cycles {
        assert!(c.is_closed(&g.ends));
    }
    let solver = WrapSolver::new(&cycles, 6).unwrap();
    assert_eq!(solver.abs_det(), 2);
    assert_eq!(dense_abs_det(&g, &cycles), 2);
    assert!(!solver.is_integral());
    // γ from an integer k is solvable …
    let k = [1, 0, -2, 3, 0, 1];
    let gamma = gamma_of(&cycles, &k);
    let got = solver.wraps(&cycles, &gamma).unwrap();
    assert_eq!(gamma_of(&cycles, &got), gamma);
    // … but γ = (1, 0, 0) is not: the three rows sum to 2·(a + …), an even vector.
    assert!(matches!(
        solver.wraps(&cycles, &[1, 0, 0]),
        Err(WrapError::Fractional { .. })
    ));
}

/// Random GF(2) bases of simple cycles of K5: the sparse exact
/// determinant equals the dense Bareiss one, and integral ones give integer wraps.
#[test]
fn determinants_of_random_bases_match_dense_elimination() {
    let k5 = unit(
        5,
        (0..5)
            .flat_map(|a| (a + 1..5).map(move |b| (a, b)))
            .collect(),
    );
    let mut seen_non_integral = 0;
    for g in [k5] {
        let m = g.ends.len();
        let all = simple_cycles(&g);
        let l = m + 1 - g.n;
        let mut s = 12345u64;
        let mut next = |k: usize| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 33) as usize % k
        };
        for _ in 0..400 {
            let mut gf2 = Gf2::default();
            let mut chosen = Vec::new();
            while chosen.len() < l {
                let (_, mk) = all[next(all.len())];
                if gf2.insert(mk) {
                    chosen.push(mk);
                }
            }
            let cycles: Vec<Cycle> = chosen.iter().map(|&mk| cycle_of(&g, mk)).collect();
            let solver = WrapSolver::new(&cycles, m).unwrap();
            assert_eq!(solver.abs_det(), dense_abs_det(&g, &cycles));
            assert_eq!(
                solver.abs_det() % 2,
                1,
                "a GF(2) basis has an odd determinant"
            );
            if solver.is_integral() {
                let truth: Vec<i64> = (0..m as i64).map(|e| e % 3 - 1).collect();
                let gamma = gamma_of(&cycles, &truth);
                let k = solver.wraps(&cycles, &gamma).unwrap();
                assert_eq!(gamma_of(&cycles, &k), gamma);
            } else {
                seen_non_integral += 1;
            }
        }
    }
    assert!(seen_non_integral > 0, "K5 has non-integral cycle bases");
}

/// The simple cycle with edge mask `mk`, as a closed walk.
fn cycle_of(g: &Graph, mk: u64) -> Cycle {
    let edges: Vec<usize> = (0..g.ends.len()).filter(|e| mk >> e & 1 == 1).collect();
    let mut terms = smallvec::SmallVec::new();
    let mut used = vec![false; edges.len()];
    let (mut node, first) = (g.ends[edges[0]].1, edges[0]);
    used[0] = true;
    terms.push(SignedEdge::new(first, true));
    while terms.len() < edges.len() {
        let Some(i) = (0..edges.len())
            .find(|&i| !used[i] && (g.ends[edges[i]].0 == node || g.ends[edges[i]].1 == node))
        else {
            break;
        };
        used[i] = true;
        let (a, b) = g.ends[edges[i]];
        terms.push(SignedEdge::new(edges[i], a == node));
        node = if a == node { b } else { a };
    }
    Cycle { terms }
}

#[test]
fn invalid_input_is_a_typed_error() {
    use so2lin::cycles::McbError;
    assert!(matches!(
        minimum_cycle_basis(2, &[(0, 1), (1, 0)], &[1.0, 0.0], None),
        Err(McbError::Weight { edge: 1, .. })
    ));
    assert!(matches!(
        minimum_cycle_basis(2, &[(0, 0)], &[1.0], None),
        Err(McbError::SelfLoop { edge: 0 })
    ));
    assert!(matches!(
        minimum_cycle_basis(2, &[(0, 2)], &[1.0], None),
        Err(McbError::Node { edge: 0, nodes: 2 })
    ));
    assert!(matches!(
        approximate_minimum_cycle_basis(2, &[(0, 1), (1, 0)], &[1.0, 1.0], 0, None),
        Err(McbError::Stretch { k: 0 })
    ));
    assert!(matches!(
        minimum_cycle_basis(2, &[(0, 1), (1, 0)], &[1.0], None),
        Err(McbError::Length {
            ends: 2,
            weights: 1
        })
    ));
    // A deadline already passed stops the search.
    let g = varied(
        unit(
            7,
            (0..7)
                .flat_map(|a| (a + 1..7).map(move |b| (a, b)))
                .collect(),
        ),
        3,
    );
    let past = std::time::Instant::now() - std::time::Duration::from_millis(1);
    assert!(matches!(
        minimum_cycle_basis(g.n, &g.ends, &g.w, Some(past)),
        Err(McbError::Deadline)
    ));
}

#[test]
fn output_is_deterministic() {
    let g = varied(
        unit(
            7,
            (0..7)
                .flat_map(|a| (a + 1..7).map(move |b| (a, b)))
                .collect(),
        ),
        9,
    );
    let a = minimum_cycle_basis(g.n, &g.ends, &g.w, None).unwrap();
    let b = minimum_cycle_basis(g.n, &g.ends, &g.w, None).unwrap();
    assert_eq!(a, b);
}
