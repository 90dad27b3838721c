//! Equalized-learning-rate layers (StyleGAN / StyleGAN2): parameters are stored at unit scale
//! and multiplied at run time by `lr_multiplier / sqrt(fan_in)` (weights) and `lr_multiplier`
//! (biases). Adam's step is then the same for every layer in the effective weights' own scale,
//! and a layer with `lr_multiplier = 0.01` (the mapping network) learns 100x slower. The
//! paper's learning rates (0.0022 / 0.0025) assume this parameterisation.

use burn::config::Config;
use burn::module::{Module, Param};
use burn::tensor::module::conv_transpose2d;
use burn::tensor::ops::ConvTransposeOptions;
use burn::tensor::{Device, Distribution, Tensor};

use crate::batched_matmul::batched_matmul;
use crate::bias_act;
use crate::convolution::{self, ConvGeometry};

/// Configuration of an [`EqualizedLinear`] layer.
#[derive(Config, Debug)]
pub struct EqualizedLinearConfig {
    /// Input features (the fan-in).
    pub d_input: usize,
    /// Output features.
    pub d_output: usize,
    /// Learning-rate multiplier (StyleGAN2's `lr_multiplier`; 0.01 in the mapping network).
    #[config(default = 1.0)]
    pub lr_multiplier: f64,
    /// Initial value of the effective bias.
    #[config(default = 0.0)]
    pub bias_init: f64,
    /// Whether the layer has a bias.
    #[config(default = true)]
    pub bias: bool,
}

/// A fully connected layer with equalized learning rate: `y = x (g W)^T + b_mul b`.
#[derive(Module, Debug)]
pub struct EqualizedLinear {
    /// Stored weight `[d_output, d_input]`, initialised `N(0, 1 / lr_multiplier^2)`.
    pub weight: Param<Tensor<2>>,
    /// Stored bias `[d_output]`, initialised `bias_init / lr_multiplier`.
    pub bias: Option<Param<Tensor<1>>>,
    /// `lr_multiplier / sqrt(d_input)`.
    pub weight_gain: f64,
    /// `lr_multiplier`.
    pub bias_gain: f64,
}

impl EqualizedLinearConfig {
    /// A layer with freshly initialised parameters on `device`.
    pub fn init(&self, device: &Device) -> EqualizedLinear {
        let weight = Tensor::<2>::random(
            [self.d_output, self.d_input],
            Distribution::Normal(0.0, 1.0 / self.lr_multiplier),
            device,
        );
        let bias = self.bias.then(|| {
            Param::from_tensor(
                Tensor::<1>::ones([self.d_output], device)
                    .mul_scalar(self.bias_init / self.lr_multiplier),
            )
        });
        EqualizedLinear {
            weight: Param::from_tensor(weight),
            bias,
            weight_gain: self.lr_multiplier / (self.d_input as f64).sqrt(),
            bias_gain: self.lr_multiplier,
        }
    }
}

impl EqualizedLinear {
    /// The weight the layer applies, `[d_output, d_input]`.
    pub fn effective_weight(&self) -> Tensor<2> {
        self.weight.val().mul_scalar(self.weight_gain)
    }

    /// The bias the layer adds, `[d_output]`, if any.
    pub fn effective_bias(&self) -> Option<Tensor<1>> {
        self.bias
            .as_ref()
            .map(|b| b.val().mul_scalar(self.bias_gain))
    }

    /// `[batch, d_input] -> [batch, d_output]`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let y = self.linear(x);
        match self.effective_bias() {
            Some(b) => y + b.unsqueeze_dim(0),
            None => y,
        }
    }

    /// [`Self::forward`] followed by StyleGAN2's leaky ReLU with `gain`, the bias, activation
    /// and gain as one fused operation ([`bias_act::bias_lrelu`]).
    pub fn forward_lrelu(&self, x: Tensor<2>, gain: f64) -> Tensor<2> {
        bias_act::bias_lrelu(self.linear(x), self.effective_bias(), gain)
    }

    /// `x W^T`, without bias: one [`batched_matmul`] of a single batch element, reading
    /// `W` transposed through its strides.
    pub fn linear(&self, x: Tensor<2>) -> Tensor<2> {
        let [rows, _] = x.dims();
        let w_t = self.effective_weight().transpose().unsqueeze_dim(0);
        let out = w_t.dims()[2];
        batched_matmul(x.unsqueeze_dim(0), w_t).reshape([rows, out])
    }
}

