//! Screening the cycle integers γ (method [§3](crate::method#3-first-screening), [§4](crate::method#4-second-screening), [§8](crate::method#8-success-probability)).
//!
//! **First screening** (per cycle): with `q_i = sqrt(χ²_d⁻¹(1 − α_i))`, the candidates of γ_i
//! are the integers in `[m_i − q_i s_i, m_i + q_i s_i]`, where `(m_i, s_i²)` are the mean and
//! variance of γ_i conditioned on the determined set U. A cycle with a single candidate is
//! determined (moved to U); iterate until nothing changes. An interval holding no integer means
//! the cycle **failed its consistency test** at level α_i: it stays ambiguous with its two
//! nearest integers, and is reported with its level and residual.
//!
//! **Levels.** The default is family-wise ([`ScreeningConfig::family_wise`]): the per-cycle
//! levels share α/2 and the joint test of the second screening gets the other α/2, so that by
//! the union bound the probability that any cycle fails its test, or that the surviving set
//! misses the true γ, is at most α on data that follow the declared noise model:
//!
//! - batch, ℓ cycles known: `α_i = α/(2ℓ)` (Bonferroni);
//! - online, ℓ unknown: the **α-spending sequence**
//!   `α_t = (α/2) · w_t,  w_t = c / ((t + 100) · ln²(t + 100))`, t = 0, 1, … the cycle's index
//!   in closing order, with c chosen so that `Σ_t w_t ≤ 1` ([`spending_weight`]). It decays
//!   slowly (like 1/(t ln² t), the slowest standard summable form), so a long run keeps its
//!   power: at t = 2000 the interval is 11 % wider than Bonferroni's for ℓ = 2000, at
//!   t = 10⁵ 10 % wider than Bonferroni's for ℓ = 10⁵; the offset 100 keeps the first cycles
//!   from taking most of α.
//!
//! With [`family_wise`](ScreeningConfig::family_wise) off, every cycle is tested at α (the
//! paper's setting): about α·ℓ true cycles then fail their test on clean data. Each cycle's
//! level counts its first test; re-tests of an ambiguous cycle with more conditioning are
//! strongly correlated with it and not charged again (the guarantee is checked empirically
//! in `tests/statistics.rs`).
//!
//! **Second screening** (joint): the vectors `v` of the candidate box with
//! `(v − m_A)ᵀ Q_A⁻¹ (v − m_A) ≤ χ²_{|A|}⁻¹(1 − α_J)`, `Q_A` the conditional covariance of the
//! ambiguous set and α_J the joint level ([`ScreeningConfig::joint_level`]), are enumerated by
//! sphere decoding over `Q_A = L D Lᵀ` (Schnorr–Euchner-style depth-first search, each
//! coordinate clamped to its box), never by materialising the Cartesian product; with an
//! explicit cap. Coordinates equal in every surviving vector are determined and the screening
//! repeats.
//!
//! **Success-rate bound** (Teunissen 1998): `Π_i (2Φ(1/(2 s_i)) − 1) = Π_i erf(1/(2√2 s_i))`
//! over the sequential conditional standard deviations.

use statrs::distribution::{ChiSquared, ContinuousCDF};

use std::time::Instant;

use crate::gamma::{Conditioner, GammaModel, Moments, SingularError};

/// Screening settings.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct ScreeningConfig {
    /// Significance level α.
    pub alpha: f64,
    /// Degrees of freedom of the χ² quantile of the per-cycle test (1 is the standard
    /// choice for a scalar; the paper used 3).
    pub dof: u32,
    /// Family-wise level (the default): the probability that any cycle fails its test or
    /// that the surviving set misses the true γ is ≤ α. The per-cycle tests share α/2 —
    /// α/(2ℓ) each in batch (Bonferroni), the α-spending sequence online — and the joint test
    /// gets α/2 (module docs). Off: every cycle is tested at α (the paper's setting).
    pub family_wise: bool,
    /// Cap on the hypotheses enumerated by the second screening.
    pub max_hypotheses: usize,
}

impl Default for ScreeningConfig {
    /// α = 0.01 family-wise, 1 degree of freedom, cap 10⁶.
    fn default() -> Self {
        Self {
            alpha: 0.01,
            dof: 1,
            family_wise: true,
            max_hypotheses: 1_000_000,
        }
    }
}

/// Invalid screening settings.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("invalid screening setting: {0}")]
pub struct ConfigError(pub String);

impl ScreeningConfig {
    /// The paper's setting: α = 0.01 per cycle, 3 degrees of freedom.
    pub fn paper() -> Self {
        Self {
            dof: 3,
            family_wise: false,
            ..Self::default()
        }
    }

    /// The same α tested per cycle (not family-wise).
    pub fn per_cycle(self) -> Self {
        Self {
            family_wise: false,
            ..self
        }
    }

