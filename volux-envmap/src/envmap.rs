//! The equirectangular environment map type.

use crate::direction::{self, Dir};
use crate::error::{EnvMapError, IN_MEMORY};

/// One linear-RGB radiance value.
pub type Rgb = [f32; 3];

/// Rec. 709 luminance of a linear-RGB value.
pub fn luminance(c: Rgb) -> f64 {
    0.2126 * f64::from(c[0]) + 0.7152 * f64::from(c[1]) + 0.0722 * f64::from(c[2])
}

/// An equirectangular, linear-RGB, f32 environment map: `width = 2 * height` texels stored
/// row-major from the top (`v = 0`, +y) row, each row from `u = 0` (azimuth -pi, the -z side).
///
/// Every texel is finite and non-negative; constructors enforce it.
#[derive(Clone, Debug, PartialEq)]
pub struct EnvMap {
    width: usize,
    height: usize,
    texels: Vec<Rgb>,
}

/// The brightest texel value a map may hold. The shipped maps peak at 3.3e4 (an unclipped
/// sun), and a sun in absolute units is about 1.6e9 cd/m^2; above 1e15 the light maps, the
/// shading products and the look-up's gradients (texel differences times the map width,
/// squared by Adam) come within reach of f32's 3.4e38, so such a value is refused by name
/// rather than turned into infinite shading.
pub const MAX_RADIANCE: f32 = 1e15;

/// Negative texels down to this are compression noise, clamped with only a debug message.
const NEGATIVE_NOISE: f32 = 0.01;

impl EnvMap {
    /// A map from row-major texels. Errors on a size mismatch, an empty or non-2:1 map, NaN/Inf
    /// values and values above [`MAX_RADIANCE`]; negative values are clamped to 0 and counted in a `tracing` warning
    /// (a debug message when none is below -0.01, compression noise around black).
    pub fn new(width: usize, height: usize, texels: Vec<Rgb>) -> Result<Self, EnvMapError> {
        Self::validated(width, height, texels, IN_MEMORY)
    }

    /// Like [`EnvMap::new`], naming `origin` (usually the file path) in errors and warnings.
    pub fn validated(
        width: usize,
        height: usize,
        mut texels: Vec<Rgb>,
        origin: &str,
    ) -> Result<Self, EnvMapError> {
        check_shape(width, height, texels.len(), origin)?;
        let stats = MapStats::of(width, height, &texels);
        if stats.non_finite > 0 {
            let first = texels
                .iter()
                .position(|c| c.iter().any(|v| !v.is_finite()))
                .unwrap_or(0);
            return Err(EnvMapError::NonFinite {
                origin: origin.to_string(),
                count: stats.non_finite,
                x: first % width,
                y: first / width,
            });
        }
        if let Some(first) = texels
            .iter()
            .position(|c| c.iter().any(|v| *v > MAX_RADIANCE))
        {
            let value = texels[first].iter().copied().fold(f32::MIN, f32::max);
            return Err(EnvMapError::TooBright {
                origin: origin.to_string(),
                value,
                x: first % width,
                y: first / width,
                max: MAX_RADIANCE,
            });
        }
        if stats.negative > 0 {
            for c in &mut texels {
                for v in c.iter_mut() {
                    *v = v.max(0.0);
                }
            }
            // Compression noise around black (lossy EXR codecs leave values of -1e-3) is
            // routine; a clearly negative value means a broken map and deserves a warning.
            if stats.min_value < -NEGATIVE_NOISE {
                tracing::warn!(
                    "{origin}: clamped {} negative texel values to 0 (most negative {:e})",
                    stats.negative,
                    stats.min_value
                );
            } else {
                tracing::debug!(
                    "{origin}: clamped {} slightly negative texel values to 0 (most negative {:e})",
                    stats.negative,
                    stats.min_value
                );
            }
        }
        Ok(Self {
            width,
            height,
            texels,
        })
    }

    /// A map of one colour everywhere.
    pub fn constant(height: usize, value: Rgb) -> Result<Self, EnvMapError> {
        Self::new(2 * height, height, vec![value; 2 * height * height])
    }

