use super::*;
use crate::test_support::Reseed;
use burn::tensor::{DType, TensorData};
use volux_envmap::random::SplitMix64;

/// The centred quadratic B-spline.
fn b2(x: f64) -> f64 {
    let a = x.abs();
    if a <= 0.5 {
        0.75 - a * a
    } else if a <= 1.5 {
        (1.5 - a) * (1.5 - a) / 2.0
    } else {
        0.0
    }
}

/// The features at `x` in f64 straight from the definition: every control point of every
/// plane (the grid extended by its edge values) times the B-spline at its distance, with the
/// coordinate clamped to the planes' square.
fn reference(planes: &[f64], n: usize, c: usize, bound: f64, x: [f64; 3]) -> Vec<f64> {
    let last = (n - 1) as f64;
    let s: Vec<f64> = x
        .iter()
        .map(|v| ((v + bound) * last / (2.0 * bound)).clamp(0.0, last))
        .collect();
    let mut out = vec![0.0; c];
    for (plane, &(a, b)) in PLANE_AXES.iter().enumerate() {
        for ka in -1..=n as i64 {
            for kb in -1..=n as i64 {
                let w = b2(s[a] - ka as f64) * b2(s[b] - kb as f64);
                if w == 0.0 {
                    continue;
                }
                let (ia, ib) = (ka.clamp(0, n as i64 - 1), kb.clamp(0, n as i64 - 1));
                let row = plane * n * n + ia as usize * n + ib as usize;
                for (ch, o) in out.iter_mut().enumerate() {
                    *o += w * planes[row * c + ch];
                }
            }
        }
    }
    out
}

fn planes(resolution: usize, channels: usize, bound: f64, device: &Device) -> TemplatePlanes {
    TemplatePlanesConfig::new(resolution)
        .with_channels(channels)
        .with_bound(bound)
        .init(device)
        .map(&mut Reseed::new(3, DType::F32))
}

/// Points inside, on the edges of and outside the planes' square.
fn test_points() -> Vec<[f64; 3]> {
    let mut rng = SplitMix64::new(9);
    let mut points: Vec<[f64; 3]> = (0..40)
        .map(|_| std::array::from_fn(|_| rng.next_f64() * 1.6 - 0.8))
        .collect();
    points.extend([
        [0.0, 0.0, 0.0],
        [0.8, -0.8, 0.3],
        [0.95, 0.2, -0.95],
        [1.7, -3.0, 0.1],
    ]);
    points
}

fn tensor(points: &[[f64; 3]], device: &Device) -> Tensor<2> {
    let v: Vec<f32> = points.iter().flatten().map(|&x| x as f32).collect();
    Tensor::from_data(TensorData::new(v, [points.len(), 3]), device)
}

#[test]
fn quadratic_taps_are_a_partition_of_unity_that_reproduces_lines() {
    for s in [0.3, 2.0, 2.49, 2.5, 2.51, 6.999] {
        let (taps, w, d) = quadratic_taps(s, 8);
        assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-15, "s {s}");
        assert!(d.iter().sum::<f64>().abs() < 1e-15, "s {s}");
        if (1.0..6.0).contains(&s) {
            // Away from the edges (no tap clamped): linear functions are reproduced, sum w_k k
            // = s with derivative 1, and each weight is the B-spline at the tap's distance.
            let at: f64 = taps.iter().zip(&w).map(|(&k, w)| k as f64 * w).sum();
            let slope: f64 = taps.iter().zip(&d).map(|(&k, d)| k as f64 * d).sum();
            assert!(
                (at - s).abs() < 1e-12 && (slope - 1.0).abs() < 1e-12,
                "s {s}"
            );
            for (&tap, &wk) in taps.iter().zip(&w) {
                assert!((wk - b2(s - tap as f64)).abs() < 1e-15, "s {s} tap {tap}");
            }
        }
    }
}