    /// Check ranges.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if !(self.alpha > 0.0 && self.alpha < 1.0) {
            return Err(ConfigError(format!(
                "alpha = {} must be in (0, 1)",
                self.alpha
            )));
        }
        if self.dof == 0 {
            return Err(ConfigError("dof must be ≥ 1".into()));
        }
        // 1 − α must differ from 1 in double precision, or q is infinite and every box spans
        // all integers.
        if 1.0 - self.alpha == 1.0 || !self.quantile(1).is_finite() {
            return Err(ConfigError(format!(
                "alpha = {:e} is too small: 1 − α rounds to 1 in double precision (use α ≥ 1e-15)",
                self.alpha
            )));
        }
        if self.max_hypotheses == 0 {
            return Err(ConfigError("max_hypotheses must be ≥ 1".into()));
        }
        Ok(())
    }

    /// Per-cycle level: α, or α/(2ℓ) when family-wise.
    ///
    /// Family-wise, the ℓ per-cycle tests share α/2 (Bonferroni) and the joint ellipsoid test
    /// of the second screening gets the other α/2 ([`joint_level`](Self::joint_level)), so by
    /// the union bound the surviving set misses the true γ with probability ≤ α.
    pub fn level(&self, cycles: usize) -> f64 {
        if self.family_wise {
            self.alpha / (2 * cycles.max(1)) as f64
        } else {
            self.alpha
        }
    }

    /// Level of the joint (ellipsoid) test: α, or α/2 when family-wise.
    pub fn joint_level(&self) -> f64 {
        if self.family_wise {
            self.alpha / 2.0
        } else {
            self.alpha
        }
    }

    /// Interval half-width factor `q = sqrt(χ²_d⁻¹(1 − level))` for ℓ = `cycles` (batch).
    pub fn quantile(&self, cycles: usize) -> f64 {
        self.quantile_at(self.level(cycles))
    }

    /// Level of cycle t (0-based, in closing order) when ℓ is not known in advance: α, or the
    /// α-spending level `(α/2) · w_t` when family-wise (module docs, [`spending_weight`]).
    pub fn online_level(&self, t: usize) -> f64 {
        if self.family_wise {
            self.alpha / 2.0 * spending_weight(t)
        } else {
            self.alpha
        }
    }

    /// Interval half-width factor of cycle t at [`online_level`](Self::online_level).
    pub fn online_quantile(&self, t: usize) -> f64 {
        self.quantile_at(self.online_level(t))
    }

    /// `q = sqrt(χ²_d⁻¹(1 − level))`; for d = 1 computed as `√2 · erfc⁻¹(level)`, which stays
    /// accurate for levels far below machine epsilon.
    pub fn quantile_at(&self, level: f64) -> f64 {
        if self.dof == 1 {
            std::f64::consts::SQRT_2 * statrs::function::erf::erfc_inv(level)
        } else {
            chi2_quantile(f64::from(self.dof), 1.0 - level).sqrt()
        }
    }

    /// The level a half-width factor q stands for: `P(χ²_d > q²)`.
    pub fn level_of_quantile(&self, q: f64) -> f64 {
        if self.dof == 1 {
            libm::erfc(q / std::f64::consts::SQRT_2)
        } else {
            chi2_p_value(self.dof as usize, q * q)
        }
    }
}

/// Offset of the α-spending sequence (module docs).
const SPENDING_OFFSET: f64 = 100.0;

/// `1 / ((t + 100) ln²(t + 100))`, the unnormalised spending term.
fn spending_term(t: f64) -> f64 {
    let x = t + SPENDING_OFFSET;
    1.0 / (x * x.ln() * x.ln())
}

/// An upper bound on `S = Σ_{t ≥ 0} spending_term(t)`: the first 2²⁰ terms summed, then the
/// tail bounded by `f(N) + ∫_N^∞ f = f(N) + 1/ln(N + 100)` (f decreasing), times `1 + 10⁻⁹`
/// for the rounding of the sum. A constant, because summing 2²⁰ logarithms at the first
/// cycle would cost that step about 10 ms; `spending_bound_is_the_documented_sum` recomputes
/// it.
const SPENDING_SUM_BOUND: f64 = 0.21738357185601767;

fn spending_sum_bound() -> f64 {
    SPENDING_SUM_BOUND
}

/// Weight `w_t = c / ((t + 100) ln²(t + 100))` of cycle t in the α-spending sequence, with
/// `c = 1/S̄` for an upper bound S̄ of the series, so `Σ_t w_t ≤ 1`.
pub fn spending_weight(t: usize) -> f64 {
    spending_term(t as f64) / spending_sum_bound()
}

/// `χ²_d⁻¹(p)`.
pub fn chi2_quantile(dof: f64, p: f64) -> f64 {
    match ChiSquared::new(dof) {
        Ok(d) => d.inverse_cdf(p),
        Err(_) => f64::NAN,
    }
}

/// Upper tail `P(χ²_d > x)`, the consistency p-value.
pub fn chi2_p_value(dof: usize, x: f64) -> f64 {
    if dof == 0 {
        return 1.0;
    }
    match ChiSquared::new(dof as f64) {
        Ok(d) => d.sf(x),
        Err(_) => f64::NAN,
    }
}

/// The candidate integers of one cycle: `lo..=hi`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Interval {
    /// Smallest candidate.
    pub lo: i64,
    /// Largest candidate.
    pub hi: i64,
    /// The confidence interval held no integer; `lo..=hi` are the two nearest integers.
    pub inconsistent: bool,
}

impl Interval {
    /// Candidates of a cycle with conditional moments `m` and half-width factor `q`, within
    /// ±[`MAX_CANDIDATE`] (beyond it f64 does not resolve integers).
    pub fn new(m: Moments, q: f64) -> Self {
        let half = q * m.sd();
        let lo = (m.mean - half).ceil().max(-MAX_CANDIDATE as f64);
        let hi = (m.mean + half).floor().min(MAX_CANDIDATE as f64);
        if lo <= hi {
            Self {
                lo: lo as i64,
                hi: hi as i64,
                inconsistent: false,
            }
        } else {
            let f = (m.mean.floor() as i64).clamp(-MAX_CANDIDATE, MAX_CANDIDATE - 1);
            Self {
                lo: f,
                hi: f + 1,
                inconsistent: true,
            }
        }
    }

    /// Number of candidates.
    pub fn count(&self) -> u64 {
        self.hi.abs_diff(self.lo).saturating_add(1)
    }