/// Configuration of an [`EqualizedConv2d`] layer.
#[derive(Config, Debug)]
pub struct EqualizedConv2dConfig {
    /// Input channels.
    pub channels_in: usize,
    /// Output channels.
    pub channels_out: usize,
    /// Kernel height and width (odd for [`EqualizedConv2d::forward`]'s 'same' padding).
    pub kernel_size: usize,
    /// Learning-rate multiplier (1 everywhere in the discriminators).
    #[config(default = 1.0)]
    pub lr_multiplier: f64,
    /// Initial value of the effective bias.
    #[config(default = 0.0)]
    pub bias_init: f64,
    /// Whether the layer has a bias.
    #[config(default = true)]
    pub bias: bool,
}

/// A 2D convolution with equalized learning rate: `y = conv(x, g W) + b_mul b`, with
/// `g = lr_multiplier / sqrt(channels_in * k * k)` (StyleGAN2's `Conv2dLayer`).
#[derive(Module, Debug)]
pub struct EqualizedConv2d {
    /// Stored weight `[channels_out, channels_in, k, k]`, initialised `N(0, 1 / lr_multiplier^2)`.
    pub weight: Param<Tensor<4>>,
    /// Stored bias `[channels_out]`, initialised `bias_init / lr_multiplier`.
    pub bias: Option<Param<Tensor<1>>>,
    /// `lr_multiplier / sqrt(channels_in * k * k)`.
    pub weight_gain: f64,
    /// `lr_multiplier`.
    pub bias_gain: f64,
}

impl EqualizedConv2dConfig {
    /// A layer with freshly initialised parameters on `device`.
    pub fn init(&self, device: &Device) -> EqualizedConv2d {
        let k = self.kernel_size;
        let weight = Tensor::<4>::random(
            [self.channels_out, self.channels_in, k, k],
            Distribution::Normal(0.0, 1.0 / self.lr_multiplier),
            device,
        );
        let bias = self.bias.then(|| {
            Param::from_tensor(
                Tensor::<1>::ones([self.channels_out], device)
                    .mul_scalar(self.bias_init / self.lr_multiplier),
            )
        });
        EqualizedConv2d {
            weight: Param::from_tensor(weight),
            bias,
            weight_gain: self.lr_multiplier / ((self.channels_in * k * k) as f64).sqrt(),
            bias_gain: self.lr_multiplier,
        }
    }
}

impl EqualizedConv2d {
    /// The weight the layer applies, `[channels_out, channels_in, k, k]`.
    pub fn effective_weight(&self) -> Tensor<4> {
        self.weight.val().mul_scalar(self.weight_gain)
    }

    /// The bias the layer adds, `[channels_out]`, if any.
    pub fn effective_bias(&self) -> Option<Tensor<1>> {
        self.bias
            .as_ref()
            .map(|b| b.val().mul_scalar(self.bias_gain))
    }

    /// Kernel height and width.
    pub fn kernel_size(&self) -> usize {
        self.weight.dims()[3]
    }

