//! The upsampler (paper section 3.3): low-resolution features to high-resolution albedo and
//! features. Each block doubles the resolution: two 1x1 convolutions modulated by the latent
//! (the second to `4 C` channels), a pixel shuffle x2, and a BlurPool with stride 1 (a `[1, 2,
//! 1]` binomial blur that removes the checkerboard of the shuffle). The first three channels
//! are the albedo. Shading maps do not go through here: they are upsampled bilinearly
//! ([`bilinear_upsample`]).
//!
//! Decisions the paper leaves open (ARCHITECTURE.md): the input is `[A_lo, F_lo]`, so the
//! first three input channels are already the low-resolution albedo; each block predicts an
//! albedo *residual* on top of the bilinearly upsampled albedo of the previous resolution,
//! scaled by the block's fade-in weight. With a weight of 0 a block's albedo is a plain
//! bilinear upsampling, with 1 it is fully learned: progressive growing (stage 1) fades blocks
//! in from the lowest resolution up, as PGGAN fades in its ToRGB outputs.

use burn::config::Config;
use burn::module::Module;
use burn::nn::{PixelShuffle, PixelShuffleConfig};
use burn::tensor::{Device, Tensor};

use crate::fir_filter::{Fir, fir2d, fir2d_adjoint};
use crate::fused_activation;
use crate::modulated::{ModulatedLinear, ModulatedLinearConfig};

/// Configuration of an [`Upsampler`].
#[derive(Config, Debug)]
pub struct UpsamplerConfig {
    /// Dimension of `w`.
    pub w_dim: usize,
    /// Input channels: 3 (albedo) + the renderer's feature channels.
    pub in_channels: usize,
    /// Channels of every block's output (at least 3).
    pub channels: usize,
    /// Number of x2 blocks (1 for 64 -> 128, 2 for 64 -> 256).
    pub blocks: usize,
}

/// One x2 block.
#[derive(Module, Debug)]
pub struct UpsampleBlock {
    pub conv1: ModulatedLinear,
    pub conv2: ModulatedLinear,
    pub shuffle: PixelShuffle,
}

/// The upsampler.
#[derive(Module, Debug)]
pub struct Upsampler {
    pub blocks: Vec<UpsampleBlock>,
}

impl UpsamplerConfig {
    /// Channels of the output, albedo first: the blocks' `channels`, or the input's when there
    /// are no blocks (the output resolution is the volume's, and the input passes through).
    pub fn output_channels(&self) -> usize {
        if self.blocks == 0 {
            self.in_channels
        } else {
            self.channels
        }
    }

    /// An upsampler with freshly initialised parameters on `device`.
    pub fn init(&self, device: &Device) -> Upsampler {
        assert!(
            self.channels >= 3,
            "the first three channels are the albedo"
        );
        assert!(self.in_channels >= 3, "the input starts with the albedo");
        let blocks = (0..self.blocks)
            .map(|i| {
                let c_in = if i == 0 {
                    self.in_channels
                } else {
                    self.channels
                };
                UpsampleBlock {
                    conv1: ModulatedLinearConfig::new(self.w_dim, c_in, self.channels).init(device),
                    conv2: ModulatedLinearConfig::new(self.w_dim, self.channels, 4 * self.channels)
                        .init(device),
                    shuffle: PixelShuffleConfig::new(2).init(),
                }
            })
            .collect();
        Upsampler { blocks }
    }
}

/// A modulated layer applied per pixel (a modulated 1x1 convolution): `[b, c, h, w]`.
fn conv1x1(layer: &ModulatedLinear, x: Tensor<4>, w: Tensor<2>) -> Tensor<4> {
    per_pixel(x, |x| layer.forward(x, w))
}

/// [`conv1x1`] followed by the smooth activation, the bias and activation in one fused
/// operation ([`fused_activation::activate`]).
fn conv1x1_activated(layer: &ModulatedLinear, x: Tensor<4>, w: Tensor<2>) -> Tensor<4> {
    per_pixel(x, |x| {
        let m = layer.modulation(w);
        fused_activation::activate(layer.linear(x, &m), layer.bias.val())
    })
}

