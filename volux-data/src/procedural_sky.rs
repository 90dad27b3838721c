//! Procedural HDR environments for the built-in HDRI collection, so that lighting has variety
//! without downloads: a sunny sky (sun disc of a given irradiance over a sky whose brightness
//! and haze follow the sun's elevation and a turbidity), a CIE overcast sky, and studio set-ups
//! of one to three disc-shaped area lights. All are equirectangular, linear RGB, in the
//! conventions of `volux_envmap::direction` (+y up, `u = 1/2` facing +z).

use std::f64::consts::PI;

use volux_envmap::direction::{self, Dir};
use volux_envmap::{EnvMap, EnvMapError, Rgb};

/// A sun over a clear sky.
#[derive(Clone, Debug, PartialEq)]
pub struct SunSky {
    /// Sun elevation above the horizon, radians (may be negative: below the horizon).
    pub elevation: f64,
    /// Sun azimuth, radians (0: towards +z, the side the face looks at).
    pub azimuth: f64,
    /// Haze, 2 (clear) to 10 (hazy): widens the glow around the sun and whitens the sky.
    pub turbidity: f64,
    /// Irradiance of the sun disc on a surface facing it (the sky adds to this).
    pub sun_irradiance: f64,
    /// Angular radius of the sun disc, radians (the real sun: 0.0047; larger is softer).
    pub sun_radius: f64,
}

/// A studio light: a disc of uniform radiance.
#[derive(Clone, Debug, PartialEq)]
pub struct AreaLight {
    /// Direction from the head to the light's centre (need not be unit).
    pub direction: Dir,
    /// Angular radius, radians.
    pub radius: f64,
    /// Irradiance on a surface facing the light.
    pub irradiance: Rgb,
}

/// Direction of elevation `e` above the horizon and azimuth `a` (0 towards +z).
pub fn sun_direction(elevation: f64, azimuth: f64) -> Dir {
    [
        elevation.cos() * azimuth.sin(),
        elevation.sin(),
        elevation.cos() * azimuth.cos(),
    ]
}

/// Fills a `2h x h` map from a radiance function of direction, averaging `s x s`
/// sub-samples per texel so that discs smaller than a texel keep their energy.
fn render(height: usize, samples: usize, radiance: impl Fn(Dir) -> [f64; 3]) -> Vec<Rgb> {
    let width = 2 * height;
    let (sw, sh) = (width * samples, height * samples);
    let mut texels = vec![[0.0f64; 3]; width * height];
    for sy in 0..sh {
        let omega = direction::row_solid_angle(sy, sw, sh);
        for sx in 0..sw {
            let l = radiance(direction::texel_dir(sx, sy, sw, sh));
            let t = &mut texels[(sy / samples) * width + sx / samples];
            for k in 0..3 {
                t[k] += l[k] * omega;
            }
        }
    }
    // Back from energy to radiance per texel.
    (0..width * height)
        .map(|i| {
            let omega = direction::row_solid_angle(i / width, width, height);
            texels[i].map(|e| (e / omega) as f32)
        })
        .collect()
}

/// Sub-samples per texel side: enough to resolve a disc of angular radius `radius`.
fn samples_for(height: usize, radius: f64) -> usize {
    let texel = PI / height as f64;
    ((2.0 * texel / radius).ceil() as usize).clamp(1, 64)
}

