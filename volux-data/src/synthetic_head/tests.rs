//! The synthetic heads against what must hold of any correct render: normals are the distance
//! field's gradient, depths lie on the surface, two poses of one head agree, a constant
//! environment shades uniformly, and the same seed renders the same image.

use volux_envmap::direction::{dot, normalize};
use volux_envmap::io::tonemap_pixel;
use volux_envmap::{EnvMap, LightMap, PreconvolveOptions, preconvolve};
use volux_model::pose::Pose;
use volux_model::ray_sampling::{camera_basis, camera_position, camera_rays};

use super::photo::ambient_occlusion;
use super::*;

fn lights_of(map: &EnvMap) -> volux_envmap::LightMapSet {
    preconvolve(map, &PreconvolveOptions::default()).unwrap()
}

/// Central-difference gradient of the f64 distance.
fn fd_gradient(head: &SyntheticHead, p: [f64; 3]) -> [f64; 3] {
    let h = 1e-6;
    std::array::from_fn(|k| {
        let (mut a, mut b) = (p, p);
        a[k] += h;
        b[k] -= h;
        (head.distance(a) - head.distance(b)) / (2.0 * h)
    })
}

/// Camera-space normal to world space.
fn to_world(n: [f32; 3], basis: [[f64; 3]; 3]) -> [f64; 3] {
    std::array::from_fn(|k| {
        basis[0][k] * f64::from(n[0])
            + basis[1][k] * f64::from(n[1])
            + basis[2][k] * f64::from(n[2])
    })
}

#[test]
fn normals_are_the_distance_gradient_and_depths_lie_on_the_surface() {
    let settings = RenderSettings::square(48);
    let pose = Pose::new(0.25, -0.1);
    let basis = camera_basis(&settings.camera, pose);
    let (origins, dirs) = camera_rays(&settings.camera, pose, 48, 48);
    for seed in [0, 7] {
        let head = SyntheticHead::from_seed(seed);
        let render = render(&head, pose, &settings);
        let mut checked = 0;
        let mut worst = 0.0f64;
        let mut distances = Vec::new();
        let mut worst_grazing = 0.0f64;
        for i in 0..48 * 48 {
            if render.image.mask[i] < 1.0 {
                assert_eq!(
                    render.depth[i], settings.camera.far as f32,
                    "background depth"
                );
                continue;
            }
            let t = f64::from(render.depth[i]);
            let p: [f64; 3] = std::array::from_fn(|k| origins[i][k] + t * dirs[i][k]);
            let exact = render.hits[i][0].point;
            let fd = normalize(fd_gradient(&head, exact));
            if dot(fd, dirs[i]).abs() < 0.1 {
                worst_grazing = worst_grazing.max(head.distance(p).abs());
            } else {
                distances.push(head.distance(p).abs());
            }
            let n = to_world(render.image.normals[i], basis);
            worst = worst.max(1.0 - dot(fd, n));
            checked += 1;
        }
        assert!(checked > 700, "only {checked} foreground pixels");
        distances.sort_by(f64::total_cmp);
        let (median, max) = (
            distances[distances.len() / 2],
            distances[distances.len() - 1],
        );
        // The f32 depth puts points within its rounding of the surface; rays within 6 degrees
        // of tangent (the silhouette) converge more slowly and stop within 1e-3.
        assert!(
            median < 2e-7 && max < 1e-6 && worst_grazing < 1e-3,
            "seed {seed}: |distance| median {median:e}, max {max:e}, grazing {worst_grazing:e}"
        );
        // f32 normals against f64 finite differences: 1 - cos < 1e-6 is about 0.08 degrees.
        assert!(worst < 1e-6, "seed {seed}: worst 1 - cos {worst:e}");
    }
}

