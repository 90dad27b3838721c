//! The neural implicit intrinsic field (NeIIF; paper section 3.2 and appendix B): a point `x`
//! and a latent `w` give a volume density `sigma`, its gradient (hence the normal), an albedo,
//! specular blend weights `omega_i` and a feature `f`.
//!
//! Fourier positional encoding (10 frequencies) -> 6 modulated fully connected layers (256 in
//! the paper) with a smooth activation -> density from a linear layer on layer 4 (softplus);
//! on layer 6 a two-layer head gives albedo (3, sigmoid) and specular weights (one per light
//! map, softplus, so non-negative); the layer-6 output is the feature `f`.
//!
//! Normals `n = -grad(sigma) / |grad(sigma)|` enter the loss (through `D = L_1(n)` and the
//! normal maps), so `grad(sigma)` must itself be differentiable. Burn's autodiff is first order,
//! so `grad(sigma)` is computed explicitly, by a reverse sweep written in tensor ops: from the
//! density head back through layers 1-4, each step the activation's derivative (the
//! [`fused_activation::pullback`]) and the transposed modulated weight, then the encoding's
//! Jacobian. That is exact, costs one more product per layer (forward-mode tangents would cost
//! three, one per coordinate), and is ordinary tensor algebra that first-order autodiff
//! differentiates, as PyTorch's double backward would. The activation must be
//! smooth so that the normals are continuous: `0.2 x + 0.8 softplus(x)`, a leaky ReLU with the
//! corner rounded (slope from 0.2 to 1, never dead).

use burn::config::Config;
use burn::module::Module;
use burn::tensor::{Device, Tensor, activation};

use crate::batched_matmul::batched_matmul;
use crate::equalized::{EqualizedLinear, EqualizedLinearConfig};
use crate::field::{Field, FieldOutput, FieldWants, normals_from_gradient};
use crate::fused_activation;
use crate::modulated::{ModulatedLinear, ModulatedLinearConfig};
use crate::positional_encoding::{PositionalEncoding, PositionalEncodingConfig};
use crate::profile::{self, Phase};

/// `1 / sqrt(E[a(x)^2])` for `x ~ N(0, 1)`: keeps unit second moment through a layer, as
/// StyleGAN2's `sqrt(2)` does for its leaky ReLU.
pub const SMOOTH_GAIN: f64 = 1.125;

/// The smooth activation `gain (0.2 x + 0.8 softplus(x))`.
pub fn smooth_lrelu<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    smooth_lrelu_parts(x, false).0
}

/// Its value and (optionally) its derivative `gain (0.2 + 0.8 sigmoid(x))`, from one
/// `e = exp(-|x|)`:
/// `softplus(x) = max(x, 0) + ln(1 + e)` and `sigmoid(x) = 1 / (1 + e)` for `x >= 0`,
/// `e / (1 + e)` otherwise; both stable for any `x`. About 3x faster on flex than Burn's
/// `softplus` + `sigmoid` (whose `log1p` is slow), which matters: the NeIIF applies this
/// to every hidden unit of every sample, and its derivative in every normal's sweep.
pub fn smooth_lrelu_parts<const D: usize>(
    x: Tensor<D>,
    derivative: bool,
) -> (Tensor<D>, Option<Tensor<D>>) {
    let e = x.clone().abs().neg().exp();
    let one_plus = e.clone().add_scalar(1.0);
    let softplus = x.clone().clamp_min(0.0) + one_plus.clone().log();
    let derivative = derivative.then(|| {
        let negative = x.clone().lower_elem(0.0);
        let sigmoid = e.mask_fill(negative.bool_not(), 1.0) / one_plus;
        sigmoid
            .mul_scalar(0.8 * SMOOTH_GAIN)
            .add_scalar(0.2 * SMOOTH_GAIN)
    });
    let value = (x.mul_scalar(0.2) + softplus.mul_scalar(0.8)).mul_scalar(SMOOTH_GAIN);
    (value, derivative)
}

