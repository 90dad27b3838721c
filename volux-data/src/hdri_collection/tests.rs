//! Tests of HDRI collections: built-in maps, procedural parameters, folders, configs.

use std::f64::consts::TAU;
use std::fs;
use std::path::Path;

use volux_envmap::{EnvMap, io};

use super::*;
use volux_envmap::direction::{self, Dir};
use volux_envmap::{PreconvolveOptions, preconvolve};

fn procedural_only(skies: usize, overcast: usize, studios: usize) -> HdriCollectionConfig {
    HdriCollectionConfig {
        builtin: false,
        skies,
        overcast,
        studios,
        procedural_height: 64,
        ..HdriCollectionConfig::default()
    }
}

fn write_map(path: &Path, value: f32) {
    let map = EnvMap::from_fn(8, |d| [value, (1.0 + d[1]) as f32, 0.25]).unwrap();
    io::save_envmap_exr(path, &map).unwrap();
}

#[test]
fn builtin_maps_decode_from_memory() {
    let entries = builtin_entries();
    let names: Vec<&str> = entries.iter().map(|e| e.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "city",
            "courtyard",
            "forest",
            "interior",
            "night",
            "studio",
            "sunrise",
            "sunset"
        ]
    );
    let mut keys = Vec::new();
    for e in &entries {
        let map = e.load().unwrap();
        assert!(map.width() > 0 && map.height() > 0, "{}", e.name);
        assert_eq!(map.width(), 2 * map.height(), "{}", e.name);
        assert!(
            map.texels().iter().flatten().all(|v| v.is_finite()),
            "{}",
            e.name
        );
        let stats = map.stats();
        assert!(
            stats.mean_luminance > 1e-3,
            "{} is black: {stats:?}",
            e.name
        );
        keys.push(e.content_key().unwrap());
    }
    keys.sort();
    keys.dedup();
    assert_eq!(keys.len(), 8, "eight distinct contents");
}

#[test]
fn procedural_parameters_are_seeded_per_index() {
    // The same (seed, index) gives the same parameters; other indices and seeds differ.
    for i in 0..16 {
        assert_eq!(random_sky(7, i), random_sky(7, i));
        assert_eq!(random_studio(7, i), random_studio(7, i));
        assert_ne!(random_sky(7, i), random_sky(8, i));
        for j in 0..i {
            assert_ne!(random_sky(7, i), random_sky(7, j), "skies {i} {j}");
            assert_ne!(random_overcast(7, i), random_overcast(7, j));
            assert_ne!(random_studio(7, i), random_studio(7, j));
        }
    }
    // Entry i of a kind does not depend on how many entries there are.
    let few = HdriCollection::from_config(&procedural_only(3, 1, 2)).unwrap();
    let many = HdriCollection::from_config(&procedural_only(8, 1, 5)).unwrap();
    assert_eq!(few.entries()[..3], many.entries()[..3]);
    assert_eq!(few.entries()[4], many.entries()[9]);
    let names: Vec<&str> = few.entries().iter().map(|e| e.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "sky-00",
            "sky-01",
            "sky-02",
            "overcast-00",
            "studio-00",
            "studio-01"
        ]
    );
    // Content keys follow the parameters and the height.
    let key = |c: &HdriCollection, i: usize| c.entries()[i].content_key().unwrap();
    assert_eq!(key(&few, 0), key(&many, 0));
    assert_ne!(key(&few, 0), key(&few, 1));
    let taller = HdriCollection::from_config(&HdriCollectionConfig {
        procedural_height: 128,
        ..procedural_only(3, 1, 2)
    })
    .unwrap();
    assert_ne!(key(&few, 0), key(&taller, 0));
}

