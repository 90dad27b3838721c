use crate::pose::Pose;
use burn::tensor::{Device, Distribution, TensorData};
use volux_envmap::random::SplitMix64;

use super::*;
use crate::analytic::SoftSphere;
use crate::backend::to_f32_vec;
use crate::field::{Field, FieldOutput, FieldWants};
use crate::neiif::{LatentField, NeiifConfig};
use crate::ray_sampling::camera_ray_batch;
use crate::test_support::{Scaled, lighting, wave_light_maps};
use crate::volume_rendering::{RenderWants, render};

fn sphere(softness: f64, peak: f64) -> SoftSphere {
    SoftSphere {
        radius: 0.3,
        softness,
        peak,
        albedo: [0.8, 0.5, 0.3],
        specular_weights: vec![0.1, 0.4, 0.2, 0.05],
    }
}

fn layout(stratified: usize, proposal: usize, refine: usize, importance: usize) -> RendererConfig {
    RendererConfig::new()
        .with_stratified(stratified)
        .with_proposal(proposal)
        .with_refine(refine)
        .with_importance(importance)
}

/// The plain f64 reference of [`segment_weights`] for one ray.
fn segment_weights_reference(camera: &CameraConfig, t: &[f64], sigma: &[f64]) -> Vec<f64> {
    let s = t.len();
    let mut edges = vec![camera.near];
    edges.extend_from_slice(t);
    edges.push(camera.far);
    let mut depth = 0.0f64;
    (0..=s)
        .map(|i| {
            let density = match i {
                0 => sigma[0],
                _ if i == s => sigma[s - 1],
                _ => 0.5 * (sigma[i - 1] + sigma[i]),
            };
            let tau = density * (edges[i + 1] - edges[i]);
            let w = (-depth).exp() * -(-tau).exp_m1();
            depth += tau;
            w
        })
        .collect()
}

#[test]
fn segment_weights_match_the_f64_reference() {
    let device = Device::flex();
    let camera = CameraConfig::new();
    let mut rng = SplitMix64::new(11);
    let (rays, s) = (6, 9);
    let mut t = Vec::new();
    let mut sigma = Vec::new();
    for ray in 0..rays {
        let mut row: Vec<f64> = (0..s)
            .map(|_| camera.near + (camera.far - camera.near) * rng.next_f64())
            .collect();
        row.sort_by(f64::total_cmp);
        t.extend(row);
        // A stiff ray, an empty one and soft ones.
        sigma.extend((0..s).map(|i| match ray {
            0 => {
                if i >= 4 {
                    1e4
                } else {
                    0.0
                }
            }
            1 => 0.0,
            _ => 30.0 * rng.next_f64().powi(2),
        }));
    }
    let tensor = |v: &[f64]| {
        let v: Vec<f32> = v.iter().map(|x| *x as f32).collect();
        Tensor::<2>::from_data(TensorData::new(v, [rays, s]), &device)
    };
    let got = to_f32_vec(segment_weights(&camera, tensor(&t), tensor(&sigma)));
    for ray in 0..rays {
        let t32: Vec<f64> = t[ray * s..(ray + 1) * s]
            .iter()
            .map(|x| f64::from(*x as f32))
            .collect();
        let want = segment_weights_reference(&camera, &t32, &sigma[ray * s..(ray + 1) * s]);
        for (i, w) in want.iter().enumerate() {
            let g = f64::from(got[ray * (s + 1) + i]);
            assert!((g - w).abs() < 2e-6, "ray {ray} segment {i}: {g} vs {w}");
        }
    }
    // The wall puts all its weight on the segment that crosses into it.
    let wall = &got[0..=s];
    assert!((wall[4] - 1.0).abs() < 1e-6, "{wall:?}");
}

