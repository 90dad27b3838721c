//! `poses.csv`: one `name,yaw,pitch` row per photo, radians, checked row by row.

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};

use volux_model::pose::Pose;

use super::{FolderError, MAX_YAW};

/// Reads `poses.csv`: one row per photo in `photos`.
pub(super) fn read_poses(
    path: &Path,
    photos: &BTreeMap<String, PathBuf>,
) -> Result<BTreeMap<String, Pose>, FolderError> {
    let text = fs::read_to_string(path).map_err(|source| FolderError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    parse_poses(&text, path, photos)
}

/// Checks the text of a `poses.csv` (read from `path`) against the photos it must cover, the
/// way opening a folder dataset does.
pub fn parse_poses<V>(
    text: &str,
    path: &Path,
    photos: &BTreeMap<String, V>,
) -> Result<BTreeMap<String, Pose>, FolderError> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty());
    let (header_line, header) = lines.next().unwrap_or((1, ""));
    let fields: Vec<String> = header
        .split(',')
        .map(|f| f.trim().to_ascii_lowercase())
        .collect();
    if fields != ["name", "yaw", "pitch"] {
        return Err(FolderError::PosesHeader {
            path: path.to_path_buf(),
            line: header_line,
            found: header.to_owned(),
        });
    }
    let mut poses = BTreeMap::new();
    let mut lines_of = BTreeMap::new();
    for (line, row) in lines {
        let fields: Vec<&str> = row.split(',').map(str::trim).collect();
        let [stem, yaw, pitch] = fields[..] else {
            return Err(FolderError::PoseFields {
                path: path.to_path_buf(),
                line,
                found: fields.len(),
            });
        };
        if !photos.contains_key(stem) {
            return Err(FolderError::PoseUnknownName {
                path: path.to_path_buf(),
                line,
                stem: stem.to_owned(),
            });
        }
        if let Some(&first) = lines_of.get(stem) {
            return Err(FolderError::PoseDuplicate {
                path: path.to_path_buf(),
                line,
                first,
                stem: stem.to_owned(),
            });
        }
        let value = |column: &'static str, text: &str| {
            let error = |reason| FolderError::PoseValue {
                path: path.to_path_buf(),
                line,
                column,
                value: text.to_owned(),
                reason,
            };
            let v: f64 = text.parse().map_err(|_| error("is not a number"))?;
            if v.is_finite() {
                Ok(v)
            } else {
                Err(error("is not finite"))
            }
        };
        let yaw_value = value("yaw", yaw)?;
        if yaw_value.abs() > MAX_YAW {
            return Err(FolderError::PoseValue {
                path: path.to_path_buf(),
                line,
                column: "yaw",
                value: yaw.to_owned(),
                reason: "must be within [-2 pi, 2 pi] radians (degrees given?)",
            });
        }
        let yaw = yaw_value;
        let pitch_value = value("pitch", pitch)?;
        if pitch_value.abs() >= std::f64::consts::FRAC_PI_2 {
            return Err(FolderError::PoseValue {
                path: path.to_path_buf(),
                line,
                column: "pitch",
                value: pitch.to_owned(),
                reason: "must be strictly between -pi/2 and pi/2 radians",
            });
        }
        lines_of.insert(stem.to_owned(), line);
        poses.insert(stem.to_owned(), Pose::new(yaw, pitch_value));
    }
    let stems: Vec<String> = photos
        .keys()
        .filter(|s| !poses.contains_key(*s))
        .cloned()
        .collect();
    if !stems.is_empty() {
        return Err(FolderError::PosesMissing {
            path: path.to_path_buf(),
            stems,
        });
    }
    Ok(poses)
}
