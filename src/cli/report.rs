//! `volux report RUN`: one self-contained HTML page of a run (state, curves, the latest
//! evaluation, grids over time, samples, config) that opens offline.

use std::path::PathBuf;

use anyhow::bail;
use clap::Args;
use volux_eval::run_page::save_run_page;

#[derive(Debug, Args)]
pub struct ReportArgs {
    /// Run folder (its checkpoints, metrics.jsonl, grids/ and samples/ are read).
    pub run: PathBuf,
    /// Output file (default: RUN/report.html).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

pub fn run(args: ReportArgs) -> anyhow::Result<()> {
    // Checked before the output's folder is made: a mistyped RUN created an empty folder.
    if !args.run.is_dir() {
        bail!("{}: not a run folder (no such folder)", args.run.display());
    }
    let out = args.out.unwrap_or_else(|| args.run.join("report.html"));
    super::output_file(&out)?;
    let name = args
        .run
        .canonicalize()
        .ok()
        .and_then(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
        .unwrap_or_else(|| args.run.display().to_string());
    save_run_page(&args.run, &format!("volux run {name}"), &out)?;
    let size = std::fs::metadata(&out).map(|m| m.len()).unwrap_or(0);
    println!(
        "wrote {} ({:.1} MB, self-contained)",
        out.display(),
        size as f64 / 1e6
    );
    Ok(())
}
