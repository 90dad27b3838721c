//! Training VoLux-GAN (paper section 3.4) and sampling what it learned.
//!
//! - [`config`]: the TOML training config (`[model]`, `[train]`, `[schedule]`, `[loss]`,
//!   `[output]`, `[data]`), checked with errors naming the file and key.
//! - [`losses`]: non-saturating logistic losses, lazy R1, the path loss, the shading
//!   discriminator's condition, loss weights.
//! - [`schedule`]: stage 1 with progressive growing, stage 2 end to end, which terms run.
//! - [`progressive`]: the high-resolution albedo discriminator growing with the upsampler.
//! - [`networks`]: the discriminators a config needs, the generator's moving average.
//! - [`fake_poses`]: the cameras of the fakes (the dataset's poses, a prior, or swapped).
//! - [`step`]: one generator phase and one discriminator phase, skipping non-finite steps.
//! - [`training_loop`]: the [`training_loop::Trainer`] (data, schedule, EMA, metrics, grids,
//!   checkpoints, resume).
//! - [`checkpoint`]: atomic checkpoint folders, keep-last-K, resume.
//! - [`run_folder`]: what in a run folder belongs to a run; refusing to mix two runs.
//! - [`metrics`]: the JSON-lines metrics log.
//! - [`bench`]: real training steps timed phase by phase, with FLOPs and the matmul peak.
//! - [`mesh`]: shape export: marching cubes on one latent's density, albedo colours and exact
//!   normals at the vertices, PLY and OBJ files.
//! - [`pretrained`]: trained generators for sampling: checkpoints on disk and the models
//!   shipped in the binary, by name.
//! - [`sampling`]: latents from seeds, every layer of a sample, the sample grid;
//!   [`animation`]: looping GIFs; [`video`]: MP4 (H.264) videos.

pub mod adam;
pub mod animation;
pub mod bench;
pub mod checkpoint;
pub mod config;
pub mod fake_poses;
pub mod losses;
pub mod mesh;
pub mod metrics;
pub mod networks;
pub mod pretrained;
pub mod progressive;
pub mod run_folder;
pub mod sampling;
pub mod schedule;
pub mod step;
pub mod training_loop;
pub mod video;
