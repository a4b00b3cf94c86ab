//! Screening the cycle integers γ (METHOD.md §3, §4, §8).
//!
//! **First screening** (per cycle): with `q = sqrt(χ²_d⁻¹(1 − α'))`, the candidates of γ_i are
//! the integers in `[m_i − q s_i, m_i + q s_i]`, where `(m_i, s_i²)` are the mean and variance of
//! γ_i conditioned on the determined set U. A cycle with a single candidate is determined
//! (moved to U); iterate until nothing changes. `α' = α` per cycle (the paper), or `α/(2ℓ)`
//! (Bonferroni, [`ScreeningConfig::family_wise`], with the other α/2 for the joint test) so
//! the whole surviving set contains the truth with probability ≥ 1 − α. An interval holding no integer marks the cycle **inconsistent** at
//! that level: it stays ambiguous with its two nearest integers, and is reported.
//!
//! **Second screening** (joint): the vectors `v` of the candidate box with
//! `(v − m_A)ᵀ Q_A⁻¹ (v − m_A) ≤ χ²_{|A|}⁻¹(1 − α)`, `Q_A` the conditional covariance of the
//! ambiguous set, are enumerated by sphere decoding over `Q_A = L D Lᵀ`
//! (Schnorr–Euchner-style depth-first search, each coordinate clamped to its box), never by
//! materialising the Cartesian product; with an explicit cap. Coordinates equal in every
//! surviving vector are determined and the screening repeats.
//!
//! **Success-rate bound** (Teunissen 1998): `Π_i (2Φ(1/(2 s_i)) − 1) = Π_i erf(1/(2√2 s_i))`
//! over the sequential conditional standard deviations.

use statrs::distribution::{ChiSquared, ContinuousCDF};

use crate::gamma::Moments;

/// Screening settings.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct ScreeningConfig {
    /// Significance level α.
    pub alpha: f64,
    /// Degrees of freedom of the χ² quantile of the per-cycle test (1 is the standard
    /// choice for a scalar; the paper used 3).
    pub dof: u32,
    /// Per-cycle level α/ℓ (Bonferroni), so that the surviving set holds the truth with
    /// probability ≥ 1 − α as a whole.
    pub family_wise: bool,
    /// Cap on the hypotheses enumerated by the second screening.
    pub max_hypotheses: usize,
}

impl Default for ScreeningConfig {
    /// α = 0.01, 1 degree of freedom, per-cycle level, cap 10⁶.
    fn default() -> Self {
        Self {
            alpha: 0.01,
            dof: 1,
            family_wise: false,
            max_hypotheses: 1_000_000,
        }
    }
}

/// Invalid screening settings.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("invalid screening setting: {0}")]
pub struct ConfigError(pub String);

impl ScreeningConfig {
    /// The paper's setting: α = 0.01, 3 degrees of freedom, per-cycle level.
    pub fn paper() -> Self {
        Self {
            dof: 3,
            ..Self::default()
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

    /// Interval half-width factor `q = sqrt(χ²_d⁻¹(1 − level))`.
    pub fn quantile(&self, cycles: usize) -> f64 {
        chi2_quantile(f64::from(self.dof), 1.0 - self.level(cycles)).sqrt()
    }
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
    /// Candidates of a cycle with conditional moments `m` and half-width factor `q`.
    pub fn new(m: Moments, q: f64) -> Self {
        let half = q * m.sd();
        let lo = (m.mean - half).ceil();
        let hi = (m.mean + half).floor();
        if lo <= hi {
            Self {
                lo: lo as i64,
                hi: hi as i64,
                inconsistent: false,
            }
        } else {
            let f = m.mean.floor() as i64;
            Self {
                lo: f,
                hi: f + 1,
                inconsistent: true,
            }
        }
    }

    /// Number of candidates.
    pub fn count(&self) -> u64 {
        self.hi.abs_diff(self.lo) + 1
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

/// Why enumeration stopped early.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct TooMany {
    /// Vectors found before stopping (`cap` unless the search budget ran out first).
    pub found: usize,
    /// The cap.
    pub cap: usize,
    /// Partial vectors visited by the search (its budget is `64 · cap`).
    pub visited: usize,
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
    /// vectors, or when the search has visited `64 · cap` partial vectors.
    pub fn enumerate(
        &self,
        boxes: &[Interval],
        r2: f64,
        cap: usize,
    ) -> Result<Vec<(Vec<i64>, f64)>, TooMany> {
        let k = self.mean.len();
        let mut out = Vec::new();
        if k == 0 {
            out.push((Vec::new(), 0.0));
            return Ok(out);
        }
        let budget = cap.saturating_mul(64);
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
                if out.len() >= cap {
                    return Err(TooMany {
                        found: out.len(),
                        cap,
                        visited: visits,
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_match_tables() {
        let per = ScreeningConfig::default();
        assert!((per.quantile(100) - 6.6349f64.sqrt()).abs() < 1e-3);
        assert!((ScreeningConfig::paper().quantile(100) - 11.3449f64.sqrt()).abs() < 1e-3);
        let fw = ScreeningConfig {
            family_wise: true,
            ..per
        };
        assert!(fw.quantile(100) > per.quantile(100));
        assert!((fw.level(100) - 5e-5).abs() < 1e-18);
        assert!((fw.joint_level() - 5e-3).abs() < 1e-18);
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
                if (i + j) % 2 == 0 { v / det } else { -v / det }
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
    fn success_bound_is_a_probability() {
        assert!((rounding_success(0.01) - 1.0).abs() < 1e-12);
        let b = success_lower_bound([0.1, 0.2, 0.3]);
        assert!(b > 0.0 && b < 1.0);
        assert!((rounding_success(0.5) - 0.6826894921).abs() < 1e-8);
    }
}
