//! Surface-anchored noise inputs for the upsampler (`[model] upsampler_noise = K`; a deviation
//! from the paper, off by default).
//!
//! Why: every output pixel of the paper's 1x1 upsampler blocks is a function of the volume's
//! features enlarged from the rays around it, so the finest level of the high-resolution albedo
//! can only hold what those features vary by between rays. Texture finer than the rays (hair
//! strands, pores, knit) has no source. StyleGAN2 draws such detail from per-pixel noise
//! inputs; noise drawn per image pixel would move with the camera and break the views'
//! consistency. Here the noise is a field in 3D instead: value noise ([`crate::value_noise`])
//! evaluated at the surface point each output pixel sees (the volume's expected depth along
//! its ray, enlarged bilinearly from the volume's pixels to the block's), seeded per latent
//! from the bits of `z`, and times the ray's opacity (enlarged alike), so the background gets
//! none. The same latent seen from another view gets the same noise on the same point of the
//! head; the noise stays with the surface as the head turns.
//!
//! `K` octaves per block: octave `k` has a lattice spacing of `2^k` output pixels, measured at
//! the orbit's centre ([`pixel_footprint`]). A block with noise has a modulated 1x1 layer
//! `gain` from its output `y` (`C` channels) to `K C` gains and one strength per gain, zero at
//! initialisation (StyleGAN2's noise strength), and outputs `y + sum_k strength_k * gain_k(y) *
//! n_k`: the content decides where and in which colour the noise shows (hair, not skin), and a
//! fresh generator computes what it computed without noise. The points, the opacity and the
//! seeds are constants: no gradient flows into the volume through the noise.

use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor, TensorData};
use volux_envmap::random::{GOLDEN_GAMMA, SplitMix64, mix};

use crate::backend::{to_f32_vec, to_f64_vec};
use crate::modulated::{ModulatedLinear, ModulatedLinearConfig};
use crate::ray_sampling::CameraConfig;
use crate::value_noise::value_noise;

/// The most octaves a block may take (`[model] upsampler_noise`): the coarsest spans 8 output
/// pixels, the volume's scale at the paper's x4 upsampling and coarser than any block needs.
pub const MAX_OCTAVES: usize = 4;

/// One block's noise input: gains from the block's output and their strengths.
#[derive(Module, Debug)]
pub struct NoiseInjection {
    /// Per-pixel modulated layer `C -> K C` (octave-major: gain `k C + c` is octave `k`'s for
    /// channel `c`).
    pub gain: ModulatedLinear,
    /// `[K C]`, zero at initialisation.
    pub strength: Param<Tensor<1>>,
}

impl NoiseInjection {
    /// A noise input of `octaves` octaves for a block of `channels` channels.
    pub fn new(w_dim: usize, channels: usize, octaves: usize, device: &Device) -> Self {
        Self {
            gain: ModulatedLinearConfig::new(w_dim, channels, octaves * channels).init(device),
            strength: Param::from_tensor(Tensor::zeros([octaves * channels], device)),
        }
    }

    /// Number of octaves.
    pub fn octaves(&self) -> usize {
        let [k_c, c] = self.gain.weight.dims();
        k_c / c
    }

    /// `y: [batch, C, h, w]` plus its noise `n: [batch, K, h, w]`, each octave scaled per
    /// channel by its gain at the pixel and its strength.
    pub fn forward(&self, y: Tensor<4>, w: Tensor<2>, n: Tensor<4>) -> Tensor<4> {
        let [b, c, h, wd] = y.dims();
        let k = self.octaves();
        assert_eq!(
            n.dims(),
            [b, k, h, wd],
            "one noise image per octave at the block's resolution"
        );
        let gains = crate::upsampler::per_pixel(y.clone(), |x| self.gain.forward(x, w));
        let scaled = gains * self.strength.val().reshape([1, k * c, 1, 1]);
        let noise = scaled.reshape([b, k, c, h, wd]) * n.reshape([b, k, 1, h, wd]);
        y + noise.sum_dim(1).reshape([b, c, h, wd])
    }
}

