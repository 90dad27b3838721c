//! Training configs: one TOML file holds `[model]`, `[train]`, `[schedule]`, `[loss]`,
//! `[output]` and `[data]` (read by [`volux_data::dataset::DataConfig::load`]). Unknown keys,
//! wrong types and impossible values are errors naming the file and the key.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use volux_data::config_file::{self, ConfigFileError};
use volux_data::dataset::{DataConfig, DataError};
use volux_model::discriminator::DiscriminatorConfig;
use volux_model::generator::GeneratorConfig;
use volux_model::presets::{DiscriminatorRole, Preset};
use volux_model::volume_rendering::Shading;

use volux_data::pose_distribution::PoseDistribution;

use crate::fake_poses::FakePoses;
use crate::losses::{LeftOut, LossWeights};
use crate::schedule::ScheduleConfig;

/// A config that cannot be used, with the file it came from.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error(transparent)]
    File(#[from] ConfigFileError),
    /// `[data]` cannot be used: the data's own error, with its causes (boxed: it is large).
    #[error("{}", path.display())]
    Data {
        path: PathBuf,
        #[source]
        source: Box<DataError>,
    },
}

/// The largest batch a config may ask for (the paper trains at 24; a batch of 10^12 would
/// otherwise hang allocating before any output).
pub const MAX_BATCH: usize = 1024;

/// The most samples of any one kind per ray a config may ask for.
pub const MAX_SAMPLES_PER_RAY: usize = 1024;

/// The largest learning rate, R1 gamma, loss weight or sphere-prior sharpness a config may
/// give: each multiplies f32 values, and far above this they overflow (1e308 is infinity in
/// f32, and every step was skipped as non-finite with no cause named).
pub const MAX_WEIGHT: f64 = 1e6;

/// The most latents a sample grid may have (`[output] grid_seeds`, one column each, as
/// `volux sample --seeds`): 100 000 aborted after a minute asking for 40 GB.
pub const MAX_GRID_SEEDS: usize = 64;

/// The most batches a config may ask to be prepared ahead (`[train] prefetch`): each is held
/// in memory (a batch of 24 at 256x256 is about 100 MiB), and 10^12 aborted on allocation.
pub const MAX_PREFETCH: usize = 16;

/// The most layers `[model] mapping_layers` may give (StyleGAN2 uses 8, EG3D 2).
pub const MAX_MAPPING_LAYERS: usize = 32;

/// The largest `[model] template_resolution`: EG3D's planes are 256 on a side.
pub const MAX_TEMPLATE_RESOLUTION: usize = 256;

/// The most `[model] template_channels` (EG3D's planes have 32).
pub const MAX_TEMPLATE_CHANNELS: usize = 64;

/// The most `[model] template_basis` sets of planes (each as large as the shared planes).
pub const MAX_TEMPLATE_BASIS: usize = 64;

/// The largest `[model] template_bound`: every ray sample of the default camera lies within
/// about 0.8 of the origin (docs/model.md, "Template planes"), so much wider planes only
/// spread their control points where no ray goes.
pub const MAX_TEMPLATE_BOUND: f64 = 4.0;

/// The largest `[model] d_channel_max`: StyleGAN2's largest configs use 512; a 3x3
/// convolution of 4096 channels already holds 600 MB of weights.
pub const MAX_D_CHANNEL_MAX: usize = 4096;

/// The largest `[model] d_channel_base` (StyleGAN2 uses 16384 or 32768; channels are capped
/// by `d_channel_max` anyway).
pub const MAX_D_CHANNEL_BASE: usize = 1 << 22;

