use std::f64::consts::SQRT_2;

use burn::tensor::{Device, TensorData};
use volux_envmap::random::SplitMix64;

use super::*;
use crate::backend::to_f32_vec;
use crate::test_support::normals;

fn tensor<const D: usize>(values: &[f64], shape: [usize; D], device: &Device) -> Tensor<D> {
    let v: Vec<f32> = values.iter().map(|x| *x as f32).collect();
    Tensor::from_data(TensorData::new(v, shape), device)
}

type BiasLrelu = fn(Tensor<4>, Option<Tensor<1>>, f64) -> Tensor<4>;

/// `sum(f(x, bias) * r)`: the output and the gradients with respect to `x` and `bias`.
fn loss_and_grads(
    f: BiasLrelu,
    x: &[f64],
    bias: &[f64],
    r: &[f64],
    shape: [usize; 4],
    gain: f64,
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let device = Device::flex().autodiff();
    let xt = tensor(x, shape, &device).require_grad();
    let bt = tensor(bias, [shape[1]], &device).require_grad();
    let out = f(xt.clone(), Some(bt.clone()), gain);
    let grads = (out.clone() * tensor(r, shape, &device)).sum().backward();
    (
        to_f32_vec(out),
        to_f32_vec(xt.grad(&grads).unwrap()),
        to_f32_vec(bt.grad(&grads).unwrap()),
    )
}

fn assert_close(got: &[f32], want: &[f64], tol: f64, what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        let g = f64::from(*g);
        assert!(
            (g - w).abs() <= tol * (1.0 + w.abs()),
            "{what}[{i}]: {g} vs {w}"
        );
    }
}

fn wide(v: &[f32]) -> Vec<f64> {
    v.iter().map(|x| f64::from(*x)).collect()
}

/// Shapes with planes smaller than, equal to and larger than a task, one channel, and a
/// rank-2 layout in the rank-4 form `[batch, channels, 1, 1]`.
const SHAPES: [[usize; 4]; 5] = [
    [2, 3, 5, 7],
    [4, 32, 64, 64],
    [3, 1, 130, 129],
    [4, 128, 1, 1],
    [1, 5, 128, 128],
];

#[test]
fn fused_matches_the_reference_in_values_and_gradients() {
    let mut rng = SplitMix64::new(21);
    for shape in SHAPES {
        for gain in [SQRT_2, 1.0, 0.25] {
            let n = shape.iter().product();
            let x: Vec<f64> = normals(&mut rng, n).iter().map(|v| 2.0 * v).collect();
            let bias = normals(&mut rng, shape[1]);
            let r = normals(&mut rng, n);
            let fused = loss_and_grads(bias_lrelu, &x, &bias, &r, shape, gain);
            let reference = loss_and_grads(bias_lrelu_reference, &x, &bias, &r, shape, gain);
            let what = format!("{shape:?}, gain {gain}");
            assert_close(&fused.0, &wide(&reference.0), 1e-6, &format!("{what}: y"));
            assert_close(&fused.1, &wide(&reference.1), 1e-6, &format!("{what}: dx"));
            // The bias gradient sums up to 65536 terms: f32 rounding in the reference's sum.
            assert_close(&fused.2, &wide(&reference.2), 1e-4, &format!("{what}: db"));
            let plain = to_f32_vec(bias_lrelu(
                tensor(&x, shape, &Device::flex()),
                Some(tensor(&bias, [shape[1]], &Device::flex())),
                gain,
            ));
            assert_eq!(plain, fused.0, "{what}: flex without autodiff");
        }
    }
}

/// `y`, `dL/dx` and `dL/dbias` for `L = sum(gain lrelu(x + bias) r)` in f64 loops.
fn bias_lrelu_f64(
    x: &[f64],
    bias: &[f64],
    r: &[f64],
    shape: [usize; 4],
    gain: f64,
) -> (Vec<f64>, Vec<f64>, Vec<f64>, f64) {
    let inner = shape[2] * shape[3];
    let (mut y, mut dx, mut db, mut loss) = (
        vec![0.0; x.len()],
        vec![0.0; x.len()],
        vec![0.0; bias.len()],
        0.0,
    );
    for i in 0..x.len() {
        let c = (i / inner) % shape[1];
        let z = x[i] + bias[c];
        let slope = if z > 0.0 { gain } else { gain * LRELU_SLOPE };
        y[i] = slope * z;
        dx[i] = slope * r[i];
        db[c] += dx[i];
        loss += y[i] * r[i];
    }
    (y, dx, db, loss)
}

