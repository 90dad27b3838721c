//! `volux model`: sizes of the networks, the renderer's error against run time, and the
//! generator's speed.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use volux_model::pose::Pose;

use super::environment::env_map;
use clap::{Args, Subcommand, ValueEnum};
use volux_envmap::{PreconvolveOptions, preconvolve};
use volux_model::backend::BackendKind;
use volux_model::generated::GeneratorWants;
use volux_model::generator::GeneratorConfig;
use volux_model::light_lookup::LightMapBatch;
use volux_model::light_lookup::Lighting;
use volux_model::presets::{self, DiscriminatorRole};
use volux_model::sampling_report::{self, DEFAULT_LAYOUTS, ProposalLayout, SamplingSettings};

#[derive(Debug, Subcommand)]
pub enum ModelCommand {
    /// Print the parameter count of each part of a preset.
    Info(InfoArgs),
    /// Error of A, N, D, S against samples per ray, with the wall time of each render.
    SamplingReport(SamplingArgs),
    /// Generator forward + backward speed (rays/s, NeIIF points/s) and peak memory.
    Bench(BenchArgs),
}

/// A named model size.
#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum Preset {
    /// 32x32 volume, 64x64 output, NeIIF width 64: trains on two CPU cores.
    Small,
    /// The paper's model at 128x128 output (CelebA).
    Paper128,
    /// The paper's model at 256x256 output (FFHQ).
    Paper256,
}

impl Preset {
    fn preset(self) -> presets::Preset {
        match self {
            Preset::Small => presets::Preset::Small,
            Preset::Paper128 => presets::Preset::Paper128,
            Preset::Paper256 => presets::Preset::Paper256,
        }
    }

    fn config(self) -> GeneratorConfig {
        self.preset().generator()
    }
}

#[derive(Debug, Args)]
pub struct InfoArgs {
    #[arg(long, value_enum, default_value = "small")]
    pub preset: Preset,
}

#[derive(Debug, Args)]
pub struct SamplingArgs {
    /// HDR environment map to light the scenes with (default: the shipped sunrise map).
    #[arg(long)]
    pub hdri: Option<PathBuf>,
    /// Image side in pixels (one ray per pixel).
    #[arg(long, default_value_t = 32)]
    pub side: usize,
    /// Stratified sample counts to measure (each also with as many importance samples).
    #[arg(long, value_delimiter = ',', default_value = "8,16,32,64")]
    pub counts: Vec<usize>,
    /// Samples per ray of the reference.
    #[arg(long, default_value_t = 1024)]
    pub reference: usize,
    /// Layouts with density-only proposal passes, `S:P:R:I` (stratified, proposal, refine,
    /// importance samples per ray), comma-separated; `none` for no such rows.
    #[arg(long, value_delimiter = ',', default_values_t = DEFAULT_LAYOUTS.map(String::from))]
    pub layouts: Vec<String>,
    /// Backend: cpu or wgpu.
    #[arg(long, default_value = "cpu")]
    pub backend: BackendKind,
}

#[derive(Debug, Args)]
pub struct BenchArgs {
    #[arg(long, value_enum, default_value = "small")]
    pub preset: Preset,
    /// HDR environment map to light the generator with (default: the shipped sunrise map).
    #[arg(long)]
    pub hdri: Option<PathBuf>,
    /// Batch size.
    #[arg(long, default_value_t = 4)]
    pub batch: usize,
    /// Timed iterations (after one warm-up).
    #[arg(long, default_value_t = 3)]
    pub iterations: usize,
    /// Backend: cpu or wgpu.
    #[arg(long, default_value = "cpu")]
    pub backend: BackendKind,
}

pub fn run(cmd: ModelCommand) -> anyhow::Result<()> {
    match cmd {
        ModelCommand::Info(args) => info(args),
        ModelCommand::SamplingReport(args) => sampling(args),
        ModelCommand::Bench(args) => bench(args),
    }
}

fn info(args: InfoArgs) -> anyhow::Result<()> {
    let config = args.preset.config();
    let generator = config.init(&burn::tensor::Device::flex())?;
    println!(
        "{:?}: volume {1}x{1}, output {2}x{2}, {3}+{4} samples per ray",
        args.preset,
        config.volume_resolution,
        config.output_resolution,
        config.renderer.stratified,
        config.renderer.importance,
    );
    let mut total = 0;
    for (name, count) in generator.parameter_counts() {
        println!("  {name:<20} {count:>12}");
        total += count;
    }
    println!("  {:<20} {total:>12}", "generator");
    let device = burn::tensor::Device::flex();
    for role in DiscriminatorRole::ALL {
        let cfg = args.preset.preset().discriminator(role);
        let d = cfg.init(&device);
        println!(
            "  {:<22} {:>10}   ({} channels, {}x{})",
            role.name(),
            d.num_params(),
            cfg.in_channels,
            cfg.resolution,
            cfg.resolution
        );
    }
    Ok(())
}

