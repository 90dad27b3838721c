//! The NeIIF's activation as one operation with a hand-written backward pass.
//!
//! A modulated layer's output `y: [batch, p, o]` (pre-activations without bias) becomes
//! `a(z)` with `z = y + bias` and `a` the smooth activation [`crate::neiif::smooth_lrelu`].
//! Written with tensor ops that is about ten elementwise passes over `[batch, p, o]` tensors,
//! each recorded by autodiff and each with its own backward passes; here it is one pass
//! forward and one backward. [`pullback`] is the activation's step in the reverse sweep that
//! gives the normals, `u a'(z)`.
//!
//! On the `flex` backend (with or without autodiff) the fused kernels run; on any other backend
//! [`activate_reference`], the same function in plain tensor ops, does. Both are tested against
//! each other and against f64 finite differences.
//!
//! Backward, with `a' = g (0.2 + 0.8 sigmoid(z))`: `dL/dy = G a'(z)`,
//! `dL/dbias = sum over batch and points of dL/dy`.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::flex::FlexTensor;
use burn::backend::{Autodiff, Flex, GradientCheckpointingStrategy, TensorMetadata};
use burn::tensor::{DType, DispatchTensor, Tensor};
use burn_dispatch::DispatchKindConversion;
use rayon::prelude::*;

use std::mem::MaybeUninit;

use crate::flex_extension::{
    Route, autodiff_parts, contiguous, dispatch_simd, flex_tensor, route, written_by,
};
use crate::neiif::{SMOOTH_GAIN, smooth_lrelu};

/// Rows of `o` channels per parallel task.
const ROWS_PER_TASK: usize = 256;

/// `a(y + bias)` for `y: [batch, p, o]` and `bias: [o]` (see the module documentation).
pub fn activate(y: Tensor<3>, bias: Tensor<1>) -> Tensor<3> {
    let o = y.dims()[2];
    assert_eq!(bias.dims(), [o], "one bias per channel");
    if y.dtype() != DType::F32 || bias.dtype() != DType::F32 {
        return activate_reference(y, bias);
    }
    match route(&y.device()) {
        Route::Flex => {
            let (Ok(y), Ok(bias)) = (
                y.try_into_primitive::<Flex>(),
                bias.try_into_primitive::<Flex>(),
            ) else {
                unreachable!("a flex device holds flex tensors")
            };
            Tensor::from_primitive::<Flex>(forward_flex(&y, &bias))
        }
        Route::Autodiff(GradientCheckpointingStrategy::Disabled) => {
            activate_autodiff::<NoCheckpointing>(y, bias)
        }
        Route::Autodiff(GradientCheckpointingStrategy::Balanced) => {
            activate_autodiff::<BalancedCheckpointing>(y, bias)
        }
        Route::Other => activate_reference(y, bias),
    }
}

/// The same in plain tensor ops: the reference, and what backends other than flex run.
pub fn activate_reference(y: Tensor<3>, bias: Tensor<1>) -> Tensor<3> {
    let o = y.dims()[2];
    smooth_lrelu(y + bias.reshape([1, 1, o]))
}

/// The autodiff route, for either checkpointing strategy `C`.
fn activate_autodiff<C>(y: Tensor<3>, bias: Tensor<1>) -> Tensor<3>
where
    C: CheckpointStrategy,
    DispatchTensor: DispatchKindConversion<Autodiff<Flex, C>>,
{
    let (y, y_node) = autodiff_parts::<C, 3>(y);
    let (bias, bias_node) = autodiff_parts::<C, 1>(bias);
    let out = forward_flex(&y, &bias);
    let out = match ActivateBackward
        .prepare::<C>([y_node, bias_node])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => prep.finish(ActivateState { y, bias }, out),
        OpsKind::UnTracked(prep) => prep.finish(out),
    };
    Tensor::from_primitive::<Autodiff<Flex, C>>(out)
}

#[derive(Debug)]
struct ActivateBackward;

#[derive(Clone, Debug)]
struct ActivateState {
    y: FlexTensor,
    bias: FlexTensor,
}