    /// Stride 1 with 'same' padding (`k / 2` on every side):
    /// `[batch, channels_in, h, w] -> [batch, channels_out, h, w]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let k = self.kernel_size();
        assert!(
            !k.is_multiple_of(2),
            "'same' padding needs an odd kernel, got {k}"
        );
        self.forward_strided(x, 1, k / 2)
    }

    /// The convolution with any stride and symmetric zero padding:
    /// `[batch, channels_in, h, w] -> [batch, channels_out, (h + 2 padding - k) / stride + 1, ..]`.
    pub fn forward_strided(&self, x: Tensor<4>, stride: usize, padding: usize) -> Tensor<4> {
        self.forward_scaled(x, stride, padding, 1.0)
    }

    /// [`Self::forward_strided`] times `gain`, the gain applied to the (small) weights and
    /// bias rather than to the output.
    pub fn forward_scaled(
        &self,
        x: Tensor<4>,
        stride: usize,
        padding: usize,
        gain: f64,
    ) -> Tensor<4> {
        let y = self.convolve(x, stride, padding, gain);
        match self.effective_bias() {
            Some(b) => {
                let o = b.dims()[0];
                y + scaled(b, gain).reshape([1, o, 1, 1])
            }
            None => y,
        }
    }

    /// [`Self::forward`] ('same' padding) followed by StyleGAN2's leaky ReLU with `gain`.
    pub fn forward_lrelu(&self, x: Tensor<4>, gain: f64) -> Tensor<4> {
        let k = self.kernel_size();
        self.forward_strided_lrelu(x, 1, k / 2, gain)
    }

    /// [`Self::forward_strided`] followed by StyleGAN2's leaky ReLU with `gain`, the bias,
    /// activation and gain as one fused operation ([`bias_act::bias_lrelu`]).
    pub fn forward_strided_lrelu(
        &self,
        x: Tensor<4>,
        stride: usize,
        padding: usize,
        gain: f64,
    ) -> Tensor<4> {
        let y = self.convolve(x, stride, padding, 1.0);
        bias_act::bias_lrelu(y, self.effective_bias(), gain)
    }

    /// The linear part with the weights times `gain`, without bias.
    fn convolve(&self, x: Tensor<4>, stride: usize, padding: usize, gain: f64) -> Tensor<4> {
        convolution::conv2d(
            x,
            self.scaled_weight(gain),
            ConvGeometry::new(stride, padding),
        )
    }

    /// The effective weight times `gain` (no operation for a gain of 1).
    fn scaled_weight(&self, gain: f64) -> Tensor<4> {
        scaled(self.effective_weight(), gain)
    }

    /// The adjoint (transpose) of the linear part of [`Self::forward_strided`] with the same
    /// `stride` and `padding`: maps a gradient `[batch, channels_out, h', w']` with respect to
    /// the output back to one with respect to an input of spatial size `input_hw`,
    /// `[batch, channels_in, input_hw[0], input_hw[1]]`: [`convolution::conv2d_adjoint`] with the
    /// same weights, so it is differentiable in the weights.
    pub fn adjoint(
        &self,
        y: Tensor<4>,
        stride: usize,
        padding: usize,
        input_hw: [usize; 2],
    ) -> Tensor<4> {
        self.adjoint_scaled(y, stride, padding, input_hw, 1.0)
    }

    /// The adjoint of the linear part of [`Self::forward_scaled`] with `gain`.
    pub fn adjoint_scaled(
        &self,
        y: Tensor<4>,
        stride: usize,
        padding: usize,
        input_hw: [usize; 2],
        gain: f64,
    ) -> Tensor<4> {
        convolution::conv2d_adjoint(
            y,
            self.scaled_weight(gain),
            ConvGeometry::new(stride, padding),
            input_hw,
        )
    }
}

/// `t gain`, or `t` itself for a gain of exactly 1.
fn scaled<const D: usize>(t: Tensor<D>, gain: f64) -> Tensor<D> {
    if gain == 1.0 { t } else { t.mul_scalar(gain) }
}

