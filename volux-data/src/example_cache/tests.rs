use super::*;
use crate::dataset::DataConfig;
use std::cell::Cell;
use std::sync::Arc;
use volux_envmap::{EnvMap, PreconvolveOptions, preconvolve};

fn dataset(seed: u64) -> Dataset {
    let lights = Arc::new(vec![
        preconvolve(
            &EnvMap::constant(16, [0.8; 3]).unwrap(),
            &PreconvolveOptions::default(),
        )
        .unwrap(),
    ]);
    let text = format!("seed = {seed}\nresolution = 8\nvolume_resolution = 4");
    let config: DataConfig = toml::from_str(&text).unwrap();
    Dataset::new(&config, lights).unwrap()
}

#[test]
fn a_shard_changed_after_the_build_is_refused_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let data = dataset(2);
    let spec = CacheSpec {
        examples: 4,
        shard_size: 2,
    };
    build(dir.path(), &data, "fp", spec, &|_, _| {}).unwrap();
    // One flipped byte in shard 1's data: the size is right, so opening succeeds.
    let shard = dir.path().join(shard_name(1));
    let mut bytes = fs::read(&shard).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 0x40;
    fs::write(&shard, bytes).unwrap();
    let cache = ExampleCache::open(dir.path()).unwrap();
    assert!(cache.example(0).is_ok(), "shard 0 is intact");
    let e = cache.example(3).unwrap_err().to_string();
    assert!(
        e.contains("shard-00001.bin") && e.contains("SHA-256") && e.contains("volux data build"),
        "{e}"
    );
    // A rebuild repairs it.
    build(dir.path(), &data, "fp", spec, &|_, _| {}).unwrap();
    assert!(ExampleCache::open(dir.path()).unwrap().example(3).is_ok());
}

#[test]
fn a_built_cache_returns_the_datasets_examples() {
    let dir = tempfile::tempdir().unwrap();
    let data = dataset(1);
    let spec = CacheSpec {
        examples: 5,
        shard_size: 2,
    };
    let calls = Cell::new(0);
    let report = build(dir.path(), &data, "fp", spec, &|_, total| {
        assert_eq!(total, 3);
        calls.set(calls.get() + 1);
    })
    .unwrap();
    assert_eq!((report.shards, report.built, report.kept), (3, 3, 0));
    assert_eq!(calls.get(), 3);
    let cache = ExampleCache::open(dir.path()).unwrap();
    for i in 0..5 {
        let (cached, live) = (cache.example(i).unwrap(), data.example(i).unwrap());
        // Poses and yaws are stored as f32.
        assert!((cached.pose.yaw - live.pose.yaw).abs() < 1e-6);
        assert!((cached.draw.yaw - live.draw.yaw).abs() < 1e-6);
        assert_eq!(cached.draw.map, live.draw.map);
        assert_eq!(cached.layers, live.layers);
    }
    assert!(matches!(
        cache.example(5),
        Err(CacheError::OutOfRange { index: 5, len: 5 })
    ));
    // Batches wrap around: batch 2 of 2 is examples 4, 0.
    let batch = cache.batch(2, 2).unwrap();
    let want = [cache.example(4).unwrap(), cache.example(0).unwrap()];
    assert_eq!(batch, Batch::collate(2, &want));
}

#[test]
fn reruns_redo_only_what_changed_and_interrupted_builds_resume() {
    let dir = tempfile::tempdir().unwrap();
    let data = dataset(1);
    let spec = |examples| CacheSpec {
        examples,
        shard_size: 2,
    };
    let quiet = &|_: usize, _: usize| {};
    build(dir.path(), &data, "fp", spec(4), quiet).unwrap();
    // The same again: nothing to do.
    let again = build(dir.path(), &data, "fp", spec(4), quiet).unwrap();
    assert_eq!((again.built, again.kept), (0, 2));
    // More examples: only the new shard (and the short last one, if it changed size).
    let more = build(dir.path(), &data, "fp", spec(6), quiet).unwrap();
    assert_eq!((more.built, more.kept), (1, 2));
    // An interrupted build: one shard lost, one corrupted; both are remade.
    fs::remove_file(dir.path().join(shard_name(0))).unwrap();
    fs::write(dir.path().join(shard_name(2)), b"garbage").unwrap();
    assert!(ExampleCache::open(dir.path()).is_err());
    let resumed = build(dir.path(), &data, "fp", spec(6), quiet).unwrap();
    assert_eq!((resumed.built, resumed.kept), (2, 1));
    let cache = ExampleCache::open(dir.path()).unwrap();
    assert_eq!(
        cache.example(4).unwrap().layers.photo,
        data.example(4).unwrap().layers.photo
    );
    // A different dataset (fingerprint): everything is rebuilt.
    let other = dataset(2);
    let changed = build(dir.path(), &other, "fp2", spec(6), quiet).unwrap();
    assert_eq!((changed.built, changed.kept), (3, 0));
    let cache = ExampleCache::open(dir.path()).unwrap();
    assert_eq!(
        cache.example(1).unwrap().layers.photo,
        other.example(1).unwrap().layers.photo
    );
    // No temporary files are left behind.
    let stray = fs::read_dir(dir.path())
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .file_name()
                .to_string_lossy()
                .starts_with(".tmp")
        })
        .count();
    assert_eq!(stray, 0);
}

#[test]
fn unfinished_or_damaged_caches_are_refused_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    let err = ExampleCache::open(dir.path()).unwrap_err().to_string();
    assert!(err.contains("no manifest"), "{err}");
    let data = dataset(1);
    build(
        dir.path(),
        &data,
        "fp",
        CacheSpec {
            examples: 3,
            shard_size: 2,
        },
        &|_, _| {},
    )
    .unwrap();
    let path = dir.path().join(shard_name(1));
    let bytes = fs::read(&path).unwrap();
    fs::write(&path, &bytes[..bytes.len() - 4]).unwrap();
    let err = ExampleCache::open(dir.path()).unwrap_err().to_string();
    assert!(
        err.contains("shard-00001.bin") && err.contains("expected"),
        "{err}"
    );
    fs::write(dir.path().join(MANIFEST), "fingerprint = 3").unwrap();
    let err = ExampleCache::open(dir.path()).unwrap_err().to_string();
    assert!(err.contains("manifest.toml"), "{err}");
    assert!(
        build(
            dir.path(),
            &data,
            "fp",
            CacheSpec {
                examples: 0,
                shard_size: 2
            },
            &|_, _| {}
        )
        .is_err()
    );
    assert_ne!(fingerprint(&[b"a", b"bc"]), fingerprint(&[b"ab", b"c"]));
}

#[test]
fn a_cache_the_disk_cannot_hold_is_refused_before_anything_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let data = dataset(3);
    // 10^15 examples of 8x8 are petabytes: more than any disk here holds.
    let spec = CacheSpec {
        examples: 1_000_000_000_000_000,
        shard_size: 256,
    };
    let e = build(dir.path(), &data, "fp", spec, &|_, _| {}).unwrap_err();
    assert!(matches!(e, CacheError::NoSpace { .. }), "{e:?}");
    let message = e.to_string();
    assert!(
        message.contains(&dir.path().display().to_string())
            && message.contains("GiB free")
            && message.contains("[data.cache] examples"),
        "{message}"
    );
    assert_eq!(
        fs::read_dir(dir.path()).unwrap().count(),
        0,
        "nothing written"
    );
}