/// The noise seed of each latent: a hash of the bits of its row of `z: [batch, z_dim]`, so that
/// a latent keeps its noise in every view and every run, and two latents differ.
pub fn latent_seeds(z: Tensor<2>) -> Vec<u64> {
    let [b, d] = z.dims();
    let bits: Vec<u64> = to_f32_vec(z)
        .into_iter()
        .map(|v| u64::from(v.to_bits()))
        .collect();
    (0..b)
        .map(|i| {
            bits[i * d..(i + 1) * d]
                .iter()
                .fold(0x05EE_D0FA_015E, |h, &v| {
                    SplitMix64::new(mix(h, v, GOLDEN_GAMMA)).next_u64()
                })
        })
        .collect()
}

/// The seed of octave `k` of a latent's noise.
fn octave_seed(seed: u64, k: usize) -> u64 {
    mix(seed, k as u64 + 1, 0xA24B_AED4_963E_E407)
}

/// The world-space width of one pixel of an image of `resolution` pixels a side, at the
/// orbit's centre (the camera's distance): octave 0's lattice spacing.
pub fn pixel_footprint(camera: &CameraConfig, resolution: usize) -> f64 {
    2.0 * camera.radius * (camera.fov_degrees.to_radians() / 2.0).tan() / resolution as f64
}

