//! The training loop: builds (or resumes) the networks and optimisers of a config, feeds them
//! batches in order, follows the schedule, keeps the EMA, logs metrics, draws the sample grid
//! and checkpoints. Every step is a pure function of the checkpointed state, the config and
//! the step number (batch `s` is examples `s * batch ..`, latents and ray jitter are seeded by
//! `(seed, s)`), so a resumed run computes the same losses as one that never stopped.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use burn::module::Module;
use burn::optim::ModuleOptimizer;
use burn::tensor::Device;
use volux_data::batch::BatchLoader;
use volux_data::examples::{Examples, ExamplesError};
use volux_envmap::LightMapSet;
use volux_envmap::random::{self, SplitMix64};
use volux_model::backend::BackendKind;
use volux_model::generator::Generator;
use volux_model::pose::Pose;
use volux_model::profile::{self, Phase as ProfilePhase};

use crate::adam::FusedAdam;
use crate::checkpoint::{self, CHECKPOINT_FORMAT, CheckpointError, Networks, TrainState};
use crate::config::TrainConfig;
use crate::fake_poses::FakePoses;
use crate::metrics::{
    Averages, EvalLine, MetricsLine, MetricsLog, ProgressEvaluator, peak_rss_mib,
};
use crate::networks::{Discriminators, ema_beta, materialize, update_ema};
use crate::run_folder;
use crate::sampling;
use crate::schedule::Stage;
use crate::step::{Phase, StepInputs, side_by_side_on, train_step};

mod error;

pub use error::TrainError;
use error::io_error;

/// How to run a config.
#[derive(Clone, Debug)]
pub struct TrainOptions {
    pub backend: BackendKind,
    /// The run folder: checkpoints, grids, metrics.
    pub out: PathBuf,
    /// Continue from the newest checkpoint in `out` (an error if there is none).
    pub resume: bool,
    /// Start afresh in an `out` that holds a run, deleting that run's checkpoints, metrics
    /// and grids first (without it, such a folder is refused unless resuming).
    pub force: bool,
    /// Stop after this many steps of this invocation (a checkpoint is written first).
    pub max_steps: Option<u64>,
}

/// What one step reported.
#[derive(Clone, Debug)]
pub struct StepReport {
    pub step: u64,
    pub images: u64,
    pub total_images: u64,
    pub stage: Stage,
    pub fade: Vec<f64>,
    pub losses: BTreeMap<&'static str, f64>,
    /// The pose each fake was rendered from.
    pub fake_poses: Vec<Pose>,
    pub seconds: f64,
    pub skipped: Option<String>,
}

/// What the loop tells its caller as it goes.
#[derive(Clone, Debug)]
pub enum Event {
    Step(StepReport),
    Metrics(MetricsLine),
    Eval(EvalLine),
    Grid(PathBuf),
    Checkpoint(PathBuf),
}

/// Why [`Trainer::run`] returned.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Finish {
    /// The schedule is complete.
    Done,
    /// `max_steps` were taken.
    Steps,
    /// `output.minutes` ran out.
    Time,
}

/// A training run in progress.
pub struct Trainer {
    config: TrainConfig,
    options: TrainOptions,
    device: Device,
    nets: Networks,
    state: TrainState,
    lights: Arc<Vec<LightMapSet>>,
    examples: Examples,
    loader: Option<BatchLoader<ExamplesError>>,
    metrics: MetricsLog,
    averages: Averages,
    last_checkpoint: Option<PathBuf>,
    poisoned: Vec<(u64, Phase)>,
    /// Where the fakes' cameras come from (resolved for this dataset).
    fake_poses: FakePoses,
    /// The light evaluation of `[output] eval_kimg`, when one is attached.
    evaluator: Option<Box<dyn ProgressEvaluator>>,
    /// Whether steps run their independent parts side by side: [`side_by_side_on`] this
    /// config and device, unless [`Trainer::set_in_turn`] asked for them in turn.
    side_by_side: bool,
}

/// The `purpose` of [`derived_seed`] for the fakes' camera draws (latents use `0..batch`, the
/// ray jitter `u64::MAX`).
const POSE_PURPOSE: u64 = u64::MAX - 1;

/// Mixes the run's seed with a step number and a purpose.
fn derived_seed(seed: u64, step: u64, purpose: u64) -> u64 {
    random::stream_seed(seed ^ purpose, step, random::GOLDEN_GAMMA)
}