#[test]
fn the_density_only_query_matches_the_full_fields_density() {
    // With the encoding's octaves partly closed too: the density-only query runs on
    // `valid()`, which must keep the window.
    for (autodiff, window) in [
        (false, None),
        (true, None),
        (false, Some(2.5)),
        (true, Some(2.5)),
    ] {
        let mut device = Device::flex();
        if autodiff {
            device = device.autodiff();
        }
        device.seed(5);
        let mut net = NeiifConfig::new()
            .with_w_dim(32)
            .with_width(32)
            .with_head_width(32)
            .with_sphere_prior(10.0)
            .with_sphere_radius(0.35)
            .init(&device);
        net.encoding.set_window(window);
        let w = Tensor::<2>::random([2, 32], Distribution::Normal(0.0, 1.0), &device);
        let field = LatentField { field: &net, w };
        let points = Tensor::<3>::random([2, 300, 3], Distribution::Uniform(-0.6, 0.6), &device);
        let density = field.density(points.clone());
        assert!(
            !density.is_autodiff(),
            "the proposal's densities carry no graph"
        );
        let density = to_f32_vec(density);
        for wants in [FieldWants::ALL, FieldWants::DENSITY] {
            let full = to_f32_vec(field.query(points.clone(), wants).sigma);
            for (i, (a, b)) in density.iter().zip(&full).enumerate() {
                // The same layers on the same values; the full query's matmul also carries
                // the tangents, which may change the summation order in the last bit.
                assert!(
                    (a - b).abs() <= 1e-6 * (1.0 + b.abs()),
                    "{wants:?} point {i}: {a} vs {b}"
                );
            }
        }
    }
}

#[test]
fn importance_samples_bracket_a_stiff_surface() {
    let device = Device::flex();
    let stiff = sphere(0.001, 1e4);
    let cfg = layout(0, 32, 16, 12);
    // The centre ray of a frontal camera: the weight of the reference sits at t = 2.3977,
    // where the optical depth from the front reaches 1 (2.3 e-folding lengths before the
    // half-density radius at 2.4).
    let (o, d) = camera_ray_batch(&cfg.camera, &[Pose::new(0.0, 0.0)], 1, 1, &device);
    let t = to_f32_vec(place(&cfg, &stiff, &o, &d, false).importance);
    assert_eq!(t.len(), 12);
    assert!(t.windows(2).all(|p| p[0] <= p[1]), "sorted: {t:?}");
    let near_surface = t.iter().filter(|&&x| (2.385..2.415).contains(&x)).count();
    assert!(
        near_surface >= 10,
        "{near_surface} of 12 near the surface: {t:?}"
    );
    // Without the refine level the draws still fall in the segment that crosses the surface.
    let t = to_f32_vec(place(&layout(0, 32, 0, 12), &stiff, &o, &d, false).importance);
    let bracket = t.iter().filter(|&&x| (2.36..2.44).contains(&x)).count();
    assert!(bracket >= 11, "{t:?}");
}

#[test]
fn empty_rays_and_an_empty_batch_stay_finite() {
    let device = Device::flex().autodiff();
    let ball = sphere(0.01, 60.0);
    let empty = Scaled(&ball, 0.0);
    let cfg = layout(0, 16, 8, 8);
    let maps = wave_light_maps(3, 1.0);
    let light = lighting(&[maps.clone(), maps], &[0.2f32, -0.4], &device);
    let (o, d) = camera_ray_batch(
        &cfg.camera,
        &[Pose::new(0.0, 0.0), Pose::new(0.5, 0.1)],
        4,
        4,
        &device,
    );
    // An empty batch: the draws fall back on the uniform share and spread over the ray.
    let p = place(&cfg, &empty, &o, &d, false);
    assert!(to_f32_vec(p.sigma).iter().all(|s| *s == 0.0));
    let t = to_f32_vec(p.importance);
    for row in t.chunks(8) {
        for (i, x) in row.iter().enumerate() {
            let want = 2.25 + (i as f32 + 0.5) / 8.0 * 1.05;
            assert!((x - want).abs() < 1e-3, "{i}: {x} vs {want}");
        }
    }
    let out = render(
        &cfg,
        &empty,
        o.clone(),
        d.clone(),
        Some(&light),
        RenderWants::ALL,
        true,
    );
    assert!(to_f32_vec(out.opacity.clone()).iter().all(|v| *v == 0.0));
    for map in [
        out.albedo,
        out.normals,
        out.diffuse,
        out.specular,
        out.features,
    ] {
        assert!(to_f32_vec(map.unwrap()).iter().all(|v| *v == 0.0));
    }
    let depth = to_f32_vec(out.depth.unwrap());
    assert!(depth.iter().all(|v| (v - 3.3).abs() < 1e-5), "{depth:?}");
    // Rays that miss a stiff sphere beside rays that hit it: finite values and gradients.
    let k = Tensor::<1>::from_floats([1.0], &device).require_grad();
    let stiff = sphere(0.001, 1e4);
    let field = ScaledBy {
        sphere: &stiff,
        k: k.clone(),
    };
    let (o, d) = camera_ray_batch(&cfg.camera, &[Pose::new(0.0, 0.0)], 6, 6, &device);
    let out = render(
        &cfg,
        &field,
        o,
        d,
        Some(&light_one(&device)),
        RenderWants::ALL,
        true,
    );
    let loss = out.diffuse.unwrap().sum() + out.normals.unwrap().sum() + out.depth.unwrap().sum();
    assert!(loss.clone().into_scalar::<f32>().is_finite());
    let g: f32 = k.grad(&loss.backward()).unwrap().into_scalar();
    assert!(g.is_finite(), "{g}");
}

