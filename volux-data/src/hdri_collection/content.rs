//! Content keys: SHA-256 of what determines an entry's pixels, so that light maps are cached by
//! content rather than by name, and an entry's content read once.

use std::borrow::Cow;
use std::fs;
use std::path::PathBuf;

use volux_envmap::{EnvMap, io};

use crate::digest::Digest;

use super::{HdriEntry, HdriError, HdriSource, Procedural};

/// SHA-256 of what determines an entry's pixels: a file's bytes, or the canonical text of
/// procedural parameters (with the map height).
pub type ContentKey = Digest;

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