/// A disc of angular radius `radius` around `dir` (unit) as `2h x h` radiance texels,
/// rasterised with sub-samples and then scaled so that the map itself (texel centres and
/// solid angles, as every integral over it sees it) delivers `irradiance` to a surface facing
/// the disc: small discs keep their energy exactly, whatever the resolution.
fn disc_texels(height: usize, dir: Dir, radius: f64, irradiance: [f64; 3]) -> Vec<[f64; 3]> {
    let width = 2 * height;
    let cos_r = radius.cos();
    let coverage = render(height, samples_for(height, radius), |d| {
        [f64::from(u8::from(direction::dot(d, dir) >= cos_r)); 3]
    });
    let mut delivered = 0.0f64;
    for (i, c) in coverage.iter().enumerate() {
        let (x, y) = (i % width, i / width);
        let cos = direction::dot(direction::texel_dir(x, y, width, height), dir).max(0.0);
        delivered += f64::from(c[0]) * cos * direction::row_solid_angle(y, width, height);
    }
    let scale = if delivered > 0.0 {
        1.0 / delivered
    } else {
        0.0
    };
    coverage
        .iter()
        .map(|c| irradiance.map(|e| e * f64::from(c[0]) * scale))
        .collect()
}

impl SunSky {
    /// The environment at `height` rows (width `2 * height`).
    pub fn render(&self, height: usize) -> Result<EnvMap, EnvMapError> {
        let sun = sun_direction(self.elevation, self.azimuth);
        let day = self.elevation.sin().max(0.0).sqrt(); // brightness of the sky with sun height
        let haze = ((self.turbidity - 2.0) / 8.0).clamp(0.0, 1.0);
        let zenith = [0.25, 0.45, 0.9].map(|c: f64| c * (1.0 - 0.6 * haze) + 0.6 * haze);
        let horizon = [0.8, 0.85, 0.95];
        let glow_width = 0.1 + 0.4 * haze;
        let sky_scale = 0.03 * self.sun_irradiance * (0.1 + day);
        let ground = [0.3, 0.28, 0.25];
        let sky = render(height, 1, |d| {
            let cos_sun = direction::dot(d, sun);
            let mut l = [0.0f64; 3];
            let up = d[1];
            let glow = (-(1.0 - cos_sun) / glow_width).exp();
            if up >= 0.0 {
                let t = (1.0 - up).powi(3);
                for k in 0..3 {
                    let base = zenith[k] * (1.0 - t) + horizon[k] * t;
                    l[k] += sky_scale * (base + 2.0 * glow);
                }
            } else {
                // Ground: a grey plane lit by sun and sky.
                let lit = sky_scale * (0.5 + 10.0 * self.elevation.sin().max(0.0));
                for k in 0..3 {
                    l[k] += lit * ground[k];
                }
            }
            l
        });
        let disc = disc_texels(height, sun, self.sun_radius, [self.sun_irradiance; 3]);
        let texels = sky
            .iter()
            .zip(disc)
            .map(|(s, d)| std::array::from_fn(|k| s[k] + d[k] as f32))
            .collect();
        EnvMap::new(2 * height, height, texels)
    }
}

/// The CIE overcast sky: radiance `zenith (1 + 2 cos theta) / 3` above the horizon, a dim
/// ground below.
pub fn overcast(height: usize, zenith: f64) -> Result<EnvMap, EnvMapError> {
    let texels = render(height, 1, |d| {
        if d[1] >= 0.0 {
            [zenith * (1.0 + 2.0 * d[1]) / 3.0; 3]
        } else {
            [zenith * 0.1; 3]
        }
    });
    EnvMap::new(2 * height, height, texels)
}