    /// The single candidate, if there is exactly one (never for an inconsistent cycle).
    pub fn single(&self) -> Option<i64> {
        (self.lo == self.hi && !self.inconsistent).then_some(self.lo)
    }
}

/// Distance from the mean to the nearest integer, in standard deviations.
pub fn normalised_residual(m: Moments) -> f64 {
    (m.mean - m.mean.round()).abs() / m.sd()
}

/// `2Φ(1/(2s)) − 1`: the probability that rounding a N(γ, s²) variable gives γ.
pub fn rounding_success(sd: f64) -> f64 {
    libm::erf(1.0 / (2.0 * std::f64::consts::SQRT_2 * sd))
}

/// `Π_i (2Φ(1/(2 s_i)) − 1)` over conditional standard deviations.
pub fn success_lower_bound(sds: impl IntoIterator<Item = f64>) -> f64 {
    sds.into_iter()
        .map(|s| rounding_success(s).ln())
        .sum::<f64>()
        .exp()
}

/// The largest |γ| candidate: 2⁵³, beyond which f64 does not resolve integers.
pub const MAX_CANDIDATE: i64 = 1 << 53;

/// Memory the second screening may use for the vectors it enumerates: 256 MiB. A vector of k
/// coordinates costs `8k + 32` bytes, so the effective cap is
/// `min(max_hypotheses, MAX_ENUMERATION_BYTES / (8k + 32))`.
pub const MAX_ENUMERATION_BYTES: usize = 256 << 20;

/// Which bound stopped an enumeration.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Limit {
    /// [`ScreeningConfig::max_hypotheses`] vectors were found.
    Hypotheses,
    /// The search visited `64 · cap` partial vectors.
    Visits,
    /// The vectors found would exceed [`MAX_ENUMERATION_BYTES`].
    Memory,
}

/// Why enumeration stopped early.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct TooMany {
    /// Vectors found before stopping.
    pub found: usize,
    /// The cap.
    pub cap: usize,
    /// Partial vectors visited by the search (its budget is `64 · cap`).
    pub visited: usize,
    /// The bound that stopped it.
    pub limit: Limit,
}

/// `Q = L D Lᵀ` of a dense symmetric matrix (row-major), L unit lower triangular.
/// `None` if a pivot is not positive.
pub fn ldl(q: &[f64], k: usize) -> Option<(Vec<f64>, Vec<f64>)> {
    let mut l = vec![0.0; k * k];
    let mut d = vec![0.0; k];
    for j in 0..k {
        let mut dj = q[j * k + j];
        for p in 0..j {
            dj -= l[j * k + p] * l[j * k + p] * d[p];
        }
        if !dj.is_finite() || dj <= 0.0 {
            return None;
        }
        d[j] = dj;
        l[j * k + j] = 1.0;
        for i in j + 1..k {
            let mut v = q[i * k + j];
            for p in 0..j {
                v -= l[i * k + p] * l[j * k + p] * d[p];
            }
            l[i * k + j] = v / dj;
        }
    }
    Some((l, d))
}

/// The ambiguous set's joint Gaussian, factored for enumeration: coordinates reordered by
/// increasing conditional variance, `Q = L D Lᵀ` in that order.
#[derive(Clone, Debug)]
pub struct JointGaussian {
    /// Positions (into the caller's set) in factor order.
    pub order: Vec<usize>,
    /// Means in factor order.
    pub mean: Vec<f64>,
    /// Unit lower-triangular factor, row-major.
    pub l: Vec<f64>,
    /// Pivots: sequential conditional variances in factor order.
    pub d: Vec<f64>,
}

impl JointGaussian {
    /// Factor `N(mean, q)` (q dense row-major); `None` if q is not positive definite.
    pub fn new(mean: &[f64], q: &[f64]) -> Option<Self> {
        let k = mean.len();
        let mut order: Vec<usize> = (0..k).collect();
        order.sort_by(|&a, &b| q[a * k + a].total_cmp(&q[b * k + b]).then(a.cmp(&b)));
        let qp: Vec<f64> = (0..k * k)
            .map(|x| q[order[x / k] * k + order[x % k]])
            .collect();
        let (l, d) = ldl(&qp, k)?;
        Some(Self {
            mean: order.iter().map(|&i| mean[i]).collect(),
            order,
            l,
            d,
        })
    }

    /// Conditional center of coordinate `level` given the earlier coordinates' residuals e.
    fn center(&self, level: usize, e: &[f64]) -> f64 {
        let k = self.mean.len();
        let row = &self.l[level * k..level * k + level];
        self.mean[level] + row.iter().zip(e).map(|(a, b)| a * b).sum::<f64>()
    }

    /// Sequential rounding (integer bootstrapping), clamped to the boxes: the fallback answer
    /// when enumeration is capped. Returns values in the caller's order and their quadratic form.
    pub fn bootstrap(&self, boxes: &[Interval]) -> (Vec<i64>, f64) {
        let k = self.mean.len();
        let mut e = vec![0.0; k];
        let mut v = vec![0i64; k];
        let mut form = 0.0;
        for lv in 0..k {
            let b = boxes[self.order[lv]];
            let c = self.center(lv, &e);
            let x = (c.round() as i64).clamp(b.lo, b.hi);
            e[lv] = x as f64 - c;
            form += e[lv] * e[lv] / self.d[lv];
            v[self.order[lv]] = x;
        }
        (v, form)
    }

    /// All integer vectors `v` with `v_i ∈ boxes[i]` and `(v − m)ᵀ Q⁻¹ (v − m) ≤ r2`, each with
    /// its quadratic form, in the caller's coordinate order. Stops with [`TooMany`] at `cap`
    /// vectors, when the search has visited `64 · cap` partial vectors, or when the vectors
    /// found would take more than [`MAX_ENUMERATION_BYTES`].
    pub fn enumerate(
        &self,
        boxes: &[Interval],
        r2: f64,
        cap: usize,
    ) -> Result<Vec<(Vec<i64>, f64)>, TooMany> {
        self.enumerate_within(boxes, r2, cap, MAX_ENUMERATION_BYTES)
    }

