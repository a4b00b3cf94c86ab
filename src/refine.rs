//! Refinement of a pose graph on SE(2): Levenberg–Marquardt on the full cost
//!
//! ```text
//! F(x) = Σ_e r_eᵀ Ω_e r_e,     E_e = Z_e⁻¹ (X_i⁻¹ X_j) = (e_t, e_θ),
//! e_t = R_zᵀ (R_iᵀ (t_j − t_i) − t_z),   e_θ = wrap(θ_j − θ_i − θ_z),
//! ∂e_t/∂t_j = R_zᵀR_iᵀ = −∂e_t/∂t_i,   ∂e_t/∂θ_i = R_zᵀ (dR_iᵀ/dθ) (t_j − t_i),   ∂e_θ/∂θ_j = 1 = −∂e_θ/∂θ_i.
//! ```
//!
//! The residual `r_e` of an edge is one of two charts of the error transform `E_e`
//! ([`Residual`]):
//!
//! - **`Log`** (the default): the SE(2) logarithm, the geodesic error GTSAM's `BetweenFactor<Pose2>`
//!   uses. With `h = e_θ/2` and `a = h cot h` (→ 1 − e_θ²/12 as e_θ → 0),
//!   `r = (a e_x + h e_y, −h e_x + a e_y, e_θ)`; its Jacobian is the chain rule through
//!   `∂r/∂(e_x, e_y, e_θ) = [[a, h, a′e_x + e_y/2], [−h, a, −e_x/2 + a′e_y], [0, 0, 1]]`,
//!   `a′ = (cot h − h / sin²h) / 2`.
//! - **`T2v`**: `r = (e_t, e_θ)` itself, g2o's `EdgeSE2` error (F is then g2o's χ²).
//!
//! The two agree to first order and differ at second order in the error, so on strongly
//! anisotropic information their minima are different points.
//!
//! With `H = Σ JᵀΩJ` and `g = Σ JᵀΩe` (so ∇F = 2g), each iteration solves
//! `(H + λ diag H) h = −g` ([`crate::estimate`]'s sparse normal equations, one anchor pose per
//! component held fixed) and compares the actual decrease with the decrease the quadratic
//! model predicts, `L(0) − L(h) = −2gᵀh − hᵀHh`, through the **gain ratio**
//! `ρ = (F(x) − F(x + h)) / (L(0) − L(h))`. **Nielsen's damping rule** (Madsen, Nielsen &
//! Tingleff, *Methods for non-linear least squares problems*, 2004, §3.2): if ρ > 0 the step is
//! taken and `λ ← λ · max(1/3, 1 − (2ρ − 1)³)`, `ν ← 2`; otherwise it is refused and
//! `λ ← λ · ν`, `ν ← 2ν`. λ starts at [`RefineConfig::initial_damping`].
//!
//! **Stopping** ([`Stop`]): converged when `‖g‖∞ ≤ gradient_tolerance` (the cost is stationary),
//! when a taken step lowers F by less than `relative_decrease · F`, or when a taken step is
//! below `step_tolerance · (‖x‖∞ + step_tolerance)`; not converged when `iterations` linear
//! solves are spent, or when no step lowers F even at a damping of 10¹⁶ (stalled). The result
//! says which ([`Refined::stop`]).
//!
//! Written here, compactly, rather than pulling in a factor-graph framework: the whole method
//! is the Jacobian above plus the shared sparse Cholesky.

use crate::estimate::{Anchored, EstimateError, NormalEquations, solve};
use crate::graph::wrap_angle;
use crate::graph::{Pose2, PoseGraph};

/// Which chart of an edge's error transform `Z⁻¹ X_i⁻¹ X_j` the cost uses (module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Residual {
    /// The SE(2) logarithm (geodesic error; GTSAM's `BetweenFactor<Pose2>`). The default.
    #[default]
    Log,
    /// `t2v`: translation and wrapped angle of the error transform (g2o's `EdgeSE2`).
    T2v,
}

impl Residual {
    /// `Σ_e r_eᵀ Ω_e r_e` of poses `x` (one per node, dense index order) in this chart.
    pub fn cost(self, graph: &PoseGraph, x: &[Pose2]) -> f64 {
        self.edge_costs(graph, x).sum()
    }

