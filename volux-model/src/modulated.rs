//! Modulated fully connected layers (StyleGAN2's modulation / demodulation; paper appendix B):
//! each layer turns `w` into a style `s = A w + 1` with its own affine `A`, scales its input
//! features by `s`, and divides each output by the norm of its modulated weight row,
//! `y_o = sum_i W_oi s_i x_i / sqrt(sum_i (W_oi s_i)^2 + 1e-8) + b_o`.
//!
//! The NeIIF's layers are these, applied per 3D point; the upsampler's "1x1 modulated
//! convolutions" are the same layer applied per pixel (a 1x1 convolution is a fully connected
//! layer over channels), so one implementation serves both. Each sample's modulated,
//! demodulated weight is built once (`W_b = diag(s_b) W^T diag(d_b)`, with the demodulation
//! `d = rsqrt(s^2 (W^2)^T)`) and applied by a batched matmul, StyleGAN2's grouped convolution
//! without the grouping.

use burn::config::Config;
use burn::module::{Module, Param};
use burn::tensor::{Device, Distribution, Tensor};

use crate::batched_matmul::batched_matmul;
use crate::equalized::{EqualizedLinear, EqualizedLinearConfig};

/// Added under the square root of the demodulation (StyleGAN2's value).
pub(crate) const DEMOD_EPS: f64 = 1e-8;

/// Configuration of a [`ModulatedLinear`] layer.
#[derive(Config, Debug)]
pub struct ModulatedLinearConfig {
    /// Dimension of `w`.
    pub w_dim: usize,
    /// Input features.
    pub d_input: usize,
    /// Output features.
    pub d_output: usize,
    /// Whether outputs are demodulated (StyleGAN2 does, except in its ToRGB layers).
    #[config(default = true)]
    pub demodulate: bool,
}

/// A fully connected layer modulated by a per-sample style.
#[derive(Module, Debug)]
pub struct ModulatedLinear {
    /// `w -> s`, bias initialised to 1 so that styles start near 1.
    pub affine: EqualizedLinear,
    /// Stored weight `[d_output, d_input]`, `N(0, 1)`, applied with gain `1 / sqrt(d_input)`.
    pub weight: Param<Tensor<2>>,
    /// Bias `[d_output]`, initialised to 0.
    pub bias: Param<Tensor<1>>,
    pub weight_gain: f64,
    pub demodulate: bool,
}

/// One layer's weight for each sample of a batch: the styles `s` and demodulation `d` folded
/// in, `diag(s_b) W^T diag(d_b)`, `[batch, d_input, d_output]`.
#[derive(Clone, Debug)]
pub struct Modulation {
    pub weight: Tensor<3>,
}

impl ModulatedLinearConfig {
    /// A layer with freshly initialised parameters on `device`.
    pub fn init(&self, device: &Device) -> ModulatedLinear {
        ModulatedLinear {
            affine: EqualizedLinearConfig::new(self.w_dim, self.d_input)
                .with_bias_init(1.0)
                .init(device),
            weight: Param::from_tensor(Tensor::random(
                [self.d_output, self.d_input],
                Distribution::Normal(0.0, 1.0),
                device,
            )),
            bias: Param::from_tensor(Tensor::zeros([self.d_output], device)),
            weight_gain: 1.0 / (self.d_input as f64).sqrt(),
            demodulate: self.demodulate,
        }
    }
}

impl ModulatedLinear {
    /// Output features.
    pub fn d_output(&self) -> usize {
        self.weight.dims()[0]
    }

    /// The weight the layer applies before modulation, `[d_output, d_input]`.
    pub fn effective_weight(&self) -> Tensor<2> {
        self.weight.val().mul_scalar(self.weight_gain)
    }

    /// The folded per-sample weight for `w: [batch, w_dim]`.
    pub fn modulation(&self, w: Tensor<2>) -> Modulation {
        let styles = self.affine.forward(w);
        let [b, i] = styles.dims();
        let o = self.d_output();
        let transposed = self.effective_weight().transpose(); // [in, out]
        let weight = transposed.clone().reshape([1, i, o]) * styles.clone().reshape([b, i, 1]);
        let weight = if self.demodulate {
            let demod = styles
                .powi_scalar(2)
                .matmul(transposed.powi_scalar(2))
                .add_scalar(DEMOD_EPS)
                .sqrt()
                .recip();
            weight * demod.reshape([b, 1, o])
        } else {
            weight
        };
        Modulation { weight }
    }