/// `[model]`: a preset size, optionally with fewer or more samples per ray.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ModelConfig {
    /// `small`, `paper128` or `paper256`.
    pub preset: String,
    /// Stratified samples per ray (the preset's if absent).
    #[serde(default)]
    pub stratified: Option<usize>,
    /// Importance samples per ray (the preset's if absent).
    #[serde(default)]
    pub importance: Option<usize>,
    /// Density-only samples per ray that place the importance samples and are not
    /// composited (0 or absent: EG3D's scheme, importance drawn from the stratified samples).
    #[serde(default)]
    pub proposal: Option<usize>,
    /// Density-only samples drawn from the proposal's weights before the importance samples
    /// are (0 or absent: none). Needs `proposal`.
    #[serde(default)]
    pub refine: Option<usize>,
    /// Sharpness of the NeIIF's sphere prior on the density logit (0 or absent: none).
    #[serde(default)]
    pub sphere_prior: Option<f64>,
    /// Radius of the sphere prior (0.5 if absent).
    #[serde(default)]
    pub sphere_radius: Option<f64>,
    /// Octaves of the NeIIF's positional encoding (the preset's 10 if absent). A small volume
    /// cannot show the top octaves of a 10-octave encoding; they turn into banding.
    #[serde(default)]
    pub frequencies: Option<usize>,
    /// Where the renderer shades: `volume` (per sample, the paper's method; the default) or
    /// `surface` (once per pixel at the accumulated normal: the paper's "surface relighting"
    /// ablation).
    #[serde(default)]
    pub shading: Option<ShadingKind>,
    /// Fully connected layers of the mapping network `z -> w` (the preset's 8, StyleGAN2's, if
    /// absent; EG3D uses 2).
    #[serde(default)]
    pub mapping_layers: Option<usize>,
    /// The NeIIF's positional encoding: `axis-aligned` (the paper's; the default) or
    /// `rotated` (each octave turns the point by its own fixed rotation first, so that no
    /// octave's bands line up with the axes).
    #[serde(default)]
    pub encoding: Option<EncodingKind>,
    /// Side of the volume-rendered images (the preset's if absent: 32 for `small`, 64 for the
    /// paper's); the output resolution must be it times a power of two (1 included: no
    /// upsampling blocks), and `[data] volume_resolution` must equal it.
    #[serde(default)]
    pub volume_resolution: Option<usize>,
    /// Every discriminator's `channel_base`: feature channels at resolution `r` are
    /// `min(d_channel_base / r, d_channel_max)` (StyleGAN2's `cbase`; the preset's if absent:
    /// 2048 for `small`, 32768 for the paper's).
    #[serde(default)]
    pub d_channel_base: Option<usize>,
    /// Every discriminator's `channel_max` (StyleGAN2's `cmax`; the preset's if absent: 128 for
    /// `small`, 512 for the paper's).
    #[serde(default)]
    pub d_channel_max: Option<usize>,
    /// Control points per side of a latent-independent tri-plane of features beside the
    /// NeIIF's positional encoding (absent or 0: none, the paper's field).
    #[serde(default)]
    pub template_resolution: Option<usize>,
    /// Features of that tri-plane (8 if absent).
    #[serde(default)]
    pub template_channels: Option<usize>,
    /// Half the side of the square each of its planes covers, world units (1 if absent):
    /// the control points span `[-template_bound, template_bound]`.
    #[serde(default)]
    pub template_bound: Option<f64>,
    /// Sets of planes each latent weights and adds to that tri-plane, so that each latent
    /// has planes of its own (absent or 0: one tri-plane for every latent). Needs
    /// `template_resolution`.
    #[serde(default)]
    pub template_basis: Option<usize>,
    /// Side of both convolutions of every upsampler block: 1 (the paper's 1x1; the default)
    /// or 3 (each pixel also reads its neighbours: detail finer than the volume's rays).
    #[serde(default)]
    pub upsampler_kernel: Option<usize>,
    /// Octaves of surface-anchored noise each upsampler block adds (0, the paper's, to 4; the
    /// default 0): texture finer than the volume's rays that stays on the head as it turns.
    #[serde(default)]
    pub upsampler_noise: Option<usize>,
}

/// The `[model] encoding` key.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum EncodingKind {
    AxisAligned,
    Rotated,
}

/// The `[model] shading` key.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ShadingKind {
    Volume,
    Surface,
}

impl From<ShadingKind> for Shading {
    fn from(kind: ShadingKind) -> Shading {
        match kind {
            ShadingKind::Volume => Shading::Volume,
            ShadingKind::Surface => Shading::Surface,
        }
    }
}

impl ModelConfig {
    /// The preset this config names.
    pub fn preset(&self) -> Result<Preset, String> {
        match self.preset.as_str() {
            "small" => Ok(Preset::Small),
            "paper128" => Ok(Preset::Paper128),
            "paper256" => Ok(Preset::Paper256),
            other => Err(format!(
                "model.preset = \"{other}\": expected \"small\", \"paper128\" or \"paper256\""
            )),
        }
    }

