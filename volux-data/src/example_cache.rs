//! An on-disk cache of training examples (`volux data build`): examples `0..n` of a
//! [`Dataset`], in shards of a fixed number of examples, with a manifest.
//!
//! - A shard is one file: a header (magic, version, sizes, count) and the examples' layers as
//!   little-endian f32, so example `i` is read with one seek.
//! - `manifest.toml` records the dataset's fingerprint (a hash of everything examples depend
//!   on: the data config, the light maps' keys, the sizes and the renderer's version), the
//!   shard size and, per finished shard, its file name and SHA-256.
//! - A build writes each shard atomically (temporary name, then rename) and rewrites the
//!   manifest after each shard, so an interrupted build resumes: finished shards whose file
//!   still has its hash are kept, the rest are made. Reading checks each shard's hash once
//!   per process, before its first example is used, so a file changed after the build is an
//!   error naming it, not silently different training data. A changed fingerprint or shard size makes
//!   every shard stale; a larger example count only adds shards. Stale files are removed.

use std::fs;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sha2::{Digest as _, Sha256};
use volux_envmap::durable::{self, FileError};
use volux_model::pose::Pose;

use crate::batch::Batch;
use crate::dataset::{DataError, Dataset};
use crate::digest::{Digest, hex};
use crate::layers::{Layer, Layers};
use crate::training_sample::{LightingDraw, TrainingSample};

/// Bump when the examples a dataset makes change (rendering, relighting, layer conventions), so
/// that caches built before are rebuilt.
pub const EXAMPLE_FORMAT_VERSION: u32 = 1;

const MAGIC: &[u8; 8] = b"VOLUXEX1";
const HEADER_BYTES: usize = 8 + 4 * 4;
const MANIFEST: &str = "manifest.toml";

/// How many examples, in shards of how many.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CacheSpec {
    pub examples: u64,
    pub shard_size: usize,
}

/// The cache's table of contents.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    pub format_version: u32,
    pub fingerprint: String,
    pub side: usize,
    pub factor: usize,
    pub spec: CacheSpec,
    /// The layers each example stores, in the order of [`Layer::ALL`] (a photos-only
    /// dataset's examples have the photo alone). Absent: every layer.
    #[serde(default = "every_layer_name")]
    pub layers: Vec<String>,
    /// Finished shards, by index.
    pub shards: Vec<ShardEntry>,
}

fn every_layer_name() -> Vec<String> {
    layer_names(&Layers::from_fn(|_| true))
}

/// The names of the `provided` layers, in the order of [`Layer::ALL`].
fn layer_names(provided: &Layers<bool>) -> Vec<String> {
    provided
        .iter()
        .filter(|(_, p)| **p)
        .map(|(l, _)| l.name().to_string())
        .collect()
}

/// The layers a manifest's names list, or the first name that is no layer (or out of order).
fn parse_layers(names: &[String]) -> Result<Layers<bool>, String> {
    let provided = Layers::from_fn(|l| names.iter().any(|n| n == l.name()));
    if layer_names(&provided) != names {
        let bad = names
            .iter()
            .find(|n| !Layer::ALL.iter().any(|l| l.name() == n.as_str()))
            .map_or_else(
                || format!("layers {names:?} are repeated or out of order"),
                |n| format!("no layer is called {n:?}"),
            );
        return Err(bad);
    }
    Ok(provided)
}

#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ShardEntry {
    pub index: u64,
    pub file: String,
    pub examples: usize,
    pub sha256: String,
}

/// What a build did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BuildReport {
    pub shards: usize,
    pub built: usize,
    pub kept: usize,
    pub examples: u64,
}

