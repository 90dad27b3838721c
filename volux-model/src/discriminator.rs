//! StyleGAN2's residual discriminator (paper section 3.4) with an explicit, differentiable
//! gradient with respect to its input, for the R1 penalty.
//!
//! One type serves every discriminator of the paper, parameterised by input channels and
//! resolution: D_A on albedo, D_G on normal maps, D_S on `[I_relit, D, S]` (9 channels), D_P on
//! relit images. The architecture is StyleGAN2-ADA's `resnet` discriminator
//! (`training/networks.py`), with equalized learning rate everywhere:
//!
//! - FromRGB: 1x1 convolution + leaky ReLU at the input resolution `R`.
//! - One block per resolution `r = R, R/2, .., 8`, from `channels(r)` to `channels(r/2)`:
//!   main path 3x3 conv + lrelu, then [`blur`] with padding 2 and a 3x3 stride-2 conv + lrelu
//!   (StyleGAN2's `conv2d_resample` with `down = 2`); skip path [`blur_downsample2`] and a 1x1
//!   conv without bias; output `(skip + main) / sqrt(2)`.
//! - Epilogue at 4x4: minibatch standard deviation ([`minibatch_std`]), 3x3 conv + lrelu,
//!   flatten, fully connected + lrelu, fully connected to one logit.
//!
//! Leaky ReLU has slope 0.2 and gain sqrt(2); `channels(r) = min(channel_base / r, channel_max)`.
//!
//! R1 (`gamma / 2 * E ||d logit / d x||^2` on reals) needs a gradient inside a loss, and Burn's
//! autodiff is first order. [`Discriminator::input_gradient`] therefore computes
//! `d(sum of logits) / d x` by a reverse sweep written with ordinary tensor ops (convolutions by
//! transposed convolutions with the same weights, leaky ReLU by its derivative mask
//! ([`crate::bias_act::lrelu_input_gradient`], read from the activation's output), blur and
//! downsampling by their adjoints, minibatch std by its exact derivative, fully connected layers
//! by the transposed matmul). First-order autodiff of [`r1_penalty`] with respect to the weights
//! is then the exact R1 gradient. The same sweep, started from any cotangent of the logits,
//! is the [`Pullback`] of a pass ([`Discriminator::forward_with_pullback`]): a training step
//! takes the generator's gradient through it from the pass whose logits train the
//! discriminator, so that the fakes are judged once.

use std::f64::consts::{FRAC_1_SQRT_2, SQRT_2};

use burn::config::Config;
use burn::module::Module;
use burn::tensor::{Device, Tensor};

use crate::bias_act::lrelu_input_gradient;
use crate::blur::{blur, blur_adjoint, blur_downsample2, blur_downsample2_adjoint};
use crate::equalized::{
    EqualizedConv2d, EqualizedConv2dConfig, EqualizedLinear, EqualizedLinearConfig,
};

/// Added to the group variance before the square root (StyleGAN2's value).
const MBSTD_EPSILON: f64 = 1e-8;

/// Configuration of a [`Discriminator`].
#[derive(Config, Debug)]
pub struct DiscriminatorConfig {
    /// Channels of the input image (3 for RGB, 9 for D_S's `[I_relit, D, S]`).
    pub in_channels: usize,
    /// Input height and width, a power of two, at least 8.
    pub resolution: usize,
    /// Feature channels at resolution `r` are `min(channel_base / r, channel_max)`
    /// (StyleGAN2's `cbase`).
    #[config(default = 32768)]
    pub channel_base: usize,
    /// Upper bound on feature channels (StyleGAN2's `cmax`).
    #[config(default = 512)]
    pub channel_max: usize,
    /// Minibatch std group size; the batch must be divisible by `min(mbstd_group, batch)`.
    #[config(default = 4)]
    pub mbstd_group: usize,
    /// Number of minibatch std features appended (the channels are split into this many groups).
    #[config(default = 1)]
    pub mbstd_channels: usize,
}

