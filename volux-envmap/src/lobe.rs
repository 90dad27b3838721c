//! The cosine lobes of Phong exponents and their spherical-harmonic (Funk-Hecke) spectra.
//!
//! The lobe of exponent `n` is the zonal kernel `k_n(t) = (n + 1) / (2 pi) max(0, t)^n` of
//! `t = w.u`. By the Funk-Hecke theorem, convolving a map with it multiplies every spherical
//! harmonic of degree `l` by `Lambda_l = 2 pi integral_{-1}^{1} k_n(t) P_l(t) dt
//! = (n + 1) integral_0^1 t^n P_l(t) dt`, computed exactly by the recurrence
//! `I(n, l) = (n - l + 2) / (n + l + 1) I(n, l - 2)`, `I(n, 0) = 1 / (n + 1)`,
//! `I(n, 1) = 1 / (n + 2)`. `Lambda_0 = 1`: a constant map is left unchanged.
//!
//! Everything a lobe needs is planned from its width and one tolerance ([`LobePlan`]): the band
//! limit, the taper (window) against ringing, and the output resolution of its light map.

use std::collections::HashMap;
use std::f64::consts::PI;
use std::sync::{Mutex, OnceLock};

use crate::legendre::legendre_p;

/// `Lambda_l` for `l = 0..=lmax` of the normalised Phong lobe of exponent `n`.
pub fn phong_spectrum(n: u32, lmax: usize) -> Vec<f64> {
    let nf = f64::from(n);
    let mut integral = Vec::with_capacity(lmax + 1);
    for l in 0..=lmax {
        let lf = l as f64;
        let value = match l {
            0 => 1.0 / (nf + 1.0),
            1 => 1.0 / (nf + 2.0),
            _ => (nf - lf + 2.0) / (nf + lf + 1.0) * integral[l - 2],
        };
        integral.push(value);
    }
    integral.iter().map(|i| (nf + 1.0) * i).collect()
}

/// `integral over the sphere of k_n^2 = sum_l (2l + 1) / (4 pi) Lambda_l^2
/// = (n + 1)^2 / (2 pi (2n + 1))`: the energy of the lobe, the denominator of its relative
/// truncation error.
pub fn phong_energy(n: u32) -> f64 {
    let nf = f64::from(n);
    (nf + 1.0) * (nf + 1.0) / (2.0 * PI * (2.0 * nf + 1.0))
}

/// The raised-cosine taper: 1 up to `(1 - taper) L`, then falling smoothly to 0 just past `L`.
/// `taper = 0` is plain truncation.
pub fn taper_weights(band_limit: usize, taper: f64) -> Vec<f64> {
    let start = (1.0 - taper) * band_limit as f64;
    let span = band_limit as f64 + 1.0 - start;
    (0..=band_limit)
        .map(|l| {
            let x = (l as f64 - start) / span;
            if x <= 0.0 {
                1.0
            } else {
                0.5 * (1.0 + (PI * x).cos())
            }
        })
        .collect()
}

/// Relative L2 error, over the sphere, of the tapered and truncated lobe against the exact
/// lobe: `sqrt(sum_l (2l+1) (Lambda_l - K_l)^2 / sum_l (2l+1) Lambda_l^2)`. By Parseval this
/// is exactly the relative RMS error of the light map of a point light, whose spectrum is flat
/// in degree. Real maps' spectra fall off with degree, which weights the truncated degrees
/// less, so the point light is the design case (the bench measures real maps).
pub fn truncation_error(n: u32, band_limit: usize, taper: f64) -> f64 {
    let spectrum = phong_spectrum(n, band_limit);
    let weights = taper_weights(band_limit, taper);
    let total = phong_energy(n) * 4.0 * PI;
    let mut kept = 0.0;
    let mut bias = 0.0;
    for l in 0..=band_limit {
        let e = (2 * l + 1) as f64 * spectrum[l] * spectrum[l];
        kept += e;
        bias += e * (1.0 - weights[l]).powi(2);
    }
    (((total - kept).max(0.0) + bias) / total).sqrt()
}

