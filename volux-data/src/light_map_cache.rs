//! The on-disk light-map cache: one file per (environment content, preconvolution options).
//!
//! # Key
//!
//! [`cache_key`] is SHA-256 of a text naming the cache format version, the environment's
//! [`ContentKey`] (SHA-256 of its file bytes, or of its procedural parameters and map height),
//! and every preconvolution option: exponents in order, tolerance, taper and maximum height
//! (floats in shortest round-trip form). The file is `<key in hex>.vlm` in the cache
//! directory, so renaming an HDRI keeps its cache entry and changing one byte of it does not.
//!
//! # File format (version [`CACHE_FORMAT_VERSION`], all numbers little-endian)
//!
//! | bytes | what |
//! |---|---|
//! | 8 | magic `VLXLMAP\0` |
//! | 4 | format version (u32) |
//! | 32 | the cache key the file was written under |
//! | 4 | number of light maps `m` (u32) |
//! | 28 per map | exponent (u32), width (u32), height (u32), clamped count (u64), ringing (f64) |
//! | 12 `w h` per map | texels, row-major from the top row, RGB f32 |
//! | 32 | SHA-256 of every byte before it |
//!
//! A file is used only if every check passes: magic, version, key, the exponents asked for in
//! order, 2:1 shapes of at most [`MAX_HEIGHT`] rows, the exact length those imply, the checksum,
//! and finite non-negative texels. Anything else is a [`CacheFileError`]: the caller logs it
//! and recomputes (a cache is never trusted and never panics). Files are written atomically
//! (temporary file, then rename), so a crash leaves the old file or none.

use std::fs;
use std::path::{Path, PathBuf};

use sha2::{Digest as _, Sha256};
use volux_envmap::{EnvMapError, LightMap, LightMapSet, PreconvolveOptions, durable};

use crate::digest::Digest;
use crate::hdri_collection::ContentKey;

/// Version of the file format and of the key text. Bump it whenever either changes, or when
/// `volux_envmap::preconvolve` computes different light maps for the same options.
pub const CACHE_FORMAT_VERSION: u32 = 1;

/// The first eight bytes of a cache file.
pub const MAGIC: [u8; 8] = *b"VLXLMAP\0";

/// Largest light-map height a cache file may declare (preconvolution tops out at 2048).
pub const MAX_HEIGHT: usize = 4096;

/// Largest number of light maps in one file.
const MAX_MAPS: usize = 64;

const HEADER_BYTES: usize = 8 + 4 + 32 + 4;
const MAP_HEADER_BYTES: usize = 4 + 4 + 4 + 8 + 8;
const CHECKSUM_BYTES: usize = 32;

/// The key of one cached light-map set: the digest of [`cache_key`]'s text.
pub type CacheKey = Digest;

/// The cache key of the light maps of the environment with `content` under `options`.
pub fn cache_key(content: ContentKey, options: &PreconvolveOptions) -> CacheKey {
    let exponents: Vec<String> = options.exponents.iter().map(u32::to_string).collect();
    let text = format!(
        "volux light-map cache v{CACHE_FORMAT_VERSION}\ncontent {}\nexponents {}\ntolerance {:?}\ntaper {:?}\nmax_height {}\n",
        content.to_hex(),
        exponents.join(","),
        options.tolerance,
        options.taper,
        options.max_height,
    );
    Digest::of(text.as_bytes())
}

/// Why a cache file was not used.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CacheFileError {
    #[error("{len} bytes is too short for a light-map cache file")]
    TooShort { len: usize },
    #[error("not a light-map cache file (bad magic)")]
    Magic,
    #[error("format version {found}, expected {CACHE_FORMAT_VERSION}")]
    Version { found: u32 },
    #[error("written under key {found}, expected {expected}")]
    Key { found: String, expected: String },
    #[error("holds exponents {found:?}, expected {expected:?}")]
    Exponents { found: Vec<u32>, expected: Vec<u32> },
    #[error("light map {index} is {width}x{height}: not 2:1 or taller than {MAX_HEIGHT}")]
    Shape {
        index: usize,
        width: usize,
        height: usize,
    },
    #[error("{actual} bytes, the header implies {expected}")]
    Length { expected: u64, actual: usize },
    #[error("checksum mismatch (corrupt file)")]
    Checksum,
    #[error("light map n={exponent} has a negative or non-finite value at texel {index}")]
    Texel { exponent: u32, index: usize },
}

