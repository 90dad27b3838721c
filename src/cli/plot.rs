//! `volux plot RUN [RUN...]`: a run's losses and light-evaluation scores against images and
//! minutes, or the scores of several runs against each other.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::Args;
use volux_eval::plot::{plot_run, plot_runs};

#[derive(Debug, Args)]
pub struct PlotArgs {
    /// Run folder(s) (their metrics.jsonl is read). With two or more, their light
    /// evaluations are drawn against each other, one colour per run.
    #[arg(required = true)]
    pub runs: Vec<PathBuf>,
    /// Output folder: for one run `curves-kimg.png` and `curves-minutes.png` (default:
    /// RUN/plots), for several `compare-kimg.png` and `compare-minutes.png` (required).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// A run's name for titles and legends: its folder's name.
fn name(run: &Path) -> String {
    run.canonicalize()
        .ok()
        .and_then(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
        .unwrap_or_else(|| run.display().to_string())
}

pub fn run(args: PlotArgs) -> anyhow::Result<()> {
    let written = match args.runs.as_slice() {
        [run] => {
            let out = args.out.unwrap_or_else(|| run.join("plots"));
            plot_run(run, &out, &format!("volux run {}", name(run)))
                .with_context(|| format!("plotting {}", run.display()))?
        }
        runs => {
            let Some(out) = args.out else {
                bail!(
                    "comparing {} runs needs --out DIR for the plots",
                    runs.len()
                );
            };
            let labelled: Vec<(String, PathBuf)> =
                runs.iter().map(|r| (name(r), r.clone())).collect();
            plot_runs(&labelled, &out).context("comparing runs")?
        }
    };
    for path in written {
        println!("wrote {}", path.display());
    }
    Ok(())
}