#[test]
fn procedural_parameters_stay_in_their_ranges_and_render() {
    let mut light_counts = [0usize; 4];
    for i in 0..200 {
        let s = random_sky(3, i);
        assert!((0.05..1.23).contains(&s.elevation), "{s:?}");
        assert!((0.0..TAU).contains(&s.azimuth), "{s:?}");
        assert!((2.0..=8.0).contains(&s.turbidity), "{s:?}");
        assert!((2.0..=8.0).contains(&s.sun_irradiance), "{s:?}");
        let Procedural::Studio { lights } = random_studio(3, i) else {
            unreachable!()
        };
        light_counts[lights.len()] += 1;
        for (k, l) in lights.iter().enumerate() {
            // Key and fill in front of the face (+z), the rim behind it.
            assert_eq!(l.direction[2] > 0.0, k < 2, "studio {i} light {k}: {l:?}");
            assert!((0.1..0.35).contains(&l.radius), "{l:?}");
            assert!(l.irradiance.iter().all(|e| *e > 0.0 && *e <= 8.0), "{l:?}");
        }
        // The key is the brightest light.
        assert!(
            lights
                .iter()
                .all(|l| l.irradiance[1] <= lights[0].irradiance[1])
        );
    }
    assert_eq!(light_counts[0], 0);
    assert!(
        light_counts[1..].iter().all(|&c| c > 40),
        "{light_counts:?}"
    );
    for entry in HdriCollection::from_config(&procedural_only(2, 2, 2))
        .unwrap()
        .entries()
    {
        let map = entry.load().unwrap();
        assert_eq!(map.height(), 64);
        assert!(map.stats().mean_luminance > 0.0, "{} is black", entry.name);
    }
}

#[test]
fn a_studio_is_brighter_on_its_lights_side() {
    let options = PreconvolveOptions::default();
    for i in 0..6 {
        let environment = random_studio(0, i);
        let Procedural::Studio { lights } = &environment else {
            unreachable!()
        };
        let set = preconvolve(&environment.render(128).unwrap(), &options).unwrap();
        let lum = |c: [f32; 3]| f64::from(c[0] + c[1] + c[2]);
        let key: Dir = direction::normalize(lights[0].direction);
        for map in set.maps() {
            let towards = lum(map.lookup(key));
            let away = lum(map.lookup(key.map(|c| -c)));
            assert!(
                towards > 2.0 * away,
                "studio {i} n={}: {towards} towards the key light, {away} away",
                map.exponent()
            );
        }
        // Every light stands out in the glossiest map, where it is.
        let glossy = set.maps().last().unwrap();
        let mean =
            glossy.texels().iter().map(|c| lum(*c)).sum::<f64>() / glossy.texels().len() as f64;
        for (k, l) in lights.iter().enumerate() {
            let at = lum(glossy.lookup(l.direction));
            assert!(at > 3.0 * mean, "studio {i} light {k}: {at} vs mean {mean}");
        }
    }
}

#[test]
fn config_parses_from_toml_and_rejects_unknown_keys() {
    let c: HdriCollectionConfig = toml::from_str("").unwrap();
    assert_eq!(c, HdriCollectionConfig::default());
    let c: HdriCollectionConfig =
        toml::from_str("builtin = false\nskies = 2\nfolders = [\"maps\"]\nseed = 9").unwrap();
    assert_eq!(
        c,
        HdriCollectionConfig {
            builtin: false,
            skies: 2,
            folders: vec![PathBuf::from("maps")],
            seed: 9,
            ..HdriCollectionConfig::default()
        }
    );
    let e = toml::from_str::<HdriCollectionConfig>("skys = 3").unwrap_err();
    assert!(e.to_string().contains("skys"), "{e}");
}

#[test]
fn invalid_and_empty_configs_are_errors_naming_the_problem() {
    let e = HdriCollection::from_config(&procedural_only(0, 0, 0)).unwrap_err();
    assert!(matches!(e, HdriError::EmptyCollection), "{e}");
    let e = HdriCollection::from_config(&HdriCollectionConfig {
        procedural_height: 3,
        ..HdriCollectionConfig::default()
    })
    .unwrap_err();
    assert!(e.to_string().contains("procedural_height") && e.to_string().contains('3'));
    let e = HdriCollection::from_config(&HdriCollectionConfig {
        studios: MAX_PROCEDURAL_COUNT + 1,
        ..HdriCollectionConfig::default()
    })
    .unwrap_err();
    assert!(e.to_string().contains("studios"), "{e}");
}