/// Why the cache could not be used at all or a file not written.
#[derive(Debug, thiserror::Error)]
pub enum CacheError {
    #[error("{}: cannot create or open the light-map cache directory", path.display())]
    Dir {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: is not a directory (light-map cache)", path.display())]
    NotADir { path: PathBuf },
    #[error("cannot write light-map cache file")]
    Write(#[source] EnvMapError),
}

/// The bytes of a cache file holding `set` under `key`.
pub fn encode(key: CacheKey, set: &LightMapSet) -> Vec<u8> {
    let maps = set.maps();
    let texels: usize = maps.iter().map(|m| m.texels().len()).sum();
    let mut out = Vec::with_capacity(
        HEADER_BYTES + maps.len() * MAP_HEADER_BYTES + 12 * texels + CHECKSUM_BYTES,
    );
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&CACHE_FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&key.0);
    out.extend_from_slice(&(maps.len() as u32).to_le_bytes());
    for m in maps {
        out.extend_from_slice(&m.exponent().to_le_bytes());
        out.extend_from_slice(&(m.width() as u32).to_le_bytes());
        out.extend_from_slice(&(m.height() as u32).to_le_bytes());
        out.extend_from_slice(&(m.clamped() as u64).to_le_bytes());
        out.extend_from_slice(&m.ringing().to_le_bytes());
    }
    for m in maps {
        for v in m.texels().iter().flatten() {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    let checksum = Sha256::digest(&out);
    out.extend_from_slice(&checksum);
    out
}

/// Reads little-endian numbers from the front of a slice whose length was checked.
struct Reader<'a>(&'a [u8]);

impl Reader<'_> {
    fn take<const N: usize>(&mut self) -> [u8; N] {
        let (head, rest) = self.0.split_at(N);
        self.0 = rest;
        head.try_into().expect("split_at gave N bytes")
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }
    fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.take())
    }
    fn f64(&mut self) -> f64 {
        f64::from_le_bytes(self.take())
    }
}

