//! The volume renderer (paper section 3.2, eq. 2): ties ray sampling, a field, compositing and
//! the light-map look-up together. Along each ray it accumulates albedo `A`, normal `N`, diffuse
//! `D = L_1(n)`, specular `S = sum_i omega_i L_{n_i}(r)` (with `r = d - 2 (d.n) n`, each
//! evaluated per sample, which is the paper's volumetric relighting), features `F`, depth and
//! opacity. [`Shading::Surface`] shades once per pixel instead, at the accumulated normal (the
//! paper's ablation; [`crate::shading`]).
//!
//! Sampling is EG3D's by default: stratified samples, then importance samples drawn from the
//! stratified pass's weights; both passes are evaluated by the field and composited together:
//! the quadrature runs over their depths and densities in depth order, and each sample's mass
//! then weighs its own values where the passes left them (no gathering of every channel into
//! depth order). With `proposal > 0` the importance samples are placed by density-only
//! passes instead ([`crate::proposal`]), whose samples join the compositing weights and lend
//! them to the nearest full sample's values. What is not asked for is not computed: no light-map look-ups without shading, no
//! density-gradient sweep without normals or shading, no field head without albedo, features or
//! shading. Like EG3D's renderer this file knows the field only through [`Field`].

use burn::config::Config;
use burn::tensor::{IndexingUpdateOp, Tensor};

use crate::field::{Field, FieldWants};
use crate::light_lookup::Lighting;
use crate::proposal;
use crate::ray_marching;
use crate::ray_sampling::{CameraConfig, importance_samples, segment_lengths, stratified_samples};
pub use crate::shading::Shading;
use crate::shading::{normalize_accumulated, shade};

/// Configuration of the renderer.
#[derive(Config, Debug)]
pub struct RendererConfig {
    /// Camera and ray bounds.
    #[config(default = "CameraConfig::new()")]
    pub camera: CameraConfig,
    /// Stratified samples per ray.
    #[config(default = 24)]
    pub stratified: usize,
    /// Importance samples per ray (0: none, and no second pass).
    #[config(default = 24)]
    pub importance: usize,
    /// Density-only samples per ray that place the importance samples
    /// ([`crate::proposal`]); their densities join the compositing weights, their weights go
    /// to the nearest full sample's values. 0: EG3D's scheme, the importance samples are
    /// drawn from the stratified samples' weights. Needs `importance > 0`.
    #[config(default = 0)]
    pub proposal: usize,
    /// Density-only samples drawn from the proposal samples' weights and merged with them
    /// before the importance samples are drawn (a second level that narrows in on surfaces).
    /// Needs `proposal > 0`.
    #[config(default = 0)]
    pub refine: usize,
    /// Quadrature of the compositing integral: `true` is EG3D's midpoint rule (each segment
    /// between two samples carries the mean of their values), `false` NeRF's left rule (each
    /// sample's values hold up to the next sample, the last up to `far`). The midpoint rule is
    /// second order on the uneven spacing importance sampling makes (docs/model.md).
    #[config(default = true)]
    pub midpoint: bool,
    /// Where `D` and `S` are evaluated: per sample and accumulated (the paper's method), or once
    /// per pixel at the accumulated normal (the paper's "surface relighting" ablation).
    #[config(default = "Shading::Volume")]
    pub shading: Shading,
}

/// A sample layout the renderer cannot use.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SamplesError {
    #[error("no samples to composite: stratified and importance are both 0")]
    Nothing,
    #[error("importance = {importance} without stratified or proposal samples to draw them from")]
    ImportanceUnplaced { importance: usize },
    #[error("proposal = {proposal} places importance samples, but importance = 0")]
    ProposalUnused { proposal: usize },
    #[error("refine = {refine} needs proposal samples to refine (proposal = 0)")]
    RefineWithoutProposal { refine: usize },
}

