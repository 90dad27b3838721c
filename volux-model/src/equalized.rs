//! Equalized-learning-rate layers (StyleGAN / StyleGAN2): parameters are stored at unit scale
//! and multiplied at run time by `lr_multiplier / sqrt(fan_in)` (weights) and `lr_multiplier`
//! (biases). Adam's step is then the same for every layer in the effective weights' own scale,
//! and a layer with `lr_multiplier = 0.01` (the mapping network) learns 100x slower. The
//! paper's learning rates (0.0022 / 0.0025) assume this parameterisation.

use burn::config::Config;
use burn::module::{Module, Param};
use burn::tensor::{Device, Distribution, Tensor};

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
        let y = x.matmul(self.effective_weight().transpose());
        match self.effective_bias() {
            Some(b) => y + b.unsqueeze_dim(0),
            None => y,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::to_f32_vec;
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
}
