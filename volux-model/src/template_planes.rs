//! A latent-independent tri-plane of features beside the positional encoding (an option, not
//! in the paper): three learned planes of `channels` features on `resolution^2` control points
//! (EG3D's xy, xz and yz planes), sampled at a point by projecting it onto each and summing
//! the three, and handed to the NeIIF's first layer with the encoding.
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
//! gather and the weighted sums are tensor ops, differentiable in the planes.

use burn::config::Config;
use burn::module::{Module, Param};
use burn::tensor::{Device, Int, Tensor, TensorData};

use crate::backend::to_f32_vec;

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
}

/// The planes: `[3 resolution^2, channels]` (plane-major, then row `a`, column `b`), xy, xz,
/// yz.
#[derive(Module, Debug)]
pub struct TemplatePlanes {
    pub planes: Param<Tensor<2>>,
    pub resolution: usize,
    pub channels: usize,
    #[module(skip)]
    pub bound: f64,
}

/// The world axes each plane spans.
pub const PLANE_AXES: [(usize, usize); 3] = [(0, 1), (0, 2), (1, 2)];

/// Taps per point: 3 planes of 3 x 3.
pub const TAPS: usize = 27;

impl TemplatePlanesConfig {
    /// Planes of zeros: a fresh field is the encoding's alone, and the planes learn from the
    /// first step (the first layer's weights on them are not zero).
    pub fn init(&self, device: &Device) -> TemplatePlanes {
        assert!(
            self.resolution >= 2,
            "template planes need 2+ control points"
        );
        TemplatePlanes {
            planes: Param::from_tensor(Tensor::zeros(
                [3 * self.resolution * self.resolution, self.channels],
                device,
            )),
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

/// Where a point's 27 taps are and what they weigh: `index[tap]` into the stacked planes,
/// `weight[tap]` and `d weight[tap] / dx_j` for each axis `j`.
struct Taps {
    index: Vec<i64>,
    weight: Vec<f32>,
    derivative: [Vec<f32>; 3],
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

    /// The taps of `points` (`[p, 3]`, flattened), laid out `[TAPS, p]`.
    fn taps(&self, points: &[f32]) -> Taps {
        let p = points.len() / 3;
        let n = self.resolution;
        let mut taps = Taps {
            index: vec![0; TAPS * p],
            weight: vec![0.0; TAPS * p],
            derivative: [
                vec![0.0; TAPS * p],
                vec![0.0; TAPS * p],
                vec![0.0; TAPS * p],
            ],
        };
        for (q, point) in points.chunks_exact(3).enumerate() {
            let axes: Vec<_> = point
                .iter()
                .map(|&x| {
                    let (s, ds) = self.grid_coordinate(f64::from(x));
                    let (index, w, dw) = quadratic_taps(s, n);
                    (index, w, dw.map(|d| d * ds))
                })
                .collect();
            for (plane, &(a, b)) in PLANE_AXES.iter().enumerate() {
                let ((ia, wa, da), (ib, wb, db)) = (&axes[a], &axes[b]);
                for oa in 0..3 {
                    for ob in 0..3 {
                        let tap = plane * 9 + oa * 3 + ob;
                        let at = tap * p + q;
                        taps.index[at] = (plane * n * n + ia[oa] * n + ib[ob]) as i64;
                        taps.weight[at] = (wa[oa] * wb[ob]) as f32;
                        taps.derivative[a][at] = (da[oa] * wb[ob]) as f32;
                        taps.derivative[b][at] = (wa[oa] * db[ob]) as f32;
                    }
                }
            }
        }
        taps
    }

    /// The features at `points: [p, 3]`, `[p, channels]`, and with `derivative` their
    /// derivatives along x, y and z (`[p, channels]` each).
    pub fn forward(
        &self,
        points: Tensor<2>,
        derivative: bool,
    ) -> (Tensor<2>, Option<[Tensor<2>; 3]>) {
        let [p, _] = points.dims();
        let device = points.device();
        let taps = self.taps(&to_f32_vec(points));
        let c = self.channels;
        let index = Tensor::<1, Int>::from_data(TensorData::new(taps.index, [TAPS * p]), &device);
        let gathered = self.planes.val().select(0, index).reshape([TAPS, p, c]);
        let sum = |w: Vec<f32>| {
            let w = Tensor::<3>::from_data(TensorData::new(w, [TAPS, p, 1]), &device);
            (gathered.clone() * w).sum_dim(0).reshape([p, c])
        };
        let [dx, dy, dz] = taps.derivative;
        let derivatives = derivative.then(|| [sum(dx), sum(dy), sum(dz)]);
        (sum(taps.weight), derivatives)
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
