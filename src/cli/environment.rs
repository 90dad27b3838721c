//! Environment maps named on the command line (files), or shipped ones by name, preconvolved
//! into light maps; shared by `volux sample` and `volux eval`.

use std::path::{Path, PathBuf};

use anyhow::Context;
use volux_data::hdri_collection::BUILTIN_HDRIS;
use volux_envmap::{EnvMap, PreconvolveOptions, io, preconvolve};
use volux_eval::evaluate::Environment;

/// The environment map in `file` (EXR or HDR), or the shipped map `default` when no file is
/// given (so that a command works outside the checkout); with a name to print.
pub fn env_map(file: Option<&Path>, default: &str) -> anyhow::Result<(String, EnvMap)> {
    match file {
        Some(p) => Ok((p.display().to_string(), io::load(p)?)),
        None => {
            let h = BUILTIN_HDRIS
                .iter()
                .find(|h| h.name == default)
                .with_context(|| format!("no shipped environment map is called {default}"))?;
            let map = io::load_bytes(h.bytes, Path::new(h.path))?;
            Ok((format!("the shipped {} map", h.name), map))
        }
    }
}

fn make(name: String, map: EnvMap) -> anyhow::Result<Environment> {
    let lights = preconvolve(&map, &PreconvolveOptions::default())
        .with_context(|| format!("preconvolving {name}"))?;
    Ok(Environment { name, lights })
}

/// The light maps of `files` (EXR or HDR), named by their stems; when none are given, those of
/// the shipped maps `defaults`.
pub fn environments(files: &[PathBuf], defaults: &[&str]) -> anyhow::Result<Vec<Environment>> {
    if files.is_empty() {
        return defaults
            .iter()
            .map(|&name| {
                let h = BUILTIN_HDRIS
                    .iter()
                    .find(|h| h.name == name)
                    .with_context(|| format!("no shipped environment map is called {name}"))?;
                make(h.name.into(), io::load_bytes(h.bytes, Path::new(h.path))?)
            })
            .collect();
    }
    files
        .iter()
        .map(|p| {
            let name = p
                .file_stem()
                .map_or("env".into(), |s| s.to_string_lossy().into_owned());
            make(name, io::load(p)?)
        })
        .collect()
}