/// Light maps of the default exponents of an HDRI (the shipped sunrise map without one), the
/// same for each of `batch` elements; with the map's name.
fn lighting(
    path: Option<&std::path::Path>,
    batch: usize,
    device: &burn::tensor::Device,
) -> anyhow::Result<(Lighting, String)> {
    let (name, map) = env_map(path, "sunrise")?;
    let load = || -> anyhow::Result<Lighting> {
        let set = preconvolve(&map, &PreconvolveOptions::default())?;
        let maps = set
            .maps()
            .iter()
            .map(|m| LightMapBatch::new(&vec![m; batch], device))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Lighting::new(maps, None)?)
    };
    let lighting = load().with_context(|| format!("lighting from {name}"))?;
    Ok((lighting, name))
}

fn sampling(args: SamplingArgs) -> anyhow::Result<()> {
    let device = args.backend.device()?;
    for (flag, value, range) in [
        ("--side", args.side, 1..=512),
        ("--reference", args.reference, 2..=8192),
    ] {
        if !range.contains(&value) {
            bail!(
                "{flag} {value} must be in {}..={}",
                range.start(),
                range.end()
            );
        }
    }
    if let Some(c) = args.counts.iter().find(|c| !(1..=1024).contains(*c)) {
        bail!("--counts {c}: each count must be in 1..=1024");
    }
    let (lighting, hdri) = lighting(args.hdri.as_deref(), 1, &device)?;
    let layouts = args
        .layouts
        .iter()
        .filter(|l| l.as_str() != "none")
        .map(|l| l.parse::<ProposalLayout>())
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| anyhow::anyhow!("--layouts: {e}"))?;
    let settings = SamplingSettings {
        side: args.side,
        counts: args.counts,
        reference: args.reference,
        layouts,
        ..SamplingSettings::default()
    };
    let rows = sampling_report::run(&settings, &lighting, &device);
    println!(
        "{}x{} rays, reference {} stratified samples, {}, lit by {}\n",
        args.side, args.side, args.reference, args.backend, hdri
    );
    print!("{}", sampling_report::to_markdown(&rows));
    Ok(())
}

/// Peak resident memory of this process (Linux `VmHWM`), in MiB.
fn peak_memory_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// The largest `volux model bench --batch` (16x the default): a typo such as 100000 would
/// exhaust memory instead of measuring anything.
const MAX_BENCH_BATCH: usize = 64;

fn bench(args: BenchArgs) -> anyhow::Result<()> {
    use burn::tensor::{Distribution, Tensor};
    if !(1..=MAX_BENCH_BATCH).contains(&args.batch) {
        bail!("--batch {}: give 1 to {MAX_BENCH_BATCH}", args.batch);
    }
    let device = args.backend.device()?.autodiff();
    let config = args.preset.config();
    let generator = config.init(&device)?;
    let (lighting, _) = lighting(args.hdri.as_deref(), args.batch, &device)?;
    let poses: Vec<Pose> = (0..args.batch)
        .map(|i| Pose::new(0.3 * (i as f64 - 1.5), 0.1))
        .collect();
    let rays = args.batch * config.volume_resolution.pow(2);
    let points = rays * (config.renderer.stratified + config.renderer.importance);
    let mut times = Vec::new();
    for i in 0..=args.iterations {
        let z = Tensor::<2>::random(
            [args.batch, config.mapping.z_dim],
            Distribution::Normal(0.0, 1.0),
            &device,
        );
        let start = Instant::now();
        let out = generator.forward(
            z,
            &poses,
            Some(&lighting),
            [0.0; 3],
            GeneratorWants::ALL,
            None,
            true,
        )?;
        let loss = out.layers.relit.expect("asked").mean()
            + out.layers.albedo_lo.expect("asked").mean()
            + out.layers.normals_lo.expect("asked").mean();
        let _grads = loss.backward();
        let s = start.elapsed().as_secs_f64();
        if i > 0 {
            times.push(s);
        }
        tracing::info!("iteration {i}: {s:.3} s");
    }
    times.sort_by(f64::total_cmp);
    let best = times.first().copied().unwrap_or(f64::NAN);
    let median = times.get(times.len() / 2).copied().unwrap_or(f64::NAN);
    println!(
        "{:?} on {}: batch {}, {} rays, {} NeIIF points per step (everything, forward + backward)",
        args.preset, args.backend, args.batch, rays, points
    );
    println!(
        "  best {:.3} s, median {:.3} s per step; {:.0} rays/s, {:.0} points/s (best)",
        best,
        median,
        rays as f64 / best,
        points as f64 / best
    );
    if let Some(mib) = peak_memory_mib() {
        println!("  peak resident memory {mib:.0} MiB");
    }
    Ok(())
}
