use super::*;
use crate::analytic::{RayReference, SoftSphere};
use crate::backend::to_f32_vec;
use crate::neiif::{LatentField, NeiifConfig};
use crate::pose::Pose;
use crate::ray_sampling::{camera_ray_batch, camera_rays};
use crate::test_support::{Scaled, lighting, wave_light_maps as light_maps};
use burn::tensor::{Device, Distribution};
use volux_envmap::LightMap;

fn sphere() -> SoftSphere {
    SoftSphere {
        radius: 0.3,
        softness: 0.01,
        peak: 60.0,
        albedo: [0.8, 0.5, 0.3],
        specular_weights: vec![0.1, 0.4, 0.2, 0.05],
    }
}

fn close3(got: &[f32], want: [f64; 3], tol: f64, what: &str) {
    for c in 0..3 {
        let g = f64::from(got[c]);
        assert!(
            (g - want[c]).abs() <= tol * (1.0 + want[c].abs()),
            "{what}[{c}]: {g} vs {}",
            want[c]
        );
    }
}

#[test]
fn soft_sphere_matches_the_analytic_values_at_the_image_centre() {
    let device = Device::flex();
    let cfg = RendererConfig::new()
        .with_stratified(64)
        .with_importance(64);
    let maps = light_maps(5, 1.0);
    let light = lighting(std::slice::from_ref(&maps), &[0.7], &device);
    let (o, d) = camera_ray_batch(&cfg.camera, &[Pose::new(0.0, 0.0)], 5, 5, &device);
    let out = render(&cfg, &sphere(), o, d, Some(&light), RenderWants::ALL, false);
    let at = |x: Option<Tensor<3>>| to_f32_vec(x.unwrap())[12 * 3..13 * 3].to_vec();
    let opacity = to_f32_vec(out.opacity.clone())[12];
    assert!(opacity > 0.999, "opacity {opacity}");
    // The surface (density at half its peak) is at t = 2.7 - 0.3; the weights' mean sits
    // a fraction of the e-folding length 1 / 30 in front of the full density.
    let depth = to_f32_vec(out.depth.clone().unwrap())[12];
    assert!((depth - 2.4).abs() < 0.03, "depth {depth}");
    let n = at(out.normals.clone());
    close3(&n, [0.0, 0.0, 1.0], 1e-3, "normal");
    // D = L_1(n) with n = +z; S at the mirror direction of -z about +z, also +z.
    let up = [0.0, 0.0, 1.0];
    let l1 = maps[0].lookup_rotated(up, 0.7).map(f64::from);
    close3(&at(out.diffuse.clone()), l1, 2e-3, "diffuse");
    let spec: [f64; 3] = std::array::from_fn(|c| {
        maps.iter()
            .zip(&sphere().specular_weights)
            .map(|(m, w)| f64::from(*w) * f64::from(m.lookup_rotated(up, 0.7)[c]))
            .sum()
    });
    close3(&at(out.specular.clone()), spec, 2e-3, "specular");
    close3(&at(out.albedo), [0.8, 0.5, 0.3], 1e-3, "albedo");
    // Features are the points: the expected surface point is (0, 0, 2.7 - depth).
    let f = at(out.features);
    close3(
        &f,
        [0.0, 0.0, 2.7 - f64::from(depth)],
        2e-3,
        "feature (point)",
    );
}

/// Every pixel of an image of the sphere, against the f64 quadrature with 20,000 steps.
#[test]
fn soft_sphere_image_matches_the_f64_reference() {
    let device = Device::flex();
    let cfg = RendererConfig::new()
        .with_stratified(64)
        .with_importance(64);
    let maps = light_maps(9, 1.0);
    let refs: Vec<&LightMap> = maps.iter().collect();
    let light = lighting(std::slice::from_ref(&maps), &[-1.2], &device);
    let pose = Pose::new(0.4, -0.2);
    let (w, h) = (8, 8);
    let (o, d) = camera_ray_batch(&cfg.camera, &[pose], w, h, &device);
    let out = render(&cfg, &sphere(), o, d, Some(&light), RenderWants::ALL, false);
    let (origins, dirs) = camera_rays(&cfg.camera, pose, w, h);
    let opacity = to_f32_vec(out.opacity);
    let depth = to_f32_vec(out.depth.unwrap());
    let maps3 = [
        to_f32_vec(out.albedo.unwrap()),
        to_f32_vec(out.normals.unwrap()),
        to_f32_vec(out.diffuse.unwrap()),
        to_f32_vec(out.specular.unwrap()),
    ];
    let mut hits = 0;
    for i in 0..w * h {
        let want: RayReference =
            sphere().reference_ray(&cfg.camera, origins[i], dirs[i], 20_000, &refs, -1.2);
        hits += usize::from(want.opacity > 0.5);
        assert!(
            (f64::from(opacity[i]) - want.opacity).abs() < 2e-3,
            "pixel {i} opacity {} vs {}",
            opacity[i],
            want.opacity
        );
        assert!(
            (f64::from(depth[i]) - want.depth).abs() < 5e-3,
            "pixel {i} depth {} vs {}",
            depth[i],
            want.depth
        );
        for (k, m) in [want.albedo, want.normal, want.diffuse, want.specular]
            .into_iter()
            .enumerate()
        {
            close3(
                &maps3[k][3 * i..3 * i + 3],
                m,
                1e-2,
                &format!("pixel {i} map {k}"),
            );
        }
    }
    assert!(
        hits > 4 && hits < w * h,
        "the image shows the sphere's edge ({hits} hits)"
    );
}

