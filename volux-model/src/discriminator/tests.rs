use super::*;
use crate::backend::{to_f32_vec, to_f64_vec};
use crate::bias_act::bias_lrelu_reference;
use crate::test_support::{Reseed, normals, shift_element};
use burn::module::Param;
use burn::tensor::{DType, Gradients, TensorData};
use volux_envmap::random::SplitMix64;

fn tensor<const D: usize>(
    v: Vec<f64>,
    shape: [usize; D],
    device: &Device,
    dtype: DType,
) -> Tensor<D> {
    Tensor::from_data(TensorData::new(v, shape), (device, dtype))
}

/// 3 channels at 16x16: channels 4 (16x16), 8 (8x8), 16 (4x4).
fn tiny(device: &Device, seed: u64, dtype: DType) -> Discriminator {
    DiscriminatorConfig::new(3, 16)
        .with_channel_base(64)
        .with_channel_max(16)
        .init(device)
        .map(&mut Reseed::new(seed, dtype))
}

/// Parameters of StyleGAN2's resnet discriminator, counted layer by layer.
fn expected_params(cfg: &DiscriminatorConfig) -> usize {
    let ch = |r| cfg.channels_at(r);
    let mut n = cfg.in_channels * ch(cfg.resolution) + ch(cfg.resolution);
    let mut r = cfg.resolution;
    while r > 4 {
        let (a, b) = (ch(r), ch(r / 2));
        n += (a * a * 9 + a) + (a * b * 9 + b) + a * b;
        r /= 2;
    }
    let c = ch(4);
    n + ((c + cfg.mbstd_channels) * c * 9 + c) + (c * 16 * c + c) + (c + 1)
}

/// [`minibatch_std`]'s appended values in f64 loops: `[n][features]`.
fn minibatch_std_ref(
    x: &[f64],
    [n, c, h, w]: [usize; 4],
    group: usize,
    features: usize,
) -> Vec<Vec<f64>> {
    let g = group.min(n);
    let m = n / g;
    let cf = c / features;
    let at = |i: usize, ch: usize, p: usize| x[(i * c + ch) * h * w + p];
    (0..n)
        .map(|i| {
            let members: Vec<usize> = (0..g).map(|k| k * m + i % m).collect();
            (0..features)
                .map(|f| {
                    let mut acc = 0.0;
                    for ch in f * cf..(f + 1) * cf {
                        for p in 0..h * w {
                            let mean =
                                members.iter().map(|&j| at(j, ch, p)).sum::<f64>() / g as f64;
                            let var = members
                                .iter()
                                .map(|&j| (at(j, ch, p) - mean).powi(2))
                                .sum::<f64>()
                                / g as f64;
                            acc += (var + MBSTD_EPSILON).sqrt();
                        }
                    }
                    acc / (cf * h * w) as f64
                })
                .collect()
        })
        .collect()
}

#[test]
fn minibatch_std_matches_an_f64_loop() {
    let device = Device::flex();
    let mut rng = SplitMix64::new(1);
    for (n, group, features) in [(8, 4, 2), (4, 4, 1), (2, 4, 1), (6, 3, 2), (1, 4, 1)] {
        let shape = [n, 4, 3, 2];
        let xv = normals(&mut rng, shape.iter().product());
        let x = tensor(xv.clone(), shape, &device, DType::F32);
        let y = minibatch_std(x, group, features);
        assert_eq!(y.dims(), [n, 4 + features, 3, 2]);
        let yv = to_f32_vec(y);
        // The input channels pass through unchanged.
        for i in 0..n {
            for k in 0..4 * 6 {
                assert_eq!(yv[i * (4 + features) * 6 + k], xv[i * 24 + k] as f32);
            }
        }
        let want = minibatch_std_ref(&xv, shape, group, features);
        for i in 0..n {
            for f in 0..features {
                for p in 0..6 {
                    let got = f64::from(yv[(i * (4 + features) + 4 + f) * 6 + p]);
                    assert!(
                        (got - want[i][f]).abs() < 1e-5,
                        "n {n} sample {i} feature {f}: {got} vs {}",
                        want[i][f]
                    );
                }
            }
        }
    }
}