/// `f` applied to `x: [batch, c, h, w]` as `[batch, h w, c]` pixels, back to `[batch, o, h, w]`.
fn per_pixel(x: Tensor<4>, f: impl FnOnce(Tensor<3>) -> Tensor<3>) -> Tensor<4> {
    let [b, c, h, wd] = x.dims();
    let y = f(x.reshape([b, c, h * wd]).swap_dims(1, 2));
    let o = y.dims()[2];
    y.swap_dims(1, 2).reshape([b, o, h, wd])
}

/// BlurPool with stride 1: a `[1, 2, 1]^T [1, 2, 1] / 16` blur per channel, edges replicated.
pub fn blur_stride1(x: Tensor<4>) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let out = fir2d(pad_replicate(x), &Fir::new(vec![0.25, 0.5, 0.25], 0, 1));
    debug_assert_eq!(out.dims(), [b, c, h, w]);
    out
}

/// Replicates the outermost rows and columns once: `[b, c, h, w] -> [b, c, h + 2, w + 2]`.
fn pad_replicate(x: Tensor<4>) -> Tensor<4> {
    let [_, _, h, w] = x.dims();
    let rows = Tensor::cat(
        vec![x.clone().narrow(2, 0, 1), x.clone(), x.narrow(2, h - 1, 1)],
        2,
    );
    Tensor::cat(
        vec![
            rows.clone().narrow(3, 0, 1),
            rows.clone(),
            rows.narrow(3, w - 1, 1),
        ],
        3,
    )
}

/// Bilinear x`factor` upsampling with half-pixel centres and clamped edges (PyTorch's
/// `align_corners = False`), used for the shading maps and the albedo skip path.
///
/// Written as a depthwise transposed convolution with the tent kernel
/// `k_j = 1 - |j - f + 1/2| / f` (`j < 2f`) on the edge-replicated input, then a crop
/// ([`crate::fir_filter::fir2d_adjoint`]), because Burn's `interpolate` has no bilinear backward
/// on the wgpu backend. `factor` must be 1 or even. Equal to `interpolate` on flex (tested).
pub fn bilinear_upsample(x: Tensor<4>, factor: usize) -> Tensor<4> {
    if factor == 1 {
        return x;
    }
    assert!(
        factor.is_multiple_of(2),
        "bilinear upsampling by an even factor, got {factor}"
    );
    let [b, c, h, w] = x.dims();
    let f = factor;
    // The transposed convolution's full output of the `(h + 2) x (w + 2)` padded input.
    let full_hw = [(h + 1) * f + 2 * f, (w + 1) * f + 2 * f];
    let full = fir2d_adjoint(pad_replicate(x), &Fir::new(tent_taps(f), 0, f), full_hw);
    let crop = 3 * f / 2;
    let out = full.narrow(2, crop, h * f).narrow(3, crop, w * f);
    debug_assert_eq!(out.dims(), [b, c, h * f, w * f]);
    out
}

/// The 1D tent of bilinear upsampling by `factor`: `k_j = 1 - |j - f + 1/2| / f`, `j < 2f`.
pub(crate) fn tent_taps(factor: usize) -> Vec<f32> {
    let f = factor as f32;
    (0..2 * factor)
        .map(|j| 1.0 - (j as f32 - f + 0.5).abs() / f)
        .collect()
}

impl Upsampler {
    /// Resolution factor.
    pub fn factor(&self) -> usize {
        1 << self.blocks.len()
    }

