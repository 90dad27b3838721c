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
//! [`HdriCollection::draw`] picks an entry uniformly and a yaw uniformly in `[0, 2 pi)`; the
//! yaw is applied at light-map look-up ([`volux_envmap::LightMap::lookup_rotated`]), so a draw
//! costs nothing and nothing is preconvolved twice.

use std::borrow::Cow;
use std::f64::consts::TAU;
use std::fmt;
use std::fs;
use std::path::{Path, PathBuf};

use serde::Deserialize;
use sha2::{Digest, Sha256};
use volux_envmap::report::SplitMix64;
use volux_envmap::{EnvMap, EnvMapError, io};

use crate::procedural_sky::{self, AreaLight, SunSky, sun_direction};

/// Rows of a procedural environment map (width twice that) unless the config says otherwise.
///
/// Preconvolution costs about the same (11-32 ms) from 64 to 256 rows: it is dominated by
/// synthesising the light maps, whose sizes the tolerance fixes. So the height is set by
/// fidelity and by the cost of rendering the map: 256 rows sample the highest degree any
/// default lobe keeps (68, for `n = 1`) at more than two rows per wavelength, and render in
/// 15-60 ms, against 50-230 ms at 512 rows (`docs/data-hdri.md`).
pub const DEFAULT_PROCEDURAL_HEIGHT: usize = 256;

/// Version of the procedural parameter text hashed into content keys. Bump it whenever
/// `procedural_sky` renders the same parameters differently, so that cached light maps of the
/// old rendering are not reused.
pub const PROCEDURAL_VERSION: u32 = 1;

/// Largest count of one procedural kind a config may ask for.
pub const MAX_PROCEDURAL_COUNT: usize = 10_000;

/// One of the HDR maps embedded in the binary.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BuiltinHdri {
    /// Stable name (the file stem).
    pub name: &'static str,
    /// The path the map was embedded from, relative to the repository root; named in errors.
    pub path: &'static str,
    /// The OpenEXR file's bytes.
    pub bytes: &'static [u8],
}

macro_rules! builtin {
    ($name:literal) => {
        BuiltinHdri {
            name: $name,
            path: concat!("assets/hdri/", $name, ".exr"),
            bytes: include_bytes!(concat!("../../assets/hdri/", $name, ".exr")),
        }
    };
}

/// The eight shipped CC0 maps (1024x512 OpenEXR; `assets/hdri/SOURCE.md`), in name order.
pub const BUILTIN_HDRIS: [BuiltinHdri; 8] = [
    builtin!("city"),
    builtin!("courtyard"),
    builtin!("forest"),
    builtin!("interior"),
    builtin!("night"),
    builtin!("studio"),
    builtin!("sunrise"),
    builtin!("sunset"),
];

/// A procedural environment's parameters.
#[derive(Clone, Debug, PartialEq)]
pub enum Procedural {
    /// A sun over a clear sky.
    SunSky(SunSky),
    /// A CIE overcast sky of this zenith radiance.
    Overcast { zenith: f64 },
    /// Area lights on black walls.
    Studio { lights: Vec<AreaLight> },
}

impl Procedural {
    /// The environment at `height` rows.
    pub fn render(&self, height: usize) -> Result<EnvMap, EnvMapError> {
        match self {
            Procedural::SunSky(sky) => sky.render(height),
            Procedural::Overcast { zenith } => procedural_sky::overcast(height, *zenith),
            Procedural::Studio { lights } => procedural_sky::studio(height, lights),
        }
    }