    /// The linear part, without bias: `[batch, points, d_input] -> [batch, points, d_output]`,
    /// one batched matmul with the folded weight.
    pub fn linear(&self, x: Tensor<3>, m: &Modulation) -> Tensor<3> {
        batched_matmul(x, m.weight.clone())
    }

    /// Adds the bias to the output of [`Self::linear`].
    pub fn add_bias(&self, y: Tensor<3>) -> Tensor<3> {
        let o = self.d_output();
        y + self.bias.val().reshape([1, 1, o])
    }

    /// `x: [batch, points, d_input]`, `w: [batch, w_dim]` -> `[batch, points, d_output]`.
    pub fn forward(&self, x: Tensor<3>, w: Tensor<2>) -> Tensor<3> {
        let m = self.modulation(w);
        self.add_bias(self.linear(x, &m))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::to_f32_vec;

    /// The plain reference: per-sample weights built explicitly, in f64.
    fn reference(layer: &ModulatedLinear, x: &[f32], w: &[f32], dims: [usize; 3]) -> Vec<f64> {
        let [b, p, i] = dims;
        let o = layer.d_output();
        let device = layer.weight.device();
        let w_dim = w.len() / b;
        let styles = to_f32_vec(
            layer
                .affine
                .forward(Tensor::<1>::from_floats(w, &device).reshape([b, w_dim])),
        );
        let weight = to_f32_vec(layer.effective_weight());
        let bias = to_f32_vec(layer.bias.val());
        let mut out = Vec::with_capacity(b * p * o);
        for bi in 0..b {
            let wmod: Vec<f64> = (0..o * i)
                .map(|k| f64::from(weight[k]) * f64::from(styles[bi * i + k % i]))
                .collect();
            for pi in 0..p {
                for oi in 0..o {
                    let row = &wmod[oi * i..(oi + 1) * i];
                    let norm = if layer.demodulate {
                        (row.iter().map(|v| v * v).sum::<f64>() + DEMOD_EPS).sqrt()
                    } else {
                        1.0
                    };
                    let dot: f64 = row
                        .iter()
                        .enumerate()
                        .map(|(k, v)| v * f64::from(x[(bi * p + pi) * i + k]))
                        .sum();
                    out.push(dot / norm + f64::from(bias[oi]));
                }
            }
        }
        out
    }

    #[test]
    fn matches_per_sample_weights_with_and_without_demodulation() {
        let device = Device::flex();
        let (b, p, i, o, w_dim) = (3, 5, 7, 4, 6);
        for demodulate in [true, false] {
            let layer = ModulatedLinearConfig::new(w_dim, i, o)
                .with_demodulate(demodulate)
                .init(&device);
            let layer = ModulatedLinear {
                bias: Param::from_tensor(Tensor::random(
                    [o],
                    Distribution::Normal(0.0, 1.0),
                    &device,
                )),
                ..layer
            };
            let x = to_f32_vec(Tensor::<3>::random(
                [b, p, i],
                Distribution::Normal(0.0, 1.0),
                &device,
            ));
            let w = to_f32_vec(Tensor::<2>::random(
                [b, w_dim],
                Distribution::Normal(0.0, 1.0),
                &device,
            ));
            let got = to_f32_vec(layer.forward(
                Tensor::<1>::from_floats(x.as_slice(), &device).reshape([b, p, i]),
                Tensor::<1>::from_floats(w.as_slice(), &device).reshape([b, w_dim]),
            ));
            let want = reference(&layer, &x, &w, [b, p, i]);
            for (g, r) in got.iter().zip(&want) {
                assert!(
                    (f64::from(*g) - r).abs() < 1e-4 * (1.0 + r.abs()),
                    "{g} vs {r}"
                );
            }
        }
    }

    #[test]
    fn demodulation_gives_unit_output_variance_for_unit_inputs() {
        let device = Device::flex();
        let layer = ModulatedLinearConfig::new(32, 256, 256).init(&device);
        let x = Tensor::<3>::random([2, 512, 256], Distribution::Normal(0.0, 1.0), &device);
        let w = Tensor::<2>::random([2, 32], Distribution::Normal(0.0, 3.0), &device);
        let ms: f32 = layer.forward(x, w).powi_scalar(2).mean().into_scalar();
        assert!((ms - 1.0).abs() < 0.1, "mean square {ms}");
    }
}
