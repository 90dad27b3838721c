//! Why a dataset, its lighting or one of its examples cannot be made.

use std::path::PathBuf;

use crate::config_file::ConfigFileError;
use crate::folder_dataset::FolderError;
use crate::hdri_collection::HdriError;
use crate::training_sample::SampleError;

/// Why the dataset's lighting cannot be made: its HDRI collection, or the light maps of it.
#[derive(Debug, thiserror::Error)]
pub enum LightingError {
    #[error(transparent)]
    Collection(HdriError),
    #[error(transparent)]
    Bank(crate::light_map_bank::LightMapBankError),
}

/// Why a dataset or an example cannot be made.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    #[error("data config: {0}")]
    Config(String),
    #[error(transparent)]
    File(#[from] ConfigFileError),
    #[error("lighting")]
    Lighting(#[source] LightingError),
    #[error(transparent)]
    Folder(#[from] FolderError),
    #[error("{stem}")]
    Sample { stem: String, source: SampleError },
    #[error(
        "{}: the photo is {width}x{height}: a folder image must be square, {side} pixels or a multiple of it",
        path.display()
    )]
    FolderSize {
        path: PathBuf,
        width: usize,
        height: usize,
        side: usize,
    },
}
