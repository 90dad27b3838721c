//! Fourier positional encoding of 3D points (NeRF; paper section 3.2): `x -> [x, sin(2^k pi x),
//! cos(2^k pi x)]` for `k = 0..frequencies`, the NeIIF's input.
//!
//! Optionally each octave first turns the point by its own fixed rotation `R_k`
//! (`x -> [x, sin(2^k pi R_k x), cos(2^k pi R_k x)]`), so that no octave's planes of constant
//! phase line up with the world's axes or with another octave's: with the axis-aligned
//! encoding a field can build horizontal structure out of `sin(2^k pi y)` alone, and on a
//! small volume the top octave then shows as bands of constant height across the whole head
//! (docs/RESULTS.md, "5 octaves over the whole 30 minutes"). The rotations are fixed functions
//! of `k` ([`octave_rotation`]), not parameters.
//!
//! Octaves can open coarse to fine (BARF, Lin et al. 2021): with a window `alpha` (octaves
//! open, fractional), octave `k` is weighted by `(1 - cos(pi clamp(alpha - k, 0, 1))) / 2`, so
//! a closed octave feeds the field zeros and one opening rises smoothly from 0 to 1. The
//! training schedule sets the window (`[schedule] open_octaves`, `octave_fade_kimg`); it is
//! state of the run, not a parameter, and is not saved with the weights.

use std::f64::consts::PI;

use burn::config::Config;
use burn::module::Module;
use burn::tensor::{Tensor, TensorData};

/// Configuration of a [`PositionalEncoding`].
#[derive(Config, Debug)]
pub struct PositionalEncodingConfig {
    /// Number of octaves `F` (10 in the paper).
    #[config(default = 10)]
    pub frequencies: usize,
    /// Whether the raw coordinates come first in the output.
    #[config(default = true)]
    pub include_input: bool,
    /// Whether each octave turns the point by its own fixed rotation first (the paper's
    /// encoding is axis-aligned: false).
    #[config(default = false)]
    pub rotated: bool,
}

/// The encoding; it has no parameters.
#[derive(Module, Debug)]
pub struct PositionalEncoding {
    pub frequencies: usize,
    pub include_input: bool,
    pub rotated: bool,
    /// Octaves open (BARF's `alpha`; fractional while one opens); `None`: all, the paper's
    /// encoding. Set by the training schedule ([`Self::set_window`]).
    #[module(skip)]
    pub window: Option<f64>,
}

/// BARF's weight of octave `k` at window `alpha`: 0 while closed, `(1 - cos(pi t)) / 2` while
/// opening (`t = alpha - k` in `[0, 1]`), 1 once open.
pub fn octave_weight(alpha: f64, k: usize) -> f64 {
    let t = (alpha - k as f64).clamp(0.0, 1.0);
    (1.0 - (PI * t).cos()) / 2.0
}

impl PositionalEncodingConfig {
    pub fn init(&self) -> PositionalEncoding {
        PositionalEncoding {
            frequencies: self.frequencies,
            include_input: self.include_input,
            rotated: self.rotated,
            window: None,
        }
    }
}

/// The largest share of a world axis in any direction of a rotated octave: the rotation of
/// each octave is drawn again until no direction it measures lies within 25.8 degrees
/// (`acos 0.9`) of an axis.
const MAX_AXIS_COSINE: f64 = 0.9;

/// The fixed rotation of octave `k`: the first uniformly distributed rotation (Shoemake's
/// unit quaternion from three uniform numbers, drawn from `splitmix64` seeded by `k`) whose
/// rows all lie off the axes ([`MAX_AXIS_COSINE`]), so every build and every platform turns
/// octave `k` the same way. Row `i` is the direction whose phase the encoding's `i`-th
/// coordinate of that octave measures.
pub fn octave_rotation(k: usize) -> [[f64; 3]; 3] {
    let mut state = 0x9e37_79b9_7f4a_7c15_u64 ^ (k as u64).wrapping_mul(0xd1b5_4a32_d192_ed03);
    let mut uniform = || {
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64
    };
    loop {
        let r = quaternion_rotation(uniform(), uniform(), uniform());
        if r.iter().flatten().all(|v| v.abs() < MAX_AXIS_COSINE) {
            return r;
        }
    }
}

