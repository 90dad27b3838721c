//! VoLux-GAN's networks as Burn modules. Today: backend selection ([`backend`]) and the
//! differentiable light-map look-up ([`light_lookup`]); the generator and discriminators follow.

pub mod backend;
pub mod light_lookup;