/// Why a cache cannot be built or read.
#[derive(Debug, thiserror::Error)]
pub enum CacheError {
    #[error("{path}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {message}")]
    Corrupt { path: PathBuf, message: String },
    #[error("{}: not a cache manifest", path.display())]
    Manifest {
        path: PathBuf,
        #[source]
        source: toml::de::Error,
    },
    #[error("{path}: cannot write")]
    Write {
        path: PathBuf,
        #[source]
        source: FileError,
    },
    #[error("cache spec: {0}")]
    Spec(String),
    #[error(
        "{}: the cache's {examples} examples need {:.1} GiB more and the disk has {:.1} GiB free; lower [data.cache] examples or free space",
        dir.display(),
        *needed as f64 / GIB,
        *available as f64 / GIB
    )]
    NoSpace {
        dir: PathBuf,
        examples: u64,
        needed: u64,
        available: u64,
    },
    #[error("example {index} is outside the cache's {len} examples")]
    OutOfRange { index: u64, len: u64 },
    #[error(transparent)]
    Data(#[from] DataError),
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> CacheError + '_ {
    move |source| CacheError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// The fingerprint of everything a dataset's examples depend on, as hex SHA-256.
pub fn fingerprint(parts: &[&[u8]]) -> String {
    let mut hash = Sha256::new();
    hash.update(EXAMPLE_FORMAT_VERSION.to_le_bytes());
    for part in parts {
        // Length-prefixed, so that parts cannot run into each other.
        hash.update((part.len() as u64).to_le_bytes());
        hash.update(part);
    }
    hex(&hash.finalize())
}

fn shard_name(index: u64) -> String {
    format!("shard-{index:05}.bin")
}

/// Floats per example at `side` and `side / factor` with the `provided` layers.
fn example_floats(side: usize, factor: usize, provided: &Layers<bool>) -> usize {
    // pose (2), draw (2), then every provided layer in the order of `Layer::ALL`.
    4 + provided
        .iter()
        .filter(|(_, p)| **p)
        .map(|(l, _)| l.floats(side, factor))
        .sum::<usize>()
}

fn encode_example(out: &mut Vec<u8>, s: &TrainingSample) {
    let mut put = |v: f32| out.extend_from_slice(&v.to_le_bytes());
    put(s.pose.yaw as f32);
    put(s.pose.pitch as f32);
    put(s.draw.map as f32);
    put(s.draw.yaw as f32);
    for (_, values) in s.layers.iter() {
        values.iter().for_each(|&v| put(v));
    }
}

fn decode_example(
    bytes: &[u8],
    side: usize,
    factor: usize,
    provided: &Layers<bool>,
) -> TrainingSample {
    let floats: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    let pose = Pose::new(f64::from(floats[0]), f64::from(floats[1]));
    let draw = LightingDraw {
        map: floats[2] as usize,
        yaw: f64::from(floats[3]),
    };
    let mut at = 4;
    let mut take = |n: usize| {
        let part = &floats[at..at + n];
        at += n;
        part
    };
    let layers = Layers::from_fn(|layer| {
        let n = if *provided.get(layer) {
            layer.floats(side, factor)
        } else {
            0
        };
        take(n).to_vec()
    });
    TrainingSample {
        side,
        factor,
        pose,
        draw,
        layers,
    }
}

fn read_manifest(dir: &Path) -> Result<Option<Manifest>, CacheError> {
    let path = dir.join(MANIFEST);
    match fs::read_to_string(&path) {
        Ok(text) => toml::from_str(&text)
            .map(Some)
            .map_err(|source| CacheError::Manifest { path, source }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(io_error(&path)(e)),
    }
}

/// Writes `bytes` to `path` through a temporary file and a rename (`durable::write_atomically`).
fn write_atomically(path: &Path, bytes: &[u8]) -> Result<(), CacheError> {
    durable::write_atomically(path, |tmp| {
        fs::write(tmp, bytes).map_err(FileError::at(tmp))
    })
    .map_err(|source| CacheError::Write {
        path: path.to_path_buf(),
        source,
    })
}

fn write_manifest(dir: &Path, manifest: &Manifest) -> Result<(), CacheError> {
    let text = toml::to_string(manifest).expect("the manifest serialises");
    write_atomically(&dir.join(MANIFEST), text.as_bytes())
}

const GIB: f64 = (1u64 << 30) as f64;

/// Bytes free to an unprivileged writer on the file system holding `dir`, if the OS says.
fn free_bytes(dir: &Path) -> Option<u128> {
    use std::os::unix::ffi::OsStrExt;
    let path = std::ffi::CString::new(dir.as_os_str().as_bytes()).ok()?;
    let mut stat = std::mem::MaybeUninit::<libc::statvfs>::uninit();
    // SAFETY: `path` is a NUL-terminated string and `stat` is writable storage for the
    // result, read only when the call succeeds.
    let ok = unsafe { libc::statvfs(path.as_ptr(), stat.as_mut_ptr()) } == 0;
    // SAFETY: statvfs filled `stat` when it returned 0.
    let stat = ok.then(|| unsafe { stat.assume_init() })?;
    Some(u128::from(stat.f_bavail) * u128::from(stat.f_frsize))
}

fn file_sha256(path: &Path) -> Result<String, CacheError> {
    let bytes = fs::read(path).map_err(io_error(path))?;
    Ok(Digest::of(&bytes).to_hex())
}

/// Builds (or completes) the cache of `spec.examples` examples of `dataset` in `dir`;
/// `fingerprint` identifies what the examples depend on (see [`fingerprint`]).
/// `progress(done, total)` is called after each shard, with shards kept counted as done.
pub fn build(
    dir: &Path,
    dataset: &Dataset,
    fingerprint: &str,
    spec: CacheSpec,
    progress: &dyn Fn(usize, usize),
) -> Result<BuildReport, CacheError> {
    if spec.examples == 0 || spec.shard_size == 0 {
        return Err(CacheError::Spec(format!(
            "examples = {} and shard_size = {} must be at least 1",
            spec.examples, spec.shard_size
        )));
    }
    fs::create_dir_all(dir).map_err(io_error(dir))?;
    let (side, factor) = (dataset.side(), dataset.factor());
    let shards = spec.examples.div_ceil(spec.shard_size as u64);
    let size_of =
        |s: u64| (spec.examples - s * spec.shard_size as u64).min(spec.shard_size as u64) as usize;
    // Keep what an earlier build with the same fingerprint and shard size finished, if the
    // file is still intact and holds as many examples as the shard should now.
    let provided = dataset.provided();
    let mut manifest = Manifest {
        format_version: EXAMPLE_FORMAT_VERSION,
        fingerprint: fingerprint.to_string(),
        side,
        factor,
        spec,
        layers: layer_names(&provided),
        shards: Vec::new(),
    };
    if let Some(old) = read_manifest(dir)? {
        let compatible = old.format_version == EXAMPLE_FORMAT_VERSION
            && old.fingerprint == fingerprint
            && (old.side, old.factor) == (side, factor)
            && old.layers == manifest.layers
            && old.spec.shard_size == spec.shard_size;
        for entry in old.shards {
            let path = dir.join(&entry.file);
            let intact = compatible
                && entry.index < shards
                && entry.examples == size_of(entry.index)
                && file_sha256(&path).is_ok_and(|h| h == entry.sha256);
            if intact {
                manifest.shards.push(entry);
            } else {
                tracing::info!("{}: stale, rebuilding", path.display());
                let _ = fs::remove_file(&path);
            }
        }
    }
    let kept = manifest.shards.len();
    let floats = example_floats(side, factor, &provided);
    // Refuse a build the disk cannot hold before writing any of it (it would run until the
    // disk is full, shard by shard).
    let shards_left = u128::from(shards) - kept as u128;
    if shards_left > 0 {
        let kept_examples: u128 = manifest.shards.iter().map(|e| e.examples as u128).sum();
        let to_build = u128::from(spec.examples) - kept_examples;
        let needed = shards_left * HEADER_BYTES as u128 + to_build * floats as u128 * 4;
        if let Some(available) = free_bytes(dir).filter(|free| needed > *free) {
            return Err(CacheError::NoSpace {
                dir: dir.to_path_buf(),
                examples: spec.examples,
                needed: u64::try_from(needed).unwrap_or(u64::MAX),
                available: u64::try_from(available).unwrap_or(u64::MAX),
            });
        }
    }
    let mut built = 0;
    for s in 0..shards {
        if manifest.shards.iter().any(|e| e.index == s) {
            continue;
        }
        let n = size_of(s);
        let first = s * spec.shard_size as u64;
        let examples = (first..first + n as u64)
            .into_par_iter()
            .map(|i| dataset.example(i))
            .collect::<Result<Vec<_>, _>>()?;
        let mut bytes = Vec::with_capacity(HEADER_BYTES + n * floats * 4);
        bytes.extend_from_slice(MAGIC);
        for v in [EXAMPLE_FORMAT_VERSION, side as u32, factor as u32, n as u32] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        for e in &examples {
            encode_example(&mut bytes, e);
        }
        let file = shard_name(s);
        write_atomically(&dir.join(&file), &bytes)?;
        manifest.shards.push(ShardEntry {
            index: s,
            file,
            examples: n,
            sha256: Digest::of(&bytes).to_hex(),
        });
        manifest.shards.sort_by_key(|e| e.index);
        write_manifest(dir, &manifest)?;
        built += 1;
        progress(manifest.shards.len(), shards as usize);
    }
    write_manifest(dir, &manifest)?;
    Ok(BuildReport {
        shards: shards as usize,
        built,
        kept,
        examples: spec.examples,
    })
}

/// A finished cache, read example by example.
#[derive(Clone, Debug)]
pub struct ExampleCache {
    dir: PathBuf,
    manifest: Manifest,
    /// The layers the examples store (the manifest's `layers`).
    provided: Layers<bool>,
    /// Per shard, whether its file still has the manifest's SHA-256: checked once per process,
    /// the first time one of its examples is read.
    verified: Vec<std::sync::OnceLock<Result<(), String>>>,
}

impl ExampleCache {
    /// Opens the cache in `dir`: the manifest must list every shard (a finished build) and
    /// every shard file must have the size its examples need.
    pub fn open(dir: &Path) -> Result<ExampleCache, CacheError> {
        let manifest = read_manifest(dir)?.ok_or_else(|| CacheError::Corrupt {
            path: dir.join(MANIFEST),
            message: "no manifest: build the cache with `volux data build`".into(),
        })?;
        let shards = manifest
            .spec
            .examples
            .div_ceil(manifest.spec.shard_size as u64);
        if manifest.format_version != EXAMPLE_FORMAT_VERSION {
            return Err(CacheError::Corrupt {
                path: dir.join(MANIFEST),
                message: format!(
                    "format version {} (this build reads {EXAMPLE_FORMAT_VERSION}): rebuild it",
                    manifest.format_version
                ),
            });
        }
        if manifest.shards.len() as u64 != shards {
            return Err(CacheError::Corrupt {
                path: dir.join(MANIFEST),
                message: format!(
                    "{} of {shards} shards finished: run `volux data build` again to complete it",
                    manifest.shards.len()
                ),
            });
        }
        let provided = parse_layers(&manifest.layers).map_err(|message| CacheError::Corrupt {
            path: dir.join(MANIFEST),
            message,
        })?;
        let floats = example_floats(manifest.side, manifest.factor, &provided);
        for entry in &manifest.shards {
            let path = dir.join(&entry.file);
            let len = fs::metadata(&path).map_err(io_error(&path))?.len() as usize;
            let want = HEADER_BYTES + entry.examples * floats * 4;
            if len != want {
                return Err(CacheError::Corrupt {
                    path,
                    message: format!("{len} bytes, expected {want}"),
                });
            }
        }
        let verified = manifest.shards.iter().map(|_| Default::default()).collect();
        Ok(ExampleCache {
            dir: dir.to_path_buf(),
            manifest,
            provided,
            verified,
        })
    }

    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// Which layers the examples have (the others are empty).
    pub fn provided(&self) -> Layers<bool> {
        self.provided.clone()
    }

    pub fn len(&self) -> u64 {
        self.manifest.spec.examples
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Example `index` (`< len()`).
    pub fn example(&self, index: u64) -> Result<TrainingSample, CacheError> {
        if index >= self.len() {
            return Err(CacheError::OutOfRange {
                index,
                len: self.len(),
            });
        }
        let size = self.manifest.spec.shard_size as u64;
        let shard = (index / size) as usize;
        let entry = &self.manifest.shards[shard];
        let path = self.dir.join(&entry.file);
        let intact = self.verified[shard].get_or_init(|| match file_sha256(&path) {
            Ok(h) if h == entry.sha256 => Ok(()),
            Ok(h) => Err(format!(
                "SHA-256 {h} differs from the manifest's {}: the file changed after the build; run `volux data build` again",
                entry.sha256
            )),
            Err(e) => Err(e.to_string()),
        });
        if let Err(message) = intact {
            return Err(CacheError::Corrupt {
                path,
                message: message.clone(),
            });
        }
        let (side, factor) = (self.manifest.side, self.manifest.factor);
        let bytes_per = example_floats(side, factor, &self.provided) * 4;
        let mut file = fs::File::open(&path).map_err(io_error(&path))?;
        let mut header = [0u8; HEADER_BYTES];
        file.read_exact(&mut header).map_err(io_error(&path))?;
        if &header[..8] != MAGIC {
            return Err(CacheError::Corrupt {
                path,
                message: "not a volux example shard".into(),
            });
        }
        let offset = HEADER_BYTES + (index % size) as usize * bytes_per;
        file.seek(SeekFrom::Start(offset as u64))
            .map_err(io_error(&path))?;
        let mut bytes = vec![0u8; bytes_per];
        file.read_exact(&mut bytes).map_err(io_error(&path))?;
        Ok(decode_example(&bytes, side, factor, &self.provided))
    }

    /// Batch `index` of `size` examples: examples `index * size ..`, wrapping around the cache.
    pub fn batch(&self, index: u64, size: usize) -> Result<Batch, CacheError> {
        let first = index * size as u64;
        let examples = (first..first + size as u64)
            .into_par_iter()
            .map(|i| self.example(i % self.len()))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Batch::collate(index, &examples))
    }
}

#[cfg(test)]
mod tests;
