//! A loop closure's step: the new cycle screened (after its translation and angle tests when
//! quarantine is on), the ambiguous cycles that share an edge with a newly determined one
//! re-screened with fresh conditional moments, and the wraps that follow γ:
//!
//! ```text
//! k_chord = s_chord · (γ_t − Σ_rest s_e k_e)     (s: the edge's sign in cycle t)
//! ```
//!
//! by forward substitution in cycle order, re-done only for the cycles a step changed and the
//! later cycles through a chord whose wrap moved. Between determinations an ambiguous cycle's
//! γ is its most likely integer: the rounded conditional mean, clamped to its candidates.

use std::collections::{BTreeSet, VecDeque};

use super::{
    ANGLE_SCALE_MAX_SD, ANGLE_TEST, CycleStep, Decision, NONE, OnlineError, OnlineEstimator,
    Rescreen, Step, StepKind, TRANSLATION_TEST, checkpoint, quarantine,
};
use crate::batch::RejectedEdge;
use crate::closure;
use crate::cycles::Cycle;
#[cfg(doc)]
use crate::cycles::IncrementalBasis;
use crate::gamma::Moments;
use crate::graph::{Edge, NodePolicy};
use crate::screening::normalised_residual;

impl OnlineEstimator {
    /// A loop closure between connected nodes a and b (input index `input`). Its cycle is the
    /// one [`IncrementalBasis::probe`] finds; with quarantine on, it is tested first —
    /// translation closure at `level`, then the angle (the cycle's screening) — and a failed
    /// test returns the rejection with nothing changed. Otherwise the edge is added: basis,
    /// γ model, conditioning, estimate.
    pub(super) fn add_chord(
        &mut self,
        input: usize,
        edge: Edge,
        a: usize,
        b: usize,
        level: f64,
    ) -> Result<Result<Step, RejectedEdge>, OnlineError> {
        let e = self.graph.edge_count();
        // At its arrival within a replay, the path it failed on before may serve ([`replay`]).
        let arrival = input == self.arrivals;
        let hinted = (self.hints.as_ref())
            .filter(|_| arrival)
            .and_then(|h| h.cycle(input, &self.paths, e));
        let cycle = (hinted.or_else(|| self.basis.probe(a, b))).ok_or(OnlineError::NoCycle {
            from: edge.from(),
            to: edge.to(),
        })?;
        let quarantine = self.config.quarantine;
        let reject = |test: &'static str, statistic: f64, threshold: f64| RejectedEdge {
            edge: input,
            from: edge.from(),
            to: edge.to(),
            test,
            statistic,
            threshold,
        };
        let noise = closure::EdgeNoise::of(&edge);
        debug_assert_eq!(self.noise.len(), e, "one closure noise per graph edge");
        if quarantine {
            let limit = closure::threshold(level);
            let far = closure::threshold(self.eviction_level(self.model.len()));
            let (angle_scale, translation_scale) = (self.angle_scale(), self.translation_scale());
            // Failing the eviction level's threshold and the test's by far (so the test's own)
            // at the first end decides everything below, the re-test schedule included.
            let decided = |chi2: f64| {
                let tested = chi2 / translation_scale;
                closure::fails(tested, far) && quarantine::translation_by_far(tested, limit)
            };
            let translation =
                (self.closure_with(&cycle.terms, &[noise], angle_scale, &decided)).map(|c| c.chi2);
            if let Some(chi2) = translation {
                let tested = chi2 / translation_scale;
                // A doubtful loop closure that passes: a copy of the state before anything of
                // it is kept, from which a replay starts should it be evicted (module
                // `checkpoint`).
                if arrival
                    && !closure::fails(tested, limit)
                    && checkpoint::doubtful(cycle.terms.len(), tested, limit)
                {
                    self.checkpoint_before_doubtful();
                }
                if !closure::fails(tested, far) {
                    self.scale.push(chi2);
                }
                if closure::fails(tested, limit) {
                    if closure::fails(tested, far) {
                        self.suspect(&cycle, edge);
                    }
                    if arrival {
                        self.paths.failed(input, &cycle, &self.input_of);
                    }
                    return Ok(Err(reject(TRANSLATION_TEST, tested, limit)));
                }
            }
        }
        self.sigma2.push(edge.sigma2());
        self.delta.push(edge.delta());
        self.noise.push(noise);
        let t = self.model.push_cycle(&cycle, &self.sigma2, &self.delta);
        self.screener.grow(t + 1);
        let q = self.config.screening.quantile_at(level);
        // The angle test at the angle noise scale s_θ (module docs): the residual to the
        // nearest integer in sd·√s_θ; s_θ = 1 is the interval holding no integer. A cycle
        // that fails it is not determined.
        let root = self.angle_scale().sqrt();
        let fails = |m: Moments| quarantine && normalised_residual(m) / root > q;
        // The moments from the estimate's factor when it holds exactly the determined
        // cycles' information (module docs: one factor); otherwise from P_UU.
        let predicted = self.predict(&cycle, &edge, a, b);
        let (m, iv, determined) = match predicted {
            Some(m) => {
                let (iv, value) = (self.screener).screen_given(t, m, q, || edges_of(&cycle), fails);
                if let Some(v) = value {
                    self.backlog.push((t as u32, v, m.sd()));
                } else {
                    self.estimate.undo_chord();
                }
                (m, iv, value.is_some())
            }
            None => {
                self.sync_conditioner();
                (self.screener).screen_unless(&self.model, t, q, || edges_of(&cycle), fails)
            }
        };
        let residual = normalised_residual(m) / root;
        let far = self.config.screening.quantile_at(self.eviction_level(t));
        if quarantine && m.sd() < ANGLE_SCALE_MAX_SD && residual <= far {
            let r = normalised_residual(m);
            self.angle_scale.push(r * r);
        }
        // With s_θ ≤ 1 a cycle whose interval holds no integer fails this test too; with
        // s_θ > 1 (the declared angle noise too tight, [`closure::Scale`]) such a cycle is
        // judged in the noise the data show: accepted as inconsistent, its loop closure kept.
        if fails(m) {
            if predicted.is_some() {
                self.estimate.undo_chord();
            }
            self.model.pop_cycle(&cycle);
            self.screener.truncate(t);
            self.sigma2.pop();
            self.delta.pop();
            self.noise.pop();
            if iv.inconsistent || residual > far {
                self.suspect(&cycle, edge);
            }
            if arrival {
                self.paths.failed(input, &cycle, &self.input_of);
            }
            return Ok(Err(reject(ANGLE_TEST, residual, q)));
        }
        // Cannot fail with CreateUnknown between known nodes.
        self.graph.add_edge(edge, NodePolicy::CreateUnknown)?;
        self.basis.commit(a, b, edge.sigma2(), true);
        self.accept(input);

