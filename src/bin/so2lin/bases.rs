//! `so2lin bases`: every cycle basis of a file side by side — the paper's Table I, extended
//! with weights, lengths, integrality and the density of P_γ.
//!
//! Time budget (`--max-seconds S`): each basis gets S seconds of its own, measured from the
//! start of its construction. The exact and approximate MCB check the deadline between
//! shortest-path trees and between de Pina phases, so they stop within one such step after S;
//! the other bases take milliseconds and cannot be interrupted: they are timed and listed with
//! an error if they took longer than S. `seconds` is the construction time only (the
//! integrality check and P_γ are computed afterwards, outside the budget).
//!
//! `density` is `nnz(P_γ) / ℓ²`, the structural nonzeros of the full symmetric matrix (both
//! triangles and the diagonal): the fraction of ordered cycle pairs that share an edge
//! (`(P_γ)_st ≠ 0` unless signed terms cancel exactly, which is not looked for) — the paper's `d`
//! for the whole matrix. It is counted with one bit-packed set of cycles per edge
//! (`m · ℓ / 64` words): row t of the pattern is the union of the sets of its edges, so a
//! fundamental basis whose P_γ has 10⁸ nonzeros (city10000) is counted without storing them.

use std::path::Path;
use std::time::{Duration, Instant};

use serde_json::{Value, json};

use so2lin::cycles::Cycle;
use so2lin::cycles::{BasisKind, CycleBasis, McbError};
use so2lin::io::InfoOrder;

/// Options of the `bases` command.
pub struct BasesArgs<'a> {
    pub file: &'a Path,
    pub order: InfoOrder,
    pub max_seconds: Option<f64>,
    pub k: u32,
    pub json: bool,
}

/// The bases, in the order they are listed.
const KINDS: [BasisKind; 5] = [
    BasisKind::Odometric,
    BasisKind::Mst,
    BasisKind::Incremental,
    BasisKind::Mcb,
    BasisKind::McbApprox,
];

/// One row of the table.
struct Row {
    kind: BasisKind,
    outcome: Result<Stats, String>,
}

struct Stats {
    weight: f64,
    mean: f64,
    max: usize,
    integral: bool,
    density: f64,
    seconds: f64,
}

pub fn run(args: BasesArgs) -> Result<(), String> {
    if let Some(s) = args.max_seconds
        && !(s.is_finite() && s > 0.0)
    {
        return Err(format!(
            "--max-seconds {s}: must be a positive number of seconds"
        ));
    }
    let (graph, _) = crate::files::load(args.file, args.order)?;
    let sigma2: Vec<f64> = graph.edges().iter().map(|e| e.sigma2()).collect();
    let m = graph.edge_count();
    let rows: Vec<Row> = KINDS
        .iter()
        .map(|&kind| {
            let bar = crate::files::phase(format!(
                "building the {} basis",
                crate::report::basis_name(kind)
            ));
            let start = Instant::now();
            let deadline = args.max_seconds.map(|s| start + Duration::from_secs_f64(s));
            let built = match kind {
                BasisKind::McbApprox => CycleBasis::approximate(&graph, args.k, deadline),
                _ => CycleBasis::try_build(&graph, kind, deadline),
            };
            let seconds = start.elapsed().as_secs_f64();
            let outcome = match built {
                Err(McbError::Deadline) => Err(format!(
                    "not computed within the budget of {} s",
                    args.max_seconds.unwrap_or(0.0)
                )),
                Err(e) => Err(e.to_string()),
                Ok(_) if args.max_seconds.is_some_and(|s| seconds > s) => Err(format!(
                    "took {seconds:.3} s, over the budget of {} s",
                    args.max_seconds.unwrap_or(0.0)
                )),
                Ok(b) => {
                    let l = b.cycles.len();
                    Ok(Stats {
                        weight: b.weight(&sigma2),
                        mean: b.mean_length(),
                        max: b.max_length(),
                        integral: b.wrap_solver(m).is_ok_and(|s| s.is_integral()),
                        density: if l == 0 {
                            0.0
                        } else {
                            pattern_nnz(&b.cycles, m) as f64 / (l as f64 * l as f64)
                        },
                        seconds,
                    })
                }
            };
            bar.finish_and_clear();
            Row { kind, outcome }
        })
        .collect();
    let mcb = rows
        .iter()
        .find(|r| r.kind == BasisKind::Mcb)
        .and_then(|r| r.outcome.as_ref().ok())
        .map(|s| s.weight)
        .filter(|&w| w > 0.0);
    if args.json {
        let list: Vec<Value> = rows
            .iter()
            .map(|r| match &r.outcome {
                Err(e) => json!({"kind": r.kind, "error": e}),
                Ok(s) => json!({
                    "kind": r.kind,
                    "weight": s.weight,
                    "ratio_to_mcb": mcb.map(|w| s.weight / w),
                    "mean_cycle_length": s.mean,
                    "max_cycle_length": s.max,
                    "integral": s.integral,
                    "density": s.density,
                    "seconds": s.seconds,
                }),
            })
            .collect();
        println!("{}", json!({ "bases": list }));
        return Ok(());
    }
    println!(
        "{}: {} nodes, {} edges, {} cycles",
        args.file.display(),
        graph.node_count(),
        m,
        graph.stats().cycles
    );
    println!(
        "  {:<12} {:>14} {:>8} {:>9} {:>8} {:>9} {:>9} {:>9}",
        "basis", "weight Σσ²", "÷ MCB", "mean len", "max len", "integral", "density", "seconds"
    );
    for r in &rows {
        let name = serde_json::to_value(r.kind)
            .ok()
            .and_then(|v| v.as_str().map(str::to_owned))
            .unwrap_or_default();
        match &r.outcome {
            Err(e) => println!("  {name:<12} error: {e}"),
            Ok(s) => println!(
                "  {name:<12} {:>14.4} {:>8} {:>9.2} {:>8} {:>9} {:>9.5} {:>9.4}",
                s.weight,
                mcb.map_or("–".to_owned(), |w| format!("{:.4}", s.weight / w)),
                s.mean,
                s.max,
                if s.integral { "yes" } else { "no" },
                s.density,
                s.seconds
            ),
        }
    }
    Ok(())
}

/// Number of ordered pairs `(s, t)` of cycles sharing at least one edge (diagonal included):
/// the structural nonzeros of `P_γ = C P Cᵀ / 4π²`.
fn pattern_nnz(cycles: &[Cycle], edges: usize) -> u64 {
    let words = cycles.len().div_ceil(64);
    let mut through = vec![0u64; edges * words];
    for (t, c) in cycles.iter().enumerate() {
        for term in &c.terms {
            through[term.edge as usize * words + t / 64] |= 1 << (t % 64);
        }
    }
    let mut row = vec![0u64; words];
    let mut nnz = 0;
    for c in cycles {
        row.iter_mut().for_each(|w| *w = 0);
        for term in &c.terms {
            let set = &through[term.edge as usize * words..][..words];
            row.iter_mut().zip(set).for_each(|(r, s)| *r |= s);
        }
        nnz += row.iter().map(|w| u64::from(w.count_ones())).sum::<u64>();
    }
    nnz
}
