//! Tests of the batched product against Burn's matmul, an f64 loop and f64 central
//! differences.

use burn::tensor::{Device, TensorData};

use super::*;
use crate::backend::to_f32_vec;
use crate::test_support::normals;
use volux_envmap::random::SplitMix64;

fn tensor(values: &[f32], shape: [usize; 3], device: &Device) -> Tensor<3> {
    Tensor::from_data(TensorData::new(values.to_vec(), shape), device)
}

fn random(rng: &mut SplitMix64, n: usize) -> Vec<f32> {
    normals(rng, n).iter().map(|v| *v as f32).collect()
}

/// `[batch, m, k] x [batch, k, n]` in f64.
fn product_f64(a: &[f32], b: &[f32], [batch, m, k, n]: [usize; 4]) -> Vec<f64> {
    let mut out = vec![0.0; batch * m * n];
    for bi in 0..batch {
        for i in 0..m {
            for j in 0..n {
                out[(bi * m + i) * n + j] = (0..k)
                    .map(|l| {
                        f64::from(a[(bi * m + i) * k + l]) * f64::from(b[(bi * k + l) * n + j])
                    })
                    .sum();
            }
        }
    }
    out
}

fn assert_close(got: &[f32], want: &[f64], tol: f64, what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    let scale = want.iter().fold(1.0f64, |m, v| m.max(v.abs()));
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            (f64::from(*g) - w).abs() <= tol * scale,
            "{what}[{i}]: {g} vs {w}"
        );
    }
}

/// `[batch, m, k, n]`: batches that run in parallel and one by one, the NeIIF's shape at
/// small size, vectors, a single element.
const SHAPES: [[usize; 4]; 5] = [
    [4, 37, 9, 5],
    [1, 300, 27, 16],
    [3, 1, 7, 1],
    [2, 5, 1, 6],
    [1, 1, 1, 1],
];

#[test]
fn values_match_f64_and_burns_matmul_with_and_without_autodiff() {
    let mut rng = SplitMix64::new(51);
    for shape in SHAPES {
        let [batch, m, k, n] = shape;
        let (a, b) = (
            random(&mut rng, batch * m * k),
            random(&mut rng, batch * k * n),
        );
        let want = product_f64(&a, &b, shape);
        for device in [Device::flex(), Device::flex().autodiff()] {
            let (at, bt) = (
                tensor(&a, [batch, m, k], &device),
                tensor(&b, [batch, k, n], &device),
            );
            let got = to_f32_vec(batched_matmul(at.clone(), bt.clone()));
            assert_close(&got, &want, 1e-6, &format!("{shape:?}"));
            let reference = to_f32_vec(batched_matmul_reference(at, bt));
            let reference: Vec<f64> = reference.iter().map(|v| f64::from(*v)).collect();
            assert_close(&got, &reference, 1e-6, &format!("{shape:?} against Burn"));
        }
    }
}

#[test]
fn transposed_and_sliced_views_are_read_through_their_strides() {
    let mut rng = SplitMix64::new(52);
    let device = Device::flex();
    let [batch, m, k, n] = [3, 11, 6, 4];
    let a = random(&mut rng, batch * m * k);
    // `b` stored as `[batch, n, k]` and transposed; `a` as a slice of a wider tensor.
    let b_stored = random(&mut rng, batch * n * k);
    let wide = random(&mut rng, batch * m * (k + 3));
    let a_view = tensor(&wide, [batch, m, k + 3], &device).narrow(2, 2, k);
    let a_copy = to_f32_vec(a_view.clone());
    let b_view = tensor(&b_stored, [batch, n, k], &device).swap_dims(1, 2);
    let b_copy = to_f32_vec(b_view.clone());
    let want = product_f64(&a_copy, &b_copy, [batch, m, k, n]);
    assert_close(
        &to_f32_vec(batched_matmul(a_view, b_view)),
        &want,
        1e-6,
        "views",
    );
    // A broadcast (stride 0) batch of weights, as `expand` gives.
    let w = random(&mut rng, k * n);
    let w_view = tensor(&w, [1, k, n], &device).expand([batch, k, n]);
    let w_copy: Vec<f32> = (0..batch).flat_map(|_| w.iter().copied()).collect();
    let want = product_f64(&a, &w_copy, [batch, m, k, n]);
    assert_close(
        &to_f32_vec(batched_matmul(tensor(&a, [batch, m, k], &device), w_view)),
        &want,
        1e-6,
        "broadcast",
    );
}

