//! `so2lin solve`: screening, orientations, positions and SE(2) refinement of a file.

use std::io::Write;
use std::path::Path;
use std::time::Instant;

use serde_json::json;

use so2lin::batch::{self, BatchConfig, BatchResult, RobustConfig, Solution};
use so2lin::estimate::{OrientationEstimator, odometry_poses};
use so2lin::graph::PoseGraph;
use so2lin::io::InfoOrder;
use so2lin::refine::{self, RefineConfig, Refined};

/// Options of the `solve` command.
pub struct SolveArgs<'a> {
    pub file: &'a Path,
    pub order: InfoOrder,
    pub config: BatchConfig,
    pub refine: RefineConfig,
    pub all_hypotheses: bool,
    /// The DCS kernel on loop closures (None: plain least squares).
    pub robust: Option<RobustConfig>,
    pub odometry: bool,
    pub out: Option<&'a Path>,
    pub json: bool,
}

/// Every requested hypothesis solved, best (lowest refined cost) first, with its index in the
/// screening's χ² order.
pub struct Solved {
    pub screening: BatchResult,
    pub solutions: Vec<(usize, Solution)>,
    pub screen_seconds: f64,
}

/// Screen a graph and solve its best hypothesis, or all of them.
pub fn solve_graph(
    graph: &PoseGraph,
    config: &BatchConfig,
    refine: &RefineConfig,
    all: bool,
) -> Result<Solved, String> {
    solve_graph_with(graph, config, refine, all, None)
}

/// [`solve_graph`], with the robust kernel when `robust` is set.
pub fn solve_graph_with(
    graph: &PoseGraph,
    config: &BatchConfig,
    refine: &RefineConfig,
    all: bool,
    robust: Option<&RobustConfig>,
) -> Result<Solved, String> {
    let t = Instant::now();
    let screening = batch::screen(graph, config).map_err(|e| e.to_string())?;
    solve_screened_with(
        graph,
        screening,
        t.elapsed().as_secs_f64(),
        refine,
        all,
        robust,
    )
}

/// Solve the best hypothesis of a screening, or all of them.
pub fn solve_screened(
    graph: &PoseGraph,
    screening: BatchResult,
    screen_seconds: f64,
    refine: &RefineConfig,
    all: bool,
) -> Result<Solved, String> {
    solve_screened_with(graph, screening, screen_seconds, refine, all, None)
}

/// [`solve_screened`], with the robust kernel when `robust` is set.
pub fn solve_screened_with(
    graph: &PoseGraph,
    screening: BatchResult,
    screen_seconds: f64,
    refine: &RefineConfig,
    all: bool,
    robust: Option<&RobustConfig>,
) -> Result<Solved, String> {
    let orient = OrientationEstimator::new(graph).map_err(|e| e.to_string())?;
    let take = if all { screening.hypotheses.len() } else { 1 };
    let mut solutions = Vec::with_capacity(take);
    for (i, h) in screening.hypotheses.iter().take(take).enumerate() {
        let s = match robust {
            Some(rc) => batch::solve_robust(graph, &screening, &orient, h, refine, rc),
            None => batch::solve(graph, &screening, &orient, h, refine),
        }
        .map_err(|e| e.to_string())?;
        solutions.push((i, s));
    }
    solutions.sort_by(|a, b| a.1.refined.cost().total_cmp(&b.1.refined.cost()));
    Ok(Solved {
        screening,
        solutions,
        screen_seconds,
    })
}

