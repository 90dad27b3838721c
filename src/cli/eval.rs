//! `volux eval`: the consistency measurements of a checkpoint's EMA generator (multi-view,
//! relighting, geometry), its sliced Wasserstein distance to the training data, the same
//! measurements on the synthetic data, a table, `eval.json` and figure strips.

use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;
use volux_eval::evaluate::{EvalOptions, evaluate};
use volux_model::backend::BackendKind;
use volux_train::pretrained::load_for_sampling;

use super::environment::environments;
use super::sample::save_sheet;

/// The shipped maps the relighting measurement uses when no `--hdri` is given.
const DEFAULT_ENVIRONMENTS: [&str; 3] = ["sunrise", "studio", "forest"];

#[derive(Debug, Args)]
pub struct EvalArgs {
    /// A checkpoint folder, a run folder (its newest checkpoint is used), or the name of a
    /// model shipped in the binary (`quickstart`).
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// Latents (and synthetic heads, and dataset images) per measurement.
    #[arg(long, default_value_t = 100)]
    pub samples: usize,
    /// Seed of the first latent; the others follow.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Side-view camera yaws in degrees, compared with the frontal view (comma-separated).
    /// Default: -28.65, -14.32, 14.32 and 28.65 degrees (+-0.25 and +-0.5 rad, the views the
    /// documented tables use).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub yaw: Vec<f64>,
    /// Environment maps (EXR or HDR) for the relighting measurement; the first also lights the
    /// multi-view one. Default: the shipped sunrise, studio and forest maps.
    #[arg(long)]
    pub hdri: Vec<PathBuf>,
    /// Largest depth disagreement (world units) of a consistent reprojection.
    #[arg(long, default_value_t = volux_eval::reprojection::DEFAULT_TOLERANCE)]
    pub tolerance: f64,
    /// Images per generator forward pass.
    #[arg(long, default_value_t = 8)]
    pub batch: usize,
    /// Compute backend: cpu or wgpu.
    #[arg(long, default_value = "cpu")]
    pub backend: BackendKind,
    /// Output folder (eval.json and the figures).
    #[arg(long, default_value = "eval")]
    pub out: PathBuf,
}

pub fn run(args: EvalArgs) -> anyhow::Result<()> {
    if !(1..=10_000).contains(&args.samples) {
        bail!("--samples {}: give 1 to 10000", args.samples);
    }
    if !(1..=256).contains(&args.batch) {
        bail!("--batch {}: give 1 to 256", args.batch);
    }
    super::output_folder(&args.out)?;
    if !(args.tolerance.is_finite() && args.tolerance > 0.0) {
        bail!("--tolerance {} must be positive", args.tolerance);
    }
    if let Some(y) = args
        .yaw
        .iter()
        .find(|y| !y.is_finite() || **y == 0.0 || y.abs() > 85.0)
    {
        bail!("--yaw {y}: side views need a non-zero yaw within [-85, 85] degrees");
    }
    let trained = load_for_sampling(&args.checkpoint, args.backend)?;
    let (state, dir) = (&trained.state, &trained.origin);
    println!(
        "checkpoint {} ({} model, {:.2} kimg)",
        dir.display(),
        trained.config.model.preset,
        state.images as f64 / 1000.0
    );
    let mut options = EvalOptions::new(environments(&args.hdri, &DEFAULT_ENVIRONMENTS)?);
    options.samples = args.samples;
    options.first_seed = args.seed;
    if !args.yaw.is_empty() {
        options.yaws = args.yaw.iter().map(|y| y.to_radians()).collect();
    }
    options.tolerance = args.tolerance;
    options.batch = args.batch;
    let evaluation = evaluate(
        &trained.g,
        &trained.device,
        &trained.config,
        &dir.display().to_string(),
        state.images,
        &options,
    )?;
    let table = evaluation.report.to_table();
    print!("{table}");
    let txt = args.out.join("eval.txt");
    std::fs::write(&txt, &table).with_context(|| format!("writing {}", txt.display()))?;
    let json = args.out.join("eval.json");
    let text = serde_json::to_string_pretty(&evaluation.report)?;
    std::fs::write(&json, text + "\n").with_context(|| format!("writing {}", json.display()))?;
    println!("wrote {}", json.display());
    for figure in &evaluation.figures {
        save_sheet(
            &args.out.join(format!("{}.png", figure.name)),
            &figure.sheet,
        )?;
    }
    Ok(())
}
