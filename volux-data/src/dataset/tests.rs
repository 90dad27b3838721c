use volux_model::pose::Pose;

use super::*;
use std::path::Path;

use crate::layers::{Layer, Layers};
use crate::relighting::DEFAULT_SPECULAR_WEIGHTS;
use volux_envmap::error::chain;
use volux_envmap::{EnvMap, PreconvolveOptions, preconvolve};

fn bank() -> Arc<Vec<LightMapSet>> {
    let maps = [
        EnvMap::constant(16, [1.0; 3]).unwrap(),
        crate::procedural_sky::overcast(32, 2.0).unwrap(),
    ];
    Arc::new(
        maps.iter()
            .map(|m| preconvolve(m, &PreconvolveOptions::default()).unwrap())
            .collect(),
    )
}

#[test]
fn configs_parse_with_defaults_and_reject_unknown_keys() {
    let config: DataConfig =
        toml::from_str("seed = 3\n[source]\nkind = \"synthetic\"\nidentities = 50\n").unwrap();
    assert_eq!(config.seed, 3);
    assert!(matches!(
        config.source,
        SourceConfig::Synthetic {
            identities: 50,
            supersample: 1,
            ..
        }
    ));
    let folder: DataConfig =
        toml::from_str("[source]\nkind = \"folder\"\npath = \"faces\"\n").unwrap();
    assert!(
        matches!(folder.source, SourceConfig::Folder { specular_weights, .. } if specular_weights == DEFAULT_SPECULAR_WEIGHTS)
    );
    let err = toml::from_str::<DataConfig>("[source]\nkind = \"synthetic\"\nidentitys = 5\n")
        .unwrap_err();
    assert!(err.to_string().contains("identitys"), "{err}");
    let err = toml::from_str::<DataConfig>("sed = 1\n").unwrap_err();
    assert!(err.to_string().contains("sed"), "{err}");
    let err = toml::from_str::<DataConfig>("[source]\nkind = \"video\"\n").unwrap_err();
    assert!(err.to_string().contains("video"), "{err}");
}

#[test]
fn impossible_values_are_errors_naming_the_key() {
    let lights = bank();
    let bad = |toml_text: &str| {
        let config: DataConfig = toml::from_str(toml_text).unwrap();
        Dataset::new(&config, lights.clone())
            .err()
            .unwrap()
            .to_string()
    };
    let sizes = bad("resolution = 30\nvolume_resolution = 8");
    assert!(sizes.contains("resolution = 30") && sizes.contains("volume_resolution = 8"));
    let huge = bad("resolution = 1048576\nvolume_resolution = 32");
    assert!(huge.contains("resolution = 1048576 exceeds 2048"), "{huge}");
    assert!(bad("background = [0.0, 2.0, 0.0]").contains("background[1]"));
    assert!(bad("[source]\nkind = \"synthetic\"\nidentities = 0").contains("identities"));
    assert!(bad("[source]\nkind = \"synthetic\"\nsupersample = 9").contains("supersample"));
    let poses = "[source]\nkind = \"synthetic\"\n[source.poses]\nyaw_sd = -1.0";
    assert!(bad(poses).contains("source.poses.yaw_sd"));
    let folder = "[source]\nkind = \"folder\"\npath = \"no/such/folder\"";
    assert!(bad(folder).contains("no/such/folder"));
    let config: DataConfig = toml::from_str("").unwrap();
    assert!(Dataset::new(&config, Arc::new(Vec::new())).is_err());
}

