//! Dense 2D convolution (one group, square kernel, symmetric zero padding, a stride) and its
//! adjoint as flex operations with hand-written backward passes: im2col and one matrix
//! product per image, the way Caffe and PyTorch's CPU path lower convolutions.
//!
//! [`conv2d`] computes `y[b, o, i, j] = sum_{c, u, v} w[o, c, u, v] x_pad[b, c, i s + u, j s + v]`
//! (`x_pad` zero-padded by `pad`); [`conv2d_adjoint`] is its transpose in `x` (a transposed
//! convolution with the same weight), which the discriminators' explicit R1 gradient is
//! made of. Per image, with `col(x)` the `[c k k, ho wo]` matrix of patches:
//!
//! - forward: `y_b = W col(x_b)`, `W` the weight as `[o, c k k]`;
//! - adjoint: `x_b = col^T(W^T y_b)`, `col^T` scatter-adding patches back (col2im);
//! - weight gradient: `dW = sum_b g_b col(x_b)^T`.
//!
//! Each direction's backward is the other direction plus the weight gradient, so both are
//! exactly differentiable to first order in input and weight. Every discriminator and
//! relighting-network convolution in volux is one of them ([`crate::equalized`]).
//!
//! Flex's own `conv2d` is already im2col + GEMM in the forward pass, but its backward comes from
//! Burn's generic rules: the input gradient is a transposed convolution (a GEMM and a scalar
//! scatter), and the weight gradient a convolution of the batch-transposed input by the
//! batch-transposed output gradient, whose "kernel" is the whole output plane: a GEMM with
//! nine columns and an inner dimension of `batch * ho * wo`, after a copy of the input per
//! kernel position. Here both are one GEMM per image with the shapes the forward pass has.
//! The plain tensor-op versions ([`conv2d_reference`], [`conv2d_adjoint_reference`]) are what
//! other backends run and what the kernels are tested against, with an f64 loop and f64
//! finite differences beside them.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::flex::FlexTensor;
use burn::backend::{Autodiff, Flex, GradientCheckpointingStrategy, TensorMetadata};
use burn::tensor::module;
use burn::tensor::ops::ConvOptions;
use burn::tensor::{DType, DispatchTensor, Tensor};
use burn_dispatch::DispatchKindConversion;
use rayon::prelude::*;

use crate::equalized::conv_transpose_to;
use crate::flex_extension::{Route, autodiff_parts, contiguous, flex_tensor, route};

/// Stride and symmetric zero padding of a convolution.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConvGeometry {
    pub stride: usize,
    pub pad: usize,
}

impl ConvGeometry {
    pub fn new(stride: usize, pad: usize) -> Self {
        assert!(stride >= 1, "stride must be at least 1");
        Self { stride, pad }
    }

    /// Output length along an axis of input length `n` for a kernel of `k` taps.
    pub fn out_len(&self, n: usize, k: usize) -> usize {
        let padded = n + 2 * self.pad;
        assert!(
            padded >= k,
            "an axis of {n} padded by {} is shorter than the kernel ({k})",
            self.pad
        );
        (padded - k) / self.stride + 1
    }
}

/// `conv2d(x, weight)` without bias: `x: [batch, c, h, w]`, `weight: [o, c, k, k]`, output
/// `[batch, o, ho, wo]` (see the module documentation).
pub fn conv2d(x: Tensor<4>, weight: Tensor<4>, geometry: ConvGeometry) -> Tensor<4> {
    let [_, c, h, w] = x.dims();
    let [_, wc, k, k2] = weight.dims();
    assert_eq!(wc, c, "the weight takes {wc} channels, the input has {c}");
    assert_eq!(k, k2, "square kernels only");
    let in_hw = [h, w];
    run(x, weight, geometry, Direction::Forward, in_hw)
}

/// The adjoint of [`conv2d`] in `x` for inputs of spatial size `in_hw`:
/// `y: [batch, o, ho, wo] -> [batch, c, in_hw[0], in_hw[1]]`.
pub fn conv2d_adjoint(
    y: Tensor<4>,
    weight: Tensor<4>,
    geometry: ConvGeometry,
    in_hw: [usize; 2],
) -> Tensor<4> {
    let [_, o, ho, wo] = y.dims();
    let [wo_, _, k, k2] = weight.dims();
    assert_eq!(wo_, o, "the weight gives {wo_} channels, the input has {o}");
    assert_eq!(k, k2, "square kernels only");
    assert_eq!(
        [ho, wo],
        [geometry.out_len(in_hw[0], k), geometry.out_len(in_hw[1], k)],
        "the adjoint of a convolution of {in_hw:?} takes its output size"
    );
    run(y, weight, geometry, Direction::Adjoint, in_hw)
}

