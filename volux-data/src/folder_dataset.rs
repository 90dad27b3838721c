//! Folder datasets: a person's own photos with the intrinsic layers of each (paper appendix A;
//! docs/data.md). Any decomposition tool can make the albedo, normals and masks; the
//! lighting half of the pseudo ground truth is computed from them by [`crate::relighting`].
//!
//! # Layout
//!
//! ```text
//! my_faces/
//!   photos/   NAME.png | .jpg | .jpeg          sRGB photos (required)
//!   albedo/   NAME.png | .jpg | .jpeg | .exr   albedo: PNG/JPEG are sRGB and linearised, EXR is linear (required)
//!   normals/  NAME.png | .exr                  camera-space normals: PNG stores RGB = (n + 1) / 2, EXR stores n (required)
//!   masks/    NAME.png | .jpg | .jpeg          foreground coverage in [0, 1], first channel (optional)
//!   poses.csv                                  header `name,yaw,pitch`, radians, one row per NAME (optional)
//! ```
//!
//! - Files are matched by file stem (`NAME`); extensions are case-insensitive. Every photo
//!   needs an albedo and a normal map of the same size, and every albedo, normal map or mask
//!   needs a photo. Hidden files (names starting with `.`) are skipped; other files and folders
//!   in the layout's folders are ignored with a warning ([`FolderDataset::ignored`] lists them).
//! - Normals are in camera space (docs/conventions.md): +x right, +y up, +z towards the
//!   camera. A PNG normal map's background grey `(0.5, 0.5, 0.5)` is the zero normal.
//! - A mask is optional per photo. Without one, the mask is 1 where the decoded normal is
//!   longer than [`MASK_FROM_NORMAL_LENGTH`] and 0 elsewhere: the background of a normal map
//!   is its zero normal.
//! - Without `poses.csv` every photo is frontal, pose `(0, 0)`. With it, every photo has
//!   exactly one row; yaw and pitch follow the dataset camera (`volux_model::ray_sampling`),
//!   pitch strictly between -pi/2 and pi/2. Blank lines, spaces around fields, a UTF-8 byte
//!   order mark and CRLF line ends are accepted.
//!
//! # Photos only
//!
//! A dataset may leave the intrinsic layers out on purpose ([`FolderContent::Photos`],
//! `layers = ["photo"]` in a config's `[data.source]`): then only `photos/` (with the
//! optional `masks/` and `poses.csv`) is read, `albedo/` and `normals/` are not required and
//! ignored if present, and training runs only the terms whose data exists (D_P). Without a
//! mask such a photo is used as it is (no mask is derived: there are no normals to derive it
//! from). Albedo and normals come together or not at all: the relit, diffuse and specular
//! layers need both, and the default mask comes from the normals.
//!
//! [`FolderDataset::open`] only lists the folders and reads `poses.csv`;
//! [`FolderDataset::load`] decodes one sample. Normals of foreground pixels (mask > 0) are
//! made unit length: those further than [`UNIT_TOLERANCE`] from it are counted as
//! renormalised, those shorter than [`DEGENERATE_LENGTH`] are counted as degenerate and become
//! `(0, 0, 1)`. Background normals (mask 0) are set to zero, like a normal map's background
//! and the generator's normal maps over a background of 0. Bad input is an error naming the
//! file, folder or name at fault, never a panic. [`write_dataset`] writes samples in this
//! layout.

use std::collections::BTreeMap;
use std::collections::btree_map::Entry;
use std::fs;
use std::path::{Path, PathBuf};

use volux_envmap::Rgb;
use volux_envmap::io::{self, Format, RawImage};

use crate::layers::Layers;
use crate::relighting::IntrinsicImage;

/// Decoded normals whose length differs from 1 by more than this are counted as renormalised.
///
/// 8-bit quantisation of `(n + 1) / 2` moves each component by at most 1/255 and a unit
/// normal's length by at most `sqrt(3) / 255 = 0.0068` (0.0065 measured over 200 000
/// directions with rounding, 0.0132 with an encoder that truncates, and 0.0067 rad in
/// direction); 0.02 counts neither, and still counts normals that are not unit length by
/// mistake (a map scaled by 0.9, or stored as `n` in a PNG).
pub const UNIT_TOLERANCE: f32 = 0.02;