/// Highest band limit a plan may have.
pub const MAX_BAND_LIMIT: usize = 4096;

/// The smallest band limit (1 to [`MAX_BAND_LIMIT`]) whose [`truncation_error`] is within
/// `part`, and that error: the same sums as [`truncation_error`] in the same order, with the
/// spectrum computed once and the kept energy carried from one band limit to the next, so the
/// search costs `O(L taper L)` instead of `O(L^2)` spectra.
pub fn band_limit(n: u32, part: f64, taper: f64) -> (usize, f64) {
    let spectrum = phong_spectrum(n, MAX_BAND_LIMIT);
    let energy: Vec<f64> = spectrum
        .iter()
        .enumerate()
        .map(|(l, s)| (2 * l + 1) as f64 * s * s)
        .collect();
    let total = phong_energy(n) * 4.0 * PI;
    let mut kept = energy[0];
    let mut error = f64::INFINITY;
    for band_limit in 1..=MAX_BAND_LIMIT {
        kept += energy[band_limit];
        let weights = taper_weights(band_limit, taper);
        let bias: f64 = energy[..=band_limit]
            .iter()
            .zip(&weights)
            .map(|(e, w)| e * (1.0 - w).powi(2))
            .sum();
        error = (((total - kept).max(0.0) + bias) / total).sqrt();
        if error <= part {
            return (band_limit, error);
        }
    }
    (MAX_BAND_LIMIT, error)
}

/// The profile of a zonal kernel with coefficients `coeffs` at `t = cos(angle)`:
/// `sum_l (2l + 1) / (4 pi) coeffs_l P_l(t)`.
pub fn zonal_profile(coeffs: &[f64], t: f64, scratch: &mut Vec<f64>) -> f64 {
    legendre_p(coeffs.len() - 1, t, scratch);
    coeffs
        .iter()
        .zip(scratch.iter())
        .enumerate()
        .map(|(l, (c, p))| (2 * l + 1) as f64 / (4.0 * PI) * c * p)
        .sum()
}

/// A zonal kernel's profile tabulated against the angle from its axis, fine enough that
/// linear interpolation in the table is far more accurate than any light-map grid it judges.
pub struct ProfileTable {
    step: f64,
    values: Vec<f64>,
}

impl ProfileTable {
    /// Tabulates `zonal_profile(coeffs, cos(angle))` for angles in `[0, pi]`, with at least
    /// 64 samples per period of the highest degree.
    pub fn new(coeffs: &[f64]) -> Self {
        let samples = (64 * coeffs.len()).clamp(4096, 1 << 16);
        let step = PI / samples as f64;
        let mut scratch = Vec::new();
        let values = (0..=samples)
            .map(|i| zonal_profile(coeffs, (i as f64 * step).cos(), &mut scratch))
            .collect();
        Self { step, values }
    }

    /// The profile at `angle` (mirrored about 0 and pi, as a zonal function is).
    pub fn at(&self, angle: f64) -> f64 {
        let a = angle.abs();
        let a = if a > PI { 2.0 * PI - a } else { a };
        let x = a / self.step;
        let i = (x.floor() as usize).min(self.values.len() - 2);
        let f = x - i as f64;
        self.values[i] + f * (self.values[i + 1] - self.values[i])
    }
}

/// Relative RMS error of bilinear look-up on a light map with `height` rows (texel pitch
/// `pi / height` in both directions) of the light map of a point light, the worst case.
///
/// Model: linear interpolation of the kernel's profile along a great circle through its peak,
/// over all offsets of the grid, weighted by the solid angle of each ring around the peak, and
/// counted twice (bilinear interpolates along two axes whose errors add in quadrature).
pub fn interpolation_error(profile: &ProfileTable, height: usize) -> f64 {
    let h = PI / height as f64;
    let samples = 2048usize;
    let offsets = 8usize;
    let (mut err2, mut ref2) = (0.0, 0.0);
    for i in 0..samples {
        let angle = PI * (i as f64 + 0.5) / samples as f64;
        let weight = angle.sin();
        let exact = profile.at(angle);
        for k in 0..offsets {
            let s = (k as f64 + 0.5) / offsets as f64;
            let interp =
                (1.0 - s) * profile.at(angle - s * h) + s * profile.at(angle + (1.0 - s) * h);
            err2 += weight * (interp - exact).powi(2);
        }
        ref2 += weight * exact * exact * offsets as f64;
    }
    (2.0 * err2 / ref2).sqrt()
}