/// The noise each pixel sees: `points: [batch, 3, h, w]` (world space), one seed per image,
/// octave 0 at lattice spacing `spacing` -> `[batch, octaves, h, w]` of value noise in
/// `[-1, 1]`, on the points' device and in their dtype.
pub fn noise_images(points: Tensor<4>, seeds: &[u64], spacing: f64, octaves: usize) -> Tensor<4> {
    let [b, three, h, w] = points.dims();
    assert_eq!(three, 3, "points are [batch, 3, h, w]");
    assert_eq!(seeds.len(), b, "one seed per image");
    let (device, dtype) = (points.device(), points.dtype());
    let p = to_f64_vec(points);
    let hw = h * w;
    let mut out = vec![0.0; b * octaves * hw];
    for (n, &seed) in seeds.iter().enumerate() {
        for k in 0..octaves {
            let (s, scale) = (octave_seed(seed, k), 1.0 / (spacing * f64::from(1u32 << k)));
            for i in 0..hw {
                let at = |c: usize| p[(n * 3 + c) * hw + i] * scale;
                out[(n * octaves + k) * hw + i] = value_noise(s, [at(0), at(1), at(2)]);
            }
        }
    }
    Tensor::from_data(TensorData::new(out, [b, octaves, h, w]), (&device, dtype))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::modulated::DEMOD_EPS;
    use crate::test_support::{Reseed, f64_tensor, normals, shift_element};
    use burn::tensor::{DType, Distribution};

    #[test]
    fn noise_images_are_value_noise_at_each_pixels_point() {
        let device = Device::flex();
        let (b, h, w, octaves, spacing) = (2, 3, 4, 3, 0.0125);
        let mut rng = SplitMix64::new(3);
        let pv: Vec<f64> = normals(&mut rng, b * 3 * h * w)
            .into_iter()
            .map(|v| 0.3 * v)
            .collect();
        let points = f64_tensor(pv.clone(), [b, 3, h, w], &device);
        let seeds = [11, 12];
        let got = to_f64_vec(noise_images(points, &seeds, spacing, octaves));
        for n in 0..b {
            for k in 0..octaves {
                for i in 0..h * w {
                    let f = 1.0 / (spacing * (1 << k) as f64);
                    let p = [0, 1, 2].map(|c| pv[(n * 3 + c) * h * w + i] * f);
                    let want = value_noise(octave_seed(seeds[n], k), p);
                    assert_eq!(
                        got[(n * octaves + k) * h * w + i],
                        want,
                        "image {n} octave {k} pixel {i}"
                    );
                }
            }
        }
    }

    /// Anchoring: the noise is a function of the point and the seed alone, so two views that see
    /// the same surface point in different pixels get the same value there; octaves and latents
    /// differ; octave 0 varies from pixel to pixel, octave `k` about `2^k` times more slowly.
    #[test]
    fn noise_follows_the_point_not_the_pixel() {
        let device = Device::flex();
        let spacing = 0.0125;
        // A row of points one footprint apart, and the same points in reverse order.
        let row: Vec<f64> = (0..64).map(|i| 0.01 + i as f64 * spacing).collect();
        let make = |xs: Vec<f64>| {
            let n = xs.len();
            let mut v = xs;
            v.extend(vec![0.05; n]);
            v.extend(vec![0.2; n]);
            f64_tensor(v, [1, 3, 1, n], &device)
        };
        let forward = to_f64_vec(noise_images(make(row.clone()), &[5], spacing, 3));
        let reversed = to_f64_vec(noise_images(
            make(row.iter().rev().copied().collect()),
            &[5],
            spacing,
            3,
        ));
        for k in 0..3 {
            for i in 0..64 {
                assert_eq!(forward[k * 64 + i], reversed[k * 64 + 63 - i]);
            }
        }
        let other = to_f64_vec(noise_images(make(row), &[6], spacing, 3));
        assert_ne!(forward, other, "another latent draws other noise");
        let roughness = |k: usize| {
            let o = &forward[k * 64..(k + 1) * 64];
            let steps: f64 = o.windows(2).map(|p| (p[1] - p[0]).abs()).sum();
            let range = o.iter().cloned().fold(f64::MIN, f64::max)
                - o.iter().cloned().fold(f64::MAX, f64::min);
            (steps / 63.0, range)
        };
        let (r0, range0) = roughness(0);
        let (r2, _) = roughness(2);
        assert!(
            range0 > 0.5,
            "octave 0 spans its range over 64 pixels ({range0})"
        );
        assert!(
            r0 > 2.0 * r2,
            "octave 0 changes faster per pixel than octave 2 ({r0} vs {r2})"
        );
    }

    #[test]
    fn latent_seeds_are_per_row_and_repeatable() {
        let device = Device::flex();
        let z = Tensor::<2>::random([3, 16], Distribution::Normal(0.0, 1.0), &device);
        let a = latent_seeds(z.clone());
        assert_eq!(a, latent_seeds(z.clone()));
        assert!(a[0] != a[1] && a[1] != a[2] && a[0] != a[2]);
        // A row's seed does not depend on the other rows.
        assert_eq!(latent_seeds(z.narrow(0, 1, 1)), vec![a[1]]);
    }

    #[test]
    fn footprint_is_the_images_width_over_its_pixels() {
        let camera = CameraConfig::new();
        let width = 2.0 * 2.7 * (18.84f64.to_radians() / 2.0).tan();
        assert!((pixel_footprint(&camera, 64) - width / 64.0).abs() < 1e-12);
    }

    /// The block's output plus its noise, from the definition in f64 loops: the demodulated gain
    /// layer per pixel, its bias, the strengths and the noise.
    #[test]
    fn injection_adds_gained_noise() {
        let device = Device::flex();
        let (b, c, k, h, w, w_dim) = (2, 3, 2, 2, 3, 4);
        let inj = NoiseInjection::new(w_dim, c, k, &device).map(&mut Reseed::new(4, DType::F64));
        let mut rng = SplitMix64::new(5);
        let yv = normals(&mut rng, b * c * h * w);
        let nv = normals(&mut rng, b * k * h * w);
        let wv = normals(&mut rng, b * w_dim);
        let wt = f64_tensor(wv, [b, w_dim], &device);
        let got = to_f64_vec(inj.forward(
            f64_tensor(yv.clone(), [b, c, h, w], &device),
            wt.clone(),
            f64_tensor(nv.clone(), [b, k, h, w], &device),
        ));
        let styles = to_f64_vec(inj.gain.affine.forward(wt));
        let weight = to_f64_vec(inj.gain.effective_weight());
        let bias = to_f64_vec(inj.gain.bias.val());
        let strength = to_f64_vec(inj.strength.val());
        let hw = h * w;
        for n in 0..b {
            for ci in 0..c {
                for i in 0..hw {
                    let mut want = yv[(n * c + ci) * hw + i];
                    for o in 0..k {
                        let g = o * c + ci;
                        let row: Vec<f64> = (0..c)
                            .map(|j| weight[g * c + j] * styles[n * c + j])
                            .collect();
                        let norm = (row.iter().map(|v| v * v).sum::<f64>() + DEMOD_EPS).sqrt();
                        let acc: f64 = (0..c).map(|j| row[j] * yv[(n * c + j) * hw + i]).sum();
                        let gain = acc / norm + bias[g];
                        want += strength[g] * gain * nv[(n * k + o) * hw + i];
                    }
                    let g = got[(n * c + ci) * hw + i];
                    assert!(
                        (g - want).abs() < 1e-12 * (1.0 + want.abs()),
                        "{g} vs {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn a_fresh_injection_adds_nothing() {
        let device = Device::flex();
        let inj = NoiseInjection::new(8, 5, 3, &device);
        assert_eq!(inj.octaves(), 3);
        let y = Tensor::<4>::random([2, 5, 4, 4], Distribution::Normal(0.0, 1.0), &device);
        let n = Tensor::<4>::random([2, 3, 4, 4], Distribution::Normal(0.0, 1.0), &device);
        let w = Tensor::<2>::random([2, 8], Distribution::Normal(0.0, 1.0), &device);
        assert_eq!(to_f32_vec(inj.forward(y.clone(), w, n)), to_f32_vec(y));
    }

    /// Gradients in the block's output, the gain layer's weight and style and the strengths
    /// against central differences of the same f64 forward.
    #[test]
    fn injection_gradients_match_central_differences() {
        let device = Device::flex().autodiff();
        let (b, c, k, h, w, w_dim) = (2, 3, 2, 2, 2, 3);
        let inj = NoiseInjection::new(w_dim, c, k, &device).map(&mut Reseed::new(9, DType::F64));
        let mut rng = SplitMix64::new(10);
        let yv = normals(&mut rng, b * c * h * w);
        let n = f64_tensor(normals(&mut rng, b * k * h * w), [b, k, h, w], &device);
        let wv = normals(&mut rng, b * w_dim);
        let r = f64_tensor(normals(&mut rng, b * c * h * w), [b, c, h, w], &device);
        let loss = |inj: &NoiseInjection, y: Tensor<4>| {
            (inj.forward(y, f64_tensor(wv.clone(), [b, w_dim], &device), n.clone()) * r.clone())
                .sum()
        };
        let y = f64_tensor(yv.clone(), [b, c, h, w], &device).require_grad();
        let grads = loss(&inj, y.clone()).backward();
        let step = 1e-6;
        let close = |got: f64, plus: f64, minus: f64, what: &str| {
            let want = (plus - minus) / (2.0 * step);
            assert!(
                got != 0.0 && (got - want).abs() < 1e-6 * (1.0 + want.abs()),
                "{what}: autodiff {got:e} vs central differences {want:e}"
            );
        };
        let gy = to_f64_vec(y.grad(&grads).unwrap());
        for e in [0, 5, yv.len() - 1] {
            let at = |d: f64| {
                let mut v = yv.clone();
                v[e] += d;
                to_f64_vec(loss(&inj, f64_tensor(v, [b, c, h, w], &device)))[0]
            };
            close(gy[e], at(step), at(-step), &format!("output {e}"));
        }
        let plain = || f64_tensor(yv.clone(), [b, c, h, w], &device);
        type Pick2 = fn(&mut NoiseInjection) -> &mut Param<Tensor<2>>;
        let picks: [(&str, Pick2, usize); 2] = [
            ("gain weight", |i| &mut i.gain.weight, 7),
            ("gain style", |i| &mut i.gain.affine.weight, 4),
        ];
        for (what, pick, e) in picks {
            let got = to_f64_vec(pick(&mut inj.clone()).grad(&grads).unwrap())[e];
            let at = |d: f64| {
                let mut moved = inj.clone();
                shift_element(pick(&mut moved), e, d);
                to_f64_vec(loss(&moved, plain()))[0]
            };
            close(got, at(step), at(-step), what);
        }
        let got = to_f64_vec(inj.strength.grad(&grads).unwrap());
        for e in [0, 3, 5] {
            let at = |d: f64| {
                let mut moved = inj.clone();
                shift_element(&mut moved.strength, e, d);
                to_f64_vec(loss(&moved, plain()))[0]
            };
            close(got[e], at(step), at(-step), &format!("strength {e}"));
        }
    }
}