/// `conv_transpose2d` whose output has spatial size `out_hw` (the output padding is chosen to
/// give it); `weight` is `[channels_in_of_y, channels_out / groups, k, k]`.
pub(crate) fn conv_transpose_to(
    y: Tensor<4>,
    weight: Tensor<4>,
    stride: usize,
    padding: usize,
    groups: usize,
    out_hw: [usize; 2],
) -> Tensor<4> {
    let [_, _, hy, wy] = y.dims();
    let [_, _, kh, kw] = weight.dims();
    let pad_out = |n_in: usize, k: usize, n_out: usize| {
        let base = (n_in - 1) * stride + k - 2 * padding;
        assert!(
            n_out >= base && n_out - base < stride.max(1),
            "no output padding turns {n_in} into {n_out} (stride {stride}, padding {padding}, kernel {k})"
        );
        n_out - base
    };
    let options = ConvTransposeOptions::new(
        [stride, stride],
        [padding, padding],
        [pad_out(hy, kh, out_hw[0]), pad_out(wy, kw, out_hw[1])],
        [1, 1],
        groups,
    );
    conv_transpose2d(y, weight, None, options)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::to_f32_vec;
    use crate::test_support::conv2d_f64;
    use burn::tensor::TensorData;

    #[test]
    fn forward_applies_the_runtime_gains() {
        let device = Device::flex();
        let layer = EqualizedLinearConfig::new(4, 3)
            .with_lr_multiplier(0.5)
            .with_bias_init(1.0)
            .init(&device);
        let x = Tensor::<2>::from_data(
            TensorData::new(vec![0.5f32, -1.0, 2.0, 0.25], [1, 4]),
            &device,
        );
        let y = to_f32_vec(layer.forward(x));
        let w = to_f32_vec(layer.weight.val());
        let g = 0.5 / 2.0;
        for (o, yo) in y.iter().enumerate() {
            let want: f32 = [0.5f32, -1.0, 2.0, 0.25]
                .iter()
                .enumerate()
                .map(|(i, xi)| xi * w[o * 4 + i] * g)
                .sum::<f32>()
                + 1.0;
            assert!((yo - want).abs() < 1e-5, "{yo} vs {want}");
        }
    }

    #[test]
    fn effective_weights_have_unit_fan_in_variance_whatever_the_multiplier() {
        let device = Device::flex();
        for lr in [1.0, 0.01] {
            let layer = EqualizedLinearConfig::new(256, 256)
                .with_lr_multiplier(lr)
                .init(&device);
            let w = to_f32_vec(layer.effective_weight());
            let var = w.iter().map(|v| f64::from(*v).powi(2)).sum::<f64>() / w.len() as f64;
            assert!(
                (var * 256.0 - 1.0).abs() < 0.05,
                "lr {lr}: fan-in variance {}",
                var * 256.0
            );
        }
    }

    #[test]
    fn gradient_of_the_stored_weight_is_scaled_by_the_gain() {
        // d loss / d stored = gain * d loss / d effective: a multiplier of 0.01 makes the
        // stored parameters (what Adam updates) move 100x slower in effective terms.
        let device = Device::flex().autodiff();
        let layer = EqualizedLinearConfig::new(3, 2)
            .with_lr_multiplier(0.01)
            .init(&device);
        let x = Tensor::<2>::from_data(TensorData::new(vec![1.0f32, 2.0, -1.0], [1, 3]), &device);
        let grads = layer.forward(x).sum().backward();
        let g = to_f32_vec(layer.weight.val().grad(&grads).unwrap());
        let gain = 0.01 / 3f32.sqrt();
        for o in 0..2 {
            for (i, xi) in [1.0f32, 2.0, -1.0].iter().enumerate() {
                assert!((g[o * 3 + i] - gain * xi).abs() < 1e-7, "{g:?}");
            }
        }
        let gb = to_f32_vec(layer.bias.as_ref().unwrap().val().grad(&grads).unwrap());
        assert!(gb.iter().all(|v| (v - 0.01).abs() < 1e-7), "{gb:?}");
    }

    #[test]
    fn conv_matches_an_f64_loop_with_gain_and_bias() {
        let device = Device::flex();
        let layer = EqualizedConv2dConfig::new(3, 4, 3)
            .with_bias_init(0.5)
            .init(&device);
        let shape = [2, 3, 7, 6];
        let x = Tensor::<4>::random(shape, Distribution::Normal(0.0, 1.0), &device);
        let xv: Vec<f64> = to_f32_vec(x.clone()).into_iter().map(f64::from).collect();
        let wv: Vec<f64> = to_f32_vec(layer.effective_weight())
            .into_iter()
            .map(f64::from)
            .collect();
        for (stride, pad) in [(1, 1), (2, 0), (2, 1)] {
            let y = to_f32_vec(layer.forward_strided(x.clone(), stride, pad));
            let (want, _) = conv2d_f64(&xv, shape, &wv, [4, 3], stride, pad);
            assert_eq!(y.len(), want.len());
            for (a, b) in y.iter().zip(&want) {
                assert!(
                    (f64::from(*a) - (b + 0.5)).abs() < 1e-4,
                    "{a} vs {}",
                    b + 0.5
                );
            }
        }
        assert_eq!(layer.forward(x).dims(), [2, 4, 7, 6]);
        // The gain is 1 / sqrt(fan_in) with fan_in = 3 * 3 * 3.
        assert!((layer.weight_gain - 1.0 / 27f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn conv_adjoint_is_the_transpose() {
        // <A x, y> = <x, A^T y> for stride 1 and 2, with even and odd input sizes.
        let device = Device::flex();
        let layer = EqualizedConv2dConfig::new(3, 5, 3).init(&device);
        for (stride, pad, hw) in [
            (1, 1, [6, 5]),
            (2, 0, [9, 9]),
            (2, 0, [8, 7]),
            (2, 1, [6, 6]),
        ] {
            let x = Tensor::<4>::random(
                [2, 3, hw[0], hw[1]],
                Distribution::Normal(0.0, 1.0),
                &device,
            );
            let ax = layer.forward_strided(x.clone(), stride, pad)
                - layer.effective_bias().unwrap().reshape([1, 5, 1, 1]);
            let y = Tensor::<4>::random(ax.dims(), Distribution::Normal(0.0, 1.0), &device);
            let aty = layer.adjoint(y.clone(), stride, pad, hw);
            assert_eq!(aty.dims(), x.dims());
            let lhs: f32 = (ax * y).sum().into_scalar();
            let rhs: f32 = (x * aty).sum().into_scalar();
            assert!(
                (lhs - rhs).abs() < 1e-4 * lhs.abs().max(1.0),
                "stride {stride} pad {pad} {hw:?}: {lhs} vs {rhs}"
            );
        }
    }
}