impl Backward<Flex, 2> for ActivateBackward {
    type State = ActivateState;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [y_node, bias_node] = ops.parents;
        let grad = grads.consume::<Flex>(&ops.node);
        if y_node.is_none() && bias_node.is_none() {
            return;
        }
        let state = ops.state;
        let (grad_y, grad_bias) = backward_flex(&state.y, &state.bias, &grad);
        if let Some(node) = bias_node {
            grads.register::<Flex>(node.id, grad_bias);
        }
        if let Some(node) = y_node {
            grads.register::<Flex>(node.id, grad_y);
        }
    }
}

/// `exp(x)` for `x <= 0` without a library call, so that loops over it vectorise: Cephes'
/// `expf` (range reduction by `ln 2` in two parts, a degree-6 polynomial, the exponent put
/// back through the bits). Arguments below -87 return `exp(-87) = 1.6e-38` instead of
/// underflowing: it only ever meets `1 +` or a product with a bounded factor here. Relative
/// error within 2 ulp of f64 `exp` (`exp_and_ln_match_f64`).
#[inline(always)]
pub(crate) fn exp_nonpositive(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // 1.5 * 2^23: adding it rounds to an integer, which then sits in the low mantissa bits.
    const SHIFTER: f32 = 12_582_912.0;
    let x = x.clamp(-87.0, 0.0);
    let shifted = x * LOG2E + SHIFTER;
    let n = shifted - SHIFTER;
    let r = x - n * LN2_HI - n * LN2_LO;
    let poly = ((((1.987_569_1e-4 * r + 1.398_199_9e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2)
        * r
        + 1.666_666_5e-1)
        * r
        + 0.5;
    let y = poly * r * r + r + 1.0;
    // 2^n for n in -126..=0, a normal number built from its exponent bits (integer bit
    // arithmetic rather than a float-to-int cast, which would not vectorise).
    let n_bits = shifted.to_bits().wrapping_sub(SHIFTER.to_bits());
    y * f32::from_bits(n_bits.wrapping_add(127) << 23)
}

/// `ln(1 + e)` for `e` in `[0, 1]` without a library call: `2 atanh(s)` with
/// `s = e / (2 + e)` in `[0, 1/3]`, its odd series to `s^15` (truncation below `3e-9`
/// relative). More accurate than `ln(1 + e)` for small `e`, as `log1p` is.
#[inline(always)]
pub(crate) fn ln_1p_unit(e: f32) -> f32 {
    let s = e / (2.0 + e);
    let s2 = s * s;
    let series = ((((((s2 * (1.0 / 15.0) + 1.0 / 13.0) * s2 + 1.0 / 11.0) * s2 + 1.0 / 9.0) * s2
        + 1.0 / 7.0)
        * s2
        + 1.0 / 5.0)
        * s2
        + 1.0 / 3.0)
        * s2
        + 1.0;
    2.0 * s * series
}

/// `e = exp(-|z|)`, then `(a(z), a'(z), a''(z))`, stable for any `z`. No library calls and
/// no branches, so that the loops over channels vectorise.
#[inline(always)]
pub(crate) fn parts(z: f32) -> (f32, f32, f32) {
    let g = SMOOTH_GAIN as f32;
    let e = exp_nonpositive(-z.abs());
    let softplus = z.max(0.0) + ln_1p_unit(e);
    let r = 1.0 / (1.0 + e);
    let sigmoid = if z >= 0.0 { r } else { e * r };
    let value = g * (0.2 * z + 0.8 * softplus);
    let first = g * (0.2 + 0.8 * sigmoid);
    // sigmoid (1 - sigmoid) = e / (1 + e)^2 on both sides of 0.
    let second = g * 0.8 * e * r * r;
    (value, first, second)
}

/// One parallel task of [`forward_flex`] or [`backward_flex`]: its rows of the output, the
/// flat offset of those rows in the inputs, and the inputs.
struct KernelArgs<'a> {
    offset: usize,
    out: &'a mut [MaybeUninit<f32>],
    y: &'a [f32],
    grad: &'a [f32],
    bias: &'a [f32],
}

/// The forward task; returns nothing (an empty vector).
#[inline(always)]
fn forward_task(args: KernelArgs<'_>) -> Vec<f32> {
    let KernelArgs {
        offset,
        out,
        y,
        bias,
        ..
    } = args;
    let o = bias.len();
    for (r, row) in out.chunks_exact_mut(o).enumerate() {
        let at = offset + r * o;
        for ((v, yv), b) in row.iter_mut().zip(&y[at..at + o]).zip(bias) {
            v.write(parts(yv + b).0);
        }
    }
    Vec::new()
}

/// The backward task; returns its partial sum of the bias gradient.
#[inline(always)]
fn backward_task(args: KernelArgs<'_>) -> Vec<f32> {
    let KernelArgs {
        offset,
        out,
        y,
        grad,
        bias,
    } = args;
    let o = bias.len();
    let mut bias_sum = vec![0.0f32; o];
    for (r, row) in out.chunks_exact_mut(o).enumerate() {
        let at = offset + r * o;
        let rows = row.iter_mut().zip(&y[at..at + o]).zip(&grad[at..at + o]);
        for ((((v, yv), g), b), total) in rows.zip(bias).zip(&mut bias_sum) {
            let d = g * parts(yv + b).1;
            v.write(d);
            *total += d;
        }
    }
    bias_sum
}

fn forward_flex(y: &FlexTensor, bias: &FlexTensor) -> FlexTensor {
    let shape = y.shape().to_vec();
    let o = shape[2];
    let (y, bias) = (contiguous(y), contiguous(bias));
    let fill = |out: &mut [MaybeUninit<f32>]| {
        if o == 0 {
            return;
        }
        out.par_chunks_mut(ROWS_PER_TASK * o)
            .enumerate()
            .for_each(|(task, rows)| {
                dispatch_simd!(
                    forward_task,
                    KernelArgs {
                        offset: task * ROWS_PER_TASK * o,
                        out: rows,
                        y: &y,
                        grad: &[],
                        bias: &bias,
                    },
                    KernelArgs<'_>
                );
            })
    };
    // SAFETY: `y` is `[.., o]` (o = 0: no elements), so the tasks' whole rows cover every
    // output element, and each task writes all of its rows.
    let out = unsafe { written_by(y.len(), fill) };
    flex_tensor(out, shape)
}

/// Gradients with respect to `y` and `bias` for the output gradient `grad`.
fn backward_flex(y: &FlexTensor, bias: &FlexTensor, grad: &FlexTensor) -> (FlexTensor, FlexTensor) {
    let shape = y.shape().to_vec();
    let o = shape[2];
    let (y, bias, grad) = (contiguous(y), contiguous(bias), contiguous(grad));
    let mut grad_bias = vec![0.0f32; o];
    let mut partial_bias: Vec<Vec<f32>> = Vec::new();
    let fill = |grad_y: &mut [MaybeUninit<f32>]| {
        if o == 0 {
            return;
        }
        partial_bias = grad_y
            .par_chunks_mut(ROWS_PER_TASK * o)
            .enumerate()
            .map(|(task, rows)| {
                dispatch_simd!(
                    backward_task,
                    KernelArgs {
                        offset: task * ROWS_PER_TASK * o,
                        out: rows,
                        y: &y,
                        grad: &grad,
                        bias: &bias,
                    },
                    KernelArgs<'_>
                )
            })
            .collect();
    };
    // SAFETY: as in `forward_flex`: the tasks' whole rows cover every element of `grad_y`.
    let grad_y = unsafe { written_by(y.len(), fill) };
    for partial in partial_bias {
        for (total, v) in grad_bias.iter_mut().zip(partial) {
            *total += v;
        }
    }
    (flex_tensor(grad_y, shape), flex_tensor(grad_bias, vec![o]))
}

pub mod pullback;

#[cfg(test)]
mod tests;