    /// A map whose texel at the centre of `(x, y)` takes `f(direction)`.
    pub fn from_fn(height: usize, f: impl Fn(Dir) -> Rgb) -> Result<Self, EnvMapError> {
        let width = 2 * height;
        let texels = (0..height)
            .flat_map(|y| (0..width).map(move |x| (x, y)))
            .map(|(x, y)| f(direction::texel_dir(x, y, width, height)))
            .collect();
        Self::new(width, height, texels)
    }

    /// Width in texels (`2 * height`).
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in texels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// All texels, row-major from the top row.
    pub fn texels(&self) -> &[Rgb] {
        &self.texels
    }

    /// One row of texels.
    pub fn row(&self, y: usize) -> &[Rgb] {
        &self.texels[y * self.width..(y + 1) * self.width]
    }

    /// The texel at column `x`, row `y`.
    pub fn texel(&self, x: usize, y: usize) -> Rgb {
        self.texels[y * self.width + x]
    }

    /// Mutable texel access; values written must stay finite and non-negative.
    pub fn set_texel(&mut self, x: usize, y: usize, value: Rgb) {
        debug_assert!(value.iter().all(|v| v.is_finite() && *v >= 0.0));
        self.texels[y * self.width + x] = value;
    }

    /// Whether every texel is zero.
    pub fn is_black(&self) -> bool {
        self.texels.iter().all(|c| c.iter().all(|v| *v == 0.0))
    }

    /// Summary statistics (see [`MapStats`]).
    pub fn stats(&self) -> MapStats {
        MapStats::of(self.width, self.height, &self.texels)
    }

    /// The map rotated by `angle` radians about +y (right-handed), i.e. light that came from
    /// direction `d` now comes from `rotate_yaw(d, angle)`; `u` shifts by `angle / (2 pi)` with
    /// wrap-around (the paper's random HDRI rotation).
    ///
    /// A whole number of texels is an exact shift. Otherwise each row is resampled linearly,
    /// which keeps every row's energy and non-negativity but blurs by up to half a texel;
    /// [`crate::LightMap::lookup_rotated`] rotates light maps exactly at look-up time instead.
    pub fn rotated_yaw(&self, angle: f64) -> EnvMap {
        let w = self.width;
        let shift = (angle / std::f64::consts::TAU).rem_euclid(1.0) * w as f64;
        let whole = shift.floor();
        let frac = (shift - whole) as f32;
        let whole = whole as usize % w;
        let mut texels = Vec::with_capacity(self.texels.len());
        for y in 0..self.height {
            let row = self.row(y);
            for x in 0..w {
                // new(x) = old(x - shift): a mix of old(x - whole) and old(x - whole - 1).
                let a = row[(x + w - whole) % w];
                let b = row[(x + 2 * w - whole - 1) % w];
                texels.push(std::array::from_fn(|c| (1.0 - frac) * a[c] + frac * b[c]));
            }
        }
        EnvMap {
            width: w,
            height: self.height,
            texels,
        }
    }

    /// The map area-averaged by an integer `factor` in both directions (texels weighted by
    /// their exact solid angle, so the total energy is kept). `factor` must divide the height.
    pub fn downsampled(&self, factor: usize) -> EnvMap {
        assert!(
            factor >= 1 && self.height.is_multiple_of(factor),
            "factor must divide the height"
        );
        let (w, h) = (self.width / factor, self.height / factor);
        let mut texels = vec![[0f32; 3]; w * h];
        for (y, row_out) in texels.chunks_mut(w).enumerate() {
            let mut acc = vec![[0f64; 3]; w];
            let mut weight = 0.0;
            for yy in y * factor..(y + 1) * factor {
                let omega = direction::row_solid_angle(yy, self.width, self.height);
                weight += omega * factor as f64;
                for (x, c) in self.row(yy).iter().enumerate() {
                    for k in 0..3 {
                        acc[x / factor][k] += omega * f64::from(c[k]);
                    }
                }
            }
            for (out, a) in row_out.iter_mut().zip(&acc) {
                *out = std::array::from_fn(|k| (a[k] / weight) as f32);
            }
        }
        EnvMap {
            width: w,
            height: h,
            texels,
        }
    }
}