    /// The generator's sizes.
    pub fn generator(&self) -> Result<GeneratorConfig, String> {
        let mut g = self.preset()?.generator();
        if let Some(n) = self.stratified {
            g.renderer.stratified = n;
        }
        if let Some(n) = self.importance {
            g.renderer.importance = n;
        }
        if let Some(n) = self.proposal {
            g.renderer.proposal = n;
        }
        if let Some(n) = self.refine {
            g.renderer.refine = n;
        }
        let r = &g.renderer;
        for (key, n) in [
            ("stratified", r.stratified),
            ("importance", r.importance),
            ("proposal", r.proposal),
            ("refine", r.refine),
        ] {
            if n > MAX_SAMPLES_PER_RAY {
                return Err(format!(
                    "model.{key} = {n} exceeds {MAX_SAMPLES_PER_RAY} samples per ray"
                ));
            }
        }
        if let Some(s) = self.sphere_prior {
            if !(0.0..=MAX_WEIGHT).contains(&s) {
                return Err(format!(
                    "model.sphere_prior = {s:?} must be in [0, {MAX_WEIGHT:e}]"
                ));
            }
            g.neiif.sphere_prior = s;
        }
        if let Some(r) = self.sphere_radius {
            if !(r.is_finite() && r > 0.0 && r < 1.0) {
                return Err(format!("model.sphere_radius = {r:?} must be in (0, 1)"));
            }
            g.neiif.sphere_radius = r;
        }
        if let Some(f) = self.frequencies {
            if !(1..=16).contains(&f) {
                return Err(format!("model.frequencies = {f} must be in 1..=16"));
            }
            g.neiif.frequencies = f;
        }
        if let Some(kind) = self.shading {
            g.renderer.shading = kind.into();
        }
        if let Some(v) = self.volume_resolution {
            if !(4..=g.output_resolution).contains(&v) {
                return Err(format!(
                    "model.volume_resolution = {v} must be in 4..={} (the output's)",
                    g.output_resolution
                ));
            }
            g.volume_resolution = v;
        }
        if let Some(kind) = self.encoding {
            g.neiif.rotated_encoding = kind == EncodingKind::Rotated;
        }
        if let Some(n) = self.template_resolution {
            if n == 1 || n > MAX_TEMPLATE_RESOLUTION {
                return Err(format!(
                    "model.template_resolution = {n} must be 0 (none) or in 2..={MAX_TEMPLATE_RESOLUTION}"
                ));
            }
            g.neiif.template_resolution = n;
        }
        if let Some(n) = self.template_channels {
            if !(1..=MAX_TEMPLATE_CHANNELS).contains(&n) {
                return Err(format!(
                    "model.template_channels = {n} must be in 1..={MAX_TEMPLATE_CHANNELS}"
                ));
            }
            g.neiif.template_channels = n;
        }
        if let Some(b) = self.template_bound {
            if !(b.is_finite() && b > 0.0 && b <= MAX_TEMPLATE_BOUND) {
                return Err(format!(
                    "model.template_bound = {b:?} must be in (0, {MAX_TEMPLATE_BOUND}]"
                ));
            }
            g.neiif.template_bound = b;
        }
        if let Some(k) = self.template_basis {
            if k > MAX_TEMPLATE_BASIS {
                return Err(format!(
                    "model.template_basis = {k} must be in 0..={MAX_TEMPLATE_BASIS}"
                ));
            }
            if k > 0 && g.neiif.template_resolution == 0 {
                return Err(format!(
                    "model.template_basis = {k} needs template planes: give model.template_resolution"
                ));
            }
            g.neiif.template_basis = k;
        }
        if let Some(k) = self.upsampler_kernel {
            if !volux_model::upsampler::KERNELS.contains(&k) {
                return Err(format!("model.upsampler_kernel = {k} must be 1 or 3"));
            }
            g.upsampler_kernel = k;
        }
        if let Some(k) = self.upsampler_noise {
            let max = volux_model::upsampler_noise::MAX_OCTAVES;
            if k > max {
                return Err(format!(
                    "model.upsampler_noise = {k} must be at most {max} octaves"
                ));
            }
            g.upsampler_noise = k;
        }
        if let Some(n) = self.mapping_layers {
            if !(1..=MAX_MAPPING_LAYERS).contains(&n) {
                return Err(format!(
                    "model.mapping_layers = {n} must be in 1..={MAX_MAPPING_LAYERS}"
                ));
            }
            g.mapping.layers = n;
        }
        // Compositing needs two samples per ray: stratified ones, or importance ones placed
        // by a proposal.
        let composited = if g.renderer.proposal > 0 {
            ("importance", g.renderer.importance)
        } else {
            ("stratified", g.renderer.stratified)
        };
        if composited.1 < 2 {
            return Err(format!(
                "model.{} = {} must be at least 2",
                composited.0, composited.1
            ));
        }
        g.validate()
            .map_err(|e| format!("[model]: {}", volux_envmap::error::chain(&e)))?;
        Ok(g)
    }

