//! Training the estimator (`volux data pseudo-gt --train`): a pool of synthetic pairs rendered
//! once (identities `0..pool`, each at its own pose and lighting), augmented afresh every time
//! one is drawn ([`crate::augmentation`]); Adam on the three losses ([`crate::objective`]) with
//! a cosine decay of the learning rate over the run; every `eval_every` steps the held-out
//! identities are measured, a line is added to `log.jsonl` and the estimator is saved
//! ([`crate::weights`]), so a run stopped at any point leaves its last measured estimator.

use std::fs::{File, OpenOptions};
use std::io::Write as _;
use std::path::Path;
use std::time::Instant;

use burn::optim::{GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;
use serde::Serialize;
use volux_envmap::LightMapSet;
use volux_envmap::random::{self, SplitMix64};
use volux_model::backend::to_f32_vec;
use volux_train::adam::FusedAdam;

use crate::augmentation::{AugmentationRanges, Augmented, augment};
use crate::error::PseudoGtError;
use crate::estimator::{Estimate, Estimator, EstimatorConfig, photo_tensor};
use crate::objective::{self, Accuracy, Targets, losses};
use crate::synthetic_pairs::{HELD_OUT_FIRST, SyntheticPair, render_pair};
use crate::weights::{self, EstimatorFile, TrainingRecord};

/// The random stream of batch draws and augmentations.
const BATCH_STREAM: u64 = 0xB5AD_4ECE_DA1C_E2A9;

/// What a training run does.
#[derive(Clone, Debug)]
pub struct TrainOptions {
    pub config: EstimatorConfig,
    pub batch: usize,
    pub learning_rate: f64,
    /// Training pairs rendered once (identities `0..pool`).
    pub pool: usize,
    /// Held-out identities measured at every evaluation.
    pub held_out: usize,
    /// Rays per pixel per axis of the rendered pairs.
    pub supersample: usize,
    pub seed: u64,
    /// Wall-clock budget of the steps (the learning rate decays over it).
    pub minutes: f64,
    /// Stop after this many steps even if time is left (the decay then runs over the steps).
    pub max_steps: Option<u64>,
    pub eval_every: u64,
    pub augmentation: AugmentationRanges,
}

impl Default for TrainOptions {
    fn default() -> Self {
        TrainOptions {
            config: EstimatorConfig::default(),
            batch: 8,
            learning_rate: 2e-3,
            pool: 3000,
            held_out: 64,
            supersample: 1,
            seed: 0,
            minutes: 45.0,
            max_steps: None,
            eval_every: 500,
            augmentation: AugmentationRanges::default(),
        }
    }
}

impl TrainOptions {
    /// Why these options cannot run, if they cannot.
    pub fn check(&self) -> Result<(), PseudoGtError> {
        self.config.check().map_err(PseudoGtError::Invalid)?;
        let bad = |what: String| Err(PseudoGtError::Invalid(what));
        if !(1..=256).contains(&self.batch) {
            return bad(format!("batch = {} must be 1 to 256", self.batch));
        }
        if !(1..=100_000).contains(&self.pool) || !(1..=10_000).contains(&self.held_out) {
            return bad(format!(
                "pool = {} must be 1 to 100000 and held_out = {} 1 to 10000",
                self.pool, self.held_out
            ));
        }
        if !(self.learning_rate.is_finite() && self.learning_rate > 0.0 && self.learning_rate < 1.0)
        {
            return bad(format!(
                "learning rate {} must be in (0, 1)",
                self.learning_rate
            ));
        }
        if !(self.minutes.is_finite() && self.minutes > 0.0 && self.minutes <= 10_080.0) {
            return bad(format!("minutes = {} must be in (0, 10080]", self.minutes));
        }
        if self.max_steps == Some(0) {
            return bad("steps = 0: give at least 1".to_string());
        }
        if !(1..=4).contains(&self.supersample) || self.eval_every == 0 {
            return bad(format!(
                "supersample = {} must be 1 to 4 and eval_every = {} at least 1",
                self.supersample, self.eval_every
            ));
        }
        Ok(())
    }
}

/// One evaluation of a run: what `log.jsonl` holds per line.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Progress {
    pub step: u64,
    pub images: u64,
    /// Seconds of steps (rendering the pool and evaluating not counted).
    pub seconds: f64,
    /// Training losses averaged since the last evaluation.
    pub albedo_l1: f64,
    pub normal_1_minus_cos: f64,
    pub mask_bce: f64,
    /// On the held-out identities at the working resolution.
    pub held_out: Accuracy,
}

