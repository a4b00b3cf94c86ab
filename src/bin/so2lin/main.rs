//! The `so2lin` command-line tool.

use std::io::{BufReader, IsTerminal};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;

mod bases;
mod inject;
mod plot;
mod replay;
mod screen;
mod solve;
mod stream;

use so2lin::batch::BatchConfig;
use so2lin::cycles::BasisKind;
use so2lin::graph::{GraphStats, PoseGraph};
use so2lin::io::{self, InfoOrder, ReadOptions, ReadSummary};
use so2lin::online::OnlineConfig;
use so2lin::screening::ScreeningConfig;
use so2lin::sim::{self, OutlierConfig, OutlierKind, SimConfig};

/// Placement of false loop closures (`--outlier-kind`, `--kind`).
#[derive(Clone, Copy, ValueEnum)]
enum OutlierKindArg {
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
enum ResidualArg {
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
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, ValueEnum)]
enum OrderArg {
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
struct ScreeningArgs {
    /// Significance level α, in (0, 1) [default: 0.01, also with --paper].
    #[arg(long, allow_hyphen_values = true, value_parser = parse_alpha)]
    alpha: Option<f64>,
    /// Degrees of freedom of the per-cycle χ² quantile [default: 1; 3 with --paper].
    #[arg(long)]
    dof: Option<u32>,
    /// The paper's setting: α = 0.01 per cycle, 3 degrees of freedom (explicit --alpha/--dof
    /// win).
    #[arg(long)]
    paper: bool,
    /// Test every cycle at α instead of the family-wise default (about α·ℓ cycles of clean
    /// data then fail their test).
    #[arg(long, long_help = PER_CYCLE_HELP)]
    per_cycle: bool,
    /// Cap on the hypotheses of the second screening.
    #[arg(long, default_value_t = 1_000_000)]
    max_hypotheses: usize,
}

/// The family-wise rule, described once for every command's help.
const PER_CYCLE_HELP: &str = "Test every cycle at α instead of the default family-wise rule. \
Family-wise (the default): the probability that any cycle fails its consistency test, or that \
the surviving set misses the true cycle integers, is at most α on data that follow the declared \
noise; the per-cycle tests share α/2 (α/(2ℓ) each in batch; the α-spending sequence \
α_t = (α/2)·c/((t+100)·ln²(t+100)) online, where ℓ is not known in advance) and the joint test of \
the second screening gets the other α/2. Per cycle, about α·ℓ cycles of clean data fail their test.";

impl ScreeningArgs {
    fn config(&self) -> ScreeningConfig {
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
struct BatchArgs {
    /// Graph file (g2o or TORO).
    file: PathBuf,
    /// Cycle basis.
    #[arg(long, value_enum, default_value = "incremental")]
    basis: BasisKind,
    #[command(flatten)]
    screening: ScreeningArgs,
    /// Information-matrix order of edge lines (default: detect).
    #[arg(long, value_enum, default_value = "auto")]
    order: OrderArg,
}

impl BatchArgs {
    fn config(&self) -> BatchConfig {
        BatchConfig {
            basis: self.basis,
            screening: self.screening.config(),
        }
    }
}

#[derive(Subcommand)]
enum Command {
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
        order: stream::EdgeOrder,
        /// What is read after every step (inside the measured latency).
        #[arg(long, value_enum, default_value = "newest")]
        estimate: stream::EstimateQuery,
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

/// A one-line error for the user.
type CliResult = Result<(), String>;

/// `--alpha`: a level the screening arithmetic can represent ([`ScreeningConfig::validate`]).
fn parse_alpha(text: &str) -> Result<f64, String> {
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

/// Exit status when stdout is a closed pipe: 128 + SIGPIPE, what a shell reports for a
/// process killed by a broken pipe (`cat file | head -c 1`).
const BROKEN_PIPE_STATUS: i32 = 141;

/// `println!` panics when stdout fails. Turn that panic into the conventional exits: quietly
/// with [`BROKEN_PIPE_STATUS`] on a closed pipe, with a one-line error and status 1 on any
/// other failure (a full disk); every other panic keeps Rust's report.
fn handle_stdout_failures() {
    let default = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let message = info
            .payload()
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| info.payload().downcast_ref::<&str>().copied())
            .unwrap_or("");
        if let Some(why) = message.strip_prefix("failed printing to stdout: ") {
            if why.contains("Broken pipe") {
                std::process::exit(BROKEN_PIPE_STATUS);
            }
            eprintln!("error: writing to stdout: {why}");
            std::process::exit(1);
        }
        default(info);
    }));
}

fn main() -> ExitCode {
    handle_stdout_failures();
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Info { file, order, json } => info(&file, order.into(), json),
        Command::Simulate {
            poses,
            seed,
            sigma_theta,
            sigma_xy,
            loop_closure_prob,
            outliers,
            outlier_kind,
            out,
        } => {
            let mut c = SimConfig::new(poses, seed);
            c.sigma_theta = sigma_theta.unwrap_or(c.sigma_theta);
            c.sigma_xy = sigma_xy.unwrap_or(c.sigma_xy);
            c.loop_closure_probability = loop_closure_prob.unwrap_or(c.loop_closure_probability);
            let outliers = OutlierConfig {
                count: outliers,
                kind: outlier_kind.into(),
                seed,
            };
            simulate(&c, &outliers, &out)
        }
        Command::Inject {
            file,
            outliers,
            kind,
            seed,
            out,
            truth,
            order,
        } => inject::run(inject::InjectArgs {
            file: &file,
            order: order.into(),
            outliers: OutlierConfig {
                count: outliers,
                kind: kind.into(),
                seed,
            },
            out: &out,
            truth: truth.as_deref(),
        }),
        Command::Demo {
            poses,
            seed,
            sigma_theta,
            log,
        } => demo(poses, seed, sigma_theta, log),
        Command::Stream {
            file,
            screening,
            orientations,
            log,
            snapshot_every,
            step_time,
            order,
            estimate,
            info_order,
            no_quarantine,
            rate,
            renewal_delay,
            no_reserve,
            maintain,
            json,
        } => {
            // At least one edge every 10⁶ s (the log's longest step), at most 10⁹ a second.
            let rate_ok = rate.is_none_or(|r| r.is_finite() && r > 1e-6 && r <= 1e9);
            // The log's clock follows the edges' pace unless given.
            let step_time = step_time.unwrap_or(match rate {
                Some(hz) if rate_ok => hz.recip(),
                _ => 0.1,
            });
            let step_time_ok = step_time.is_finite() && (0.0..1e6).contains(&step_time);
            let config = OnlineConfig {
                screening: screening.config(),
                quarantine: !no_quarantine,
                // The recorder reads the newest pose every step.
                estimate_every_step: !matches!(estimate, stream::EstimateQuery::None)
                    || log.is_some(),
                renewal_delay,
                ..OnlineConfig::default()
            };
            if !rate_ok {
                Err(format!(
                    "--rate {:?}: must be a number of edges per second in (10⁻⁶, 10⁹]",
                    rate.unwrap_or(f64::NAN)
                ))
            } else if !step_time_ok {
                Err(format!(
                    "--step-time {step_time:?}: must be a number of seconds in [0, 10⁶)"
                ))
            } else {
                stream::run(stream::StreamArgs {
                    file: &file,
                    info_order: info_order.into(),
                    edge_order: order,
                    estimate,
                    config,
                    orientations: orientations.as_deref(),
                    log: log.as_deref(),
                    log_options: so2lin::log::LogOptions {
                        snapshot_every,
                        ..Default::default()
                    },
                    step_time_ns: (step_time * 1e9) as u64,
                    rate,
                    reserve: !no_reserve,
                    maintain,
                    json,
                })
            }
        }
        Command::Replay { log, verify, json } => replay::run(&log, verify, json),
        Command::Plot {
            input,
            out,
            all_hypotheses,
            width,
            height,
            basis,
            screening,
            refine,
            order,
        } => explained(
            &input.clone(),
            order.into(),
            plot::run(plot::PlotArgs {
                input: &input,
                out: &out,
                order: order.into(),
                config: BatchConfig {
                    basis,
                    screening: screening.config(),
                },
                refine: so2lin::refine::RefineConfig::with_iterations(refine),
                all_hypotheses,
                size: (width, height),
            }),
        ),
        Command::Solve {
            batch,
            refine,
            tolerance,
            gradient_tolerance,
            residual,
            all_hypotheses,
            no_robust,
            odometry,
            out,
            json,
        } => explained(
            &batch.file.clone(),
            batch.order.into(),
            solve::run(solve::SolveArgs {
                file: &batch.file,
                order: batch.order.into(),
                config: batch.config(),
                robust: (!no_robust).then(|| so2lin::batch::RobustConfig {
                    alpha: batch.config().screening.alpha,
                    ..Default::default()
                }),
                refine: so2lin::refine::RefineConfig {
                    iterations: refine,
                    relative_decrease: tolerance,
                    gradient_tolerance,
                    residual: residual.into(),
                    ..Default::default()
                },
                all_hypotheses,
                odometry,
                out: out.as_deref(),
                json,
            }),
        ),
        Command::Bases {
            file,
            max_seconds,
            approx_k,
            order,
            json,
        } => bases::run(bases::BasesArgs {
            file: &file,
            order: order.into(),
            max_seconds,
            k: approx_k,
            json,
        }),
        Command::Screen {
            batch,
            orientations,
            json,
        } => explained(
            &batch.file,
            batch.order.into(),
            screen::run(screen::ScreenArgs {
                file: &batch.file,
                order: batch.order.into(),
                config: batch.config(),
                orientations: orientations.as_deref(),
                json,
            }),
        ),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(msg) => {
            eprintln!("error: {msg}");
            ExitCode::FAILURE
        }
    }
}