    /// The sizes of one discriminator.
    pub fn discriminator(&self, role: DiscriminatorRole) -> Result<DiscriminatorConfig, String> {
        let mut d = self.preset()?.discriminator_for(role, &self.generator()?);
        if let Some(n) = self.d_channel_base {
            if !(1..=MAX_D_CHANNEL_BASE).contains(&n) {
                return Err(format!(
                    "model.d_channel_base = {n} must be in 1..={MAX_D_CHANNEL_BASE}"
                ));
            }
            d.channel_base = n;
        }
        if let Some(n) = self.d_channel_max {
            if !(1..=MAX_D_CHANNEL_MAX).contains(&n) {
                return Err(format!(
                    "model.d_channel_max = {n} must be in 1..={MAX_D_CHANNEL_MAX}"
                ));
            }
            d.channel_max = n;
        }
        Ok(d)
    }
}

/// `[train]`: batch, optimisers, R1, EMA, the non-finite guard.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct OptimConfig {
    /// Seed of latents, ray jitter and initial weights.
    pub seed: u64,
    /// Images per step.
    pub batch: usize,
    /// Adam learning rate of the generator.
    pub lr_g: f64,
    /// Adam learning rate of every discriminator.
    pub lr_d: f64,
    pub beta1: f64,
    pub beta2: f64,
    /// R1 weight `gamma` (StyleGAN2's `r1_gamma`).
    pub r1_gamma: f64,
    /// R1 runs every `r1_interval` discriminator steps (lazy regularisation); 0 turns it off.
    pub r1_interval: usize,
    /// Half-life of the generator's moving average, in thousands of images.
    pub ema_kimg: f64,
    /// The half-life is at most `ema_rampup` times the images seen so far (0: no ramp-up).
    pub ema_rampup: f64,
    /// Stop after this many non-finite steps in a row (each is skipped).
    pub max_nonfinite: usize,
    /// Batches prepared ahead of the step on a background thread.
    pub prefetch: usize,
    /// Where the fakes' cameras come from: `auto` (the reals' poses if the dataset has
    /// poses, else the prior), `dataset`, `prior` or `swap` (the reals' poses, shifted by one).
    pub fake_poses: FakePoses,
    /// The camera prior of the fakes (`[train.pose_prior]`; pi-GAN's CelebA values).
    pub pose_prior: PoseDistribution,
}

impl Default for OptimConfig {
    fn default() -> Self {
        OptimConfig {
            seed: 0,
            batch: 24,
            lr_g: 0.0022,
            lr_d: 0.0025,
            beta1: 0.0,
            beta2: 0.99,
            r1_gamma: 1.0,
            r1_interval: 16,
            ema_kimg: 10.0,
            ema_rampup: 0.05,
            max_nonfinite: 10,
            prefetch: 2,
            fake_poses: FakePoses::Auto,
            pose_prior: PoseDistribution::default(),
        }
    }
}

/// `[output]`: how often to log, draw the sample grid and checkpoint.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct OutputConfig {
    /// Steps per metrics line (losses are averaged over them).
    pub log_every: u64,
    /// Thousands of images between sample grids (0: only at the end).
    pub grid_kimg: f64,
    /// Latent seeds of the grid's columns.
    pub grid_seeds: Vec<u64>,
    /// Thousands of images between checkpoints (0: only at the end).
    pub checkpoint_kimg: f64,
    /// Checkpoints kept (the oldest are deleted).
    pub keep: usize,
    /// Stop after this many minutes of training (0: run the whole schedule), checkpointing first.
    pub minutes: f64,
    /// Thousands of images between light evaluations of the EMA generator written to
    /// metrics.jsonl (0: none). Each one also runs at the start and the end of the run.
    pub eval_kimg: f64,
    /// Latents (and dataset images) of each light evaluation's sliced Wasserstein distance.
    pub eval_samples: usize,
}

impl Default for OutputConfig {
    fn default() -> Self {
        OutputConfig {
            log_every: 10,
            grid_kimg: 5.0,
            grid_seeds: (0..8).collect(),
            checkpoint_kimg: 10.0,
            keep: 3,
            minutes: 0.0,
            eval_kimg: 0.0,
            eval_samples: 32,
        }
    }
}

