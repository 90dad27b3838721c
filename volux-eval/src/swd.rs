//! Sliced Wasserstein distance between two sets of images on multi-scale Laplacian patches
//! (Karras et al. 2018, "Progressive Growing of GANs", appendix D; their `sliced_wasserstein.py`).
//!
//! Each image is split into a Laplacian pyramid down to `min_side` (5x5 binomial filter,
//! mirrored borders, as `cv2.pyrDown` / `pyrUp`). At every level, `patches_per_image` random
//! 7x7 neighbourhoods become descriptors; each set's descriptors are normalised per channel by
//! their own mean and standard deviation; the distance is the mean, over `repeats` draws of
//! `directions` random unit directions, of the 1D Wasserstein-1 distance between the projected
//! descriptor sets (sorted projections, mean absolute difference). Reported times 1e3 per
//! level, like ProGAN's tables. Needs no pretrained network. Unlike ProGAN, both sets take
//! their patches at the same random places.

use rayon::prelude::*;
use serde::Serialize;
use volux_envmap::random::{self, SplitMix64};

/// Side of a descriptor patch.
pub const PATCH: usize = 7;

/// How descriptors and directions are drawn.
#[derive(Clone, Debug, PartialEq)]
pub struct SwdOptions {
    /// Random patches per image and level (ProGAN: 128).
    pub patches_per_image: usize,
    /// Direction draws (ProGAN: 4) of `directions` each (ProGAN: 128).
    pub repeats: usize,
    pub directions: usize,
    /// The pyramid stops at this side (ProGAN: 16).
    pub min_side: usize,
    pub seed: u64,
}

impl Default for SwdOptions {
    fn default() -> Self {
        SwdOptions {
            patches_per_image: 128,
            repeats: 4,
            directions: 128,
            min_side: 16,
            seed: 0,
        }
    }
}

/// A set of `side x side` images of `channels` planes each (planar, row-major).
#[derive(Clone, Debug, PartialEq)]
pub struct ImageSet {
    pub side: usize,
    pub channels: usize,
    pub images: Vec<Vec<f32>>,
}

impl ImageSet {
    pub fn new(side: usize, channels: usize) -> ImageSet {
        ImageSet {
            side,
            channels,
            images: Vec::new(),
        }
    }

    /// Appends the images of a planar `[b, channels, side, side]` buffer.
    pub fn extend_planar(&mut self, data: &[f32]) {
        let n = self.channels * self.side * self.side;
        assert_eq!(data.len() % n, 0, "whole images");
        self.images.extend(data.chunks(n).map(<[f32]>::to_vec));
    }
}

/// The distance at each pyramid level (finest first), times 1e3, and their mean.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Swd {
    /// Side of each level.
    pub sides: Vec<usize>,
    pub levels: Vec<f64>,
    pub mean: f64,
}

/// Why two sets cannot be compared.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SwdError {
    #[error("the sets differ: {0}x{0}x{1} against {2}x{2}x{3}")]
    Shape(usize, usize, usize, usize),
    #[error("the sets hold {0} and {1} images: they must be equal and non-zero")]
    Count(usize, usize),
    #[error("images of side {0} are smaller than a {PATCH}x{PATCH} patch")]
    Small(usize),
}

/// 5x5 binomial filter weights `[1, 4, 6, 4, 1] / 16` (separable).
const BINOMIAL: [f32; 5] = [1.0 / 16.0, 4.0 / 16.0, 6.0 / 16.0, 4.0 / 16.0, 1.0 / 16.0];

/// Mirrored index (`d c b | a b c d | c b a`), scipy's `mode='mirror'`.
fn mirror(i: isize, n: usize) -> usize {
    let n = n as isize;
    if n == 1 {
        return 0;
    }
    let period = 2 * (n - 1);
    let mut i = i.rem_euclid(period);
    if i >= n {
        i = period - i;
    }
    i as usize
}

/// Separable 5x5 binomial blur of one `side x side` plane, mirrored borders, times `gain`.
fn blur(plane: &[f32], side: usize, gain: f32) -> Vec<f32> {
    let pass = |src: &[f32], horizontal: bool| -> Vec<f32> {
        let mut out = vec![0.0f32; side * side];
        for y in 0..side {
            for x in 0..side {
                let mut acc = 0.0f32;
                for (k, w) in BINOMIAL.iter().enumerate() {
                    let o = k as isize - 2;
                    let (sx, sy) = if horizontal {
                        (mirror(x as isize + o, side), y)
                    } else {
                        (x, mirror(y as isize + o, side))
                    };
                    acc += w * src[sy * side + sx];
                }
                out[y * side + x] = acc;
            }
        }
        out
    };
    let mut out = pass(&pass(plane, true), false);
    if gain != 1.0 {
        out.iter_mut().for_each(|v| *v *= gain);
    }
    out
}

