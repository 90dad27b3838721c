//! Content keys: SHA-256 of what determines an entry's pixels, so that light maps are cached by
//! content rather than by name, and an entry's content read once.

use std::borrow::Cow;
use std::fmt;
use std::fs;
use std::path::PathBuf;

use sha2::{Digest, Sha256};
use volux_envmap::{EnvMap, io};

use super::{HdriEntry, HdriError, HdriSource, Procedural};

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
