//! Progressive growing on the discriminator's side (PGGAN, which the paper cites for its
//! stage 1): while the generator's upsampling blocks fade in, the high-resolution albedo
//! discriminator sees its inputs, real and fake alike, with the resolutions that are not yet
//! grown faded out in the same way. So `D_A` (high) cannot tell reals from fakes by detail
//! the generator is not yet allowed to make, and it grows with the generator.
//!
//! With `n` blocks and fade weights `alpha_1 .. alpha_n` (block 1 the lowest), an image `x`
//! at the output resolution becomes
//!
//! ```text
//! r_0 = area_downsample(x, 2^n)
//! r_k = up(r_{k-1}) + alpha_k (area_downsample(x, 2^(n-k)) - up(r_{k-1}))
//! ```
//!
//! with `up` the bilinear x2 upsampling the generator's albedo path uses. All weights 1 give
//! `x` itself; all 0 give `x` brought to the volume resolution and bilinearly back up, which
//! is what the generator's albedo is before any block has faded in.

use burn::tensor::Tensor;
use volux_model::upsampler::bilinear_upsample;

use crate::losses::area_downsample;

/// `x: [b, c, H, W]` as the high-resolution discriminator sees it at fade weights `fade` (one
/// per upsampling block, lowest first; `None`: fully grown, `x` itself).
pub fn faded_input(x: Tensor<4>, fade: Option<&[f64]>) -> Tensor<4> {
    let Some(fade) = fade else {
        return x;
    };
    if fade.iter().all(|&a| a >= 1.0) {
        return x;
    }
    let n = fade.len();
    let mut r = area_downsample(x.clone(), 1 << n);
    for (k, &alpha) in fade.iter().enumerate() {
        let up = bilinear_upsample(r, 2);
        let target = area_downsample(x.clone(), 1 << (n - k - 1));
        r = if alpha >= 1.0 {
            target
        } else if alpha <= 0.0 {
            up
        } else {
            up.clone() + (target - up).mul_scalar(alpha)
        };
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, Distribution};
    use volux_model::backend::to_f32_vec;

    fn close(a: Tensor<4>, b: Tensor<4>) -> f32 {
        to_f32_vec(a)
            .iter()
            .zip(to_f32_vec(b))
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
    }

    #[test]
    fn grown_is_the_image_and_ungrown_is_its_low_resolution_upsampled() {
        let device = Device::flex();
        let x = Tensor::<4>::random([2, 3, 16, 16], Distribution::Normal(0.0, 1.0), &device);
        assert_eq!(close(faded_input(x.clone(), None), x.clone()), 0.0);
        assert_eq!(
            close(faded_input(x.clone(), Some(&[1.0, 1.0])), x.clone()),
            0.0
        );
        // Nothing grown: the 4x4 average, bilinearly up twice.
        let low = bilinear_upsample(bilinear_upsample(area_downsample(x.clone(), 4), 2), 2);
        assert!(close(faded_input(x.clone(), Some(&[0.0, 0.0])), low) < 1e-6);
        // The first block grown: the 8x8 average, up once.
        let mid = bilinear_upsample(area_downsample(x.clone(), 2), 2);
        assert!(close(faded_input(x.clone(), Some(&[1.0, 0.0])), mid.clone()) < 1e-6);
        // Half way through the second block: the mean of the two.
        let half = (mid.clone() + x.clone()).mul_scalar(0.5);
        assert!(close(faded_input(x.clone(), Some(&[1.0, 0.5])), half) < 1e-6);
    }

    #[test]
    fn a_constant_image_is_unchanged_at_any_fade() {
        let device = Device::flex();
        let x = Tensor::<4>::ones([1, 3, 8, 8], &device).mul_scalar(0.7);
        for fade in [[0.0], [0.3], [1.0]] {
            assert!(close(faded_input(x.clone(), Some(&fade)), x.clone()) < 1e-6);
        }
    }
}
