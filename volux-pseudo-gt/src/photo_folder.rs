//! `volux data pseudo-gt --photos DIR --out DATASET`: every photo of a folder centre-cropped to
//! a square, resized to the dataset's side (area averaging in linear light when shrinking),
//! its albedo, normals and mask estimated ([`crate::estimator`]), and the four written as a
//! sample of a folder dataset (`volux_data::folder_dataset`'s layout, no `poses.csv`).
//!
//! - Every file is written atomically and a sample's photo last, so a sample whose four files
//!   exist is complete; a rerun into the same folder keeps those and makes the rest (an
//!   interrupted run resumes). `pseudo_gt.toml` records the side and the estimator; a rerun
//!   with a different side or estimator is refused.
//! - Framing: the model's camera sees a head that covers a known share of the frame, centred.
//!   Each photo's estimated mask is compared with the range the synthetic heads cover at the
//!   dataset camera ([`framing_range`]); photos outside it are reported by name, and every
//!   photo's figures are in `framing.csv`.
//! - A blank photo (no contrast, [`is_blank`]) holds no face: it is left out and named.
//! - `contact_sheet.png`: the first photos with their albedo, normals and mask.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::fs;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use volux_data::folder_dataset::{FolderSample, sample_paths, write_sample};
use volux_data::relighting::IntrinsicImage;
use volux_envmap::io::{self, linear_to_srgb, srgb_to_linear};
use volux_envmap::{LightMapSet, Rgb, durable};
use volux_model::pose::Pose;

use crate::error::PseudoGtError;
use crate::estimator::{Estimate, Estimator};
use crate::sheets;
use crate::synthetic_pairs::{HELD_OUT_FIRST, render_pair};
use crate::weights::EstimatorFile;
use volux_data::resample;

/// The record of a pseudo-ground-truth folder.
pub const RECORD: &str = "pseudo_gt.toml";
/// Photos shown in the contact sheet.
const SHEET_ROWS: usize = 8;
/// Photos estimated together.
const BATCH: usize = 8;
/// Below this standard deviation (sRGB, of each pixel's mean channel) a photo is blank: two
/// 8-bit levels.
pub const BLANK_SD: f64 = 2.0 / 255.0;
/// The largest side of a dataset made here.
pub const MAX_SIDE: usize = 1024;

/// `pseudo_gt.toml`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PseudoGtRecord {
    /// Side of the dataset's images.
    pub resolution: usize,
    /// Where the estimator came from.
    pub estimator: String,
    /// The estimator's working resolution and training steps.
    pub estimator_resolution: usize,
    pub estimator_steps: u64,
}

/// Where a head sits in a frame, from its mask.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Framing {
    /// Share of the frame covered.
    pub coverage: f64,
    /// Centroid of the mask, `(x, y)` in [0, 1] from the top-left.
    pub centre: (f64, f64),
}

/// What synthetic heads at the dataset camera look like, with margins.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FramingRange {
    pub coverage: (f64, f64),
    /// Largest distance of the centroid from the frame's centre.
    pub off_centre: f64,
}

/// The framing of a mask (`side x side`).
pub fn framing(mask: &[f32], side: usize) -> Framing {
    let (mut sum, mut sx, mut sy) = (0.0f64, 0.0f64, 0.0f64);
    for (i, &m) in mask.iter().enumerate() {
        let m = f64::from(m);
        sum += m;
        sx += m * ((i % side) as f64 + 0.5);
        sy += m * ((i / side) as f64 + 0.5);
    }
    let n = (side * side) as f64;
    if sum <= 0.0 {
        return Framing {
            coverage: 0.0,
            centre: (0.5, 0.5),
        };
    }
    Framing {
        coverage: sum / n,
        centre: (sx / sum / side as f64, sy / sum / side as f64),
    }
}

impl FramingRange {
    /// Whether `f` lies in the range.
    pub fn holds(&self, f: &Framing) -> bool {
        let d = ((f.centre.0 - 0.5).powi(2) + (f.centre.1 - 0.5).powi(2)).sqrt();
        (self.coverage.0..=self.coverage.1).contains(&f.coverage) && d <= self.off_centre
    }
}