    /// `x: [batch, in_channels, h, w]` (`[A_lo, F_lo]`), `w: [batch, w_dim]`, one fade-in
    /// weight per block in [0, 1] (`None`: all 1) -> `[batch, channels, h f, w f]` whose first
    /// three channels are the high-resolution albedo.
    pub fn forward(&self, x: Tensor<4>, w: Tensor<2>, fade: Option<&[f64]>) -> Tensor<4> {
        if let Some(f) = fade {
            assert_eq!(f.len(), self.blocks.len(), "one fade-in weight per block");
        }
        let mut x = x;
        for (i, block) in self.blocks.iter().enumerate() {
            let albedo = bilinear_upsample(x.clone().narrow(1, 0, 3), 2);
            let h = conv1x1_activated(&block.conv1, x, w.clone());
            let y = blur_stride1(block.shuffle.forward(conv1x1(&block.conv2, h, w.clone())));
            let c = y.dims()[1];
            let alpha = fade.map_or(1.0, |f| f[i]);
            let residual = y.clone().narrow(1, 0, 3).mul_scalar(alpha);
            x = Tensor::cat(vec![albedo + residual, y.narrow(1, 3, c - 3)], 1);
        }
        x
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
    use burn::tensor::{Distribution, TensorData};

    #[test]
    fn blur_matches_a_reference_loop_and_keeps_constants() {
        let device = Device::flex();
        let (h, w) = (5, 6);
        let x = Tensor::<4>::random([1, 2, h, w], Distribution::Normal(0.0, 1.0), &device);
        let xv = to_f32_vec(x.clone());
        let got = to_f32_vec(blur_stride1(x));
        let k = [1.0f64, 2.0, 1.0];
        for c in 0..2 {
            for i in 0..h {
                for j in 0..w {
                    let mut want = 0.0;
                    for (di, ki) in k.iter().enumerate() {
                        for (dj, kj) in k.iter().enumerate() {
                            let y = (i + di).saturating_sub(1).min(h - 1);
                            let x = (j + dj).saturating_sub(1).min(w - 1);
                            want += ki * kj / 16.0 * f64::from(xv[(c * h + y) * w + x]);
                        }
                    }
                    let g = f64::from(got[(c * h + i) * w + j]);
                    assert!((g - want).abs() < 1e-5, "({c},{i},{j}): {g} vs {want}");
                }
            }
        }
        let ones = blur_stride1(Tensor::<4>::ones([1, 1, 4, 4], &device));
        assert!(to_f32_vec(ones).iter().all(|v| (v - 1.0).abs() < 1e-6));
    }

    #[test]
    fn bilinear_upsampling_uses_half_pixel_centres() {
        let device = Device::flex();
        let x = Tensor::<4>::from_data(TensorData::new(vec![0.0f32, 1.0], [1, 1, 1, 2]), &device);
        let y = to_f32_vec(bilinear_upsample(x, 2));
        // Output pixel centres at 0.25, 0.75, 1.25, 1.75 input pixels (clamped at the edges).
        assert_eq!(y.len(), 8);
        let want = [0.0, 0.25, 0.75, 1.0];
        for (g, w) in y[..4].iter().zip(want) {
            assert!((g - w).abs() < 1e-6, "{y:?}");
        }
    }

    #[test]
    fn bilinear_upsampling_equals_burns_interpolate() {
        use burn::tensor::module::interpolate;
        use burn::tensor::ops::{InterpolateMode, InterpolateOptions};
        let device = Device::flex();
        for (f, h, w) in [(2, 5, 7), (4, 3, 6), (8, 2, 2)] {
            let x = Tensor::<4>::random([2, 3, h, w], Distribution::Normal(0.0, 1.0), &device);
            let want = interpolate(
                x.clone(),
                InterpolateOptions::new(InterpolateMode::Bilinear)
                    .with_align_corners(false)
                    .with_output_size([h * f, w * f]),
            );
            let diff: f32 = (bilinear_upsample(x, f) - want).abs().max().into_scalar();
            assert!(diff < 1e-5, "factor {f}: {diff}");
        }
    }

    #[test]
    fn shapes_and_fade_in_zero_is_bilinear_albedo() {
        let device = Device::flex();
        let up = UpsamplerConfig::new(8, 3 + 5, 12, 2).init(&device);
        assert_eq!(up.factor(), 4);
        let x = Tensor::<4>::random([2, 8, 4, 4], Distribution::Normal(0.0, 1.0), &device);
        let w = Tensor::<2>::random([2, 8], Distribution::Normal(0.0, 1.0), &device);
        let y = up.forward(x.clone(), w.clone(), None);
        assert_eq!(y.dims(), [2, 12, 16, 16]);
        let faded = up.forward(x.clone(), w, Some(&[0.0, 0.0]));
        let want = bilinear_upsample(bilinear_upsample(x.narrow(1, 0, 3), 2), 2);
        let diff: f32 = (faded.clone().narrow(1, 0, 3) - want)
            .abs()
            .max()
            .into_scalar();
        assert!(
            diff < 1e-5,
            "with every block faded out the albedo is bilinear ({diff})"
        );
        let full: f32 = (y.narrow(1, 0, 3) - faded.narrow(1, 0, 3))
            .abs()
            .max()
            .into_scalar();
        assert!(full > 1e-3, "faded-in blocks change the albedo");
    }
}