/// Renders pairs of `identities` in parallel.
pub fn render_pairs(
    lights: &[LightMapSet],
    identities: impl IntoParallelIterator<Item = u64>,
    seed: u64,
    side: usize,
    supersample: usize,
) -> Result<Vec<SyntheticPair>, PseudoGtError> {
    identities
        .into_par_iter()
        .map(|identity| {
            render_pair(lights, identity, seed, side, supersample)
                .map_err(|source| PseudoGtError::Synthetic { identity, source })
        })
        .collect()
}

/// The held-out test inputs: pairs of identities from [`HELD_OUT_FIRST`] on, at `side`,
/// augmented with fixed draws.
pub fn held_out_inputs(
    lights: &[LightMapSet],
    count: usize,
    seed: u64,
    side: usize,
    supersample: usize,
    ranges: &AugmentationRanges,
) -> Result<Vec<Augmented>, PseudoGtError> {
    let first = HELD_OUT_FIRST;
    let pairs = render_pairs(lights, first..first + count as u64, seed, side, supersample)?;
    Ok(pairs
        .iter()
        .enumerate()
        .map(|(i, p)| {
            augment(
                p,
                ranges,
                &mut SplitMix64::new(random::stream_seed(seed, i as u64, BATCH_STREAM ^ 1)),
            )
        })
        .collect())
}

/// The estimates of `estimator` for `inputs` (each at its own side), in batches of 16.
pub fn estimate_inputs(
    estimator: &Estimator,
    inputs: &[Augmented],
    resolution: usize,
) -> Vec<Estimate> {
    let mut all = Vec::with_capacity(inputs.len());
    for chunk in inputs.chunks(16) {
        let side = chunk[0].side;
        let photos: Vec<&[volux_envmap::Rgb]> = chunk.iter().map(|a| a.photo.as_slice()).collect();
        all.extend(estimator.estimate(&photos, side, resolution));
    }
    all
}

/// The mean accuracy of `estimates` against the true layers of `inputs`.
pub fn score(estimates: &[Estimate], inputs: &[Augmented]) -> Accuracy {
    let all: Vec<Accuracy> = estimates
        .iter()
        .zip(inputs)
        .map(|(e, a)| {
            objective::accuracy(
                (&e.albedo, &e.normals, &e.mask),
                (&a.albedo, &a.normals, &a.mask),
            )
        })
        .collect();
    objective::mean(&all)
}

/// The mean accuracy of `estimator` on `inputs` (estimated at their own side).
pub fn measure(estimator: &Estimator, inputs: &[Augmented], resolution: usize) -> Accuracy {
    score(&estimate_inputs(estimator, inputs, resolution), inputs)
}

fn planar<const N: usize>(images: &[&[[f32; N]]], side: usize, device: &Device) -> Tensor<4> {
    let mut flat = Vec::with_capacity(images.len() * N * side * side);
    for image in images {
        for c in 0..N {
            flat.extend(image.iter().map(|t| t[c]));
        }
    }
    Tensor::from_data(TensorData::new(flat, [images.len(), N, side, side]), device)
}