    /// Every edge's term `r_eᵀ Ω_e r_e` of [`Residual::cost`], in edge order.
    pub fn edge_costs<'a>(
        self,
        graph: &'a PoseGraph,
        x: &'a [Pose2],
    ) -> impl Iterator<Item = f64> + 'a {
        graph
            .edges()
            .iter()
            .zip(graph.endpoints())
            .map(move |(edge, &(a, b))| {
                let e = self.error(edge.measurement(), x[a], x[b]);
                let o = edge.information().matrix();
                (0..3)
                    .map(|i| (0..3).map(|j| e[i] * o[i][j] * e[j]).sum::<f64>())
                    .sum::<f64>()
            })
    }

    /// The residual of one edge (no Jacobians).
    fn error(self, z: Pose2, xi: Pose2, xj: Pose2) -> [f64; 3] {
        let (e, _, _) = t2v_linearised(z, xi, xj);
        match self {
            Residual::T2v => e,
            Residual::Log => log_chart(e).0,
        }
    }

    /// The residual of one edge and its Jacobians w.r.t. `(x_i, y_i, θ_i)` and `(x_j, y_j, θ_j)`.
    fn linearise(self, z: Pose2, xi: Pose2, xj: Pose2) -> ([f64; 3], Block, Block) {
        let (e, ja, jb) = t2v_linearised(z, xi, xj);
        match self {
            Residual::T2v => (e, ja, jb),
            Residual::Log => {
                let (r, d) = log_chart(e);
                (r, mul(&d, &ja), mul(&d, &jb))
            }
        }
    }
}

impl std::fmt::Display for Residual {
    /// `log` or `t2v`, as the CLI spells it.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Residual::Log => "log",
            Residual::T2v => "t2v",
        })
    }
}

/// When to stop (module docs). Defaults ([`RefineConfig::default`]): the SE(2)-logarithm
/// residual, at most 100 iterations, converged when a step lowers the cost by less than 1e-10
/// of it, when `‖g‖∞ ≤ 1e-8`, or when a step is below 1e-12 relative to the poses; initial
/// damping 1e-6. Deserialised fields left out take these defaults.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct RefineConfig {
    /// At most this many linear solves (taken and refused steps). Default 100.
    pub iterations: usize,
    /// Converged once a taken step lowers the cost by less than this fraction of it.
    /// Default 1e-10.
    pub relative_decrease: f64,
    /// Converged once the gradient `g = Σ JᵀΩe` has `‖g‖∞` at most this. Default 1e-8.
    pub gradient_tolerance: f64,
    /// Converged once a taken step `h` has `‖h‖∞ ≤ step_tolerance · (‖x‖∞ + step_tolerance)`.
    /// Default 1e-12.
    pub step_tolerance: f64,
    /// Initial damping λ (relative to diag H). Default 1e-6: nearly a Gauss–Newton step first.
    pub initial_damping: f64,
    /// The chart of each edge's error ([`Residual`]). Default: the SE(2) logarithm.
    pub residual: Residual,
}

impl Default for RefineConfig {
    fn default() -> Self {
        Self {
            iterations: 100,
            relative_decrease: 1e-10,
            gradient_tolerance: 1e-8,
            step_tolerance: 1e-12,
            initial_damping: 1e-6,
            residual: Residual::Log,
        }
    }
}

impl RefineConfig {
    /// The defaults with a different iteration cap.
    pub fn with_iterations(iterations: usize) -> Self {
        Self {
            iterations,
            ..Self::default()
        }
    }
}

/// Why a refinement stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Stop {
    /// Converged: `‖g‖∞ ≤ gradient_tolerance`.
    Gradient,
    /// Converged: a taken step lowered the cost by less than `relative_decrease`.
    RelativeDecrease,
    /// Converged: a taken step was below `step_tolerance`.
    Step,
    /// Converged trivially: no unknowns (every node is an anchor).
    NothingToRefine,
    /// Not converged: the iteration cap was reached.
    IterationCap,
    /// Not converged: no step lowered the cost even with damping above 10¹⁶.
    Stalled,
}

impl Stop {
    /// Whether this is a convergence criterion.
    pub fn converged(self) -> bool {
        matches!(
            self,
            Stop::Gradient | Stop::RelativeDecrease | Stop::Step | Stop::NothingToRefine
        )
    }
}

impl std::fmt::Display for Stop {
    /// `converged (gradient)` or `not converged (iteration cap)`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (ok, why) = match self {
            Stop::Gradient => (true, "gradient below tolerance"),
            Stop::RelativeDecrease => (true, "relative decrease below tolerance"),
            Stop::Step => (true, "step below tolerance"),
            Stop::NothingToRefine => (true, "nothing to refine"),
            Stop::IterationCap => (false, "iteration cap reached"),
            Stop::Stalled => (false, "no step lowers the cost"),
        };
        let head = if ok { "converged" } else { "not converged" };
        write!(f, "{head} ({why})")
    }
}

