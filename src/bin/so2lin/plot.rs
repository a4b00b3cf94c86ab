//! `so2lin plot`: the estimated trajectory of every (or the best) hypothesis, one panel each,
//! like the paper's Fig. 1 — odometry edges grey, loop closures blue, chords of ambiguous
//! cycles orange and of inconsistent cycles red, the refined SE(2) cost in each title.

use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;

use so2lin::batch::BatchResult;
use so2lin::graph::PoseGraph;
use so2lin::io::InfoOrder;
use so2lin::online::OnlineEstimator;

use crate::solve::{Solved, solve_graph, solve_screened};

/// Options of the `plot` command.
pub struct PlotArgs<'a> {
    pub input: &'a Path,
    pub out: &'a Path,
    pub order: InfoOrder,
    pub config: so2lin::batch::BatchConfig,
    pub refine: so2lin::refine::RefineConfig,
    pub all_hypotheses: bool,
    pub size: (u32, u32),
}

/// One panel: positions, the edges by style, a title.
struct Panel {
    pos: Vec<(f64, f64)>,
    segments: [Vec<(usize, usize)>; 4],
    title: String,
}

const STYLES: [(RGBColor, f64, u32); 4] = [
    (RGBColor(150, 150, 150), 1.0, 1),
    (RGBColor(40, 90, 230), 0.5, 1),
    (RGBColor(245, 140, 0), 1.0, 3),
    (RGBColor(220, 20, 20), 1.0, 3),
];

/// Where a sans-serif TrueType font is usually found (the bitmap and SVG layouts need its
/// metrics); `SO2LIN_FONT` overrides.
const FONT_PATHS: [&str; 6] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/System/Library/Fonts/Supplemental/Arial.ttf",
    "C:\\Windows\\Fonts\\arial.ttf",
];

/// Register a system font once; false when none was found (plots then carry no text).
fn register_font() -> bool {
    static FOUND: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *FOUND.get_or_init(|| {
        let env = std::env::var("SO2LIN_FONT").ok();
        let candidates = env.iter().map(String::as_str).chain(FONT_PATHS);
        for path in candidates {
            if let Ok(bytes) = std::fs::read(path) {
                // plotters keeps fonts for the whole process.
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                if plotters::style::register_font("sans-serif", FontStyle::Normal, bytes).is_ok() {
                    return true;
                }
            }
        }
        false
    })
}

pub fn run(args: PlotArgs) -> Result<(), String> {
    let head = is_mcap(args.input).map_err(|e| format!("{}: {e}", args.input.display()))?;
    let (graph, solved) = if head {
        crate::files::in_phase("replaying the log and solving", || {
            from_log(args.input, &args.refine, args.all_hypotheses)
        })?
    } else {
        let (graph, _) = crate::files::load(args.input, args.order)?;
        let solved = crate::files::in_phase("screening and solving", || {
            solve_graph(&graph, &args.config, &args.refine, args.all_hypotheses)
        })?;
        (graph, solved)
    };
    let n = crate::files::in_phase("drawing", || {
        plot_solved(&graph, &solved, args.out, args.size)
    })?;
    println!(
        "wrote {} ({n} panel{}, {}×{})",
        args.out.display(),
        if n == 1 { "" } else { "s" },
        args.size.0,
        args.size.1
    );
    Ok(())
}

/// Draw the solved hypotheses of a graph into `out` (.svg or .png); returns the panel count.
pub fn plot_solved(
    graph: &PoseGraph,
    solved: &Solved,
    out: &Path,
    size: (u32, u32),
) -> Result<usize, String> {
    let panels = panels(graph, solved);
    if panels.is_empty() {
        return Err("no hypothesis to plot".into());
    }
    render(out, size, &panels)?;
    Ok(panels.len())
}

/// Whether the file starts with the MCAP magic (only its first bytes are read).
fn is_mcap(path: &Path) -> std::io::Result<bool> {
    use std::io::Read;
    let mut head = Vec::with_capacity(mcap::MAGIC.len());
    std::fs::File::open(path)?
        .take(mcap::MAGIC.len() as u64)
        .read_to_end(&mut head)?;
    Ok(head == mcap::MAGIC)
}

