//! The pullback of the NeIIF's activation, `v = u a'(y + bias)`, as one operation with a
//! hand-written backward pass: the step of the reverse sweep that gives the density's
//! gradient with respect to the point (the normals, [`crate::neiif`]).
//!
//! The sweep carries the cotangent `u` of a layer's output back to its pre-activation,
//! `v = u a'(z)` with `z = y + bias`, then through the layer's weight. The normals enter the
//! losses, so this step is itself differentiated:
//! `dL/du = G a'(z)`, `dL/dy = G u a''(z)`, `dL/dbias = sum over batch and points of dL/dy`.
//! Written with tensor ops that is a dozen passes over `[batch, points, o]` tensors, each
//! recorded by autodiff; here it is one pass forward and one backward.
//!
//! On the `flex` backend (with or without autodiff) the fused kernels run; on any other backend
//! [`pullback_reference`], the same function in plain tensor ops, does. Both are tested against
//! each other and against f64 central differences.

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

use super::{ROWS_PER_TASK, parts};
use std::mem::MaybeUninit;

use crate::flex_extension::{
    Route, autodiff_parts, contiguous, dispatch_simd, flex_tensor, route, written_by,
};
use crate::neiif::smooth_lrelu_parts;

/// `u a'(y + bias)` for `u, y: [batch, p, o]` and `bias: [o]` (see the module documentation).
pub fn pullback(u: Tensor<3>, y: Tensor<3>, bias: Tensor<1>) -> Tensor<3> {
    let o = y.dims()[2];
    assert_eq!(u.dims(), y.dims(), "one cotangent per pre-activation");
    assert_eq!(bias.dims(), [o], "one bias per channel");
    if [u.dtype(), y.dtype(), bias.dtype()]
        .iter()
        .any(|d| *d != DType::F32)
    {
        return pullback_reference(u, y, bias);
    }
    match route(&y.device()) {
        Route::Flex => {
            let (Ok(u), Ok(y), Ok(bias)) = (
                u.try_into_primitive::<Flex>(),
                y.try_into_primitive::<Flex>(),
                bias.try_into_primitive::<Flex>(),
            ) else {
                unreachable!("a flex device holds flex tensors")
            };
            Tensor::from_primitive::<Flex>(forward_flex(&u, &y, &bias))
        }
        Route::Autodiff(GradientCheckpointingStrategy::Disabled) => {
            pullback_autodiff::<NoCheckpointing>(u, y, bias)
        }
        Route::Autodiff(GradientCheckpointingStrategy::Balanced) => {
            pullback_autodiff::<BalancedCheckpointing>(u, y, bias)
        }
        Route::Other => pullback_reference(u, y, bias),
    }
}

/// The same in plain tensor ops: the reference, and what backends other than flex run.
pub fn pullback_reference(u: Tensor<3>, y: Tensor<3>, bias: Tensor<1>) -> Tensor<3> {
    let o = y.dims()[2];
    let (_, derivative) = smooth_lrelu_parts(y + bias.reshape([1, 1, o]), true);
    u * derivative.expect("asked")
}

/// The autodiff route, for either checkpointing strategy `C`.
fn pullback_autodiff<C>(u: Tensor<3>, y: Tensor<3>, bias: Tensor<1>) -> Tensor<3>
where
    C: CheckpointStrategy,
    DispatchTensor: DispatchKindConversion<Autodiff<Flex, C>>,
{
    let (u, u_node) = autodiff_parts::<C, 3>(u);
    let (y, y_node) = autodiff_parts::<C, 3>(y);
    let (bias, bias_node) = autodiff_parts::<C, 1>(bias);
    let out = forward_flex(&u, &y, &bias);
    let out = match PullbackBackward
        .prepare::<C>([u_node, y_node, bias_node])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => prep.finish(PullbackState { u, y, bias }, out),
        OpsKind::UnTracked(prep) => prep.finish(out),
    };
    Tensor::from_primitive::<Autodiff<Flex, C>>(out)
}

#[derive(Debug)]
struct PullbackBackward;

#[derive(Clone, Debug)]
struct PullbackState {
    u: FlexTensor,
    y: FlexTensor,
    bias: FlexTensor,
}

