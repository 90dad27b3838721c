//! The light maps of a whole HDRI collection, in memory: each entry preconvolved once (or read
//! from the on-disk cache), in parallel with rayon.
//!
//! Cache directory policy: `None` means no disk cache. `Some(dir)` is created with its parents
//! if missing; if it cannot be created or is not a directory, building fails with an error
//! naming it (the caller asked for a cache there). A cache file that cannot be read or used is
//! logged and recomputed; one that cannot be written (a read-only directory, a full disk) is
//! logged and counted in [`CacheStats::write_failures`], and the bank is built regardless:
//! the cache only saves time.

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use rayon::prelude::*;
use volux_envmap::{EnvMapError, LightMapSet, PreconvolveOptions, preconvolve};

use crate::hdri_collection::{HdriCollection, HdriEntry, HdriError};
use crate::light_map_cache::{CacheError, CacheKey, LightMapCache, cache_key};

/// How the light maps of a bank were obtained.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CacheStats {
    /// Entries read from the cache.
    pub hits: usize,
    /// Entries preconvolved (no cache, no file, or an unusable file).
    pub misses: usize,
    /// Cache files that could not be written.
    pub write_failures: usize,
}

/// Why a bank could not be built.
#[derive(Debug, thiserror::Error)]
pub enum LightMapBankError {
    #[error("light-map options")]
    Options(#[source] EnvMapError),
    #[error(transparent)]
    Cache(#[from] CacheError),
    #[error("HDRI `{name}`")]
    Entry {
        name: String,
        #[source]
        source: HdriError,
    },
}

/// The light maps of every entry of a collection, in the collection's order. The maps are
/// shared ([`LightMapBank::shared`]), not copied, by the dataset and the trainer: a bank of
/// hundreds of environments is held once.
#[derive(Clone, Debug)]
pub struct LightMapBank {
    names: Vec<String>,
    keys: Vec<CacheKey>,
    sets: Arc<Vec<LightMapSet>>,
    options: PreconvolveOptions,
    stats: CacheStats,
}

enum Outcome {
    Hit,
    Miss { written: bool },
}

impl LightMapBank {
    /// Preconvolves every entry of `collection` with `options`, through the cache in
    /// `cache_dir` if given (see the module docs for what happens when it is unusable).
    pub fn build(
        collection: &HdriCollection,
        options: &PreconvolveOptions,
        cache_dir: Option<&Path>,
    ) -> Result<LightMapBank, LightMapBankError> {
        options.validate().map_err(LightMapBankError::Options)?;
        let cache = cache_dir.map(LightMapCache::open).transpose()?;
        let start = Instant::now();
        let built: Vec<(CacheKey, LightMapSet, Outcome)> = collection
            .entries()
            .par_iter()
            .map(|entry| {
                build_one(entry, options, cache.as_ref()).map_err(|source| {
                    LightMapBankError::Entry {
                        name: entry.name.clone(),
                        source,
                    }
                })
            })
            .collect::<Result<_, _>>()?;
        let mut stats = CacheStats::default();
        let (mut keys, mut sets) = (Vec::new(), Vec::new());
        for (key, set, outcome) in built {
            match outcome {
                Outcome::Hit => stats.hits += 1,
                Outcome::Miss { written } => {
                    stats.misses += 1;
                    stats.write_failures += usize::from(!written);
                }
            }
            keys.push(key);
            sets.push(set);
        }
        tracing::info!(
            "light maps of {} HDRIs in {:.2} s: {} from the cache, {} computed{}",
            sets.len(),
            start.elapsed().as_secs_f64(),
            stats.hits,
            stats.misses,
            if stats.write_failures > 0 {
                format!(", {} not written to the cache", stats.write_failures)
            } else {
                String::new()
            }
        );
        Ok(LightMapBank {
            names: collection
                .entries()
                .iter()
                .map(|e| e.name.clone())
                .collect(),
            keys,
            sets: Arc::new(sets),
            options: options.clone(),
            stats,
        })
    }

    /// Number of environments (that of the collection).
    pub fn len(&self) -> usize {
        self.sets.len()
    }

    /// Whether there are none (never, for a bank built from a collection).
    pub fn is_empty(&self) -> bool {
        self.sets.is_empty()
    }

    /// The light maps of entry `index` (panics if out of range, like slice indexing).
    pub fn get(&self, index: usize) -> &LightMapSet {
        &self.sets[index]
    }

    /// All light-map sets, in the collection's order.
    pub fn sets(&self) -> &[LightMapSet] {
        &self.sets
    }

    /// All light-map sets, shared: what a [`crate::dataset::Dataset`] and the trainer hold.
    pub fn shared(&self) -> Arc<Vec<LightMapSet>> {
        Arc::clone(&self.sets)
    }

    /// Bytes of light-map texels held (`f32` RGB).
    pub fn texel_bytes(&self) -> usize {
        self.sets
            .iter()
            .flat_map(|set| set.maps())
            .map(|m| std::mem::size_of_val(m.texels()))
            .sum()
    }

    /// The name of entry `index`.
    pub fn name(&self, index: usize) -> &str {
        &self.names[index]
    }

    /// The cache key of entry `index`.
    pub fn key(&self, index: usize) -> CacheKey {
        self.keys[index]
    }

    /// The preconvolution options the maps were made with.
    pub fn options(&self) -> &PreconvolveOptions {
        &self.options
    }

    /// Cache hits, misses and failed writes of the build.
    pub fn stats(&self) -> CacheStats {
        self.stats
    }
}

/// One entry: hash its content, then read its light maps from the cache or preconvolve them
/// (and store them).
fn build_one(
    entry: &HdriEntry,
    options: &PreconvolveOptions,
    cache: Option<&LightMapCache>,
) -> Result<(CacheKey, LightMapSet, Outcome), HdriError> {
    let content = entry.read()?;
    let key = cache_key(content.key(), options);
    if let Some(set) = cache.and_then(|c| c.load(key, &options.exponents)) {
        return Ok((key, set, Outcome::Hit));
    }
    let set = preconvolve(&content.environment()?, options)?;
    let written = match cache.map(|c| c.store(key, &set)) {
        None | Some(Ok(_)) => true,
        Some(Err(e)) => {
            tracing::warn!("HDRI `{}`: {}", entry.name, volux_envmap::error::chain(&e));
            false
        }
    };
    Ok((key, set, Outcome::Miss { written }))
}

#[cfg(test)]
mod tests;