#[test]
fn values_and_gradients_match_f64_loops_and_central_differences() {
    let mut rng = SplitMix64::new(4);
    let shape = [2, 3, 4, 5];
    let n = shape.iter().product();
    let gain = SQRT_2;
    // Away from the kink (|z| > 0.05), where central differences are exact.
    let bias = normals(&mut rng, 3);
    let x: Vec<f64> = normals(&mut rng, n)
        .iter()
        .enumerate()
        .map(|(i, v)| {
            let b = bias[(i / 20) % 3];
            let z = f64::from((2.0 * v) as f32);
            if (z + b).abs() < 0.05 { z + 0.1 } else { z }
        })
        .collect();
    let r = normals(&mut rng, n);
    let (y, dx, db) = loss_and_grads(bias_lrelu, &x, &bias, &r, shape, gain);
    let round = |v: &[f64]| -> Vec<f64> { v.iter().map(|x| f64::from(*x as f32)).collect() };
    let (x, bias) = (round(&x), round(&bias));
    let (y64, dx64, db64, _) = bias_lrelu_f64(&x, &bias, &r, shape, gain);
    assert_close(&y, &y64, 1e-6, "y");
    assert_close(&dx, &dx64, 1e-6, "dx");
    assert_close(&db, &db64, 1e-5, "db");
    let h = 1e-4;
    let loss = |x: &[f64], b: &[f64]| bias_lrelu_f64(x, b, &r, shape, gain).3;
    for k in 0..n {
        let (mut plus, mut minus) = (x.clone(), x.clone());
        plus[k] += h;
        minus[k] -= h;
        let want = (loss(&plus, &bias) - loss(&minus, &bias)) / (2.0 * h);
        assert!(
            (f64::from(dx[k]) - want).abs() < 1e-5 * (1.0 + want.abs()),
            "dx[{k}]"
        );
    }
    for c in 0..3 {
        let (mut plus, mut minus) = (bias.clone(), bias.clone());
        plus[c] += h;
        minus[c] -= h;
        let want = (loss(&x, &plus) - loss(&x, &minus)) / (2.0 * h);
        assert!(
            (f64::from(db[c]) - want).abs() < 1e-4 * (1.0 + want.abs()),
            "db[{c}]"
        );
    }
}

#[test]
fn no_bias_and_rank_two_take_the_same_kernel() {
    let mut rng = SplitMix64::new(8);
    let x = normals(&mut rng, 4 * 6);
    let device = Device::flex();
    let fused: Tensor<2> = bias_lrelu(tensor(&x, [4, 6], &device), None, SQRT_2);
    let reference = bias_lrelu_reference(tensor(&x, [4, 6], &device), None, SQRT_2);
    // One rounding (`x (0.2 gain)`) against the reference's two (`(0.2 x) gain`).
    assert_close(&to_f32_vec(fused), &wide(&to_f32_vec(reference)), 1e-6, "y");
}

/// `sum(lrelu_input_gradient(g, y) * r)` and its gradient with respect to `g`; `y` requires a
/// gradient too, which must come back absent or zero.
fn input_gradient_and_grad(
    f: fn(Tensor<4>, Tensor<4>, f64) -> Tensor<4>,
    g: &[f64],
    y: &[f64],
    r: &[f64],
    shape: [usize; 4],
    gain: f64,
) -> (Vec<f32>, Vec<f32>, Option<Vec<f32>>) {
    let device = Device::flex().autodiff();
    let gt = tensor(g, shape, &device).require_grad();
    let yt = tensor(y, shape, &device).require_grad();
    let out = f(gt.clone(), yt.clone(), gain);
    let grads = (out.clone() * tensor(r, shape, &device)).sum().backward();
    (
        to_f32_vec(out),
        to_f32_vec(gt.grad(&grads).unwrap()),
        yt.grad(&grads).map(to_f32_vec),
    )
}

