//! A training dataset: a source of intrinsic images (the built-in synthetic heads or a folder
//! dataset), a bank of light maps, and the draws that light each example, as a pure function
//! of the example's index.
//!
//! Example `i` of a dataset with seed `s` uses its own random stream (SplitMix64 of a hash of
//! `s` and `i`): which head or image, which pose (synthetic heads), which environment and
//! rotation. So batches can be made in any order, on any number of threads, and a resumed run
//! sees exactly the data of an uninterrupted one.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use volux_envmap::io::{linear_to_srgb, srgb_to_linear};
use volux_envmap::random::{self, SplitMix64};
use volux_envmap::{LightMap, LightMapSet, PreconvolveOptions, Rgb};

use crate::batch::Batch;
use crate::config_file::{self, BoxError, ConfigFileError};
use crate::folder_dataset::{FolderDataset, FolderError};
use crate::hdri_collection::{HdriCollection, HdriCollectionConfig, HdriError};
use crate::light_map_bank::LightMapBank;
use crate::pose_distribution::PoseDistribution;
use crate::relighting::{DEFAULT_SPECULAR_WEIGHTS, IntrinsicImage};
use crate::synthetic_head::{self, RenderSettings, SyntheticHead};
use crate::training_sample::{Intrinsics, LightingDraw, SampleError, TrainingSample, make_sample};

/// Where the intrinsic images come from (`[data.source]` in a config, `kind = ...`).
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum SourceConfig {
    /// The built-in procedural heads.
    Synthetic {
        /// How many distinct heads (seeds `0..identities`); examples draw among them.
        #[serde(default = "default_identities")]
        identities: u64,
        /// Rays per pixel along each axis (2: anti-aliased, 4x the cost).
        #[serde(default = "one")]
        supersample: usize,
        /// Camera pose distribution.
        #[serde(default)]
        poses: PoseDistribution,
    },
    /// A folder dataset (see [`crate::folder_dataset`] for the layout).
    Folder {
        path: PathBuf,
        /// Specular weights of the lobes 1, 16, 32, 64.
        #[serde(default = "default_weights")]
        specular_weights: [f32; 4],
    },
}

fn default_identities() -> u64 {
    10_000
}

fn one() -> usize {
    1
}

fn default_weights() -> [f32; 4] {
    DEFAULT_SPECULAR_WEIGHTS
}

impl Default for SourceConfig {
    fn default() -> Self {
        SourceConfig::Synthetic {
            identities: default_identities(),
            supersample: 1,
            poses: PoseDistribution::default(),
        }
    }
}

/// Where `volux data build` puts rendered examples (`[data.cache]`).
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct CacheConfig {
    /// Folder of the shards and manifest.
    pub dir: PathBuf,
    /// How many examples to render.
    pub examples: u64,
    #[serde(default = "default_shard_size")]
    pub shard_size: usize,
}

fn default_shard_size() -> usize {
    256
}

fn default_resolution() -> usize {
    64
}

fn default_volume_resolution() -> usize {
    32
}

/// The data half of a training config (the `[data]` table).
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct DataConfig {
    /// Seed of every draw (heads, poses, environments, rotations).
    #[serde(default)]
    pub seed: u64,
    /// Background colour, sRGB in `[0, 1]` (the generator composites over the same).
    #[serde(default)]
    pub background: [f32; 3],
    /// Output (high) resolution of the examples, pixels per side.
    #[serde(default = "default_resolution")]
    pub resolution: usize,
    /// Volume (low) resolution: the generator's rendered resolution; divides `resolution`.
    #[serde(default = "default_volume_resolution")]
    pub volume_resolution: usize,
    #[serde(default)]
    pub source: SourceConfig,
    /// The environments examples are lit with.
    #[serde(default)]
    pub lighting: HdriCollectionConfig,
    /// Folder where preconvolved light maps are cached (none: preconvolve every run).
    #[serde(default)]
    pub light_map_cache: Option<PathBuf>,
    /// The on-disk example cache, if examples are rendered ahead of training.
    #[serde(default)]
    pub cache: Option<CacheConfig>,
}

/// Largest `resolution` of a dataset: an example of 2048x2048 already takes about 300 MiB of
/// layers.
pub const MAX_RESOLUTION: usize = 2048;

impl DataConfig {
    /// The background as an albedo (linear): what the generator composites its albedo over.
    pub fn albedo_background(&self) -> [f32; 3] {
        self.background.map(srgb_to_linear)
    }