fn light_one(device: &Device) -> crate::light_lookup::Lighting {
    lighting(&[wave_light_maps(4, 1.0)], &[0.3f32], device)
}

/// A sphere whose density is scaled by a tensor `k` that can require a gradient.
struct ScaledBy<'a> {
    sphere: &'a SoftSphere,
    k: Tensor<1>,
}

impl Field for ScaledBy<'_> {
    fn query(&self, points: Tensor<3>, wants: FieldWants) -> FieldOutput {
        let mut out = self.sphere.query(points, wants);
        out.sigma = out.sigma * self.k.clone().reshape([1, 1]);
        out
    }
}

#[test]
fn gradients_through_the_composited_samples_match_f64_finite_differences() {
    let device = Device::flex().autodiff();
    let ball = sphere(0.01, 60.0);
    let cfg = layout(0, 24, 12, 10);
    let k0 = 1.3f64;
    let k = Tensor::<1>::from_floats([k0 as f32], &device).require_grad();
    let field = ScaledBy {
        sphere: &ball,
        k: k.clone(),
    };
    let (side, pose) = (5, Pose::new(0.2, -0.1));
    let (o, d) = camera_ray_batch(&cfg.camera, &[pose], side, side, &device);
    let wants = RenderWants {
        albedo: false,
        normals: false,
        shading: false,
        features: false,
        depth: true,
    };
    let depth = render(&cfg, &field, o.clone(), d.clone(), None, wants, false)
        .depth
        .unwrap();
    let got: f32 = k.grad(&depth.sum().backward()).unwrap().into_scalar();
    assert!(got.is_finite());

    // f64: the same placement (the importance depths, and the density-only depths with
    // their densities, held fixed as the renderer holds them), the midpoint rule over all
    // of them sorted together, the density-only densities moving with the composited ones
    // around them ([`lend_density_gradient`]).
    let p = place(&cfg, &field, &o, &d, false);
    let (fine, proposal_t, proposal_sigma) = (
        to_f32_vec(p.importance),
        to_f32_vec(p.t),
        to_f32_vec(p.sigma),
    );
    let (origins, dirs) = (to_f32_vec(o), to_f32_vec(d));
    let (n, m) = (cfg.importance, cfg.proposal + cfg.refine);
    let loss = |k: f64| -> f64 {
        let mut total = 0.0;
        for ray in 0..side * side {
            let radius = |tt: f64| -> f64 {
                (0..3)
                    .map(|c| {
                        let x = f64::from(origins[ray * 3 + c]) + tt * f64::from(dirs[ray * 3 + c]);
                        x * x
                    })
                    .sum::<f64>()
                    .sqrt()
            };
            let full: Vec<f64> = fine[ray * n..(ray + 1) * n]
                .iter()
                .map(|&x| f64::from(x))
                .collect();
            // A density-only entry's density is the one found, plus the change of the
            // composited densities interpolated there (zero at k0): its gradient.
            let interpolated = |tt: f64, k: f64| -> f64 {
                let before = full.iter().filter(|&&c| c <= tt).count();
                let (l, r) = (before.saturating_sub(1), before.min(n - 1));
                let a = if full[r] > full[l] {
                    ((tt - full[l]) / (full[r] - full[l])).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                k * ((1.0 - a) * ball.sigma_at(radius(full[l]))
                    + a * ball.sigma_at(radius(full[r])))
            };
            let mut entries: Vec<(f64, f64)> = full
                .iter()
                .map(|&tt| (tt, k * ball.sigma_at(radius(tt))))
                .collect();
            entries.extend((ray * m..(ray + 1) * m).map(|i| {
                let tt = f64::from(proposal_t[i]);
                let lent = interpolated(tt, k) - interpolated(tt, k0);
                (tt, f64::from(proposal_sigma[i]) + lent)
            }));
            entries.sort_by(|a, b| a.0.total_cmp(&b.0));
            let (mut optical, mut opacity, mut expected) = (0.0f64, 0.0f64, 0.0f64);
            for pair in entries.windows(2) {
                let ((t0, s0), (t1, s1)) = (pair[0], pair[1]);
                let tau = 0.5 * (s0 + s1) * (t1 - t0);
                let w = (-optical).exp() * -(-tau).exp_m1();
                optical += tau;
                opacity += w;
                expected += w * 0.5 * (t0 + t1);
            }
            total += expected + (1.0 - opacity) * cfg.camera.far;
        }
        total
    };
    let h = 1e-6;
    let fd = (loss(k0 + h) - loss(k0 - h)) / (2.0 * h);
    assert!(fd.abs() > 1e-3, "the loss depends on k: {fd}");
    assert!(
        (f64::from(got) - fd).abs() < 2e-3 * fd.abs().max(1e-2),
        "autodiff {got} vs f64 finite differences {fd}"
    );
}

/// The plain reference of [`lend`] for one ray: `(left, right, to_right)` per entry.
fn lend_reference(t: &[f32], composited: &[f32]) -> Vec<(usize, usize, f64)> {
    let mut order: Vec<usize> = (0..composited.len()).collect();
    order.sort_by(|&a, &b| composited[a].total_cmp(&composited[b]));
    let sorted: Vec<f64> = order.iter().map(|&i| f64::from(composited[i])).collect();
    let last = sorted.len() - 1;
    t.iter()
        .map(|&tt| {
            let tt = f64::from(tt);
            let at_or_before = sorted.iter().filter(|&&c| c <= tt).count();
            let (l, r) = (at_or_before.saturating_sub(1), at_or_before.min(last));
            let gap = sorted[r] - sorted[l];
            let to_right = if gap > 0.0 {
                ((tt - sorted[l]) / gap).clamp(0.0, 1.0)
            } else {
                0.0
            };
            (order[l], order[r], to_right)
        })
        .collect()
}

#[test]
fn lending_matches_the_plain_reference() {
    let device = Device::flex();
    // Rays: entries before, between, on and after unsorted composited depths; two composited
    // samples at one depth; a single composited sample.
    let cases: Vec<(Vec<f32>, Vec<f32>)> = vec![
        (
            vec![1.0, 2.0, 2.5, 3.0, 3.25, 4.0, 5.0],
            vec![4.0, 2.0, 3.0],
        ),
        (vec![2.0, 3.0, 3.0, 3.5, 6.0, 7.0, 8.0], vec![3.0, 3.0, 6.0]),
        (vec![0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 9.0], vec![8.0, 1.0, 2.5]),
    ];
    let n = cases[0].0.len();
    for (t, c) in &cases {
        let got = lend(
            Tensor::<1>::from_floats(t.as_slice(), &device).reshape([1, n]),
            Tensor::<1>::from_floats(c.as_slice(), &device).reshape([1, c.len()]),
        );
        let left: Vec<i64> = got.left.into_data().convert::<i64>().try_to_vec().unwrap();
        let right: Vec<i64> = got.right.into_data().convert::<i64>().try_to_vec().unwrap();
        let to_right = to_f32_vec(got.to_right);
        for (j, want) in lend_reference(t, c).into_iter().enumerate() {
            assert_eq!(
                (left[j] as usize, right[j] as usize),
                (want.0, want.1),
                "entry {j} of {t:?} to {c:?}"
            );
            assert!(
                (f64::from(to_right[j]) - want.2).abs() < 1e-6,
                "entry {j} of {t:?} to {c:?}: {} vs {}",
                to_right[j],
                want.2
            );
        }
    }
    let single = lend(
        Tensor::<1>::from_floats([1.0, 2.0, 3.0], &device).reshape([1, 3]),
        Tensor::<1>::from_floats([2.0], &device).reshape([1, 1]),
    );
    assert_eq!(
        single
            .left
            .into_data()
            .convert::<i64>()
            .try_to_vec::<i64>()
            .unwrap(),
        vec![0, 0, 0]
    );
    assert_eq!(to_f32_vec(single.to_right), vec![0.0, 0.0, 0.0]);
}

/// A sphere whose albedo is `k` times the point's coordinates (shifted into [0, 1]), so that
/// the values change along every ray.
struct Graded<'a> {
    sphere: &'a SoftSphere,
    k: Tensor<1>,
}

