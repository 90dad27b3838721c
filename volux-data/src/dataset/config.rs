//! The `[data]` table of a config: the source, the lighting, the resolutions and the caches,
//! read from a file with unknown keys refused and relative paths resolved.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use volux_envmap::PreconvolveOptions;
use volux_envmap::io::srgb_to_linear;

use super::{DataError, LightingError};
use crate::config_file::{self, BoxError, ConfigFileError};
use crate::folder_dataset::{FolderContent, FolderDataset};
use crate::hdri_collection::{HdriCollection, HdriCollectionConfig};
use crate::layers::Layers;
use crate::light_map_bank::LightMapBank;
use crate::pose_distribution::PoseDistribution;
use crate::relighting::DEFAULT_SPECULAR_WEIGHTS;

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
        /// The layers the folder provides: `["photo", "albedo", "normals"]` (the default) or
        /// `["photo"]` for photos alone ([`FolderContent`]).
        #[serde(default = "all_folder_layers")]
        layers: Vec<FolderLayer>,
    },
}

/// A layer a folder dataset can provide (`layers` of `[data.source]`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum FolderLayer {
    Photo,
    Albedo,
    Normals,
}

impl FolderLayer {
    /// The layer's name in a config.
    pub const fn name(self) -> &'static str {
        match self {
            FolderLayer::Photo => "photo",
            FolderLayer::Albedo => "albedo",
            FolderLayer::Normals => "normals",
        }
    }
}

fn all_folder_layers() -> Vec<FolderLayer> {
    vec![
        FolderLayer::Photo,
        FolderLayer::Albedo,
        FolderLayer::Normals,
    ]
}

/// What a folder dataset with `layers` provides, or why no such dataset can be: the photo
/// is required, and albedo and normals come together (module docs of
/// [`crate::folder_dataset`]).
pub fn folder_content(layers: &[FolderLayer]) -> Result<FolderContent, String> {
    let has = |l: FolderLayer| layers.contains(&l);
    let listed = || {
        let names: Vec<String> = layers.iter().map(|l| format!("\"{}\"", l.name())).collect();
        format!("source.layers = [{}]", names.join(", "))
    };
    if let Some(k) = (1..layers.len()).find(|&k| layers[..k].contains(&layers[k])) {
        return Err(format!(
            "{}: \"{}\" is listed twice",
            listed(),
            layers[k].name()
        ));
    }
    if !has(FolderLayer::Photo) {
        return Err(format!(
            "{}: a folder dataset always has its photos; list \"photo\"",
            listed()
        ));
    }
    match (has(FolderLayer::Albedo), has(FolderLayer::Normals)) {
        (true, true) => Ok(FolderContent::Intrinsics),
        (false, false) => Ok(FolderContent::Photos),
        _ => Err(format!(
            "{}: albedo and normals come together (the relit, diffuse and specular layers need both): list both or neither",
            listed()
        )),
    }
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

    /// Checks every value that needs no file: the resolutions, the background, the source's
    /// counts, pose deviations, specular weights and layers, and the example cache's sizes.
    /// Keys are named as in `[data]`.
    pub fn validate(&self) -> Result<(), DataError> {
        self.factor()?;
        let bad = |message: String| Err(DataError::Config(message));
        if let Some(k) = self
            .background
            .iter()
            .position(|v| !(0.0..=1.0).contains(v))
        {
            return bad(format!(
                "background[{k}] = {:?} must be in [0, 1]",
                self.background[k]
            ));
        }
        match &self.source {
            SourceConfig::Synthetic {
                identities,
                supersample,
                poses,
            } => {
                if *identities == 0 {
                    return bad("source.identities must be at least 1".into());
                }
                if !(1..=4).contains(supersample) {
                    return bad(format!("source.supersample = {supersample} must be 1 to 4"));
                }
                poses
                    .validate()
                    .or_else(|e| bad(format!("source.poses.{e}")))?;
            }
            SourceConfig::Folder {
                specular_weights,
                layers,
                ..
            } => {
                folder_content(layers).map_err(DataError::Config)?;
                if let Some(k) = specular_weights
                    .iter()
                    .position(|w| !(w.is_finite() && *w >= 0.0))
                {
                    return bad(format!(
                        "source.specular_weights[{k}] = {:?} must be finite and >= 0",
                        specular_weights[k]
                    ));
                }
            }
        }
        if let Some(cache) = &self.cache
            && (cache.examples == 0 || cache.shard_size == 0)
        {
            return bad(format!(
                "cache.examples = {} and cache.shard_size = {} must be at least 1",
                cache.examples, cache.shard_size
            ));
        }
        Ok(())
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
        config.validate().map_err(|e| match e {
            DataError::Config(message) => in_table("data", message.into()),
            other => in_table("data", other.into()),
        })?;
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

    /// Which layers the examples have: every one for the synthetic heads and a folder with
    /// intrinsics, the photo alone for a photos-only folder. An error names a bad
    /// `source.layers`.
    pub fn provided(&self) -> Result<Layers<bool>, DataError> {
        match &self.source {
            SourceConfig::Synthetic { .. } => Ok(Layers::from_fn(|_| true)),
            SourceConfig::Folder { layers, .. } => {
                let content = folder_content(layers).map_err(DataError::Config)?;
                Ok(content.provided())
            }
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
