//! Rendering a generator for people: latents from seeds (as StyleGAN's `--seeds`), every layer
//! of a batch of samples as images, and the sample grid (one sample per row; albedo, normals,
//! diffuse, specular, relit, depth per column).

use burn::tensor::{Device, Tensor, TensorData};
use volux_data::contact_sheet::{self, ContactSheet};
use volux_envmap::random::SplitMix64;
use volux_envmap::{LightMapSet, Rgb};
use volux_model::backend::to_f32_vec;
use volux_model::generated::GeneratorWants;
use volux_model::generator::{Generator, GeneratorError};
use volux_model::light_lookup::Lighting;
use volux_model::light_lookup::{LightingTensorError, lighting_tensors};
use volux_model::pose::Pose;

/// The latent of `seed`: `z_dim` standard normal numbers (Box-Muller on SplitMix64).
pub fn latent(seed: u64, z_dim: usize) -> Vec<f32> {
    let mut rng = SplitMix64::new(seed ^ 0x5EED_1A7E_27AB_C0DE);
    let mut z = Vec::with_capacity(z_dim + 1);
    while z.len() < z_dim {
        let u1 = 1.0 - rng.next_f64();
        let u2 = rng.next_f64();
        let r = (-2.0 * u1.ln()).sqrt();
        let phi = std::f64::consts::TAU * u2;
        z.push((r * phi.cos()) as f32);
        z.push((r * phi.sin()) as f32);
    }
    z.truncate(z_dim);
    z
}

/// `[seeds.len(), z_dim]` latents on `device`.
pub fn latents(seeds: &[u64], z_dim: usize, device: &Device) -> Tensor<2> {
    let data: Vec<f32> = seeds.iter().flat_map(|&s| latent(s, z_dim)).collect();
    Tensor::<2>::from_data(TensorData::new(data, [seeds.len(), z_dim]), device)
}

/// `[steps, z_dim]` latents on the straight line from seed `a`'s latent to seed `b`'s.
pub fn interpolate(a: u64, b: u64, steps: usize, z_dim: usize, device: &Device) -> Tensor<2> {
    let (za, zb) = (latent(a, z_dim), latent(b, z_dim));
    let data: Vec<f32> = (0..steps)
        .flat_map(|i| {
            let t = if steps > 1 {
                i as f32 / (steps - 1) as f32
            } else {
                0.0
            };
            za.iter()
                .zip(&zb)
                .map(move |(x, y)| x + t * (y - x))
                .collect::<Vec<_>>()
        })
        .collect();
    Tensor::<2>::from_data(TensorData::new(data, [steps, z_dim]), device)
}

/// Every layer of a batch of samples at the output resolution, one `Vec` per sample
/// (row-major). Low-resolution layers are repeated up to the output resolution.
#[derive(Clone, Debug)]
pub struct SampleLayers {
    pub side: usize,
    /// Linear albedo `A_hi`.
    pub albedo: Vec<Vec<Rgb>>,
    /// Camera-space normals.
    pub normals: Vec<Vec<Rgb>>,
    /// Linear HDR diffuse and specular shading.
    pub diffuse: Vec<Vec<Rgb>>,
    pub specular: Vec<Vec<Rgb>>,
    /// sRGB relit image in `[0, 1]`.
    pub relit: Vec<Vec<Rgb>>,
    /// Expected ray depth and opacity.
    pub depth: Vec<Vec<f32>>,
    pub opacity: Vec<Vec<f32>>,
}

/// `[b, c, s, s]` to per-sample pixel lists with `c` channels, repeated `factor` times.
fn planes(t: Tensor<4>, factor: usize) -> Vec<Vec<Vec<f32>>> {
    let [b, c, s, _] = t.dims();
    let v = to_f32_vec(t);
    let big = s * factor;
    (0..b)
        .map(|i| {
            (0..big * big)
                .map(|p| {
                    let (y, x) = (p / big / factor, p % big / factor);
                    (0..c).map(|k| v[((i * c + k) * s + y) * s + x]).collect()
                })
                .collect()
        })
        .collect()
}

fn rgb(t: Tensor<4>, factor: usize) -> Vec<Vec<Rgb>> {
    planes(t, factor)
        .into_iter()
        .map(|img| img.into_iter().map(|p| [p[0], p[1], p[2]]).collect())
        .collect()
}

fn grey(t: Tensor<4>, factor: usize) -> Vec<Vec<f32>> {
    planes(t, factor)
        .into_iter()
        .map(|img| img.into_iter().map(|p| p[0]).collect())
        .collect()
}