/// A byte-progress bar with rate and ETA on a terminal, hidden otherwise (stderr redirected).
pub(crate) fn progress_bar(len: u64, what: &str) -> ProgressBar {
    if !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(len);
    let template = "{msg} [{bar:30}] {bytes}/{total_bytes} ({bytes_per_sec}, ETA {eta})";
    if let Ok(style) = ProgressStyle::with_template(template) {
        bar.set_style(style);
    }
    bar.set_message(what.to_owned());
    bar
}

/// A phase of unknown length (screening, estimating, refining, plotting) shown as a spinner
/// with its elapsed time on a terminal, hidden otherwise; clear it with `finish_and_clear`.
pub(crate) fn phase(what: String) -> ProgressBar {
    if !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new_spinner();
    if let Ok(style) = ProgressStyle::with_template("{spinner} {msg} ({elapsed})") {
        bar.set_style(style);
    }
    bar.set_message(what);
    bar.enable_steady_tick(std::time::Duration::from_millis(100));
    bar
}

/// `f` run as a [`phase`] named `what`.
pub(crate) fn in_phase<T>(what: impl Into<String>, f: impl FnOnce() -> T) -> T {
    let bar = phase(what.into());
    let out = f();
    bar.finish_and_clear();
    out
}

/// Read a graph file, with a progress bar on a terminal. Skipped lines are reported on stderr
/// by tag; a file without a single 2D pose edge is an error.
pub(crate) fn load(path: &Path, order: InfoOrder) -> Result<(PoseGraph, ReadSummary), String> {
    load_reporting(path, order, true)
}

