//! Tests of the fused activation against its reference, f64 loops and f64 central
//! differences.

use burn::tensor::{Device, TensorData};

use super::*;
use crate::backend::to_f32_vec;
use crate::flex_extension::simd_cap;
use crate::test_support::normals;
use volux_envmap::random::SplitMix64;

fn tensor<const D: usize>(values: &[f64], shape: [usize; D], device: &Device) -> Tensor<D> {
    let v: Vec<f32> = values.iter().map(|x| *x as f32).collect();
    Tensor::from_data(TensorData::new(v, shape), device)
}

/// `sum(activate(y, bias) * r)` and its gradients with respect to `y` and `bias`.
fn loss_and_grads(
    f: fn(Tensor<3>, Tensor<1>) -> Tensor<3>,
    y: &[f64],
    bias: &[f64],
    r: &[f64],
    shape: [usize; 3],
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let device = Device::flex().autodiff();
    let yt = tensor(y, shape, &device).require_grad();
    let bt = tensor(bias, [shape[2]], &device).require_grad();
    let out = f(yt.clone(), bt.clone());
    let grads = (out.clone() * tensor(r, shape, &device)).sum().backward();
    (
        to_f32_vec(out),
        to_f32_vec(yt.grad(&grads).unwrap()),
        to_f32_vec(bt.grad(&grads).unwrap()),
    )
}

fn assert_close(got: &[f32], want: &[f32], tol: f32, what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            (g - w).abs() <= tol * (1.0 + w.abs()),
            "{what}[{i}]: {g} vs {w}"
        );
    }
}

#[test]
fn fused_matches_the_reference_in_values_and_gradients() {
    let mut rng = SplitMix64::new(5);
    // 600 points: more than one task per batch element, the last one short; a few; one.
    for (p, o) in [(600, 5), (7, 5), (1, 1)] {
        let shape = [2, p, o];
        let n = shape.iter().product();
        let y: Vec<f64> = normals(&mut rng, n).iter().map(|v| 3.0 * v).collect();
        let bias = normals(&mut rng, o);
        let r = normals(&mut rng, n);
        let fused = loss_and_grads(activate, &y, &bias, &r, shape);
        let reference = loss_and_grads(activate_reference, &y, &bias, &r, shape);
        let what = format!("{p} points");
        assert_close(&fused.0, &reference.0, 1e-6, &format!("{what}: value"));
        assert_close(&fused.1, &reference.1, 1e-5, &format!("{what}: d/dy"));
        assert_close(&fused.2, &reference.2, 1e-4, &format!("{what}: d/dbias"));
        // Without autodiff the same kernel runs.
        let plain = to_f32_vec(activate(
            tensor(&y, shape, &Device::flex()),
            tensor(&bias, [o], &Device::flex()),
        ));
        assert_eq!(plain, fused.0, "{what}: flex without autodiff");
    }
}

/// The activation in f64: `gain (0.2 z + 0.8 softplus(z))` and its derivative.
fn activation_f64(z: f64) -> (f64, f64) {
    let softplus = z.max(0.0) + (-z.abs()).exp().ln_1p();
    let sigmoid = 1.0 / (1.0 + (-z).exp());
    (
        SMOOTH_GAIN * (0.2 * z + 0.8 * softplus),
        SMOOTH_GAIN * (0.2 + 0.8 * sigmoid),
    )
}

/// `sum(activate(y, bias) * r)` in f64.
fn loss_f64(y: &[f64], bias: &[f64], r: &[f64]) -> f64 {
    let o = bias.len();
    (0..y.len())
        .map(|i| activation_f64(y[i] + bias[i % o]).0 * r[i])
        .sum()
}

#[test]
fn gradients_match_f64_central_differences() {
    let mut rng = SplitMix64::new(9);
    let (p, o) = (6, 3);
    let shape = [1, p, o];
    let n = shape.iter().product();
    // Pre-activations from -6 to 6, where the curvature is.
    let y: Vec<f64> = normals(&mut rng, n).iter().map(|v| 2.5 * v).collect();
    let bias = normals(&mut rng, o);
    let r = normals(&mut rng, n);
    let (_, grad_y, grad_bias) = loss_and_grads(activate, &y, &bias, &r, shape);
    // The kernel sees f32 inputs: differentiate the f64 loss at those.
    let round = |v: &[f64]| -> Vec<f64> { v.iter().map(|x| f64::from(*x as f32)).collect() };
    let (y, bias) = (round(&y), round(&bias));
    let h = 1e-6;
    let fd = |at: &dyn Fn(f64) -> f64| (at(h) - at(-h)) / (2.0 * h);
    for k in 0..n {
        let want = fd(&|d| {
            let mut y = y.clone();
            y[k] += d;
            loss_f64(&y, &bias, &r)
        });
        let got = f64::from(grad_y[k]);
        assert!(
            (got - want).abs() < 1e-5 * (1.0 + want.abs()),
            "d/dy[{k}]: {got} vs {want}"
        );
    }
    for c in 0..o {
        let want = fd(&|d| {
            let mut bias = bias.clone();
            bias[c] += d;
            loss_f64(&y, &bias, &r)
        });
        let got = f64::from(grad_bias[c]);
        assert!(
            (got - want).abs() < 1e-5 * (1.0 + want.abs()),
            "d/dbias[{c}]: {got} vs {want}"
        );
    }
}

