//! A trained estimator on disk: `estimator.bpk` (Burn's record of the weights) and
//! `estimator.toml` (its shape, how it was trained, its held-out accuracy), written atomically,
//! the description last; and the one shipped in `assets/estimator/` and embedded in the binary,
//! so that `volux data pseudo-gt` works with no training and no files beside it.

use std::fs;
use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::tensor::Device;
use serde::{Deserialize, Serialize};
use volux_envmap::durable;
use volux_train::networks::first_non_finite;

use crate::error::PseudoGtError;
use crate::estimator::{Estimator, EstimatorConfig};
use crate::objective::Accuracy;

/// The weights' file name in an estimator folder.
pub const WEIGHTS: &str = "estimator.bpk";
/// The description's file name in an estimator folder.
pub const DESCRIPTION: &str = "estimator.toml";

/// How an estimator was trained.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainingRecord {
    pub seed: u64,
    pub steps: u64,
    pub images: u64,
    pub seconds: f64,
    pub batch: usize,
    pub learning_rate: f64,
    /// Training pairs rendered (identities `0..pool`).
    pub pool: usize,
    /// Held-out identities measured (from `HELD_OUT_FIRST` on).
    pub held_out: usize,
}

/// `estimator.toml`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EstimatorFile {
    pub estimator: EstimatorConfig,
    pub training: TrainingRecord,
    /// Accuracy on the held-out identities at the working resolution when it was saved.
    pub held_out: Accuracy,
}

/// Writes `estimator` and its description into `dir` (created if missing), each atomically,
/// the description last.
pub fn save(dir: &Path, estimator: &Estimator, file: &EstimatorFile) -> Result<(), PseudoGtError> {
    fs::create_dir_all(dir).map_err(|source| PseudoGtError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let weights = dir.join(WEIGHTS);
    durable::write_atomically(&weights, |tmp| {
        estimator
            .clone()
            .save_file(tmp)
            .map_err(|source| PseudoGtError::Weights {
                path: weights.clone(),
                source,
            })
    })?;
    let description = dir.join(DESCRIPTION);
    let text = toml::to_string(file).map_err(|e| PseudoGtError::Description {
        path: description.clone(),
        reason: e.to_string(),
    })?;
    durable::write_atomically(&description, |tmp| {
        fs::write(tmp, &text).map_err(|source| PseudoGtError::Io {
            path: description.clone(),
            source,
        })
    })
}

fn parse(path: &Path, text: &str) -> Result<EstimatorFile, PseudoGtError> {
    let file: EstimatorFile = toml::from_str(text).map_err(|e| PseudoGtError::Description {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })?;
    file.estimator
        .check()
        .map_err(|reason| PseudoGtError::Description {
            path: path.to_path_buf(),
            reason: format!("[estimator] {reason}"),
        })?;
    Ok(file)
}

fn finish(
    origin: &Path,
    file: EstimatorFile,
    record: Result<burn::store::ModuleRecord, burn::store::RecordError>,
    device: &Device,
) -> Result<(Estimator, EstimatorFile), PseudoGtError> {
    let weights = |source| PseudoGtError::Weights {
        path: origin.to_path_buf(),
        source,
    };
    let estimator = file
        .estimator
        .init(device)
        .try_load_record(record.map_err(weights)?)
        .map_err(weights)?;
    if let Some(parameter) = first_non_finite(&estimator) {
        return Err(PseudoGtError::NonFinite {
            path: origin.to_path_buf(),
            parameter,
        });
    }
    Ok((estimator, file))
}

/// The estimator saved in `dir`, on `device`.
pub fn load(dir: &Path, device: &Device) -> Result<(Estimator, EstimatorFile), PseudoGtError> {
    let description = dir.join(DESCRIPTION);
    let text = fs::read_to_string(&description).map_err(|source| PseudoGtError::Io {
        path: description.clone(),
        source,
    })?;
    let file = parse(&description, &text)?;
    let weights = dir.join(WEIGHTS);
    if !weights.is_file() {
        return Err(PseudoGtError::Io {
            path: weights,
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "no weights"),
        });
    }
    let record = burn::store::ModuleRecord::load(&weights);
    finish(&weights, file, record, device)
}
/// The shipped estimator's folder in the repository.
pub const SHIPPED_FOLDER: &str = "assets/estimator";