impl Trainer {
    /// Builds the networks of `config` (or loads the newest checkpoint of `options.out` when
    /// resuming), the data and the logs.
    pub fn new(config: TrainConfig, options: TrainOptions) -> Result<Trainer, TrainError> {
        let device = options.backend.device()?.autodiff();
        if !options.resume {
            let existing = run_folder::run_files(&options.out);
            if !existing.is_empty() && !options.force {
                return Err(TrainError::RunExists {
                    out: options.out.clone(),
                    found: existing,
                    resumable: !checkpoint::list(&options.out).is_empty(),
                });
            }
            run_folder::clear(&options.out).map_err(|(path, e)| io_error(&path, e))?;
        }
        std::fs::create_dir_all(&options.out).map_err(|e| io_error(&options.out, e))?;
        let t = &config.train;
        // The backend's random generator is process-wide: one run per process is reproducible.
        device.seed(t.seed);
        let g = config.generator().init(&device)?;
        materialize(&g);
        let d = Discriminators::init(&config, &device);
        materialize(&d);
        let ema = g.valid();
        let adam = || ModuleOptimizer::from(FusedAdam::new(t.beta1 as f32, t.beta2 as f32, 1e-8));
        let mut nets = Networks {
            g,
            ema,
            d,
            opt_g: adam(),
            opt_d: adam(),
        };
        let config_path = std::fs::canonicalize(&config.path).unwrap_or(config.path.clone());
        let resolved_config = config.resolved();
        tracing::debug!("the config with its defaults filled in:\n{resolved_config}");
        let mut state = TrainState {
            format: CHECKPOINT_FORMAT,
            step: 0,
            images: 0,
            nonfinite_in_row: 0,
            skipped: 0,
            seed: t.seed,
            seconds: 0.0,
            shapes: config.shapes(),
            discriminators: nets.d.names().iter().map(|s| s.to_string()).collect(),
            config_path,
            config: config.text.clone(),
            resolved_config,
        };
        let mut last_checkpoint = None;
        if options.resume {
            let dir = checkpoint::latest(&options.out)?;
            let saved = checkpoint::read_state(&dir)?;
            if saved.shapes != state.shapes || saved.discriminators != state.discriminators {
                return Err(CheckpointError::Mismatch {
                    path: dir,
                    checkpoint: format!(
                        "{} discriminators {:?}",
                        saved.shapes.trim().replace('\n', ", "),
                        saved.discriminators
                    ),
                    config: format!(
                        "{} discriminators {:?}",
                        state.shapes.trim().replace('\n', ", "),
                        state.discriminators
                    ),
                }
                .into());
            }
            nets = checkpoint::load(&dir, nets)?;
            tracing::info!(
                "resuming from {} (step {}, {:.1} kimg)",
                dir.display(),
                saved.step,
                saved.images as f64 / 1000.0
            );
            state = TrainState {
                config_path: state.config_path,
                config: state.config,
                resolved_config: state.resolved_config,
                ..saved
            };
            last_checkpoint = Some(dir);
        }
        let bank = config.data.light_bank()?;
        let examples = Examples::open(&config.data, &config.data_hashed, &bank)?;
        let lights = bank.shared();
        let fake_poses = config.train.fake_poses.resolve(config.data.has_poses());
        tracing::info!(
            "fakes are rendered from {}",
            match fake_poses {
                FakePoses::Dataset => "the real batch's poses",
                FakePoses::Swap => "the real batch's poses, swapped between examples",
                _ => "the camera prior [train.pose_prior]",
            }
        );
        let running: Vec<&str> = config
            .loss
            .named()
            .into_iter()
            .filter(|&(_, w)| w > 0.0)
            .map(|(term, _)| term)
            .collect();
        if config.left_out.is_empty() {
            tracing::info!("loss terms: {}", running.join(", "));
        } else {
            let left_out: Vec<String> = config.left_out.iter().map(ToString::to_string).collect();
            tracing::info!(
                "loss terms: {}; left out, the dataset lacks their reals: {}",
                running.join(", "),
                left_out.join(", ")
            );
        }
        let metrics_path = options.out.join(run_folder::METRICS);
        let metrics =
            MetricsLog::open(&metrics_path, state.step).map_err(|e| io_error(&metrics_path, e))?;
        let side_by_side = side_by_side_on(&device, &config);
        let mut trainer = Trainer {
            config,
            options,
            device,
            nets,
            state,
            lights,
            examples,
            loader: None,
            metrics,
            averages: Averages::default(),
            last_checkpoint,
            poisoned: Vec::new(),
            fake_poses,
            evaluator: None,
            side_by_side,
        };
        trainer.open_octaves();
        Ok(trainer)
    }

