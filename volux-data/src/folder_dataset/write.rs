//! Writing samples as a folder dataset (what `volux data` and the tests make datasets with).

use std::collections::BTreeSet;
use std::fmt::Write as _;
use std::fs;
use std::path::Path;

use volux_envmap::EnvMapError;
use volux_envmap::{durable, io};
use volux_model::pose::Pose;

use super::{ALBEDO, FolderError, FolderSample, MASKS, MAX_YAW, NORMALS, PHOTOS, POSES_FILE};

/// Writes `samples` as a folder dataset at `root`, which must be new or empty: photos and
/// masks as 8-bit PNG, albedo and normals as f32 OpenEXR (lossless), and `poses.csv` with
/// every pose (written exactly). Every file is written atomically (a temporary name, then a
/// rename). All samples are checked before anything is written.
pub fn write_dataset(root: &Path, samples: &[FolderSample]) -> Result<(), FolderError> {
    if samples.is_empty() {
        return Err(FolderError::NothingToWrite {
            root: root.to_path_buf(),
        });
    }
    let mut seen = BTreeSet::new();
    for sample in samples {
        check_sample(sample)?;
        if !seen.insert(sample.stem.as_str()) {
            return Err(FolderError::InvalidSample {
                stem: sample.stem.clone(),
                reason: "two samples have this name".into(),
            });
        }
    }
    let io_err = |path: &Path| {
        let path = path.to_path_buf();
        move |source| FolderError::Io { path, source }
    };
    if root.exists() {
        if !root.is_dir() {
            return Err(FolderError::NotAFolder {
                path: root.to_path_buf(),
            });
        }
        if fs::read_dir(root).map_err(io_err(root))?.next().is_some() {
            return Err(FolderError::NotEmpty {
                path: root.to_path_buf(),
            });
        }
    }
    for layer in [PHOTOS, ALBEDO, NORMALS, MASKS] {
        let dir = root.join(layer.folder);
        fs::create_dir_all(&dir).map_err(io_err(&dir))?;
    }
    let mut csv = String::from("name,yaw,pitch\n");
    for s in samples {
        write_files(root, s)?;
        let Pose { yaw, pitch } = s.image.pose;
        let _ = writeln!(csv, "{},{yaw},{pitch}", s.stem);
    }
    let poses = root.join(POSES_FILE);
    durable::write_atomically(&poses, |tmp| {
        fs::write(tmp, &csv).map_err(|source| EnvMapError::Io {
            path: poses.clone(),
            source,
        })
    })?;
    Ok(())
}

/// Writes one sample's files into the layout under `root` (its folders made if missing):
/// albedo, normals and mask first, the photo last, each atomically, so that a sample whose
/// photo exists is complete. Nothing is written for a sample [`write_dataset`] would refuse.
/// With the pose left out of `poses.csv` (not written here), a folder of such samples is a
/// dataset of frontal photos or, in training, photos with poses from a prior.
pub fn write_sample(root: &Path, sample: &FolderSample) -> Result<(), FolderError> {
    check_sample(sample)?;
    for layer in [PHOTOS, ALBEDO, NORMALS, MASKS] {
        let dir = root.join(layer.folder);
        fs::create_dir_all(&dir).map_err(|source| FolderError::Io {
            path: dir.clone(),
            source,
        })?;
    }
    write_files(root, sample)
}

/// The paths of sample `stem`'s photo, albedo, normals and mask as [`write_sample`] writes them.
pub fn sample_paths(root: &Path, stem: &str) -> [std::path::PathBuf; 4] {
    [
        root.join(PHOTOS.folder).join(format!("{stem}.png")),
        root.join(ALBEDO.folder).join(format!("{stem}.exr")),
        root.join(NORMALS.folder).join(format!("{stem}.exr")),
        root.join(MASKS.folder).join(format!("{stem}.png")),
    ]
}

fn write_files(root: &Path, s: &FolderSample) -> Result<(), FolderError> {
    let to_u8 = |v: f32| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
    let (w, h) = (s.image.width, s.image.height);
    let [photo_path, albedo_path, normals_path, mask_path] = sample_paths(root, &s.stem);
    io::save_exr(&albedo_path, w, h, &s.image.albedo)?;
    io::save_exr(&normals_path, w, h, &s.image.normals)?;
    let mask: Vec<[u8; 3]> = s.image.mask.iter().map(|&m| [to_u8(m); 3]).collect();
    io::save_png(&mask_path, w, h, &mask)?;
    let photo: Vec<[u8; 3]> = s.photo.iter().map(|c| c.map(to_u8)).collect();
    io::save_png(&photo_path, w, h, &photo)?;
    Ok(())
}

/// Why [`write_dataset`] cannot write `sample`, if it cannot.
fn check_sample(sample: &FolderSample) -> Result<(), FolderError> {
    let stem = &sample.stem;
    let invalid = |reason: String| FolderError::InvalidSample {
        stem: stem.clone(),
        reason,
    };
    let bad_char = stem
        .chars()
        .find(|c| matches!(c, '/' | '\\' | ',' | '"') || c.is_control());
    if stem.is_empty() || stem.starts_with('.') || stem.trim() != stem || bad_char.is_some() {
        return Err(invalid(
            "a name must be non-empty, not start with '.' or a space, and hold no '/', '\\', \
             ',', '\"' or control character"
                .into(),
        ));
    }
    let image = &sample.image;
    let pixels = image.width * image.height;
    if sample.photo.len() != pixels {
        return Err(invalid(format!(
            "photo has {} pixels, the image is {}x{}",
            sample.photo.len(),
            image.width,
            image.height
        )));
    }
    if pixels == 0 {
        return Err(invalid("the image is empty".into()));
    }
    if let Some(i) = sample
        .photo
        .iter()
        .position(|c| c.iter().any(|v| !v.is_finite()))
    {
        return Err(invalid(format!(
            "photo has a non-finite value at pixel ({}, {})",
            i % image.width,
            i / image.width
        )));
    }
    image.validate().map_err(|e| invalid(e.to_string()))?;
    let Pose { yaw, pitch } = image.pose;
    if !yaw.is_finite()
        || yaw.abs() > MAX_YAW
        || !pitch.is_finite()
        || pitch.abs() >= std::f64::consts::FRAC_PI_2
    {
        return Err(invalid(format!(
            "pose ({yaw}, {pitch}) must be finite with yaw within [-2 pi, 2 pi] and pitch strictly between -pi/2 and pi/2 (what reading poses.csv accepts)"
        )));
    }
    Ok(())
}
