//! Bright sources summed directly, so that a sun does not ring over the rest of the sky.
//!
//! A band-limited convolution rings around a point light with an amplitude of a small fraction
//! of its peak ([`crate::lobe::LobePlan::ringing`]). A 1e6 sun on a sky of 0.02 rings far
//! louder than the sky it sits on. So the few texels that hold enough of the map's energy for
//! their ringing to exceed the tolerance relative to the average sky are taken out of the map
//! before the spherical-harmonic analysis and added back exactly: their lobes are integrated
//! over each texel (sub-divided as in [`crate::reference`]) at every light-map texel centre.
//! Ordinary maps, whose brightest texel holds a tiny share of the energy, extract nothing and
//! pay nothing.

use rayon::prelude::*;

use crate::direction;
use crate::envmap::{EnvMap, Rgb, luminance};
use crate::lobe::LobePlan;
use crate::reference::lobe_width;

/// Kernel evaluations one lobe's direct sum may cost (about 0.05 s on two cores). A lobe for
/// which the bright texels would cost more (texels much larger than the lobe: tiny maps, very
/// narrow lobes) is left to the band-limited convolution of the whole map.
pub const DIRECT_BUDGET: usize = 50_000_000;

/// At most this many texels are summed directly (the brightest first).
pub const MAX_BRIGHT_TEXELS: usize = 64;

/// Texels to sum directly: `(x, y)` of each texel whose share of the map's energy is above
/// what the plans can band-limit within `tolerance`, brightest first.
pub fn select(map: &EnvMap, plans: &[LobePlan], tolerance: f64) -> Vec<(usize, usize)> {
    let (w, h) = (map.width(), map.height());
    let omega: Vec<f64> = (0..h)
        .map(|y| direction::row_solid_angle(y, w, h))
        .collect();
    let row_luminance: Vec<f64> = (0..h)
        .map(|y| map.row(y).iter().map(|c| luminance(*c)).sum())
        .collect();
    let total: f64 = row_luminance.iter().zip(&omega).map(|(l, o)| l * o).sum();
    if total <= 0.0 {
        return Vec::new();
    }
    // A texel of energy E lights its lobe's peak with about E / max(Omega, 2 pi / (n + 1))
    // (a point inside the lobe, or a patch wider than it); the band limit rings at r of that
    // peak. Texels whose ringing would exceed the tolerance relative to the average light,
    // total / (4 pi), in any lobe are summed directly. Per row, that is a luminance threshold.
    let sky = tolerance * total / (4.0 * std::f64::consts::PI);
    let mut bright: Vec<(f64, usize, usize)> = Vec::new();
    for (y, &omega) in omega.iter().enumerate() {
        let threshold = plans
            .iter()
            .map(|p| {
                let spread = omega.max(std::f64::consts::TAU / (f64::from(p.exponent) + 1.0));
                sky * spread / (p.ringing.max(1e-12) * omega)
            })
            .fold(f64::INFINITY, f64::min);
        for (x, c) in map.row(y).iter().enumerate() {
            let lum = luminance(*c);
            if lum > threshold {
                bright.push((lum * omega, x, y));
            }
        }
    }
    bright.sort_by(|a, b| b.0.total_cmp(&a.0));
    bright.truncate(MAX_BRIGHT_TEXELS);
    bright.into_iter().map(|(_, x, y)| (x, y)).collect()
}

/// Whether summing `count` texels of a map `map_height` tall directly for `plan` fits
/// [`DIRECT_BUDGET`].
pub fn affordable(plan: &LobePlan, map_height: usize, count: usize) -> bool {
    plan.width() * plan.height * subdivision(map_height, plan.exponent).pow(2) * count
        <= DIRECT_BUDGET
}

/// Sub-cells per texel side for a lobe: at most a quarter of the lobe's width (the midpoint
/// rule is then well within the tolerance; the reference uses a sixteenth).
fn subdivision(height: usize, exponent: u32) -> usize {
    let texel = std::f64::consts::PI / height as f64;
    ((4.0 * texel / lobe_width(exponent)).ceil() as usize).max(1)
}

/// A sub-cell: centre direction and exact solid angle.
type SubCell = ([f64; 3], f64);

/// Sub-cells of one texel: centre direction and exact solid angle.
fn sub_cells(x: usize, y: usize, w: usize, h: usize, exponent: u32) -> Vec<SubCell> {
    let s = subdivision(h, exponent);
    let (sw, sh) = (w * s, h * s);
    let mut cells = Vec::with_capacity(s * s);
    for sy in y * s..(y + 1) * s {
        let omega = direction::row_solid_angle(sy, sw, sh);
        for sx in x * s..(x + 1) * s {
            cells.push((direction::texel_dir(sx, sy, sw, sh), omega));
        }
    }
    cells
}

/// Adds the exact light of `texels` of `map`, for lobe `exponent`, to the light-map `out`
/// (`2 height x height`, values at texel centres).
pub fn add_direct(
    map: &EnvMap,
    texels: &[(usize, usize)],
    exponent: u32,
    height: usize,
    out: &mut [[f64; 3]],
) {
    let (w, h) = (map.width(), map.height());
    let norm = (f64::from(exponent) + 1.0) / std::f64::consts::TAU;
    let sources: Vec<(Rgb, Vec<SubCell>)> = texels
        .iter()
        .map(|&(x, y)| (map.texel(x, y), sub_cells(x, y, w, h, exponent)))
        .collect();
    let width = 2 * height;
    out.par_chunks_mut(width).enumerate().for_each(|(oy, row)| {
        for (ox, value) in row.iter_mut().enumerate() {
            let d = direction::texel_dir(ox, oy, width, height);
            for (radiance, cells) in &sources {
                let k: f64 = cells
                    .iter()
                    .map(|(u, omega)| {
                        let c = direction::dot(d, *u);
                        if c > 0.0 {
                            omega * c.powi(exponent as i32)
                        } else {
                            0.0
                        }
                    })
                    .sum::<f64>()
                    * norm;
                for c in 0..3 {
                    value[c] += k * f64::from(radiance[c]);
                }
            }
        }
    });
}
