//! `volux data`: render a dataset into its example cache; preview the built-in synthetic heads.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use clap::{Args, Subcommand};
use volux_data::contact_sheet::{self, ContactSheet};
use volux_data::dataset::{DataConfig, Dataset};
use volux_data::example_cache::{self, CacheSpec};
use volux_data::examples;
use volux_data::pose_distribution::PoseDistribution;
use volux_data::synthetic_head::{self, RenderSettings, SyntheticHead};
use volux_envmap::random::SplitMix64;
use volux_envmap::{LightMap, PreconvolveOptions, io, preconvolve};
use volux_model::pose::Pose;

#[derive(Debug, Subcommand)]
pub enum DataCommand {
    /// Render a config's dataset into its on-disk example cache ([data.cache]): sharded, with
    /// a manifest; a rerun redoes only what changed and an interrupted build resumes.
    Build(BuildArgs),
    /// Render synthetic heads into a contact sheet of every layer (photo, relit, albedo,
    /// normals, mask, depth, diffuse, specular) and report images per second.
    Heads(HeadsArgs),
    /// Make a folder dataset from photos alone: estimate each photo's albedo, camera-space
    /// normals and mask with the intrinsic estimator (shipped, or trained with --train on the
    /// synthetic heads); --evaluate measures the estimator on held-out identities.
    PseudoGt(super::pseudo_gt::PseudoGtArgs),
}

#[derive(Debug, Args)]
pub struct BuildArgs {
    /// Config file with a [data] table (a training config).
    #[arg(long)]
    pub config: PathBuf,
}

#[derive(Debug, Args)]
pub struct HeadsArgs {
    /// Identity seeds: a range `0-7` or a list `1,5,9`.
    #[arg(long, default_value = "0-7")]
    pub seeds: String,
    /// Image side in pixels.
    #[arg(long, default_value_t = 128)]
    pub side: usize,
    /// Rays per pixel along each axis (2 anti-aliases with 4 rays per pixel).
    #[arg(long, default_value_t = 1)]
    pub supersample: usize,
    /// HDR environment map to light the heads with (default: the shipped sunrise map).
    #[arg(long)]
    pub hdri: Option<PathBuf>,
    /// Rotation of the environment, degrees.
    #[arg(long, default_value_t = 0.0)]
    pub env_yaw: f64,
    /// Seed of the camera poses (drawn from the default pose distribution); omit for frontal.
    #[arg(long)]
    pub pose_seed: Option<u64>,
    /// Output folder for heads.png.
    #[arg(long, default_value = "heads")]
    pub out: PathBuf,
}

pub fn run(cmd: DataCommand) -> anyhow::Result<()> {
    match cmd {
        DataCommand::Build(args) => build(args),
        DataCommand::Heads(args) => heads(args),
        DataCommand::PseudoGt(args) => super::pseudo_gt::run(args),
    }
}

fn build(args: BuildArgs) -> anyhow::Result<()> {
    let (config, hashed) = DataConfig::load(&args.config)?;
    let Some(cache) = config.cache.clone() else {
        bail!(
            "{}: no [data.cache] table: add one with `dir` and `examples` to render examples ahead of training",
            args.config.display()
        );
    };
    let start = Instant::now();
    let bank = config.light_bank()?;
    let stats = bank.stats();
    println!(
        "{} environments ({} light-map cache hits, {} preconvolved) in {:.1} s",
        bank.len(),
        stats.hits,
        stats.misses,
        start.elapsed().as_secs_f64()
    );
    let dataset = Dataset::new(&config, bank.shared())?;
    let fingerprint = examples::fingerprint(&hashed, &bank);
    let spec = CacheSpec {
        examples: cache.examples,
        shard_size: cache.shard_size,
    };
    let shards = cache.examples.div_ceil(cache.shard_size.max(1) as u64) as usize;
    let bar = super::envmap::progress_bar(std::io::stderr().is_terminal(), shards);
    bar.set_message("shards");
    let start = Instant::now();
    let report = example_cache::build(&cache.dir, &dataset, &fingerprint, spec, &|done, _| {
        bar.set_position(done as u64);
        if bar.is_hidden() {
            tracing::info!("{done}/{shards} shards");
        }
    })?;
    bar.finish_and_clear();
    let seconds = start.elapsed().as_secs_f64();
    let made = report.built.min(report.shards) as f64 * cache.shard_size as f64;
    println!(
        "{}: {} examples in {} shards ({} kept, {} built) in {:.1} s{}",
        cache.dir.display(),
        report.examples,
        report.shards,
        report.kept,
        report.built,
        seconds,
        if report.built > 0 {
            format!(
                ", about {:.1} examples/s",
                made.min(report.examples as f64) / seconds
            )
        } else {
            String::new()
        }
    );
    Ok(())
}