#[test]
fn config_files_name_themselves_in_errors_and_resolve_relative_paths() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("run.toml");
    let write = |text: &str| std::fs::write(&file, text).unwrap();
    write(
        "[train]\nsteps = 3\n[data]\nseed = 4\nlight_map_cache = \"lm\"\n[data.source]\nkind = \"folder\"\npath = \"faces\"\n[data.cache]\ndir = \"cache\"\nexamples = 8\n",
    );
    let (config, hashed) = DataConfig::load(&file).unwrap();
    assert_eq!(config.seed, 4);
    assert!(
        matches!(&config.source, SourceConfig::Folder { path, .. } if *path == dir.path().join("faces"))
    );
    assert_eq!(config.cache.as_ref().unwrap().dir, dir.path().join("cache"));
    assert_eq!(config.cache.as_ref().unwrap().shard_size, 256);
    // The fingerprinted text leaves out where things are cached.
    assert!(hashed.contains("seed") && !hashed.contains("examples") && !hashed.contains("lm"));
    write("[data]\nseed = \"x\"\n");
    let err = chain(&DataConfig::load(&file).unwrap_err());
    assert!(err.contains("run.toml") && err.contains("seed"), "{err}");
    write("[data.lighting]\nskys = 3\n");
    let err = chain(&DataConfig::load(&file).unwrap_err());
    assert!(err.contains("run.toml") && err.contains("skys"), "{err}");
    // Values out of range are named with the file when it is read (they were found only
    // when the dataset was opened, or the cache built, without the file).
    for (text, says) in [
        (
            "[data.source]\nkind = \"synthetic\"\nidentities = 0\n",
            "source.identities must be at least 1",
        ),
        (
            "[data]\nbackground = [0.0, 2.0, 0.0]\n",
            "background[1] = 2",
        ),
        (
            "[data.cache]\ndir = \"c\"\nexamples = 0\n",
            "cache.examples = 0 and cache.shard_size = 256 must be at least 1",
        ),
        (
            "[data.source]\nkind = \"folder\"\npath = \"f\"\nspecular_weights = [0.0, -1.0, 0.0, 0.0]\n",
            "source.specular_weights[1] = -1",
        ),
    ] {
        write(text);
        let err = chain(&DataConfig::load(&file).unwrap_err());
        assert!(
            err.contains("run.toml: [data]") && err.contains(says),
            "{err}"
        );
    }
    write("[model]\n");
    assert!(
        DataConfig::load(&file)
            .unwrap_err()
            .to_string()
            .contains("no [data] table")
    );
    assert!(
        DataConfig::load(&dir.path().join("none.toml"))
            .unwrap_err()
            .to_string()
            .contains("none.toml")
    );
}

#[test]
fn examples_are_a_pure_function_of_their_index() {
    let config: DataConfig =
        toml::from_str("seed = 9\nresolution = 16\nvolume_resolution = 8\n[source]\nkind = \"synthetic\"\nidentities = 4\n").unwrap();
    let data = Dataset::new(&config, bank()).unwrap();
    let batch = data.batch(2, 3).unwrap();
    assert_eq!(
        (batch.size, batch.side, batch.side_lo, batch.index),
        (3, 16, 8, 2)
    );
    // Batch 2 of size 3 is examples 6, 7, 8, whichever way it is made.
    let alone = Batch::collate(
        2,
        &[
            data.example(6).unwrap(),
            data.example(7).unwrap(),
            data.example(8).unwrap(),
        ],
    );
    assert_eq!(batch, alone);
    let other = Dataset::new(
        &DataConfig {
            seed: 10,
            ..config.clone()
        },
        bank(),
    )
    .unwrap();
    assert_ne!(
        other.example(6).unwrap().layers.photo,
        data.example(6).unwrap().layers.photo
    );
    // Draws cover the bank and the full turn.
    let draws: Vec<LightingDraw> = (0..64).map(|i| data.example(i).unwrap().draw).collect();
    assert!(draws.iter().any(|d| d.map == 0) && draws.iter().any(|d| d.map == 1));
    assert!(
        draws
            .iter()
            .all(|d| (0.0..std::f64::consts::TAU).contains(&d.yaw))
    );
    assert!(draws.iter().any(|d| d.yaw > 5.0) && draws.iter().any(|d| d.yaw < 1.0));
}

