//! Errors of volux-envmap. Every variant names where the bad data came from (a file path, or
//! "in-memory map") and what is wrong with it.

use std::path::PathBuf;

/// A cause of any error type (an image codec's, a config table's, an evaluation's): the one
/// boxed error every crate uses.
pub type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// What went wrong reading, validating, writing or convolving an environment map.
#[derive(Debug, thiserror::Error)]
pub enum EnvMapError {
    /// The file could not be opened, read or written.
    #[error("{}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The file extension is not one we read or write.
    #[error(
        "{}: unsupported file type (expected .exr, .hdr, .png, .jpg or .jpeg)",
        path.display()
    )]
    UnsupportedFormat { path: PathBuf },
    /// The decoder rejected the file (truncated, corrupt, or a variant it does not support).
    #[error("{}: cannot decode {format} image", path.display())]
    Decode {
        path: PathBuf,
        format: &'static str,
        #[source]
        source: BoxError,
    },
    /// The decoder refused to allocate what the file's header asks for.
    #[error(
        "{}: the {format} image is larger than volux reads (at most {max} texels)",
        path.display()
    )]
    DecodeLimit {
        path: PathBuf,
        format: &'static str,
        max: usize,
        #[source]
        source: BoxError,
    },
    /// The encoder failed.
    #[error("{}: cannot encode {format} image", path.display())]
    Encode {
        path: PathBuf,
        format: &'static str,
        #[source]
        source: BoxError,
    },
    /// The image has no texels.
    #[error("{origin}: empty image ({width}x{height})")]
    Empty {
        origin: String,
        width: usize,
        height: usize,
    },
    /// Equirectangular maps are twice as wide as they are tall.
    #[error(
        "{origin}: {width}x{height} is not an equirectangular map (width must be exactly 2 x height)"
    )]
    AspectRatio {
        origin: String,
        width: usize,
        height: usize,
    },
    /// The buffer does not hold width x height RGB texels.
    #[error("{origin}: expected {expected} RGB texels for {width}x{height}, got {actual}")]
    BufferSize {
        origin: String,
        width: usize,
        height: usize,
        expected: usize,
        actual: usize,
    },
    /// A texel brighter than [`crate::envmap::MAX_RADIANCE`]: finite, but shading with it would
    /// overflow f32 (infinite light maps, black relit images).
    #[error(
        "{origin}: texel x={x}, y={y} has radiance {value:e}, above the largest accepted ({max:e}; real maps, suns included, are far below): is the file scaled or corrupt?"
    )]
    TooBright {
        origin: String,
        value: f32,
        x: usize,
        y: usize,
        max: f32,
    },
    /// NaN or infinite texel values: there is no sensible light to take from them.
    #[error(
        "{origin}: {count} texel values are NaN or infinite (first at texel x={x}, y={y}); fix or re-export the map"
    )]
    NonFinite {
        origin: String,
        count: usize,
        x: usize,
        y: usize,
    },
    /// A Phong exponent outside what the light maps support.
    #[error("Phong exponent {exponent} is out of range (1..={max})")]
    Exponent { exponent: u32, max: u32 },
    /// A list of exponents with nothing in it, or a repeated one.
    #[error("exponent list {0:?} is empty or has repeats")]
    ExponentList(Vec<u32>),
    /// A tolerance that is not a positive finite number below 1.
    #[error("tolerance {0} must be in (0, 1)")]
    Tolerance(f64),
    /// A tolerance so fine that the spherical-harmonic analysis would need more memory than
    /// [`crate::preconvolve::MAX_ANALYSIS_BYTES`].
    #[error(
        "tolerance {tolerance:e}: the n={exponent} light map needs spherical harmonics to degree {band_limit}, whose analysis takes {:.1} GiB, over the {:.1} GiB limit; use a tolerance of {coarsest_allowed:.1e} or more (the default is 2e-3)",
        *bytes as f64 / (1u64 << 30) as f64,
        *limit as f64 / (1u64 << 30) as f64
    )]
    TooFine {
        tolerance: f64,
        exponent: u32,
        band_limit: usize,
        bytes: u64,
        limit: u64,
        coarsest_allowed: f64,
    },
    /// The file's header claims more texels than any input may hold (checked before the
    /// pixels are allocated).
    #[error(
        "{}: the header claims a {width}x{height} image; volux reads at most {max} texels",
        path.display()
    )]
    TooLarge {
        path: PathBuf,
        width: usize,
        height: usize,
        max: usize,
    },
    /// A taper outside `[0, 1)`.
    #[error("taper {0} must be in [0, 1)")]
    Taper(f64),
}

/// Label of a map that did not come from a file.
pub(crate) const IN_MEMORY: &str = "in-memory map";

/// An error and every cause under it, `outer: cause: root cause`, the way `{:#}` prints an
/// `anyhow` chain: for the places that must put an error into one line of text (a log
/// warning, a message about several keys). The error types themselves never repeat their
/// source in their own message, so nothing is printed twice.
pub fn chain(error: &dyn std::error::Error) -> String {
    let mut text = error.to_string();
    let mut cause = error.source();
    while let Some(e) = cause {
        text.push_str(": ");
        text.push_str(&e.to_string());
        cause = e.source();
    }
    text
}

impl From<crate::durable::FileError> for EnvMapError {
    fn from(e: crate::durable::FileError) -> Self {
        EnvMapError::Io {
            path: e.path,
            source: e.source,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_chain_names_every_cause_once() {
        let e = EnvMapError::Io {
            path: PathBuf::from("maps/sky.exr"),
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "no such file"),
        };
        assert_eq!(e.to_string(), "maps/sky.exr");
        assert_eq!(chain(&e), "maps/sky.exr: no such file");
    }
}
