//! VoLux-GAN's networks as Burn modules. Today: backend selection ([`backend`]), the
//! differentiable light-map look-up ([`light_lookup`]), equalized-learning-rate layers
//! ([`equalized`]), the mapping network ([`mapping`]), the positional encoding
//! ([`positional_encoding`]) and compositing along rays ([`ray_marching`]); the NeIIF, ray
//! sampling, upsampler, relighting network and discriminators follow.

pub mod backend;
pub mod equalized;
pub mod light_lookup;
pub mod mapping;
pub mod positional_encoding;
pub mod ray_marching;
