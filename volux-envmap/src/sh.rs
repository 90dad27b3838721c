//! Spherical-harmonic transform of equirectangular maps, ring by ring: an FFT along each row,
//! then a Legendre transform along the columns.
//!
//! Analysis integrates each texel exactly as a constant patch: along the azimuth with the
//! closed-form integral of `e^{-i m phi}` over the texel (a sinc factor), along the polar angle
//! with Gauss-Legendre nodes whose count follows from the band limit and a tolerance. So the
//! coefficients are those of the piecewise-constant map itself, whatever its resolution, and
//! an 8x4 map is as valid an input as a 4096x2048 one. Rows that are entirely black are
//! skipped.
//!
//! Synthesis evaluates a band-limited function at the texel centres of any equirectangular
//! grid; orders above the grid's Nyquist limit are folded (aliased) onto the FFT bins they
//! fall on, which is exactly what point sampling them would give.

use std::f64::consts::PI;
use std::sync::Arc;

use rayon::prelude::*;
use rustfft::num_complex::Complex64;
use rustfft::{Fft, FftPlanner};

use crate::envmap::EnvMap;
use crate::legendre::{LegendreTable, gauss_legendre};

/// Spherical-harmonic coefficients `a_lm = integral H Y_lm^*` for `0 <= m <= l <= lmax` (the
/// negative orders of a real map are their conjugates), one per colour channel.
#[derive(Clone, Debug)]
pub struct ShCoeffs {
    table: LegendreTable,
    coeffs: Vec<[Complex64; 3]>,
}

impl ShCoeffs {
    /// Largest degree.
    pub fn lmax(&self) -> usize {
        self.table.lmax()
    }

    /// Coefficient of degree `l`, order `m >= 0`, per channel.
    pub fn get(&self, l: usize, m: usize) -> [Complex64; 3] {
        self.coeffs[self.table.index(l, m)]
    }

    /// Energy per degree, `sum_m |a_lm|^2` over `m = -l..=l`, summed over channels.
    pub fn degree_energy(&self) -> Vec<f64> {
        let lmax = self.lmax();
        let mut e = vec![0.0; lmax + 1];
        for m in 0..=lmax {
            for (l, energy) in e.iter_mut().enumerate().skip(m) {
                let c = self.get(l, m);
                let s: f64 = c.iter().map(|z| z.norm_sqr()).sum();
                *energy += if m == 0 { s } else { 2.0 * s };
            }
        }
        e
    }
}

/// Number of Gauss-Legendre nodes per row so that a degree-`lmax` harmonic is integrated over a
/// row `dtheta` tall to within `tol` (relative): the smallest `q >= 2` whose error term
/// `(lmax dtheta / 2)^{2q} / (2q)!` is below `tol`.
pub fn quadrature_points(lmax: usize, dtheta: f64, tol: f64) -> usize {
    let x = (lmax as f64 + 1.0) * dtheta / 2.0;
    let mut q = 2usize;
    loop {
        let log_err = 2.0 * q as f64 * x.max(1e-300).ln() - ln_factorial(2 * q);
        if log_err <= tol.ln() || q >= 64 {
            return q;
        }
        q += 1;
    }
}

fn ln_factorial(n: usize) -> f64 {
    (2..=n).map(|k| (k as f64).ln()).sum()
}

/// `sin(x) / x`, 1 at 0.
fn sinc(x: f64) -> f64 {
    if x.abs() < 1e-8 {
        1.0 - x * x / 6.0
    } else {
        x.sin() / x
    }
}

