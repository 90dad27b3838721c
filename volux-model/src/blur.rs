//! StyleGAN2's anti-aliasing FIR filter and its use before downsampling, as depthwise
//! convolutions, together with their adjoints.
//!
//! The filter is the outer product of `[1, 3, 3, 1]` with itself, normalised to sum 1
//! (`upfirdn2d.setup_filter([1, 3, 3, 1])`). It is symmetric, so convolution and correlation
//! agree. StyleGAN2 uses it in two places of the residual discriminator (paper section 3.4):
//!
//! - [`blur_downsample2`] is `upfirdn2d.downsample2d`: pad 1 on every side, filter, keep every
//!   second pixel; `h -> h / 2`. The skip branch of a block and nothing else.
//! - [`blur`] with `padding = 2` is the blur in front of a 3x3 stride-2 convolution
//!   (`conv2d_resample` with `down = 2`): `h -> h + 1`, and the convolution then gives `h / 2`.
//!
//! A 4-tap filter has no centre, so a stride-1 blur that keeps the size would need uneven
//! padding; the discriminator never needs one.
//!
//! The adjoints ([`blur_adjoint`], [`blur_downsample2_adjoint`]) are transposed convolutions
//! with the same filter, stride and padding. The discriminator's explicit input gradient
//! (`crate::discriminator`) uses them in its reverse sweep. All four run as
//! [`crate::fir_filter`]'s separable kernels (depthwise convolutions on backends other than
//! flex).

use burn::tensor::Tensor;

use crate::fir_filter::{Fir, fir2d, fir2d_adjoint};

/// The 1D taps before normalisation.
pub const FIR_TAPS: [f64; 4] = [1.0, 3.0, 3.0, 1.0];

/// The normalised 2D filter, row-major `[4, 4]`, summing to 1.
pub fn fir_filter_2d() -> [[f64; 4]; 4] {
    let sum: f64 = FIR_TAPS.iter().sum();
    let mut f = [[0.0; 4]; 4];
    for (i, row) in f.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = FIR_TAPS[i] * FIR_TAPS[j] / (sum * sum);
        }
    }
    f
}

/// The filter with `padding` and `stride`, as [`crate::fir_filter`] runs it.
fn fir(padding: usize, stride: usize) -> Fir {
    let sum: f64 = FIR_TAPS.iter().sum();
    let taps = FIR_TAPS.iter().map(|t| (t / sum) as f32).collect();
    Fir::new(taps, padding, stride)
}

/// Blurs every channel with zero padding `padding` on each side:
/// `[batch, channels, h, w] -> [batch, channels, h + 2 padding - 3, w + 2 padding - 3]`.
pub fn blur(x: Tensor<4>, padding: usize) -> Tensor<4> {
    fir2d(x, &fir(padding, 1))
}

/// The adjoint of [`blur`] with the same `padding`:
/// `[batch, channels, h', w'] -> [batch, channels, h' - 2 padding + 3, w' - 2 padding + 3]`.
pub fn blur_adjoint(y: Tensor<4>, padding: usize) -> Tensor<4> {
    let [_, _, h, w] = y.dims();
    fir2d_adjoint(
        y,
        &fir(padding, 1),
        [h + 3 - 2 * padding, w + 3 - 2 * padding],
    )
}

/// StyleGAN2's `downsample2d`: blur with padding 1, then keep every second pixel.
/// `[batch, channels, h, w] -> [batch, channels, h / 2, w / 2]` for even `h` and `w`.
pub fn blur_downsample2(x: Tensor<4>) -> Tensor<4> {
    let [_, _, h, w] = x.dims();
    assert!(
        h.is_multiple_of(2) && w.is_multiple_of(2),
        "blur_downsample2 needs even sizes, got {h}x{w}"
    );
    fir2d(x, &fir(1, 2))
}