/// Everything a training config holds except `[data]`.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
struct ConfigFile {
    model: ModelConfig,
    #[serde(default)]
    train: OptimConfig,
    #[serde(default)]
    schedule: ScheduleConfig,
    #[serde(default)]
    loss: LossWeights,
    #[serde(default)]
    output: OutputConfig,
    /// Read separately by `DataConfig::load`.
    data: toml::Value,
}

/// A checked training config.
#[derive(Clone, Debug)]
pub struct TrainConfig {
    pub model: ModelConfig,
    pub train: OptimConfig,
    pub schedule: ScheduleConfig,
    pub loss: LossWeights,
    pub output: OutputConfig,
    pub data: DataConfig,
    /// The `[data]` table as hashed for example caches.
    pub data_hashed: String,
    /// The file as written (stored in checkpoints).
    pub text: String,
    /// Where it was read from.
    pub path: PathBuf,
    /// Adversarial terms of `[loss]` whose reals the dataset does not provide: their weights
    /// in `loss` are 0 ([`LossWeights::restricted_to`]).
    pub left_out: Vec<LeftOut>,
}

impl TrainConfig {
    /// Reads and checks `path`.
    pub fn load(path: &Path) -> Result<TrainConfig, ConfigError> {
        let text = config_file::read(path)?;
        Self::from_text(text, path)
    }

    /// Checks the text of a config file that lives (or lived) at `path`; relative paths in
    /// `[data]` are taken relative to its folder.
    pub fn from_text(text: String, path: &Path) -> Result<TrainConfig, ConfigError> {
        let (data, data_hashed) = DataConfig::from_text(&text, path).map_err(|e| match e {
            DataError::File(e) => ConfigError::File(e),
            other => ConfigError::Data {
                path: path.to_path_buf(),
                source: Box::new(other),
            },
        })?;
        let file: ConfigFile = config_file::parse(&text, path)?;
        let provided = data.provided().map_err(|e| ConfigError::Data {
            path: path.to_path_buf(),
            source: Box::new(e),
        })?;
        let (loss, left_out) = file.loss.restricted_to(&provided);
        let config = TrainConfig {
            model: file.model,
            train: file.train,
            schedule: file.schedule,
            loss,
            output: file.output,
            data,
            data_hashed,
            text,
            path: path.to_path_buf(),
            left_out,
        };
        config
            .validate()
            .map_err(|message| ConfigFileError::Invalid {
                path: path.to_path_buf(),
                message,
            })?;
        Ok(config)
    }

    /// The generator's sizes (checked by `load`).
    pub fn generator(&self) -> GeneratorConfig {
        self.model.generator().expect("validated")
    }

    /// The positional encoding's window after `images` images (`[schedule] open_octaves`;
    /// `None`: every octave open).
    pub fn octave_window(&self, images: u64) -> Option<f64> {
        self.schedule
            .octave_window(images, self.generator().neiif.frequencies)
    }

    /// Upsampling blocks of the generator.
    pub fn blocks(&self) -> usize {
        let g = self.generator();
        (g.output_resolution / g.volume_resolution).trailing_zeros() as usize
    }