/// The light maps in cache-file `bytes`, if it was written under `key` for `exponents` and is
/// intact (see the module docs for every check).
pub fn decode(
    bytes: &[u8],
    key: CacheKey,
    exponents: &[u32],
) -> Result<LightMapSet, CacheFileError> {
    if bytes.len() < HEADER_BYTES + CHECKSUM_BYTES {
        return Err(CacheFileError::TooShort { len: bytes.len() });
    }
    let mut r = Reader(bytes);
    if r.take::<8>() != MAGIC {
        return Err(CacheFileError::Magic);
    }
    let version = r.u32();
    if version != CACHE_FORMAT_VERSION {
        return Err(CacheFileError::Version { found: version });
    }
    let found_key = r.take::<32>();
    if found_key != key.0 {
        return Err(CacheFileError::Key {
            found: Digest(found_key).to_hex(),
            expected: key.to_hex(),
        });
    }
    let count = r.u32() as usize;
    if count > MAX_MAPS || bytes.len() < HEADER_BYTES + count * MAP_HEADER_BYTES + CHECKSUM_BYTES {
        return Err(CacheFileError::TooShort { len: bytes.len() });
    }
    struct MapHeader {
        exponent: u32,
        width: usize,
        height: usize,
        clamped: u64,
        ringing: f64,
    }
    let headers: Vec<MapHeader> = (0..count)
        .map(|_| MapHeader {
            exponent: r.u32(),
            width: r.u32() as usize,
            height: r.u32() as usize,
            clamped: r.u64(),
            ringing: r.f64(),
        })
        .collect();
    let found: Vec<u32> = headers.iter().map(|h| h.exponent).collect();
    if found != exponents {
        return Err(CacheFileError::Exponents {
            found,
            expected: exponents.to_vec(),
        });
    }
    let mut expected = (HEADER_BYTES + count * MAP_HEADER_BYTES + CHECKSUM_BYTES) as u64;
    for (index, h) in headers.iter().enumerate() {
        if h.height == 0 || h.height > MAX_HEIGHT || h.width != 2 * h.height {
            return Err(CacheFileError::Shape {
                index,
                width: h.width,
                height: h.height,
            });
        }
        expected += 12 * (h.width * h.height) as u64;
    }
    if expected != bytes.len() as u64 {
        return Err(CacheFileError::Length {
            expected,
            actual: bytes.len(),
        });
    }
    let (body, checksum) = bytes.split_at(bytes.len() - CHECKSUM_BYTES);
    if Sha256::digest(body).as_slice() != checksum {
        return Err(CacheFileError::Checksum);
    }
    let mut maps = Vec::with_capacity(count);
    for h in headers {
        let texels: Vec<[f32; 3]> = (0..h.width * h.height)
            .map(|_| std::array::from_fn(|_| f32::from_le_bytes(r.take())))
            .collect();
        if let Some(index) = texels
            .iter()
            .position(|t| t.iter().any(|v| !v.is_finite() || *v < 0.0))
        {
            return Err(CacheFileError::Texel {
                exponent: h.exponent,
                index,
            });
        }
        maps.push(
            LightMap::new(h.exponent, h.width, h.height, texels)
                .with_clamped(h.clamped as usize, h.ringing),
        );
    }
    Ok(LightMapSet::new(maps))
}

/// A directory of cache files.
#[derive(Clone, Debug)]
pub struct LightMapCache {
    dir: PathBuf,
}

impl LightMapCache {
    /// The cache in `dir`, created (with its parents) if missing. An error names `dir` if it
    /// cannot be created or is not a directory. A directory that exists but cannot be written
    /// is accepted: each failed write is reported by [`LightMapCache::store`].
    pub fn open(dir: &Path) -> Result<LightMapCache, CacheError> {
        if dir.exists() && !dir.is_dir() {
            return Err(CacheError::NotADir {
                path: dir.to_path_buf(),
            });
        }
        fs::create_dir_all(dir).map_err(|source| CacheError::Dir {
            path: dir.to_path_buf(),
            source,
        })?;
        Ok(LightMapCache {
            dir: dir.to_path_buf(),
        })
    }

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The file of `key`.
    pub fn path(&self, key: CacheKey) -> PathBuf {
        self.dir.join(format!("{}.vlm", key.to_hex()))
    }

    /// The cached light maps of `key` for `exponents`, or `None` if there is no file or it
    /// cannot be used; an unusable file is logged with `tracing::warn` naming it and why.
    pub fn load(&self, key: CacheKey, exponents: &[u32]) -> Option<LightMapSet> {
        let path = self.path(key);
        let bytes = match fs::read(&path) {
            Ok(bytes) => bytes,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return None,
            Err(e) => {
                tracing::warn!(
                    "{}: cannot read light-map cache file, recomputing: {e}",
                    path.display()
                );
                return None;
            }
        };
        match decode(&bytes, key, exponents) {
            Ok(set) => Some(set),
            Err(e) => {
                tracing::warn!(
                    "{}: light-map cache file not used, recomputing: {e}",
                    path.display()
                );
                None
            }
        }
    }

