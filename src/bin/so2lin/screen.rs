//! `so2lin screen`: the batch pipeline on a file, with the paper's tables.

use std::io::Write;
use std::path::Path;
use std::time::Instant;

use serde_json::json;

use so2lin::batch::{self, BatchConfig, BatchResult, Iteration, SecondOutcome};
use so2lin::estimate::OrientationEstimator;
use so2lin::graph::PoseGraph;
use so2lin::io::InfoOrder;

/// Options of the `screen` command.
pub struct ScreenArgs<'a> {
    pub file: &'a Path,
    pub order: InfoOrder,
    pub config: BatchConfig,
    pub orientations: Option<&'a Path>,
    pub json: bool,
}

/// The best hypothesis' orientations and the time it took.
pub struct Estimate {
    pub theta: Vec<f64>,
    /// Node ids of the anchors (θ = 0), one per connected component.
    pub anchors: Vec<u64>,
    pub chi2: f64,
    pub seconds: f64,
}

/// Orientations of the best hypothesis (the first in χ² order).
pub fn estimate_best(graph: &PoseGraph, r: &BatchResult) -> Result<Option<Estimate>, String> {
    let Some(best) = r.hypotheses.first() else {
        return Ok(None);
    };
    let t = Instant::now();
    let k = r.wraps(best).map_err(|e| e.to_string())?;
    let est = OrientationEstimator::new(graph).map_err(|e| e.to_string())?;
    let theta = est.orientations(&k);
    let chi2 = est.cost(&theta, &k);
    let anchors = est.anchors().iter().map(|&v| graph.nodes()[v].id).collect();
    Ok(Some(Estimate {
        theta,
        anchors,
        chi2,
        seconds: t.elapsed().as_secs_f64(),
    }))
}