/// [`conv2d`] in Burn's tensor ops: the reference, and what other backends run.
pub fn conv2d_reference(x: Tensor<4>, weight: Tensor<4>, geometry: ConvGeometry) -> Tensor<4> {
    let (s, p) = (geometry.stride, geometry.pad);
    module::conv2d(x, weight, None, ConvOptions::new([s, s], [p, p], [1, 1], 1))
}

/// [`conv2d_adjoint`] in Burn's tensor ops: the reference, and what other backends run.
pub fn conv2d_adjoint_reference(
    y: Tensor<4>,
    weight: Tensor<4>,
    geometry: ConvGeometry,
    in_hw: [usize; 2],
) -> Tensor<4> {
    conv_transpose_to(y, weight, geometry.stride, geometry.pad, 1, in_hw)
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Direction {
    /// `x -> y`.
    Forward,
    /// `y -> x`.
    Adjoint,
}

/// Sizes of one convolution: `x: [batch, c, h, w]`, `weight: [o, c, k, k]`,
/// `y: [batch, o, ho, wo]`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Shape {
    batch: usize,
    c: usize,
    h: usize,
    w: usize,
    o: usize,
    k: usize,
    ho: usize,
    wo: usize,
    geometry: ConvGeometry,
}

impl Shape {
    /// From the operand of `direction` (`x` forward, `y` adjoint), the weight and `in_hw`.
    fn new(operand: &[usize], weight: &[usize], geometry: ConvGeometry, in_hw: [usize; 2]) -> Self {
        let (o, c, k) = (weight[0], weight[1], weight[2]);
        let [h, w] = in_hw;
        Self {
            batch: operand[0],
            c,
            h,
            w,
            o,
            k,
            ho: geometry.out_len(h, k),
            wo: geometry.out_len(w, k),
            geometry,
        }
    }

    /// Rows of the patch matrix, `c k k`.
    fn patch(&self) -> usize {
        self.c * self.k * self.k
    }

    fn x_len(&self) -> usize {
        self.c * self.h * self.w
    }

    fn y_len(&self) -> usize {
        self.o * self.ho * self.wo
    }

    /// A 1x1 kernel with stride 1 and no padding: the patch matrix is the input itself.
    fn pointwise(&self) -> bool {
        self.k == 1 && self.geometry == ConvGeometry::new(1, 0)
    }
}

fn run(
    operand: Tensor<4>,
    weight: Tensor<4>,
    geometry: ConvGeometry,
    direction: Direction,
    in_hw: [usize; 2],
) -> Tensor<4> {
    let reference = |a: Tensor<4>, w: Tensor<4>| match direction {
        Direction::Forward => conv2d_reference(a, w, geometry),
        Direction::Adjoint => conv2d_adjoint_reference(a, w, geometry, in_hw),
    };
    if operand.dtype() != DType::F32 || weight.dtype() != DType::F32 {
        return reference(operand, weight);
    }
    match route(&operand.device()) {
        Route::Flex => {
            let (Ok(a), Ok(w)) = (
                operand.try_into_primitive::<Flex>(),
                weight.try_into_primitive::<Flex>(),
            ) else {
                unreachable!("a flex device holds flex tensors")
            };
            let shape = Shape::new(a.shape().as_slice(), w.shape().as_slice(), geometry, in_hw);
            Tensor::from_primitive::<Flex>(apply(direction, &a, &w, shape))
        }
        Route::Autodiff(GradientCheckpointingStrategy::Disabled) => {
            run_autodiff::<NoCheckpointing>(operand, weight, geometry, direction, in_hw)
        }
        Route::Autodiff(GradientCheckpointingStrategy::Balanced) => {
            run_autodiff::<BalancedCheckpointing>(operand, weight, geometry, direction, in_hw)
        }
        Route::Other => reference(operand, weight),
    }
}

