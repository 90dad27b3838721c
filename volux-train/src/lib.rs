//! Training VoLux-GAN (paper section 3.4) and sampling what it learned.
//!
//! - [`config`]: the TOML training config (`[model]`, `[train]`, `[schedule]`, `[loss]`,
//!   `[output]`, `[data]`), checked with errors naming the file and key.
//! - [`losses`]: non-saturating logistic losses, lazy R1, the path loss, the shading
//!   discriminator's condition, loss weights.
//! - [`schedule`]: stage 1 with progressive growing, stage 2 end to end, which terms run.
//! - [`networks`]: the discriminators a config needs, the generator's moving average.
//! - [`step`]: one generator phase and one discriminator phase, skipping non-finite steps.
//! - [`training_loop`]: the [`training_loop::Trainer`] (data, schedule, EMA, metrics, grids,
//!   checkpoints, resume).
//! - [`checkpoint`]: atomic checkpoint folders, keep-last-K, resume.
//! - [`metrics`]: the JSON-lines metrics log.
//! - [`bench`]: real training steps timed phase by phase, with FLOPs and the matmul peak.
//! - [`sampling`]: latents from seeds, every layer of a sample, the sample grid;
//!   [`animation`]: looping GIFs.

pub mod animation;
pub mod bench;
pub mod checkpoint;
pub mod config;
pub mod losses;
pub mod metrics;
pub mod networks;
pub mod sampling;
pub mod schedule;
pub mod step;
pub mod training_loop;
