//! Relighting augmentation (paper appendix A): the lighting half of the pseudo ground truth,
//! made from an image's albedo, normals and mask under an HDRI at a yaw rotation.
//!
//! Per pixel, with the normal taken from camera to world space by the pose and the view ray of
//! the dataset camera (docs/conventions.md): diffuse `D = L_1(n)`, specular
//! `S = sum_i w_i L_{n_i}(r)` with `r = d - 2 (d.n) n`, and the relit image
//! `tonemap(A D + S)` (the curve of `volux_envmap::io::tonemap_pixel` at exposure 1, the same
//! the generator uses) composited over the background with the mask. `D` and `S` are
//! multiplied by the mask, like the generator's accumulated maps over a background of 0.

use volux_envmap::direction::{self, Dir};
use volux_envmap::io::tonemap_pixel;
use volux_envmap::{LightMap, Rgb};
use volux_model::pose::Pose;
use volux_model::ray_sampling::{CameraConfig, camera_basis, camera_rays};

/// Specular blend weights for exponents 1, 16, 32, 64 when a dataset does not set its own:
/// a broad sheen and a little gloss, in the range of skin.
pub const DEFAULT_SPECULAR_WEIGHTS: [f32; 4] = [0.0, 0.12, 0.06, 0.03];

/// Normals further than this from unit length are renormalised and counted.
const UNIT_TOLERANCE: f32 = 1e-3;

/// An image's intrinsic layers, row-major from the top-left pixel.
#[derive(Clone, Debug, PartialEq)]
pub struct IntrinsicImage {
    pub width: usize,
    pub height: usize,
    /// Linear albedo in [0, 1].
    pub albedo: Vec<Rgb>,
    /// Camera-space normals (+x right, +y up, +z towards the camera), unit length.
    pub normals: Vec<[f32; 3]>,
    /// Foreground coverage in [0, 1].
    pub mask: Vec<f32>,
    /// Camera pose.
    pub pose: Pose,
}

/// The lighting layers of one (HDRI, yaw) draw.
#[derive(Clone, Debug, PartialEq)]
pub struct RelitLayers {
    /// Linear HDR diffuse shading times the mask.
    pub diffuse: Vec<Rgb>,
    /// Linear HDR specular shading times the mask.
    pub specular: Vec<Rgb>,
    /// sRGB in [0, 1], composited over the background.
    pub relit: Vec<Rgb>,
    /// Foreground normals that were not unit length and were renormalised.
    pub renormalised: usize,
    /// Foreground normals of (near) zero length: no shading there.
    pub degenerate: usize,
}

/// Why an image cannot be relit.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RelightError {
    #[error("{layer} has {got} pixels, the image is {width}x{height} = {want}")]
    LayerSize {
        layer: &'static str,
        got: usize,
        width: usize,
        height: usize,
        want: usize,
    },
    #[error("{layer} has a non-finite value at pixel ({x}, {y})")]
    NonFinite {
        layer: &'static str,
        x: usize,
        y: usize,
    },
    #[error("the first light map must have Phong exponent 1 (diffuse), got {0}")]
    FirstNotDiffuse(u32),
    #[error(
        "{weights} specular weights for {maps} light maps{}",
        if *per_pixel { format!(" and {pixels} pixels (want {})", maps * pixels) } else { String::new() }
    )]
    Weights {
        weights: usize,
        maps: usize,
        pixels: usize,
        per_pixel: bool,
    },
    #[error("no light maps")]
    NoMaps,
}

