use super::*;
use crate::backend::to_f32_vec;
use crate::test_support::{Reseed, normals};
use burn::tensor::{DType, Distribution, TensorData};
use volux_envmap::random::SplitMix64;

fn small(frequencies: usize, device: &Device) -> Neiif {
    small_with_prior(frequencies, 0.0, device)
}

fn small_with_prior(frequencies: usize, sphere_prior: f64, device: &Device) -> Neiif {
    small_config(frequencies, sphere_prior).init(device)
}

fn small_config(frequencies: usize, sphere_prior: f64) -> NeiifConfig {
    NeiifConfig::new()
        .with_w_dim(16)
        .with_width(32)
        .with_head_width(16)
        .with_frequencies(frequencies)
        .with_sphere_prior(sphere_prior)
}

fn points(n: usize, seed: u64, device: &Device) -> Tensor<3> {
    let mut rng = SplitMix64::new(seed);
    let v: Vec<f32> = (0..3 * n)
        .map(|_| (rng.next_f64() * 1.6 - 0.8) as f32)
        .collect();
    Tensor::from_data(TensorData::new(v, [1, n, 3]), device)
}

/// `values` as an f32 tensor of `shape` on `device`.
fn tensor_of<const D: usize>(values: &[f64], shape: [usize; D], device: &Device) -> Tensor<D> {
    let v: Vec<f32> = values.iter().map(|v| *v as f32).collect();
    Tensor::from_data(TensorData::new(v, shape), device)
}

/// The fixed cotangent of `grad(sigma)` at `n` points and the fixed latent the second-order
/// tests use.
fn cotangent_and_latent(n: usize, device: &Device) -> (Tensor<3>, Vec<f64>) {
    let r = normals(&mut SplitMix64::new(43), 3 * n);
    (
        tensor_of(&r, [1, n, 3], device),
        normals(&mut SplitMix64::new(42), 16),
    )
}

/// The reverse sweep's `grad(sigma)` against central differences of the density on random
/// weights. `h` and the tolerance are set by the highest octave: central differences of
/// `sin(2^(F-1) pi x)` have a truncation error `~ (2^(F-1) pi h)^2 / 6`.
fn check_gradient(frequencies: usize, sphere_prior: f64, h: f64, tol: f64) {
    check_gradient_of(small_config(frequencies, sphere_prior), h, tol);
}

fn check_gradient_of(config: NeiifConfig, h: f64, tol: f64) {
    check_windowed_gradient_of(config, None, h, tol);
}

/// [`check_gradient_of`] with the encoding's octaves opened to `window`.
fn check_windowed_gradient_of(config: NeiifConfig, window: Option<f64>, h: f64, tol: f64) {
    let device = Device::flex();
    let frequencies = config.frequencies;
    // Fixed weights and latent, so that the error measured here is the error of every run.
    let mut field = config.init(&device).map(&mut Reseed::new(21, DType::F32));
    field.encoding.set_window(window);
    let w = tensor_of(&normals(&mut SplitMix64::new(22), 16), [1, 16], &device);
    let n = 24;
    let pts = points(n, 7, &device);
    let got = field.forward(pts.clone(), w.clone(), FieldWants::ALL);
    let grad = to_f32_vec(got.grad_sigma.unwrap());
    let normals = to_f32_vec(got.normals.unwrap());
    let base = to_f32_vec(pts);
    let sigma_at = |delta: [f64; 3]| {
        let v: Vec<f32> = base
            .chunks(3)
            .flat_map(|p| (0..3).map(move |k| (f64::from(p[k]) + delta[k]) as f32))
            .collect();
        let pts = Tensor::<3>::from_data(TensorData::new(v, [1, n, 3]), &device);
        to_f32_vec(field.forward(pts, w.clone(), FieldWants::DENSITY).sigma)
    };
    let mut worst = 0.0f64;
    for j in 0..3 {
        let mut e = [0.0; 3];
        e[j] = h;
        let plus = sigma_at(e);
        e[j] = -h;
        let minus = sigma_at(e);
        for i in 0..n {
            let fd = (f64::from(plus[i]) - f64::from(minus[i])) / (2.0 * h);
            let g = f64::from(grad[3 * i + j]);
            let scale = (0..3)
                .map(|k| f64::from(grad[3 * i + k]).powi(2))
                .sum::<f64>()
                .sqrt();
            worst = worst.max((g - fd).abs() / (scale + 1e-3));
        }
    }
    assert!(worst < tol, "F={frequencies}: worst relative error {worst}");
    for i in 0..n {
        let len: f32 = (0..3).map(|k| normals[3 * i + k].powi(2)).sum::<f32>();
        assert!((len - 1.0).abs() < 1e-4, "normal {i} has length^2 {len}");
        let dot: f32 = (0..3).map(|k| normals[3 * i + k] * grad[3 * i + k]).sum();
        assert!(dot < 0.0, "normals point against the density gradient");
    }
}

