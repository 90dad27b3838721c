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
mod tests;
