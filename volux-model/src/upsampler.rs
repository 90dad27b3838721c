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
//!
//! `kernel = 3` (a deviation from the paper, off by default) makes both convolutions of every
//! block 3x3: each pixel's layer reads its 3x3 neighbourhood ([`neighbourhoods`], edges
//! replicated), so the block can draw detail finer than the volume's rays from how the
//! features change between them. It is the same modulated layer on the stacked
//! neighbourhood, so each tap of each input channel has its own style (StyleGAN2's
//! modulated convolution shares one style among a channel's taps).

use burn::config::Config;
use burn::module::Module;
use burn::nn::{PixelShuffle, PixelShuffleConfig};
use burn::tensor::{Device, Tensor};

use crate::fir_filter::{Fir, fir2d, fir2d_adjoint};
use crate::fused_activation;
use crate::modulated::{ModulatedLinear, ModulatedLinearConfig};
use crate::upsampler_noise::NoiseInjection;

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
    /// Side of both convolutions of every block: 1 (the paper's) or 3.
    #[config(default = 1)]
    pub kernel: usize,
}

/// One x2 block.
#[derive(Module, Debug)]
pub struct UpsampleBlock {
    pub conv1: ModulatedLinear,
    pub conv2: ModulatedLinear,
    pub shuffle: PixelShuffle,
    /// Surface-anchored noise added to the block's output (`None`: the paper's block).
    pub noise: Option<NoiseInjection>,
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
        assert!(
            KERNELS.contains(&self.kernel),
            "upsampler kernel {} is not one of {KERNELS:?}",
            self.kernel
        );
        let taps = self.kernel * self.kernel;
        let blocks = (0..self.blocks)
            .map(|i| {
                let c_in = if i == 0 {
                    self.in_channels
                } else {
                    self.channels
                };
                UpsampleBlock {
                    conv1: ModulatedLinearConfig::new(self.w_dim, taps * c_in, self.channels)
                        .init(device),
                    conv2: ModulatedLinearConfig::new(
                        self.w_dim,
                        taps * self.channels,
                        4 * self.channels,
                    )
                    .init(device),
                    shuffle: PixelShuffleConfig::new(2).init(),
                    noise: None,
                }
            })
            .collect();
        Upsampler { blocks }
    }
}

/// The sides [`UpsamplerConfig::kernel`] may take.
pub const KERNELS: [usize; 2] = [1, 3];

/// A modulated layer applied per pixel to the `kernel x kernel` neighbourhoods of `x: [b, c, h,
/// w]` (a modulated `kernel x kernel` convolution, edges replicated).
fn conv(layer: &ModulatedLinear, x: Tensor<4>, w: Tensor<2>, kernel: usize) -> Tensor<4> {
    per_pixel(neighbourhoods(x, kernel), |x| layer.forward(x, w))
}

/// [`conv`] followed by the smooth activation, the bias and activation in one fused
/// operation ([`fused_activation::activate`]).
fn conv_activated(layer: &ModulatedLinear, x: Tensor<4>, w: Tensor<2>, kernel: usize) -> Tensor<4> {
    per_pixel(neighbourhoods(x, kernel), |x| {
        let m = layer.modulation(w);
        fused_activation::activate(layer.linear(x, &m), layer.bias.val())
    })
}

/// Every pixel's `kernel x kernel` neighbourhood stacked along the channels, edges replicated:
/// `[b, c, h, w] -> [b, kernel^2 c, h, w]`, tap-major (channel `(dy kernel + dx) c + i` is
/// input channel `i` at offset `(dy - kernel / 2, dx - kernel / 2)`). Kernel 1 is `x` itself.
pub fn neighbourhoods(x: Tensor<4>, kernel: usize) -> Tensor<4> {
    match kernel {
        1 => x,
        3 => {
            let [_, _, h, w] = x.dims();
            let padded = pad_replicate(x);
            let taps = (0..3)
                .flat_map(|dy| (0..3).map(move |dx| (dy, dx)))
                .map(|(dy, dx)| padded.clone().narrow(2, dy, h).narrow(3, dx, w))
                .collect();
            Tensor::cat(taps, 1)
        }
        k => panic!("upsampler kernel {k} is not one of {KERNELS:?}"),
    }
}

