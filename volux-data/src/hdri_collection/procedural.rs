//! Procedural environments ([`crate::procedural_sky`]): sunny skies, overcast skies and
//! studios of one to three area lights, their parameters drawn with SplitMix64 from the
//! collection seed, the kind and the index, so that entry `i` of a kind does not depend on how
//! many entries of that kind there are.

use std::f64::consts::TAU;

use volux_envmap::random::SplitMix64;
use volux_envmap::{EnvMap, EnvMapError};

use super::ranges::{OvercastRanges, SkyRanges, StudioRanges};
use crate::procedural_sky::{self, AreaLight, SunSky, sun_direction};

/// Rows of a procedural environment map (width twice that) unless the config says otherwise.
///
/// Preconvolution costs about the same (11-32 ms) from 64 to 256 rows: it is dominated by
/// synthesising the light maps, whose sizes the tolerance fixes. So the height is set by
/// fidelity and by the cost of rendering the map: 256 rows sample the highest degree any
/// default lobe keeps (68, for `n = 1`) at more than two rows per wavelength, and render in
/// 15-60 ms, against 50-230 ms at 512 rows (`docs/data-hdri.md`).
pub const DEFAULT_PROCEDURAL_HEIGHT: usize = 256;

/// Version of the procedural parameter text hashed into content keys. Bump it whenever
/// `procedural_sky` renders the same parameters differently, so that cached light maps of the
/// old rendering are not reused.
pub const PROCEDURAL_VERSION: u32 = 1;

/// Largest count of one procedural kind a config may ask for.
pub const MAX_PROCEDURAL_COUNT: usize = 10_000;

/// A procedural environment's parameters.
#[derive(Clone, Debug, PartialEq)]
pub enum Procedural {
    /// A sun over a clear sky.
    SunSky(SunSky),
    /// A CIE overcast sky of this zenith radiance.
    Overcast { zenith: f64 },
    /// Area lights on black walls.
    Studio { lights: Vec<AreaLight> },
}

impl Procedural {
    /// The environment at `height` rows.
    pub fn render(&self, height: usize) -> Result<EnvMap, EnvMapError> {
        match self {
            Procedural::SunSky(sky) => sky.render(height),
            Procedural::Overcast { zenith } => procedural_sky::overcast(height, *zenith),
            Procedural::Studio { lights } => procedural_sky::studio(height, lights),
        }
    }

    /// The canonical text of the parameters at `height` rows: what the content key hashes.
    /// Floats are written in Rust's shortest round-trip form, so equal text means equal bits.
    pub fn canonical_text(&self, height: usize) -> String {
        let mut s =
            format!("volux procedural environment v{PROCEDURAL_VERSION}\nheight {height}\n");
        match self {
            Procedural::SunSky(p) => s.push_str(&format!(
                "sun-sky elevation {:?} azimuth {:?} turbidity {:?} sun_irradiance {:?} sun_radius {:?}\n",
                p.elevation, p.azimuth, p.turbidity, p.sun_irradiance, p.sun_radius
            )),
            Procedural::Overcast { zenith } => s.push_str(&format!("overcast zenith {zenith:?}\n")),
            Procedural::Studio { lights } => {
                s.push_str(&format!("studio lights {}\n", lights.len()));
                for l in lights {
                    s.push_str(&format!(
                        "light direction {:?} radius {:?} irradiance {:?}\n",
                        l.direction, l.radius, l.irradiance
                    ));
                }
            }
        }
        s
    }
}

/// Salts that keep the parameter streams of the procedural kinds apart.
const SKY_STREAM: u64 = 0x736b_7900; // "sky"
const OVERCAST_STREAM: u64 = 0x6f76_6300; // "ovc"
const STUDIO_STREAM: u64 = 0x7374_7500; // "stu"

/// The parameter stream of entry `index` of the kind `stream` under `seed`: each input passes
/// through SplitMix64's output mix, so neighbouring seeds and indices give unrelated streams.
fn parameter_stream(seed: u64, stream: u64, index: usize) -> SplitMix64 {
    let mixed = SplitMix64::new(seed).next_u64() ^ stream;
    let mixed = SplitMix64::new(mixed).next_u64() ^ index as u64;
    SplitMix64::new(SplitMix64::new(mixed).next_u64())
}

fn uniform(rng: &mut SplitMix64, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * rng.next_f64()
}

/// Log-uniform in `[lo, hi]`: as likely to halve as to double.
fn log_uniform(rng: &mut SplitMix64, lo: f64, hi: f64) -> f64 {
    (lo.ln() + (hi.ln() - lo.ln()) * rng.next_f64()).exp()
}

