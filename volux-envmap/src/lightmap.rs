//! Preconvolved light maps and their bilinear look-up.
//!
//! # Layout (shared with the tensor look-up of the model)
//!
//! A light map of exponent `n` is an equirectangular `width x height` grid (`width = 2 height`)
//! of linear RGB, row-major from the top row, holding `L_n` at the texel centres: texel `(x, y)`
//! is at `u = (x + 0.5) / width`, `v = (y + 0.5) / height` (the environment-map convention).
//!
//! Look-up at `(u, v)` is bilinear at pixel coordinates `(u width - 0.5, v height - 0.5)` over
//! the map extended by one texel on every side ([`LightMap::padded`]):
//! - columns wrap: column `-1` is column `width - 1`, column `width` is column 0;
//! - across a pole, row `-1` is row 0 and row `height` is row `height - 1`, each taken half a
//!   turn away (column `x + width / 2`): the texel that is really there.
//!
//! So the padded `(height + 2) x (width + 2)` array, sampled bilinearly with pixel centres at
//! integer coordinates (`align_corners = true`) at `(u width + 0.5, v height + 0.5)`, gives
//! exactly [`LightMap::lookup_uv`]; that is how a tensor library samples the same maps. The
//! look-up is continuous everywhere, across the seam and over the poles, and second-order
//! accurate at the poles.

use std::path::Path;

use crate::direction::{self, Dir};
use crate::envmap::Rgb;
use crate::error::EnvMapError;
use crate::io;

/// One preconvolved light map `L_n`.
#[derive(Clone, Debug, PartialEq)]
pub struct LightMap {
    exponent: u32,
    width: usize,
    height: usize,
    texels: Vec<Rgb>,
    clamped: usize,
    ringing: f64,
}

impl LightMap {
    /// A light map from its texels (see the module docs for the layout).
    ///
    /// # Panics
    /// If `width != 2 * height`, the map is empty, or `texels` has the wrong length: light maps
    /// are made by this crate, never read from users without validation.
    pub fn new(exponent: u32, width: usize, height: usize, texels: Vec<Rgb>) -> LightMap {
        assert!(height > 0 && width == 2 * height, "light maps are 2:1");
        assert_eq!(texels.len(), width * height, "light-map texel count");
        LightMap {
            exponent,
            width,
            height,
            texels,
            clamped: 0,
            ringing: 0.0,
        }
    }

    /// Records how many values were negative (band-limit ringing) and clamped to 0, and the
    /// deepest of them relative to the map's peak.
    pub fn with_clamped(mut self, clamped: usize, ringing: f64) -> LightMap {
        self.clamped = clamped;
        self.ringing = ringing;
        self
    }

    /// The deepest negative value before clamping, relative to the peak (0 if none).
    pub fn ringing(&self) -> f64 {
        self.ringing
    }

    /// How many channel values were negative when computed and are stored as 0.
    pub fn clamped(&self) -> usize {
        self.clamped
    }

    /// The Phong exponent `n`.
    pub fn exponent(&self) -> u32 {
        self.exponent
    }

    /// Width in texels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in texels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Texels, row-major from the top row.
    pub fn texels(&self) -> &[Rgb] {
        &self.texels
    }

    /// The texel at `(x, y)` for `x` in `-1..=width`, `y` in `-1..=height` (see the layout).
    #[inline]
    pub fn fetch(&self, x: isize, y: isize) -> Rgb {
        let (w, h) = (self.width as isize, self.height as isize);
        let (x, y) = if y < 0 {
            (x + w / 2, 0)
        } else if y >= h {
            (x + w / 2, h - 1)
        } else {
            (x, y)
        };
        self.texels[(y * w + x.rem_euclid(w)) as usize]
    }

    /// Bilinear look-up at texture coordinates `u` (any real, wrapped) and `v` in `[0, 1]`.
    pub fn lookup_uv(&self, u: f64, v: f64) -> Rgb {
        let x = u.rem_euclid(1.0) * self.width as f64 - 0.5;
        let y = v.clamp(0.0, 1.0) * self.height as f64 - 0.5;
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = ((x - x0) as f32, (y - y0) as f32);
        let (x0, y0) = (x0 as isize, y0 as isize);
        let c00 = self.fetch(x0, y0);
        let c10 = self.fetch(x0 + 1, y0);
        let c01 = self.fetch(x0, y0 + 1);
        let c11 = self.fetch(x0 + 1, y0 + 1);
        std::array::from_fn(|c| {
            let top = c00[c] + fx * (c10[c] - c00[c]);
            let bottom = c01[c] + fx * (c11[c] - c01[c]);
            top + fy * (bottom - top)
        })
    }

    /// `L_n` in direction `d` (need not be normalised; must be non-zero).
    pub fn lookup(&self, d: Dir) -> Rgb {
        let (u, v) = direction::dir_to_uv(d);
        self.lookup_uv(u, v)
    }

