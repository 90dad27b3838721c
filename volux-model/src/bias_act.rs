//! StyleGAN2's `bias_act` for its leaky ReLU: `gain * lrelu(x + bias)` as one operation with a
//! hand-written backward pass, and the activation's derivative applied to a gradient, which the
//! discriminators' explicit input gradient (R1) needs.
//!
//! Written with tensor ops, a layer's bias, leaky ReLU and gain are a broadcast add, Burn's
//! `leaky_relu` (a comparison, a product and a select) and a scalar product: about five passes
//! over the activations forward and as many backward, each recorded by autodiff and each
//! allocating. Here it is one pass forward and one backward (the bias gradient summed in the
//! same pass), the way StyleGAN2-ADA's `bias_act` CUDA kernel does it.
//!
//! The derivative is read from the output's sign: with `gain > 0` and slope 0.2, `y > 0`
//! exactly where `x + bias > 0` (to the underflow of `gain (x + bias)` below `1e-38`, where
//! either derivative multiplies a vanishing value). So an op keeps its output, which the next
//! layer keeps anyway, and nothing else; the discriminator's trace does the same.
//!
//! On the `flex` backend (with or without autodiff) the kernels run; on any other backend, or
//! for dtypes other than f32, [`bias_lrelu_reference`] and [`lrelu_input_gradient_reference`],
//! the same functions in plain tensor ops, do. Both are tested against each other, against
//! f64 loops and against f64 central differences.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::flex::FlexTensor;
use burn::backend::{Autodiff, Flex, GradientCheckpointingStrategy, TensorMetadata};
use burn::tensor::{DType, DispatchTensor, Tensor, activation};
use burn_dispatch::DispatchKindConversion;
use rayon::prelude::*;

use crate::flex_extension::{Route, autodiff_parts, contiguous, flex_tensor, route, written_by};

/// Negative slope of StyleGAN2's leaky ReLU.
pub const LRELU_SLOPE: f64 = 0.2;

/// Elements per parallel task (whole channel planes are never split).
const TASK_ELEMENTS: usize = 1 << 14;

/// `gain * lrelu(x + bias)` with one bias per channel (dimension 1) of `x: [batch, channels,
/// ..]`; `gain > 0`.
pub fn bias_lrelu<const D: usize>(x: Tensor<D>, bias: Option<Tensor<1>>, gain: f64) -> Tensor<D> {
    let channels = check(&x.dims(), gain);
    let bias = bias.unwrap_or_else(|| Tensor::zeros([channels], &x.device()));
    assert_eq!(bias.dims(), [channels], "one bias per channel");
    if x.dtype() != DType::F32 || bias.dtype() != DType::F32 {
        return bias_lrelu_reference(x, Some(bias), gain);
    }
    match route(&x.device()) {
        Route::Flex => {
            let (Ok(x), Ok(bias)) = (
                x.try_into_primitive::<Flex>(),
                bias.try_into_primitive::<Flex>(),
            ) else {
                unreachable!("a flex device holds flex tensors")
            };
            Tensor::from_primitive::<Flex>(forward_flex(&x, &bias, gain))
        }
        Route::Autodiff(GradientCheckpointingStrategy::Disabled) => {
            bias_lrelu_autodiff::<NoCheckpointing, D>(x, bias, gain)
        }
        Route::Autodiff(GradientCheckpointingStrategy::Balanced) => {
            bias_lrelu_autodiff::<BalancedCheckpointing, D>(x, bias, gain)
        }
        Route::Other => bias_lrelu_reference(x, Some(bias), gain),
    }
}

/// [`bias_lrelu`] in plain tensor ops: the reference, and what other backends run.
pub fn bias_lrelu_reference<const D: usize>(
    x: Tensor<D>,
    bias: Option<Tensor<1>>,
    gain: f64,
) -> Tensor<D> {
    let channels = check(&x.dims(), gain);
    let z = match bias {
        Some(b) => {
            let mut shape = [1usize; D];
            shape[1] = channels;
            x + b.reshape(shape)
        }
        None => x,
    };
    activation::leaky_relu(z, LRELU_SLOPE).mul_scalar(gain)
}