impl RendererConfig {
    /// Checks that the sample counts make a renderer: something to composite, and every
    /// pass that places samples used by one that is composited.
    pub fn check_samples(&self) -> Result<(), SamplesError> {
        if self.stratified == 0 && self.importance == 0 {
            return Err(SamplesError::Nothing);
        }
        if self.importance > 0 && self.stratified == 0 && self.proposal == 0 {
            return Err(SamplesError::ImportanceUnplaced {
                importance: self.importance,
            });
        }
        if self.proposal > 0 && self.importance == 0 {
            return Err(SamplesError::ProposalUnused {
                proposal: self.proposal,
            });
        }
        if self.refine > 0 && self.proposal == 0 {
            return Err(SamplesError::RefineWithoutProposal {
                refine: self.refine,
            });
        }
        Ok(())
    }

    /// Density-only field queries per ray (placing samples only).
    pub fn density_only_samples(&self) -> usize {
        self.proposal + self.refine
    }
}

/// Which accumulated maps a render needs. Opacity always comes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RenderWants {
    pub albedo: bool,
    pub normals: bool,
    /// Diffuse and specular (needs [`Lighting`]).
    pub shading: bool,
    pub features: bool,
    pub depth: bool,
}

impl RenderWants {
    /// Everything.
    pub const ALL: Self = Self {
        albedo: true,
        normals: true,
        shading: true,
        features: true,
        depth: true,
    };

    fn field(self) -> FieldWants {
        FieldWants {
            normals: self.normals || self.shading,
            appearance: self.albedo || self.features || self.shading,
        }
    }
}

/// Accumulated maps of `[batch, rays]`, before compositing over a background (`N`, `D`, `S`,
/// `F` are zero where nothing is, `A` is weighted by opacity).
#[derive(Clone, Debug)]
pub struct RenderOutput {
    /// `[batch, rays]`, the sum of the weights, in [0, 1].
    pub opacity: Tensor<2>,
    /// `[batch, rays]`: expected depth, with the transparent remainder at `far`.
    pub depth: Option<Tensor<2>>,
    /// `[batch, rays, 3]`.
    pub albedo: Option<Tensor<3>>,
    /// `[batch, rays, 3]`, world space.
    pub normals: Option<Tensor<3>>,
    /// `[batch, rays, 3]`, linear HDR.
    pub diffuse: Option<Tensor<3>>,
    /// `[batch, rays, 3]`, linear HDR.
    pub specular: Option<Tensor<3>>,
    /// `[batch, rays, channels]`.
    pub features: Option<Tensor<3>>,
}

/// Per-sample quantities in the `[batch * rays, samples, channels]` layout.
struct Samples {
    t: Tensor<2>,
    sigma: Tensor<2>,
    normals: Option<Tensor<3>>,
    albedo: Option<Tensor<3>>,
    specular_weights: Option<Tensor<3>>,
    features: Option<Tensor<3>>,
}

fn per_ray(x: Tensor<3>, rays: usize, samples: usize) -> Tensor<3> {
    let [b, _, c] = x.dims();
    x.reshape([b * rays, samples, c])
}

/// Evaluates the field at depths `t: [batch * rays, samples]` along the rays.
fn evaluate(
    field: &impl Field,
    origins: &Tensor<3>,
    dirs: &Tensor<3>,
    t: Tensor<2>,
    wants: FieldWants,
) -> Samples {
    let [b, r, _] = origins.dims();
    let s = t.dims()[1];
    let points = origins.clone().reshape([b, r, 1, 3])
        + dirs.clone().reshape([b, r, 1, 3]) * t.clone().reshape([b, r, s, 1]);
    let out = field.query(points.reshape([b, r * s, 3]), wants);
    Samples {
        t,
        sigma: out.sigma.reshape([b * r, s]),
        normals: out.normals.map(|x| per_ray(x, r, s)),
        albedo: out.albedo.map(|x| per_ray(x, r, s)),
        specular_weights: out.specular_weights.map(|x| per_ray(x, r, s)),
        features: out.features.map(|x| per_ray(x, r, s)),
    }
}

fn concat3(a: Option<Tensor<3>>, b: Option<Tensor<3>>) -> Option<Tensor<3>> {
    Some(Tensor::cat(vec![a?, b?], 1))
}

