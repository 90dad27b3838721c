//! VoLux-GAN's networks as Burn modules, one module per concept of the paper.
//!
//! - Generator (section 3, appendix B): [`mapping`] network, [`positional_encoding`],
//!   [`modulated`] layers (their products [`batched_matmul`]), the [`neiif`] (its activation a [`fused_activation`]) (density, normals by a reverse sweep, albedo, specular
//!   weights, features), volume rendering ([`ray_sampling`], optionally placed by
//!   density-only [`proposal`] passes, -> [`volume_rendering`] -> [`ray_marching`], with the [`light_lookup`] and [`shading`] for `D` and `S`, per sample or,
//!   for the paper's surface-relighting ablation, per pixel), the [`upsampler`], the
//!   [`relighting`] U-Net, all tied together in [`generator`] (its outputs described once in [`generated`]); [`presets`] sizes the
//!   generator and the discriminators together (`small`, `paper`).
//! - Discriminators (section 3.4): [`equalized`] layers, StyleGAN2's [`blur`], the residual
//!   [`discriminator`] with its explicit input gradient and the R1 penalty.
//! - Cameras: [`pose`] (yaw and pitch on the orbit; the rays are [`ray_sampling`]'s).
//! - Checks: [`backend`] (device selection and a self-check), [`analytic`] fields with known
//!   answers, the samples-per-ray [`sampling_report`].
//! - Performance: [`profile`] (named timing spans, no-ops unless a profiler runs) and
//!   [`flops`] (operation counts from the configured shapes).

pub mod analytic;
pub mod backend;
pub mod batched_matmul;
pub mod bias_act;
pub mod blur;
pub mod convolution;
pub mod discriminator;
pub mod equalized;
pub mod field;
pub mod fir_filter;
pub mod flex_extension;
pub mod flops;
pub mod fused_activation;
pub mod generated;
pub mod generator;
pub mod light_lookup;
pub mod mapping;
pub mod modulated;
pub mod neiif;
pub mod pose;
pub mod positional_encoding;
pub mod presets;
pub mod profile;
pub mod proposal;
pub mod ray_marching;
pub mod ray_sampling;
pub mod relighting;
pub mod sampling_report;
pub mod shading;
pub mod template_planes;
#[cfg(test)]
mod test_support;
pub mod unet;
pub mod upsampler;
pub mod upsampler_noise;
pub mod value_noise;
pub mod volume_rendering;
