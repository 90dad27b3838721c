use burn::optim::GradientsParams;
use burn::tensor::{Device, TensorData};
use volux_envmap::random::SplitMix64;

use super::*;

fn values(rng: &mut SplitMix64, n: usize, scale: f64) -> Vec<f32> {
    (0..n)
        .map(|_| ((rng.next_f64() - 0.5) * scale) as f32)
        .collect()
}

fn read(t: Tensor<2>) -> Vec<f32> {
    volux_model::backend::to_f32_vec(t)
}

/// Five steps of both optimizers on the same parameter and gradients, with betas that
/// exercise both moments (StyleGAN2's `beta_1 = 0` included); parameters and moments agree
/// to f32 rounding at every step.
#[test]
fn fused_steps_match_burns_adam() {
    let device = Device::flex();
    for (b1, b2) in [(0.0f32, 0.99f32), (0.9, 0.999), (0.5, 0.9)] {
        let mut rng = SplitMix64::new(3);
        // 70 000 elements: several tasks, the last one short; gradients from 1e-12 to 1e3.
        let shape = [350, 200];
        let n = shape[0] * shape[1];
        let start =
            Tensor::<2>::from_data(TensorData::new(values(&mut rng, n, 2.0), shape), &device);
        let fused = FusedAdam::new(b1, b2, 1e-8);
        let reference = AdamConfig::new()
            .with_beta_1(b1)
            .with_beta_2(b2)
            .with_epsilon(1e-8)
            .build();
        let (mut p_fused, mut p_ref) = (start.clone(), start);
        let (mut s_fused, mut s_ref) = (None, None);
        for step in 0..5 {
            let g: Vec<f32> = values(&mut rng, n, 2.0)
                .iter()
                .enumerate()
                .map(|(i, g)| g * 10f32.powi((i % 16) as i32 - 12))
                .collect();
            let g = Tensor::<2>::from_data(TensorData::new(g, shape), &device);
            (p_fused, s_fused) = fused.step(0.0025, p_fused, g.clone(), s_fused);
            (p_ref, s_ref) = reference.step(0.0025, p_ref, g, s_ref);
            let (a, b) = (s_fused.clone().unwrap(), s_ref.clone().unwrap());
            assert_eq!(a.momentum.time, b.momentum.time);
            for (what, got, want) in [
                ("parameter", read(p_fused.clone()), read(p_ref.clone())),
                ("m", read(a.momentum.moment_1), read(b.momentum.moment_1)),
                ("v", read(a.momentum.moment_2), read(b.momentum.moment_2)),
            ] {
                for (i, (x, y)) in got.iter().zip(&want).enumerate() {
                    assert!(
                        (x - y).abs() <= 2e-6 * y.abs().max(1e-30),
                        "betas ({b1}, {b2}) step {step} {what}[{i}]: {x} vs {y}"
                    );
                }
            }
        }
    }
}

/// The update in f64 on a few values, against the formula of the module documentation.
#[test]
fn one_step_matches_the_formula_in_f64() {
    let device = Device::flex();
    let (b1, b2, eps, lr) = (0.0f64, 0.99f64, 1e-8f64, 0.002f64);
    let p = [0.5f32, -1.0, 3.0, 0.0];
    // Up to 1e15: the square of 1e20 would overflow f32 (the step is then 0, as in Burn's Adam).
    let g = [1e-3f32, -2.0, 0.0, 1e15];
    let fused = FusedAdam::new(b1 as f32, b2 as f32, eps as f32);
    let t = |v: &[f32]| Tensor::<2>::from_data(TensorData::new(v.to_vec(), [1, 4]), &device);
    let (p1, s1) = fused.step(lr, t(&p), t(&g), None);
    let (p2, _) = fused.step(lr, p1.clone(), t(&g), s1);
    let (p1, p2) = (read(p1), read(p2));
    let mut m = [0.0f64; 4];
    let mut v = [0.0f64; 4];
    let mut x: Vec<f64> = p.iter().map(|p| f64::from(*p)).collect();
    for (step, got) in [(1, &p1), (2, &p2)] {
        let c2 = (1.0 - b2.powi(step)).sqrt();
        for i in 0..4 {
            let gi = f64::from(g[i]);
            m[i] = b1 * m[i] + (1.0 - b1) * gi;
            v[i] = b2 * v[i] + (1.0 - b2) * gi * gi;
            x[i] -= lr * c2 / (1.0 - b1.powi(step)) * m[i] / (v[i].sqrt() + eps * c2);
            let got = f64::from(got[i]);
            assert!(
                (got - x[i]).abs() <= 1e-6 * (1.0 + x[i].abs()),
                "step {step} [{i}]: {got} vs {}",
                x[i]
            );
        }
    }
}

/// A whole module through `ModuleOptimizer`, as training steps it: the fused optimizer and
/// Burn's give the same parameters, and a NaN gradient gives NaN parameters (the training
/// loop's finiteness check then undoes the step), never a panic.
#[test]
fn module_steps_agree_and_nan_propagates() {
    use burn::module::Module;
    use volux_model::equalized::EqualizedLinearConfig;
    let device = Device::flex().autodiff();
    let layer = EqualizedLinearConfig::new(6, 5).init(&device);
    let x = Tensor::<2>::from_data(
        TensorData::new(values(&mut SplitMix64::new(5), 24, 2.0), [4, 6]),
        &device,
    );
    let grads_of = |l: &volux_model::equalized::EqualizedLinear, x: Tensor<2>| {
        GradientsParams::from_grads(l.forward(x).square().sum().backward(), l)
    };
    let mut fused = burn::optim::ModuleOptimizer::from(FusedAdam::new(0.0, 0.99, 1e-8));
    let mut plain = AdamConfig::new()
        .with_beta_1(0.0)
        .with_beta_2(0.99)
        .with_epsilon(1e-8)
        .init();
    let (mut a, mut b) = (layer.clone(), layer);
    for _ in 0..3 {
        let ga = grads_of(&a, x.clone());
        let gb = grads_of(&b, x.clone());
        a = fused.step(0.01, a, ga);
        b = plain.step(0.01, b, gb);
    }
    let (wa, wb) = (read(a.weight.val().inner()), read(b.weight.val().inner()));
    for (x, y) in wa.iter().zip(&wb) {
        assert!((x - y).abs() <= 1e-6 * (1.0 + y.abs()), "{x} vs {y}");
    }
    let nan = x.clone().mul_scalar(f32::NAN);
    let g = grads_of(&a, nan);
    let a = fused.step(0.01, a, g);
    assert!(read(a.weight.val().inner()).iter().all(|w| w.is_nan()));
    let _ = a.num_params();
}
