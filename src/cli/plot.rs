//! `volux plot RUN`: a run's losses and light-evaluation scores against images and minutes.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use volux_eval::plot::plot_run;

#[derive(Debug, Args)]
pub struct PlotArgs {
    /// Run folder (its metrics.jsonl is read).
    pub run: PathBuf,
    /// Folder for curves-kimg.png and curves-minutes.png (default: RUN/plots).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

pub fn run(args: PlotArgs) -> anyhow::Result<()> {
    let out = args.out.unwrap_or_else(|| args.run.join("plots"));
    let title = args
        .run
        .canonicalize()
        .ok()
        .and_then(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
        .unwrap_or_else(|| args.run.display().to_string());
    let written = plot_run(&args.run, &out, &format!("volux run {title}"))
        .with_context(|| format!("plotting {}", args.run.display()))?;
    for path in written {
        println!("wrote {}", path.display());
    }
    Ok(())
}
