//! The estimate does not depend on node labels, on 2π added to a measurement, or on the
//! direction an edge is written in (swap its ends, invert its measurement); the full poses
//! (positions and refinement) do not depend on labels or on 2π added to measurements.

use proptest::prelude::*;
use so2lin::batch::{BatchConfig, screen, solve};
use so2lin::cycles::BasisKind;
use so2lin::estimate::OrientationEstimator;
use so2lin::graph::{Edge, NodePolicy, Pose2, PoseGraph};
use so2lin::sim::{SimConfig, simulate, wrap_angle};

mod common;

fn best_orientations(g: &PoseGraph, basis: BasisKind) -> Vec<f64> {
    let cfg = BatchConfig {
        basis,
        ..Default::default()
    };
    let r = screen(g, &cfg).unwrap();
    let k = r.wraps(&r.hypotheses[0]).unwrap();
    OrientationEstimator::new(g).unwrap().orientations(&k)
}

/// Rebuild a graph edge by edge, with nodes added in the same order.
fn rebuild(
    g: &PoseGraph,
    relabel: impl Fn(u64) -> u64,
    edit: impl Fn(usize, &Edge) -> Edge,
) -> PoseGraph {
    let mut out = PoseGraph::new();
    for node in g.nodes() {
        out.add_node(relabel(node.id), node.initial).unwrap();
    }
    for (k, e) in g.edges().iter().enumerate() {
        let e = edit(k, e);
        let e = Edge::new(
            relabel(e.from()),
            relabel(e.to()),
            e.measurement(),
            e.information(),
        )
        .unwrap();
        out.add_edge(e, NodePolicy::RequireKnown).unwrap();
    }
    out
}

/// Refined poses of the best hypothesis (incremental basis, 5 iterations).
fn best_poses(g: &PoseGraph) -> Vec<Pose2> {
    let r = screen(g, &BatchConfig::default()).unwrap();
    let orient = OrientationEstimator::new(g).unwrap();
    solve(g, &r, &orient, &r.hypotheses[0], &Default::default())
        .unwrap()
        .refined
        .poses
}

fn assert_same_wrapped(a: &[f64], b: &[f64]) -> Result<(), TestCaseError> {
    prop_assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        prop_assert!(wrap_angle(x - y).abs() < 1e-8, "{} vs {}", x, y);
    }
    Ok(())
}

fn world(poses: usize, seed: u64, sigma: f64) -> PoseGraph {
    let mut c = SimConfig::new(poses, seed);
    c.sigma_theta = sigma;
    simulate(&c).unwrap().graph
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn relabelling_nodes(poses in 20usize..150, seed in any::<u64>(), sigma in 0.01f64..0.15,
                         mult in 1u64..1_000_000, offset in 0u64..1u64 << 40) {
        let g = world(poses, seed, sigma);
        let relabelled = rebuild(&g, |id| id * (2 * mult + 1) + offset, |_, e| *e);
        for basis in [BasisKind::Incremental, BasisKind::Mst] {
            assert_same_wrapped(&best_orientations(&g, basis), &best_orientations(&relabelled, basis))?;
        }
    }

    #[test]
    fn adding_two_pi_to_measurements(poses in 20usize..150, seed in any::<u64>(), sigma in 0.01f64..0.15,
                                     pick in any::<prop::sample::Index>(), turns in -3i32..=3) {
        let g = world(poses, seed, sigma);
        let target = pick.index(g.edge_count());
        let shifted = rebuild(&g, |id| id, |k, e| if k == target { common::turned(e, turns) } else { *e });
        for basis in [BasisKind::Incremental, BasisKind::Odometric] {
            assert_same_wrapped(&best_orientations(&g, basis), &best_orientations(&shifted, basis))?;
        }
    }

    #[test]
    fn reversing_an_edge(poses in 20usize..150, seed in any::<u64>(), sigma in 0.01f64..0.15,
                         pick in any::<prop::sample::Index>()) {
        let g = world(poses, seed, sigma);
        let target = pick.index(g.edge_count());
        let reversed = rebuild(&g, |id| id, |k, e| if k == target { common::reversed(e) } else { *e });
        for basis in [BasisKind::Incremental, BasisKind::Mst, BasisKind::Odometric] {
            assert_same_wrapped(&best_orientations(&g, basis), &best_orientations(&reversed, basis))?;
        }
    }

    #[test]
    fn poses_do_not_depend_on_labels_or_turns(poses in 20usize..150, seed in any::<u64>(),
                                              sigma in 0.01f64..0.15, mult in 1u64..1_000,
                                              pick in any::<prop::sample::Index>(), turns in -3i32..=3) {
        let g = world(poses, seed, sigma);
        let target = pick.index(g.edge_count());
        let edited = rebuild(&g, |id| id * (2 * mult + 1) + 7, |k, e| if k == target { common::turned(e, turns) } else { *e });
        let (a, b) = (best_poses(&g), best_poses(&edited));
        prop_assert_eq!(a.len(), b.len());
        for (p, q) in a.iter().zip(&b) {
            prop_assert!((p.x - q.x).abs() < 1e-7 && (p.y - q.y).abs() < 1e-7, "{:?} vs {:?}", p, q);
            prop_assert!(wrap_angle(p.theta - q.theta).abs() < 1e-8);
        }
    }
}