#[test]
fn two_poses_of_one_head_agree_when_reprojected() {
    let side = 96;
    let settings = RenderSettings::square(side);
    let head = SyntheticHead::from_seed(3);
    let (pose_a, pose_b) = (Pose::new(0.3, 0.1), Pose::new(-0.2, -0.05));
    let a = render(&head, pose_a, &settings);
    let b = render(&head, pose_b, &settings);
    let camera = &settings.camera;
    let (origins_b, dirs_b) = camera_rays(camera, pose_b, side, side);
    let basis_a = camera_basis(camera, pose_a);
    let basis_b = camera_basis(camera, pose_b);
    let o_a = camera_position(camera, pose_a);
    let tan = (camera.fov_degrees.to_radians() / 2.0).tan();
    let (mut interior, mut visible, mut depth_agree) = (0, 0, 0);
    let (mut angles, mut albedo_errors) = (Vec::new(), Vec::new());
    for y in 1..side - 1 {
        for x in 1..side - 1 {
            let i = y * side + x;
            let solid = (0..9).all(|k| b.image.mask[(y + k / 3 - 1) * side + x + k % 3 - 1] == 1.0);
            if !solid {
                continue;
            }
            interior += 1;
            let t = f64::from(b.depth[i]);
            let p: [f64; 3] = std::array::from_fn(|k| origins_b[i][k] + t * dirs_b[i][k]);
            let v: [f64; 3] = std::array::from_fn(|k| p[k] - o_a[k]);
            let z = -dot(v, basis_a[2]);
            let sx = dot(v, basis_a[0]) / z / tan;
            let sy = dot(v, basis_a[1]) / z / tan;
            // Continuous pixel coordinates in A, and the (up to) four pixels around them.
            let fx = (sx + 1.0) / 2.0 * side as f64 - 0.5;
            let fy = (1.0 - sy) / 2.0 * side as f64 - 0.5;
            let around: Vec<usize> = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)]
                .iter()
                .map(|(dx, dy)| (fx.floor() + dx, fy.floor() + dy))
                .filter(|(x, y)| (0.0..side as f64).contains(x) && (0.0..side as f64).contains(y))
                .map(|(x, y)| y as usize * side + x as usize)
                .collect();
            // Is the point visible from A? Trace A's ray towards it.
            let distance = dot(v, v).sqrt();
            let towards = v.map(|c| c / distance);
            let first = render::trace(&head, o_a, towards, camera.near, camera.far);
            if first.is_none_or(|t| (t - distance).abs() > 1e-3) {
                continue;
            }
            // Seen at grazing incidence, a pixel spans a long stretch of depth: leave those out.
            let nb = to_world(b.image.normals[i], basis_b);
            if dot(nb, towards) > -0.25 {
                continue;
            }
            visible += 1;
            // A's layers at the pixels the point projects between: one of them covered and at
            // the point's depth to within a pixel's footprint on a slanted surface, with the
            // same normal and albedo.
            let error = |j: usize| (f64::from(a.depth[j]) - distance).abs();
            let Some(j) = around
                .into_iter()
                .filter(|&j| a.image.mask[j] == 1.0)
                .min_by(|&j, &k| error(j).total_cmp(&error(k)))
            else {
                continue;
            };
            if error(j) > 0.02 {
                continue;
            }
            depth_agree += 1;
            let na = to_world(a.image.normals[j], basis_a);
            angles.push(dot(na, nb).clamp(-1.0, 1.0).acos().to_degrees());
            let (aa, ab) = (a.image.albedo[j], b.image.albedo[i]);
            albedo_errors.push((0..3).map(|k| (aa[k] - ab[k]).abs()).fold(0.0, f32::max));
        }
    }
    let frac = |n: usize, of: usize| n as f64 / of as f64;
    assert!(interior > 1200, "interior {interior}");
    // A yaw difference of 0.5 rad hides one side of the head and of the nose; points A sees
    // at grazing incidence are left out.
    assert!(
        frac(visible, interior) > 0.6,
        "visible {visible} of {interior}"
    );
    assert!(
        frac(depth_agree, visible) > 0.99,
        "depth {depth_agree} of {visible}"
    );
    // Normals: the two pixels' surface points are up to half a pixel apart, which turns the
    // normal a lot only on small, sharply curved forms (the hair cap's rim, nostrils, lids).
    angles.sort_by(f64::total_cmp);
    let (median, p90) = (angles[angles.len() / 2], angles[angles.len() * 9 / 10]);
    assert!(
        median < 2.0 && p90 < 15.0,
        "normal angles: median {median}, 90% {p90} degrees"
    );
    // Albedo: the same up to texture detail within half a pixel (hair strands, iris edges).
    albedo_errors.sort_by(f32::total_cmp);
    let (median, p90) = (
        albedo_errors[albedo_errors.len() / 2],
        albedo_errors[albedo_errors.len() * 9 / 10],
    );
    assert!(
        median < 0.01 && p90 < 0.05,
        "albedo differences: median {median}, 90% {p90}"
    );
}