/// Both passes' samples side by side, the stratified ones first. Compositing is a sum over
/// samples, so only the quadrature needs them in depth order: [`render`] sorts the depths and
/// densities (one channel each) and sends each sample's mass back to its place here, instead
/// of gathering every channel of every sample into depth order (and scattering them back in
/// the backward pass).
fn concat(a: Samples, b: Samples) -> Samples {
    Samples {
        t: Tensor::cat(vec![a.t, b.t], 1),
        sigma: Tensor::cat(vec![a.sigma, b.sigma], 1),
        normals: concat3(a.normals, b.normals),
        albedo: concat3(a.albedo, b.albedo),
        specular_weights: concat3(a.specular_weights, b.specular_weights),
        features: concat3(a.features, b.features),
    }
}

/// Renders rays `origins, dirs: [batch, rays, 3]` (unit directions) through `field`. `jitter`
/// randomises sample positions (training); without it, sampling is deterministic.
pub fn render(
    config: &RendererConfig,
    field: &impl Field,
    origins: Tensor<3>,
    dirs: Tensor<3>,
    lighting: Option<&Lighting>,
    wants: RenderWants,
    jitter: bool,
) -> RenderOutput {
    let [b, r, _] = origins.dims();
    let device = origins.device();
    assert!(
        !wants.shading || lighting.is_some(),
        "shading needs lighting"
    );
    if let Err(e) = config.check_samples() {
        panic!("{e}");
    }
    let field_wants = wants.field();
    let coarse = (config.stratified > 0).then(|| {
        let (t, _) = stratified_samples(&config.camera, b * r, config.stratified, jitter, &device);
        evaluate(field, &origins, &dirs, t, field_wants)
    });
    let mut proposed = None;
    let fine = (config.importance > 0).then(|| {
        let t = match &coarse {
            Some(coarse) if config.proposal == 0 => {
                let w = ray_marching::weights(
                    coarse.sigma.clone(),
                    segment_lengths(coarse.t.clone(), config.camera.far),
                );
                importance_samples(
                    &config.camera,
                    coarse.t.clone(),
                    w,
                    config.importance,
                    jitter,
                )
            }
            _ => {
                let p = proposal::place(config, field, &origins, &dirs, jitter);
                let t = p.importance.clone();
                proposed = Some(p);
                t
            }
        };
        evaluate(field, &origins, &dirs, t, field_wants)
    });
    let samples = match (coarse, fine) {
        (Some(coarse), Some(fine)) => concat(coarse, fine),
        (Some(only), None) | (None, Some(only)) => only,
        (None, None) => unreachable!("check_samples asks for samples to composite"),
    };
    let s = samples.t.dims()[1];
    // The quadrature runs over the composited samples, joined by the density-only ones when a
    // proposal placed them, in depth order; `owner` is, for each entry in that order, the
    // composited sample (its index in `samples`) whose values it carries: itself, or for a
    // density-only entry the nearest composited sample.
    let (t_all, sigma_all, owner) = match proposed {
        Some(p) => {
            let (t, order) = Tensor::cat(vec![samples.t.clone(), p.t], 1).sort_with_indices(1);
            let sigma = Tensor::cat(vec![samples.sigma.clone(), p.sigma], 1).gather(1, order);
            let owner = proposal::nearest(t.clone(), samples.t.clone());
            (t, sigma, owner)
        }
        None => {
            let (t, order) = samples.t.clone().sort_with_indices(1);
            let sigma = samples.sigma.clone().gather(1, order.clone());
            (t, sigma, order)
        }
    };
    let n = t_all.dims()[1];
    // Midpoint rule: segment i runs from entry i to entry i + 1 and carries the mean of their
    // values, so each entry carries half of the weight of each segment it bounds. Left rule:
    // segment i runs from entry i to the next (the last one to `far`) and carries entry i's
    // values. Either way the accumulation is `sum_i mass_i value_i` over the entries.
    let (weights, mass) = if config.midpoint && n > 1 {
        let delta = t_all.clone().narrow(1, 1, n - 1) - t_all.clone().narrow(1, 0, n - 1);
        let sigma =
            (sigma_all.clone().narrow(1, 0, n - 1) + sigma_all.narrow(1, 1, n - 1)).mul_scalar(0.5);
        let w = ray_marching::weights(sigma, delta);
        let zero = Tensor::<2>::zeros([b * r, 1], &device);
        let mass = (Tensor::cat(vec![zero.clone(), w.clone()], 1)
            + Tensor::cat(vec![w.clone(), zero], 1))
        .mul_scalar(0.5);
        (w, mass)
    } else {
        let w = ray_marching::weights(sigma_all, segment_lengths(t_all.clone(), config.camera.far));
        (w.clone(), w)
    };
    // Each composited sample's share: its own mass and that of the density-only entries it
    // owns, in the samples' own order.
    let share = Tensor::<2>::zeros([b * r, s], &device).scatter(
        1,
        owner,
        mass.clone(),
        IndexingUpdateOp::Add,
    );
    let to_image = |x: Tensor<2>| -> Tensor<3> {
        let c = x.dims()[1];
        x.reshape([b, r, c])
    };
    let acc = |x: Tensor<3>| to_image(ray_marching::accumulate(share.clone(), x));
    let opacity = ray_marching::opacity(weights).reshape([b, r]);
    let depth = wants.depth.then(|| {
        let expected = ray_marching::accumulate(mass.clone(), t_all.clone().reshape([b * r, n, 1]))
            .reshape([b, r]);
        expected
            + opacity
                .clone()
                .neg()
                .add_scalar(1.0)
                .mul_scalar(config.camera.far)
    });
    let surface = wants.shading && config.shading == Shading::Surface;
    let normals =
        (wants.normals || surface).then(|| acc(samples.normals.clone().expect("normals queried")));
    let (mut diffuse, mut specular) = (None, None);
    if wants.shading {
        let lighting = lighting.expect("checked above");
        let n = samples.normals.clone().expect("shading queries normals");
        let omega = samples
            .specular_weights
            .clone()
            .expect("shading queries specular weights");
        let k = lighting.maps.len();
        assert_eq!(omega.dims()[2], k, "one specular weight per light map");
        let (d, sp) = match config.shading {
            Shading::Volume => {
                let d = dirs
                    .clone()
                    .reshape([b, r, 1, 3])
                    .expand([b, r, s, 3])
                    .reshape([b, r * s, 3]);
                let (d, sp) = shade(
                    lighting,
                    n.reshape([b, r * s, 3]),
                    d,
                    omega.reshape([b, r * s, k]),
                );
                (
                    acc(d.reshape([b * r, s, 3])),
                    acc(sp.reshape([b * r, s, 3])),
                )
            }
            Shading::Surface => {
                // The accumulated specular weights carry the opacity once, like the albedo;
                // the diffuse shading gets it explicitly.
                let n = normalize_accumulated(normals.clone().expect("accumulated above"));
                let (d, sp) = shade(lighting, n, dirs.clone(), acc(omega));
                (d * opacity.clone().reshape([b, r, 1]), sp)
            }
        };
        diffuse = Some(d);
        specular = Some(sp);
    }
    RenderOutput {
        opacity,
        depth,
        albedo: wants
            .albedo
            .then(|| acc(samples.albedo.expect("albedo queried"))),
        normals: normals.filter(|_| wants.normals),
        diffuse,
        specular,
        features: wants
            .features
            .then(|| acc(samples.features.expect("features queried"))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analytic::{RayReference, SoftSphere};
    use crate::backend::to_f32_vec;
    use crate::neiif::{LatentField, NeiifConfig};
    use crate::pose::Pose;
    use crate::ray_sampling::{camera_ray_batch, camera_rays};
    use crate::test_support::{Scaled, lighting, wave_light_maps as light_maps};
    use burn::tensor::{Device, Distribution};
    use volux_envmap::LightMap;

    fn sphere() -> SoftSphere {
        SoftSphere {
            radius: 0.3,
            softness: 0.01,
            peak: 60.0,
            albedo: [0.8, 0.5, 0.3],
            specular_weights: vec![0.1, 0.4, 0.2, 0.05],
        }
    }

    fn close3(got: &[f32], want: [f64; 3], tol: f64, what: &str) {
        for c in 0..3 {
            let g = f64::from(got[c]);
            assert!(
                (g - want[c]).abs() <= tol * (1.0 + want[c].abs()),
                "{what}[{c}]: {g} vs {}",
                want[c]
            );
        }
    }

    #[test]
    fn soft_sphere_matches_the_analytic_values_at_the_image_centre() {
        let device = Device::flex();
        let cfg = RendererConfig::new()
            .with_stratified(64)
            .with_importance(64);
        let maps = light_maps(5, 1.0);
        let light = lighting(std::slice::from_ref(&maps), &[0.7], &device);
        let (o, d) = camera_ray_batch(&cfg.camera, &[Pose::new(0.0, 0.0)], 5, 5, &device);
        let out = render(&cfg, &sphere(), o, d, Some(&light), RenderWants::ALL, false);
        let at = |x: Option<Tensor<3>>| to_f32_vec(x.unwrap())[12 * 3..13 * 3].to_vec();
        let opacity = to_f32_vec(out.opacity.clone())[12];
        assert!(opacity > 0.999, "opacity {opacity}");
        // The surface (density at half its peak) is at t = 2.7 - 0.3; the weights' mean sits
        // a fraction of the e-folding length 1 / 30 in front of the full density.
        let depth = to_f32_vec(out.depth.clone().unwrap())[12];
        assert!((depth - 2.4).abs() < 0.03, "depth {depth}");
        let n = at(out.normals.clone());
        close3(&n, [0.0, 0.0, 1.0], 1e-3, "normal");
        // D = L_1(n) with n = +z; S at the mirror direction of -z about +z, also +z.
        let up = [0.0, 0.0, 1.0];
        let l1 = maps[0].lookup_rotated(up, 0.7).map(f64::from);
        close3(&at(out.diffuse.clone()), l1, 2e-3, "diffuse");
        let spec: [f64; 3] = std::array::from_fn(|c| {
            maps.iter()
                .zip(&sphere().specular_weights)
                .map(|(m, w)| f64::from(*w) * f64::from(m.lookup_rotated(up, 0.7)[c]))
                .sum()
        });
        close3(&at(out.specular.clone()), spec, 2e-3, "specular");
        close3(&at(out.albedo), [0.8, 0.5, 0.3], 1e-3, "albedo");
        // Features are the points: the expected surface point is (0, 0, 2.7 - depth).
        let f = at(out.features);
        close3(
            &f,
            [0.0, 0.0, 2.7 - f64::from(depth)],
            2e-3,
            "feature (point)",
        );
    }

    /// Every pixel of an image of the sphere, against the f64 quadrature with 20,000 steps.
    #[test]
    fn soft_sphere_image_matches_the_f64_reference() {
        let device = Device::flex();
        let cfg = RendererConfig::new()
            .with_stratified(64)
            .with_importance(64);
        let maps = light_maps(9, 1.0);
        let refs: Vec<&LightMap> = maps.iter().collect();
        let light = lighting(std::slice::from_ref(&maps), &[-1.2], &device);
        let pose = Pose::new(0.4, -0.2);
        let (w, h) = (8, 8);
        let (o, d) = camera_ray_batch(&cfg.camera, &[pose], w, h, &device);
        let out = render(&cfg, &sphere(), o, d, Some(&light), RenderWants::ALL, false);
        let (origins, dirs) = camera_rays(&cfg.camera, pose, w, h);
        let opacity = to_f32_vec(out.opacity);
        let depth = to_f32_vec(out.depth.unwrap());
        let maps3 = [
            to_f32_vec(out.albedo.unwrap()),
            to_f32_vec(out.normals.unwrap()),
            to_f32_vec(out.diffuse.unwrap()),
            to_f32_vec(out.specular.unwrap()),
        ];
        let mut hits = 0;
        for i in 0..w * h {
            let want: RayReference =
                sphere().reference_ray(&cfg.camera, origins[i], dirs[i], 20_000, &refs, -1.2);
            hits += usize::from(want.opacity > 0.5);
            assert!(
                (f64::from(opacity[i]) - want.opacity).abs() < 2e-3,
                "pixel {i} opacity {} vs {}",
                opacity[i],
                want.opacity
            );
            assert!(
                (f64::from(depth[i]) - want.depth).abs() < 5e-3,
                "pixel {i} depth {} vs {}",
                depth[i],
                want.depth
            );
            for (k, m) in [want.albedo, want.normal, want.diffuse, want.specular]
                .into_iter()
                .enumerate()
            {
                close3(
                    &maps3[k][3 * i..3 * i + 3],
                    m,
                    1e-2,
                    &format!("pixel {i} map {k}"),
                );
            }
        }
        assert!(
            hits > 4 && hits < w * h,
            "the image shows the sphere's edge ({hits} hits)"
        );
    }

    #[test]
    fn stiff_and_extreme_cases_give_finite_outputs_and_gradients() {
        let device = Device::flex().autodiff();
        let net = NeiifConfig::new()
            .with_w_dim(8)
            .with_width(16)
            .with_head_width(8)
            .init(&device);
        let maps = light_maps(2, 1e5); // 1e5 light-map values
        let light = lighting(&[maps.clone(), maps], &[0.0, 3.0], &device);
        let base = CameraConfig::new();
        let cameras = [
            ("paper bounds", base.clone()),
            (
                "very short rays",
                base.clone().with_near(2.7).with_far(2.7 + 1e-5),
            ),
            ("very long rays", base.clone().with_near(1e-3).with_far(1e3)),
        ];
        for (what, camera) in cameras {
            for scale in [0.0, 1.0, 1e4] {
                let w = Tensor::<2>::random([2, 8], Distribution::Normal(0.0, 1.0), &device)
                    .require_grad();
                let field = LatentField {
                    field: &net,
                    w: w.clone(),
                };
                let cfg = RendererConfig::new()
                    .with_camera(camera.clone())
                    .with_stratified(12)
                    .with_importance(12);
                let (o, d) = camera_ray_batch(
                    &camera,
                    &[Pose::new(0.0, 0.0), Pose::new(0.5, 0.2)],
                    4,
                    4,
                    &device,
                );
                let out = render(
                    &cfg,
                    &Scaled(&field, scale),
                    o,
                    d,
                    Some(&light),
                    RenderWants::ALL,
                    true,
                );
                let opacity = to_f32_vec(out.opacity.clone());
                assert!(
                    opacity.iter().all(|v| (0.0..=1.0 + 1e-6).contains(v)),
                    "{what}, density x{scale}: opacity {opacity:?}"
                );
                if scale == 0.0 {
                    assert!(
                        opacity.iter().all(|v| *v == 0.0),
                        "{what}: empty space is transparent"
                    );
                }
                let parts = [
                    out.albedo.unwrap(),
                    out.normals.unwrap(),
                    out.diffuse.unwrap(),
                    out.specular.unwrap(),
                    out.features.unwrap(),
                ];
                let mut loss = out.opacity.sum() + out.depth.unwrap().sum();
                for p in parts {
                    let v = to_f32_vec(p.clone());
                    assert!(
                        v.iter().all(|x| x.is_finite()),
                        "{what}, density x{scale}: non-finite output"
                    );
                    loss = loss + p.sum();
                }
                let grads = loss.backward();
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
                        "{what}, density x{scale}: non-finite gradient"
                    );
                }
            }
        }
    }

    #[test]
    fn unwanted_outputs_are_not_computed() {
        let device = Device::flex();
        let cfg = RendererConfig::new().with_stratified(8).with_importance(0);
        let (o, d) = camera_ray_batch(&cfg.camera, &[Pose::new(0.0, 0.0)], 3, 3, &device);
        let wants = RenderWants {
            albedo: true,
            normals: false,
            shading: false,
            features: false,
            depth: false,
        };
        // No lighting is needed without shading.
        let out = render(&cfg, &sphere(), o, d, None, wants, false);
        assert!(out.albedo.is_some());
        assert!(out.normals.is_none() && out.diffuse.is_none() && out.features.is_none());
        assert!(out.depth.is_none());
    }
}

