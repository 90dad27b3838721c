//! The fast preconvolution against the f64 reference, on ordinary, stiff and extreme inputs.

use std::path::PathBuf;

use volux_envmap::direction::{self, Dir};
use volux_envmap::random::SplitMix64;
use volux_envmap::reference::Reference;
use volux_envmap::report::{compare, random_directions};
use volux_envmap::{EnvMap, EnvMapError, LightMapSet, PreconvolveOptions, Rgb, io, preconvolve};

fn asset(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../assets/hdri")
        .join(name)
}

/// Relative RMS error of a light map's look-up against the reference at `count` random
/// directions.
fn lookup_error(map: &EnvMap, set: &LightMapSet, n: u32, count: usize) -> f64 {
    let dirs = random_directions(count, 17 + u64::from(n));
    let reference = Reference::new(map, n).eval_many(&dirs);
    let lm = set.get(n).unwrap();
    let fast: Vec<Rgb> = dirs.iter().map(|d| lm.lookup(*d)).collect();
    compare(&fast, &reference).rel_rms
}

fn assert_finite_non_negative(set: &LightMapSet) {
    for lm in set.maps() {
        for c in lm.texels() {
            assert!(
                c.iter().all(|v| v.is_finite() && *v >= 0.0),
                "n={}: {c:?}",
                lm.exponent()
            );
        }
    }
}

fn options(exponents: &[u32]) -> PreconvolveOptions {
    PreconvolveOptions::with_exponents(exponents)
}

#[test]
fn constant_map_stays_constant_for_every_exponent_and_size() {
    for h in [4usize, 32] {
        let map = EnvMap::constant(h, [2.5, 1.0, 0.0]).unwrap();
        let set = preconvolve(&map, &options(&[1, 16, 32, 64, 128, 512])).unwrap();
        for lm in set.maps() {
            for c in lm.texels() {
                assert!(
                    (c[0] - 2.5).abs() < 1e-5 && (c[1] - 1.0).abs() < 1e-5 && c[2] == 0.0,
                    "{h} n={}: {c:?}",
                    lm.exponent()
                );
            }
            for d in random_directions(64, 3) {
                let v = lm.lookup(d);
                assert!((v[0] - 2.5).abs() < 1e-5, "{v:?}");
            }
        }
    }
}

#[test]
fn all_black_map_gives_black_light_maps() {
    let map = EnvMap::constant(64, [0.0; 3]).unwrap();
    let set = preconvolve(&map, &PreconvolveOptions::default()).unwrap();
    assert_eq!(set.exponents(), vec![1, 16, 32, 64]);
    for lm in set.maps() {
        assert!(lm.texels().iter().all(|c| *c == [0.0; 3]));
        assert_eq!(lm.lookup([0.0, 1.0, 0.0]), [0.0; 3]);
    }
}

#[test]
fn map_with_black_lower_half_matches_the_reference() {
    // Black rows are skipped by the analysis; the result must not notice.
    let map = EnvMap::from_fn(64, |d| {
        if d[1] > 0.0 {
            [1.0 + d[0] as f32, 0.5, 2.0 * d[1] as f32]
        } else {
            [0.0; 3]
        }
    })
    .unwrap();
    let set = preconvolve(&map, &options(&[1, 32])).unwrap();
    for n in [1, 32] {
        let e = lookup_error(&map, &set, n, 256);
        assert!(e < 2e-3, "n={n}: {e}");
    }
}

#[test]
fn one_texel_sun_of_a_million_on_a_dim_sky() {
    let mut map = EnvMap::from_fn(64, |d| [0.02 + 0.01 * d[1].max(0.0) as f32; 3]).unwrap();
    let (sx, sy) = (40, 20);
    map.set_texel(sx, sy, [1e6, 9e5, 8e5]);
    let exponents = [1, 16, 32, 64, 512];
    let set = preconvolve(&map, &options(&exponents)).unwrap();
    assert_finite_non_negative(&set);
    let tolerance = PreconvolveOptions::default().tolerance;
    for n in exponents {
        let e = lookup_error(&map, &set, n, 384);
        assert!(e <= tolerance, "n={n}: rel RMS {e}");
    }
    // Far from the sun the narrow lobes see only the sky: no ringing of the sun shows there.
    let sun_dir = direction::texel_dir(sx, sy, 128, 64);
    for n in [16, 32, 64, 512] {
        let far: Vec<Dir> = random_directions(400, 11)
            .into_iter()
            .filter(|d| direction::dot(*d, sun_dir) < -0.2)
            .collect();
        let reference = Reference::new(&map, n).eval_many(&far);
        let lm = set.get(n).unwrap();
        let fast: Vec<Rgb> = far.iter().map(|d| lm.lookup(*d)).collect();
        let e = compare(&fast, &reference);
        assert!(e.max_rel < 1e-3, "n={n}: far field off by {:e}", e.max_rel);
    }
    // The narrow lobes peak at the sun.
    let sun = direction::texel_dir(sx, sy, 128, 64);
    let lm = set.get(64).unwrap();
    let at_sun = lm.lookup(sun)[0];
    for d in random_directions(200, 9) {
        assert!(lm.lookup(d)[0] <= at_sun * 1.001);
    }
}