impl IntrinsicImage {
    /// Checks layer sizes and finiteness.
    pub fn validate(&self) -> Result<(), RelightError> {
        let want = self.width * self.height;
        let sizes = [
            ("albedo", self.albedo.len()),
            ("normals", self.normals.len()),
            ("mask", self.mask.len()),
        ];
        for (layer, got) in sizes {
            if got != want {
                return Err(RelightError::LayerSize {
                    layer,
                    got,
                    width: self.width,
                    height: self.height,
                    want,
                });
            }
        }
        let at = |i: usize| (i % self.width.max(1), i / self.width.max(1));
        let checks: [(&'static str, Option<usize>); 3] = [
            (
                "albedo",
                self.albedo
                    .iter()
                    .position(|c| c.iter().any(|v| !v.is_finite())),
            ),
            (
                "normals",
                self.normals
                    .iter()
                    .position(|c| c.iter().any(|v| !v.is_finite())),
            ),
            ("mask", self.mask.iter().position(|v| !v.is_finite())),
        ];
        for (layer, bad) in checks {
            if let Some(i) = bad {
                let (x, y) = at(i);
                return Err(RelightError::NonFinite { layer, x, y });
            }
        }
        Ok(())
    }
}

/// How the specular layer blends the light maps.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SpecularWeights<'a> {
    /// One weight per light map for every pixel (a dataset's default).
    Uniform(&'a [f32]),
    /// One weight per light map per pixel, pixel-major (`pixels * maps` values): materials
    /// that vary over the face, like the synthetic heads' oily forehead and wet eyes.
    PerPixel(&'a [f32]),
}

/// Relights `image` under light maps `lights` (`lights[0]` is `L_1`; `weights[i]` blends
/// `lights[i]` into the specular) of an environment rotated by `env_yaw` radians, seen by
/// `camera`, over `background` (sRGB in [0, 1]).
pub fn relight(
    image: &IntrinsicImage,
    lights: &[&LightMap],
    weights: &[f32],
    env_yaw: f64,
    camera: &CameraConfig,
    background: Rgb,
) -> Result<RelitLayers, RelightError> {
    relight_weighted(
        image,
        lights,
        SpecularWeights::Uniform(weights),
        env_yaw,
        camera,
        background,
    )
}

/// [`relight`] with specular weights that may vary per pixel.
pub fn relight_weighted(
    image: &IntrinsicImage,
    lights: &[&LightMap],
    weights: SpecularWeights<'_>,
    env_yaw: f64,
    camera: &CameraConfig,
    background: Rgb,
) -> Result<RelitLayers, RelightError> {
    image.validate()?;
    let first = lights.first().ok_or(RelightError::NoMaps)?;
    if first.exponent() != 1 {
        return Err(RelightError::FirstNotDiffuse(first.exponent()));
    }
    let maps = lights.len();
    let per_pixel = match weights {
        SpecularWeights::Uniform(w) if w.len() == maps => false,
        SpecularWeights::PerPixel(w) if w.len() == maps * image.width * image.height => true,
        SpecularWeights::Uniform(w) | SpecularWeights::PerPixel(w) => {
            return Err(RelightError::Weights {
                weights: w.len(),
                maps,
                pixels: image.width * image.height,
                per_pixel: matches!(weights, SpecularWeights::PerPixel(_)),
            });
        }
    };
    let (SpecularWeights::Uniform(all) | SpecularWeights::PerPixel(all)) = weights;
    let weights_at = |i: usize| {
        if per_pixel {
            &all[i * maps..(i + 1) * maps]
        } else {
            all
        }
    };
    let [right, up, back] = camera_basis(camera, image.pose);
    let (_, dirs) = camera_rays(camera, image.pose, image.width, image.height);
    let n_pixels = image.width * image.height;
    let mut out = RelitLayers {
        diffuse: Vec::with_capacity(n_pixels),
        specular: Vec::with_capacity(n_pixels),
        relit: Vec::with_capacity(n_pixels),
        renormalised: 0,
        degenerate: 0,
    };
    for (i, ray) in dirs.iter().enumerate() {
        let m = image.mask[i].clamp(0.0, 1.0);
        let n = image.normals[i].map(f64::from);
        let len = direction::dot(n, n).sqrt();
        let (mut d, mut s) = ([0.0f32; 3], [0.0f32; 3]);
        if m > 0.0 {
            if len < 1e-6 {
                out.degenerate += 1;
            } else {
                if (len as f32 - 1.0).abs() > UNIT_TOLERANCE {
                    out.renormalised += 1;
                }
                let n: Dir = std::array::from_fn(|k| {
                    (right[k] * n[0] + up[k] * n[1] + back[k] * n[2]) / len
                });
                let r = direction::reflect(*ray, n);
                d = first.lookup_rotated(n, env_yaw);
                for (map, w) in lights.iter().zip(weights_at(i)) {
                    let l = map.lookup_rotated(r, env_yaw);
                    for (sk, lk) in s.iter_mut().zip(l) {
                        *sk += w * lk;
                    }
                }
            }
        }
        let a = image.albedo[i];
        let shaded = tonemap_pixel(std::array::from_fn(|k| a[k] * d[k] + s[k]), 1.0);
        out.relit.push(std::array::from_fn(|k| {
            m * shaded[k] + (1.0 - m) * background[k]
        }));
        out.diffuse.push(d.map(|v| v * m));
        out.specular.push(s.map(|v| v * m));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use volux_envmap::random::SplitMix64;
    use volux_envmap::reference::Reference;
    use volux_envmap::{EnvMap, PreconvolveOptions, preconvolve};

    /// A sphere of radius 0.3 seen at `pose`: camera-space normals and mask by ray casting.
    fn sphere_image(side: usize, pose: Pose, albedo: Rgb) -> IntrinsicImage {
        let camera = CameraConfig::new();
        let [right, up, back] = camera_basis(&camera, pose);
        let (origins, dirs) = camera_rays(&camera, pose, side, side);
        let mut normals = Vec::new();
        let mut mask = Vec::new();
        for (o, d) in origins.iter().zip(&dirs) {
            let b = direction::dot(*o, *d);
            let c = direction::dot(*o, *o) - 0.09;
            let disc = b * b - c;
            if disc > 0.0 {
                let t = -b - disc.sqrt();
                let p: Dir = std::array::from_fn(|k| (o[k] + t * d[k]) / 0.3);
                normals.push([
                    direction::dot(p, right) as f32,
                    direction::dot(p, up) as f32,
                    direction::dot(p, back) as f32,
                ]);
                mask.push(1.0);
            } else {
                normals.push([0.0, 0.0, 1.0]);
                mask.push(0.0);
            }
        }
        IntrinsicImage {
            width: side,
            height: side,
            albedo: vec![albedo; side * side],
            normals,
            mask,
            pose,
        }
    }

    fn env(seed: u64) -> EnvMap {
        let mut rng = SplitMix64::new(seed);
        let (w, h) = (64, 32);
        let a: Vec<f64> = (0..6).map(|_| rng.next_f64()).collect();
        let texels = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64 / w as f64, (i / w) as f64 / h as f64);
                std::array::from_fn(|c| {
                    (1.0 + 0.8
                        * (std::f64::consts::TAU * x + 5.0 * a[c]).sin()
                        * (3.0 * y + a[c + 3]).cos()) as f32
                })
            })
            .collect();
        EnvMap::new(w, h, texels).unwrap()
    }