impl Backward<Flex, 3> for PullbackBackward {
    type State = PullbackState;

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [u_node, y_node, bias_node] = ops.parents;
        let grad = grads.consume::<Flex>(&ops.node);
        if u_node.is_none() && y_node.is_none() && bias_node.is_none() {
            return;
        }
        let s = ops.state;
        let (grad_u, grad_y, grad_bias) = backward_flex(&s.u, &s.y, &s.bias, &grad);
        if let Some(node) = u_node {
            grads.register::<Flex>(node.id, grad_u);
        }
        if let Some(node) = y_node {
            grads.register::<Flex>(node.id, grad_y);
        }
        if let Some(node) = bias_node {
            grads.register::<Flex>(node.id, grad_bias);
        }
    }
}

/// One parallel task: rows `offset / o ..` of the inputs, the task's output rows (one block
/// forward; `dL/du` then `dL/dy` backward).
struct PullbackArgs<'a> {
    offset: usize,
    out: [&'a mut [MaybeUninit<f32>]; 2],
    u: &'a [f32],
    y: &'a [f32],
    grad: &'a [f32],
    bias: &'a [f32],
}

/// The forward task; returns nothing (an empty vector).
#[inline(always)]
fn forward_task(args: PullbackArgs<'_>) -> Vec<f32> {
    let PullbackArgs {
        offset,
        out: [out, _],
        u,
        y,
        bias,
        ..
    } = args;
    let o = bias.len();
    for (r, v_row) in out.chunks_exact_mut(o).enumerate() {
        let at = offset + r * o;
        let rows = v_row.iter_mut().zip(&u[at..at + o]).zip(&y[at..at + o]);
        for (((v, u), y), b) in rows.zip(bias) {
            let (_, first, _) = parts(y + b);
            v.write(u * first);
        }
    }
    Vec::new()
}

/// The backward task; returns its partial sum of the bias gradient.
#[inline(always)]
fn backward_task(args: PullbackArgs<'_>) -> Vec<f32> {
    let PullbackArgs {
        offset,
        out: [grad_u, grad_y],
        u,
        y,
        grad,
        bias,
    } = args;
    let o = bias.len();
    let mut bias_sum = vec![0.0f32; o];
    let rows = grad_u.chunks_exact_mut(o).zip(grad_y.chunks_exact_mut(o));
    for (r, (gu_row, gy_row)) in rows.enumerate() {
        let at = offset + r * o;
        let (u_row, y_row, g_row) = (&u[at..at + o], &y[at..at + o], &grad[at..at + o]);
        for c in 0..o {
            let (_, first, second) = parts(y_row[c] + bias[c]);
            let gy = g_row[c] * u_row[c] * second;
            gu_row[c].write(g_row[c] * first);
            gy_row[c].write(gy);
            bias_sum[c] += gy;
        }
    }
    bias_sum
}

fn forward_flex(u: &FlexTensor, y: &FlexTensor, bias: &FlexTensor) -> FlexTensor {
    let shape = y.shape().to_vec();
    let o = shape[2];
    let (u, y, bias) = (contiguous(u), contiguous(y), contiguous(bias));
    assert_eq!(
        u.len(),
        y.len(),
        "the cotangent and the pre-activation differ in size"
    );
    let fill = |out: &mut [MaybeUninit<f32>]| {
        if o == 0 {
            return;
        }
        out.par_chunks_mut(ROWS_PER_TASK * o)
            .enumerate()
            .for_each(|(task, rows)| {
                dispatch_simd!(
                    forward_task,
                    PullbackArgs {
                        offset: task * ROWS_PER_TASK * o,
                        out: [rows, &mut []],
                        u: &u,
                        y: &y,
                        grad: &[],
                        bias: &bias,
                    },
                    PullbackArgs<'_>
                );
            })
    };
    // SAFETY: `y` is `[.., o]` (o = 0: no elements), so the tasks' whole rows cover every
    // output element, and each task writes all of its rows.
    let out = unsafe { written_by(y.len(), fill) };
    flex_tensor(out, shape)
}

