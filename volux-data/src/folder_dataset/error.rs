//! The folder dataset's errors, and the name lists they print.

use std::fmt::Write as _;
use std::path::PathBuf;

use volux_envmap::EnvMapError;

use super::{ALBEDO, FolderContent, LISTED_NAMES, MASKS, NORMALS, PHOTOS, POSES_FILE};

/// What is wrong with a folder dataset, or with samples to write as one. Every message names
/// the file, folder or name at fault.
#[derive(Debug, thiserror::Error)]
pub enum FolderError {
    /// The dataset root does not exist.
    #[error("{}: no such folder", path.display())]
    NoSuchFolder { path: PathBuf },
    /// The dataset root, or a folder of the layout, is a file.
    #[error("{}: not a folder", path.display())]
    NotAFolder { path: PathBuf },
    /// Required folders of the layout are missing.
    #[error(
        "{}: missing {}; {}",
        root.display(),
        folders.iter().map(|f| format!("{f}/")).collect::<Vec<_>>().join(", "),
        match content {
            FolderContent::Intrinsics => format!(
                "a folder dataset holds photos/, albedo/ and normals/ (masks/ and {POSES_FILE} are optional); for photos alone set layers = [\"photo\"] in [data.source]"
            ),
            FolderContent::Photos => format!(
                "a photos-only dataset holds photos/ (masks/ and {POSES_FILE} are optional)"
            ),
        }
    )]
    MissingFolders {
        root: PathBuf,
        folders: Vec<&'static str>,
        content: FolderContent,
    },
    /// Intrinsic layers asked of a photos-only dataset.
    #[error("{}: a photos-only dataset has no albedo or normals", root.display())]
    NoIntrinsics { root: PathBuf },
    /// `photos/` holds no photo.
    #[error(
        "{}: no photos (.png, .jpg or .jpeg){}",
        folder.display(),
        if *ignored > 0 { format!("; {ignored} other file(s) ignored") } else { String::new() }
    )]
    NoPhotos { folder: PathBuf, ignored: usize },
    /// Two files in one folder share a name (`a.png` and `a.jpg`).
    #[error(
        "two files for one name: {}",
        pairs.iter()
            .map(|(a, b)| format!("{} and {}", a.display(), b.display()))
            .collect::<Vec<_>>()
            .join("; ")
    )]
    DuplicateNames { pairs: Vec<(PathBuf, PathBuf)> },
    /// Photos without an albedo or normal map, or layers without a photo: per folder, the
    /// names without their counterpart.
    #[error("{}: files do not match up by name: {}", root.display(), unmatched_list(missing, orphans))]
    Unmatched {
        root: PathBuf,
        /// Folders with no file for some photos: `(folder, names)`.
        missing: Vec<(&'static str, Vec<String>)>,
        /// Folders with files that have no photo: `(folder, names)`.
        orphans: Vec<(&'static str, Vec<String>)>,
    },
    /// A layer's image is not the size of its photo.
    #[error(
        "{stem}: {layer} {} is {}x{}, the photo is {}x{}",
        path.display(), size.0, size.1, photo.0, photo.1
    )]
    SizeMismatch {
        stem: String,
        layer: &'static str,
        path: PathBuf,
        /// The layer's `(width, height)`.
        size: (usize, usize),
        /// The photo's `(width, height)`.
        photo: (usize, usize),
    },
    /// NaN or infinite values in an EXR layer.
    #[error("{}: {count} pixel(s) with NaN or infinite values (first at x={x}, y={y})", path.display())]
    NonFinite {
        path: PathBuf,
        count: usize,
        x: usize,
        y: usize,
    },
    /// A file could not be read or decoded, or written (the path and the reason).
    #[error(transparent)]
    Image(#[from] EnvMapError),
    /// A folder could not be listed or created, or a file read.
    #[error("{}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The first line of `poses.csv` is not `name,yaw,pitch`.
    #[error("{}: line {line}: the header must be `name,yaw,pitch`, found `{found}`", path.display())]
    PosesHeader {
        path: PathBuf,
        line: usize,
        found: String,
    },
    /// A row of `poses.csv` without exactly three fields.
    #[error("{}: line {line}: expected 3 fields `name,yaw,pitch`, found {found}", path.display())]
    PoseFields {
        path: PathBuf,
        line: usize,
        found: usize,
    },
    /// A yaw or pitch that is not a number, not finite, or a pitch out of range.
    #[error("{}: line {line}: {column} `{value}` {reason}", path.display())]
    PoseValue {
        path: PathBuf,
        line: usize,
        column: &'static str,
        value: String,
        reason: &'static str,
    },
    /// A row of `poses.csv` for a name with no photo.
    #[error(
        "{}: line {line}: no photo named `{stem}` (names are file stems, without extension)",
        path.display()
    )]
    PoseUnknownName {
        path: PathBuf,
        line: usize,
        stem: String,
    },
    /// Two rows of `poses.csv` for one name.
    #[error("{}: line {line}: a second row for `{stem}` (the first is on line {first})", path.display())]
    PoseDuplicate {
        path: PathBuf,
        line: usize,
        first: usize,
        stem: String,
    },
    /// Photos with no row in `poses.csv`.
    #[error("{}: no row for {}", path.display(), name_list(stems))]
    PosesMissing { path: PathBuf, stems: Vec<String> },
    /// A sample with no foreground at all: its mask (or, without a mask file, its normals) is
    /// zero everywhere.
    #[error(
        "{}: no foreground pixel in `{stem}` (the mask is zero everywhere{}); remove the photo or fix its layers",
        path.display(),
        if *from_normals { ", and without a mask file it comes from the normals' length" } else { "" }
    )]
    NoForeground {
        stem: String,
        path: PathBuf,
        from_normals: bool,
    },
    /// A normal map without usable camera-space normals in the foreground.
    #[error("{}: {reason} in {percent:.0}% of the foreground; normals must be camera-space, +z towards the camera (docs/data.md)", path.display())]
    BadNormals {
        path: PathBuf,
        reason: &'static str,
        percent: f64,
    },
    /// [`write_dataset`] writes into a new or empty folder only.
    #[error("{}: not empty; write a folder dataset into a new or empty folder", path.display())]
    NotEmpty { path: PathBuf },
    /// [`write_dataset`] was given no samples.
    #[error("{}: no samples to write", root.display())]
    NothingToWrite { root: PathBuf },
    /// A sample [`write_dataset`] cannot write.
    #[error("sample `{stem}`: {reason}")]
    InvalidSample { stem: String, reason: String },
}