pub fn run(args: ScreenArgs) -> Result<(), String> {
    let t0 = Instant::now();
    let (graph, _) = crate::files::load(args.file, args.order)?;
    let read_s = t0.elapsed().as_secs_f64();
    let what = format!(
        "screening {} edges, {} cycles",
        graph.edge_count(),
        graph.stats().cycles
    );
    let r = crate::files::in_phase(what, || batch::screen(&graph, &args.config))
        .map_err(|e| e.to_string())?;
    let est = crate::files::in_phase("estimating orientations", || estimate_best(&graph, &r))?;
    let s = args.config.screening;
    let translation = batch::translation_failures(&graph, &r.basis, &s);
    let rejected = crate::files::in_phase("streaming the cycle tests", || {
        batch::quarantined(&graph, s.alpha)
    })
    .map_err(|e| e.to_string())?;
    let total = t0.elapsed().as_secs_f64();
    if let (Some(path), Some(e)) = (args.orientations, &est) {
        write_orientations(path, &graph, &e.theta)?;
    }
    let sigma2: Vec<f64> = graph.edges().iter().map(|e| e.sigma2()).collect();
    let estimate_s = est.as_ref().map_or(0.0, |e| e.seconds);
    if args.json {
        let second = match r.outcome {
            SecondOutcome::TooMany(t) => {
                json!({"too_many": t.found, "cap": t.cap, "visited": t.visited, "limit": t.limit})
            }
            _ => json!(r.second),
        };
        let v = json!({
            "file": args.file.display().to_string(),
            "nodes": graph.node_count(),
            "edges": graph.edge_count(),
            "cycles": r.model.len(),
            "anchors": est.as_ref().map(|e| &e.anchors),
            "config": args.config,
            "basis": {
                "kind": r.basis.kind,
                "weight": r.basis.weight(&sigma2),
                "mean_cycle_length": r.basis.mean_length(),
                "max_cycle_length": r.basis.max_length(),
                "seconds": r.basis_seconds,
                "fallback": r.fallback,
            },
            "first_screening": r.first,
            "second_screening": second,
            "outcome": r.outcome,
            "determined": r.determined,
            "ambiguous": r.ambiguous.len(),
            "inconsistent_cycles": r.inconsistent,
            "translation_failures": translation,
            "rejected_edges": rejected,
            "hypotheses": r.hypotheses.iter().map(|h| json!({"chi2": h.chi2, "p_value": h.p_value})).collect::<Vec<_>>(),
            "best_chi2_from_orientations": est.as_ref().map(|e| e.chi2),
            "success_probability_lower_bound": r.success_lower_bound,
            "seconds": {"read": read_s, "basis": r.basis_seconds, "screening": r.screening_seconds,
                        "estimate": estimate_s, "total": total},
        });
        println!("{v}");
        return Ok(());
    }
    println!(
        "{}: {} nodes, {} edges, {} cycles",
        args.file.display(),
        graph.node_count(),
        graph.edge_count(),
        r.model.len()
    );
    if let Some(e) = est.as_ref().filter(|e| e.anchors.len() > 1) {
        let shown: Vec<u64> = e.anchors.iter().take(10).copied().collect();
        println!(
            "{} connected components: each anchored (θ = 0) at its first node: {:?}{}",
            e.anchors.len(),
            shown,
            if e.anchors.len() > 10 { " …" } else { "" }
        );
    }
    if let Some(f) = &r.fallback {
        println!(
            "basis {} not used ({}): falling back to the incremental basis",
            crate::report::basis_name(f.requested),
            f.reason
        );
    }
    println!(
        "basis {}: weight {:.4}, mean cycle length {:.1}, max {}, {:.4} s",
        crate::report::basis_name(r.basis.kind),
        r.basis.weight(&sigma2),
        r.basis.mean_length(),
        r.basis.max_length(),
        r.basis_seconds
    );
    let ell = r.model.len();
    println!(
        "first screening ({}; {} dof, q = {:.3})",
        if s.family_wise {
            format!(
                "family-wise α = {}: each cycle at α/(2ℓ) = {:.2e}, joint test at α/2",
                s.alpha,
                s.level(ell)
            )
        } else {
            format!("per cycle: each cycle at α = {}", s.alpha)
        },
        s.dof,
        s.quantile(ell)
    );
    print_table(&r.first);
    match r.outcome {
        SecondOutcome::TooMany(_) | SecondOutcome::NoneInside => {
            if let Some(words) = crate::report::second_screening_words(&r, s.joint_level()) {
                println!("{words}");
            }
        }
        SecondOutcome::Complete if r.second.is_empty() => {
            println!(
                "second screening: nothing to fix ({} ambiguous cycles)",
                r.ambiguous.len()
            )
        }
        SecondOutcome::Complete => {
            println!("second screening");
            print_table(&r.second);
        }
    }
    if !r.inconsistent.is_empty() {
        println!(
            "{} cycles failed their consistency test (no integer within q conditional standard deviations of the mean):",
            r.inconsistent.len()
        );
        for c in r.inconsistent.iter().take(10) {
            println!(
                "  {c} ({} edges, first {:?})",
                c.edges.len(),
                &c.edges[..c.edges.len().min(4)]
            );
        }
    }
    println!(
        "determined {} of {} cycles; {} ambiguous; {}",
        r.determined,
        r.model.len(),
        r.ambiguous.len(),
        crate::report::plural(r.hypotheses.len(), "hypothesis", "hypotheses")
    );
    for (k, h) in r.hypotheses.iter().take(10).enumerate() {
        println!(
            "  #{:<3} χ² = {:<12} p = {}",
            k + 1,
            crate::report::fixed(h.chi2, 4),
            crate::report::fixed(h.p_value, 4)
        );
    }
    if !translation.is_empty() {
        println!(
            "{} failed the SE(2) translation closure test (family-wise, each at the per-cycle level):",
            crate::report::plural(translation.len(), "cycle", "cycles")
        );
        for f in translation.iter().take(10) {
            println!("  {f} ({} edges)", f.edges.len());
        }
    }
    crate::report::print_rejected(
        &rejected,
        "fail their cycle tests as they arrive in robot order (`stream` quarantines them, `solve` leaves them out; the screening above includes them)",
    );
    let edges_words = if rejected.is_empty() {
        crate::report::accepted_words(r.edges, 0)
    } else {
        format!(
            "computed with all {} edges, including the {} listed above",
            r.edges,
            rejected.len()
        )
    };
    println!(
        "success probability ≥ {:.6} (integer bootstrapping; assumes the declared noise; {edges_words})",
        r.success_lower_bound
    );
    println!(
        "seconds: read {read_s:.4}, basis {:.4}, screening {:.4}, estimate {estimate_s:.4}, total {total:.4}",
        r.basis_seconds, r.screening_seconds
    );
    Ok(())
}

fn print_table(rows: &[Iteration]) {
    println!("  iter  determined %   density   log10|Γ|   seconds");
    for it in rows {
        println!(
            "  {:>4}  {:>11.2}   {:>7.4}   {:>8}   {:>7.4}",
            it.iteration,
            it.determined_percent,
            it.density,
            crate::report::fixed(it.log10_candidates, 2),
            it.seconds
        );
    }
}

pub fn write_orientations(path: &Path, graph: &PoseGraph, theta: &[f64]) -> Result<(), String> {
    let err = |e: std::io::Error| format!("{}: {e}", path.display());
    let mut w = std::io::BufWriter::new(std::fs::File::create(path).map_err(err)?);
    for (node, t) in graph.nodes().iter().zip(theta) {
        writeln!(w, "{} {:?}", node.id, t).map_err(err)?;
    }
    w.flush().map_err(err)
}