impl DiscriminatorConfig {
    /// A small discriminator for CPU runs and tests: `channel_base = 2048`, `channel_max = 128`
    /// (32 channels at 64x64, 128 from 16x16 down). 1.18M parameters at 64x64 with 3 input
    /// channels.
    pub fn small(in_channels: usize, resolution: usize) -> Self {
        Self::new(in_channels, resolution)
            .with_channel_base(2048)
            .with_channel_max(128)
    }

    /// StyleGAN2's discriminator (`channel_base = 32768`, `channel_max = 512`), e.g. at 128 or
    /// 256: 256 channels at 128x128, 512 from 64x64 down.
    pub fn stylegan2(in_channels: usize, resolution: usize) -> Self {
        Self::new(in_channels, resolution)
    }

    /// Feature channels at resolution `r`.
    pub fn channels_at(&self, r: usize) -> usize {
        (self.channel_base / r).clamp(1, self.channel_max)
    }

    /// A discriminator with freshly initialised parameters on `device`.
    pub fn init(&self, device: &Device) -> Discriminator {
        let r = self.resolution;
        assert!(
            r.is_power_of_two() && r >= 8,
            "resolution must be a power of two >= 8, got {r}"
        );
        assert!(self.mbstd_channels >= 1 && self.mbstd_group >= 1);
        let from_rgb =
            EqualizedConv2dConfig::new(self.in_channels, self.channels_at(r), 1).init(device);
        let mut blocks = Vec::new();
        let mut res = r;
        while res > 4 {
            let (cin, cout) = (self.channels_at(res), self.channels_at(res / 2));
            blocks.push(DiscriminatorBlock {
                conv0: EqualizedConv2dConfig::new(cin, cin, 3).init(device),
                conv1: EqualizedConv2dConfig::new(cin, cout, 3).init(device),
                skip: EqualizedConv2dConfig::new(cin, cout, 1)
                    .with_bias(false)
                    .init(device),
            });
            res /= 2;
        }
        let c4 = self.channels_at(4);
        assert!(
            c4.is_multiple_of(self.mbstd_channels),
            "{c4} channels at 4x4 do not split into {} minibatch std groups",
            self.mbstd_channels
        );
        Discriminator {
            from_rgb,
            blocks,
            conv: EqualizedConv2dConfig::new(c4 + self.mbstd_channels, c4, 3).init(device),
            fc: EqualizedLinearConfig::new(c4 * 16, c4).init(device),
            out: EqualizedLinearConfig::new(c4, 1).init(device),
            mbstd_group: self.mbstd_group,
            mbstd_channels: self.mbstd_channels,
        }
    }
}

/// One residual block: `[batch, c_in, r, r] -> [batch, c_out, r/2, r/2]`.
#[derive(Module, Debug)]
pub struct DiscriminatorBlock {
    /// 3x3, `c_in -> c_in`, stride 1.
    pub conv0: EqualizedConv2d,
    /// 3x3, `c_in -> c_out`, stride 2 after a blur with padding 2.
    pub conv1: EqualizedConv2d,
    /// 1x1, `c_in -> c_out`, no bias, after [`blur_downsample2`].
    pub skip: EqualizedConv2d,
}

/// StyleGAN2's residual discriminator; see the module documentation.
#[derive(Module, Debug)]
pub struct Discriminator {
    /// 1x1 convolution from the input channels to `channels(R)`.
    pub from_rgb: EqualizedConv2d,
    /// Residual blocks from resolution `R` down to 8 (each halves the size).
    pub blocks: Vec<DiscriminatorBlock>,
    /// Epilogue 3x3 convolution, `c4 + mbstd_channels -> c4`, at 4x4.
    pub conv: EqualizedConv2d,
    /// `c4 * 16 -> c4`.
    pub fc: EqualizedLinear,
    /// `c4 -> 1`.
    pub out: EqualizedLinear,
    /// Minibatch std group size.
    pub mbstd_group: usize,
    /// Minibatch std features.
    pub mbstd_channels: usize,
}

/// Outputs of one block's two activations, kept for the reverse sweep (their signs are the
/// activations' derivatives, [`crate::bias_act`]).
struct BlockTrace {
    input_hw: [usize; 2],
    h0: Tensor<4>,
    h1: Tensor<4>,
}