/// The worst relative error of [`exp_nonpositive`] on `[-87, 0]` and of [`ln_1p_unit`] on
/// `[0, 1]` against f64, over a dense sweep.
fn worst_errors() -> (f64, f64) {
    let n = 1 << 20;
    let mut worst = (0.0f64, 0.0f64);
    for i in 0..=n {
        let x = -87.0 * (i as f64 / n as f64);
        let x32 = x as f32;
        let want = f64::from(x32).exp();
        let got = f64::from(exp_nonpositive(x32));
        worst.0 = worst.0.max((got - want).abs() / want);
        let e = (i as f64 / n as f64) as f32;
        let want = f64::from(e).ln_1p();
        let got = f64::from(ln_1p_unit(e));
        if want > 0.0 {
            worst.1 = worst.1.max((got - want).abs() / want);
        } else {
            assert_eq!(got, 0.0);
        }
    }
    worst
}

#[test]
fn exp_and_ln_match_f64() {
    let (exp, ln) = worst_errors();
    // 2 and 3 ulp of f32 (the measured figures: docs/performance.md).
    assert!(exp < 2.4e-7, "exp: worst relative error {exp}");
    assert!(ln < 3.6e-7, "ln(1 + e): worst relative error {ln}");
    eprintln!("worst relative error: exp {exp:.3e}, ln(1 + e) {ln:.3e}");
    // The ends: exactly 1 at 0, the clamp below -87, NaN stays NaN.
    assert_eq!(exp_nonpositive(0.0), 1.0);
    assert_eq!(exp_nonpositive(-0.0), 1.0);
    for x in [-87.0f32, -100.0, -1e4, f32::NEG_INFINITY] {
        let v = exp_nonpositive(x);
        assert!(v > 0.0 && v <= 1.7e-38, "exp({x}) = {v}");
    }
    assert!(exp_nonpositive(f32::NAN).is_nan());
    assert_eq!(ln_1p_unit(0.0), 0.0);
    assert!((f64::from(ln_1p_unit(1e-30)) - 1e-30).abs() < 1e-36);
}

#[test]
fn stiff_and_zero_pre_activations_give_the_limits() {
    let g = SMOOTH_GAIN;
    let zs = [1e4, -1e4, 0.0, 88.0, -88.0, 1e-30, 3e38, -3e38];
    let p = zs.len();
    let r = vec![1.0; p];
    let (out, grad_y, grad_bias) = loss_and_grads(activate, &zs, &[0.0], &r, [1, p, 1]);
    assert!(
        out.iter()
            .chain(&grad_y)
            .chain(&grad_bias)
            .all(|v| v.is_finite())
    );
    // With r = 1, d loss / dz is a'(z): g at the top, 0.2 g at the bottom, 0.6 g at 0.
    let want_value = [g * 1e4, g * 0.2 * -1e4, g * 0.8 * 2f64.ln()];
    let want_first = [g, 0.2 * g, 0.6 * g];
    for i in 0..3 {
        let v = f64::from(out[i]);
        assert!(
            (v - want_value[i]).abs() < 1e-6 * (1.0 + want_value[i].abs()),
            "a({})",
            zs[i]
        );
        let d = f64::from(grad_y[i]);
        assert!((d - want_first[i]).abs() < 1e-6, "a'({})", zs[i]);
    }
    // The reference agrees on the finite cases, except for `d/dz` at exactly 0: it
    // differentiates `exp(-|z|)`, and autodiff takes `|z|`'s derivative at 0 to be 0, which
    // gives a wrong `a'(0)` there (the fused backward has it, checked above).
    let finite = &zs[..6];
    let reference = loss_and_grads(activate_reference, finite, &[0.0], &r[..6], [1, 6, 1]);
    assert_close(&out[..6], &reference.0, 1e-6, "stiff value");
    let (mut got, mut want) = (grad_y[..6].to_vec(), reference.1.clone());
    got.remove(2);
    want.remove(2);
    assert_close(&got, &want, 1e-5, "stiff d/dy");
}

/// The fused activation and pullback, values and gradients, compiled for every instruction
/// set this CPU has, against the tensor-op references.
#[test]
fn every_instruction_set_matches_the_reference() {
    let mut rng = SplitMix64::new(77);
    let shape = [2, 300, 7];
    let n: usize = shape.iter().product();
    let y: Vec<f64> = normals(&mut rng, n).iter().map(|v| 4.0 * v).collect();
    let bias = normals(&mut rng, 7);
    let r = normals(&mut rng, n);
    let u = normals(&mut rng, n);
    let want = loss_and_grads(activate_reference, &y, &bias, &r, shape);
    let pull = |f: fn(Tensor<3>, Tensor<3>, Tensor<1>) -> Tensor<3>| {
        let device = Device::flex().autodiff();
        let ut = tensor(&u, shape, &device).require_grad();
        let yt = tensor(&y, shape, &device).require_grad();
        let out = f(ut.clone(), yt.clone(), tensor(&bias, [7], &device));
        let grads = (out.clone() * tensor(&r, shape, &device)).sum().backward();
        [
            to_f32_vec(out),
            to_f32_vec(ut.grad(&grads).unwrap()),
            to_f32_vec(yt.grad(&grads).unwrap()),
        ]
    };
    let want_pull = pull(pullback::pullback_reference);
    simd_cap::each(|level| {
        let got = loss_and_grads(activate, &y, &bias, &r, shape);
        assert_close(&got.0, &want.0, 1e-6, &format!("{level:?}: value"));
        assert_close(&got.1, &want.1, 1e-5, &format!("{level:?}: d/dy"));
        assert_close(&got.2, &want.2, 1e-4, &format!("{level:?}: d/dbias"));
        let got = pull(pullback::pullback);
        for (k, what) in ["pullback", "d/du", "d/dy"].iter().enumerate() {
            assert_close(&got[k], &want_pull[k], 1e-5, &format!("{level:?}: {what}"));
        }
    });
}
