//! Why training stopped with an error.

use std::path::{Path, PathBuf};

use volux_data::dataset::DataError;
use volux_data::examples::ExamplesError;
use volux_model::backend::BackendError;
use volux_model::generator::GeneratorError;
use volux_model::light_lookup::LightingTensorError;

use crate::checkpoint::CheckpointError;
use crate::metrics::BoxError;
use crate::sampling;

/// Why training stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error(transparent)]
    Config(#[from] crate::config::ConfigError),
    #[error(transparent)]
    Backend(#[from] BackendError),
    #[error(transparent)]
    Data(#[from] DataError),
    #[error(transparent)]
    Examples(#[from] ExamplesError),
    #[error(
        "{} already holds a run ({}): {}",
        out.display(),
        found.iter().map(|p| p.file_name().map_or(String::new(), |n| n.to_string_lossy().into_owned())).collect::<Vec<_>>().join(", "),
        if *resumable {
            "continue it with --resume, start afresh with --force (deletes that run), or choose another --out"
        } else {
            "it stopped before its first checkpoint, so there is nothing to resume; start afresh with --force (deletes what it left) or choose another --out"
        }
    )]
    RunExists {
        out: PathBuf,
        found: Vec<PathBuf>,
        /// Whether it holds a complete checkpoint `--resume` can continue.
        resumable: bool,
    },
    #[error("the batch loader has stopped after an earlier error")]
    LoaderStopped,
    #[error("lighting a batch")]
    Lighting(#[from] LightingTensorError),
    #[error("generator")]
    Model(#[from] GeneratorError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error(
        "no checkpoint or run folder at {path}, and no shipped model of that name (shipped: {shipped})"
    )]
    NoCheckpoint { path: PathBuf, shipped: String },
    #[error("sample grid")]
    Sample(#[from] sampling::SampleError),
    #[error("evaluating the EMA generator at {kimg:.2} kimg")]
    Eval {
        kimg: f64,
        #[source]
        source: BoxError,
    },
    #[error("{}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A sample grid cannot be written (the image writer's error names the file).
    #[error("writing a sample grid")]
    Grid(#[source] volux_envmap::EnvMapError),
    #[error(
        "{count} steps in a row had non-finite losses or weights (last: {reason}); stopped after step {step} (metrics.jsonl's count). The last good checkpoint is {}",
        last_good.as_ref().map_or("none (no checkpoint was written)".to_string(), |p| p.display().to_string())
    )]
    NonFinite {
        count: usize,
        reason: String,
        step: u64,
        last_good: Option<PathBuf>,
    },
}

pub(super) fn io_error(path: &Path, source: std::io::Error) -> TrainError {
    TrainError::Io {
        path: path.to_path_buf(),
        source,
    }
}
