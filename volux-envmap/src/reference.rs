//! The brute-force light map: ground truth for the tests and the error report.
//!
//! `L_n(w) = sum_c H_c Omega_c max(0, w.u_c)^n / sum_c Omega_c max(0, w.u_c)^n` over sub-cells
//! `c` of every texel, in f64. Each texel is split into `s x s` equirectangular sub-cells with
//! their exact solid angles `Omega_c`, `s` chosen so that a sub-cell is at most a sixteenth of
//! the lobe's width; so the sum converges to the integral of the piecewise-constant map even
//! for an 8x4 map and a lobe narrower than a texel. Dividing by the kernel's own sum instead of
//! its exact integral `2 pi / (n + 1)` makes a constant map come out exactly constant.
//!
//! Cost: one pass over every sub-cell per output direction. It is slow on purpose.

use std::f64::consts::PI;

use rayon::prelude::*;

use crate::direction::{self, Dir};
use crate::envmap::EnvMap;

/// Sub-cells of one map, ready to integrate lobes of exponent `n` against.
pub struct Reference {
    exponent: i32,
    /// Sub-cell centre directions, solid angles and radiance, as structure of arrays.
    x: Vec<f64>,
    y: Vec<f64>,
    z: Vec<f64>,
    omega: Vec<f64>,
    radiance: Vec<[f64; 3]>,
    subdivision: usize,
}

/// Angular width of the lobe of exponent `n`: its standard deviation for a narrow lobe
/// (`cos^n t ~ exp(-n t^2 / 2)`), capped at one radian for the broad diffuse lobe.
pub fn lobe_width(n: u32) -> f64 {
    (1.0 / f64::from(n)).sqrt().min(1.0)
}

impl Reference {
    /// Prepares the sub-cells of `map` for exponent `n`.
    pub fn new(map: &EnvMap, n: u32) -> Reference {
        let (w, h) = (map.width(), map.height());
        let texel = PI / h as f64;
        let s = ((16.0 * texel / lobe_width(n)).ceil() as usize).max(1);
        let (sw, sh) = (w * s, h * s);
        let cells = sw * sh;
        let mut r = Reference {
            exponent: n as i32,
            x: Vec::with_capacity(cells),
            y: Vec::with_capacity(cells),
            z: Vec::with_capacity(cells),
            omega: Vec::with_capacity(cells),
            radiance: Vec::with_capacity(cells),
            subdivision: s,
        };
        for sy in 0..sh {
            let omega = direction::row_solid_angle(sy, sw, sh);
            for sx in 0..sw {
                let d = direction::texel_dir(sx, sy, sw, sh);
                let c = map.texel(sx / s, sy / s);
                r.x.push(d[0]);
                r.y.push(d[1]);
                r.z.push(d[2]);
                r.omega.push(omega);
                r.radiance.push(c.map(f64::from));
            }
        }
        r
    }

    /// Sub-cells per texel along each axis.
    pub fn subdivision(&self) -> usize {
        self.subdivision
    }

    /// `L_n` in the unit direction `w`.
    pub fn eval(&self, w: Dir) -> [f64; 3] {
        let mut num = [0.0f64; 3];
        let mut den = 0.0f64;
        for i in 0..self.x.len() {
            let d = w[0] * self.x[i] + w[1] * self.y[i] + w[2] * self.z[i];
            if d > 0.0 {
                let k = self.omega[i] * d.powi(self.exponent);
                let c = &self.radiance[i];
                num[0] += k * c[0];
                num[1] += k * c[1];
                num[2] += k * c[2];
                den += k;
            }
        }
        if den > 0.0 {
            num.map(|v| v / den)
        } else {
            [0.0; 3]
        }
    }

    /// `L_n` in many directions, in parallel.
    pub fn eval_many(&self, dirs: &[Dir]) -> Vec<[f64; 3]> {
        dirs.par_iter().map(|d| self.eval(*d)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constant_map_gives_the_constant_for_every_exponent() {
        let map = EnvMap::constant(4, [3.0, 0.25, 0.0]).unwrap();
        for n in [1, 16, 64, 512] {
            let r = Reference::new(&map, n);
            for d in [[0.0, 1.0, 0.0], [0.6, 0.0, 0.8], [0.0, -1.0, 0.0]] {
                let v = r.eval(d);
                let ok = (v[0] - 3.0).abs() < 1e-10 && (v[1] - 0.25).abs() < 1e-10 && v[2] == 0.0;
                assert!(ok, "n={n} d={d:?}: {v:?}");
            }
        }
    }

    #[test]
    fn normaliser_converges_to_the_exact_lobe_integral() {
        // The unnormalised sum over the sphere approaches 2 pi / (n + 1), so the reference is
        // the true integral and not an artefact of its own normalisation.
        let map = EnvMap::constant(16, [1.0; 3]).unwrap();
        for n in [1u32, 16, 64] {
            let r = Reference::new(&map, n);
            let w = [0.3f64, 0.5, (1.0f64 - 0.34).sqrt()];
            let den: f64 = (0..r.x.len())
                .map(|i| {
                    let d = w[0] * r.x[i] + w[1] * r.y[i] + w[2] * r.z[i];
                    if d > 0.0 {
                        r.omega[i] * d.powi(n as i32)
                    } else {
                        0.0
                    }
                })
                .sum();
            let exact = 2.0 * PI / (f64::from(n) + 1.0);
            assert!(
                (den - exact).abs() / exact < 2e-3,
                "n={n}: {den} vs {exact}"
            );
        }
    }

    #[test]
    fn diffuse_of_a_hemisphere_matches_the_analytic_value() {
        // Upper hemisphere white, lower black: L_1 at angle a from +y is (1 + cos a) / 2.
        let map = EnvMap::from_fn(64, |d| if d[1] > 0.0 { [1.0; 3] } else { [0.0; 3] }).unwrap();
        let r = Reference::new(&map, 1);
        for a in [0.0f64, 0.5, 1.2, 2.0, PI] {
            let v = r.eval([a.sin(), a.cos(), 0.0])[0];
            let want = (1.0 + a.cos()) / 2.0;
            assert!((v - want).abs() < 2e-3, "a={a}: {v} vs {want}");
        }
    }

    #[test]
    fn narrow_lobe_on_a_tiny_map_is_subdivided() {
        let map = EnvMap::constant(4, [1.0; 3]).unwrap();
        assert!(Reference::new(&map, 512).subdivision() > 100);
        assert_eq!(
            Reference::new(&EnvMap::constant(512, [1.0; 3]).unwrap(), 64).subdivision(),
            1
        );
    }
}