    /// [`enumerate`](Self::enumerate) with the memory bound `max_bytes`.
    fn enumerate_within(
        &self,
        boxes: &[Interval],
        r2: f64,
        cap: usize,
        max_bytes: usize,
    ) -> Result<Vec<(Vec<i64>, f64)>, TooMany> {
        let k = self.mean.len();
        let mut out = Vec::new();
        if k == 0 {
            out.push((Vec::new(), 0.0));
            return Ok(out);
        }
        let budget = cap.saturating_mul(64);
        let memory_cap = (max_bytes / (8 * k + 32)).max(1);
        let mut visits = 0usize;
        let mut cur = vec![0i64; k];
        let mut hi = vec![0i64; k];
        let mut center = vec![0.0; k];
        let mut e = vec![0.0; k];
        let mut partial = vec![0.0; k + 1];
        // Open level `lv`: compute its center and feasible range.
        let open = |lv: usize, e: &[f64], partial: &[f64], center: &mut [f64]| -> (i64, i64) {
            let c = self.center(lv, e);
            center[lv] = c;
            let room = (r2 - partial[lv]).max(0.0);
            let half = (self.d[lv] * room).sqrt();
            let b = boxes[self.order[lv]];
            let lo = ((c - half).ceil() as i64).max(b.lo);
            let h = ((c + half).floor() as i64).min(b.hi);
            (lo, h)
        };
        let mut lv = 0;
        (cur[0], hi[0]) = open(0, &e, &partial, &mut center);
        loop {
            if cur[lv] > hi[lv] {
                if lv == 0 {
                    break;
                }
                lv -= 1;
                cur[lv] += 1;
                continue;
            }
            visits += 1;
            if visits > budget {
                return Err(TooMany {
                    found: out.len(),
                    cap,
                    visited: visits,
                    limit: Limit::Visits,
                });
            }
            e[lv] = cur[lv] as f64 - center[lv];
            partial[lv + 1] = partial[lv] + e[lv] * e[lv] / self.d[lv];
            if partial[lv + 1] > r2 {
                cur[lv] += 1;
                continue;
            }
            if lv + 1 == k {
                let mut v = vec![0i64; k];
                for (p, &x) in cur.iter().enumerate() {
                    v[self.order[p]] = x;
                }
                out.push((v, partial[k]));
                if out.len() >= cap.min(memory_cap) {
                    return Err(TooMany {
                        found: out.len(),
                        cap,
                        visited: visits,
                        limit: if out.len() >= cap {
                            Limit::Hypotheses
                        } else {
                            Limit::Memory
                        },
                    });
                }
                cur[lv] += 1;
                continue;
            }
            lv += 1;
            (cur[lv], hi[lv]) = open(lv, &e, &partial, &mut center);
        }
        Ok(out)
    }
}

/// One row of a screening table (the paper's Tables II–IV).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Iteration {
    /// 1-based iteration number.
    pub iteration: usize,
    /// Cycles determined at this iteration.
    pub determined: usize,
    /// The same, in % of all cycles.
    pub determined_percent: f64,
    /// Density (nonzeros / entries) of P_UU, the matrix conditioned on in this iteration.
    pub density: f64,
    /// log10 of the number of candidate vectors after the iteration (first screening: the
    /// product of the interval sizes; second screening: the vectors inside the ellipsoid).
    pub log10_candidates: f64,
    /// Wall time of the iteration.
    pub seconds: f64,
}

/// A cycle that failed its consistency test: its confidence interval held no integer (first
/// detection).
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct InconsistentCycle {
    /// Cycle index in the basis.
    pub cycle: usize,
    /// Its edges (indices in the graph).
    pub edges: Vec<usize>,
    /// Distance from the conditional mean to the nearest integer, in standard deviations.
    pub residual: f64,
    /// The level of the test it failed.
    pub level: f64,
}

impl std::fmt::Display for InconsistentCycle {
    /// `cycle 402 failed its consistency test at level 3.1e-7: residual 5.2 σ`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "cycle {} failed its consistency test at level {:.1e}: residual {:.1} σ",
            self.cycle, self.level, self.residual
        )
    }
}

/// How the second screening ended.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SecondOutcome {
    /// Every surviving vector was enumerated.
    Complete,
    /// The cap was hit (or the search budget ran out): the hypothesis list holds only the
    /// integer-bootstrapping answer.
    TooMany(TooMany),
    /// No vector of the candidate box passes the joint test at its level
    /// ([`ScreeningConfig::joint_level`]): the data disagree with the declared noise, or hold
    /// an outlier. The list holds only the bootstrapping answer.
    NoneInside,
}

/// One surviving hypothesis: values of the final ambiguous cycles, and its χ².
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Hypothesis {
    /// γ on [`Screened::ambiguous`], in that order.
    pub values: Vec<i64>,
    /// `(γ − μ)ᵀ P_γ⁻¹ (γ − μ)`.
    pub chi2: f64,
    /// `P(χ²_ℓ > chi2)`.
    pub p_value: f64,
}