pub fn run(args: SolveArgs) -> Result<(), String> {
    let t0 = Instant::now();
    let (graph, _) = crate::files::load(args.file, args.order)?;
    let read_seconds = t0.elapsed().as_secs_f64();
    let solved = solve_graph_with(
        &graph,
        &args.config,
        &args.refine,
        args.all_hypotheses,
        args.robust.as_ref(),
    )?;
    let total = t0.elapsed().as_secs_f64();
    let baseline = args.odometry.then(|| {
        let t = Instant::now();
        let start = odometry_poses(&graph);
        refine::refine(&graph, &start, &args.refine).map(|r| (r, t.elapsed().as_secs_f64()))
    });
    let baseline = baseline.transpose().map_err(|e| e.to_string())?;
    if let (Some(path), Some((_, best))) = (args.out, solved.solutions.first()) {
        let err = |e: std::io::Error| format!("{}: {e}", path.display());
        let file = std::fs::File::create(path).map_err(err)?;
        let mut w = std::io::BufWriter::new(file);
        so2lin::io::write_g2o(&mut w, &graph, Some(&best.refined.poses)).map_err(err)?;
        w.flush().map_err(err)?;
    }
    let r = &solved.screening;
    if args.json {
        let hyps: Vec<_> = solved
            .solutions
            .iter()
            .map(|(i, s)| {
                json!({
                    "index": i,
                    "chi2_orientation": s.chi2_orientation,
                    "cost_linear": s.cost_linear,
                    "cost_refined": s.refined.cost(),
                    "cost_refined_all_edges": args.refine.residual.cost(&graph, &s.refined.poses),
                    "rejected_edges": s.rejected,
                    "noise_scales": s.noise_scales,
                    "drop_scale": s.drop_scale,
                    "refine_costs": s.refined.costs,
                    "iterations": s.refined.iterations,
                    "converged": s.refined.converged,
                    "stop": s.refined.stop,
                    "refinement": s.refined.stop.to_string(),
                    "seconds": s.seconds,
                })
            })
            .collect();
        let v = json!({
            "file": args.file.display().to_string(),
            "nodes": graph.node_count(),
            "edges": graph.edge_count(),
            "basis": r.basis.kind,
            "hypotheses_screened": r.hypotheses.len(),
            "outcome": r.outcome,
            "hypotheses": hyps,
            "best": solved.solutions.first().map(|(i, _)| i),
            "odometry": baseline.as_ref().map(|(b, s)| odometry_json(b, *s)),
            "refine": args.refine,
            "robust": args.robust,
            "read_seconds": read_seconds,
            "screen_seconds": solved.screen_seconds,
            "total_seconds": total,
        });
        println!("{v}");
        return Ok(());
    }
    println!(
        "{}: {} nodes, {} edges; {:?} basis, {} after screening ({:.1} ms read, {:.1} ms screening)",
        args.file.display(),
        graph.node_count(),
        graph.edge_count(),
        r.basis.kind,
        crate::report::plural(r.hypotheses.len(), "hypothesis", "hypotheses"),
        1e3 * read_seconds,
        1e3 * solved.screen_seconds
    );
    if let Some(words) =
        crate::report::second_screening_words(r, args.config.screening.joint_level())
    {
        println!("{words}");
    }
    println!(
        "costs: Σ_e r_eᵀ Ω_e r_e with r_e the {} of Z⁻¹ X_i⁻¹ X_j",
        match args.refine.residual {
            so2lin::refine::Residual::Log =>
                "SE(2) logarithm (GTSAM's error; --residual t2v for g2o's)",
            so2lin::refine::Residual::T2v => "t2v (g2o's EdgeSE2 error, its χ²)",
        }
    );
    println!(
        "{:>4} {:>14} {:>16} {:>16} {:>6} {:>9}  refinement",
        "hyp", "χ² orient.", "cost linear", "cost refined", "iters", "ms"
    );
    for (i, s) in &solved.solutions {
        println!(
            "{:>4} {:>14.4} {:>16.6e} {:>16.6e} {:>6} {:>9.1}  {}",
            i,
            s.chi2_orientation,
            s.cost_linear,
            s.refined.cost(),
            s.refined.iterations,
            1e3 * s.seconds,
            s.refined.stop
        );
    }
    if let Some((i, best)) = solved.solutions.first() {
        println!("best: hypothesis {i} (lowest refined cost)");
        match (&args.robust, best.rejected.len()) {
            (None, _) => println!("robust kernel: off (plain least squares on every edge)"),
            (Some(_), 0) => {
                println!("robust kernel (DCS on loop closures): no loop closure rejected")
            }
            (Some(rc), n) => {
                let by = |tests: &[&str]| {
                    (best.rejected.iter())
                        .filter(|r| tests.contains(&r.test))
                        .count()
                };
                println!(
                    "robust kernel (DCS on loop closures): {n} rejected ({} by the online quarantine's cycle tests, {} by the SE(2) χ²_e test, {} by the leave-out test; family-wise α = {}); the refined cost is over the other edges, and the screening's success bound and p-values were computed with these edges included",
                    by(&["cycle_angle", "cycle_translation"]),
                    by(&["se2_chi2"]),
                    by(&["leave_out"]),
                    rc.alpha
                );
                crate::report::print_rejected(&best.rejected, "rejected");
            }
        }
        if let Some(scales) = &best.noise_scales {
            crate::report::print_noise_scales(scales);
        }
        if let Some(d) = best.drop_scale {
            let quarantine = best.noise_scales.map_or(1.0, |s| s.larger());
            println!(
                "leave-out test: the loop closures' cost drops show a noise scale of {d:.3}; tested at {:.3} (the smaller of it and the quarantine's larger scale, {quarantine:.3})",
                d.min(quarantine)
            );
        }
    }
    if let Some((b, s)) = &baseline {
        println!(
            "odometry start, same refinement: cost {:.6e} → {:.6e} ({} iterations, {:.1} ms, {})",
            b.costs.first().copied().unwrap_or(f64::NAN),
            b.cost(),
            b.iterations,
            1e3 * s,
            b.stop
        );
    }
    println!("total {:.1} ms", 1e3 * total);
    Ok(())
}

fn odometry_json(b: &Refined, seconds: f64) -> serde_json::Value {
    json!({
        "cost_initial": b.costs.first(),
        "cost_refined": b.cost(),
        "refine_costs": b.costs,
        "iterations": b.iterations,
        "converged": b.converged,
        "stop": b.stop,
        "seconds": seconds,
    })
}