    #[test]
    fn diffuse_and_specular_equal_the_brute_force_integrals() {
        let camera = CameraConfig::new();
        let map = env(3);
        let set = preconvolve(&map, &PreconvolveOptions::default()).unwrap();
        let lights: Vec<&LightMap> = set.maps().iter().collect();
        let weights = [0.1, 0.3, 0.2, 0.1];
        let pose = Pose::new(0.35, -0.1);
        let env_yaw = 1.3;
        let image = sphere_image(16, pose, [0.6, 0.4, 0.3]);
        let out = relight(&image, &lights, &weights, env_yaw, &camera, [0.0; 3]).unwrap();
        let references: Vec<Reference> = set
            .exponents()
            .iter()
            .map(|&n| Reference::new(&map, n))
            .collect();
        let [right, up, back] = camera_basis(&camera, pose);
        let (_, dirs) = camera_rays(&camera, pose, 16, 16);
        let mut checked = 0;
        for i in (0..256).filter(|&i| image.mask[i] > 0.0).step_by(7) {
            let nc = image.normals[i].map(f64::from);
            let n: Dir =
                std::array::from_fn(|k| right[k] * nc[0] + up[k] * nc[1] + back[k] * nc[2]);
            let r = direction::reflect(dirs[i], n);
            // Rotating the environment by +yaw is looking up the unrotated one at -yaw.
            let d_ref = references[0].eval(direction::rotate_yaw(n, -env_yaw));
            let mut s_ref = [0.0f64; 3];
            for (reference, w) in references.iter().zip(weights) {
                let l = reference.eval(direction::rotate_yaw(r, -env_yaw));
                for k in 0..3 {
                    s_ref[k] += f64::from(w) * l[k];
                }
            }
            for k in 0..3 {
                let (d, s) = (f64::from(out.diffuse[i][k]), f64::from(out.specular[i][k]));
                // The light maps' own tolerance (2e-3 relative RMS) with room for one pixel.
                assert!(
                    (d - d_ref[k]).abs() < 1e-2 * (1.0 + d_ref[k]),
                    "pixel {i} D {d} vs {}",
                    d_ref[k]
                );
                assert!(
                    (s - s_ref[k]).abs() < 1e-2 * (1.0 + s_ref[k]),
                    "pixel {i} S {s} vs {}",
                    s_ref[k]
                );
            }
            checked += 1;
        }
        assert!(checked >= 10, "checked {checked} pixels");
    }