/// The autodiff route, for either checkpointing strategy `C`.
fn run_autodiff<C>(
    operand: Tensor<4>,
    weight: Tensor<4>,
    geometry: ConvGeometry,
    direction: Direction,
    in_hw: [usize; 2],
) -> Tensor<4>
where
    C: CheckpointStrategy,
    DispatchTensor: DispatchKindConversion<Autodiff<Flex, C>>,
{
    let (a, a_node) = autodiff_parts::<C, 4>(operand);
    let (w, w_node) = autodiff_parts::<C, 4>(weight);
    let shape = Shape::new(a.shape().as_slice(), w.shape().as_slice(), geometry, in_hw);
    let out = apply(direction, &a, &w, shape);
    let out = match ConvBackward
        .prepare::<C>([a_node, w_node])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => prep.finish(
            ConvState {
                operand: a,
                weight: w,
                shape,
                direction,
            },
            out,
        ),
        OpsKind::UnTracked(prep) => prep.finish(out),
    };
    Tensor::from_primitive::<Autodiff<Flex, C>>(out)
}

#[derive(Debug)]
struct ConvBackward;

#[derive(Clone, Debug)]
struct ConvState {
    /// `x` (forward) or `y` (adjoint).
    operand: FlexTensor,
    weight: FlexTensor,
    shape: Shape,
    direction: Direction,
}

impl Backward<Flex, 2> for ConvBackward {
    type State = ConvState;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [operand_node, weight_node] = ops.parents;
        let grad = grads.consume::<Flex>(&ops.node);
        let s = ops.state;
        let shape = s.shape;
        let weight_shape = vec![shape.o, shape.c, shape.k, shape.k];
        // Forward: y = conv(x); dx = adjoint(g), dW = weight_grad(x, g).
        // Adjoint: x = adjoint(y); dy = conv(G), dW = weight_grad(G, y), since
        // <G, adjoint(y, W)> = <conv(G, W), y>.
        if let Some(node) = weight_node {
            let grad_w = match s.direction {
                Direction::Forward => {
                    weight_gradient(&contiguous(&s.operand), &contiguous(&grad), shape)
                }
                Direction::Adjoint => {
                    weight_gradient(&contiguous(&grad), &contiguous(&s.operand), shape)
                }
            };
            grads.register::<Flex>(node.id, flex_tensor(grad_w, weight_shape));
        }
        if let Some(node) = operand_node {
            let back = match s.direction {
                Direction::Forward => Direction::Adjoint,
                Direction::Adjoint => Direction::Forward,
            };
            grads.register::<Flex>(node.id, apply(back, &grad, &s.weight, shape));
        }
    }
}

/// Runs `direction` on flex tensors: `operand` is `x` (forward) or `y` (adjoint).
fn apply(
    direction: Direction,
    operand: &FlexTensor,
    weight: &FlexTensor,
    shape: Shape,
) -> FlexTensor {
    let (a, w) = (contiguous(operand), contiguous(weight));
    match direction {
        Direction::Forward => flex_tensor(
            forward(&a, &w, shape),
            vec![shape.batch, shape.o, shape.ho, shape.wo],
        ),
        Direction::Adjoint => flex_tensor(
            adjoint(&a, &w, shape),
            vec![shape.batch, shape.c, shape.h, shape.w],
        ),
    }
}

/// Whether each image's GEMM runs on one thread (images in parallel) or on all of them.
fn images_in_parallel(batch: usize) -> bool {
    batch >= rayon::current_num_threads()
}

fn gemm_parallelism(images_in_parallel: bool) -> gemm::Parallelism {
    if images_in_parallel {
        gemm::Parallelism::None
    } else {
        gemm::Parallelism::Rayon(0)
    }
}

/// A row-major matrix view for [`matmul`]: element `(i, j)` at `ptr[i * row + j * col]`.
#[derive(Clone, Copy)]
struct View {
    ptr: *const f32,
    row: isize,
    col: isize,
}

impl View {
    /// A row-major matrix of `cols` columns.
    fn rows(m: &[f32], cols: usize) -> Self {
        Self {
            ptr: m.as_ptr(),
            row: cols as isize,
            col: 1,
        }
    }

    /// The transpose of a row-major matrix of `cols` columns: element `(i, j)` at
    /// `m[j * cols + i]`.
    fn transposed(m: &[f32], cols: usize) -> Self {
        Self {
            ptr: m.as_ptr(),
            row: 1,
            col: cols as isize,
        }
    }
}