#[test]
fn folders_list_their_maps_sorted_and_skip_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    let folder = dir.path().join("my_maps");
    fs::create_dir(&folder).unwrap();
    write_map(&folder.join("b.exr"), 1.0);
    write_map(&folder.join("A.EXR"), 2.0);
    write_map(&folder.join(".hidden.exr"), 3.0);
    fs::write(folder.join("notes.txt"), "not a map").unwrap();
    fs::create_dir(folder.join("sub.exr")).unwrap();
    let entries = folder_entries(&folder).unwrap();
    let names: Vec<&str> = entries.iter().map(|e| e.name.as_str()).collect();
    assert_eq!(names, ["my_maps/A.EXR", "my_maps/b.exr"]);
    assert_eq!(entries[1].load().unwrap().texel(0, 0)[0], 1.0);
    let collection = HdriCollection::from_config(&HdriCollectionConfig {
        folders: vec![folder.clone()],
        ..procedural_only(1, 0, 0)
    })
    .unwrap();
    assert_eq!(collection.len(), 3);
    assert_eq!(collection.entries()[2].name, "my_maps/b.exr");
}

#[test]
fn empty_missing_and_unreadable_folders_and_files_are_errors_naming_them() {
    let dir = tempfile::tempdir().unwrap();
    let empty = dir.path().join("empty_maps");
    fs::create_dir(&empty).unwrap();
    fs::write(empty.join("readme.md"), "no maps").unwrap();
    let e = HdriCollection::from_config(&HdriCollectionConfig {
        folders: vec![empty.clone()],
        ..HdriCollectionConfig::default()
    })
    .unwrap_err();
    assert!(matches!(e, HdriError::EmptyFolder { .. }), "{e}");
    assert!(e.to_string().contains("empty_maps"), "{e}");
    let e = folder_entries(&dir.path().join("no_such_folder")).unwrap_err();
    assert!(
        matches!(e, HdriError::ReadFolder { .. }) && e.to_string().contains("no_such_folder"),
        "{e}"
    );
    // A file that is not a decodable map, and one gone since the folder was listed.
    let bad = dir.path().join("bad");
    fs::create_dir(&bad).unwrap();
    fs::write(bad.join("broken.exr"), b"not an exr").unwrap();
    write_map(&bad.join("gone.exr"), 1.0);
    let entries = folder_entries(&bad).unwrap();
    let e = entries[0].load().unwrap_err();
    assert!(e.to_string().contains("broken.exr"), "{e}");
    fs::remove_file(bad.join("gone.exr")).unwrap();
    let e = entries[1].content_key().unwrap_err();
    assert!(
        matches!(e, HdriError::ReadFile { .. }) && e.to_string().contains("gone.exr"),
        "{e}"
    );
}

#[test]
fn one_changed_byte_of_a_file_changes_its_key() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.exr");
    write_map(&path, 1.0);
    let entry = HdriEntry {
        name: "m".into(),
        source: HdriSource::File(path.clone()),
    };
    let before = entry.content_key().unwrap();
    assert_eq!(before, entry.content_key().unwrap());
    let mut bytes = fs::read(&path).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 0x01;
    fs::write(&path, &bytes).unwrap();
    assert_ne!(before, entry.content_key().unwrap());
}

fn kinds(collection: &HdriCollection) -> [usize; 4] {
    let mut counts = [0; 4];
    for e in collection.entries() {
        let k = match &e.source {
            HdriSource::Builtin(_) => 0,
            HdriSource::Procedural {
                environment: Procedural::SunSky(_),
                ..
            } => 1,
            HdriSource::Procedural {
                environment: Procedural::Overcast { .. },
                ..
            } => 2,
            HdriSource::Procedural {
                environment: Procedural::Studio { .. },
                ..
            } => 3,
            HdriSource::File(_) => panic!("no folders here"),
        };
        counts[k] += 1;
    }
    counts
}