/// Spherical-harmonic coefficients of `map` up to degree `lmax`, each texel integrated as a
/// constant patch (see the module docs); `quad_tol` bounds the polar quadrature's error.
pub fn analyse(map: &EnvMap, lmax: usize, quad_tol: f64) -> ShCoeffs {
    let (w, h) = (map.width(), map.height());
    let table = LegendreTable::new(lmax);
    let n = table.len();
    let fft: Arc<dyn Fft<f64>> = FftPlanner::new().plan_fft_forward(w);
    let dphi = 2.0 * PI / w as f64;
    let phi0 = -PI + 0.5 * dphi;
    let dtheta = PI / h as f64;
    let q = quadrature_points(lmax, dtheta, quad_tol);
    let (gx, gw) = gauss_legendre(q);
    // Azimuthal factor per order: texel integral of e^{-i m phi}, phase of the first column.
    let azimuth: Vec<Complex64> = (0..=lmax)
        .map(|m| {
            let mf = m as f64;
            Complex64::from_polar(dphi * sinc(0.5 * mf * dphi), -mf * phi0)
        })
        .collect();

    // Fixed blocks of rows, summed in order, so the result does not depend on thread timing;
    // at most `analysis_blocks_in_flight` partial sums exist at once (each holds every
    // coefficient), so memory at fine tolerances does not grow with the number of blocks.
    let blocks = h.min(64);
    let mut coeffs = vec![[Complex64::default(); 3]; n];
    let block_ids: Vec<usize> = (0..blocks).collect();
    for group in block_ids.chunks(analysis_blocks_in_flight(lmax)) {
        let partials: Vec<Option<Vec<[Complex64; 3]>>> = group
            .par_iter()
            .map(|&b| {
                let rows = (b * h / blocks)..((b + 1) * h / blocks);
                let mut acc: Option<Vec<[Complex64; 3]>> = None;
                let mut spectrum = vec![vec![Complex64::default(); w]; 3];
                let mut scratch = vec![Complex64::default(); fft.get_inplace_scratch_len()];
                let mut legendre = vec![0.0; n];
                let mut ring = vec![0.0; n];
                for y in rows {
                    let row = map.row(y);
                    if row.iter().all(|c| c.iter().all(|v| *v == 0.0)) {
                        continue;
                    }
                    for (c, s) in spectrum.iter_mut().enumerate() {
                        for (z, texel) in s.iter_mut().zip(row) {
                            *z = Complex64::new(f64::from(texel[c]), 0.0);
                        }
                        fft.process_with_scratch(s, &mut scratch);
                    }
                    // Polar integral of each Pbar_lm over the row.
                    let (t0, t1) = (dtheta * y as f64, dtheta * (y + 1) as f64);
                    let (mid, half) = (0.5 * (t0 + t1), 0.5 * (t1 - t0));
                    ring.iter_mut().for_each(|r| *r = 0.0);
                    let mut orders = 0;
                    for (x, wq) in gx.iter().zip(&gw) {
                        let theta = mid + half * x;
                        let (s, c) = theta.sin_cos();
                        let filled = table.eval(c, s, &mut legendre);
                        orders = orders.max(filled);
                        let weight = half * wq * s;
                        let end = if filled > lmax {
                            n
                        } else {
                            table.index(filled, filled)
                        };
                        for (r, p) in ring[..end].iter_mut().zip(&legendre[..end]) {
                            *r += weight * p;
                        }
                    }
                    // The constant term exactly: the row's solid angle over the azimuth.
                    ring[0] = (t0.cos() - t1.cos()) * (1.0 / (4.0 * PI)).sqrt();
                    let acc = acc.get_or_insert_with(|| vec![[Complex64::default(); 3]; n]);
                    for m in 0..orders.min(lmax + 1) {
                        let f: [Complex64; 3] =
                            std::array::from_fn(|c| spectrum[c][m % w] * azimuth[m]);
                        let base = table.index(m, m);
                        for (k, a) in acc[base..base + (lmax + 1 - m)].iter_mut().enumerate() {
                            let r = ring[base + k];
                            for c in 0..3 {
                                a[c] += f[c] * r;
                            }
                        }
                    }
                }
                acc
            })
            .collect();
        for part in partials.into_iter().flatten() {
            for (a, p) in coeffs.iter_mut().zip(part) {
                for c in 0..3 {
                    a[c] += p[c];
                }
            }
        }
    }
    ShCoeffs { table, coeffs }
}