/// Candidate light-map heights (widths are twice these): powers of two and 1.5x powers of two,
/// so that each step costs at most 1.5x the previous one.
const HEIGHTS: [usize; 19] = [
    4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256, 384, 512, 768, 1024, 1536, 2048,
];

/// How one lobe is computed: everything here follows from the exponent and the tolerance.
#[derive(Clone, Debug, PartialEq)]
pub struct LobePlan {
    /// Phong exponent `n`.
    pub exponent: u32,
    /// Largest spherical-harmonic degree kept.
    pub band_limit: usize,
    /// Multipliers `Lambda_l * taper_l` for `l = 0..=band_limit`.
    pub coefficients: Vec<f64>,
    /// Light-map rows (the width is twice this).
    pub height: usize,
    /// Predicted worst-case relative RMS error of truncation and taper.
    pub truncation_error: f64,
    /// Predicted worst-case relative RMS error of bilinear look-up.
    pub interpolation_error: f64,
    /// The most negative value of the band-limited kernel relative to its peak: the ringing
    /// that the taper is there to suppress (0 if the kernel is non-negative everywhere).
    pub ringing: f64,
}

impl LobePlan {
    /// Plans lobe `n` so that truncation and look-up each stay within `tolerance / sqrt(2)`
    /// of relative RMS error in the worst case (together `tolerance`), with `taper` the
    /// fraction of the band that is tapered (0 = none). Light maps never get more rows than
    /// `max_height`.
    pub fn new(exponent: u32, tolerance: f64, taper: f64, max_height: usize) -> LobePlan {
        type Key = (u32, u64, u64, usize);
        static CACHE: OnceLock<Mutex<HashMap<Key, LobePlan>>> = OnceLock::new();
        let key = (exponent, tolerance.to_bits(), taper.to_bits(), max_height);
        let cache = CACHE.get_or_init(Default::default);
        if let Some(plan) = cache.lock().ok().and_then(|c| c.get(&key).cloned()) {
            return plan;
        }
        let plan = Self::compute(exponent, tolerance, taper, max_height);
        if let Ok(mut c) = cache.lock() {
            c.insert(key, plan.clone());
        }
        plan
    }

    fn compute(exponent: u32, tolerance: f64, taper: f64, max_height: usize) -> LobePlan {
        let part = tolerance / 2f64.sqrt();
        let (band_limit, truncation) = band_limit(exponent, part, taper);
        let weights = taper_weights(band_limit, taper);
        let coefficients: Vec<f64> = phong_spectrum(exponent, band_limit)
            .iter()
            .zip(&weights)
            .map(|(s, w)| s * w)
            .collect();
        let profile = ProfileTable::new(&coefficients);
        let mut height = HEIGHTS[0];
        let mut interpolation = f64::NAN;
        for &h in HEIGHTS.iter().filter(|&&h| h <= max_height.max(HEIGHTS[0])) {
            height = h;
            interpolation = interpolation_error(&profile, h);
            if interpolation <= part {
                break;
            }
        }
        LobePlan {
            exponent,
            band_limit,
            coefficients,
            height,
            truncation_error: truncation,
            interpolation_error: interpolation,
            ringing: -profile.values.iter().copied().fold(0.0, f64::min) / profile.values[0],
        }
    }

