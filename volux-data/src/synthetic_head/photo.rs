//! The synthetic "photo": the same head and light maps as the pseudo ground truth, plus what
//! the Phong model of the generator lacks, so that the photorealism discriminator has
//! something to learn beyond it (paper appendix A):
//!
//! - ambient occlusion from the signed distance (creases, eye sockets, under the nose);
//! - a soft shadow towards the environment's dominant light, weighted by how directional the
//!   environment is (a sun casts shadows, an overcast sky barely does);
//! - a subsurface-like softening of skin: the diffuse term blends, per colour channel, towards
//!   the light map at a smoothed normal (the iso-surface a little outside), red most, and
//!   shadows keep a little red, as light scattered under the skin does.
//!
//! Specular light is occluded like diffuse light. Everything is tone-mapped with the
//! generator's curve and composited over the background per ray, so silhouettes are
//! anti-aliased when the render is supersampled.

use volux_envmap::direction::{self, Dir};
use volux_envmap::envmap::luminance;
use volux_envmap::io::tonemap_pixel;
use volux_envmap::{LightMap, Rgb};

use super::head::SyntheticHead;
use super::render::{HeadRender, SurfaceHit};
use super::{SyntheticError, check_light_maps};

/// How far each channel's diffuse light follows the smoothed normal on skin.
const SOFTENING: [f64; 3] = [0.55, 0.3, 0.15];
/// The fraction of each channel's shadow that scattered light fills in on skin.
const SHADOW_FILL: [f64; 3] = [0.3, 0.1, 0.05];

/// The light an environment casts, as the photo's effects need it.
#[derive(Clone, Debug)]
pub struct PhotoLighting<'a> {
    lights: Vec<&'a LightMap>,
    yaw: f64,
    /// Unit world direction of the brightest part of the environment (after rotation).
    key: Dir,
    /// 1 - darkest / brightest diffuse luminance: 0 for a uniform environment, near 1 for a
    /// single sun.
    directionality: f64,
}

impl<'a> PhotoLighting<'a> {
    /// `lights`: `L_1, L_16, L_32, L_64` of an environment rotated by `yaw` (checked by
    /// [`super::check_light_maps`]).
    pub fn new(lights: &[&'a LightMap], yaw: f64) -> Result<PhotoLighting<'a>, SyntheticError> {
        check_light_maps(lights)?;
        let sharpest = lights[lights.len() - 1];
        let (w, h) = (sharpest.width(), sharpest.height());
        let brightest = (0..w * h)
            .max_by(|&a, &b| {
                let la = luminance(sharpest.texels()[a]);
                let lb = luminance(sharpest.texels()[b]);
                la.total_cmp(&lb)
            })
            .unwrap_or(0);
        let key = direction::rotate_yaw(
            direction::texel_dir(brightest % w, brightest / w, w, h),
            yaw,
        );
        let diffuse = lights[0];
        let (lo, hi) = diffuse
            .texels()
            .iter()
            .fold((f64::MAX, 0.0f64), |(lo, hi), &t| {
                let l = luminance(t);
                (lo.min(l), hi.max(l))
            });
        let directionality = if hi > 0.0 {
            (1.0 - lo / hi).clamp(0.0, 1.0)
        } else {
            0.0
        };
        Ok(PhotoLighting {
            lights: lights.to_vec(),
            yaw,
            key,
            directionality,
        })
    }

    pub fn key_direction(&self) -> Dir {
        self.key
    }

    pub fn directionality(&self) -> f64 {
        self.directionality
    }
}

/// Ambient occlusion at `p` with normal `n`: 1 in the open, less in creases (the distance
/// field sampled along the normal, as in Quilez's distance-field AO).
pub fn ambient_occlusion(head: &SyntheticHead, p: [f64; 3], n: [f64; 3]) -> f64 {
    let (mut occlusion, mut weight) = (0.0, 1.0);
    for i in 1..=5 {
        let h = 0.01 + 0.025 * i as f64;
        let d = head.distance(std::array::from_fn(|k| p[k] + h * n[k]));
        occlusion += (h - d).max(0.0) * weight;
        weight *= 0.8;
    }
    (1.0 - 3.0 * occlusion).clamp(0.0, 1.0)
}

/// Soft visibility of direction `l` from `p` in `[0, 1]`: marches the distance field towards
/// the light and keeps the narrowest cone that passes (penumbra width set by `k`).
pub fn soft_shadow(head: &SyntheticHead, p: [f64; 3], l: Dir, k: f64) -> f64 {
    let mut visibility: f64 = 1.0;
    let mut t = 0.01;
    for _ in 0..64 {
        let d = head.distance(std::array::from_fn(|c| p[c] + t * l[c]));
        visibility = visibility.min(k * d / t);
        if visibility < 1e-3 || t > 1.5 {
            break;
        }
        t += d.clamp(0.005, 0.1);
    }
    visibility.clamp(0.0, 1.0)
}

/// Linear radiance of one surface point in the photo.
pub fn shade_hit(head: &SyntheticHead, hit: &SurfaceHit, light: &PhotoLighting<'_>) -> Rgb {
    let n = hit.normal;
    let lifted = std::array::from_fn(|k| hit.point[k] + 2e-3 * n[k]);
    let ao = ambient_occlusion(head, hit.point, n);
    let visible = if light.directionality > 0.0 {
        soft_shadow(head, lifted, light.key, 8.0)
    } else {
        1.0
    };
    let shadow = 1.0 - light.directionality * (1.0 - visible);
    let diffuse_map = light.lights[0];
    let sharp = diffuse_map.lookup_rotated(n, light.yaw);
    let soft = diffuse_map.lookup_rotated(hit.soft_normal, light.yaw);
    let r = direction::reflect(hit.ray, n);
    let mut specular = [0.0f64; 3];
    for (map, w) in light.lights.iter().zip(hit.material.specular) {
        let l = map.lookup_rotated(r, light.yaw);
        for c in 0..3 {
            specular[c] += w * f64::from(l[c]);
        }
    }
    let skin = hit.material.skin;
    std::array::from_fn(|c| {
        let blend = skin * SOFTENING[c];
        let d = f64::from(sharp[c]) * (1.0 - blend) + f64::from(soft[c]) * blend;
        let shadow_c = 1.0 - (1.0 - shadow) * (1.0 - skin * SHADOW_FILL[c]);
        let occluded = ao * shadow_c;
        (hit.material.albedo[c] * d * occluded + specular[c] * occluded) as f32
    })
}

/// The photo of a render under `light`, sRGB in `[0, 1]`, over `background`: each covered ray
/// shaded and tone-mapped, uncovered rays showing the background, averaged per pixel.
pub fn photo(
    head: &SyntheticHead,
    render: &HeadRender,
    light: &PhotoLighting<'_>,
    background: Rgb,
) -> Vec<Rgb> {
    use rayon::prelude::*;
    let rays = render.rays_per_pixel as f32;
    render
        .hits
        .par_iter()
        .map(|found| {
            let mut sum = [0.0f32; 3];
            for hit in found {
                let c = tonemap_pixel(shade_hit(head, hit, light), 1.0);
                for k in 0..3 {
                    sum[k] += c[k];
                }
            }
            let missed = rays - found.len() as f32;
            std::array::from_fn(|k| (sum[k] + missed * background[k]) / rays)
        })
        .collect()
}
