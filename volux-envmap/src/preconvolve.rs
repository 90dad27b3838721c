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

use crate::envmap::EnvMap;
use crate::error::EnvMapError;
use crate::lightmap::{LightMap, LightMapSet};
use crate::lobe::LobePlan;
use crate::sh;

/// Largest Phong exponent accepted (its light map is 4096x2048 at the default tolerance).
pub const MAX_EXPONENT: u32 = 4096;

/// Default relative RMS error budget of a light map, for a point light (the worst case).
pub const DEFAULT_TOLERANCE: f64 = 2e-3;

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
            return Err(EnvMapError::Tolerance(self.taper));
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
            .map(|p| LightMap::new(p.exponent, p.width(), p.height, vec![[0.0; 3]; p.width() * p.height]))
            .collect();
        return Ok(LightMapSet::new(maps));
    }
    let lmax = plans.iter().map(|p| p.band_limit).max().unwrap_or(0);
    progress(Progress::Analysis);
    // The analysis quadrature is kept two orders of magnitude below the budget.
    let coeffs = sh::analyse(map, lmax, options.tolerance * 1e-2);
    let mut maps = Vec::with_capacity(total);
    for (index, plan) in plans.iter().enumerate() {
        progress(Progress::Lobe {
            index,
            total,
            exponent: plan.exponent,
        });
        let (texels, negatives) = sh::synthesise(&coeffs, &plan.coefficients, plan.height);
        if negatives > 0 {
            tracing::debug!(
                "n={}: clamped {negatives} negative values (band-limit ringing) to 0",
                plan.exponent
            );
        }
        maps.push(
            LightMap::new(plan.exponent, plan.width(), plan.height, texels).with_clamped(negatives),
        );
    }
    Ok(LightMapSet::new(maps))
}