/// The second order: the gradient of a loss on `grad(sigma)` with respect to the latent
/// `w` (which every layer's modulation sees, so the sweep's weights, pullbacks and biases
/// all take part) against central differences of that loss, on fixed weights.
#[test]
fn a_loss_on_the_density_gradient_has_the_central_difference_gradient_in_w() {
    check_w_gradient(small_config(3, 10.0));
}

/// [`a_loss_on_the_density_gradient_has_the_central_difference_gradient_in_w`] on `config`.
fn check_w_gradient(config: NeiifConfig) {
    let device = Device::flex().autodiff();
    let field = config.init(&device).map(&mut Reseed::new(41, DType::F32));
    let n = 16;
    let pts = points(n, 9, &device);
    let (r, w0) = cotangent_and_latent(n, &device);
    let loss_at = |w: &[f64]| {
        let w = tensor_of(w, [1, 16], &device).require_grad();
        let out = field.forward(pts.clone(), w.clone(), FieldWants::ALL);
        let loss = (out.grad_sigma.unwrap() * r.clone()).sum();
        (w, loss)
    };
    let (w, loss) = loss_at(&w0);
    let grads = loss.backward();
    let got = to_f32_vec(w.grad(&grads).unwrap());
    let h = 1e-2;
    let scale = got.iter().fold(0.0f32, |m, v| m.max(v.abs())) as f64;
    for k in 0..16 {
        let at = |d: f64| {
            let mut w = w0.clone();
            w[k] += d;
            f64::from(loss_at(&w).1.into_scalar::<f32>())
        };
        let fd = (at(h) - at(-h)) / (2.0 * h);
        let g = f64::from(got[k]);
        assert!(
            (g - fd).abs() < 2e-2 * scale,
            "d loss / d w[{k}]: {g} vs central difference {fd} (scale {scale})"
        );
    }
    assert!(scale > 0.0, "the loss does not depend on w");
}

