use super::*;
use crate::backend::to_f32_vec;
use crate::light_lookup::LightMapBatch;
use burn::tensor::Distribution;
use volux_envmap::LightMap;

/// Light maps with a gradient in red and, in blue, one texel of `spike` (a sun).
fn lighting(batch: usize, spike: f32, device: &Device) -> Lighting {
    let maps: Vec<LightMap> = [1u32, 16, 32, 64]
        .iter()
        .map(|&n| {
            let texels = (0..16 * 8)
                .map(|i| [1.0 + (i % 16) as f32, 2.0, spike * f32::from(i == 40)])
                .collect();
            LightMap::new(n, 16, 8, texels)
        })
        .collect();
    let batches = maps
        .iter()
        .map(|m| LightMapBatch::new(&vec![m; batch], device).unwrap())
        .collect();
    let yaw: Vec<f32> = (0..batch).map(|i| 0.7 + 2.1 * i as f32).collect();
    let yaw = Tensor::from_floats(yaw.as_slice(), device);
    Lighting::new(batches, Some(yaw)).unwrap()
}

/// The named parts all received finite, non-zero gradients.
fn check_grads(g: &Generator, grads: &burn::tensor::Gradients, parts: &[&str]) {
    let all: [(&str, Vec<Option<Vec<f32>>>); 4] = [
        (
            "mapping",
            vec![g.mapping.layers[0].weight.val().grad(grads).map(to_f32_vec)],
        ),
        (
            "neiif",
            vec![
                g.neiif.layers[0].weight.val().grad(grads).map(to_f32_vec),
                g.neiif.head_out.weight.val().grad(grads).map(to_f32_vec),
            ],
        ),
        (
            "upsampler",
            vec![
                g.upsampler
                    .blocks
                    .first()
                    .and_then(|b| b.conv1.weight.val().grad(grads))
                    .map(to_f32_vec),
            ],
        ),
        (
            "relighting",
            vec![g.relighting.out.weight.val().grad(grads).map(to_f32_vec)],
        ),
    ];
    for (name, params) in all {
        if !parts.contains(&name) {
            continue;
        }
        for grad in params {
            let grad = grad.unwrap_or_else(|| panic!("no gradient reached the {name}"));
            assert!(
                grad.iter().all(|v| v.is_finite()),
                "{name}: non-finite gradient"
            );
            assert!(grad.iter().any(|v| *v != 0.0), "{name}: zero gradient");
        }
    }
}

/// Every output of `g` for two latents at two poses, lit by [`lighting`] with `spike`.
fn two_views_lit(g: &Generator, spike: f32, device: &Device) -> GeneratorOutput {
    let z = Tensor::<2>::random([2, 128], Distribution::Normal(0.0, 1.0), device);
    let light = lighting(2, spike, device);
    g.forward(
        z,
        &[Pose::new(0.0, 0.0), Pose::new(0.4, -0.1)],
        Some(&light),
        [0.0; 3],
        GeneratorWants::ALL,
        None,
        true,
    )
    .unwrap()
}

#[test]
fn small_preset_gives_every_output_and_a_full_backward_pass() {
    let device = Device::flex().autodiff();
    let config = GeneratorConfig::small();
    let g = config.init(&device).unwrap();
    assert_eq!(g.output_resolution(), 64);
    let counts = g.parameter_counts();
    assert_eq!(
        counts.iter().map(|c| c.1).sum::<usize>(),
        Module::num_params(&g),
        "{counts:?}"
    );
    let out = two_views_lit(&g, 1e5, &device);
    assert_eq!(out.opacity.dims(), [2, 1, 32, 32]);
    for (name, t, c) in [
        ("A_lo", &out.layers.albedo_lo, 3),
        ("N_lo", &out.layers.normals_lo, 3),
        ("D_lo", &out.layers.diffuse_lo, 3),
        ("S_lo", &out.layers.specular_lo, 3),
        ("F_lo", &out.layers.features_lo, 64),
        ("depth", &out.layers.depth, 1),
    ] {
        assert_eq!(t.as_ref().unwrap().dims(), [2, c, 32, 32], "{name}");
    }
    assert_eq!(
        out.layers.albedo_hi.as_ref().unwrap().dims(),
        [2, 3, 64, 64]
    );
    assert_eq!(out.layers.relit.as_ref().unwrap().dims(), [2, 3, 64, 64]);
    let loss = out.layers.relit.unwrap().mean()
        + out.layers.albedo_lo.unwrap().mean()
        + out.layers.normals_lo.unwrap().mean()
        + out.layers.albedo_hi.unwrap().mean();
    let v: f32 = loss.clone().into_scalar();
    assert!(v.is_finite());
    check_grads(
        &g,
        &loss.backward(),
        &["mapping", "neiif", "upsampler", "relighting"],
    );
}