#[test]
fn minibatch_std_input_gradient_matches_autodiff() {
    // d/dx <minibatch_std(x), y> by the explicit formula and by Burn's autodiff.
    let device = Device::flex().autodiff();
    let mut rng = SplitMix64::new(2);
    for (n, group, features) in [(8, 4, 2), (4, 4, 1), (2, 4, 1)] {
        let shape = [n, 4, 3, 3];
        let x = tensor(
            normals(&mut rng, shape.iter().product()),
            shape,
            &device,
            DType::F32,
        )
        .require_grad();
        let out_shape = [n, 4 + features, 3, 3];
        let y = tensor(
            normals(&mut rng, out_shape.iter().product()),
            out_shape,
            &device,
            DType::F32,
        );
        let grads = (minibatch_std(x.clone(), group, features) * y.clone())
            .sum()
            .backward();
        let want = to_f32_vec(x.grad(&grads).unwrap());
        let got = to_f32_vec(minibatch_std_input_gradient(x, y, group, features));
        let scale = want.iter().fold(0f32, |m, v| m.max(v.abs()));
        for (a, b) in got.iter().zip(&want) {
            assert!((a - b).abs() < 1e-5 * scale, "n {n}: {a} vs {b}");
        }
    }
}

/// Asserts `got` within `tolerance` of `want`'s largest magnitude (which must be non-zero).
fn assert_close(got: &[f64], want: &[f64], tolerance: f64, what: &str) {
    let scale = want.iter().fold(0f64, |m, v| m.max(v.abs()));
    assert!(scale > 0.0, "{what}: all zero");
    let err = got
        .iter()
        .zip(want)
        .fold(0f64, |m, (a, b)| m.max((a - b).abs()));
    assert!(
        err < tolerance * scale,
        "{what}: max error {err:e}, largest {scale}"
    );
}

/// In f32 (what training runs) and in f64 (where 1e-9 leaves no room for a missing term,
/// e.g. the minibatch std's cross-sample one, whose share is small): `check(d, x, rng, what)`
/// for batches 8 and 4 (two groups, one group of 4) and 2, 1 (groups smaller than 4).
fn for_each_batch(
    seed: u64,
    check: impl Fn(&Discriminator, Tensor<4>, &mut SplitMix64, f64, &str),
) {
    let device = Device::flex().autodiff();
    for (dtype, tolerance) in [(DType::F32, 1e-4), (DType::F64, 1e-9)] {
        let d = tiny(&device, seed, dtype);
        let mut rng = SplitMix64::new(seed + 1);
        for batch in [8, 4, 2, 1] {
            let shape = [batch, 3, 16, 16];
            let x = tensor(
                normals(&mut rng, shape.iter().product()),
                shape,
                &device,
                dtype,
            );
            check(
                &d,
                x,
                &mut rng,
                tolerance,
                &format!("{dtype:?} batch {batch}"),
            );
        }
    }
}

#[test]
fn input_gradient_matches_autodiff() {
    for_each_batch(3, |d, x, _, tolerance, what| {
        let x_leaf = x.clone().require_grad();
        let logits = d.forward(x_leaf.clone());
        let grads = logits.clone().sum().backward();
        let want = to_f64_vec(x_leaf.grad(&grads).unwrap());
        let (logits2, grad) = d.input_gradient(x.clone());
        assert_eq!(grad.dims(), x.dims());
        assert_eq!(to_f64_vec(logits), to_f64_vec(logits2));
        assert_close(&to_f64_vec(grad), &want, tolerance, what);
    });
}

/// The pullback of one forward pass gives `sum_b c_b d logit_b / d x` for any cotangent `c`
/// (minibatch std's cross-sample terms included), untracked, while the pass's logits keep
/// the weights' gradient of a plain forward.
#[test]
fn pullback_gives_the_input_gradient_of_any_cotangent() {
    for_each_batch(5, |d, x, rng, tolerance, what| {
        let batch = x.dims()[0];
        let c = Tensor::<2>::from_data(
            TensorData::new(normals(rng, batch), [batch, 1]),
            (&x.device(), x.dtype()),
        );
        let x_leaf = x.clone().require_grad();
        let logits = d.forward(x_leaf.clone());
        let grads = (logits.clone() * c.clone()).sum().backward();
        let want = to_f64_vec(x_leaf.grad(&grads).unwrap());
        let w = d.blocks[0].conv0.weight.val();
        let want_w = to_f64_vec(w.grad(&grads).unwrap());

        let (logits2, pullback) = d.forward_with_pullback(x.clone());
        assert_eq!(to_f64_vec(logits), to_f64_vec(logits2.clone()));
        let grad = pullback.input_gradient(c.clone());
        assert_eq!(grad.dims(), x.dims());
        assert!(!grad.is_require_grad(), "the pullback is a constant");
        assert_close(
            &to_f64_vec(grad),
            &want,
            tolerance,
            &format!("{what} input gradient"),
        );
        let grads = (logits2 * c).sum().backward();
        let got_w = to_f64_vec(w.grad(&grads).unwrap());
        assert_close(
            &got_w,
            &want_w,
            tolerance,
            &format!("{what} weight gradient"),
        );
    });
}

