//! The generator (paper section 3, figure 2): `z` -> mapping network -> `w`; the NeIIF
//! rendered by the volume renderer at low resolution into `A_lo, N_lo, D_lo, S_lo, F_lo`,
//! depth and opacity; the upsampler gives `A_hi, F_hi`; the relighting network gives
//! `I_relit` from `[A_hi, D_up, S_up, F_hi]`.
//!
//! A forward pass computes only what [`GeneratorWants`] asks for and what that needs: stage 1
//! (albedo, normals, path loss) runs no light-map look-up and no relighting network; a sampler
//! that wants only `I_relit` gets no depth. Presets: [`GeneratorConfig::small`] (trains on two
//! CPU cores) and [`GeneratorConfig::paper`].

use burn::config::Config;
use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};

use crate::generated::{Generated, GeneratorWants};
use crate::light_lookup::Lighting;
use crate::mapping::{MappingNetwork, MappingNetworkConfig};
use crate::neiif::{LatentField, Neiif, NeiifConfig};
use crate::pose::Pose;
use crate::profile::{self, Phase};
use crate::ray_sampling::{CameraConfig, camera_basis, camera_ray_batch};
use crate::relighting::{RelightingConfig, RelightingNet};
use crate::upsampler::{Upsampler, UpsamplerConfig, bilinear_upsample};
use crate::upsampler_noise;
use crate::volume_rendering::{RenderOutput, RenderWants, RendererConfig, render};

/// Sizes of every part of a generator.
#[derive(Config, Debug)]
pub struct GeneratorConfig {
    pub mapping: MappingNetworkConfig,
    pub neiif: NeiifConfig,
    pub renderer: RendererConfig,
    /// Side of the volume-rendered images (64 in the paper).
    pub volume_resolution: usize,
    /// Side of `A_hi` and `I_relit` (a power-of-two multiple of `volume_resolution`).
    pub output_resolution: usize,
    /// Channels of the upsampler (the first three are the albedo).
    pub upsampler_channels: usize,
    /// Channels per level of the relighting U-Net, finest first.
    pub relighting_channels: Vec<usize>,
    /// Side of the upsampler's convolutions: 1 (the paper's) or 3 ([`UpsamplerConfig::kernel`]).
    #[config(default = 1)]
    pub upsampler_kernel: usize,
    /// Octaves of the upsampler's surface-anchored noise inputs, 0 (the paper's: none) to
    /// [`crate::upsampler_noise::MAX_OCTAVES`].
    #[config(default = 0)]
    pub upsampler_noise: usize,
}

