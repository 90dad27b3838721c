//! Reading TOML config files: why one cannot be used, naming the file and keeping the cause.
//!
//! Each variant displays the file (and the table), and hands the underlying error on as its
//! `source`, so that a printed chain reads `config.toml: [data]: unknown field ...` once.

use std::path::{Path, PathBuf};

pub use volux_envmap::error::BoxError;

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

#[cfg(test)]
mod tests {
    use super::*;
    use volux_envmap::error::chain;

    #[test]
    fn the_file_is_named_once_and_the_cause_is_kept_not_copied() {
        let path = Path::new("dir/run.toml");
        let e = parse::<toml::Table>("[data\nseed = 1", path).unwrap_err();
        let ConfigFileError::Toml { source, .. } = &e else {
            panic!("{e:?}");
        };
        // The message names the file; the parser's words are the cause, printed once.
        assert_eq!(e.to_string(), "dir/run.toml");
        let printed = chain(&e);
        assert!(printed.starts_with("dir/run.toml: "), "{printed}");
        assert_eq!(printed.matches(&source.to_string()).count(), 1, "{printed}");
        let e = read(Path::new("no/such/run.toml")).unwrap_err();
        assert!(
            matches!(&e, ConfigFileError::Read { source, .. } if source.kind() == std::io::ErrorKind::NotFound)
        );
        assert!(chain(&e).starts_with("no/such/run.toml: "), "{}", chain(&e));
    }
}
