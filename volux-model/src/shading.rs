//! Shading with preconvolved light maps (paper section 3.2): `D = L_1(n)` and
//! `S = sum_i w_i L_{n_i}(r)` with `r = d - 2 (d.n) n`, and where along a ray it is evaluated.
//!
//! [`Shading::Volume`] is the paper's volumetric relighting: every sample is shaded with its
//! own normal and specular weights, and `D` and `S` are accumulated like albedo.
//! [`Shading::Surface`] is the paper's "surface relighting" ablation (tables 1 and 2): the
//! normal and the specular weights are accumulated first, and the pixel is shaded once with
//! the normalised accumulated normal, as a renderer of surfaces would.

use burn::config::Config;
use burn::tensor::Tensor;

use crate::light_lookup::Lighting;
use crate::light_lookup::directions_to_uv;

/// Where the renderer evaluates the light maps.
#[derive(Config, Debug, Copy, PartialEq, Eq)]
pub enum Shading {
    /// Per sample, accumulated along the ray (the paper's method).
    Volume,
    /// Once per pixel, at the normalised accumulated normal with the accumulated specular
    /// weights (the paper's "surface relighting" ablation).
    Surface,
}

/// Below this squared length an accumulated normal shrinks towards zero instead of being
/// blown up to unit length: `n / sqrt(|n|^2 + SURFACE_NORMAL_EPS2)`. A pixel whose samples'
/// normals cancel, or that sees almost nothing, then gets a bounded gradient (at most
/// `1 / sqrt(eps) = 1000` times its opacity); a normal of length 0.01 is still made 0.995
/// long.
pub const SURFACE_NORMAL_EPS2: f64 = 1e-6;

/// `n / sqrt(|n|^2 + SURFACE_NORMAL_EPS2)` over the last axis of `[.., .., 3]`.
pub fn normalize_accumulated(n: Tensor<3>) -> Tensor<3> {
    let norm = n
        .clone()
        .powi_scalar(2)
        .sum_dim(2)
        .add_scalar(SURFACE_NORMAL_EPS2)
        .sqrt();
    n / norm
}

/// Diffuse `L_1(n)` and specular `sum_i omega_i L_{n_i}(r)` at points `[batch, points, ..]`:
/// normals `n` and view directions `dirs` (`[batch, points, 3]`, `dirs` unit), specular
/// weights `omega` (`[batch, points, maps]`). Returns `(D, S)`, `[batch, points, 3]` each.
pub fn shade(
    lighting: &Lighting,
    n: Tensor<3>,
    dirs: Tensor<3>,
    omega: Tensor<3>,
) -> (Tensor<3>, Tensor<3>) {
    let reflected = dirs.clone() - n.clone() * (dirs * n.clone()).sum_dim(2).mul_scalar(2.0);
    let yaw = lighting.yaw.clone();
    let diffuse = lighting.maps[0].lookup(n, yaw.clone());
    // One direction for every specular map: convert it to (u, v) once.
    let (u, v) = directions_to_uv(reflected, yaw);
    let specular = lighting
        .maps
        .iter()
        .enumerate()
        .map(|(i, map)| map.lookup_uv(u.clone(), v.clone()) * omega.clone().narrow(2, i, 1))
        .reduce(|a, b| a + b)
        .expect("at least one map");
    (diffuse, specular)
}

#[cfg(test)]
mod tests {
    use burn::tensor::{Device, Distribution};
    use volux_envmap::LightMap;

    use super::*;
    use crate::analytic::SoftSphere;
    use crate::backend::to_f32_vec;
    use crate::neiif::LatentField;
    use crate::neiif::NeiifConfig;
    use crate::pose::Pose;
    use crate::ray_sampling::{camera_ray_batch, camera_rays};
    use crate::test_support::{Scaled, lighting, wave_light_maps as light_maps};
    use crate::volume_rendering::{RenderOutput, RenderWants, RendererConfig, render};

    fn sphere() -> SoftSphere {
        SoftSphere {
            radius: 0.3,
            softness: 0.02,
            peak: 40.0,
            albedo: [0.8, 0.5, 0.3],
            specular_weights: vec![0.1, 0.4, 0.2, 0.05],
        }
    }