#[test]
fn hundreds_of_procedural_environments_come_in_the_asked_kinds_and_are_all_distinct() {
    let config: HdriCollectionConfig =
        toml::from_str("skies = 250\novercast = 50\nstudios = 100\nseed = 4").unwrap();
    let collection = HdriCollection::from_config(&config).unwrap();
    assert_eq!(collection.len(), 408);
    assert_eq!(kinds(&collection), [8, 250, 50, 100]);
    let without: HdriCollectionConfig =
        toml::from_str("builtin = false\nskies = 0\novercast = 3\nstudios = 400").unwrap();
    assert_eq!(
        kinds(&HdriCollection::from_config(&without).unwrap()),
        [0, 0, 3, 400]
    );
    // Distinct names and distinct contents (so distinct light maps and cache files).
    let names: std::collections::BTreeSet<&str> = collection
        .entries()
        .iter()
        .map(|e| e.name.as_str())
        .collect();
    assert_eq!(names.len(), 408);
    assert!(names.contains("sky-249") && names.contains("studio-99"));
    let keys: std::collections::BTreeSet<ContentKey> = collection
        .entries()
        .iter()
        .map(|e| e.content_key().unwrap())
        .collect();
    assert_eq!(keys.len(), 408, "every environment has its own content");
    // Another seed gives other procedural environments (the built-in maps stay).
    let other = HdriCollection::from_config(&HdriCollectionConfig {
        seed: 5,
        ..config.clone()
    })
    .unwrap();
    let shared = other
        .entries()
        .iter()
        .filter(|e| keys.contains(&e.content_key().unwrap()))
        .count();
    assert_eq!(shared, 8);
}