/// The framing of `count` held-out synthetic heads at 64x64 at the training poses, widened by
/// a quarter of the coverage range on each side and by 0.05 in the centre's distance.
pub fn framing_range(lights: &[LightMapSet], count: usize) -> Result<FramingRange, PseudoGtError> {
    let side = 64;
    let mut all = Vec::with_capacity(count);
    for k in 0..count as u64 {
        let identity = HELD_OUT_FIRST + 1_000_000 + k;
        let pair = render_pair(lights, identity, 0, side, 1)
            .map_err(|source| PseudoGtError::Synthetic { identity, source })?;
        all.push(framing(&pair.mask, side));
    }
    let lo = all.iter().map(|f| f.coverage).fold(f64::INFINITY, f64::min);
    let hi = all.iter().map(|f| f.coverage).fold(0.0, f64::max);
    let off = all
        .iter()
        .map(|f| ((f.centre.0 - 0.5).powi(2) + (f.centre.1 - 0.5).powi(2)).sqrt())
        .fold(0.0, f64::max);
    let margin = 0.25 * (hi - lo);
    Ok(FramingRange {
        coverage: ((lo - margin).max(0.0), (hi + margin).min(1.0)),
        off_centre: off + 0.05,
    })
}

/// The photos of a folder, by stem, in name order; two files with one stem are an error.
pub fn list_photos(dir: &Path) -> Result<Vec<(String, PathBuf)>, PseudoGtError> {
    let io = |source| PseudoGtError::Io {
        path: dir.to_path_buf(),
        source,
    };
    let mut found: BTreeMap<String, PathBuf> = BTreeMap::new();
    for entry in fs::read_dir(dir).map_err(io)? {
        let path = entry.map_err(io)?.path();
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let ext = path
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        if name.starts_with('.')
            || !path.is_file()
            || !["png", "jpg", "jpeg"].contains(&ext.as_str())
        {
            continue;
        }
        let stem = path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        if let Some(other) = found.insert(stem.clone(), path.clone()) {
            return Err(PseudoGtError::Invalid(format!(
                "{} and {} share the name {stem:?}: a dataset matches its layers by name, so keep one",
                other.display(),
                path.display()
            )));
        }
    }
    if found.is_empty() {
        return Err(PseudoGtError::NoPhotos {
            path: dir.to_path_buf(),
        });
    }
    Ok(found.into_iter().collect())
}

/// A photo file as a `side x side` sRGB image: centre-cropped, resized in linear light.
pub fn square_photo(path: &Path, side: usize) -> Result<Vec<Rgb>, PseudoGtError> {
    let raw = io::read_encoded(path)?;
    if raw.width == 0 || raw.height == 0 {
        return Err(PseudoGtError::Invalid(format!(
            "{}: the image is empty",
            path.display()
        )));
    }
    let linear: Vec<Rgb> = raw.texels.iter().map(|t| t.map(srgb_to_linear)).collect();
    let (square, from) = resample::centre_crop(&linear, raw.width, raw.height);
    Ok(resample::resize(&square, from, side)
        .into_iter()
        .map(|t| t.map(linear_to_srgb))
        .collect())
}

/// What [`make_dataset`] did.
#[derive(Clone, Debug, PartialEq)]
pub struct MadeDataset {
    pub photos: usize,
    /// Samples made now.
    pub made: usize,
    /// Samples complete from an earlier run, kept.
    pub kept: usize,
    /// Photos whose head is framed unlike the model's camera, with their framing.
    pub misframed: Vec<(String, Framing)>,
    /// Photos with no contrast ([`is_blank`]), not written.
    pub blank: Vec<String>,
    pub range: FramingRange,
}

