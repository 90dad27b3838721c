//! Preconvolution of an environment map into light maps `L_n` (paper section 3.2).
//!
//! Method: spherical-harmonic zonal convolution. The map is analysed once up to the largest
//! band limit any lobe needs ([`crate::sh::analyse`]); each lobe then scales degree `l` by its
//! Funk-Hecke coefficient `Lambda_l` (tapered near the band limit to suppress ringing) and is
//! synthesised on its own grid ([`crate::sh::synthesise`]). Each lobe's band limit and grid
//! follow from its width and the one tolerance ([`crate::lobe::LobePlan`]): the diffuse lobe
//! gets a small map and few degrees, `n = 512` a large map and many. A black map costs
//! nothing, black rows are skipped in the analysis, and nothing is computed at a resolution
//! the tolerance does not ask for.

use crate::bright;
use crate::envmap::EnvMap;
use crate::error::EnvMapError;
use crate::lightmap::{LightMap, LightMapSet};
use crate::lobe::{self, LobePlan};
use crate::sh;

/// Largest Phong exponent accepted (its light map is 4096x2048 at the default tolerance).
pub const MAX_EXPONENT: u32 = 4096;

/// Default relative RMS error budget of a light map, for a point light (the worst case).
pub const DEFAULT_TOLERANCE: f64 = 2e-3;

/// Most memory the spherical-harmonic analyses of one preconvolution may plan (the map and
/// the map without its bright texels, [`crate::sh::analysis_bytes`] each); a finer tolerance is
/// refused before anything is allocated. At the default tolerance they take a few MiB; 1e-5
/// takes about 0.2 GiB with 2 threads.
pub const MAX_ANALYSIS_BYTES: u64 = 2 << 30;

/// Default fraction of each lobe's band that is tapered by a raised cosine.
pub const DEFAULT_TAPER: f64 = 0.5;

/// What to preconvolve and how accurately.
#[derive(Clone, Debug, PartialEq)]
pub struct PreconvolveOptions {
    /// Phong exponents, in the order the light maps are returned (default 1, 16, 32, 64).
    pub exponents: Vec<u32>,
    /// Relative RMS error budget per light map for a point light (truncation plus look-up).
    pub tolerance: f64,
    /// Fraction of the band tapered by a raised cosine (0 = plain truncation, which rings).
    pub taper: f64,
    /// Upper bound on light-map rows, whatever the tolerance asks for.
    pub max_height: usize,
}

impl Default for PreconvolveOptions {
    fn default() -> Self {
        Self {
            exponents: crate::DEFAULT_EXPONENTS.to_vec(),
            tolerance: DEFAULT_TOLERANCE,
            taper: DEFAULT_TAPER,
            max_height: 2048,
        }
    }
}

impl PreconvolveOptions {
    /// Options for these exponents, defaults otherwise.
    pub fn with_exponents(exponents: &[u32]) -> Self {
        Self {
            exponents: exponents.to_vec(),
            ..Self::default()
        }
    }

    /// Checks the exponents (non-empty, distinct, `1..=MAX_EXPONENT`), the tolerance and taper.
    pub fn validate(&self) -> Result<(), EnvMapError> {
        let mut sorted = self.exponents.clone();
        sorted.sort_unstable();
        sorted.dedup();
        if sorted.is_empty() || sorted.len() != self.exponents.len() {
            return Err(EnvMapError::ExponentList(self.exponents.clone()));
        }
        if let Some(&n) = self.exponents.iter().find(|&&n| n == 0 || n > MAX_EXPONENT) {
            return Err(EnvMapError::Exponent {
                exponent: n,
                max: MAX_EXPONENT,
            });
        }
        if !(self.tolerance > 0.0 && self.tolerance < 1.0) {
            return Err(EnvMapError::Tolerance(self.tolerance));
        }
        if !(0.0..1.0).contains(&self.taper) {
            return Err(EnvMapError::Taper(self.taper));
        }
        // Only the band limits matter here, which are cheap to find (no profile tables).
        let fits = |tolerance: f64| {
            let part = tolerance / 2f64.sqrt();
            let (exponent, band_limit) = self
                .exponents
                .iter()
                .map(|&n| (n, lobe::band_limit(n, part, self.taper).0))
                .max_by_key(|&(_, l)| l)
                .expect("exponents checked non-empty");
            let bytes = 2 * sh::analysis_bytes(band_limit);
            (bytes <= MAX_ANALYSIS_BYTES, exponent, band_limit, bytes)
        };
        let (ok, exponent, band_limit, bytes) = fits(self.tolerance);
        if !ok {
            // The finest tolerance that fits, on a grid of 10^(1/10) steps (bisected: whether
            // a tolerance fits only improves as it grows).
            let grid: Vec<f64> = (1..)
                .map(|k| self.tolerance * 10f64.powf(k as f64 / 10.0))
                .take_while(|&t| t < 1.0)
                .collect();
            let first = grid.partition_point(|&t| !fits(t).0);
            let coarsest_allowed = grid.get(first).copied().unwrap_or(DEFAULT_TOLERANCE);
            return Err(EnvMapError::TooFine {
                tolerance: self.tolerance,
                exponent,
                band_limit,
                bytes,
                limit: MAX_ANALYSIS_BYTES,
                coarsest_allowed,
            });
        }
        Ok(())
    }

