use std::fs;
use std::path::PathBuf;

use volux_envmap::{EnvMap, LightMap, io};

use super::*;
use crate::hdri_collection::{HdriCollectionConfig, HdriSource};
use crate::light_map_cache;

fn small_collection() -> HdriCollection {
    HdriCollection::from_config(&HdriCollectionConfig {
        builtin: false,
        skies: 2,
        overcast: 1,
        studios: 1,
        procedural_height: 64,
        ..HdriCollectionConfig::default()
    })
    .unwrap()
}

fn cache_files(dir: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    files
}

fn bits(set: &LightMapSet) -> Vec<u32> {
    set.maps()
        .iter()
        .flat_map(LightMap::texels)
        .flatten()
        .map(|v| v.to_bits())
        .collect()
}

fn assert_bit_identical(a: &LightMapBank, b: &LightMapBank) {
    assert_eq!(a.len(), b.len());
    for i in 0..a.len() {
        assert_eq!(a.get(i), b.get(i), "{}", a.name(i));
        assert_eq!(bits(a.get(i)), bits(b.get(i)), "{}", a.name(i));
    }
}

/// Also the measurement of docs/data-hdri.md: run with `--nocapture` to see the times.
#[test]
fn default_collection_cold_then_warm_is_all_hits_and_bit_identical() {
    let dir = tempfile::tempdir().unwrap();
    let collection = HdriCollection::from_config(&HdriCollectionConfig::default()).unwrap();
    let options = PreconvolveOptions::default();
    let t = Instant::now();
    let cold = LightMapBank::build(&collection, &options, Some(dir.path())).unwrap();
    let cold_s = t.elapsed().as_secs_f64();
    let n = collection.len();
    assert_eq!(
        cold.stats(),
        CacheStats {
            hits: 0,
            misses: n,
            write_failures: 0
        }
    );
    let t = Instant::now();
    let warm = LightMapBank::build(&collection, &options, Some(dir.path())).unwrap();
    let warm_s = t.elapsed().as_secs_f64();
    assert_eq!(
        warm.stats(),
        CacheStats {
            hits: n,
            misses: 0,
            write_failures: 0
        }
    );
    assert_bit_identical(&cold, &warm);
    let files = cache_files(dir.path());
    assert_eq!(
        files.len(),
        n,
        "one file per entry, no temporary files left"
    );
    let sizes: Vec<u64> = files
        .iter()
        .map(|f| fs::metadata(f).unwrap().len())
        .collect();
    let t = Instant::now();
    let uncached = LightMapBank::build(&collection, &options, None).unwrap();
    let uncached_s = t.elapsed().as_secs_f64();
    assert_eq!(uncached.stats().misses, n);
    assert_bit_identical(&cold, &uncached);
    println!(
        "default collection ({n} HDRIs, {} rayon threads): cold {cold_s:.2} s, warm {warm_s:.2} s, \
         no cache {uncached_s:.2} s; cache files {}..{} bytes, {:.1} MB in all; light maps {:?}",
        rayon::current_num_threads(),
        sizes.iter().min().unwrap(),
        sizes.iter().max().unwrap(),
        sizes.iter().sum::<u64>() as f64 / 1e6,
        cold.get(0)
            .maps()
            .iter()
            .map(|m| (m.exponent(), m.width(), m.height()))
            .collect::<Vec<_>>()
    );
}

#[test]
fn changed_exponents_tolerance_or_taper_miss_the_cache() {
    let dir = tempfile::tempdir().unwrap();
    let collection = small_collection();
    let n = collection.len();
    let base = PreconvolveOptions::default();
    LightMapBank::build(&collection, &base, Some(dir.path())).unwrap();
    let variants = [
        PreconvolveOptions::with_exponents(&[1, 16, 32]),
        PreconvolveOptions {
            tolerance: 5e-3,
            ..base.clone()
        },
        PreconvolveOptions {
            taper: 0.25,
            ..base.clone()
        },
    ];
    for (k, options) in variants.iter().enumerate() {
        let bank = LightMapBank::build(&collection, options, Some(dir.path())).unwrap();
        assert_eq!(bank.stats().misses, n, "{options:?}");
        assert_eq!(bank.get(0).exponents(), options.exponents);
        assert_eq!(cache_files(dir.path()).len(), n * (k + 2));
    }
    // Each earlier set is still there.
    let again = LightMapBank::build(&collection, &base, Some(dir.path())).unwrap();
    assert_eq!(again.stats().hits, n);
}