#[test]
fn parameter_ranges_are_honoured_and_the_default_ranges_draw_as_before() {
    // Written out, the defaults are the defaults, and draw what the plain functions draw.
    let written: HdriCollectionConfig = toml::from_str(
        "[ranges.sky]\nelevation = [3.0, 70.0]\nturbidity = [2.0, 8.0]\nirradiance = [2.0, 8.0]\n\
         [ranges.overcast]\nzenith = [0.6, 2.5]\n\
         [ranges.studio]\nlights = [1, 3]\nkey_irradiance = [2.0, 8.0]\nradius = [6.0, 20.0]\n",
    )
    .unwrap();
    assert_eq!(written, HdriCollectionConfig::default());
    // The parameters of seeds 0 and 7, indices 0-39 of each kind, as the code before
    // configurable ranges drew them: SHA-256 of their canonical texts at 256 rows. So every
    // content key, light-map cache file and example-cache fingerprint stays valid.
    let mut text = String::new();
    for seed in [0u64, 7] {
        for i in 0..40 {
            text.push_str(&Procedural::SunSky(random_sky(seed, i)).canonical_text(256));
            text.push_str(&random_overcast(seed, i).canonical_text(256));
            text.push_str(&random_studio(seed, i).canonical_text(256));
        }
    }
    assert_eq!(
        ContentKey::of(text.as_bytes()).to_hex(),
        "1fa342894913c5453b0cf5c51d75c424d11a7b042fbd7305aaa255e09c497662"
    );
    let r = ProceduralRanges::default();
    for i in 0..50 {
        assert_eq!(random_sky_in(&r.sky, 7, i), random_sky(7, i));
        assert_eq!(random_overcast_in(&r.overcast, 7, i), random_overcast(7, i));
        assert_eq!(random_studio_in(&r.studio, 7, i), random_studio(7, i));
    }
    let config: HdriCollectionConfig = toml::from_str(
        "builtin = false\nskies = 60\novercast = 60\nstudios = 60\nprocedural_height = 16\n\
         [ranges.sky]\nelevation = [40.0, 50.0]\nturbidity = [3.0, 3.5]\nirradiance = [20.0, 40.0]\nsun_radius = [1.0, 2.0]\n\
         [ranges.overcast]\nzenith = [5.0, 6.0]\n\
         [ranges.studio]\nlights = [2, 2]\nkey_irradiance = [0.5, 1.0]\nradius = [30.0, 31.0]\n",
    )
    .unwrap();
    let collection = HdriCollection::from_config(&config).unwrap();
    for e in collection.entries() {
        let HdriSource::Procedural { environment, .. } = &e.source else {
            unreachable!()
        };
        match environment {
            Procedural::SunSky(s) => {
                let degrees = s.elevation.to_degrees();
                assert!((40.0..=50.0).contains(&degrees), "{s:?}");
                assert!((3.0..=3.5).contains(&s.turbidity), "{s:?}");
                assert!((20.0..=40.0).contains(&s.sun_irradiance), "{s:?}");
                assert!((1.0..=2.0).contains(&s.sun_radius.to_degrees()), "{s:?}");
            }
            Procedural::Overcast { zenith } => assert!((5.0..=6.0).contains(zenith)),
            Procedural::Studio { lights } => {
                assert_eq!(lights.len(), 2);
                for l in lights {
                    assert!((30.0..=31.0).contains(&l.radius.to_degrees()), "{l:?}");
                    assert!(l.irradiance.iter().all(|e| *e <= 1.0), "{l:?}");
                }
            }
        }
    }
    // Narrow ranges are used, not just respected: the draws spread over them.
    let elevations: Vec<f64> = collection.entries()[..60]
        .iter()
        .map(|e| match &e.source {
            HdriSource::Procedural {
                environment: Procedural::SunSky(s),
                ..
            } => s.elevation.to_degrees(),
            _ => unreachable!(),
        })
        .collect();
    let lo = elevations.iter().cloned().fold(f64::INFINITY, f64::min);
    let hi = elevations.iter().cloned().fold(0.0, f64::max);
    assert!(lo < 42.0 && hi > 48.0, "{lo} {hi}");
    // One light, three lights.
    for n in [1usize, 3] {
        let c = HdriCollectionConfig {
            ranges: ProceduralRanges {
                studio: StudioRanges {
                    lights: [n, n],
                    ..StudioRanges::default()
                },
                ..ProceduralRanges::default()
            },
            ..procedural_only(0, 0, 20)
        };
        for e in HdriCollection::from_config(&c).unwrap().entries() {
            let HdriSource::Procedural {
                environment: Procedural::Studio { lights },
                ..
            } = &e.source
            else {
                unreachable!()
            };
            assert_eq!(lights.len(), n);
        }
    }
}

#[test]
fn bad_ranges_and_unknown_range_keys_are_errors_naming_the_key() {
    let cases = [
        (
            "[ranges.sky]\nelevation = [70.0, 3.0]",
            "ranges.sky.elevation",
        ),
        (
            "[ranges.sky]\nelevation = [3.0, 100.0]",
            "ranges.sky.elevation",
        ),
        (
            "[ranges.sky]\nturbidity = [0.0, 5.0]",
            "ranges.sky.turbidity",
        ),
        (
            "[ranges.sky]\nirradiance = [nan, 5.0]",
            "ranges.sky.irradiance",
        ),
        (
            "[ranges.sky]\nsun_radius = [0.0, 1.0]",
            "ranges.sky.sun_radius",
        ),
        (
            "[ranges.overcast]\nzenith = [-1.0, 2.0]",
            "ranges.overcast.zenith",
        ),
        ("[ranges.studio]\nlights = [0, 2]", "ranges.studio.lights"),
        ("[ranges.studio]\nlights = [2, 4]", "ranges.studio.lights"),
        (
            "[ranges.studio]\nkey_irradiance = [inf, inf]",
            "ranges.studio.key_irradiance",
        ),
        (
            "[ranges.studio]\nradius = [10.0, 90.0]",
            "ranges.studio.radius",
        ),
    ];
    for (text, key) in cases {
        let config: HdriCollectionConfig = toml::from_str(text).unwrap();
        let e = HdriCollection::from_config(&config).unwrap_err();
        assert!(
            matches!(e, HdriError::Config { .. }) && e.to_string().contains(key),
            "{text}: {e}"
        );
    }
    for (text, key) in [
        ("[ranges.sky]\nelevations = [3.0, 70.0]", "elevations"),
        ("[ranges.skies]\nelevation = [3.0, 70.0]", "skies"),
        ("[ranges.studio]\nlights = [1.5, 2.0]", "lights"),
    ] {
        let e = toml::from_str::<HdriCollectionConfig>(text).unwrap_err();
        assert!(e.to_string().contains(key), "{text}: {e}");
    }
}