/// Bytes of one partial sum of [`analyse`] at degree `lmax`: three complex numbers per
/// coefficient.
fn partial_bytes(lmax: usize) -> u64 {
    ((lmax + 1) * (lmax + 2) / 2) as u64 * std::mem::size_of::<[Complex64; 3]>() as u64
}

/// Memory the partial sums in flight may take before [`analyse`] holds fewer of them (never
/// fewer than one per thread).
const PARTIALS_BUDGET: u64 = 256 << 20;

/// Row blocks [`analyse`] sums at once at degree `lmax`: all 64 while their partial sums fit in
/// [`PARTIALS_BUDGET`] (every band limit the default tolerance plans), else one per thread, so
/// memory stays bounded at fine tolerances without costing parallelism at ordinary ones.
pub fn analysis_blocks_in_flight(lmax: usize) -> usize {
    let threads = rayon::current_num_threads().max(1);
    ((PARTIALS_BUDGET / partial_bytes(lmax)) as usize).clamp(threads.min(64), 64)
}

/// Bytes [`analyse`] holds at its peak for degree `lmax`: the result and the partial sums in
/// flight.
pub fn analysis_bytes(lmax: usize) -> u64 {
    (analysis_blocks_in_flight(lmax) as u64 + 1) * partial_bytes(lmax)
}

