//! Files that survive a crash: every file volux writes (maps, light-map and example caches,
//! datasets, checkpoints, meshes, videos, pages) goes through [`write_atomically`] or
//! [`sync_file`] and [`sync_dir`], so that after a kill or a power cut a path holds either its
//! old contents or the whole new file, never a torn one.

use std::fs;
use std::path::{Path, PathBuf};

/// A file-system step that failed: the path it was on, and the OS error.
#[derive(Debug, thiserror::Error)]
#[error("{}", path.display())]
pub struct FileError {
    pub path: PathBuf,
    #[source]
    pub source: std::io::Error,
}

impl FileError {
    /// A closure for `map_err` that names `path`.
    pub fn at(path: &Path) -> impl FnOnce(std::io::Error) -> FileError + '_ {
        move |source| FileError {
            path: path.to_path_buf(),
            source,
        }
    }
}

/// Flushes a file's contents to the disk (`fsync`).
pub fn sync_file(path: &Path) -> std::io::Result<()> {
    fs::File::open(path)?.sync_all()
}

/// Flushes a folder's entries (names created, renamed or removed in it) to the disk, so that a
/// rename survives a power cut. On systems where a folder cannot be opened as a file (Windows)
/// there is nothing to do.
pub fn sync_dir(path: &Path) -> std::io::Result<()> {
    #[cfg(unix)]
    {
        fs::File::open(path)?.sync_all()
    }
    #[cfg(not(unix))]
    {
        let _ = path;
        Ok(())
    }
}

/// The folder a path's entry lives in (`.` for a bare file name).
fn parent_folder(path: &Path) -> &Path {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// Runs `write` on a temporary file next to `path`, flushes it to the disk, renames it to
/// `path` and flushes the folder, so that after a crash or a power cut `path` holds either its
/// old contents or the whole new file. On any error the temporary file is removed and `path`
/// is untouched. `write`'s own error type `E` is kept; the flush and rename steps fail as a
/// [`FileError`] converted into it.
pub fn write_atomically<E: From<FileError>>(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
) -> Result<(), E> {
    let file_name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    // Unique per process and call, so that threads writing the same target do not share a
    // temporary file. Keep the extension last: encoders pick the format from it.
    static CALLS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let call = CALLS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let tmp: PathBuf =
        path.with_file_name(format!(".tmp.{}.{call}.{file_name}", std::process::id()));
    let steps = || -> Result<(), FileError> {
        sync_file(&tmp).map_err(FileError::at(&tmp))?;
        fs::rename(&tmp, path).map_err(FileError::at(path))?;
        let folder = parent_folder(path);
        sync_dir(folder).map_err(FileError::at(folder))
    };
    let result = write(&tmp).and_then(|()| steps().map_err(E::from));
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug)]
    enum Failure {
        Writer,
        File(FileError),
    }

    impl From<FileError> for Failure {
        fn from(e: FileError) -> Self {
            Failure::File(e)
        }
    }

    fn entries(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    #[test]
    fn a_write_replaces_the_file_whole_and_a_failure_leaves_it_and_no_temporary() {
        let dir = std::env::temp_dir().join(format!("volux-durable-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(&dir).unwrap();
        let path = dir.join("a.txt");
        write_atomically::<FileError>(&path, |tmp| {
            fs::write(tmp, "old").map_err(FileError::at(tmp))
        })
        .unwrap();
        // The writer's own error comes back as it was, with the old file intact.
        let failed = write_atomically(&path, |tmp| {
            fs::write(tmp, "half").unwrap();
            Err(Failure::Writer)
        });
        assert!(matches!(failed, Err(Failure::Writer)));
        assert_eq!(fs::read_to_string(&path).unwrap(), "old");
        assert_eq!(entries(&dir), ["a.txt"]);
        // A step after the writer fails as a FileError naming its path: here the rename onto
        // a folder.
        let folder = dir.join("sub");
        fs::create_dir_all(folder.join("x")).unwrap();
        let failed = write_atomically::<Failure>(&folder, |tmp| {
            fs::write(tmp, "new").map_err(|e| Failure::File(FileError::at(tmp)(e)))
        });
        match failed {
            Err(Failure::File(e)) => assert_eq!(e.path, folder),
            other => panic!("expected a FileError, got {other:?}"),
        }
        assert_eq!(entries(&dir), ["a.txt", "sub"]);
        fs::remove_dir_all(&dir).unwrap();
    }
}