/// `g * d y / d z` for `y = bias_lrelu(z, .., gain)` known by its output `y`:
/// `g gain` where `y > 0`, else `g gain 0.2`. Differentiable in `g`; `y` only selects (its
/// derivative is zero almost everywhere) and is treated as a constant.
pub fn lrelu_input_gradient<const D: usize>(g: Tensor<D>, y: Tensor<D>, gain: f64) -> Tensor<D> {
    check(&g.dims(), gain);
    assert_eq!(g.dims(), y.dims(), "a gradient per output");
    if g.dtype() != DType::F32 || y.dtype() != DType::F32 {
        return lrelu_input_gradient_reference(g, y, gain);
    }
    match route(&g.device()) {
        Route::Flex => {
            let (Ok(g), Ok(y)) = (
                g.try_into_primitive::<Flex>(),
                y.try_into_primitive::<Flex>(),
            ) else {
                unreachable!("a flex device holds flex tensors")
            };
            Tensor::from_primitive::<Flex>(gradient_flex(&g, &y, gain))
        }
        Route::Autodiff(GradientCheckpointingStrategy::Disabled) => {
            input_gradient_autodiff::<NoCheckpointing, D>(g, y, gain)
        }
        Route::Autodiff(GradientCheckpointingStrategy::Balanced) => {
            input_gradient_autodiff::<BalancedCheckpointing, D>(g, y, gain)
        }
        Route::Other => lrelu_input_gradient_reference(g, y, gain),
    }
}

/// [`lrelu_input_gradient`] in plain tensor ops.
pub fn lrelu_input_gradient_reference<const D: usize>(
    g: Tensor<D>,
    y: Tensor<D>,
    gain: f64,
) -> Tensor<D> {
    let y = y.detach();
    let slope = y
        .ones_like()
        .mask_fill(y.lower_equal_elem(0.0), LRELU_SLOPE)
        .mul_scalar(gain);
    g * slope
}

/// Checks the rank and the gain; returns the channel count.
fn check(dims: &[usize], gain: f64) -> usize {
    assert!(dims.len() >= 2, "bias_act needs [batch, channels, ..]");
    assert!(
        gain > 0.0 && gain.is_finite(),
        "the gain must be positive, got {gain}"
    );
    dims[1]
}

fn bias_lrelu_autodiff<C, const D: usize>(x: Tensor<D>, bias: Tensor<1>, gain: f64) -> Tensor<D>
where
    C: CheckpointStrategy,
    DispatchTensor: DispatchKindConversion<Autodiff<Flex, C>>,
{
    let (x, x_node) = autodiff_parts::<C, D>(x);
    let (bias, bias_node) = autodiff_parts::<C, 1>(bias);
    let out = forward_flex(&x, &bias, gain);
    let out = match BiasLreluBackward
        .prepare::<C>([x_node, bias_node])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => prep.finish(
            LreluState {
                y: out.clone(),
                gain,
            },
            out,
        ),
        OpsKind::UnTracked(prep) => prep.finish(out),
    };
    Tensor::from_primitive::<Autodiff<Flex, C>>(out)
}

fn input_gradient_autodiff<C, const D: usize>(g: Tensor<D>, y: Tensor<D>, gain: f64) -> Tensor<D>
where
    C: CheckpointStrategy,
    DispatchTensor: DispatchKindConversion<Autodiff<Flex, C>>,
{
    let (g, g_node) = autodiff_parts::<C, D>(g);
    let (y, _) = autodiff_parts::<C, D>(y.detach());
    let out = gradient_flex(&g, &y, gain);
    let out = match InputGradientBackward
        .prepare::<C>([g_node])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => prep.finish(LreluState { y, gain }, out),
        OpsKind::UnTracked(prep) => prep.finish(out),
    };
    Tensor::from_primitive::<Autodiff<Flex, C>>(out)
}

/// What both backward passes keep: the activation's output (its sign is the derivative).
#[derive(Clone, Debug)]
struct LreluState {
    y: FlexTensor,
    gain: f64,
}

#[derive(Debug)]
struct BiasLreluBackward;

impl Backward<Flex, 2> for BiasLreluBackward {
    type State = LreluState;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [x_node, bias_node] = ops.parents;
        let grad = grads.consume::<Flex>(&ops.node);
        if x_node.is_none() && bias_node.is_none() {
            return;
        }
        let (grad_x, grad_bias) = backward_flex(&grad, &ops.state.y, ops.state.gain);
        if let Some(node) = bias_node {
            grads.register::<Flex>(node.id, grad_bias);
        }
        if let Some(node) = x_node {
            grads.register::<Flex>(node.id, grad_x);
        }
    }
}

#[derive(Debug)]
struct InputGradientBackward;

impl Backward<Flex, 1> for InputGradientBackward {
    type State = LreluState;

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [g_node] = ops.parents;
        let grad = grads.consume::<Flex>(&ops.node);
        if let Some(node) = g_node {
            // The operation is linear in `g` with a diagonal factor: its own transpose.
            grads.register::<Flex>(node.id, gradient_flex(&grad, &ops.state.y, ops.state.gain));
        }
    }
}

/// `[batch, channels, rest..]` as (planes of `inner` elements, channels).
fn layout(shape: &[usize]) -> (usize, usize) {
    (shape[2..].iter().product(), shape[1])
}