    /// Light-map width (twice the height).
    pub fn width(&self) -> usize {
        2 * self.height
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::legendre::gauss_legendre;

    /// `Lambda_l` by brute-force quadrature of `2 pi integral k_n(t) P_l(t) dt`.
    fn spectrum_by_quadrature(n: u32, lmax: usize) -> Vec<f64> {
        // Gauss-Legendre on [0, 1], where the lobe is a polynomial: exact.
        let (x, w) = gauss_legendre(n as usize + lmax + 2);
        let mut p = Vec::new();
        let mut out = vec![0.0; lmax + 1];
        for (xi, wi) in x.iter().zip(&w) {
            let t = 0.5 * (xi + 1.0);
            legendre_p(lmax, t, &mut p);
            let k = (f64::from(n) + 1.0) / (2.0 * PI) * t.powi(n as i32);
            for l in 0..=lmax {
                out[l] += 2.0 * PI * 0.5 * wi * k * p[l];
            }
        }
        out
    }

    #[test]
    fn the_band_limit_search_equals_the_plain_loop() {
        for n in [1, 16, 64, 512] {
            for tolerance in [1e-1, 2e-3, 1e-4, 3e-6] {
                for taper in [0.0, 0.5] {
                    let part = tolerance / 2f64.sqrt();
                    let mut plain = 1;
                    while truncation_error(n, plain, taper) > part && plain < MAX_BAND_LIMIT {
                        plain += 1;
                    }
                    let (fast, error) = band_limit(n, part, taper);
                    assert_eq!(fast, plain, "n={n} tolerance={tolerance} taper={taper}");
                    assert_eq!(error, truncation_error(n, plain, taper));
                }
            }
        }
    }

    #[test]
    fn spectrum_matches_quadrature_and_known_values() {
        for n in [1, 2, 16, 33, 64] {
            let a = phong_spectrum(n, 40);
            let b = spectrum_by_quadrature(n, 40);
            for l in 0..=40 {
                assert!(
                    (a[l] - b[l]).abs() < 1e-12,
                    "n={n} l={l}: {} vs {}",
                    a[l],
                    b[l]
                );
            }
        }
        // Clamped cosine / pi (irradiance / pi): 1, 2/3, 1/4, 0, -1/24 (Ramamoorthi-Hanrahan).
        let a = phong_spectrum(1, 4);
        for (got, want) in a.iter().zip([1.0, 2.0 / 3.0, 0.25, 0.0, -1.0 / 24.0]) {
            assert!((got - want).abs() < 1e-15);
        }
    }

    #[test]
    fn energy_closed_form_matches_the_sum() {
        for n in [1u32, 16, 64] {
            let s = phong_spectrum(n, 3000);
            let sum: f64 = s
                .iter()
                .enumerate()
                .map(|(l, v)| (2 * l + 1) as f64 * v * v)
                .sum();
            let rel = (sum / (4.0 * PI) - phong_energy(n)).abs() / phong_energy(n);
            assert!(rel < 1e-7, "n={n}: {rel}");
        }
    }

    #[test]
    fn plans_follow_the_lobe_width_and_tolerance() {
        let wide = LobePlan::new(1, 1e-3, 0.5, 4096);
        let narrow = LobePlan::new(64, 1e-3, 0.5, 4096);
        let narrower = LobePlan::new(512, 1e-3, 0.5, 4096);
        assert!(narrow.band_limit < narrower.band_limit);
        assert!(wide.height < narrow.height && narrow.height < narrower.height);
        let loose = LobePlan::new(64, 1e-2, 0.5, 4096);
        assert!(loose.band_limit < narrow.band_limit && loose.height <= narrow.height);
        for p in [&wide, &narrow, &narrower, &loose] {
            assert!(p.truncation_error <= 1e-2 / 2f64.sqrt());
            assert_eq!(p.coefficients[0], 1.0, "constant maps stay constant");
        }
        // The taper costs degrees for the same error, and removes ringing.
        let plain = LobePlan::new(64, 1e-3, 0.0, 4096);
        assert!(plain.band_limit <= narrow.band_limit);
        assert!(narrow.ringing < plain.ringing);
    }

    #[test]
    fn interpolation_error_shrinks_quadratically() {
        let plan = LobePlan::new(16, 1e-4, 0.5, 4096);
        let profile = ProfileTable::new(&plan.coefficients);
        let e1 = interpolation_error(&profile, 64);
        let e2 = interpolation_error(&profile, 128);
        assert!((e1 / e2 - 4.0).abs() < 0.5, "{e1} {e2}");
    }
}
