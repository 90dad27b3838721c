//! Sample quality as a distribution distance: the sliced Wasserstein distance of the albedo,
//! normals and relit image of generated samples against the training data. The fakes are
//! rendered at the poses and under the lightings of dataset images, and compared with a second,
//! disjoint draw of dataset images; the first draw against the second is the floor a perfect
//! generator reaches at this sample count.

use std::sync::Arc;

use burn::tensor::Device;
use volux_data::batch::Batch;
use volux_data::examples::Examples;
use volux_data::training_sample::LightingDraw;
use volux_envmap::LightMapSet;
use volux_model::generator::Generator;
use volux_model::pose::Pose;
use volux_train::config::TrainConfig;
use volux_train::sampling;

use crate::evaluate::EvalError;
use crate::report::SwdRow;
use crate::swd::{ImageSet, Swd, SwdOptions, swd};
use crate::views::render_model;

/// The compared layers, in the order of every `[ImageSet; 3]` here.
pub const LAYERS: [&str; 3] = ["albedo", "normals", "relit"];

/// Index of the second draw's first batch: far from the first draw's batches, so that the two
/// share no image.
const OTHER_START: u64 = 1 << 20;

/// Planar `[3, s, s]` from pixels.
fn planar(pixels: &[[f32; 3]]) -> Vec<f32> {
    (0..3)
        .flat_map(|k| pixels.iter().map(move |p| p[k]))
        .collect()
}

/// Empty albedo / normals / relit sets at the output and volume resolutions.
fn empty_sets(side: usize, side_lo: usize) -> [ImageSet; 3] {
    [
        ImageSet::new(side, 3),
        ImageSet::new(side_lo, 3),
        ImageSet::new(side, 3),
    ]
}

fn extend(sets: &mut [ImageSet; 3], batch: &Batch) {
    sets[0].extend_planar(&batch.layers.albedo_hi);
    sets[1].extend_planar(&batch.layers.normals_lo);
    let relit: Vec<f32> = batch.layers.relit.iter().map(|v| 0.5 * (v + 1.0)).collect();
    sets[2].extend_planar(&relit);
}

/// Two disjoint draws of `samples` dataset images, and the cameras and lightings of the first,
/// which the fakes copy.
pub struct DataSets {
    /// The environments the draws index.
    pub lights: Arc<Vec<LightMapSet>>,
    /// Per image of the first draw: its camera pose and lighting.
    pub poses: Vec<Pose>,
    pub draws: Vec<LightingDraw>,
    /// The first draw's layers (the floor's left side).
    pub real: [ImageSet; 3],
    /// The second draw's layers: what fakes and the first draw are compared with.
    pub other: [ImageSet; 3],
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
        let mut out = DataSets {
            lights: bank.shared(),
            poses: Vec::with_capacity(samples),
            draws: Vec::with_capacity(samples),
            real: empty_sets(side, side_lo),
            other: empty_sets(side, side_lo),
        };
        let batches = samples.div_ceil(batch);
        for i in 0..batches as u64 {
            tracing::info!("sample quality: dataset batch {} of {batches}", i + 1);
            let a = examples.batch(i, batch)?;
            let o = examples.batch(OTHER_START + i, batch)?;
            out.poses.extend_from_slice(&a.poses);
            out.draws.extend_from_slice(&a.draws);
            extend(&mut out.real, &a);
            extend(&mut out.other, &o);
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

    /// The first draw against the second, per layer.
    pub fn floor(&self, options: &SwdOptions) -> Result<[Swd; 3], EvalError> {
        distances(&self.real, &self.other, options)
    }
}

/// Per layer, `a` against `b`.
pub fn distances(
    a: &[ImageSet; 3],
    b: &[ImageSet; 3],
    options: &SwdOptions,
) -> Result<[Swd; 3], EvalError> {
    let d = |k: usize| -> Result<Swd, EvalError> {
        tracing::info!("sample quality: {}", LAYERS[k]);
        Ok(swd(&a[k], &b[k], options)?)
    };
    Ok([d(0)?, d(1)?, d(2)?])
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
) -> Result<[ImageSet; 3], EvalError> {
    let mut fake = empty_sets(g.output_resolution(), g.volume_resolution);
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
            fake[0].images.push(planar(&v.albedo));
            fake[1].images.push(planar(&v.normals_lo));
            fake[2].images.push(planar(&v.relit));
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
    let model = distances(&fake, &data.other, options)?;
    let floor = data.floor(options)?;
    Ok(LAYERS
        .iter()
        .zip(model.into_iter().zip(floor))
        .map(|(layer, (model, data))| SwdRow {
            layer: layer.to_string(),
            model,
            data,
        })
        .collect())
}