/// Foreground normals shorter than this have no usable direction: they become `(0, 0, 1)` and
/// are counted as degenerate. 8-bit quantisation alone turns a direction of this length by up
/// to 0.0068 / 0.1 rad (4 degrees); an encoded zero normal decodes to length 0.0068.
pub const DEGENERATE_LENGTH: f32 = 0.1;

/// Without a mask, pixels whose decoded normal is longer than this are foreground (mask 1).
pub const MASK_FROM_NORMAL_LENGTH: f32 = 0.5;

/// The name of the optional pose file in a dataset's root.
pub const POSES_FILE: &str = "poses.csv";

/// Largest accepted `|yaw|` in `poses.csv`, radians: one turn either way. Beyond it a value is
/// a unit mistake (degrees), and far beyond it f32 cameras overflow.
pub const MAX_YAW: f64 = std::f64::consts::TAU;

/// Above this fraction of foreground normals facing away from the camera (`n_z < -0.1`), a
/// normal map is refused: camera-space normals of a visible surface face the camera, so such
/// a map is in another convention or an all-black image (which decodes to `(-1, -1, -1)`).
pub const MAX_AWAY_FRACTION: f64 = 0.5;

/// The longest list of names an error message spells out.
const LISTED_NAMES: usize = 20;

/// One folder of the layout and the extensions it accepts.
#[derive(Clone, Copy, Debug)]
struct Layer {
    folder: &'static str,
    extensions: &'static [&'static str],
}

const PHOTOS: Layer = Layer {
    folder: "photos",
    extensions: &["png", "jpg", "jpeg"],
};
const ALBEDO: Layer = Layer {
    folder: "albedo",
    extensions: &["png", "jpg", "jpeg", "exr"],
};
const NORMALS: Layer = Layer {
    folder: "normals",
    extensions: &["png", "exr"],
};
const MASKS: Layer = Layer {
    folder: "masks",
    extensions: &["png", "jpg", "jpeg"],
};

/// Which layers a folder dataset provides (module docs: "Photos only").
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum FolderContent {
    /// Photos with their albedo and normal maps: every layer of a training example.
    #[default]
    Intrinsics,
    /// Photos alone (and masks, if given): only the photo layer.
    Photos,
}

impl FolderContent {
    /// Which layers of a training example a dataset of this content provides.
    pub fn provided(self) -> Layers<bool> {
        match self {
            FolderContent::Intrinsics => Layers::from_fn(|_| true),
            FolderContent::Photos => Layers::from_fn(|l| l == crate::layers::Layer::Photo),
        }
    }

    /// The folders of the layout a dataset of this content reads (masks are optional).
    fn required(self) -> &'static [Layer] {
        match self {
            FolderContent::Intrinsics => &[PHOTOS, ALBEDO, NORMALS],
            FolderContent::Photos => &[PHOTOS],
        }
    }
}

/// The intrinsic files of one photo.
#[derive(Clone, Debug)]
struct IntrinsicFiles {
    albedo: PathBuf,
    normals: PathBuf,
}

/// The files of one photo.
#[derive(Clone, Debug)]
struct SampleFiles {
    stem: String,
    photo: PathBuf,
    /// `None` in a photos-only dataset.
    intrinsics: Option<IntrinsicFiles>,
    mask: Option<PathBuf>,
    pose: Pose,
}

/// A folder dataset, listed and checked but not decoded (module docs: the layout).
#[derive(Clone, Debug)]
pub struct FolderDataset {
    root: PathBuf,
    content: FolderContent,
    entries: Vec<SampleFiles>,
    ignored: Vec<PathBuf>,
    has_poses: bool,
}

/// One decoded photo of a folder dataset, without intrinsic layers ([`FolderDataset::load_photo`]).
#[derive(Clone, Debug, PartialEq)]
pub struct PhotoSample {
    /// The file stem shared by the sample's files.
    pub stem: String,
    pub width: usize,
    pub height: usize,
    /// The photo, sRGB-encoded in [0, 1], row-major from the top-left pixel.
    pub photo: Vec<Rgb>,
    /// The mask file's coverage in [0, 1], if the photo has one.
    pub mask: Option<Vec<f32>>,
    pub pose: Pose,
}