/// `dst (m x n, row-major) = [dst +] a (m x k) b (k x n)`.
///
/// # Safety
/// `a` and `b` must address `m x k` and `k x n` valid elements through their strides, and
/// `dst` must hold `m n` elements.
unsafe fn matmul(
    dst: &mut [f32],
    accumulate: bool,
    (m, k, n): (usize, usize, usize),
    a: View,
    b: View,
    parallelism: gemm::Parallelism,
) {
    debug_assert_eq!(dst.len(), m * n);
    if m == 0 || n == 0 {
        return;
    }
    // SAFETY: the caller guarantees the views; `dst` is `m x n` row-major.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            a.ptr,
            a.col,
            a.row,
            b.ptr,
            b.col,
            b.row,
            if accumulate { 1.0 } else { 0.0 },
            1.0,
            false,
            false,
            false,
            parallelism,
        );
    }
}

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

/// Runs `image` on each image's output and input (`(values, per image)` of each), the images
/// in parallel or one after another.
fn for_each_image(
    (out, out_len): (&mut [f32], usize),
    (input, in_len): (&[f32], usize),
    parallel: bool,
    image: impl Fn((&mut [f32], &[f32])) + Send + Sync,
) {
    if parallel {
        out.par_chunks_mut(out_len)
            .zip(input.par_chunks(in_len))
            .for_each(image);
    } else {
        out.chunks_mut(out_len)
            .zip(input.chunks(in_len))
            .for_each(image);
    }
}

/// The patch matrix of image `x_b`: the image itself for a pointwise kernel, else
/// [`im2col`] into `buffer`.
fn patches<'a>(x_b: &'a [f32], s: Shape, buffer: &'a mut Vec<f32>) -> &'a [f32] {
    if s.pointwise() {
        return x_b;
    }
    buffer.resize(s.patch() * s.ho * s.wo, 0.0);
    im2col(x_b, s, buffer);
    buffer
}

/// `y_b = W col(x_b)` for every image.
fn forward(x: &[f32], weight: &[f32], s: Shape) -> Vec<f32> {
    let (patch, n) = (s.patch(), s.ho * s.wo);
    let mut y = vec![0.0f32; s.batch * s.y_len()];
    if y.is_empty() {
        return y;
    }
    let parallel = images_in_parallel(s.batch);
    let image = |(y_b, x_b): (&mut [f32], &[f32])| {
        let mut buffer = Vec::new();
        let col = patches(x_b, s, &mut buffer);
        let w = View::rows(weight, patch);
        let b = View::rows(col, n);
        // SAFETY: `weight` is `[o, patch]`, `col` is `[patch, n]`, `y_b` is `[o, n]`.
        unsafe {
            matmul(
                y_b,
                false,
                (s.o, patch, n),
                w,
                b,
                gemm_parallelism(parallel),
            )
        };
    };
    for_each_image((&mut y, s.y_len()), (x, s.x_len()), parallel, image);
    y
}

/// `x_b = col^T(W^T y_b)` for every image.
fn adjoint(y: &[f32], weight: &[f32], s: Shape) -> Vec<f32> {
    let (patch, n) = (s.patch(), s.ho * s.wo);
    let mut x = vec![0.0f32; s.batch * s.x_len()];
    if x.is_empty() {
        return x;
    }
    let parallel = images_in_parallel(s.batch);
    let image = |(x_b, y_b): (&mut [f32], &[f32])| {
        // W^T: element (r, o) of `[patch, o]` at weight[o * patch + r].
        let wt = View::transposed(weight, patch);
        let b = View::rows(y_b, n);
        let p = gemm_parallelism(parallel);
        if s.pointwise() {
            // SAFETY: `weight` is `[o, patch]`, `y_b` is `[o, n]`, `x_b` is `[patch, n]`.
            unsafe { matmul(x_b, false, (patch, s.o, n), wt, b, p) };
        } else {
            let mut col = vec![0.0f32; patch * n];
            // SAFETY: as above, into `col: [patch, n]`.
            unsafe { matmul(&mut col, false, (patch, s.o, n), wt, b, p) };
            col2im(&col, s, x_b);
        }
    };
    for_each_image((&mut x, s.x_len()), (y, s.y_len()), parallel, image);
    x
}

