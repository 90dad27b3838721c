//! Where training takes its examples from: a dataset made on the fly ([`crate::dataset`]) or a
//! finished example cache ([`crate::example_cache`]) that must have been built from the very
//! same `[data]` config and environments (its fingerprint). This module sits above both, so
//! that neither the dataset nor the cache knows the other's errors.

use std::path::PathBuf;
use std::sync::Arc;

use crate::batch::{Batch, BatchLoader};
use crate::dataset::{DataConfig, DataError, Dataset};
use crate::example_cache::{self, CacheError, ExampleCache};
use crate::layers::Layers;
use crate::light_map_bank::LightMapBank;

/// Why examples cannot be opened or read.
#[derive(Debug, thiserror::Error)]
pub enum ExamplesError {
    #[error(transparent)]
    Data(#[from] DataError),
    #[error(transparent)]
    Cache(#[from] CacheError),
    #[error(
        "the example cache in {} was built from another [data] config or other environments: run `volux data build` again",
        dir.display()
    )]
    Stale { dir: PathBuf },
}

/// The fingerprint of a dataset's examples: the `[data]` table as [`crate::dataset::DataConfig::load`]
/// returns it and the content keys of the environments (see [`example_cache::fingerprint`]).
pub fn fingerprint(hashed_config: &str, bank: &LightMapBank) -> String {
    let keys: Vec<String> = (0..bank.len()).map(|i| bank.key(i).to_hex()).collect();
    example_cache::fingerprint(&[hashed_config.as_bytes(), keys.join(",").as_bytes()])
}

/// Where training takes its examples from: made on the fly, or read from a finished cache.
#[derive(Clone)]
pub enum Examples {
    Live(Arc<Dataset>),
    Cached(Arc<ExampleCache>),
}

impl Examples {
    /// The config's example cache if it has one (it must be finished and built from this very
    /// config and environments), else examples made on the fly.
    pub fn open(
        config: &DataConfig,
        hashed_config: &str,
        bank: &LightMapBank,
    ) -> Result<Examples, ExamplesError> {
        let Some(cache) = &config.cache else {
            let dataset = Dataset::new(config, bank.shared())?;
            return Ok(Examples::Live(Arc::new(dataset)));
        };
        let opened = ExampleCache::open(&cache.dir)?;
        if opened.manifest().fingerprint != fingerprint(hashed_config, bank) {
            return Err(ExamplesError::Stale {
                dir: cache.dir.clone(),
            });
        }
        Ok(Examples::Cached(Arc::new(opened)))
    }

    /// Which layers the examples have (the others are empty).
    pub fn provided(&self) -> Layers<bool> {
        match self {
            Examples::Live(d) => d.provided(),
            Examples::Cached(c) => c.provided(),
        }
    }

    /// Batch `index` of `size` examples.
    pub fn batch(&self, index: u64, size: usize) -> Result<Batch, ExamplesError> {
        Ok(match self {
            Examples::Live(d) => d.batch(index, size)?,
            Examples::Cached(c) => c.batch(index, size)?,
        })
    }

    /// Batches `start, start + 1, ...` of `size` made on another thread, `prefetch` ahead.
    pub fn loader(&self, start: u64, size: usize, prefetch: usize) -> BatchLoader<ExamplesError> {
        let examples = self.clone();
        BatchLoader::spawn(start, prefetch, move |i| examples.batch(i, size))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn examples_come_from_a_matching_cache_or_are_made_live() {
        use crate::hdri_collection::HdriCollectionConfig;
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("d.toml");
        let write = |seed: u64| {
            std::fs::write(&file, format!("[data]\nseed = {seed}\nresolution = 8\nvolume_resolution = 4\n[data.lighting]\nbuiltin = false\nskies = 1\novercast = 0\nstudios = 0\nprocedural_height = 16\n[data.cache]\ndir = \"ex\"\nexamples = 3\nshard_size = 2\n")).unwrap();
            DataConfig::load(&file).unwrap()
        };
        let (config, hashed) = write(1);
        assert_eq!(
            config.lighting,
            HdriCollectionConfig {
                builtin: false,
                skies: 1,
                overcast: 0,
                studios: 0,
                procedural_height: 16,
                ..Default::default()
            }
        );
        let bank = config.light_bank().unwrap();
        // No cache yet: an error saying how to make it.
        assert!(Examples::open(&config, &hashed, &bank).is_err());
        let live = Dataset::new(&config, Arc::new(bank.sets().to_vec())).unwrap();
        let spec = example_cache::CacheSpec {
            examples: 3,
            shard_size: 2,
        };
        let cache_dir = &config.cache.as_ref().unwrap().dir;
        example_cache::build(
            cache_dir,
            &live,
            &fingerprint(&hashed, &bank),
            spec,
            &|_, _| {},
        )
        .unwrap();
        let examples = Examples::open(&config, &hashed, &bank).unwrap();
        assert!(matches!(examples, Examples::Cached(_)));
        let mut loader = examples.loader(1, 2, 2);
        let cached = loader.next_batch().unwrap().unwrap();
        let made = live.batch(1, 2);
        // Batch 1 of 2 wraps around the 3 cached examples: examples 2 and 0.
        let wrapped = Batch::collate(1, &[live.example(2).unwrap(), live.example(0).unwrap()]);
        assert_eq!(cached.layers.photo, wrapped.layers.photo);
        assert!(made.is_ok());
        // Another seed: the cache no longer matches.
        let (other, other_hashed) = write(2);
        let err = Examples::open(&other, &other_hashed, &bank)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("volux data build"), "{err}");
        // Without a cache table examples are made on the fly.
        let no_cache = DataConfig {
            cache: None,
            ..other
        };
        assert!(matches!(
            Examples::open(&no_cache, &other_hashed, &bank).unwrap(),
            Examples::Live(_)
        ));
    }
}
