//! The mapping network (StyleGAN2; paper section 3.2 and appendix B): `z ~ N(0, I)` -> pixel
//! norm -> fully connected layers with leaky ReLU -> `w`, which every modulated layer turns into
//! its own style with its own affine.

use std::f64::consts::SQRT_2;

use burn::config::Config;
use burn::module::Module;
use burn::tensor::{Device, Tensor};

use crate::equalized::{EqualizedLinear, EqualizedLinearConfig};

/// Configuration of a [`MappingNetwork`].
#[derive(Config, Debug)]
pub struct MappingNetworkConfig {
    /// Dimension of `z` (256 default, 512 in the paper).
    #[config(default = 256)]
    pub z_dim: usize,
    /// Dimension of `w` and of every hidden layer (512 in the paper).
    #[config(default = 512)]
    pub w_dim: usize,
    /// Number of fully connected layers.
    #[config(default = 8)]
    pub layers: usize,
    /// Learning-rate multiplier of every layer.
    #[config(default = 0.01)]
    pub lr_multiplier: f64,
}

/// `z` to `w`.
#[derive(Module, Debug)]
pub struct MappingNetwork {
    /// The fully connected layers, first to last.
    pub layers: Vec<EqualizedLinear>,
}

/// Normalises each row to unit mean square (StyleGAN's pixel norm on `z`).
pub fn pixel_norm(x: Tensor<2>) -> Tensor<2> {
    let ms = x.clone().powi_scalar(2).mean_dim(1).add_scalar(1e-8);
    x / ms.sqrt()
}

impl MappingNetworkConfig {
    /// A network with freshly initialised parameters on `device`.
    pub fn init(&self, device: &Device) -> MappingNetwork {
        let layers = (0..self.layers)
            .map(|i| {
                let d_input = if i == 0 { self.z_dim } else { self.w_dim };
                EqualizedLinearConfig::new(d_input, self.w_dim)
                    .with_lr_multiplier(self.lr_multiplier)
                    .init(device)
            })
            .collect();
        MappingNetwork { layers }
    }
}

impl MappingNetwork {
    /// `z: [batch, z_dim] -> w: [batch, w_dim]`.
    pub fn forward(&self, z: Tensor<2>) -> Tensor<2> {
        self.layers
            .iter()
            .fold(pixel_norm(z), |x, layer| layer.forward_lrelu(x, SQRT_2))
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
    use burn::tensor::Distribution;

    #[test]
    fn maps_z_to_w_of_the_configured_width_and_unit_scale() {
        let device = Device::flex();
        let net = MappingNetworkConfig::new()
            .with_z_dim(64)
            .with_w_dim(128)
            .init(&device);
        let z = Tensor::<2>::random([256, 64], Distribution::Normal(0.0, 1.0), &device);
        let w = net.forward(z);
        assert_eq!(w.dims(), [256, 128]);
        // Equalized init and the sqrt(2) gain keep activations O(1) through 8 layers.
        let ms: f32 = w.powi_scalar(2).mean().into_scalar();
        assert!((0.1..10.0).contains(&ms), "mean square of w: {ms}");
        assert_eq!(net.num_params(), 64 * 128 + 128 + 7 * (128 * 128 + 128));
    }

    #[test]
    fn pixel_norm_makes_rows_unit_mean_square_and_ignores_scale() {
        let device = Device::flex();
        let x = Tensor::<2>::random([4, 32], Distribution::Normal(0.0, 3.0), &device);
        let a = pixel_norm(x.clone());
        let b = pixel_norm(x.mul_scalar(1e3));
        let ms: Vec<f32> = to_f32_vec(a.clone().powi_scalar(2).mean_dim(1));
        assert!(ms.iter().all(|m| (m - 1.0).abs() < 1e-4), "{ms:?}");
        let diff: f32 = (a - b).abs().max().into_scalar();
        assert!(diff < 1e-4);
    }
}