/// The result of screening a γ model to the end (both screenings).
#[derive(Clone, Debug, PartialEq)]
pub struct Screened {
    /// First-screening iterations.
    pub first: Vec<Iteration>,
    /// Second-screening iterations.
    pub second: Vec<Iteration>,
    /// How the second screening ended.
    pub outcome: SecondOutcome,
    /// γ of every determined cycle (0 for the ambiguous ones).
    pub determined_gamma: Vec<i64>,
    /// Number of determined cycles.
    pub determined: usize,
    /// Cycles still ambiguous at the end, ascending.
    pub ambiguous: Vec<usize>,
    /// Cycles found inconsistent at some point, ascending.
    pub inconsistent: Vec<InconsistentCycle>,
    /// Hypotheses sorted by χ² (best first).
    pub hypotheses: Vec<Hypothesis>,
    /// Integer-bootstrapping lower bound on the probability that the answer is right.
    pub success_lower_bound: f64,
}

impl Screened {
    /// The full γ of a hypothesis.
    pub fn gamma(&self, h: &Hypothesis) -> Vec<i64> {
        let mut g = self.determined_gamma.clone();
        for (&i, &v) in self.ambiguous.iter().zip(&h.values) {
            g[i] = v;
        }
        g
    }
}

/// Screening state: the conditioner, every cycle's current candidates, and the inconsistent
/// cycles seen. The batch pipeline and the online estimator both drive this type; they differ
/// only in when they test which cycle.
#[derive(Clone, Debug, Default)]
pub struct Screener {
    /// Conditioning on the determined cycles.
    pub cond: Conditioner,
    intervals: Vec<Interval>,
    determined: Vec<bool>,
    /// Cycles that failed their test: (residual, half-width factor q, edges).
    inconsistent: Vec<Option<(f64, f64, Vec<usize>)>>,
    inconsistent_count: usize,
}

/// The first screening's decision on moments `m` at half-width factor `q`: the one integer
/// left in the interval, unless `veto(m)`.
fn decision(m: Moments, q: f64, veto: &impl Fn(Moments) -> bool) -> Option<i64> {
    if veto(m) {
        None
    } else {
        Interval::new(m, q).single()
    }
}

impl Screener {
    /// An empty state.
    pub fn new() -> Self {
        Self::default()
    }

    /// A copy of the per-cycle state without the factor of P_UU (an empty [`Conditioner`]):
    /// for a copy of the online state that rebuilds the factor when it is used again.
    pub(crate) fn without_conditioner(&self) -> Self {
        Self {
            cond: Conditioner::new(),
            intervals: self.intervals.clone(),
            determined: self.determined.clone(),
            inconsistent: self.inconsistent.clone(),
            inconsistent_count: self.inconsistent_count,
        }
    }

    /// Room for `cycles` more cycles without growing its arrays (the factor of P_UU aside:
    /// its renewals rebuild it).
    pub fn try_reserve(&mut self, cycles: usize) -> Result<(), std::collections::TryReserveError> {
        self.intervals.try_reserve(cycles)?;
        self.determined.try_reserve(cycles)?;
        self.inconsistent.try_reserve(cycles)?;
        Ok(())
    }

    /// Register cycles up to `model.len()` (undetermined, no candidates yet).
    pub fn grow(&mut self, cycles: usize) {
        let blank = Interval {
            lo: 0,
            hi: 0,
            inconsistent: false,
        };
        self.intervals.resize(cycles, blank);
        self.determined.resize(cycles, false);
        self.inconsistent.resize(cycles, None);
    }

    /// Forget the cycles from `len` on (never determined ones): the online estimator takes back
    /// the cycle of a quarantined loop closure. Their failed tests are forgotten too.
    pub fn truncate(&mut self, len: usize) {
        for x in self.inconsistent.drain(len.min(self.inconsistent.len())..) {
            self.inconsistent_count -= usize::from(x.is_some());
        }
        self.intervals.truncate(len);
        self.determined.truncate(len);
    }

    /// Current candidates of cycle i.
    pub fn interval(&self, i: usize) -> Interval {
        self.intervals[i]
    }

    /// Whether cycle i is determined.
    pub fn is_determined(&self, i: usize) -> bool {
        self.determined[i]
    }

    /// Number of cycles that failed their consistency test so far.
    pub fn inconsistent_count(&self) -> usize {
        self.inconsistent_count
    }

    /// Undetermined cycles, ascending.
    pub fn undetermined(&self) -> Vec<usize> {
        (0..self.determined.len())
            .filter(|&i| !self.determined[i])
            .collect()
    }

    /// Density of `P_UU`.
    pub fn density(&self, model: &GammaModel) -> f64 {
        let u = self.cond.len();
        if u == 0 {
            0.0
        } else {
            model.nnz_within(&self.determined) as f64 / (u * u) as f64
        }
    }

    /// Test cycle i with its conditional moments at half-width factor q: store and return its
    /// candidates; an empty interval is recorded as a failed test (edges from `edges`).
    pub fn test(
        &mut self,
        i: usize,
        m: Moments,
        q: f64,
        edges: impl FnOnce() -> Vec<usize>,
    ) -> Interval {
        let iv = Interval::new(m, q);
        self.intervals[i] = iv;
        if iv.inconsistent && self.inconsistent[i].is_none() {
            self.inconsistent[i] = Some((normalised_residual(m), q, edges()));
            self.inconsistent_count += 1;
        }
        iv
    }

    /// Screen cycle i given the determined set and determine it when one candidate is left,
    /// with a single sparse solve. Returns its moments, its candidates and whether it was
    /// determined (a numerically singular determination leaves it undetermined).
    pub fn screen(
        &mut self,
        model: &GammaModel,
        i: usize,
        q: f64,
        edges: impl FnOnce() -> Vec<usize>,
    ) -> (Moments, Interval, bool) {
        self.screen_unless(model, i, q, edges, |_| false)
    }

