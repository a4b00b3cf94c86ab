//! The second screening's search (method [§4](crate::method#4-second-screening)): the integer
//! vectors `v` of a candidate box with `(v − m)ᵀ Q⁻¹ (v − m) ≤ r²`, enumerated depth-first over
//! `Q = L D Lᵀ` (coordinates ordered by increasing variance, each level's range the box cut by
//! what the ellipsoid leaves, `c_i ± sqrt(d_i (r² − partial_i))`), with caps on the vectors
//! found, the partial vectors visited and the memory; and integer bootstrapping (sequential
//! rounding), the answer when the search is capped.

use super::Interval;

/// Memory the second screening may use for the vectors it enumerates: 256 MiB. A vector of k
/// coordinates costs `8k + 32` bytes, so the effective cap is
/// `min(max_hypotheses, MAX_ENUMERATION_BYTES / (8k + 32))`.
pub const MAX_ENUMERATION_BYTES: usize = 256 << 20;

/// Which bound stopped an enumeration.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Limit {
    /// [`max_hypotheses`](super::ScreeningConfig::max_hypotheses) vectors were found.
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

#[cfg(test)]
mod tests {
    use super::*;

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
}