/// `cv2.pyrDown`: blur, keep even pixels.
fn pyr_down(plane: &[f32], side: usize) -> Vec<f32> {
    let b = blur(plane, side, 1.0);
    let half = side / 2;
    (0..half * half)
        .map(|i| b[(i / half) * 2 * side + (i % half) * 2])
        .collect()
}

/// `cv2.pyrUp`: zeros between pixels, blur times 4.
fn pyr_up(plane: &[f32], side: usize) -> Vec<f32> {
    let big = side * 2;
    let mut z = vec![0.0f32; big * big];
    for y in 0..side {
        for x in 0..side {
            z[2 * y * big + 2 * x] = plane[y * side + x];
        }
    }
    blur(&z, big, 4.0)
}

/// Laplacian pyramid of one image (planar), finest first; the last level is the Gaussian
/// remainder. Returns each level's planes.
pub fn laplacian_pyramid(
    image: &[f32],
    side: usize,
    channels: usize,
    levels: usize,
) -> Vec<Vec<f32>> {
    let mut pyramid: Vec<Vec<f32>> = vec![image.to_vec()];
    let mut s = side;
    for _ in 1..levels {
        let plane_len = s * s;
        let current = pyramid.last().expect("one level at least").clone();
        let mut down = Vec::with_capacity(channels * plane_len / 4);
        let mut detail = Vec::with_capacity(channels * plane_len);
        for c in 0..channels {
            let plane = &current[c * plane_len..(c + 1) * plane_len];
            let d = pyr_down(plane, s);
            let up = pyr_up(&d, s / 2);
            detail.extend(plane.iter().zip(&up).map(|(a, b)| a - b));
            down.extend(d);
        }
        *pyramid.last_mut().expect("one level at least") = detail;
        pyramid.push(down);
        s /= 2;
    }
    pyramid
}

/// The pyramid's sides: `side, side / 2, ...` down to `min_side` (at least a patch).
pub fn level_sides(side: usize, min_side: usize) -> Vec<usize> {
    let mut sides = vec![side];
    let floor = min_side.max(PATCH);
    while sides.last().is_some_and(|&s| s / 2 >= floor && s % 2 == 0) {
        sides.push(sides.last().expect("non-empty") / 2);
    }
    sides
}

/// `patches` random 7x7 neighbourhoods of each image at one level: `[n * patches, dim]`
/// descriptors (channel-major within a descriptor), normalised per channel by the set's own
/// mean and standard deviation.
fn descriptors(
    levels: &[&[f32]],
    side: usize,
    channels: usize,
    patches: usize,
    rng: &mut SplitMix64,
) -> (Vec<f32>, usize) {
    let h = PATCH / 2;
    let dim = channels * PATCH * PATCH;
    let mut out = Vec::with_capacity(levels.len() * patches * dim);
    let span = (side - 2 * h) as u64;
    for img in levels {
        for _ in 0..patches {
            let cx = h + (rng.next_u64() % span) as usize;
            let cy = h + (rng.next_u64() % span) as usize;
            for c in 0..channels {
                for dy in 0..PATCH {
                    let row = (c * side + cy + dy - h) * side + cx - h;
                    out.extend_from_slice(&img[row..row + PATCH]);
                }
            }
        }
    }
    // Per-channel normalisation over every descriptor and position.
    let per = PATCH * PATCH;
    for c in 0..channels {
        let (mut sum, mut sq, mut n) = (0.0f64, 0.0f64, 0usize);
        for d in out.chunks(dim) {
            for &v in &d[c * per..(c + 1) * per] {
                sum += f64::from(v);
                sq += f64::from(v) * f64::from(v);
                n += 1;
            }
        }
        let mean = sum / n as f64;
        let std = (sq / n as f64 - mean * mean).max(0.0).sqrt();
        let scale = if std > 1e-12 { 1.0 / std } else { 1.0 };
        for d in out.chunks_mut(dim) {
            for v in &mut d[c * per..(c + 1) * per] {
                *v = ((f64::from(*v) - mean) * scale) as f32;
            }
        }
    }
    (out, dim)
}