#[test]
fn a_changed_user_file_misses_and_a_renamed_one_hits() {
    let dir = tempfile::tempdir().unwrap();
    let maps = dir.path().join("maps");
    fs::create_dir(&maps).unwrap();
    let cache = dir.path().join("cache");
    let write = |name: &str, corner: f32| {
        let mut map = EnvMap::from_fn(16, |d| [1.0, (1.0 + d[1]) as f32, 0.5]).unwrap();
        map.set_texel(3, 2, [corner, 0.0, 0.0]);
        io::save_envmap_exr(&maps.join(name), &map).unwrap();
    };
    write("a.exr", 1.0);
    let config = HdriCollectionConfig {
        builtin: false,
        skies: 0,
        overcast: 0,
        studios: 0,
        folders: vec![maps.clone()],
        ..HdriCollectionConfig::default()
    };
    let build = || {
        let collection = HdriCollection::from_config(&config).unwrap();
        LightMapBank::build(&collection, &PreconvolveOptions::default(), Some(&cache)).unwrap()
    };
    let first = build();
    assert_eq!(first.stats().misses, 1);
    assert_eq!(build().stats().hits, 1);
    // One texel changed: new content, new key, new light maps.
    write("a.exr", 50.0);
    let changed = build();
    assert_eq!(changed.stats().misses, 1);
    assert_ne!(changed.key(0), first.key(0));
    assert_ne!(changed.get(0), first.get(0));
    // The name is not part of the key.
    fs::rename(maps.join("a.exr"), maps.join("renamed.exr")).unwrap();
    let renamed = build();
    assert_eq!(renamed.name(0), "maps/renamed.exr");
    assert_eq!(renamed.stats().hits, 1);
    assert_eq!(renamed.key(0), changed.key(0));
}

#[test]
fn truncated_and_garbage_cache_files_are_recomputed_and_rewritten() {
    let dir = tempfile::tempdir().unwrap();
    let collection = small_collection();
    let options = PreconvolveOptions::default();
    let first = LightMapBank::build(&collection, &options, Some(dir.path())).unwrap();
    let cache = LightMapCache::open(dir.path()).unwrap();
    let (truncated, garbage) = (cache.path(first.key(0)), cache.path(first.key(1)));
    let bytes = fs::read(&truncated).unwrap();
    fs::write(&truncated, &bytes[..bytes.len() / 3]).unwrap();
    fs::write(&garbage, vec![0xA5; bytes.len()]).unwrap();
    let second = LightMapBank::build(&collection, &options, Some(dir.path())).unwrap();
    assert_eq!(
        second.stats(),
        CacheStats {
            hits: collection.len() - 2,
            misses: 2,
            write_failures: 0
        }
    );
    assert_bit_identical(&first, &second);
    // Both files are valid again.
    for (i, path) in [(0, &truncated), (1, &garbage)] {
        let set =
            light_map_cache::decode(&fs::read(path).unwrap(), first.key(i), &options.exponents)
                .unwrap();
        assert_eq!(&set, first.get(i));
    }
    assert_eq!(
        LightMapBank::build(&collection, &options, Some(dir.path()))
            .unwrap()
            .stats()
            .hits,
        collection.len()
    );
}

#[test]
fn cache_dir_missing_is_created_and_unusable_is_an_error_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let collection = small_collection();
    let options = PreconvolveOptions::default();
    let nested = dir.path().join("a/b/light_cache");
    let bank = LightMapBank::build(&collection, &options, Some(&nested)).unwrap();
    assert_eq!(bank.stats().misses, collection.len());
    assert_eq!(cache_files(&nested).len(), collection.len());
    // A file where the directory should be, or above it.
    let file = dir.path().join("plain_file");
    fs::write(&file, "x").unwrap();
    for bad in [file.clone(), file.join("cache")] {
        let e = LightMapBank::build(&collection, &options, Some(&bad)).unwrap_err();
        assert!(
            matches!(e, LightMapBankError::Cache(_)) && e.to_string().contains("plain_file"),
            "{e}"
        );
    }
}