#[test]
fn stiff_and_extreme_cases_give_finite_outputs_and_gradients() {
    let device = Device::flex().autodiff();
    let net = NeiifConfig::new()
        .with_w_dim(8)
        .with_width(16)
        .with_head_width(8)
        .init(&device);
    let maps = light_maps(2, 1e5); // 1e5 light-map values
    let light = lighting(&[maps.clone(), maps], &[0.0, 3.0], &device);
    let base = CameraConfig::new();
    let cameras = [
        ("paper bounds", base.clone()),
        (
            "very short rays",
            base.clone().with_near(2.7).with_far(2.7 + 1e-5),
        ),
        ("very long rays", base.clone().with_near(1e-3).with_far(1e3)),
    ];
    for (what, camera) in cameras {
        for scale in [0.0, 1.0, 1e4] {
            let w =
                Tensor::<2>::random([2, 8], Distribution::Normal(0.0, 1.0), &device).require_grad();
            let field = LatentField {
                field: &net,
                w: w.clone(),
            };
            let cfg = RendererConfig::new()
                .with_camera(camera.clone())
                .with_stratified(12)
                .with_importance(12);
            let (o, d) = camera_ray_batch(
                &camera,
                &[Pose::new(0.0, 0.0), Pose::new(0.5, 0.2)],
                4,
                4,
                &device,
            );
            let out = render(
                &cfg,
                &Scaled(&field, scale),
                o,
                d,
                Some(&light),
                RenderWants::ALL,
                true,
            );
            let opacity = to_f32_vec(out.opacity.clone());
            assert!(
                opacity.iter().all(|v| (0.0..=1.0 + 1e-6).contains(v)),
                "{what}, density x{scale}: opacity {opacity:?}"
            );
            if scale == 0.0 {
                assert!(
                    opacity.iter().all(|v| *v == 0.0),
                    "{what}: empty space is transparent"
                );
            }
            let parts = [
                out.albedo.unwrap(),
                out.normals.unwrap(),
                out.diffuse.unwrap(),
                out.specular.unwrap(),
                out.features.unwrap(),
            ];
            let mut loss = out.opacity.sum() + out.depth.unwrap().sum();
            for p in parts {
                let v = to_f32_vec(p.clone());
                assert!(
                    v.iter().all(|x| x.is_finite()),
                    "{what}, density x{scale}: non-finite output"
                );
                loss = loss + p.sum();
            }
            let grads = loss.backward();
            for g in [
                w.grad(&grads).map(to_f32_vec),
                net.layers[0].weight.val().grad(&grads).map(to_f32_vec),
                net.head_out.weight.val().grad(&grads).map(to_f32_vec),
            ]
            .into_iter()
            .flatten()
            {
                assert!(
                    g.iter().all(|x| x.is_finite()),
                    "{what}, density x{scale}: non-finite gradient"
                );
            }
        }
    }
}

#[test]
fn unwanted_outputs_are_not_computed() {
    let device = Device::flex();
    let cfg = RendererConfig::new().with_stratified(8).with_importance(0);
    let (o, d) = camera_ray_batch(&cfg.camera, &[Pose::new(0.0, 0.0)], 3, 3, &device);
    let wants = RenderWants {
        albedo: true,
        normals: false,
        shading: false,
        features: false,
        depth: false,
    };
    // No lighting is needed without shading.
    let out = render(&cfg, &sphere(), o, d, None, wants, false);
    assert!(out.albedo.is_some());
    assert!(out.normals.is_none() && out.diffuse.is_none() && out.features.is_none());
    assert!(out.depth.is_none());
}