#[test]
fn r1_weight_gradient_matches_finite_differences() {
    // In f64: autodiff of the penalty through the explicit input gradient against central
    // differences of the penalty, for weights before, inside and after the minibatch std.
    let device = Device::flex().autodiff();
    let d = tiny(&device, 5, DType::F64);
    let shape = [4, 3, 16, 16];
    let x = tensor(
        normals(&mut SplitMix64::new(6), 4 * 3 * 256),
        shape,
        &device,
        DType::F64,
    );
    let gamma = 2.0;
    let (_, penalty) = r1_penalty(&d, x.clone(), gamma);
    let grads = penalty.clone().backward();

    // The penalty itself is gamma / 2 * mean ||input gradient||^2, with the input gradient
    // from Burn's autodiff.
    let x_leaf = x.clone().require_grad();
    let g = x_leaf
        .grad(&d.forward(x_leaf.clone()).sum().backward())
        .unwrap();
    let want = to_f64_vec(g.powi_scalar(2).sum())[0] / 4.0 * gamma / 2.0;
    let value = to_f64_vec(penalty)[0];
    assert!((value - want).abs() < 1e-9 * want, "{value} vs {want}");

    type Pick4 = fn(&mut Discriminator) -> &mut Param<Tensor<4>>;
    let convs: [(&str, Pick4, usize); 5] = [
        ("from_rgb", |d| &mut d.from_rgb.weight, 5),
        ("block 0 conv0", |d| &mut d.blocks[0].conv0.weight, 40),
        ("block 0 conv1", |d| &mut d.blocks[0].conv1.weight, 77),
        ("block 1 skip", |d| &mut d.blocks[1].skip.weight, 9),
        ("epilogue conv", |d| &mut d.conv.weight, 1000),
    ];
    for (name, pick, index) in convs {
        check_r1_element(&d, &x, gamma, &grads, name, pick, index);
    }
    type Pick2 = fn(&mut Discriminator) -> &mut Param<Tensor<2>>;
    let fcs: [(&str, Pick2, usize); 2] = [
        ("fc", |d| &mut d.fc.weight, 300),
        ("out", |d| &mut d.out.weight, 3),
    ];
    for (name, pick, index) in fcs {
        check_r1_element(&d, &x, gamma, &grads, name, pick, index);
    }
    // A bias acts on the input gradient only through the minibatch std (elsewhere it just
    // moves the piecewise-constant masks), so this one checks the mbstd's second derivative.
    let bias: fn(&mut Discriminator) -> &mut Param<Tensor<1>> =
        |d| d.from_rgb.bias.as_mut().unwrap();
    check_r1_element(&d, &x, gamma, &grads, "from_rgb bias", bias, 2);
}

/// Autodiff's `d penalty / d p[index]` (from `grads`) against a central difference of the
/// f64 penalty, for the parameter `p` that `pick` selects.
fn check_r1_element<const D: usize>(
    d: &Discriminator,
    x: &Tensor<4>,
    gamma: f64,
    grads: &Gradients,
    name: &str,
    pick: fn(&mut Discriminator) -> &mut Param<Tensor<D>>,
    index: usize,
) {
    let h = 1e-5;
    let mut d = d.clone();
    let analytic = to_f64_vec(pick(&mut d).val().grad(grads).unwrap())[index];
    let penalty_shifted = |delta: f64| {
        let mut d = d.clone();
        shift_element(pick(&mut d), index, delta);
        to_f64_vec(r1_penalty(&d, x.clone(), gamma).1)[0]
    };
    let fd = (penalty_shifted(h) - penalty_shifted(-h)) / (2.0 * h);
    assert!(
        analytic != 0.0 && (analytic - fd).abs() < 1e-6 * analytic.abs(),
        "{name}: autodiff {analytic:e} vs finite differences {fd:e}"
    );
}