    /// The plan of each lobe, in order.
    pub fn plans(&self) -> Vec<LobePlan> {
        self.exponents
            .iter()
            .map(|&n| LobePlan::new(n, self.tolerance, self.taper, self.max_height))
            .collect()
    }
}

/// Where a long preconvolution is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Progress {
    /// The spherical-harmonic analysis of the map has started.
    Analysis,
    /// Light map `index` (of `total`), exponent `exponent`, has started.
    Lobe {
        index: usize,
        total: usize,
        exponent: u32,
    },
}

/// The light maps of `map` for `options.exponents`.
pub fn preconvolve(map: &EnvMap, options: &PreconvolveOptions) -> Result<LightMapSet, EnvMapError> {
    preconvolve_with_progress(map, options, |_| {})
}

/// [`preconvolve`], reporting each stage to `progress` as it starts.
pub fn preconvolve_with_progress(
    map: &EnvMap,
    options: &PreconvolveOptions,
    mut progress: impl FnMut(Progress),
) -> Result<LightMapSet, EnvMapError> {
    options.validate()?;
    let plans = options.plans();
    let total = plans.len();
    if map.is_black() {
        let maps = plans
            .iter()
            .map(|p| {
                LightMap::new(
                    p.exponent,
                    p.width(),
                    p.height,
                    vec![[0.0; 3]; p.width() * p.height],
                )
            })
            .collect();
        return Ok(LightMapSet::new(maps));
    }
    let lmax = plans.iter().map(|p| p.band_limit).max().unwrap_or(0);
    let quad_tol = options.tolerance * 1e-2; // analysis quadrature far below the budget
    let bright = bright::select(map, &plans, options.tolerance);
    let direct: Vec<bool> = plans
        .iter()
        .map(|p| !bright.is_empty() && bright::affordable(p, map.height(), bright.len()))
        .collect();
    progress(Progress::Analysis);
    // Lobes that sum the bright texels directly convolve the rest of the map; the others
    // convolve all of it.
    let whole = direct
        .iter()
        .any(|d| !d)
        .then(|| sh::analyse(map, lmax, quad_tol));
    let rest = direct.iter().any(|d| *d).then(|| {
        tracing::debug!("summing {} bright texels directly", bright.len());
        let mut rest = map.clone();
        for &(x, y) in &bright {
            rest.set_texel(x, y, [0.0; 3]);
        }
        sh::analyse(&rest, lmax, quad_tol)
    });
    let mut maps = Vec::with_capacity(total);
    for (index, (plan, &direct)) in plans.iter().zip(&direct).enumerate() {
        progress(Progress::Lobe {
            index,
            total,
            exponent: plan.exponent,
        });
        let coeffs = if direct { &rest } else { &whole };
        let coeffs = coeffs.as_ref().expect("analysed above");
        let mut values = sh::synthesise(coeffs, &plan.coefficients, plan.height);
        if direct {
            bright::add_direct(map, &bright, plan.exponent, plan.height, &mut values);
        }
        maps.push(finish(plan, values));
    }
    Ok(LightMapSet::new(maps))
}

/// Rounds a lobe's values to f32, clamping the negative values that band-limit ringing leaves
/// to zero and recording how many there were and how deep the deepest went.
fn finish(plan: &LobePlan, values: Vec<[f64; 3]>) -> LightMap {
    let peak = values.iter().flatten().copied().fold(0.0f64, f64::max);
    let mut clamped = 0;
    let mut deepest = 0.0f64;
    let texels = values
        .iter()
        .map(|c| {
            c.map(|v| {
                if v < 0.0 {
                    clamped += 1;
                    deepest = deepest.min(v);
                }
                v.max(0.0) as f32
            })
        })
        .collect();
    if clamped > 0 {
        tracing::debug!(
            "n={}: clamped {clamped} negative values (band-limit ringing, deepest {:.2e} of the peak)",
            plan.exponent,
            -deepest / peak
        );
    }
    LightMap::new(plan.exponent, plan.width(), plan.height, texels)
        .with_clamped(clamped, if peak > 0.0 { -deepest / peak } else { 0.0 })
}
