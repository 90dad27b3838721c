//! The estimator's training and test pairs: a synthetic head's photo with its exact albedo,
//! camera-space normals and mask (volux-data's renderer), at a random pose, under an
//! environment of the HDRI collection at a random yaw, with the photo model's shadows and
//! occlusion. The photo is rendered over black so that augmentation can put any background
//! behind it ([`crate::augmentation`]).
//!
//! Identities below [`HELD_OUT_FIRST`] are for training; those from it on are never trained
//! on, and every accuracy figure is measured on them.

use volux_data::hdri_collection::{HdriCollection, HdriCollectionConfig};
use volux_data::light_map_bank::LightMapBank;
use volux_data::pose_distribution::PoseDistribution;
use volux_data::synthetic_head::{
    self, PhotoLighting, RenderSettings, SyntheticError, SyntheticHead,
};
use volux_data::training_sample::LightingDraw;
use volux_envmap::random::{self, SplitMix64};
use volux_envmap::{LightMap, LightMapSet, PreconvolveOptions, Rgb};

use crate::error::PseudoGtError;

/// The first identity seed held out of training.
pub const HELD_OUT_FIRST: u64 = 1 << 40;

/// The random stream of pair draws (pose, environment, yaw), apart from the datasets'.
const PAIR_STREAM: u64 = 0x9E6C_63D0_676A_9A99;

/// One photo and its exact intrinsic layers, row-major, `side x side`.
#[derive(Clone, Debug, PartialEq)]
pub struct SyntheticPair {
    pub side: usize,
    /// sRGB in [0, 1], over black (the covered part of each pixel only).
    pub photo: Vec<Rgb>,
    /// Linear albedo.
    pub albedo: Vec<Rgb>,
    /// Unit camera-space normals, zero where nothing is covered.
    pub normals: Vec<[f32; 3]>,
    /// Coverage in [0, 1].
    pub mask: Vec<f32>,
}

/// The light maps of the default HDRI collection (the shipped maps, procedural skies and
/// studios), which light every training and held-out pair.
pub fn collection_lights() -> Result<Vec<LightMapSet>, PseudoGtError> {
    let collection = HdriCollection::from_config(&HdriCollectionConfig::default())
        .map_err(PseudoGtError::Collection)?;
    let bank = LightMapBank::build(&collection, &PreconvolveOptions::default(), None)
        .map_err(PseudoGtError::LightMaps)?;
    Ok(bank.sets().to_vec())
}

/// The poses pairs are drawn from: wider than the dataset default, since photos are.
pub fn pair_poses() -> PoseDistribution {
    PoseDistribution {
        yaw_sd: 0.45,
        pitch_sd: 0.2,
        ..PoseDistribution::default()
    }
}

/// The pair of `identity` drawn with `seed` at `side` pixels, `supersample` rays per pixel
/// per axis, lit by one of `lights` (each the light maps 1, 16, 32, 64 of an environment).
pub fn render_pair(
    lights: &[LightMapSet],
    identity: u64,
    seed: u64,
    side: usize,
    supersample: usize,
) -> Result<SyntheticPair, SyntheticError> {
    let mut rng = SplitMix64::new(random::stream_seed(seed, identity, PAIR_STREAM));
    let pose = pair_poses().sample(&mut rng);
    let draw = LightingDraw::sample(lights.len(), &mut rng);
    let maps: Vec<&LightMap> = lights[draw.map].maps().iter().collect();
    let light = PhotoLighting::new(&maps, draw.yaw)?;
    let head = SyntheticHead::from_seed(identity);
    let settings = RenderSettings {
        supersample,
        ..RenderSettings::square(side)
    };
    let render = synthetic_head::render(&head, pose, &settings);
    let photo = synthetic_head::photo::photo(&head, &render, &light, [0.0; 3]);
    let image = render.image;
    Ok(SyntheticPair {
        side,
        photo,
        albedo: image.albedo,
        normals: image.normals,
        mask: image.mask,
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Two environments of the collection: enough for tests that need light, not variety.
    pub fn bank() -> Vec<LightMapSet> {
        collection_lights().unwrap()[..2].to_vec()
    }

    #[test]
    fn pairs_are_reproducible_and_consistent() {
        let lights = bank();
        let a = render_pair(&lights, 3, 7, 24, 1).unwrap();
        assert_eq!(a, render_pair(&lights, 3, 7, 24, 1).unwrap());
        assert_ne!(a.photo, render_pair(&lights, 4, 7, 24, 1).unwrap().photo);
        let covered = a.mask.iter().filter(|&&m| m > 0.0).count();
        assert!(covered > 24 * 24 / 5, "{covered}");
        for (i, &m) in a.mask.iter().enumerate() {
            let n = a.normals[i];
            let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            if m == 0.0 {
                assert_eq!(a.photo[i], [0.0; 3]);
            } else {
                assert!((l - 1.0).abs() < 1e-3, "{l}");
            }
        }
    }
}
