//! The convolution's products by im2col: each image's `[c k k, ho wo]` patch matrix and one
//! product with the `[o, c k k]` weight, the layout Caffe and PyTorch's CPU path use. For
//! small planes, where the patch matrix stays in cache and one product with the long inner
//! dimension `c k^2` beats `k^2` short ones ([`super::shifted`]).

use std::mem::MaybeUninit;

use super::kernels::{matmul, rows, rows_out, rows_uninit, transposed};
use super::{ConvGeometry, Shape};
use crate::flex_extension::zeroed;

/// The columns `lo..hi` of the output along one axis whose input index
/// `out * stride + tap - pad` falls inside `0..n`.
fn valid_range(out_len: usize, n: usize, tap: usize, g: ConvGeometry) -> (usize, usize) {
    let (s, p) = (g.stride, g.pad);
    let lo = if p > tap { (p - tap).div_ceil(s) } else { 0 };
    let hi = if n + p > tap {
        ((n + p - tap - 1) / s + 1).min(out_len)
    } else {
        0
    };
    (lo.min(hi), hi)
}

/// The patch matrix `col(x)` of one image: `[c k k, ho wo]`, row `(c, u, v)`, column `(i, j)`
/// holding `x_pad[c, i s + u, j s + v]`.
fn im2col(x: &[f32], s: Shape, col: &mut [f32]) {
    let (k, g) = (s.k, s.geometry);
    let n = s.ho * s.wo;
    for (r, row) in col.chunks_exact_mut(n).enumerate() {
        let (c, u, v) = (r / (k * k), (r / k) % k, r % k);
        let plane = &x[c * s.h * s.w..(c + 1) * s.h * s.w];
        let (j_lo, j_hi) = valid_range(s.wo, s.w, v, g);
        for (i, out) in row.chunks_exact_mut(s.wo).enumerate() {
            let Some(y) = (i * g.stride + u).checked_sub(g.pad).filter(|y| *y < s.h) else {
                out.fill(0.0);
                continue;
            };
            out[..j_lo].fill(0.0);
            out[j_hi..].fill(0.0);
            if j_lo == j_hi {
                continue;
            }
            let x_row = &plane[y * s.w..(y + 1) * s.w];
            // Input column of output column j: j s + v - pad.
            let first = j_lo * g.stride + v - g.pad;
            if g.stride == 1 {
                out[j_lo..j_hi].copy_from_slice(&x_row[first..first + (j_hi - j_lo)]);
            } else {
                for (o, xi) in out[j_lo..j_hi]
                    .iter_mut()
                    .zip(x_row[first..].iter().step_by(g.stride))
                {
                    *o = *xi;
                }
            }
        }
    }
}

/// The transpose of [`im2col`]: adds every patch-matrix entry back onto the input position
/// it was read from; `x` must start at zero.
fn col2im(col: &[f32], s: Shape, x: &mut [f32]) {
    let (k, g) = (s.k, s.geometry);
    let n = s.ho * s.wo;
    for (r, row) in col.chunks_exact(n).enumerate() {
        let (c, u, v) = (r / (k * k), (r / k) % k, r % k);
        let plane = &mut x[c * s.h * s.w..(c + 1) * s.h * s.w];
        let (j_lo, j_hi) = valid_range(s.wo, s.w, v, g);
        for (i, src) in row.chunks_exact(s.wo).enumerate() {
            let Some(y) = (i * g.stride + u).checked_sub(g.pad).filter(|y| *y < s.h) else {
                continue;
            };
            if j_lo == j_hi {
                continue;
            }
            let x_row = &mut plane[y * s.w..(y + 1) * s.w];
            let first = j_lo * g.stride + v - g.pad;
            if g.stride == 1 {
                for (o, a) in x_row[first..first + (j_hi - j_lo)]
                    .iter_mut()
                    .zip(&src[j_lo..j_hi])
                {
                    *o += a;
                }
            } else {
                for (o, a) in x_row[first..]
                    .iter_mut()
                    .step_by(g.stride)
                    .zip(&src[j_lo..j_hi])
                {
                    *o += a;
                }
            }
        }
    }
}

/// Elements of one image's patch matrix, the scratch the functions below need.
pub(super) fn scratch_len(s: Shape) -> usize {
    s.patch() * s.ho * s.wo
}

/// `y_b = W col(x_b)` for one image (`[o, ho, wo]`, written whole).
pub(super) fn forward_image(
    x_b: &[f32],
    weight: &[f32],
    s: Shape,
    y_b: &mut [MaybeUninit<f32>],
    col: &mut [f32],
    parallelism: gemm::Parallelism,
) {
    let (patch, n) = (s.patch(), s.ho * s.wo);
    im2col(x_b, s, col);
    // SAFETY: `weight` is `[o, patch]`, `col` `[patch, n]`, `y_b` `[o, n]`, written whole.
    unsafe {
        matmul(
            rows_uninit(y_b, n),
            false,
            (s.o, patch, n),
            rows(weight, patch),
            rows(col, n),
            parallelism,
        )
    };
}

/// `x_b = col^T(W^T y_b)` for one image (`[c, h, w]`, written whole).
pub(super) fn adjoint_image(
    y_b: &[f32],
    weight: &[f32],
    s: Shape,
    x_b: &mut [MaybeUninit<f32>],
    col: &mut [f32],
    parallelism: gemm::Parallelism,
) {
    let (patch, n) = (s.patch(), s.ho * s.wo);
    // SAFETY: `W^T` is `[patch, o]` (element `(r, o)` at `weight[o patch + r]`), `y_b`
    // `[o, n]`, `col` `[patch, n]`, written whole.
    unsafe {
        matmul(
            rows_out(col, n),
            false,
            (patch, s.o, n),
            transposed(weight, patch),
            rows(y_b, n),
            parallelism,
        )
    };
    // col2im adds every patch entry onto its input position: `x_b` starts at zero.
    col2im(col, s, zeroed(x_b));
}

/// `dW^T += col(x_b) g_b^T` for one image into `dw_t` (`[c k k, o]`): the product in this
/// orientation, with the long inner dimension `ho wo` contiguous in the patch matrix, runs at
/// 80-90 GFLOP/s on one core where `dW = g col^T` ran at 17-31 (the small discriminators'
/// 64x64 and 32x32 layers), packing the transposed patch matrix.
pub(super) fn weight_gradient_image(
    x_b: &[f32],
    g_b: &[f32],
    s: Shape,
    dw_t: &mut [f32],
    col: &mut [f32],
    parallelism: gemm::Parallelism,
) {
    let (patch, n) = (s.patch(), s.ho * s.wo);
    im2col(x_b, s, col);
    // SAFETY: `col` is `[patch, n]`, `g_b^T` `[n, o]`, `dw_t` `[patch, o]`, initialised.
    unsafe {
        matmul(
            rows_out(dw_t, s.o),
            true,
            (patch, n, s.o),
            rows(col, n),
            transposed(g_b, n),
            parallelism,
        )
    };
}
