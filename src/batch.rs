//! The batch pipeline of the paper (METHOD.md §2–§6, §8): basis → γ model → first screening
//! (iterated) → second screening (iterated) → hypotheses with χ², p-value and the
//! success-rate bound. It is the reference the online estimator is checked against, and it is
//! only a driver: every formula lives in [`crate::cycles`], [`crate::gamma`],
//! [`crate::screening`], [`crate::wraps`] and [`crate::estimate`].

use std::time::Instant;

use crate::cycles::{BasisKind, CycleBasis};
use crate::gamma::{Conditioner, GammaModel, Moments, SingularError};
use crate::graph::PoseGraph;
use crate::screening::{
    self, ConfigError, Interval, JointGaussian, ScreeningConfig, TooMany, chi2_p_value,
    chi2_quantile,
};
use crate::wraps::{WrapError, WrapSolver};

/// What to run.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct BatchConfig {
    /// Cycle basis.
    pub basis: BasisKind,
    /// Screening settings.
    pub screening: ScreeningConfig,
}

impl Default for BatchConfig {
    fn default() -> Self {
        Self {
            basis: BasisKind::Incremental,
            screening: ScreeningConfig::default(),
        }
    }
}

/// One row of a screening table (the paper's Tables II–III).
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

/// A cycle whose confidence interval held no integer at some iteration.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct InconsistentCycle {
    /// Cycle index in the basis.
    pub cycle: usize,
    /// Its edges (indices in the graph).
    pub edges: Vec<usize>,
    /// Distance from the conditional mean to the nearest integer, in standard deviations.
    pub residual: f64,
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
    /// No vector of the candidate box passes the joint test (the data are inconsistent at
    /// level α): the list holds only the bootstrapping answer.
    NoneInside,
}

/// One surviving hypothesis: values of the final ambiguous cycles, and its χ².
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Hypothesis {
    /// γ on [`BatchResult::ambiguous`], in that order.
    pub values: Vec<i64>,
    /// `(γ − μ)ᵀ P_γ⁻¹ (γ − μ)`.
    pub chi2: f64,
    /// `P(χ²_ℓ > chi2)`.
    pub p_value: f64,
}

/// Everything the pipeline produced.
#[derive(Clone, Debug)]
pub struct BatchResult {
    /// Number of edges of the graph.
    pub edges: usize,
    /// The basis used.
    pub basis: CycleBasis,
    /// The γ model of that basis.
    pub model: GammaModel,
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
    /// Cycles found inconsistent at some iteration.
    pub inconsistent: Vec<InconsistentCycle>,
    /// Hypotheses sorted by χ² (best first).
    pub hypotheses: Vec<Hypothesis>,
    /// Integer-bootstrapping lower bound on the probability that the answer is right.
    pub success_lower_bound: f64,
    /// Time to build the basis.
    pub basis_seconds: f64,
    /// Time for the γ model and both screenings.
    pub screening_seconds: f64,
}

impl BatchResult {
    /// The full γ of a hypothesis.
    pub fn gamma(&self, h: &Hypothesis) -> Vec<i64> {
        let mut g = self.determined_gamma.clone();
        for (&i, &v) in self.ambiguous.iter().zip(&h.values) {
            g[i] = v;
        }
        g
    }

    /// The wraps k of every edge for a hypothesis (`k = [0; C_L⁻¹ γ]`).
    pub fn wraps(&self, h: &Hypothesis) -> Result<Vec<i64>, WrapError> {
        let edges = self.edges;
        WrapSolver::new(&self.basis.cycles, edges)?.wraps(&self.basis.cycles, &self.gamma(h))
    }
}

/// Why the pipeline stopped.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum BatchError {
    /// Bad settings.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// P_γ numerically singular.
    #[error(transparent)]
    Singular(#[from] SingularError),
}

/// Mutable state of the screening, shared by both phases.
struct State<'a> {
    model: &'a GammaModel,
    cond: Conditioner,
    intervals: Vec<Interval>,
    member: Vec<bool>,
    inconsistent: Vec<Option<InconsistentCycle>>,
    cycles: &'a CycleBasis,
    q: f64,
}

