//! Orthonormal associated Legendre functions and Gauss-Legendre quadrature, the two pieces of
//! the spherical-harmonic transform in [`crate::sh`].
//!
//! `Pbar(l, m, x)` is normalised so that `Y_lm(theta, phi) = Pbar(l, m, cos theta) e^{i m phi}`
//! is orthonormal on the sphere (`2 pi integral_{-1}^{1} Pbar^2 dx = 1`), without the
//! Condon-Shortley phase (the convolution in [`crate::preconvolve`] only scales each degree,
//! so the sign convention cancels between analysis and synthesis).

use std::f64::consts::PI;

/// Recurrence coefficients for all `0 <= m <= l <= lmax`, indexed by [`LegendreTable::index`].
#[derive(Clone, Debug)]
pub struct LegendreTable {
    lmax: usize,
    /// `a_lm = sqrt((4 l^2 - 1) / (l^2 - m^2))`
    a: Vec<f64>,
    /// `b_lm = sqrt(((l - 1)^2 - m^2) / (4 (l - 1)^2 - 1))`
    b: Vec<f64>,
    /// `sqrt((2m + 1) / (2m))` for the diagonal `Pbar(m, m)`.
    diag: Vec<f64>,
}

/// Values of `Pbar(m, m, x)` smaller than this are treated as zero: every `Pbar(l, m)` built
/// on them stays below 1e-220, far under anything a light map can resolve.
const UNDERFLOW: f64 = 1e-280;

impl LegendreTable {
    /// Tables up to degree `lmax`.
    pub fn new(lmax: usize) -> Self {
        let n = Self::len_for(lmax);
        let mut a = vec![0.0; n];
        let mut b = vec![0.0; n];
        for m in 0..=lmax {
            for l in m + 2..=lmax {
                let (lf, mf) = (l as f64, m as f64);
                let i = Self::index_for(lmax, l, m);
                a[i] = ((4.0 * lf * lf - 1.0) / (lf * lf - mf * mf)).sqrt();
                let l1 = lf - 1.0;
                b[i] = ((l1 * l1 - mf * mf) / (4.0 * l1 * l1 - 1.0)).sqrt();
            }
        }
        let diag = (0..=lmax)
            .map(|m| {
                if m == 0 {
                    0.0
                } else {
                    ((2 * m + 1) as f64 / (2 * m) as f64).sqrt()
                }
            })
            .collect();
        Self { lmax, a, b, diag }
    }

    /// Largest degree.
    pub fn lmax(&self) -> usize {
        self.lmax
    }

    /// Number of `(l, m)` pairs with `0 <= m <= l <= lmax`.
    pub fn len(&self) -> usize {
        Self::len_for(self.lmax)
    }

    /// Whether the table is empty (never: degree 0 always exists).
    pub fn is_empty(&self) -> bool {
        false
    }

    fn len_for(lmax: usize) -> usize {
        (lmax + 1) * (lmax + 2) / 2
    }

    /// Position of `(l, m)` in arrays laid out by `m`, then `l` (`m`-major, contiguous in `l`).
    #[inline]
    pub fn index(&self, l: usize, m: usize) -> usize {
        Self::index_for(self.lmax, l, m)
    }

    #[inline]
    fn index_for(lmax: usize, l: usize, m: usize) -> usize {
        m * (lmax + 1) - m * m.saturating_sub(1) / 2 + (l - m)
    }

    /// Fills `out[index(l, m)] = Pbar(l, m, cos theta)` for all `l, m <= lmax`, given
    /// `x = cos theta` and `s = sin theta >= 0`. Returns the number of orders `m` filled; the
    /// rest underflowed and are left untouched (callers treat them as zero).
    pub fn eval(&self, x: f64, s: f64, out: &mut [f64]) -> usize {
        let lmax = self.lmax;
        let mut pmm = (1.0 / (4.0 * PI)).sqrt();
        for m in 0..=lmax {
            if m > 0 {
                pmm *= self.diag[m] * s;
                if pmm.abs() < UNDERFLOW {
                    return m;
                }
            }
            let base = self.index(m, m);
            out[base] = pmm;
            if m < lmax {
                let mut p1 = pmm;
                let mut p = (2.0 * m as f64 + 3.0).sqrt() * x * pmm;
                out[base + 1] = p;
                for l in m + 2..=lmax {
                    let i = base + (l - m);
                    let next = self.a[i] * (x * p - self.b[i] * p1);
                    p1 = p;
                    p = next;
                    out[i] = p;
                }
            }
        }
        lmax + 1
    }
}

/// Legendre polynomials `P_l(x)` for `l = 0..=lmax` (unnormalised, `P_l(1) = 1`).
pub fn legendre_p(lmax: usize, x: f64, out: &mut Vec<f64>) {
    out.clear();
    out.push(1.0);
    if lmax >= 1 {
        out.push(x);
    }
    for l in 1..lmax {
        let lf = l as f64;
        let next = ((2.0 * lf + 1.0) * x * out[l] - lf * out[l - 1]) / (lf + 1.0);
        out.push(next);
    }
}