impl Field for Graded<'_> {
    fn query(&self, points: Tensor<3>, wants: FieldWants) -> FieldOutput {
        let mut out = self.sphere.query(points.clone(), wants);
        if wants.appearance {
            out.albedo = Some((points.inner().add_scalar(0.5)) * self.k.clone().reshape([1, 1, 1]));
        }
        out
    }
}

#[test]
fn lent_values_are_interpolated_between_the_composited_samples() {
    let device = Device::flex().autodiff();
    let ball = sphere(0.01, 60.0);
    let cfg = layout(0, 16, 8, 6);
    let k0 = 0.7f64;
    let k = Tensor::<1>::from_floats([k0 as f32], &device).require_grad();
    let field = Graded {
        sphere: &ball,
        k: k.clone(),
    };
    let (side, pose) = (4, Pose::new(-0.3, 0.15));
    let (o, d) = camera_ray_batch(&cfg.camera, &[pose], side, side, &device);
    let wants = RenderWants {
        albedo: true,
        normals: false,
        shading: false,
        features: false,
        depth: false,
    };
    let albedo = render(&cfg, &field, o.clone(), d.clone(), None, wants, false)
        .albedo
        .unwrap();
    let got_values = to_f32_vec(albedo.clone());
    let got_grad: f32 = k.grad(&albedo.sum().backward()).unwrap().into_scalar();

    // f64: the renderer's placement held fixed; every entry's values the linear
    // interpolation in depth of the composited samples' values around it.
    let p = place(&cfg, &field, &o, &d, false);
    let (fine, proposal_t, proposal_sigma) = (
        to_f32_vec(p.importance),
        to_f32_vec(p.t),
        to_f32_vec(p.sigma),
    );
    let (origins, dirs) = (to_f32_vec(o), to_f32_vec(d));
    let (n, m) = (cfg.importance, cfg.proposal + cfg.refine);
    let render_ref = |k: f64| -> Vec<f64> {
        let mut out = Vec::new();
        for ray in 0..side * side {
            let point = |tt: f64| -> [f64; 3] {
                std::array::from_fn(|c| {
                    f64::from(origins[ray * 3 + c]) + tt * f64::from(dirs[ray * 3 + c])
                })
            };
            let radius = |tt: f64| point(tt).iter().map(|x| x * x).sum::<f64>().sqrt();
            let value = |tt: f64| point(tt).map(|x| k * (x + 0.5));
            let full: Vec<f64> = fine[ray * n..(ray + 1) * n]
                .iter()
                .map(|&x| f64::from(x))
                .collect();
            let lent = |tt: f64| -> [f64; 3] {
                let before = full.iter().filter(|&&c| c <= tt).count();
                let (l, r) = (before.saturating_sub(1), before.min(n - 1));
                let a = if full[r] > full[l] {
                    ((tt - full[l]) / (full[r] - full[l])).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                let (vl, vr) = (value(full[l]), value(full[r]));
                std::array::from_fn(|c| (1.0 - a) * vl[c] + a * vr[c])
            };
            let mut entries: Vec<(f64, f64, [f64; 3])> = full
                .iter()
                .map(|&tt| (tt, ball.sigma_at(radius(tt)), value(tt)))
                .collect();
            entries.extend((ray * m..(ray + 1) * m).map(|i| {
                let tt = f64::from(proposal_t[i]);
                (tt, f64::from(proposal_sigma[i]), lent(tt))
            }));
            entries.sort_by(|a, b| a.0.total_cmp(&b.0));
            let (mut optical, mut acc) = (0.0f64, [0.0f64; 3]);
            for pair in entries.windows(2) {
                let ((t0, s0, v0), (t1, s1, v1)) = (pair[0], pair[1]);
                let tau = 0.5 * (s0 + s1) * (t1 - t0);
                let w = (-optical).exp() * -(-tau).exp_m1();
                optical += tau;
                for c in 0..3 {
                    acc[c] += w * 0.5 * (v0[c] + v1[c]);
                }
            }
            out.extend(acc);
        }
        out
    };
    let want = render_ref(k0);
    // The renderer's albedo is `[batch, rays, 3]`, as the reference.
    for ray in 0..side * side {
        for c in 0..3 {
            let (g, w) = (f64::from(got_values[ray * 3 + c]), want[ray * 3 + c]);
            assert!((g - w).abs() < 2e-4, "ray {ray} channel {c}: {g} vs {w}");
        }
    }
    let h = 1e-5;
    let fd: f64 = render_ref(k0 + h)
        .iter()
        .zip(render_ref(k0 - h))
        .map(|(a, b)| (a - b) / (2.0 * h))
        .sum();
    assert!(fd.abs() > 1e-2, "the albedo depends on k: {fd}");
    assert!(
        (f64::from(got_grad) - fd).abs() < 1e-3 * fd.abs(),
        "autodiff {got_grad} vs f64 finite differences {fd}"
    );
}