#[test]
fn a_volume_at_the_output_resolution_needs_no_upsampling_blocks() {
    // Output side = volume side: the upsampler has no blocks and passes `[A_lo, F_lo]`
    // through, so the relighting network takes the renderer's features.
    let device = Device::flex().autodiff();
    let mut config = GeneratorConfig::small();
    config.volume_resolution = 16;
    config.output_resolution = 16;
    let g = config.init(&device).unwrap();
    assert!(g.upsampler.blocks.is_empty());
    let out = two_views_lit(&g, 1.0, &device);
    let (lo, hi) = (out.layers.albedo_lo.unwrap(), out.layers.albedo_hi.unwrap());
    assert_eq!(hi.dims(), [2, 3, 16, 16]);
    assert_eq!(to_f32_vec(lo.clone()), to_f32_vec(hi), "A_hi is A_lo");
    let relit = out.layers.relit.unwrap();
    assert_eq!(relit.dims(), [2, 3, 16, 16]);
    let loss = relit.mean() + lo.mean();
    assert!(loss.clone().into_scalar::<f32>().is_finite());
    check_grads(&g, &loss.backward(), &["mapping", "neiif", "relighting"]);
}

#[test]
fn stage_one_runs_without_lighting_or_relighting() {
    let device = Device::flex().autodiff();
    let g = GeneratorConfig::small().init(&device).unwrap();
    let z = Tensor::<2>::random([1, 128], Distribution::Normal(0.0, 1.0), &device);
    let out = g
        .forward(
            z,
            &[Pose::new(0.0, 0.0)],
            None,
            [1.0; 3],
            GeneratorWants::STAGE1,
            Some(&[0.5]),
            true,
        )
        .unwrap();
    assert!(
        out.layers.relit.is_none() && out.layers.diffuse_lo.is_none() && out.layers.depth.is_none()
    );
    let loss = out.layers.albedo_hi.unwrap().mean() + out.layers.normals_lo.unwrap().mean();
    check_grads(&g, &loss.backward(), &["mapping", "neiif", "upsampler"]);
}

#[test]
fn paper_preset_on_a_subset_of_rays_and_its_full_resolution_2d_half() {
    let device = Device::flex().autodiff();
    let config = GeneratorConfig::paper(128);
    let g = config.init(&device).unwrap();
    let counts = g.parameter_counts();
    assert_eq!(counts[1].1, {
        // 63 -> 256, five 256 -> 256 modulated layers (each with a 512 -> in affine), the
        // density head, the 256 -> 256 -> 7 head.
        let modulated = |i: usize| 512 * i + i + 256 * i + 256;
        modulated(63) + 5 * modulated(256) + 257 + (256 * 256 + 256) + (256 * 7 + 7)
    });
    let z = Tensor::<2>::random([1, 512], Distribution::Normal(0.0, 1.0), &device);
    let w = g.mapping.forward(z);
    // 48 rays of the 64x64 image: its central row, and 16 rays more.
    let (o, d) = camera_ray_batch(
        &config.renderer.camera,
        &[Pose::new(0.2, 0.0)],
        64,
        64,
        &device,
    );
    let (o, d) = (o.narrow(1, 64 * 32, 48), d.narrow(1, 64 * 32, 48));
    let light = lighting(1, 1e5, &device);
    let r = g
        .render_rays(w.clone(), o, d, Some(&light), RenderWants::ALL, true)
        .unwrap();
    assert_eq!(r.features.as_ref().unwrap().dims(), [1, 48, 256]);
    // The 2D half at full size: 64x64 features to 128x128 albedo and relit image.
    let x = Tensor::<4>::random(
        [1, 3 + 256, 64, 64],
        Distribution::Normal(0.0, 1.0),
        &device,
    );
    let hi = g.upsampler.forward(x, w, None);
    assert_eq!(hi.dims(), [1, 128, 128, 128]);
    let shading = Tensor::<4>::random([1, 3, 128, 128], Distribution::Uniform(0.0, 2.0), &device);
    let relit = g.relighting.forward(
        hi.clone().narrow(1, 0, 3),
        shading.clone(),
        shading,
        hi.narrow(1, 3, 125),
    );
    assert_eq!(relit.dims(), [1, 3, 128, 128]);
    let loss = relit.mean()
        + r.diffuse.unwrap().mean()
        + r.specular.unwrap().mean()
        + r.normals.unwrap().mean();
    check_grads(
        &g,
        &loss.backward(),
        &["mapping", "neiif", "upsampler", "relighting"],
    );
}