#[test]
fn features_match_the_f64_definition_inside_on_and_outside_the_square() {
    let device = Device::flex();
    for (n, c, bound) in [(8, 3, 1.0), (5, 2, 0.7), (2, 1, 1.0)] {
        let t = planes(n, c, bound, &device);
        let values: Vec<f64> = to_f32_vec(t.planes.val())
            .iter()
            .map(|&v| f64::from(v))
            .collect();
        let points = test_points();
        let (got, _) = t.sample(&t.shared(), tensor(&points, &device), false);
        let got = to_f32_vec(got);
        for (q, x) in points.iter().enumerate() {
            let want = reference(&values, n, c, bound, *x);
            for ch in 0..c {
                let g = f64::from(got[q * c + ch]);
                assert!(
                    (g - want[ch]).abs() < 1e-5 * (1.0 + want[ch].abs()),
                    "n {n} point {x:?} channel {ch}: {g} vs {}",
                    want[ch]
                );
            }
        }
    }
}

#[test]
fn derivatives_match_central_differences_of_the_f64_definition() {
    let device = Device::flex();
    let (n, c, bound) = (8, 3, 1.0);
    let t = planes(n, c, bound, &device);
    let values: Vec<f64> = to_f32_vec(t.planes.val())
        .iter()
        .map(|&v| f64::from(v))
        .collect();
    // Inside the square, including points on a cell's boundary (s = k + 1/2, where the taps
    // change: the derivative is continuous there) and on a control point.
    let mut points = test_points();
    points.truncate(40);
    let cell = 2.0 * bound / (n - 1) as f64;
    points.push([-bound + 2.5 * cell, -bound + 3.0 * cell, 0.1]);
    let (_, derivatives) = t.sample(&t.shared(), tensor(&points, &device), true);
    let derivatives = derivatives.unwrap().map(to_f32_vec);
    let h = 1e-5;
    for (q, x) in points.iter().enumerate() {
        for j in 0..3 {
            let (mut a, mut b) = (*x, *x);
            a[j] += h;
            b[j] -= h;
            let (fa, fb) = (
                reference(&values, n, c, bound, a),
                reference(&values, n, c, bound, b),
            );
            for ch in 0..c {
                let fd = (fa[ch] - fb[ch]) / (2.0 * h);
                let got = f64::from(derivatives[j][q * c + ch]);
                assert!(
                    (got - fd).abs() < 1e-4 * (1.0 + fd.abs()),
                    "point {x:?} axis {j} channel {ch}: {got} vs {fd}"
                );
            }
        }
    }
    // Outside the square the features are constant in the clamped coordinate.
    let (_, d) = t.sample(&t.shared(), tensor(&[[1.7, 0.1, 0.2]], &device), true);
    assert!(to_f32_vec(d.unwrap()[0].clone()).iter().all(|&v| v == 0.0));
}

#[test]
fn the_planes_gradient_is_each_taps_weight() {
    let device = Device::flex().autodiff();
    let (n, c) = (6, 2);
    let t = planes(n, c, 1.0, &device);
    let points = test_points();
    let p = points.len();
    let mut rng = SplitMix64::new(4);
    let r: Vec<f64> = (0..p * c).map(|_| rng.next_f64() - 0.5).collect();
    let r32: Vec<f32> = r.iter().map(|&v| v as f32).collect();
    let r_t = Tensor::<2>::from_data(TensorData::new(r32, [p, c]), &device);
    let (features, _) = t.sample(&t.shared(), tensor(&points, &device), false);
    let grads = (features * r_t).sum().backward();
    let got = to_f32_vec(t.planes.grad(&grads).unwrap());
    // d/dP[row, ch] of sum_q r[q, ch] f(x_q)[ch]: the f64 definition's weight of that row
    // at each point, found by evaluating it on one-hot planes.
    for row in [0, 7, n * n + 3, 2 * n * n + n * n - 1] {
        let mut one_hot = vec![0.0; 3 * n * n * c];
        one_hot[row * c] = 1.0;
        let want: f64 = points
            .iter()
            .enumerate()
            .map(|(q, x)| r[q * c] * reference(&one_hot, n, c, 1.0, *x)[0])
            .sum();
        let g = f64::from(got[row * c]);
        assert!(
            (g - want).abs() < 1e-5 * (1.0 + want.abs()),
            "row {row}: {g} vs {want}"
        );
    }
}

