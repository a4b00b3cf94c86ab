//! The screening driven to the end (method [§3](crate::method#3-first-screening),
//! [§4](crate::method#4-second-screening)): [`Screener`] holds the conditioning on the determined
//! cycles and every cycle's candidates, tests a cycle (first screening: the integers of
//! `[m_i − q_i s_i, m_i + q_i s_i]`, one left: determined), iterates until nothing changes, then
//! enumerates the ambiguous set's joint candidates ([`super::JointGaussian`]) and reports the
//! hypotheses with their χ² and the success bound ([`Screened`]). The batch pipeline and the
//! online estimator both drive it.

use std::time::Instant;

use super::{
    Interval, JointGaussian, ScreeningConfig, TooMany, chi2_p_value, chi2_quantile,
    normalised_residual, success_lower_bound,
};
use crate::gamma::{Conditioner, GammaModel, Moments, SingularError};

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