/// The estimator shipped in the binary, on `device`.
pub fn shipped(device: &Device) -> Result<(Estimator, EstimatorFile), PseudoGtError> {
    let origin = PathBuf::from(SHIPPED_FOLDER);
    let file = parse(
        &origin.join(DESCRIPTION),
        include_str!("../../assets/estimator/estimator.toml"),
    )?;
    let bytes = include_bytes!("../../assets/estimator/estimator.bpk");
    let record =
        burn::store::ModuleRecord::from_bytes(burn::tensor::Bytes::from_bytes_vec(bytes.to_vec()));
    finish(&origin.join(WEIGHTS), file, record, device)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::augmentation::AugmentationRanges;
    use crate::synthetic_pairs::collection_lights;
    use crate::training::{held_out_inputs, measure};

    /// The shipped weights give the held-out accuracy their description records (measured as
    /// training measured it: every environment of the default collection, the default
    /// augmentations, the working resolution, the recorded seed and count).
    #[test]
    fn the_shipped_estimator_reproduces_its_recorded_accuracy() {
        let (estimator, file) = shipped(&Device::flex()).unwrap();
        let lights = collection_lights().unwrap();
        let side = file.estimator.resolution;
        let t = &file.training;
        let inputs = held_out_inputs(
            &lights,
            t.held_out,
            t.seed,
            side,
            1,
            &AugmentationRanges::default(),
        )
        .unwrap();
        let got = measure(&estimator, &inputs, side);
        let want = &file.held_out;
        assert!(
            (got.normal_degrees - want.normal_degrees).abs() < 0.01,
            "{got:?} vs {want:?}"
        );
        assert!(
            (got.albedo_error - want.albedo_error).abs() < 1e-4,
            "{got:?} vs {want:?}"
        );
        assert!(
            (got.mask_iou - want.mask_iou).abs() < 1e-4,
            "{got:?} vs {want:?}"
        );
    }

    #[test]
    fn bad_folders_are_named() {
        let device = Device::flex();
        let (estimator, file) = shipped(&device).unwrap();
        let dir = tempfile::tempdir().unwrap();
        save(dir.path(), &estimator, &file).unwrap();
        let (_, loaded) = load(dir.path(), &device).unwrap();
        assert_eq!(loaded, file);

        let description = dir.path().join(DESCRIPTION);
        let text = fs::read_to_string(&description).unwrap();
        fs::write(
            &description,
            text.replace("[estimator]", "[estimator]\nchanels = [8]"),
        )
        .unwrap();
        let e = load(dir.path(), &device).unwrap_err().to_string();
        assert!(e.contains("estimator.toml") && e.contains("chanels"), "{e}");
        fs::write(
            &description,
            text.replace("resolution = 128", "resolution = 100"),
        )
        .unwrap();
        let e = load(dir.path(), &device).unwrap_err().to_string();
        assert!(e.contains("resolution = 100"), "{e}");
        // A description whose shape differs from the weights.
        fs::write(
            &description,
            text.replace("[16, 32, 64, 128, 128]", "[16, 32, 64, 128, 64]"),
        )
        .unwrap();
        let e = load(dir.path(), &device).unwrap_err();
        assert!(matches!(e, PseudoGtError::Weights { .. }), "{e}");

        fs::write(&description, &text).unwrap();
        fs::write(dir.path().join(WEIGHTS), b"truncated").unwrap();
        let e = load(dir.path(), &device).unwrap_err();
        assert!(e.to_string().contains("estimator.bpk"), "{e}");
        fs::remove_file(dir.path().join(WEIGHTS)).unwrap();
        let e = load(dir.path(), &device).unwrap_err().to_string();
        assert!(e.contains("estimator.bpk"), "{e}");
    }
}