    /// `L_n` of the environment rotated by `yaw` about +y (as [`crate::EnvMap::rotated_yaw`]),
    /// in direction `d`. Exact: rotating the environment and convolving commute, so this is the
    /// look-up at the direction rotated back.
    pub fn lookup_rotated(&self, d: Dir, yaw: f64) -> Rgb {
        // Rotating the direction back by `yaw` subtracts `yaw / 2 pi` from `u` (and, on the
        // vertical axis, keeps the convention u = 1/2 of `dir_to_uv` for the unrotated map).
        let (u, v) = direction::dir_to_uv(d);
        self.lookup_uv(u - yaw / std::f64::consts::TAU, v)
    }

    /// The map extended by one texel on every side, `(height + 2) x (width + 2)` row-major:
    /// the array a tensor look-up samples (see the module docs).
    pub fn padded(&self) -> Vec<Rgb> {
        let (w, h) = (self.width as isize, self.height as isize);
        (-1..=h)
            .flat_map(|y| (-1..=w).map(move |x| (x, y)))
            .map(|(x, y)| self.fetch(x, y))
            .collect()
    }
}

/// The light maps of one environment, one per exponent, in the order asked for.
#[derive(Clone, Debug, PartialEq)]
pub struct LightMapSet {
    maps: Vec<LightMap>,
}

impl LightMapSet {
    /// A set from its maps.
    pub fn new(maps: Vec<LightMap>) -> Self {
        Self { maps }
    }

    /// The maps, in the order of their exponents as requested.
    pub fn maps(&self) -> &[LightMap] {
        &self.maps
    }

    /// The map of exponent `n`, if present.
    pub fn get(&self, n: u32) -> Option<&LightMap> {
        self.maps.iter().find(|m| m.exponent == n)
    }

    /// The exponents, in order.
    pub fn exponents(&self) -> Vec<u32> {
        self.maps.iter().map(|m| m.exponent).collect()
    }

    /// File name of the EXR of exponent `n` inside an output directory.
    pub fn file_name(n: u32) -> String {
        format!("light_n{n:03}.exr")
    }

