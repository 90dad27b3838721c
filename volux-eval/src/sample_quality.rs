//! Sample quality as a distribution distance: the sliced Wasserstein distance of the albedo,
//! normals and relit image of generated samples against the training data. The fakes are
//! rendered at the poses and under the lightings of dataset images, and compared with a second,
//! disjoint draw of dataset images; the first draw against the second is the floor a perfect
//! generator reaches at this sample count. A photos-only dataset has no albedo, normals or
//! relit layers: its one comparison is the relit image against the photos (what D_P judges).

use std::sync::Arc;

use burn::tensor::Device;
use volux_data::batch::Batch;
use volux_data::examples::Examples;
use volux_data::layers::{Layer, Layers};
use volux_data::resample::resize;
use volux_data::training_sample::LightingDraw;
use volux_envmap::LightMapSet;
use volux_model::generator::Generator;
use volux_model::pose::Pose;
use volux_train::config::TrainConfig;
use volux_train::sampling;

use crate::evaluate::EvalError;
use crate::report::SwdRow;
use crate::swd::{ImageSet, Swd, SwdOptions, swd};
use crate::views::{Rendered, render_model};

/// One compared layer: its name in reports, the dataset's layer and the generated view's
/// image compared with it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Compared {
    pub name: &'static str,
    pub real: Layer,
    fake: Generated,
}

/// Which image of a generated view a comparison takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Generated {
    Albedo,
    NormalsLo,
    Relit,
}

/// The comparisons of a dataset that provides `provided`: albedo, normals and relit where
/// they are there, else the relit image against the photos.
pub fn compared(provided: &Layers<bool>) -> Vec<Compared> {
    let all = [
        ("albedo", Layer::AlbedoHi, Generated::Albedo),
        ("normals", Layer::NormalsLo, Generated::NormalsLo),
        ("relit", Layer::Relit, Generated::Relit),
    ];
    let mut out: Vec<Compared> = all
        .into_iter()
        .filter(|&(_, real, _)| *provided.get(real))
        .map(|(name, real, fake)| Compared { name, real, fake })
        .collect();
    if out.is_empty() && provided.photo {
        out.push(Compared {
            name: "photo",
            real: Layer::Photo,
            fake: Generated::Relit,
        });
    }
    out
}

/// Index of the second draw's first batch: far from the first draw's batches, so that the two
/// share no image.
const OTHER_START: u64 = 1 << 20;

/// Planar `[3, s, s]` from pixels.
fn planar(pixels: &[[f32; 3]]) -> Vec<f32> {
    (0..3)
        .flat_map(|k| pixels.iter().map(move |p| p[k]))
        .collect()
}

/// Empty sets of the `compared` layers at the output and volume resolutions.
fn empty_sets(compared: &[Compared], side: usize, side_lo: usize) -> Vec<ImageSet> {
    compared
        .iter()
        .map(|c| ImageSet::new(c.real.side(side, side / side_lo), 3))
        .collect()
}

fn extend(sets: &mut [ImageSet], compared: &[Compared], batch: &Batch) {
    for (set, c) in sets.iter_mut().zip(compared) {
        let values = batch.layers.get(c.real);
        if c.real.is_srgb() {
            let values: Vec<f32> = values.iter().map(|v| 0.5 * (v + 1.0)).collect();
            set.extend_planar(&values);
        } else {
            set.extend_planar(values);
        }
    }
}

/// The image of `view` that `c` compares, planar.
fn generated(view: &Rendered, c: &Compared) -> Vec<f32> {
    planar(match c.fake {
        Generated::Albedo => &view.albedo,
        Generated::NormalsLo => &view.normals_lo,
        Generated::Relit => &view.relit,
    })
}

/// Two disjoint draws of `samples` dataset images, and the cameras and lightings of the first,
/// which the fakes copy.
pub struct DataSets {
    /// The environments the draws index.
    pub lights: Arc<Vec<LightMapSet>>,
    /// Per image of the first draw: its camera pose and lighting.
    pub poses: Vec<Pose>,
    pub draws: Vec<LightingDraw>,
    /// What is compared, in the order of every list of sets and distances here.
    pub compared: Vec<Compared>,
    /// The first draw's layers (the floor's left side).
    pub real: Vec<ImageSet>,
    /// The second draw's layers: what fakes and the first draw are compared with.
    pub other: Vec<ImageSet>,
}

