//! # so2lin
//!
//! Linear orientation estimation on SO(2) for planar pose graphs, after Carlone & Censi,
//! "Linear Estimation on SO(2) for Graph-based SLAM": orientations are a linear problem plus
//! one integer per cycle of the graph, and those integers are screened with Gaussian
//! confidence tests. The mathematics is written out in [`method`] (q, log10|Γ|, the success bound and every
//! figure the commands print); each module implements one of its concepts:
//!
//! - [`graph`]: the pose-graph model, edges with their angle variance σ² = (Ω⁻¹)_θθ;
//! - [`io`]: g2o / TORO readers (streaming and whole-file) and a g2o writer;
//! - [`sim`]: a seeded Manhattan-world simulator with ground truth;
//! - [`tree`]: spanning trees (odometric, minimum-weight) and forests;
//! - [`closure`]: the SE(2) translation closure of a cycle, its χ² test and noise scale;
//! - [`cycles`]: cycle bases (fundamental, incremental) as signed edge lists;
//! - [`gamma`]: the Gaussian model of the cycle integers γ and its sequential conditioning;
//! - [`screening`]: first (per-cycle) and second (joint) screening, success-rate bound;
//! - [`wraps`]: from γ to the wraps k of every edge;
//! - [`estimate`]: orientations θ* for a hypothesis (sparse Cholesky of the Laplacian) and
//!   least-squares positions given them;
//! - [`refine`]: Levenberg–Marquardt refinement of the full SE(2) cost;
//! - [`batch`]: the paper's pipeline, driving the modules above;
//! - [`online`]: the online estimator, driving the same modules one edge at a time;
//! - [`log`]: MCAP recording and bit-exact replay of online runs.
//! - [`work`]: the work a thread does in searches and factors, counted (deterministic, unlike
//!   a latency).
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

pub mod batch;
pub mod closure;
pub mod cycles;
pub mod error;
pub mod estimate;
pub mod gamma;
pub mod graph;
pub mod io;
#[doc = include_str!("method.md")]
pub mod method {}
#[cfg(feature = "mcap")]
pub mod log;
pub mod online;
pub mod refine;
pub mod screening;
pub mod sim;
pub mod tree;
pub mod work;
pub mod wraps;

pub use error::{Error, Result};
pub use graph::{Edge, GraphError, Information, NodeId, NodePolicy, Pose2, PoseGraph};
pub use io::{InfoOrder, ReadError, ReadOptions, Reader, Record};

/// The README's code examples, compiled and run as doctests.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
mod readme {}