/// What a refinement did.
#[derive(Clone, Debug, PartialEq)]
pub struct Refined {
    /// The refined poses.
    pub poses: Vec<Pose2>,
    /// The cost before refining, then after every taken step.
    pub costs: Vec<f64>,
    /// Linear solves made (taken and refused steps).
    pub iterations: usize,
    /// Whether it stopped on a convergence criterion ([`Stop::converged`]).
    pub converged: bool,
    /// Why it stopped.
    pub stop: Stop,
    /// `‖g‖∞` at the returned poses (NaN when it was not evaluated there: after the last
    /// taken step of a run stopped by the cap or the step/decrease criteria).
    pub gradient: f64,
}

impl Refined {
    /// The final cost.
    pub fn cost(&self) -> f64 {
        self.costs.last().copied().unwrap_or(0.0)
    }
}

/// A 3 × 3 Jacobian block, row-major.
type Block = [[f64; 3]; 3];

/// `a b` for 3 × 3 blocks.
fn mul(a: &Block, b: &Block) -> Block {
    std::array::from_fn(|r| std::array::from_fn(|c| (0..3).map(|k| a[r][k] * b[k][c]).sum()))
}

/// The SE(2) logarithm of an error transform given as `(e_x, e_y, e_θ)` (e_θ wrapped), and its
/// derivative in `(e_x, e_y, e_θ)` (module docs).
fn log_chart(e: [f64; 3]) -> ([f64; 3], Block) {
    let [ex, ey, th] = e;
    let h = 0.5 * th;
    // a = h cot h and a′ = da/dθ; below |θ| = 1e-3 their series (error < 1e-20) avoid the
    // cancellation of cot h − h / sin²h.
    let (a, da) = if th.abs() < 1e-3 {
        let t2 = th * th;
        (
            1.0 - t2 / 12.0 - t2 * t2 / 720.0,
            -th / 6.0 - t2 * th / 180.0,
        )
    } else {
        let (s, c) = libm::sincos(h);
        (h * c / s, 0.5 * (c / s - h / (s * s)))
    };
    (
        [a * ex + h * ey, -h * ex + a * ey, th],
        [
            [a, h, da * ex + 0.5 * ey],
            [-h, a, -0.5 * ex + da * ey],
            [0.0, 0.0, 1.0],
        ],
    )
}

/// The t2v error of one edge and its Jacobians w.r.t. `(x_i, y_i, θ_i)` and `(x_j, y_j, θ_j)`.
fn t2v_linearised(z: Pose2, xi: Pose2, xj: Pose2) -> ([f64; 3], Block, Block) {
    let (si, ci) = libm::sincos(xi.theta);
    let (sz, cz) = libm::sincos(z.theta);
    let (dx, dy) = (xj.x - xi.x, xj.y - xi.y);
    // R_iᵀ d and its derivative in θ_i.
    let (lx, ly) = (ci * dx + si * dy, -si * dx + ci * dy);
    let (dlx, dly) = (-si * dx + ci * dy, -ci * dx - si * dy);
    let (ux, uy) = (lx - z.x, ly - z.y);
    let e = [
        cz * ux + sz * uy,
        -sz * ux + cz * uy,
        wrap_angle(xj.theta - xi.theta - z.theta),
    ];
    // M = R_zᵀ R_iᵀ.
    let m = [
        [cz * ci - sz * si, cz * si + sz * ci],
        [-sz * ci - cz * si, -sz * si + cz * ci],
    ];
    let dth = [cz * dlx + sz * dly, -sz * dlx + cz * dly];
    let ja = [
        [-m[0][0], -m[0][1], dth[0]],
        [-m[1][0], -m[1][1], dth[1]],
        [0.0, 0.0, -1.0],
    ];
    let jb = [
        [m[0][0], m[0][1], 0.0],
        [m[1][0], m[1][1], 0.0],
        [0.0, 0.0, 1.0],
    ];
    (e, ja, jb)
}

/// `Σ_e r_eᵀ Ω_e r_e` of poses `x` in the default chart ([`Residual::Log`]); see
/// [`Residual::cost`] for the other.
pub fn cost(graph: &PoseGraph, x: &[Pose2]) -> f64 {
    Residual::default().cost(graph, x)
}

/// Every edge's term of [`cost`] (default chart), in edge order.
pub fn edge_costs<'a>(graph: &'a PoseGraph, x: &'a [Pose2]) -> impl Iterator<Item = f64> + 'a {
    Residual::default().edge_costs(graph, x)
}

