use burn::tensor::{Device, TensorData};

use super::kernels::forced;
use super::*;
use crate::backend::to_f32_vec;
use crate::test_support::{conv2d_f64, normals};
use volux_envmap::random::SplitMix64;

/// `(x: [batch, c, h, w], o, k, geometry)`: the discriminators' shapes (3x3 'same', 3x3
/// stride 2 on odd planes, 1x1) at reduced width, the batches that run images in
/// parallel and one by one, and the awkward ones: a 1x1 plane, padding wider than the
/// kernel, a stride that skips inputs, a strided 1x1 kernel, an even kernel, a stride wider
/// than the plane (phases that hold no input column), a 5x5 kernel with stride 2, and 3x3
/// kernels of stride 1 on odd planes (partial Winograd tiles) with padding 1, 0 and 2, and
/// one image alone (its products on every thread).
fn cases() -> Vec<([usize; 4], usize, usize, ConvGeometry)> {
    let g = ConvGeometry::new;
    vec![
        ([4, 8, 12, 12], 6, 3, g(1, 1)),
        ([1, 3, 9, 9], 5, 3, g(2, 0)),
        ([2, 4, 8, 7], 6, 3, g(2, 0)),
        ([3, 5, 6, 6], 4, 1, g(1, 0)),
        ([2, 3, 5, 5], 2, 1, g(2, 0)),
        ([2, 2, 1, 1], 3, 3, g(1, 1)),
        ([1, 2, 5, 11], 3, 3, g(3, 3)),
        ([2, 9, 4, 4], 8, 3, g(1, 1)),
        ([1, 1, 3, 3], 2, 2, g(1, 4)),
        ([2, 3, 2, 5], 4, 1, g(3, 0)),
        ([1, 2, 4, 2], 3, 2, g(3, 1)),
        ([1, 2, 7, 6], 3, 5, g(2, 2)),
        ([3, 4, 7, 5], 5, 3, g(1, 1)),
        ([2, 3, 6, 9], 4, 3, g(1, 0)),
        ([2, 3, 5, 4], 2, 3, g(1, 2)),
        ([1, 3, 5, 6], 4, 3, g(1, 1)),
    ]
}

fn tensor(values: &[f32], shape: [usize; 4], device: &Device) -> Tensor<4> {
    Tensor::from_data(TensorData::new(values.to_vec(), shape), device)
}

fn random(rng: &mut SplitMix64, n: usize) -> Vec<f32> {
    normals(rng, n).iter().map(|v| *v as f32).collect()
}

fn wide(v: &[f32]) -> Vec<f64> {
    v.iter().map(|x| f64::from(*x)).collect()
}

fn out_shape([b, _, h, w]: [usize; 4], o: usize, k: usize, g: ConvGeometry) -> [usize; 4] {
    [b, o, g.out_len(h, k), g.out_len(w, k)]
}

/// The adjoint in f64 loops: `y: [b, o, ho, wo]` back to `[b, c, h, w]`.
fn adjoint_f64(
    y: &[f64],
    [b, c, h, w]: [usize; 4],
    wt: &[f64],
    [o, k]: [usize; 2],
    g: ConvGeometry,
) -> Vec<f64> {
    let (ho, wo) = (g.out_len(h, k), g.out_len(w, k));
    let mut x = vec![0.0; b * c * h * w];
    for n in 0..b {
        for oc in 0..o {
            for i in 0..ho {
                for j in 0..wo {
                    let yv = y[((n * o + oc) * ho + i) * wo + j];
                    for ci in 0..c {
                        for u in 0..k {
                            for v in 0..k {
                                let (r, s) = (i * g.stride + u, j * g.stride + v);
                                if r < g.pad || s < g.pad || r - g.pad >= h || s - g.pad >= w {
                                    continue;
                                }
                                x[((n * c + ci) * h + r - g.pad) * w + s - g.pad] +=
                                    wt[((oc * c + ci) * k + u) * k + v] * yv;
                            }
                        }
                    }
                }
            }
        }
    }
    x
}

fn assert_close(got: &[f32], want: &[f64], tol: f64, what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            (f64::from(*g) - w).abs() <= tol * (1.0 + w.abs()),
            "{what}[{i}]: {g} vs {w}"
        );
    }
}

