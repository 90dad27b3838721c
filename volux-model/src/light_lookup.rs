//! Light-map look-up on tensors (paper section 3.2, eq. 2): `D = L_1(n)` and
//! `S = sum_i w_i L_{n_i}(r)` sample preconvolved light maps at directions the network
//! computes, so the look-up must be differentiable with respect to the direction.
//!
//! Each batch element has its own light maps (its own HDRI) and its own yaw rotation. The maps
//! are the padded arrays of [`volux_envmap::LightMap::padded`], sampled bilinearly (as Burn's
//! `grid_sample_2d` with `align_corners = true` would; on the CPU one fused kernel,
//! `bilinear.rs`) at padded pixel `(u W + 0.5, v H + 0.5)`, which is
//! exactly [`volux_envmap::LightMap::lookup_rotated`]: wrapped in azimuth, continuous over the
//! poles.

use std::f32::consts::PI;

use burn::tensor::{Device, Tensor, TensorData};
use volux_envmap::LightMap;

mod bilinear;
mod lighting;

pub use lighting::{Lighting, LightingError, LightingTensorError, lighting_tensors};

/// Keeps `atan2` and `sqrt` differentiable exactly at the poles, where the azimuth is
/// undefined (it moves `theta` by at most 1e-6 rad there).
const POLE_EPS: f32 = 1e-12;

/// One light map (one Phong exponent) per batch element, on a device.
#[derive(Clone, Debug)]
pub struct LightMapBatch {
    /// `[batch, 3, height + 2, width + 2]`, the padded layout.
    padded: Tensor<4>,
    exponent: u32,
}

/// Why a batch of light maps cannot be built.
#[derive(Debug, thiserror::Error)]
pub enum LightLookupError {
    #[error("a light-map batch needs at least one map")]
    Empty,
    #[error(
        "light maps in one batch must share exponent and size: map {index} is n={exponent} {width}x{height}, map 0 is n={exponent0} {width0}x{height0}"
    )]
    Mismatch {
        index: usize,
        exponent: u32,
        width: usize,
        height: usize,
        exponent0: u32,
        width0: usize,
        height0: usize,
    },
}

impl LightMapBatch {
    /// Stacks `maps` (one per batch element, same exponent and size) on `device`.
    pub fn new(maps: &[&LightMap], device: &Device) -> Result<Self, LightLookupError> {
        let first = maps.first().ok_or(LightLookupError::Empty)?;
        let (w, h) = (first.width(), first.height());
        for (index, m) in maps.iter().enumerate() {
            if m.width() != w || m.height() != h || m.exponent() != first.exponent() {
                return Err(LightLookupError::Mismatch {
                    index,
                    exponent: m.exponent(),
                    width: m.width(),
                    height: m.height(),
                    exponent0: first.exponent(),
                    width0: w,
                    height0: h,
                });
            }
        }
        let (pw, ph) = (w + 2, h + 2);
        let mut data = Vec::with_capacity(maps.len() * 3 * pw * ph);
        for m in maps {
            let padded = m.padded();
            for c in 0..3 {
                data.extend(padded.iter().map(|t| t[c]));
            }
        }
        let padded = Tensor::<4>::from_data(TensorData::new(data, [maps.len(), 3, ph, pw]), device);
        Ok(Self {
            padded,
            exponent: first.exponent(),
        })
    }

    /// The Phong exponent the maps share.
    pub fn exponent(&self) -> u32 {
        self.exponent
    }

    /// Batch size.
    pub fn batch(&self) -> usize {
        self.padded.dims()[0]
    }

    /// `L_n` at `dirs` (`[batch, points, 3]`, need not be normalised) of each element's
    /// environment rotated by `yaw[b]` radians about +y (`None`: no rotation). Returns
    /// `[batch, points, 3]`, differentiable with respect to `dirs` (and `yaw`).
    pub fn lookup(&self, dirs: Tensor<3>, yaw: Option<Tensor<1>>) -> Tensor<3> {
        let (u, v) = directions_to_uv(dirs, yaw);
        self.lookup_uv(u, v)
    }

