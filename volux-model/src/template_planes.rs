//! A latent-independent tri-plane of features beside the positional encoding (an option, not
//! in the paper): three learned planes of `channels` features on `resolution^2` control points
//! (EG3D's xy, xz and yz planes), sampled at a point by projecting it onto each and summing
//! the three, and handed to the NeIIF's first layer with the encoding.
//!
//! Optionally the planes are a latent's own (`basis > 0`): the shared planes plus `basis`
//! more, each weighted by a coefficient that an affine layer makes of `w`, in the way a
//! morphable model adds weighted shape components to a mean shape ([`PlaneBasis`]). The
//! modulated first layer can only scale each shared channel per latent; the basis lets a
//! latent move features in space (a longer nose, wider cheeks) at the cost of one small
//! matrix product per query.
//!
//! Why: a Fourier-encoded MLP has no spatial locality. To put something at the height of
//! the eyes it builds `sin(2^k pi y)` structure, and that shows as bands across the whole
//! head (docs/RESULTS.md: at 4 and 5 octaves, axis-aligned, rotated or opened coarse to
//! fine). A feature plane holds local structure directly; the modulated layers still make
//! every identity's field from it. The planes are shared by all latents, like StyleGAN's
//! constant input.
//!
//! Each plane is a quadratic B-spline over its control points (9 taps per plane), so the
//! features are C1 in the point and the normals, which come from their derivative, are
//! continuous (bilinear interpolation would crease them along every cell edge). Control point
//! `k` of an axis sits at `-bound + 2 bound k / (resolution - 1)`; outside `[-bound, bound]`
//! the coordinate is clamped (features constant, derivative 0). The taps and weights depend
//! on the points alone, which carry no gradient, so they are computed on the host; the
//! weighted gathers are one flex operation with a hand-written backward into the planes
//! ([`kernel`]; tensor ops on other backends, and as its reference).

use std::sync::Arc;

use burn::config::Config;
use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor};

use crate::backend::to_f32_vec;
use crate::equalized::{EqualizedLinear, EqualizedLinearConfig};
use kernel::Taps;

mod kernel;

/// Configuration of [`TemplatePlanes`].
#[derive(Config, Debug)]
pub struct TemplatePlanesConfig {
    /// Control points per side of each plane.
    pub resolution: usize,
    /// Features per point (the three planes' sum).
    #[config(default = 8)]
    pub channels: usize,
    /// Half the side of the square the planes cover (world units).
    #[config(default = 1.0)]
    pub bound: f64,
    /// Planes a latent weights and adds to the shared ones ([`PlaneBasis`]); 0: the shared
    /// planes alone.
    #[config(default = 0)]
    pub basis: usize,
    /// Width of the latents `w` that weight the basis (with `basis > 0`).
    #[config(default = 0)]
    pub w_dim: usize,
}

/// The planes: `[3 resolution^2, channels]` (plane-major, then row `a`, column `b`), xy, xz,
/// yz.
#[derive(Module, Debug)]
pub struct TemplatePlanes {
    pub planes: Param<Tensor<2>>,
    /// Each latent's own addition to the planes, if any.
    pub basis: Option<PlaneBasis>,
    pub resolution: usize,
    pub channels: usize,
    #[module(skip)]
    pub bound: f64,
}

/// `K` planes of the same layout as the shared ones, and the affine layer that gives a
/// latent's coefficient of each: latent `w`'s planes are `planes + sum_k a_k(w) basis_k`.
#[derive(Module, Debug)]
pub struct PlaneBasis {
    /// `[K, 3 resolution^2 channels]`, each row one set of planes, flattened.
    pub planes: Param<Tensor<2>>,
    /// `w: [batch, w_dim] -> a: [batch, K]`.
    pub coefficients: EqualizedLinear,
}