/// One decoded sample of a folder dataset.
#[derive(Clone, Debug, PartialEq)]
pub struct FolderSample {
    /// The file stem shared by the sample's files.
    pub stem: String,
    /// The photo, sRGB-encoded in [0, 1], row-major from the top-left pixel.
    pub photo: Vec<Rgb>,
    /// Linear albedo, camera-space normals (unit in the foreground, zero where the mask is 0),
    /// the mask and the pose; the photo's size.
    pub image: IntrinsicImage,
    /// Foreground normals further than [`UNIT_TOLERANCE`] from unit length, renormalised.
    pub renormalised: usize,
    /// Foreground normals shorter than [`DEGENERATE_LENGTH`], set to `(0, 0, 1)`.
    pub degenerate: usize,
}

impl FolderDataset {
    /// Lists a folder dataset of every layer at `root` ([`FolderDataset::open_with`]).
    pub fn open(root: &Path) -> Result<FolderDataset, FolderError> {
        Self::open_with(root, FolderContent::Intrinsics)
    }

    /// Lists a folder dataset at `root` that provides `content`, and checks that its files
    /// match up and that `poses.csv` (if any) is valid. Decodes no image, so it is cheap;
    /// samples are sorted by name. Files outside the layout are ignored with a warning; so are
    /// `albedo/` and `normals/` in a photos-only dataset.
    pub fn open_with(root: &Path, content: FolderContent) -> Result<FolderDataset, FolderError> {
        if !is_folder(root)? {
            return Err(FolderError::NoSuchFolder {
                path: root.to_path_buf(),
            });
        }
        let mut missing_folders = Vec::new();
        for layer in content.required() {
            if !is_folder(&root.join(layer.folder))? {
                missing_folders.push(layer.folder);
            }
        }
        if !missing_folders.is_empty() {
            return Err(FolderError::MissingFolders {
                root: root.to_path_buf(),
                folders: missing_folders,
                content,
            });
        }
        let has_masks = is_folder(&root.join(MASKS.folder))?;
        let intrinsics = content == FolderContent::Intrinsics;
        if !intrinsics {
            let unused: Vec<String> = [ALBEDO, NORMALS]
                .iter()
                .filter(|l| root.join(l.folder).exists())
                .map(|l| format!("{}/", l.folder))
                .collect();
            if !unused.is_empty() {
                tracing::warn!(
                    "{}: photos only (layers = [\"photo\"]): {} not read",
                    root.display(),
                    unused.join(" and ")
                );
            }
        }

        let mut duplicates = Vec::new();
        let mut ignored = Vec::new();
        let mut scan_layer = |layer: Layer| scan(root, layer, &mut duplicates, &mut ignored);
        let photos = scan_layer(PHOTOS)?;
        let (albedo, normals) = if intrinsics {
            (scan_layer(ALBEDO)?, scan_layer(NORMALS)?)
        } else {
            (BTreeMap::new(), BTreeMap::new())
        };
        let masks = if has_masks {
            scan_layer(MASKS)?
        } else {
            BTreeMap::new()
        };
        if !duplicates.is_empty() {
            return Err(FolderError::DuplicateNames { pairs: duplicates });
        }
        if photos.is_empty() {
            let folder = root.join(PHOTOS.folder);
            let ignored = ignored.iter().filter(|p| p.starts_with(&folder)).count();
            return Err(FolderError::NoPhotos { folder, ignored });
        }
        let mut missing = Vec::new();
        let required: &[(Layer, &BTreeMap<String, PathBuf>)] = if intrinsics {
            &[(ALBEDO, &albedo), (NORMALS, &normals)]
        } else {
            &[]
        };
        for &(layer, files) in required {
            let names: Vec<String> = photos
                .keys()
                .filter(|s| !files.contains_key(*s))
                .cloned()
                .collect();
            if !names.is_empty() {
                missing.push((layer.folder, names));
            }
        }
        let mut orphans = Vec::new();
        for (layer, files) in [(ALBEDO, &albedo), (NORMALS, &normals), (MASKS, &masks)] {
            let names: Vec<String> = files
                .keys()
                .filter(|s| !photos.contains_key(*s))
                .cloned()
                .collect();
            if !names.is_empty() {
                orphans.push((layer.folder, names));
            }
        }
        if !missing.is_empty() || !orphans.is_empty() {
            return Err(FolderError::Unmatched {
                root: root.to_path_buf(),
                missing,
                orphans,
            });
        }
        if !ignored.is_empty() {
            let names: Vec<String> = ignored
                .iter()
                .map(|p| p.strip_prefix(root).unwrap_or(p).display().to_string())
                .collect();
            tracing::warn!(
                "{}: ignoring {} file(s) outside the folder dataset layout: {}",
                root.display(),
                ignored.len(),
                name_list(&names)
            );
        }

        let has_poses = FolderDataset::has_poses_file(root);
        let poses = if has_poses {
            Some(read_poses(&root.join(POSES_FILE), &photos)?)
        } else {
            None
        };
        let entries = photos
            .into_iter()
            .map(|(stem, photo)| SampleFiles {
                intrinsics: intrinsics.then(|| IntrinsicFiles {
                    albedo: albedo[&stem].clone(),
                    normals: normals[&stem].clone(),
                }),
                mask: masks.get(&stem).cloned(),
                pose: poses.as_ref().map_or(Pose::new(0.0, 0.0), |p| p[&stem]),
                stem,
                photo,
            })
            .collect();
        Ok(FolderDataset {
            root: root.to_path_buf(),
            content,
            entries,
            ignored,
            has_poses,
        })
    }

