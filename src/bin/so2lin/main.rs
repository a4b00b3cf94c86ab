//! The `so2lin` command-line tool.

use std::process::ExitCode;

use clap::Parser;

mod args;
mod bases;
mod demo;
mod files;
mod inject;
mod plot;
mod replay;
mod report;
mod screen;
mod solve;
mod stream;

use args::{Cli, Command};
use files::{explained, info};
use so2lin::batch::BatchConfig;
use so2lin::online::OnlineConfig;
use so2lin::sim::{OutlierConfig, SimConfig};

/// The tool's allocator: mimalloc, whose threads allocate from their own heaps and free
/// another thread's memory without a lock. With glibc's malloc, the renewal builder (which
/// frees the snapshot the robot's thread copied, and the retired factors) and the robot's
/// thread took turns on the same arena lock: on M3500 the robot's thread slept on it about 70
/// times a stream and the builder about 100, the builder was off its core for most of its
/// builds' wall time, and collections waited for it (`benches/MEASUREMENTS.md`, fortieth
/// session). A program embedding the estimator chooses its own allocator; the crate's docs
/// say why a thread-caching one matters (`so2lin::online`).
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// A one-line error for the user.
type CliResult = Result<(), String>;

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
            demo::simulate(&c, &outliers, &out)
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
        } => demo::demo(poses, seed, sigma_theta, log),
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
            trace,
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
                    trace: trace.as_deref(),
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
