//! The command line: the subcommands, their options and the value enums they parse.

use std::path::PathBuf;

use clap::{Parser, Subcommand, ValueEnum};
use so2lin::batch::BatchConfig;
use so2lin::cycles::BasisKind;
use so2lin::io::InfoOrder;
use so2lin::screening::ScreeningConfig;
use so2lin::sim::OutlierKind;

/// Placement of false loop closures (`--outlier-kind`, `--kind`).
#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum OutlierKindArg {
    /// Independent random node pairs.
    Random,
    /// Groups of 10 consecutive edges between two regions sharing one measurement.
    Clustered,
}

impl From<OutlierKindArg> for OutlierKind {
    fn from(k: OutlierKindArg) -> Self {
        match k {
            OutlierKindArg::Random => OutlierKind::Random,
            OutlierKindArg::Clustered => OutlierKind::Clustered,
        }
    }
}

/// The chart of an edge's SE(2) error in the refinement (`--residual`).
#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum ResidualArg {
    /// The SE(2) logarithm: the geodesic error, as GTSAM's BetweenFactor<Pose2>.
    Log,
    /// g2o's EdgeSE2 error: translation and wrapped angle of Z⁻¹ X_i⁻¹ X_j (g2o's χ²).
    T2v,
}

impl From<ResidualArg> for so2lin::refine::Residual {
    fn from(r: ResidualArg) -> Self {
        match r {
            ResidualArg::Log => Self::Log,
            ResidualArg::T2v => Self::T2v,
        }
    }
}

#[derive(Parser)]
#[command(
    name = "so2lin",
    version,
    about = "Linear orientation estimation on SO(2) for planar pose graphs"
)]
pub(crate) struct Cli {
    #[command(subcommand)]
    pub(crate) command: Command,
}

#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum OrderArg {
    Auto,
    G2o,
    Toro,
}

impl From<OrderArg> for InfoOrder {
    fn from(o: OrderArg) -> Self {
        match o {
            OrderArg::Auto => InfoOrder::Auto,
            OrderArg::G2o => InfoOrder::G2o,
            OrderArg::Toro => InfoOrder::Toro,
        }
    }
}

/// Screening options shared by `screen` and `stream`.
#[derive(clap::Args)]
pub(crate) struct ScreeningArgs {
    /// Significance level α, in (0, 1) [default: 0.01, also with --paper].
    #[arg(long, allow_hyphen_values = true, value_parser = parse_alpha)]
    pub(crate) alpha: Option<f64>,
    /// Degrees of freedom of the per-cycle χ² quantile [default: 1; 3 with --paper].
    #[arg(long)]
    pub(crate) dof: Option<u32>,
    /// The paper's setting: α = 0.01 per cycle, 3 degrees of freedom (explicit --alpha/--dof
    /// win).
    #[arg(long)]
    pub(crate) paper: bool,
    /// Test every cycle at α instead of the family-wise default (about α·ℓ cycles of clean
    /// data then fail their test).
    #[arg(long, long_help = PER_CYCLE_HELP)]
    pub(crate) per_cycle: bool,
    /// Cap on the hypotheses of the second screening.
    #[arg(long, default_value_t = 1_000_000)]
    pub(crate) max_hypotheses: usize,
}

/// The family-wise rule, described once for every command's help.
pub(crate) const PER_CYCLE_HELP: &str = "Test every cycle at α instead of the default family-wise rule. \
Family-wise (the default): the probability that any cycle fails its consistency test, or that \
the surviving set misses the true cycle integers, is at most α on data that follow the declared \
noise; the per-cycle tests share α/2 (α/(2ℓ) each in batch; the α-spending sequence \
α_t = (α/2)·c/((t+100)·ln²(t+100)) online, where ℓ is not known in advance) and the joint test of \
the second screening gets the other α/2. Per cycle, about α·ℓ cycles of clean data fail their test.";

