//! What turns a synthetic pair into a training input that looks like a photo someone took,
//! so that the estimator does not learn the renderer's quirks: a mirror image (all layers),
//! a background behind the head (two colours in a gradient with a soft pattern), exposure
//! and white balance (in linear light), blur, sensor noise and JPEG compression. Each is
//! drawn from the pair's own random stream, so an augmented pair is a pure function of its
//! seed.

use std::f32::consts::TAU;

use image::codecs::jpeg::JpegEncoder;
use image::{ExtendedColorType, ImageFormat};
use volux_envmap::Rgb;
use volux_envmap::io::{linear_to_srgb, srgb_to_linear};
use volux_envmap::random::SplitMix64;

use crate::synthetic_pairs::SyntheticPair;

/// A training input: the augmented photo and the (mirrored with it) exact layers.
#[derive(Clone, Debug, PartialEq)]
pub struct Augmented {
    pub side: usize,
    /// sRGB in [0, 1].
    pub photo: Vec<Rgb>,
    pub albedo: Vec<Rgb>,
    pub normals: Vec<[f32; 3]>,
    pub mask: Vec<f32>,
}

/// Ranges of the augmentations.
#[derive(Clone, Debug, PartialEq)]
pub struct AugmentationRanges {
    /// Exposure change, stops either way.
    pub exposure_stops: f32,
    /// White balance: each channel's gain is `exp(u)`, `u` uniform in +- this.
    pub white_balance: f32,
    /// Probability and largest sigma (pixels) of a Gaussian blur.
    pub blur: (f32, f32),
    /// Largest standard deviation of Gaussian noise (sRGB units).
    pub noise: f32,
    /// Probability and lowest quality of JPEG compression (highest 95).
    pub jpeg: (f32, u8),
}

impl Default for AugmentationRanges {
    fn default() -> Self {
        AugmentationRanges {
            exposure_stops: 0.7,
            white_balance: 0.15,
            blur: (0.5, 1.2),
            noise: 0.03,
            jpeg: (0.5, 40),
        }
    }
}

fn uniform(rng: &mut SplitMix64, lo: f32, hi: f32) -> f32 {
    lo + (hi - lo) * rng.next_f64() as f32
}

