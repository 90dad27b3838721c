//! Reading TOML config files: why one cannot be used, naming the file and keeping the cause.
//!
//! Each variant displays the file (and the table), and hands the underlying error on as its
//! `source`, so that a printed chain reads `config.toml: [data]: unknown field ...` once.

use std::path::{Path, PathBuf};

/// A cause carried by [`ConfigFileError::Table`].
pub type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// Why a config file cannot be read or used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigFileError {
    /// The file cannot be read.
    #[error("{}", path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The file is not TOML, or its top level is not what the program reads.
    #[error("{}", path.display())]
    Toml {
        path: PathBuf,
        #[source]
        source: toml::de::Error,
    },
    /// A table is absent.
    #[error("{}: no [{table}] table", path.display())]
    MissingTable { path: PathBuf, table: &'static str },
    /// A table holds a key, type or value it may not.
    #[error("{}: [{table}]", path.display())]
    Table {
        path: PathBuf,
        table: &'static str,
        #[source]
        source: BoxError,
    },
    /// A value the program checks itself is out of range.
    #[error("{}: {message}", path.display())]
    Invalid { path: PathBuf, message: String },
}

/// Reads the text of the config file at `path`.
pub fn read(path: &Path) -> Result<String, ConfigFileError> {
    std::fs::read_to_string(path).map_err(|source| ConfigFileError::Read {
        path: path.to_path_buf(),
        source,
    })
}

/// Parses `text`, the contents of the file at `path`, as TOML.
pub fn parse<T: serde::de::DeserializeOwned>(
    text: &str,
    path: &Path,
) -> Result<T, ConfigFileError> {
    toml::from_str(text).map_err(|source| ConfigFileError::Toml {
        path: path.to_path_buf(),
        source,
    })
}