/// The template planes in the field: the density gradient (whose sweep ends in the planes'
/// derivatives as well as the encoding's) matches central differences, and the gradient in
/// the planes of a loss on it matches central differences of that loss.
#[test]
fn template_planes_give_the_central_difference_density_gradient_and_plane_gradient() {
    let config = small_config(4, 10.0)
        .with_template_resolution(8)
        .with_template_channels(4);
    check_gradient_of(config.clone(), 1e-3, 5e-3);

    let device = Device::flex().autodiff();
    let mut field = config.init(&device).map(&mut Reseed::new(41, DType::F32));
    let n = 16;
    let pts = points(n, 9, &device);
    let (r, w) = cotangent_and_latent(n, &device);
    let w = tensor_of(&w, [1, 16], &device);
    let loss_of = |field: &Neiif| {
        let out = field.forward(pts.clone(), w.clone(), FieldWants::ALL);
        (out.grad_sigma.unwrap() * r.clone()).sum()
    };
    let grads = loss_of(&field).backward();
    let template = field.template.as_ref().unwrap();
    let got = to_f32_vec(template.planes.grad(&grads).unwrap());
    let values = to_f32_vec(template.planes.val());
    let dims = template.planes.val().dims();
    // The entries the loss leans on most, against central differences.
    let mut order: Vec<usize> = (0..got.len()).collect();
    order.sort_by(|&a, &b| got[b].abs().total_cmp(&got[a].abs()));
    let scale = f64::from(got[order[0]].abs());
    assert!(scale > 0.0, "the loss does not reach the planes");
    let h = 1e-2;
    for &k in &order[..8] {
        let mut at = |delta: f64| {
            let mut v = values.clone();
            v[k] += delta as f32;
            let planes = Tensor::<2>::from_data(TensorData::new(v, dims), &device);
            field.template.as_mut().unwrap().planes = burn::module::Param::from_tensor(planes);
            f64::from(loss_of(&field).into_scalar::<f32>())
        };
        let fd = (at(h) - at(-h)) / (2.0 * h);
        let g = f64::from(got[k]);
        assert!(
            (g - fd).abs() < 2e-2 * scale,
            "d loss / d plane[{k}]: {g} vs central difference {fd} (scale {scale})"
        );
    }
}

/// Template planes of each latent's own (a basis): the density gradient matches central
/// differences, a loss on it has the central-difference gradient in `w` (which now also
/// reaches the planes through the basis' coefficients), and a batch of two latents is each
/// latent queried alone, in every output (each latent's points read its own planes).
#[test]
fn a_basis_of_template_planes_keeps_the_gradients_and_each_latent_reads_its_own_planes() {
    let config = small_config(3, 10.0)
        .with_template_resolution(8)
        .with_template_channels(4)
        .with_template_basis(3);
    check_gradient_of(config.clone(), 1e-3, 5e-3);
    check_w_gradient(config.clone());

    let device = Device::flex();
    let field = config.init(&device).map(&mut Reseed::new(43, DType::F32));
    let n = 12;
    let (a, b) = (points(n, 3, &device), points(n, 4, &device));
    let w = normals(&mut SplitMix64::new(44), 2 * 16);
    let (wa, wb) = (
        tensor_of(&w[..16], [1, 16], &device),
        tensor_of(&w[16..], [1, 16], &device),
    );
    let both = field.forward(
        Tensor::cat(vec![a.clone(), b.clone()], 0),
        Tensor::cat(vec![wa.clone(), wb.clone()], 0),
        FieldWants::ALL,
    );
    let (alone_a, alone_b) = (
        field.forward(a, wa, FieldWants::ALL),
        field.forward(b, wb, FieldWants::ALL),
    );
    // Each output as `[latents, values per latent]`: the batch's first half is latent 0's.
    let outputs = |o: FieldOutput, latents: usize| {
        [
            ("sigma", o.sigma.reshape([latents, n])),
            (
                "grad sigma",
                o.grad_sigma.unwrap().reshape([latents, 3 * n]),
            ),
            ("albedo", o.albedo.unwrap().reshape([latents, 3 * n])),
        ]
    };
    let alone = outputs(alone_a, 1).into_iter().zip(outputs(alone_b, 1));
    for ((what, both), ((_, a), (_, b))) in outputs(both, 2).into_iter().zip(alone) {
        let both = to_f32_vec(both);
        let want: Vec<f32> = [to_f32_vec(a), to_f32_vec(b)].concat();
        assert_eq!(both.len(), want.len());
        for (i, (g, w)) in both.iter().zip(&want).enumerate() {
            assert!(
                (g - w).abs() <= 1e-4 * (1.0 + w.abs()),
                "{what} of latent {}: {g} vs {w}",
                i / (want.len() / 2)
            );
        }
    }
}