/// Gauss-Legendre nodes and weights on `[-1, 1]` with `q` points (Newton's method on `P_q`).
pub fn gauss_legendre(q: usize) -> (Vec<f64>, Vec<f64>) {
    assert!(q >= 1);
    if q == 1 {
        return (vec![0.0], vec![2.0]);
    }
    let mut nodes = vec![0.0; q];
    let mut weights = vec![0.0; q];
    let qf = q as f64;
    for i in 0..q.div_ceil(2) {
        let mut x = (PI * (i as f64 + 0.75) / (qf + 0.5)).cos();
        let mut dp = 1.0;
        for _ in 0..100 {
            // p1 = P_q(x), p0 = P_{q-1}(x)
            let (mut p0, mut p1) = (1.0, x);
            for k in 1..q {
                let kf = k as f64;
                let p2 = ((2.0 * kf + 1.0) * x * p1 - kf * p0) / (kf + 1.0);
                p0 = p1;
                p1 = p2;
            }
            dp = qf * (x * p1 - p0) / (x * x - 1.0);
            let dx = p1 / dp;
            x -= dx;
            if dx.abs() < 1e-15 {
                break;
            }
        }
        nodes[i] = -x;
        nodes[q - 1 - i] = x;
        let w = 2.0 / ((1.0 - x * x) * dp * dp);
        weights[i] = w;
        weights[q - 1 - i] = w;
    }
    (nodes, weights)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn closed_forms_for_low_degrees() {
        let t = LegendreTable::new(3);
        let mut out = vec![0.0; t.len()];
        let theta: f64 = 0.7;
        let (x, s) = (theta.cos(), theta.sin());
        t.eval(x, s, &mut out);
        let k = |v: f64| v / (4.0 * PI);
        assert!((out[t.index(0, 0)] - k(1.0).sqrt()).abs() < 1e-15);
        assert!((out[t.index(1, 0)] - k(3.0).sqrt() * x).abs() < 1e-15);
        assert!((out[t.index(1, 1)] - (k(3.0) / 2.0).sqrt() * s).abs() < 1e-15);
        assert!((out[t.index(2, 0)] - k(5.0).sqrt() * 0.5 * (3.0 * x * x - 1.0)).abs() < 1e-14);
        assert!((out[t.index(2, 2)] - (k(15.0) / 8.0).sqrt() * s * s).abs() < 1e-14);
        assert!(
            (out[t.index(3, 1)] - (k(21.0) / 16.0).sqrt() * s * (5.0 * x * x - 1.0)).abs() < 1e-14
        );
    }

    #[test]
    fn orthonormal_up_to_high_degree() {
        // 2 pi integral Pbar(l,m) Pbar(l',m) dx = delta_ll', by Gauss-Legendre (exact here).
        let lmax = 60;
        let t = LegendreTable::new(lmax);
        let (nodes, weights) = gauss_legendre(lmax + 2);
        let mut vals = vec![vec![0.0; t.len()]; nodes.len()];
        for (x, v) in nodes.iter().zip(&mut vals) {
            t.eval(*x, (1.0 - x * x).sqrt(), v);
        }
        for m in [0, 1, 7, 30, 60] {
            for l in m..=lmax {
                for l2 in [m, l, lmax] {
                    if l2 < m {
                        continue;
                    }
                    let dot: f64 = (0..nodes.len())
                        .map(|q| weights[q] * vals[q][t.index(l, m)] * vals[q][t.index(l2, m)])
                        .sum::<f64>()
                        * 2.0
                        * PI;
                    let want = if l == l2 { 1.0 } else { 0.0 };
                    assert!((dot - want).abs() < 1e-10, "l={l} l'={l2} m={m}: {dot}");
                }
            }
        }
    }

    #[test]
    fn high_orders_near_the_pole_underflow_to_zero_not_nan() {
        let t = LegendreTable::new(400);
        let mut out = vec![f64::NAN; t.len()];
        let s = 1e-3f64;
        let filled = t.eval((1.0 - s * s).sqrt(), s, &mut out);
        assert!(filled < 400);
        for m in 0..filled {
            for l in m..=400 {
                assert!(out[t.index(l, m)].is_finite());
            }
        }
    }

    #[test]
    fn gauss_legendre_integrates_polynomials_exactly() {
        for q in 1..=12 {
            let (x, w) = gauss_legendre(q);
            for deg in 0..2 * q {
                let got: f64 = x.iter().zip(&w).map(|(x, w)| w * x.powi(deg as i32)).sum();
                let want = if deg % 2 == 1 {
                    0.0
                } else {
                    2.0 / (deg as f64 + 1.0)
                };
                assert!(
                    (got - want).abs() < 1e-13,
                    "q={q} deg={deg}: {got} vs {want}"
                );
            }
        }
    }

    #[test]
    fn legendre_polynomials_match_closed_forms() {
        let mut p = Vec::new();
        legendre_p(4, 0.3, &mut p);
        assert!((p[2] - 0.5 * (3.0 * 0.09 - 1.0)).abs() < 1e-15);
        assert!((p[4] - (35.0 * 0.0081 - 30.0 * 0.09 + 3.0) / 8.0).abs() < 1e-15);
        legendre_p(50, 1.0, &mut p);
        assert!(p.iter().all(|v| (v - 1.0).abs() < 1e-12));
    }
}