/// Sunny sky `index` under the default ranges: sun 3 to 70 degrees high at any azimuth,
/// turbidity 2 to 8, a disc 0.27 to 0.86 degrees in radius delivering 2 to 8 (log-uniform) to
/// a surface facing it. The shipped maps' diffuse light maps peak at 0.4 to 2.6, that is
/// irradiance 1.3 to 8.
pub fn random_sky(seed: u64, index: usize) -> SunSky {
    random_sky_in(&SkyRanges::default(), seed, index)
}

/// Sunny sky `index` with parameters drawn from `ranges`.
pub fn random_sky_in(ranges: &SkyRanges, seed: u64, index: usize) -> SunSky {
    let mut rng = parameter_stream(seed, SKY_STREAM, index);
    let [e0, e1] = ranges.elevation;
    SunSky {
        elevation: uniform(&mut rng, e0.to_radians(), e1.to_radians()),
        azimuth: uniform(&mut rng, 0.0, TAU),
        turbidity: uniform(&mut rng, ranges.turbidity[0], ranges.turbidity[1]),
        sun_irradiance: log_uniform(&mut rng, ranges.irradiance[0], ranges.irradiance[1]),
        sun_radius: match ranges.sun_radius {
            None => uniform(&mut rng, 0.0047, 0.015),
            Some([r0, r1]) => uniform(&mut rng, r0.to_radians(), r1.to_radians()),
        },
    }
}

/// Overcast sky `index` under the default ranges: zenith radiance 0.6 to 2.5 (log-uniform),
/// so an upward surface receives 1.5 to 6.
pub fn random_overcast(seed: u64, index: usize) -> Procedural {
    random_overcast_in(&OvercastRanges::default(), seed, index)
}

/// Overcast sky `index` with its zenith radiance drawn from `ranges`.
pub fn random_overcast_in(ranges: &OvercastRanges, seed: u64, index: usize) -> Procedural {
    let mut rng = parameter_stream(seed, OVERCAST_STREAM, index);
    Procedural::Overcast {
        zenith: log_uniform(&mut rng, ranges.zenith[0], ranges.zenith[1]),
    }
}

/// Studio `index` under the default ranges: a key light in front of the face (which faces +z)
/// and above it, to one side; with a second light, a weaker fill on the other side in front;
/// with a third, a rim light behind and above. Disc radii 6 to 20 degrees (soft boxes), key
/// irradiance 2 to 8 (log-uniform), fill 15-40% and rim 30-70% of it, each a random tint
/// between warm (1, 0.9, 0.8) and cool (0.85, 0.92, 1).
pub fn random_studio(seed: u64, index: usize) -> Procedural {
    random_studio_in(&StudioRanges::default(), seed, index)
}

/// Studio `index` with its number of lights, key irradiance and light radii drawn from
/// `ranges` (placements, shares and tints as in [`random_studio`]).
pub fn random_studio_in(ranges: &StudioRanges, seed: u64, index: usize) -> Procedural {
    let mut rng = parameter_stream(seed, STUDIO_STREAM, index);
    let [n0, n1] = ranges.lights;
    let count = n0 + (rng.next_u64() % (n1 - n0 + 1) as u64) as usize;
    let side = if rng.next_u64() & 1 == 0 { 1.0 } else { -1.0 };
    let key = log_uniform(&mut rng, ranges.key_irradiance[0], ranges.key_irradiance[1]);
    // (azimuth from +z, elevation, share of the key's irradiance), degrees.
    let mut placements = vec![(
        side * uniform(&mut rng, 20.0, 60.0),
        uniform(&mut rng, 15.0, 50.0),
        1.0,
    )];
    if count >= 2 {
        placements.push((
            -side * uniform(&mut rng, 20.0, 60.0),
            uniform(&mut rng, -5.0, 25.0),
            uniform(&mut rng, 0.15, 0.4),
        ));
    }
    if count >= 3 {
        placements.push((
            180.0 + uniform(&mut rng, -50.0, 50.0),
            uniform(&mut rng, 20.0, 60.0),
            uniform(&mut rng, 0.3, 0.7),
        ));
    }
    let lights = placements
        .into_iter()
        .map(|(azimuth, elevation, share)| {
            let radius = uniform(&mut rng, ranges.radius[0], ranges.radius[1]).to_radians();
            let t = rng.next_f64();
            let tint = [1.0 - 0.15 * t, 0.9 + 0.02 * t, 0.8 + 0.2 * t];
            AreaLight {
                direction: sun_direction(elevation.to_radians(), azimuth.to_radians()),
                radius,
                irradiance: tint.map(|c| (c * key * share) as f32),
            }
        })
        .collect();
    Procedural::Studio { lights }
}
