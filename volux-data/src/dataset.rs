//! A training dataset: a source of intrinsic images (the built-in synthetic heads or a folder
//! dataset), a bank of light maps, and the draws that light each example, as a pure function
//! of the example's index.
//!
//! Example `i` of a dataset with seed `s` uses its own random stream (SplitMix64 of a hash of
//! `s` and `i`): which head or image, which pose (synthetic heads), which environment and
//! rotation. So batches can be made in any order, on any number of threads, and a resumed run
//! sees exactly the data of an uninterrupted one.

use std::sync::Arc;

use rayon::prelude::*;
use volux_envmap::io::{linear_to_srgb, srgb_to_linear};
use volux_envmap::random::{self, SplitMix64};
use volux_envmap::{LightMap, LightMapSet, Rgb};

use crate::batch::Batch;
use crate::folder_dataset::{FolderContent, FolderDataset};
use crate::layers::Layers;
use crate::pose_distribution::PoseDistribution;
use crate::relighting::IntrinsicImage;
use crate::synthetic_head::{self, RenderSettings, SyntheticHead};
use crate::training_sample::{
    Intrinsics, LightingDraw, TrainingSample, make_photo_sample, make_sample,
};

mod config;
mod error;
#[cfg(test)]
mod tests;

pub use config::{
    CacheConfig, DataConfig, FolderLayer, MAX_RESOLUTION, SourceConfig, folder_content,
};
pub use error::{DataError, LightingError};

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
        config.validate()?;
        let factor = config.factor()?;
        let side = config.resolution;
        let source = match &config.source {
            SourceConfig::Synthetic {
                identities,
                supersample,
                poses,
            } => Source::Synthetic {
                identities: *identities,
                settings: RenderSettings {
                    supersample: *supersample,
                    ..RenderSettings::square(side)
                },
                poses: *poses,
            },
            SourceConfig::Folder {
                path,
                specular_weights,
                layers,
            } => {
                let content = folder_content(layers).map_err(DataError::Config)?;
                Source::Folder {
                    dataset: FolderDataset::open_with(path, content)?,
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

    /// Which layers the examples have (the others are empty).
    pub fn provided(&self) -> Layers<bool> {
        match &self.source {
            Source::Synthetic { .. } => Layers::from_fn(|_| true),
            Source::Folder { dataset, .. } => dataset.content().provided(),
        }
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
                if dataset.content() == FolderContent::Photos {
                    let loaded = dataset.load_photo(i)?;
                    let stem = loaded.stem.clone();
                    let size_error = |(width, height)| DataError::FolderSize {
                        path: dataset.photo_path(i).to_path_buf(),
                        width,
                        height,
                        side: self.side,
                    };
                    let (photo, mask) = fit_photo(
                        loaded.photo,
                        loaded.mask,
                        (loaded.width, loaded.height),
                        self.side,
                    )
                    .map_err(size_error)?;
                    return make_photo_sample(
                        self.side,
                        &photo,
                        mask.as_deref(),
                        loaded.pose,
                        draw,
                        self.background,
                        self.factor,
                    )
                    .map_err(|source| DataError::Sample { stem, source });
                }
                let loaded = dataset.load(i)?;
                let stem = loaded.stem;
                let (image, photo) =
                    fit(loaded.image, loaded.photo, self.side).map_err(|(width, height)| {
                        DataError::FolderSize {
                            path: dataset.photo_path(i).to_path_buf(),
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

/// The factor `k` by which a `(w, h)` folder image is averaged down to `side x side`, or its
/// size if it cannot be (not square, or its side not a multiple of `side`).
fn fit_factor((w, h): (usize, usize), side: usize) -> Result<usize, (usize, usize)> {
    if w != h || w % side != 0 {
        return Err((w, h));
    }
    Ok(w / side)
}

/// A photo of side `w` area-averaged over `k x k` blocks in linear light.
fn average_photo(photo: &[Rgb], w: usize, k: usize) -> Vec<Rgb> {
    let linear: Vec<Rgb> = photo.iter().map(|c| c.map(srgb_to_linear)).collect();
    crate::resample::area_downsample(&linear, w, k)
        .into_iter()
        .map(|c| c.map(linear_to_srgb))
        .collect()
}

/// A mask of side `w` area-averaged over `k x k` blocks.
fn average_mask(mask: &[f32], w: usize, k: usize) -> Vec<f32> {
    let mask_rgb: Vec<[f32; 3]> = mask.iter().map(|&m| [m; 3]).collect();
    crate::resample::area_downsample(&mask_rgb, w, k)
        .into_iter()
        .map(|m| m[0])
        .collect()
}

/// Brings a photo of `(width, height)` and its mask (if any) to `side x side` by area
/// averaging, the photo in linear light (the side must be a multiple of `side`).
#[allow(clippy::type_complexity)]
fn fit_photo(
    photo: Vec<Rgb>,
    mask: Option<Vec<f32>>,
    (w, h): (usize, usize),
    side: usize,
) -> Result<(Vec<Rgb>, Option<Vec<f32>>), (usize, usize)> {
    let k = fit_factor((w, h), side)?;
    if k == 1 {
        return Ok((photo, mask));
    }
    Ok((
        average_photo(&photo, w, k),
        mask.map(|m| average_mask(&m, w, k)),
    ))
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
    let w = image.width;
    let k = fit_factor((w, image.height), side)?;
    if k == 1 {
        return Ok((image, photo));
    }
    let average = |layer: &[[f32; 3]]| crate::resample::area_downsample(layer, w, k);
    let photo = average_photo(&photo, w, k);
    let mask = average_mask(&image.mask, w, k);
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