    /// `L_n` at texture coordinates from [`directions_to_uv`] (`[batch, points, 1]` each), so
    /// that several maps sampled in one direction share its conversion.
    pub fn lookup_uv(&self, u: Tensor<3>, v: Tensor<3>) -> Tensor<3> {
        bilinear::sample(&self.padded, u, v)
    }
}

/// Texture coordinates `(u, v)`, `[batch, points, 1]` each, of directions `[batch, points, 3]`
/// (need not be normalised) in each element's environment rotated by `yaw[b]` radians about
/// +y: `u` wrapped to [0, 1), `v` in [0, 1]. Differentiable, also exactly at the poles.
pub fn directions_to_uv(dirs: Tensor<3>, yaw: Option<Tensor<1>>) -> (Tensor<3>, Tensor<3>) {
    let [b, _, _] = dirs.dims();
    let x = dirs.clone().narrow(2, 0, 1);
    let y = dirs.clone().narrow(2, 1, 1);
    let z = dirs.narrow(2, 2, 1);
    let r2 = x.clone() * x.clone() + z.clone() * z.clone();
    // On the vertical axis the azimuth is undefined: use 0 (u = 1/2, as the CPU look-up
    // does) through inputs whose gradient is defined.
    let axis = r2.clone().lower_elem(POLE_EPS);
    let phi = x.mask_fill(axis.clone(), 0.0).atan2(z.mask_fill(axis, 1.0));
    let u = phi.add_scalar(PI).div_scalar(2.0 * PI);
    let u = match yaw {
        Some(yaw) => u - yaw.reshape([b, 1, 1]).div_scalar(2.0 * PI),
        None => u,
    };
    let u = u.clone() - u.floor().detach(); // wrap to [0, 1)
    let v = r2.add_scalar(POLE_EPS).sqrt().atan2(y).div_scalar(PI);
    (u, v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::to_f32_vec;
    use volux_envmap::direction;
    use volux_envmap::random::SplitMix64;
    use volux_envmap::report::random_directions;

    fn map(seed: u64, exponent: u32, h: usize) -> LightMap {
        let mut rng = SplitMix64::new(seed);
        let texels = (0..2 * h * h)
            .map(|_| std::array::from_fn(|_| (rng.next_f64() * 10.0) as f32))
            .collect();
        LightMap::new(exponent, 2 * h, h, texels)
    }

    /// Directions that stress the layout: random, near the seam, at and near the poles.
    fn directions() -> Vec<direction::Dir> {
        let mut d = random_directions(200, 3);
        d.extend([
            [1e-7, 0.3, -1.0],
            [-1e-7, -0.2, -1.0],
            [0.0, 0.0, -1.0],
            [0.0, 1.0, 0.0],
            [0.0, -2.0, 0.0],
            [1e-4, 1.0, 2e-4],
            [-3e-4, -1.0, 1e-4],
            [0.5, 0.1, -0.0001],
        ]);
        d
    }

    fn to_tensor(dirs: &[direction::Dir], batch: usize, device: &Device) -> Tensor<3> {
        let data: Vec<f32> = (0..batch)
            .flat_map(|_| dirs.iter().flat_map(|d| d.map(|v| v as f32)))
            .collect();
        Tensor::from_data(TensorData::new(data, [batch, dirs.len(), 3]), device)
    }

    #[test]
    fn agrees_with_the_cpu_lookup_per_batch_element_and_yaw() {
        check_against_cpu_lookup(&Device::flex());
    }

    /// The GPU path; CI runs it on a software Vulkan driver.
    #[cfg(feature = "wgpu")]
    #[test]
    fn wgpu_agrees_with_the_cpu_lookup() {
        check_against_cpu_lookup(&crate::backend::BackendKind::Wgpu.device().unwrap());
    }

    fn check_against_cpu_lookup(device: &Device) {
        let device = device.clone();
        let maps = [map(1, 16, 8), map(2, 16, 8)];
        let batch = LightMapBatch::new(&[&maps[0], &maps[1]], &device).unwrap();
        let dirs = directions();
        let yaw = [0.0f32, 2.3];
        let out = batch.lookup(
            to_tensor(&dirs, 2, &device),
            Some(Tensor::from_floats(yaw.as_slice(), &device)),
        );
        let out: Vec<f32> = to_f32_vec(out);
        for b in 0..2 {
            for (i, d) in dirs.iter().enumerate() {
                // Rotate the direction in f32 the way the tensor path does.
                let want = maps[b].lookup_rotated(*d, f64::from(yaw[b]));
                for c in 0..3 {
                    let got = out[(b * dirs.len() + i) * 3 + c];
                    assert!(
                        (got - want[c]).abs() <= 1e-4 * (1.0 + want[c].abs()),
                        "b={b} d={d:?} c={c}: {got} vs {}",
                        want[c]
                    );
                }
            }
        }
    }

    #[test]
    fn gradient_with_respect_to_direction_matches_finite_differences() {
        let device = Device::flex().autodiff();
        let lm = map(7, 1, 16);
        let batch = LightMapBatch::new(&[&lm], &device).unwrap();
        let dirs = random_directions(64, 11);
        let weights = [0.3f64, -1.2, 0.7];
        let d = to_tensor(&dirs, 1, &device).require_grad();
        let w = Tensor::<1>::from_floats([0.3f32, -1.2, 0.7], &device).reshape([1, 1, 3]);
        let loss = (batch.lookup(d.clone(), None) * w).sum();
        let grads = loss.backward();
        let g: Vec<f32> = to_f32_vec(d.grad(&grads).unwrap());
        let f = |p: direction::Dir| -> f64 {
            let v = lm.lookup(p);
            (0..3).map(|c| weights[c] * f64::from(v[c])).sum()
        };
        let h = 1e-3; // far below a texel (0.2 rad), far above f32 round-off
        let mut checked = 0;
        for (i, p) in dirs.iter().enumerate() {
            for k in 0..3 {
                let (mut a, mut b) = (*p, *p);
                a[k] += h;
                b[k] -= h;
                // One-sided slopes disagree where the step crosses a texel edge (bilinear kink).
                let (fa, f0, fb) = (f(a), f(*p), f(b));
                if ((fa - f0) - (f0 - fb)).abs() > 2e-2 * (fa - fb).abs().max(1e-3) {
                    continue;
                }
                let fd = (fa - fb) / (2.0 * h);
                let ad = f64::from(g[i * 3 + k]);
                assert!(
                    (fd - ad).abs() <= 2e-2 * (1.0 + fd.abs()),
                    "dir {i} axis {k}: {ad} vs {fd}"
                );
                checked += 1;
            }
        }
        assert!(checked > 150, "only {checked} smooth samples");
    }

    #[test]
    fn gradients_are_finite_at_the_poles_and_the_seam() {
        let device = Device::flex().autodiff();
        let lm = map(5, 16, 8);
        let batch = LightMapBatch::new(&[&lm], &device).unwrap();
        let d = to_tensor(
            &[[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]],
            1,
            &device,
        )
        .require_grad();
        let grads = batch.lookup(d.clone(), None).sum().backward();
        let g: Vec<f32> = to_f32_vec(d.grad(&grads).unwrap());
        assert!(g.iter().all(|v| v.is_finite()), "{g:?}");
    }

    /// `sum(sample(u, v) * r)`: the samples and the gradients with respect to `u` and `v`.
    fn sample_and_grads(
        f: fn(&Tensor<4>, Tensor<3>, Tensor<3>) -> Tensor<3>,
        batch: &LightMapBatch,
        u: &[f32],
        v: &[f32],
        r: &[f32],
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let device = batch.padded.device();
        let (b, n) = (batch.batch(), u.len() / batch.batch());
        let coordinate = |x: &[f32]| {
            Tensor::<1>::from_floats(x, &device)
                .reshape([b, n, 1])
                .require_grad()
        };
        let (ut, vt) = (coordinate(u), coordinate(v));
        let rt = Tensor::<1>::from_floats(r, &device).reshape([b, n, 3]);
        let out = f(&batch.padded, ut.clone(), vt.clone());
        let grads = (out.clone() * rt).sum().backward();
        (
            to_f32_vec(out),
            to_f32_vec(ut.grad(&grads).unwrap()),
            to_f32_vec(vt.grad(&grads).unwrap()),
        )
    }

    /// Coordinates inside the map, on texel centres and edges, at the borders and beyond
    /// them (clamped), for `b` elements.
    fn coordinates(b: usize, seed: u64) -> (Vec<f32>, Vec<f32>) {
        let mut rng = SplitMix64::new(seed);
        let special = [0.0f32, 1.0, 0.5, 1.0 / 16.0, 0.03125, 0.999_999, -0.2, 1.3];
        let mut u = Vec::new();
        let mut v = Vec::new();
        for _ in 0..b {
            for i in 0..300 {
                let (a, c) = if i < special.len() * special.len() {
                    (special[i % special.len()], special[i / special.len()])
                } else {
                    (rng.next_f64() as f32, rng.next_f64() as f32)
                };
                u.push(a);
                v.push(c);
            }
        }
        (u, v)
    }

    #[test]
    fn fused_sampling_matches_grid_sample_in_values_and_gradients() {
        let device = Device::flex().autodiff();
        let maps = [map(3, 16, 8), map(4, 16, 8)];
        let batch = LightMapBatch::new(&[&maps[0], &maps[1]], &device).unwrap();
        let (u, v) = coordinates(2, 5);
        let r: Vec<f32> = (0..u.len() * 3)
            .map(|i| ((i * 37 % 23) as f32 - 11.0) / 7.0)
            .collect();
        let fused = sample_and_grads(bilinear::sample, &batch, &u, &v, &r);
        let reference = sample_and_grads(bilinear::sample_reference, &batch, &u, &v, &r);
        let close = |a: &[f32], b: &[f32], what: &str| {
            assert_eq!(a.len(), b.len(), "{what}");
            for (i, (x, y)) in a.iter().zip(b).enumerate() {
                assert!(
                    (x - y).abs() <= 1e-4 * (1.0 + y.abs()),
                    "{what}[{i}]: {x} vs {y}"
                );
            }
        };
        close(&fused.0, &reference.0, "value");
        // On texel edges the two may take the slope of either side; compare elsewhere.
        let on_edge = |x: f32, size: f32| {
            ((x * size + 0.5).fract()).min(1.0 - (x * size + 0.5).fract()) < 1e-4
        };
        let smooth: Vec<usize> = (0..u.len())
            .filter(|&i| !on_edge(u[i], 16.0) && !on_edge(v[i], 8.0))
            .collect();
        assert!(smooth.len() > 500, "{} smooth points", smooth.len());
        let pick = |g: &[f32]| smooth.iter().map(|&i| g[i]).collect::<Vec<_>>();
        close(&pick(&fused.1), &pick(&reference.1), "d/du");
        close(&pick(&fused.2), &pick(&reference.2), "d/dv");
        // Without autodiff the same kernel runs.
        let plain = LightMapBatch::new(&[&maps[0], &maps[1]], &Device::flex()).unwrap();
        let flex = |x: &[f32]| Tensor::<1>::from_floats(x, &Device::flex()).reshape([2, 300, 1]);
        let values = to_f32_vec(plain.lookup_uv(flex(&u), flex(&v)));
        assert_eq!(values, fused.0);
    }

    #[test]
    fn sampling_gradients_match_f64_central_differences() {
        let device = Device::flex().autodiff();
        let lm = map(9, 32, 8);
        let batch = LightMapBatch::new(&[&lm], &device).unwrap();
        let (u, v) = coordinates(1, 8);
        let r: Vec<f32> = (0..u.len() * 3).map(|i| [0.3, -1.2, 0.7][i % 3]).collect();
        let (_, du, dv) = sample_and_grads(bilinear::sample, &batch, &u, &v, &r);
        // The padded map's bilinear interpolant in f64.
        let (w, h) = (lm.width(), lm.height());
        let padded = lm.padded();
        let value = |u: f64, v: f64| -> f64 {
            let x = (u * w as f64 + 0.5).clamp(0.0, (w + 1) as f64);
            let y = (v * h as f64 + 0.5).clamp(0.0, (h + 1) as f64);
            let (x0, y0) = ((x.floor() as usize).min(w), (y.floor() as usize).min(h));
            let (fx, fy) = (x - x0 as f64, y - y0 as f64);
            let t = |yy: usize, xx: usize, c: usize| f64::from(padded[yy * (w + 2) + xx][c]);
            (0..3)
                .map(|c| {
                    let top = t(y0, x0, c) * (1.0 - fx) + t(y0, x0 + 1, c) * fx;
                    let bottom = t(y0 + 1, x0, c) * (1.0 - fx) + t(y0 + 1, x0 + 1, c) * fx;
                    [0.3, -1.2, 0.7][c] * (top * (1.0 - fy) + bottom * fy)
                })
                .sum()
        };
        let step = 1e-5;
        let mut checked = 0;
        for i in 0..u.len() {
            let (p, q) = (f64::from(u[i]), f64::from(v[i]));
            let fd_u = (value(p + step, q) - value(p - step, q)) / (2.0 * step);
            let fd_v = (value(p, q + step) - value(p, q - step)) / (2.0 * step);
            // Skip kinks (texel edges) and the clamp's edge, where one-sided slopes differ.
            let one_sided = (value(p + step, q) - value(p, q)) / step;
            let one_sided_v = (value(p, q + step) - value(p, q)) / step;
            if (one_sided - fd_u).abs() > 1e-3 * (1.0 + fd_u.abs())
                || (one_sided_v - fd_v).abs() > 1e-3 * (1.0 + fd_v.abs())
            {
                continue;
            }
            for (got, want, what) in [(du[i], fd_u, "u"), (dv[i], fd_v, "v")] {
                let got = f64::from(got);
                assert!(
                    (got - want).abs() <= 1e-3 * (1.0 + want.abs()),
                    "d/d{what} at ({p}, {q}): {got} vs {want}"
                );
            }
            checked += 1;
        }
        assert!(checked > 200, "only {checked} smooth points");
    }

    #[test]
    fn sampling_extreme_coordinates_is_finite_or_nan_never_a_panic() {
        let device = Device::flex().autodiff();
        let lm = map(2, 16, 8);
        let batch = LightMapBatch::new(&[&lm], &device).unwrap();
        let u = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 3e38, -3e38, 0.5];
        let v = [0.5, 0.5, 0.5, 0.5, 0.5, f32::NAN];
        let r = [1.0f32; 18];
        let (values, du, dv) = sample_and_grads(bilinear::sample, &batch, &u, &v, &r);
        for k in 0..6 {
            let nan_in = u[k].is_nan() || v[k].is_nan();
            for c in 0..3 {
                assert_eq!(values[3 * k + c].is_nan(), nan_in, "point {k}: {values:?}");
            }
        }
        // Clamped coordinates have no slope.
        assert_eq!(&du[1..5], &[0.0; 4]);
        assert!(dv[1..5].iter().all(|g| g.is_finite()));
    }

    #[test]
    fn mismatched_maps_are_refused() {
        let device = Device::flex();
        let (a, b) = (map(1, 16, 8), map(2, 16, 4));
        let e = LightMapBatch::new(&[&a, &b], &device).unwrap_err();
        assert!(e.to_string().contains("map 1"), "{e}");
        assert!(LightMapBatch::new(&[], &device).is_err());
    }
}
