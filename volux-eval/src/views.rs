//! What the measurements read: one image's layers at the output resolution (albedo, relit,
//! physically shaded, depth, coverage) and at the volume's (normals, depth, coverage), made
//! either by a generator or by the built-in synthetic heads, whose layers are exact.

use burn::tensor::{Tensor, TensorData};
use volux_data::relighting::{RelightError, SpecularWeights, relight_weighted};
use volux_data::synthetic_head::{self, RenderSettings, SyntheticHead};
use volux_envmap::io::srgb_to_linear;
use volux_envmap::{LightMap, LightMapSet, Rgb};
use volux_model::backend::to_f32_vec;
use volux_model::generated::GeneratorWants;
use volux_model::generator::Generator;
use volux_model::pose::Pose;
use volux_model::relighting::tonemap_srgb;
use volux_model::upsampler::bilinear_upsample;
use volux_train::sampling::SampleError;

/// One image's layers, row-major from the top-left pixel.
#[derive(Clone, Debug, PartialEq)]
pub struct Rendered {
    /// Camera pose.
    pub pose: Pose,
    /// Side of the output-resolution layers.
    pub side: usize,
    /// Linear albedo over the background's albedo.
    pub albedo: Vec<Rgb>,
    /// The relit image, sRGB in `[0, 1]` over the background.
    pub relit: Vec<Rgb>,
    /// The physically shaded image `tonemap(A D + S)` over the background, sRGB: what the relit
    /// image is without the relighting network's learned correction.
    pub shaded: Vec<Rgb>,
    /// Expected distance along each (unit) camera ray; the far bound where nothing is hit.
    pub depth: Vec<f32>,
    /// Coverage (accumulated opacity) in `[0, 1]`.
    pub mask: Vec<f32>,
    /// Side of the volume-resolution layers.
    pub side_lo: usize,
    /// Camera-space normals over 0.
    pub normals_lo: Vec<[f32; 3]>,
    pub depth_lo: Vec<f32>,
    pub mask_lo: Vec<f32>,
}

/// `[b, c, s, s]` to per-image pixel lists of `C` channels.
fn pixels<const C: usize>(t: Tensor<4>) -> Vec<Vec<[f32; C]>> {
    let [b, c, s, _] = t.dims();
    assert_eq!(c, C, "channel count");
    let v = to_f32_vec(t);
    let plane = s * s;
    (0..b)
        .map(|i| {
            (0..plane)
                .map(|p| std::array::from_fn(|k| v[(i * C + k) * plane + p]))
                .collect()
        })
        .collect()
}

fn scalars(t: Tensor<4>) -> Vec<Vec<f32>> {
    pixels::<1>(t)
        .into_iter()
        .map(|img| img.into_iter().map(|[v]| v).collect())
        .collect()
}

/// Renders latents `z` at `poses` (no ray jitter), element `i` lit by `lights[i]` turned by
/// `env_yaws[i]`, over `background` (sRGB).
pub fn render_model(
    g: &Generator,
    z: Tensor<2>,
    poses: &[Pose],
    lights: &[&LightMapSet],
    env_yaws: &[f64],
    background: Rgb,
) -> Result<Vec<Rendered>, SampleError> {
    let device = z.device();
    let lighting = volux_model::light_lookup::lighting_tensors(lights, env_yaws, &device)?;
    let wants = GeneratorWants {
        albedo_lo: false,
        features_lo: false,
        ..GeneratorWants::ALL
    };
    let albedo_bg = background.map(srgb_to_linear);
    let out = g.forward(z, poses, Some(&lighting), albedo_bg, wants, None, false)?;
    let f = g.upsampler.factor();
    let need = |t: Option<Tensor<4>>| t.expect("asked for");
    let (diffuse, specular) = (need(out.layers.diffuse_lo), need(out.layers.specular_lo));
    let albedo = need(out.layers.albedo_hi);
    let depth_lo = need(out.layers.depth);
    let mask = bilinear_upsample(out.opacity.clone(), f).clamp(0.0, 1.0);
    let bg = Tensor::<1>::from_data(TensorData::new(background.to_vec(), [3]), &device)
        .reshape([1, 3, 1, 1]);
    let core = tonemap_srgb(
        albedo.clone() * bilinear_upsample(diffuse, f) + bilinear_upsample(specular, f),
    );
    let shaded = core * mask.clone() + (mask.clone().neg().add_scalar(1.0)) * bg;
    let relit = need(out.layers.relit)
        .add_scalar(1.0)
        .mul_scalar(0.5)
        .clamp(0.0, 1.0);
    let depth = bilinear_upsample(depth_lo.clone(), f);
    let side = g.output_resolution();
    let side_lo = side / f;
    let (albedo, relit, shaded) = (pixels::<3>(albedo), pixels::<3>(relit), pixels::<3>(shaded));
    let (depth, mask) = (scalars(depth), scalars(mask));
    let normals = pixels::<3>(need(out.layers.normals_lo));
    let (depth_lo, mask_lo) = (scalars(depth_lo), scalars(out.opacity));
    Ok((0..poses.len())
        .map(|i| Rendered {
            pose: poses[i],
            side,
            albedo: albedo[i].clone(),
            relit: relit[i].clone(),
            shaded: shaded[i].clone(),
            depth: depth[i].clone(),
            mask: mask[i].clone(),
            side_lo,
            normals_lo: normals[i].clone(),
            depth_lo: depth_lo[i].clone(),
            mask_lo: mask_lo[i].clone(),
        })
        .collect())
}

/// Renders synthetic `head` at `pose`: exact albedo, normals, depth and coverage (2x2 rays per
/// pixel at the output resolution, so that resampling its texture is not mistaken for
/// inconsistency; one at the volume's), the relit image under `lights` turned by `env_yaw` over `background` (sRGB), which
/// is the physically shaded image itself.
pub fn render_synthetic(
    head: &SyntheticHead,
    pose: Pose,
    side: usize,
    side_lo: usize,
    lights: &LightMapSet,
    env_yaw: f64,
    background: Rgb,
) -> Result<Rendered, RelightError> {
    let hi = synthetic_head::render(
        head,
        pose,
        &RenderSettings {
            supersample: 2,
            ..RenderSettings::square(side)
        },
    );
    let lo = synthetic_head::render(head, pose, &RenderSettings::square(side_lo));
    let maps: Vec<&LightMap> = lights.maps().iter().collect();
    let layers = relight_weighted(
        &hi.image,
        &maps,
        SpecularWeights::PerPixel(&hi.specular_weights),
        env_yaw,
        &hi.camera,
        background,
    )?;
    let albedo_bg = background.map(srgb_to_linear);
    let albedo = hi
        .image
        .albedo
        .iter()
        .zip(&hi.image.mask)
        .map(|(a, &m)| std::array::from_fn(|k| m * a[k] + (1.0 - m) * albedo_bg[k]))
        .collect();
    let normals_lo = lo
        .image
        .normals
        .iter()
        .zip(&lo.image.mask)
        .map(|(n, &m)| n.map(|v| v * m))
        .collect();
    Ok(Rendered {
        pose,
        side,
        albedo,
        shaded: layers.relit.clone(),
        relit: layers.relit,
        depth: hi.depth,
        mask: hi.image.mask,
        side_lo,
        normals_lo,
        depth_lo: lo.depth,
        mask_lo: lo.image.mask,
    })
}