    /// `resolution / volume_resolution`, checked.
    pub fn factor(&self) -> Result<usize, DataError> {
        let (hi, lo) = (self.resolution, self.volume_resolution);
        if hi > MAX_RESOLUTION {
            return Err(DataError::Config(format!(
                "resolution = {hi} exceeds {MAX_RESOLUTION} pixels per side (the paper's largest is 256)"
            )));
        }
        if lo == 0 || hi == 0 || !hi.is_multiple_of(lo) {
            return Err(DataError::Config(format!(
                "resolution = {hi} must be a positive multiple of volume_resolution = {lo}"
            )));
        }
        Ok(hi / lo)
    }

    /// Reads the `[data]` table of a config file (other tables belong to other commands),
    /// rejecting unknown keys; relative paths are taken relative to the file's folder.
    pub fn load(path: &Path) -> Result<(DataConfig, String), DataError> {
        let text = config_file::read(path)?;
        Self::from_text(&text, path)
    }

    /// [`DataConfig::load`] on the text of the file at `path` (read before, or stored).
    pub fn from_text(text: &str, path: &Path) -> Result<(DataConfig, String), DataError> {
        let table: toml::Table = config_file::parse(text, path)?;
        let data = table
            .get("data")
            .ok_or_else(|| ConfigFileError::MissingTable {
                path: path.to_path_buf(),
                table: "data",
            })?
            .clone();
        let in_table = |table: &'static str, source: BoxError| ConfigFileError::Table {
            path: path.to_path_buf(),
            table,
            source,
        };
        let mut config: DataConfig = data
            .clone()
            .try_into()
            .map_err(|e: toml::de::Error| in_table("data", e.into()))?;
        config
            .lighting
            .validate()
            .map_err(|e| in_table("data.lighting", e.into()))?;
        let base = path.parent().unwrap_or(Path::new(""));
        config.resolve_paths(base);
        // What examples depend on: the table as written, without the example cache's own
        // settings (a bigger cache is the same dataset).
        let mut hashed = data;
        if let Some(t) = hashed.as_table_mut() {
            t.remove("cache");
            t.remove("light_map_cache");
        }
        Ok((config, toml::to_string(&hashed).unwrap_or_default()))
    }

    /// Joins relative paths to `base`.
    pub fn resolve_paths(&mut self, base: &Path) {
        let join = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        };
        if let SourceConfig::Folder { path, .. } = &mut self.source {
            join(path);
        }
        self.lighting.folders.iter_mut().for_each(join);
        if let Some(p) = self.light_map_cache.as_mut() {
            join(p);
        }
        if let Some(c) = self.cache.as_mut() {
            join(&mut c.dir);
        }
    }

    /// Whether examples carry their camera pose: the synthetic heads do, a folder dataset
    /// only with a `poses.csv` (without one every photo is frontal, `(0, 0)`).
    pub fn has_poses(&self) -> bool {
        match &self.source {
            SourceConfig::Synthetic { .. } => true,
            SourceConfig::Folder { path, .. } => FolderDataset::has_poses_file(path),
        }
    }

    /// The light maps of the configured collection (through the light-map cache, if any).
    pub fn light_bank(&self) -> Result<LightMapBank, DataError> {
        let collection = HdriCollection::from_config(&self.lighting)
            .map_err(|e| DataError::Lighting(LightingError::Collection(e)))?;
        LightMapBank::build(
            &collection,
            &PreconvolveOptions::default(),
            self.light_map_cache.as_deref(),
        )
        .map_err(|e| DataError::Lighting(LightingError::Bank(e)))
    }
}

/// Why the dataset's lighting cannot be made: its HDRI collection, or the light maps of it.
#[derive(Debug, thiserror::Error)]
pub enum LightingError {
    #[error(transparent)]
    Collection(HdriError),
    #[error(transparent)]
    Bank(crate::light_map_bank::LightMapBankError),
}

/// Why a dataset or an example cannot be made.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    #[error("data config: {0}")]
    Config(String),
    #[error(transparent)]
    File(#[from] ConfigFileError),
    #[error("lighting")]
    Lighting(#[source] LightingError),
    #[error(transparent)]
    Folder(#[from] FolderError),
    #[error("{stem}")]
    Sample { stem: String, source: SampleError },
    #[error(
        "folder image {stem} is {width}x{height}: it must be square, {side} pixels or a multiple of it"
    )]
    FolderSize {
        stem: String,
        width: usize,
        height: usize,
        side: usize,
    },
}