/// The GPU path (CI runs it on a software Vulkan driver): logits, the explicit input
/// gradient and the R1 weight gradient equal the CPU's for the same weights.
#[cfg(feature = "wgpu")]
#[test]
fn wgpu_agrees_with_flex_including_r1() {
    let gpu = crate::backend::BackendKind::Wgpu.device().unwrap();
    let mut rng = SplitMix64::new(11);
    let x = normals(&mut rng, 4 * 3 * 16 * 16);
    let mut results = Vec::new();
    for device in [Device::flex().autodiff(), gpu.autodiff()] {
        let d = tiny(&device, 5, DType::F32);
        let input = tensor(x.clone(), [4, 3, 16, 16], &device, DType::F32);
        let (logits, grad) = d.input_gradient(input.clone().detach());
        let (_, penalty) = r1_penalty(&d, input, 10.0);
        let grads = penalty.backward();
        let w = d
            .from_rgb
            .weight
            .val()
            .grad(&grads)
            .expect("R1 reaches FromRGB");
        results.push([to_f64_vec(logits), to_f64_vec(grad), to_f64_vec(w)]);
    }
    let (cpu, gpu) = (&results[0], &results[1]);
    for (k, what) in ["logits", "input gradient", "R1 gradient of FromRGB"]
        .iter()
        .enumerate()
    {
        let scale = cpu[k].iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let worst = cpu[k]
            .iter()
            .zip(&gpu[k])
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(
            worst <= 1e-3 * scale.max(1e-6),
            "{what}: {worst} (scale {scale})"
        );
    }
}

/// The fused path (bias and activation in one op, the block's `1 / sqrt(2)` folded into
/// the skip weights and the second activation's gain) against StyleGAN2's formula written
/// with separate ops: `lrelu` with gain sqrt(2) after every biased convolution and fully
/// connected layer, `(skip + main) / sqrt(2)` per block.
#[test]
fn fused_forward_equals_stylegan2s_formula_in_separate_ops() {
    let device = Device::flex();
    let d = tiny(&device, 3, DType::F32);
    let mut rng = SplitMix64::new(8);
    let x = tensor(
        normals(&mut rng, 2 * 3 * 16 * 16),
        [2, 3, 16, 16],
        &device,
        DType::F32,
    );
    let act = |t: Tensor<4>| bias_lrelu_reference(t, None, SQRT_2);
    let mut h = act(d.from_rgb.forward(x.clone()));
    for block in &d.blocks {
        let skip = block
            .skip
            .forward_strided(blur_downsample2(h.clone()), 1, 0);
        let main = act(block
            .conv1
            .forward_strided(blur(act(block.conv0.forward(h)), 2), 2, 0));
        h = (skip + main).mul_scalar(FRAC_1_SQRT_2);
    }
    let c = act(d
        .conv
        .forward(minibatch_std(h, d.mbstd_group, d.mbstd_channels)));
    let [_, ch, hh, ww] = c.dims();
    let fc = bias_lrelu_reference(d.fc.forward(c.reshape([2, ch * hh * ww])), None, SQRT_2);
    let want = to_f64_vec(d.out.forward(fc));
    let got = to_f64_vec(d.forward(x));
    for (g, w) in got.iter().zip(&want) {
        assert!((g - w).abs() <= 1e-5 * (1.0 + w.abs()), "{g} vs {w}");
    }
}

#[test]
fn presets_give_one_logit_per_image() {
    let device = Device::flex();
    for (channels, res) in [(3, 64), (9, 64), (3, 128)] {
        let cfg = DiscriminatorConfig::small(channels, res);
        let d = cfg.init(&device);
        let x = Tensor::<4>::random(
            [2, channels, res, res],
            burn::tensor::Distribution::Normal(0.0, 1.0),
            &device,
        );
        let logits = d.forward(x.clone());
        assert_eq!(logits.dims(), [2, 1]);
        assert!(to_f32_vec(logits).iter().all(|v| v.is_finite()));
        assert_eq!(d.blocks.len(), res.trailing_zeros() as usize - 2);
        assert_eq!(d.num_params(), expected_params(&cfg));
    }
}

#[test]
fn parameter_counts_follow_the_architecture() {
    let device = Device::flex();
    let small = DiscriminatorConfig::small(3, 64);
    assert_eq!(small.init(&device).num_params(), expected_params(&small));
    assert_eq!(expected_params(&small), 1_183_137);
    // StyleGAN2 at 256x256 and (StyleGAN2-ADA's 29.0M) at 1024x1024, counted without
    // building them.
    assert_eq!(
        expected_params(&DiscriminatorConfig::stylegan2(3, 256)),
        28_864_129
    );
    assert_eq!(
        expected_params(&DiscriminatorConfig::stylegan2(3, 1024)),
        29_012_513
    );
    let sg128 = DiscriminatorConfig::stylegan2(3, 128);
    assert_eq!(sg128.channels_at(128), 256);
    assert_eq!(sg128.channels_at(64), 512);
    assert_eq!(sg128.init(&device).num_params(), expected_params(&sg128));
}