/// `f` applied to `x: [batch, c, h, w]` as `[batch, h w, c]` pixels, back to `[batch, o, h, w]`.
pub(crate) fn per_pixel(x: Tensor<4>, f: impl FnOnce(Tensor<3>) -> Tensor<3>) -> Tensor<4> {
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

impl UpsampleBlock {
    /// Side of the block's convolutions, from its second layer's shape (`kernel^2 C` inputs,
    /// `4 C` outputs).
    pub fn kernel(&self) -> usize {
        let [d_out, d_in] = self.conv2.weight.dims();
        let taps = 4 * d_in / d_out;
        KERNELS
            .into_iter()
            .find(|k| k * k == taps)
            .expect("the block was built with one of KERNELS")
    }
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
        self.forward_noised(x, w, fade, &[])
    }

    /// [`Self::forward`] with each block's noise images `[batch, octaves, h, w]` at its output
    /// resolution ([`crate::upsampler_noise`]); a block without an image here, or without a
    /// noise input, adds none.
    pub fn forward_noised(
        &self,
        x: Tensor<4>,
        w: Tensor<2>,
        fade: Option<&[f64]>,
        noise: &[Tensor<4>],
    ) -> Tensor<4> {
        if let Some(f) = fade {
            assert_eq!(f.len(), self.blocks.len(), "one fade-in weight per block");
        }
        let mut x = x;
        for (i, block) in self.blocks.iter().enumerate() {
            let albedo = bilinear_upsample(x.clone().narrow(1, 0, 3), 2);
            let k = block.kernel();
            let h = conv_activated(&block.conv1, x, w.clone(), k);
            let y = blur_stride1(block.shuffle.forward(conv(&block.conv2, h, w.clone(), k)));
            let y = match (&block.noise, noise.get(i)) {
                (Some(injection), Some(n)) => injection.forward(y, w.clone(), n.clone()),
                _ => y,
            };
            let c = y.dims()[1];
            let alpha = fade.map_or(1.0, |f| f[i]);
            let residual = y.clone().narrow(1, 0, 3).mul_scalar(alpha);
            x = Tensor::cat(vec![albedo + residual, y.narrow(1, 3, c - 3)], 1);
        }
        x
    }

    /// Octaves of the blocks' noise inputs (0: none).
    pub fn noise_octaves(&self) -> usize {
        self.blocks
            .first()
            .and_then(|b| b.noise.as_ref())
            .map_or(0, NoiseInjection::octaves)
    }

    /// Gives every block a noise input of `octaves` octaves, zero strength
    /// ([`crate::upsampler_noise`]); 0 removes them.
    pub fn with_noise(mut self, octaves: usize, w_dim: usize, device: &Device) -> Self {
        for block in &mut self.blocks {
            let channels = block.conv2.d_output() / 4;
            block.noise =
                (octaves > 0).then(|| NoiseInjection::new(w_dim, channels, octaves, device));
        }
        self
    }

    /// Number of scalar parameters.
    pub fn num_params(&self) -> usize {
        Module::num_params(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::{to_f32_vec, to_f64_vec};
    use crate::modulated::DEMOD_EPS;
    use crate::test_support::{f64_tensor, normals, shift_element};
    use burn::module::{Module, Param};
    use burn::tensor::{DType, Distribution, TensorData};
    use volux_envmap::random::SplitMix64;

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
    fn neighbourhoods_stack_the_replicated_3x3_taps() {
        let device = Device::flex();
        let (b, c, h, w) = (2, 3, 4, 5);
        let x = Tensor::<4>::random([b, c, h, w], Distribution::Normal(0.0, 1.0), &device);
        let xv = to_f32_vec(x.clone());
        assert_eq!(to_f32_vec(neighbourhoods(x.clone(), 1)), xv);
        let got = to_f32_vec(neighbourhoods(x, 3));
        assert_eq!(got.len(), 9 * xv.len());
        for n in 0..b {
            for (tap, (dy, dx)) in (0..3usize)
                .flat_map(|dy| (0..3usize).map(move |dx| (dy, dx)))
                .enumerate()
            {
                for i in 0..c {
                    for y in 0..h {
                        for z in 0..w {
                            let sy = (y + dy).saturating_sub(1).min(h - 1);
                            let sz = (z + dx).saturating_sub(1).min(w - 1);
                            let want = xv[((n * c + i) * h + sy) * w + sz];
                            let at = (((n * 9 + tap) * c + i) * h + y) * w + z;
                            assert_eq!(
                                got[at], want,
                                "image {n} tap {tap} channel {i} at ({y}, {z})"
                            );
                        }
                    }
                }
            }
        }
    }

    /// The modulated, demodulated 3x3 convolution of a block's first layer, in f64 loops from
    /// the definition (edges replicated, a style per tap and input channel), then the bias.
    #[test]
    fn a_kernel_3_layer_is_a_modulated_3x3_convolution() {
        let device = Device::flex();
        let (b, c, o, h, w, w_dim) = (2, 5, 4, 4, 3, 6);
        let up = UpsamplerConfig::new(w_dim, c, o, 1)
            .with_kernel(3)
            .init(&device)
            .map(&mut crate::test_support::Reseed::new(7, DType::F64));
        let layer = &up.blocks[0].conv1;
        let mut rng = SplitMix64::new(8);
        let xv = normals(&mut rng, b * c * h * w);
        let wv = normals(&mut rng, b * w_dim);
        let x = f64_tensor(xv.clone(), [b, c, h, w], &device);
        let wt = f64_tensor(wv.clone(), [b, w_dim], &device);
        let got = to_f64_vec(conv(layer, x, wt.clone(), 3));
        let styles = to_f64_vec(layer.affine.forward(wt));
        let weight = to_f64_vec(layer.effective_weight());
        let bias = to_f64_vec(layer.bias.val());
        let d_in = 9 * c;
        for n in 0..b {
            for oi in 0..o {
                let row: Vec<f64> = (0..d_in)
                    .map(|j| weight[oi * d_in + j] * styles[n * d_in + j])
                    .collect();
                let norm = (row.iter().map(|v| v * v).sum::<f64>() + DEMOD_EPS).sqrt();
                for y in 0..h {
                    for z in 0..w {
                        let mut acc = 0.0;
                        for dy in 0..3 {
                            for dx in 0..3 {
                                let sy = (y + dy).saturating_sub(1).min(h - 1);
                                let sz = (z + dx).saturating_sub(1).min(w - 1);
                                for i in 0..c {
                                    acc += row[(dy * 3 + dx) * c + i]
                                        * xv[((n * c + i) * h + sy) * w + sz];
                                }
                            }
                        }
                        let want = acc / norm + bias[oi];
                        let g = got[((n * o + oi) * h + y) * w + z];
                        assert!(
                            (g - want).abs() < 1e-12 * (1.0 + want.abs()),
                            "{g} vs {want}"
                        );
                    }
                }
            }
        }
    }

    /// Gradients of a kernel-3 upsampler (two blocks, every fade weight 1) in its input and in
    /// both layers' weights and styles, against central differences of the same f64 forward.
    #[test]
    fn kernel_3_gradients_match_central_differences() {
        let device = Device::flex().autodiff();
        let (b, c, ch, side, w_dim) = (2, 5, 4, 3, 3);
        let up = UpsamplerConfig::new(w_dim, c, ch, 2)
            .with_kernel(3)
            .init(&device)
            .map(&mut crate::test_support::Reseed::new(11, DType::F64));
        let mut rng = SplitMix64::new(12);
        let xv = normals(&mut rng, b * c * side * side);
        let wv = normals(&mut rng, b * w_dim);
        let out = 4 * side;
        let r = f64_tensor(
            normals(&mut rng, b * ch * out * out),
            [b, ch, out, out],
            &device,
        );
        let loss = |up: &Upsampler, x: Vec<f64>| {
            let y = up.forward(
                f64_tensor(x, [b, c, side, side], &device),
                f64_tensor(wv.clone(), [b, w_dim], &device),
                None,
            );
            (y * r.clone()).sum()
        };
        let x = f64_tensor(xv.clone(), [b, c, side, side], &device).require_grad();
        let y = up.forward(x.clone(), f64_tensor(wv.clone(), [b, w_dim], &device), None);
        let grads = (y * r.clone()).sum().backward();
        let h = 1e-6;
        let central = |plus: f64, minus: f64| (plus - minus) / (2.0 * h);
        let close = |got: f64, want: f64, what: &str| {
            assert!(
                got != 0.0 && (got - want).abs() < 1e-6 * (1.0 + want.abs()),
                "{what}: autodiff {got:e} vs central differences {want:e}"
            );
        };
        let gx = to_f64_vec(x.grad(&grads).unwrap());
        for k in [0, 7, 20, xv.len() - 1] {
            let shifted = |d: f64| {
                let mut v = xv.clone();
                v[k] += d;
                to_f64_vec(loss(&up, v))[0]
            };
            close(
                gx[k],
                central(shifted(h), shifted(-h)),
                &format!("input {k}"),
            );
        }
        type Pick = fn(&mut Upsampler) -> &mut Param<Tensor<2>>;
        let params: [(&str, Pick, usize); 4] = [
            (
                "block 0 conv1 weight",
                |u| &mut u.blocks[0].conv1.weight,
                13,
            ),
            (
                "block 0 conv2 weight",
                |u| &mut u.blocks[0].conv2.weight,
                40,
            ),
            (
                "block 1 conv1 weight",
                |u| &mut u.blocks[1].conv1.weight,
                30,
            ),
            (
                "block 1 conv2 style",
                |u| &mut u.blocks[1].conv2.affine.weight,
                5,
            ),
        ];
        for (what, pick, k) in params {
            let got = to_f64_vec(pick(&mut up.clone()).grad(&grads).unwrap())[k];
            let shifted = |d: f64| {
                let mut u = up.clone();
                shift_element(pick(&mut u), k, d);
                to_f64_vec(loss(&u, xv.clone()))[0]
            };
            close(got, central(shifted(h), shifted(-h)), what);
        }
    }

    #[test]
    fn shapes_and_fade_in_zero_is_bilinear_albedo() {
        for kernel in KERNELS {
            fade_in_zero_is_bilinear_albedo(kernel);
        }
    }

    fn fade_in_zero_is_bilinear_albedo(kernel: usize) {
        let device = Device::flex();
        let up = UpsamplerConfig::new(8, 3 + 5, 12, 2)
            .with_kernel(kernel)
            .init(&device);
        assert_eq!(up.factor(), 4);
        assert!(up.blocks.iter().all(|b| b.kernel() == kernel));
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