#[test]
fn unwritable_cache_files_are_counted_and_the_bank_is_built() {
    // A directory in the place of a cache file makes both its read and its write fail,
    // whoever runs the test (permissions do not stop root).
    let dir = tempfile::tempdir().unwrap();
    let collection = small_collection();
    let options = PreconvolveOptions::default();
    let reference = LightMapBank::build(&collection, &options, None).unwrap();
    let cache = LightMapCache::open(dir.path()).unwrap();
    let blocked = cache.path(reference.key(2));
    fs::create_dir(&blocked).unwrap();
    fs::write(blocked.join("keep"), "x").unwrap();
    let bank = LightMapBank::build(&collection, &options, Some(dir.path())).unwrap();
    assert_eq!(
        bank.stats(),
        CacheStats {
            hits: 0,
            misses: collection.len(),
            write_failures: 1
        }
    );
    assert_bit_identical(&reference, &bank);
}

#[test]
fn a_bad_map_or_bad_options_are_errors_naming_them() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("broken.exr");
    fs::write(&path, b"definitely not OpenEXR").unwrap();
    let collection = HdriCollection::new(vec![HdriEntry {
        name: "broken".into(),
        source: HdriSource::File(path),
    }])
    .unwrap();
    let e = LightMapBank::build(&collection, &PreconvolveOptions::default(), None).unwrap_err();
    // The chain names the entry, then the file: each once.
    let text = volux_envmap::error::chain(&e);
    assert_eq!(text.matches("broken.exr").count(), 1, "{text}");
    assert!(
        text.contains("`broken`") && text.contains("broken.exr"),
        "{text}"
    );
    let e = LightMapBank::build(
        &small_collection(),
        &PreconvolveOptions::with_exponents(&[]),
        None,
    )
    .unwrap_err();
    assert!(matches!(e, LightMapBankError::Options(_)), "{e}");
}

#[test]
fn the_maps_are_shared_not_copied() {
    let bank =
        LightMapBank::build(&small_collection(), &PreconvolveOptions::default(), None).unwrap();
    let (a, b) = (bank.shared(), bank.shared());
    assert!(Arc::ptr_eq(&a, &b));
    assert_eq!(a.as_ptr(), bank.sets().as_ptr());
    // 192x96 + 256x128 + 384x192 + 512x256 RGB f32 texels per environment.
    assert_eq!(bank.texel_bytes(), 4 * 256_000 * 12);
}

/// The start-up cost of a run that draws from hundreds of environments (docs/data-hdri.md):
/// `cargo test -p volux-data --lib many_environments -- --ignored --nocapture`
/// (`VOLUX_ENVIRONMENTS` sets how many; the default is 400, 1.2 GB of cache files).
#[test]
#[ignore = "a measurement: tens of seconds and a gigabyte of temporary files"]
fn many_environments_start_up_time_and_memory() {
    let n: usize = std::env::var("VOLUX_ENVIRONMENTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(400);
    let config = HdriCollectionConfig {
        builtin: false,
        skies: n / 2,
        overcast: n / 8,
        studios: n - n / 2 - n / 8,
        ..HdriCollectionConfig::default()
    };
    let collection = HdriCollection::from_config(&config).unwrap();
    let options = PreconvolveOptions::default();
    let dir = tempfile::tempdir().unwrap();
    let status = |key: &str| -> f64 {
        let text = fs::read_to_string("/proc/self/status").unwrap_or_default();
        text.lines()
            .find(|l| l.starts_with(key))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|kb| kb.parse::<f64>().ok())
            .map_or(f64::NAN, |kb| kb / 1024.0 / 1024.0)
    };
    let before = status("VmRSS:");
    let t = Instant::now();
    let cold = LightMapBank::build(&collection, &options, Some(dir.path())).unwrap();
    let cold_s = t.elapsed().as_secs_f64();
    let cold_peak = status("VmHWM:");
    assert_eq!(cold.stats().misses, n);
    let held = cold.texel_bytes() as f64 / (1u64 << 30) as f64;
    drop(cold);
    let t = Instant::now();
    let warm = LightMapBank::build(&collection, &options, Some(dir.path())).unwrap();
    let warm_s = t.elapsed().as_secs_f64();
    assert_eq!(warm.stats().hits, n);
    let after = status("VmRSS:");
    let disk: u64 = cache_files(dir.path())
        .iter()
        .map(|f| fs::metadata(f).unwrap().len())
        .sum();
    println!(
        "{n} procedural environments at {} rows, tolerance {}, {} rayon threads: \
         cold {cold_s:.1} s, warm {warm_s:.1} s; light maps held {held:.2} GiB; \
         resident {before:.2} GiB before, {after:.2} GiB after the warm build, \
         peak {cold_peak:.2} GiB during the cold one; cache {:.2} GB on disk",
        config.procedural_height,
        options.tolerance,
        rayon::current_num_threads(),
        disk as f64 / 1e9
    );
}