#[test]
fn a_constant_environment_shades_uniformly_and_the_photo_only_darkens_creases() {
    let c = [0.6f32, 0.5, 0.4];
    let set = lights_of(&EnvMap::constant(32, c).unwrap());
    let lights: Vec<&LightMap> = set.maps().iter().collect();
    let head = SyntheticHead::from_seed(11);
    let render = render(&head, Pose::new(0.1, 0.05), &RenderSettings::square(40));
    let shading = shade(&head, &render, &lights, 0.7, [0.0; 3]).unwrap();
    let mut aos = Vec::new();
    for i in 0..40 * 40 {
        let m = render.image.mask[i];
        for (d, c) in shading.layers.diffuse[i].iter().zip(c) {
            assert!((d - c * m).abs() < 2e-3 * c, "pixel {i}: diffuse {d}");
        }
        if m < 1.0 {
            continue;
        }
        // No directional light and L_1 constant (so no softening): the photo is the Phong
        // image with diffuse and specular light occluded.
        let hit = &render.hits[i][0];
        let ao = ambient_occlusion(&head, hit.point, hit.normal) as f32;
        let (a, d, s) = (
            render.image.albedo[i],
            shading.layers.diffuse[i],
            shading.layers.specular[i],
        );
        let want = tonemap_pixel(std::array::from_fn(|k| ao * (a[k] * d[k] + s[k])), 1.0);
        for k in 0..3 {
            assert!(
                (shading.photo[i][k] - want[k]).abs() < 1e-5,
                "pixel {i}: {:?} vs {want:?}",
                shading.photo[i]
            );
        }
        aos.push(ao);
    }
    // Open skin is (nearly) unoccluded, the creases are not.
    aos.sort_by(f32::total_cmp);
    let median = aos[aos.len() / 2];
    assert!(median > 0.9, "median occlusion {median}");
    assert!(
        aos[aos.len() / 50] < 0.8,
        "no creases: 2nd percentile {}",
        aos[aos.len() / 50]
    );
}

#[test]
fn a_sun_casts_shadows_into_the_photo_only() {
    // A small bright sun to the right: the left of the face lies in the nose's and head's
    // shadow in the photo, not in the Phong layers.
    let sun = crate::procedural_sky::studio(
        64,
        &[crate::procedural_sky::AreaLight {
            direction: normalize([1.0, 0.2, 0.4]),
            radius: 0.05,
            irradiance: [3.0; 3],
        }],
    )
    .unwrap();
    let set = lights_of(&sun);
    let lights: Vec<&LightMap> = set.maps().iter().collect();
    let head = SyntheticHead::from_seed(2);
    let render = render(&head, Pose::new(0.0, 0.0), &RenderSettings::square(48));
    let light = PhotoLighting::new(&lights, 0.0).unwrap();
    assert!(light.directionality() > 0.9, "{}", light.directionality());
    assert!(dot(light.key_direction(), normalize([1.0, 0.2, 0.4])) > 0.99);
    let shading = shade(&head, &render, &lights, 0.0, [0.0; 3]).unwrap();
    // Pixels lit in the Phong layers (normal towards the sun) but in shadow in the photo.
    let shadowed = (0..48 * 48)
        .filter(|&i| render.image.mask[i] == 1.0)
        .filter(|&i| shading.layers.diffuse[i][1] > 0.3)
        .filter(|&i| shading.photo[i][1] < 0.5 * shading.layers.relit[i][1])
        .count();
    assert!(shadowed > 5, "no cast shadows ({shadowed})");
}

#[test]
fn the_same_seed_renders_the_same_image_on_any_number_of_threads() {
    let set = lights_of(&crate::procedural_sky::overcast(32, 1.5).unwrap());
    let lights: Vec<&LightMap> = set.maps().iter().collect();
    let settings = RenderSettings {
        supersample: 2,
        ..RenderSettings::square(24)
    };
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let head = SyntheticHead::from_seed(42);
            let render = render(&head, Pose::new(0.2, 0.1), &settings);
            let shading = shade(&head, &render, &lights, 1.0, [0.5; 3]).unwrap();
            (render.image, render.depth, shading)
        })
    };
    let one = run(1);
    assert_eq!(one, run(3));
    let other = {
        let head = SyntheticHead::from_seed(43);
        render(&head, Pose::new(0.2, 0.1), &settings).image
    };
    assert_ne!(one.0.albedo, other.albedo, "two seeds gave the same head");
}