/// Refine `initial` (one pose per node; each component's anchor, its first node, stays fixed)
/// by Levenberg–Marquardt with Nielsen's damping rule (module docs).
pub fn refine(
    graph: &PoseGraph,
    initial: &[Pose2],
    config: &RefineConfig,
) -> Result<Refined, EstimateError> {
    EstimateError::check_size(
        "initial poses for the graph's nodes",
        graph.node_count(),
        initial.len(),
    )?;
    let anchored = Anchored::new(graph);
    let mut ne = NormalEquations::<3>::new(graph, &anchored)?;
    let mut x = initial.to_vec();
    let chart = config.residual;
    let mut c = chart.cost(graph, &x);
    let mut costs = vec![c];
    let mut lambda = config.initial_damping.max(f64::MIN_POSITIVE);
    let mut nu = 2.0f64;
    let mut iterations = 0;
    let mut gradient = f64::NAN;
    // Jacobian blocks of every edge at x, for the model's predicted decrease.
    let mut jac: Vec<[Block; 2]> = Vec::with_capacity(graph.edge_count());
    let mut assembled = false;
    let stop = loop {
        if ne.dim() == 0 {
            break Stop::NothingToRefine;
        }
        if !assembled {
            ne.clear();
            jac.clear();
            for (e, (edge, &(a, b))) in graph.edges().iter().zip(graph.endpoints()).enumerate() {
                let (err, ja, jb) = chart.linearise(edge.measurement(), x[a], x[b]);
                ne.add(e, &ja, &jb, &edge.information().matrix(), &err);
                jac.push([ja, jb]);
            }
            assembled = true;
            gradient = ne.rhs().iter().fold(0.0f64, |m, v| m.max(v.abs()));
            if gradient <= config.gradient_tolerance {
                break Stop::Gradient;
            }
        }
        if iterations >= config.iterations {
            break Stop::IterationCap;
        }
        if lambda > 1e16 {
            break Stop::Stalled;
        }
        iterations += 1;
        let Ok(llt) = ne.factor(lambda) else {
            lambda *= nu;
            nu *= 2.0;
            continue;
        };
        let rhs = ne.rhs();
        let h = solve(llt.as_ref(), &rhs);
        let delta = |v: usize, i: usize| anchored.value(&h, v, 3, i);
        let trial: Vec<Pose2> = x
            .iter()
            .enumerate()
            .map(|(v, p)| Pose2::new(p.x + delta(v, 0), p.y + delta(v, 1), p.theta + delta(v, 2)))
            .collect();
        // L(0) − L(h) = −2gᵀh − hᵀHh, with −g = rhs and hᵀHh = Σ_e (J h)ᵀ Ω (J h).
        let g_h: f64 = rhs.iter().zip(h.iter()).map(|(r, s)| r * s).sum();
        let h_h_h: f64 = graph
            .edges()
            .iter()
            .zip(graph.endpoints())
            .zip(&jac)
            .map(|((edge, &(a, b)), [ja, jb])| {
                let jh: [f64; 3] = std::array::from_fn(|r| {
                    (0..3)
                        .map(|k| ja[r][k] * delta(a, k) + jb[r][k] * delta(b, k))
                        .sum()
                });
                let o = edge.information().matrix();
                (0..3)
                    .map(|i| (0..3).map(|j| jh[i] * o[i][j] * jh[j]).sum::<f64>())
                    .sum::<f64>()
            })
            .sum();
        let predicted = 2.0 * g_h - h_h_h;
        let ct = chart.cost(graph, &trial);
        let rho = if predicted > 0.0 {
            (c - ct) / predicted
        } else {
            f64::NAN
        };
        if ct.is_finite() && ct <= c {
            let decrease = if c > 0.0 { (c - ct) / c } else { 0.0 };
            let step = h.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let size = x
                .iter()
                .flat_map(|p| [p.x, p.y, p.theta])
                .fold(0.0f64, |m, v| m.max(v.abs()));
            x = trial;
            c = ct;
            costs.push(c);
            assembled = false;
            gradient = f64::NAN;
            let r = if rho.is_finite() { rho.min(1.0) } else { 1.0 };
            lambda *= (1.0 - (2.0 * r - 1.0).powi(3)).max(1.0 / 3.0);
            lambda = lambda.max(1e-15);
            nu = 2.0;
            if decrease < config.relative_decrease {
                break Stop::RelativeDecrease;
            }
            if step <= config.step_tolerance * (size + config.step_tolerance) {
                break Stop::Step;
            }
        } else {
            lambda *= nu;
            nu *= 2.0;
        }
    };
    Ok(Refined {
        poses: x,
        costs,
        iterations,
        converged: stop.converged(),
        stop,
        gradient,
    })
}