    /// Whether the dataset at `root` has a `poses.csv` (checked without listing it).
    pub fn has_poses_file(root: &Path) -> bool {
        root.join(POSES_FILE).exists()
    }

    /// The dataset's root folder.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Which layers the dataset provides.
    pub fn content(&self) -> FolderContent {
        self.content
    }

    /// The number of samples (at least 1: [`FolderDataset::open`] rejects an empty dataset).
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Always false: [`FolderDataset::open`] rejects an empty dataset.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The samples' names (file stems), sorted.
    pub fn stems(&self) -> impl ExactSizeIterator<Item = &str> + '_ {
        self.entries.iter().map(|e| e.stem.as_str())
    }

    /// The photo file of sample `i`. Panics if `i >= len()`.
    pub fn photo_path(&self, i: usize) -> &Path {
        &self.entries[i].photo
    }

    /// Camera pose of sample `i`. Panics if `i >= len()`.
    pub fn pose(&self, i: usize) -> Pose {
        self.entries[i].pose
    }

    /// Whether sample `i` has a mask file (without one its mask is derived from the normal
    /// map's length). Panics if `i >= len()`.
    pub fn has_mask(&self, i: usize) -> bool {
        self.entries[i].mask.is_some()
    }

    /// Whether the dataset has a `poses.csv` (without one every photo is frontal).
    pub fn has_poses(&self) -> bool {
        self.has_poses
    }

    /// Files in the layout's folders that are not part of it (unknown extensions, folders),
    /// sorted per folder; hidden files are not listed.
    pub fn ignored(&self) -> &[PathBuf] {
        &self.ignored
    }

    /// Decodes sample `i` (module docs: what happens to masks and normals). Panics if
    /// `i >= len()`.
    /// The dataset must provide [`FolderContent::Intrinsics`] (else an error naming the root).
    pub fn load(&self, i: usize) -> Result<FolderSample, FolderError> {
        let entry = &self.entries[i];
        let Some(files) = &entry.intrinsics else {
            return Err(FolderError::NoIntrinsics {
                root: self.root.clone(),
            });
        };
        let PhotoSample {
            photo,
            width,
            height,
            mask,
            ..
        } = self.load_photo(i)?;
        let check_size = |layer: &'static str, path: &Path, raw: &RawImage| {
            check_size(&entry.stem, layer, path, raw, (width, height))
        };

        let raw = io::read_raw(&files.albedo)?;
        check_size("albedo", &files.albedo, &raw)?;
        check_finite(&files.albedo, &raw)?;
        let mut clamped = 0;
        let albedo: Vec<Rgb> = raw
            .texels
            .into_iter()
            .map(|c| {
                let inside = c.map(|v| v.clamp(0.0, 1.0));
                clamped += usize::from(inside != c);
                inside
            })
            .collect();
        if clamped > 0 {
            tracing::warn!(
                "{}: {clamped} pixel(s) outside [0, 1] clamped",
                files.albedo.display()
            );
        }

        let mut normals: Vec<[f32; 3]> = if Format::of(&files.normals)? == Format::Exr {
            let raw = io::read_raw(&files.normals)?;
            check_size("normals", &files.normals, &raw)?;
            check_finite(&files.normals, &raw)?;
            raw.texels
        } else {
            let raw = io::read_encoded(&files.normals)?;
            check_size("normals", &files.normals, &raw)?;
            raw.texels
                .into_iter()
                .map(|c| c.map(|v| 2.0 * v - 1.0))
                .collect()
        };

        let mask: Vec<f32> = match mask {
            Some(mask) => mask,
            None => normals
                .iter()
                .map(|n| f32::from(u8::from(length(*n) > MASK_FROM_NORMAL_LENGTH)))
                .collect(),
        };

        let foreground = mask.iter().filter(|&&m| m > 0.0).count();
        if foreground == 0 {
            return Err(FolderError::NoForeground {
                stem: entry.stem.clone(),
                path: entry.mask.clone().unwrap_or_else(|| files.normals.clone()),
                from_normals: entry.mask.is_none(),
            });
        }
        let away = normals
            .iter()
            .zip(&mask)
            .filter(|(n, m)| **m > 0.0 && length(**n) >= DEGENERATE_LENGTH && n[2] < -0.1)
            .count();
        let (mut renormalised, mut degenerate) = (0, 0);
        for (n, &m) in normals.iter_mut().zip(&mask) {
            let len = length(*n);
            if m <= 0.0 {
                *n = [0.0; 3];
            } else if len < DEGENERATE_LENGTH {
                degenerate += 1;
                *n = [0.0, 0.0, 1.0];
            } else {
                renormalised += usize::from((len - 1.0).abs() > UNIT_TOLERANCE);
                *n = n.map(|v| v / len);
            }
        }

        let percent = |count: usize| 100.0 * count as f64 / foreground as f64;
        if degenerate == foreground {
            return Err(FolderError::BadNormals {
                path: files.normals.clone(),
                reason: "normals have no direction (zero length)",
                percent: 100.0,
            });
        }
        if away as f64 > MAX_AWAY_FRACTION * foreground as f64 {
            return Err(FolderError::BadNormals {
                path: files.normals.clone(),
                reason: "normals face away from the camera",
                percent: percent(away),
            });
        }
        // A grey image (one channel, or three equal ones) decodes to normals along the
        // diagonal (1, 1, 1) alone: not a normal map, though most of it faces the camera.
        if normals
            .iter()
            .zip(&mask)
            .all(|(n, &m)| m <= 0.0 || (n[0] == n[1] && n[1] == n[2]))
        {
            return Err(FolderError::BadNormals {
                path: files.normals.clone(),
                reason: "normals have equal x, y and z (a greyscale image?)",
                percent: 100.0,
            });
        }

        Ok(FolderSample {
            stem: entry.stem.clone(),
            photo,
            image: IntrinsicImage {
                width,
                height,
                albedo,
                normals,
                mask,
                pose: entry.pose,
            },
            renormalised,
            degenerate,
        })
    }
}

