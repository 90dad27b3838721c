//! Command definitions (clap derive) and dispatch.

mod backend;
mod data;
mod environment;
mod envmap;
mod eval;
mod export;
mod model;
mod plot;
mod pseudo_gt;
mod report;
mod sample;
mod train;

use std::path::Path;

use anyhow::{Context, bail};
use clap::{Parser, Subcommand};

/// Makes the output folder `--out` (and its parents), refusing a path that is a file with an
/// error that says so (creating it would only say "File exists"). Commands call it before
/// their work, so a bad `--out` costs nothing.
pub fn output_folder(out: &Path) -> anyhow::Result<()> {
    if out.exists() && !out.is_dir() {
        bail!("--out {} is a file: give a folder", out.display());
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))
}

/// Checks an output file `--out` before the work: refuses a folder, and makes the folder it
/// goes in (with its parents), so a table or page is not lost at the end for want of a folder.
pub fn output_file(out: &Path) -> anyhow::Result<()> {
    if out.is_dir() {
        bail!("--out {} is a folder: give a file", out.display());
    }
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        if dir.exists() && !dir.is_dir() {
            bail!(
                "--out {}: {} is a file, not a folder",
                out.display(),
                dir.display()
            );
        }
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    Ok(())
}

/// Relightable 3D-aware face generation (VoLux-GAN) on Burn.
#[derive(Debug, Parser)]
#[command(name = "volux", version, about, propagate_version = true)]
pub struct Cli {
    /// Log debug details (or set RUST_LOG).
    #[arg(short, long, global = true)]
    pub verbose: bool,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// HDR environment maps: inspect, preconvolve into light maps, measure accuracy.
    #[command(subcommand)]
    Envmap(envmap::EnvmapCommand),
    /// The networks: parameter counts, the renderer's error against samples per ray, speed.
    #[command(subcommand)]
    Model(model::ModelCommand),
    /// Training data: build a dataset's example cache, preview the synthetic heads.
    #[command(subcommand)]
    Data(data::DataCommand),
    /// Train a model from a TOML config: the staged adversarial schedule, checkpoints, sample
    /// grids, metrics; `--resume` continues the newest checkpoint. `volux train bench` times
    /// real training steps phase by phase.
    Train(train::TrainCommand),
    /// Render a checkpoint: layer grids, several cameras, EXR layers, rotating-light and
    /// rotating-camera animations and latent interpolations as GIF and MP4 (H.264).
    Sample(sample::SampleArgs),
    /// Measure a checkpoint: multi-view and relighting consistency, geometry, sliced
    /// Wasserstein distance to the data, the same on the synthetic data; table, JSON, figures.
    Eval(eval::EvalArgs),
    /// Export what a checkpoint makes for other tools: `volux export mesh` writes a head as a
    /// PLY or OBJ mesh.
    #[command(subcommand)]
    Export(export::ExportCommand),
    /// Plot a run's losses and light-evaluation scores (`[output] eval_kimg`) against images
    /// and wall-clock minutes, as PNG; or several runs' scores against each other.
    Plot(plot::PlotArgs),
    /// One self-contained HTML page of a run (state, curves, the latest evaluation, grids over
    /// time, samples, config) that opens offline in a browser.
    Report(report::ReportArgs),
    /// Check that a compute backend works: a small forward and backward pass compared with the CPU.
    Backend(backend::BackendArgs),
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Envmap(cmd) => envmap::run(cmd),
        Command::Model(cmd) => model::run(cmd),
        Command::Data(cmd) => data::run(cmd),
        Command::Train(args) => train::run(args),
        Command::Sample(args) => sample::run(args),
        Command::Eval(args) => eval::run(args),
        Command::Export(cmd) => export::run(cmd),
        Command::Plot(args) => plot::run(args),
        Command::Report(args) => report::run(args),
        Command::Backend(args) => backend::run(args),
    }
}
