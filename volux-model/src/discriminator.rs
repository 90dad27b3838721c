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
//! is then the exact R1 gradient.

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

    /// The logits of two batches of the same size, `(forward(a), forward(b))`, from one pass
    /// over both: fewer and larger operations than two passes. The batches are interleaved
    /// `[a_0, b_0, a_1, b_1, ..]`, which puts every sample in the minibatch-std group it has in
    /// its own batch (group `i mod m` of `m = batch / group` groups), so the logits are those of
    /// two passes. When the batch is not a multiple of the group size (a smaller group would
    /// then span both batches), it makes the two passes.
    pub fn forward_pair(&self, a: Tensor<4>, b: Tensor<4>) -> (Tensor<2>, Tensor<2>) {
        let dims @ [n, c, h, w] = a.dims();
        assert_eq!(b.dims(), dims, "both batches have one shape");
        if !n.is_multiple_of(self.mbstd_group) || n < self.mbstd_group {
            return (self.forward(a), self.forward(b));
        }
        let both = Tensor::stack::<5>(vec![a, b], 1).reshape([2 * n, c, h, w]);
        let logits = self.forward(both).reshape([n, 2]);
        (logits.clone().narrow(1, 0, 1), logits.narrow(1, 1, 1))
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
        let [batch, _] = logits.dims();
        let g_fc_out = logits.ones_like().matmul(self.out.effective_weight());
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
        let grad = self.from_rgb.adjoint(g_pre, 1, 0, trace.input_hw);
        (logits, grad)
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
mod tests {
    use super::*;
    use crate::backend::{to_f32_vec, to_f64_vec};
    use crate::bias_act::bias_lrelu_reference;
    use crate::test_support::{Reseed, normals};
    use burn::module::Param;
    use burn::tensor::{DType, Gradients, TensorData};
    use volux_envmap::random::SplitMix64;

    fn tensor<const D: usize>(
        v: Vec<f64>,
        shape: [usize; D],
        device: &Device,
        dtype: DType,
    ) -> Tensor<D> {
        Tensor::from_data(TensorData::new(v, shape), (device, dtype))
    }

    /// 3 channels at 16x16: channels 4 (16x16), 8 (8x8), 16 (4x4).
    fn tiny(device: &Device, seed: u64, dtype: DType) -> Discriminator {
        DiscriminatorConfig::new(3, 16)
            .with_channel_base(64)
            .with_channel_max(16)
            .init(device)
            .map(&mut Reseed::new(seed, dtype))
    }

    /// Parameters of StyleGAN2's resnet discriminator, counted layer by layer.
    fn expected_params(cfg: &DiscriminatorConfig) -> usize {
        let ch = |r| cfg.channels_at(r);
        let mut n = cfg.in_channels * ch(cfg.resolution) + ch(cfg.resolution);
        let mut r = cfg.resolution;
        while r > 4 {
            let (a, b) = (ch(r), ch(r / 2));
            n += (a * a * 9 + a) + (a * b * 9 + b) + a * b;
            r /= 2;
        }
        let c = ch(4);
        n + ((c + cfg.mbstd_channels) * c * 9 + c) + (c * 16 * c + c) + (c + 1)
    }

    /// [`minibatch_std`]'s appended values in f64 loops: `[n][features]`.
    fn minibatch_std_ref(
        x: &[f64],
        [n, c, h, w]: [usize; 4],
        group: usize,
        features: usize,
    ) -> Vec<Vec<f64>> {
        let g = group.min(n);
        let m = n / g;
        let cf = c / features;
        let at = |i: usize, ch: usize, p: usize| x[(i * c + ch) * h * w + p];
        (0..n)
            .map(|i| {
                let members: Vec<usize> = (0..g).map(|k| k * m + i % m).collect();
                (0..features)
                    .map(|f| {
                        let mut acc = 0.0;
                        for ch in f * cf..(f + 1) * cf {
                            for p in 0..h * w {
                                let mean =
                                    members.iter().map(|&j| at(j, ch, p)).sum::<f64>() / g as f64;
                                let var = members
                                    .iter()
                                    .map(|&j| (at(j, ch, p) - mean).powi(2))
                                    .sum::<f64>()
                                    / g as f64;
                                acc += (var + MBSTD_EPSILON).sqrt();
                            }
                        }
                        acc / (cf * h * w) as f64
                    })
                    .collect()
            })
            .collect()
    }

    #[test]
    fn minibatch_std_matches_an_f64_loop() {
        let device = Device::flex();
        let mut rng = SplitMix64::new(1);
        for (n, group, features) in [(8, 4, 2), (4, 4, 1), (2, 4, 1), (6, 3, 2), (1, 4, 1)] {
            let shape = [n, 4, 3, 2];
            let xv = normals(&mut rng, shape.iter().product());
            let x = tensor(xv.clone(), shape, &device, DType::F32);
            let y = minibatch_std(x, group, features);
            assert_eq!(y.dims(), [n, 4 + features, 3, 2]);
            let yv = to_f32_vec(y);
            // The input channels pass through unchanged.
            for i in 0..n {
                for k in 0..4 * 6 {
                    assert_eq!(yv[i * (4 + features) * 6 + k], xv[i * 24 + k] as f32);
                }
            }
            let want = minibatch_std_ref(&xv, shape, group, features);
            for i in 0..n {
                for f in 0..features {
                    for p in 0..6 {
                        let got = f64::from(yv[(i * (4 + features) + 4 + f) * 6 + p]);
                        assert!(
                            (got - want[i][f]).abs() < 1e-5,
                            "n {n} sample {i} feature {f}: {got} vs {}",
                            want[i][f]
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn minibatch_std_input_gradient_matches_autodiff() {
        // d/dx <minibatch_std(x), y> by the explicit formula and by Burn's autodiff.
        let device = Device::flex().autodiff();
        let mut rng = SplitMix64::new(2);
        for (n, group, features) in [(8, 4, 2), (4, 4, 1), (2, 4, 1)] {
            let shape = [n, 4, 3, 3];
            let x = tensor(
                normals(&mut rng, shape.iter().product()),
                shape,
                &device,
                DType::F32,
            )
            .require_grad();
            let out_shape = [n, 4 + features, 3, 3];
            let y = tensor(
                normals(&mut rng, out_shape.iter().product()),
                out_shape,
                &device,
                DType::F32,
            );
            let grads = (minibatch_std(x.clone(), group, features) * y.clone())
                .sum()
                .backward();
            let want = to_f32_vec(x.grad(&grads).unwrap());
            let got = to_f32_vec(minibatch_std_input_gradient(x, y, group, features));
            let scale = want.iter().fold(0f32, |m, v| m.max(v.abs()));
            for (a, b) in got.iter().zip(&want) {
                assert!((a - b).abs() < 1e-5 * scale, "n {n}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn input_gradient_matches_autodiff() {
        // In f32 (what training runs) and in f64 (where 1e-9 leaves no room for a missing
        // term, e.g. the minibatch std's cross-sample one, whose share is small).
        let device = Device::flex().autodiff();
        for (dtype, tolerance) in [(DType::F32, 1e-4), (DType::F64, 1e-9)] {
            let d = tiny(&device, 3, dtype);
            let mut rng = SplitMix64::new(4);
            // Batches 8 and 4 (two groups, one group of 4) and 2, 1 (groups smaller than 4).
            for batch in [8, 4, 2, 1] {
                let shape = [batch, 3, 16, 16];
                let x = tensor(
                    normals(&mut rng, shape.iter().product()),
                    shape,
                    &device,
                    dtype,
                );
                let x_leaf = x.clone().require_grad();
                let logits = d.forward(x_leaf.clone());
                let grads = logits.clone().sum().backward();
                let want = to_f64_vec(x_leaf.grad(&grads).unwrap());
                let (logits2, grad) = d.input_gradient(x);
                assert_eq!(grad.dims(), shape);
                assert_eq!(to_f64_vec(logits), to_f64_vec(logits2));
                let got = to_f64_vec(grad);
                let scale = want.iter().fold(0f64, |m, v| m.max(v.abs()));
                assert!(scale > 0.0);
                let err = got
                    .iter()
                    .zip(&want)
                    .fold(0f64, |m, (a, b)| m.max((a - b).abs()));
                assert!(
                    err < tolerance * scale,
                    "{dtype:?} batch {batch}: max error {err:e}, largest {scale}"
                );
            }
        }
    }

    #[test]
    fn r1_weight_gradient_matches_finite_differences() {
        // In f64: autodiff of the penalty through the explicit input gradient against central
        // differences of the penalty, for weights before, inside and after the minibatch std.
        let device = Device::flex().autodiff();
        let d = tiny(&device, 5, DType::F64);
        let shape = [4, 3, 16, 16];
        let x = tensor(
            normals(&mut SplitMix64::new(6), 4 * 3 * 256),
            shape,
            &device,
            DType::F64,
        );
        let gamma = 2.0;
        let (_, penalty) = r1_penalty(&d, x.clone(), gamma);
        let grads = penalty.clone().backward();

        // The penalty itself is gamma / 2 * mean ||input gradient||^2, with the input gradient
        // from Burn's autodiff.
        let x_leaf = x.clone().require_grad();
        let g = x_leaf
            .grad(&d.forward(x_leaf.clone()).sum().backward())
            .unwrap();
        let want = to_f64_vec(g.powi_scalar(2).sum())[0] / 4.0 * gamma / 2.0;
        let value = to_f64_vec(penalty)[0];
        assert!((value - want).abs() < 1e-9 * want, "{value} vs {want}");

        type Pick4 = fn(&mut Discriminator) -> &mut Param<Tensor<4>>;
        let convs: [(&str, Pick4, usize); 5] = [
            ("from_rgb", |d| &mut d.from_rgb.weight, 5),
            ("block 0 conv0", |d| &mut d.blocks[0].conv0.weight, 40),
            ("block 0 conv1", |d| &mut d.blocks[0].conv1.weight, 77),
            ("block 1 skip", |d| &mut d.blocks[1].skip.weight, 9),
            ("epilogue conv", |d| &mut d.conv.weight, 1000),
        ];
        for (name, pick, index) in convs {
            check_r1_element(&d, &x, gamma, &grads, name, pick, index);
        }
        type Pick2 = fn(&mut Discriminator) -> &mut Param<Tensor<2>>;
        let fcs: [(&str, Pick2, usize); 2] = [
            ("fc", |d| &mut d.fc.weight, 300),
            ("out", |d| &mut d.out.weight, 3),
        ];
        for (name, pick, index) in fcs {
            check_r1_element(&d, &x, gamma, &grads, name, pick, index);
        }
        // A bias acts on the input gradient only through the minibatch std (elsewhere it just
        // moves the piecewise-constant masks), so this one checks the mbstd's second derivative.
        let bias: fn(&mut Discriminator) -> &mut Param<Tensor<1>> =
            |d| d.from_rgb.bias.as_mut().unwrap();
        check_r1_element(&d, &x, gamma, &grads, "from_rgb bias", bias, 2);
    }

    /// Autodiff's `d penalty / d p[index]` (from `grads`) against a central difference of the
    /// f64 penalty, for the parameter `p` that `pick` selects.
    fn check_r1_element<const D: usize>(
        d: &Discriminator,
        x: &Tensor<4>,
        gamma: f64,
        grads: &Gradients,
        name: &str,
        pick: fn(&mut Discriminator) -> &mut Param<Tensor<D>>,
        index: usize,
    ) {
        let h = 1e-5;
        let mut d = d.clone();
        let analytic = to_f64_vec(pick(&mut d).val().grad(grads).unwrap())[index];
        let penalty_shifted = |delta: f64| {
            let mut d = d.clone();
            let p = pick(&mut d);
            let t = p.val();
            let mut v = to_f64_vec(t.clone());
            v[index] += delta;
            *p = Param::from_tensor(tensor(v, t.dims(), &t.device(), DType::F64));
            to_f64_vec(r1_penalty(&d, x.clone(), gamma).1)[0]
        };
        let fd = (penalty_shifted(h) - penalty_shifted(-h)) / (2.0 * h);
        assert!(
            analytic != 0.0 && (analytic - fd).abs() < 1e-6 * analytic.abs(),
            "{name}: autodiff {analytic:e} vs finite differences {fd:e}"
        );
    }

    /// The GPU path (CI runs it on a software Vulkan driver): logits, the explicit input
    /// gradient and the R1 weight gradient equal the CPU's for the same weights.
    #[cfg(feature = "wgpu")]
    #[test]
    fn wgpu_agrees_with_flex_including_r1() {
        let gpu = crate::backend::BackendKind::Wgpu.device().unwrap();
        let mut rng = SplitMix64::new(11);
        let x = normals(&mut rng, 4 * 3 * 16 * 16);
        let mut results = Vec::new();
        for device in [Device::flex().autodiff(), gpu.autodiff()] {
            let d = tiny(&device, 5, DType::F32);
            let input = tensor(x.clone(), [4, 3, 16, 16], &device, DType::F32);
            let (logits, grad) = d.input_gradient(input.clone().detach());
            let (_, penalty) = r1_penalty(&d, input, 10.0);
            let grads = penalty.backward();
            let w = d
                .from_rgb
                .weight
                .val()
                .grad(&grads)
                .expect("R1 reaches FromRGB");
            results.push([to_f64_vec(logits), to_f64_vec(grad), to_f64_vec(w)]);
        }
        let (cpu, gpu) = (&results[0], &results[1]);
        for (k, what) in ["logits", "input gradient", "R1 gradient of FromRGB"]
            .iter()
            .enumerate()
        {
            let scale = cpu[k].iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let worst = cpu[k]
                .iter()
                .zip(&gpu[k])
                .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
            assert!(
                worst <= 1e-3 * scale.max(1e-6),
                "{what}: {worst} (scale {scale})"
            );
        }
    }

    /// The fused path (bias and activation in one op, the block's `1 / sqrt(2)` folded into
    /// the skip weights and the second activation's gain) against StyleGAN2's formula written
    /// with separate ops: `lrelu` with gain sqrt(2) after every biased convolution and fully
    /// connected layer, `(skip + main) / sqrt(2)` per block.
    #[test]
    fn fused_forward_equals_stylegan2s_formula_in_separate_ops() {
        let device = Device::flex();
        let d = tiny(&device, 3, DType::F32);
        let mut rng = SplitMix64::new(8);
        let x = tensor(
            normals(&mut rng, 2 * 3 * 16 * 16),
            [2, 3, 16, 16],
            &device,
            DType::F32,
        );
        let act = |t: Tensor<4>| bias_lrelu_reference(t, None, SQRT_2);
        let mut h = act(d.from_rgb.forward(x.clone()));
        for block in &d.blocks {
            let skip = block
                .skip
                .forward_strided(blur_downsample2(h.clone()), 1, 0);
            let main = act(block
                .conv1
                .forward_strided(blur(act(block.conv0.forward(h)), 2), 2, 0));
            h = (skip + main).mul_scalar(FRAC_1_SQRT_2);
        }
        let c = act(d
            .conv
            .forward(minibatch_std(h, d.mbstd_group, d.mbstd_channels)));
        let [_, ch, hh, ww] = c.dims();
        let fc = bias_lrelu_reference(d.fc.forward(c.reshape([2, ch * hh * ww])), None, SQRT_2);
        let want = to_f64_vec(d.out.forward(fc));
        let got = to_f64_vec(d.forward(x));
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w).abs() <= 1e-5 * (1.0 + w.abs()), "{g} vs {w}");
        }
    }

    #[test]
    fn one_pass_over_two_batches_gives_the_logits_and_gradients_of_two_passes() {
        let device = Device::flex().autodiff();
        for (batch, group) in [(4, 4), (8, 4), (2, 4), (6, 3)] {
            let d = DiscriminatorConfig::new(3, 16)
                .with_channel_base(64)
                .with_channel_max(16)
                .with_mbstd_group(group)
                .init(&device)
                .map(&mut Reseed::new(4, DType::F32));
            let mut rng = SplitMix64::new(batch as u64);
            let n = batch * 3 * 16 * 16;
            let shape = [batch, 3, 16, 16];
            let a = tensor(normals(&mut rng, n), shape, &device, DType::F32);
            let b = tensor(normals(&mut rng, n), shape, &device, DType::F32);
            let loss = |(la, lb): (Tensor<2>, Tensor<2>)| {
                (la.clone(), lb.clone(), (la - lb.mul_scalar(3.0)).sum())
            };
            let (pa, pb, pl) = loss(d.forward_pair(a.clone(), b.clone()));
            let (sa, sb, sl) = loss((d.forward(a), d.forward(b)));
            let close = |x: Vec<f64>, y: Vec<f64>, what: &str| {
                for (i, (x, y)) in x.iter().zip(&y).enumerate() {
                    assert!(
                        (x - y).abs() <= 1e-4 * (1.0 + y.abs()),
                        "batch {batch} {what}[{i}]: {x} vs {y}"
                    );
                }
            };
            close(to_f64_vec(pa), to_f64_vec(sa), "first logits");
            close(to_f64_vec(pb), to_f64_vec(sb), "second logits");
            let (gp, gs) = (pl.backward(), sl.backward());
            let w = d.blocks[0].conv0.weight.val();
            close(
                to_f64_vec(w.grad(&gp).unwrap()),
                to_f64_vec(w.grad(&gs).unwrap()),
                "weight gradient",
            );
        }
    }

    #[test]
    fn presets_give_one_logit_per_image() {
        let device = Device::flex();
        for (channels, res) in [(3, 64), (9, 64), (3, 128)] {
            let cfg = DiscriminatorConfig::small(channels, res);
            let d = cfg.init(&device);
            let x = Tensor::<4>::random(
                [2, channels, res, res],
                burn::tensor::Distribution::Normal(0.0, 1.0),
                &device,
            );
            let logits = d.forward(x.clone());
            assert_eq!(logits.dims(), [2, 1]);
            assert!(to_f32_vec(logits).iter().all(|v| v.is_finite()));
            assert_eq!(d.blocks.len(), res.trailing_zeros() as usize - 2);
            assert_eq!(d.num_params(), expected_params(&cfg));
        }
    }

    #[test]
    fn parameter_counts_follow_the_architecture() {
        let device = Device::flex();
        let small = DiscriminatorConfig::small(3, 64);
        assert_eq!(small.init(&device).num_params(), expected_params(&small));
        assert_eq!(expected_params(&small), 1_183_137);
        // StyleGAN2 at 256x256 and (StyleGAN2-ADA's 29.0M) at 1024x1024, counted without
        // building them.
        assert_eq!(
            expected_params(&DiscriminatorConfig::stylegan2(3, 256)),
            28_864_129
        );
        assert_eq!(
            expected_params(&DiscriminatorConfig::stylegan2(3, 1024)),
            29_012_513
        );
        let sg128 = DiscriminatorConfig::stylegan2(3, 128);
        assert_eq!(sg128.channels_at(128), 256);
        assert_eq!(sg128.channels_at(64), 512);
        assert_eq!(sg128.init(&device).num_params(), expected_params(&sg128));
    }
}