/// `dW = sum_b g_b col(x_b)^T`, `[o, c k k]`, for inputs `x` and output gradients `g`.
///
/// Each image's product is taken as its transpose, `dW^T += col(x_b) g_b^T` into a
/// `[c k k, o]` buffer, and transposed once at the end: `gemm` runs the product with the
/// long inner dimension `ho wo` at 80-90 GFLOP/s on one core in this orientation and at
/// 17-31 GFLOP/s in the other (`[32, 4096] x [4096, 288]` and `[64, 1024] x [1024, 576]`,
/// the small discriminators' 64x64 and 32x32 layers), where packing the transposed patch
/// matrix dominated.
fn weight_gradient(x: &[f32], g: &[f32], s: Shape) -> Vec<f32> {
    let (patch, n) = (s.patch(), s.ho * s.wo);
    let len = s.o * patch;
    let parallel = images_in_parallel(s.batch);
    // One partial sum per worker's share of the images.
    let shares = if parallel {
        rayon::current_num_threads().min(s.batch)
    } else {
        1
    };
    let per_share = s.batch.div_ceil(shares.max(1)).max(1);
    let share = |images: std::ops::Range<usize>| -> Vec<f32> {
        let mut dw_t = vec![0.0f32; len];
        let mut buffer = Vec::new();
        for (i, b) in images.enumerate() {
            let x_b = &x[b * s.x_len()..(b + 1) * s.x_len()];
            let g_b = &g[b * s.y_len()..(b + 1) * s.y_len()];
            let col = patches(x_b, s, &mut buffer);
            let a = View::rows(col, n);
            // g_b^T: element (j, o) of `[n, o]` at g_b[o * n + j].
            let gt = View::transposed(g_b, n);
            // SAFETY: `col` is `[patch, n]`, `g_b` is `[o, n]`, `dw_t` is `[patch, o]`.
            unsafe {
                matmul(
                    &mut dw_t,
                    i > 0,
                    (patch, n, s.o),
                    a,
                    gt,
                    gemm_parallelism(parallel),
                );
            }
        }
        dw_t
    };
    let ranges: Vec<_> = (0..s.batch)
        .step_by(per_share)
        .map(|start| start..(start + per_share).min(s.batch))
        .collect();
    let partials: Vec<Vec<f32>> = if parallel {
        ranges.into_par_iter().map(share).collect()
    } else {
        ranges.into_iter().map(share).collect()
    };
    let mut partials = partials.into_iter();
    let mut dw_t = partials.next().unwrap_or_else(|| vec![0.0; len]);
    for p in partials {
        for (t, v) in dw_t.iter_mut().zip(p) {
            *t += v;
        }
    }
    // `[patch, o] -> [o, patch]`.
    let mut dw = vec![0.0f32; len];
    for (r, row) in dw_t.chunks_exact(s.o).enumerate() {
        for (o, v) in row.iter().enumerate() {
            dw[o * patch + r] = *v;
        }
    }
    dw
}

#[cfg(test)]
mod tests {
    use burn::tensor::{Device, TensorData};

    use super::*;
    use crate::backend::to_f32_vec;
    use crate::test_support::{conv2d_f64, normals};
    use volux_envmap::random::SplitMix64;

    /// `(x: [batch, c, h, w], o, k, geometry)`: the discriminators' shapes (3x3 'same', 3x3
    /// stride 2 on odd planes, 1x1) at reduced width, the batches that run images in
    /// parallel and one by one, and the awkward ones: a 1x1 plane, padding wider than the
    /// kernel, a stride that skips inputs, a strided 1x1 kernel, an even kernel.
    fn cases() -> Vec<([usize; 4], usize, usize, ConvGeometry)> {
        let g = ConvGeometry::new;
        vec![
            ([4, 8, 12, 12], 6, 3, g(1, 1)),
            ([1, 3, 9, 9], 5, 3, g(2, 0)),
            ([2, 4, 8, 7], 6, 3, g(2, 0)),
            ([3, 5, 6, 6], 4, 1, g(1, 0)),
            ([2, 3, 5, 5], 2, 1, g(2, 0)),
            ([2, 2, 1, 1], 3, 3, g(1, 1)),
            ([1, 2, 5, 11], 3, 3, g(3, 3)),
            ([2, 9, 4, 4], 8, 3, g(1, 1)),
            ([1, 1, 3, 3], 2, 2, g(1, 4)),
        ]
    }

