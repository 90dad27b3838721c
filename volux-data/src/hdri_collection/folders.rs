//! User folders of `.exr` / `.hdr` environment maps (for example the Poly Haven set).

use std::fs;
use std::path::Path;

use super::{HdriEntry, HdriError, HdriSource};

/// Entries for the `.exr` / `.hdr` files of `folder` (not recursive), sorted by file name.
/// Hidden files (name starting with `.`) and sub-folders are skipped; other files are skipped
/// with a warning. An unreadable folder, or one without maps, is an error naming it.
pub fn folder_entries(folder: &Path) -> Result<Vec<HdriEntry>, HdriError> {
    let read_err = |source| HdriError::ReadFolder {
        path: folder.to_path_buf(),
        source,
    };
    let mut files = Vec::new();
    for entry in fs::read_dir(folder).map_err(read_err)? {
        let entry = entry.map_err(read_err)?;
        let path = entry.path();
        let file_name = entry.file_name();
        if file_name.to_string_lossy().starts_with('.') || path.is_dir() {
            continue;
        }
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        if matches!(ext.as_deref(), Some("exr" | "hdr")) {
            files.push((file_name, path));
        } else {
            tracing::warn!(
                "{}: ignored, not an .exr or .hdr environment map",
                path.display()
            );
        }
    }
    if files.is_empty() {
        return Err(HdriError::EmptyFolder {
            path: folder.to_path_buf(),
        });
    }
    files.sort();
    let folder_name = folder
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| folder.display().to_string());
    Ok(files
        .into_iter()
        .map(|(file_name, path)| HdriEntry {
            name: format!("{folder_name}/{}", file_name.to_string_lossy()),
            source: HdriSource::File(path),
        })
        .collect())
}
