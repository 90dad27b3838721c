//! Fourier positional encoding of 3D points (NeRF; paper section 3.2): `x -> [x, sin(2^k pi x),
//! cos(2^k pi x)]` for `k = 0..frequencies`, the NeIIF's input.

use std::f64::consts::PI;

use burn::config::Config;
use burn::module::Module;
use burn::tensor::Tensor;

/// Configuration of a [`PositionalEncoding`].
#[derive(Config, Debug)]
pub struct PositionalEncodingConfig {
    /// Number of octaves `F` (10 in the paper).
    #[config(default = 10)]
    pub frequencies: usize,
    /// Whether the raw coordinates come first in the output.
    #[config(default = true)]
    pub include_input: bool,
}

/// The encoding; it has no parameters.
#[derive(Module, Debug)]
pub struct PositionalEncoding {
    pub frequencies: usize,
    pub include_input: bool,
}

impl PositionalEncodingConfig {
    pub fn init(&self) -> PositionalEncoding {
        PositionalEncoding {
            frequencies: self.frequencies,
            include_input: self.include_input,
        }
    }
}

impl PositionalEncoding {
    /// Output features per input coordinate triple: `3 (include_input) + 6 F`.
    pub fn output_dim(&self) -> usize {
        3 * usize::from(self.include_input) + 6 * self.frequencies
    }

    /// `[points, 3] -> [points, output_dim]`, laid out as `[x, sin(pi x), cos(pi x),
    /// sin(2 pi x), cos(2 pi x), ...]` with each block holding the three coordinates.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let mut parts = Vec::with_capacity(1 + 2 * self.frequencies);
        if self.include_input {
            parts.push(x.clone());
        }
        for k in 0..self.frequencies {
            let scaled = x.clone().mul_scalar(PI * 2f64.powi(k as i32));
            parts.push(scaled.clone().sin());
            parts.push(scaled.cos());
        }
        Tensor::cat(parts, 1)
    }

    /// The encoding and its derivative: `[points, 3] -> ([points, output_dim],
    /// [points, output_dim])`, where column `c` of the second is `d enc_c / d x_{c mod 3}`.
    /// Every feature depends on one coordinate only (column `c` on coordinate `c mod 3`), so
    /// this diagonal is the whole Jacobian: the NeIIF's reverse sweep ends with it.
    pub fn forward_with_derivative(&self, x: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let [points, _] = x.dims();
        let device = x.device();
        let mut parts = Vec::with_capacity(1 + 2 * self.frequencies);
        let mut derivs = Vec::with_capacity(1 + 2 * self.frequencies);
        if self.include_input {
            parts.push(x.clone());
            derivs.push(Tensor::ones([points, 3], &device));
        }
        for k in 0..self.frequencies {
            let f = PI * 2f64.powi(k as i32);
            let scaled = x.clone().mul_scalar(f);
            let (sin, cos) = (scaled.clone().sin(), scaled.cos());
            derivs.push(cos.clone().mul_scalar(f));
            derivs.push(sin.clone().mul_scalar(-f));
            parts.push(sin);
            parts.push(cos);
        }
        (Tensor::cat(parts, 1), Tensor::cat(derivs, 1))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::to_f32_vec;
    use burn::tensor::{Device, TensorData};

    #[test]
    fn matches_the_formula_in_f64() {
        let device = Device::flex();
        let enc = PositionalEncodingConfig::new().init();
        assert_eq!(enc.output_dim(), 63);
        let pts = [[0.1f64, -0.7, 0.35], [0.9, 0.0, -0.05]];
        let data: Vec<f32> = pts.iter().flatten().map(|v| *v as f32).collect();
        let out = enc.forward(Tensor::<2>::from_data(
            TensorData::new(data, [2, 3]),
            &device,
        ));
        assert_eq!(out.dims(), [2, 63]);
        let out: Vec<f32> = to_f32_vec(out);
        for (p, x) in pts.iter().enumerate() {
            let mut want: Vec<f64> = x.to_vec();
            for k in 0..10 {
                let f = PI * 2f64.powi(k);
                want.extend(x.iter().map(|v| (f * v).sin()));
                want.extend(x.iter().map(|v| (f * v).cos()));
            }
            for (i, w) in want.iter().enumerate() {
                // f32 arguments up to 512 pi: absolute error grows with the octave.
                let got = f64::from(out[p * 63 + i]);
                assert!(
                    (got - w).abs() < 2e-4,
                    "point {p} feature {i}: {got} vs {w}"
                );
            }
        }
    }

    #[test]
    fn derivative_matches_central_differences() {
        let device = Device::flex();
        let enc = PositionalEncodingConfig::new().with_frequencies(4).init();
        let x = [0.3f64, -0.45, 0.8];
        let at = |p: [f64; 3]| {
            let data: Vec<f32> = p.iter().map(|v| *v as f32).collect();
            Tensor::<2>::from_data(TensorData::new(data, [1, 3]), &device)
        };
        let (_, deriv) = enc.forward_with_derivative(at(x));
        let deriv = to_f32_vec(deriv);
        let h = 1e-3;
        for j in 0..3 {
            let (mut a, mut b) = (x, x);
            a[j] += h;
            b[j] -= h;
            let fa = to_f32_vec(enc.forward(at(a)));
            let fb = to_f32_vec(enc.forward(at(b)));
            for c in 0..enc.output_dim() {
                let fd = (f64::from(fa[c]) - f64::from(fb[c])) / (2.0 * h);
                // Column c depends on coordinate c mod 3 alone.
                let got = if c % 3 == j { f64::from(deriv[c]) } else { 0.0 };
                // Central differences of sin(8 pi x) with h = 1e-3 are good to ~1e-3 relative.
                assert!(
                    (got - fd).abs() < 5e-3 * (1.0 + fd.abs()),
                    "j {j} c {c}: {got} vs {fd}"
                );
            }
        }
    }

    #[test]
    fn can_leave_out_the_raw_input() {
        let enc = PositionalEncodingConfig::new()
            .with_frequencies(4)
            .with_include_input(false)
            .init();
        assert_eq!(enc.output_dim(), 24);
        let out = enc.forward(Tensor::<2>::zeros([5, 3], &Device::flex()));
        assert_eq!(out.dims(), [5, 24]);
    }
}
