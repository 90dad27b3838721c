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
//! around each sample can put the weight half a bin past the surface.) The placement carries
//! no gradient: the composited samples are differentiated exactly as if their depths had
//! been given.
//!
//! The density-only samples also join the compositing (in [`crate::volume_rendering`]): the
//! weights are those of every sample, full and density-only, sorted together, so that the
//! opacity and the place of a surface are resolved as finely as the samples that found it;
//! each density-only sample lends its weight to the values of the two full samples around
//! it, in proportion to its distance from each (linear interpolation in depth). With
//! the full samples alone the quadrature would lose the weight outside the first and last
//! of them (half a quantile of the weights at each end: 3% of the opacity of a soft sphere
//! at 12 samples, measured). The density-only densities are constants, but the quadrature's
//! sensitivity to them is passed on to the full samples around them, by the same
//! interpolation ([`lend_density_gradient`]): the gradient sees only what the full samples
//! give, with the weight of the whole ray (without it, a seventh of the depth's sensitivity
//! to the density was left in a soft sphere's test).

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

/// How the entries of the quadrature lend their weight to the composited samples' values:
/// entry `j` (`[rays, n]`, in depth order) carries `1 - to_right` of its weight to the
/// composited sample `left` and `to_right` to `right` (indices into the composited samples'
/// own order), its values being the linear interpolation in depth between its two
/// neighbours. A composited sample's own entry lends everything to itself; an entry before
/// the first or after the last composited sample lends to that one. All constants.
#[derive(Clone, Debug)]
pub struct Lending {
    pub left: Tensor<2, Int>,
    pub right: Tensor<2, Int>,
    pub to_right: Tensor<2>,
}

impl Lending {
    /// `x` of the composited samples (`[rays, c]`, their own order) interpolated at every
    /// entry, `[rays, n]`.
    pub fn interpolate(&self, x: Tensor<2>) -> Tensor<2> {
        let left = x.clone().gather(1, self.left.clone());
        let right = x.gather(1, self.right.clone());
        left.clone() + (right - left) * self.to_right.clone()
    }
}

/// The densities `sigma` of the quadrature's entries (`[rays, n]`, in depth order) with the
/// density-only ones (where `density_only` is 1) given the gradient of the composited
/// samples' densities interpolated there: the value is unchanged (`x - x` is exactly zero),
/// but the quadrature's sensitivity to a density-only entry's density reaches the two
/// composited samples around it, as its values do. Without this, the density-only entries
/// (two thirds of the quadrature at `0:16:8:12`) would hold their share of the transmittance
/// out of every gradient, and the geometry would learn from a fraction of the sensitivity
/// the appearance learns from.
pub fn lend_density_gradient(
    sigma: Tensor<2>,
    density_only: Tensor<2>,
    lending: &Lending,
    composited_sigma: Tensor<2>,
) -> Tensor<2> {
    if !sigma.is_autodiff() {
        return sigma; // no gradient to lend
    }
    let lent = lending.interpolate(composited_sigma);
    sigma + (lent.clone() - lent.detach()) * density_only
}

/// The [`Lending`] of the sorted depths `t` (`[rays, n]`) to the composited depths
/// `composited` (`[rays, c]`, any order) on the same ray. Interpolating between the two
/// neighbours instead of taking the nearest one keeps the values along a ray continuous, so
/// that the normals of a surface found between two composited samples do not step with the
/// proposal's depth grid.
pub fn lend(t: Tensor<2>, composited: Tensor<2>) -> Lending {
    let autodiff = t.is_autodiff();
    let (t, composited) = (t.inner(), composited.inner());
    let [rays, n] = t.dims();
    let c = composited.dims()[1];
    let (sorted, order) = composited.sort_with_indices(1);
    // How many composited depths lie at or before each entry: the rank of its right
    // neighbour (a composited sample's own entry counts itself, so it is its own left one).
    let at_or_before = sorted
        .clone()
        .reshape([rays, 1, c])
        .lower_equal(t.clone().reshape([rays, n, 1]))
        .int()
        .sum_dim(2)
        .reshape([rays, n]);
    let right_rank = at_or_before.clone().clamp_max(c as i64 - 1);
    let left_rank = at_or_before.sub_scalar(1).clamp_min(0);
    let t_left = sorted.clone().gather(1, left_rank.clone());
    let gap = sorted.gather(1, right_rank.clone()) - t_left.clone();
    let to_right = (t - t_left)
        .div(gap.clone())
        .mask_fill(gap.lower_equal_elem(0.0), 0.0)
        .clamp(0.0, 1.0);
    let left = order.clone().gather(1, left_rank);
    let right = order.gather(1, right_rank);
    if autodiff {
        Lending {
            left: left.autodiff(),
            right: right.autodiff(),
            to_right: to_right.autodiff(),
        }
    } else {
        Lending {
            left,
            right,
            to_right,
        }
    }
}

#[cfg(test)]
mod tests;
