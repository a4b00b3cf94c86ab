//! Does the screening keep the true γ, and does it stay quiet on clean data?
//!
//! - The default (family-wise) screening: the surviving set must hold the truth in ≥ 1 − α of
//!   200 simulated worlds (minus a 3σ binomial margin). Per-cycle (the paper's setting): the
//!   rate is printed, not asserted — a per-cycle level promises nothing for thousands of cycles
//!   together. Among worlds whose success-rate bound is ≥ 0.99, the best hypothesis may be
//!   wrong no more often than the bound allows (same margin).
//! - False alarms: on 200 clean simulated worlds, batch and online with the defaults, the
//!   number of worlds where any cycle fails its test, the joint test rejects every vector, or
//!   a cycle is determined wrong — online also: a loop closure quarantined (angle or
//!   translation test at arrival) — must be at most 8 (if the rate were α = 0.01,
//!   P(X ≥ 9) = 2·10⁻⁴; the per-cycle setting on the same worlds is counted to show the test
//!   can fail).
//! - No alarm with the defaults on the clean benchmark files of ≤ 25 000 edges, batch and
//!   online (manhattan.g2o aside: its declared angle information is too tight for its
//!   measurements, χ²/ℓ = 1.59, p < 10⁻³⁰⁰, so the screening's alarm there is right); online,
//!   no loop closure is quarantined, manhattan.g2o included (its quarantine tests in the
//!   noise the data show).

mod common;

use so2lin::batch::{BatchConfig, BatchResult, SecondOutcome, screen};
use so2lin::cycles::BasisKind;
use so2lin::online::{OnlineConfig, OnlineEstimator};
use so2lin::screening::ScreeningConfig;
use so2lin::sim::{SimConfig, simulate};
use so2lin::wraps::gamma_of;

struct Outcome {
    contains: Option<bool>,
    best_is_truth: bool,
    bound: f64,
}

fn judge(r: &BatchResult, truth: &[i64]) -> Outcome {
    let determined_ok =
        (0..truth.len()).all(|i| r.ambiguous.contains(&i) || r.determined_gamma[i] == truth[i]);
    let truth_a: Vec<i64> = r.ambiguous.iter().map(|&i| truth[i]).collect();
    let contains = match r.outcome {
        SecondOutcome::Complete => {
            Some(determined_ok && r.hypotheses.iter().any(|h| h.values == truth_a))
        }
        // The set was not enumerated: its membership cannot be checked by listing.
        _ => None,
    };
    let best_is_truth = determined_ok && r.hypotheses[0].values == truth_a;
    Outcome {
        contains,
        best_is_truth,
        bound: r.success_lower_bound,
    }
}

fn margin(p: f64, n: usize) -> f64 {
    3.0 * (p * (1.0 - p) / n as f64).sqrt()
}