/// `AᵀB` (3 × 3) of two sparse 3-column matrices given by rows, positions ascending.
fn sparse_dot3(a: &[(u32, [f64; 3])], b: &[(u32, [f64; 3])]) -> Block {
    let (mut i, mut j, mut s) = (0, 0, [[0.0; 3]; 3]);
    while i < a.len() && j < b.len() {
        match a[i].0.cmp(&b[j].0) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                for (p, row) in s.iter_mut().enumerate() {
                    for (q, v) in row.iter_mut().enumerate() {
                        *v += a[i].1[p] * b[j].1[q];
                    }
                }
                i += 1;
                j += 1;
            }
        }
    }
    s
}

/// `rᵀ S⁻¹ r` for the SPD `S = I − [Y_eᵀY_f]` of the edges `ys` (3 rows each) and their
/// whitened residuals `r`; NaN if S is not positive definite.
fn downdate_chi2(ys: &[&Vec<(u32, [f64; 3])>], r: &[[f64; 3]]) -> f64 {
    let n = 3 * ys.len();
    let mut s = faer::Mat::<f64>::zeros(n, n);
    for e in 0..ys.len() {
        for f in 0..=e {
            let c = sparse_dot3(ys[e], ys[f]);
            for p in 0..3 {
                for q in 0..3 {
                    let v = f64::from(u8::from(e == f && p == q)) - c[p][q];
                    s[(3 * e + p, 3 * f + q)] = v;
                    s[(3 * f + q, 3 * e + p)] = v;
                }
            }
        }
    }
    let rhs = faer::Mat::<f64>::from_fn(n, 1, |i, _| r[i / 3][i % 3]);
    match s.llt(faer::Side::Lower) {
        Ok(l) => {
            let y = faer::linalg::solvers::Solve::solve(&l, &rhs);
            (0..n).map(|i| rhs[(i, 0)] * y[(i, 0)]).sum()
        }
        Err(_) => f64::NAN,
    }
}

/// The drops of [`leave_out_drops`]: of each edge alone, and of each group as a whole.
#[derive(Clone, Debug, PartialEq)]
pub struct LeaveOut {
    /// For each group, the drop of each of its edges left out alone (in the group's order).
    pub edges: Vec<Vec<f64>>,
    /// For each group, the drop of the whole group left out (for one edge, its drop).
    pub groups: Vec<f64>,
}

/// The largest group whose drop as a whole [`leave_out_drops`] computes: its dense
/// `3|G| × 3|G|` system stays small (a file whose loop closures chain into one group of
/// thousands must not ask for gigabytes); a larger group gets NaN as a whole, its edges
/// their own drops.
pub const MAX_GROUP_EDGES: usize = 64;

