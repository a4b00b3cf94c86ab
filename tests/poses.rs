//! From orientations to poses on simulated worlds with ground truth: linear positions, then
//! SE(2) refinement, against the truth and against the same refinement from dead reckoning.
//!
//! `cargo test --release --test poses -- --nocapture` prints the RMS errors per noise level.

mod common;

use so2lin::batch::{BatchConfig, screen, solve};
use so2lin::estimate::{OrientationEstimator, odometry_poses};
use so2lin::graph::Pose2;
use so2lin::refine::{RefineConfig, cost, refine};
use so2lin::sim::{SimConfig, simulate, wrap_angle};

/// Converged refinement, so that "the same minimum" can be compared to 1e-6.
const CONVERGED: RefineConfig = RefineConfig {
    iterations: 100,
    relative_decrease: 1e-12,
    gradient_tolerance: 1e-9,
    step_tolerance: 1e-12,
    initial_damping: 1e-6,
    residual: so2lin::refine::Residual::Log,
};

/// RMS position and heading error of `x` against the truth expressed in node 0's frame.
fn rms_errors(x: &[Pose2], truth: &[Pose2]) -> (f64, f64) {
    let p0 = truth[0];
    let (mut dp, mut dt) = (0.0, 0.0);
    for (p, t) in x.iter().zip(truth) {
        let rel = p0.between(*t);
        dp += (p.x - rel.x).powi(2) + (p.y - rel.y).powi(2);
        dt += wrap_angle(p.theta - rel.theta).powi(2);
    }
    let n = x.len() as f64;
    ((dp / n).sqrt(), (dt / n).sqrt())
}

#[test]
fn refined_poses_are_within_the_noise_and_never_worse_than_from_odometry() {
    let sigmas = [0.02, 0.05, 0.1];
    let per_sigma = 20;
    let mut worlds = 0;
    let mut odometry_stuck = 0;
    for (s, &sigma) in sigmas.iter().enumerate() {
        let (mut pos2, mut th2, mut n) = (0.0, 0.0, 0.0);
        for seed in 0..per_sigma {
            let mut c = SimConfig::new(300 + 100 * (seed as usize % 5), 1000 * s as u64 + seed);
            c.sigma_theta = sigma;
            c.sigma_xy = sigma;
            let w = simulate(&c).unwrap();
            let g = &w.graph;
            let r = screen(g, &BatchConfig::default()).unwrap();
            let orient = OrientationEstimator::new(g).unwrap();
            let ours = solve(g, &r, &orient, &r.hypotheses[0], &CONVERGED).unwrap();
            let from_odometry = refine(g, &odometry_poses(g), &CONVERGED).unwrap();
            let ours_cost = ours.refined.cost();
            // Never worse than the local-minimum baseline.
            assert!(
                ours_cost <= from_odometry.cost() * (1.0 + 1e-6),
                "σ {sigma} seed {seed}: ours {ours_cost} > from odometry {}",
                from_odometry.cost()
            );
            if ours_cost < from_odometry.cost() * (1.0 - 1e-6) {
                odometry_stuck += 1;
            }
            // Refinement only lowers the cost, and the linear start is already close to it.
            assert!(ours.refined.costs.windows(2).all(|p| p[1] <= p[0]));
            assert!(ours_cost <= ours.cost_linear);
            // Within the noise: the estimate explains the data at least as well as the truth
            // does (the truth's cost is χ² with 3m degrees of freedom), and refining from the
            // truth itself finds no lower minimum.
            let truth: Vec<Pose2> = w
                .truth
                .poses
                .iter()
                .map(|t| w.truth.poses[0].between(*t))
                .collect();
            assert!(ours_cost <= cost(g, &truth), "σ {sigma} seed {seed}");
            let from_truth = refine(g, &truth, &CONVERGED).unwrap();
            assert!(
                ours_cost <= from_truth.cost() * (1.0 + 1e-6),
                "σ {sigma} seed {seed}: ours {ours_cost} vs from the truth {}",
                from_truth.cost()
            );
            let (dp, dt) = rms_errors(&ours.refined.poses, &w.truth.poses);
            // Heading errors of a few σ (they accumulate along the graph), never a wrap.
            assert!(
                dt < 10.0 * sigma,
                "σ {sigma} seed {seed}: RMS heading error {dt}"
            );
            pos2 += dp * dp;
            th2 += dt * dt;
            n += 1.0;
            worlds += 1;
        }
        println!(
            "σ_θ = σ_xy = {sigma}: {per_sigma} worlds, RMS position error {:.4}, RMS heading error {:.4} rad",
            (pos2 / n).sqrt(),
            (th2 / n).sqrt()
        );
    }
    println!("{worlds} worlds; refinement from odometry ended higher in {odometry_stuck}");
    assert!(worlds >= 50);
}

/// The paper's experiment: on the noisy Manhattan worlds, refinement from our linear start
/// ends far below the same refinement from dead reckoning (stuck in a local minimum).
#[test]
#[cfg_attr(
    so2lin_no_datasets,
    ignore = "benchmark datasets not found (set SO2LIN_DATASETS)"
)]
fn noisy_manhattan_worlds_escape_the_odometry_local_minimum() {
    let refine = RefineConfig {
        iterations: 20,
        relative_decrease: 1e-6,
        ..RefineConfig::default()
    };
    for name in ["M3500a.g2o", "M3500b.g2o", "M3500c.g2o"] {
        let Some(path) = common::dataset(name) else {
            return;
        };
        let (g, _) = so2lin::io::read_graph(&path, Default::default()).unwrap();
        let r = screen(&g, &BatchConfig::default()).unwrap();
        let orient = OrientationEstimator::new(&g).unwrap();
        let ours = solve(&g, &r, &orient, &r.hypotheses[0], &refine).unwrap();
        let baseline = refine_from_odometry(&g, &refine);
        println!(
            "{name}: ours {:.1}, from odometry {:.1}",
            ours.refined.cost(),
            baseline
        );
        assert!(ours.refined.cost() < 0.5 * baseline, "{name}");
    }
}

fn refine_from_odometry(g: &so2lin::PoseGraph, config: &RefineConfig) -> f64 {
    refine(g, &odometry_poses(g), config).unwrap().cost()
}