/// `sum(op(a, b) * r)` and its gradients in `a` and `b`.
fn grads_of(
    op: fn(Tensor<3>, Tensor<3>) -> Tensor<3>,
    a: &[f32],
    b: &[f32],
    r: &[f32],
    [batch, m, k, n]: [usize; 4],
    transpose_b: bool,
) -> (Vec<f32>, Vec<f32>) {
    let device = Device::flex().autodiff();
    let at = tensor(a, [batch, m, k], &device).require_grad();
    let b_shape = if transpose_b {
        [batch, n, k]
    } else {
        [batch, k, n]
    };
    let bt = tensor(b, b_shape, &device).require_grad();
    let b_used = if transpose_b {
        bt.clone().swap_dims(1, 2)
    } else {
        bt.clone()
    };
    let grads = (op(at.clone(), b_used) * tensor(r, [batch, m, n], &device))
        .sum()
        .backward();
    (
        to_f32_vec(at.grad(&grads).unwrap()),
        to_f32_vec(bt.grad(&grads).unwrap()),
    )
}

#[test]
fn gradients_match_burns_and_f64_central_differences() {
    let mut rng = SplitMix64::new(53);
    for shape in SHAPES {
        for transpose_b in [false, true] {
            let [batch, m, k, n] = shape;
            let a = random(&mut rng, batch * m * k);
            let b = random(&mut rng, batch * k * n);
            let r = random(&mut rng, batch * m * n);
            let fast = grads_of(batched_matmul, &a, &b, &r, shape, transpose_b);
            let slow = grads_of(batched_matmul_reference, &a, &b, &r, shape, transpose_b);
            let wide = |v: &[f32]| -> Vec<f64> { v.iter().map(|x| f64::from(*x)).collect() };
            let what = format!("{shape:?}, b transposed {transpose_b}");
            assert_close(&fast.0, &wide(&slow.0), 1e-5, &format!("{what}: d/da"));
            assert_close(&fast.1, &wide(&slow.1), 1e-5, &format!("{what}: d/db"));
            if batch * m * k * n > 2000 {
                continue;
            }
            // The loss is bilinear: central differences in f64 are exact up to rounding.
            let b_plain: Vec<f32> = if transpose_b {
                // Stored `[batch, n, k]`: the product reads it transposed.
                let mut t = vec![0.0; b.len()];
                for bi in 0..batch {
                    for l in 0..k {
                        for j in 0..n {
                            t[(bi * k + l) * n + j] = b[(bi * n + j) * k + l];
                        }
                    }
                }
                t
            } else {
                b.clone()
            };
            let loss = |a: &[f32], b: &[f32]| -> f64 {
                product_f64(a, b, shape)
                    .iter()
                    .zip(&r)
                    .map(|(p, r)| p * f64::from(*r))
                    .sum()
            };
            let h = 0.5f32;
            for i in 0..a.len() {
                let (mut plus, mut minus) = (a.clone(), a.clone());
                plus[i] += h;
                minus[i] -= h;
                let fd = (loss(&plus, &b_plain) - loss(&minus, &b_plain)) / (2.0 * f64::from(h));
                let got = f64::from(fast.0[i]);
                assert!(
                    (got - fd).abs() < 1e-4 * (1.0 + fd.abs()),
                    "{what}: d/da[{i}]"
                );
            }
            for bi in 0..batch {
                for l in 0..k {
                    for j in 0..n {
                        let plain = (bi * k + l) * n + j;
                        let stored = if transpose_b {
                            (bi * n + j) * k + l
                        } else {
                            plain
                        };
                        let (mut plus, mut minus) = (b_plain.clone(), b_plain.clone());
                        plus[plain] += h;
                        minus[plain] -= h;
                        let fd = (loss(&a, &plus) - loss(&a, &minus)) / (2.0 * f64::from(h));
                        let got = f64::from(fast.1[stored]);
                        assert!(
                            (got - fd).abs() < 1e-4 * (1.0 + fd.abs()),
                            "{what}: d/db[{stored}]"
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn huge_tiny_and_empty_inner_dimensions() {
    let device = Device::flex();
    // Products of 1e20 overflow f32 as Burn's do; tiny ones underflow to (signed) zero.
    let a = tensor(&[1e20, 1e-30, -1e-30, 0.0], [1, 2, 2], &device);
    let b = tensor(&[1e20, 0.0, 1e-30, 1.0], [1, 2, 2], &device);
    let got = to_f32_vec(batched_matmul(a.clone(), b.clone()));
    let want = to_f32_vec(batched_matmul_reference(a, b));
    assert_eq!(got, want);
    assert!(got[0].is_infinite());
    // An inner dimension of 0 gives zeros.
    let a = Tensor::<3>::zeros([2, 3, 0], &device);
    let b = Tensor::<3>::zeros([2, 0, 4], &device);
    let got = batched_matmul(a, b);
    assert_eq!(got.dims(), [2, 3, 4]);
    assert!(to_f32_vec(got).iter().all(|v| *v == 0.0));
}