pub(crate) fn check_shape(
    width: usize,
    height: usize,
    len: usize,
    origin: &str,
) -> Result<(), EnvMapError> {
    if width == 0 || height == 0 {
        return Err(EnvMapError::Empty {
            origin: origin.to_string(),
            width,
            height,
        });
    }
    if width != 2 * height {
        return Err(EnvMapError::AspectRatio {
            origin: origin.to_string(),
            width,
            height,
        });
    }
    if len != width * height {
        return Err(EnvMapError::BufferSize {
            origin: origin.to_string(),
            width,
            height,
            expected: width * height,
            actual: len,
        });
    }
    Ok(())
}

/// What `volux envmap info` prints about a map (computed on the raw texels, before any
/// validation, so that it can describe a broken file too).
#[derive(Clone, Debug, PartialEq)]
pub struct MapStats {
    pub width: usize,
    pub height: usize,
    /// Smallest and largest luminance over finite texels.
    pub min_luminance: f64,
    pub max_luminance: f64,
    /// Luminance averaged over the sphere, each texel weighted by its solid angle (so that
    /// the stretched polar rows do not count more than they light).
    pub mean_luminance: f64,
    /// The brightest finite texel and the direction of its centre.
    pub brightest_texel: (usize, usize),
    pub brightest_direction: Dir,
    /// Most negative channel value (0 if none is negative).
    pub min_value: f32,
    /// Number of negative channel values.
    pub negative: usize,
    /// Number of NaN or infinite channel values.
    pub non_finite: usize,
}

