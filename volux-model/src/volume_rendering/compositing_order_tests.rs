use super::*;
use crate::analytic::SoftSphere;
use crate::backend::to_f32_vec;
use crate::pose::Pose;
use crate::ray_sampling::camera_ray_batch;
use burn::tensor::Device;

/// The plain way: every channel of both passes gathered into depth order, then the
/// midpoint rule over the sorted samples.
fn sorted_reference(coarse: Samples, fine: Samples) -> [Tensor<2>; 4] {
    let (t, order) = Tensor::cat(vec![coarse.t, fine.t], 1).sort_with_indices(1);
    let sigma = Tensor::cat(vec![coarse.sigma, fine.sigma], 1).gather(1, order.clone());
    let gather = |a: Option<Tensor<3>>, b: Option<Tensor<3>>| -> Tensor<3> {
        let both = Tensor::cat(vec![a.unwrap(), b.unwrap()], 1);
        let [n, s, c] = both.dims();
        both.gather(1, order.clone().reshape([n, s, 1]).expand([n, s, c]))
    };
    let albedo = gather(coarse.albedo, fine.albedo);
    let normals = gather(coarse.normals, fine.normals);
    let features = gather(coarse.features, fine.features);
    let [rays, n] = t.dims();
    let delta = t.clone().narrow(1, 1, n - 1) - t.clone().narrow(1, 0, n - 1);
    let mid = (sigma.clone().narrow(1, 0, n - 1) + sigma.narrow(1, 1, n - 1)).mul_scalar(0.5);
    let w = ray_marching::weights(mid, delta);
    let zero = Tensor::<2>::zeros([rays, 1], &t.device());
    let mass = (Tensor::cat(vec![zero.clone(), w.clone()], 1) + Tensor::cat(vec![w, zero], 1))
        .mul_scalar(0.5);
    [
        ray_marching::accumulate(mass.clone(), albedo),
        ray_marching::accumulate(mass.clone(), normals),
        ray_marching::accumulate(mass.clone(), features),
        ray_marching::accumulate(mass, t.reshape([rays, n, 1])),
    ]
}

#[test]
fn compositing_in_the_passes_order_equals_compositing_in_depth_order() {
    let device = Device::flex();
    let sphere = SoftSphere {
        radius: 0.3,
        softness: 0.01,
        peak: 60.0,
        albedo: [0.5, 0.3, 0.9],
        specular_weights: vec![0.1],
    };
    let config = RendererConfig::new()
        .with_stratified(8)
        .with_importance(8)
        .with_midpoint(true);
    let cfg = config.camera.clone();
    let (o, d) = camera_ray_batch(&cfg, &[Pose::new(0.1, 0.05)], 6, 6, &device);
    let wants = RenderWants {
        albedo: true,
        normals: true,
        features: true,
        depth: true,
        shading: false,
    };
    let out = render(&config, &sphere, o.clone(), d.clone(), None, wants, false);
    // The same samples, composited the plain way.
    let (t, _) = stratified_samples(&cfg, 36, 8, false, &device);
    let coarse = evaluate(&sphere, &o, &d, t, wants.field());
    let w = ray_marching::weights(
        coarse.sigma.clone(),
        segment_lengths(coarse.t.clone(), cfg.far),
    );
    let t_fine = importance_samples(&cfg, coarse.t.clone(), w, 8, false);
    let fine = evaluate(&sphere, &o, &d, t_fine, wants.field());
    let [albedo, normals, features, depth] = sorted_reference(coarse, fine);
    let opacity = to_f32_vec(out.opacity.clone());
    let depth: Vec<f32> = to_f32_vec(depth)
        .iter()
        .zip(&opacity)
        .map(|(e, a)| e + (1.0 - a) * cfg.far as f32)
        .collect();
    assert!(opacity.iter().any(|a| *a > 0.9), "some rays hit the sphere");
    for (what, got, want) in [
        (
            "albedo",
            to_f32_vec(out.albedo.unwrap()),
            to_f32_vec(albedo),
        ),
        (
            "normals",
            to_f32_vec(out.normals.unwrap()),
            to_f32_vec(normals),
        ),
        (
            "features",
            to_f32_vec(out.features.unwrap()),
            to_f32_vec(features),
        ),
        ("depth", to_f32_vec(out.depth.unwrap()), depth),
    ] {
        assert_eq!(got.len(), want.len(), "{what}");
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w).abs() < 1e-5 * (1.0 + w.abs()), "{what}: {g} vs {w}");
        }
    }
}