impl DataSets {
    /// Draws `samples` images twice from the dataset of `config`, `batch` at a time.
    pub fn draw(config: &TrainConfig, samples: usize, batch: usize) -> Result<DataSets, EvalError> {
        if samples == 0 || batch == 0 {
            return Err(EvalError::Options(
                "samples and batch must be at least 1".into(),
            ));
        }
        let bank = config.data.light_bank()?;
        let examples = Examples::open(&config.data, &config.data_hashed, &bank)?;
        let g = config.generator();
        let (side, side_lo) = (g.output_resolution, g.volume_resolution);
        let compared = compared(&examples.provided());
        let mut out = DataSets {
            lights: bank.shared(),
            poses: Vec::with_capacity(samples),
            draws: Vec::with_capacity(samples),
            real: empty_sets(&compared, side, side_lo),
            other: empty_sets(&compared, side, side_lo),
            compared,
        };
        let batches = samples.div_ceil(batch);
        for i in 0..batches as u64 {
            tracing::info!("sample quality: dataset batch {} of {batches}", i + 1);
            let a = examples.batch(i, batch)?;
            let o = examples.batch(OTHER_START + i, batch)?;
            out.poses.extend_from_slice(&a.poses);
            out.draws.extend_from_slice(&a.draws);
            extend(&mut out.real, &out.compared, &a);
            extend(&mut out.other, &out.compared, &o);
        }
        out.poses.truncate(samples);
        out.draws.truncate(samples);
        for set in out.real.iter_mut().chain(out.other.iter_mut()) {
            set.images.truncate(samples);
        }
        Ok(out)
    }

    /// Images per draw.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// The first draw against the second, per compared layer.
    pub fn floor(&self, options: &SwdOptions) -> Result<Vec<Swd>, EvalError> {
        distances(&self.compared, &self.real, &self.other, options)
    }

    /// Per compared layer, the first draw brought down to `side_lo` and back up
    /// ([`through_resolution`]) against the second: what a perfect volume of `side_lo` rays
    /// scores when nothing adds detail above its resolution. `None` for layers compared at
    /// `side_lo` or below.
    pub fn through_resolution_distance(
        &self,
        side_lo: usize,
        options: &SwdOptions,
    ) -> Result<Vec<Option<Swd>>, EvalError> {
        self.compared
            .iter()
            .zip(self.real.iter().zip(&self.other))
            .map(|(c, (real, other))| {
                if real.side <= side_lo {
                    return Ok(None);
                }
                tracing::info!("sample quality: {} through the volume's resolution", c.name);
                Ok(Some(swd(
                    &through_resolution(real, side_lo),
                    other,
                    options,
                )?))
            })
            .collect()
    }
}

/// Each image of a 3-channel `set` area-averaged to `side_lo` and enlarged back bilinearly
/// (`volux_data::resample::resize` both ways, the data pipeline's own resampling): its detail
/// above `side_lo` taken away.
pub fn through_resolution(set: &ImageSet, side_lo: usize) -> ImageSet {
    assert_eq!(set.channels, 3, "planar RGB images");
    let side = set.side;
    let images = set
        .images
        .iter()
        .map(|img| {
            let n = side * side;
            let pixels: Vec<[f32; 3]> = (0..n)
                .map(|i| [img[i], img[n + i], img[2 * n + i]])
                .collect();
            let low = resize(&pixels, side, side_lo);
            planar(&resize(&low, side_lo, side))
        })
        .collect();
    ImageSet {
        side,
        channels: 3,
        images,
    }
}

/// Per compared layer, `a` against `b`.
pub fn distances(
    compared: &[Compared],
    a: &[ImageSet],
    b: &[ImageSet],
    options: &SwdOptions,
) -> Result<Vec<Swd>, EvalError> {
    compared
        .iter()
        .zip(a.iter().zip(b))
        .map(|(c, (a, b))| {
            tracing::info!("sample quality: {}", c.name);
            Ok(swd(a, b, options)?)
        })
        .collect()
}

/// The generator's layers for latents `first_seed ..`, one per image of `data`'s first draw, at
/// its camera and under its lighting, `batch` at a time.
pub fn fake_sets(
    g: &Generator,
    device: &Device,
    config: &TrainConfig,
    data: &DataSets,
    first_seed: u64,
    batch: usize,
) -> Result<Vec<ImageSet>, EvalError> {
    let mut fake = empty_sets(&data.compared, g.output_resolution(), g.volume_resolution);
    let z_dim = config.generator().mapping.z_dim;
    let n = data.len();
    for start in (0..n).step_by(batch.max(1)) {
        let end = (start + batch).min(n);
        let seeds: Vec<u64> = (start..end).map(|i| first_seed + i as u64).collect();
        let z = sampling::latents(&seeds, z_dim, device);
        let sets: Vec<&LightMapSet> = data.draws[start..end]
            .iter()
            .map(|d| &data.lights[d.map])
            .collect();
        let yaws: Vec<f64> = data.draws[start..end].iter().map(|d| d.yaw).collect();
        let views = render_model(
            g,
            z,
            &data.poses[start..end],
            &sets,
            &yaws,
            config.data.background,
        )?;
        for v in &views {
            for (set, c) in fake.iter_mut().zip(&data.compared) {
                set.images.push(generated(v, c));
            }
        }
    }
    Ok(fake)
}

