//! HDRI collections: the environments a dataset relights its images with (paper appendix A,
//! "random HDRI, random rotation").
//!
//! A collection is a list of [`HdriEntry`]s, each with a stable human-readable name and a
//! stable [`ContentKey`] (SHA-256 of what determines its pixels), from three kinds of source:
//! - the eight CC0 Poly Haven maps shipped in `assets/hdri`, embedded in the binary so that an
//!   installed `volux` needs no checkout ([`BUILTIN_HDRIS`]);
//! - procedural environments ([`crate::procedural_sky`]): sunny skies, overcast skies and
//!   studios of one to three area lights, their parameters drawn with SplitMix64 from the
//!   collection seed, the kind and the index, so that entry `i` of a kind does not depend on
//!   how many entries of that kind there are;
//! - folders of `.exr` / `.hdr` maps.
//!
//! An example's draw ([`crate::training_sample::LightingDraw::sample`]) picks an environment
//! uniformly and a yaw uniformly in `[0, 2 pi)`; the yaw is applied at light-map look-up ([`volux_envmap::LightMap::lookup_rotated`]), so a draw
//! costs nothing and nothing is preconvolved twice.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use volux_envmap::EnvMapError;

mod builtin;
mod content;
mod folders;
mod procedural;
mod ranges;
#[cfg(test)]
mod tests;

pub use builtin::{BUILTIN_HDRIS, BuiltinHdri, builtin_entries};
pub use content::{ContentKey, SourceContent};
pub use folders::folder_entries;
pub use procedural::{
    DEFAULT_PROCEDURAL_HEIGHT, MAX_PROCEDURAL_COUNT, PROCEDURAL_VERSION, Procedural,
    random_overcast, random_overcast_in, random_sky, random_sky_in, random_studio,
    random_studio_in,
};
pub use ranges::{OvercastRanges, ProceduralRanges, SkyRanges, StudioRanges};

/// Where an entry's pixels come from.
#[derive(Clone, Debug, PartialEq)]
pub enum HdriSource {
    /// A map embedded in the binary.
    Builtin(BuiltinHdri),
    /// A procedural environment rendered at `height` rows.
    Procedural {
        environment: Procedural,
        height: usize,
    },
    /// An `.exr` or `.hdr` file.
    File(PathBuf),
}

/// One environment of a collection.
#[derive(Clone, Debug, PartialEq)]
pub struct HdriEntry {
    /// Stable, human-readable: `sunrise`, `sky-03`, `overcast-00`, `studio-05`, or
    /// `<folder name>/<file name>`.
    pub name: String,
    pub source: HdriSource,
}

/// What a collection holds; the `[data.lighting]` table of a dataset config.
///
/// ```toml
/// builtin = true
/// skies = 8
/// overcast = 2
/// studios = 6
/// folders = ["my_hdris"]
/// seed = 0
/// procedural_height = 256
/// [ranges.sky]          # optional: what procedural parameters are drawn from
/// elevation = [3.0, 70.0]
/// ```
///
/// Every key is optional (the defaults above, without folders: 24 environments and no
/// downloads; [`ProceduralRanges`] for the ranges); an unknown key is an error naming it. Relative folders are taken as given
/// (relative to the working directory); a config loader that wants them relative to its file
/// joins them first.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct HdriCollectionConfig {
    /// Include the eight embedded maps.
    pub builtin: bool,
    /// Number of procedural sunny skies.
    pub skies: usize,
    /// Number of procedural overcast skies.
    pub overcast: usize,
    /// Number of procedural studios (one to three area lights each).
    pub studios: usize,
    /// Folders whose `.exr` / `.hdr` files (not recursive) are added, sorted by file name.
    pub folders: Vec<PathBuf>,
    /// Seed of the procedural parameters.
    pub seed: u64,
    /// Rows of each procedural map.
    pub procedural_height: usize,
    /// What the procedural parameters are drawn from.
    pub ranges: ProceduralRanges,
}