/// Why a generator cannot be built or run.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum GeneratorError {
    #[error("output_resolution {output} must be volume_resolution {volume} times a power of two")]
    Resolution { volume: usize, output: usize },
    #[error("mapping w_dim {mapping} differs from the NeIIF's w_dim {neiif}")]
    WDim { mapping: usize, neiif: usize },
    #[error(
        "relighting U-Net with {levels} levels needs a resolution divisible by {divisor}, got {resolution}"
    )]
    UnetResolution {
        levels: usize,
        divisor: usize,
        resolution: usize,
    },
    #[error("upsampler_kernel {0} must be 1 or 3")]
    UpsamplerKernel(usize),
    #[error("upsampler_noise {0} must be at most {max} octaves", max = crate::upsampler_noise::MAX_OCTAVES)]
    UpsamplerNoise(usize),
    #[error("renderer samples")]
    Samples(#[from] crate::volume_rendering::SamplesError),
    #[error("{what} needs lighting (light maps and yaw per batch element)")]
    NoLighting { what: &'static str },
    #[error("the field blends {lobes} specular lobes but {maps} light maps were given")]
    Lobes { lobes: usize, maps: usize },
    #[error("batch mismatch: z has {z}, poses {poses}, lighting {lighting}")]
    Batch {
        z: usize,
        poses: usize,
        lighting: usize,
    },
}

impl GeneratorConfig {
    /// A model that trains on two CPU cores: 32x32 volume, 64x64 output, NeIIF width 64,
    /// 12 + 12 samples per ray, z and w of 128.
    pub fn small() -> Self {
        Self::new(
            MappingNetworkConfig::new().with_z_dim(128).with_w_dim(128),
            NeiifConfig::new()
                .with_w_dim(128)
                .with_width(64)
                .with_head_width(64),
            RendererConfig::new()
                .with_stratified(12)
                .with_importance(12),
            32,
            64,
            32,
            vec![16, 32],
        )
    }

    /// The paper's model: z and w of 512, NeIIF 6x256, a 64x64 volume, `output_resolution`
    /// (128 for CelebA, 256 for FFHQ), 24 + 24 samples per ray.
    pub fn paper(output_resolution: usize) -> Self {
        Self::new(
            MappingNetworkConfig::new().with_z_dim(512).with_w_dim(512),
            NeiifConfig::new().with_w_dim(512),
            RendererConfig::new()
                .with_stratified(24)
                .with_importance(24),
            64,
            output_resolution,
            128,
            vec![64, 128],
        )
    }

    /// Checks that the sizes fit together.
    pub fn validate(&self) -> Result<(), GeneratorError> {
        let (v, o) = (self.volume_resolution, self.output_resolution);
        if v == 0 || o < v || o % v != 0 || !(o / v).is_power_of_two() {
            return Err(GeneratorError::Resolution {
                volume: v,
                output: o,
            });
        }
        if self.mapping.w_dim != self.neiif.w_dim {
            return Err(GeneratorError::WDim {
                mapping: self.mapping.w_dim,
                neiif: self.neiif.w_dim,
            });
        }
        self.renderer.check_samples()?;
        if !crate::upsampler::KERNELS.contains(&self.upsampler_kernel) {
            return Err(GeneratorError::UpsamplerKernel(self.upsampler_kernel));
        }
        if self.upsampler_noise > crate::upsampler_noise::MAX_OCTAVES {
            return Err(GeneratorError::UpsamplerNoise(self.upsampler_noise));
        }
        let levels = self.relighting_channels.len();
        let divisor = 1 << levels.saturating_sub(1);
        if levels == 0 || o % divisor != 0 {
            return Err(GeneratorError::UnetResolution {
                levels,
                divisor,
                resolution: o,
            });
        }
        Ok(())
    }

    /// A generator with freshly initialised parameters on `device`.
    pub fn init(&self, device: &Device) -> Result<Generator, GeneratorError> {
        self.validate()?;
        let neiif = self.neiif.init(device);
        let blocks = (self.output_resolution / self.volume_resolution).trailing_zeros() as usize;
        let upsampler_config = UpsamplerConfig::new(
            self.mapping.w_dim,
            3 + neiif.feature_dim(),
            self.upsampler_channels,
            blocks,
        )
        .with_kernel(self.upsampler_kernel);
        // The networks draw their initial weights in this order (NeIIF, upsampler,
        // relighting, mapping): a run is a pure function of its seed only while it stays.
        let upsampler = upsampler_config.init(device);
        let relighting = RelightingConfig::new(upsampler_config.output_channels() - 3)
            .with_channels(self.relighting_channels.clone())
            .init(device);
        let mapping = self.mapping.init(device);
        // Options drawn after the paper's networks, so that turning one on leaves every other
        // initial weight as it was.
        let upsampler = upsampler.with_noise(self.upsampler_noise, self.mapping.w_dim, device);
        Ok(Generator {
            mapping,
            neiif,
            upsampler,
            relighting,
            renderer: self.renderer.clone(),
            volume_resolution: self.volume_resolution,
        })
    }
}

/// The generator.
#[derive(Module, Debug)]
pub struct Generator {
    pub mapping: MappingNetwork,
    pub neiif: Neiif,
    pub upsampler: Upsampler,
    pub relighting: RelightingNet,
    #[module(skip)]
    pub renderer: RendererConfig,
    pub volume_resolution: usize,
}

/// A batch of generated images; what was not wanted is `None` (see [`crate::generated`] for
/// each output's shape and range).
#[derive(Clone, Debug)]
pub struct GeneratorOutput {
    /// `[batch, w_dim]`.
    pub w: Tensor<2>,
    /// `[batch, 1, h, w]`.
    pub opacity: Tensor<4>,
    pub layers: Generated<Option<Tensor<4>>>,
}

/// `[b, rays, c] -> [b, c, side, side]`.
fn image(x: Tensor<3>, side: usize) -> Tensor<4> {
    let [b, _, c] = x.dims();
    x.swap_dims(1, 2).reshape([b, c, side, side])
}

/// World-space `[b, rays, 3]` to each pose's camera space.
fn to_camera_space(
    n: Tensor<3>,
    camera: &CameraConfig,
    poses: &[Pose],
    device: &Device,
) -> Tensor<3> {
    let basis: Vec<f32> = poses
        .iter()
        .flat_map(|&pose| {
            let [r, u, b] = camera_basis(camera, pose);
            // Columns are the axes: n [1, 3] x M [3, 3] = (n.r, n.u, n.b).
            (0..3).flat_map(move |k| [r[k] as f32, u[k] as f32, b[k] as f32])
        })
        .collect();
    let m = Tensor::<3>::from_data(TensorData::new(basis, [poses.len(), 3, 3]), device);
    n.matmul(m)
}

impl Generator {
    /// Side of the high-resolution outputs.
    pub fn output_resolution(&self) -> usize {
        self.volume_resolution * self.upsampler.factor()
    }

    /// Opens the first `alpha` octaves of the NeIIF's positional encoding (coarse to fine,
    /// [`crate::positional_encoding`]); `None` opens all. The training schedule sets it before
    /// each step, and a loaded generator takes the window of the images it was trained on.
    pub fn set_octave_window(&mut self, alpha: Option<f64>) {
        self.neiif.encoding.set_window(alpha);
    }

    /// Renders the NeIIF of latents `w: [batch, w_dim]` along given rays `[batch, rays, 3]`
    /// (the low-resolution half of the generator, on any set of rays).
    pub fn render_rays(
        &self,
        w: Tensor<2>,
        origins: Tensor<3>,
        dirs: Tensor<3>,
        lighting: Option<&Lighting>,
        wants: RenderWants,
        jitter: bool,
    ) -> Result<RenderOutput, GeneratorError> {
        if wants.shading {
            let lighting = lighting.ok_or(GeneratorError::NoLighting {
                what: "diffuse and specular shading",
            })?;
            let lobes = self.neiif.specular_lobes();
            if lighting.maps.len() != lobes {
                return Err(GeneratorError::Lobes {
                    lobes,
                    maps: lighting.maps.len(),
                });
            }
            let (b, lb) = (w.dims()[0], lighting.maps[0].batch());
            if b != lb {
                return Err(GeneratorError::Batch {
                    z: b,
                    poses: origins.dims()[0],
                    lighting: lb,
                });
            }
        }
        let field = LatentField {
            field: &self.neiif,
            w,
        };
        Ok(render(
            &self.renderer,
            &field,
            origins,
            dirs,
            lighting,
            wants,
            jitter,
        ))
    }

    /// Generates `z: [batch, z_dim]` seen from `poses` (one per element) under
    /// `lighting`, over a background colour (the dataset's), computing only what `wants` needs.
    /// `fade` holds the upsampler's fade-in weights (`None`: fully grown); `jitter` randomises
    /// ray samples (training).
    #[allow(clippy::too_many_arguments)]
    pub fn forward(
        &self,
        z: Tensor<2>,
        poses: &[Pose],
        lighting: Option<&Lighting>,
        background: [f32; 3],
        wants: GeneratorWants,
        fade: Option<&[f64]>,
        jitter: bool,
    ) -> Result<GeneratorOutput, GeneratorError> {
        let device = z.device();
        let b = z.dims()[0];
        if poses.len() != b {
            return Err(GeneratorError::Batch {
                z: b,
                poses: poses.len(),
                lighting: lighting.map_or(0, |l| l.maps[0].batch()),
            });
        }
        let up = wants.needs_upsampler();
        let noised = up && self.upsampler.noise_octaves() > 0;
        // The noise's seeds hash the latents themselves.
        let z_noise = noised.then(|| z.clone().detach());
        let w = profile::timed(Phase::Mapping, || self.mapping.forward(z));
        let side = self.volume_resolution;
        let render_wants = RenderWants {
            albedo: wants.albedo_lo || up,
            normals: wants.normals_lo,
            shading: wants.needs_shading(),
            features: wants.features_lo || up,
            depth: wants.depth || noised,
        };
        // The renderer's own work; the field's queries inside it are timed as their own phase.
        let compositing = profile::span(Phase::Compositing);
        let (origins, dirs) = camera_ray_batch(&self.renderer.camera, poses, side, side, &device);
        let r = self.render_rays(
            w.clone(),
            origins.clone(),
            dirs.clone(),
            lighting,
            render_wants,
            jitter,
        )?;
        let opacity = r.opacity.clone().reshape([b, 1, side, side]);
        let bg = Tensor::<1>::from_floats(background.as_slice(), &device).reshape([1, 3, 1, 1]);
        let clear = opacity.clone().neg().add_scalar(1.0);
        let albedo_lo = r.albedo.map(|a| image(a, side) + clear.clone() * bg);
        let features_lo = r.features.map(|f| image(f, side));
        let diffuse_lo = r.diffuse.map(|d| image(d, side));
        let specular_lo = r.specular.map(|s| image(s, side));
        let normals_lo = r.normals.map(|n| {
            image(
                to_camera_space(n, &self.renderer.camera, poses, &device),
                side,
            )
        });
        let noise = match (&r.depth, z_noise) {
            (Some(depth), Some(z)) => {
                let seeds = upsampler_noise::latent_seeds(z);
                let points = origins + dirs * depth.clone().detach().unsqueeze_dim::<3>(2);
                self.noise_images(image(points, side), opacity.clone().detach(), &seeds)
            }
            _ => Vec::new(),
        };
        let depth = r.depth.map(|d| d.reshape([b, 1, side, side]));
        drop(compositing);
        let (mut albedo_hi, mut relit) = (None, None);
        if up {
            let x = Tensor::cat(
                vec![
                    albedo_lo.clone().expect("rendered for the upsampler"),
                    features_lo.clone().expect("rendered for the upsampler"),
                ],
                1,
            );
            let hi = profile::timed(Phase::Upsampler, || {
                self.upsampler.forward_noised(x, w.clone(), fade, &noise)
            });
            let c = hi.dims()[1];
            let a_hi = hi.clone().narrow(1, 0, 3);
            if wants.relit {
                let _relighting = profile::span(Phase::Relighting);
                let f = self.upsampler.factor();
                let d_up = bilinear_upsample(diffuse_lo.clone().expect("shading rendered"), f);
                let s_up = bilinear_upsample(specular_lo.clone().expect("shading rendered"), f);
                relit =
                    Some(
                        self.relighting
                            .forward(a_hi.clone(), d_up, s_up, hi.narrow(1, 3, c - 3)),
                    );
            }
            albedo_hi = Some(a_hi);
        }
        let layers = Generated {
            albedo_lo,
            normals_lo,
            diffuse_lo,
            specular_lo,
            features_lo,
            depth,
            albedo_hi,
            relit,
        };
        Ok(GeneratorOutput {
            w,
            opacity,
            layers: layers.wanted(wants),
        })
    }

    /// Each upsampler block's noise images `[batch, octaves, h, w]` from the surface points
    /// `[batch, 3, side, side]` the volume's pixels see and their opacity `[batch, 1, side,
    /// side]`, both enlarged bilinearly to the block's resolution: the noise on the surface,
    /// faded out where the ray sees less of it, none on the background
    /// ([`crate::upsampler_noise`]).
    fn noise_images(&self, points: Tensor<4>, opacity: Tensor<4>, seeds: &[u64]) -> Vec<Tensor<4>> {
        let octaves = self.upsampler.noise_octaves();
        (1..=self.upsampler.blocks.len())
            .map(|i| {
                let at = bilinear_upsample(points.clone(), 1 << i);
                let resolution = self.volume_resolution << i;
                let spacing = upsampler_noise::pixel_footprint(&self.renderer.camera, resolution);
                upsampler_noise::noise_images(at, seeds, spacing, octaves)
                    * bilinear_upsample(opacity.clone(), 1 << i)
            })
            .collect()
    }

    /// Parameter counts of each part, in the order mapping, NeIIF, upsampler, relighting.
    pub fn parameter_counts(&self) -> [(&'static str, usize); 4] {
        [
            ("mapping network", self.mapping.num_params()),
            ("NeIIF", self.neiif.num_params()),
            ("upsampler", self.upsampler.num_params()),
            ("relighting network", self.relighting.num_params()),
        ]
    }
}

#[cfg(test)]
mod tests;