    /// Sets the positional encoding's window of the generator and its EMA to the schedule's
    /// at the images seen (`[schedule] open_octaves`): after every step (and on starting or
    /// seeking), so that the next step, and grids and evaluations between steps, see the
    /// schedule's field at the images seen.
    fn open_octaves(&mut self) {
        let window = self.config.octave_window(self.state.images);
        self.nets.g.set_octave_window(window);
        self.nets.ema.set_octave_window(window);
    }

    pub fn state(&self) -> &TrainState {
        &self.state
    }

    pub fn config(&self) -> &TrainConfig {
        &self.config
    }

    /// The EMA generator (on the backend's device without autodiff).
    pub fn ema(&self) -> &Generator {
        &self.nets.ema
    }

    /// Images in the whole schedule.
    pub fn total_images(&self) -> u64 {
        let s = &self.config.schedule;
        ((s.stage1_kimg + s.stage2_kimg) * 1000.0).round() as u64
    }

    /// The generator being trained.
    pub fn generator(&self) -> &Generator {
        &self.nets.g
    }

    /// The discriminators being trained.
    pub fn discriminators(&self) -> &Discriminators {
        &self.nets.d
    }

    /// The training device (with autodiff).
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// Runs each step's independent parts (the discriminators, the generator's backward pass
    /// beside the discriminator phase) in turn instead of side by side on the CPU's threads:
    /// the same results, slower, with each part's time its own (the benchmark's `--in-turn`).
    pub fn set_in_turn(&mut self, in_turn: bool) {
        self.side_by_side = !in_turn && side_by_side_on(&self.device, &self.config);
    }

    /// Places the run at `step` with `images` seen, without training (benchmarks): the next
    /// step trains batch `step` at the stage, fade-in and active terms of `images`. The batch
    /// stream restarts only if `step` is not the next step anyway.
    pub fn seek(&mut self, step: u64, images: u64) {
        if step != self.state.step {
            self.loader = None;
        }
        self.state.step = step;
        self.state.images = images;
        self.open_octaves();
    }

    /// Attaches the light evaluation that [`Trainer::run`] takes every `[output] eval_kimg`
    /// thousand images (and at the run's start and end); without one, none is taken.
    pub fn set_evaluator(&mut self, evaluator: Box<dyn ProgressEvaluator>) {
        self.evaluator = Some(evaluator);
    }

    /// Measures the EMA generator with the attached evaluator and appends the result to
    /// metrics.jsonl (`None` without an evaluator).
    pub fn evaluate(&mut self) -> Result<Option<EvalLine>, TrainError> {
        let Some(evaluator) = self.evaluator.as_mut() else {
            return Ok(None);
        };
        let started = Instant::now();
        let kimg = self.state.images as f64 / 1000.0;
        let eval = evaluator
            .measure(&self.nets.ema)
            .map_err(|source| TrainError::Eval { kimg, source })?;
        let line = EvalLine {
            step: self.state.step,
            images: self.state.images,
            kimg,
            minutes: self.state.seconds / 60.0,
            eval_seconds: started.elapsed().as_secs_f64(),
            eval,
        };
        self.metrics
            .write(&line)
            .map_err(|e| io_error(self.metrics.path(), e))?;
        Ok(Some(line))
    }

    /// Test hook: the loss of this phase of these steps is made NaN.
    #[doc(hidden)]
    pub fn poison_steps(&mut self, steps: &[(u64, Phase)]) {
        self.poisoned = steps.to_vec();
    }

