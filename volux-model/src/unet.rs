//! The U-Net both image-to-image networks share: levels of two 3x3 convolutions with leaky
//! ReLU, 2x2 box downsampling between encoder levels, bilinear upsampling and a skip
//! concatenation before each decoder level, and a 1x1 convolution to the output channels.
//! The relighting network ([`crate::relighting`]) wraps it around the Phong image; the
//! intrinsic estimator of `volux data pseudo-gt` is one on its own.

use std::f64::consts::SQRT_2;

use burn::config::Config;
use burn::module::Module;
use burn::tensor::{Device, Tensor};

use crate::equalized::{EqualizedConv2d, EqualizedConv2dConfig};
use crate::upsampler::bilinear_upsample;

/// Two 3x3 convolutions with leaky ReLU.
#[derive(Module, Debug)]
pub struct ConvPair {
    pub a: EqualizedConv2d,
    pub b: EqualizedConv2d,
}

impl ConvPair {
    pub fn new(c_in: usize, c_out: usize, device: &Device) -> Self {
        Self {
            a: EqualizedConv2dConfig::new(c_in, c_out, 3).init(device),
            b: EqualizedConv2dConfig::new(c_out, c_out, 3).init(device),
        }
    }

    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        self.b
            .forward_lrelu(self.a.forward_lrelu(x, SQRT_2), SQRT_2)
    }
}

/// 2x2 box downsampling (the mean of each 2x2 block), as plain reshapes.
pub fn box_downsample2(x: Tensor<4>) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    x.reshape([b, c, h / 2, 2, w / 2, 2])
        .mean_dim(5)
        .mean_dim(3)
        .reshape([b, c, h / 2, w / 2])
}

/// Encoder and decoder levels for `channels` (finest first) on `c_in` input channels; the
/// decoder's last level has `channels[0]` channels.
pub fn levels(c_in: usize, channels: &[usize], device: &Device) -> (Vec<ConvPair>, Vec<ConvPair>) {
    assert!(!channels.is_empty(), "at least one U-Net level");
    let mut down = Vec::new();
    let mut c = c_in;
    for &next in channels {
        down.push(ConvPair::new(c, next, device));
        c = next;
    }
    let mut up = Vec::new();
    for level in (0..channels.len() - 1).rev() {
        let skip = channels[level];
        up.push(ConvPair::new(c + skip, skip, device));
        c = skip;
    }
    (down, up)
}

/// The encoder and decoder applied to `x: [b, c_in, H, W]` -> `[b, channels[0], H, W]`;
/// `H` and `W` must divide by `2^(levels - 1)`.
pub fn encode_decode(down: &[ConvPair], up: &[ConvPair], x: Tensor<4>) -> Tensor<4> {
    let mut skips = Vec::with_capacity(down.len());
    let mut x = x;
    for (i, level) in down.iter().enumerate() {
        if i > 0 {
            x = box_downsample2(x);
        }
        x = level.forward(x);
        skips.push(x.clone());
    }
    skips.pop();
    for (level, skip) in up.iter().zip(skips.into_iter().rev()) {
        x = level.forward(Tensor::cat(vec![bilinear_upsample(x, 2), skip], 1));
    }
    x
}

/// Configuration of a [`UNet`].
#[derive(Config, Debug)]
pub struct UNetConfig {
    pub in_channels: usize,
    pub out_channels: usize,
    /// Channels per level, finest first.
    pub channels: Vec<usize>,
}

/// A U-Net with a 1x1 output convolution.
#[derive(Module, Debug)]
pub struct UNet {
    /// Encoder levels, finest first.
    pub down: Vec<ConvPair>,
    /// Decoder levels, coarsest first.
    pub up: Vec<ConvPair>,
    /// 1x1 to the output channels.
    pub out: EqualizedConv2d,
}

impl UNetConfig {
    /// The side an input's height and width must divide by.
    pub fn divisor(&self) -> usize {
        1 << self.channels.len().saturating_sub(1)
    }

    /// A network with freshly initialised parameters on `device`.
    pub fn init(&self, device: &Device) -> UNet {
        let (down, up) = levels(self.in_channels, &self.channels, device);
        let out = EqualizedConv2dConfig::new(self.channels[0], self.out_channels, 1).init(device);
        UNet { down, up, out }
    }
}

impl UNet {
    /// `x: [b, in_channels, H, W]` -> `[b, out_channels, H, W]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        self.out.forward(encode_decode(&self.down, &self.up, x))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::to_f32_vec;
    use burn::tensor::Distribution;

    #[test]
    fn shapes_and_gradients_reach_every_level() {
        let device = Device::flex().autodiff();
        let config = UNetConfig::new(3, 7, vec![4, 8, 8]);
        assert_eq!(config.divisor(), 4);
        let net = config.init(&device);
        let x = Tensor::<4>::random([2, 3, 16, 16], Distribution::Uniform(-1.0, 1.0), &device);
        let y = net.forward(x);
        assert_eq!(y.dims(), [2, 7, 16, 16]);
        let grads = y.powf_scalar(2.0).sum().backward();
        for w in [
            &net.down[0].a.weight,
            &net.down[2].b.weight,
            &net.up[1].a.weight,
        ] {
            let g = to_f32_vec(w.val().grad(&grads).unwrap());
            assert!(g.iter().all(|v| v.is_finite()) && g.iter().any(|v| *v != 0.0));
        }
    }

    #[test]
    fn box_downsampling_averages_blocks() {
        let device = Device::flex();
        let values: Vec<f32> = (0..16).map(|v| v as f32).collect();
        let x =
            Tensor::<4>::from_data(burn::tensor::TensorData::new(values, [1, 1, 4, 4]), &device);
        let y = to_f32_vec(box_downsample2(x));
        assert_eq!(y, vec![2.5, 4.5, 10.5, 12.5]);
    }
}