    /// Every check that needs more than one key.
    fn validate(&self) -> Result<(), String> {
        let g = self.model.generator()?;
        let t = &self.train;
        if !(1..=MAX_BATCH).contains(&t.batch) {
            return Err(format!(
                "train.batch = {} must be in 1..={MAX_BATCH}",
                t.batch
            ));
        }
        for role in DiscriminatorRole::ALL {
            let group = self.model.discriminator(role)?.mbstd_group;
            if !t.batch.is_multiple_of(group.min(t.batch)) {
                return Err(format!(
                    "train.batch = {} is not divisible by the discriminators' minibatch-std group of {group}",
                    t.batch
                ));
            }
        }
        for (key, v) in [("lr_g", t.lr_g), ("lr_d", t.lr_d), ("r1_gamma", t.r1_gamma)] {
            if !(0.0..=MAX_WEIGHT).contains(&v) {
                return Err(format!(
                    "train.{key} = {v:?} must be in [0, {MAX_WEIGHT:e}]"
                ));
            }
        }
        for (key, v) in [("ema_kimg", t.ema_kimg), ("ema_rampup", t.ema_rampup)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("train.{key} = {v:?} must be finite and >= 0"));
            }
        }
        if t.prefetch > MAX_PREFETCH {
            return Err(format!(
                "train.prefetch = {} must be in 0..={MAX_PREFETCH}",
                t.prefetch
            ));
        }
        for (key, v) in [("beta1", t.beta1), ("beta2", t.beta2)] {
            if !(0.0..1.0).contains(&v) {
                return Err(format!("train.{key} = {v:?} must be in [0, 1)"));
            }
        }
        t.pose_prior
            .validate()
            .map_err(|e| format!("train.pose_prior.{e}"))?;
        if t.max_nonfinite == 0 {
            return Err("train.max_nonfinite must be at least 1".into());
        }
        self.loss.validate()?;
        self.schedule.validate(self.blocks(), g.neiif.frequencies)?;
        let stage_one = self.loss.albedo > 0.0 || self.loss.geometry > 0.0;
        if self.schedule.stage1_kimg > 0.0 && !stage_one && !self.left_out.is_empty() {
            let terms: Vec<String> = self.left_out.iter().map(ToString::to_string).collect();
            return Err(format!(
                "schedule.stage1_kimg = {}: stage 1 trains albedo and geometry, and the dataset provides neither ({} left out); set stage1_kimg = 0 and fade_kimg = 0 to train on what it has from the start",
                self.schedule.stage1_kimg,
                terms.join(", ")
            ));
        }
        let o = &self.output;
        for (key, v) in [
            ("grid_kimg", o.grid_kimg),
            ("checkpoint_kimg", o.checkpoint_kimg),
            ("minutes", o.minutes),
            ("eval_kimg", o.eval_kimg),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("output.{key} = {v:?} must be finite and >= 0"));
            }
        }
        if !(2..=4096).contains(&o.eval_samples) {
            return Err(format!(
                "output.eval_samples = {} must be within 2..=4096",
                o.eval_samples
            ));
        }
        if o.keep == 0 {
            return Err("output.keep must be at least 1".into());
        }
        if o.log_every == 0 {
            return Err("output.log_every must be at least 1".into());
        }
        if !(1..=MAX_GRID_SEEDS).contains(&o.grid_seeds.len()) {
            return Err(format!(
                "output.grid_seeds names {} seeds: give 1 to {MAX_GRID_SEEDS}",
                o.grid_seeds.len()
            ));
        }
        let d = &self.data;
        if d.resolution != g.output_resolution || d.volume_resolution != g.volume_resolution {
            return Err(format!(
                "data.resolution = {} and data.volume_resolution = {} must equal the {} model's {} and {}",
                d.resolution,
                d.volume_resolution,
                self.model.preset,
                g.output_resolution,
                g.volume_resolution
            ));
        }
        Ok(())
    }

    /// The table that fixes every tensor's shape (compared when resuming).
    /// The whole config with every default filled in, as TOML (StyleGAN2 saves the same with
    /// each snapshot): what the run actually used, whatever the file left out. Loading it
    /// again gives the same config ([`TrainConfig::from_text`]; tested).
    pub fn resolved(&self) -> String {
        #[derive(Serialize)]
        struct Resolved<'a> {
            model: &'a ModelConfig,
            train: &'a OptimConfig,
            schedule: &'a ScheduleConfig,
            loss: &'a LossWeights,
            output: &'a OutputConfig,
            data: &'a DataConfig,
        }
        toml::to_string(&Resolved {
            model: &self.model,
            train: &self.train,
            schedule: &self.schedule,
            loss: &self.loss,
            output: &self.output,
            data: &self.data,
        })
        .unwrap_or_else(|e| format!("# the resolved config could not be written: {e}\n"))
    }

    pub fn shapes(&self) -> String {
        // `shading = "volume"`, `encoding = "axis-aligned"`, `upsampler_kernel = 1` and
        // `upsampler_noise = 0` are the defaults written out: the same model as no key.
        let mut model = self.model.clone();
        if model.upsampler_kernel == Some(1) {
            model.upsampler_kernel = None;
        }
        if model.upsampler_noise == Some(0) {
            model.upsampler_noise = None;
        }
        if model.shading == Some(ShadingKind::Volume) {
            model.shading = None;
        }
        if model.encoding == Some(EncodingKind::AxisAligned) {
            model.encoding = None;
        }
        toml::to_string(&model).unwrap_or_default()
    }
}

#[cfg(test)]
mod tests;
