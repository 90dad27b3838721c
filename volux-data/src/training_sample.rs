//! One training example with every layer the discriminators see (paper appendix A): the photo
//! (for D_P), albedo at the output and the volume resolution (D_A), normals at the volume
//! resolution (D_G), the mask, and diffuse, specular and relit layers under one (HDRI, yaw)
//! draw (D_S), in the generator's conventions:
//!
//! - albedo is linear, composited over the background's albedo (its linearised colour);
//! - normals are camera space times the mask (over 0), area-averaged to the volume resolution
//!   without renormalising, which is what accumulating unit normals with opacity weights gives;
//! - diffuse and specular are linear HDR times the mask;
//! - photo and relit are sRGB over the background.
//!
//! Low-resolution layers are area averages of the high-resolution ones (an exact box filter
//! over `factor x factor` blocks).

use volux_envmap::io::srgb_to_linear;
use volux_envmap::random::SplitMix64;
use volux_envmap::{LightMap, Rgb};
use volux_model::pose::Pose;

use crate::layers::{Layer, Layers, rgb};
use crate::relighting::{IntrinsicImage, RelightError, SpecularWeights, relight_weighted};
use crate::resample;
use crate::synthetic_head::{self, HeadRender, SyntheticError, SyntheticHead};

/// Which light maps, rotated by how much, lit a sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LightingDraw {
    /// Index of the environment in the collection's light-map bank.
    pub map: usize,
    /// Rotation of the environment about +y, radians in `[0, 2 pi)`.
    pub yaw: f64,
}

impl LightingDraw {
    /// One of `environments` environments uniformly at random (modulo bias below
    /// `environments / 2^64`), rotated by a yaw uniform in `[0, 2 pi)`: the draw that lights
    /// every training example.
    pub fn sample(environments: usize, rng: &mut SplitMix64) -> LightingDraw {
        assert!(environments > 0, "a draw needs at least one environment");
        let map = (rng.next_u64() % environments as u64) as usize;
        LightingDraw {
            map,
            yaw: std::f64::consts::TAU * rng.next_f64(),
        }
    }
}

/// Where a sample's intrinsic layers and photo come from.
pub enum Intrinsics<'a> {
    /// A synthetic head and its render: per-pixel specular weights, and a photo rendered under
    /// the same light as the pseudo ground truth.
    Synthetic {
        head: &'a SyntheticHead,
        render: &'a HeadRender,
    },
    /// A folder dataset's image: its own photo, the dataset's specular weights.
    Photo {
        image: &'a IntrinsicImage,
        photo: &'a [Rgb],
        specular_weights: &'a [f32],
        /// Composite the photo over the background with the image's mask, as the relit
        /// image is (so D_P and D_S ask for the same background). Only for a mask that was
        /// given: one derived from the normals' length is not trusted with the photo.
        over_background: bool,
    },
}

/// All layers of one example at `side x side` (output) and `side / factor` (volume)
/// resolution: row-major, channels interleaved per pixel ([`crate::layers`]). A layer the
/// dataset does not provide is empty.
#[derive(Clone, Debug, PartialEq)]
pub struct TrainingSample {
    pub side: usize,
    pub factor: usize,
    pub pose: Pose,
    pub draw: LightingDraw,
    pub layers: Layers<Vec<f32>>,
}

impl TrainingSample {
    /// The pixels of a three-channel layer.
    pub fn rgb(&self, layer: Layer) -> &[Rgb] {
        rgb(self.layers.get(layer))
    }
}