    fn tensor(values: &[f32], shape: [usize; 4], device: &Device) -> Tensor<4> {
        Tensor::from_data(TensorData::new(values.to_vec(), shape), device)
    }

    fn random(rng: &mut SplitMix64, n: usize) -> Vec<f32> {
        normals(rng, n).iter().map(|v| *v as f32).collect()
    }

    fn wide(v: &[f32]) -> Vec<f64> {
        v.iter().map(|x| f64::from(*x)).collect()
    }

    fn out_shape([b, _, h, w]: [usize; 4], o: usize, k: usize, g: ConvGeometry) -> [usize; 4] {
        [b, o, g.out_len(h, k), g.out_len(w, k)]
    }

    /// The adjoint in f64 loops: `y: [b, o, ho, wo]` back to `[b, c, h, w]`.
    fn adjoint_f64(
        y: &[f64],
        [b, c, h, w]: [usize; 4],
        wt: &[f64],
        [o, k]: [usize; 2],
        g: ConvGeometry,
    ) -> Vec<f64> {
        let (ho, wo) = (g.out_len(h, k), g.out_len(w, k));
        let mut x = vec![0.0; b * c * h * w];
        for n in 0..b {
            for oc in 0..o {
                for i in 0..ho {
                    for j in 0..wo {
                        let yv = y[((n * o + oc) * ho + i) * wo + j];
                        for ci in 0..c {
                            for u in 0..k {
                                for v in 0..k {
                                    let (r, s) = (i * g.stride + u, j * g.stride + v);
                                    if r < g.pad || s < g.pad || r - g.pad >= h || s - g.pad >= w {
                                        continue;
                                    }
                                    x[((n * c + ci) * h + r - g.pad) * w + s - g.pad] +=
                                        wt[((oc * c + ci) * k + u) * k + v] * yv;
                                }
                            }
                        }
                    }
                }
            }
        }
        x
    }

    fn assert_close(got: &[f32], want: &[f64], tol: f64, what: &str) {
        assert_eq!(got.len(), want.len(), "{what}: lengths");
        for (i, (g, w)) in got.iter().zip(want).enumerate() {
            assert!(
                (f64::from(*g) - w).abs() <= tol * (1.0 + w.abs()),
                "{what}[{i}]: {g} vs {w}"
            );
        }
    }

    #[test]
    fn both_directions_match_f64_loops_and_the_tensor_op_reference() {
        let device = Device::flex();
        let mut rng = SplitMix64::new(11);
        for (shape, o, k, g) in cases() {
            let what = format!("{shape:?} -> {o}, k {k}, {g:?}");
            let wshape = [o, shape[1], k, k];
            let (xv, wv) = (
                random(&mut rng, shape.iter().product()),
                random(&mut rng, wshape.iter().product()),
            );
            let (x, w) = (tensor(&xv, shape, &device), tensor(&wv, wshape, &device));
            let y = conv2d(x.clone(), w.clone(), g);
            let yshape = out_shape(shape, o, k, g);
            assert_eq!(y.dims(), yshape, "{what}");
            let (want, _) = conv2d_f64(&wide(&xv), shape, &wide(&wv), [o, k], g.stride, g.pad);
            let got = to_f32_vec(y);
            assert_close(&got, &want, 1e-5, &format!("{what}: forward against f64"));
            let reference = to_f32_vec(conv2d_reference(x, w.clone(), g));
            assert_close(
                &got,
                &wide(&reference),
                1e-5,
                &format!("{what}: forward against conv2d"),
            );

            let yv = random(&mut rng, yshape.iter().product());
            let back = to_f32_vec(conv2d_adjoint(
                tensor(&yv, yshape, &device),
                w.clone(),
                g,
                [shape[2], shape[3]],
            ));
            let want = adjoint_f64(&wide(&yv), shape, &wide(&wv), [o, k], g);
            assert_close(&back, &want, 1e-5, &format!("{what}: adjoint against f64"));
            let reference = to_f32_vec(conv2d_adjoint_reference(
                tensor(&yv, yshape, &device),
                w,
                g,
                [shape[2], shape[3]],
            ));
            assert_close(
                &back,
                &wide(&reference),
                1e-5,
                &format!("{what}: adjoint against conv_transpose2d"),
            );
            // <A x, y> = <x, A^T y>, in f64.
            let dot = |a: &[f32], b: &[f32]| -> f64 {
                wide(a).iter().zip(wide(b)).map(|(a, b)| a * b).sum()
            };
            let (lhs, rhs) = (dot(&got, &yv), dot(&xv, &back));
            assert!(
                (lhs - rhs).abs() <= 1e-5 * (1.0 + lhs.abs()),
                "{what}: {lhs} vs {rhs}"
            );
        }
    }

