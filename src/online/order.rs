//! Robot order: the order in which a robot produces the edges of a pose graph. An edge exists
//! once its later node does, so a loop closure arrives with the pose that closes it, not after
//! every odometry edge (as M3500.g2o lists them). Streams and their latencies are measured in
//! this order unless a caller asks for the file's.

use std::collections::BTreeMap;

use crate::graph::{Edge, NodeId};

/// The edges in **robot order**: a robot produces an edge when its later node appears, so the
/// edges are stably sorted by the first appearance (in the given order) of the later of their
/// two nodes. Files that list all odometry first and every loop closure after (M3500) are
/// streamed as a robot would have produced them; a file already in robot order is unchanged.
pub fn robot_order(edges: &[Edge]) -> Vec<Edge> {
    robot_order_indices(edges)
        .into_iter()
        .map(|i| edges[i])
        .collect()
}

/// The permutation behind [`robot_order`]: position k of the robot order holds
/// `edges[robot_order_indices(edges)[k]]`.
pub fn robot_order_indices(edges: &[Edge]) -> Vec<usize> {
    let mut first: BTreeMap<NodeId, usize> = BTreeMap::new();
    for e in edges {
        for n in [e.from(), e.to()] {
            let next = first.len();
            first.entry(n).or_insert(next);
        }
    }
    let key = |e: &Edge| first[&e.from()].max(first[&e.to()]);
    let mut out: Vec<usize> = (0..edges.len()).collect();
    out.sort_by_key(|&i| key(&edges[i]));
    out
}
