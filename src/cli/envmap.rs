//! `volux envmap ...`: environment maps and light maps.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use volux_data::hdri_collection::BUILTIN_HDRIS;
use volux_envmap::lobe::LobePlan;
use volux_envmap::preconvolve::{
    DEFAULT_TAPER, DEFAULT_TOLERANCE, Progress, preconvolve_with_progress,
};
use volux_envmap::report::{self, BenchSettings};
use volux_envmap::{EnvMap, MapStats, PreconvolveOptions, io};

#[derive(Debug, Subcommand)]
pub enum EnvmapCommand {
    /// Size, luminance range, brightest direction, negative and non-finite texel counts.
    Info {
        /// An .exr, .hdr, .png or .jpg equirectangular map.
        file: PathBuf,
        /// Also write a tone-mapped PNG preview of the map here.
        #[arg(long)]
        preview: Option<PathBuf>,
    },
    /// Preconvolve a map into cosine-lobe light maps: one EXR per exponent and a PNG contact sheet.
    Preconvolve(PreconvolveArgs),
    /// Error against run time of the fast preconvolution, measured against the f64 reference.
    Bench(BenchArgs),
}

#[derive(Debug, Args)]
pub struct PreconvolveArgs {
    /// Environment map to convolve.
    pub file: PathBuf,
    /// Phong exponents, comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = volux_envmap::DEFAULT_EXPONENTS)]
    pub exponents: Vec<u32>,
    /// Relative RMS error budget per light map (for a point light, the worst case).
    #[arg(long, default_value_t = DEFAULT_TOLERANCE)]
    pub tolerance: f64,
    /// Fraction of each lobe's band tapered against ringing (0 = plain truncation).
    #[arg(long, default_value_t = DEFAULT_TAPER)]
    pub taper: f64,
    /// Rotate the environment by this many degrees about +y first.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub yaw: f64,
    /// Output directory (created if missing).
    #[arg(long, default_value = "light_maps")]
    pub out: PathBuf,
}