#[test]
fn folder_images_are_averaged_down_to_the_training_size() {
    // A 4x4 image brought to 2x2: each output pixel averages a 2x2 block.
    let n = 16;
    let image = IntrinsicImage {
        width: 4,
        height: 4,
        albedo: (0..n).map(|i| [i as f32 / 16.0; 3]).collect(),
        normals: vec![[0.6, 0.0, 0.8]; n],
        mask: (0..n).map(|i| if i % 4 < 2 { 1.0 } else { 0.0 }).collect(),
        pose: Pose::new(0.1, 0.0),
    };
    let photo = vec![[0.5; 3]; n];
    let (small, small_photo) = fit(image.clone(), photo.clone(), 2).unwrap();
    assert_eq!((small.width, small.albedo.len()), (2, 4));
    assert!((small.albedo[0][0] - (0.0 + 1.0 + 4.0 + 5.0) / 64.0).abs() < 1e-7);
    assert_eq!(small.mask, vec![1.0, 0.0, 1.0, 0.0]);
    assert_eq!(small.normals[0], [0.6, 0.0, 0.8]);
    assert_eq!(small.normals[1], [0.0; 3]);
    assert!((small_photo[0][0] - 0.5).abs() < 1e-6);
    assert_eq!(fit(image.clone(), photo.clone(), 3).unwrap_err(), (4, 4));
    assert_eq!(fit(image, photo, 4).unwrap().0.width, 4);
}

#[test]
fn folder_photos_with_masks_are_composited_over_the_background_like_the_relit_image() {
    use crate::folder_dataset::{FolderSample, write_dataset};
    let side = 8;
    let n = side * side;
    let mask: Vec<f32> = (0..n).map(|i| f32::from(u8::from(i % side < 5))).collect();
    let sample = FolderSample {
        stem: "face".into(),
        photo: vec![[0.2, 0.6, 0.4]; n],
        image: IntrinsicImage {
            width: side,
            height: side,
            albedo: vec![[0.5; 3]; n],
            normals: mask.iter().map(|&m| [0.0, 0.0, m]).collect(),
            mask: mask.clone(),
            pose: Pose::new(0.0, 0.0),
        },
        renormalised: 0,
        degenerate: 0,
    };
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("faces");
    write_dataset(&root, &[sample]).unwrap();
    let config = |root: &Path| DataConfig {
        background: [1.0, 0.0, 0.0],
        resolution: side,
        volume_resolution: side / 2,
        source: SourceConfig::Folder {
            path: root.to_path_buf(),
            specular_weights: DEFAULT_SPECULAR_WEIGHTS,
            layers: vec![
                FolderLayer::Photo,
                FolderLayer::Albedo,
                FolderLayer::Normals,
            ],
        },
        ..toml::from_str("").unwrap()
    };
    let example = Dataset::new(&config(&root), bank())
        .unwrap()
        .example(0)
        .unwrap();
    for (i, &m) in mask.iter().enumerate() {
        let want = if m > 0.0 {
            [0.2, 0.6, 0.4]
        } else {
            [1.0, 0.0, 0.0]
        };
        let got = example.rgb(Layer::Photo)[i];
        assert!(
            (0..3).all(|k| (got[k] - want[k]).abs() < 3e-3),
            "pixel {i}: {got:?}"
        );
        if m == 0.0 {
            assert_eq!(
                example.rgb(Layer::Relit)[i],
                example.rgb(Layer::Photo)[i],
                "pixel {i}"
            );
        }
    }
    // Without mask files (the mask then comes from the normals' length) the photo keeps
    // its own background.
    std::fs::remove_dir_all(root.join("masks")).unwrap();
    let example = Dataset::new(&config(&root), bank())
        .unwrap()
        .example(0)
        .unwrap();
    assert!(
        example
            .rgb(Layer::Photo)
            .iter()
            .all(|p| (0..3).all(|k| (p[k] - [0.2, 0.6, 0.4][k]).abs() < 3e-3))
    );
}

