//! Fields with known answers, rendered through the same renderer as the NeIIF: the soft sphere
//! the renderer's tests and the samples-per-ray report measure against.

use burn::tensor::{Tensor, activation};
use volux_envmap::LightMap;

use crate::field::{Field, FieldOutput, FieldWants, normals_from_gradient};
use crate::ray_sampling::CameraConfig;

/// What one ray of a [`SoftSphere`] renders to, in f64.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RayReference {
    pub opacity: f64,
    /// Expected depth, the transparent remainder at `far` (the renderer's convention).
    pub depth: f64,
    pub albedo: [f64; 3],
    pub normal: [f64; 3],
    pub diffuse: [f64; 3],
    pub specular: [f64; 3],
}

/// `sigma(x) = peak * sigmoid((radius - |x|) / softness)`: a ball of density `peak` whose
/// surface is smeared over a few `softness`. Outward normals `x / |x|`, a constant albedo and
/// specular weights, and features `x` (so a feature map is the expected surface point).
#[derive(Clone, Debug)]
pub struct SoftSphere {
    pub radius: f64,
    pub softness: f64,
    pub peak: f64,
    pub albedo: [f32; 3],
    pub specular_weights: Vec<f32>,
}

impl SoftSphere {
    /// Density along a ray at distance `r` from the centre, in f64 (for references).
    pub fn sigma_at(&self, r: f64) -> f64 {
        self.peak / (1.0 + (-(self.radius - r) / self.softness).exp())
    }

    /// The rendering integral along one ray (`dir` unit), by the same exponential quadrature
    /// as the renderer but on `steps` equal segments in f64: as `steps` grows it converges to
    /// the continuous integral, so with many steps it is the reference the renderer's sample
    /// counts are measured against. `lights[0]` must be `L_1`; `lights[i]` goes with
    /// `specular_weights[i]`; the environment is rotated by `yaw`. No lights: no shading.
    pub fn reference_ray(
        &self,
        camera: &CameraConfig,
        origin: [f64; 3],
        dir: [f64; 3],
        steps: usize,
        lights: &[&LightMap],
        yaw: f64,
    ) -> RayReference {
        let h = (camera.far - camera.near) / steps as f64;
        let mut out = RayReference::default();
        let mut optical = 0.0f64;
        for k in 0..steps {
            let t = camera.near + (k as f64 + 0.5) * h;
            let x: [f64; 3] = std::array::from_fn(|c| origin[c] + t * dir[c]);
            let r = x.iter().map(|v| v * v).sum::<f64>().sqrt();
            let tau = self.sigma_at(r) * h;
            let w = (-optical).exp() * -(-tau).exp_m1();
            optical += tau;
            if w == 0.0 {
                continue;
            }
            let n = x.map(|v| v / r.max(1e-300));
            out.opacity += w;
            out.depth += w * t;
            for (c, nc) in n.iter().enumerate() {
                out.albedo[c] += w * f64::from(self.albedo[c]);
                out.normal[c] += w * nc;
            }
            if let Some(diffuse) = lights.first() {
                let dn: f64 = (0..3).map(|c| dir[c] * n[c]).sum();
                let refl: [f64; 3] = std::array::from_fn(|c| dir[c] - 2.0 * dn * n[c]);
                let d = diffuse.lookup_rotated(n, yaw);
                for (acc, dc) in out.diffuse.iter_mut().zip(d) {
                    *acc += w * f64::from(dc);
                }
                for (map, omega) in lights.iter().zip(&self.specular_weights) {
                    let l = map.lookup_rotated(refl, yaw);
                    for (acc, lc) in out.specular.iter_mut().zip(l) {
                        *acc += w * f64::from(*omega) * f64::from(lc);
                    }
                }
            }
        }
        out.depth += (1.0 - out.opacity) * camera.far;
        out
    }
}

impl Field for SoftSphere {
    fn query(&self, points: Tensor<3>, wants: FieldWants) -> FieldOutput {
        let [b, p, _] = points.dims();
        let device = points.device();
        let r = points
            .clone()
            .powi_scalar(2)
            .sum_dim(2)
            .add_scalar(1e-12)
            .sqrt(); // [b, p, 1]
        let s = activation::sigmoid(
            r.clone()
                .neg()
                .add_scalar(self.radius)
                .div_scalar(self.softness),
        );
        let sigma = s.clone().mul_scalar(self.peak);
        let mut out = FieldOutput {
            sigma: sigma.reshape([b, p]),
            grad_sigma: None,
            normals: None,
            albedo: None,
            specular_weights: None,
            features: None,
        };
        if wants.normals {
            let outward = points.clone() / r;
            // d sigma / dx = -peak s (1 - s) / softness * x / |x|.
            let slope = s.clone() * s.neg().add_scalar(1.0);
            let g = outward * slope.mul_scalar(-self.peak / self.softness);
            out.normals = Some(normals_from_gradient(g.clone()));
            out.grad_sigma = Some(g);
        }
        if wants.appearance {
            let k = self.specular_weights.len();
            out.albedo = Some(
                Tensor::<1>::from_floats(self.albedo.as_slice(), &device)
                    .reshape([1, 1, 3])
                    .expand([b, p, 3]),
            );
            out.specular_weights = Some(
                Tensor::<1>::from_floats(self.specular_weights.as_slice(), &device)
                    .reshape([1, 1, k])
                    .expand([b, p, k]),
            );
            out.features = Some(points);
        }
        out
    }
}