/// The linearised **cost drop of leaving edges out**, for each edge of `groups` (disjoint
/// sets of edges) alone and for each group as a whole: at poses `x` (a minimum of the cost of
/// `graph` in chart `residual`), with each edge's residual and Jacobian whitened by its
/// information (`r̃_e = L_eᵀ r_e`, `J̃_e = L_eᵀ J_e`, `Ω_e = L_e L_eᵀ`) and
/// `H = Σ_e J̃_eᵀ J̃_e`,
///
/// ```text
/// Δ_G = r̃_Gᵀ (I − J̃_G H⁻¹ J̃_Gᵀ)⁻¹ r̃_G,
/// ```
///
/// the exact `min F − min F_{without G}` of the linearised problem (the down-date of a
/// least-squares problem by the rows of G). For data that follow the model, `Δ_G ~ χ²_{3|G|}`.
/// A false edge the map bent to fit has a small residual, but a small redundancy
/// `I − J̃_e H⁻¹ J̃_eᵀ` too, so its Δ is large where its χ²_e is not.
///
/// `J̃_G H⁻¹ J̃_Gᵀ = YᵀY` with `Y = R⁻ᵀ J̃_Gᵀ`, R the square-root information factor of H in a
/// fill-reducing order (the incremental square-root solver the online estimate uses): one sparse forward solve
/// per edge, along its elimination-tree paths only; never a dense inverse. A removal that
/// would leave a pose undetermined (`I − YᵀY` not positive definite), an edge of singular
/// information, or a group of more than [`MAX_GROUP_EDGES`] edges as a whole gets NaN.
pub fn leave_out_drops(
    graph: &PoseGraph,
    x: &[Pose2],
    residual: Residual,
    groups: &[Vec<usize>],
) -> Result<LeaveOut, EstimateError> {
    use crate::estimate::ANCHOR;
    use crate::estimate::incremental::{SqrtInfo, WhitenScratch, fill_reducing_order};
    EstimateError::check_size("poses for the graph's nodes", graph.node_count(), x.len())?;
    let anchored = Anchored::new(graph);
    let mut out = LeaveOut {
        edges: groups.iter().map(|g| vec![f64::NAN; g.len()]).collect(),
        groups: vec![f64::NAN; groups.len()],
    };
    if anchored.free == 0 {
        return Ok(out);
    }
    let edges = graph.edges();
    let ends = graph.endpoints();
    // Unknown i of node v; an anchor's entries get coefficient 0 on unknown 0.
    let unknown = |v: usize| Some(anchored.var_of[v]).filter(|&u| u != ANCHOR);
    type Row = [(usize, f64); 6];
    let mut white: Vec<Option<([f64; 3], [Row; 3])>> = Vec::with_capacity(edges.len());
    for (edge, &(a, b)) in edges.iter().zip(ends) {
        let (r, ja, jb) = residual.linearise(edge.measurement(), x[a], x[b]);
        // Ω = L Lᵀ: rᵀΩr = ‖Lᵀr‖².
        let lt = edge
            .information()
            .cholesky()
            .map(|l| std::array::from_fn::<[f64; 3], 3, _>(|i| std::array::from_fn(|j| l[j][i])));
        white.push(lt.map(|lt| {
            let rt: [f64; 3] = std::array::from_fn(|k| (0..3).map(|l| lt[k][l] * r[l]).sum());
            let rows: [Row; 3] = std::array::from_fn(|k| {
                std::array::from_fn(|c| {
                    let (v, j, i) = if c < 3 { (a, &ja, c) } else { (b, &jb, c - 3) };
                    match unknown(v) {
                        Some(u) => (3 * u + i, (0..3).map(|l| lt[k][l] * j[l][i]).sum()),
                        None => (0, 0.0),
                    }
                })
            });
            (rt, rows)
        }));
    }
    let pairs: Vec<(usize, usize)> = ends
        .iter()
        .filter_map(|&(a, b)| Some((unknown(a)?, unknown(b)?)))
        .collect();
    let vars: Vec<usize> = fill_reducing_order(anchored.free, &pairs, &[])
        .into_iter()
        .flat_map(|u| [3 * u, 3 * u + 1, 3 * u + 2])
        .collect();
    let rows = || {
        white
            .iter()
            .flatten()
            .flat_map(|(_, rows)| rows.iter().map(|r| (*r, [0.0])))
    };
    let f = SqrtInfo::<1>::factored(&vars, rows()).unwrap_or_else(|| {
        // Extreme weights: rotate the rows in (the better-conditioned QR).
        let mut f = SqrtInfo::<1>::new();
        for &v in &vars {
            f.push_variable(v);
        }
        for (row, beta) in rows() {
            f.add_row(&row, beta);
        }
        f
    });
    let mut scratch = WhitenScratch::default();
    for (g, group) in groups.iter().enumerate() {
        // Each edge's whitened residual and Y = R⁻ᵀ J̃_eᵀ (by rows).
        type Part<'a> = (&'a [f64; 3], Vec<(u32, [f64; 3])>);
        let parts: Vec<Option<Part>> = group
            .iter()
            .map(|&e| {
                white[e]
                    .as_ref()
                    .map(|(r, rows)| (r, f.whiten3(rows, &mut scratch)))
            })
            .collect();
        for (slot, part) in out.edges[g].iter_mut().zip(&parts) {
            if let Some((r, y)) = part {
                *slot = downdate_chi2(&[y], &[**r]);
            }
        }
        out.groups[g] = if group.len() == 1 {
            out.edges[g][0]
        } else if group.len() > MAX_GROUP_EDGES {
            f64::NAN
        } else if let Some(parts) = parts.into_iter().collect::<Option<Vec<_>>>() {
            let ys: Vec<&Vec<(u32, [f64; 3])>> = parts.iter().map(|(_, y)| y).collect();
            let rs: Vec<[f64; 3]> = parts.iter().map(|(r, _)| **r).collect();
            downdate_chi2(&ys, &rs)
        } else {
            f64::NAN
        };
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{SimConfig, simulate};

    /// Finite differences of the error agree with the analytic Jacobians, in both charts, for
    /// an error angle in the closed form's range and one in the series' range.
    #[test]
    fn jacobians_match_finite_differences() {
        for residual in [Residual::T2v, Residual::Log] {
            for theta_j in [0.9, -2.5 + 2.9 + 4e-4] {
                let z = Pose2::new(0.7, -0.3, 2.9);
                let xi = Pose2::new(1.0, 2.0, -2.5);
                let xj = Pose2::new(1.4, 1.1, theta_j);
                let (_, ja, jb) = residual.linearise(z, xi, xj);
                let h = 1e-6;
                for k in 0..3 {
                    let bump = |p: Pose2, s: f64| {
                        let mut v = [p.x, p.y, p.theta];
                        v[k] += s;
                        Pose2::new(v[0], v[1], v[2])
                    };
                    let ep = residual.error(z, bump(xi, h), xj);
                    let em = residual.error(z, bump(xi, -h), xj);
                    let fp = residual.error(z, xi, bump(xj, h));
                    let fm = residual.error(z, xi, bump(xj, -h));
                    for r in 0..3 {
                        assert!(
                            ((ep[r] - em[r]) / (2.0 * h) - ja[r][k]).abs() < 1e-6,
                            "{residual} a {r} {k}"
                        );
                        assert!(
                            ((fp[r] - fm[r]) / (2.0 * h) - jb[r][k]).abs() < 1e-6,
                            "{residual} b {r} {k}"
                        );
                    }
                }
            }
        }
    }

    /// The Log chart inverts the SE(2) exponential `Exp(u, θ) = (V(θ) u, θ)`,
    /// `V = [[sin θ, −(1 − cos θ)], [1 − cos θ, sin θ]] / θ`, on both sides of the series switch.
    #[test]
    fn log_inverts_the_exponential() {
        for (ux, uy, th) in [
            (0.3, -1.2, 2.0),
            (-4.0, 0.5, -3.1),
            (1.0, 2.0, 3e-4),
            (1.0, 2.0, 1.1e-3),
        ] {
            let (s, c) = (f64::sin(th), f64::cos(th));
            let t = [
                (s * ux - (1.0 - c) * uy) / th,
                ((1.0 - c) * ux + s * uy) / th,
            ];
            let (r, _) = log_chart([t[0], t[1], th]);
            for (got, want) in r.iter().zip([ux, uy, th]) {
                assert!((got - want).abs() < 1e-12, "{r:?} vs {:?}", (ux, uy, th));
            }
        }
        // At a zero angle the chart is the identity.
        assert_eq!(log_chart([0.5, -0.25, 0.0]).0, [0.5, -0.25, 0.0]);
    }

    /// On strongly anisotropic information the two charts' minima differ, and each refinement
    /// ends at its own chart's minimum: neither chart's cost improves by starting its
    /// refinement from the other's result.
    #[test]
    fn each_chart_converges_to_its_own_minimum() {
        let w = simulate(&SimConfig::new(200, 11)).unwrap();
        // Very unequal translation information (x much stiffer than y), as on MIT and CSAIL,
        // with noise drawn to match it (the simulator's unit-variance draws, rescaled).
        let (sx, sy, st) = (0.005, 0.5, 0.05);
        let mut g = crate::graph::PoseGraph::new();
        for (e, n) in w.graph.edges().iter().zip(&w.truth.noise) {
            let (i, j) = (e.from() as usize, e.to() as usize);
            let t = w.truth.poses[i].between(w.truth.poses[j]);
            let u = w.config.sigma_xy;
            // Noise in the measurement's own end frame, where the error is measured.
            let z = t.compose(Pose2::new(sx * n.x / u, sy * n.y / u, n.theta));
            let info =
                crate::graph::Information::diagonal(1.0 / sx / sx, 1.0 / sy / sy, 1.0 / st / st);
            let e = crate::graph::Edge::new(e.from(), e.to(), z, info).unwrap();
            g.add_edge(e, crate::graph::NodePolicy::CreateUnknown)
                .unwrap();
        }
        let p0 = w.truth.poses[0];
        let start: Vec<Pose2> = w.truth.poses.iter().map(|t| p0.between(*t)).collect();
        let run = |residual, from: &[Pose2]| {
            let cfg = RefineConfig {
                residual,
                ..RefineConfig::default()
            };
            let r = refine(&g, from, &cfg).unwrap();
            assert!(r.converged, "{residual}: {}", r.stop);
            r
        };
        let log = run(Residual::Log, &start);
        let t2v = run(Residual::T2v, &start);
        let log_again = run(Residual::Log, &t2v.poses);
        let t2v_again = run(Residual::T2v, &log.poses);
        assert!(log_again.cost() >= log.cost() * (1.0 - 1e-8));
        assert!(t2v_again.cost() >= t2v.cost() * (1.0 - 1e-8));
        // The minima differ measurably: the t2v minimum is worse in the Log chart.
        let cross = Residual::Log.cost(&g, &t2v.poses);
        assert!(
            cross > log.cost() * (1.0 + 1e-4),
            "{cross} vs {}",
            log.cost()
        );
    }

    #[test]
    fn the_truth_costs_about_the_noise_and_refinement_never_increases_the_cost() {
        let w = simulate(&SimConfig::new(300, 3)).unwrap();
        let p0 = w.truth.poses[0];
        let truth: Vec<Pose2> = w.truth.poses.iter().map(|t| p0.between(*t)).collect();
        let c = cost(&w.graph, &truth);
        // E[χ²] = 3 m for correctly weighted noise.
        let m = w.graph.edge_count() as f64;
        assert!(c > 2.0 * m && c < 4.0 * m, "{c} vs 3m = {}", 3.0 * m);
        let r = refine(&w.graph, &truth, &RefineConfig::default()).unwrap();
        assert!(r.costs.windows(2).all(|p| p[1] <= p[0]));
        assert!(r.cost() < c);
        assert!(r.converged, "{}", r.stop);
    }

    /// The linearised leave-out drops equal the drops of refining without the edges (the
    /// problem is nearly linear at small noise): for single loop closures, for a group of
    /// them, and for all chunks of a partition computed at once; a bridge (an odometry edge
    /// whose removal leaves a pose undetermined) gets NaN.
    #[test]
    fn leave_out_drops_match_refining_without_the_edges() {
        let w = simulate(&SimConfig::new(300, 7)).unwrap();
        let g = &w.graph;
        let p0 = w.truth.poses[0];
        let truth: Vec<Pose2> = w.truth.poses.iter().map(|t| p0.between(*t)).collect();
        let x = refine(g, &truth, &RefineConfig::default()).unwrap();
        let lcs: Vec<usize> = (0..g.edge_count())
            .filter(|&e| !g.edges()[e].is_odometric())
            .collect();
        assert!(lcs.len() >= 6);
        let group = lcs[..4].to_vec();
        let groups = vec![group.clone(), vec![lcs[4]], vec![lcs[5]], vec![0]];
        let d = leave_out_drops(g, &x.poses, Residual::Log, &groups).unwrap();
        let without = |left: &[usize]| {
            let mut h = PoseGraph::new();
            for n in g.nodes() {
                h.add_node(n.id, n.initial).unwrap();
            }
            for (e, edge) in g.edges().iter().enumerate() {
                if !left.contains(&e) {
                    h.add_edge(*edge, Default::default()).unwrap();
                }
            }
            x.cost()
                - refine(&h, &x.poses, &RefineConfig::default())
                    .unwrap()
                    .cost()
        };
        let close = |lin: f64, exact: f64| (lin - exact).abs() <= 0.02 * exact.abs() + 1e-6;
        let exact = without(&group);
        assert!(close(d.groups[0], exact), "{} vs {exact}", d.groups[0]);
        for (i, &e) in group.iter().enumerate() {
            let exact = without(&[e]);
            assert!(close(d.edges[0][i], exact), "{} vs {exact}", d.edges[0][i]);
        }
        for k in [1, 2] {
            let exact = without(&groups[k]);
            assert!(close(d.groups[k], exact), "{} vs {exact}", d.groups[k]);
            assert_eq!(d.groups[k], d.edges[k][0]);
        }
        // Edge 0 is the first odometry edge: node 0 hangs on it unless a loop closure meets it.
        let first_is_bridge = g.edges().iter().skip(1).all(|e| {
            let ids = [g.nodes()[0].id];
            !ids.contains(&e.from()) && !ids.contains(&e.to())
        });
        assert!(first_is_bridge, "world 7 has a loop closure at node 0");
        assert!(d.groups[3].is_nan(), "{}", d.groups[3]);
    }

    /// From a start far from the optimum (dead reckoning of a noisy world) the refinement
    /// converges by its own rule, at a stationary point; a cap of 2 iterations says it did not.
    #[test]
    fn converges_and_says_so() {
        let mut cfg = SimConfig::new(400, 5);
        cfg.sigma_theta = 0.1;
        let w = simulate(&cfg).unwrap();
        let start = crate::estimate::odometry_poses(&w.graph);
        let r = refine(&w.graph, &start, &RefineConfig::default()).unwrap();
        assert!(r.converged, "{} after {} iterations", r.stop, r.iterations);
        assert!(r.iterations < 100);
        // Stationary: a fresh assembly at the result has a small gradient relative to the
        // start's.
        let again = refine(&w.graph, &r.poses, &RefineConfig::default()).unwrap();
        assert!(again.cost() >= r.cost() * (1.0 - 1e-8));
        let capped = refine(&w.graph, &start, &RefineConfig::with_iterations(2)).unwrap();
        assert_eq!(capped.stop, Stop::IterationCap);
        assert!(!capped.converged);
        assert!(capped.stop.to_string().starts_with("not converged"));
        assert!(Stop::Gradient.to_string().starts_with("converged"));
    }
}
