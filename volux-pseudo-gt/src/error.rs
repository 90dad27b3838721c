//! Why pseudo ground truth cannot be made or its estimator trained or loaded.

use std::path::PathBuf;

use volux_data::folder_dataset::FolderError;
use volux_data::hdri_collection::HdriError;
use volux_data::light_map_bank::LightMapBankError;
use volux_data::synthetic_head::SyntheticError;
use volux_envmap::EnvMapError;
use volux_envmap::durable::FileError;

#[derive(Debug, thiserror::Error)]
pub enum PseudoGtError {
    /// A file or folder could not be read, listed or written.
    #[error("{}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// An atomic write failed at one of its steps.
    #[error(transparent)]
    File(#[from] FileError),
    /// An image could not be read or written.
    #[error(transparent)]
    Image(#[from] EnvMapError),
    /// The environments that light the training photos could not be made.
    #[error("the HDRI collection")]
    Collection(#[source] HdriError),
    #[error("the light maps of the HDRI collection")]
    LightMaps(#[source] LightMapBankError),
    /// A synthetic head could not be rendered.
    #[error("synthetic head {identity}")]
    Synthetic {
        identity: u64,
        #[source]
        source: SyntheticError,
    },
    /// Burn could not write, read or apply the estimator's weights.
    #[error("{}: the estimator's weights", path.display())]
    Weights {
        path: PathBuf,
        #[source]
        source: burn::store::RecordError,
    },
    /// The estimator's `estimator.toml` cannot be read or used.
    #[error("{}: {reason}", path.display())]
    Description { path: PathBuf, reason: String },
    /// The weights hold a NaN or an infinity.
    #[error("{}: parameter {parameter} is not finite", path.display())]
    NonFinite { path: PathBuf, parameter: String },
    /// A value given to a command is out of range.
    #[error("{0}")]
    Invalid(String),
    /// The photo folder has no photos.
    #[error("{}: no .png, .jpg or .jpeg photos", path.display())]
    NoPhotos { path: PathBuf },
    /// The folder dataset could not be written.
    #[error(transparent)]
    Folder(#[from] FolderError),
    /// Training stopped on a non-finite loss.
    #[error("training step {step}: the loss is {value}")]
    NonFiniteLoss { step: u64, value: f32 },
}