/// Makes the folder dataset `out` from the photos in `photos` at `side`, with `estimator`
/// (described by `file`, from `origin`); `lights` light the synthetic heads the framing is
/// compared with; `progress(done, total)` after each batch.
pub fn make_dataset(
    photos: &Path,
    out: &Path,
    side: usize,
    (estimator, file, origin): (&Estimator, &EstimatorFile, &str),
    lights: &[LightMapSet],
    progress: &dyn Fn(usize, usize),
) -> Result<MadeDataset, PseudoGtError> {
    if !(8..=MAX_SIDE).contains(&side) {
        return Err(PseudoGtError::Invalid(format!(
            "resolution {side} must be 8 to {MAX_SIDE} pixels"
        )));
    }
    let list = list_photos(photos)?;
    let record = PseudoGtRecord {
        resolution: side,
        estimator: origin.to_string(),
        estimator_resolution: file.estimator.resolution,
        estimator_steps: file.training.steps,
    };
    let record_path = out.join(RECORD);
    if record_path.is_file() {
        let text = fs::read_to_string(&record_path).map_err(|source| PseudoGtError::Io {
            path: record_path.clone(),
            source,
        })?;
        let earlier: PseudoGtRecord =
            toml::from_str(&text).map_err(|e| PseudoGtError::Description {
                path: record_path.clone(),
                reason: e.to_string(),
            })?;
        if earlier.resolution != side {
            return Err(PseudoGtError::Invalid(format!(
                "{} holds a dataset at {} pixels: give --resolution {} to resume it, or another --out",
                out.display(),
                earlier.resolution,
                earlier.resolution
            )));
        }
        if earlier != record {
            return Err(PseudoGtError::Invalid(format!(
                "{} was made with the estimator {} ({} steps): resume it with that estimator, or give another --out",
                out.display(),
                earlier.estimator,
                earlier.estimator_steps
            )));
        }
    } else if out.exists() && !out.is_dir() {
        return Err(PseudoGtError::Invalid(format!(
            "{} is a file: give a folder for the dataset",
            out.display()
        )));
    } else if out.is_dir()
        && fs::read_dir(out)
            .map_err(|source| PseudoGtError::Io {
                path: out.to_path_buf(),
                source,
            })?
            .next()
            .is_some()
    {
        return Err(PseudoGtError::Invalid(format!(
            "{} is not empty and holds no {RECORD}: give a new or empty folder",
            out.display()
        )));
    }
    fs::create_dir_all(out).map_err(|source| PseudoGtError::Io {
        path: out.to_path_buf(),
        source,
    })?;
    let text = toml::to_string(&record).unwrap_or_default();
    durable::write_atomically(&record_path, |tmp| {
        fs::write(tmp, &text).map_err(|source| PseudoGtError::Io {
            path: record_path.clone(),
            source,
        })
    })?;
    let range = framing_range(lights, 32)?;
    let mut framings: Vec<(String, Framing)> = Vec::with_capacity(list.len());
    let mut sheet_rows: Vec<(Vec<Rgb>, Estimate)> = Vec::new();
    let (mut made, mut kept) = (0, 0);
    let mut blank = Vec::new();
    for (k, chunk) in list.chunks(BATCH).enumerate() {
        let mut todo = Vec::new();
        for (stem, path) in chunk {
            let done = sample_paths(out, stem).iter().all(|p| p.is_file());
            if done && sheet_rows.len() >= SHEET_ROWS {
                kept += 1;
                let mask = io::read_encoded(&sample_paths(out, stem)[3])?;
                let mask: Vec<f32> = mask.texels.iter().map(|t| t[0]).collect();
                framings.push((stem.clone(), framing(&mask, side)));
                continue;
            }
            let photo = square_photo(path, side)?;
            if !done && is_blank(&photo) {
                blank.push(stem.clone());
                continue;
            }
            todo.push((stem.clone(), photo, done));
        }
        let refs: Vec<&[Rgb]> = todo.iter().map(|(_, p, _)| p.as_slice()).collect();
        let estimates = if refs.is_empty() {
            Vec::new()
        } else {
            estimator.estimate(&refs, side, file.estimator.resolution)
        };
        for ((stem, photo, done), estimate) in todo.into_iter().zip(estimates) {
            framings.push((stem.clone(), framing(&estimate.mask, side)));
            if done {
                kept += 1;
            } else {
                write_sample(
                    out,
                    &FolderSample {
                        stem: stem.clone(),
                        photo: photo.clone(),
                        image: IntrinsicImage {
                            width: side,
                            height: side,
                            albedo: estimate.albedo.clone(),
                            normals: estimate.normals.clone(),
                            mask: estimate.mask.clone(),
                            pose: Pose::FRONTAL,
                        },
                        renormalised: 0,
                        degenerate: 0,
                    },
                )?;
                made += 1;
            }
            if sheet_rows.len() < SHEET_ROWS {
                sheet_rows.push((photo, estimate));
            }
        }
        progress(((k + 1) * BATCH).min(list.len()), list.len());
    }
    let rows: Vec<(&[Rgb], &Estimate)> =
        sheet_rows.iter().map(|(p, e)| (p.as_slice(), e)).collect();
    sheets::save_estimates(&out.join("contact_sheet.png"), side, &rows)?;
    let mut csv = String::from("name,coverage,centre_x,centre_y,framed_like_the_camera\n");
    let mut misframed = Vec::new();
    for (stem, f) in &framings {
        let ok = range.holds(f);
        let _ = writeln!(
            csv,
            "{stem},{:.4},{:.4},{:.4},{ok}",
            f.coverage, f.centre.0, f.centre.1
        );
        if !ok {
            misframed.push((stem.clone(), *f));
        }
    }
    if made + kept == 0 {
        return Err(PseudoGtError::Invalid(format!(
            "none of the {} photos in {} holds a face to estimate (all are blank: {}{})",
            list.len(),
            photos.display(),
            blank
                .iter()
                .take(20)
                .cloned()
                .collect::<Vec<_>>()
                .join(", "),
            if blank.len() > 20 { ", ..." } else { "" }
        )));
    }
    let csv_path = out.join("framing.csv");
    durable::write_atomically(&csv_path, |tmp| {
        fs::write(tmp, &csv).map_err(|source| PseudoGtError::Io {
            path: csv_path.clone(),
            source,
        })
    })?;
    Ok(MadeDataset {
        photos: list.len(),
        made,
        kept,
        misframed,
        blank,
        range,
    })
}