    /// Writes one EXR per lobe (`light_n001.exr`, ...) and a contact sheet `light_maps.png`
    /// (the lobes top to bottom in order, all at the same size and exposure) into `dir`,
    /// creating it if needed. Returns the paths written.
    pub fn save(&self, dir: &Path) -> Result<Vec<std::path::PathBuf>, EnvMapError> {
        std::fs::create_dir_all(dir).map_err(|source| EnvMapError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        let mut written = Vec::new();
        for m in &self.maps {
            let path = dir.join(Self::file_name(m.exponent));
            io::save_exr(&path, m.width, m.height, &m.texels)?;
            written.push(path);
        }
        if !self.maps.is_empty() {
            let path = dir.join("light_maps.png");
            let (w, h, sheet) = self.contact_sheet(256);
            io::save_png(&path, w, h, &sheet)?;
            written.push(path);
        }
        Ok(written)
    }

    /// All lobes resampled to `2 tile_height x tile_height`, stacked top to bottom, tone-mapped
    /// with one exposure (that of the first lobe) so their brightness compares.
    pub fn contact_sheet(&self, tile_height: usize) -> (usize, usize, Vec<[u8; 3]>) {
        let tw = 2 * tile_height;
        let mut linear = Vec::with_capacity(tw * tile_height * self.maps.len());
        for m in &self.maps {
            for y in 0..tile_height {
                for x in 0..tw {
                    let u = (x as f64 + 0.5) / tw as f64;
                    let v = (y as f64 + 0.5) / tile_height as f64;
                    linear.push(m.lookup_uv(u, v));
                }
            }
        }
        let exposure = io::auto_exposure(&linear[..tw * tile_height]);
        (
            tw,
            tile_height * self.maps.len(),
            io::tonemap(&linear, exposure),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn ramp(h: usize) -> LightMap {
        let w = 2 * h;
        let texels = (0..w * h)
            .map(|i| [(i % w) as f32, (i / w) as f32, ((i * 7919) % 13) as f32])
            .collect();
        LightMap::new(16, w, h, texels)
    }

    #[test]
    fn texel_centres_return_the_texel() {
        let m = ramp(4);
        for y in 0..4 {
            for x in 0..8 {
                let got = m.lookup_uv((x as f64 + 0.5) / 8.0, (y as f64 + 0.5) / 4.0);
                assert_eq!(got, m.texels()[y * 8 + x]);
            }
        }
    }

    #[test]
    fn wraps_across_the_seam_continuously() {
        let m = ramp(4);
        let left = m.lookup_uv(1e-9, 0.4);
        let right = m.lookup_uv(1.0 - 1e-9, 0.4);
        for c in 0..3 {
            assert!((left[c] - right[c]).abs() < 1e-5);
        }
        // Half-way between the last and first columns.
        let mid = m.lookup_uv(0.0, 0.375);
        let (a, b) = (m.texels()[8 + 7], m.texels()[8]);
        for c in 0..3 {
            assert!((mid[c] - 0.5 * (a[c] + b[c])).abs() < 1e-5);
        }
        assert_eq!(m.lookup_uv(1.25, 0.3), m.lookup_uv(0.25, 0.3));
        assert_eq!(m.lookup_uv(-0.75, 0.3), m.lookup_uv(0.25, 0.3));
    }

    #[test]
    fn continuous_over_the_poles() {
        let m = ramp(8);
        for u in [0.0, 0.1, 0.37, 0.8] {
            // Crossing the north pole along a meridian: v -> 0 at u equals v -> 0 at u + 1/2.
            let a = m.lookup_uv(u, 1e-9);
            let b = m.lookup_uv(u + 0.5, 1e-9);
            for c in 0..3 {
                assert!((a[c] - b[c]).abs() < 1e-4, "north u={u}");
            }
            let a = m.lookup_uv(u, 1.0 - 1e-9);
            let b = m.lookup_uv(u + 0.5, 1.0 - 1e-9);
            for c in 0..3 {
                assert!((a[c] - b[c]).abs() < 1e-4, "south u={u}");
            }
        }
    }

    #[test]
    fn smooth_function_is_second_order_accurate_at_the_pole() {
        // f(d) = 1 + d.x: at the pole it is 1 from every azimuth, up to O(h^2).
        for h in [16usize, 64] {
            let w = 2 * h;
            let texels = (0..w * h)
                .map(|i| {
                    let d = direction::texel_dir(i % w, i / w, w, h);
                    [(1.0 + d[0]) as f32; 3]
                })
                .collect();
            let m = LightMap::new(1, w, h, texels);
            let err = (0..16)
                .map(|k| (m.lookup_uv(k as f64 / 16.0, 0.0)[0] - 1.0).abs())
                .fold(0.0f32, f32::max);
            let bound = (PI / h as f64).powi(2) as f32;
            assert!(err <= bound, "h={h}: {err} > {bound}");
        }
    }

    #[test]
    fn padded_layout_reproduces_the_lookup() {
        let m = ramp(4);
        let (w, h) = (8usize, 4usize);
        let p = m.padded();
        assert_eq!(p.len(), (w + 2) * (h + 2));
        // Bilinear with align_corners = true on the padded array at (u w + 0.5, v h + 0.5).
        let sample = |u: f64, v: f64| -> Rgb {
            let (x, y) = (u * w as f64 + 0.5, v * h as f64 + 0.5);
            let (x0, y0) = (x.floor() as usize, y.floor() as usize);
            let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
            let at = |x: usize, y: usize| p[y.min(h + 1) * (w + 2) + x.min(w + 1)];
            std::array::from_fn(|c| {
                let top = at(x0, y0)[c] * (1.0 - fx) + at(x0 + 1, y0)[c] * fx;
                let bot = at(x0, y0 + 1)[c] * (1.0 - fx) + at(x0 + 1, y0 + 1)[c] * fx;
                top * (1.0 - fy) + bot * fy
            })
        };
        for (u, v) in [
            (0.0, 0.0),
            (0.01, 0.02),
            (0.5, 0.5),
            (0.99, 0.97),
            (0.3, 1.0),
            (0.77, 0.13),
        ] {
            let (a, b) = (sample(u, v), m.lookup_uv(u, v));
            for c in 0..3 {
                assert!((a[c] - b[c]).abs() < 1e-4, "({u},{v}): {a:?} vs {b:?}");
            }
        }
    }

    #[test]
    fn rotated_lookup_matches_the_rotated_map() {
        // Rotating by whole texels shifts the map exactly, so the two must agree exactly.
        let m = ramp(8);
        let shifted_texels: Vec<Rgb> = (0..16 * 8)
            .map(|i| {
                let (x, y) = (i % 16, i / 16);
                m.texels()[y * 16 + (x + 16 - 3) % 16]
            })
            .collect();
        let shifted = LightMap::new(16, 16, 8, shifted_texels);
        let yaw = 2.0 * PI * 3.0 / 16.0;
        for (u, v) in [(0.1, 0.2), (0.55, 0.5), (0.9, 0.93)] {
            let d = direction::uv_to_dir(u, v);
            let (a, b) = (m.lookup_rotated(d, yaw), shifted.lookup(d));
            for c in 0..3 {
                assert!((a[c] - b[c]).abs() < 1e-3, "{a:?} {b:?}");
            }
        }
    }
}