/// Sliced Wasserstein-1 distance between two equally large descriptor sets `[n, dim]`.
pub fn sliced_wasserstein(
    a: &[f32],
    b: &[f32],
    dim: usize,
    repeats: usize,
    directions: usize,
    seed: u64,
) -> f64 {
    assert_eq!(a.len(), b.len(), "equal descriptor counts");
    let n = a.len() / dim;
    let mut rng = SplitMix64::new(seed);
    let mut results = Vec::with_capacity(repeats);
    for _ in 0..repeats {
        let dirs: Vec<Vec<f32>> = (0..directions)
            .map(|_| {
                let v: Vec<f64> = (0..dim).map(|_| gaussian(&mut rng)).collect();
                let norm = v.iter().map(|x| x * x).sum::<f64>().sqrt();
                v.iter().map(|x| (x / norm) as f32).collect()
            })
            .collect();
        let total: f64 = dirs
            .par_iter()
            .map(|d| {
                let project = |set: &[f32]| -> Vec<f32> {
                    let mut p: Vec<f32> = set
                        .chunks(dim)
                        .map(|x| x.iter().zip(d).map(|(a, b)| a * b).sum())
                        .collect();
                    p.sort_unstable_by(f32::total_cmp);
                    p
                };
                let (pa, pb) = (project(a), project(b));
                pa.iter()
                    .zip(&pb)
                    .map(|(x, y)| f64::from((x - y).abs()))
                    .sum::<f64>()
                    / n as f64
            })
            .sum();
        results.push(total / directions as f64);
    }
    results.iter().sum::<f64>() / repeats as f64
}

