//! Density-only proposal passes: where the composited samples go, at the price of density
//! alone.
//!
//! EG3D evaluates its stratified samples with every output (the gradient for the normals, the
//! appearance head) and composites them, so each sample that only serves to find the surface
//! costs as much as one that shades it. Here the samples that place the importance samples
//! ask the field for its density only (layers 1 to the density layer, no gradient sweep, no head,
//! no autodiff: [`Field::density`]), about a fifth of a full query in the forward pass and
//! nothing in the backward one, so there can be many of them:
//!
//! 1. `proposal` stratified depths, densities only;
//! 2. optionally `refine` depths drawn from their weights and merged with them (a second
//!    level: a surface found in one proposal segment is sampled again inside that segment);
//! 3. the `importance` depths of the composited samples, drawn from the weights of all the
//!    density-only samples.
//!
//! The weights here belong to the *segments between* samples (the midpoint rule, with the
//! segments from `near` to the first sample and from the last to `far` at their one sample's
//! density), and the draws are uniform inside a segment: a surface crossed between two
//! samples lies in the segment that carries its weight, so the draws bracket it. (NeRF's bins
//! around each sample can put the weight half a bin past the surface.) Nothing here carries
//! a gradient: only the composited samples' values do, exactly as if their depths had been
//! given; the proposal changes where the quadrature looks, not what it differentiates.
//!
//! The density-only samples also join the compositing (in [`crate::volume_rendering`]): the
//! weights are those of every sample, full and density-only, sorted together, so that the
//! opacity and the place of a surface are resolved as finely as the samples that found it;
//! each density-only sample lends its weight to the values of the nearest full sample. With
//! the full samples alone the quadrature would lose the weight outside the first and last
//! of them (half a quantile of the weights at each end: 3% of the opacity of a soft sphere
//! at 12 samples, measured).

use burn::tensor::{Int, Tensor};

use crate::field::Field;
use crate::profile::{self, Phase};
use crate::ray_marching;
use crate::ray_sampling::{
    CameraConfig, segment_edges, segment_importance_samples, stratified_samples,
};
use crate::volume_rendering::RendererConfig;

/// Compositing weights `[rays, samples + 1]` of the segments `near..t_0, t_0..t_1, ...,
/// t_last..far` between sorted depths `t` with densities `sigma` (both `[rays, samples]`):
/// inner segments at the mean density of their two ends, the two end segments at their one
/// sample's density.
pub fn segment_weights(camera: &CameraConfig, t: Tensor<2>, sigma: Tensor<2>) -> Tensor<2> {
    let s = t.dims()[1];
    let edges = segment_edges(camera, t);
    let lengths = edges.clone().narrow(1, 1, s + 1) - edges.narrow(1, 0, s + 1);
    let mut parts = vec![sigma.clone().narrow(1, 0, 1)];
    if s > 1 {
        parts.push(
            (sigma.clone().narrow(1, 0, s - 1) + sigma.clone().narrow(1, 1, s - 1)).mul_scalar(0.5),
        );
    }
    parts.push(sigma.narrow(1, s - 1, 1));
    ray_marching::weights(Tensor::cat(parts, 1), lengths)
}

/// Densities `[batch * rays, samples]` of `field` at depths `t` (`[batch * rays, samples]`)
/// along the rays `origins, dirs` (`[batch, rays, 3]`, without autodiff).
fn densities(
    field: &impl Field,
    origins: &Tensor<3>,
    dirs: &Tensor<3>,
    t: &Tensor<2>,
) -> Tensor<2> {
    let [b, r, _] = origins.dims();
    let s = t.dims()[1];
    let points = origins.clone().reshape([b, r, 1, 3])
        + dirs.clone().reshape([b, r, 1, 3]) * t.clone().reshape([b, r, s, 1]);
    field
        .density(points.reshape([b, r * s, 3]))
        .reshape([b * r, s])
}

/// What the density-only passes found along each ray of `[batch * rays]`.
#[derive(Clone, Debug)]
pub struct Proposal {
    /// Depths of the importance samples to query in full and composite,
    /// `[batch * rays, importance]`, sorted.
    pub importance: Tensor<2>,
    /// Depths of every density-only sample, `[batch * rays, proposal + refine]`, sorted.
    pub t: Tensor<2>,
    /// Their densities, same shape.
    pub sigma: Tensor<2>,
}

/// Places the importance samples by the density-only passes (`config.proposal`, then
/// `config.refine`; see the module documentation). Every tensor is sorted along the ray,
/// carries no gradient and lives on the device of `origins` (with autodiff when it has it,
/// as a constant).
pub fn place(
    config: &RendererConfig,
    field: &impl Field,
    origins: &Tensor<3>,
    dirs: &Tensor<3>,
    jitter: bool,
) -> Proposal {
    let autodiff = origins.is_autodiff();
    let (o, d) = (origins.clone().inner(), dirs.clone().inner());
    let [b, r, _] = o.dims();
    let camera = &config.camera;
    let (importance, t, sigma) = profile::timed(Phase::Proposal, || {
        let (mut t, _) = stratified_samples(camera, b * r, config.proposal, jitter, &o.device());
        let mut sigma = densities(field, &o, &d, &t);
        if config.refine > 0 {
            let w = segment_weights(camera, t.clone(), sigma.clone());
            let extra = segment_importance_samples(camera, t.clone(), w, config.refine, jitter);
            let extra_sigma = densities(field, &o, &d, &extra);
            let (merged, order) = Tensor::cat(vec![t, extra], 1).sort_with_indices(1);
            sigma = Tensor::cat(vec![sigma, extra_sigma], 1).gather(1, order);
            t = merged;
        }
        let w = segment_weights(camera, t.clone(), sigma.clone());
        let importance =
            segment_importance_samples(camera, t.clone(), w, config.importance, jitter);
        (importance, t, sigma)
    });
    let on_device = |x: Tensor<2>| if autodiff { x.autodiff() } else { x };
    Proposal {
        importance: on_device(importance),
        t: on_device(t),
        sigma: on_device(sigma),
    }
}

/// For each of the sorted depths `t` (`[rays, n]`), the index of the nearest of the
/// composited depths `composited` (`[rays, c]`) on the same ray, `[rays, n]`: whose values
/// a density-only sample lends its weight to.
pub fn nearest(t: Tensor<2>, composited: Tensor<2>) -> Tensor<2, Int> {
    let [rays, n] = t.dims();
    let c = composited.dims()[1];
    (t.reshape([rays, n, 1]) - composited.reshape([rays, 1, c]))
        .abs()
        .argmin(2)
        .reshape([rays, n])
}

#[cfg(test)]
mod tests;
