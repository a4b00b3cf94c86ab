//! Template for embedding so2lin in a SLAM front end.
//!
//! A simulated robot drives through a Manhattan world. Every time step it produces an
//! odometry measurement and, when it recognises a place it has seen, loop closures; each goes
//! to `OnlineEstimator::add_edge` the moment it exists, and the robot asks for its current
//! heading after every step; while it waits for its next reading (a 10 ms sensor period here),
//! the estimator renews its factor when that is due and fits (`maintain`). The printout is what
//! an operator would watch: loop-closure decisions as they happen, and a periodic status line.
//!
//! ```text
//! cargo run --release --example robot_loop -- [poses] [seed] [sigma_theta]
//! ```
//!
//! In a real front end, replace the simulated `world.graph.edges()` by your measurements
//! (`OnlineEstimator::add_measurement` or `add_measurement_info` validate them), keep the
//! returned `Step` for logging, and read `orientation(node)` / `orientations()` when the back
//! end needs headings. A refused measurement (`Err`) leaves the estimator unchanged.

use so2lin::online::{Decision, OnlineConfig, OnlineEstimator, StepKind};
use so2lin::screening::normalised_residual;
use so2lin::sim::{SimConfig, simulate, wrap_angle};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let poses = args.next().map(|a| a.parse()).transpose()?.unwrap_or(2000);
    let seed = args.next().map(|a| a.parse()).transpose()?.unwrap_or(7);
    let mut config = SimConfig::new(poses, seed);
    if let Some(s) = args.next() {
        config.sigma_theta = s.parse()?;
    }
    let world = simulate(&config)?;
    // Family-wise by default: cycle t is tested at the α-spending level α_t (Σ α_t ≤ α/2),
    // so on data that follow the declared noise no cycle fails its test with probability ≥ 1 − α.
    let online = OnlineConfig::default();
    let mut est = OnlineEstimator::new(online)?;
    // Room for the whole mission, reserved before the first edge (as a real-time loop
    // preallocates): no step then copies a growing array. A front end that does not know its
    // mission's size reserves a bound on it; the room costs address space until it is used.
    est.reserve(world.graph.node_count(), world.graph.edge_count())?;
    println!(
        "robot: {poses} poses, seed {seed}, σ_θ = {} rad; screening family-wise at α = {}",
        config.sigma_theta, online.screening.alpha
    );

    let mut worst_us = 0.0f64;
    // The robot's sensor period: the time it has between two readings. While it waits, the
    // estimator may renew its factor (`maintain`) if that is due and fits in what is left; a
    // renewal costs about as much per node as the last one did.
    let period = std::time::Duration::from_millis(10);
    let mut per_node = 2e-6;
    for edge in world.graph.edges() {
        let t = std::time::Instant::now();
        let step = est.add_edge(*edge)?;
        // The heading of the newest pose, as the front end would ask for it every step.
        let latest = edge.from().max(edge.to());
        let heading = est.orientation(latest)?.unwrap_or(0.0);
        worst_us = worst_us.max(t.elapsed().as_secs_f64() * 1e6);
        let left = period.saturating_sub(t.elapsed()).as_secs_f64();
        if est
            .maintenance_due()
            .is_some_and(|nodes| nodes as f64 * per_node < left)
        {
            let m = std::time::Instant::now();
            let done = est.maintain();
            per_node = m.elapsed().as_secs_f64() / done.variables.max(1) as f64;
        }

        if let StepKind::Cycle(c) = &step.kind {
            match c.decision {
                Decision::Determined => {}
                Decision::Ambiguous => println!(
                    "  loop {}→{}: ambiguous, γ ∈ {}..={} (mean {:.2} ± {:.2})",
                    edge.from(),
                    edge.to(),
                    c.candidates.lo,
                    c.candidates.hi,
                    c.mean,
                    c.sd
                ),
                Decision::Inconsistent => println!(
                    "  loop {}→{}: cycle {} failed its consistency test at level {:.1e}: residual {:.1} σ (a false loop closure, or noise larger than declared)",
                    edge.from(),
                    edge.to(),
                    c.cycle,
                    online.screening.online_level(c.cycle),
                    normalised_residual(so2lin::gamma::Moments {
                        mean: c.mean,
                        var: c.sd * c.sd,
                    })
                ),
            }
        }
        for r in step
            .rescreened
            .iter()
            .filter(|r| r.decision == Decision::Determined)
        {
            println!(
                "  earlier cycle {} now determined (γ = {})",
                r.cycle, r.after.lo
            );
        }
        if edge.is_odometric() && edge.to() % 250 == 0 {
            let c = est.counters();
            let truth = world.truth.poses[latest as usize].theta;
            println!(
                "pose {:>6}: {:>5} loops, {:>5} determined, {:>3} ambiguous | heading {:+.3} rad (truth {:+.3}, error {:+.3}) | P(right) ≥ {:.4} (declared noise; the {} accepted edges, {} quarantined) | worst step {:.0} µs, {} renewals between steps",
                latest,
                c.cycles,
                c.determined,
                c.ambiguous,
                wrap_angle(heading),
                truth,
                wrap_angle(heading - truth),
                est.success_probability_lower_bound(),
                c.steps,
                c.quarantined,
                worst_us,
                c.maintenance_renewals
            );
            worst_us = 0.0;
        }
    }

    let result = est.finish()?;
    println!(
        "finished: {} hypotheses; best χ² = {:.1} (p = {:.3}); {} cycles still ambiguous",
        result.hypotheses.len(),
        result.hypotheses[0].chi2,
        result.hypotheses[0].p_value,
        result.ambiguous.len()
    );
    Ok(())
}