impl State<'_> {
    fn density(&self) -> f64 {
        let u = self.cond.len();
        if u == 0 {
            0.0
        } else {
            self.model.nnz_within(&self.member) as f64 / (u * u) as f64
        }
    }

    fn undetermined(&self) -> Vec<usize> {
        (0..self.model.len()).filter(|&i| !self.member[i]).collect()
    }

    fn determine(&mut self, i: usize, v: i64) -> Result<(), SingularError> {
        self.cond.determine(self.model, i, v)?;
        self.member[i] = true;
        self.intervals[i] = Interval {
            lo: v,
            hi: v,
            inconsistent: false,
        };
        Ok(())
    }

    fn note(&mut self, i: usize, m: Moments) {
        if self.intervals[i].inconsistent && self.inconsistent[i].is_none() {
            let edges = self.cycles.cycles[i]
                .terms
                .iter()
                .map(|t| t.edge as usize)
                .collect();
            let residual = screening::normalised_residual(m);
            self.inconsistent[i] = Some(InconsistentCycle {
                cycle: i,
                edges,
                residual,
            });
        }
    }

    fn log10_product(&self) -> f64 {
        self.intervals
            .iter()
            .map(|iv| (iv.count() as f64).log10())
            .sum()
    }

    /// First screening iterated to its fixed point; appends its rows to `rows`.
    fn first_screening(&mut self, rows: &mut Vec<Iteration>) -> Result<(), SingularError> {
        loop {
            let start = Instant::now();
            let density = self.density();
            let mut newly = Vec::new();
            for i in self.undetermined() {
                let m = self.cond.moments(self.model, i);
                self.intervals[i] = Interval::new(m, self.q);
                self.note(i, m);
                if let Some(v) = self.intervals[i].single() {
                    newly.push((i, v));
                }
            }
            // Append in a fill-reducing order (conditioning does not depend on the order).
            let set: Vec<usize> = newly.iter().map(|&(i, _)| i).collect();
            for i in self.model.fill_reducing_order(&set) {
                self.determine(i, self.intervals[i].lo)?;
            }
            if !newly.is_empty() || rows.is_empty() {
                rows.push(Iteration {
                    iteration: rows.len() + 1,
                    determined: newly.len(),
                    determined_percent: percent(newly.len(), self.model.len()),
                    density,
                    log10_candidates: self.log10_product(),
                    seconds: start.elapsed().as_secs_f64(),
                });
            }
            if newly.is_empty() || self.cond.len() == self.model.len() {
                return Ok(());
            }
        }
    }
}

fn percent(k: usize, n: usize) -> f64 {
    if n == 0 {
        100.0
    } else {
        100.0 * k as f64 / n as f64
    }
}

/// Run the whole pipeline on a graph.
pub fn screen(graph: &PoseGraph, config: &BatchConfig) -> Result<BatchResult, BatchError> {
    config.screening.validate()?;
    let t0 = Instant::now();
    let basis = CycleBasis::build(graph, config.basis);
    let basis_seconds = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let sigma2: Vec<f64> = graph.edges().iter().map(|e| e.sigma2()).collect();
    let delta: Vec<f64> = graph.edges().iter().map(|e| e.delta()).collect();
    let model = GammaModel::from_cycles(&basis.cycles, &sigma2, &delta);
    let ell = model.len();
    let cfg = config.screening;
    let mut st = State {
        model: &model,
        cond: Conditioner::new(),
        intervals: vec![
            Interval {
                lo: 0,
                hi: 0,
                inconsistent: false
            };
            ell
        ],
        member: vec![false; ell],
        inconsistent: vec![None; ell],
        cycles: &basis,
        q: cfg.quantile(ell),
    };
    let mut first = Vec::new();
    st.first_screening(&mut first)?;

    // Second screening, iterated.
    let mut second = Vec::new();
    let (ambiguous, hypotheses_raw, outcome, joint) = loop {
        let start = Instant::now();
        let set = st.undetermined();
        if set.is_empty() {
            break (set, vec![(Vec::new(), 0.0)], SecondOutcome::Complete, None);
        }
        let (means, q) = st.cond.joint(&model, &set);
        let jg = JointGaussian::new(&means, &q).ok_or(SingularError {
            cycle: set[0],
            var: f64::NAN,
        })?;
        let boxes: Vec<Interval> = set.iter().map(|&i| st.intervals[i]).collect();
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
        let density = st.density();
        for &(i, v) in &fixed {
            st.determine(i, v)?;
        }
        let mut rows = Vec::new();
        st.first_screening(&mut rows)?;
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

    let base_chi2 = st.cond.chi2();
    let mut hypotheses: Vec<Hypothesis> = hypotheses_raw
        .into_iter()
        .map(|(values, form)| {
            let chi2 = base_chi2 + form;
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

    let sds = st.cond.conditional_sds().iter().copied();
    let joint_sds: Vec<f64> = joint
        .map(|j| j.d.iter().map(|d| d.sqrt()).collect())
        .unwrap_or_default();
    let success_lower_bound = screening::success_lower_bound(sds.chain(joint_sds));

    let mut determined_gamma = vec![0i64; ell];
    for (i, g) in determined_gamma.iter_mut().enumerate() {
        *g = st.cond.value(i).unwrap_or(0);
    }
    let inconsistent = st.inconsistent.into_iter().flatten().collect();
    let determined = st.cond.len();
    Ok(BatchResult {
        edges: graph.edge_count(),
        basis,
        first,
        second,
        outcome,
        determined_gamma,
        determined,
        ambiguous,
        inconsistent,
        hypotheses,
        success_lower_bound,
        basis_seconds,
        screening_seconds: t1.elapsed().as_secs_f64(),
        model,
    })
}
