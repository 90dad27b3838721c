//! The measurements on the synthetic heads' exact renders: what a perfect score looks like,
//! and that a deliberately wrong geometry is caught.

use volux_data::synthetic_head::SyntheticHead;
use volux_envmap::{EnvMap, LightMapSet, PreconvolveOptions, preconvolve};
use volux_eval::geometry::{GeometryScore, render_angles};
use volux_eval::relighting_consistency::{invariance, relit_against_shaded};
use volux_eval::reprojection::{DEFAULT_TOLERANCE, reproject};
use volux_eval::views::{Rendered, render_synthetic};
use volux_model::pose::Pose;
use volux_model::ray_sampling::CameraConfig;

/// A sky with a warm key light above and to the right.
fn lights(key: [f64; 3]) -> LightMapSet {
    let map = EnvMap::from_fn(32, |d| {
        let c = (d[0] * key[0] + d[1] * key[1] + d[2] * key[2])
            .max(0.0)
            .powi(8);
        [
            0.2 + 3.0 * c as f32,
            0.2 + 2.5 * c as f32,
            0.25 + 2.0 * c as f32,
        ]
    })
    .unwrap();
    preconvolve(&map, &PreconvolveOptions::default()).unwrap()
}

fn render(seed: u64, yaw: f64, l: &LightMapSet) -> Rendered {
    let head = SyntheticHead::from_seed(seed);
    render_synthetic(&head, Pose::new(yaw, 0.0), 64, 32, l, 0.0, [1.0, 1.0, 1.0]).unwrap()
}

#[test]
fn true_depth_reprojects_consistently_and_wrong_depth_does_not() {
    let camera = CameraConfig::new();
    let l = lights([0.5, 0.7, 0.5]);
    for seed in [0, 1] {
        let front = render(seed, 0.0, &l);
        for yaw in [-0.5, 0.25] {
            let side = render(seed, yaw, &l);
            let good = reproject(&front, &side, &camera, DEFAULT_TOLERANCE);
            let fraction = good.consistent_fraction();
            println!(
                "seed {seed} yaw {yaw}: consistent {fraction:.3}, albedo PSNR {:.2} L1 {:.4}, relit PSNR {:.2}",
                good.albedo.psnr(),
                good.albedo.l1(),
                good.relit.psnr()
            );
            assert!(good.foreground > 1000, "{}", good.foreground);
            // Self-occlusion hides part of the face from a side view; the rest agrees.
            assert!(fraction > 0.65, "{fraction}");
            assert!(
                good.albedo.psnr() > 27.0 && good.albedo.l1() < 0.015,
                "{:?}",
                good.albedo
            );

            // Depth pushed 0.15 back: points land elsewhere, fail the depth test, and
            // without that test the colours they fetch are wrong.
            let mut wrong = front.clone();
            wrong.depth.iter_mut().for_each(|t| *t += 0.15);
            let bad = reproject(&wrong, &side, &camera, DEFAULT_TOLERANCE);
            assert!(
                bad.consistent_fraction() < 0.1 * fraction,
                "{}",
                bad.consistent_fraction()
            );
            let blind = reproject(&wrong, &side, &camera, f64::INFINITY);
            println!(
                "  wrong depth: consistent {:.3}, untested albedo L1 {:.4}",
                bad.consistent_fraction(),
                blind.albedo.l1()
            );
            assert!(
                blind.albedo.l1() > 2.0 * good.albedo.l1(),
                "{} vs {}",
                blind.albedo.l1(),
                good.albedo.l1()
            );
            assert!(blind.albedo.psnr() < good.albedo.psnr() - 3.0);
        }
    }
}

#[test]
fn the_heads_normals_agree_with_their_depth() {
    let camera = CameraConfig::new();
    let l = lights([0.0, 1.0, 0.0]);
    let mut angles = Vec::new();
    for seed in 0..3 {
        for yaw in [0.0, 0.4] {
            angles.extend(render_angles(&camera, &render(seed, yaw, &l)));
        }
    }
    let score = GeometryScore::of(&angles);
    println!("{score:?}");
    assert!(score.pixels > 1000);
    assert!(score.median_degrees < 8.0, "{score:?}");
    // Normals of a flat card on the same depth are far off.
    let mut flat = render(0, 0.0, &l);
    flat.normals_lo
        .iter_mut()
        .for_each(|n| *n = [0.0, 0.0, 1.0]);
    let off = GeometryScore::of(&render_angles(&camera, &flat));
    assert!(
        off.median_degrees > 2.0 * score.median_degrees,
        "{off:?} vs {score:?}"
    );
}

#[test]
fn relighting_a_head_keeps_its_intrinsics_and_is_its_own_shading() {
    let views: Vec<Rendered> = [[0.6, 0.6, 0.5], [-0.8, 0.2, 0.5], [0.0, -1.0, 0.0]]
        .into_iter()
        .map(|key| render(3, 0.0, &lights(key)))
        .collect();
    let i = invariance(&views);
    assert_eq!(
        (i.albedo.l1(), i.albedo_max, i.normals.l1()),
        (0.0, 0.0, 0.0)
    );
    // The lights differ, so the relit images do.
    assert!(views[0].relit != views[1].relit);
    for v in &views {
        assert_eq!(relit_against_shaded(v).l1(), 0.0);
    }
}