#[derive(Debug, Args)]
pub struct BenchArgs {
    /// Maps to measure; the shipped HDRIs (assets/hdri) if none is given.
    pub files: Vec<PathBuf>,
    /// Phong exponents, comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = volux_envmap::DEFAULT_EXPONENTS)]
    pub exponents: Vec<u32>,
    /// Tolerances to sweep, comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = vec![1e-2, 5e-3, 2e-3, 1e-3, 5e-4])]
    pub tolerances: Vec<f64>,
    /// Tapers to sweep, comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = vec![0.0, DEFAULT_TAPER])]
    pub tapers: Vec<f64>,
    /// Random directions per map and lobe (bilinear look-up error).
    #[arg(long, default_value_t = 2048)]
    pub directions: usize,
    /// Random texel centres per light map (convolution error without look-up).
    #[arg(long, default_value_t = 256)]
    pub texels: usize,
    /// Timing runs per setting (the fastest is reported).
    #[arg(long, default_value_t = 5)]
    pub repeats: usize,
    /// Also write the Markdown report to this file.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

pub fn run(cmd: EnvmapCommand) -> anyhow::Result<()> {
    match cmd {
        EnvmapCommand::Info { file, preview } => info(&file, preview.as_deref()),
        EnvmapCommand::Preconvolve(args) => preconvolve(args),
        EnvmapCommand::Bench(args) => bench(args),
    }
}

fn info(file: &Path, preview: Option<&Path>) -> anyhow::Result<()> {
    let raw = io::read_raw(file)?;
    let s = MapStats::of(raw.width, raw.height, &raw.texels);
    let d = s.brightest_direction;
    let (theta, phi) = (
        d[1].clamp(-1.0, 1.0).acos().to_degrees(),
        d[0].atan2(d[2]).to_degrees(),
    );
    println!("file:               {}", file.display());
    println!(
        "size:               {} x {}{}",
        s.width,
        s.height,
        if s.width == 2 * s.height {
            ""
        } else {
            "  (not 2:1: not an equirectangular map)"
        }
    );
    println!(
        "luminance min/max:  {:.4e} / {:.4e}",
        s.min_luminance, s.max_luminance
    );
    println!(
        "luminance mean:     {:.4e}  (solid-angle weighted)",
        s.mean_luminance
    );
    println!(
        "brightest texel:    x={} y={}  direction ({:.3}, {:.3}, {:.3})  polar {:.1} deg, azimuth {:.1} deg",
        s.brightest_texel.0, s.brightest_texel.1, d[0], d[1], d[2], theta, phi
    );
    println!(
        "negative values:    {}{}",
        s.negative,
        if s.negative > 0 {
            format!("  (most negative {:e}; clamped to 0 on load)", s.min_value)
        } else {
            String::new()
        }
    );
    println!(
        "non-finite values:  {}{}",
        s.non_finite,
        if s.non_finite > 0 {
            "  (the map is rejected on load)"
        } else {
            ""
        }
    );
    if let Some(path) = preview {
        io::save_preview_png(path, &io::load(file)?)?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

fn preconvolve(args: PreconvolveArgs) -> anyhow::Result<()> {
    if !args.yaw.is_finite() {
        bail!("--yaw {}: degrees must be a finite number", args.yaw);
    }
    super::output_folder(&args.out)?;
    let mut map = io::load(&args.file)?;
    if args.yaw != 0.0 {
        map = map.rotated_yaw(args.yaw.to_radians());
    }
    let options = PreconvolveOptions {
        exponents: args.exponents.clone(),
        tolerance: args.tolerance,
        taper: args.taper,
        ..PreconvolveOptions::default()
    };
    options.validate()?;
    let bar = progress_bar(
        slow_preconvolution(map.width() * map.height(), &options.plans()),
        options.exponents.len() + 1,
    );
    let start = Instant::now();
    let set = preconvolve_with_progress(&map, &options, |p| match p {
        Progress::Analysis => bar.set_message("spherical-harmonic analysis"),
        Progress::Lobe { exponent, .. } => {
            bar.inc(1);
            bar.set_message(format!("light map n={exponent}"));
        }
    })?;
    bar.finish_and_clear();
    let elapsed = start.elapsed();
    let written = set.save(&args.out)?;
    println!(
        "{} ({}x{}) -> {} light maps in {:.1} ms",
        args.file.display(),
        map.width(),
        map.height(),
        set.maps().len(),
        elapsed.as_secs_f64() * 1e3
    );
    for (lm, plan) in set.maps().iter().zip(options.plans()) {
        println!(
            "  n={:<4} {:>4}x{:<4} band limit {:<4} predicted worst-case error {:.2}%",
            lm.exponent(),
            lm.width(),
            lm.height(),
            plan.band_limit,
            100.0 * plan.truncation_error.hypot(plan.interpolation_error)
        );
    }
    for path in written {
        println!("wrote {}", path.display());
    }
    Ok(())
}

/// Whether a preconvolution takes long enough for a progress bar (seconds or more): a large
/// input map, or a fine tolerance, whose band limits and light maps grow (at `--tolerance
/// 1e-5` the n=64 map is far larger than its input and took minutes with nothing printed).
fn slow_preconvolution(input_texels: usize, plans: &[LobePlan]) -> bool {
    const SLOW_TEXELS: usize = 2048 * 1024;
    const SLOW_BAND_LIMIT: usize = 256;
    input_texels >= SLOW_TEXELS
        || plans
            .iter()
            .any(|p| 2 * p.height * p.height >= SLOW_TEXELS || p.band_limit >= SLOW_BAND_LIMIT)
}

pub(crate) fn progress_bar(show: bool, steps: usize) -> ProgressBar {
    if !show {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(steps as u64);
    bar.set_style(
        ProgressStyle::with_template("{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} {msg}")
            .expect("valid template"),
    );
    bar.enable_steady_tick(std::time::Duration::from_millis(100));
    bar
}

/// The most random directions or texel centres per light map in `volux envmap bench` (each
/// costs an f64 reference integral).
const MAX_POINTS: usize = 1 << 20;
/// The most timing runs per setting.
const MAX_REPEATS: usize = 100;

fn bench(args: BenchArgs) -> anyhow::Result<()> {
    for (flag, value) in [
        ("--directions", args.directions),
        ("--texels", args.texels),
        ("--repeats", args.repeats),
    ] {
        let most = if flag == "--repeats" {
            MAX_REPEATS
        } else {
            MAX_POINTS
        };
        if !(1..=most).contains(&value) {
            bail!("{flag} {value}: give 1 to {most}");
        }
    }
    if let Some(out) = &args.out {
        super::output_file(out)?;
    }
    // Without files: the shipped maps, embedded in the binary.
    let maps: Vec<(String, EnvMap)> = if args.files.is_empty() {
        BUILTIN_HDRIS
            .iter()
            .map(|h| {
                Ok((
                    h.name.to_string(),
                    io::load_bytes(h.bytes, Path::new(h.path))?,
                ))
            })
            .collect::<anyhow::Result<_>>()?
    } else {
        args.files
            .iter()
            .map(|f| {
                let name = f
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_default();
                Ok((name, io::load(f)?))
            })
            .collect::<anyhow::Result<_>>()?
    };
    let settings = BenchSettings {
        exponents: args.exponents,
        tolerances: args.tolerances,
        tapers: args.tapers,
        directions: args.directions,
        texels: args.texels,
        repeats: args.repeats,
    };
    let start = Instant::now();
    let report = report::run(&maps, &settings, |line| tracing::info!("{line}"))?;
    let threads = rayon::current_num_threads();
    let header = format!(
        "Measured by `volux envmap bench` with {threads} threads, {} random directions and {} texel centres per light map, best of {} runs; the whole report took {:.0} s.\n\n",
        settings.directions,
        settings.texels,
        settings.repeats,
        start.elapsed().as_secs_f64()
    );
    let text = header + &report.to_markdown();
    println!("{text}");
    if let Some(out) = args.out {
        std::fs::write(&out, &text).with_context(|| format!("writing {}", out.display()))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fine_tolerances_and_large_maps_get_a_progress_bar() {
        let plans = |tolerance: f64| {
            PreconvolveOptions {
                tolerance,
                ..PreconvolveOptions::default()
            }
            .plans()
        };
        // The default tolerance on a small map is quick; a large map or a fine tolerance is not.
        assert!(!slow_preconvolution(256 * 128, &plans(DEFAULT_TOLERANCE)));
        assert!(slow_preconvolution(4096 * 2048, &plans(DEFAULT_TOLERANCE)));
        assert!(slow_preconvolution(256 * 128, &plans(1e-5)));
    }
}