impl FolderDataset {
    /// Decodes the photo of sample `i` with its mask file (if any) and pose, and nothing
    /// else: all a photos-only dataset has. Panics if `i >= len()`.
    pub fn load_photo(&self, i: usize) -> Result<PhotoSample, FolderError> {
        let entry = &self.entries[i];
        let photo = io::read_encoded(&entry.photo)?;
        let (width, height) = (photo.width, photo.height);
        let mask = match &entry.mask {
            Some(path) => {
                let raw = io::read_encoded(path)?;
                check_size(&entry.stem, "mask", path, &raw, (width, height))?;
                let mask: Vec<f32> = raw.texels.into_iter().map(|c| c[0]).collect();
                if entry.intrinsics.is_none() && !mask.iter().any(|&m| m > 0.0) {
                    return Err(FolderError::NoForeground {
                        stem: entry.stem.clone(),
                        path: path.clone(),
                        from_normals: false,
                    });
                }
                Some(mask)
            }
            None => None,
        };
        Ok(PhotoSample {
            stem: entry.stem.clone(),
            width,
            height,
            photo: photo.texels,
            mask,
            pose: entry.pose,
        })
    }
}

/// An error unless `raw` (the `layer` of sample `stem`, read from `path`) has the photo's
/// `(width, height)`.
fn check_size(
    stem: &str,
    layer: &'static str,
    path: &Path,
    raw: &RawImage,
    photo: (usize, usize),
) -> Result<(), FolderError> {
    if (raw.width, raw.height) == photo {
        Ok(())
    } else {
        Err(FolderError::SizeMismatch {
            stem: stem.to_string(),
            layer,
            path: path.to_path_buf(),
            size: (raw.width, raw.height),
            photo,
        })
    }
}