/// [`load`], with skipped lines reported on stderr or not (`info` lists them itself).
fn load_reporting(
    path: &Path,
    order: InfoOrder,
    report_skipped: bool,
) -> Result<(PoseGraph, ReadSummary), String> {
    let file = io::open_file(path).map_err(|e| e.to_string())?;
    let len = file.metadata().map(|m| m.len()).unwrap_or(0);
    let bar = progress_bar(len, "reading");
    let src = BufReader::new(bar.wrap_read(file));
    let opts = ReadOptions {
        order,
        ..Default::default()
    };
    let out = io::read_graph_from(src, &path.display().to_string(), opts);
    bar.finish_and_clear();
    let (graph, summary) = out.map_err(|e| e.to_string())?;
    let skipped = skipped_lines(&summary);
    if graph.edge_count() == 0 {
        return Err(format!(
            "{}: no 2D pose edge (EDGE_SE2 or EDGE2) in the file{}",
            path.display(),
            skipped.map_or(String::new(), |s| format!("; skipped {s}"))
        ));
    }
    if let Some(s) = skipped.filter(|_| report_skipped) {
        eprintln!("{}: skipped {s}", path.display());
    }
    Ok((graph, summary))
}

/// "12 lines with other tags: LANDMARK ×2, VERTEX_SE3:QUAT ×10", or None.
pub(crate) fn skipped_lines(summary: &ReadSummary) -> Option<String> {
    if summary.skipped.is_empty() {
        return None;
    }
    let total: usize = summary.skipped.values().sum();
    let list: Vec<String> = summary
        .skipped
        .iter()
        .map(|(t, n)| format!("{t} ×{n}"))
        .collect();
    Some(format!(
        "{} with other tags: {}",
        plural(total, "line", "lines"),
        list.join(", ")
    ))
}