enum Source {
    Synthetic {
        identities: u64,
        settings: RenderSettings,
        poses: PoseDistribution,
    },
    Folder {
        dataset: FolderDataset,
        specular_weights: [f32; 4],
    },
}

/// A dataset ready to make examples at one resolution.
pub struct Dataset {
    source: Source,
    lights: Arc<Vec<LightMapSet>>,
    seed: u64,
    background: Rgb,
    side: usize,
    factor: usize,
}

impl Dataset {
    /// Opens the source of `config` (a folder is listed, not decoded) for examples at the
    /// config's resolutions, lit by `lights` (each the light maps 1, 16, 32, 64 of one
    /// environment; see [`DataConfig::light_bank`]).
    pub fn new(config: &DataConfig, lights: Arc<Vec<LightMapSet>>) -> Result<Dataset, DataError> {
        if lights.is_empty() {
            return Err(DataError::Config("the light-map bank is empty".into()));
        }
        let factor = config.factor()?;
        let side = config.resolution;
        if let Some(k) = config
            .background
            .iter()
            .position(|v| !(0.0..=1.0).contains(v))
        {
            return Err(DataError::Config(format!(
                "background[{k}] = {} must be in [0, 1]",
                config.background[k]
            )));
        }
        let source = match &config.source {
            SourceConfig::Synthetic {
                identities,
                supersample,
                poses,
            } => {
                if *identities == 0 {
                    return Err(DataError::Config(
                        "source.identities must be at least 1".into(),
                    ));
                }
                if !(1..=4).contains(supersample) {
                    return Err(DataError::Config(format!(
                        "source.supersample = {supersample} must be 1 to 4"
                    )));
                }
                poses
                    .validate()
                    .map_err(|e| DataError::Config(format!("source.poses.{e}")))?;
                Source::Synthetic {
                    identities: *identities,
                    settings: RenderSettings {
                        supersample: *supersample,
                        ..RenderSettings::square(side)
                    },
                    poses: *poses,
                }
            }
            SourceConfig::Folder {
                path,
                specular_weights,
            } => {
                if let Some(k) = specular_weights
                    .iter()
                    .position(|w| !(w.is_finite() && *w >= 0.0))
                {
                    return Err(DataError::Config(format!(
                        "source.specular_weights[{k}] = {} must be finite and >= 0",
                        specular_weights[k]
                    )));
                }
                Source::Folder {
                    dataset: FolderDataset::open(path)?,
                    specular_weights: *specular_weights,
                }
            }
        };
        Ok(Dataset {
            source,
            lights,
            seed: config.seed,
            background: config.background,
            side,
            factor,
        })
    }

    pub fn side(&self) -> usize {
        self.side
    }

    pub fn factor(&self) -> usize {
        self.factor
    }

    /// The light-map bank the draws index.
    pub fn lights(&self) -> &Arc<Vec<LightMapSet>> {
        &self.lights
    }

    /// Example `index`.
    pub fn example(&self, index: u64) -> Result<TrainingSample, DataError> {
        let mut rng = SplitMix64::new(mix(self.seed, index));
        let finish = |intrinsics: Intrinsics<'_>, draw: LightingDraw, stem: &str| {
            make_sample(
                intrinsics,
                &self.maps(draw),
                draw,
                self.background,
                self.factor,
            )
            .map_err(|source| DataError::Sample {
                stem: stem.to_string(),
                source,
            })
        };
        match &self.source {
            Source::Synthetic {
                identities,
                settings,
                poses,
            } => {
                let identity = rng.next_u64() % identities;
                let pose = poses.sample(&mut rng);
                let draw = LightingDraw::sample(self.lights.len(), &mut rng);
                let head = SyntheticHead::from_seed(identity);
                let render = synthetic_head::render(&head, pose, settings);
                let intrinsics = Intrinsics::Synthetic {
                    head: &head,
                    render: &render,
                };
                finish(intrinsics, draw, &format!("synthetic head {identity}"))
            }
            Source::Folder {
                dataset,
                specular_weights,
            } => {
                let i = (rng.next_u64() % dataset.len() as u64) as usize;
                let draw = LightingDraw::sample(self.lights.len(), &mut rng);
                let loaded = dataset.load(i)?;
                let stem = loaded.stem;
                let (image, photo) =
                    fit(loaded.image, loaded.photo, self.side).map_err(|(width, height)| {
                        DataError::FolderSize {
                            stem: stem.clone(),
                            width,
                            height,
                            side: self.side,
                        }
                    })?;
                let intrinsics = Intrinsics::Photo {
                    image: &image,
                    photo: &photo,
                    specular_weights,
                    over_background: dataset.has_mask(i),
                };
                finish(intrinsics, draw, &stem)
            }
        }
    }

    /// Batch `index` of `size` examples (examples `index * size ..`), made in parallel.
    pub fn batch(&self, index: u64, size: usize) -> Result<Batch, DataError> {
        let first = index * size as u64;
        let examples = (first..first + size as u64)
            .into_par_iter()
            .map(|i| self.example(i))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Batch::collate(index, &examples))
    }

    fn maps(&self, draw: LightingDraw) -> Vec<&LightMap> {
        self.lights[draw.map].maps().iter().collect()
    }
}