    /// [`Self::screen`], except that the cycle is not determined when `veto(moments)` holds
    /// (the online quarantine's sharpened angle test: a cycle about to be quarantined must not
    /// enter the conditioning).
    pub fn screen_unless(
        &mut self,
        model: &GammaModel,
        i: usize,
        q: f64,
        edges: impl FnOnce() -> Vec<usize>,
        veto: impl Fn(Moments) -> bool,
    ) -> (Moments, Interval, bool) {
        let (m, outcome) = self.cond.decide(model, i, |m| decision(m, q, &veto));
        let iv = self.test(i, m, q, edges);
        if let Ok(Some(v)) = outcome {
            self.settle(i, v);
            return (m, iv, true);
        }
        (m, iv, false)
    }

    /// [`Self::screen_unless`] with the conditional moments `m` of cycle i given the
    /// determined set computed by the caller (the online estimator's prediction from its
    /// factor): the same test and decision. A cycle determined here is not appended to the
    /// conditioner; the caller appends it ([`Self::determine`]) before the conditioner is used
    /// again. Returns its candidates and its value when determined.
    pub fn screen_given(
        &mut self,
        i: usize,
        m: Moments,
        q: f64,
        edges: impl FnOnce() -> Vec<usize>,
        veto: impl Fn(Moments) -> bool,
    ) -> (Interval, Option<i64>) {
        let value = decision(m, q, &veto);
        let iv = self.test(i, m, q, edges);
        if let Some(v) = value {
            self.settle(i, v);
        }
        (iv, value)
    }

    fn settle(&mut self, i: usize, v: i64) {
        self.determined[i] = true;
        self.intervals[i] = Interval {
            lo: v,
            hi: v,
            inconsistent: false,
        };
    }

    /// Determine cycle i with value v (appends to the conditioner). On error nothing changes.
    pub fn determine(
        &mut self,
        model: &GammaModel,
        i: usize,
        v: i64,
    ) -> Result<Moments, SingularError> {
        let m = self.cond.determine(model, i, v)?;
        self.settle(i, v);
        Ok(m)
    }

    fn log10_product(&self) -> f64 {
        self.intervals
            .iter()
            .map(|iv| (iv.count() as f64).log10())
            .sum()
    }

    /// First screening iterated to its fixed point (method [§3](crate::method#3-first-screening)):
    /// every undetermined cycle i is tested conditioned on the determined set at half-width
    /// factor `q(i)`; the newly determined are appended in a fill-reducing order; repeat until
    /// nothing changes. Appends its rows to `rows`.
    pub fn first_screening(
        &mut self,
        model: &GammaModel,
        q: &dyn Fn(usize) -> f64,
        cycle_edges: &dyn Fn(usize) -> Vec<usize>,
        rows: &mut Vec<Iteration>,
    ) -> Result<(), SingularError> {
        let start_rows = rows.len();
        loop {
            let start = Instant::now();
            let density = self.density(model);
            let mut newly = Vec::new();
            for i in self.undetermined() {
                let m = self.cond.moments(model, i);
                if self.test(i, m, q(i), || cycle_edges(i)).single().is_some() {
                    newly.push(i);
                }
            }
            for i in model.fill_reducing_order(&newly) {
                self.determine(model, i, self.intervals[i].lo)?;
            }
            if !newly.is_empty() || rows.len() == start_rows {
                rows.push(Iteration {
                    iteration: rows.len() + 1,
                    determined: newly.len(),
                    determined_percent: percent(newly.len(), model.len()),
                    density,
                    log10_candidates: self.log10_product(),
                    seconds: start.elapsed().as_secs_f64(),
                });
            }
            if newly.is_empty() || self.cond.len() == model.len() {
                return Ok(());
            }
        }
    }

    /// Second screening iterated (method [§4](crate::method#4-second-screening)), then the
    /// hypotheses, their χ² and the success-rate bound. `first` are the first-screening rows
    /// already run; `q(i)` is cycle i's half-width factor.
    pub fn finish(
        &mut self,
        model: &GammaModel,
        cfg: &ScreeningConfig,
        q: &dyn Fn(usize) -> f64,
        cycle_edges: &dyn Fn(usize) -> Vec<usize>,
        first: Vec<Iteration>,
    ) -> Result<Screened, SingularError> {
        let ell = model.len();
        let mut second = Vec::new();
        let (ambiguous, raw, outcome, joint) = loop {
            let start = Instant::now();
            let set = self.undetermined();
            if set.is_empty() {
                break (set, vec![(Vec::new(), 0.0)], SecondOutcome::Complete, None);
            }
            let (means, cov) = self.cond.joint(model, &set);
            let jg = JointGaussian::new(&means, &cov).ok_or(SingularError {
                cycle: set[0],
                var: f64::NAN,
            })?;
            let boxes: Vec<Interval> = set.iter().map(|&i| self.intervals[i]).collect();
            let r2 = chi2_quantile(set.len() as f64, 1.0 - cfg.joint_level());
            let found = match jg.enumerate(&boxes, r2, cfg.max_hypotheses) {
                Err(too_many) => {
                    let boot = jg.bootstrap(&boxes);
                    break (set, vec![boot], SecondOutcome::TooMany(too_many), Some(jg));
                }
                Ok(found) if found.is_empty() => {
                    let boot = jg.bootstrap(&boxes);
                    break (set, vec![boot], SecondOutcome::NoneInside, Some(jg));
                }
                Ok(found) => found,
            };
            let fixed: Vec<(usize, i64)> = (0..set.len())
                .filter(|&p| found.iter().all(|(v, _)| v[p] == found[0].0[p]))
                .map(|p| (set[p], found[0].0[p]))
                .collect();
            if fixed.is_empty() {
                break (set, found, SecondOutcome::Complete, Some(jg));
            }
            let density = self.density(model);
            for &(i, v) in &fixed {
                self.determine(model, i, v)?;
            }
            let mut rows = Vec::new();
            self.first_screening(model, q, cycle_edges, &mut rows)?;
            let more: usize = rows.iter().map(|r| r.determined).sum();
            second.push(Iteration {
                iteration: second.len() + 1,
                determined: fixed.len() + more,
                determined_percent: percent(fixed.len() + more, ell),
                density,
                log10_candidates: (found.len() as f64).log10(),
                seconds: start.elapsed().as_secs_f64(),
            });
        };

        let base = self.cond.chi2();
        let mut hypotheses: Vec<Hypothesis> = raw
            .into_iter()
            .map(|(values, form)| {
                let chi2 = base + form;
                Hypothesis {
                    values,
                    chi2,
                    p_value: chi2_p_value(ell, chi2),
                }
            })
            .collect();
        hypotheses.sort_by(|a, b| {
            a.chi2
                .total_cmp(&b.chi2)
                .then_with(|| a.values.cmp(&b.values))
        });
        let joint_sds: Vec<f64> = joint
            .map(|j| j.d.iter().map(|d| d.sqrt()).collect())
            .unwrap_or_default();
        let sds = self.cond.conditional_sds().iter().copied().chain(joint_sds);
        let determined_gamma = (0..ell).map(|i| self.cond.value(i).unwrap_or(0)).collect();
        let inconsistent = self
            .inconsistent
            .iter()
            .enumerate()
            .filter_map(|(cycle, x)| {
                x.as_ref().map(|(residual, q, edges)| InconsistentCycle {
                    cycle,
                    edges: edges.clone(),
                    residual: *residual,
                    level: cfg.level_of_quantile(*q),
                })
            })
            .collect();
        Ok(Screened {
            first,
            second,
            outcome,
            determined_gamma,
            determined: self.cond.len(),
            ambiguous,
            inconsistent,
            hypotheses,
            success_lower_bound: success_lower_bound(sds),
        })
    }
}