#[test]
fn activation_matches_softplus_and_sigmoid_in_f64() {
    let device = Device::flex();
    let xs: Vec<f32> = (-400..=400).map(|i| i as f32 * 0.1).collect();
    let x = Tensor::<1>::from_floats(xs.as_slice(), &device);
    let (v, d) = smooth_lrelu_parts(x, true);
    let (v, d) = (to_f32_vec(v), to_f32_vec(d.unwrap()));
    for (i, x) in xs.iter().map(|x| f64::from(*x)).enumerate() {
        let softplus = x.max(0.0) + (-x.abs()).exp().ln_1p();
        let sigmoid = 1.0 / (1.0 + (-x).exp());
        let want_v = SMOOTH_GAIN * (0.2 * x + 0.8 * softplus);
        let want_d = SMOOTH_GAIN * (0.2 + 0.8 * sigmoid);
        assert!(
            (f64::from(v[i]) - want_v).abs() < 1e-5 * (1.0 + want_v.abs()),
            "x={x}"
        );
        assert!((f64::from(d[i]) - want_d).abs() < 1e-6, "x={x}");
    }
}

#[test]
fn density_gradient_matches_central_differences_at_low_frequencies() {
    check_gradient(4, 0.0, 1e-3, 2e-3);
    check_gradient(4, 10.0, 1e-3, 2e-3);
}

#[test]
fn density_gradient_matches_central_differences_at_the_papers_ten_octaves() {
    // With fixed weights the worst relative error is 4.1e-3 at h = 5e-5 (f32 rounding of
    // the sigma differences and the truncation of sin(512 pi x) balance there; 1e-4 gives
    // 1.6e-2, 2e-4 gives 6e-2). A wrong sweep is off by O(1).
    check_gradient(10, 0.0, 5e-5, 1e-2);
}

#[test]
fn density_gradient_matches_central_differences_with_rotated_octaves() {
    // The sweep ends in the rotated encoding's fold (each octave's block turned back by its
    // rotation); a fold that summed the blocks as the axis-aligned one does is off by O(1).
    check_gradient_of(
        small_config(5, 10.0).with_rotated_encoding(true),
        5e-4,
        3e-3,
    );
    check_gradient_of(
        small_config(10, 0.0).with_rotated_encoding(true),
        5e-5,
        1e-2,
    );
}

#[test]
fn density_gradient_matches_central_differences_with_octaves_opening() {
    // The fifth octave half open and the fourth open: the sweep must carry each octave's
    // weight through the encoding's derivative (without it the gradient is off by the
    // closed part of the octave, O(1)).
    for rotated in [false, true] {
        check_windowed_gradient_of(
            small_config(5, 10.0).with_rotated_encoding(rotated),
            Some(4.5),
            5e-4,
            3e-3,
        );
        check_windowed_gradient_of(
            small_config(5, 0.0).with_rotated_encoding(rotated),
            Some(2.2),
            1e-3,
            2e-3,
        );
    }
}

#[test]
fn outputs_have_their_shapes_and_ranges_and_skip_what_is_not_wanted() {
    let device = Device::flex();
    let field = small(10, &device);
    let w = Tensor::<2>::random([2, 16], Distribution::Normal(0.0, 1.0), &device);
    let pts = Tensor::cat(vec![points(9, 1, &device), points(9, 2, &device)], 0);
    let all = field.forward(pts.clone(), w.clone(), FieldWants::ALL);
    assert_eq!(all.sigma.dims(), [2, 9]);
    assert_eq!(all.normals.as_ref().unwrap().dims(), [2, 9, 3]);
    assert_eq!(all.features.as_ref().unwrap().dims(), [2, 9, 32]);
    let albedo = to_f32_vec(all.albedo.unwrap());
    assert!(albedo.iter().all(|a| (0.0..=1.0).contains(a)));
    let spec = to_f32_vec(all.specular_weights.unwrap());
    assert_eq!(spec.len(), 2 * 9 * 4);
    assert!(spec.iter().all(|s| *s >= 0.0));
    assert!(to_f32_vec(all.sigma.clone()).iter().all(|s| *s >= 0.0));
    let density = field.forward(pts.clone(), w.clone(), FieldWants::DENSITY);
    assert!(density.normals.is_none() && density.albedo.is_none());
    let diff: f32 = (density.sigma - all.sigma).abs().max().into_scalar();
    assert!(diff < 1e-5, "density-only query differs by {diff}");
    let no_normals = field.forward(
        pts,
        w,
        FieldWants {
            normals: false,
            appearance: true,
        },
    );
    assert!(no_normals.normals.is_none() && no_normals.features.is_some());
}

