//! One error type for the whole crate: [`Error`] wraps every module's error, so an
//! application can use `so2lin::Result` with `?` across modules and still match on the cause.
//!
//! ```
//! fn orientations(text: &str) -> so2lin::Result<Vec<f64>> {
//!     let (graph, _) = so2lin::io::read_graph_from(text.as_bytes(), "mem", Default::default())?;
//!     let r = so2lin::batch::screen(&graph, &Default::default())?;
//!     let orient = so2lin::estimate::OrientationEstimator::new(&graph)?;
//!     let wraps = r.wraps(&r.hypotheses[0])?;
//!     Ok(orient.orientations(&wraps))
//! }
//! let theta = orientations("EDGE_SE2 0 1 1 0 0.5 1 0 0 1 0 100\n").unwrap();
//! assert_eq!(theta.len(), 2);
//! assert!(matches!(orientations("EDGE_SE2 0 0 1 0 0 1 0 0 1 0 1\n"), Err(so2lin::Error::Read(_))));
//! ```

/// Any error of the crate, by module.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// An edge or node was rejected ([`crate::graph`]).
    #[error(transparent)]
    Graph(#[from] crate::graph::GraphError),
    /// A file could not be read ([`crate::io`]).
    #[error(transparent)]
    Read(#[from] crate::io::ReadError),
    /// Invalid screening settings ([`crate::screening`]).
    #[error(transparent)]
    Config(#[from] crate::screening::ConfigError),
    /// The batch pipeline stopped ([`crate::batch`]).
    #[error(transparent)]
    Batch(#[from] crate::batch::BatchError),
    /// Poses could not be computed for a hypothesis ([`crate::batch::solve`]).
    #[error(transparent)]
    Solve(#[from] crate::batch::SolveError),
    /// A linear system failed ([`crate::estimate`]).
    #[error(transparent)]
    Estimate(#[from] crate::estimate::EstimateError),
    /// Wraps could not be computed ([`crate::wraps`]).
    #[error(transparent)]
    Wraps(#[from] crate::wraps::WrapError),
    /// P_γ numerically singular ([`crate::gamma`]).
    #[error(transparent)]
    Singular(#[from] crate::gamma::SingularError),
    /// The online estimator refused an input or query ([`crate::online`]).
    #[error(transparent)]
    Online(#[from] crate::online::OnlineError),
    /// A simulator setting out of range ([`crate::sim`]).
    #[error(transparent)]
    Sim(#[from] crate::sim::SimError),
    /// A minimum cycle basis was not computed ([`crate::cycles::mcb`]).
    #[error(transparent)]
    Mcb(#[from] crate::cycles::mcb::McbError),
    /// An MCAP log could not be written or read ([`crate::log`]).
    #[cfg(feature = "mcap")]
    #[error(transparent)]
    Log(#[from] crate::log::LogError),
}

/// `Result` with the crate's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;