/// A studio: black walls and disc area lights.
pub fn studio(height: usize, lights: &[AreaLight]) -> Result<EnvMap, EnvMapError> {
    let mut texels = vec![[0.0f32; 3]; 2 * height * height];
    for l in lights {
        let disc = disc_texels(
            height,
            direction::normalize(l.direction),
            l.radius,
            l.irradiance.map(f64::from),
        );
        for (t, d) in texels.iter_mut().zip(disc) {
            for (tk, dk) in t.iter_mut().zip(d) {
                *tk += dk as f32;
            }
        }
    }
    EnvMap::new(2 * height, height, texels)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Irradiance on a surface with normal `n`: sum of L max(0, n.w) over texels, in f64.
    fn irradiance(map: &EnvMap, n: Dir) -> [f64; 3] {
        let (w, h) = (map.width(), map.height());
        let mut e = [0.0f64; 3];
        for y in 0..h {
            let omega = direction::row_solid_angle(y, w, h);
            for x in 0..w {
                let c = direction::dot(direction::texel_dir(x, y, w, h), n).max(0.0);
                let t = map.texel(x, y);
                for k in 0..3 {
                    e[k] += f64::from(t[k]) * c * omega;
                }
            }
        }
        e
    }

    #[test]
    fn the_sun_delivers_its_irradiance_and_the_sky_is_finite() {
        let sky = SunSky {
            elevation: 0.6,
            azimuth: 0.8,
            turbidity: 3.0,
            sun_irradiance: 1e6,
            sun_radius: 0.0047,
        };
        let map = sky.render(64).unwrap();
        assert!(
            map.texels()
                .iter()
                .flatten()
                .all(|v| v.is_finite() && *v >= 0.0)
        );
        let n = sun_direction(0.6, 0.8);
        // Facing the sun: the disc's 1e6 plus a sky of a few percent of it.
        let e = irradiance(&map, n)[0];
        assert!((1e6..1.2e6).contains(&e), "irradiance facing the sun {e}");
        let without = SunSky {
            sun_irradiance: 0.0,
            ..sky.clone()
        }
        .render(64)
        .unwrap();
        assert!(
            without.texels().iter().flatten().all(|v| *v == 0.0),
            "no sun, no light"
        );
        // The brightest texel is the sun's.
        let (i, _) = map
            .texels()
            .iter()
            .enumerate()
            .fold(
                (0, 0.0f32),
                |best, (i, t)| if t[0] > best.1 { (i, t[0]) } else { best },
            );
        let d = direction::texel_dir(i % 128, i / 128, 128, 64);
        assert!(direction::dot(d, n) > 0.99, "brightest texel at {d:?}");
    }

    #[test]
    fn overcast_is_three_times_brighter_at_the_zenith_than_at_the_horizon() {
        let map = overcast(32, 3.0).unwrap();
        for y in 0..16 {
            let up = direction::texel_dir(0, y, 64, 32)[1];
            let want = 3.0 * (1.0 + 2.0 * up) / 3.0;
            let got = f64::from(map.texel(0, y)[0]);
            assert!((got - want).abs() < 1e-4 * want, "row {y}: {got} vs {want}");
        }
        let (top, horizon) = (map.texel(0, 0)[0], map.texel(0, 15)[0]);
        assert!(
            top / horizon > 2.5,
            "zenith {top}, near the horizon {horizon}"
        );
        // Irradiance on an upward surface: integral of L cos = pi Lz (1/3 + 4/9) = 7 pi Lz / 9.
        let e = irradiance(&map, [0.0, 1.0, 0.0])[0];
        assert!((e - 7.0 * PI * 3.0 / 9.0).abs() < 0.05 * e, "{e}");
    }

    #[test]
    fn studio_lights_deliver_their_irradiance_from_their_directions() {
        let lights = [
            AreaLight {
                direction: [1.0, 0.5, 1.0],
                radius: 0.2,
                irradiance: [3.0, 2.0, 1.0],
            },
            AreaLight {
                direction: [-1.0, 0.0, 0.2],
                radius: 0.05,
                irradiance: [0.5; 3],
            },
        ];
        let map = studio(64, &lights).unwrap();
        for l in &lights {
            let n = direction::normalize(l.direction);
            let e = irradiance(&map, n);
            for (got, want) in e.iter().zip(l.irradiance.map(f64::from)) {
                // Facing one light; the other is more than 90 degrees away.
                assert!(
                    (got - want).abs() < 1e-3 * want,
                    "light {:?}: {got} vs {want}",
                    l.direction
                );
            }
        }
        let black = direction::texel_dir(0, 63, 128, 64);
        assert_eq!(map.texel(0, 63), [0.0; 3], "walls are black ({black:?})");
    }
}