/// Replay a log's edges through the online estimator and screen its final state.
fn from_log(
    path: &Path,
    refine: &so2lin::refine::RefineConfig,
    all: bool,
) -> Result<(PoseGraph, Solved), String> {
    let err = |e: String| format!("{}: {e}", path.display());
    let bytes = std::fs::read(path).map_err(|e| err(e.to_string()))?;
    let log = so2lin::log::read_log(&bytes).map_err(|e| err(e.to_string()))?;
    let mut est = OnlineEstimator::new(log.config().map_err(|e| err(e.to_string()))?)
        .map_err(|e| err(e.to_string()))?;
    for e in &log.edges {
        est.add_edge(*e).map_err(|e| err(e.to_string()))?;
    }
    let t = std::time::Instant::now();
    let screening: BatchResult = est.finish().map_err(|e| err(e.to_string()))?;
    let graph = est.graph().clone();
    let solved = solve_screened(&graph, screening, t.elapsed().as_secs_f64(), refine, all)?;
    Ok((graph, solved))
}

fn panels(graph: &PoseGraph, solved: &Solved) -> Vec<Panel> {
    let r = &solved.screening;
    // Style of every edge: odometry 0, loop closure 1, chord of an ambiguous cycle 2, of an
    // inconsistent cycle 3.
    let mut style: Vec<usize> = graph
        .edges()
        .iter()
        .map(|e| if e.is_odometric() { 0 } else { 1 })
        .collect();
    let chord = |c: usize| r.basis.cycles[c].chord() as usize;
    for &c in &r.ambiguous {
        style[chord(c)] = 2;
    }
    for c in &r.inconsistent {
        style[chord(c.cycle)] = 3;
    }
    let mut segments: [Vec<(usize, usize)>; 4] = Default::default();
    for (&st, &ends) in style.iter().zip(graph.endpoints()) {
        segments[st].push(ends);
    }
    solved
        .solutions
        .iter()
        .map(|(i, s)| Panel {
            pos: s.refined.poses.iter().map(|p| (p.x, p.y)).collect(),
            segments: segments.clone(),
            title: format!(
                "hypothesis {i}: cost {:.4e} (χ²θ {:.1})",
                s.refined.cost(),
                s.chi2_orientation
            ),
        })
        .collect()
}

fn render(out: &Path, size: (u32, u32), panels: &[Panel]) -> Result<(), String> {
    let font = register_font();
    if !font {
        eprintln!("note: no TrueType font found (set SO2LIN_FONT); the plot has no titles");
    }
    let ext = out
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    let err = |e: String| format!("{}: {e}", out.display());
    match ext.as_deref() {
        Some("svg") => draw(SVGBackend::new(out, size).into_drawing_area(), panels, font),
        Some("png") => draw(
            BitMapBackend::new(out, size).into_drawing_area(),
            panels,
            font,
        ),
        _ => Err("the output must end in .svg or .png".into()),
    }
    .map_err(err)
}

fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    panels: &[Panel],
    font: bool,
) -> Result<(), String> {
    let e = |x: DrawingAreaErrorKind<DB::ErrorType>| x.to_string();
    root.fill(&WHITE).map_err(e)?;
    let cols = (panels.len() as f64).sqrt().ceil() as usize;
    let rows = panels.len().div_ceil(cols);
    let areas = root.split_evenly((rows, cols));
    for (panel, area) in panels.iter().zip(&areas) {
        let (w, h) = area.dim_in_pixel();
        let (x, y) = equal_aspect(&panel.pos, f64::from(w), f64::from(h).max(1.0) - 30.0);
        let mut builder = ChartBuilder::on(area);
        builder.margin(8);
        if font {
            builder.caption(&panel.title, ("sans-serif", 16));
        }
        let mut chart = builder.build_cartesian_2d(x, y).map_err(e)?;
        for (segments, &(color, alpha, width)) in panel.segments.iter().zip(&STYLES) {
            let style = color.mix(alpha).stroke_width(width);
            chart
                .draw_series(
                    segments
                        .iter()
                        .map(|&(a, b)| PathElement::new(vec![panel.pos[a], panel.pos[b]], style)),
                )
                .map_err(e)?;
        }
    }
    root.present().map_err(e)
}

/// Axis ranges holding every position with equal scales on both axes.
fn equal_aspect(
    pos: &[(f64, f64)],
    w: f64,
    h: f64,
) -> (std::ops::Range<f64>, std::ops::Range<f64>) {
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in pos {
        (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
    }
    if x0 > x1 {
        return (-1.0..1.0, -1.0..1.0);
    }
    let scale = ((x1 - x0) / w.max(1.0))
        .max((y1 - y0) / h.max(1.0))
        .max(1e-9)
        * 1.04;
    let (cx, cy) = (0.5 * (x0 + x1), 0.5 * (y0 + y1));
    let (hw, hh) = (0.5 * scale * w, 0.5 * scale * h);
    (cx - hw..cx + hw, cy - hh..cy + hh)
}
