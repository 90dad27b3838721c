//! HDR environment maps and their cosine-lobe light maps (VoLux-GAN section 3.2,
//! "Efficient Shading Computation").
//!
//! - [`EnvMap`]: an equirectangular f32 linear-RGB map, read from OpenEXR, Radiance `.hdr` or
//!   8-bit PNG/JPEG ([`io`]), rotated about the vertical axis, summarised by [`EnvMap::stats`].
//! - [`durable`]: atomic, fsynced writes that every crate's files go through.
//! - [`direction`]: the one place that maps directions to texture coordinates and back.
//! - [`preconvolve`]: the light maps `L_n` for a list of Phong exponents, by spherical-harmonic
//!   (Funk-Hecke) zonal convolution whose band limit and output resolution follow from a
//!   tolerance; [`reference`] is the brute-force f64 ground truth it is tested against.
//! - [`LightMap`]: a preconvolved map with its bilinear look-up ([`lightmap`]).
//! - [`random`]: the seeded generator and seed derivation every crate's reproducibility rests on.
//! - [`report`]: error against run time of the fast method, measured against the reference.
//!
//! Conventions (`docs/conventions.md`): +y up, texel centre `(u, v)` has polar angle `theta = pi v` from
//! +y and azimuth `phi = 2 pi u - pi`, direction `(sin theta sin phi, cos theta,
//! sin theta cos phi)`; the centre column faces +z. For exponent `n`,
//! `L_n(w) = (n + 1) / (2 pi) * integral H(u) max(0, w.u)^n du`, so a constant map gives the
//! same constant for every `n`.

pub mod bright;
pub mod direction;
pub mod durable;
pub mod envmap;
pub mod error;
pub mod io;
pub mod legendre;
pub mod lightmap;
pub mod lobe;
pub mod preconvolve;
pub mod random;
pub mod reference;
pub mod report;
pub mod sh;

pub use envmap::{EnvMap, MapStats, Rgb};
pub use error::EnvMapError;
pub use lightmap::{LightMap, LightMapSet};
pub use preconvolve::{PreconvolveOptions, preconvolve};

/// The Phong exponents of the paper's light maps (those Total Relighting used).
pub const DEFAULT_EXPONENTS: [u32; 4] = [1, 16, 32, 64];
