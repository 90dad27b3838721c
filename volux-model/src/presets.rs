//! Named model sizes: the generator and the four discriminators of section 3.4 (`D_A` at low
//! and high resolution, `D_G`, `D_S`, `D_P`) sized together.

use crate::discriminator::DiscriminatorConfig;
use crate::generator::GeneratorConfig;

/// A model size.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Preset {
    /// 32x32 volume, 64x64 output, NeIIF width 64, small discriminators: trains on 2 CPU cores.
    Small,
    /// The paper's model at 128x128 (CelebA), StyleGAN2's discriminators.
    Paper128,
    /// The paper's model at 256x256 (FFHQ), StyleGAN2's discriminators.
    Paper256,
}

/// Which discriminator, and what it sees.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DiscriminatorRole {
    /// `D_A` on the low-resolution albedo `A_lo`.
    AlbedoLow,
    /// `D_A` on the high-resolution albedo `A_hi`.
    AlbedoHigh,
    /// `D_G` on normal maps.
    Geometry,
    /// `D_S` on `[I_relit, D, S]` (9 channels).
    Shading,
    /// `D_P` on `I_relit` against the photos.
    Photo,
}

/// One value per discriminator role (what each sees, each one's weight, ...).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ByRole<T> {
    pub albedo_lo: T,
    pub albedo_hi: T,
    pub geometry: T,
    pub shading: T,
    pub photo: T,
}

impl<T> ByRole<T> {
    /// The value of `role`.
    pub fn get(&self, role: DiscriminatorRole) -> &T {
        match role {
            DiscriminatorRole::AlbedoLow => &self.albedo_lo,
            DiscriminatorRole::AlbedoHigh => &self.albedo_hi,
            DiscriminatorRole::Geometry => &self.geometry,
            DiscriminatorRole::Shading => &self.shading,
            DiscriminatorRole::Photo => &self.photo,
        }
    }

    /// `f` of every role's value, in the order of [`DiscriminatorRole::ALL`].
    pub fn map<U>(&self, mut f: impl FnMut(DiscriminatorRole, &T) -> U) -> ByRole<U> {
        ByRole {
            albedo_lo: f(DiscriminatorRole::AlbedoLow, &self.albedo_lo),
            albedo_hi: f(DiscriminatorRole::AlbedoHigh, &self.albedo_hi),
            geometry: f(DiscriminatorRole::Geometry, &self.geometry),
            shading: f(DiscriminatorRole::Shading, &self.shading),
            photo: f(DiscriminatorRole::Photo, &self.photo),
        }
    }
}

impl DiscriminatorRole {
    pub const ALL: [Self; 5] = [
        Self::AlbedoLow,
        Self::AlbedoHigh,
        Self::Geometry,
        Self::Shading,
        Self::Photo,
    ];

    /// The run's name for it: its field in a run's discriminators, the `discriminators` of a
    /// checkpoint's state, and the suffix of its loss terms.
    pub const fn key(self) -> &'static str {
        match self {
            Self::AlbedoLow => "albedo_lo",
            Self::AlbedoHigh => "albedo_hi",
            Self::Geometry => "geometry",
            Self::Shading => "shading",
            Self::Photo => "photo",
        }
    }

    /// The names its losses are logged under: generator, discriminator, R1 (`G_<key>`,
    /// `D_<key>`, `R1_<key>`).
    pub const fn terms(self) -> [&'static str; 3] {
        match self {
            Self::AlbedoLow => ["G_albedo_lo", "D_albedo_lo", "R1_albedo_lo"],
            Self::AlbedoHigh => ["G_albedo_hi", "D_albedo_hi", "R1_albedo_hi"],
            Self::Geometry => ["G_geometry", "D_geometry", "R1_geometry"],
            Self::Shading => ["G_shading", "D_shading", "R1_shading"],
            Self::Photo => ["G_photo", "D_photo", "R1_photo"],
        }
    }

    /// The paper's name.
    pub fn name(self) -> &'static str {
        match self {
            Self::AlbedoLow => "D_A (low-res albedo)",
            Self::AlbedoHigh => "D_A (high-res albedo)",
            Self::Geometry => "D_G (normals)",
            Self::Shading => "D_S (relit, D, S)",
            Self::Photo => "D_P (relit vs photo)",
        }
    }
}

impl Preset {
    /// The generator's sizes.
    pub fn generator(self) -> GeneratorConfig {
        match self {
            Self::Small => GeneratorConfig::small(),
            Self::Paper128 => GeneratorConfig::paper(128),
            Self::Paper256 => GeneratorConfig::paper(256),
        }
    }

    /// The sizes of one discriminator of the preset's generator.
    pub fn discriminator(self, role: DiscriminatorRole) -> DiscriminatorConfig {
        self.discriminator_for(role, &self.generator())
    }

    /// The sizes of one discriminator of the preset's width for the images of `g` (a
    /// generator of this preset with, say, another volume resolution).
    pub fn discriminator_for(
        self,
        role: DiscriminatorRole,
        g: &GeneratorConfig,
    ) -> DiscriminatorConfig {
        let (channels, resolution) = match role {
            DiscriminatorRole::AlbedoLow => (3, g.volume_resolution),
            DiscriminatorRole::AlbedoHigh => (3, g.output_resolution),
            DiscriminatorRole::Geometry => (3, g.volume_resolution),
            DiscriminatorRole::Shading => (9, g.output_resolution),
            DiscriminatorRole::Photo => (3, g.output_resolution),
        };
        match self {
            Self::Small => DiscriminatorConfig::small(channels, resolution),
            Self::Paper128 | Self::Paper256 => DiscriminatorConfig::stylegan2(channels, resolution),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, Distribution, Tensor};

    #[test]
    fn every_small_discriminator_takes_what_the_generator_makes() {
        let device = Device::flex();
        let g = Preset::Small.generator();
        for role in DiscriminatorRole::ALL {
            let cfg = Preset::Small.discriminator(role);
            let d = cfg.init(&device);
            let x = Tensor::<4>::random(
                [2, cfg.in_channels, cfg.resolution, cfg.resolution],
                Distribution::Normal(0.0, 1.0),
                &device,
            );
            assert_eq!(d.forward(x).dims(), [2, 1], "{}", role.name());
            assert!([g.volume_resolution, g.output_resolution].contains(&cfg.resolution));
        }
    }
}