#[test]
fn extra_folders_join_the_shipped_maps_or_replace_them() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("poly_haven"), dir.path().join("mine"));
    for (folder, files) in [(&a, ["x.exr", "w.exr"]), (&b, ["v.exr", "u.exr"])] {
        fs::create_dir(folder).unwrap();
        for (k, f) in files.iter().enumerate() {
            write_map(&folder.join(f), 1.0 + k as f32);
        }
    }
    let names = |c: &HdriCollection| -> Vec<String> {
        c.entries().iter().map(|e| e.name.clone()).collect()
    };
    // In addition to the defaults: the shipped and procedural maps first, then each folder
    // in the order given, its files sorted.
    let with = HdriCollection::from_config(&HdriCollectionConfig {
        folders: vec![a.clone(), b.clone()],
        ..HdriCollectionConfig::default()
    })
    .unwrap();
    assert_eq!(with.len(), 28);
    assert_eq!(
        names(&with)[24..],
        [
            "poly_haven/w.exr",
            "poly_haven/x.exr",
            "mine/u.exr",
            "mine/v.exr"
        ]
    );
    assert_eq!(names(&with)[0], "city");
    // Instead of them.
    let only: HdriCollectionConfig = toml::from_str(&format!(
        "builtin = false\nskies = 0\novercast = 0\nstudios = 0\nfolders = [{:?}]",
        a.display().to_string()
    ))
    .unwrap();
    let only = HdriCollection::from_config(&only).unwrap();
    assert_eq!(names(&only), ["poly_haven/w.exr", "poly_haven/x.exr"]);
    for e in only.entries() {
        assert!(e.load().unwrap().stats().mean_luminance > 0.0, "{}", e.name);
    }
}

#[test]
fn lighting_in_a_data_config_names_the_file_and_key_and_takes_folders_relative_to_it() {
    use crate::dataset::DataConfig;
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("run.toml");
    let load = |lighting: &str| {
        fs::write(
            &file,
            format!("[data]\nseed = 1\n[data.lighting]\n{lighting}\n"),
        )
        .unwrap();
        DataConfig::load(&file).map(|(c, _)| c)
    };
    let c = load("folders = [\"hdris/poly_haven\"]\nskies = 300").unwrap();
    assert_eq!(c.lighting.folders, [dir.path().join("hdris/poly_haven")]);
    assert_eq!(c.lighting.skies, 300);
    for (text, key) in [
        ("skies = 20000", "skies"),
        ("procedural_height = 4", "procedural_height"),
        (
            "[data.lighting.ranges.studio]\nlights = [0, 2]",
            "ranges.studio.lights",
        ),
        (
            "[data.lighting.ranges.overcast]\nzeniths = [1.0, 2.0]",
            "zeniths",
        ),
    ] {
        let e = volux_envmap::error::chain(&load(text).unwrap_err());
        assert!(e.contains("run.toml") && e.contains(key), "{text}: {e}");
    }
}