impl MapStats {
    /// Statistics of `width x height` row-major texels (any values).
    pub fn of(width: usize, height: usize, texels: &[Rgb]) -> MapStats {
        let mut s = MapStats {
            width,
            height,
            min_luminance: f64::INFINITY,
            max_luminance: f64::NEG_INFINITY,
            mean_luminance: 0.0,
            brightest_texel: (0, 0),
            brightest_direction: [0.0, 1.0, 0.0],
            min_value: 0.0,
            negative: 0,
            non_finite: 0,
        };
        let mut weighted = 0.0;
        let mut total_weight = 0.0;
        for (i, c) in texels.iter().enumerate() {
            let (x, y) = (i % width.max(1), i / width.max(1));
            let mut finite = true;
            for &v in c {
                if !v.is_finite() {
                    s.non_finite += 1;
                    finite = false;
                } else if v < 0.0 {
                    s.negative += 1;
                    s.min_value = s.min_value.min(v);
                }
            }
            if !finite {
                continue;
            }
            let lum = luminance(*c);
            s.min_luminance = s.min_luminance.min(lum);
            if lum > s.max_luminance {
                s.max_luminance = lum;
                s.brightest_texel = (x, y);
            }
            let omega = direction::row_solid_angle(y, width, height);
            weighted += omega * lum;
            total_weight += omega;
        }
        if total_weight > 0.0 {
            s.mean_luminance = weighted / total_weight;
            s.brightest_direction =
                direction::texel_dir(s.brightest_texel.0, s.brightest_texel.1, width, height);
        } else {
            s.min_luminance = 0.0;
            s.max_luminance = 0.0;
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn ramp(h: usize) -> EnvMap {
        let w = 2 * h;
        let texels = (0..w * h)
            .map(|i| [i as f32, (i % w) as f32, 1.0])
            .collect();
        EnvMap::new(w, h, texels).unwrap()
    }

    #[test]
    fn rejects_empty_non_equirect_and_short_buffers() {
        let e = EnvMap::new(0, 0, vec![]).unwrap_err();
        assert!(matches!(e, EnvMapError::Empty { .. }), "{e}");
        let e = EnvMap::new(6, 4, vec![[0.0; 3]; 24]).unwrap_err();
        assert!(e.to_string().contains("6x4"), "{e}");
        let e = EnvMap::new(8, 4, vec![[0.0; 3]; 31]).unwrap_err();
        assert!(e.to_string().contains("got 31"), "{e}");
    }

    #[test]
    fn rejects_non_finite_with_count_and_position() {
        let mut t = vec![[1.0f32; 3]; 32];
        t[9] = [f32::NAN, 1.0, f32::INFINITY];
        t[20][1] = f32::NEG_INFINITY;
        let e = EnvMap::validated(8, 4, t, "sky.exr").unwrap_err();
        let msg = e.to_string();
        assert!(
            msg.contains("sky.exr") && msg.contains("3 texel values"),
            "{msg}"
        );
        assert!(msg.contains("x=1, y=1"), "{msg}");
    }

    #[test]
    fn refuses_radiance_that_would_overflow_shading_by_name() {
        let mut t = vec![[1.0f32; 3]; 32];
        t[13] = [0.5, 3e38, 2.0];
        let e = EnvMap::validated(8, 4, t.clone(), "hot.exr").unwrap_err();
        let msg = e.to_string();
        assert!(
            matches!(e, EnvMapError::TooBright { x: 5, y: 1, .. }),
            "{msg}"
        );
        assert!(msg.contains("hot.exr") && msg.contains("3e38"), "{msg}");
        // The limit itself, and a very bright but real sun, are accepted.
        t[13] = [MAX_RADIANCE, 1.6e9, 1.0];
        assert!(EnvMap::validated(8, 4, t, "sun.exr").is_ok());
    }

    #[test]
    fn clamps_negatives() {
        let mut t = vec![[1.0f32; 3]; 32];
        t[3] = [-1e-3, 2.0, -0.5];
        let stats = MapStats::of(8, 4, &t);
        assert_eq!((stats.negative, stats.min_value), (2, -0.5));
        let m = EnvMap::new(8, 4, t).unwrap();
        assert_eq!(m.texel(3, 0), [0.0, 2.0, 0.0]);
        assert_eq!(m.stats().negative, 0);
    }

    #[test]
    fn stats_weight_by_solid_angle_and_find_the_sun() {
        let mut m = EnvMap::constant(16, [1.0, 1.0, 1.0]).unwrap();
        assert!((m.stats().mean_luminance - 1.0).abs() < 1e-12);
        m.set_texel(5, 7, [100.0, 100.0, 100.0]);
        let s = m.stats();
        assert_eq!(s.brightest_texel, (5, 7));
        assert_eq!(s.max_luminance, 100.0);
        let omega = direction::row_solid_angle(7, 32, 16);
        assert!((s.mean_luminance - (1.0 + 99.0 * omega / (4.0 * PI))).abs() < 1e-9);
        assert_eq!(s.brightest_direction, direction::texel_dir(5, 7, 32, 16));
    }

    #[test]
    fn rotation_by_whole_texels_is_a_shift_and_full_turn_is_identity() {
        let m = ramp(4);
        assert_eq!(m.rotated_yaw(2.0 * PI), m);
        assert_eq!(m.rotated_yaw(0.0), m);
        let r = m.rotated_yaw(2.0 * PI * 3.0 / 8.0);
        for y in 0..4 {
            for x in 0..8 {
                assert_eq!(r.texel((x + 3) % 8, y), m.texel(x, y));
            }
        }
        // Negative angles go the other way.
        assert_eq!(m.rotated_yaw(-2.0 * PI / 8.0).texel(0, 2), m.texel(1, 2));
    }

    #[test]
    fn fractional_rotation_keeps_energy_and_moves_light_with_the_direction() {
        let mut m = EnvMap::constant(32, [0.0; 3]).unwrap();
        m.set_texel(10, 12, [1.0, 1.0, 1.0]);
        let angle = 0.3;
        let r = m.rotated_yaw(angle);
        let sum = |e: &EnvMap| e.texels().iter().map(|c| f64::from(c[0])).sum::<f64>();
        assert!((sum(&r) - 1.0).abs() < 1e-6);
        // The centroid of the row moves by angle / (2 pi) * width texels.
        let cx: f64 = (0..64)
            .map(|x| x as f64 * f64::from(r.texel(x, 12)[0]))
            .sum();
        assert!(
            (cx - (10.0 + angle / (2.0 * PI) * 64.0)).abs() < 1e-4,
            "{cx}"
        );
    }

    #[test]
    fn downsampling_keeps_energy() {
        let m = ramp(8);
        let d = m.downsampled(4);
        assert_eq!((d.width(), d.height()), (4, 2));
        let energy = |e: &EnvMap| -> f64 {
            (0..e.height())
                .map(|y| {
                    let omega = direction::row_solid_angle(y, e.width(), e.height());
                    e.row(y)
                        .iter()
                        .map(|c| omega * f64::from(c[0]))
                        .sum::<f64>()
                })
                .sum()
        };
        assert!(
            (energy(&m) - energy(&d)).abs() < 1e-6 * energy(&m),
            "f32 rounding only"
        );
    }
}