#[test]
fn every_identity_is_one_plausible_head() {
    // Over many seeds: the head fills a sensible part of the frame, is one connected piece
    // (no part floats free), shows both eyes and, unless bald, hair.
    let side = 48;
    let settings = RenderSettings::square(side);
    for seed in 0..24 {
        let head = SyntheticHead::from_seed(seed);
        let render = render(&head, Pose::new(0.0, 0.0), &settings);
        let mask = &render.image.mask;
        let coverage = mask.iter().sum::<f32>() / mask.len() as f32;
        assert!(
            (0.3..0.8).contains(&coverage),
            "seed {seed}: coverage {coverage}"
        );
        // Flood fill from the centre reaches every foreground pixel.
        let mut seen = vec![false; side * side];
        let mut stack = vec![side / 2 * side + side / 2];
        while let Some(i) = stack.pop() {
            if seen[i] || mask[i] < 1.0 {
                continue;
            }
            seen[i] = true;
            let (x, y) = (i % side, i / side);
            if x > 0 {
                stack.push(i - 1);
            }
            if x + 1 < side {
                stack.push(i + 1);
            }
            if y > 0 {
                stack.push(i - side);
            }
            if y + 1 < side {
                stack.push(i + side);
            }
        }
        let pieces = (0..side * side)
            .filter(|&i| mask[i] == 1.0 && !seen[i])
            .count();
        assert_eq!(
            pieces, 0,
            "seed {seed}: {pieces} pixels not connected to the head"
        );
        let regions = |r: Region| {
            render
                .hits
                .iter()
                .flatten()
                .filter(|h| h.material.region == r)
                .count()
        };
        let eyes_left = render
            .hits
            .iter()
            .flatten()
            .filter(|h| h.material.region == Region::Eye && h.point[0] < 0.0)
            .count();
        let eyes_right = regions(Region::Eye) - eyes_left;
        assert!(
            eyes_left >= 2 && eyes_right >= 2,
            "seed {seed}: eyes {eyes_left} {eyes_right}"
        );
        let bald = head.identity().hair_thickness == 0.0;
        assert_eq!(
            regions(Region::Hair) == 0,
            bald,
            "seed {seed}: hair pixels {}",
            regions(Region::Hair)
        );
    }
}

#[test]
fn extreme_light_stays_finite() {
    // A 1e6 sun and an all-black environment: every layer finite, black gives black shading.
    let sun = crate::procedural_sky::studio(
        64,
        &[crate::procedural_sky::AreaLight {
            direction: [0.0, 0.6, 0.8],
            radius: 0.02,
            irradiance: [1e6; 3],
        }],
    )
    .unwrap();
    let head = SyntheticHead::from_seed(5);
    let render = render(&head, Pose::new(0.0, 0.0), &RenderSettings::square(24));
    for map in [sun, EnvMap::constant(32, [0.0; 3]).unwrap()] {
        let set = lights_of(&map);
        let lights: Vec<&LightMap> = set.maps().iter().collect();
        let s = shade(&head, &render, &lights, 0.0, [0.2; 3]).unwrap();
        let layers = [
            &s.layers.diffuse,
            &s.layers.specular,
            &s.layers.relit,
            &s.photo,
        ];
        for layer in layers {
            assert!(layer.iter().flatten().all(|v| v.is_finite() && *v >= 0.0));
        }
        assert!(s.photo.iter().flatten().all(|v| *v <= 1.0));
        if map.is_black() {
            assert!(s.layers.diffuse.iter().flatten().all(|v| *v == 0.0));
        }
    }
}

#[test]
fn light_maps_other_than_the_four_lobes_are_refused() {
    let set = preconvolve(
        &EnvMap::constant(16, [1.0; 3]).unwrap(),
        &PreconvolveOptions::with_exponents(&[1, 16]),
    )
    .unwrap();
    let lights: Vec<&LightMap> = set.maps().iter().collect();
    let head = SyntheticHead::from_seed(0);
    let render = render(&head, Pose::new(0.0, 0.0), &RenderSettings::square(8));
    let err = shade(&head, &render, &lights, 0.0, [0.0; 3]).unwrap_err();
    assert_eq!(err, SyntheticError::Exponents(vec![1, 16]));
}