/// The most heads `volux data heads` draws in one contact sheet.
const MAX_HEAD_SEEDS: usize = 1024;

/// Parses `0-7` or `1,5,9` into at most `max` seeds (checked before any is collected, so
/// that `0-18446744073709551615` is an error, not an allocation).
pub fn parse_seeds(text: &str, max: usize) -> anyhow::Result<Vec<u64>> {
    let bad = || format!("--seeds {text:?}: expected a range like 0-7 or a list like 1,5,9");
    let too_many = |n: u128| anyhow::anyhow!("--seeds {text:?} names {n} seeds: give 1 to {max}");
    if let Some((a, b)) = text.split_once('-') {
        let (a, b): (u64, u64) = (
            a.trim().parse().with_context(bad)?,
            b.trim().parse().with_context(bad)?,
        );
        if a > b {
            bail!(bad());
        }
        let count = u128::from(b - a) + 1;
        if count > max as u128 {
            return Err(too_many(count));
        }
        return Ok((a..=b).collect());
    }
    let count = text.split(',').count();
    if count > max {
        return Err(too_many(count as u128));
    }
    text.split(',')
        .map(|s| s.trim().parse::<u64>().with_context(bad))
        .collect()
}

fn heads(args: HeadsArgs) -> anyhow::Result<()> {
    let seeds = parse_seeds(&args.seeds, MAX_HEAD_SEEDS)?;
    if !(8..=1024).contains(&args.side) || !(1..=4).contains(&args.supersample) {
        bail!(
            "--side {} must be in 8..=1024 and --supersample {} in 1..=4",
            args.side,
            args.supersample
        );
    }
    if !args.env_yaw.is_finite() {
        bail!(
            "--env-yaw {}: degrees must be a finite number",
            args.env_yaw
        );
    }
    super::output_folder(&args.out)?;
    let (_, map) = super::environment::env_map(args.hdri.as_deref(), "sunrise")?;
    let set = preconvolve(&map, &PreconvolveOptions::default())?;
    let lights: Vec<&LightMap> = set.maps().iter().collect();
    let settings = RenderSettings {
        supersample: args.supersample,
        ..RenderSettings::square(args.side)
    };
    let mut pose_rng = args.pose_seed.map(SplitMix64::new);
    let env_yaw = args.env_yaw.to_radians();
    let background = [1.0, 1.0, 1.0];
    let columns = 8;
    let mut sheet = ContactSheet::new(args.side, args.side, columns, seeds.len());
    let (mut render_s, mut shade_s) = (0.0, 0.0);
    for (row, &seed) in seeds.iter().enumerate() {
        let pose = match pose_rng.as_mut() {
            Some(rng) => PoseDistribution::default().sample(rng),
            None => Pose::FRONTAL,
        };
        let start = Instant::now();
        let head = SyntheticHead::from_seed(seed);
        let render = synthetic_head::render(&head, pose, &settings);
        render_s += start.elapsed().as_secs_f64();
        let start = Instant::now();
        let shading = synthetic_head::shade(&head, &render, &lights, env_yaw, background)?;
        shade_s += start.elapsed().as_secs_f64();
        let image = &render.image;
        let far = settings.camera.far as f32;
        let near = settings.camera.near as f32;
        let tiles = [
            shading.photo.clone(),
            shading.layers.relit.clone(),
            contact_sheet::albedo_colours(&image.albedo),
            contact_sheet::normal_colours(&image.normals, &image.mask),
            contact_sheet::grey(&image.mask, 0.0, 1.0),
            contact_sheet::grey(&render.depth, far, near + 0.1),
            contact_sheet::shading_colours(&shading.layers.diffuse, 1.0),
            contact_sheet::shading_colours(&shading.layers.specular, 1.0),
        ];
        for (column, tile) in tiles.iter().enumerate() {
            sheet.put(column, row, tile);
        }
    }
    let path = args.out.join("heads.png");
    io::save_png(&path, sheet.width(), sheet.height(), &sheet.to_u8())?;
    let n = seeds.len() as f64;
    println!(
        "{} heads at {}x{} ({} rays/pixel, {} threads): intrinsics {:.1} images/s, shading + photo {:.1} images/s, both {:.1} images/s",
        seeds.len(),
        args.side,
        args.side,
        args.supersample * args.supersample,
        rayon::current_num_threads(),
        n / render_s,
        n / shade_s,
        n / (render_s + shade_s)
    );
    println!("columns: photo, relit, albedo, normals, mask, depth, diffuse, specular");
    println!("wrote {}", path.display());
    Ok(())
}