    const POSES: [Pose; 2] = [Pose::new(0.4, -0.2), Pose::new(-0.3, 0.1)];
    const YAWS: [f32; 2] = [-1.2, 0.5];
    const SIDE: usize = 8;

    fn render_sphere(shading: Shading, maps: &[Vec<LightMap>]) -> RenderOutput {
        let device = Device::flex();
        let cfg = RendererConfig::new()
            .with_stratified(32)
            .with_importance(32)
            .with_shading(shading);
        let light = lighting(maps, &YAWS, &device);
        let (o, d) = camera_ray_batch(&cfg.camera, &POSES, SIDE, SIDE, &device);
        render(&cfg, &sphere(), o, d, Some(&light), RenderWants::ALL, false)
    }

    /// The plain reference: at each pixel, the normalised accumulated normal `n`, then
    /// `D = a L_1(n)` and `S = sum_i (a omega_i) L_i(reflect(d, n))` with the CPU look-up
    /// (`a` the opacity; the sphere's specular weights are constant, so they accumulate to
    /// `a omega_i`).
    #[test]
    fn surface_shading_is_the_light_maps_at_the_normalised_accumulated_normal() {
        let maps = [light_maps(3, 1.0), light_maps(4, 2.0)];
        let out = render_sphere(Shading::Surface, &maps);
        let opacity = to_f32_vec(out.opacity);
        let normals = to_f32_vec(out.normals.unwrap());
        let diffuse = to_f32_vec(out.diffuse.unwrap());
        let specular = to_f32_vec(out.specular.unwrap());
        let camera = RendererConfig::new().camera;
        let omega = sphere().specular_weights;
        let (mut edge, mut covered) = (0, 0);
        for (e, &pose) in POSES.iter().enumerate() {
            let (_, dirs) = camera_rays(&camera, pose, SIDE, SIDE);
            let light_yaw = f64::from(YAWS[e]);
            for (i, d) in dirs.iter().enumerate() {
                let p = e * SIDE * SIDE + i;
                let a = f64::from(opacity[p]);
                let acc: [f64; 3] = std::array::from_fn(|c| f64::from(normals[3 * p + c]));
                let norm = (acc.iter().map(|v| v * v).sum::<f64>() + SURFACE_NORMAL_EPS2).sqrt();
                let n = acc.map(|v| v / norm);
                let dn: f64 = (0..3).map(|c| d[c] * n[c]).sum();
                let r: [f64; 3] = std::array::from_fn(|c| d[c] - 2.0 * dn * n[c]);
                let l1 = maps[e][0].lookup_rotated(n, light_yaw);
                let want_d: [f64; 3] = std::array::from_fn(|c| a * f64::from(l1[c]));
                let want_s: [f64; 3] = std::array::from_fn(|c| {
                    maps[e]
                        .iter()
                        .zip(&omega)
                        .map(|(m, w)| {
                            a * f64::from(*w) * f64::from(m.lookup_rotated(r, light_yaw)[c])
                        })
                        .sum()
                });
                for c in 0..3 {
                    for (what, got, want) in [
                        ("D", diffuse[3 * p + c], want_d[c]),
                        ("S", specular[3 * p + c], want_s[c]),
                    ] {
                        let got = f64::from(got);
                        assert!(
                            (got - want).abs() <= 1e-4 * (1.0 + want.abs()),
                            "element {e} pixel {i} {what}[{c}]: {got} vs {want} (opacity {a})"
                        );
                    }
                }
                edge += usize::from((0.05..0.95).contains(&a));
                covered += usize::from(a > 0.95);
            }
        }
        assert!(
            edge > 2 && covered > 4,
            "{edge} edge, {covered} covered pixels"
        );
    }

