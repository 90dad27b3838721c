//! Trained generators to sample and evaluate: checkpoints on disk, and the models shipped in
//! `assets/models/<name>/` and embedded in the binary, so that `volux sample --checkpoint
//! quickstart` shows samples on a fresh machine with no training and no files beside the
//! binary.
//!
//! A shipped model is a checkpoint folder cut down to what sampling needs: its `state.toml`
//! (the config it was trained from, the image count) and its EMA generator. How each was
//! trained, and its `volux eval` numbers, are in `assets/models/README.md`.

use std::path::{Path, PathBuf};

use burn::tensor::Device;
use volux_model::backend::BackendKind;
use volux_model::generator::Generator;

use crate::checkpoint::{self, CheckpointError, TrainState};
use crate::config::TrainConfig;
use crate::training_loop::TrainError;

/// A model shipped in the binary.
#[derive(Debug)]
pub struct ShippedModel {
    /// What `--checkpoint` takes.
    pub name: &'static str,
    /// Its folder in the repository.
    pub folder: &'static str,
    /// One line on what it is.
    pub about: &'static str,
    state: &'static str,
    generator_ema: &'static [u8],
}

/// The shipped models.
pub const SHIPPED: &[ShippedModel] = &[ShippedModel {
    name: "quickstart",
    folder: "assets/models/quickstart",
    about: "configs/quickstart.toml, 30 minutes on 2 CPU cores (9.0 kimg): faces in the geometry (brow, eye sockets, nose, mouth), one face shape for every seed, SWD within 2x of the data's",
    state: include_str!("../../assets/models/quickstart/state.toml"),
    generator_ema: include_bytes!("../../assets/models/quickstart/generator_ema.bpk"),
}];

/// The shipped model called `name`.
pub fn shipped(name: &str) -> Option<&'static ShippedModel> {
    SHIPPED.iter().find(|m| m.name == name)
}

/// A generator ready to sample: the EMA weights, the config and state it was trained with,
/// where it came from, and the device it runs on.
pub struct TrainedGenerator {
    pub g: Generator,
    pub config: TrainConfig,
    pub state: TrainState,
    /// The checkpoint folder, or the shipped model's folder.
    pub origin: PathBuf,
    pub device: Device,
}

impl TrainedGenerator {
    /// Builds the generator `state`'s config describes on `backend` and fills it with `load`
    /// (the EMA weights from a file or from embedded bytes).
    fn build(
        state: TrainState,
        origin: PathBuf,
        backend: BackendKind,
        load: impl FnOnce(Generator) -> Result<Generator, CheckpointError>,
    ) -> Result<Self, TrainError> {
        let config = TrainConfig::from_text(state.config.clone(), &state.config_path)?;
        let device = backend.device()?;
        let mut g = load(config.generator().init(&device)?)?;
        // The field as trained: the encoding's octaves open as far as the schedule had
        // opened them at the checkpoint's images.
        g.set_octave_window(config.octave_window(state.images));
        Ok(TrainedGenerator {
            g,
            config,
            state,
            origin,
            device,
        })
    }
}

impl ShippedModel {
    /// Parses the embedded state and loads the embedded EMA generator.
    pub fn load(&self, backend: BackendKind) -> Result<TrainedGenerator, TrainError> {
        let origin = PathBuf::from(self.folder);
        let state = checkpoint::parse_state(self.state, &origin.join(checkpoint::STATE))?;
        let weights = origin.join(checkpoint::GENERATOR_EMA);
        TrainedGenerator::build(state, origin, backend, |g| {
            checkpoint::load_ema_bytes(&weights, self.generator_ema, g)
        })
    }
}

/// The EMA generator at `checkpoint`: a checkpoint folder, a run folder (its newest
/// checkpoint), or the name of a shipped model ([`SHIPPED`]) when no such folder exists.
pub fn load_for_sampling(
    checkpoint: &Path,
    backend: BackendKind,
) -> Result<TrainedGenerator, TrainError> {
    if !checkpoint.exists() {
        return match checkpoint.to_str().and_then(shipped) {
            Some(model) => model.load(backend),
            None => Err(TrainError::NoCheckpoint {
                path: checkpoint.to_path_buf(),
                shipped: SHIPPED
                    .iter()
                    .map(|m| m.name)
                    .collect::<Vec<_>>()
                    .join(", "),
            }),
        };
    }
    let dir = checkpoint::resolve(checkpoint)?;
    let state = checkpoint::read_state(&dir)?;
    TrainedGenerator::build(state, dir.clone(), backend, |g| {
        checkpoint::load_ema(&dir, g)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_shipped_state_of_another_checkpoint_format_is_refused_naming_its_file() {
        for model in SHIPPED {
            let path = Path::new(model.folder).join(checkpoint::STATE);
            let state = checkpoint::parse_state(model.state, &path).unwrap();
            assert_eq!(state.format, checkpoint::CHECKPOINT_FORMAT);
            let other = model.state.replacen(
                &format!("format = {}", state.format),
                &format!("format = {}", state.format + 1),
                1,
            );
            assert_ne!(other, model.state, "the state names its format");
            let e = checkpoint::parse_state(&other, &path).unwrap_err();
            assert!(
                matches!(e, CheckpointError::Format { found, .. } if found == state.format + 1),
                "{e}"
            );
            assert!(e.to_string().contains("state.toml"), "{e}");
        }
    }

    #[test]
    fn every_shipped_model_loads_with_finite_weights_and_its_config() {
        for model in SHIPPED {
            let t = model.load(BackendKind::Cpu).unwrap();
            assert!(t.state.images > 0, "{}", model.name);
            assert_eq!(t.origin, Path::new(model.folder));
            // The shipped files are a checkpoint folder: the same model loads from disk.
            let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
            let disk = load_for_sampling(&root.join(model.folder), BackendKind::Cpu).unwrap();
            assert_eq!(disk.state, t.state);
            assert_eq!(
                crate::networks::first_non_finite(&t.g),
                None,
                "{}",
                model.name
            );
        }
    }

    #[test]
    fn an_unknown_name_is_an_error_listing_the_shipped_models() {
        let e = load_for_sampling(Path::new("no-such-model"), BackendKind::Cpu)
            .map(drop)
            .expect_err("refused");
        let message = e.to_string();
        assert!(
            message.contains("no-such-model") && message.contains("quickstart"),
            "{message}"
        );
    }
}