/// A standard normal (Box-Muller).
fn normal(rng: &mut SplitMix64) -> f32 {
    let u = rng.next_f64().max(1e-300);
    let v = rng.next_f64();
    ((-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()) as f32
}

/// `pair` augmented with the draws of `rng` within `ranges`.
pub fn augment(
    pair: &SyntheticPair,
    ranges: &AugmentationRanges,
    rng: &mut SplitMix64,
) -> Augmented {
    let side = pair.side;
    let mut out = Augmented {
        side,
        photo: pair.photo.clone(),
        albedo: pair.albedo.clone(),
        normals: pair.normals.clone(),
        mask: pair.mask.clone(),
    };
    if rng.next_f64() < 0.5 {
        mirror(&mut out);
    }
    let background = background(side, rng);
    for ((p, b), m) in out.photo.iter_mut().zip(&background).zip(&out.mask) {
        for c in 0..3 {
            p[c] += (1.0 - m) * b[c];
        }
    }
    let gain = 2f32.powf(uniform(rng, -ranges.exposure_stops, ranges.exposure_stops));
    let balance: [f32; 3] =
        std::array::from_fn(|_| uniform(rng, -ranges.white_balance, ranges.white_balance).exp());
    for p in &mut out.photo {
        for c in 0..3 {
            p[c] = linear_to_srgb(srgb_to_linear(p[c]) * gain * balance[c]);
        }
    }
    if rng.next_f64() < f64::from(ranges.blur.0) {
        let sigma = uniform(rng, 0.3, ranges.blur.1.max(0.3));
        out.photo = gaussian_blur(&out.photo, side, sigma);
    }
    let sd = uniform(rng, 0.0, ranges.noise);
    for p in &mut out.photo {
        for v in p.iter_mut() {
            *v = (*v + sd * normal(rng)).clamp(0.0, 1.0);
        }
    }
    if rng.next_f64() < f64::from(ranges.jpeg.0) {
        let quality =
            ranges.jpeg.1 + (rng.next_u64() % u64::from(96 - ranges.jpeg.1.min(95))) as u8;
        out.photo = jpeg_round_trip(&out.photo, side, quality);
    }
    out
}

/// Mirrors every layer left to right (normals' x negated).
fn mirror(a: &mut Augmented) {
    let side = a.side;
    for row in 0..side {
        let r = row * side..(row + 1) * side;
        a.photo[r.clone()].reverse();
        a.albedo[r.clone()].reverse();
        a.mask[r.clone()].reverse();
        a.normals[r.clone()].reverse();
        for n in &mut a.normals[r] {
            n[0] = -n[0];
        }
    }
}

/// Two random colours along a random direction, with a soft sinusoidal pattern.
fn background(side: usize, rng: &mut SplitMix64) -> Vec<Rgb> {
    let a: Rgb = std::array::from_fn(|_| rng.next_f64() as f32);
    let b: Rgb = std::array::from_fn(|_| rng.next_f64() as f32);
    let angle = uniform(rng, 0.0, TAU);
    let (dx, dy) = (angle.cos(), angle.sin());
    let amplitude = uniform(rng, 0.0, 0.15);
    let (fx, fy, phase) = (
        uniform(rng, 1.0, 6.0),
        uniform(rng, 1.0, 6.0),
        uniform(rng, 0.0, TAU),
    );
    (0..side * side)
        .map(|i| {
            let (x, y) = (
                (i % side) as f32 / side as f32,
                (i / side) as f32 / side as f32,
            );
            let t = (0.5 + (x - 0.5) * dx + (y - 0.5) * dy).clamp(0.0, 1.0);
            let pattern = amplitude * (TAU * (fx * x + fy * y) + phase).sin();
            std::array::from_fn(|c| (a[c] * (1.0 - t) + b[c] * t + pattern).clamp(0.0, 1.0))
        })
        .collect()
}

/// A separable Gaussian blur with clamped edges.
pub fn gaussian_blur(image: &[Rgb], side: usize, sigma: f32) -> Vec<Rgb> {
    let radius = (3.0 * sigma).ceil() as isize;
    let taps: Vec<f32> = (-radius..=radius)
        .map(|k| (-(k * k) as f32 / (2.0 * sigma * sigma)).exp())
        .collect();
    let total: f32 = taps.iter().sum();
    let at = |i: isize| i.clamp(0, side as isize - 1) as usize;
    let pass = |src: &[Rgb], horizontal: bool| -> Vec<Rgb> {
        (0..side * side)
            .map(|i| {
                let (x, y) = ((i % side) as isize, (i / side) as isize);
                let mut sum = [0.0f32; 3];
                for (j, w) in taps.iter().enumerate() {
                    let k = j as isize - radius;
                    let t = if horizontal {
                        src[(y as usize) * side + at(x + k)]
                    } else {
                        src[at(y + k) * side + x as usize]
                    };
                    for c in 0..3 {
                        sum[c] += w * t[c];
                    }
                }
                sum.map(|v| v / total)
            })
            .collect()
    };
    pass(&pass(image, true), false)
}

/// The image after JPEG compression at `quality` and decoding (itself if either fails, which
/// in-memory 8-bit RGB does not).
fn jpeg_round_trip(image: &[Rgb], side: usize, quality: u8) -> Vec<Rgb> {
    let bytes: Vec<u8> = image
        .iter()
        .flat_map(|p| p.map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8))
        .collect();
    let mut encoded = Vec::new();
    let ok = JpegEncoder::new_with_quality(&mut encoded, quality)
        .encode(&bytes, side as u32, side as u32, ExtendedColorType::Rgb8)
        .is_ok();
    let decoded = ok
        .then(|| image::load_from_memory_with_format(&encoded, ImageFormat::Jpeg).ok())
        .flatten();
    match decoded {
        Some(d) => d
            .into_rgb8()
            .pixels()
            .map(|p| p.0.map(|v| f32::from(v) / 255.0))
            .collect(),
        None => image.to_vec(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pair(side: usize) -> SyntheticPair {
        let n = side * side;
        SyntheticPair {
            side,
            photo: (0..n)
                .map(|i| [0.5, (i % side) as f32 / side as f32, 0.2])
                .collect(),
            albedo: (0..n)
                .map(|i| [(i % side) as f32 / side as f32, 0.3, 0.4])
                .collect(),
            normals: (0..n)
                .map(|i| {
                    if i % side < side / 2 {
                        [0.6, 0.0, 0.8]
                    } else {
                        [0.0, 0.6, 0.8]
                    }
                })
                .collect(),
            mask: (0..n)
                .map(|i| if i / side < side / 2 { 1.0 } else { 0.0 })
                .collect(),
        }
    }

    #[test]
    fn mirroring_flips_layers_and_the_normals_x() {
        let p = pair(8);
        let mut a = Augmented {
            side: 8,
            photo: p.photo.clone(),
            albedo: p.albedo.clone(),
            normals: p.normals.clone(),
            mask: p.mask.clone(),
        };
        mirror(&mut a);
        assert_eq!(a.albedo[0], p.albedo[7]);
        assert_eq!(a.normals[0], [-0.0, 0.6, 0.8]);
        assert_eq!(a.normals[7], [-0.6, 0.0, 0.8]);
        mirror(&mut a);
        assert_eq!(a.normals, p.normals);
    }

    #[test]
    fn augmented_photos_stay_in_range_and_layers_stay_exact() {
        let p = pair(32);
        let ranges = AugmentationRanges {
            blur: (1.0, 1.2),
            jpeg: (1.0, 40),
            ..Default::default()
        };
        for seed in 0..8 {
            let a = augment(&p, &ranges, &mut SplitMix64::new(seed));
            assert!(a.photo.iter().flatten().all(|v| (0.0..=1.0).contains(v)));
            assert!(a.albedo == p.albedo || a.albedo[0] == p.albedo[31]);
            assert_eq!(a.mask, p.mask);
            assert_ne!(a.photo, p.photo);
            assert_eq!(a, augment(&p, &ranges, &mut SplitMix64::new(seed)));
        }
    }

    #[test]
    fn the_blur_keeps_constants_and_spreads_a_point() {
        let flat = vec![[0.3f32, 0.6, 0.9]; 100];
        for t in gaussian_blur(&flat, 10, 1.0) {
            for c in 0..3 {
                assert!((t[c] - flat[0][c]).abs() < 1e-5);
            }
        }
        let mut point = vec![[0.0f32; 3]; 121];
        point[60] = [1.0; 3];
        let blurred = gaussian_blur(&point, 11, 1.0);
        let sum: f32 = blurred.iter().map(|t| t[0]).sum();
        assert!((sum - 1.0).abs() < 1e-4);
        // 1D Gaussian at 1 px with sigma 1, normalised over 7 taps: exp(-1/2) of the centre.
        assert!((blurred[61][0] / blurred[60][0] - (-0.5f32).exp()).abs() < 1e-4);
    }
}
