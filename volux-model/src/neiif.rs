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
use crate::template_planes::{TemplatePlanes, TemplatePlanesConfig};

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
    /// Whether each octave of the positional encoding turns the point by its own fixed
    /// rotation first (see [`crate::positional_encoding`]; the paper's is axis-aligned).
    #[config(default = false)]
    pub rotated_encoding: bool,
    /// Control points per side of a latent-independent tri-plane of features handed to the
    /// first layer beside the encoding (see [`crate::template_planes`]; not in the paper);
    /// 0: none.
    #[config(default = 0)]
    pub template_resolution: usize,
    /// Features of the tri-plane.
    #[config(default = 8)]
    pub template_channels: usize,
    /// Half the side of the square each plane covers (world units): the control points span
    /// `[-template_bound, template_bound]`, and a point outside is clamped onto the edge.
    #[config(default = 1.0)]
    pub template_bound: f64,
    /// Planes each latent weights and adds to the tri-plane (see
    /// [`crate::template_planes::PlaneBasis`]); 0: one tri-plane for every latent.
    #[config(default = 0)]
    pub template_basis: usize,
}

/// The field.
#[derive(Module, Debug)]
pub struct Neiif {
    pub encoding: PositionalEncoding,
    /// The tri-plane of features beside the encoding, if any.
    pub template: Option<TemplatePlanes>,
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
            .with_rotated(self.rotated_encoding)
            .init();
        let template = (self.template_resolution > 0).then(|| {
            TemplatePlanesConfig::new(self.template_resolution)
                .with_channels(self.template_channels)
                .with_bound(self.template_bound)
                .with_basis(self.template_basis)
                .with_w_dim(self.w_dim)
                .init(device)
        });
        let template_dim = template.as_ref().map_or(0, |t| t.channels);
        let layers = (0..self.layers)
            .map(|i| {
                let d_input = if i == 0 {
                    encoding.output_dim() + template_dim
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
            template,
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
        let template = self
            .template
            .as_ref()
            .map(|t| t.forward(flat.clone(), &w, wants.normals));
        let (encoded, mut encoding_derivative) = if wants.normals {
            let (encoded, deriv) = self.encoding.forward_with_derivative(flat);
            (encoded, Some(deriv.reshape([b, p, d])))
        } else {
            (self.encoding.forward(flat), None)
        };
        let (encoded, template_derivative) = match template {
            Some((features, derivative)) => (Tensor::cat(vec![encoded, features], 1), derivative),
            None => (encoded, None),
        };
        let input = encoded.dims()[1];
        let mut h = encoded.reshape([b, p, input]);
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
                let mut g = self.encoding.fold(u.clone().narrow(2, 0, d) * deriv);
                if let (Some(t), Some(derivative)) = (&self.template, &template_derivative) {
                    g = g + t.fold(u.narrow(2, d, t.channels), derivative);
                }
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
mod tests;