/// Whole planes per parallel task.
fn planes_per_task(inner: usize) -> usize {
    (TASK_ELEMENTS / inner.max(1)).max(1)
}

fn forward_flex(x: &FlexTensor, bias: &FlexTensor, gain: f64) -> FlexTensor {
    let shape = x.shape().to_vec();
    let (inner, channels) = layout(&shape);
    let (x, bias) = (contiguous(x), contiguous(bias));
    let (positive, negative) = (gain as f32, (gain * LRELU_SLOPE) as f32);
    let per_task = planes_per_task(inner);
    let chunk = per_task * inner.max(1);
    // SAFETY: the chunks of `out` and `x` pair up element for element, and every output
    // element is written.
    let out = unsafe {
        written_by(x.len(), |out| {
            out.par_chunks_mut(chunk)
                .zip(x.par_chunks(chunk))
                .enumerate()
                .for_each(|(task, (out, x))| {
                    let planes = out.chunks_mut(inner.max(1)).zip(x.chunks(inner.max(1)));
                    for (p, (out, x)) in planes.enumerate() {
                        let b = bias[(task * per_task + p) % channels];
                        for (y, &x) in out.iter_mut().zip(x) {
                            let z = x + b;
                            y.write(z * if z > 0.0 { positive } else { negative });
                        }
                    }
                })
        })
    };
    flex_tensor(out, shape)
}

/// `g * dy/dz` from the output `y`.
fn gradient_flex(g: &FlexTensor, y: &FlexTensor, gain: f64) -> FlexTensor {
    let shape = g.shape().to_vec();
    let (g, y) = (contiguous(g), contiguous(y));
    let (positive, negative) = (gain as f32, (gain * LRELU_SLOPE) as f32);
    assert_eq!(
        g.len(),
        y.len(),
        "the gradient and the output differ in size"
    );
    // SAFETY: the chunks of `out`, `g` and `y` pair up element for element (equal lengths),
    // and every output element is written.
    let out = unsafe {
        written_by(g.len(), |out| {
            out.par_chunks_mut(TASK_ELEMENTS)
                .zip(g.par_chunks(TASK_ELEMENTS).zip(y.par_chunks(TASK_ELEMENTS)))
                .for_each(|(out, (g, y))| {
                    for ((o, &g), &y) in out.iter_mut().zip(g).zip(y) {
                        o.write(g * if y > 0.0 { positive } else { negative });
                    }
                })
        })
    };
    flex_tensor(out, shape)
}

/// Gradients with respect to `x` and `bias` for the output gradient `grad`, from the output.
fn backward_flex(grad: &FlexTensor, y: &FlexTensor, gain: f64) -> (FlexTensor, FlexTensor) {
    let shape = y.shape().to_vec();
    let (inner, channels) = layout(&shape);
    let (grad, y) = (contiguous(grad), contiguous(y));
    let (positive, negative) = (gain as f32, (gain * LRELU_SLOPE) as f32);
    assert_eq!(
        grad.len(),
        y.len(),
        "the gradient and the output differ in size"
    );
    let per_task = planes_per_task(inner);
    let chunk = per_task * inner.max(1);
    let mut partial: Vec<Vec<f64>> = Vec::new();
    // SAFETY: the chunks of `grad_x`, `grad` and `y` pair up element for element (equal
    // lengths), and every element of `grad_x` is written.
    let grad_x = unsafe {
        written_by(y.len(), |grad_x| {
            partial = grad_x
                .par_chunks_mut(chunk)
                .zip(grad.par_chunks(chunk).zip(y.par_chunks(chunk)))
                .enumerate()
                .map(|(task, (out, (grad, y)))| {
                    let mut sums = vec![0.0f64; channels];
                    let planes = out
                        .chunks_mut(inner.max(1))
                        .zip(grad.chunks(inner.max(1)).zip(y.chunks(inner.max(1))));
                    for (p, (out, (grad, y))) in planes.enumerate() {
                        let mut sum = 0.0f32;
                        for ((o, &g), &y) in out.iter_mut().zip(grad).zip(y) {
                            let v = g * if y > 0.0 { positive } else { negative };
                            o.write(v);
                            sum += v;
                        }
                        sums[(task * per_task + p) % channels] += f64::from(sum);
                    }
                    sums
                })
                .collect();
        })
    };
    let mut grad_bias = vec![0.0f64; channels];
    for sums in partial {
        for (total, s) in grad_bias.iter_mut().zip(sums) {
            *total += s;
        }
    }
    let grad_bias = grad_bias.into_iter().map(|s| s as f32).collect();
    (
        flex_tensor(grad_x, shape),
        flex_tensor(grad_bias, vec![channels]),
    )
}

#[cfg(test)]
mod tests;