/// "1 hypothesis", "3 hypotheses".
/// Print rejected edges (at most ten, then a count): one line naming how many and `what`
/// happened to them, then `edge i (from → to): test statistic > threshold`, and what a
/// translation statistic is when one is listed. Nothing when empty.
pub(crate) fn print_rejected(rejected: &[so2lin::batch::RejectedEdge], what: &str) {
    if rejected.is_empty() {
        return;
    }
    println!(
        "{} {what}:",
        plural(rejected.len(), "loop closure", "loop closures")
    );
    for r in rejected.iter().take(10) {
        println!(
            "  edge {} ({} → {}): {} {:.2} > {:.2}",
            r.edge, r.from, r.to, r.test, r.statistic, r.threshold
        );
    }
    if rejected.len() > 10 {
        println!("  … {} more (--json lists all)", rejected.len() - 10);
    }
    if rejected
        .iter()
        .any(|r| r.test == so2lin::online::TRANSLATION_TEST)
    {
        println!(
            "  ({} statistics: the larger of the closure at the chord's two ends, or the first end's alone when it already fails, a lower bound)",
            so2lin::online::TRANSLATION_TEST
        );
    }
}

/// Print the quarantine's noise scales (one line).
pub(crate) fn print_noise_scales(s: &so2lin::online::NoiseScales) {
    println!(
        "noise scales from the accepted cycles (quarantine tests only; the screening keeps the declared noise): angle {:.3} (from {} cycle tests), translation {:.3} (from {})",
        s.angle, s.angle_samples, s.translation, s.translation_samples
    );
}

/// What a success bound or p-value is stated for: "all N edges accepted, none rejected", or
/// "the N accepted edges; R rejected edges left out".
pub(crate) fn accepted_words(accepted: usize, rejected: usize) -> String {
    if rejected == 0 {
        format!("all {accepted} edges accepted, none rejected")
    } else {
        format!(
            "for the {accepted} accepted edges; {} left out",
            plural(rejected, "rejected edge", "rejected edges")
        )
    }
}

/// What the second screening of `r` did, in words (one sentence for every command): `None`
/// when it completed, else why it stopped and that the answer shown is the bootstrapped one.
pub(crate) fn second_screening_words(
    r: &so2lin::batch::BatchResult,
    joint_level: f64,
) -> Option<String> {
    use so2lin::screening::{Limit, SecondOutcome};
    const SHOWING: &str = "showing the bootstrapped answer, not a screened set";
    match r.outcome {
        SecondOutcome::Complete => None,
        SecondOutcome::TooMany(t) => Some(match t.limit {
            Limit::Hypotheses => format!(
                "second screening stopped: too many hypotheses ({} ≥ cap {}); {SHOWING}",
                t.found, t.cap
            ),
            Limit::Visits => format!(
                "second screening stopped: its search budget of {} partial vectors was exhausted with {} found; {SHOWING}",
                t.visited, t.found
            ),
            Limit::Memory => format!(
                "second screening stopped: the memory bound of {} MiB was reached with {} found; {SHOWING}",
                so2lin::screening::MAX_ENUMERATION_BYTES >> 20,
                t.found
            ),
        }),
        SecondOutcome::NoneInside => Some(format!(
            "second screening: no candidate vector of the {} ambiguous cycles passes the joint χ² test at level {} (the measurements disagree with their declared noise, or hold an outlier); {SHOWING}",
            r.ambiguous.len(),
            joint_level
        )),
    }
}

pub(crate) fn plural(n: usize, one: &str, many: &str) -> String {
    format!("{n} {}", if n == 1 { one } else { many })
}