#[test]
fn fold_is_the_cotangent_through_the_derivatives() {
    let device = Device::flex();
    let t = planes(8, 3, 1.0, &device);
    let points = test_points();
    let p = points.len();
    let (_, d) = t.sample(&t.shared(), tensor(&points, &device), true);
    let d = d.unwrap();
    let u = Tensor::<3>::from_data(
        TensorData::new(
            (0..p * 3).map(|i| (i % 7) as f32 - 3.0).collect::<Vec<_>>(),
            [1, p, 3],
        ),
        &device,
    );
    let got = to_f32_vec(t.fold(u.clone(), &d));
    let (u, d) = (to_f32_vec(u), d.map(to_f32_vec));
    for q in 0..p {
        for j in 0..3 {
            let want: f32 = (0..3).map(|ch| u[q * 3 + ch] * d[j][q * 3 + ch]).sum();
            assert!((got[q * 3 + j] - want).abs() < 1e-5 * (1.0 + want.abs()));
        }
    }
}

#[test]
fn fresh_planes_are_zero() {
    let t = TemplatePlanesConfig::new(4).init(&Device::flex());
    assert_eq!(t.planes.val().dims(), [48, 8]);
    assert!(to_f32_vec(t.planes.val()).iter().all(|&v| v == 0.0));
}

/// The taps of [`test_points`] for planes `t`, and the planes as a tensor on `device`.
fn taps_of(t: &TemplatePlanes, derivative: bool) -> Arc<Taps> {
    let v: Vec<f32> = test_points().iter().flatten().map(|&x| x as f32).collect();
    Arc::new(t.taps(&v, 1, derivative))
}

#[test]
fn the_kernel_equals_its_tensor_op_reference_in_values_and_gradients() {
    for derivative in [false, true] {
        // Values, without autodiff.
        let device = Device::flex();
        let t = planes(8, 5, 1.0, &device);
        let taps = taps_of(&t, derivative);
        let got = to_f32_vec(kernel::sample(t.planes.val(), taps.clone()));
        let want = to_f32_vec(kernel::sample_reference(t.planes.val(), &taps));
        assert_eq!(got.len(), want.len());
        for (i, (a, b)) in got.iter().zip(&want).enumerate() {
            assert!(
                (a - b).abs() <= 1e-5 * (1.0 + b.abs()),
                "{derivative} {i}: {a} vs {b}"
            );
        }
        // The planes' gradient of a fixed linear functional of every output.
        let device = Device::flex().autodiff();
        let t = planes(8, 5, 1.0, &device);
        let k = taps.outputs;
        let p = taps.points;
        let mut rng = SplitMix64::new(12);
        let r: Vec<f32> = (0..p * k * 5)
            .map(|_| (rng.next_f64() - 0.5) as f32)
            .collect();
        let r = Tensor::<3>::from_data(TensorData::new(r, [p, k, 5]), &device);
        let gradient = |out: Tensor<3>| {
            let grads = (out * r.clone()).sum().backward();
            to_f32_vec(t.planes.grad(&grads).unwrap())
        };
        let got = gradient(kernel::sample(t.planes.val(), taps.clone()));
        let want = gradient(kernel::sample_reference(t.planes.val(), &taps));
        let scale = want.iter().fold(0f32, |m, v| m.max(v.abs()));
        assert!(scale > 0.0);
        for (i, (a, b)) in got.iter().zip(&want).enumerate() {
            assert!(
                (a - b).abs() <= 1e-5 * scale,
                "{derivative} row {}: {a} vs {b}",
                i / 5
            );
        }
    }
}

