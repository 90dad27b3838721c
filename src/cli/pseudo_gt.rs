//! `volux data pseudo-gt`: a folder of photos into a folder dataset with estimated albedo,
//! normals and masks; `--train` trains the estimator on the synthetic heads; `--evaluate`
//! measures one on held-out identities.

use std::fmt::Write as _;
use std::io::IsTerminal;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use burn::tensor::Device;
use clap::Args;
use volux_envmap::LightMapSet;
use volux_pseudo_gt::augmentation::AugmentationRanges;
use volux_pseudo_gt::estimator::Estimator;
use volux_pseudo_gt::training::{self, TrainOptions};
use volux_pseudo_gt::weights::{self, EstimatorFile};
use volux_pseudo_gt::{photo_folder, sheets, synthetic_pairs};

#[derive(Debug, Args)]
pub struct PseudoGtArgs {
    /// Folder of photos (.png, .jpg, .jpeg) to make a dataset of.
    #[arg(long, required_unless_present_any = ["train", "evaluate"])]
    pub photos: Option<PathBuf>,
    /// Where to write: the dataset (with --photos), the estimator folder (with --train) or
    /// the accuracy table (with --evaluate; a contact sheet of estimates and truth is written
    /// beside it, as .png).
    #[arg(long)]
    pub out: PathBuf,
    /// Side of the dataset's images in pixels (photos are centre-cropped to a square and
    /// resized to it).
    #[arg(long, default_value_t = 64)]
    pub resolution: usize,
    /// Estimator folder (estimator.toml, estimator.bpk); default: the one shipped in the binary.
    #[arg(long)]
    pub estimator: Option<PathBuf>,
    /// Train an estimator on the synthetic heads into --out instead.
    #[arg(long, conflicts_with_all = ["photos", "evaluate"])]
    pub train: bool,
    /// Measure the estimator on held-out synthetic identities at --sides instead.
    #[arg(long, conflicts_with = "photos")]
    pub evaluate: bool,
    /// With --evaluate: image sides to measure at.
    #[arg(long, default_value = "64,128,256", value_delimiter = ',')]
    pub sides: Vec<usize>,
    /// With --train: minutes of training steps.
    #[arg(long, default_value_t = 45.0)]
    pub minutes: f64,
    /// With --train: stop after this many steps.
    #[arg(long)]
    pub steps: Option<u64>,
    /// With --train or --evaluate: seed of the pairs, batches, augmentations and (--train) the
    /// initial weights.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// With --train: training pairs rendered (identities 0..pool).
    #[arg(long, default_value_t = 3000)]
    pub pool: usize,
    /// With --train: photos per step.
    #[arg(long, default_value_t = 8)]
    pub batch: usize,
    /// With --train or --evaluate: held-out identities measured.
    #[arg(long, default_value_t = 64)]
    pub held_out: usize,
    /// With --train: steps between evaluations (and saves).
    #[arg(long, default_value_t = 500)]
    pub eval_every: u64,
}

pub fn run(args: PseudoGtArgs) -> anyhow::Result<()> {
    if args.train {
        return train(args);
    }
    let device = Device::flex();
    let (estimator, file, origin) = match &args.estimator {
        Some(dir) => {
            let (e, f) = weights::load(dir, &device)?;
            (e, f, dir.display().to_string())
        }
        None => {
            let (e, f) = weights::shipped(&device)?;
            (e, f, format!("shipped ({})", weights::SHIPPED_FOLDER))
        }
    };
    if args.evaluate {
        return evaluate(&args, &estimator, &file, &origin);
    }
    let photos = args.photos.as_deref().context("--photos is required")?;
    let lights = collection_lights()?;
    // Its length comes with the first report: make_dataset lists the photos once.
    let bar = super::envmap::progress_bar(std::io::stderr().is_terminal(), 0);
    bar.set_message("photos");
    let start = Instant::now();
    let made = photo_folder::make_dataset(
        photos,
        &args.out,
        args.resolution,
        (&estimator, &file, &origin),
        &lights,
        &|done, total| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
            if bar.is_hidden() {
                tracing::info!("{done}/{total} photos");
            }
        },
    )?;
    bar.finish_and_clear();
    println!(
        "{}: {} photos at {}x{} ({} made, {} kept from an earlier run) in {:.1} s with the estimator {origin}",
        args.out.display(),
        made.photos,
        args.resolution,
        args.resolution,
        made.made,
        made.kept,
        start.elapsed().as_secs_f64()
    );
    if !made.blank.is_empty() {
        println!(
            "warning: {} of {} photos are blank (no contrast: no face to estimate) and were left out: {}",
            made.blank.len(),
            made.photos,
            made.blank.join(", ")
        );
    }
    if !made.misframed.is_empty() {
        let names: Vec<String> = made
            .misframed
            .iter()
            .take(10)
            .map(|(stem, f)| {
                format!(
                    "{stem} (covers {:.0}%, centre at {:.2}, {:.2})",
                    100.0 * f.coverage,
                    f.centre.0,
                    f.centre.1
                )
            })
            .collect();
        println!(
            "warning: {} of {} photos frame the face unlike the model's camera (synthetic heads cover {:.0}-{:.0}% of the frame, centred within {:.2}): {}{}; see framing.csv",
            made.misframed.len(),
            made.photos,
            100.0 * made.range.coverage.0,
            100.0 * made.range.coverage.1,
            made.range.off_centre,
            names.join(", "),
            if made.misframed.len() > 10 {
                ", ..."
            } else {
                ""
            }
        );
    }
    println!(
        "wrote the dataset, contact_sheet.png and framing.csv; train on it with [data.source] kind = \"folder\", path = \"{}\"",
        args.out.display()
    );
    Ok(())
}