/// A seed for example `index` of a stream seeded `seed`.
fn mix(seed: u64, index: u64) -> u64 {
    random::stream_seed(seed, index, random::EXAMPLE_STREAM)
}

/// Brings a folder image to `side x side` by area averaging (its side must be a multiple):
/// albedo and photo averaged in linear light, normals averaged and renormalised, mask averaged.
fn fit(
    image: IntrinsicImage,
    photo: Vec<Rgb>,
    side: usize,
) -> Result<(IntrinsicImage, Vec<Rgb>), (usize, usize)> {
    let (w, h) = (image.width, image.height);
    if w != h || w % side != 0 {
        return Err((w, h));
    }
    let k = w / side;
    if k == 1 {
        return Ok((image, photo));
    }
    let average = |layer: &[[f32; 3]]| crate::training_sample::area_downsample(layer, w, k);
    let linear: Vec<Rgb> = photo.iter().map(|c| c.map(srgb_to_linear)).collect();
    let photo = average(&linear)
        .into_iter()
        .map(|c| c.map(linear_to_srgb))
        .collect();
    let mask_rgb: Vec<[f32; 3]> = image.mask.iter().map(|&m| [m; 3]).collect();
    let mask = average(&mask_rgb)
        .into_iter()
        .map(|m| m[0])
        .collect::<Vec<f32>>();
    let normals = average(&image.normals)
        .into_iter()
        .zip(&mask)
        .map(|(n, &m)| {
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            if m > 0.0 && len > 1e-6 {
                n.map(|c| c / len)
            } else {
                [0.0; 3]
            }
        })
        .collect();
    Ok((
        IntrinsicImage {
            width: side,
            height: side,
            albedo: average(&image.albedo),
            normals,
            mask,
            pose: image.pose,
        },
        photo,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use volux_envmap::error::chain;
    use volux_envmap::{EnvMap, PreconvolveOptions, preconvolve};
    use volux_model::pose::Pose;

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
            other.example(6).unwrap().photo,
            data.example(6).unwrap().photo
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
            let got = example.photo[i];
            assert!(
                (0..3).all(|k| (got[k] - want[k]).abs() < 3e-3),
                "pixel {i}: {got:?}"
            );
            if m == 0.0 {
                assert_eq!(example.relit[i], example.photo[i], "pixel {i}");
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
                .photo
                .iter()
                .all(|p| (0..3).all(|k| (p[k] - [0.2, 0.6, 0.4][k]).abs() < 3e-3))
        );
    }

    #[test]
    fn the_documented_config_parses() {
        let doc = include_str!("../../docs/data.md");
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
        use volux_model::generator::GeneratorWants;
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
        let real = batch.to_tensors(&device);
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
        assert_eq!(fake.albedo_hi.unwrap().dims(), real.albedo_hi.dims());
        assert_eq!(fake.albedo_lo.unwrap().dims(), real.albedo_lo.dims());
        assert_eq!(fake.normals_lo.unwrap().dims(), real.normals_lo.dims());
        assert_eq!(fake.relit.unwrap().dims(), real.relit.dims());
        let lo = g_config.volume_resolution;
        assert_eq!(fake.opacity.dims(), [2, 1, lo, lo]);
        assert_eq!(
            fake.diffuse_lo.unwrap().dims()[..2],
            real.diffuse.dims()[..2]
        );
        // A draw naming a missing environment is an error, not a panic.
        let mut bad = batch.clone();
        bad.draws[1].map = 7;
        assert!(bad.lighting(&lights, &device).is_err());
    }
}