#[test]
fn both_directions_match_f64_loops_and_the_tensor_op_reference() {
    // Each strategy on every shape, whichever the shape would pick.
    forced::each(|strategy| {
        let device = Device::flex();
        let mut rng = SplitMix64::new(11);
        for (shape, o, k, g) in cases() {
            let what = format!("{strategy:?}: {shape:?} -> {o}, k {k}, {g:?}");
            let wshape = [o, shape[1], k, k];
            let (xv, wv) = (
                random(&mut rng, shape.iter().product()),
                random(&mut rng, wshape.iter().product()),
            );
            let (x, w) = (tensor(&xv, shape, &device), tensor(&wv, wshape, &device));
            let y = conv2d(x.clone(), w.clone(), g);
            let yshape = out_shape(shape, o, k, g);
            assert_eq!(y.dims(), yshape, "{what}");
            let (want, _) = conv2d_f64(&wide(&xv), shape, &wide(&wv), [o, k], g.stride, g.pad);
            let got = to_f32_vec(y);
            assert_close(&got, &want, 1e-5, &format!("{what}: forward against f64"));
            let reference = to_f32_vec(conv2d_reference(x, w.clone(), g));
            assert_close(
                &got,
                &wide(&reference),
                1e-5,
                &format!("{what}: forward against conv2d"),
            );

            let yv = random(&mut rng, yshape.iter().product());
            let back = to_f32_vec(conv2d_adjoint(
                tensor(&yv, yshape, &device),
                w.clone(),
                g,
                [shape[2], shape[3]],
            ));
            let want = adjoint_f64(&wide(&yv), shape, &wide(&wv), [o, k], g);
            assert_close(&back, &want, 1e-5, &format!("{what}: adjoint against f64"));
            let reference = to_f32_vec(conv2d_adjoint_reference(
                tensor(&yv, yshape, &device),
                w,
                g,
                [shape[2], shape[3]],
            ));
            assert_close(
                &back,
                &wide(&reference),
                1e-5,
                &format!("{what}: adjoint against conv_transpose2d"),
            );
            // <A x, y> = <x, A^T y>, in f64.
            let dot = |a: &[f32], b: &[f32]| -> f64 {
                wide(a).iter().zip(wide(b)).map(|(a, b)| a * b).sum()
            };
            let (lhs, rhs) = (dot(&got, &yv), dot(&xv, &back));
            assert!(
                (lhs - rhs).abs() <= 1e-5 * (1.0 + lhs.abs()),
                "{what}: {lhs} vs {rhs}"
            );
        }
    });
}

type Op = fn(Tensor<4>, Tensor<4>, ConvGeometry, [usize; 2]) -> Tensor<4>;

fn forward_op(x: Tensor<4>, w: Tensor<4>, g: ConvGeometry, _: [usize; 2]) -> Tensor<4> {
    conv2d(x, w, g)
}
fn forward_reference(x: Tensor<4>, w: Tensor<4>, g: ConvGeometry, _: [usize; 2]) -> Tensor<4> {
    conv2d_reference(x, w, g)
}

/// `0.5 sum(r op(a, w)^2)` and its gradients with respect to `a` and `w`, on autodiff
/// flex: quadratic, so the gradient depends on the operation's output as well as its
/// transpose.
fn grads_of(
    op: Op,
    (a, ashape): (&[f32], [usize; 4]),
    (w, wshape): (&[f32], [usize; 4]),
    g: ConvGeometry,
    in_hw: [usize; 2],
    r: &[f32],
) -> (Vec<f32>, Vec<f32>) {
    let device = Device::flex().autodiff();
    let a = tensor(a, ashape, &device).require_grad();
    let w = tensor(w, wshape, &device).require_grad();
    let out = op(a.clone(), w.clone(), g, in_hw);
    let r = tensor(r, out.dims(), &device);
    let grads = (out.clone() * out * r).sum().mul_scalar(0.5).backward();
    (
        to_f32_vec(a.grad(&grads).expect("tracked")),
        to_f32_vec(w.grad(&grads).expect("tracked")),
    )
}

#[test]
fn gradients_match_the_reference_in_both_directions() {
    // Each strategy on every shape, whichever the shape would pick.
    forced::each(|strategy| {
        let mut rng = SplitMix64::new(12);
        for (shape, o, k, g) in cases() {
            let what = format!("{strategy:?}: {shape:?} -> {o}, k {k}, {g:?}");
            let wshape = [o, shape[1], k, k];
            let yshape = out_shape(shape, o, k, g);
            let in_hw = [shape[2], shape[3]];
            let n = |s: [usize; 4]| s.iter().product::<usize>();
            let w = random(&mut rng, n(wshape));

            let (x, r) = (random(&mut rng, n(shape)), random(&mut rng, n(yshape)));
            let fast = grads_of(forward_op, (&x, shape), (&w, wshape), g, in_hw, &r);
            let slow = grads_of(forward_reference, (&x, shape), (&w, wshape), g, in_hw, &r);
            assert_close(
                &fast.0,
                &wide(&slow.0),
                1e-4,
                &format!("{what}: d conv / dx"),
            );
            assert_close(
                &fast.1,
                &wide(&slow.1),
                1e-4,
                &format!("{what}: d conv / dw"),
            );

            let (y, r) = (random(&mut rng, n(yshape)), random(&mut rng, n(shape)));
            let fast = grads_of(conv2d_adjoint, (&y, yshape), (&w, wshape), g, in_hw, &r);
            let slow = grads_of(
                conv2d_adjoint_reference,
                (&y, yshape),
                (&w, wshape),
                g,
                in_hw,
                &r,
            );
            assert_close(
                &fast.0,
                &wide(&slow.0),
                1e-4,
                &format!("{what}: d adjoint / dy"),
            );
            assert_close(
                &fast.1,
                &wide(&slow.1),
                1e-4,
                &format!("{what}: d adjoint / dw"),
            );
        }
    });
}