/// The planes a batch's points read: `[latents 3 resolution^2, channels]`, the rows of each
/// latent's planes after those of the latent before; `latents` is 1 when all share one set.
#[derive(Clone, Debug)]
pub struct LatentPlanes {
    pub planes: Tensor<2>,
    pub latents: usize,
}

/// The world axes each plane spans.
pub const PLANE_AXES: [(usize, usize); 3] = [(0, 1), (0, 2), (1, 2)];

/// Taps per point: 3 planes of 3 x 3.
pub const TAPS: usize = 27;

impl TemplatePlanesConfig {
    /// Planes of zeros: a fresh field is the encoding's alone, and the planes learn from the
    /// first step (the first layer's weights on them are not zero).
    ///
    /// The basis planes start at zero too, so a fresh field with a basis is the same for
    /// every latent; the coefficients' layer starts as any equalized layer (unit-scale
    /// coefficients for unit-scale latents), so the basis learns from the first step.
    pub fn init(&self, device: &Device) -> TemplatePlanes {
        assert!(
            self.resolution >= 2,
            "template planes need 2+ control points"
        );
        assert!(
            self.basis == 0 || self.w_dim > 0,
            "a basis of template planes needs the latents' width"
        );
        let rows = 3 * self.resolution * self.resolution;
        let basis = (self.basis > 0).then(|| PlaneBasis {
            planes: Param::from_tensor(Tensor::zeros([self.basis, rows * self.channels], device)),
            coefficients: EqualizedLinearConfig::new(self.w_dim, self.basis).init(device),
        });
        TemplatePlanes {
            planes: Param::from_tensor(Tensor::zeros([rows, self.channels], device)),
            basis,
            resolution: self.resolution,
            channels: self.channels,
            bound: self.bound,
        }
    }
}

/// Quadratic B-spline weights of the three taps around continuous coordinate `s` in
/// `[0, n - 1]`, their derivatives in `s`, and the taps (clamped to the grid): the nearest
/// control point `i` and its neighbours, with `t = s - i` in `[-1/2, 1/2]`.
pub fn quadratic_taps(s: f64, n: usize) -> ([usize; 3], [f64; 3], [f64; 3]) {
    let i = (s + 0.5).floor();
    let t = s - i;
    let weights = [
        (0.5 - t) * (0.5 - t) / 2.0,
        0.75 - t * t,
        (0.5 + t) * (0.5 + t) / 2.0,
    ];
    let derivatives = [t - 0.5, -2.0 * t, t + 0.5];
    let last = (n - 1) as f64;
    let tap = |o: f64| (i + o).clamp(0.0, last) as usize;
    ([tap(-1.0), tap(0.0), tap(1.0)], weights, derivatives)
}

impl TemplatePlanes {
    /// Grid coordinate of world coordinate `x` (clamped), and `ds/dx` (0 where clamped).
    fn grid_coordinate(&self, x: f64) -> (f64, f64) {
        let last = (self.resolution - 1) as f64;
        let scale = last / (2.0 * self.bound);
        let s = (x + self.bound) * scale;
        if s <= 0.0 {
            (0.0, 0.0)
        } else if s >= last {
            (last, 0.0)
        } else {
            (s, scale)
        }
    }