    #[test]
    fn constant_environment_gives_constant_shading_and_a_full_turn_changes_nothing() {
        let camera = CameraConfig::new();
        let c = [0.7f32, 1.2, 2.0];
        let lights: Vec<LightMap> = [1, 16, 32, 64]
            .iter()
            .map(|&n| LightMap::new(n, 16, 8, vec![c; 128]))
            .collect();
        let refs: Vec<&LightMap> = lights.iter().collect();
        let image = sphere_image(12, Pose::new(0.2, 0.1), [0.5; 3]);
        let weights = DEFAULT_SPECULAR_WEIGHTS;
        let out = relight(&image, &refs, &weights, 0.4, &camera, [0.2; 3]).unwrap();
        let w_sum: f32 = weights.iter().sum();
        for i in 0..144 {
            let m = image.mask[i];
            for (k, ck) in c.iter().enumerate() {
                assert!((out.diffuse[i][k] - m * ck).abs() < 1e-5);
                assert!((out.specular[i][k] - m * w_sum * ck).abs() < 1e-5);
            }
            if m == 0.0 {
                assert_eq!(out.relit[i], [0.2; 3], "background shows outside the mask");
            }
        }
        let map = env(5);
        let set = preconvolve(&map, &PreconvolveOptions::default()).unwrap();
        let refs: Vec<&LightMap> = set.maps().iter().collect();
        let a = relight(&image, &refs, &weights, 0.9, &camera, [0.0; 3]).unwrap();
        let b = relight(
            &image,
            &refs,
            &weights,
            0.9 + std::f64::consts::TAU,
            &camera,
            [0.0; 3],
        )
        .unwrap();
        for (x, y) in a.relit.iter().flatten().zip(b.relit.iter().flatten()) {
            assert!((x - y).abs() < 1e-5, "{x} vs {y}");
        }
    }

    #[test]
    fn bad_inputs_are_errors_and_non_unit_normals_are_counted() {
        let camera = CameraConfig::new();
        let lights: Vec<LightMap> = [1, 16]
            .iter()
            .map(|&n| LightMap::new(n, 16, 8, vec![[1.0; 3]; 128]))
            .collect();
        let refs: Vec<&LightMap> = lights.iter().collect();
        let mut image = sphere_image(8, Pose::new(0.0, 0.0), [0.5; 3]);
        let ok = relight(&image, &refs, &[0.1, 0.1], 0.0, &camera, [0.0; 3]).unwrap();
        assert_eq!((ok.renormalised, ok.degenerate), (0, 0));
        assert_eq!(
            relight(&image, &refs, &[0.1], 0.0, &camera, [0.0; 3]).unwrap_err(),
            RelightError::Weights {
                weights: 1,
                maps: 2,
                pixels: 64,
                per_pixel: false
            }
        );
        // Per-pixel weights equal to the uniform ones give the same layers; a wrong count is
        // an error that says how many were wanted.
        let repeated: Vec<f32> = [0.1, 0.1].repeat(64);
        let weighted = SpecularWeights::PerPixel(&repeated);
        let same = relight_weighted(&image, &refs, weighted, 0.0, &camera, [0.0; 3]).unwrap();
        assert_eq!(same, ok);
        let short = SpecularWeights::PerPixel(&repeated[1..]);
        let err = relight_weighted(&image, &refs, short, 0.0, &camera, [0.0; 3]).unwrap_err();
        assert_eq!(
            err.to_string(),
            "127 specular weights for 2 light maps and 64 pixels (want 128)"
        );
        assert_eq!(
            relight(&image, &refs[1..], &[0.1], 0.0, &camera, [0.0; 3]).unwrap_err(),
            RelightError::FirstNotDiffuse(16)
        );
        let centre = 4 * 8 + 4;
        image.normals[centre] = [0.0, 0.0, 2.0];
        image.normals[centre + 1] = [0.0; 3];
        let counted = relight(&image, &refs, &[0.1, 0.1], 0.0, &camera, [0.0; 3]).unwrap();
        assert_eq!((counted.renormalised, counted.degenerate), (1, 1));
        assert_eq!(
            counted.diffuse[centre], ok.diffuse[centre],
            "renormalised, not rescaled"
        );
        image.mask.pop();
        assert!(matches!(
            relight(&image, &refs, &[0.1, 0.1], 0.0, &camera, [0.0; 3]).unwrap_err(),
            RelightError::LayerSize {
                layer: "mask",
                got: 63,
                ..
            }
        ));
        image.mask.push(1.0);
        image.albedo[9] = [f32::NAN, 0.0, 0.0];
        assert_eq!(
            relight(&image, &refs, &[0.1, 0.1], 0.0, &camera, [0.0; 3]).unwrap_err(),
            RelightError::NonFinite {
                layer: "albedo",
                x: 1,
                y: 1
            }
        );
    }
}
