//! The ranges procedural parameters are drawn from (`[data.lighting.ranges]`): every key is
//! optional, and the defaults are the ranges the collection has always used, so a config
//! without the table draws exactly the same environments (same content keys, same caches).

use serde::{Deserialize, Serialize};

use super::HdriError;

/// `[data.lighting.ranges]`: one table per procedural kind.
#[derive(Clone, Debug, Default, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct ProceduralRanges {
    pub sky: SkyRanges,
    pub overcast: OvercastRanges,
    pub studio: StudioRanges,
}

/// `[data.lighting.ranges.sky]`: sun and sky. The azimuth is always uniform over the circle.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct SkyRanges {
    /// Sun elevation above the horizon, degrees, uniform (default 3 to 70; -10 to 90 allowed).
    pub elevation: [f64; 2],
    /// Turbidity (haze), uniform (default 2 to 8; 1 to 10 allowed).
    pub turbidity: [f64; 2],
    /// Irradiance of the sun disc on a surface facing it, log-uniform (default 2 to 8).
    pub irradiance: [f64; 2],
    /// Angular radius of the sun disc, degrees, uniform (absent: 0.27 to 0.86 degrees, drawn
    /// as exactly 0.0047 to 0.015 radians, so that the defaults keep their content keys).
    pub sun_radius: Option<[f64; 2]>,
}

impl Default for SkyRanges {
    fn default() -> Self {
        SkyRanges {
            elevation: [3.0, 70.0],
            turbidity: [2.0, 8.0],
            irradiance: [2.0, 8.0],
            sun_radius: None,
        }
    }
}

/// `[data.lighting.ranges.overcast]`: CIE overcast skies.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct OvercastRanges {
    /// Zenith radiance, log-uniform (default 0.6 to 2.5: an upward surface receives 1.5 to 6).
    pub zenith: [f64; 2],
}

impl Default for OvercastRanges {
    fn default() -> Self {
        OvercastRanges { zenith: [0.6, 2.5] }
    }
}

/// `[data.lighting.ranges.studio]`: studios. Where the key, fill and rim lights stand, their
/// shares of the key's irradiance and their tints are fixed (docs/data-hdri.md).
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct StudioRanges {
    /// Number of lights, uniform over the integers (default 1 to 3: key, fill, rim).
    pub lights: [usize; 2],
    /// Irradiance of the key light, log-uniform (default 2 to 8).
    pub key_irradiance: [f64; 2],
    /// Angular radius of each light, degrees, uniform (default 6 to 20: soft boxes).
    pub radius: [f64; 2],
}

impl Default for StudioRanges {
    fn default() -> Self {
        StudioRanges {
            lights: [1, 3],
            key_irradiance: [2.0, 8.0],
            radius: [6.0, 20.0],
        }
    }
}

/// `lo <= hi`, both finite and within `[min, max]`; the error names `key` and the range.
fn check(key: &'static str, [lo, hi]: [f64; 2], min: f64, max: f64) -> Result<(), HdriError> {
    if !(lo.is_finite() && hi.is_finite() && min <= lo && lo <= hi && hi <= max) {
        return Err(HdriError::Config {
            key,
            message: format!("[{lo}, {hi}] must be a range low to high within [{min}, {max}]"),
        });
    }
    Ok(())
}

impl ProceduralRanges {
    /// Checks every range, naming the first bad key.
    pub fn validate(&self) -> Result<(), HdriError> {
        let (s, o, t) = (&self.sky, &self.overcast, &self.studio);
        check("ranges.sky.elevation", s.elevation, -10.0, 90.0)?;
        check("ranges.sky.turbidity", s.turbidity, 1.0, 10.0)?;
        check("ranges.sky.irradiance", s.irradiance, 1e-3, 1e5)?;
        if let Some(r) = s.sun_radius {
            check("ranges.sky.sun_radius", r, 0.05, 10.0)?;
        }
        check("ranges.overcast.zenith", o.zenith, 1e-3, 1e5)?;
        check("ranges.studio.lights", t.lights.map(|n| n as f64), 1.0, 3.0)?;
        check("ranges.studio.key_irradiance", t.key_irradiance, 1e-3, 1e5)?;
        check("ranges.studio.radius", t.radius, 0.5, 45.0)?;
        Ok(())
    }
}
