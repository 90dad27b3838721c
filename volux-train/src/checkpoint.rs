//! Checkpoints: one folder per save, `checkpoint-<step>/`, holding the generator, its EMA,
//! the discriminators, both optimisers' states (burnpack files) and `state.toml` (step, image
//! count, the non-finite counters, the seed, the config as written). Nothing else is needed to
//! resume: latents and ray jitter are functions of the seed and the step.
//!
//! A checkpoint is written into a hidden `.checkpoint-<step>.partial/` folder, flushed to the
//! disk (every file, then the folder) and renamed into place once complete, so a crash or a
//! power cut mid-write leaves the previous checkpoints untouched; only the newest `keep` are
//! kept. An old checkpoint is first renamed to a hidden `.checkpoint-<step>.deleting/` and
//! then removed, so a kill during the clean-up never leaves a visible folder without its
//! `state.toml`; the next save removes whatever such leftovers (and stale partial folders) a
//! killed run left behind. Loading refuses weights that hold NaN or infinity, naming the file
//! and the parameter.

use std::fs;
use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::optim::ModuleOptimizer;
use serde::{Deserialize, Serialize};
use volux_model::generator::Generator;

use crate::networks::{Discriminators, first_non_finite};
use volux_envmap::durable::{sync_dir, sync_file};

/// Bumped when the layout changes.
pub const CHECKPOINT_FORMAT: u32 = 1;

const GENERATOR: &str = "generator.bpk";
pub const GENERATOR_EMA: &str = "generator_ema.bpk";
const DISCRIMINATORS: &str = "discriminators.bpk";
const OPTIMIZER_G: &str = "optimizer_g.bpk";
const OPTIMIZER_D: &str = "optimizer_d.bpk";
pub const STATE: &str = "state.toml";
const PREFIX: &str = "checkpoint-";
/// Every file a checkpoint folder holds.
const FILES: [&str; 6] = [
    GENERATOR,
    GENERATOR_EMA,
    DISCRIMINATORS,
    OPTIMIZER_G,
    OPTIMIZER_D,
    STATE,
];

/// Why a checkpoint cannot be written or read.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("{}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}", path.display())]
    ReadState {
        path: PathBuf,
        #[source]
        source: toml::de::Error,
    },
    #[error("{}", path.display())]
    WriteState {
        path: PathBuf,
        #[source]
        source: toml::ser::Error,
    },
    #[error("{}: checkpoint format {found} (this program reads {CHECKPOINT_FORMAT})", path.display())]
    Format { path: PathBuf, found: u32 },
    /// Burn cannot write, read or apply a network's or an optimiser's record.
    #[error("{}", path.display())]
    Record {
        path: PathBuf,
        #[source]
        source: burn::store::RecordError,
    },
    #[error("no complete checkpoint in {0}")]
    None(PathBuf),
    #[error(
        "{path}: parameter `{parameter}` holds NaN or infinity: the file is damaged; resume or sample from an older checkpoint of the run"
    )]
    NonFinite { path: PathBuf, parameter: String },
    /// An optimiser state that a loaded run must not step with (Burn's loader panics on a
    /// tensor without a parameter id, and NaN moments make every step non-finite).
    #[error(
        "{path}: optimiser state `{tensor}` {problem}: the file is damaged; resume from an older checkpoint of the run"
    )]
    OptimizerState {
        path: PathBuf,
        tensor: String,
        problem: &'static str,
    },
    #[error(
        "checkpoint {path} was written by a run with other shapes:\n  checkpoint: {checkpoint}\n  config:     {config}"
    )]
    Mismatch {
        path: PathBuf,
        checkpoint: String,
        config: String,
    },
}