/// `volux eval`'s table rows: generated against the dataset, and the dataset's floor.
pub fn sample_quality(
    g: &Generator,
    device: &Device,
    config: &TrainConfig,
    samples: usize,
    first_seed: u64,
    batch: usize,
    options: &SwdOptions,
) -> Result<Vec<SwdRow>, EvalError> {
    let data = DataSets::draw(config, samples, batch)?;
    let fake = fake_sets(g, device, config, &data, first_seed, batch)?;
    let model = distances(&data.compared, &fake, &data.other, options)?;
    let floor = data.floor(options)?;
    let through =
        data.through_resolution_distance(config.generator().volume_resolution, options)?;
    Ok(data
        .compared
        .iter()
        .zip(model.into_iter().zip(floor).zip(through))
        .map(|(c, ((model, data), data_through_volume))| SwdRow {
            layer: c.name.to_string(),
            model,
            data,
            data_through_volume,
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_dataset_is_compared_on_the_layers_it_has() {
        let names = |provided: Layers<bool>| -> Vec<&str> {
            compared(&provided).iter().map(|c| c.name).collect()
        };
        assert_eq!(
            names(Layers::from_fn(|_| true)),
            ["albedo", "normals", "relit"]
        );
        // Photos alone: the relit image against the photos, at the output resolution.
        let photos = compared(&Layers::from_fn(|l| l == Layer::Photo));
        assert_eq!(photos.len(), 1);
        assert_eq!((photos[0].name, photos[0].real), ("photo", Layer::Photo));
        assert_eq!(photos[0].fake, Generated::Relit);
        let sets = empty_sets(&photos, 64, 32);
        assert_eq!(sets.len(), 1);
        let normals = compared(&Layers::from_fn(|l| l == Layer::NormalsLo));
        assert_eq!(empty_sets(&normals, 64, 32)[0].side, 32);
        assert!(compared(&Layers::default()).is_empty());
    }

    /// Through a lower resolution, a linear ramp keeps its values away from the edges, a
    /// pixel-sized checkerboard becomes its mean, and the distance is left out of layers
    /// already at that resolution.
    #[test]
    fn through_resolution_takes_away_only_the_detail_above_it() {
        let (side, lo) = (8, 4);
        let n = side * side;
        let ramp: Vec<f32> = (0..3 * n).map(|i| ((i % n) % side) as f32 / 8.0).collect();
        let checker: Vec<f32> = (0..3 * n)
            .map(|i| (((i % n) % side + (i % n) / side) % 2) as f32)
            .collect();
        let mut set = ImageSet::new(side, 3);
        set.images = vec![ramp.clone(), checker];
        let out = through_resolution(&set, lo);
        assert_eq!((out.side, out.channels, out.images.len()), (side, 3, 2));
        for c in 0..3 {
            for y in 0..side {
                for x in 1..side - 1 {
                    let at = c * n + y * side + x;
                    assert!((out.images[0][at] - ramp[at]).abs() < 1e-6, "ramp at {x}");
                }
            }
        }
        assert!(out.images[1].iter().all(|v| (v - 0.5).abs() < 1e-6));
        let mut normals = ImageSet::new(lo, 3);
        normals.images = vec![vec![0.0; 3 * lo * lo]];
        let data = DataSets {
            lights: Arc::new(Vec::new()),
            poses: Vec::new(),
            draws: Vec::new(),
            compared: compared(&Layers::from_fn(|_| true)),
            real: vec![set.clone(), normals.clone(), set.clone()],
            other: vec![set.clone(), normals, set],
        };
        let options = SwdOptions {
            min_side: side,
            ..SwdOptions::default()
        };
        let got = data.through_resolution_distance(lo, &options).unwrap();
        assert!(
            got[1].is_none(),
            "the normals are compared at the volume's side"
        );
        let relit = got[2].as_ref().unwrap();
        assert!(relit.mean > 0.0, "the checkerboard's detail is gone");
        let identical = swd(&data.real[2], &data.other[2], &options).unwrap();
        assert_eq!(identical.mean, 0.0);
    }
}