/// What the reverse sweep needs from the forward pass.
struct Trace {
    input_hw: [usize; 2],
    from_rgb_out: Tensor<4>,
    blocks: Vec<BlockTrace>,
    epilogue_in: Tensor<4>,
    conv_out: Tensor<4>,
    fc_out: Tensor<2>,
}

impl Trace {
    /// The same values cut from the autodiff graph.
    fn detached(self) -> Self {
        Self {
            input_hw: self.input_hw,
            from_rgb_out: self.from_rgb_out.detach(),
            blocks: self
                .blocks
                .into_iter()
                .map(|b| BlockTrace {
                    input_hw: b.input_hw,
                    h0: b.h0.detach(),
                    h1: b.h1.detach(),
                })
                .collect(),
            epilogue_in: self.epilogue_in.detach(),
            conv_out: self.conv_out.detach(),
            fc_out: self.fc_out.detach(),
        }
    }
}

/// A forward pass kept for one input gradient with any cotangent of the logits
/// ([`Discriminator::forward_with_pullback`]): the transposed Jacobian at the point the pass
/// went through, outside the autodiff graph.
pub struct Pullback {
    /// The discriminator with its weights frozen (the same values as the forward pass's).
    frozen: Discriminator,
    trace: Trace,
}

impl Pullback {
    /// `sum_b c_b d logit_b / d x` for the cotangent `c = cotangent`, `[batch, 1]`: the input
    /// gradient of any loss of the logits whose derivative is `c`, cross-sample terms of
    /// minibatch std included. Neither the weights nor the input are tracked: the result is
    /// a constant.
    pub fn input_gradient(self, cotangent: Tensor<2>) -> Tensor<4> {
        self.frozen.sweep(self.trace, cotangent.detach())
    }
}

impl DiscriminatorBlock {
    /// StyleGAN2's block: `y = (skip(x) + sqrt(2) lrelu(conv1(..))) / sqrt(2)`, the `1 / sqrt(2)`
    /// folded into the skip convolution's weights and the second activation's gain
    /// (`sqrt(2) / sqrt(2) = 1`), as StyleGAN2 passes `gain = sqrt(0.5)` to both.
    fn forward_traced(&self, x: Tensor<4>) -> (Tensor<4>, BlockTrace) {
        let [_, _, h, w] = x.dims();
        let skip = self
            .skip
            .forward_scaled(blur_downsample2(x.clone()), 1, 0, FRAC_1_SQRT_2);
        let h0 = self.conv0.forward_lrelu(x, SQRT_2);
        let h1 = self
            .conv1
            .forward_strided_lrelu(blur(h0.clone(), 2), 2, 0, 1.0);
        let y = skip + h1.clone();
        let trace = BlockTrace {
            input_hw: [h, w],
            h0,
            h1,
        };
        (y, trace)
    }

    /// The transpose of the block's Jacobian applied to `g` (gradient with respect to the
    /// output) at the point recorded in `trace`.
    fn input_gradient(&self, g: Tensor<4>, trace: BlockTrace) -> Tensor<4> {
        let [h, w] = trace.input_hw;
        let g_skip = blur_downsample2_adjoint(self.skip.adjoint_scaled(
            g.clone(),
            1,
            0,
            [h / 2, w / 2],
            FRAC_1_SQRT_2,
        ));
        let g_pre1 = lrelu_input_gradient(g, trace.h1, 1.0);
        let g_blurred = self.conv1.adjoint(g_pre1, 2, 0, [h + 1, w + 1]);
        let g_pre0 = lrelu_input_gradient(blur_adjoint(g_blurred, 2), trace.h0, SQRT_2);
        g_skip + self.conv0.adjoint(g_pre0, 1, 1, [h, w])
    }
}