    type Op = fn(Tensor<4>, Tensor<4>, ConvGeometry, [usize; 2]) -> Tensor<4>;

    fn forward_op(x: Tensor<4>, w: Tensor<4>, g: ConvGeometry, _: [usize; 2]) -> Tensor<4> {
        conv2d(x, w, g)
    }
    fn forward_reference(x: Tensor<4>, w: Tensor<4>, g: ConvGeometry, _: [usize; 2]) -> Tensor<4> {
        conv2d_reference(x, w, g)
    }

    /// `0.5 sum(r op(a, w)^2)` and its gradients with respect to `a` and `w`, on autodiff
    /// flex: quadratic, so the gradient depends on the operation's output as well as its
    /// transpose.
    fn grads_of(
        op: Op,
        (a, ashape): (&[f32], [usize; 4]),
        (w, wshape): (&[f32], [usize; 4]),
        g: ConvGeometry,
        in_hw: [usize; 2],
        r: &[f32],
    ) -> (Vec<f32>, Vec<f32>) {
        let device = Device::flex().autodiff();
        let a = tensor(a, ashape, &device).require_grad();
        let w = tensor(w, wshape, &device).require_grad();
        let out = op(a.clone(), w.clone(), g, in_hw);
        let r = tensor(r, out.dims(), &device);
        let grads = (out.clone() * out * r).sum().mul_scalar(0.5).backward();
        (
            to_f32_vec(a.grad(&grads).expect("tracked")),
            to_f32_vec(w.grad(&grads).expect("tracked")),
        )
    }

    #[test]
    fn gradients_match_the_reference_in_both_directions() {
        let mut rng = SplitMix64::new(12);
        for (shape, o, k, g) in cases() {
            let what = format!("{shape:?} -> {o}, k {k}, {g:?}");
            let wshape = [o, shape[1], k, k];
            let yshape = out_shape(shape, o, k, g);
            let in_hw = [shape[2], shape[3]];
            let n = |s: [usize; 4]| s.iter().product::<usize>();
            let w = random(&mut rng, n(wshape));

            let (x, r) = (random(&mut rng, n(shape)), random(&mut rng, n(yshape)));
            let fast = grads_of(forward_op, (&x, shape), (&w, wshape), g, in_hw, &r);
            let slow = grads_of(forward_reference, (&x, shape), (&w, wshape), g, in_hw, &r);
            assert_close(
                &fast.0,
                &wide(&slow.0),
                1e-4,
                &format!("{what}: d conv / dx"),
            );
            assert_close(
                &fast.1,
                &wide(&slow.1),
                1e-4,
                &format!("{what}: d conv / dw"),
            );

            let (y, r) = (random(&mut rng, n(yshape)), random(&mut rng, n(shape)));
            let fast = grads_of(conv2d_adjoint, (&y, yshape), (&w, wshape), g, in_hw, &r);
            let slow = grads_of(
                conv2d_adjoint_reference,
                (&y, yshape),
                (&w, wshape),
                g,
                in_hw,
                &r,
            );
            assert_close(
                &fast.0,
                &wide(&slow.0),
                1e-4,
                &format!("{what}: d adjoint / dy"),
            );
            assert_close(
                &fast.1,
                &wide(&slow.1),
                1e-4,
                &format!("{what}: d adjoint / dw"),
            );
        }
    }