#[test]
fn the_kernels_gradient_does_not_depend_on_the_thread_count() {
    let device = Device::flex().autodiff();
    let t = planes(6, 4, 1.0, &device);
    // Enough points for several blocks of the backward.
    let mut rng = SplitMix64::new(5);
    let v: Vec<f32> = (0..3 * 5000)
        .map(|_| (rng.next_f64() * 1.8 - 0.9) as f32)
        .collect();
    let taps = Arc::new(t.taps(&v, 1, true));
    let gradient = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let out = kernel::sample(t.planes.val(), taps.clone());
            let grads = out.sum().backward();
            to_f32_vec(t.planes.grad(&grads).unwrap())
        })
    };
    let one = gradient(1);
    assert_eq!(one, gradient(3), "bit for bit");
    assert!(one.iter().any(|&g| g != 0.0));
}

#[test]
fn extreme_points_clamp_and_a_nan_point_stays_its_own() {
    let device = Device::flex();
    let t = planes(8, 3, 1.0, &device);
    let points = [
        [1e30, -1e30, 0.0],
        [f64::INFINITY, f64::NEG_INFINITY, 0.5],
        [f64::NAN, 0.1, 0.2],
        [0.3, 0.2, 0.1],
    ];
    let (values, derivatives) = t.sample(&t.shared(), tensor(&points, &device), true);
    let values = to_f32_vec(values);
    let derivatives = derivatives.unwrap().map(to_f32_vec);
    let values64: Vec<f64> = to_f32_vec(t.planes.val())
        .iter()
        .map(|&v| f64::from(v))
        .collect();
    for q in [0, 1, 3] {
        let clamped = points[q].map(|x| x.clamp(-1.0, 1.0));
        let want = reference(&values64, 8, 3, 1.0, clamped);
        for ch in 0..3 {
            let got = f64::from(values[q * 3 + ch]);
            assert!(
                (got - want[ch]).abs() < 1e-5 * (1.0 + want[ch].abs()),
                "point {q}"
            );
        }
        assert!(
            derivatives
                .iter()
                .all(|d| d[q * 3..q * 3 + 3].iter().all(|v| v.is_finite()))
        );
    }
    // Clamped axes have no derivative.
    assert!(derivatives[0][..3].iter().all(|&v| v == 0.0));
    assert!(derivatives[1][3..6].iter().all(|&v| v == 0.0));
    // A NaN point gives NaN features, and only it.
    assert!(values[6..9].iter().all(|v| v.is_nan()));
}

/// Planes with a basis of `k` for latents of width `w_dim`, every parameter N(0, 1).
fn planes_with_basis(
    n: usize,
    c: usize,
    k: usize,
    w_dim: usize,
    device: &Device,
) -> TemplatePlanes {
    TemplatePlanesConfig::new(n)
        .with_channels(c)
        .with_basis(k)
        .with_w_dim(w_dim)
        .init(device)
        .map(&mut Reseed::new(7, DType::F32))
}

/// The parameters of planes with a basis in f64: the shared planes, the basis, and the
/// coefficients' effective weight `[K, w_dim]` and bias.
#[derive(Clone)]
struct BasisF64 {
    shared: Vec<f64>,
    basis: Vec<f64>,
    weight: Vec<f64>,
    bias: Vec<f64>,
}

fn f64s<const D: usize>(t: Tensor<D>) -> Vec<f64> {
    to_f32_vec(t).into_iter().map(f64::from).collect()
}

impl BasisF64 {
    fn of(t: &TemplatePlanes) -> Self {
        let basis = t.basis.as_ref().unwrap();
        Self {
            shared: f64s(t.planes.val()),
            basis: f64s(basis.planes.val()),
            weight: f64s(basis.coefficients.effective_weight()),
            bias: f64s(basis.coefficients.effective_bias().unwrap()),
        }
    }