/// The adjoint of [`blur_downsample2`]:
/// `[batch, channels, h, w] -> [batch, channels, 2 h, 2 w]`.
pub fn blur_downsample2_adjoint(y: Tensor<4>) -> Tensor<4> {
    let [_, _, h, w] = y.dims();
    fir2d_adjoint(y, &fir(1, 2), [2 * h, 2 * w])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::to_f32_vec;
    use burn::tensor::{Device, Distribution};

    /// Blur of one `[h, w]` plane in f64: zero padding `pad`, then every `stride`-th output.
    fn blur_ref(x: &[f64], [h, w]: [usize; 2], pad: usize, stride: usize) -> Vec<f64> {
        let f = fir_filter_2d();
        let ho = (h + 2 * pad - 4) / stride + 1;
        let wo = (w + 2 * pad - 4) / stride + 1;
        let mut y = vec![0.0; ho * wo];
        for i in 0..ho {
            for j in 0..wo {
                let mut acc = 0.0;
                for (u, row) in f.iter().enumerate() {
                    for (v, fv) in row.iter().enumerate() {
                        let (r, s) = (i * stride + u, j * stride + v);
                        if r >= pad && s >= pad && r - pad < h && s - pad < w {
                            acc += fv * x[(r - pad) * w + s - pad];
                        }
                    }
                }
                y[i * wo + j] = acc;
            }
        }
        y
    }

    fn random(shape: [usize; 4]) -> Tensor<4> {
        Tensor::<4>::random(shape, Distribution::Normal(0.0, 1.0), &Device::flex())
    }

    fn check_against_reference(x: Tensor<4>, y: Tensor<4>, pad: usize, stride: usize) {
        let [b, c, h, w] = x.dims();
        let [_, _, ho, wo] = y.dims();
        let xv = to_f32_vec(x);
        let yv = to_f32_vec(y);
        for plane in 0..b * c {
            let xp: Vec<f64> = xv[plane * h * w..(plane + 1) * h * w]
                .iter()
                .map(|v| f64::from(*v))
                .collect();
            let want = blur_ref(&xp, [h, w], pad, stride);
            assert_eq!(want.len(), ho * wo);
            for (k, want) in want.iter().enumerate() {
                let got = f64::from(yv[plane * ho * wo + k]);
                assert!(
                    (got - want).abs() < 1e-5,
                    "plane {plane} pixel {k}: {got} vs {want}"
                );
            }
        }
    }

    #[test]
    fn filter_is_the_normalised_outer_product() {
        let f = fir_filter_2d();
        let sum: f64 = f.iter().flatten().sum();
        assert!((sum - 1.0).abs() < 1e-15);
        assert_eq!(f[1][2], 9.0 / 64.0);
        assert_eq!(f[0][3], 1.0 / 64.0);
    }

    #[test]
    fn blur_matches_an_f64_loop() {
        for pad in [0, 1, 2] {
            let x = random([2, 3, 7, 6]);
            let y = blur(x.clone(), pad);
            assert_eq!(y.dims(), [2, 3, 7 + 2 * pad - 3, 6 + 2 * pad - 3]);
            check_against_reference(x, y, pad, 1);
        }
    }

    #[test]
    fn blur_downsample2_matches_an_f64_loop_and_halves() {
        let x = random([2, 3, 8, 6]);
        let y = blur_downsample2(x.clone());
        assert_eq!(y.dims(), [2, 3, 4, 3]);
        check_against_reference(x, y, 1, 2);
    }

    #[test]
    fn blur_downsample2_keeps_constants_inside() {
        // Sum-1 filter: a constant image stays constant away from the zero-padded border.
        let x = Tensor::<4>::ones([1, 1, 8, 8], &Device::flex()).mul_scalar(2.0);
        let y = to_f32_vec(blur_downsample2(x));
        for i in 1..3 {
            for j in 1..3 {
                assert!((y[i * 4 + j] - 2.0).abs() < 1e-6, "{y:?}");
            }
        }
    }

    /// `<A x, y>` against `<x, A^T y>`.
    fn assert_adjoint(ax: Tensor<4>, x: Tensor<4>, y: Tensor<4>, aty: Tensor<4>) {
        assert_eq!(ax.dims(), y.dims());
        assert_eq!(aty.dims(), x.dims());
        let lhs: f32 = (ax * y).sum().into_scalar();
        let rhs: f32 = (x * aty).sum().into_scalar();
        assert!(
            (lhs - rhs).abs() < 1e-4 * lhs.abs().max(1.0),
            "{lhs} vs {rhs}"
        );
    }

    #[test]
    fn blur_adjoint_is_the_transpose() {
        for pad in [0, 1, 2] {
            let x = random([2, 3, 8, 7]);
            let ax = blur(x.clone(), pad);
            let y = random(ax.dims());
            let aty = blur_adjoint(y.clone(), pad);
            assert_adjoint(ax, x, y, aty);
        }
    }

    #[test]
    fn blur_downsample2_adjoint_is_the_transpose() {
        for [h, w] in [[8, 8], [4, 6], [2, 2]] {
            let x = random([2, 3, h, w]);
            let ax = blur_downsample2(x.clone());
            let y = random(ax.dims());
            let aty = blur_downsample2_adjoint(y.clone());
            assert_adjoint(ax, x, y, aty);
        }
    }
}