#[test]
fn input_gradient_matches_the_reference_and_an_f64_loop() {
    let mut rng = SplitMix64::new(13);
    for shape in [[2, 3, 5, 7], [4, 32, 64, 64]] {
        let n = shape.iter().product();
        let g = normals(&mut rng, n);
        // Outputs with exact zeros among them (the derivative there is the slope's).
        let y: Vec<f64> = normals(&mut rng, n)
            .iter()
            .enumerate()
            .map(|(i, v)| if i % 11 == 0 { 0.0 } else { *v })
            .collect();
        let r = normals(&mut rng, n);
        let gain = SQRT_2;
        let fused = input_gradient_and_grad(lrelu_input_gradient, &g, &y, &r, shape, gain);
        let reference =
            input_gradient_and_grad(lrelu_input_gradient_reference, &g, &y, &r, shape, gain);
        assert_close(&fused.0, &wide(&reference.0), 1e-6, "value");
        assert_close(&fused.1, &wide(&reference.1), 1e-6, "d/dg");
        for grad_y in [fused.2, reference.2].into_iter().flatten() {
            assert!(grad_y.iter().all(|v| *v == 0.0), "y only selects");
        }
        let want: Vec<f64> = (0..n)
            .map(|i| {
                let g32 = f64::from(g[i] as f32);
                g32 * if (y[i] as f32) > 0.0 {
                    gain
                } else {
                    gain * LRELU_SLOPE
                }
            })
            .collect();
        assert_close(&fused.0, &want, 1e-6, "f64 loop");
        let plain = lrelu_input_gradient(
            tensor(&g, shape, &Device::flex()),
            tensor(&y, shape, &Device::flex()),
            gain,
        );
        assert_eq!(to_f32_vec(plain), fused.0, "flex without autodiff");
    }
}

/// The derivative read from the output agrees with the one at the pre-activation: a
/// bias_lrelu output fed back selects the slope of the input that made it.
#[test]
fn the_output_sign_is_the_pre_activation_sign() {
    let pre = [-3.0, -1e-30, 0.0, 1e-30, 2.0, 1e4, -1e4];
    let device = Device::flex();
    let x = tensor(&pre, [1, 7, 1, 1], &device);
    let y = bias_lrelu(x, None, SQRT_2);
    let ones = Tensor::<4>::ones([1, 7, 1, 1], &device);
    let d = to_f32_vec(lrelu_input_gradient(ones, y, SQRT_2));
    for (p, d) in pre.iter().zip(d) {
        let want = if *p > 0.0 {
            SQRT_2
        } else {
            SQRT_2 * LRELU_SLOPE
        };
        assert!((f64::from(d) - want).abs() < 1e-6, "pre {p}: {d}");
    }
}

#[test]
fn huge_tiny_zero_and_non_finite_inputs() {
    let values = [
        1e30,
        -1e30,
        1e-30,
        -1e-30,
        0.0,
        3e38,
        -3e38,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NAN,
    ];
    let n = values.len();
    for device in [Device::flex(), Device::flex().autodiff()] {
        let x = || tensor(&values, [1, 1, 1, n], &device);
        let fused = to_f32_vec(bias_lrelu(x(), None, SQRT_2));
        let reference = to_f32_vec(bias_lrelu_reference(x(), None, SQRT_2));
        for (i, (f, r)) in fused.iter().zip(&reference).enumerate() {
            let (f, r) = (f64::from(*f), f64::from(*r));
            assert!(
                f == r || (f.is_nan() && r.is_nan()) || (f - r).abs() <= 1e-6 * r.abs(),
                "{}: {f} vs {r}",
                values[i]
            );
        }
        // 3e38 sqrt(2) overflows to infinity in both, as in any f32 implementation.
        assert!(fused[5].is_infinite() && fused[9].is_nan());
    }
}

#[test]
#[should_panic(expected = "gain must be positive")]
fn a_non_positive_gain_is_refused() {
    let x = Tensor::<2>::zeros([2, 3], &Device::flex());
    let _ = bias_lrelu(x, None, 0.0);
}
