//! Reading a graph file for a command (progress on a terminal, skipped lines reported), `info`,
//! progress bars and spinners, and a failed solve explained by the edges responsible.

use std::io::{BufReader, IsTerminal};
use std::path::Path;

use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;
use so2lin::graph::{GraphStats, PoseGraph};
use so2lin::io::{self, InfoOrder, ReadOptions, ReadSummary};

use crate::CliResult;
use crate::report::{order_name, plural};

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
fn skipped_lines(summary: &ReadSummary) -> Option<String> {
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

/// `result`, its error explained by [`explain_solver_error`].
pub(crate) fn explained(path: &Path, order: InfoOrder, result: CliResult) -> CliResult {
    result.map_err(|e| explain_solver_error(path, order, e))
}

/// A failed linear solve explained: when the graph's angle information spans more than double
/// precision can factor, name the two edges (file lines) responsible.
fn explain_solver_error(path: &Path, order: InfoOrder, error: String) -> String {
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

pub(crate) fn info(path: &Path, order: InfoOrder, as_json: bool) -> CliResult {
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

pub(crate) fn print_stats(s: &GraphStats) {
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