#[cfg(test)]
mod compositing_order_tests {
    use super::*;
    use crate::analytic::SoftSphere;
    use crate::backend::to_f32_vec;
    use crate::pose::Pose;
    use crate::ray_sampling::camera_ray_batch;
    use burn::tensor::Device;

    /// The plain way: every channel of both passes gathered into depth order, then the
    /// midpoint rule over the sorted samples.
    fn sorted_reference(coarse: Samples, fine: Samples) -> [Tensor<2>; 4] {
        let (t, order) = Tensor::cat(vec![coarse.t, fine.t], 1).sort_with_indices(1);
        let sigma = Tensor::cat(vec![coarse.sigma, fine.sigma], 1).gather(1, order.clone());
        let gather = |a: Option<Tensor<3>>, b: Option<Tensor<3>>| -> Tensor<3> {
            let both = Tensor::cat(vec![a.unwrap(), b.unwrap()], 1);
            let [n, s, c] = both.dims();
            both.gather(1, order.clone().reshape([n, s, 1]).expand([n, s, c]))
        };
        let albedo = gather(coarse.albedo, fine.albedo);
        let normals = gather(coarse.normals, fine.normals);
        let features = gather(coarse.features, fine.features);
        let [rays, n] = t.dims();
        let delta = t.clone().narrow(1, 1, n - 1) - t.clone().narrow(1, 0, n - 1);
        let mid = (sigma.clone().narrow(1, 0, n - 1) + sigma.narrow(1, 1, n - 1)).mul_scalar(0.5);
        let w = ray_marching::weights(mid, delta);
        let zero = Tensor::<2>::zeros([rays, 1], &t.device());
        let mass = (Tensor::cat(vec![zero.clone(), w.clone()], 1) + Tensor::cat(vec![w, zero], 1))
            .mul_scalar(0.5);
        [
            ray_marching::accumulate(mass.clone(), albedo),
            ray_marching::accumulate(mass.clone(), normals),
            ray_marching::accumulate(mass.clone(), features),
            ray_marching::accumulate(mass, t.reshape([rays, n, 1])),
        ]
    }

