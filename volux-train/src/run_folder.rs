//! A run folder (`volux train --out`): its checkpoints, `metrics.jsonl` and `grids/`. A folder
//! that already holds a run is continued (`--resume`) or, only when asked (`--force`), cleared
//! of that run first; it is never silently mixed with a new one.

use std::fs;
use std::io;
use std::path::{Path, PathBuf};

use crate::checkpoint;

/// The metrics log of a run.
pub const METRICS: &str = "metrics.jsonl";
/// The folder of a run's sample grids.
pub const GRIDS: &str = "grids";

/// What in `out` belongs to a run (checkpoints, complete or not, the metrics log, the grids),
/// sorted. Other files are not a run's and are left alone.
pub fn run_files(out: &Path) -> Vec<PathBuf> {
    let Ok(entries) = fs::read_dir(out) else {
        return Vec::new();
    };
    let mut found: Vec<PathBuf> = entries
        .filter_map(|e| {
            let e = e.ok()?;
            let name = e.file_name();
            let name = name.to_str()?;
            let ours = name == METRICS
                || name == GRIDS
                || checkpoint::is_checkpoint_name(name.trim_start_matches('.'));
            ours.then(|| e.path())
        })
        .collect();
    found.sort();
    found
}

/// Deletes what [`run_files`] lists.
pub fn clear(out: &Path) -> Result<(), (PathBuf, io::Error)> {
    for path in run_files(out) {
        let removed = if path.is_dir() {
            fs::remove_dir_all(&path)
        } else {
            fs::remove_file(&path)
        };
        removed.map_err(|e| (path, e))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_runs_files_are_found_and_cleared_and_others_kept() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path();
        assert!(run_files(out).is_empty());
        assert!(run_files(&out.join("missing")).is_empty());
        fs::create_dir_all(out.join("checkpoint-00000004")).unwrap();
        fs::create_dir_all(out.join(".checkpoint-00000008.partial")).unwrap();
        fs::create_dir_all(out.join("grids")).unwrap();
        fs::write(out.join("metrics.jsonl"), "{}\n").unwrap();
        fs::write(out.join("notes.txt"), "mine").unwrap();
        fs::create_dir_all(out.join("checkpoints-backup")).unwrap();
        assert_eq!(run_files(out).len(), 4);
        clear(out).unwrap();
        assert!(run_files(out).is_empty());
        assert!(out.join("notes.txt").is_file() && out.join("checkpoints-backup").is_dir());
    }
}