    /// The canonical text of the parameters at `height` rows: what the content key hashes.
    /// Floats are written in Rust's shortest round-trip form, so equal text means equal bits.
    pub fn canonical_text(&self, height: usize) -> String {
        let mut s =
            format!("volux procedural environment v{PROCEDURAL_VERSION}\nheight {height}\n");
        match self {
            Procedural::SunSky(p) => s.push_str(&format!(
                "sun-sky elevation {:?} azimuth {:?} turbidity {:?} sun_irradiance {:?} sun_radius {:?}\n",
                p.elevation, p.azimuth, p.turbidity, p.sun_irradiance, p.sun_radius
            )),
            Procedural::Overcast { zenith } => s.push_str(&format!("overcast zenith {zenith:?}\n")),
            Procedural::Studio { lights } => {
                s.push_str(&format!("studio lights {}\n", lights.len()));
                for l in lights {
                    s.push_str(&format!(
                        "light direction {:?} radius {:?} irradiance {:?}\n",
                        l.direction, l.radius, l.irradiance
                    ));
                }
            }
        }
        s
    }
}

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

/// SHA-256 of what determines an entry's pixels: a file's bytes, or the canonical text of
/// procedural parameters (with the map height).
#[derive(Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ContentKey(pub [u8; 32]);

impl ContentKey {
    /// SHA-256 of `bytes`.
    pub fn of(bytes: &[u8]) -> ContentKey {
        ContentKey(Sha256::digest(bytes).into())
    }

    /// Lower-case hexadecimal, 64 characters.
    pub fn to_hex(&self) -> String {
        self.0.iter().map(|b| format!("{b:02x}")).collect()
    }
}

impl fmt::Display for ContentKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.to_hex())
    }
}

impl fmt::Debug for ContentKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "ContentKey({})", self.to_hex())
    }
}

/// One environment of a collection.
#[derive(Clone, Debug, PartialEq)]
pub struct HdriEntry {
    /// Stable, human-readable: `sunrise`, `sky-03`, `overcast-00`, `studio-05`, or
    /// `<folder name>/<file name>`.
    pub name: String,
    pub source: HdriSource,
}

/// An entry's content, read once: its key, and what decodes or renders to its map (so a file
/// is read once even when its light maps are not cached).
#[derive(Clone, Debug)]
pub struct SourceContent<'a> {
    key: ContentKey,
    kind: ContentKind<'a>,
}

#[derive(Clone, Debug)]
enum ContentKind<'a> {
    Bytes {
        bytes: Cow<'a, [u8]>,
        path: PathBuf,
    },
    Procedural {
        environment: &'a Procedural,
        height: usize,
    },
}

impl SourceContent<'_> {
    /// The content key.
    pub fn key(&self) -> ContentKey {
        self.key
    }

    /// Decodes (files, built-in maps) or renders (procedural) the environment map.
    pub fn environment(&self) -> Result<EnvMap, HdriError> {
        match &self.kind {
            ContentKind::Bytes { bytes, path } => Ok(io::load_bytes(bytes, path)?),
            ContentKind::Procedural {
                environment,
                height,
            } => Ok(environment.render(*height)?),
        }
    }
}

impl HdriEntry {
    /// Reads the entry's bytes (a file) or parameters and hashes them.
    pub fn read(&self) -> Result<SourceContent<'_>, HdriError> {
        let (key, kind) = match &self.source {
            HdriSource::Builtin(b) => (
                ContentKey::of(b.bytes),
                ContentKind::Bytes {
                    bytes: Cow::Borrowed(b.bytes),
                    path: PathBuf::from(b.path),
                },
            ),
            HdriSource::Procedural {
                environment,
                height,
            } => (
                ContentKey::of(environment.canonical_text(*height).as_bytes()),
                ContentKind::Procedural {
                    environment,
                    height: *height,
                },
            ),
            HdriSource::File(path) => {
                let bytes = fs::read(path).map_err(|source| HdriError::ReadFile {
                    path: path.clone(),
                    source,
                })?;
                (
                    ContentKey::of(&bytes),
                    ContentKind::Bytes {
                        bytes: Cow::Owned(bytes),
                        path: path.clone(),
                    },
                )
            }
        };
        Ok(SourceContent { key, kind })
    }

    /// The content key (reads a file whole).
    pub fn content_key(&self) -> Result<ContentKey, HdriError> {
        Ok(self.read()?.key())
    }

    /// The environment map.
    pub fn load(&self) -> Result<EnvMap, HdriError> {
        self.read()?.environment()
    }
}