#[test]
fn fused_activation_gives_the_reference_outputs_and_gradients() {
    let device = Device::flex().autodiff();
    let field = small_with_prior(4, 10.0, &device).map(&mut Reseed::new(31, DType::F32));
    let w = Tensor::<2>::random([2, 16], Distribution::Normal(0.0, 1.0), &device);
    let pts = Tensor::cat(vec![points(300, 4, &device), points(300, 5, &device)], 0);
    let run = |kernels: ActivationKernels| {
        let out = field.forward_with(pts.clone(), w.clone(), FieldWants::ALL, kernels);
        let parts = [
            out.grad_sigma.unwrap(),
            out.normals.unwrap(),
            out.albedo.unwrap(),
            out.specular_weights.unwrap(),
            out.features.unwrap(),
        ];
        let mut loss = out.sigma.clone().sum();
        let mut values = to_f32_vec(out.sigma);
        for (k, p) in parts.into_iter().enumerate() {
            values.extend(to_f32_vec(p.clone()));
            loss = loss + p.sum().mul_scalar(k as f64 + 1.0);
        }
        let grads = loss.backward();
        let mut g = Vec::new();
        for layer in &field.layers {
            g.extend(to_f32_vec(layer.weight.val().grad(&grads).unwrap()));
            g.extend(to_f32_vec(layer.bias.val().grad(&grads).unwrap()));
            g.extend(to_f32_vec(layer.affine.weight.val().grad(&grads).unwrap()));
        }
        g.extend(to_f32_vec(
            field.head_hidden.weight.val().grad(&grads).unwrap(),
        ));
        (values, g)
    };
    let (fused, reference) = (
        run(ActivationKernels::FUSED),
        run(ActivationKernels::REFERENCE),
    );
    for (what, got, want, tol) in [
        ("outputs", &fused.0, &reference.0, 1e-5),
        ("parameter gradients", &fused.1, &reference.1, 1e-4),
    ] {
        let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let worst = got
            .iter()
            .zip(want.iter())
            .fold(0.0f32, |m, (g, w)| m.max((g - w).abs()));
        assert!(
            worst <= tol * scale,
            "{what}: worst difference {worst}, scale {scale}"
        );
    }
}

#[test]
fn a_loss_on_normals_reaches_the_first_layer_and_the_mapping_input() {
    let device = Device::flex().autodiff();
    let field = small(6, &device);
    let w = Tensor::<2>::random([1, 16], Distribution::Normal(0.0, 1.0), &device).require_grad();
    let out = field.forward(points(16, 3, &device), w.clone(), FieldWants::ALL);
    let loss = out.normals.unwrap().narrow(2, 2, 1).sum();
    let grads = loss.backward();
    let g1 = to_f32_vec(field.layers[0].weight.val().grad(&grads).unwrap());
    assert!(g1.iter().all(|v| v.is_finite()));
    assert!(
        g1.iter().any(|v| v.abs() > 0.0),
        "no gradient reached layer 1"
    );
    let gw = to_f32_vec(w.grad(&grads).unwrap());
    assert!(gw.iter().any(|v| v.abs() > 0.0));
    // Layers 5-6 do not shape the density, so a loss on normals leaves them untouched.
    assert!(
        field.layers[5]
            .weight
            .val()
            .grad(&grads)
            .is_none_or(|g| { to_f32_vec(g).iter().all(|v| *v == 0.0) })
    );
}
