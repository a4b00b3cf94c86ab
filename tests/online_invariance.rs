//! The online estimator's answer with false loop closures in the stream — which loop closures
//! it keeps in quarantine and the estimate of every node — does not depend on how the input is
//! written: node labels, 2π added to a measurement, or the direction an edge is written in
//! (swap its ends, invert its measurement). `tests/invariance.rs` checks the same of the batch
//! pipeline on clean worlds.
//!
//! The streams are simulated worlds with random or clustered false loop closures (method §11),
//! given in robot order with the default configuration (quarantine, eviction, family-wise
//! screening), as a robot would give them.

use std::collections::BTreeMap;

mod common;

use proptest::prelude::*;
use so2lin::graph::{Edge, NodeId, Pose2};
use so2lin::online::{OnlineConfig, OnlineEstimator, robot_order};
use so2lin::sim::{
    OutlierConfig, OutlierKind, SimConfig, compose, inject_outliers, simulate, wrap_angle,
};

/// What a caller reads at the end of a stream.
struct Answer {
    /// Input indices of the loop closures in quarantine, ascending.
    rejected: Vec<usize>,
    /// Every step's quarantined and re-admitted input indices, in order.
    events: Vec<(Vec<usize>, Vec<usize>)>,
    /// The exact pose of every node, by label.
    poses: BTreeMap<NodeId, Pose2>,
}

/// A simulated world of `poses` poses with `count` false loop closures of `kind`, in robot
/// order.
fn corrupted_world(poses: usize, seed: u64, count: usize, kind: OutlierKind) -> Vec<Edge> {
    let world = simulate(&SimConfig::new(poses, seed)).unwrap().graph;
    let config = OutlierConfig { count, kind, seed };
    robot_order(inject_outliers(&world, &config).unwrap().graph.edges())
}

fn stream(edges: &[Edge]) -> Answer {
    let mut est = OnlineEstimator::new(OnlineConfig::default()).unwrap();
    let events = edges
        .iter()
        .map(|e| {
            let step = est.add_edge(*e).unwrap();
            let quarantined = step.quarantined.iter().map(|r| r.edge).collect();
            (quarantined, step.readmitted)
        })
        .collect();
    let mut rejected: Vec<usize> = est.rejected().iter().map(|r| r.edge).collect();
    rejected.sort_unstable();
    let poses = est.poses_by_id().unwrap().into_iter().collect();
    Answer {
        rejected,
        events,
        poses,
    }
}

/// `edges` with node labels mapped by `relabel` and edge `k` rewritten by `edit`.
fn rewrite(
    edges: &[Edge],
    relabel: impl Fn(NodeId) -> NodeId,
    edit: impl Fn(usize, &Edge) -> Edge,
) -> Vec<Edge> {
    (edges.iter().enumerate())
        .map(|(k, e)| {
            let e = edit(k, e);
            if (relabel(e.from()), relabel(e.to())) == (e.from(), e.to()) {
                // As edited: a reversed edge keeps its angle variance to the bit.
                return e;
            }
            Edge::new(
                relabel(e.from()),
                relabel(e.to()),
                e.measurement(),
                e.information(),
            )
            .unwrap()
        })
        .collect()
}

/// The same decisions, step by step and at the end.
fn assert_same_decisions(a: &Answer, b: &Answer) -> Result<(), TestCaseError> {
    prop_assert_eq!(&a.rejected, &b.rejected, "quarantined at the end");
    for (k, (x, y)) in a.events.iter().zip(&b.events).enumerate() {
        prop_assert_eq!(x, y, "quarantined, re-admitted at step {}", k);
    }
    Ok(())
}

/// Poses equal node by node (`label` maps a's labels to b's), headings wrapped, within 1e-7 m
/// and 1e-8 rad, after both are expressed in the frame of node `reference` (the estimate's
/// gauge is its first node: reversing the first edge changes which node that is).
fn assert_same_poses(
    a: &Answer,
    b: &Answer,
    label: impl Fn(NodeId) -> NodeId,
    reference: NodeId,
    positions: bool,
) -> Result<(), TestCaseError> {
    prop_assert_eq!(a.poses.len(), b.poses.len());
    let relative = |poses: &BTreeMap<NodeId, Pose2>, origin: NodeId, p: Pose2| {
        compose(poses[&origin].inverse(), p)
    };
    for (&id, &p) in &a.poses {
        let q = b.poses.get(&label(id)).copied();
        prop_assert!(q.is_some(), "node {} missing", id);
        let p = relative(&a.poses, reference, p);
        let q = relative(&b.poses, label(reference), q.unwrap_or(p));
        prop_assert!(
            wrap_angle(p.theta - q.theta).abs() < 1e-8,
            "node {}: heading {} vs {}",
            id,
            p.theta,
            q.theta
        );
        if positions {
            prop_assert!(
                (p.x - q.x).abs() < 1e-7 && (p.y - q.y).abs() < 1e-7,
                "node {}: {:?} vs {:?}",
                id,
                p,
                q
            );
        }
    }
    Ok(())
}