fn file_error(path: &Path, source: std::io::Error) -> CheckpointError {
    CheckpointError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn record_error(path: &Path, source: burn::store::RecordError) -> CheckpointError {
    CheckpointError::Record {
        path: path.to_path_buf(),
        source,
    }
}

/// Training progress and what it was trained from (`state.toml`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainState {
    pub format: u32,
    /// Steps taken (skipped ones included): the next batch's index.
    pub step: u64,
    /// Images trained on (skipped steps excluded): what the schedule follows.
    pub images: u64,
    /// Non-finite steps in a row at the time of the save.
    pub nonfinite_in_row: usize,
    /// Non-finite steps in all.
    pub skipped: u64,
    /// The run's seed (latents and ray jitter of step `s` derive from it and `s`).
    pub seed: u64,
    /// Wall-clock seconds the run has trained so far, over all its invocations (grids,
    /// checkpoints and evaluations included). Absent from checkpoints older than the field.
    #[serde(default)]
    pub seconds: f64,
    /// `[model]` as TOML: every tensor's shape follows from it.
    pub shapes: String,
    /// The discriminators that exist.
    pub discriminators: Vec<String>,
    /// The config file's path when training started, and its text.
    pub config_path: PathBuf,
    pub config: String,
    /// The config with every default filled in ([`crate::config::TrainConfig::resolved`]), as
    /// this invocation of the run used it. Empty in checkpoints older than the field.
    #[serde(default)]
    pub resolved_config: String,
}

/// The networks and optimiser states a checkpoint holds.
pub struct Networks {
    pub g: Generator,
    pub ema: Generator,
    pub d: Discriminators,
    pub opt_g: ModuleOptimizer,
    pub opt_d: ModuleOptimizer,
}

/// The step number in a checkpoint folder's name, if it is one.
fn step_of(name: &str) -> Option<u64> {
    name.strip_prefix(PREFIX)?.parse().ok()
}

/// Whether `name` is a checkpoint folder's name (`checkpoint-<step>`, or its partial
/// `checkpoint-<step>.partial` without the leading dot).
pub fn is_checkpoint_name(name: &str) -> bool {
    step_of(name.trim_end_matches(".partial")).is_some()
}

/// Complete checkpoints under `root`, oldest first.
pub fn list(root: &Path) -> Vec<(u64, PathBuf)> {
    let Ok(entries) = fs::read_dir(root) else {
        return Vec::new();
    };
    let mut found: Vec<(u64, PathBuf)> = entries
        .filter_map(|e| {
            let e = e.ok()?;
            let step = step_of(e.file_name().to_str()?)?;
            e.path().join(STATE).is_file().then(|| (step, e.path()))
        })
        .collect();
    found.sort();
    found
}

/// The newest complete checkpoint under `root`.
pub fn latest(root: &Path) -> Result<PathBuf, CheckpointError> {
    list(root)
        .pop()
        .map(|(_, p)| p)
        .ok_or_else(|| CheckpointError::None(root.to_path_buf()))
}

/// `path` itself if it is a checkpoint, else the newest checkpoint in it (a run folder).
pub fn resolve(path: &Path) -> Result<PathBuf, CheckpointError> {
    if path.join(STATE).is_file() {
        Ok(path.to_path_buf())
    } else {
        latest(path)
    }
}

/// What a killed run can leave in a run folder: hidden `.checkpoint-<step>.partial/` and
/// `.checkpoint-<step>.deleting/` folders, and (from before deletions were renamed first)
/// visible `checkpoint-<step>/` folders without `state.toml` that hold nothing but checkpoint
/// files.
fn leftovers(root: &Path) -> Vec<PathBuf> {
    let Ok(entries) = fs::read_dir(root) else {
        return Vec::new();
    };
    entries
        .filter_map(|e| {
            let e = e.ok()?;
            let name = e.file_name().to_str()?.to_string();
            let path = e.path();
            if !path.is_dir() {
                return None;
            }
            let hidden = name
                .strip_prefix('.')
                .and_then(|n| n.strip_suffix(".partial").or(n.strip_suffix(".deleting")))
                .is_some_and(|n| step_of(n).is_some());
            let half_deleted = step_of(&name).is_some()
                && !path.join(STATE).exists()
                && fs::read_dir(&path).is_ok_and(|files| {
                    files.filter_map(Result::ok).all(|f| {
                        f.file_name()
                            .to_str()
                            .is_some_and(|n| FILES.contains(&n) && n != STATE)
                    })
                });
            (hidden || half_deleted).then_some(path)
        })
        .collect()
}