/// Evaluates `f = sum_lm kernel_l a_lm Y_lm` (degrees `l < kernel.len()`) at the texel centres
/// of a `2 height x height` equirectangular grid, row-major from the top row.
pub fn synthesise(coeffs: &ShCoeffs, kernel: &[f64], height: usize) -> Vec<[f64; 3]> {
    let lmax = kernel.len() - 1;
    assert!(
        lmax <= coeffs.lmax(),
        "kernel degree beyond the analysed band"
    );
    let width = 2 * height;
    let table = LegendreTable::new(lmax);
    let n = table.len();
    let mut scaled = vec![[Complex64::default(); 3]; n];
    for m in 0..=lmax {
        for l in m..=lmax {
            scaled[table.index(l, m)] = coeffs.get(l, m).map(|z| z * kernel[l]);
        }
    }
    let fft: Arc<dyn Fft<f64>> = FftPlanner::new().plan_fft_inverse(width);
    let phi0 = -PI + PI / width as f64;
    let phase: Vec<Complex64> = (0..=lmax)
        .map(|m| Complex64::from_polar(1.0, m as f64 * phi0))
        .collect();
    let rows: Vec<Vec<[f64; 3]>> = (0..height)
        .into_par_iter()
        .map_init(
            || {
                (
                    vec![0.0; n],
                    vec![vec![Complex64::default(); width]; 3],
                    vec![Complex64::default(); fft.get_inplace_scratch_len()],
                )
            },
            |(legendre, spectrum, scratch), y| {
                let theta = PI * (y as f64 + 0.5) / height as f64;
                let (s, c) = theta.sin_cos();
                let orders = table.eval(c, s, legendre);
                for sp in spectrum.iter_mut() {
                    sp.iter_mut().for_each(|z| *z = Complex64::default());
                }
                for m in 0..orders.min(lmax + 1) {
                    let base = table.index(m, m);
                    let mut g = [Complex64::default(); 3];
                    for k in 0..=lmax - m {
                        let p = legendre[base + k];
                        let a = &scaled[base + k];
                        for ch in 0..3 {
                            g[ch] += a[ch] * p;
                        }
                    }
                    for (ch, sp) in spectrum.iter_mut().enumerate() {
                        if m == 0 {
                            sp[0] += Complex64::new(g[ch].re, 0.0);
                        } else {
                            let z = g[ch] * phase[m];
                            sp[m % width] += z;
                            sp[(width - m % width) % width] += z.conj();
                        }
                    }
                }
                for sp in spectrum.iter_mut() {
                    fft.process_with_scratch(sp, scratch);
                }
                (0..width)
                    .map(|x| std::array::from_fn(|ch| spectrum[ch][x].re))
                    .collect()
            },
        )
        .collect();
    rows.concat()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::direction;

    /// `Y_lm` (real part convention of this module) at a direction.
    fn ylm(l: usize, m: usize, d: direction::Dir) -> Complex64 {
        let table = LegendreTable::new(l);
        let mut p = vec![0.0; table.len()];
        let theta = d[1].clamp(-1.0, 1.0).acos();
        table.eval(theta.cos(), theta.sin(), &mut p);
        let phi = d[0].atan2(d[2]);
        Complex64::from_polar(p[table.index(l, m)], m as f64 * phi)
    }

    #[test]
    fn constant_map_has_only_the_constant_term() {
        let map = EnvMap::constant(16, [2.0, 0.5, 0.0]).unwrap();
        let sh = analyse(&map, 12, 1e-12);
        let c00 = sh.get(0, 0);
        let want = 2.0 * (4.0 * PI).sqrt();
        assert!((c00[0].re - want).abs() < 1e-12 && c00[0].im.abs() < 1e-12);
        for m in 0..=12 {
            for l in m.max(1)..=12 {
                for c in sh.get(l, m) {
                    assert!(c.norm() < 1e-9, "({l},{m}) {c}");
                }
            }
        }
    }

    #[test]
    fn round_trip_of_a_band_limited_map() {
        // A smooth map of low degree: analysis then synthesis gives it back at texel centres,
        // up to the averaging over each texel (small at this resolution).
        let f = |d: direction::Dir| {
            let v = 1.0 + 0.5 * ylm(2, 1, d).re + 0.3 * ylm(3, 0, d).re + 0.2 * ylm(5, 4, d).im;
            [v as f32, 0.0, 1.0]
        };
        let map = EnvMap::from_fn(256, f).unwrap();
        let sh = analyse(&map, 8, 1e-12);
        let out = synthesise(&sh, &[1.0; 9], 32);
        for y in 0..32 {
            for x in 0..64 {
                let want = f(direction::texel_dir(x, y, 64, 32))[0];
                let got = out[y * 64 + x][0] as f32;
                assert!((got - want).abs() < 2e-3, "({x},{y}): {got} vs {want}");
            }
        }
    }

    #[test]
    fn analysis_of_a_texel_matches_its_exact_integral() {
        // One lit texel on a 16x8 map: a_lm is the integral of Y_lm^* over that texel.
        let mut map = EnvMap::constant(8, [0.0; 3]).unwrap();
        map.set_texel(5, 2, [1.0, 0.0, 0.0]);
        let sh = analyse(&map, 6, 1e-14);
        for (l, m) in [(0, 0), (1, 1), (3, 2), (6, 5), (6, 6)] {
            // Fine midpoint rule over the texel as the check.
            let k = 200;
            let mut want = Complex64::default();
            for i in 0..k {
                for j in 0..k {
                    let u = (5.0 + (i as f64 + 0.5) / k as f64) / 16.0;
                    let v = (2.0 + (j as f64 + 0.5) / k as f64) / 8.0;
                    let theta = PI * v;
                    let area =
                        (2.0 * PI / (16.0 * k as f64)) * (PI / (8.0 * k as f64)) * theta.sin();
                    want += ylm(l, m, direction::uv_to_dir(u, v)).conj() * area;
                }
            }
            let got = sh.get(l, m)[0];
            assert!((got - want).norm() < 1e-6, "({l},{m}): {got} vs {want}");
        }
    }

    #[test]
    fn black_map_and_black_rows_cost_nothing_and_give_zero() {
        let map = EnvMap::constant(8, [0.0; 3]).unwrap();
        let sh = analyse(&map, 10, 1e-9);
        assert!(sh.degree_energy().iter().all(|e| *e == 0.0));
    }

    #[test]
    fn quadrature_points_grow_with_band_and_row_height() {
        assert_eq!(quadrature_points(10, 1e-3, 1e-6), 2);
        assert!(quadrature_points(80, PI / 4.0, 1e-6) > quadrature_points(80, PI / 64.0, 1e-6));
    }
}
