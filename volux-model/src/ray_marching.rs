//! Compositing along rays (paper eq. 1-2, the quadrature of NeRF): for samples `i` along a ray
//! with densities `sigma_i` and segment lengths `delta_i`,
//! `w_i = T_i (1 - exp(-sigma_i delta_i))`, `T_i = exp(-sum_{j<i} sigma_j delta_j)`, and every
//! accumulated quantity (albedo, normal, diffuse, specular, features, depth) is `sum_i w_i q_i`.
//!
//! `T_i` comes from an exclusive cumulative sum of optical depth, never from a cumulative
//! product of `1 - alpha`: with densities of 1e4 the product underflows and its gradient turns
//! into NaN, while `exp(-sum)` just goes to zero. The weights of a ray sum to
//! `1 - exp(-total optical depth) <= 1`. Like EG3D's ray marcher, this file knows nothing of
//! cameras or networks.

use burn::tensor::Tensor;

/// Compositing weights `[rays, samples]` from densities and segment lengths (both
/// `[rays, samples]`, non-negative).
pub fn weights(sigma: Tensor<2>, delta: Tensor<2>) -> Tensor<2> {
    let [rays, samples] = sigma.dims();
    let tau = sigma * delta; // optical depth of each segment
    let inclusive = tau.clone().cumsum(1);
    // Exclusive sum by shifting, exact (no `inclusive - tau` cancellation).
    let exclusive = if samples > 1 {
        Tensor::cat(
            vec![
                Tensor::zeros([rays, 1], &inclusive.device()),
                inclusive.narrow(1, 0, samples - 1),
            ],
            1,
        )
    } else {
        Tensor::zeros([rays, 1], &inclusive.device())
    };
    let transmittance = exclusive.neg().exp();
    // 1 - exp(-tau), computed as -expm1(-tau) would be; tau >= 0 keeps it in [0, 1].
    let alpha = tau.neg().exp().neg().add_scalar(1.0);
    transmittance * alpha
}

/// `sum_i w_i q_i`: `[rays, samples]` weights and `[rays, samples, channels]` values to
/// `[rays, channels]`.
pub fn accumulate(weights: Tensor<2>, values: Tensor<3>) -> Tensor<2> {
    let [rays, samples, channels] = values.dims();
    (values * weights.reshape([rays, samples, 1]))
        .sum_dim(1)
        .reshape([rays, channels])
}

/// Accumulated opacity `sum_i w_i`, `[rays]`.
pub fn opacity(weights: Tensor<2>) -> Tensor<1> {
    let [rays, _] = weights.dims();
    weights.sum_dim(1).reshape([rays])
}