    /// Takes one step on the next batch.
    pub fn step(&mut self) -> Result<StepReport, TrainError> {
        let started = Instant::now();
        let c = &self.config;
        let batch_size = c.train.batch;
        let loader = self.loader.get_or_insert_with(|| {
            self.examples
                .loader(self.state.step, batch_size, c.train.prefetch)
        });
        let batch = loader.next_batch().ok_or(TrainError::LoaderStopped)??;
        let (step, images) = (self.state.step, self.state.images);
        let stage = c.schedule.stage(images);
        let active = c.schedule.active(images, &c.loss);
        let blocks = c.blocks();
        let fade = c.schedule.fade(images, blocks);
        let lighting = if active.needs_relit() {
            Some(batch.lighting(&self.lights, &self.device)?)
        } else {
            None
        };
        let reals = batch.to_tensors(&self.device);
        let seeds: Vec<u64> = (0..batch_size as u64)
            .map(|i| derived_seed(c.train.seed, step, i))
            .collect();
        let z = sampling::latents(&seeds, c.generator().mapping.z_dim, &self.device);
        let poses = self.fake_poses.poses(
            &batch.poses,
            &c.train.pose_prior,
            &mut SplitMix64::new(derived_seed(c.train.seed, step, POSE_PURPOSE)),
        );
        self.device.seed(derived_seed(c.train.seed, step, u64::MAX));
        let interval = c.train.r1_interval;
        let inputs = StepInputs {
            z,
            poses: &poses,
            lighting: lighting.as_ref(),
            reals: &reals,
            background: c.data.albedo_background(),
            active,
            weights: c.loss,
            fade: (stage == Stage::One).then(|| fade.clone()),
            fade_discriminator: c.schedule.fade_discriminator,
            r1: (interval > 0 && step.is_multiple_of(interval as u64))
                .then_some((c.train.r1_gamma, interval)),
            lr_g: c.train.lr_g,
            lr_d: c.train.lr_d,
            side_by_side: self.side_by_side,
            poison: self
                .poisoned
                .iter()
                .find(|(s, _)| *s == step)
                .map(|&(_, phase)| phase),
        };
        let n = &mut self.nets;
        let outcome = train_step(&mut n.g, &mut n.d, &mut n.opt_g, &mut n.opt_d, &inputs)?;
        self.state.step += 1;
        if outcome.skipped.is_some() {
            self.state.skipped += 1;
            self.state.nonfinite_in_row += 1;
        } else {
            self.state.nonfinite_in_row = 0;
            self.state.images += batch_size as u64;
            let beta = ema_beta(
                batch_size,
                self.state.images,
                c.train.ema_kimg,
                c.train.ema_rampup,
            );
            n.ema = profile::timed(ProfilePhase::Ema, || update_ema(n.ema.clone(), &n.g, beta));
            self.averages.add(&outcome.losses);
        }
        self.open_octaves();
        Ok(StepReport {
            step,
            images: self.state.images,
            total_images: self.total_images(),
            stage,
            fade,
            losses: outcome.losses,
            fake_poses: poses,
            seconds: started.elapsed().as_secs_f64(),
            skipped: outcome.skipped,
        })
    }

    /// Writes a checkpoint of the current state.
    pub fn checkpoint(&mut self) -> Result<PathBuf, TrainError> {
        let path = checkpoint::save(
            &self.options.out,
            &self.state,
            &self.nets,
            self.config.output.keep,
        )?;
        self.last_checkpoint = Some(path.clone());
        Ok(path)
    }

    /// Renders the EMA generator at the grid seeds (frontal, under the first environment) and
    /// writes `grids/grid-<images>.png`.
    pub fn write_grid(&self) -> Result<PathBuf, TrainError> {
        let c = &self.config;
        let ema = &self.nets.ema;
        let device = self.device.clone().inner();
        let seeds = &c.output.grid_seeds;
        let z = sampling::latents(seeds, c.generator().mapping.z_dim, &device);
        let poses = vec![Pose::FRONTAL; seeds.len()];
        let layers = sampling::render_under(
            ema,
            z,
            &poses,
            &self.lights[0],
            0.0,
            c.data.albedo_background(),
        )?;
        let sheet = sampling::grid(&layers);
        let dir = self.options.out.join(run_folder::GRIDS);
        std::fs::create_dir_all(&dir).map_err(|e| io_error(&dir, e))?;
        let path = dir.join(format!("grid-{:08}.png", self.state.images));
        volux_envmap::io::save_png(&path, sheet.width(), sheet.height(), &sheet.to_u8())
            .map_err(TrainError::Grid)?;
        Ok(path)
    }