/// Configuration of a [`Neiif`].
#[derive(Config, Debug)]
pub struct NeiifConfig {
    /// Dimension of `w`.
    #[config(default = 512)]
    pub w_dim: usize,
    /// Width of every modulated layer, and so of the feature `f` (256 in the paper).
    #[config(default = 256)]
    pub width: usize,
    /// Number of modulated layers (6 in the paper).
    #[config(default = 6)]
    pub layers: usize,
    /// The layer whose output feeds the density head (4 in the paper, counting from 1).
    #[config(default = 4)]
    pub density_layer: usize,
    /// Octaves of the positional encoding (10 in the paper).
    #[config(default = 10)]
    pub frequencies: usize,
    /// Hidden width of the albedo / specular head.
    #[config(default = 256)]
    pub head_width: usize,
    /// Number of specular blend weights (one per light map: 4 for exponents 1, 16, 32, 64).
    #[config(default = 4)]
    pub specular_lobes: usize,
    /// Initial bias of the specular-weight logits: softplus(-2) = 0.13 per lobe, so a fresh
    /// field is mostly diffuse.
    #[config(default = -2.0)]
    pub specular_bias_init: f64,
    /// Sharpness `s` of a fixed sphere prior added to the density logit,
    /// `s (sphere_radius - |x|)`: a fresh field is then a soft ball instead of fog, which
    /// short runs need (StyleSDF starts from a sphere for the same reason). 0 turns it off.
    #[config(default = 0.0)]
    pub sphere_prior: f64,
    /// Radius of the sphere prior (world units; the head fits in the unit sphere).
    #[config(default = 0.5)]
    pub sphere_radius: f64,
}

/// The field.
#[derive(Module, Debug)]
pub struct Neiif {
    pub encoding: PositionalEncoding,
    pub layers: Vec<ModulatedLinear>,
    pub density_head: EqualizedLinear,
    pub head_hidden: EqualizedLinear,
    pub head_out: EqualizedLinear,
    pub density_layer: usize,
    /// `(sharpness, radius)` of the sphere prior; sharpness 0: none.
    #[module(skip)]
    pub sphere_prior: (f64, f64),
}

/// The activation's two kernels in the field: applied to pre-activations, and its pullback
/// in the reverse sweep that gives the normals.
#[derive(Clone, Copy, Debug)]
pub struct ActivationKernels {
    /// `(y, bias) -> a(y + bias)` ([`fused_activation::activate`]).
    pub activate: fn(Tensor<3>, Tensor<1>) -> Tensor<3>,
    /// `(u, y, bias) -> u a'(y + bias)` ([`fused_activation::pullback::pullback`]).
    pub pullback: fn(Tensor<3>, Tensor<3>, Tensor<1>) -> Tensor<3>,
}

impl ActivationKernels {
    /// The fused flex kernels (their references on other backends).
    pub const FUSED: Self = Self {
        activate: fused_activation::activate,
        pullback: fused_activation::pullback::pullback,
    };
    /// The plain tensor-op references.
    pub const REFERENCE: Self = Self {
        activate: fused_activation::activate_reference,
        pullback: fused_activation::pullback::pullback_reference,
    };
}

/// A NeIIF with the latents of a batch.
pub struct LatentField<'a> {
    pub field: &'a Neiif,
    /// `[batch, w_dim]`.
    pub w: Tensor<2>,
}

impl Field for LatentField<'_> {
    fn query(&self, points: Tensor<3>, wants: FieldWants) -> FieldOutput {
        profile::timed(Phase::Field, || {
            self.field.forward(points, self.w.clone(), wants)
        })
    }

    /// Layers 1 to the density layer and the density head, on the field's parameters
    /// without autodiff: nothing of it enters the graph.
    fn density(&self, points: Tensor<3>) -> Tensor<2> {
        self.field
            .valid()
            .forward(points.inner(), self.w.clone().inner(), FieldWants::DENSITY)
            .sigma
    }
}