    /// Where every sample of a ray has one normal (the accumulated normal is as long as the
    /// opacity: the ray meets the sphere head-on) the two modes agree; where the normal turns
    /// along the ray (grazing rays, the silhouette: the accumulated normal is shorter than the
    /// opacity) they do not. On this 8x8 image: under 6e-4 apart head-on, up to 0.2 where the
    /// accumulated normal is 2.5% short.
    #[test]
    fn surface_and_volume_shading_differ_only_where_the_normal_turns_along_the_ray() {
        let maps = [light_maps(5, 1.0), light_maps(6, 1.0)];
        let surface = render_sphere(Shading::Surface, &maps);
        let volume = render_sphere(Shading::Volume, &maps);
        // Albedo, normals, opacity and depth do not depend on the mode.
        for (a, b) in [
            (
                surface.albedo.clone().unwrap(),
                volume.albedo.clone().unwrap(),
            ),
            (
                surface.normals.clone().unwrap(),
                volume.normals.clone().unwrap(),
            ),
        ] {
            assert_eq!(to_f32_vec(a), to_f32_vec(b));
        }
        assert_eq!(
            to_f32_vec(surface.opacity.clone()),
            to_f32_vec(volume.opacity.clone())
        );
        let opacity = to_f32_vec(volume.opacity);
        let normals = to_f32_vec(volume.normals.unwrap());
        let (ds, dv) = (
            to_f32_vec(surface.diffuse.unwrap()),
            to_f32_vec(volume.diffuse.unwrap()),
        );
        let (mut head_on, mut turning, mut largest_turning_difference) = (0, 0, 0.0f32);
        for (p, a) in opacity.iter().enumerate() {
            if *a < 0.05 {
                continue;
            }
            let length = (0..3)
                .map(|c| normals[3 * p + c].powi(2))
                .sum::<f32>()
                .sqrt();
            let coherence = length / a;
            let diff = (0..3)
                .map(|c| (ds[3 * p + c] - dv[3 * p + c]).abs() / (1e-3 + dv[3 * p + c].abs()))
                .fold(0.0f32, f32::max);
            if coherence > 0.998 {
                head_on += 1;
                assert!(diff < 2e-3, "pixel {p}: relative difference {diff} head-on");
            } else if coherence < 0.98 {
                turning += 1;
                largest_turning_difference = largest_turning_difference.max(diff);
            }
        }
        assert!(
            head_on >= 4 && turning >= 4,
            "{head_on} head-on, {turning} turning"
        );
        assert!(
            largest_turning_difference > 5e-2,
            "the modes agree where the normal turns ({largest_turning_difference})"
        );
    }

    /// Empty space (no accumulated normal at all), ordinary and very dense fields give finite
    /// shading and finite gradients in surface mode.
    #[test]
    fn surface_shading_is_finite_with_finite_gradients_from_empty_to_dense() {
        let device = Device::flex().autodiff();
        let net = NeiifConfig::new()
            .with_w_dim(8)
            .with_width(16)
            .with_head_width(8)
            .init(&device);
        let maps = light_maps(2, 1e5);
        let light = lighting(&[maps.clone(), maps], &[0.0, 3.0], &device);
        let cfg = RendererConfig::new()
            .with_stratified(12)
            .with_importance(12)
            .with_shading(Shading::Surface);
        for scale in [0.0, 1.0, 1e4] {
            let w =
                Tensor::<2>::random([2, 8], Distribution::Normal(0.0, 1.0), &device).require_grad();
            let field = LatentField {
                field: &net,
                w: w.clone(),
            };
            let (o, d) = camera_ray_batch(
                &cfg.camera,
                &[Pose::new(0.0, 0.0), Pose::new(0.5, 0.2)],
                4,
                4,
                &device,
            );
            let wants = RenderWants {
                albedo: false,
                normals: false,
                shading: true,
                features: false,
                depth: false,
            };
            let out = render(
                &cfg,
                &Scaled(&field, scale),
                o,
                d,
                Some(&light),
                wants,
                true,
            );
            assert!(out.normals.is_none(), "normals were not asked for");
            let (diffuse, specular) = (out.diffuse.unwrap(), out.specular.unwrap());
            for v in [to_f32_vec(diffuse.clone()), to_f32_vec(specular.clone())] {
                assert!(v.iter().all(|x| x.is_finite()), "density x{scale}: {v:?}");
                if scale == 0.0 {
                    assert!(v.iter().all(|x| *x == 0.0), "empty space is unlit");
                }
            }
            let grads = (diffuse.sum() + specular.sum()).backward();
            for g in [
                w.grad(&grads).map(to_f32_vec),
                net.layers[0].weight.val().grad(&grads).map(to_f32_vec),
                net.head_out.weight.val().grad(&grads).map(to_f32_vec),
            ]
            .into_iter()
            .flatten()
            {
                assert!(
                    g.iter().all(|x| x.is_finite()),
                    "density x{scale}: non-finite gradient"
                );
            }
        }
    }
}
