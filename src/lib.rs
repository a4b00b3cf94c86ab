//! # so2lin
//!
//! Linear orientation estimation on SO(2) for planar pose graphs, after Carlone & Censi,
//! "Linear Estimation on SO(2) for Graph-based SLAM": orientations are a linear problem plus
//! one integer per cycle of the graph, and those integers are screened with Gaussian
//! confidence tests. The mathematics is restated in the repository's `METHOD.md` reference;
//! each module implements one of its concepts:
//!
//! - [`graph`]: the pose-graph model, edges with their angle variance σ² = (Ω⁻¹)_θθ;
//! - [`io`]: g2o / TORO readers (streaming and whole-file) and a g2o writer;
//! - [`sim`]: a seeded Manhattan-world simulator with ground truth.
//!
//! ```
//! use so2lin::sim::{simulate, SimConfig};
//!
//! let world = simulate(&SimConfig::new(200, 1)).unwrap();
//! let stats = world.graph.stats();
//! assert_eq!(stats.nodes, 200);
//! assert_eq!(stats.cycles, stats.edges - stats.nodes + 1);
//! ```
#![warn(missing_docs)]

pub mod graph;
pub mod io;
pub mod sim;

pub use graph::{Edge, GraphError, Information, NodeId, NodePolicy, Pose2, PoseGraph};
pub use io::{InfoOrder, ReadError, ReadOptions, Reader, Record};

/// The README's code examples, compiled and run as doctests.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
mod readme {}