/// Gradients with respect to `u`, `y` and `bias` for the output gradient `grad`.
fn backward_flex(
    u: &FlexTensor,
    y: &FlexTensor,
    bias: &FlexTensor,
    grad: &FlexTensor,
) -> (FlexTensor, FlexTensor, FlexTensor) {
    let shape = y.shape().to_vec();
    let o = shape[2];
    let (u, y, bias, grad) = (
        contiguous(u),
        contiguous(y),
        contiguous(bias),
        contiguous(grad),
    );
    let len = y.len();
    assert!(
        u.len() == len && grad.len() == len,
        "the cotangent, the pre-activation and the gradient differ in size"
    );
    let mut grad_bias = vec![0.0f32; o];
    let tasks = |grad_u: &mut [MaybeUninit<f32>], grad_y: &mut [MaybeUninit<f32>]| {
        if o == 0 {
            return Vec::new();
        }
        grad_u
            .par_chunks_mut(ROWS_PER_TASK * o)
            .zip(grad_y.par_chunks_mut(ROWS_PER_TASK * o))
            .enumerate()
            .map(|(task, (gu, gy))| {
                dispatch_simd!(
                    backward_task,
                    PullbackArgs {
                        offset: task * ROWS_PER_TASK * o,
                        out: [gu, gy],
                        u: &u,
                        y: &y,
                        grad: &grad,
                        bias: &bias,
                    },
                    PullbackArgs<'_>
                )
            })
            .collect::<Vec<Vec<f32>>>()
    };
    let mut partial_bias = Vec::new();
    let mut grad_y = Vec::new();
    // SAFETY (both): as in `forward_flex`, the tasks' whole rows cover every element of
    // `grad_u` and `grad_y`, which are chunked alike.
    let grad_u = unsafe {
        written_by(len, |gu| {
            grad_y = written_by(len, |gy| partial_bias = tasks(gu, gy));
        })
    };
    for partial in partial_bias {
        for (total, v) in grad_bias.iter_mut().zip(partial) {
            *total += v;
        }
    }
    (
        flex_tensor(grad_u, shape.clone()),
        flex_tensor(grad_y, shape),
        flex_tensor(grad_bias, vec![o]),
    )
}

#[cfg(test)]
mod tests {
    use burn::tensor::{Device, TensorData};

    use super::*;
    use crate::backend::to_f32_vec;
    use crate::neiif::SMOOTH_GAIN;
    use crate::test_support::normals;
    use volux_envmap::random::SplitMix64;

    fn tensor<const D: usize>(values: &[f64], shape: [usize; D], device: &Device) -> Tensor<D> {
        let v: Vec<f32> = values.iter().map(|x| *x as f32).collect();
        Tensor::from_data(TensorData::new(v, shape), device)
    }

    type Pullback = fn(Tensor<3>, Tensor<3>, Tensor<1>) -> Tensor<3>;

    /// `sum(pullback(u, y, bias) * r)`'s value and its gradients in `u`, `y` and `bias`.
    fn loss_and_grads(
        f: Pullback,
        [u, y, bias, r]: [&[f64]; 4],
        shape: [usize; 3],
    ) -> [Vec<f32>; 4] {
        let device = Device::flex().autodiff();
        let ut = tensor(u, shape, &device).require_grad();
        let yt = tensor(y, shape, &device).require_grad();
        let bt = tensor(bias, [shape[2]], &device).require_grad();
        let out = f(ut.clone(), yt.clone(), bt.clone());
        let grads = (out.clone() * tensor(r, shape, &device)).sum().backward();
        [
            to_f32_vec(out),
            to_f32_vec(ut.grad(&grads).unwrap()),
            to_f32_vec(yt.grad(&grads).unwrap()),
            to_f32_vec(bt.grad(&grads).unwrap()),
        ]
    }

    fn assert_close(got: &[f32], want: &[f32], tol: f32, what: &str) {
        assert_eq!(got.len(), want.len(), "{what}: lengths");
        for (i, (g, w)) in got.iter().zip(want).enumerate() {
            assert!(
                (g - w).abs() <= tol * (1.0 + w.abs()),
                "{what}[{i}]: {g} vs {w}"
            );
        }
    }

    #[test]
    fn fused_matches_the_reference_in_values_and_gradients() {
        let mut rng = SplitMix64::new(15);
        // 600 points: several tasks per batch, the last one short; then a single row.
        for (p, o) in [(600, 5), (1, 3)] {
            let shape = [2, p, o];
            let n = shape.iter().product();
            let u = normals(&mut rng, n);
            let y: Vec<f64> = normals(&mut rng, n).iter().map(|v| 3.0 * v).collect();
            let bias = normals(&mut rng, o);
            let r = normals(&mut rng, n);
            let args = [u.as_slice(), &y, &bias, &r];
            let fused = loss_and_grads(pullback, args, shape);
            let reference = loss_and_grads(pullback_reference, args, shape);
            for (i, what) in ["value", "d/du", "d/dy", "d/dbias"].iter().enumerate() {
                let tol = if i == 3 { 1e-4 } else { 1e-5 };
                assert_close(
                    &fused[i],
                    &reference[i],
                    tol,
                    &format!("{p} points: {what}"),
                );
            }
            let plain = to_f32_vec(pullback(
                tensor(&u, shape, &Device::flex()),
                tensor(&y, shape, &Device::flex()),
                tensor(&bias, [o], &Device::flex()),
            ));
            assert_eq!(plain, fused[0], "flex without autodiff");
        }
    }