/// `names` as `a, b, c`, at most [`LISTED_NAMES`] of them.
pub(super) fn name_list(names: &[String]) -> String {
    let mut s = names
        .iter()
        .take(LISTED_NAMES)
        .map(String::as_str)
        .collect::<Vec<_>>()
        .join(", ");
    if names.len() > LISTED_NAMES {
        let _ = write!(s, " and {} more", names.len() - LISTED_NAMES);
    }
    s
}

fn unmatched_list(
    missing: &[(&'static str, Vec<String>)],
    orphans: &[(&'static str, Vec<String>)],
) -> String {
    let accepted = |folder: &str| {
        let layer = [ALBEDO, NORMALS, MASKS, PHOTOS]
            .into_iter()
            .find(|l| l.folder == folder);
        layer.map_or(String::new(), |l| {
            let exts: Vec<String> = l.extensions.iter().map(|e| format!(".{e}")).collect();
            format!(" {}", exts.join("/"))
        })
    };
    let missing = missing.iter().map(|(folder, names)| {
        format!(
            "{folder}/ has no{} file for: {}",
            accepted(folder),
            name_list(names)
        )
    });
    let orphans = orphans
        .iter()
        .map(|(folder, names)| format!("{folder}/ has files with no photo: {}", name_list(names)));
    missing.chain(orphans).collect::<Vec<_>>().join("; ")
}