#[test]
fn the_documented_config_parses() {
    let doc = include_str!("../../../docs/data.md");
    let start = doc.find("```toml\n").expect("a toml block") + "```toml\n".len();
    let block = &doc[start..start + doc[start..].find("```").unwrap()];
    let table: toml::Table = toml::from_str(block).unwrap();
    let config: DataConfig = table["data"].clone().try_into().unwrap();
    assert_eq!((config.resolution, config.volume_resolution), (64, 32));
    assert_eq!(config.cache.unwrap().examples, 10_000);
}

#[test]
fn batches_match_what_the_small_generator_makes() {
    use burn::tensor::{Device, Distribution, Tensor};
    use volux_model::generated::GeneratorWants;
    use volux_model::presets::Preset;
    let g_config = Preset::Small.generator();
    let config: DataConfig = toml::from_str(&format!(
        "resolution = {}\nvolume_resolution = {}\n[source]\nkind = \"synthetic\"\nidentities = 3",
        g_config.output_resolution, g_config.volume_resolution
    ))
    .unwrap();
    let lights = bank();
    let data = Dataset::new(&config, lights.clone()).unwrap();
    let batch = data.batch(0, 2).unwrap();
    let device = Device::flex();
    device.seed(1);
    let real = batch
        .to_tensors(&device)
        .map(|_, t| t.clone().expect("every layer"));
    let lighting = batch.lighting(&lights, &device).unwrap();
    let generator = g_config.init(&device).unwrap();
    let z = Tensor::<2>::random(
        [2, g_config.mapping.z_dim],
        Distribution::Normal(0.0, 1.0),
        &device,
    );
    let fake = generator
        .forward(
            z,
            &batch.poses,
            Some(&lighting),
            config.albedo_background(),
            GeneratorWants::ALL,
            None,
            false,
        )
        .unwrap();
    assert_eq!(fake.layers.albedo_hi.unwrap().dims(), real.albedo_hi.dims());
    assert_eq!(fake.layers.albedo_lo.unwrap().dims(), real.albedo_lo.dims());
    assert_eq!(
        fake.layers.normals_lo.unwrap().dims(),
        real.normals_lo.dims()
    );
    assert_eq!(fake.layers.relit.unwrap().dims(), real.relit.dims());
    let lo = g_config.volume_resolution;
    assert_eq!(fake.opacity.dims(), [2, 1, lo, lo]);
    assert_eq!(
        fake.layers.diffuse_lo.unwrap().dims()[..2],
        real.diffuse.dims()[..2]
    );
    // A draw naming a missing environment is an error, not a panic.
    let mut bad = batch.clone();
    bad.draws[1].map = 7;
    assert!(bad.lighting(&lights, &device).is_err());
}

/// A folder of photos alone, 16x16 with a mask on the first: trained at 8x8 (area-averaged).
fn photos_only_folder(root: &Path) {
    use crate::folder_dataset::{FolderSample, write_dataset};
    let side = 16;
    let n = side * side;
    let mask: Vec<f32> = (0..n).map(|i| f32::from(u8::from(i % side < 8))).collect();
    let sample = |stem: &str, value: f32| FolderSample {
        stem: stem.into(),
        photo: vec![[value, 0.5, 0.25]; n],
        image: IntrinsicImage {
            width: side,
            height: side,
            albedo: vec![[0.5; 3]; n],
            normals: vec![[0.0, 0.0, 1.0]; n],
            mask: mask.clone(),
            pose: Pose::new(0.0, 0.0),
        },
        renormalised: 0,
        degenerate: 0,
    };
    write_dataset(root, &[sample("a", 0.8), sample("b", 0.2)]).unwrap();
    // Photos alone: no intrinsic layers, one mask kept.
    std::fs::remove_dir_all(root.join("albedo")).unwrap();
    std::fs::remove_dir_all(root.join("normals")).unwrap();
    std::fs::remove_file(root.join("masks/b.png")).unwrap();
}