/// `sqrt(sum (got - want)^2 / sum want^2)`.
fn relative_rms(got: &[f32], want: &[f64]) -> f64 {
    let (err, norm) = got.iter().zip(want).fold((0.0, 0.0), |(e, n), (g, w)| {
        (e + (f64::from(*g) - w).powi(2), n + w * w)
    });
    (err / norm).sqrt()
}

/// Winograd's rounding against the direct products' on a discriminator-sized layer (32
/// channels in and out, 16x16, 3x3 'same'): the relative RMS error of each strategy's forward
/// and adjoint against the f64 sums. Its transforms add a few roundings per output; the
/// error stays within a small factor of the direct products' (the measured figures are in
/// docs/performance.md).
#[test]
fn winograd_rounding_stays_near_the_direct_products() {
    let device = Device::flex();
    let mut rng = SplitMix64::new(14);
    let (shape, o, k, g) = ([2, 32, 16, 16], 32, 3, ConvGeometry::new(1, 1));
    let wshape = [o, shape[1], k, k];
    let yshape = out_shape(shape, o, k, g);
    let n = |s: [usize; 4]| s.iter().product::<usize>();
    let (x, w, y) = (
        random(&mut rng, n(shape)),
        random(&mut rng, n(wshape)),
        random(&mut rng, n(yshape)),
    );
    let (want_y, _) = conv2d_f64(&wide(&x), shape, &wide(&w), [o, k], 1, 1);
    let want_x = adjoint_f64(&wide(&y), shape, &wide(&w), [o, k], g);
    let mut errors = Vec::new();
    forced::each(|strategy| {
        let (xt, wt, yt) = (
            tensor(&x, shape, &device),
            tensor(&w, wshape, &device),
            tensor(&y, yshape, &device),
        );
        let forward = to_f32_vec(conv2d(xt, wt.clone(), g));
        let adjoint = to_f32_vec(conv2d_adjoint(yt, wt, g, [shape[2], shape[3]]));
        let e = (
            relative_rms(&forward, &want_y),
            relative_rms(&adjoint, &want_x),
        );
        println!("{strategy:?}: forward {:.2e}, adjoint {:.2e}", e.0, e.1);
        errors.push((strategy, e));
    });
    let direct = errors
        .iter()
        .filter(|(s, _)| *s != kernels::Strategy::Winograd)
        .fold(0.0f64, |m, (_, e)| m.max(e.0).max(e.1));
    let (_, winograd) = errors
        .iter()
        .find(|(s, _)| *s == kernels::Strategy::Winograd)
        .expect("forced");
    assert!(direct > 0.0 && direct < 1e-6, "direct products: {direct:e}");
    assert!(
        winograd.0 < 4.0 * direct && winograd.1 < 4.0 * direct,
        "Winograd {winograd:?} against the direct products' {direct:e}"
    );
}