/// Renders `z` from `poses` under `lighting` (no ray jitter) and reads every layer back.
pub fn render_layers(
    g: &Generator,
    z: Tensor<2>,
    poses: &[Pose],
    lighting: &Lighting,
    background: [f32; 3],
) -> Result<SampleLayers, GeneratorError> {
    let wants = GeneratorWants {
        features_lo: false,
        ..GeneratorWants::ALL
    };
    let out = g.forward(z, poses, Some(lighting), background, wants, None, false)?;
    let f = g.upsampler.factor();
    let need = |t: Option<Tensor<4>>| t.expect("asked for");
    Ok(SampleLayers {
        side: g.output_resolution(),
        albedo: rgb(need(out.layers.albedo_hi), 1),
        normals: rgb(need(out.layers.normals_lo), f),
        diffuse: rgb(need(out.layers.diffuse_lo), f),
        specular: rgb(need(out.layers.specular_lo), f),
        relit: rgb(need(out.layers.relit).add_scalar(1.0).mul_scalar(0.5), 1),
        depth: grey(need(out.layers.depth), f),
        opacity: grey(out.opacity, f),
    })
}

/// Why samples cannot be rendered.
#[derive(Debug, thiserror::Error)]
pub enum SampleError {
    #[error("lighting")]
    Lighting(#[from] LightingTensorError),
    #[error("generator")]
    Model(#[from] GeneratorError),
}

/// [`render_layers`] with every element lit by one environment's light maps, turned by
/// `env_yaw` radians.
pub fn render_under(
    g: &Generator,
    z: Tensor<2>,
    poses: &[Pose],
    lights: &LightMapSet,
    env_yaw: f64,
    background: [f32; 3],
) -> Result<SampleLayers, SampleError> {
    let sets = vec![lights; poses.len()];
    let lighting = lighting_tensors(&sets, &vec![env_yaw; poses.len()], &z.device())?;
    Ok(render_layers(g, z, poses, &lighting, background)?)
}

/// The columns of a sample grid.
pub const GRID_COLUMNS: [&str; 6] = ["albedo", "normals", "diffuse", "specular", "relit", "depth"];

/// One row per sample: albedo, normals, diffuse, specular, relit, depth (near is bright).
pub fn grid(layers: &SampleLayers) -> ContactSheet {
    let n = layers.albedo.len();
    let s = layers.side;
    let mut sheet = ContactSheet::new(s, s, GRID_COLUMNS.len(), n);
    for i in 0..n {
        let (near, far) = depth_range(&layers.depth[i], &layers.opacity[i]);
        let tiles = [
            contact_sheet::albedo_colours(&layers.albedo[i]),
            contact_sheet::normal_colours(&layers.normals[i], &layers.opacity[i]),
            contact_sheet::shading_colours(&layers.diffuse[i], 1.0),
            contact_sheet::shading_colours(&layers.specular[i], 1.0),
            layers.relit[i].clone(),
            contact_sheet::grey(&layers.depth[i], far, near),
        ];
        for (column, tile) in tiles.iter().enumerate() {
            sheet.put(column, i, tile);
        }
    }
    sheet
}

/// Nearest and farthest depth over pixels more than half opaque (or all pixels).
fn depth_range(depth: &[f32], opacity: &[f32]) -> (f32, f32) {
    let solid: Vec<f32> = depth
        .iter()
        .zip(opacity)
        .filter(|&(_, &o)| o > 0.5)
        .map(|(&d, _)| d)
        .collect();
    let values = if solid.is_empty() { depth } else { &solid };
    let near = values.iter().copied().fold(f32::INFINITY, f32::min);
    let far = values.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    if far > near {
        (near, far)
    } else {
        (near, near + 1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn latents_are_standard_normal_and_fixed_by_the_seed() {
        let z = latent(7, 100_000);
        let mean = z.iter().map(|&v| v as f64).sum::<f64>() / z.len() as f64;
        let var = z.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / z.len() as f64;
        assert!(mean.abs() < 0.01, "{mean}");
        assert!((var - 1.0).abs() < 0.02, "{var}");
        assert_eq!(latent(7, 128), latent(7, 128));
        assert_ne!(latent(7, 128), latent(8, 128));
        // A prefix of a longer latent is the shorter one.
        assert_eq!(latent(7, 5), latent(7, 6)[..5]);
    }

    #[test]
    fn low_resolution_planes_are_repeated_in_blocks() {
        let t = Tensor::<4>::from_data(
            TensorData::new(vec![1.0f32, 2.0, 3.0, 4.0], [1, 1, 2, 2]),
            &Device::flex(),
        );
        let g = grey(t, 2);
        assert_eq!(
            g[0],
            vec![
                1.0, 1.0, 2.0, 2.0, 1.0, 1.0, 2.0, 2.0, 3.0, 3.0, 4.0, 4.0, 3.0, 3.0, 4.0, 4.0
            ]
        );
    }
}