/// A standard normal number (Box-Muller).
fn gaussian(rng: &mut SplitMix64) -> f64 {
    let u1 = 1.0 - rng.next_f64();
    let u2 = rng.next_f64();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// The sliced Wasserstein distance between sets `a` and `b` at every pyramid level.
pub fn swd(a: &ImageSet, b: &ImageSet, options: &SwdOptions) -> Result<Swd, SwdError> {
    if (a.side, a.channels) != (b.side, b.channels) {
        return Err(SwdError::Shape(a.side, a.channels, b.side, b.channels));
    }
    if a.images.len() != b.images.len() || a.images.is_empty() {
        return Err(SwdError::Count(a.images.len(), b.images.len()));
    }
    if a.side < PATCH {
        return Err(SwdError::Small(a.side));
    }
    let sides = level_sides(a.side, options.min_side);
    let pyramids = |set: &ImageSet| -> Vec<Vec<Vec<f32>>> {
        set.images
            .par_iter()
            .map(|img| laplacian_pyramid(img, set.side, set.channels, sides.len()))
            .collect()
    };
    let (pa, pb) = (pyramids(a), pyramids(b));
    let mut levels = Vec::with_capacity(sides.len());
    for (l, &side) in sides.iter().enumerate() {
        // Both sets take patches at the same random places (common random numbers): a set
        // against itself is exactly 0, and sampling noise partly cancels.
        let level_seed = random::mix(options.seed, l as u64 + 1, random::GOLDEN_GAMMA);
        let (mut rng_a, mut rng_b) = (SplitMix64::new(level_seed), SplitMix64::new(level_seed));
        let la: Vec<&[f32]> = pa.iter().map(|p| p[l].as_slice()).collect();
        let lb: Vec<&[f32]> = pb.iter().map(|p| p[l].as_slice()).collect();
        let (da, dim) = descriptors(&la, side, a.channels, options.patches_per_image, &mut rng_a);
        let (db, _) = descriptors(&lb, side, b.channels, options.patches_per_image, &mut rng_b);
        let d = sliced_wasserstein(
            &da,
            &db,
            dim,
            options.repeats,
            options.directions,
            options.seed + l as u64,
        );
        levels.push(d * 1e3);
    }
    let mean = levels.iter().sum::<f64>() / levels.len() as f64;
    Ok(Swd {
        sides,
        levels,
        mean,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Smooth random images: a few sinusoids with random phases, per channel.
    fn images(n: usize, side: usize, seed: u64) -> ImageSet {
        let mut rng = SplitMix64::new(seed);
        let mut set = ImageSet::new(side, 3);
        for _ in 0..n {
            let mut img = Vec::with_capacity(3 * side * side);
            for _ in 0..3 {
                let (fx, fy, ph) = (
                    1.0 + 3.0 * rng.next_f64(),
                    1.0 + 3.0 * rng.next_f64(),
                    6.3 * rng.next_f64(),
                );
                for y in 0..side {
                    for x in 0..side {
                        let (u, v) = (x as f64 / side as f64, y as f64 / side as f64);
                        img.push((0.5 + 0.4 * (6.3 * (fx * u + fy * v) + ph).sin()) as f32);
                    }
                }
            }
            set.images.push(img);
        }
        set
    }

    fn noisy(set: &ImageSet, sigma: f64, seed: u64) -> ImageSet {
        let mut rng = SplitMix64::new(seed);
        let mut out = set.clone();
        for img in &mut out.images {
            for v in img.iter_mut() {
                *v += (sigma * gaussian(&mut rng)) as f32;
            }
        }
        out
    }

    #[test]
    fn mirror_reflects_without_repeating_the_edge() {
        let idx: Vec<usize> = (-3..7).map(|i| mirror(i, 4)).collect();
        assert_eq!(idx, vec![3, 2, 1, 0, 1, 2, 3, 2, 1, 0]);
    }

    #[test]
    fn the_pyramid_reconstructs_the_image() {
        let set = images(1, 32, 3);
        let img = &set.images[0];
        let pyr = laplacian_pyramid(img, 32, 3, 3);
        assert_eq!(
            pyr.iter().map(Vec::len).collect::<Vec<_>>(),
            vec![3 * 1024, 3 * 256, 3 * 64]
        );
        // Collapse: up(coarse) + detail at each level gives the image back.
        let mut coarse = pyr[2].clone();
        let mut s = 8;
        for level in (0..2).rev() {
            let mut next = Vec::new();
            for c in 0..3 {
                let up = pyr_up(&coarse[c * s * s..(c + 1) * s * s], s);
                let d = &pyr[level][c * 4 * s * s..(c + 1) * 4 * s * s];
                next.extend(up.iter().zip(d).map(|(a, b)| a + b));
            }
            coarse = next;
            s *= 2;
        }
        let worst = coarse
            .iter()
            .zip(img)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-5, "{worst}");
        // A constant image has no detail and a constant remainder.
        let flat = vec![0.25f32; 3 * 32 * 32];
        let p = laplacian_pyramid(&flat, 32, 3, 3);
        assert!(p[0].iter().chain(&p[1]).all(|v| v.abs() < 1e-6));
        assert!(p[2].iter().all(|v| (v - 0.25).abs() < 1e-6));
    }

    #[test]
    fn level_sides_stop_at_the_minimum() {
        assert_eq!(level_sides(64, 16), vec![64, 32, 16]);
        assert_eq!(level_sides(32, 16), vec![32, 16]);
        assert_eq!(level_sides(16, 16), vec![16]);
        assert_eq!(level_sides(8, 1), vec![8]);
    }

    #[test]
    fn one_dimensional_swd_is_the_wasserstein_distance() {
        // Sorted samples 0..n against the same shifted by 0.5: W1 = 0.5 for every direction.
        let a: Vec<f32> = (0..100).map(|i| i as f32).collect();
        let b: Vec<f32> = a.iter().rev().map(|v| v + 0.5).collect();
        let d = sliced_wasserstein(&a, &b, 1, 2, 8, 1);
        assert!((d - 0.5).abs() < 1e-6, "{d}");
    }

    #[test]
    fn a_set_is_near_itself_and_far_from_its_noisy_copies() {
        let options = SwdOptions {
            patches_per_image: 32,
            repeats: 2,
            directions: 32,
            ..SwdOptions::default()
        };
        let set = images(24, 32, 1);
        let same = swd(&set, &set, &options).unwrap();
        assert_eq!(same.sides, vec![32, 16]);
        assert!(same.levels.iter().all(|&v| v == 0.0), "{same:?}");
        // Added noise moves the distance up, monotonically with its strength.
        let noise: Vec<f64> = [0.01, 0.05, 0.2]
            .iter()
            .map(|&sigma| swd(&set, &noisy(&set, sigma, 5), &options).unwrap().mean)
            .collect();
        assert!(noise[0] > 0.0, "{noise:?}");
        assert!(
            noise[1] > 2.0 * noise[0] && noise[2] > 2.0 * noise[1],
            "{noise:?}"
        );
    }

    #[test]
    fn mismatched_sets_are_errors() {
        let options = SwdOptions::default();
        let a = images(2, 32, 1);
        assert_eq!(
            swd(&a, &images(3, 32, 1), &options),
            Err(SwdError::Count(2, 3))
        );
        assert_eq!(
            swd(&a, &images(2, 16, 1), &options),
            Err(SwdError::Shape(32, 3, 16, 3))
        );
        assert_eq!(
            swd(&images(1, 4, 1), &images(1, 4, 1), &options),
            Err(SwdError::Small(4))
        );
    }
}