fn photos_only_config(root: &Path, layers: &str) -> DataConfig {
    let text = format!(
        "resolution = 8\nvolume_resolution = 4\nbackground = [0.0, 0.0, 1.0]\n[source]\nkind = \"folder\"\npath = {:?}\nlayers = {layers}\n",
        root.display().to_string()
    );
    toml::from_str(&text).unwrap()
}

#[test]
fn a_folder_of_photos_alone_makes_examples_of_the_photo_layer_only() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("photos_only");
    photos_only_folder(&root);
    // Without `layers` the folder is refused, and the message says how to use it.
    let all = photos_only_config(&root, "[\"photo\", \"albedo\", \"normals\"]");
    let e = chain(&Dataset::new(&all, bank()).err().unwrap());
    assert!(
        e.contains("missing albedo/, normals/") && e.contains("layers = [\"photo\"]"),
        "{e}"
    );

    let config = photos_only_config(&root, "[\"photo\"]");
    assert_eq!(
        config.provided().unwrap(),
        Layers::from_fn(|l| l == Layer::Photo)
    );
    let data = Dataset::new(&config, bank()).unwrap();
    assert_eq!(data.provided(), config.provided().unwrap());
    let mut seen = [false; 2];
    for i in 0..16 {
        let e = data.example(i).unwrap();
        assert_eq!(e.layers.photo.len(), 3 * 8 * 8);
        assert!(
            e.layers
                .iter()
                .all(|(l, v)| v.is_empty() == (l != Layer::Photo))
        );
        let photo = e.rgb(Layer::Photo);
        // "a" has a mask: its right half is the background; "b" has none: all photo.
        let (left, right) = (photo[0], photo[7]);
        if (left[0] - 0.8).abs() < 1e-3 {
            seen[0] = true;
            assert!(
                (right[2] - 1.0).abs() < 1e-6 && right[0].abs() < 1e-6,
                "{right:?}"
            );
        } else {
            seen[1] = true;
            assert!((left[0] - 0.2).abs() < 1e-3 && (right[0] - 0.2).abs() < 1e-3);
        }
    }
    assert_eq!(seen, [true, true], "both photos drawn");
    let batch = data.batch(0, 2).unwrap();
    assert_eq!(batch.provided(), data.provided());

    // A photo whose side is not a multiple of the resolution is named by its file (the error
    // gave the stem alone).
    let mut odd = config.clone();
    (odd.resolution, odd.volume_resolution) = (12, 4);
    let e = chain(&Dataset::new(&odd, bank()).unwrap().example(0).unwrap_err());
    assert!(
        e.contains(&root.join("photos").display().to_string())
            && e.contains(".png: the photo is 16x16")
            && e.contains("12 pixels or a multiple"),
        "{e}"
    );
}

#[test]
fn folder_layers_must_be_the_photo_alone_or_with_albedo_and_normals() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("photos_only");
    photos_only_folder(&root);
    for (layers, want) in [
        ("[\"albedo\", \"normals\"]", "list \"photo\""),
        (
            "[\"photo\", \"albedo\"]",
            "albedo and normals come together",
        ),
        (
            "[\"photo\", \"normals\"]",
            "albedo and normals come together",
        ),
        ("[\"photo\", \"photo\"]", "\"photo\" is listed twice"),
    ] {
        let config = photos_only_config(&root, layers);
        let e = config.provided().unwrap_err().to_string();
        assert!(
            e.contains(want) && e.contains("source.layers"),
            "{layers}: {e}"
        );
        let e = chain(&Dataset::new(&config, bank()).err().unwrap());
        assert!(e.contains(want), "{layers}: {e}");
    }
    let unknown = format!(
        "[source]\nkind = \"folder\"\npath = {:?}\nlayers = [\"depth\"]\n",
        root.display().to_string()
    );
    let e = toml::from_str::<DataConfig>(&unknown)
        .unwrap_err()
        .to_string();
    assert!(e.contains("depth"), "{e}");
}