    #[test]
    fn gradients_match_f64_central_differences() {
        let mut rng = SplitMix64::new(13);
        for (shape, o, k, g) in [
            ([2, 2, 5, 4], 3, 3, ConvGeometry::new(2, 1)),
            ([2, 3, 3, 3], 2, 1, ConvGeometry::new(1, 0)),
        ] {
            let wshape = [o, shape[1], k, k];
            let yshape = out_shape(shape, o, k, g);
            let n = |s: [usize; 4]| s.iter().product::<usize>();
            let in_hw = [shape[2], shape[3]];
            // Inputs rounded to f32, so that both sides see the same numbers.
            let (x, w) = (random(&mut rng, n(shape)), random(&mut rng, n(wshape)));
            let (y, rx, ry) = (
                random(&mut rng, n(yshape)),
                random(&mut rng, n(shape)),
                random(&mut rng, n(yshape)),
            );
            let loss = |out: Vec<f64>, r: &[f32]| -> f64 {
                out.iter().zip(wide(r)).map(|(v, r)| 0.5 * r * v * v).sum()
            };
            let forward_loss = |x: &[f64], w: &[f64]| {
                loss(conv2d_f64(x, shape, w, [o, k], g.stride, g.pad).0, &ry)
            };
            let adjoint_loss =
                |y: &[f64], w: &[f64]| loss(adjoint_f64(y, shape, w, [o, k], g), &rx);
            let h = 1e-3;
            // Central differences are exact for these quadratics up to rounding.
            let fd = |f: &dyn Fn(&[f64]) -> f64, at: &[f64]| -> Vec<f64> {
                (0..at.len())
                    .map(|i| {
                        let (mut p, mut m) = (at.to_vec(), at.to_vec());
                        p[i] += h;
                        m[i] -= h;
                        (f(&p) - f(&m)) / (2.0 * h)
                    })
                    .collect()
            };
            let (xw, ww, yw) = (wide(&x), wide(&w), wide(&y));
            let conv = grads_of(forward_op, (&x, shape), (&w, wshape), g, in_hw, &ry);
            let adj = grads_of(conv2d_adjoint, (&y, yshape), (&w, wshape), g, in_hw, &rx);
            let checks: [(&[f32], Vec<f64>, &str); 4] = [
                (&conv.0, fd(&|x| forward_loss(x, &ww), &xw), "conv d/dx"),
                (&conv.1, fd(&|w| forward_loss(&xw, w), &ww), "conv d/dw"),
                (&adj.0, fd(&|y| adjoint_loss(y, &ww), &yw), "adjoint d/dy"),
                (&adj.1, fd(&|w| adjoint_loss(&yw, w), &ww), "adjoint d/dw"),
            ];
            for (got, want, what) in checks {
                assert_close(got, &want, 1e-4, what);
            }
        }
    }

    #[test]
    fn huge_tiny_zero_and_non_finite_inputs() {
        let device = Device::flex();
        let g = ConvGeometry::new(1, 1);
        let w = tensor(&[1e-3; 18], [2, 1, 3, 3], &device);
        for value in [1e30f32, 1e-30, 0.0, -3e4] {
            let y = to_f32_vec(conv2d(
                tensor(&[value; 36], [1, 1, 6, 6], &device),
                w.clone(),
                g,
            ));
            // An interior output sums nine inputs times 1e-3.
            let interior = y[6 + 1];
            let want = f64::from(value) * 9e-3;
            assert!(
                (f64::from(interior) - want).abs() <= 1e-6 * want.abs(),
                "{value}: {interior}"
            );
            assert!(y.iter().all(|v| v.is_finite()), "{value}: {y:?}");
            if value == 0.0 {
                assert!(y.iter().all(|v| *v == 0.0));
            }
        }
        // A NaN reaches exactly the outputs whose window holds it, in both directions, so the
        // training loop's non-finite guard sees it and nothing else is poisoned.
        let mut x = vec![1.0f32; 36];
        x[0] = f32::NAN;
        let y = to_f32_vec(conv2d(tensor(&x, [1, 1, 6, 6], &device), w.clone(), g));
        for (i, v) in y[..36].iter().enumerate() {
            assert_eq!(v.is_nan(), i % 6 <= 1 && i / 6 <= 1, "output {i}: {v}");
        }
        let mut y = vec![1.0f32; 72];
        y[0] = f32::NAN;
        let back = to_f32_vec(conv2d_adjoint(
            tensor(&y, [1, 2, 6, 6], &device),
            w,
            g,
            [6, 6],
        ));
        assert!(back[0].is_nan() && back[35].is_finite());
    }
}