    /// Writes `set` under `key`, atomically; returns the path written.
    pub fn store(&self, key: CacheKey, set: &LightMapSet) -> Result<PathBuf, CacheError> {
        let path = self.path(key);
        let bytes = encode(key, set);
        durable::write_atomically(&path, |tmp| {
            fs::write(tmp, &bytes).map_err(|source| EnvMapError::Io {
                path: path.clone(),
                source,
            })
        })
        .map_err(CacheError::Write)?;
        Ok(path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set() -> LightMapSet {
        let map = |n: u32, h: usize| {
            let texels = (0..2 * h * h)
                .map(|i| [i as f32, 0.5 * i as f32, 1e-3 * n as f32])
                .collect();
            LightMap::new(n, 2 * h, h, texels).with_clamped(3, 1.5e-4)
        };
        LightMapSet::new(vec![map(1, 4), map(16, 6)])
    }

    fn key() -> CacheKey {
        cache_key(
            ContentKey::of(b"map"),
            &PreconvolveOptions::with_exponents(&[1, 16]),
        )
    }

    #[test]
    fn round_trip_is_bit_identical_and_sized_as_documented() {
        let bytes = encode(key(), &set());
        let texels = 2 * 4 * 4 + 2 * 6 * 6;
        assert_eq!(
            bytes.len(),
            HEADER_BYTES + 2 * MAP_HEADER_BYTES + 12 * texels + CHECKSUM_BYTES
        );
        assert_eq!(decode(&bytes, key(), &[1, 16]).unwrap(), set());
    }

    #[test]
    fn every_kind_of_damage_is_detected() {
        let good = encode(key(), &set());
        let exps = [1, 16];
        // Truncated anywhere, garbage, empty.
        for keep in [0, 10, HEADER_BYTES + 3, good.len() / 2, good.len() - 1] {
            assert!(decode(&good[..keep], key(), &exps).is_err(), "kept {keep}");
        }
        assert_eq!(
            decode(&vec![0x5a; good.len()], key(), &exps),
            Err(CacheFileError::Magic)
        );
        // One flipped texel bit: the checksum.
        let mut bad = good.clone();
        bad[good.len() - CHECKSUM_BYTES - 5] ^= 1;
        assert_eq!(decode(&bad, key(), &exps), Err(CacheFileError::Checksum));
        // Another version, key or exponent list.
        let mut bad = good.clone();
        bad[8] = 9;
        assert_eq!(
            decode(&bad, key(), &exps),
            Err(CacheFileError::Version { found: 9 })
        );
        let other = cache_key(ContentKey::of(b"other"), &PreconvolveOptions::default());
        assert!(matches!(
            decode(&good, other, &exps),
            Err(CacheFileError::Key { .. })
        ));
        assert!(matches!(
            decode(&good, key(), &[1, 32]),
            Err(CacheFileError::Exponents { .. })
        ));
        // A header claiming a huge map is a length error, not an allocation.
        let mut bad = good.clone();
        bad[HEADER_BYTES + 4..HEADER_BYTES + 12].copy_from_slice(&[0, 16, 0, 0, 0, 8, 0, 0]);
        assert!(matches!(
            decode(&bad, key(), &exps),
            Err(CacheFileError::Length { .. })
        ));
        // Extra bytes at the end.
        let mut long = good.clone();
        long.push(0);
        assert!(matches!(
            decode(&long, key(), &exps),
            Err(CacheFileError::Length { .. })
        ));
    }

    #[test]
    fn the_key_covers_content_and_every_option() {
        let base = PreconvolveOptions::default();
        let content = ContentKey::of(b"map");
        let k = cache_key(content, &base);
        assert_eq!(k, cache_key(content, &base.clone()));
        assert_ne!(k, cache_key(ContentKey::of(b"maq"), &base));
        let variants = [
            PreconvolveOptions::with_exponents(&[1, 16, 32]),
            PreconvolveOptions::with_exponents(&[16, 1, 32, 64]),
            PreconvolveOptions {
                tolerance: 1e-3,
                ..base.clone()
            },
            PreconvolveOptions {
                taper: 0.25,
                ..base.clone()
            },
            PreconvolveOptions {
                max_height: 1024,
                ..base.clone()
            },
        ];
        for v in &variants {
            assert_ne!(k, cache_key(content, v), "{v:?}");
        }
    }
}