/// Trains an estimator with `options`, lighting pairs with `lights`, into `out` (its
/// `estimator.bpk`, `estimator.toml` and `log.jsonl`); `on_progress` sees every evaluation.
pub fn train(
    options: &TrainOptions,
    lights: &[LightMapSet],
    out: &Path,
    on_progress: &mut dyn FnMut(&Progress),
) -> Result<(Estimator, EstimatorFile), PseudoGtError> {
    options.check()?;
    let side = options.config.resolution;
    let io = |source| PseudoGtError::Io {
        path: out.to_path_buf(),
        source,
    };
    if out.exists() && !out.is_dir() {
        return Err(PseudoGtError::Invalid(format!(
            "{} is a file: give a folder for the estimator",
            out.display()
        )));
    }
    std::fs::create_dir_all(out).map_err(io)?;
    let log_path = out.join("log.jsonl");
    let mut log: File = OpenOptions::new()
        .create(true)
        .write(true)
        .truncate(true)
        .open(&log_path)
        .map_err(|source| PseudoGtError::Io {
            path: log_path.clone(),
            source,
        })?;
    let start = Instant::now();
    let pool = render_pairs(
        lights,
        0..options.pool as u64,
        options.seed,
        side,
        options.supersample,
    )?;
    let test = held_out_inputs(
        lights,
        options.held_out,
        options.seed,
        side,
        options.supersample,
        &options.augmentation,
    )?;
    tracing::info!(
        "rendered {} training and {} held-out pairs at {side}x{side} in {:.1} s",
        pool.len(),
        test.len(),
        start.elapsed().as_secs_f64()
    );
    let device = Device::flex().autodiff();
    device.seed(options.seed);
    let mut model = options.config.init(&device);
    let mut opt = ModuleOptimizer::from(FusedAdam::new(0.9, 0.99, 1e-8));
    let budget = options.minutes * 60.0;
    let (mut seconds, mut step) = (0.0f64, 0u64);
    let mut sums = [0.0f64; 3];
    let mut since = 0u64;
    let mut last: Option<(EstimatorFile, Estimator)> = None;
    loop {
        let fraction = match options.max_steps {
            Some(max) => (step as f64 / max as f64).max(seconds / budget),
            None => seconds / budget,
        };
        let done = fraction >= 1.0;
        if done || (step > 0 && step.is_multiple_of(options.eval_every)) {
            let n = since.max(1) as f64;
            let progress = Progress {
                step,
                images: step * options.batch as u64,
                seconds,
                albedo_l1: sums[0] / n,
                normal_1_minus_cos: sums[1] / n,
                mask_bce: sums[2] / n,
                held_out: measure(&model, &test, side),
            };
            let line = serde_json::to_string(&progress).unwrap_or_default();
            writeln!(log, "{line}").map_err(|source| PseudoGtError::Io {
                path: log_path.clone(),
                source,
            })?;
            let file = EstimatorFile {
                estimator: options.config.clone(),
                training: TrainingRecord {
                    seed: options.seed,
                    steps: step,
                    images: progress.images,
                    seconds,
                    batch: options.batch,
                    learning_rate: options.learning_rate,
                    pool: options.pool,
                    held_out: options.held_out,
                },
                held_out: progress.held_out,
            };
            weights::save(out, &model, &file)?;
            on_progress(&progress);
            (sums, since) = ([0.0; 3], 0);
            last = Some((file, model.clone()));
        }
        if done {
            break;
        }
        let t0 = Instant::now();
        let mut rng = SplitMix64::new(random::stream_seed(options.seed, step, BATCH_STREAM));
        let draws: Vec<(usize, u64)> = (0..options.batch)
            .map(|_| {
                (
                    (rng.next_u64() % pool.len() as u64) as usize,
                    rng.next_u64(),
                )
            })
            .collect();
        let batch: Vec<Augmented> = draws
            .par_iter()
            .map(|&(i, s)| augment(&pool[i], &options.augmentation, &mut SplitMix64::new(s)))
            .collect();
        let photos: Vec<&[volux_envmap::Rgb]> = batch.iter().map(|a| a.photo.as_slice()).collect();
        let albedo: Vec<&[[f32; 3]]> = batch.iter().map(|a| a.albedo.as_slice()).collect();
        let normals: Vec<&[[f32; 3]]> = batch.iter().map(|a| a.normals.as_slice()).collect();
        let masks: Vec<Vec<[f32; 1]>> = batch
            .iter()
            .map(|a| a.mask.iter().map(|&m| [m]).collect())
            .collect();
        let masks: Vec<&[[f32; 1]]> = masks.iter().map(Vec::as_slice).collect();
        let targets = Targets {
            albedo: planar(&albedo, side, &device),
            normals: planar(&normals, side, &device),
            mask: planar(&masks, side, &device),
        };
        let estimate = model.forward(photo_tensor(&photos, side, &device));
        let terms = losses(&estimate, &targets);
        let total = terms.total();
        let values = [terms.albedo, terms.normals, terms.mask].map(|t| f64::from(to_f32_vec(t)[0]));
        let value = values.iter().sum::<f64>() as f32;
        if !value.is_finite() {
            return Err(PseudoGtError::NonFiniteLoss { step, value });
        }
        let mut grads = total.backward();
        let grads = GradientsParams::from_module(&mut grads, &model);
        let lr =
            options.learning_rate * (0.1 + 0.45 * (1.0 + (std::f64::consts::PI * fraction).cos()));
        model = opt.step(lr, model, grads);
        for k in 0..3 {
            sums[k] += values[k];
        }
        since += 1;
        step += 1;
        seconds += t0.elapsed().as_secs_f64();
    }
    let (file, model) = last.expect("the loop evaluates before it stops");
    Ok((model, file))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_short_run_lowers_the_loss_and_saves_a_loadable_estimator() {
        let lights = crate::synthetic_pairs::tests::bank();
        let dir = tempfile::tempdir().unwrap();
        let options = TrainOptions {
            config: EstimatorConfig {
                resolution: 16,
                channels: vec![8, 16],
            },
            batch: 4,
            pool: 8,
            held_out: 4,
            supersample: 1,
            max_steps: Some(30),
            eval_every: 10,
            ..TrainOptions::default()
        };
        let mut seen = Vec::new();
        let (model, file) =
            train(&options, &lights, dir.path(), &mut |p| seen.push(p.clone())).unwrap();
        assert_eq!(
            seen.iter().map(|p| p.step).collect::<Vec<_>>(),
            vec![10, 20, 30]
        );
        // In 30 steps the normals learn first (the mask and albedo barely move yet), so the
        // summed loss is what falls.
        let total = |p: &Progress| p.albedo_l1 + p.normal_1_minus_cos + p.mask_bce;
        assert!(total(&seen[2]) < 0.95 * total(&seen[0]), "{seen:?}");
        assert_eq!(file.training.steps, 30);
        let log = std::fs::read_to_string(dir.path().join("log.jsonl")).unwrap();
        assert_eq!(log.lines().count(), 3);
        let (loaded, loaded_file) = weights::load(dir.path(), &Device::flex()).unwrap();
        assert_eq!(loaded_file, file);
        let photo = vec![[0.4f32, 0.5, 0.6]; 16 * 16];
        let a = model.estimate(&[&photo], 16, 16);
        let b = loaded.estimate(&[&photo], 16, 16);
        assert_eq!(a, b);
    }

    #[test]
    fn bad_options_are_named() {
        let bad = |o: TrainOptions| o.check().unwrap_err().to_string();
        assert!(
            bad(TrainOptions {
                batch: 0,
                ..Default::default()
            })
            .contains("batch = 0")
        );
        assert!(
            bad(TrainOptions {
                minutes: f64::NAN,
                ..Default::default()
            })
            .contains("minutes = NaN")
        );
        assert!(
            bad(TrainOptions {
                learning_rate: -1.0,
                ..Default::default()
            })
            .contains("-1")
        );
        assert!(
            bad(TrainOptions {
                max_steps: Some(0),
                ..Default::default()
            })
            .contains("steps = 0")
        );
        let file = tempfile::NamedTempFile::new().unwrap();
        let lights = crate::synthetic_pairs::tests::bank();
        let e = train(&TrainOptions::default(), &lights, file.path(), &mut |_| {})
            .unwrap_err()
            .to_string();
        assert!(e.contains("is a file"), "{e}");
    }
}