    /// Latent `w`'s planes from the definition: `shared + sum_k (W w + b)_k basis_k`.
    fn planes(&self, w: &[f64]) -> Vec<f64> {
        let len = self.shared.len();
        let mut out = self.shared.clone();
        for (k, bias) in self.bias.iter().enumerate() {
            let row = &self.weight[k * w.len()..(k + 1) * w.len()];
            let a = bias + row.iter().zip(w).map(|(m, x)| m * x).sum::<f64>();
            for (o, b) in out.iter_mut().zip(&self.basis[k * len..(k + 1) * len]) {
                *o += a * b;
            }
        }
        out
    }
}

/// `values` as an f32 tensor of `shape`.
fn tensor_of(values: &[f64], shape: [usize; 2], device: &Device) -> Tensor<2> {
    let v: Vec<f32> = values.iter().map(|&x| x as f32).collect();
    Tensor::from_data(TensorData::new(v, shape), device)
}

#[test]
fn each_latents_planes_are_the_shared_planes_plus_its_weighted_basis() {
    let device = Device::flex();
    let (n, c, k, w_dim) = (6, 3, 4, 5);
    let t = planes_with_basis(n, c, k, w_dim, &device);
    let params = BasisF64::of(&t);
    let w = crate::test_support::normals(&mut SplitMix64::new(21), 2 * w_dim);
    // Two latents, half of the points each.
    let points = test_points();
    let half = points.len() / 2;
    let (features, derivatives) = t.forward(
        tensor(&points, &device),
        &tensor_of(&w, [2, w_dim], &device),
        true,
    );
    let (features, derivatives) = (to_f32_vec(features), derivatives.unwrap().map(to_f32_vec));
    let h = 1e-5;
    for latent in 0..2 {
        let own = params.planes(&w[latent * w_dim..(latent + 1) * w_dim]);
        for (q, x) in points.iter().enumerate().skip(latent * half).take(half) {
            let want = reference(&own, n, c, 1.0, *x);
            for ch in 0..c {
                let got = f64::from(features[q * c + ch]);
                assert!(
                    (got - want[ch]).abs() < 1e-4 * (1.0 + want[ch].abs()),
                    "latent {latent} point {x:?} channel {ch}: {got} vs {}",
                    want[ch]
                );
            }
            if x.iter().any(|v| v.abs() > 0.9) {
                continue;
            }
            for j in 0..3 {
                let (mut a, mut b) = (*x, *x);
                a[j] += h;
                b[j] -= h;
                let (fa, fb) = (reference(&own, n, c, 1.0, a), reference(&own, n, c, 1.0, b));
                for ch in 0..c {
                    let fd = (fa[ch] - fb[ch]) / (2.0 * h);
                    let got = f64::from(derivatives[j][q * c + ch]);
                    assert!(
                        (got - fd).abs() < 1e-4 * (1.0 + fd.abs()),
                        "latent {latent} point {x:?} axis {j} channel {ch}: {got} vs {fd}"
                    );
                }
            }
        }
    }
}

