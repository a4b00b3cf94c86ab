//! `so2lin inject`: false loop closures added to a graph file by the Vertigo protocol
//! (`so2lin::sim::inject_outliers`), written as g2o with a JSON list of the false edges.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use serde_json::json;

use so2lin::io::InfoOrder;
use so2lin::sim::{self, Corrupted, OutlierConfig};

/// Options of the `inject` command.
pub struct InjectArgs<'a> {
    pub file: &'a Path,
    pub order: InfoOrder,
    pub outliers: OutlierConfig,
    pub out: &'a Path,
    pub truth: Option<&'a Path>,
}

/// Write `c.graph` as g2o to `out` (initial poses as read) and, when asked, its false edges as
/// JSON to `truth`, with `extra` merged into the JSON object.
pub fn write_corrupted(
    c: &Corrupted,
    outliers: &OutlierConfig,
    out: &Path,
    truth: Option<&Path>,
    extra: serde_json::Value,
) -> Result<(), String> {
    fn err(p: &Path) -> impl Fn(std::io::Error) -> String + '_ {
        move |e| format!("{}: {e}", p.display())
    }
    let mut w = BufWriter::new(File::create(out).map_err(err(out))?);
    so2lin::io::write_g2o(&mut w, &c.graph, None).map_err(err(out))?;
    w.flush().map_err(err(out))?;
    if let Some(path) = truth {
        let mut v = json!({
            "outliers": outliers,
            "false_edges": c.false_edges,
            "note": "edge = 0-based index in the written file's edge order; from/to = node ids",
        });
        if let (Some(obj), serde_json::Value::Object(more)) = (v.as_object_mut(), extra) {
            obj.extend(more);
        }
        let mut t = BufWriter::new(File::create(path).map_err(err(path))?);
        serde_json::to_writer(&mut t, &v).map_err(|e| format!("{}: {e}", path.display()))?;
        t.flush().map_err(err(path))?;
    }
    Ok(())
}

pub fn run(args: InjectArgs) -> Result<(), String> {
    let (graph, _) = crate::files::load(args.file, args.order)?;
    let c = sim::inject_outliers(&graph, &args.outliers).map_err(|e| e.to_string())?;
    let extra = json!({ "source": args.file.display().to_string() });
    write_corrupted(&c, &args.outliers, args.out, args.truth, extra)?;
    println!(
        "wrote {} ({} nodes, {} edges: {} from {} and {} false loop closures, {:?}, seed {}){}",
        args.out.display(),
        c.graph.node_count(),
        c.graph.edge_count(),
        graph.edge_count(),
        args.file.display(),
        c.false_edges.len(),
        args.outliers.kind,
        args.outliers.seed,
        args.truth
            .map(|t| format!(" and {}", t.display()))
            .unwrap_or_default()
    );
    Ok(())
}