fn percent(k: usize, n: usize) -> f64 {
    if n == 0 {
        100.0
    } else {
        100.0 * k as f64 / n as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spending_bound_is_the_documented_sum() {
        const N: usize = 1 << 20;
        let head: f64 = (0..N).map(|t| spending_term(t as f64)).sum();
        let n = N as f64;
        let bound = (head + spending_term(n) + 1.0 / (n + SPENDING_OFFSET).ln()) * (1.0 + 1e-9);
        assert_eq!(bound, SPENDING_SUM_BOUND);
    }

    #[test]
    fn quantiles_match_tables() {
        let per = ScreeningConfig::default().per_cycle();
        assert!((per.quantile(100) - 6.6349f64.sqrt()).abs() < 1e-3);
        assert!((ScreeningConfig::paper().quantile(100) - 11.3449f64.sqrt()).abs() < 1e-3);
        let fw = ScreeningConfig::default();
        assert!(fw.family_wise);
        assert!(fw.quantile(100) > per.quantile(100));
        assert!((fw.level(100) - 5e-5).abs() < 1e-18);
        assert!((fw.joint_level() - 5e-3).abs() < 1e-18);
        // The d = 1 closed form agrees with the χ² quantile, and inverts back to the level.
        for level in [0.3, 0.01, 1e-5, 1e-9] {
            let q = fw.quantile_at(level);
            let chi = chi2_quantile(1.0, 1.0 - level).sqrt();
            if level >= 1e-9 {
                assert!((q - chi).abs() < 1e-6 * chi, "{level}: {q} vs {chi}");
            }
            assert!((fw.level_of_quantile(q) / level - 1.0).abs() < 1e-9);
        }
        assert!(fw.quantile_at(1e-30).is_finite());
        let paper = ScreeningConfig::paper();
        assert!((paper.level_of_quantile(paper.quantile(10)) - 0.01).abs() < 1e-9);
    }

    /// The spending weights sum to at most 1 (a direct sum far beyond any run, plus the
    /// integral bound of the tail), decrease, and the online levels are per-cycle α when not
    /// family-wise.
    #[test]
    fn spending_sequence_spends_at_most_alpha() {
        let n = 4_000_000usize;
        let head: f64 = (0..n).map(spending_weight).sum();
        let tail = (1.0 / ((n as f64) + SPENDING_OFFSET).ln()) / spending_sum_bound();
        assert!(head + tail <= 1.0, "{head} + {tail}");
        // Not wastefully small either: the bound is within 1e-6 of the series.
        assert!(head + tail > 1.0 - 1e-6, "{head} + {tail}");
        assert!((1..1000).all(|t| spending_weight(t) < spending_weight(t - 1)));
        let fw = ScreeningConfig::default();
        assert!((fw.online_level(0) - 0.005 * spending_weight(0)).abs() < 1e-18);
        let per = fw.per_cycle();
        assert_eq!(per.online_level(12345), 0.01);
        assert_eq!(per.online_quantile(7), per.quantile(3));
        // Power: at t = 2000 the interval is at most 15 % wider than Bonferroni's at ℓ = 2000.
        assert!(fw.online_quantile(2000) < 1.15 * fw.quantile(2000));
    }

    #[test]
    fn intervals_and_inconsistency() {
        let q = 2.576;
        let det = Interval::new(
            Moments {
                mean: 3.02,
                var: 0.01,
            },
            q,
        );
        assert_eq!(det.single(), Some(3));
        let amb = Interval::new(
            Moments {
                mean: 0.5,
                var: 0.04,
            },
            q,
        );
        assert_eq!((amb.lo, amb.hi, amb.single()), (0, 1, None));
        let empty = Interval::new(
            Moments {
                mean: -0.5,
                var: 1e-4,
            },
            q,
        );
        assert!(empty.inconsistent);
        assert_eq!((empty.lo, empty.hi, empty.single()), (-1, 0, None));
    }

    /// Brute force over the box for a small correlated Gaussian.
    #[test]
    fn enumeration_equals_brute_force() {
        let mean = [0.3, -0.6, 1.4];
        let q = [0.5, 0.2, -0.1, 0.2, 0.4, 0.05, -0.1, 0.05, 0.3];
        let boxes = [
            Interval {
                lo: -2,
                hi: 2,
                inconsistent: false,
            },
            Interval {
                lo: -3,
                hi: 1,
                inconsistent: false,
            },
            Interval {
                lo: 0,
                hi: 3,
                inconsistent: false,
            },
        ];
        let jg = JointGaussian::new(&mean, &q).unwrap();
        // Inverse of q by Cramer's rule for the reference quadratic form.
        let inv = {
            let m = |i: usize, j: usize| q[i * 3 + j];
            let det = m(0, 0) * (m(1, 1) * m(2, 2) - m(1, 2) * m(2, 1))
                - m(0, 1) * (m(1, 0) * m(2, 2) - m(1, 2) * m(2, 0))
                + m(0, 2) * (m(1, 0) * m(2, 1) - m(1, 1) * m(2, 0));
            let c = |i: usize, j: usize| {
                let (r, s): (Vec<usize>, Vec<usize>) = (
                    (0..3).filter(|&x| x != j).collect(),
                    (0..3).filter(|&x| x != i).collect(),
                );
                let v = m(r[0], s[0]) * m(r[1], s[1]) - m(r[0], s[1]) * m(r[1], s[0]);
                if (i + j).is_multiple_of(2) {
                    v / det
                } else {
                    -v / det
                }
            };
            [
                [c(0, 0), c(0, 1), c(0, 2)],
                [c(1, 0), c(1, 1), c(1, 2)],
                [c(2, 0), c(2, 1), c(2, 2)],
            ]
        };
        for r2 in [0.5, 2.0, 7.8, 30.0] {
            let mut want = Vec::new();
            for a in -2..=2 {
                for b in -3..=1 {
                    for c in 0..=3 {
                        let d = [a as f64 - mean[0], b as f64 - mean[1], c as f64 - mean[2]];
                        let f: f64 = (0..3)
                            .flat_map(|i| (0..3).map(move |j| (i, j)))
                            .map(|(i, j)| d[i] * inv[i][j] * d[j])
                            .sum();
                        if f <= r2 {
                            want.push((vec![a, b, c], f));
                        }
                    }
                }
            }
            let mut got = jg.enumerate(&boxes, r2, 1000).unwrap();
            got.sort_by(|x, y| x.0.cmp(&y.0));
            assert_eq!(got.len(), want.len(), "r2 = {r2}");
            for (g, w) in got.iter().zip(&want) {
                assert_eq!(g.0, w.0);
                assert!((g.1 - w.1).abs() < 1e-9);
            }
        }
        let capped = jg.enumerate(&boxes, 30.0, 5);
        assert!(matches!(
            capped,
            Err(TooMany {
                found: 5,
                cap: 5,
                ..
            })
        ));
    }

    #[test]
    fn levels_the_arithmetic_cannot_hold_are_rejected() {
        for alpha in [1e-17, 1e-300, f64::MIN_POSITIVE] {
            let c = ScreeningConfig {
                alpha,
                ..ScreeningConfig::default()
            };
            let e = c.validate().unwrap_err();
            assert!(e.0.contains("too small"), "{e}");
        }
        let c = ScreeningConfig {
            alpha: 1e-15,
            ..ScreeningConfig::default()
        };
        assert!(c.validate().is_ok() && c.quantile(1).is_finite());
    }

    #[test]
    fn huge_intervals_stay_in_range() {
        let m = Moments {
            mean: 3.0,
            var: 1e300,
        };
        for q in [1.0, f64::INFINITY] {
            let iv = Interval::new(m, q);
            assert_eq!((iv.lo, iv.hi), (-MAX_CANDIDATE, MAX_CANDIDATE));
            assert_eq!(iv.count(), (1u64 << 54) + 1);
        }
        let far = Interval::new(
            Moments {
                mean: 1e300,
                var: 1e-6,
            },
            1.0,
        );
        assert!(far.hi <= MAX_CANDIDATE && far.lo < far.hi);
    }

    #[test]
    fn enumeration_memory_is_bounded() {
        let k = 50;
        let mut q = vec![0.0; k * k];
        for i in 0..k {
            q[i * k + i] = 1.0;
        }
        let jg = JointGaussian::new(&vec![0.5; k], &q).unwrap();
        let boxes = vec![
            Interval {
                lo: 0,
                hi: 1,
                inconsistent: false
            };
            k
        ];
        let per_vector = 8 * k + 32;
        let r = jg.enumerate_within(&boxes, 1e9, 1_000_000, 10 * per_vector);
        let Err(t) = r else { panic!("not capped") };
        assert_eq!((t.found, t.limit), (10, Limit::Memory));
        let r = jg.enumerate_within(&boxes, 1e9, 5, 10 * per_vector);
        assert!(matches!(
            r,
            Err(TooMany {
                found: 5,
                limit: Limit::Hypotheses,
                ..
            })
        ));
    }

    #[test]
    fn success_bound_is_a_probability() {
        assert!((rounding_success(0.01) - 1.0).abs() < 1e-12);
        let b = success_lower_bound([0.1, 0.2, 0.3]);
        assert!(b > 0.0 && b < 1.0);
        assert!((rounding_success(0.5) - 0.6826894921).abs() < 1e-8);
    }
}