    /// Trains until the schedule ends, `max_steps` or the time budget, checkpointing on the
    /// way and at the end. Too many non-finite steps in a row end it with an error (no
    /// checkpoint of the broken state is written).
    pub fn run(&mut self, on_event: &mut dyn FnMut(Event)) -> Result<Finish, TrainError> {
        let started = Instant::now();
        let seconds_before = self.state.seconds;
        let first_step = self.state.step;
        let out = self.config.output.clone();
        let every = |kimg: f64| (kimg * 1000.0).round() as u64;
        let (grid_every, ckpt_every) = (every(out.grid_kimg), every(out.checkpoint_kimg));
        let eval_every = every(out.eval_kimg);
        let crossed =
            |before: u64, after: u64, every: u64| every > 0 && before / every != after / every;
        let mut group_started = Instant::now();
        let mut group_steps = 0u64;
        let mut group_images = 0u64;
        let mut last_grid = None;
        let mut last_eval = None;
        if self.state.step == 0 {
            on_event(Event::Grid(self.write_grid()?));
            last_grid = Some(0);
            if let Some(line) = self.evaluate()? {
                on_event(Event::Eval(line));
                last_eval = Some(0);
            }
        }
        let finish = loop {
            if self.state.images >= self.total_images() {
                break Finish::Done;
            }
            if self
                .options
                .max_steps
                .is_some_and(|m| self.state.step - first_step >= m)
            {
                break Finish::Steps;
            }
            if out.minutes > 0.0 && started.elapsed().as_secs_f64() >= out.minutes * 60.0 {
                break Finish::Time;
            }
            let before = self.state.images;
            let report = self.step()?;
            self.state.seconds = seconds_before + started.elapsed().as_secs_f64();
            group_steps += 1;
            group_images += report.images - before;
            let skipped = report.skipped.clone();
            let (stage, fade) = (report.stage, report.fade.clone());
            on_event(Event::Step(report));
            if let Some(reason) = skipped {
                tracing::warn!("{}", skipped_step_message(&self.state, &reason));
                if self.state.nonfinite_in_row >= self.config.train.max_nonfinite {
                    return Err(TrainError::NonFinite {
                        count: self.state.nonfinite_in_row,
                        reason,
                        step: self.state.step,
                        last_good: self.last_checkpoint.clone(),
                    });
                }
            }
            if self.state.step.is_multiple_of(out.log_every) {
                let secs = group_started.elapsed().as_secs_f64();
                let line = self.metrics_line(
                    stage,
                    fade,
                    secs / group_steps as f64,
                    group_images as f64 / secs,
                );
                self.metrics
                    .write(&line)
                    .map_err(|e| io_error(self.metrics.path(), e))?;
                on_event(Event::Metrics(line));
                (group_started, group_steps, group_images) = (Instant::now(), 0, 0);
            }
            let after = self.state.images;
            if crossed(before, after, grid_every) {
                on_event(Event::Grid(self.write_grid()?));
                last_grid = Some(after);
            }
            if crossed(before, after, eval_every)
                && let Some(line) = self.evaluate()?
            {
                on_event(Event::Eval(line));
                last_eval = Some(after);
            }
            self.state.seconds = seconds_before + started.elapsed().as_secs_f64();
            if crossed(before, after, ckpt_every) {
                on_event(Event::Checkpoint(self.checkpoint()?));
            }
        };
        if last_eval != Some(self.state.images)
            && let Some(line) = self.evaluate()?
        {
            on_event(Event::Eval(line));
        }
        self.state.seconds = seconds_before + started.elapsed().as_secs_f64();
        if self
            .last_checkpoint
            .as_ref()
            .and_then(|p| checkpoint::read_state(p).ok())
            .is_none_or(|s| s.step != self.state.step)
        {
            on_event(Event::Checkpoint(self.checkpoint()?));
        }
        if last_grid != Some(self.state.images) {
            on_event(Event::Grid(self.write_grid()?));
        }
        Ok(finish)
    }

    /// The line of a group of steps whose last step trained in `stage` with `fade`.
    fn metrics_line(
        &mut self,
        stage: Stage,
        fade: Vec<f64>,
        sec_per_step: f64,
        images_per_sec: f64,
    ) -> MetricsLine {
        let images = self.state.images;
        MetricsLine {
            step: self.state.step,
            images,
            kimg: images as f64 / 1000.0,
            minutes: self.state.seconds / 60.0,
            stage: match stage {
                Stage::One => 1,
                Stage::Two => 2,
                Stage::Done => 3,
            },
            fade,
            sec_per_step,
            images_per_sec,
            skipped: self.state.skipped,
            peak_rss_mib: peak_rss_mib(),
            losses: self.averages.take(),
        }
    }
}

/// The warning for a skipped step, in metrics.jsonl's count: step `N` is the `N`-th step
/// taken, the one metrics.jsonl logs as `"step": N`, and the counters are those of the state
/// right after it (which a checkpoint and metrics.jsonl's `skipped` also hold).
pub fn skipped_step_message(state: &TrainState, reason: &str) -> String {
    format!(
        "step {} skipped ({} in a row, {} in all): {reason}",
        state.step, state.nonfinite_in_row, state.skipped
    )
}