    /// The taps of `points` (`[p, 3]`, flattened, the points of `latents` latents one latent
    /// after another) with the features' weights and, with `derivative`, the weights of their
    /// derivatives along x, y and z. The taps of latent `l`'s points read the rows of its own
    /// planes, `l 3 resolution^2` on ([`LatentPlanes`]).
    fn taps(&self, points: &[f32], latents: usize, derivative: bool) -> Taps {
        let p = points.len() / 3;
        assert!(
            latents > 0 && p.is_multiple_of(latents),
            "{p} points are not the same number for each of {latents} latents"
        );
        let per_latent = (p / latents).max(1);
        let n = self.resolution;
        let outputs = if derivative { 4 } else { 1 };
        let mut taps = Taps {
            points: p,
            outputs,
            index: vec![0; TAPS * p],
            weights: vec![0.0; TAPS * p * outputs],
        };
        for (q, point) in points.chunks_exact(3).enumerate() {
            let first_row = q / per_latent * 3 * n * n;
            let axes: [_; 3] = std::array::from_fn(|j| {
                let (s, ds) = self.grid_coordinate(f64::from(point[j]));
                let (index, w, dw) = quadratic_taps(s, n);
                (index, w, dw.map(|d| d * ds))
            });
            for (plane, &(a, b)) in PLANE_AXES.iter().enumerate() {
                let ((ia, wa, da), (ib, wb, db)) = (&axes[a], &axes[b]);
                for oa in 0..3 {
                    for ob in 0..3 {
                        let at = q * TAPS + plane * 9 + oa * 3 + ob;
                        taps.index[at] = (first_row + plane * n * n + ia[oa] * n + ib[ob]) as u32;
                        let weights = &mut taps.weights[at * outputs..(at + 1) * outputs];
                        weights[0] = (wa[oa] * wb[ob]) as f32;
                        if derivative {
                            weights[1 + a] = (da[oa] * wb[ob]) as f32;
                            weights[1 + b] = (wa[oa] * db[ob]) as f32;
                        }
                    }
                }
            }
        }
        taps
    }

    /// The planes every latent reads alike.
    pub fn shared(&self) -> LatentPlanes {
        LatentPlanes {
            planes: self.planes.val(),
            latents: 1,
        }
    }

    /// The planes of the latents `w: [batch, w_dim]`: each latent's own with a basis (the
    /// shared planes plus the basis weighted by the latent's coefficients), else the shared
    /// ones.
    pub fn of_latents(&self, w: &Tensor<2>) -> LatentPlanes {
        let Some(basis) = &self.basis else {
            return self.shared();
        };
        let [batch, _] = w.dims();
        let [rows, c] = self.planes.val().dims();
        let a = basis.coefficients.forward(w.clone());
        let own = a.matmul(basis.planes.val()) + self.planes.val().reshape([1, rows * c]);
        LatentPlanes {
            planes: own.reshape([batch * rows, c]),
            latents: batch,
        }
    }

    /// The features of `w`'s latents at `points: [p, 3]` (the points of each latent one
    /// latent after another), `[p, channels]`, and with `derivative` their derivatives along
    /// x, y and z (`[p, channels]` each).
    pub fn forward(
        &self,
        points: Tensor<2>,
        w: &Tensor<2>,
        derivative: bool,
    ) -> (Tensor<2>, Option<[Tensor<2>; 3]>) {
        self.sample(&self.of_latents(w), points, derivative)
    }

    /// [`Self::forward`] on given planes.
    pub fn sample(
        &self,
        planes: &LatentPlanes,
        points: Tensor<2>,
        derivative: bool,
    ) -> (Tensor<2>, Option<[Tensor<2>; 3]>) {
        let [p, _] = points.dims();
        let taps = Arc::new(self.taps(&to_f32_vec(points), planes.latents, derivative));
        let c = self.channels;
        let out = kernel::sample(planes.planes.clone(), taps);
        let output = |k: usize| out.clone().narrow(1, k, 1).reshape([p, c]);
        let derivatives = derivative.then(|| [output(1), output(2), output(3)]);
        (output(0), derivatives)
    }

    /// The gradient in the point, `[b, p, 3]`, of `<u, features>` for a cotangent `u:
    /// [b, p, channels]` of the features, from [`Self::forward`]'s derivatives (each
    /// `[b * p, channels]`).
    pub fn fold(&self, u: Tensor<3>, derivatives: &[Tensor<2>; 3]) -> Tensor<3> {
        let [b, p, c] = u.dims();
        let parts = derivatives
            .iter()
            .map(|d| (u.clone() * d.clone().reshape([b, p, c])).sum_dim(2))
            .collect();
        Tensor::cat(parts, 2)
    }
}

#[cfg(test)]
mod tests;