/// Whether `path` is a folder: false if nothing is there, an error if a file is.
fn is_folder(path: &Path) -> Result<bool, FolderError> {
    match fs::metadata(path) {
        Ok(m) if m.is_dir() => Ok(true),
        Ok(_) => Err(FolderError::NotAFolder {
            path: path.to_path_buf(),
        }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(false),
        Err(source) => Err(FolderError::Io {
            path: path.to_path_buf(),
            source,
        }),
    }
}

fn length(n: [f32; 3]) -> f32 {
    n.iter().map(|v| v * v).sum::<f32>().sqrt()
}

/// Lists `root/layer.folder`: accepted files by stem; duplicates and ignored files are added
/// to the caller's lists.
fn scan(
    root: &Path,
    layer: Layer,
    duplicates: &mut Vec<(PathBuf, PathBuf)>,
    ignored: &mut Vec<PathBuf>,
) -> Result<BTreeMap<String, PathBuf>, FolderError> {
    let dir = root.join(layer.folder);
    let io_err = |source| FolderError::Io {
        path: dir.clone(),
        source,
    };
    let mut paths = Vec::new();
    for entry in fs::read_dir(&dir).map_err(io_err)? {
        paths.push(entry.map_err(io_err)?.path());
    }
    paths.sort();
    let mut files = BTreeMap::new();
    for path in paths {
        let hidden = path
            .file_name()
            .is_none_or(|n| n.as_encoded_bytes().starts_with(b"."));
        if hidden {
            continue;
        }
        match accepted_stem(&path, layer) {
            Some(stem) => match files.entry(stem) {
                Entry::Vacant(slot) => {
                    slot.insert(path);
                }
                Entry::Occupied(first) => duplicates.push((first.get().clone(), path)),
            },
            None => ignored.push(path),
        }
    }
    Ok(files)
}

/// The stem of `path` if it is a file with one of `layer`'s extensions (any case).
fn accepted_stem(path: &Path, layer: Layer) -> Option<String> {
    let ext = path.extension()?.to_str()?.to_ascii_lowercase();
    if !layer.extensions.contains(&ext.as_str()) || !path.is_file() {
        return None;
    }
    Some(path.file_stem()?.to_str()?.to_owned())
}

/// The first non-finite pixel of an EXR layer, as an error.
fn check_finite(path: &Path, raw: &RawImage) -> Result<(), FolderError> {
    let mut bad = raw
        .texels
        .iter()
        .enumerate()
        .filter(|(_, c)| c.iter().any(|v| !v.is_finite()));
    match bad.next() {
        None => Ok(()),
        Some((i, _)) => Err(FolderError::NonFinite {
            path: path.to_path_buf(),
            count: 1 + bad.count(),
            x: i % raw.width,
            y: i / raw.width,
        }),
    }
}

mod error;
mod poses;
mod write;

pub use error::FolderError;
use error::name_list;
pub use poses::parse_poses;
use poses::read_poses;
use volux_model::pose::Pose;
pub use write::{sample_paths, write_dataset, write_sample};

#[cfg(test)]
mod tests;