/// A number with `digits` decimals, never "-0.00…".
pub(crate) fn fixed(x: f64, digits: usize) -> String {
    let s = format!("{x:.digits$}");
    match s.strip_prefix('-') {
        Some(rest) if rest.bytes().all(|b| b == b'0' || b == b'.') => rest.to_owned(),
        _ => s,
    }
}

/// The information order as a user writes it.
pub(crate) fn order_name(order: InfoOrder) -> &'static str {
    match order {
        InfoOrder::Auto => "auto",
        InfoOrder::G2o => "g2o",
        InfoOrder::Toro => "TORO",
    }
}

/// A basis as its `--basis` value.
pub(crate) fn basis_name(kind: BasisKind) -> String {
    kind.to_possible_value()
        .map_or_else(|| format!("{kind:?}"), |v| v.get_name().to_owned())
}

/// `result`, its error explained by [`explain_solver_error`].
fn explained(path: &Path, order: InfoOrder, result: CliResult) -> CliResult {
    result.map_err(|e| explain_solver_error(path, order, e))
}

/// A failed linear solve explained: when the graph's angle information spans more than double
/// precision can factor, name the two edges (file lines) responsible.
pub(crate) fn explain_solver_error(path: &Path, order: InfoOrder, error: String) -> String {
    if !error.contains("linear system") {
        return error;
    }
    let Ok((graph, summary)) = load_quiet(path, order) else {
        return error;
    };
    let Some(spread) = graph.information_spread() else {
        return error;
    };
    let describe = |e: usize| {
        let edge = graph.edges()[e];
        let line = summary
            .edge_lines
            .get(e)
            .map_or(String::new(), |l| format!(" (line {l})"));
        format!(
            "edge {e}{line}, {}→{}, angle information {:e}",
            edge.from(),
            edge.to(),
            1.0 / edge.sigma2()
        )
    };
    format!(
        "{}: the orientation system cannot be solved in double precision: {} is {:.1e} times {}; \
         ratios above {:e} exceed what f64 resolves (scale the information or drop the edge)",
        path.display(),
        describe(spread.high),
        spread.ratio,
        describe(spread.low),
        so2lin::graph::MAX_INFORMATION_SPREAD
    )
}

/// Read a graph without progress or messages.
fn load_quiet(path: &Path, order: InfoOrder) -> Result<(PoseGraph, ReadSummary), String> {
    let opts = ReadOptions {
        order,
        ..Default::default()
    };
    io::read_graph(path, opts).map_err(|e| e.to_string())
}

fn stats_json(s: &GraphStats, summary: &ReadSummary) -> serde_json::Value {
    json!({
        "nodes": s.nodes,
        "edges": s.edges,
        "odometric_edges": s.odometric_edges,
        "loop_closures": s.loop_closures,
        "cycles": s.cycles,
        "components": s.components,
        "parallel_edges": s.parallel_edges,
        "skipped": summary.skipped,
        "sigma_theta": s.sigma_theta,
        "information_order": summary.order,
        "equivalences": summary.equivalences.len(),
    })
}

fn info(path: &Path, order: InfoOrder, as_json: bool) -> CliResult {
    let (graph, summary) = load_reporting(path, order, false)?;
    let s = graph.stats();
    if as_json {
        println!("{}", stats_json(&s, &summary));
        return Ok(());
    }
    println!("{}", path.display());
    print_stats(&s);
    let order = summary.order.map_or("none (no edges)", order_name);
    println!("  information order     {order}");
    if let Some(skipped) = skipped_lines(&summary) {
        println!("  skipped               {skipped}");
    }
    if !summary.equivalences.is_empty() {
        println!(
            "  EQUIV lines           {} (reported, not merged)",
            summary.equivalences.len()
        );
    }
    Ok(())
}

fn print_stats(s: &GraphStats) {
    println!("  nodes                 {}", s.nodes);
    println!(
        "  edges                 {} ({} odometric, {} loop closures)",
        s.edges, s.odometric_edges, s.loop_closures
    );
    println!("  cycles (m − n + c)    {}", s.cycles);
    println!("  components            {}", s.components);
    println!("  parallel edges        {}", s.parallel_edges);
    if let Some(t) = s.sigma_theta {
        println!(
            "  σ_θ min/median/max    {:.4} / {:.4} / {:.4} rad",
            t.min, t.median, t.max
        );
    }
}

