//! VoLux-GAN's networks as Burn modules. Today: backend selection ([`backend`]), the
//! differentiable light-map look-up ([`light_lookup`]), equalized-learning-rate layers
//! ([`equalized`]), the mapping network ([`mapping`]), the positional encoding
//! ([`positional_encoding`]), camera rays and stratified samples ([`ray_sampling`]) and
//! compositing along rays ([`ray_marching`]), StyleGAN2's blur filter and its adjoints
//! ([`blur`]) and the residual discriminator with its explicit input gradient for R1
//! ([`discriminator`]); the NeIIF, importance sampling, upsampler and relighting network
//! follow.

pub mod analytic;
pub mod backend;
pub mod blur;
pub mod discriminator;
pub mod equalized;
pub mod light_lookup;
pub mod mapping;
pub mod modulated;
pub mod neiif;
pub mod positional_encoding;
pub mod ray_marching;
pub mod ray_sampling;
pub mod sampling_report;
pub mod upsampler;
pub mod volume_rendering;