    /// `sum(u a'(y + bias) r)` in f64.
    fn loss_f64(u: &[f64], y: &[f64], bias: &[f64], r: &[f64]) -> f64 {
        let o = bias.len();
        (0..u.len())
            .map(|i| {
                let z = y[i] + bias[i % o];
                let sigmoid = 1.0 / (1.0 + (-z).exp());
                u[i] * SMOOTH_GAIN * (0.2 + 0.8 * sigmoid) * r[i]
            })
            .sum()
    }

    #[test]
    fn gradients_match_f64_central_differences() {
        let mut rng = SplitMix64::new(16);
        let (p, o) = (5, 3);
        let n = p * o;
        // Pre-activations from -6 to 6, where the second derivative matters.
        let round = |v: Vec<f64>| -> Vec<f64> { v.iter().map(|x| f64::from(*x as f32)).collect() };
        let u = round(normals(&mut rng, n));
        let y = round(normals(&mut rng, n).iter().map(|v| 2.5 * v).collect());
        let bias = round(normals(&mut rng, o));
        let r = normals(&mut rng, n);
        let [_, grad_u, grad_y, grad_bias] =
            loss_and_grads(pullback, [&u, &y, &bias, &r], [1, p, o]);
        let h = 1e-6;
        let fd = |at: &dyn Fn(f64) -> f64| (at(h) - at(-h)) / (2.0 * h);
        let check = |got: f32, want: f64, what: String| {
            assert!(
                (f64::from(got) - want).abs() < 1e-5 * (1.0 + want.abs()),
                "{what}: {got} vs {want}"
            );
        };
        for k in 0..n {
            let want = fd(&|d| {
                let mut u = u.clone();
                u[k] += d;
                loss_f64(&u, &y, &bias, &r)
            });
            check(grad_u[k], want, format!("d/du[{k}]"));
            let want = fd(&|d| {
                let mut y = y.clone();
                y[k] += d;
                loss_f64(&u, &y, &bias, &r)
            });
            check(grad_y[k], want, format!("d/dy[{k}]"));
        }
        for c in 0..o {
            let want = fd(&|d| {
                let mut bias = bias.clone();
                bias[c] += d;
                loss_f64(&u, &y, &bias, &r)
            });
            check(grad_bias[c], want, format!("d/dbias[{c}]"));
        }
    }

    #[test]
    fn stiff_pre_activations_and_cotangents_stay_finite_with_the_limits() {
        let g = SMOOTH_GAIN;
        // Pre-activations at the stiff ends, at 0 and tiny; cotangents of 1 and a huge one.
        let zs = [1e4, -1e4, 0.0, 88.0, -88.0, 1e-30];
        let p = zs.len();
        let u = vec![1.0; p];
        let r = vec![1.0; p];
        let [out, grad_u, grad_y, grad_bias] =
            loss_and_grads(pullback, [&u, &zs, &[0.0], &r], [1, p, 1]);
        let all = out.iter().chain(&grad_u).chain(&grad_y).chain(&grad_bias);
        assert!(all.clone().all(|v| v.is_finite()));
        // a' is g at +inf, 0.2 g at -inf, 0.6 g at 0; a'' vanishes at the ends, 0.2 g at 0.
        let want_first = [g, 0.2 * g, 0.6 * g];
        let want_second = [0.0, 0.0, 0.2 * g];
        for i in 0..3 {
            assert!(
                (f64::from(out[i]) - want_first[i]).abs() < 1e-6,
                "a'({})",
                zs[i]
            );
            assert!((f64::from(grad_u[i]) - want_first[i]).abs() < 1e-6);
            assert!(
                (f64::from(grad_y[i]) - want_second[i]).abs() < 1e-6,
                "a''({})",
                zs[i]
            );
        }
        let huge = [1e30f64, -1e30, 3e38];
        let [out, ..] = loss_and_grads(
            pullback,
            [&huge, &[0.0, 5.0, -5.0], &[0.0], &[1.0; 3]],
            [1, 3, 1],
        );
        assert!(out.iter().all(|v| v.is_finite()), "{out:?}");
    }
}