        self.counters.cycles += 1;
        self.chord_cycle[e] = t as u32;
        for term in &cycle.terms[1..] {
            if self.chord_cycle[term.edge as usize] != NONE {
                self.users[term.edge as usize].push(t as u32);
            }
        }
        self.cycles.push(cycle);
        self.gamma.push(0);
        let mut rescreened = Vec::new();
        let kept = predicted.is_some() && determined;
        if kept {
            // No cycle is ambiguous: none to re-screen, and P_UU does not grow.
            self.estimate.keep_chord();
        } else if determined {
            self.propagate(t, &mut rescreened);
            self.maybe_reorder();
        } else {
            self.ambiguous.insert(t, m);
        }
        // The new chord's row with its wrap, then the right-hand sides of the chords whose wrap
        // moved with the re-screened cycles.
        let changed =
            self.update_wraps(std::iter::once(t).chain(rescreened.iter().map(|r| r.cycle)));
        self.push_edge(e, a, b, &changed, kept);
        self.after_step();
        Ok(Ok(Step {
            edge: input,
            kind: StepKind::Cycle(CycleStep {
                cycle: t,
                mean: m.mean,
                sd: m.sd(),
                candidates: iv,
                decision: Decision::of(iv, determined),
            }),
            rescreened,
            quarantined: Vec::new(),
            readmitted: Vec::new(),
        }))
    }

    /// `Σ ±k_e` over a cycle's path (every term but the chord, term 0) at the current wraps.
    pub(super) fn path_wraps(&self, cycle: &Cycle) -> i64 {
        cycle.terms[1..].iter().fold(0i64, |acc, t| {
            acc.saturating_add(i64::from(t.sign).saturating_mul(self.wrap[t.edge as usize]))
        })
    }

    /// The current best γ of cycle i: its determined value, or the rounded conditional mean
    /// (clamped to its candidates) of an ambiguous one.
    pub(super) fn best_gamma(&self, i: usize) -> i64 {
        let iv = self.screener.interval(i);
        if self.screener.is_determined(i) {
            return iv.lo;
        }
        match self.ambiguous.get(&i) {
            Some(m) => (m.mean.round() as i64).clamp(iv.lo, iv.hi),
            None => iv.lo,
        }
    }

    /// Refresh γ of the given cycles and the wraps that depend on them (forward substitution
    /// `k_chord = γ_t − Σ_rest ±k_e`, in cycle order, cascading to later cycles through a chord
    /// whose wrap changed). Returns the edges whose wrap changed.
    pub(super) fn update_wraps(&mut self, cycles: impl Iterator<Item = usize>) -> Vec<usize> {
        let mut work = BTreeSet::new();
        for c in cycles {
            let g = self.best_gamma(c);
            if self.gamma[c] != g || c + 1 == self.gamma.len() {
                self.gamma[c] = g;
                work.insert(c);
            }
        }
        let mut changed = Vec::new();
        while let Some(c) = work.pop_first() {
            let cyc = &self.cycles[c];
            let rest = self.path_wraps(cyc);
            let k = i64::from(cyc.terms[0].sign).saturating_mul(self.gamma[c].saturating_sub(rest));
            let ch = cyc.chord() as usize;
            if self.wrap[ch] != k || c + 1 == self.gamma.len() {
                if self.wrap[ch] != k {
                    changed.push(ch);
                }
                self.wrap[ch] = k;
                work.extend(self.users[ch].iter().map(|&u| u as usize));
            }
        }
        changed
    }

    /// After cycle `first` is determined: re-screen the ambiguous cycles sharing an edge with
    /// it (fresh moments), determine those left with one candidate, and continue from them.
    pub(super) fn propagate(&mut self, first: usize, out: &mut Vec<Rescreen>) {
        let mut queue = VecDeque::from([first]);
        while let Some(c) = queue.pop_front() {
            let neighbours: Vec<usize> = self
                .model
                .row(c)
                .iter()
                .map(|&(j, _)| j as usize)
                .filter(|j| self.ambiguous.contains_key(j))
                .collect();
            for i in neighbours {
                let before = self.screener.interval(i);
                let cycles = &self.cycles;
                let (m, after, determined) = self.screener.screen(
                    &self.model,
                    i,
                    self.config.screening.online_quantile(i),
                    || edges_of(&cycles[i]),
                );
                self.counters.rescreens += 1;
                if determined {
                    self.ambiguous.remove(&i);
                    queue.push_back(i);
                } else {
                    self.ambiguous.insert(i, m);
                }
                let decision = Decision::of(after, determined);
                match out.iter_mut().find(|x| x.cycle == i) {
                    Some(x) => {
                        x.after = after;
                        x.decision = decision;
                        x.changed = x.before != after || determined;
                    }
                    None => out.push(Rescreen {
                        cycle: i,
                        before,
                        after,
                        decision,
                        changed: before != after || determined,
                    }),
                }
            }
        }
        out.sort_by_key(|x| x.cycle);
    }
}

pub(super) fn edges_of(c: &Cycle) -> Vec<usize> {
    c.terms.iter().map(|t| t.edge as usize).collect()
}