/// What a collection holds; the `[hdri]` table of a dataset config.
///
/// ```toml
/// builtin = true
/// skies = 8
/// overcast = 2
/// studios = 6
/// folders = ["my_hdris"]
/// seed = 0
/// procedural_height = 256
/// ```
///
/// Every key is optional (the defaults above, without folders: 24 environments and no
/// downloads); an unknown key is an error naming it. Relative folders are taken as given
/// (relative to the working directory); a config loader that wants them relative to its file
/// joins them first.
#[derive(Clone, Debug, PartialEq, Deserialize)]
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
        }
    }
}

impl HdriCollectionConfig {
    /// Checks counts and the procedural height (the collection checks it is not empty).
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
        Ok(())
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
    #[error("{}: cannot read HDRI folder: {source}", path.display())]
    ReadFolder {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: HDRI folder has no .exr or .hdr files", path.display())]
    EmptyFolder { path: PathBuf },
    #[error("{}: cannot read HDRI: {source}", path.display())]
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

/// Salts that keep the parameter streams of the procedural kinds apart.
const SKY_STREAM: u64 = 0x736b_7900; // "sky"
const OVERCAST_STREAM: u64 = 0x6f76_6300; // "ovc"
const STUDIO_STREAM: u64 = 0x7374_7500; // "stu"

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
                Procedural::SunSky(random_sky(config.seed, i)),
            ));
        }
        for i in 0..config.overcast {
            entries.push(procedural(
                format!("overcast-{i:02}"),
                random_overcast(config.seed, i),
            ));
        }
        for i in 0..config.studios {
            entries.push(procedural(
                format!("studio-{i:02}"),
                random_studio(config.seed, i),
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

/// Entries for the embedded maps.
pub fn builtin_entries() -> Vec<HdriEntry> {
    BUILTIN_HDRIS
        .iter()
        .map(|b| HdriEntry {
            name: b.name.to_string(),
            source: HdriSource::Builtin(*b),
        })
        .collect()
}

/// Entries for the `.exr` / `.hdr` files of `folder` (not recursive), sorted by file name.
/// Hidden files (name starting with `.`) and sub-folders are skipped; other files are skipped
/// with a warning. An unreadable folder, or one without maps, is an error naming it.
pub fn folder_entries(folder: &Path) -> Result<Vec<HdriEntry>, HdriError> {
    let read_err = |source| HdriError::ReadFolder {
        path: folder.to_path_buf(),
        source,
    };
    let mut files = Vec::new();
    for entry in fs::read_dir(folder).map_err(read_err)? {
        let entry = entry.map_err(read_err)?;
        let path = entry.path();
        let file_name = entry.file_name();
        if file_name.to_string_lossy().starts_with('.') || path.is_dir() {
            continue;
        }
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        if matches!(ext.as_deref(), Some("exr" | "hdr")) {
            files.push((file_name, path));
        } else {
            tracing::warn!(
                "{}: ignored, not an .exr or .hdr environment map",
                path.display()
            );
        }
    }
    if files.is_empty() {
        return Err(HdriError::EmptyFolder {
            path: folder.to_path_buf(),
        });
    }
    files.sort();
    let folder_name = folder
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| folder.display().to_string());
    Ok(files
        .into_iter()
        .map(|(file_name, path)| HdriEntry {
            name: format!("{folder_name}/{}", file_name.to_string_lossy()),
            source: HdriSource::File(path),
        })
        .collect())
}

/// The parameter stream of entry `index` of the kind `stream` under `seed`: each input passes
/// through SplitMix64's output mix, so neighbouring seeds and indices give unrelated streams.
fn parameter_stream(seed: u64, stream: u64, index: usize) -> SplitMix64 {
    let mixed = SplitMix64::new(seed).next_u64() ^ stream;
    let mixed = SplitMix64::new(mixed).next_u64() ^ index as u64;
    SplitMix64::new(SplitMix64::new(mixed).next_u64())
}

fn uniform(rng: &mut SplitMix64, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * rng.next_f64()
}

/// Log-uniform in `[lo, hi]`: as likely to halve as to double.
fn log_uniform(rng: &mut SplitMix64, lo: f64, hi: f64) -> f64 {
    (lo.ln() + (hi.ln() - lo.ln()) * rng.next_f64()).exp()
}

/// Sunny sky `index`: sun 3 to 70 degrees high at any azimuth, turbidity 2 to 8, a disc
/// 0.27 to 0.86 degrees in radius delivering 2 to 8 (log-uniform) to a surface facing it.
/// The shipped maps' diffuse light maps peak at 0.4 to 2.6, that is irradiance 1.3 to 8.
pub fn random_sky(seed: u64, index: usize) -> SunSky {
    let mut rng = parameter_stream(seed, SKY_STREAM, index);
    SunSky {
        elevation: uniform(&mut rng, 3f64.to_radians(), 70f64.to_radians()),
        azimuth: uniform(&mut rng, 0.0, TAU),
        turbidity: uniform(&mut rng, 2.0, 8.0),
        sun_irradiance: log_uniform(&mut rng, 2.0, 8.0),
        sun_radius: uniform(&mut rng, 0.0047, 0.015),
    }
}

/// Overcast sky `index`: zenith radiance 0.6 to 2.5 (log-uniform), so an upward surface
/// receives 1.5 to 6.
pub fn random_overcast(seed: u64, index: usize) -> Procedural {
    let mut rng = parameter_stream(seed, OVERCAST_STREAM, index);
    Procedural::Overcast {
        zenith: log_uniform(&mut rng, 0.6, 2.5),
    }
}

/// Studio `index`: a key light in front of the face (which faces +z) and above it, to one
/// side; with a second light, a weaker fill on the other side in front; with a third, a rim
/// light behind and above. Disc radii 6 to 20 degrees (soft boxes), key irradiance 2 to 8
/// (log-uniform), fill 15-40% and rim 30-70% of it, each a random tint between warm
/// (1, 0.9, 0.8) and cool (0.85, 0.92, 1).
pub fn random_studio(seed: u64, index: usize) -> Procedural {
    let mut rng = parameter_stream(seed, STUDIO_STREAM, index);
    let count = 1 + (rng.next_u64() % 3) as usize;
    let side = if rng.next_u64() & 1 == 0 { 1.0 } else { -1.0 };
    let key = log_uniform(&mut rng, 2.0, 8.0);
    // (azimuth from +z, elevation, share of the key's irradiance), degrees.
    let mut placements = vec![(
        side * uniform(&mut rng, 20.0, 60.0),
        uniform(&mut rng, 15.0, 50.0),
        1.0,
    )];
    if count >= 2 {
        placements.push((
            -side * uniform(&mut rng, 20.0, 60.0),
            uniform(&mut rng, -5.0, 25.0),
            uniform(&mut rng, 0.15, 0.4),
        ));
    }
    if count >= 3 {
        placements.push((
            180.0 + uniform(&mut rng, -50.0, 50.0),
            uniform(&mut rng, 20.0, 60.0),
            uniform(&mut rng, 0.3, 0.7),
        ));
    }
    let lights = placements
        .into_iter()
        .map(|(azimuth, elevation, share)| {
            let radius = uniform(&mut rng, 6.0, 20.0).to_radians();
            let t = rng.next_f64();
            let tint = [1.0 - 0.15 * t, 0.9 + 0.02 * t, 0.8 + 0.2 * t];
            AreaLight {
                direction: sun_direction(elevation.to_radians(), azimuth.to_radians()),
                radius,
                irradiance: tint.map(|c| (c * key * share) as f32),
            }
        })
        .collect();
    Procedural::Studio { lights }
}

#[cfg(test)]
mod tests {
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
}