/// Whether a photo has (next to) no contrast: the standard deviation of its pixels' mean
/// channel below [`BLANK_SD`]. There is no face in it to estimate.
pub fn is_blank(photo: &[Rgb]) -> bool {
    let n = photo.len().max(1) as f64;
    let values = photo.iter().map(|t| f64::from(t[0] + t[1] + t[2]) / 3.0);
    let mean = values.clone().sum::<f64>() / n;
    let var = values.map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    var.sqrt() < BLANK_SD
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::EstimatorConfig;
    use crate::objective::Accuracy;
    use crate::synthetic_pairs::tests::bank;
    use crate::weights::TrainingRecord;
    use burn::tensor::Device;
    use volux_data::folder_dataset::FolderDataset;

    fn save_srgb(path: &Path, w: usize, h: usize, texels: &[Rgb]) {
        let bytes: Vec<[u8; 3]> = texels
            .iter()
            .map(|t| t.map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8))
            .collect();
        io::save_png(path, w, h, &bytes).unwrap();
    }

    fn tiny_estimator() -> (Estimator, EstimatorFile) {
        let config = EstimatorConfig {
            resolution: 16,
            channels: vec![4, 8],
        };
        let file = EstimatorFile {
            estimator: config.clone(),
            training: TrainingRecord {
                seed: 0,
                steps: 0,
                images: 0,
                seconds: 0.0,
                batch: 1,
                learning_rate: 0.0,
                pool: 0,
                held_out: 0,
            },
            held_out: Accuracy {
                normal_degrees: 0.0,
                albedo_error: 0.0,
                mask_iou: 0.0,
            },
        };
        (config.init(&Device::flex()), file)
    }

    #[test]
    fn photos_are_listed_by_name_and_clashes_or_none_are_errors() {
        let dir = tempfile::tempdir().unwrap();
        let grey = vec![[0.5f32; 3]; 4];
        for name in ["b.JPG", "a.png", ".hidden.png"] {
            let path = dir.path().join(name);
            if name.ends_with("JPG") {
                image::RgbImage::from_pixel(2, 2, image::Rgb([128, 128, 128]))
                    .save_with_format(&path, image::ImageFormat::Jpeg)
                    .unwrap();
            } else {
                save_srgb(&path, 2, 2, &grey);
            }
        }
        fs::write(dir.path().join("notes.txt"), "not a photo").unwrap();
        fs::create_dir(dir.path().join("sub.png")).unwrap();
        let got = list_photos(dir.path()).unwrap();
        let stems: Vec<&str> = got.iter().map(|(s, _)| s.as_str()).collect();
        assert_eq!(stems, ["a", "b"]);

        save_srgb(&dir.path().join("a.jpeg"), 2, 2, &grey);
        let e = list_photos(dir.path()).unwrap_err().to_string();
        assert!(e.contains("a.png") && e.contains("a.jpeg"), "{e}");

        let empty = tempfile::tempdir().unwrap();
        let e = list_photos(empty.path()).unwrap_err();
        assert!(matches!(e, PseudoGtError::NoPhotos { .. }), "{e}");
        let missing = list_photos(&empty.path().join("nope"))
            .unwrap_err()
            .to_string();
        assert!(missing.contains("nope"), "{missing}");
    }

    #[test]
    fn framing_of_a_known_mask() {
        // A 2x2 block in the top-left corner of an 8x8 frame.
        let side = 8;
        let mut mask = vec![0.0f32; side * side];
        for y in 0..2 {
            for x in 0..2 {
                mask[y * side + x] = 1.0;
            }
        }
        let f = framing(&mask, side);
        assert!((f.coverage - 4.0 / 64.0).abs() < 1e-12);
        assert!((f.centre.0 - 1.0 / 8.0).abs() < 1e-12 && (f.centre.1 - 1.0 / 8.0).abs() < 1e-12);
        let empty = framing(&vec![0.0; side * side], side);
        assert_eq!(empty.coverage, 0.0);
        let range = FramingRange {
            coverage: (0.2, 0.6),
            off_centre: 0.1,
        };
        assert!(!range.holds(&f) && !range.holds(&empty));
        assert!(range.holds(&Framing {
            coverage: 0.4,
            centre: (0.55, 0.45)
        }));
    }

    #[test]
    fn the_synthetic_framing_range_holds_held_out_heads() {
        let lights = bank();
        let range = framing_range(&lights, 8).unwrap();
        assert!(
            range.coverage.0 > 0.05 && range.coverage.1 < 0.95,
            "{range:?}"
        );
        assert!(range.off_centre < 0.3, "{range:?}");
        let pair = render_pair(&lights, HELD_OUT_FIRST + 5, 0, 64, 1).unwrap();
        assert!(range.holds(&framing(&pair.mask, 64)));
    }

    #[test]
    fn a_photo_folder_becomes_a_dataset_that_resumes_and_refuses_another_side() {
        let lights = bank();
        let photos = tempfile::tempdir().unwrap();
        // Three held-out heads, one of them in a wider frame: cropped to its centre square.
        for k in 0..3u64 {
            let pair = render_pair(&lights, HELD_OUT_FIRST + k, 1, 32, 1).unwrap();
            if k == 2 {
                let mut wide = vec![[0.2f32; 3]; 48 * 32];
                for y in 0..32 {
                    wide[y * 48 + 8..y * 48 + 40]
                        .copy_from_slice(&pair.photo[y * 32..(y + 1) * 32]);
                }
                save_srgb(&photos.path().join(format!("head{k}.png")), 48, 32, &wide);
            } else {
                save_srgb(
                    &photos.path().join(format!("head{k}.png")),
                    32,
                    32,
                    &pair.photo,
                );
            }
        }
        let wide = square_photo(&photos.path().join("head2.png"), 32).unwrap();
        let narrow = render_pair(&lights, HELD_OUT_FIRST + 2, 1, 32, 1)
            .unwrap()
            .photo;
        let worst = wide
            .iter()
            .zip(&narrow)
            .flat_map(|(a, b)| (0..3).map(move |c| (a[c] - b[c]).abs()))
            .fold(0.0f32, f32::max);
        assert!(worst < 1.0 / 255.0, "cropping moved a pixel by {worst}");

        let (estimator, file) = tiny_estimator();
        let make = |photos: &Path, out: &Path, side: usize, origin: &str| {
            make_dataset(
                photos,
                out,
                side,
                (&estimator, &file, origin),
                &lights,
                &|_, _| {},
            )
        };
        let refused = |photos: &Path, out: &Path, side: usize, origin: &str| {
            make(photos, out, side, origin).unwrap_err().to_string()
        };
        let out = tempfile::tempdir().unwrap();
        let out = out.path().join("dataset");
        let calls = std::cell::Cell::new(0);
        let progress = |done: usize, total: usize| {
            assert!(done <= total && total == 3);
            calls.set(calls.get() + 1);
        };
        let made = make_dataset(
            photos.path(),
            &out,
            24,
            (&estimator, &file, "tiny"),
            &lights,
            &progress,
        )
        .unwrap();
        assert_eq!((made.photos, made.made, made.kept), (3, 3, 0));
        assert!(calls.get() >= 1);
        for k in 0..3 {
            for path in sample_paths(&out, &format!("head{k}")) {
                assert!(path.is_file(), "{}", path.display());
            }
        }
        let photo = io::read_encoded(&sample_paths(&out, "head0")[0]).unwrap();
        assert_eq!((photo.width, photo.height), (24, 24));
        assert!(out.join("contact_sheet.png").is_file());
        let csv = fs::read_to_string(out.join("framing.csv")).unwrap();
        assert_eq!(csv.lines().count(), 4, "{csv}");
        assert!(csv.starts_with("name,coverage"));
        let record: PseudoGtRecord =
            toml::from_str(&fs::read_to_string(out.join(RECORD)).unwrap()).unwrap();
        assert_eq!((record.resolution, record.estimator.as_str()), (24, "tiny"));
        // The layout is the folder dataset's, without poses.csv.
        let listed = FolderDataset::open(&out).unwrap();
        assert_eq!(
            listed.stems().collect::<Vec<_>>(),
            ["head0", "head1", "head2"]
        );
        assert!(!listed.has_poses());

        // An interrupted run (one sample's photo missing) resumes: the rest is kept.
        fs::remove_file(&sample_paths(&out, "head1")[0]).unwrap();
        let again = make(photos.path(), &out, 24, "tiny").unwrap();
        assert_eq!((again.made, again.kept), (1, 2));

        // Another side into the same folder, or a foreign non-empty folder, is refused.
        let e = refused(photos.path(), &out, 32, "tiny");
        assert!(
            e.contains("24 pixels") && e.contains("--resolution 24"),
            "{e}"
        );
        let foreign = tempfile::tempdir().unwrap();
        fs::write(foreign.path().join("mine.txt"), "keep me").unwrap();
        let e = refused(photos.path(), foreign.path(), 24, "tiny");
        assert!(e.contains("not empty"), "{e}");
        let e = refused(photos.path(), &foreign.path().join("mine.txt"), 24, "tiny");
        assert!(e.contains("is a file"), "{e}");
        // Resuming with another estimator would mix two estimators' layers.
        let e = refused(photos.path(), &out, 24, "another");
        assert!(e.contains("estimator tiny"), "{e}");
        // A blank photo is left out and named; the others are kept.
        save_srgb(
            &photos.path().join("blank.png"),
            32,
            32,
            &vec![[0.3; 3]; 32 * 32],
        );
        let again = make(photos.path(), &out, 24, "tiny").unwrap();
        assert_eq!((again.photos, again.made, again.kept), (4, 0, 3));
        assert_eq!(again.blank, ["blank"]);
        assert!(!sample_paths(&out, "blank")[0].exists());
        // A folder of blank photos alone is an error naming them.
        let blanks = tempfile::tempdir().unwrap();
        save_srgb(&blanks.path().join("grey.png"), 8, 8, &vec![[0.5; 3]; 64]);
        let e = refused(blanks.path(), &foreign.path().join("blank_set"), 24, "tiny");
        assert!(e.contains("blank: grey"), "{e}");
        let e = refused(photos.path(), &out, 4, "tiny");
        assert!(e.contains("resolution 4"), "{e}");
    }

    #[test]
    fn blank_photos_have_no_contrast() {
        assert!(is_blank(&vec![[0.5; 3]; 64]));
        // One 8-bit level of noise is blank; a head is not.
        let noisy: Vec<Rgb> = (0..64).map(|i| [0.5 + (i % 2) as f32 / 255.0; 3]).collect();
        assert!(is_blank(&noisy));
        let lights = bank();
        let head = render_pair(&lights, HELD_OUT_FIRST, 0, 32, 1).unwrap();
        assert!(!is_blank(&head.photo));
        assert!(is_blank(&[]));
    }

    #[test]
    fn an_undecodable_photo_is_named() {
        let photos = tempfile::tempdir().unwrap();
        fs::write(photos.path().join("broken.png"), b"not a png").unwrap();
        let e = square_photo(&photos.path().join("broken.png"), 16).unwrap_err();
        let chain = format!(
            "{e}: {}",
            std::error::Error::source(&e)
                .map(|s| s.to_string())
                .unwrap_or_default()
        );
        assert!(chain.contains("broken.png"), "{chain}");
    }
}