/// Accuracy on held-out identities at each side, with the default augmentations and clean.
fn evaluate(
    args: &PseudoGtArgs,
    estimator: &Estimator,
    file: &EstimatorFile,
    origin: &str,
) -> anyhow::Result<()> {
    if args.sides.is_empty() || args.sides.iter().any(|s| !(8..=1024).contains(s)) {
        bail!("--sides {:?}: each side must be 8 to 1024", args.sides);
    }
    if !(1..=10_000).contains(&args.held_out) {
        bail!("--held-out {} must be 1 to 10000", args.held_out);
    }
    super::output_file(&args.out)?;
    let lights = collection_lights()?;
    let clean = AugmentationRanges {
        exposure_stops: 0.0,
        white_balance: 0.0,
        blur: (0.0, 0.3),
        noise: 0.0,
        jpeg: (0.0, 95),
    };
    let mut table = format!(
        "Estimator {origin} ({} steps, working resolution {}), {} held-out identities, seed {}:\n\n\
         | side | photos | normal angle (deg) | albedo error | mask IoU | seconds per photo |\n|---|---|---|---|---|---|\n",
        file.training.steps, file.estimator.resolution, args.held_out, args.seed
    );
    let sheet_side = if args.sides.contains(&128) {
        128
    } else {
        args.sides[0]
    };
    let sheet = args.out.with_extension("png");
    for &side in &args.sides {
        for (name, ranges) in [
            ("augmented", AugmentationRanges::default()),
            ("clean", clean.clone()),
        ] {
            let inputs =
                training::held_out_inputs(&lights, args.held_out, args.seed, side, 2, &ranges)?;
            let start = Instant::now();
            let estimates =
                training::estimate_inputs(estimator, &inputs, file.estimator.resolution);
            let per = start.elapsed().as_secs_f64() / inputs.len() as f64;
            let a = training::score(&estimates, &inputs);
            let _ = writeln!(
                table,
                "| {side} | {name} | {:.2} | {:.4} | {:.4} | {per:.3} |",
                a.normal_degrees, a.albedo_error, a.mask_iou
            );
            if side == sheet_side && name == "augmented" {
                let rows: Vec<_> = inputs.iter().zip(&estimates).take(8).collect();
                sheets::save_comparison(&sheet, &rows)?;
            }
        }
    }
    print!("{table}");
    std::fs::write(&args.out, &table).with_context(|| format!("writing {}", args.out.display()))?;
    println!(
        "wrote {} and {} (the first 8 augmented held-out photos at {sheet_side}: photo, then albedo, normals and mask, each estimated and true)",
        args.out.display(),
        sheet.display()
    );
    Ok(())
}

/// The light maps of the default HDRI collection, with the time they took.
fn collection_lights() -> anyhow::Result<Vec<LightMapSet>> {
    let start = Instant::now();
    let lights = synthetic_pairs::collection_lights()?;
    tracing::info!(
        "{} environments preconvolved in {:.1} s",
        lights.len(),
        start.elapsed().as_secs_f64()
    );
    Ok(lights)
}

fn train(args: PseudoGtArgs) -> anyhow::Result<()> {
    let options = TrainOptions {
        batch: args.batch,
        pool: args.pool,
        held_out: args.held_out,
        seed: args.seed,
        minutes: args.minutes,
        max_steps: args.steps,
        eval_every: args.eval_every,
        ..TrainOptions::default()
    };
    options.check()?;
    let lights = collection_lights()?;
    println!(
        "training the estimator ({} parameters at {}x{}) for {} minutes{} into {}",
        options.config.init(&Device::flex()).num_params(),
        options.config.resolution,
        options.config.resolution,
        options.minutes,
        args.steps
            .map(|s| format!(" or {s} steps"))
            .unwrap_or_default(),
        args.out.display()
    );
    let (_, file) = training::train(&options, &lights, &args.out, &mut |p| {
        println!(
            "step {:>6} ({:>7} images, {:>6.0} s): losses albedo {:.4} normals {:.4} mask {:.4}; held out: normals {:.2} deg, albedo {:.4}, mask IoU {:.4}",
            p.step,
            p.images,
            p.seconds,
            p.albedo_l1,
            p.normal_1_minus_cos,
            p.mask_bce,
            p.held_out.normal_degrees,
            p.held_out.albedo_error,
            p.held_out.mask_iou
        );
    })?;
    println!(
        "wrote {} ({} steps, {:.0} s)",
        args.out.display(),
        file.training.steps,
        file.training.seconds
    );
    Ok(())
}
