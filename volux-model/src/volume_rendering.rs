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
//! them to the two full samples around them (interpolated in depth). What is not asked for is not computed: no light-map look-ups without shading, no
//! density-gradient sweep without normals or shading, no field head without albedo, features or
//! shading. Like EG3D's renderer this file knows the field only through [`Field`].

use burn::config::Config;
use burn::tensor::{IndexingUpdateOp, Int, Tensor};

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
    /// to the two full samples around them. 0: EG3D's scheme, the importance samples are
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

/// Whose values each entry of the quadrature carries (see [`render`]). One value per render:
/// the size difference of the variants costs nothing.
#[allow(clippy::large_enum_variant)]
enum Owners {
    /// Every entry is a composited sample: the index of each in the samples' order.
    Own(Tensor<2, Int>),
    /// Density-only entries among them lend their weight ([`proposal::lend`]).
    Lent(proposal::Lending),
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
    // proposal placed them, in depth order. `Owners` says, for each entry in that order, which
    // composited samples (their indices in `samples`) carry its values: itself, or for a
    // density-only entry the two around it, interpolated in depth.
    let (t_all, sigma_all, owners) = match proposed {
        Some(p) => {
            let (t, order) = Tensor::cat(vec![samples.t.clone(), p.t], 1).sort_with_indices(1);
            let sigma =
                Tensor::cat(vec![samples.sigma.clone(), p.sigma], 1).gather(1, order.clone());
            let lending = proposal::lend(t.clone(), samples.t.clone());
            let density_only = order.greater_equal_elem(s as i64).float();
            let sigma = proposal::lend_density_gradient(
                sigma,
                density_only,
                &lending,
                samples.sigma.clone(),
            );
            (t, sigma, Owners::Lent(lending))
        }
        None => {
            let (t, order) = samples.t.clone().sort_with_indices(1);
            let sigma = samples.sigma.clone().gather(1, order.clone());
            (t, sigma, Owners::Own(order))
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
    // Each composited sample's share: its own mass and what the density-only entries lend it,
    // in the samples' own order.
    let zeros = Tensor::<2>::zeros([b * r, s], &device);
    let share = match owners {
        Owners::Own(order) => zeros.scatter(1, order, mass.clone(), IndexingUpdateOp::Add),
        Owners::Lent(l) => {
            let to_right = mass.clone() * l.to_right;
            zeros
                .scatter(
                    1,
                    l.left,
                    mass.clone() - to_right.clone(),
                    IndexingUpdateOp::Add,
                )
                .scatter(1, l.right, to_right, IndexingUpdateOp::Add)
        }
    };
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
mod tests;

#[cfg(test)]
mod compositing_order_tests;