impl Discriminator {
    fn forward_traced(&self, x: Tensor<4>) -> (Tensor<2>, Trace) {
        let [batch, _, h, w] = x.dims();
        let from_rgb_out = self.from_rgb.forward_lrelu(x, SQRT_2);
        let mut x = from_rgb_out.clone();
        let mut blocks = Vec::with_capacity(self.blocks.len());
        for block in &self.blocks {
            let (y, trace) = block.forward_traced(x);
            blocks.push(trace);
            x = y;
        }
        let epilogue_in = x;
        let conv_out = self.conv.forward_lrelu(
            minibatch_std(epilogue_in.clone(), self.mbstd_group, self.mbstd_channels),
            SQRT_2,
        );
        let [_, c, hh, ww] = conv_out.dims();
        let flat = conv_out.clone().reshape([batch, c * hh * ww]);
        let fc_out = self.fc.forward_lrelu(flat, SQRT_2);
        let logits = self.out.forward(fc_out.clone());
        let trace = Trace {
            input_hw: [h, w],
            from_rgb_out,
            blocks,
            epilogue_in,
            conv_out,
            fc_out,
        };
        (logits, trace)
    }

    /// Logits: `[batch, in_channels, resolution, resolution] -> [batch, 1]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<2> {
        self.forward_traced(x).0
    }

    /// Logits `[batch, 1]` and `d(sum of logits) / d x`, `[batch, in_channels, resolution,
    /// resolution]`, the latter by an explicit reverse sweep in ordinary tensor ops, so that it
    /// can itself be differentiated with respect to the weights (first-order autodiff).
    ///
    /// Minibatch std couples the samples of a group, so the gradient of sample `b` includes
    /// terms from the other logits of its group; this is the gradient of the sum that StyleGAN2
    /// takes (`autograd.grad(real_logits.sum(), real_img)`).
    pub fn input_gradient(&self, x: Tensor<4>) -> (Tensor<2>, Tensor<4>) {
        let (logits, trace) = self.forward_traced(x);
        let grad = self.sweep(trace, logits.ones_like());
        (logits, grad)
    }

    /// Logits `[batch, 1]` and a [`Pullback`] that gives the input gradient of any loss of
    /// them afterwards, once its derivative is known, from this one pass. The logits are as
    /// [`Self::forward`]'s, tracked for the weights' gradient as far as the weights and `x`
    /// are; the pullback is computed outside the graph, as through a frozen discriminator.
    /// A training step uses it to judge the fakes once for both phases: the generator's
    /// gradient through the pullback, the discriminator's weight gradient through the logits.
    pub fn forward_with_pullback(&self, x: Tensor<4>) -> (Tensor<2>, Pullback) {
        let (logits, trace) = self.forward_traced(x);
        let pullback = Pullback {
            frozen: Module::no_grad(self.clone()),
            trace: trace.detached(),
        };
        (logits, pullback)
    }

    /// The reverse sweep: `sum_b g_b d logit_b / d x` at the point `trace` recorded, for
    /// the logits' cotangent `g_logits`, `[batch, 1]`.
    fn sweep(&self, trace: Trace, g_logits: Tensor<2>) -> Tensor<4> {
        let [batch, _] = g_logits.dims();
        let g_fc_out = g_logits.matmul(self.out.effective_weight());
        let g_fc_pre = lrelu_input_gradient(g_fc_out, trace.fc_out, SQRT_2);
        let [_, c, hh, ww] = trace.conv_out.dims();
        let g_conv_out = g_fc_pre
            .matmul(self.fc.effective_weight())
            .reshape([batch, c, hh, ww]);
        let g_conv_pre = lrelu_input_gradient(g_conv_out, trace.conv_out, SQRT_2);
        let g_mbstd = self.conv.adjoint(g_conv_pre, 1, 1, [hh, ww]);
        let mut g = minibatch_std_input_gradient(
            trace.epilogue_in,
            g_mbstd,
            self.mbstd_group,
            self.mbstd_channels,
        );
        for (block, block_trace) in self.blocks.iter().zip(trace.blocks).rev() {
            g = block.input_gradient(g, block_trace);
        }
        let g_pre = lrelu_input_gradient(g, trace.from_rgb_out, SQRT_2);
        self.from_rgb.adjoint(g_pre, 1, 0, trace.input_hw)
    }

    /// Number of scalar parameters.
    pub fn num_params(&self) -> usize {
        Module::num_params(self)
    }
}