/// Shoemake's uniform rotation from three numbers uniform in `[0, 1)`.
fn quaternion_rotation(u1: f64, u2: f64, u3: f64) -> [[f64; 3]; 3] {
    let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
    let (x, y, z, w) = (
        a * (2.0 * PI * u2).sin(),
        a * (2.0 * PI * u2).cos(),
        b * (2.0 * PI * u3).sin(),
        b * (2.0 * PI * u3).cos(),
    );
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - z * w),
            2.0 * (x * z + y * w),
        ],
        [
            2.0 * (x * y + z * w),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - x * w),
        ],
        [
            2.0 * (x * z - y * w),
            2.0 * (y * z + x * w),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

impl PositionalEncoding {
    /// Opens the first `alpha` octaves (fractional: the next one partly); `None`, or any
    /// `alpha >= frequencies`, opens all. A window at or past every octave leaves the
    /// encoding exactly the paper's.
    pub fn set_window(&mut self, alpha: Option<f64>) {
        self.window = alpha.filter(|&a| a < self.frequencies as f64);
    }

    /// The weight of octave `k` under the window: 1 for an open one.
    pub fn weight(&self, k: usize) -> f64 {
        self.window.map_or(1.0, |alpha| octave_weight(alpha, k))
    }

    /// Output features per input coordinate triple: `3 (include_input) + 6 F`.
    pub fn output_dim(&self) -> usize {
        3 * usize::from(self.include_input) + 6 * self.frequencies
    }

    /// Octave `k`'s coordinates of `x: [points, 3]`, scaled by its frequency: `2^k pi x`, or
    /// `2^k pi R_k x` when rotated.
    fn octave(&self, x: &Tensor<2>, k: usize) -> Tensor<2> {
        let f = PI * 2f64.powi(k as i32);
        if !self.rotated {
            return x.clone().mul_scalar(f);
        }
        let r = octave_rotation(k);
        // x R^T, with the frequency folded in.
        let rt: Vec<f32> = (0..3)
            .flat_map(|j| (0..3).map(move |i| (f * r[i][j]) as f32))
            .collect();
        x.clone()
            .matmul(Tensor::from_data(TensorData::new(rt, [3, 3]), &x.device()))
    }

    /// `t` times octave `k`'s weight under the window (`t` itself when the octave is open).
    fn weighted(&self, t: Tensor<2>, k: usize) -> Tensor<2> {
        let weight = self.weight(k);
        if weight == 1.0 {
            t
        } else {
            t.mul_scalar(weight)
        }
    }

    /// `[points, 3] -> [points, output_dim]`, laid out as `[x, sin(pi x), cos(pi x),
    /// sin(2 pi x), cos(2 pi x), ...]` with each block holding the three coordinates (of
    /// `R_k x` when rotated), each octave times its weight under the window.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let mut parts = Vec::with_capacity(1 + 2 * self.frequencies);
        if self.include_input {
            parts.push(x.clone());
        }
        for k in 0..self.frequencies {
            let scaled = self.octave(&x, k);
            parts.push(self.weighted(scaled.clone().sin(), k));
            parts.push(self.weighted(scaled.cos(), k));
        }
        Tensor::cat(parts, 1)
    }

    /// The encoding and its derivative along its own coordinate: `[points, 3] -> ([points,
    /// output_dim], [points, output_dim])`, where column `c` of the second is `d enc_c / d u`
    /// for the coordinate `u` that feature `c` is a function of (coordinate `c mod 3` of `x`,
    /// or of `R_k x` when rotated). [`Self::fold`] turns a cotangent times this into the
    /// gradient in `x`: the NeIIF's reverse sweep ends with the two.
    pub fn forward_with_derivative(&self, x: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let [points, _] = x.dims();
        let device = x.device();
        let mut parts = Vec::with_capacity(1 + 2 * self.frequencies);
        let mut derivs = Vec::with_capacity(1 + 2 * self.frequencies);
        if self.include_input {
            parts.push(x.clone());
            derivs.push(Tensor::ones([points, 3], &device));
        }
        for k in 0..self.frequencies {
            let f = PI * 2f64.powi(k as i32) * self.weight(k);
            let scaled = self.octave(&x, k);
            let (sin, cos) = (scaled.clone().sin(), scaled.cos());
            derivs.push(cos.clone().mul_scalar(f));
            derivs.push(sin.clone().mul_scalar(-f));
            parts.push(self.weighted(sin, k));
            parts.push(self.weighted(cos, k));
        }
        (Tensor::cat(parts, 1), Tensor::cat(derivs, 1))
    }

    /// The gradient in `x`, `[b, p, 3]`, from `v = u * derivative`, `[b, p, output_dim]`
    /// (a cotangent `u` of the encoding times [`Self::forward_with_derivative`]'s second
    /// output). Axis-aligned, feature `c` depends on coordinate `c mod 3` alone and the
    /// gradient sums the blocks; rotated, block `k` is turned back by `R_k^T`, a product with
    /// the stacked rotations `[output_dim, 3]`.
    pub fn fold(&self, v: Tensor<3>) -> Tensor<3> {
        let [b, p, d] = v.dims();
        if !self.rotated {
            return v.reshape([b, p, d / 3, 3]).sum_dim(2).reshape([b, p, 3]);
        }
        let mut stacked = Vec::with_capacity(d * 3);
        if self.include_input {
            stacked.extend([1.0f32, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
        }
        for k in 0..self.frequencies {
            let r = octave_rotation(k);
            let rows: Vec<f32> = r.iter().flatten().map(|&v| v as f32).collect();
            // The sine block, then the cosine block: both measure the phase of R_k x.
            stacked.extend(&rows);
            stacked.extend(&rows);
        }
        let m = Tensor::<2>::from_data(TensorData::new(stacked, [d, 3]), &v.device());
        v.reshape([b * p, d]).matmul(m).reshape([b, p, 3])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::to_f32_vec;
    use burn::tensor::{Device, TensorData};

    #[test]
    fn matches_the_formula_in_f64() {
        let device = Device::flex();
        let enc = PositionalEncodingConfig::new().init();
        assert_eq!(enc.output_dim(), 63);
        let pts = [[0.1f64, -0.7, 0.35], [0.9, 0.0, -0.05]];
        let data: Vec<f32> = pts.iter().flatten().map(|v| *v as f32).collect();
        let out = enc.forward(Tensor::<2>::from_data(
            TensorData::new(data, [2, 3]),
            &device,
        ));
        assert_eq!(out.dims(), [2, 63]);
        let out: Vec<f32> = to_f32_vec(out);
        for (p, x) in pts.iter().enumerate() {
            let mut want: Vec<f64> = x.to_vec();
            for k in 0..10 {
                let f = PI * 2f64.powi(k);
                want.extend(x.iter().map(|v| (f * v).sin()));
                want.extend(x.iter().map(|v| (f * v).cos()));
            }
            for (i, w) in want.iter().enumerate() {
                // f32 arguments up to 512 pi: absolute error grows with the octave.
                let got = f64::from(out[p * 63 + i]);
                assert!(
                    (got - w).abs() < 2e-4,
                    "point {p} feature {i}: {got} vs {w}"
                );
            }
        }
    }

    /// The Jacobian `d enc_c / d x_j` from `forward_with_derivative` and `fold` (one-hot
    /// cotangents), against central differences of `forward`.
    fn check_jacobian(enc: &PositionalEncoding) {
        let device = Device::flex();
        let x = [0.3f64, -0.45, 0.8];
        let at = |p: [f64; 3]| {
            let data: Vec<f32> = p.iter().map(|v| *v as f32).collect();
            Tensor::<2>::from_data(TensorData::new(data, [1, 3]), &device)
        };
        let d = enc.output_dim();
        let (_, deriv) = enc.forward_with_derivative(at(x));
        let deriv = to_f32_vec(deriv);
        // Row c of the Jacobian: fold a cotangent that is one at feature c.
        let jacobian: Vec<Vec<f32>> = (0..d)
            .map(|c| {
                let mut v = vec![0f32; d];
                v[c] = deriv[c];
                let v = Tensor::<3>::from_data(TensorData::new(v, [1, 1, d]), &device);
                to_f32_vec(enc.fold(v))
            })
            .collect();
        let h = 1e-3;
        for j in 0..3 {
            let (mut a, mut b) = (x, x);
            a[j] += h;
            b[j] -= h;
            let fa = to_f32_vec(enc.forward(at(a)));
            let fb = to_f32_vec(enc.forward(at(b)));
            for c in 0..d {
                let fd = (f64::from(fa[c]) - f64::from(fb[c])) / (2.0 * h);
                let got = f64::from(jacobian[c][j]);
                // Central differences of sin(8 pi x) with h = 1e-3 are good to ~1e-3 relative.
                assert!(
                    (got - fd).abs() < 5e-3 * (1.0 + fd.abs()),
                    "rotated {} j {j} c {c}: {got} vs {fd}",
                    enc.rotated
                );
            }
        }
    }

    #[test]
    fn derivative_matches_central_differences() {
        let enc = PositionalEncodingConfig::new().with_frequencies(4).init();
        check_jacobian(&enc);
        // Axis-aligned, feature c depends on coordinate c mod 3 alone.
        let (_, deriv) = enc.forward_with_derivative(Tensor::<2>::from_data(
            TensorData::new(vec![0.3f32, -0.45, 0.8], [1, 3]),
            &Device::flex(),
        ));
        let deriv = to_f32_vec(deriv);
        for (c, &dc) in deriv.iter().enumerate() {
            let mut v = vec![0f32; enc.output_dim()];
            v[c] = dc;
            let v = Tensor::<3>::from_data(
                TensorData::new(v, [1, 1, enc.output_dim()]),
                &Device::flex(),
            );
            let g = to_f32_vec(enc.fold(v));
            for (j, gj) in g.iter().enumerate() {
                assert_eq!(*gj, if j == c % 3 { dc } else { 0.0 }, "c {c} j {j}");
            }
        }
    }

    #[test]
    fn rotated_derivative_matches_central_differences() {
        let enc = PositionalEncodingConfig::new()
            .with_frequencies(5)
            .with_rotated(true)
            .init();
        check_jacobian(&enc);
    }

    #[test]
    fn octave_rotations_are_proper_distinct_and_off_the_axes() {
        let rotations: Vec<[[f64; 3]; 3]> = (0..16).map(octave_rotation).collect();
        for (k, r) in rotations.iter().enumerate() {
            for i in 0..3 {
                for j in 0..3 {
                    let dot: f64 = (0..3).map(|m| r[i][m] * r[j][m]).sum();
                    let want = if i == j { 1.0 } else { 0.0 };
                    assert!(
                        (dot - want).abs() < 1e-12,
                        "k {k}: R R^T [{i}][{j}] = {dot}"
                    );
                }
            }
            let det = r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
                - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
                + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]);
            assert!((det - 1.0).abs() < 1e-12, "k {k}: det {det}");
            // No direction within 25 degrees of a world axis.
            let largest = r.iter().flatten().fold(0f64, |m, v| m.max(v.abs()));
            assert!(largest < 0.9, "k {k}: a row is {largest} along an axis");
        }
        assert_eq!(octave_rotation(3), rotations[3], "a fixed function of k");
        assert_ne!(rotations[0], rotations[1]);
    }

    #[test]
    fn octave_weights_open_smoothly_one_after_another() {
        assert_eq!(octave_weight(2.0, 2), 0.0);
        assert_eq!(octave_weight(2.0, 1), 1.0);
        assert!((octave_weight(2.5, 2) - 0.5).abs() < 1e-15);
        assert!((octave_weight(2.25, 2) - (1.0 - (PI / 4.0).cos()) / 2.0).abs() < 1e-15);
        for k in 0..4 {
            let mut previous = 0.0;
            for i in 0..=40 {
                let w = octave_weight(f64::from(i) / 10.0, k);
                assert!(w >= previous && (0.0..=1.0).contains(&w), "k {k} i {i}");
                previous = w;
            }
        }
        let mut enc = PositionalEncodingConfig::new().with_frequencies(5).init();
        enc.set_window(Some(5.0));
        assert_eq!(enc.window, None, "a window past every octave is no window");
        enc.set_window(Some(4.3));
        assert_eq!(enc.window, Some(4.3));
        assert_eq!(enc.weight(3), 1.0);
        enc.set_window(None);
        assert!((0..5).all(|k| enc.weight(k) == 1.0));
    }

    #[test]
    fn rotated_encoding_matches_the_formula_in_f64() {
        // A window past every octave is the open encoding.
        check_windowed_formula(true, 5.0);
    }

    /// The encoding with `window` against its f64 formula, octave by octave.
    fn check_windowed_formula(rotated: bool, window: f64) {
        let device = Device::flex();
        let mut enc = PositionalEncodingConfig::new()
            .with_frequencies(5)
            .with_rotated(rotated)
            .init();
        enc.set_window(Some(window));
        let x = [0.1f64, -0.7, 0.35];
        let data: Vec<f32> = x.iter().map(|v| *v as f32).collect();
        let out = to_f32_vec(enc.forward(Tensor::<2>::from_data(
            TensorData::new(data, [1, 3]),
            &device,
        )));
        let mut want: Vec<f64> = x.to_vec();
        for k in 0..5 {
            let r = if rotated {
                octave_rotation(k)
            } else {
                [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
            };
            let f = PI * 2f64.powi(k as i32);
            let t = (window - k as f64).clamp(0.0, 1.0);
            let weight = (1.0 - (PI * t).cos()) / 2.0;
            let u: Vec<f64> = (0..3)
                .map(|i| f * (0..3).map(|j| r[i][j] * x[j]).sum::<f64>())
                .collect();
            want.extend(u.iter().map(|v| weight * v.sin()));
            want.extend(u.iter().map(|v| weight * v.cos()));
        }
        for (i, (got, w)) in out.iter().zip(&want).enumerate() {
            assert!(
                (f64::from(*got) - w).abs() < 2e-5,
                "rotated {rotated} window {window} feature {i}: {got} vs {w}"
            );
        }
        // The closed octave feeds the field exact zeros.
        if window <= 4.0 {
            assert!(out[3 + 24..].iter().all(|&v| v == 0.0));
        }
    }

    #[test]
    fn windowed_encoding_matches_the_formula_in_f64() {
        for rotated in [false, true] {
            for window in [0.0, 2.0, 3.3, 4.0, 4.75] {
                check_windowed_formula(rotated, window);
            }
        }
    }

    #[test]
    fn windowed_derivative_matches_central_differences() {
        for rotated in [false, true] {
            let mut enc = PositionalEncodingConfig::new()
                .with_frequencies(5)
                .with_rotated(rotated)
                .init();
            enc.set_window(Some(3.4));
            check_jacobian(&enc);
        }
    }

    #[test]
    fn an_open_window_is_bit_identical_to_none() {
        let device = Device::flex();
        let x = Tensor::<2>::from_data(
            TensorData::new(vec![0.3f32, -0.45, 0.8, 0.01, 0.2, -0.9], [2, 3]),
            &device,
        );
        let open = PositionalEncodingConfig::new().with_frequencies(5).init();
        let mut windowed = open.clone();
        // Octaves 0-3 are fully open at 4.0: weight exactly 1, so no multiply at all.
        windowed.window = Some(4.0);
        let (a, da) = open.forward_with_derivative(x.clone());
        let (b, db) = windowed.forward_with_derivative(x);
        let (a, da, b, db) = (to_f32_vec(a), to_f32_vec(da), to_f32_vec(b), to_f32_vec(db));
        let (d, first) = (open.output_dim(), 3 + 24);
        for row in 0..2 {
            let open_part = row * d..row * d + first;
            assert_eq!(a[open_part.clone()], b[open_part.clone()], "row {row}");
            assert_eq!(da[open_part.clone()], db[open_part], "row {row}");
        }
    }

    #[test]
    fn can_leave_out_the_raw_input() {
        let enc = PositionalEncodingConfig::new()
            .with_frequencies(4)
            .with_include_input(false)
            .init();
        assert_eq!(enc.output_dim(), 24);
        let out = enc.forward(Tensor::<2>::zeros([5, 3], &Device::flex()));
        assert_eq!(out.dims(), [5, 24]);
    }
}
