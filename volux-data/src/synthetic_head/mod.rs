//! The built-in dataset: procedural relightable heads (paper appendix A, made without Total
//! Relighting).
//!
//! A seed fixes an identity ([`identity`]): the shape of the cranium, jaw, chin, cheekbones,
//! brow ridge, nose, lips, eye sockets and eyes, ears, neck and a hair cap, the skin tone and
//! texture, lip, brow, hair and iris colours, and per-region specular weights (oily T-zone,
//! wet eyes and lips, matte hair). The head is a smooth signed distance ([`head`], built from
//! [`sdf`] primitives), so it renders from any viewpoint with exact normals (forward-mode
//! derivatives, [`scalar`]). [`render`] traces it with the dataset camera into albedo,
//! camera-space normals, mask, depth and specular weights; [`shade`] adds the pseudo ground
//! truth's diffuse, specular and relit layers (the relighting augmentation with per-pixel
//! weights) and a photo with effects the Phong model lacks ([`photo`]).

pub mod head;
pub mod identity;
pub mod photo;
pub mod render;
pub mod scalar;
pub mod sdf;

pub use head::{Material, Region, SyntheticHead};
pub use identity::HeadIdentity;
pub use photo::PhotoLighting;
pub use render::{HeadRender, RenderSettings, SurfaceHit, render};

use volux_envmap::{LightMap, Rgb};

use crate::relighting::{RelightError, RelitLayers, SpecularWeights, relight_weighted};

/// The Phong exponents the heads' materials weight, in order.
pub const EXPONENTS: [u32; 4] = [1, 16, 32, 64];

/// Why a head cannot be shaded.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SyntheticError {
    #[error("synthetic heads need light maps with exponents {EXPONENTS:?}, got {0:?}")]
    Exponents(Vec<u32>),
    #[error(transparent)]
    Relight(#[from] RelightError),
}

/// Checks that `lights` are `L_1, L_16, L_32, L_64`, the lobes the materials weight.
pub fn check_light_maps(lights: &[&LightMap]) -> Result<(), SyntheticError> {
    let got: Vec<u32> = lights.iter().map(|m| m.exponent()).collect();
    if got != EXPONENTS {
        return Err(SyntheticError::Exponents(got));
    }
    Ok(())
}

/// The lighting layers of one render under one environment.
#[derive(Clone, Debug, PartialEq)]
pub struct Shading {
    /// Diffuse, specular and relit pseudo ground truth (the generator's Phong model).
    pub layers: RelitLayers,
    /// The photo, sRGB in `[0, 1]`.
    pub photo: Vec<Rgb>,
}

/// Shades `render` of `head` under the light maps of an environment rotated by `yaw`, over
/// `background` (sRGB).
pub fn shade(
    head: &SyntheticHead,
    render: &HeadRender,
    lights: &[&LightMap],
    yaw: f64,
    background: Rgb,
) -> Result<Shading, SyntheticError> {
    let light = PhotoLighting::new(lights, yaw)?;
    let layers = relight_weighted(
        &render.image,
        lights,
        SpecularWeights::PerPixel(&render.specular_weights),
        yaw,
        &render.camera,
        background,
    )?;
    let photo = photo::photo(head, render, &light, background);
    Ok(Shading { layers, photo })
}

#[cfg(test)]
mod tests;