/// Why a sample cannot be made.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SampleError {
    #[error("image is {width}x{height}; training images must be square")]
    NotSquare { width: usize, height: usize },
    #[error("image side {side} is not a multiple of the low-resolution factor {factor}")]
    Factor { side: usize, factor: usize },
    #[error("photo has {got} pixels, the image has {want}")]
    PhotoSize { got: usize, want: usize },
    #[error(transparent)]
    Relight(#[from] RelightError),
    #[error(transparent)]
    Synthetic(#[from] SyntheticError),
}

/// Makes a training example from `intrinsics` lit by `lights` (the draw's light maps, exponents
/// 1, 16, 32, 64) rotated by `draw.yaw`, over `background` (sRGB), with low-resolution layers
/// `factor` times smaller.
pub fn make_sample(
    intrinsics: Intrinsics<'_>,
    lights: &[&LightMap],
    draw: LightingDraw,
    background: Rgb,
    factor: usize,
) -> Result<TrainingSample, SampleError> {
    let (image, camera) = match &intrinsics {
        Intrinsics::Synthetic { render, .. } => (&render.image, render.camera.clone()),
        Intrinsics::Photo { image, .. } => (*image, volux_model::ray_sampling::CameraConfig::new()),
    };
    let (side, height) = (image.width, image.height);
    if side != height {
        return Err(SampleError::NotSquare {
            width: side,
            height,
        });
    }
    if factor == 0 || side % factor != 0 {
        return Err(SampleError::Factor { side, factor });
    }
    let (layers, photo) = match intrinsics {
        Intrinsics::Synthetic { head, render } => {
            let shading = synthetic_head::shade(head, render, lights, draw.yaw, background)?;
            (shading.layers, shading.photo)
        }
        Intrinsics::Photo {
            image,
            photo,
            specular_weights,
            over_background,
        } => {
            if photo.len() != side * side {
                return Err(SampleError::PhotoSize {
                    got: photo.len(),
                    want: side * side,
                });
            }
            let weights = SpecularWeights::Uniform(specular_weights);
            let layers = relight_weighted(image, lights, weights, draw.yaw, &camera, background)?;
            let photo = if over_background {
                composite(photo, &image.mask, background)
            } else {
                photo.to_vec()
            };
            (layers, photo)
        }
    };
    let bg_albedo = background.map(srgb_to_linear);
    let albedo_hi: Vec<Rgb> = image
        .albedo
        .iter()
        .zip(&image.mask)
        .map(|(a, &m)| std::array::from_fn(|k| a[k] * m + bg_albedo[k] * (1.0 - m)))
        .collect();
    let masked_normals: Vec<[f32; 3]> = image
        .normals
        .iter()
        .zip(&image.mask)
        .map(|(n, &m)| n.map(|c| c * m))
        .collect();
    Ok(TrainingSample {
        side,
        factor,
        pose: image.pose,
        draw,
        layers: Layers {
            photo: photo.into_flattened(),
            relit: layers.relit.into_flattened(),
            albedo_lo: resample::area_downsample(&albedo_hi, side, factor).into_flattened(),
            albedo_hi: albedo_hi.into_flattened(),
            normals_lo: resample::area_downsample(&masked_normals, side, factor).into_flattened(),
            mask: image.mask.clone(),
            diffuse: layers.diffuse.into_flattened(),
            specular: layers.specular.into_flattened(),
        },
    })
}

/// The example of a photos-only dataset from its `side x side` photo: the photo layer alone
/// (over the background where a mask is given), every other layer empty. No relighting runs.
pub fn make_photo_sample(
    side: usize,
    photo: &[Rgb],
    mask: Option<&[f32]>,
    pose: Pose,
    draw: LightingDraw,
    background: Rgb,
    factor: usize,
) -> Result<TrainingSample, SampleError> {
    if factor == 0 || !side.is_multiple_of(factor) {
        return Err(SampleError::Factor { side, factor });
    }
    let want = side * side;
    if let Some(got) = [Some(photo.len()), mask.map(<[f32]>::len)]
        .into_iter()
        .flatten()
        .find(|&n| n != want)
    {
        return Err(SampleError::PhotoSize { got, want });
    }
    let photo = match mask {
        Some(mask) => composite(photo, mask, background),
        None => photo.to_vec(),
    };
    let layers = Layers {
        photo: photo.into_flattened(),
        ..Layers::default()
    };
    Ok(TrainingSample {
        side,
        factor,
        pose,
        draw,
        layers,
    })
}

/// `photo` (sRGB) over `background` (sRGB) with coverage `mask`, blended in sRGB as the
/// relit image is.
pub fn composite(photo: &[Rgb], mask: &[f32], background: Rgb) -> Vec<Rgb> {
    photo
        .iter()
        .zip(mask)
        .map(|(p, &m)| std::array::from_fn(|k| m * p[k] + (1.0 - m) * background[k]))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic_head::RenderSettings;
    use volux_envmap::{EnvMap, PreconvolveOptions, preconvolve};

    #[test]
    fn draws_cover_the_environments_with_yaw_in_range() {
        use std::f64::consts::TAU;
        let environments = 24;
        let mut rng = SplitMix64::new(11);
        let mut seen = vec![0usize; environments];
        let (mut min_yaw, mut max_yaw) = (f64::INFINITY, 0.0f64);
        let draws = 24_000;
        for _ in 0..draws {
            let d = LightingDraw::sample(environments, &mut rng);
            seen[d.map] += 1;
            assert!((0.0..TAU).contains(&d.yaw), "{d:?}");
            min_yaw = min_yaw.min(d.yaw);
            max_yaw = max_yaw.max(d.yaw);
        }
        // Uniform: about 1000 each (binomial sd about 31).
        assert!(seen.iter().all(|&n| (850..1150).contains(&n)), "{seen:?}");
        assert!(
            min_yaw < 0.01 && max_yaw > TAU - 0.01,
            "{min_yaw} {max_yaw}"
        );
        // The same seed draws the same sequence.
        let (mut a, mut b) = (SplitMix64::new(5), SplitMix64::new(5));
        for _ in 0..10 {
            assert_eq!(
                LightingDraw::sample(environments, &mut a),
                LightingDraw::sample(environments, &mut b)
            );
        }
    }

    #[test]
    fn the_same_head_under_two_environments_keeps_its_intrinsic_layers() {
        let head = SyntheticHead::from_seed(4);
        let render =
            synthetic_head::render(&head, Pose::new(0.1, 0.0), &RenderSettings::square(32));
        let sun = crate::procedural_sky::SunSky {
            elevation: 0.5,
            azimuth: 1.0,
            turbidity: 3.0,
            sun_irradiance: 20.0,
            sun_radius: 0.02,
        }
        .render(32)
        .unwrap();
        let grey = EnvMap::constant(16, [0.5; 3]).unwrap();
        let make = |map: &EnvMap, yaw: f64| {
            let set = preconvolve(map, &PreconvolveOptions::default()).unwrap();
            let lights: Vec<&LightMap> = set.maps().iter().collect();
            let intrinsics = Intrinsics::Synthetic {
                head: &head,
                render: &render,
            };
            make_sample(
                intrinsics,
                &lights,
                LightingDraw { map: 0, yaw },
                [0.2; 3],
                2,
            )
            .unwrap()
        };
        let (a, b) = (make(&sun, 0.3), make(&grey, 2.0));
        let (al, bl) = (&a.layers, &b.layers);
        assert_eq!(al.albedo_hi, bl.albedo_hi);
        assert_eq!(al.albedo_lo, bl.albedo_lo);
        assert_eq!(al.normals_lo, bl.normals_lo);
        assert_eq!(al.mask, bl.mask);
        assert_ne!(al.relit, bl.relit);
        assert_ne!(al.photo, bl.photo);
        // Background pixels carry the background: albedo in linear, relit and photo in sRGB.
        let corner = 0;
        assert_eq!(al.mask[corner], 0.0);
        assert!((a.rgb(Layer::AlbedoHi)[corner][0] - srgb_to_linear(0.2)).abs() < 1e-7);
        assert_eq!(a.rgb(Layer::Relit)[corner], [0.2; 3]);
        assert_eq!(a.rgb(Layer::Photo)[corner], [0.2; 3]);
        assert_eq!(a.rgb(Layer::NormalsLo)[corner], [0.0; 3]);
        assert_eq!(
            (a.rgb(Layer::AlbedoLo).len(), a.rgb(Layer::NormalsLo).len()),
            (256, 256)
        );
    }

    #[test]
    fn bad_sizes_are_errors() {
        let image = IntrinsicImage {
            width: 6,
            height: 6,
            albedo: vec![[0.5; 3]; 36],
            normals: vec![[0.0, 0.0, 1.0]; 36],
            mask: vec![1.0; 36],
            pose: Pose::new(0.0, 0.0),
        };
        let set = preconvolve(
            &EnvMap::constant(8, [1.0; 3]).unwrap(),
            &PreconvolveOptions::default(),
        )
        .unwrap();
        let lights: Vec<&LightMap> = set.maps().iter().collect();
        let draw = LightingDraw { map: 0, yaw: 0.0 };
        let photo = vec![[0.0; 3]; 36];
        let weights = [0.0, 0.1, 0.0, 0.0];
        let intrinsics = |photo| Intrinsics::Photo {
            image: &image,
            photo,
            specular_weights: &weights,
            over_background: false,
        };
        assert_eq!(
            make_sample(intrinsics(&photo), &lights, draw, [0.0; 3], 4).unwrap_err(),
            SampleError::Factor { side: 6, factor: 4 }
        );
        assert_eq!(
            make_sample(intrinsics(&photo[1..]), &lights, draw, [0.0; 3], 2).unwrap_err(),
            SampleError::PhotoSize { got: 35, want: 36 }
        );
        let ok = make_sample(intrinsics(&photo), &lights, draw, [0.0; 3], 3).unwrap();
        // Constant unit environment, facing normals: diffuse 1 everywhere.
        assert!(ok.layers.diffuse.iter().all(|d| (d - 1.0).abs() < 2e-3));
        assert_eq!(ok.rgb(Layer::AlbedoLo).len(), 4);
    }
}