fn kind(clustered: bool) -> OutlierKind {
    if clustered {
        OutlierKind::Clustered
    } else {
        OutlierKind::Random
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(12))]

    /// Labels: any one-to-one map of the node ids (here an odd multiplier and an offset, and
    /// a scrambling one that reorders them) leaves decisions and poses as they were: the
    /// estimator numbers nodes by arrival, not by label.
    #[test]
    fn relabelling_nodes(poses in 300usize..1500, seed in any::<u64>(), count in 5usize..50,
                         clustered in any::<bool>(), mult in 1u64..1_000_000,
                         offset in 0u64..1u64 << 40, scramble in any::<bool>()) {
        let edges = corrupted_world(poses, seed, count, kind(clustered));
        let label = |id: NodeId| if scramble {
            // A bijection of u64 that does not keep the order (odd multiplier mod 2⁶⁴).
            id.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ offset
        } else {
            id * (2 * mult + 1) + offset
        };
        let (a, b) = (stream(&edges), stream(&rewrite(&edges, label, |_, e| *e)));
        assert_same_decisions(&a, &b)?;
        assert_same_poses(&a, &b, label, edges[0].from(), true)?;
    }

    /// 2π: adding whole turns to any measurement (a false one included) changes no decision
    /// and no pose (the wrap absorbs it).
    #[test]
    fn adding_two_pi_to_a_measurement(poses in 300usize..1500, seed in any::<u64>(),
                                      count in 5usize..50, clustered in any::<bool>(),
                                      pick in any::<prop::sample::Index>(), turns in -3i32..=3) {
        let edges = corrupted_world(poses, seed, count, kind(clustered));
        let target = pick.index(edges.len());
        let shifted = rewrite(&edges, |id| id, |k, e| if k == target { common::turned(e, turns) } else { *e });
        let (a, b) = (stream(&edges), stream(&shifted));
        assert_same_decisions(&a, &b)?;
        assert_same_poses(&a, &b, |id| id, edges[0].from(), true)?;
    }

}

proptest! {
    // Fixed cases (the same 48 at every run; see below).
    #![proptest_config(ProptestConfig {
        cases: 48,
        rng_seed: proptest::test_runner::RngSeed::Fixed(0x5EED_2026_1204),
        ..ProptestConfig::default()
    })]

    /// Direction: writing any edge (a false one included) the other way — ends swapped, the
    /// inverse measurement, the information of the same noise seen from the other end
    /// ([`Edge::reversed`], which keeps the angle variance to the bit) — changes no decision
    /// and no heading. Positions are not compared: the position solve takes each edge's
    /// translation information in its own frame, and the reversed edge's has the heading's
    /// lever arm folded in.
    ///
    /// What makes it hold: the cycle search starts from the later end of a loop closure
    /// whichever way it is written (the aimed search is not symmetric, and equal paths tie),
    /// the translation closure is tested at both ends of the chord (its statistic depends on
    /// the node it is taken at), and the closure keeps the translation–angle cross terms of
    /// every edge's covariance (a reversed edge's information has them). Its noise model is
    /// then the same either way up to terms of second order in the reversed edge's own angle
    /// noise, so a statistic at a threshold's very margin could still be decided
    /// differently: 0 of 4 000 random cases were (2026-12-04; 3 of 2 000 before these
    /// changes). Fixed cases, so that such a margin cannot fail a run by chance.
    #[test]
    fn reversing_an_edge(poses in 300usize..1500, seed in any::<u64>(), count in 5usize..50,
                         clustered in any::<bool>(), pick in any::<prop::sample::Index>()) {
        let edges = corrupted_world(poses, seed, count, kind(clustered));
        let target = pick.index(edges.len());
        let reversed = rewrite(&edges, |id| id, |k, e| if k == target { common::reversed(e) } else { *e });
        let (a, b) = (stream(&edges), stream(&reversed));
        assert_same_decisions(&a, &b)?;
        assert_same_poses(&a, &b, |id| id, edges[0].from(), false)?;
    }
}

/// The case that found the direction dependence (2026-12-04): 373 poses, seed
/// 2340718602608111102, 15 clustered false edges, the false edge 35 → 114 written the other
/// way — then (with its information unchanged, and the closure without cross terms)
/// quarantined on its angle instead of its translation closure (51.8 against 46.5 as
/// written), and the noise scales then moved a later decision.
#[test]
fn reversing_the_false_edge_that_found_the_direction_dependence() {
    let edges = corrupted_world(373, 2340718602608111102, 15, OutlierKind::Clustered);
    let target = edges
        .iter()
        .position(|e| (e.from(), e.to()) == (35, 114))
        .expect("the false edge 35 → 114");
    let reversed = rewrite(
        &edges,
        |id| id,
        |k, e| if k == target { common::reversed(e) } else { *e },
    );
    let (a, b) = (stream(&edges), stream(&reversed));
    assert!(a.rejected.contains(&target), "35 → 114 is quarantined");
    assert_same_decisions(&a, &b).unwrap();
    assert_same_poses(&a, &b, |id| id, edges[0].from(), false).unwrap();
}
