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

use crate::gamma::Moments;

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

mod joint;
mod screener;

pub use joint::{JointGaussian, Limit, MAX_ENUMERATION_BYTES, TooMany, ldl};
pub use screener::{Hypothesis, InconsistentCycle, Iteration, Screened, Screener, SecondOutcome};

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
    fn success_bound_is_a_probability() {
        assert!((rounding_success(0.01) - 1.0).abs() < 1e-12);
        let b = success_lower_bound([0.1, 0.2, 0.3]);
        assert!(b > 0.0 && b < 1.0);
        assert!((rounding_success(0.5) - 0.6826894921).abs() < 1e-8);
    }
}