#[test]
fn taper_suppresses_ringing() {
    // A small bright disc on black: no texel holds enough energy to be summed directly, so the
    // band-limited convolution rings on the black side, less with the taper.
    let centre = direction::uv_to_dir(0.3, 0.4);
    let map = EnvMap::from_fn(64, |d| {
        if direction::dot(d, centre) > 0.989 {
            [1e3; 3]
        } else {
            [0.0; 3]
        }
    })
    .unwrap();
    let plain = PreconvolveOptions {
        taper: 0.0,
        ..options(&[16, 64])
    };
    let a = preconvolve(&map, &plain).unwrap();
    let b = preconvolve(&map, &options(&[16, 64])).unwrap();
    for n in [16, 64] {
        let (ra, rb) = (a.get(n).unwrap().ringing(), b.get(n).unwrap().ringing());
        assert!(
            ra > 0.0 && a.get(n).unwrap().clamped() > 0,
            "n={n}: plain truncation rings below zero"
        );
        assert!(rb < 0.5 * ra, "n={n}: tapered {rb:e} vs plain {ra:e}");
    }
    assert_finite_non_negative(&a);
}

#[test]
fn exponents_up_to_512_on_a_real_map() {
    let map = io::load(&asset("sunset.exr")).unwrap().downsampled(4);
    let exponents = [128, 256, 512];
    let set = preconvolve(&map, &options(&exponents)).unwrap();
    assert_finite_non_negative(&set);
    for n in exponents {
        let e = lookup_error(&map, &set, n, 128);
        assert!(e < 3e-3, "n={n}: {e}");
    }
}

#[test]
fn tiny_8x4_map_is_integrated_texel_by_texel() {
    let mut rng = SplitMix64::new(5);
    let texels = (0..32)
        .map(|_| [rng.next_f64() as f32 * 10.0, 1.0, 0.0])
        .collect();
    let map = EnvMap::new(8, 4, texels).unwrap();
    let exponents = [1, 64, 512];
    let set = preconvolve(&map, &options(&exponents)).unwrap();
    assert_finite_non_negative(&set);
    for n in exponents {
        let e = lookup_error(&map, &set, n, 128);
        assert!(e < 2e-3, "n={n}: {e}");
    }
}

#[test]
fn large_4096x2048_map() {
    let mut map =
        EnvMap::from_fn(1024, |d| [(1.0 + d[1]) as f32, 0.3, (1.0 + d[0]) as f32]).unwrap();
    map.set_texel(1500, 300, [5e4; 3]);
    // Upsample by 2 with nearest texels: the same piecewise-constant map at 4096x2048.
    let big: Vec<Rgb> = (0..2048 * 4096)
        .map(|i| map.texel((i % 4096) / 2, (i / 4096) / 2))
        .collect();
    let big = EnvMap::new(4096, 2048, big).unwrap();
    drop(map);
    let set = preconvolve(&big, &options(&[1, 64])).unwrap();
    assert_finite_non_negative(&set);
    for n in [1, 64] {
        let e = lookup_error(&big, &set, n, 24);
        assert!(e < 2e-3, "n={n}: {e}");
    }
}

#[test]
fn every_shipped_map_meets_the_accuracy_target_with_default_options() {
    // Target: all four default lobes within 0.3% relative RMS at the look-up.
    let mut files: Vec<PathBuf> = std::fs::read_dir(asset(""))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "exr"))
        .collect();
    files.sort();
    assert_eq!(files.len(), 8, "the eight shipped maps");
    for file in files {
        let name = file.display();
        let map = io::load(&file).unwrap();
        assert_eq!((map.width(), map.height()), (1024, 512));
        let set = preconvolve(&map, &PreconvolveOptions::default()).unwrap();
        assert_finite_non_negative(&set);
        for n in [1, 16, 32, 64] {
            let e = lookup_error(&map, &set, n, 96);
            assert!(e < 3e-3, "{name} n={n}: {e}");
        }
    }
}