impl Default for HdriCollectionConfig {
    fn default() -> Self {
        Self {
            builtin: true,
            skies: 8,
            overcast: 2,
            studios: 6,
            folders: Vec::new(),
            seed: 0,
            procedural_height: DEFAULT_PROCEDURAL_HEIGHT,
            ranges: ProceduralRanges::default(),
        }
    }
}

impl HdriCollectionConfig {
    /// Checks counts, the procedural height and the ranges (the collection checks it is not
    /// empty; folders are listed when it is made).
    pub fn validate(&self) -> Result<(), HdriError> {
        for (key, value) in [
            ("skies", self.skies),
            ("overcast", self.overcast),
            ("studios", self.studios),
        ] {
            if value > MAX_PROCEDURAL_COUNT {
                return Err(HdriError::Config {
                    key,
                    message: format!("{value} is more than {MAX_PROCEDURAL_COUNT}"),
                });
            }
        }
        if !(8..=2048).contains(&self.procedural_height) {
            return Err(HdriError::Config {
                key: "procedural_height",
                message: format!("{} is outside 8..=2048", self.procedural_height),
            });
        }
        self.ranges.validate()
    }
}

/// Why a collection cannot be made or one of its maps read.
#[derive(Debug, thiserror::Error)]
pub enum HdriError {
    #[error("HDRI collection config: `{key}`: {message}")]
    Config { key: &'static str, message: String },
    #[error(
        "the HDRI collection is empty: enable `builtin`, ask for `skies`, `overcast` or `studios`, or add `folders`"
    )]
    EmptyCollection,
    #[error("{}: cannot read HDRI folder", path.display())]
    ReadFolder {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: HDRI folder has no .exr or .hdr files", path.display())]
    EmptyFolder { path: PathBuf },
    #[error("{}: cannot read HDRI", path.display())]
    ReadFile {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// Decoding, validating or preconvolving a map (the error names the file or map).
    #[error(transparent)]
    EnvMap(#[from] EnvMapError),
}

/// A non-empty list of environments.
#[derive(Clone, Debug, PartialEq)]
pub struct HdriCollection {
    entries: Vec<HdriEntry>,
}

impl HdriCollection {
    /// The collection a config describes: built-in maps, then skies, overcast skies, studios,
    /// then each folder's maps, in that order.
    pub fn from_config(config: &HdriCollectionConfig) -> Result<HdriCollection, HdriError> {
        config.validate()?;
        let mut entries = Vec::new();
        if config.builtin {
            entries.extend(builtin_entries());
        }
        let height = config.procedural_height;
        let procedural = |name: String, environment: Procedural| HdriEntry {
            name,
            source: HdriSource::Procedural {
                environment,
                height,
            },
        };
        for i in 0..config.skies {
            entries.push(procedural(
                format!("sky-{i:02}"),
                Procedural::SunSky(random_sky_in(&config.ranges.sky, config.seed, i)),
            ));
        }
        for i in 0..config.overcast {
            entries.push(procedural(
                format!("overcast-{i:02}"),
                random_overcast_in(&config.ranges.overcast, config.seed, i),
            ));
        }
        for i in 0..config.studios {
            entries.push(procedural(
                format!("studio-{i:02}"),
                random_studio_in(&config.ranges.studio, config.seed, i),
            ));
        }
        for folder in &config.folders {
            entries.extend(folder_entries(folder)?);
        }
        HdriCollection::new(entries)
    }

    /// A collection of these entries; an error if there are none.
    pub fn new(entries: Vec<HdriEntry>) -> Result<HdriCollection, HdriError> {
        if entries.is_empty() {
            return Err(HdriError::EmptyCollection);
        }
        Ok(HdriCollection { entries })
    }

    /// The entries, in order.
    pub fn entries(&self) -> &[HdriEntry] {
        &self.entries
    }

    /// Number of entries (at least one).
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Always false: a collection is never empty.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}