/// Removes a checkpoint folder: renamed to a hidden `.<name>.deleting` first, so that it stops
/// being a checkpoint at once, then deleted.
fn remove(dir: &Path) -> Result<(), CheckpointError> {
    let name = dir.file_name().and_then(|n| n.to_str()).unwrap_or_default();
    let doomed = dir.with_file_name(format!(".{name}.deleting"));
    fs::rename(dir, &doomed).map_err(|e| file_error(dir, e))?;
    fs::remove_dir_all(&doomed).map_err(|e| file_error(&doomed, e))
}

/// Writes a checkpoint of `state` under `root` and deletes all but the newest `keep`.
pub fn save(
    root: &Path,
    state: &TrainState,
    nets: &Networks,
    keep: usize,
) -> Result<PathBuf, CheckpointError> {
    fs::create_dir_all(root).map_err(|e| file_error(root, e))?;
    for stale in leftovers(root) {
        fs::remove_dir_all(&stale).map_err(|e| file_error(&stale, e))?;
    }
    let name = format!("{PREFIX}{:08}", state.step);
    let partial = root.join(format!(".{name}.partial"));
    let done = root.join(&name);
    fs::create_dir(&partial).map_err(|e| file_error(&partial, e))?;
    let write = || -> Result<(), CheckpointError> {
        let record =
            |p: &Path, r: Result<(), burn::store::RecordError>| r.map_err(|e| record_error(p, e));
        let p = partial.join(GENERATOR);
        record(&p, nets.g.clone().save_file(&p))?;
        let p = partial.join(GENERATOR_EMA);
        record(&p, nets.ema.clone().save_file(&p))?;
        let p = partial.join(DISCRIMINATORS);
        record(&p, nets.d.clone().save_file(&p))?;
        let p = partial.join(OPTIMIZER_G);
        record(&p, nets.opt_g.save(&p))?;
        let p = partial.join(OPTIMIZER_D);
        record(&p, nets.opt_d.save(&p))?;
        // The state goes last: a folder with state.toml is complete.
        let p = partial.join(STATE);
        let text = toml::to_string(state).map_err(|source| CheckpointError::WriteState {
            path: p.clone(),
            source,
        })?;
        fs::write(&p, text).map_err(|e| file_error(&p, e))?;
        for file in FILES {
            let p = partial.join(file);
            sync_file(&p).map_err(|e| file_error(&p, e))?;
        }
        sync_dir(&partial).map_err(|e| file_error(&partial, e))?;
        if done.exists() {
            remove(&done)?;
        }
        fs::rename(&partial, &done).map_err(|e| file_error(&done, e))?;
        sync_dir(root).map_err(|e| file_error(root, e))
    };
    if let Err(e) = write() {
        let _ = fs::remove_dir_all(&partial);
        return Err(e);
    }
    let all = list(root);
    for (_, old) in all.iter().take(all.len().saturating_sub(keep)) {
        remove(old)?;
    }
    sync_dir(root).map_err(|e| file_error(root, e))?;
    Ok(done)
}

/// Reads a checkpoint's `state.toml`.
pub fn read_state(dir: &Path) -> Result<TrainState, CheckpointError> {
    let p = dir.join(STATE);
    let text = fs::read_to_string(&p).map_err(|e| file_error(&p, e))?;
    parse_state(&text, &p)
}

/// Checks the text of a `state.toml` (read from `path`): its fields and its format version.
pub fn parse_state(text: &str, path: &Path) -> Result<TrainState, CheckpointError> {
    let state: TrainState = toml::from_str(text).map_err(|source| CheckpointError::ReadState {
        path: path.to_path_buf(),
        source,
    })?;
    if state.format != CHECKPOINT_FORMAT {
        return Err(CheckpointError::Format {
            path: path.to_path_buf(),
            found: state.format,
        });
    }
    Ok(state)
}