impl NeiifConfig {
    /// A field with freshly initialised parameters on `device`.
    pub fn init(&self, device: &Device) -> Neiif {
        assert!(
            (1..=self.layers).contains(&self.density_layer),
            "density layer {} outside 1..={}",
            self.density_layer,
            self.layers
        );
        let encoding = PositionalEncodingConfig::new()
            .with_frequencies(self.frequencies)
            .init();
        let layers = (0..self.layers)
            .map(|i| {
                let d_input = if i == 0 {
                    encoding.output_dim()
                } else {
                    self.width
                };
                ModulatedLinearConfig::new(self.w_dim, d_input, self.width).init(device)
            })
            .collect();
        let mut head_out =
            EqualizedLinearConfig::new(self.head_width, 3 + self.specular_lobes).init(device);
        if let Some(bias) = head_out.bias.take() {
            // Albedo logits start at 0 (albedo 0.5), specular logits at `specular_bias_init`.
            let mut init = vec![0.0f32; 3 + self.specular_lobes];
            for v in init.iter_mut().skip(3) {
                *v = (self.specular_bias_init / head_out.bias_gain) as f32;
            }
            head_out.bias = Some(burn::module::Param::from_tensor(Tensor::<1>::from_floats(
                init.as_slice(),
                &bias.device(),
            )));
        }
        Neiif {
            encoding,
            layers,
            density_head: EqualizedLinearConfig::new(self.width, 1).init(device),
            head_hidden: EqualizedLinearConfig::new(self.width, self.head_width).init(device),
            head_out,
            density_layer: self.density_layer,
            sphere_prior: (self.sphere_prior, self.sphere_radius),
        }
    }
}

/// `[b, p, c] -> [b * p, c]`, through an [`EqualizedLinear`], and back.
fn per_point(layer: &EqualizedLinear, x: Tensor<3>) -> Tensor<3> {
    let [b, p, c] = x.dims();
    let y = layer.forward(x.reshape([b * p, c]));
    let o = y.dims()[1];
    y.reshape([b, p, o])
}

impl Neiif {
    /// Width of the feature `f`.
    pub fn feature_dim(&self) -> usize {
        self.layers.last().map_or(0, ModulatedLinear::d_output)
    }

    /// Number of specular blend weights.
    pub fn specular_lobes(&self) -> usize {
        self.head_out.weight.dims()[0] - 3
    }

    /// Queries `points: [batch, points, 3]` of the fields of `w: [batch, w_dim]`.
    pub fn forward(&self, points: Tensor<3>, w: Tensor<2>, wants: FieldWants) -> FieldOutput {
        self.forward_with(points, w, wants, ActivationKernels::FUSED)
    }