    #[test]
    fn compositing_in_the_passes_order_equals_compositing_in_depth_order() {
        let device = Device::flex();
        let sphere = SoftSphere {
            radius: 0.3,
            softness: 0.01,
            peak: 60.0,
            albedo: [0.5, 0.3, 0.9],
            specular_weights: vec![0.1],
        };
        let config = RendererConfig::new()
            .with_stratified(8)
            .with_importance(8)
            .with_midpoint(true);
        let cfg = config.camera.clone();
        let (o, d) = camera_ray_batch(&cfg, &[Pose::new(0.1, 0.05)], 6, 6, &device);
        let wants = RenderWants {
            albedo: true,
            normals: true,
            features: true,
            depth: true,
            shading: false,
        };
        let out = render(&config, &sphere, o.clone(), d.clone(), None, wants, false);
        // The same samples, composited the plain way.
        let (t, _) = stratified_samples(&cfg, 36, 8, false, &device);
        let coarse = evaluate(&sphere, &o, &d, t, wants.field());
        let w = ray_marching::weights(
            coarse.sigma.clone(),
            segment_lengths(coarse.t.clone(), cfg.far),
        );
        let t_fine = importance_samples(&cfg, coarse.t.clone(), w, 8, false);
        let fine = evaluate(&sphere, &o, &d, t_fine, wants.field());
        let [albedo, normals, features, depth] = sorted_reference(coarse, fine);
        let opacity = to_f32_vec(out.opacity.clone());
        let depth: Vec<f32> = to_f32_vec(depth)
            .iter()
            .zip(&opacity)
            .map(|(e, a)| e + (1.0 - a) * cfg.far as f32)
            .collect();
        assert!(opacity.iter().any(|a| *a > 0.9), "some rays hit the sphere");
        for (what, got, want) in [
            (
                "albedo",
                to_f32_vec(out.albedo.unwrap()),
                to_f32_vec(albedo),
            ),
            (
                "normals",
                to_f32_vec(out.normals.unwrap()),
                to_f32_vec(normals),
            ),
            (
                "features",
                to_f32_vec(out.features.unwrap()),
                to_f32_vec(features),
            ),
            ("depth", to_f32_vec(out.depth.unwrap()), depth),
        ] {
            assert_eq!(got.len(), want.len(), "{what}");
            for (g, w) in got.iter().zip(&want) {
                assert!((g - w).abs() < 1e-5 * (1.0 + w.abs()), "{what}: {g} vs {w}");
            }
        }
    }
}