/// Loads the checkpoint in `dir` into networks of the same shapes (freshly built from the same
/// config): every parameter and optimiser state is replaced.
pub fn load(dir: &Path, nets: Networks) -> Result<Networks, CheckpointError> {
    let module = |name: &str| {
        let p = dir.join(name);
        burn::store::ModuleRecord::load(&p).map_err(|e| record_error(&p, e))
    };
    let apply = |name: &str, e: burn::store::RecordError| record_error(&dir.join(name), e);
    let g = nets
        .g
        .try_load_record(module(GENERATOR)?)
        .map_err(|e| apply(GENERATOR, e))?;
    let ema = nets
        .ema
        .try_load_record(module(GENERATOR_EMA)?)
        .map_err(|e| apply(GENERATOR_EMA, e))?;
    let d = nets
        .d
        .try_load_record(module(DISCRIMINATORS)?)
        .map_err(|e| apply(DISCRIMINATORS, e))?;
    finite(dir.join(GENERATOR), &g)?;
    finite(dir.join(GENERATOR_EMA), &ema)?;
    finite(dir.join(DISCRIMINATORS), &d)?;
    let opt = |o: ModuleOptimizer, name: &str| {
        let p = dir.join(name);
        check_optimizer_state(&p)?;
        o.load(&p).map_err(|e| record_error(&p, e))
    };
    Ok(Networks {
        g,
        ema,
        d,
        opt_g: opt(nets.opt_g, OPTIMIZER_G)?,
        opt_d: opt(nets.opt_d, OPTIMIZER_D)?,
    })
}

/// Loads only the EMA generator (what sampling needs) into `ema`.
pub fn load_ema(dir: &Path, ema: Generator) -> Result<Generator, CheckpointError> {
    let p = dir.join(GENERATOR_EMA);
    let ema = ema.try_load_file(&p).map_err(|e| record_error(&p, e))?;
    finite(dir.join(GENERATOR_EMA), &ema)?;
    Ok(ema)
}

/// Loads an EMA generator from the bytes of a `generator_ema.bpk` (a model embedded in the
/// binary); `origin` names it in errors.
pub fn load_ema_bytes(
    origin: &Path,
    bytes: &[u8],
    ema: Generator,
) -> Result<Generator, CheckpointError> {
    let record =
        burn::store::ModuleRecord::from_bytes(burn::tensor::Bytes::from_bytes_vec(bytes.to_vec()))
            .map_err(|e| record_error(origin, e))?;
    let ema = ema
        .try_load_record(record)
        .map_err(|e| record_error(origin, e))?;
    finite(origin.to_path_buf(), &ema)?;
    Ok(ema)
}

/// Refuses an optimiser state file with a tensor that carries no parameter id or holds NaN or
/// infinity, before Burn loads it.
fn check_optimizer_state(path: &Path) -> Result<(), CheckpointError> {
    let pack = |e: burn_pack::Error| record_error(path, e.into());
    // Read whole: a file-backed reader reads tensors lazily and panics if that read fails.
    let bytes = fs::read(path).map_err(|e| file_error(path, e))?;
    let tensors = burn_pack::Reader::from_bytes(burn_pack::Bytes::from_bytes_vec(bytes))
        .and_then(burn_pack::Reader::into_tensors)
        .map_err(pack)?;
    for tensor in tensors {
        let (name, dtype, _, param_id, bytes) = tensor.into_parts().map_err(pack)?;
        let bad = |problem| {
            Err(CheckpointError::OptimizerState {
                path: path.to_path_buf(),
                tensor: name.clone(),
                problem,
            })
        };
        if param_id.is_none() {
            return bad("carries no parameter id");
        }
        let finite = match dtype {
            burn_pack::DType::F32 => bytes
                .chunks_exact(4)
                .all(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]).is_finite()),
            burn_pack::DType::F64 => bytes.chunks_exact(8).all(|b| {
                f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]).is_finite()
            }),
            _ => true,
        };
        if !finite {
            return bad("holds NaN or infinity");
        }
    }
    Ok(())
}

/// Refuses a loaded module with a NaN or an infinity in any parameter.
fn finite<M: Module>(path: PathBuf, module: &M) -> Result<(), CheckpointError> {
    match first_non_finite(module) {
        None => Ok(()),
        Some(parameter) => Err(CheckpointError::NonFinite { path, parameter }),
    }
}