#[test]
fn screening_keeps_the_truth_on_simulated_worlds() {
    let alpha = 0.01;
    let sigmas = [0.01, 0.05, 0.1, 0.2, 0.3];
    let sizes = [200, 500, 1000, 2000];
    let per_level = 40;
    let family = ScreeningConfig::default();
    assert!(family.family_wise && family.alpha == alpha);
    let paper = ScreeningConfig::paper();
    let (mut fw_n, mut fw_in) = (0usize, 0usize);
    let (mut hi_n, mut hi_wrong, mut hi_allowed) = (0usize, 0usize, 0.0f64);
    println!(
        "(not enumerated: the second screening hit its cap or no vector passed the joint test)"
    );
    println!(
        "σ_θ    worlds | family-wise: holds truth  best=truth  not enumerated | paper: holds truth  best=truth  not enumerated | mean bound (family-wise)"
    );
    for (level, &sigma) in sigmas.iter().enumerate() {
        let mut row = [0usize; 6];
        let mut bound_sum = 0.0;
        for w in 0..per_level {
            let seed = 1000 * level as u64 + w as u64;
            let mut c = SimConfig::new(sizes[w % sizes.len()], seed);
            c.sigma_theta = sigma;
            let world = simulate(&c).unwrap();
            let basis = so2lin::cycles::CycleBasis::build(&world.graph, BasisKind::Incremental);
            let truth = gamma_of(&basis.cycles, &world.truth.wraps);
            for (k, s) in [family, paper].into_iter().enumerate() {
                let cfg = BatchConfig {
                    basis: BasisKind::Incremental,
                    screening: s,
                };
                let r = screen(&world.graph, &cfg).unwrap();
                let o = judge(&r, &truth);
                row[2 * k] += usize::from(o.contains.unwrap_or(false));
                row[2 * k + 1] += usize::from(o.best_is_truth);
                if k == 0 {
                    if let Some(inside) = o.contains {
                        fw_n += 1;
                        fw_in += usize::from(inside);
                    } else {
                        row[5] += 1;
                    }
                    bound_sum += o.bound;
                    if o.bound >= 0.99 {
                        hi_n += 1;
                        hi_wrong += usize::from(!o.best_is_truth);
                        hi_allowed += 1.0 - o.bound;
                    }
                } else {
                    row[4] += usize::from(o.contains.is_none());
                }
            }
        }
        println!(
            "{sigma:<5}  {per_level:>6} | {:>24}  {:>10}  {:>14} | {:>18}  {:>10}  {:>14} | {:.4}",
            row[0],
            row[1],
            row[5],
            row[2],
            row[3],
            row[4],
            bound_sum / per_level as f64
        );
    }
    assert!(fw_n >= 190, "too few worlds enumerated completely: {fw_n}");
    let rate = fw_in as f64 / fw_n as f64;
    println!(
        "family-wise: truth kept in {fw_in}/{fw_n} = {rate:.4} (guarantee ≥ {})",
        1.0 - alpha
    );
    assert!(
        rate >= 1.0 - alpha - margin(alpha, fw_n),
        "family-wise coverage {rate}"
    );
    let p_allowed = hi_allowed / hi_n.max(1) as f64;
    let wrong = hi_wrong as f64 / hi_n.max(1) as f64;
    println!(
        "bound ≥ 0.99: {hi_n} worlds, best wrong in {hi_wrong} ({wrong:.4}); bound allows {p_allowed:.4}"
    );
    assert!(hi_n >= 50, "too few worlds with a high bound: {hi_n}");
    assert!(wrong <= p_allowed + margin(p_allowed.max(1.0 / hi_n as f64), hi_n));
}

/// An alarm on clean data: a cycle failed its test, no vector passed the joint test, or a
/// determined cycle (or, when the set was enumerated, the whole surviving set) disagrees with
/// the truth.
fn alarm(r: &BatchResult, truth: &[i64]) -> bool {
    let wrong =
        (0..truth.len()).any(|i| !r.ambiguous.contains(&i) && r.determined_gamma[i] != truth[i]);
    let truth_a: Vec<i64> = r.ambiguous.iter().map(|&i| truth[i]).collect();
    let missed = matches!(r.outcome, SecondOutcome::Complete)
        && !r.hypotheses.iter().any(|h| h.values == truth_a);
    !r.inconsistent.is_empty() || matches!(r.outcome, SecondOutcome::NoneInside) || wrong || missed
}

/// Stream a graph; returns the finished screening, the loop closures quarantined (with
/// quarantine on, the default; off, every edge is added and the basis is the batch one) and
/// the noise scales the quarantine estimated.
fn stream(
    graph: &so2lin::PoseGraph,
    screening: ScreeningConfig,
    quarantine: bool,
) -> (
    BatchResult,
    Vec<so2lin::batch::RejectedEdge>,
    so2lin::online::NoiseScales,
) {
    let mut est = OnlineEstimator::new(OnlineConfig {
        screening,
        quarantine,
        ..OnlineConfig::default()
    })
    .unwrap();
    for e in graph.edges() {
        est.add_edge(*e).unwrap();
    }
    (est.finish().unwrap(), est.rejected(), est.noise_scales())
}

/// An online alarm: a quarantined loop closure, or (nothing quarantined, so the basis is the
/// batch one) an [`alarm`] of the finished screening.
fn online_alarm(graph: &so2lin::PoseGraph, screening: ScreeningConfig, truth: &[i64]) -> bool {
    let (r, rejected, _) = stream(graph, screening, true);
    !rejected.is_empty() || alarm(&r, truth)
}

