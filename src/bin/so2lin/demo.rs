//! `simulate` (a world to a g2o file with its truth) and `demo` (a world in memory through the
//! batch pipeline, the online estimator with its MCAP log and replay, and the refinement).

use std::path::{Path, PathBuf};

use serde_json::json;
use so2lin::batch::BatchConfig;
use so2lin::online::OnlineConfig;
use so2lin::sim::{self, OutlierConfig, SimConfig};

use crate::files::{in_phase, print_stats};
use crate::report::{basis_name, plural, second_screening_words};
use crate::{CliResult, inject, plot, screen, solve};

pub(crate) fn simulate(config: &SimConfig, outliers: &OutlierConfig, out: &Path) -> CliResult {
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

pub(crate) fn demo(
    poses: usize,
    seed: u64,
    sigma_theta: Option<f64>,
    log: Option<PathBuf>,
) -> CliResult {
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
