//! Dense 2D convolution (one group, square kernel, symmetric zero padding, a stride) and its
//! adjoint as flex operations with hand-written backward passes.
//!
//! [`conv2d`] computes `y[b, o, i, j] = sum_{c, u, v} w[o, c, u, v] x_pad[b, c, i s + u, j s + v]`
//! (`x_pad` zero-padded by `pad`); [`conv2d_adjoint`] is its transpose in `x` (a transposed
//! convolution with the same weight), which the discriminators' explicit R1 gradient is
//! made of. Each direction's backward is the other direction plus the weight gradient
//! `dW = sum_b g_b col(x_b)^T` (`col(x)` the `[c k k, ho wo]` matrix of patches), so both are
//! exactly differentiable to first order in input and weight. Every discriminator and
//! relighting-network convolution in volux is one of them ([`crate::equalized`]).
//!
//! The products (`kernels`) take each image by one of two lowerings, chosen by its plane
//! size: im2col and one matrix product (`patches`, the way Caffe and PyTorch's CPU path
//! lower convolutions) for small planes, and `k^2` shifted products over the polyphase
//! planes of the padded input (`shifted`), with no patch matrix, for large ones.
//!
//! Flex's own `conv2d` is im2col + GEMM in the forward pass, but its backward comes from
//! Burn's generic rules: the input gradient is a transposed convolution (a GEMM and a scalar
//! scatter), and the weight gradient a convolution of the batch-transposed input by the
//! batch-transposed output gradient, whose "kernel" is the whole output plane: a GEMM with
//! nine columns and an inner dimension of `batch * ho * wo`, after a copy of the input per
//! kernel position. Here both are products with the shapes the forward pass has.
//! The plain tensor-op versions ([`conv2d_reference`], [`conv2d_adjoint_reference`]) are what
//! other backends run and what the kernels are tested against (each lowering on every test
//! shape), with an f64 loop and f64 finite differences beside them.

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

use crate::equalized::conv_transpose_to;
use crate::flex_extension::{Route, autodiff_parts, contiguous, flex_tensor, route};
use kernels::{adjoint, forward, weight_gradient};

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

mod kernels;
mod patches;
mod shifted;
mod winograd;

#[cfg(test)]
mod tests;