impl ScreeningArgs {
    pub(crate) fn config(&self) -> ScreeningConfig {
        let base = if self.paper {
            ScreeningConfig::paper()
        } else {
            ScreeningConfig::default()
        };
        ScreeningConfig {
            alpha: self.alpha.unwrap_or(base.alpha),
            dof: self.dof.unwrap_or(base.dof),
            family_wise: base.family_wise && !self.per_cycle,
            max_hypotheses: self.max_hypotheses,
        }
    }
}

/// The input graph and the batch settings shared by `screen` and `solve`.
#[derive(clap::Args)]
pub(crate) struct BatchArgs {
    /// Graph file (g2o or TORO).
    pub(crate) file: PathBuf,
    /// Cycle basis.
    #[arg(long, value_enum, default_value = "incremental")]
    pub(crate) basis: BasisKind,
    #[command(flatten)]
    pub(crate) screening: ScreeningArgs,
    /// Information-matrix order of edge lines (default: detect).
    #[arg(long, value_enum, default_value = "auto")]
    pub(crate) order: OrderArg,
}

impl BatchArgs {
    pub(crate) fn config(&self) -> BatchConfig {
        BatchConfig {
            basis: self.basis,
            screening: self.screening.config(),
        }
    }
}

#[derive(Subcommand)]
pub(crate) enum Command {
    /// Counts and noise statistics of a g2o / TORO graph file.
    Info {
        /// Graph file (g2o or TORO).
        file: PathBuf,
        /// Information-matrix order of edge lines (default: detect).
        #[arg(long, value_enum, default_value = "auto")]
        order: OrderArg,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Simulate a Manhattan world; writes the graph to OUT (g2o) and its ground truth beside it
    /// (OUT with the extension `.truth.json`: `w.g2o` gives `w.truth.json`).
    Simulate {
        /// Number of poses.
        #[arg(long, default_value_t = 3500)]
        poses: usize,
        /// Random seed.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Angle noise standard deviation (radians).
        #[arg(long)]
        sigma_theta: Option<f64>,
        /// Translation noise standard deviation (grid units).
        #[arg(long)]
        sigma_xy: Option<f64>,
        /// Probability that an eligible earlier pose gets a loop closure.
        #[arg(long)]
        loop_closure_prob: Option<f64>,
        /// Add this many false loop closures (Vertigo protocol, as `inject`); the ground truth
        /// lists them under `false_edges`.
        #[arg(long, default_value_t = 0)]
        outliers: usize,
        /// Placement of the false loop closures.
        #[arg(long, value_enum, default_value = "random")]
        outlier_kind: OutlierKindArg,
        /// Output g2o file.
        #[arg(long)]
        out: PathBuf,
    },
    /// Add false loop closures to a graph file (Vertigo protocol): K random pairs, or groups
    /// of 10 consecutive edges between two regions sharing one measurement; angle uniform in
    /// (−π, π], translation uniform in ±10; a genuine loop closure's information; each false
    /// edge right after the edge introducing its later node (robot order). Writes g2o.
    Inject {
        /// Graph file (g2o or TORO).
        file: PathBuf,
        /// Number of false loop closures K.
        #[arg(long)]
        outliers: usize,
        /// Placement of the false loop closures.
        #[arg(long, value_enum, default_value = "random")]
        kind: OutlierKindArg,
        /// Random seed.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Output g2o file.
        #[arg(long)]
        out: PathBuf,
        /// Write the false edges as JSON here (`false_edges[{edge, from, to, group}]`, edge =
        /// 0-based index in OUT's edge order).
        #[arg(long)]
        truth: Option<PathBuf>,
        /// Information-matrix order of edge lines (default: detect).
        #[arg(long, value_enum, default_value = "auto")]
        order: OrderArg,
    },
    /// Screen the cycle integers of a graph with the paper's batch pipeline.
    Screen {
        #[command(flatten)]
        batch: BatchArgs,
        /// Write `node_id theta` lines of the best hypothesis (radians, unwrapped, anchor 0).
        #[arg(long)]
        orientations: Option<PathBuf>,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Screening, orientations, least-squares positions and SE(2) refinement: full poses.
    Solve {
        #[command(flatten)]
        batch: BatchArgs,
        /// Refinement: at most this many Levenberg–Marquardt iterations (0: linear poses only).
        #[arg(long, default_value_t = so2lin::refine::RefineConfig::default().iterations)]
        refine: usize,
        /// Converged once a step lowers the cost by less than this fraction.
        #[arg(long, default_value_t = so2lin::refine::RefineConfig::default().relative_decrease)]
        tolerance: f64,
        /// Converged once the gradient's largest entry (‖Σ JᵀΩe‖∞) is at most this.
        #[arg(long, default_value_t = so2lin::refine::RefineConfig::default().gradient_tolerance)]
        gradient_tolerance: f64,
        /// The error each edge contributes to the refined cost: the SE(2) logarithm (geodesic,
        /// GTSAM's) or g2o's t2v. They agree to first order; on strongly anisotropic
        /// information their minima differ.
        #[arg(long, value_enum, default_value_t = ResidualArg::Log)]
        residual: ResidualArg,
        /// Solve every surviving hypothesis and rank them by refined cost.
        #[arg(long)]
        all_hypotheses: bool,
        /// Plain least squares on every edge: no robust kernel. By default the file is first
        /// streamed through the online quarantine, then loop closures get the DCS kernel with
        /// the family-wise threshold Φ = χ²_3⁻¹(1 − α/(2·loop closures)); those still above Φ
        /// at the robust solution, or whose leave-out cost drop exceeds its threshold, are
        /// rejected (and listed; the stream runs again without those it had accepted), and
        /// the refinement runs on the rest.
        #[arg(long)]
        no_robust: bool,
        /// Also run the same refinement from dead-reckoned odometry (the local-minimum baseline).
        #[arg(long)]
        odometry: bool,
        /// Write the best refined poses and the edges as g2o.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Every cycle basis of a file side by side: weight, ratio to the MCB, cycle lengths,
    /// integrality, density of P_γ, time (the paper's Table I, extended).
    Bases {
        /// Graph file (g2o or TORO).
        file: PathBuf,
        /// Time budget per basis in seconds; a basis not done in time is listed with an error.
        #[arg(long)]
        max_seconds: Option<f64>,
        /// k of the (2k−1)-approximate MCB.
        #[arg(long, default_value_t = so2lin::cycles::approx::DEFAULT_K)]
        approx_k: u32,
        /// Information-matrix order of edge lines (default: detect).
        #[arg(long, value_enum, default_value = "auto")]
        order: OrderArg,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Plot the estimated trajectory of a graph file or an MCAP log (one panel per hypothesis).
    Plot {
        /// Graph file (g2o or TORO) or so2lin MCAP log.
        input: PathBuf,
        /// Output image, .svg or .png.
        #[arg(long)]
        out: PathBuf,
        /// One panel per surviving hypothesis (default: the best only).
        #[arg(long)]
        all_hypotheses: bool,
        /// Image width in pixels.
        #[arg(long, default_value_t = 1200)]
        width: u32,
        /// Image height in pixels.
        #[arg(long, default_value_t = 900)]
        height: u32,
        /// Cycle basis (graph files).
        #[arg(long, value_enum, default_value = "incremental")]
        basis: BasisKind,
        #[command(flatten)]
        screening: ScreeningArgs,
        /// Refinement: at most this many Levenberg–Marquardt iterations.
        #[arg(long, default_value_t = so2lin::refine::RefineConfig::default().iterations)]
        refine: usize,
        /// Information-matrix order of edge lines (default: detect).
        #[arg(long, value_enum, default_value = "auto")]
        order: OrderArg,
    },
    /// Feed a file's edges through the online estimator (as a robot produces them, by default), timing each step.
    Stream {
        /// Graph file (g2o or TORO).
        file: PathBuf,
        #[command(flatten)]
        screening: ScreeningArgs,
        /// Write `node_id theta` lines of the best hypothesis after finishing.
        #[arg(long)]
        orientations: Option<PathBuf>,
        /// Record every step to this MCAP log.
        #[arg(long)]
        log: Option<PathBuf>,
        /// With --log: full snapshots (/graph, /poses, /so2lin/estimate) every N steps.
        #[arg(long, value_name = "N", default_value_t = 100)]
        snapshot_every: usize,
        /// With --log: log time between steps in seconds (file edges carry no timestamps; the
        /// first step is at the wall-clock time of the run) [default: 0.1, or 1/HZ with
        /// --rate].
        #[arg(long, value_name = "SECONDS")]
        step_time: Option<f64>,
        /// Order in which edges reach the estimator: as a robot produces them (an edge when
        /// its later node appears) or as the file lists them.
        #[arg(long, value_enum, default_value = "robot")]
        order: crate::stream::EdgeOrder,
        /// What is read after every step (inside the measured latency).
        #[arg(long, value_enum, default_value = "newest")]
        estimate: crate::stream::EstimateQuery,
        /// Information-matrix order of edge lines (default: detect).
        #[arg(long, value_enum, default_value = "auto")]
        info_order: OrderArg,
        /// Add every edge, even a loop closure whose cycle fails its angle or translation test
        /// (by default it is quarantined: kept out of the estimate, listed, re-tested later).
        #[arg(long)]
        no_quarantine: bool,
        /// Feed the edges at this rate (edges per second), as a robot's front end produces
        /// them: edge k arrives k/HZ seconds after the first and the stream sleeps until then;
        /// each step is timed from its start, and how far the steps fell behind the arrivals
        /// is reported [default: back to back, as fast as the steps go].
        #[arg(long, value_name = "HZ")]
        rate: Option<f64>,
        /// Swap renewals of the estimate's factor in after this multiple of the default delay
        /// (counted in work): below 1 for edges at a sensor's rate, which leaves the builder
        /// time between them (back to back, steps would wait for it).
        #[arg(long, value_name = "F", default_value_t = 1.0)]
        renewal_delay: f64,
        /// Do not reserve the file's node and edge counts before the first step (as a front
        /// end that does not know its mission's size): the estimator's arrays then grow as
        /// edges arrive, each growth a copy in one step.
        #[arg(long)]
        no_reserve: bool,
        /// Give the estimator the time between steps: call `OnlineEstimator::maintain` after
        /// every step (it renews the estimate's factor on this thread once enough nodes were
        /// appended since its order was made, and re-linearises its position rows before a
        /// step has to). Its time is not in the steps' latency and is reported apart; with
        /// --rate it runs in the wait for the next edge.
        #[arg(long)]
        maintain: bool,
        /// Write one CSV line per step to FILE: step, the edge's index in the file, kind
        /// (tree, cycle, quarantined), time in ns (as in the latencies), the step's counted
        /// work (search nodes, estimate factor entries, P_UU factor entries) and whether an
        /// eviction's rebuild was in progress beside the estimator after it (1 or 0).
        #[arg(long, value_name = "FILE")]
        trace: Option<PathBuf>,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Rebuild a run from its MCAP log: verify every step, or report replay latencies.
    Replay {
        /// The MCAP log.
        log: PathBuf,
        /// Compare every replayed step with the recorded one; exit non-zero on a divergence.
        #[arg(long)]
        verify: bool,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Simulate a world in memory and run the library on it (no files needed).
    Demo {
        /// Number of poses.
        #[arg(long, default_value_t = 2000)]
        poses: usize,
        /// Random seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Angle noise standard deviation (radians).
        #[arg(long)]
        sigma_theta: Option<f64>,
        /// Where to write the MCAP log of the online run; the trajectory plot goes next to it
        /// (.svg) [default: so2lin-demo-<poses>-<seed>.mcap in the system's temporary
        /// directory, so demos of other worlds do not overwrite each other].
        #[arg(long)]
        log: Option<PathBuf>,
    },
}

/// `--alpha`: a level the screening arithmetic can represent ([`ScreeningConfig::validate`]).
pub(crate) fn parse_alpha(text: &str) -> Result<f64, String> {
    let alpha: f64 = text
        .parse()
        .map_err(|_| format!("{text:?} is not a number"))?;
    let config = ScreeningConfig {
        alpha,
        ..ScreeningConfig::default()
    };
    config.validate().map_err(|e| e.0)?;
    Ok(alpha)
}
