//! The relighting network (paper section 3.3): a shallow U-Net on `[A_hi, D_up, S_up, F_hi]`
//! that produces the relit image `I_relit`.
//!
//! Decisions the paper leaves open (ARCHITECTURE.md): the network is residual on the Phong
//! image, `I_relit = 2 tonemap(A_hi D_up + S_up) - 1 + U(inputs)`, with the U-Net's last layer
//! initialised to zero, so a fresh generator already relights physically and the U-Net learns
//! what Phong lacks (the paper's "higher order light transport"). HDR shading goes in through
//! `log1p` (a 1e5 sun stays finite and well scaled, docs/conventions.md), albedo as `2 A - 1`. The tone
//! map is [`tonemap_srgb`], the same curve as `volux_envmap::io::tonemap` at exposure 1, which
//! the data pipeline uses for its pseudo-ground-truth relit images.

use burn::config::Config;
use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor};

use crate::equalized::{EqualizedConv2d, EqualizedConv2dConfig};
use crate::unet::{self, ConvPair};

/// `[b, 3, h, w]` linear HDR -> sRGB in [0, 1]: luminance Reinhard `x / (1 + Y)`, then the sRGB
/// transfer curve. Differentiable everywhere (the curve's power runs on values clamped into
/// its own branch, so the linear toe gets no infinite derivative).
pub fn tonemap_srgb(x: Tensor<4>) -> Tensor<4> {
    let [b, _, h, w] = x.dims();
    let x = x.clamp_min(0.0);
    let lum = x.clone().narrow(1, 0, 1).mul_scalar(0.2126)
        + x.clone().narrow(1, 1, 1).mul_scalar(0.7152)
        + x.clone().narrow(1, 2, 1).mul_scalar(0.0722);
    let y = (x / lum.add_scalar(1.0)).clamp_max(1.0);
    let toe = y.clone().lower_equal_elem(0.003_130_8);
    let curve = y
        .clone()
        .clamp_min(0.003_130_8)
        .powf_scalar(1.0 / 2.4)
        .mul_scalar(1.055)
        .sub_scalar(0.055);
    let out = curve.mask_where(toe, y.mul_scalar(12.92));
    debug_assert_eq!(out.dims(), [b, 3, h, w]);
    out
}

/// Configuration of a [`RelightingNet`].
#[derive(Config, Debug)]
pub struct RelightingConfig {
    /// Feature channels of `F_hi` (the upsampler's output minus its three albedo channels).
    pub feature_channels: usize,
    /// Channels per U-Net level, finest first (two levels: one downsampling).
    #[config(default = "vec![32, 64]")]
    pub channels: Vec<usize>,
}

/// The U-Net (its levels: [`crate::unet`]).
#[derive(Module, Debug)]
pub struct RelightingNet {
    /// Encoder levels, finest first.
    pub down: Vec<ConvPair>,
    /// Decoder levels, coarsest first (each after an upsampling and a skip concatenation).
    pub up: Vec<ConvPair>,
    /// 1x1 to the RGB residual, stored weight initialised to zero.
    pub out: EqualizedConv2d,
}

impl RelightingConfig {
    /// Input channels: albedo, diffuse and specular (3 each) and the features.
    pub fn in_channels(&self) -> usize {
        9 + self.feature_channels
    }

    /// A network with freshly initialised parameters on `device`.
    pub fn init(&self, device: &Device) -> RelightingNet {
        let (down, up) = unet::levels(self.in_channels(), &self.channels, device);
        let c_in = self.channels[0];
        let mut out = EqualizedConv2dConfig::new(c_in, 3, 1).init(device);
        out.weight = Param::from_tensor(Tensor::zeros([3, c_in, 1, 1], device));
        RelightingNet { down, up, out }
    }
}

impl RelightingNet {
    /// `albedo: [b, 3, H, W]` in [0, 1], `diffuse`, `specular`: `[b, 3, H, W]` linear HDR,
    /// `features: [b, feature_channels, H, W]` -> `I_relit: [b, 3, H, W]` in network units
    /// (sRGB mapped to [-1, 1]). `H` and `W` must divide by `2^(levels - 1)`.
    pub fn forward(
        &self,
        albedo: Tensor<4>,
        diffuse: Tensor<4>,
        specular: Tensor<4>,
        features: Tensor<4>,
    ) -> Tensor<4> {
        let phong = tonemap_srgb(albedo.clone() * diffuse.clone() + specular.clone())
            .mul_scalar(2.0)
            .sub_scalar(1.0);
        let x = Tensor::cat(
            vec![
                albedo.mul_scalar(2.0).sub_scalar(1.0),
                diffuse.clamp_min(0.0).log1p(),
                specular.clamp_min(0.0).log1p(),
                features,
            ],
            1,
        );
        let x = unet::encode_decode(&self.down, &self.up, x);
        phong + self.out.forward(x)
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
    use volux_envmap::io::tonemap;

    #[test]
    fn tonemap_matches_the_envmap_preview_curve() {
        let device = Device::flex();
        let texels: Vec<[f32; 3]> = (0..64)
            .map(|i| {
                let s = 10f32.powf(i as f32 / 8.0 - 4.0);
                [s, 0.5 * s, 2.0 * s * (i % 3) as f32]
            })
            .collect();
        let want = tonemap(&texels, 1.0);
        let flat: Vec<f32> = (0..3)
            .flat_map(|c| texels.iter().map(move |t| t[c]))
            .collect();
        let x = Tensor::<4>::from_data(TensorData::new(flat, [1, 3, 1, 64]), &device);
        let got = to_f32_vec(tonemap_srgb(x));
        for (i, w) in want.iter().enumerate() {
            for c in 0..3 {
                let g = got[c * 64 + i] * 255.0;
                assert!(
                    (g - f32::from(w[c])).abs() <= 0.51,
                    "texel {i} c {c}: {g} vs {}",
                    w[c]
                );
            }
        }
    }

    #[test]
    fn a_fresh_network_outputs_the_phong_image_and_learns_a_residual() {
        let device = Device::flex().autodiff();
        let net = RelightingConfig::new(5)
            .with_channels(vec![8, 16])
            .init(&device);
        let rand = |c, s| Tensor::<4>::random([2, c, 8, 8], Distribution::Uniform(0.0, s), &device);
        let (a, d, s, f) = (rand(3, 1.0), rand(3, 1e5), rand(3, 4.0), rand(5, 1.0));
        let out = net.forward(a.clone(), d.clone(), s.clone(), f);
        assert_eq!(out.dims(), [2, 3, 8, 8]);
        let phong = tonemap_srgb(a * d + s).mul_scalar(2.0).sub_scalar(1.0);
        let diff: f32 = (out.clone() - phong).abs().max().into_scalar();
        assert_eq!(diff, 0.0);
        let grads = out.sum().backward();
        let g = to_f32_vec(net.out.weight.val().grad(&grads).unwrap());
        assert!(g.iter().all(|v| v.is_finite()) && g.iter().any(|v| *v != 0.0));
    }
}