#[test]
fn bad_sizes_and_missing_lighting_are_errors() {
    let device = Device::flex();
    let bad = GeneratorConfig::small();
    let bad = GeneratorConfig {
        output_resolution: 96,
        ..bad
    };
    assert_eq!(
        bad.init(&device).unwrap_err(),
        GeneratorError::Resolution {
            volume: 32,
            output: 96
        }
    );
    let g = GeneratorConfig::small().init(&device).unwrap();
    let z = Tensor::<2>::random([1, 128], Distribution::Normal(0.0, 1.0), &device);
    let err = g
        .forward(
            z.clone(),
            &[Pose::new(0.0, 0.0)],
            None,
            [0.0; 3],
            GeneratorWants::ALL,
            None,
            false,
        )
        .unwrap_err();
    assert!(matches!(err, GeneratorError::NoLighting { .. }), "{err}");
    let err = g
        .forward(
            z,
            &[Pose::new(0.0, 0.0), Pose::new(0.1, 0.0)],
            None,
            [0.0; 3],
            GeneratorWants::STAGE1,
            None,
            false,
        )
        .unwrap_err();
    assert!(
        matches!(err, GeneratorError::Batch { z: 1, poses: 2, .. }),
        "{err}"
    );
}

/// The whole generator on the GPU path (CI runs it on a software Vulkan driver): the same
/// weights give the same outputs as on the CPU, and a backward pass runs.
#[cfg(feature = "wgpu")]
#[test]
fn wgpu_generator_agrees_with_flex() {
    let tiny = GeneratorConfig::new(
        MappingNetworkConfig::new()
            .with_z_dim(8)
            .with_w_dim(8)
            .with_layers(2),
        NeiifConfig::new()
            .with_w_dim(8)
            .with_width(16)
            .with_head_width(8)
            .with_frequencies(4),
        RendererConfig::new().with_stratified(6).with_importance(6),
        8,
        16,
        8,
        vec![8, 8],
    );
    let flex = Device::flex();
    let gpu = crate::backend::BackendKind::Wgpu.device().unwrap();
    let g = tiny.init(&flex).unwrap();
    let z = Tensor::<2>::random([2, 8], Distribution::Normal(0.0, 1.0), &flex);
    let poses = [Pose::new(0.0, 0.0), Pose::new(0.3, 0.1)];
    let run = |g: &Generator, z: Tensor<2>, device: &Device| {
        let out = g
            .forward(
                z,
                &poses,
                Some(&lighting(2, 0.0, device)),
                [0.0; 3],
                GeneratorWants::ALL,
                None,
                false,
            )
            .unwrap();
        [
            out.layers.albedo_lo.unwrap(),
            out.layers.normals_lo.unwrap(),
            out.layers.diffuse_lo.unwrap(),
            out.layers.specular_lo.unwrap(),
            out.layers.albedo_hi.unwrap(),
            out.layers.relit.unwrap(),
        ]
    };
    let cpu = run(&g, z.clone(), &flex);
    let on_gpu = run(&g.clone().to_device(&gpu), z.to_device(&gpu), &gpu);
    for (k, (a, b)) in cpu.into_iter().zip(on_gpu).enumerate() {
        let (a, b) = (to_f32_vec(a), to_f32_vec(b));
        // Smooth light maps: next to a 1e5 texel, last-bit differences of the normals
        // would be amplified into large ones (the CPU tests cover that stiff case).
        let worst = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs() / (1.0 + x.abs()))
            .fold(0.0f32, f32::max);
        assert!(
            worst < 1e-3,
            "output {k}: wgpu differs from flex by {worst}"
        );
    }
    let ad = gpu.clone().autodiff();
    let g = tiny.init(&ad).unwrap();
    let z = Tensor::<2>::random([2, 8], Distribution::Normal(0.0, 1.0), &ad);
    let loss = run(&g, z, &ad)
        .into_iter()
        .map(|t| t.mean())
        .reduce(|a, b| a + b)
        .unwrap();
    check_grads(
        &g,
        &loss.backward(),
        &["mapping", "neiif", "upsampler", "relighting"],
    );
}

#[test]
fn normals_go_to_camera_space() {
    let device = Device::flex();
    let camera = CameraConfig::new();
    let world =
        Tensor::<1>::from_floats([0.0, 0.0, 1.0, 1.0, 0.0, 0.0], &device).reshape([2, 1, 3]);
    let cam = to_f32_vec(to_camera_space(
        world,
        &camera,
        &[
            Pose::new(0.0, 0.0),
            Pose::new(std::f64::consts::FRAC_PI_2, 0.0),
        ],
        &device,
    ));
    // Frontal: world +z faces the camera. Yaw 90 degrees: the camera sits on +x.
    for (g, w) in cam.iter().zip([0.0, 0.0, 1.0, 0.0, 0.0, 1.0]) {
        assert!((g - w).abs() < 1e-6, "{cam:?}");
    }
}