fn simulate(config: &SimConfig, outliers: &OutlierConfig, out: &Path) -> CliResult {
    let world = sim::simulate(config).map_err(|e| e.to_string())?;
    let truth_path = out.with_extension("truth.json");
    let corrupted = sim::inject_outliers(&world.graph, outliers).map_err(|e| e.to_string())?;
    let extra = json!({
        "config": world.config,
        "truth": world.truth,
        "truth_note": "truth.wraps and truth.noise are per genuine edge, in file order with the false edges left out",
    });
    inject::write_corrupted(&corrupted, outliers, out, Some(&truth_path), extra)?;
    let s = corrupted.graph.stats();
    println!(
        "wrote {} ({} nodes, {} edges of which {} false loop closures, {} cycles) and {}",
        out.display(),
        s.nodes,
        s.edges,
        corrupted.false_edges.len(),
        s.cycles,
        truth_path.display()
    );
    Ok(())
}

fn demo(poses: usize, seed: u64, sigma_theta: Option<f64>, log: Option<PathBuf>) -> CliResult {
    let mut config = SimConfig::new(poses, seed);
    config.sigma_theta = sigma_theta.unwrap_or(config.sigma_theta);
    let world = sim::simulate(&config).map_err(|e| e.to_string())?;
    println!(
        "so2lin demo: simulated Manhattan world, {poses} poses, seed {seed}, σ_θ = {} rad",
        config.sigma_theta
    );
    print_stats(&world.graph.stats());
    let wrapped = world.truth.wraps.iter().filter(|&&k| k != 0).count();
    println!(
        "  true wraps            {wrapped} of {} edges wind by a nonzero multiple of 2π",
        world.truth.wraps.len()
    );

    // The paper's batch pipeline on the simulated graph, checked against the ground truth.
    let start = std::time::Instant::now();
    let cfg = BatchConfig::default();
    let r = in_phase("screening", || so2lin::batch::screen(&world.graph, &cfg))
        .map_err(|e| e.to_string())?;
    let est = in_phase("estimating orientations", || {
        screen::estimate_best(&world.graph, &r)
    })?;
    let truth = so2lin::wraps::gamma_of(&r.basis.cycles, &world.truth.wraps);
    let best_is_truth = r.hypotheses.first().is_some_and(|h| r.gamma(h) == truth);
    println!(
        "batch screening ({} basis, family-wise α = {}: each cycle at α/(2ℓ), joint test at α/2; {} dof): {} of {} cycles determined, {} ambiguous, {}, {:.1} ms",
        basis_name(cfg.basis),
        cfg.screening.alpha,
        cfg.screening.dof,
        r.determined,
        r.model.len(),
        r.ambiguous.len(),
        plural(r.hypotheses.len(), "hypothesis", "hypotheses"),
        1e3 * start.elapsed().as_secs_f64()
    );
    println!(
        "  best hypothesis       χ² = {:.2} (p = {:.3}); {} the true cycle integers",
        r.hypotheses.first().map_or(f64::NAN, |h| h.chi2),
        r.hypotheses.first().map_or(f64::NAN, |h| h.p_value),
        if best_is_truth {
            "equals"
        } else {
            "differs from"
        }
    );
    for c in &r.inconsistent {
        println!("  {c}");
    }
    if let Some(words) = second_screening_words(&r, cfg.screening.joint_level()) {
        println!("  {words}");
    }
    println!(
        "  success probability ≥ {:.6} (integer bootstrapping; assumes the declared noise and all {} edges accepted, none rejected)",
        r.success_lower_bound,
        world.graph.edge_count()
    );
    if let Some(e) = est {
        let err: Vec<f64> = world
            .truth
            .poses
            .iter()
            .zip(&e.theta)
            .map(|(p, t)| so2lin::graph::wrap_angle(t - p.theta).abs())
            .collect();
        let rms = (err.iter().map(|x| x * x).sum::<f64>() / err.len() as f64).sqrt();
        let max = err.iter().copied().fold(0.0, f64::max);
        println!("  orientation error     RMS {rms:.4} rad, max {max:.4} rad against the truth");
    }

    // The same world online, edge by edge, recorded to an MCAP log and replayed.
    let path = log
        .unwrap_or_else(|| std::env::temp_dir().join(format!("so2lin-demo-{poses}-{seed}.mcap")));
    let online = OnlineConfig::default();
    let mut est = so2lin::online::OnlineEstimator::new(online).map_err(|e| e.to_string())?;
    let source = format!(
        "so2lin demo --poses {poses} --seed {seed} --sigma-theta {}",
        config.sigma_theta
    );
    let mut rec = so2lin::log::Recorder::create(&path, &online, &source, Default::default())
        .map_err(|e| e.to_string())?;
    let start = std::time::Instant::now();
    // A simulated robot at ten steps a second: the log plays back as the map grows.
    let t0 = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64);
    for (k, e) in world.graph.edges().iter().enumerate() {
        rec.add_edge_at(&mut est, *e, t0 + k as u64 * 100_000_000)
            .map_err(|e| e.to_string())?;
    }
    let stream_ms = 1e3 * start.elapsed().as_secs_f64();
    rec.finish(&mut est).map_err(|e| e.to_string())?;
    let finished = est.finish().map_err(|e| e.to_string())?;
    let same = finished.hypotheses.first().map(|h| finished.gamma(h))
        == r.hypotheses.first().map(|h| r.gamma(h));
    let c = est.counters();
    println!(
        "online estimator (family-wise by α-spending: cycle t at level α_t, Σ α_t ≤ α/2): {} edges in {stream_ms:.1} ms (recording on a writer thread): {} determined, {} ambiguous, {} failed their test; finish() {} the batch answer",
        c.steps,
        c.determined,
        c.ambiguous,
        c.inconsistent,
        if same { "gives" } else { "differs from" }
    );
    let bytes = std::fs::read(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    let log = so2lin::log::read_log(&bytes).map_err(|e| e.to_string())?;
    let replayed = so2lin::log::replay(&log, true).map_err(|e| e.to_string())?;
    println!(
        "  MCAP log              {} ({} kB), replay --verify: {}",
        path.display(),
        bytes.len() / 1000,
        match replayed.divergence {
            None => format!("all {} steps identical", replayed.steps),
            Some(d) => format!("DIVERGES at step {} on {}", d.step, d.channel),
        }
    );

    // Full poses: linear positions from the best orientations, then SE(2) refinement, against
    // the same refinement from dead reckoning; the trajectory drawn next to the log.
    let refine = so2lin::refine::RefineConfig::default();
    let solved = solve::solve_screened(&world.graph, r, 0.0, &refine, false)?;
    if let Some((_, s)) = solved.solutions.first() {
        let odometry = so2lin::estimate::odometry_poses(&world.graph);
        let baseline =
            so2lin::refine::refine(&world.graph, &odometry, &refine).map_err(|e| e.to_string())?;
        println!(
            "poses: SE(2) cost {:.1} (linear) → {:.1} after {} refinement iterations, {} ({:.1} ms); the same refinement from odometry: {:.1} → {:.1}",
            s.cost_linear,
            s.refined.cost(),
            s.refined.iterations,
            s.refined.stop,
            1e3 * s.seconds,
            baseline.costs.first().copied().unwrap_or(f64::NAN),
            baseline.cost()
        );
        let p0 = world.truth.poses[0];
        let n = world.truth.poses.len() as f64;
        let (mut dp, mut dt) = (0.0, 0.0);
        for (p, t) in s.refined.poses.iter().zip(&world.truth.poses) {
            let rel = p0.between(*t);
            dp += (p.x - rel.x).powi(2) + (p.y - rel.y).powi(2);
            dt += so2lin::graph::wrap_angle(p.theta - rel.theta).powi(2);
        }
        println!(
            "  pose error            RMS position {:.3}, RMS heading {:.4} rad against the truth",
            (dp / n).sqrt(),
            (dt / n).sqrt()
        );
    }
    let figure = path.with_extension("svg");
    plot::plot_solved(&world.graph, &solved, &figure, (1000, 1000))?;
    println!("  plot                  {}", figure.display());
    Ok(())
}