/// `accumulated + (1 - opacity) background`, compositing `[rays, channels]` over a constant
/// background colour (the dataset's).
pub fn over_background(
    accumulated: Tensor<2>,
    opacity: Tensor<1>,
    background: &[f32],
) -> Tensor<2> {
    let [rays, channels] = accumulated.dims();
    assert_eq!(
        background.len(),
        channels,
        "one background value per channel"
    );
    let device = accumulated.device();
    let bg = Tensor::<1>::from_floats(background, &device).reshape([1, channels]);
    let clear = opacity.neg().add_scalar(1.0).reshape([rays, 1]);
    accumulated + clear * bg
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::to_f32_vec;
    use burn::tensor::{Device, TensorData};
    use volux_envmap::random::SplitMix64;

    fn t2(v: &[f64], shape: [usize; 2], device: &Device) -> Tensor<2> {
        let v: Vec<f32> = v.iter().map(|x| *x as f32).collect();
        Tensor::from_data(TensorData::new(v, shape), device)
    }

    /// The plain f64 reference: a loop along each ray.
    fn weights_reference(sigma: &[f64], delta: &[f64], samples: usize) -> Vec<f64> {
        let mut w = Vec::with_capacity(sigma.len());
        for r in 0..sigma.len() / samples {
            let mut depth = 0.0f64;
            for i in 0..samples {
                let tau = sigma[r * samples + i] * delta[r * samples + i];
                w.push((-depth).exp() * (1.0 - (-tau).exp()));
                depth += tau;
            }
        }
        w
    }

    #[test]
    fn weights_match_the_f64_reference() {
        let device = Device::flex();
        let mut rng = SplitMix64::new(3);
        let (rays, samples) = (16, 24);
        let sigma: Vec<f64> = (0..rays * samples)
            .map(|_| rng.next_f64().powi(3) * 50.0)
            .collect();
        let delta: Vec<f64> = (0..rays * samples)
            .map(|_| 0.01 + 0.05 * rng.next_f64())
            .collect();
        let got = to_f32_vec(weights(
            t2(&sigma, [rays, samples], &device),
            t2(&delta, [rays, samples], &device),
        ));
        let want = weights_reference(&sigma, &delta, samples);
        for (g, w) in got.iter().zip(&want) {
            assert!((f64::from(*g) - w).abs() < 1e-6, "{g} vs {w}");
        }
    }

    #[test]
    fn uniform_medium_has_the_analytic_opacity() {
        let device = Device::flex();
        let (samples, length, sigma) = (64, 0.8, 3.0);
        let s = t2(&vec![sigma; samples], [1, samples], &device);
        let d = t2(
            &vec![length / samples as f64; samples],
            [1, samples],
            &device,
        );
        let o: f32 = opacity(weights(s, d)).into_scalar();
        assert!((f64::from(o) - (1.0 - (-sigma * length).exp())).abs() < 1e-6);
    }

    #[test]
    fn stiff_and_empty_rays_stay_finite_and_sum_to_at_most_one() {
        let device = Device::flex().autodiff();
        let samples = 32;
        let mut sigma = vec![0.0; samples]; // empty ray
        sigma.extend(vec![1e4; samples]); // a wall of density 1e4
        sigma.extend((0..samples).map(|i| if i == 10 { 1e4 } else { 1e-3 })); // thin hard shell
        let delta_short = vec![1e-6; samples]; // very short segments
        let mut delta = vec![0.05; 2 * samples];
        delta.extend(delta_short);
        let s = t2(&sigma, [3, samples], &device).require_grad();
        let d = t2(&delta, [3, samples], &device);
        let w = weights(s.clone(), d);
        let values = Tensor::<3>::ones([3, samples, 2], &device);
        let acc = over_background(
            accumulate(w.clone(), values),
            opacity(w.clone()),
            &[0.25, 0.5],
        );
        let grads = acc.clone().sum().backward();
        let g = to_f32_vec(s.grad(&grads).unwrap());
        assert!(g.iter().all(|v| v.is_finite()), "gradient {g:?}");
        let sums: Vec<f32> = to_f32_vec(w.clone().sum_dim(1));
        assert!(
            sums.iter().all(|s| (0.0..=1.0 + 1e-6).contains(s)),
            "{sums:?}"
        );
        assert_eq!(sums[0], 0.0, "an empty ray is transparent");
        assert!((sums[1] - 1.0).abs() < 1e-6, "a wall is opaque");
        let acc = to_f32_vec(acc);
        assert_eq!(
            &acc[0..2],
            &[0.25, 0.5],
            "an empty ray shows the background"
        );
        assert!((acc[2] - 1.0).abs() < 1e-6 && (acc[3] - 1.0).abs() < 1e-6);
        assert!(acc.iter().all(|v| v.is_finite()));
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let device = Device::flex().autodiff();
        let sigma = [0.5, 2.0, 7.0, 1.0, 0.0, 3.0];
        let delta = [0.1, 0.2, 0.05, 0.3, 0.1, 0.2];
        let q = [0.3, -1.0, 2.0, 0.5, 4.0, 1.5];
        let loss_f64 = |s: &[f64]| -> f64 {
            weights_reference(s, &delta, 6)
                .iter()
                .zip(&q)
                .map(|(w, q)| w * q)
                .sum()
        };
        let s = t2(&sigma, [1, 6], &device).require_grad();
        let w = weights(s.clone(), t2(&delta, [1, 6], &device));
        let loss = (w * t2(&q, [1, 6], &device)).sum();
        let g = to_f32_vec(s.grad(&loss.backward()).unwrap());
        for i in 0..6 {
            let (mut a, mut b) = (sigma, sigma);
            a[i] += 1e-6;
            b[i] -= 1e-6;
            let fd = (loss_f64(&a) - loss_f64(&b)) / 2e-6;
            assert!(
                (f64::from(g[i]) - fd).abs() < 1e-4 * (1.0 + fd.abs()),
                "{i}: {} vs {fd}",
                g[i]
            );
        }
    }
}