/// The upsampler's surface-anchored noise: a fresh noise input adds nothing; with strength it
/// changes the high-resolution albedo alone, the same way for the same latent, and its gains
/// and strengths are in the backward pass.
#[test]
fn upsampler_noise_changes_only_the_high_resolution_albedo() {
    let device = Device::flex().autodiff();
    let plain = GeneratorConfig::small().init(&device).unwrap();
    let mut noised = plain.clone();
    noised.upsampler = noised.upsampler.with_noise(2, 128, &device);
    assert_eq!(noised.upsampler.noise_octaves(), 2);
    let z = Tensor::<2>::random([2, 128], Distribution::Normal(0.0, 1.0), &device);
    let poses = [Pose::new(0.0, 0.0), Pose::new(0.4, -0.1)];
    let run = |g: &Generator, z: Tensor<2>| {
        g.forward(
            z,
            &poses,
            None,
            [1.0; 3],
            GeneratorWants::STAGE1,
            None,
            false,
        )
        .unwrap()
    };
    let values = |t: Option<Tensor<4>>| to_f32_vec(t.unwrap());
    let base = run(&plain, z.clone());
    let fresh = run(&noised, z.clone());
    assert!(
        fresh.layers.depth.is_none(),
        "depth is drawn for the noise, not returned"
    );
    assert_eq!(
        values(base.layers.albedo_hi.clone()),
        values(fresh.layers.albedo_hi),
        "zero strength adds nothing"
    );
    for block in &mut noised.upsampler.blocks {
        let injection = block.noise.as_mut().unwrap();
        let k = injection.strength.dims()[0];
        injection.strength =
            burn::module::Param::from_tensor(Tensor::<1>::ones([k], &device).mul_scalar(0.5));
    }
    let out = run(&noised, z.clone());
    assert_eq!(
        values(base.layers.albedo_lo),
        values(out.layers.albedo_lo.clone()),
        "the volume does not see the noise"
    );
    let (a, b) = (
        values(base.layers.albedo_hi),
        values(out.layers.albedo_hi.clone()),
    );
    let moved = a
        .iter()
        .zip(&b)
        .filter(|(x, y)| (*x - *y).abs() > 1e-4)
        .count();
    assert!(
        moved > a.len() / 2,
        "noise reaches most pixels ({moved} of {})",
        a.len()
    );
    assert_eq!(
        b,
        values(run(&noised, z.clone()).layers.albedo_hi),
        "the same latent draws the same noise"
    );
    let swapped = Tensor::cat(vec![z.clone().narrow(0, 1, 1), z.narrow(0, 0, 1)], 0);
    assert_ne!(b, values(run(&noised, swapped).layers.albedo_hi));
    let grads = out
        .layers
        .albedo_hi
        .unwrap()
        .powf_scalar(2.0)
        .mean()
        .backward();
    let injection = noised.upsampler.blocks[0].noise.as_ref().unwrap();
    for (what, grad) in [
        (
            "strength",
            injection.strength.val().grad(&grads).map(to_f32_vec),
        ),
        (
            "gain",
            injection.gain.weight.val().grad(&grads).map(to_f32_vec),
        ),
    ] {
        let grad = grad.unwrap_or_else(|| panic!("no gradient reached the noise's {what}"));
        assert!(
            grad.iter().all(|v| v.is_finite()) && grad.iter().any(|v| *v != 0.0),
            "{what}"
        );
    }
}

/// The noise images lie on the surface: times the opacity, enlarged to each block; none where
/// a ray sees nothing.
#[test]
fn upsampler_noise_is_weighted_by_the_opacity() {
    let device = Device::flex();
    let mut g = GeneratorConfig::small().init(&device).unwrap();
    g.upsampler = g.upsampler.with_noise(2, 128, &device);
    let points = Tensor::<4>::random([2, 3, 32, 32], Distribution::Normal(0.0, 0.3), &device);
    let seeds = [3, 4];
    let spacing = upsampler_noise::pixel_footprint(&g.renderer.camera, 64);
    let plain = to_f32_vec(upsampler_noise::noise_images(
        bilinear_upsample(points.clone(), 2),
        &seeds,
        spacing,
        2,
    ));
    let ones = Tensor::<4>::ones([2, 1, 32, 32], &device);
    let full = g.noise_images(points.clone(), ones.clone(), &seeds);
    assert_eq!(full.len(), 1);
    assert_eq!(full[0].dims(), [2, 2, 64, 64]);
    assert_eq!(to_f32_vec(full[0].clone()), plain);
    let empty = g.noise_images(points.clone(), ones.clone().mul_scalar(0.0), &seeds);
    assert!(to_f32_vec(empty[0].clone()).iter().all(|v| *v == 0.0));
    let half = to_f32_vec(g.noise_images(points, ones.mul_scalar(0.5), &seeds)[0].clone());
    assert!(
        half.iter()
            .zip(&plain)
            .all(|(h, p)| (h - 0.5 * p).abs() < 1e-7)
    );
}
