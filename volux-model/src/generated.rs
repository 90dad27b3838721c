//! The generator's image outputs, described once: [`Generated<T>`] holds one value per output,
//! so what a forward pass must compute ([`GeneratorWants`], `Generated<bool>`) and what it
//! returned (`Generated<Option<Tensor<4>>>`, in
//! [`GeneratorOutput`](crate::generator::GeneratorOutput)) name the same outputs.
//!
//! Low-resolution maps are `[batch, channels, h, w]` at the volume resolution, composited over
//! the background (`A_lo` over the background's albedo, the rest over 0); normals are in camera
//! space (+z towards the camera); the high-resolution ones are `[batch, 3, H, W]`.

/// One value per generated image.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Generated<T> {
    /// `A_lo`, linear albedo (D_A's low-resolution input).
    pub albedo_lo: T,
    /// `N_lo`, camera-space normals (D_G).
    pub normals_lo: T,
    /// `D_lo`, linear HDR diffuse shading.
    pub diffuse_lo: T,
    /// `S_lo`, linear HDR specular shading.
    pub specular_lo: T,
    /// `F_lo`, the features the upsampler and the relighting network take.
    pub features_lo: T,
    /// Expected depth, `[batch, 1, h, w]`.
    pub depth: T,
    /// `A_hi` in [0, 1] (up to the learned residual; D_A's high-resolution input).
    pub albedo_hi: T,
    /// The relit image, sRGB mapped to [-1, 1] (D_S and D_P).
    pub relit: T,
}

/// Which outputs a forward pass must return.
pub type GeneratorWants = Generated<bool>;

impl Generated<bool> {
    /// Everything.
    pub const ALL: Self = Self {
        albedo_lo: true,
        normals_lo: true,
        diffuse_lo: true,
        specular_lo: true,
        features_lo: true,
        depth: true,
        albedo_hi: true,
        relit: true,
    };
    /// Stage 1 of the schedule: `L_A` on both albedos, `L_G` on normals, the path loss.
    pub const STAGE1: Self = Self {
        albedo_lo: true,
        normals_lo: true,
        diffuse_lo: false,
        specular_lo: false,
        features_lo: false,
        depth: false,
        albedo_hi: true,
        relit: false,
    };

    /// Whether the upsampler runs (the high-resolution outputs need it).
    pub fn needs_upsampler(self) -> bool {
        self.albedo_hi || self.relit
    }

    /// Whether the renderer shades (the shading maps, and the relit image, need it).
    pub fn needs_shading(self) -> bool {
        self.diffuse_lo || self.specular_lo || self.relit
    }
}

impl<T> Generated<Option<T>> {
    /// The outputs `wants` asks for; the others become `None`.
    pub fn wanted(self, wants: GeneratorWants) -> Self {
        let keep = |v: Option<T>, want: bool| v.filter(|_| want);
        Generated {
            albedo_lo: keep(self.albedo_lo, wants.albedo_lo),
            normals_lo: keep(self.normals_lo, wants.normals_lo),
            diffuse_lo: keep(self.diffuse_lo, wants.diffuse_lo),
            specular_lo: keep(self.specular_lo, wants.specular_lo),
            features_lo: keep(self.features_lo, wants.features_lo),
            depth: keep(self.depth, wants.depth),
            albedo_hi: keep(self.albedo_hi, wants.albedo_hi),
            relit: keep(self.relit, wants.relit),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unwanted_outputs_are_dropped_and_needs_follow_the_wants() {
        let all = Generated {
            albedo_lo: Some(1),
            normals_lo: Some(2),
            diffuse_lo: Some(3),
            specular_lo: Some(4),
            features_lo: Some(5),
            depth: Some(6),
            albedo_hi: Some(7),
            relit: Some(8),
        };
        let kept = all.wanted(GeneratorWants::STAGE1);
        assert_eq!(
            [kept.albedo_lo, kept.normals_lo, kept.albedo_hi],
            [Some(1), Some(2), Some(7)]
        );
        assert_eq!(
            [
                kept.diffuse_lo,
                kept.specular_lo,
                kept.features_lo,
                kept.depth,
                kept.relit
            ],
            [None; 5]
        );
        assert_eq!(all.wanted(GeneratorWants::ALL), all);
        let stage1 = GeneratorWants::STAGE1;
        assert!(stage1.needs_upsampler() && !stage1.needs_shading());
        let relit_only = GeneratorWants {
            relit: true,
            ..GeneratorWants::default()
        };
        assert!(relit_only.needs_upsampler() && relit_only.needs_shading());
    }
}