/// R1 on a batch of real images, `gamma / 2 * mean_b ||d(sum logits) / d x_b||^2`, as a
/// differentiable function of the discriminator's weights (`reals` is detached first).
/// Returns the logits `[batch, 1]` and the penalty `[1]`; calling `backward()` on the penalty
/// gives the exact R1 gradient with respect to the weights.
pub fn r1_penalty(d: &Discriminator, reals: Tensor<4>, gamma: f64) -> (Tensor<2>, Tensor<1>) {
    let (logits, grad) = d.input_gradient(reals.detach());
    let [batch, c, h, w] = grad.dims();
    let per_sample = grad.square().reshape([batch, c * h * w]).sum_dim(1);
    (logits, per_sample.mean().mul_scalar(gamma / 2.0))
}

/// Checks the batch against the group size and returns `(group, groups, channels per feature)`.
fn mbstd_layout(dims: [usize; 4], group: usize, features: usize) -> (usize, usize, usize) {
    let [n, c, _, _] = dims;
    let g = group.min(n);
    assert!(
        n.is_multiple_of(g),
        "minibatch std: batch {n} is not divisible by the group size {g}"
    );
    assert!(
        c.is_multiple_of(features),
        "minibatch std: {c} channels do not split into {features} features"
    );
    (g, n / g, c / features)
}

/// StyleGAN2's minibatch standard deviation layer:
/// `[n, c, h, w] -> [n, c + features, h, w]`.
///
/// The batch is split into `n / G` groups of `G = min(group, n)` samples, sample `i` belonging
/// to group `i mod (n / G)`; the channels into `features` sets. For each group and set, the
/// standard deviation over the group (biased, `sqrt(var + 1e-8)`) is averaged over the set's
/// channels and all pixels, and appended to every sample of the group as a constant channel.
pub fn minibatch_std(x: Tensor<4>, group: usize, features: usize) -> Tensor<4> {
    let dims @ [n, _, h, w] = x.dims();
    let (g, m, cf) = mbstd_layout(dims, group, features);
    let y = x.clone().reshape([g, m, features, cf, h, w]);
    let centred = y.clone() - y.mean_dim(0);
    let std = centred
        .square()
        .mean_dim(0)
        .add_scalar(MBSTD_EPSILON)
        .sqrt();
    let s = std
        .reshape([m, features, cf * h * w])
        .mean_dim(2)
        .reshape([m, features, 1, 1])
        .repeat(&[g, 1, h, w]);
    debug_assert_eq!(s.dims(), [n, features, h, w]);
    Tensor::cat(vec![x, s], 1)
}

/// The transpose of [`minibatch_std`]'s Jacobian at `x` applied to `g_out`
/// (`[n, c + features, h, w] -> [n, c, h, w]`), in differentiable tensor ops.
///
/// With `d = x - mean_group(x)` and `s = sqrt(mean_group(d^2) + eps)`, the appended value
/// `y = mean_{set, pixels}(s)` has `dy / dx = d / (G s (c / features) h w)` (the mean's own
/// term vanishes because `d` sums to zero over the group).
pub fn minibatch_std_input_gradient(
    x: Tensor<4>,
    g_out: Tensor<4>,
    group: usize,
    features: usize,
) -> Tensor<4> {
    let dims @ [n, c, h, w] = x.dims();
    let (g, m, cf) = mbstd_layout(dims, group, features);
    let g_direct = g_out.clone().narrow(1, 0, c);
    // Each appended value is copied to G samples and h * w pixels: sum their gradients.
    let g_y = g_out
        .narrow(1, c, features)
        .reshape([g, m, features, h * w])
        .sum_dim(3)
        .sum_dim(0)
        .reshape([1, m, features, 1, 1, 1]);
    let y = x.reshape([g, m, features, cf, h, w]);
    let centred = y.clone() - y.mean_dim(0);
    let std = centred
        .clone()
        .square()
        .mean_dim(0)
        .add_scalar(MBSTD_EPSILON)
        .sqrt();
    let scale = 1.0 / (g * cf * h * w) as f64;
    let g_x = (centred / std * g_y).mul_scalar(scale);
    g_direct + g_x.reshape([n, c, h, w])
}

#[cfg(test)]
mod tests;