#[test]
fn defaults_raise_no_more_false_alarms_than_alpha_on_clean_worlds() {
    let worlds = 200;
    let fw = ScreeningConfig::default();
    let per = fw.per_cycle();
    let mut count = [0usize; 4]; // batch fw, online fw, batch per-cycle, online per-cycle
    let mut cycles = 0;
    for w in 0..worlds {
        let mut c = SimConfig::new(300 + (w * 53) % 201, 9000 + w as u64);
        c.sigma_theta = [0.02, 0.05, 0.1, 0.15][w % 4];
        let world = simulate(&c).unwrap();
        let cfg = |screening| BatchConfig {
            basis: BasisKind::Incremental,
            screening,
        };
        let batch = screen(&world.graph, &cfg(fw)).unwrap();
        let truth = gamma_of(&batch.basis.cycles, &world.truth.wraps);
        cycles += truth.len();
        count[0] += usize::from(alarm(&batch, &truth));
        // Online with the defaults: quarantine on (angle and translation tests at arrival).
        count[1] += usize::from(online_alarm(&world.graph, fw, &truth));
        count[2] += usize::from(alarm(&screen(&world.graph, &cfg(per)).unwrap(), &truth));
        // Per-cycle without quarantine: the angle tests' alarms alone (a per-cycle level is
        // not meant to quarantine).
        count[3] += usize::from(alarm(&stream(&world.graph, per, false).0, &truth));
    }
    println!(
        "{worlds} clean worlds ({cycles} cycles): worlds with an alarm — family-wise batch {}, online {}; per-cycle batch {}, online {}",
        count[0], count[1], count[2], count[3]
    );
    assert!(count[0] <= 8 && count[1] <= 8, "{count:?}");
    // The per-cycle level raises about α·ℓ alarms per world: the check above can fail.
    assert!(count[2] > 20 && count[3] > 20, "{count:?}");
}

#[test]
fn defaults_raise_no_alarm_on_clean_datasets() {
    let Some((dir, names)) = common::dataset_names() else {
        return;
    };
    let mut checked = 0;
    for name in names {
        let (graph, _) = so2lin::io::read_graph(dir.join(&name), Default::default()).unwrap();
        if graph.edge_count() > 25_000 {
            continue;
        }
        let batch = screen(&graph, &BatchConfig::default()).unwrap();
        let (online, rejected, scales) = stream(&graph, ScreeningConfig::default(), true);
        if name == "manhattan.g2o" {
            // Its declared angle information is too tight (χ²/ℓ = 1.59): the quarantine tests
            // in the noise the data show (angle scale above 1), and re-tests the loop closures
            // that failed before that scale was established at their arrival's level, so the
            // 5 cycles that fail in the declared noise cost no loop closure; the screening
            // keeps the declared noise and says that cycles fail.
            assert!(rejected.is_empty(), "{name}: quarantined {rejected:?}");
            assert!(scales.angle > 1.2, "{name}: {scales:?}");
            assert!(
                !batch.inconsistent.is_empty(),
                "{name}: declared noise fits?"
            );
            checked += 1;
            continue;
        }
        assert!(rejected.is_empty(), "{name}: quarantined {rejected:?}");
        for (path, r) in [("batch", &batch), ("online", &online)] {
            let failed: Vec<String> = r.inconsistent.iter().map(|c| c.to_string()).collect();
            assert!(failed.is_empty(), "{name} {path}: {failed:?}");
            assert!(
                !matches!(r.outcome, SecondOutcome::NoneInside),
                "{name} {path}: no vector passed the joint test"
            );
        }
        checked += 1;
    }
    assert!(checked >= 17, "only {checked} datasets checked");
}

/// The clean w20000.txt (26 831 edges, beyond the criterion above), streamed as a robot
/// would: its long loops (5 000–10 000 poses between their ends) fail their translation test
/// at 4–6× the threshold when they arrive on paths longer than the graph later offers, and
/// pass on its final graph, so their re-tests must bring them back before the stream ends.
/// Fails when failures that far above the threshold wait for 8× the cycles (164 loop
/// closures held at the end when "far" meant 4×).
#[test]
fn a_clean_streams_long_loops_come_back() {
    let Some(path) = common::dataset("w20000.txt") else {
        return;
    };
    let mut est = OnlineEstimator::new(OnlineConfig {
        estimate_every_step: false,
        ..OnlineConfig::default()
    })
    .unwrap();
    for e in so2lin::online::robot_order(&common::edges_of(&path)) {
        est.add_edge(e).unwrap();
    }
    let held = est.rejected();
    println!(
        "w20000.txt: {} quarantined and re-admitted on the way, {} held at the end",
        est.counters().readmitted,
        held.len()
    );
    assert!(held.is_empty(), "held at the end: {held:?}");
}