#[test]
fn gradients_match_f64_central_differences() {
    // Each strategy on every shape, whichever the shape would pick.
    forced::each(|strategy| {
        let mut rng = SplitMix64::new(13);
        for (shape, o, k, g) in [
            ([2, 2, 5, 4], 3, 3, ConvGeometry::new(2, 1)),
            ([2, 3, 3, 3], 2, 1, ConvGeometry::new(1, 0)),
            ([2, 2, 5, 4], 3, 3, ConvGeometry::new(1, 1)),
        ] {
            let wshape = [o, shape[1], k, k];
            let yshape = out_shape(shape, o, k, g);
            let n = |s: [usize; 4]| s.iter().product::<usize>();
            let in_hw = [shape[2], shape[3]];
            // Inputs rounded to f32, so that both sides see the same numbers.
            let (x, w) = (random(&mut rng, n(shape)), random(&mut rng, n(wshape)));
            let (y, rx, ry) = (
                random(&mut rng, n(yshape)),
                random(&mut rng, n(shape)),
                random(&mut rng, n(yshape)),
            );
            let loss = |out: Vec<f64>, r: &[f32]| -> f64 {
                out.iter().zip(wide(r)).map(|(v, r)| 0.5 * r * v * v).sum()
            };
            let forward_loss = |x: &[f64], w: &[f64]| {
                loss(conv2d_f64(x, shape, w, [o, k], g.stride, g.pad).0, &ry)
            };
            let adjoint_loss =
                |y: &[f64], w: &[f64]| loss(adjoint_f64(y, shape, w, [o, k], g), &rx);
            let h = 1e-3;
            // Central differences are exact for these quadratics up to rounding.
            let fd = |f: &dyn Fn(&[f64]) -> f64, at: &[f64]| -> Vec<f64> {
                (0..at.len())
                    .map(|i| {
                        let (mut p, mut m) = (at.to_vec(), at.to_vec());
                        p[i] += h;
                        m[i] -= h;
                        (f(&p) - f(&m)) / (2.0 * h)
                    })
                    .collect()
            };
            let (xw, ww, yw) = (wide(&x), wide(&w), wide(&y));
            let conv = grads_of(forward_op, (&x, shape), (&w, wshape), g, in_hw, &ry);
            let adj = grads_of(conv2d_adjoint, (&y, yshape), (&w, wshape), g, in_hw, &rx);
            let checks: [(&[f32], Vec<f64>, &str); 4] = [
                (&conv.0, fd(&|x| forward_loss(x, &ww), &xw), "conv d/dx"),
                (&conv.1, fd(&|w| forward_loss(&xw, w), &ww), "conv d/dw"),
                (&adj.0, fd(&|y| adjoint_loss(y, &ww), &yw), "adjoint d/dy"),
                (&adj.1, fd(&|w| adjoint_loss(&yw, w), &ww), "adjoint d/dw"),
            ];
            for (got, want, what) in checks {
                assert_close(got, &want, 1e-4, &format!("{strategy:?}: {what}"));
            }
        }
    });
}

#[test]
fn huge_tiny_zero_and_non_finite_inputs() {
    // Each strategy on every shape, whichever the shape would pick.
    forced::each(|strategy| {
        let device = Device::flex();
        let g = ConvGeometry::new(1, 1);
        let w = tensor(&[1e-3; 18], [2, 1, 3, 3], &device);
        for value in [1e30f32, 1e-30, 0.0, -3e4] {
            let y = to_f32_vec(conv2d(
                tensor(&[value; 36], [1, 1, 6, 6], &device),
                w.clone(),
                g,
            ));
            // An interior output sums nine inputs times 1e-3.
            let interior = y[6 + 1];
            let want = f64::from(value) * 9e-3;
            assert!(
                (f64::from(interior) - want).abs() <= 1e-6 * want.abs(),
                "{value}: {interior}"
            );
            assert!(y.iter().all(|v| v.is_finite()), "{value}: {y:?}");
            if value == 0.0 {
                assert!(y.iter().all(|v| *v == 0.0));
            }
        }
        // A NaN reaches exactly the outputs whose window holds it, in both directions, so the
        // training loop's non-finite guard sees it and nothing else is poisoned.
        let mut x = vec![1.0f32; 36];
        x[0] = f32::NAN;
        let y = to_f32_vec(conv2d(tensor(&x, [1, 1, 6, 6], &device), w.clone(), g));
        for (i, v) in y[..36].iter().enumerate() {
            assert_eq!(v.is_nan(), i % 6 <= 1 && i / 6 <= 1, "output {i}: {v}");
        }
        let mut y = vec![1.0f32; 72];
        y[0] = f32::NAN;
        let back = to_f32_vec(conv2d_adjoint(
            tensor(&y, [1, 2, 6, 6], &device),
            w.clone(),
            g,
            [6, 6],
        ));
        assert!(back[0].is_nan() && back[35].is_finite());
        // Inside the plane (input row 2, column 3): the direct products poison the outputs
        // whose window holds it (rows 1-3, columns 2-4); Winograd, whose transforms mix a
        // whole 4x4 input tile, every output of the tiles that hold it (rows 0-3, columns
        // 2-5), and nothing further.
        let mut x = vec![1.0f32; 36];
        x[2 * 6 + 3] = f32::NAN;
        let y = to_f32_vec(conv2d(tensor(&x, [1, 1, 6, 6], &device), w, g));
        for (i, v) in y[..36].iter().enumerate() {
            let (r, c) = (i / 6, i % 6);
            let window = (1..=3).contains(&r) && (2..=4).contains(&c);
            let tiles = r <= 3 && (2..=5).contains(&c);
            if strategy == kernels::Strategy::Winograd {
                assert!(!window || v.is_nan(), "output {i}: {v}");
                assert!(tiles || v.is_finite(), "output {i}: {v}");
            } else {
                assert_eq!(v.is_nan(), window, "{strategy:?}: output {i}: {v}");
            }
        }
    });
}