    /// [`Self::forward`] with the activation's kernels `kernels` (the fused ones or their
    /// plain references).
    ///
    /// The density's gradient comes from one reverse sweep through the density head and
    /// layers 1-4 after the forward pass: the head's weight is the cotangent of layer 4's
    /// output, each layer turns its output's cotangent `u` into its input's,
    /// `(u a'(z)) W_b^T` (the pullback, then the transposed per-sample weight), and the
    /// encoding's diagonal Jacobian turns the input's into `d raw / dx`. That is one extra
    /// product per layer where forward-mode tangents cost three, and written in tensor ops, so
    /// first-order autodiff differentiates the normals with it.
    pub fn forward_with(
        &self,
        points: Tensor<3>,
        w: Tensor<2>,
        wants: FieldWants,
        kernels: ActivationKernels,
    ) -> FieldOutput {
        let [b, p, _] = points.dims();
        let (sharpness, radius) = self.sphere_prior;
        // The prior's logit `s (r - |x|)` and its gradient `-s x / |x|`, `[b, p, 1]` and
        // `[b, p, 3]`.
        let prior = (sharpness != 0.0).then(|| {
            let norm = points.clone().square().sum_dim(2).add_scalar(1e-12).sqrt();
            let logit = norm.clone().neg().add_scalar(radius).mul_scalar(sharpness);
            let grad = (points.clone() / norm).mul_scalar(-sharpness);
            (logit, grad)
        });
        let flat = points.reshape([b * p, 3]);
        let d = self.encoding.output_dim();
        let (encoded, mut encoding_derivative) = if wants.normals {
            let (encoded, deriv) = self.encoding.forward_with_derivative(flat);
            (encoded, Some(deriv.reshape([b, p, d])))
        } else {
            (self.encoding.forward(flat), None)
        };
        let mut h = encoded.reshape([b, p, d]);
        let mut out = FieldOutput {
            sigma: Tensor::zeros([b, p], &h.device()),
            grad_sigma: None,
            normals: None,
            albedo: None,
            specular_weights: None,
            features: None,
        };
        // What the reverse sweep needs of layers 1-4: pre-activations, biases, weights.
        let mut sweep = Vec::new();
        for (i, layer) in self.layers.iter().enumerate() {
            let m = layer.modulation(w.clone());
            let y = layer.linear(h, &m);
            if wants.normals && i < self.density_layer {
                sweep.push((y.clone(), layer.bias.val(), m));
            }
            h = (kernels.activate)(y, layer.bias.val());
            if i + 1 != self.density_layer {
                continue;
            }
            let o = layer.d_output();
            let head = self.density_head.effective_weight(); // [1, o]
            let head_t = head
                .clone()
                .transpose()
                .reshape([1, o, 1])
                .expand([b, o, 1]);
            let mut raw = batched_matmul(h.clone(), head_t).reshape([b, p]);
            if let Some(bias) = self.density_head.effective_bias() {
                raw = raw + bias.reshape([1, 1]);
            }
            if let Some((logit, _)) = &prior {
                raw = raw + logit.clone().reshape([b, p]);
            }
            out.sigma = activation::softplus(raw.clone(), 1.0);
            if let Some(deriv) = encoding_derivative.take() {
                // The cotangent of layer 4's output is the head's weight at every point.
                let mut u = head.reshape([1, 1, o]).expand([b, p, o]);
                for (y, bias, m) in sweep.drain(..).rev() {
                    let v = (kernels.pullback)(u, y, bias);
                    u = batched_matmul(v, m.weight.swap_dims(1, 2));
                }
                // Feature c depends on coordinate c mod 3 alone.
                let mut g = (u * deriv)
                    .reshape([b, p, d / 3, 3])
                    .sum_dim(2)
                    .reshape([b, p, 3]);
                if let Some((_, grad)) = &prior {
                    g = g + grad.clone();
                }
                // d sigma / dx = sigmoid(raw) d raw / dx.
                let g = g * activation::sigmoid(raw).reshape([b, p, 1]);
                out.normals = Some(normals_from_gradient(g.clone()));
                out.grad_sigma = Some(g);
            }
            if !wants.appearance {
                return out;
            }
        }
        // The hidden layer's bias and activation in the fused kernel.
        let hidden = self.head_hidden.weight.dims()[0];
        let y = self
            .head_hidden
            .linear(h.clone().reshape([b * p, self.feature_dim()]))
            .reshape([b, p, hidden]);
        let bias = self
            .head_hidden
            .effective_bias()
            .unwrap_or_else(|| Tensor::zeros([hidden], &y.device()));
        let head = per_point(&self.head_out, (kernels.activate)(y, bias));
        let k = self.specular_lobes();
        out.albedo = Some(activation::sigmoid(head.clone().narrow(2, 0, 3)));
        out.specular_weights = Some(activation::softplus(head.narrow(2, 3, k), 1.0));
        out.features = Some(h);
        out
    }

