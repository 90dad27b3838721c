//! VoLux-GAN's networks as Burn modules. Today: backend selection ([`backend`]), the
//! differentiable light-map look-up ([`light_lookup`]), equalized-learning-rate layers
//! ([`equalized`]), the mapping network ([`mapping`]) and the positional encoding
//! ([`positional_encoding`]); the NeIIF, renderer, upsampler,
//! relighting network and discriminators follow.

pub mod backend;
pub mod equalized;
pub mod light_lookup;
pub mod mapping;
pub mod positional_encoding;