/// The gradient of `sum r f` (features `f` of two latents) in the shared planes, the basis,
/// and the coefficients' weight and bias, against central differences of the f64
/// definition. The features are linear in each of these, so the differences are exact up
/// to rounding.
#[test]
fn the_basis_and_its_coefficients_get_the_central_difference_gradient() {
    let device = Device::flex().autodiff();
    let (n, c, k, w_dim) = (5, 2, 3, 4);
    let t = planes_with_basis(n, c, k, w_dim, &device);
    let params = BasisF64::of(&t);
    let w = crate::test_support::normals(&mut SplitMix64::new(22), 2 * w_dim);
    let points = test_points();
    let (p, half) = (points.len(), points.len() / 2);
    let r = crate::test_support::normals(&mut SplitMix64::new(23), p * c);
    let (features, _) = t.forward(
        tensor(&points, &device),
        &tensor_of(&w, [2, w_dim], &device),
        false,
    );
    let grads = (features * tensor_of(&r, [p, c], &device)).sum().backward();
    let basis = t.basis.as_ref().unwrap();
    let gains = (basis.coefficients.weight_gain, basis.coefficients.bias_gain);
    let loss = |params: &BasisF64| -> f64 {
        (0..2)
            .map(|latent| {
                let own = params.planes(&w[latent * w_dim..(latent + 1) * w_dim]);
                (latent * half..(latent + 1) * half)
                    .map(|q| {
                        let f = reference(&own, n, c, 1.0, points[q]);
                        (0..c).map(|ch| r[q * c + ch] * f[ch]).sum::<f64>()
                    })
                    .sum::<f64>()
            })
            .sum()
    };
    type Pick = fn(&mut BasisF64) -> &mut Vec<f64>;
    let cases: [(&str, Vec<f32>, Pick, f64); 4] = [
        (
            "shared planes",
            to_f32_vec(t.planes.grad(&grads).unwrap()),
            |b| &mut b.shared,
            1.0,
        ),
        (
            "basis",
            to_f32_vec(basis.planes.grad(&grads).unwrap()),
            |b| &mut b.basis,
            1.0,
        ),
        (
            "coefficients' weight",
            to_f32_vec(basis.coefficients.weight.grad(&grads).unwrap()),
            |b| &mut b.weight,
            gains.0,
        ),
        (
            "coefficients' bias",
            to_f32_vec(
                basis
                    .coefficients
                    .bias
                    .as_ref()
                    .unwrap()
                    .grad(&grads)
                    .unwrap(),
            ),
            |b| &mut b.bias,
            gains.1,
        ),
    ];
    let h = 1e-3;
    for (what, got, pick, gain) in cases {
        // The entries the loss leans on most, and a few spread over the rest.
        let mut order: Vec<usize> = (0..got.len()).collect();
        order.sort_by(|&a, &b| got[b].abs().total_cmp(&got[a].abs()));
        let scale = f64::from(got[order[0]].abs());
        assert!(scale > 0.0, "{what}: the loss does not reach it");
        let step = (got.len() / 5).max(1);
        let entries = order.iter().take(6).chain(order.iter().step_by(step));
        for &e in entries {
            let at = |delta: f64| {
                let mut moved = params.clone();
                pick(&mut moved)[e] += delta;
                loss(&moved)
            };
            // A stored parameter moves its effective value by `gain` times as much.
            let fd = gain * (at(h) - at(-h)) / (2.0 * h);
            let g = f64::from(got[e]);
            assert!(
                (g - fd).abs() < 1e-4 * scale,
                "{what}[{e}]: {g} vs central difference {fd} (scale {scale})"
            );
        }
    }
}

#[test]
fn a_fresh_basis_is_zero_so_every_latent_starts_on_the_shared_planes() {
    let device = Device::flex();
    let mut t = TemplatePlanesConfig::new(4)
        .with_basis(3)
        .with_w_dim(6)
        .init(&device);
    let basis = t.basis.as_ref().unwrap();
    assert_eq!(basis.planes.val().dims(), [3, 48 * 8]);
    assert!(to_f32_vec(basis.planes.val()).iter().all(|&v| v == 0.0));
    let shared = crate::test_support::normals(&mut SplitMix64::new(5), 48 * 8);
    t.planes = Param::from_tensor(tensor_of(&shared, [48, 8], &device));
    let w = crate::test_support::normals(&mut SplitMix64::new(6), 3 * 6);
    let own = t.of_latents(&tensor_of(&w, [3, 6], &device));
    assert_eq!(own.latents, 3);
    assert_eq!(own.planes.dims(), [3 * 48, 8]);
    let own = to_f32_vec(own.planes);
    let shared = to_f32_vec(t.planes.val());
    for latent in 0..3 {
        assert_eq!(own[latent * 48 * 8..(latent + 1) * 48 * 8], shared[..]);
    }
    // Without a basis every latent reads the one set.
    let plain = TemplatePlanesConfig::new(4).init(&device);
    assert!(plain.basis.is_none());
    let one = plain.of_latents(&tensor_of(&w, [3, 6], &device));
    assert_eq!((one.latents, one.planes.dims()), (1, [48, 8]));
}