#[test]
fn rotating_the_map_equals_rotating_the_lookup() {
    let map = io::load(&asset("courtyard.exr")).unwrap().downsampled(8);
    let yaw = std::f64::consts::TAU * 5.0 / map.width() as f64; // whole texels: exact shift
    let rotated = map.rotated_yaw(yaw);
    let opts = options(&[1, 32]);
    let a = preconvolve(&map, &opts).unwrap();
    let b = preconvolve(&rotated, &opts).unwrap();
    for n in [1, 32] {
        let (la, lb) = (a.get(n).unwrap(), b.get(n).unwrap());
        let peak = lb.texels().iter().map(|c| c[1]).fold(0.0f32, f32::max);
        for d in random_directions(100, 4) {
            let (x, y): (Rgb, Rgb) = (la.lookup_rotated(d, yaw), lb.lookup(d));
            for c in 0..3 {
                assert!(
                    (x[c] - y[c]).abs() <= 2e-3 * peak,
                    "n={n} {d:?}: {x:?} vs {y:?}"
                );
            }
        }
    }
}

#[test]
fn bad_options_are_clear_errors() {
    let map = EnvMap::constant(4, [1.0; 3]).unwrap();
    let cases: [(PreconvolveOptions, &str); 5] = [
        (options(&[]), "empty"),
        (options(&[1, 16, 16]), "repeats"),
        (options(&[0]), "exponent 0"),
        (options(&[100_000]), "exponent 100000"),
        (
            PreconvolveOptions {
                tolerance: 0.0,
                ..options(&[1])
            },
            "tolerance 0",
        ),
    ];
    for (opts, what) in cases {
        let e: EnvMapError = preconvolve(&map, &opts).unwrap_err();
        assert!(
            e.to_string().contains(what.split(' ').next_back().unwrap()),
            "{what}: {e}"
        );
    }
}

#[test]
fn light_maps_save_as_exr_and_contact_sheet() {
    let dir = tempfile::tempdir().unwrap();
    let map = io::load(&asset("studio.exr")).unwrap().downsampled(4);
    let set = preconvolve(&map, &PreconvolveOptions::default()).unwrap();
    let written = set.save(dir.path()).unwrap();
    assert_eq!(written.len(), 5);
    let l16 = io::read_raw(&dir.path().join("light_n016.exr")).unwrap();
    let lm = set.get(16).unwrap();
    assert_eq!((l16.width, l16.height), (lm.width(), lm.height()));
    assert_eq!(l16.texels, lm.texels());
    assert!(dir.path().join("light_maps.png").exists());
}

#[test]
fn tolerances_too_fine_for_memory_are_refused_before_allocating() {
    let map = EnvMap::new(8, 4, vec![[1.0; 3]; 32]).unwrap();
    for tolerance in [1e-6, 1e-9, 1e-300] {
        let mut o = options(&[1, 16]);
        o.tolerance = tolerance;
        let e = preconvolve(&map, &o).unwrap_err();
        assert!(matches!(e, EnvMapError::TooFine { .. }), "{e:?}");
        let message = e.to_string();
        assert!(
            message.contains("degree 4096") && message.contains("GiB limit"),
            "{message}"
        );
        // The suggested tolerance is accepted, and a tenth of a decade finer is not.
        let EnvMapError::TooFine {
            coarsest_allowed, ..
        } = e
        else {
            unreachable!()
        };
        o.tolerance = coarsest_allowed;
        assert!(o.validate().is_ok(), "{coarsest_allowed}");
        o.tolerance = coarsest_allowed / 10f64.powf(0.1);
        assert!(o.validate().is_err(), "{coarsest_allowed}");
    }
    // What the analysis plans at the finest allowed tolerance stays within the limit.
    let lmax = volux_envmap::lobe::band_limit(1, 5e-6 / 2f64.sqrt(), 0.5).0;
    assert!(
        2 * volux_envmap::sh::analysis_bytes(lmax) <= volux_envmap::preconvolve::MAX_ANALYSIS_BYTES
    );
}