    /// Number of scalar parameters.
    pub fn num_params(&self) -> usize {
        Module::num_params(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::to_f32_vec;
    use crate::test_support::{Reseed, normals};
    use burn::tensor::{DType, Distribution, TensorData};
    use volux_envmap::random::SplitMix64;

    fn small(frequencies: usize, device: &Device) -> Neiif {
        small_with_prior(frequencies, 0.0, device)
    }

    fn small_with_prior(frequencies: usize, sphere_prior: f64, device: &Device) -> Neiif {
        NeiifConfig::new()
            .with_w_dim(16)
            .with_width(32)
            .with_head_width(16)
            .with_frequencies(frequencies)
            .with_sphere_prior(sphere_prior)
            .init(device)
    }

    fn points(n: usize, seed: u64, device: &Device) -> Tensor<3> {
        let mut rng = SplitMix64::new(seed);
        let v: Vec<f32> = (0..3 * n)
            .map(|_| (rng.next_f64() * 1.6 - 0.8) as f32)
            .collect();
        Tensor::from_data(TensorData::new(v, [1, n, 3]), device)
    }

    /// The reverse sweep's `grad(sigma)` against central differences of the density on random
    /// weights. `h` and the tolerance are set by the highest octave: central differences of
    /// `sin(2^(F-1) pi x)` have a truncation error `~ (2^(F-1) pi h)^2 / 6`.
    fn check_gradient(frequencies: usize, sphere_prior: f64, h: f64, tol: f64) {
        let device = Device::flex();
        // Fixed weights and latent, so that the error measured here is the error of every run.
        let field = small_with_prior(frequencies, sphere_prior, &device)
            .map(&mut Reseed::new(21, DType::F32));
        let w = normals(&mut SplitMix64::new(22), 16);
        let w = Tensor::<1>::from_floats(
            w.iter().map(|v| *v as f32).collect::<Vec<_>>().as_slice(),
            &device,
        )
        .reshape([1, 16]);
        let n = 24;
        let pts = points(n, 7, &device);
        let got = field.forward(pts.clone(), w.clone(), FieldWants::ALL);
        let grad = to_f32_vec(got.grad_sigma.unwrap());
        let normals = to_f32_vec(got.normals.unwrap());
        let base = to_f32_vec(pts);
        let sigma_at = |delta: [f64; 3]| {
            let v: Vec<f32> = base
                .chunks(3)
                .flat_map(|p| (0..3).map(move |k| (f64::from(p[k]) + delta[k]) as f32))
                .collect();
            let pts = Tensor::<3>::from_data(TensorData::new(v, [1, n, 3]), &device);
            to_f32_vec(field.forward(pts, w.clone(), FieldWants::DENSITY).sigma)
        };
        let mut worst = 0.0f64;
        for j in 0..3 {
            let mut e = [0.0; 3];
            e[j] = h;
            let plus = sigma_at(e);
            e[j] = -h;
            let minus = sigma_at(e);
            for i in 0..n {
                let fd = (f64::from(plus[i]) - f64::from(minus[i])) / (2.0 * h);
                let g = f64::from(grad[3 * i + j]);
                let scale = (0..3)
                    .map(|k| f64::from(grad[3 * i + k]).powi(2))
                    .sum::<f64>()
                    .sqrt();
                worst = worst.max((g - fd).abs() / (scale + 1e-3));
            }
        }
        assert!(worst < tol, "F={frequencies}: worst relative error {worst}");
        for i in 0..n {
            let len: f32 = (0..3).map(|k| normals[3 * i + k].powi(2)).sum::<f32>();
            assert!((len - 1.0).abs() < 1e-4, "normal {i} has length^2 {len}");
            let dot: f32 = (0..3).map(|k| normals[3 * i + k] * grad[3 * i + k]).sum();
            assert!(dot < 0.0, "normals point against the density gradient");
        }
    }

    /// The second order: the gradient of a loss on `grad(sigma)` with respect to the latent
    /// `w` (which every layer's modulation sees, so the sweep's weights, pullbacks and biases
    /// all take part) against central differences of that loss, on fixed weights.
    #[test]
    fn a_loss_on_the_density_gradient_has_the_central_difference_gradient_in_w() {
        let device = Device::flex().autodiff();
        let field = small_with_prior(3, 10.0, &device).map(&mut Reseed::new(41, DType::F32));
        let n = 16;
        let pts = points(n, 9, &device);
        let r = normals(&mut SplitMix64::new(43), 3 * n);
        let r = Tensor::<1>::from_floats(
            r.iter().map(|v| *v as f32).collect::<Vec<_>>().as_slice(),
            &device,
        )
        .reshape([1, n, 3]);
        let w0 = normals(&mut SplitMix64::new(42), 16);
        let loss_at = |w: &[f64]| {
            let w = Tensor::<1>::from_floats(
                w.iter().map(|v| *v as f32).collect::<Vec<_>>().as_slice(),
                &device,
            )
            .reshape([1, 16])
            .require_grad();
            let out = field.forward(pts.clone(), w.clone(), FieldWants::ALL);
            let loss = (out.grad_sigma.unwrap() * r.clone()).sum();
            (w, loss)
        };
        let (w, loss) = loss_at(&w0);
        let grads = loss.backward();
        let got = to_f32_vec(w.grad(&grads).unwrap());
        let h = 1e-2;
        let scale = got.iter().fold(0.0f32, |m, v| m.max(v.abs())) as f64;
        for k in 0..16 {
            let at = |d: f64| {
                let mut w = w0.clone();
                w[k] += d;
                f64::from(loss_at(&w).1.into_scalar::<f32>())
            };
            let fd = (at(h) - at(-h)) / (2.0 * h);
            let g = f64::from(got[k]);
            assert!(
                (g - fd).abs() < 2e-2 * scale,
                "d loss / d w[{k}]: {g} vs central difference {fd} (scale {scale})"
            );
        }
        assert!(scale > 0.0, "the loss does not depend on w");
    }

    #[test]
    fn activation_matches_softplus_and_sigmoid_in_f64() {
        let device = Device::flex();
        let xs: Vec<f32> = (-400..=400).map(|i| i as f32 * 0.1).collect();
        let x = Tensor::<1>::from_floats(xs.as_slice(), &device);
        let (v, d) = smooth_lrelu_parts(x, true);
        let (v, d) = (to_f32_vec(v), to_f32_vec(d.unwrap()));
        for (i, x) in xs.iter().map(|x| f64::from(*x)).enumerate() {
            let softplus = x.max(0.0) + (-x.abs()).exp().ln_1p();
            let sigmoid = 1.0 / (1.0 + (-x).exp());
            let want_v = SMOOTH_GAIN * (0.2 * x + 0.8 * softplus);
            let want_d = SMOOTH_GAIN * (0.2 + 0.8 * sigmoid);
            assert!(
                (f64::from(v[i]) - want_v).abs() < 1e-5 * (1.0 + want_v.abs()),
                "x={x}"
            );
            assert!((f64::from(d[i]) - want_d).abs() < 1e-6, "x={x}");
        }
    }

    #[test]
    fn density_gradient_matches_central_differences_at_low_frequencies() {
        check_gradient(4, 0.0, 1e-3, 2e-3);
        check_gradient(4, 10.0, 1e-3, 2e-3);
    }

    #[test]
    fn density_gradient_matches_central_differences_at_the_papers_ten_octaves() {
        // With fixed weights the worst relative error is 4.1e-3 at h = 5e-5 (f32 rounding of
        // the sigma differences and the truncation of sin(512 pi x) balance there; 1e-4 gives
        // 1.6e-2, 2e-4 gives 6e-2). A wrong sweep is off by O(1).
        check_gradient(10, 0.0, 5e-5, 1e-2);
    }

    #[test]
    fn outputs_have_their_shapes_and_ranges_and_skip_what_is_not_wanted() {
        let device = Device::flex();
        let field = small(10, &device);
        let w = Tensor::<2>::random([2, 16], Distribution::Normal(0.0, 1.0), &device);
        let pts = Tensor::cat(vec![points(9, 1, &device), points(9, 2, &device)], 0);
        let all = field.forward(pts.clone(), w.clone(), FieldWants::ALL);
        assert_eq!(all.sigma.dims(), [2, 9]);
        assert_eq!(all.normals.as_ref().unwrap().dims(), [2, 9, 3]);
        assert_eq!(all.features.as_ref().unwrap().dims(), [2, 9, 32]);
        let albedo = to_f32_vec(all.albedo.unwrap());
        assert!(albedo.iter().all(|a| (0.0..=1.0).contains(a)));
        let spec = to_f32_vec(all.specular_weights.unwrap());
        assert_eq!(spec.len(), 2 * 9 * 4);
        assert!(spec.iter().all(|s| *s >= 0.0));
        assert!(to_f32_vec(all.sigma.clone()).iter().all(|s| *s >= 0.0));
        let density = field.forward(pts.clone(), w.clone(), FieldWants::DENSITY);
        assert!(density.normals.is_none() && density.albedo.is_none());
        let diff: f32 = (density.sigma - all.sigma).abs().max().into_scalar();
        assert!(diff < 1e-5, "density-only query differs by {diff}");
        let no_normals = field.forward(
            pts,
            w,
            FieldWants {
                normals: false,
                appearance: true,
            },
        );
        assert!(no_normals.normals.is_none() && no_normals.features.is_some());
    }

    #[test]
    fn fused_activation_gives_the_reference_outputs_and_gradients() {
        let device = Device::flex().autodiff();
        let field = small_with_prior(4, 10.0, &device).map(&mut Reseed::new(31, DType::F32));
        let w = Tensor::<2>::random([2, 16], Distribution::Normal(0.0, 1.0), &device);
        let pts = Tensor::cat(vec![points(300, 4, &device), points(300, 5, &device)], 0);
        let run = |kernels: ActivationKernels| {
            let out = field.forward_with(pts.clone(), w.clone(), FieldWants::ALL, kernels);
            let parts = [
                out.grad_sigma.unwrap(),
                out.normals.unwrap(),
                out.albedo.unwrap(),
                out.specular_weights.unwrap(),
                out.features.unwrap(),
            ];
            let mut loss = out.sigma.clone().sum();
            let mut values = to_f32_vec(out.sigma);
            for (k, p) in parts.into_iter().enumerate() {
                values.extend(to_f32_vec(p.clone()));
                loss = loss + p.sum().mul_scalar(k as f64 + 1.0);
            }
            let grads = loss.backward();
            let mut g = Vec::new();
            for layer in &field.layers {
                g.extend(to_f32_vec(layer.weight.val().grad(&grads).unwrap()));
                g.extend(to_f32_vec(layer.bias.val().grad(&grads).unwrap()));
                g.extend(to_f32_vec(layer.affine.weight.val().grad(&grads).unwrap()));
            }
            g.extend(to_f32_vec(
                field.head_hidden.weight.val().grad(&grads).unwrap(),
            ));
            (values, g)
        };
        let (fused, reference) = (
            run(ActivationKernels::FUSED),
            run(ActivationKernels::REFERENCE),
        );
        for (what, got, want, tol) in [
            ("outputs", &fused.0, &reference.0, 1e-5),
            ("parameter gradients", &fused.1, &reference.1, 1e-4),
        ] {
            let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            let worst = got
                .iter()
                .zip(want.iter())
                .fold(0.0f32, |m, (g, w)| m.max((g - w).abs()));
            assert!(
                worst <= tol * scale,
                "{what}: worst difference {worst}, scale {scale}"
            );
        }
    }

    #[test]
    fn a_loss_on_normals_reaches_the_first_layer_and_the_mapping_input() {
        let device = Device::flex().autodiff();
        let field = small(6, &device);
        let w =
            Tensor::<2>::random([1, 16], Distribution::Normal(0.0, 1.0), &device).require_grad();
        let out = field.forward(points(16, 3, &device), w.clone(), FieldWants::ALL);
        let loss = out.normals.unwrap().narrow(2, 2, 1).sum();
        let grads = loss.backward();
        let g1 = to_f32_vec(field.layers[0].weight.val().grad(&grads).unwrap());
        assert!(g1.iter().all(|v| v.is_finite()));
        assert!(
            g1.iter().any(|v| v.abs() > 0.0),
            "no gradient reached layer 1"
        );
        let gw = to_f32_vec(w.grad(&grads).unwrap());
        assert!(gw.iter().any(|v| v.abs() > 0.0));
        // Layers 5-6 do not shape the density, so a loss on normals leaves them untouched.
        assert!(
            field.layers[5]
                .weight
                .val()
                .grad(&grads)
                .is_none_or(|g| { to_f32_vec(g).iter().all(|v| *v == 0.0) })
        );
    }
}
