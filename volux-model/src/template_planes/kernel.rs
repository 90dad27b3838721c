//! The template planes' weighted gathers as one flex operation with a hand-written backward.
//!
//! In tensor ops ([`sample_reference`]) a sample is a `select` of 27 rows per point into a
//! `[27 p, channels]` tensor, one product and one sum over the taps for the features and for
//! each of their three derivatives, and backward a scatter-add per output: every pass writes
//! and reads the gathered tensor again. Here the forward reads each tap's row once and
//! accumulates all the outputs asked for; the backward adds each point's output cotangents,
//! weighted, into the rows its taps read. The taps and weights are data (they depend on the
//! points, which carry no gradient): the planes are the only input with a gradient.
//!
//! The backward is deterministic whatever the thread count: each fixed block of points adds
//! into its own copy of the planes' gradient and the copies are summed in block order.

use std::sync::Arc;

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::flex::FlexTensor;
use burn::backend::{Autodiff, Flex, GradientCheckpointingStrategy, TensorMetadata};
use burn::tensor::{DType, DispatchTensor, Int, Tensor, TensorData};
use burn_dispatch::DispatchKindConversion;
use rayon::prelude::*;

use super::TAPS;
use crate::flex_extension::{Route, autodiff_parts, contiguous, flex_tensor, route};

/// Points per parallel task (and per block of the backward's partial sums).
const POINTS_PER_TASK: usize = 1024;

/// Where each point's taps read and what they weigh, point-major: tap `t` of point `q` reads
/// row `index[q * TAPS + t]` of the planes with weights `weights[(q * TAPS + t) * outputs +
/// k]` for output `k` (the features, then, when asked for, their derivatives along x, y, z).
#[derive(Debug)]
pub(crate) struct Taps {
    pub points: usize,
    pub outputs: usize,
    pub index: Vec<u32>,
    pub weights: Vec<f32>,
}

impl Taps {
    /// Point `q`'s taps: where each tap's row starts in the planes' `[rows, channels]` values,
    /// and the tap's weight of each output.
    fn of_point(&self, q: usize, channels: usize) -> impl Iterator<Item = (usize, &[f32])> {
        let k = self.outputs;
        (q * TAPS..(q + 1) * TAPS).map(move |at| {
            (
                self.index[at] as usize * channels,
                &self.weights[at * k..(at + 1) * k],
            )
        })
    }
}

/// The weighted sums `[points, outputs, channels]` of the planes' rows (`[rows, channels]`)
/// at `taps`, differentiable in the planes.
pub(crate) fn sample(planes: Tensor<2>, taps: Arc<Taps>) -> Tensor<3> {
    if planes.dtype() != DType::F32 {
        return sample_reference(planes, &taps);
    }
    match route(&planes.device()) {
        Route::Flex => {
            let Ok(planes) = planes.try_into_primitive::<Flex>() else {
                unreachable!("a flex device holds flex tensors")
            };
            Tensor::from_primitive::<Flex>(forward_flex(&planes, &taps))
        }
        Route::Autodiff(GradientCheckpointingStrategy::Disabled) => {
            sample_autodiff::<NoCheckpointing>(planes, taps)
        }
        Route::Autodiff(GradientCheckpointingStrategy::Balanced) => {
            sample_autodiff::<BalancedCheckpointing>(planes, taps)
        }
        Route::Other => sample_reference(planes, &taps),
    }
}

/// [`sample`] in tensor ops (a `select` of every tap's row, products and sums over the taps):
/// the reference, and what other backends run.
pub(crate) fn sample_reference(planes: Tensor<2>, taps: &Taps) -> Tensor<3> {
    let device = planes.device();
    let [_, c] = planes.dims();
    let (p, k) = (taps.points, taps.outputs);
    let index: Vec<i64> = taps.index.iter().map(|&i| i64::from(i)).collect();
    let index = Tensor::<1, Int>::from_data(TensorData::new(index, [p * TAPS]), &device);
    let gathered = planes.select(0, index).reshape([p, TAPS, 1, c]);
    let weights = Tensor::<4>::from_data(
        TensorData::new(taps.weights.clone(), [p, TAPS, k, 1]),
        &device,
    );
    (gathered * weights).sum_dim(1).reshape([p, k, c])
}

fn sample_autodiff<C>(planes: Tensor<2>, taps: Arc<Taps>) -> Tensor<3>
where
    C: CheckpointStrategy,
    DispatchTensor: DispatchKindConversion<Autodiff<Flex, C>>,
{
    let (planes, node) = autodiff_parts::<C, 2>(planes);
    let out = forward_flex(&planes, &taps);
    let rows = planes.shape()[0];
    let out = match SampleBackward
        .prepare::<C>([node])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => prep.finish(SampleState { taps, rows }, out),
        OpsKind::UnTracked(prep) => prep.finish(out),
    };
    Tensor::from_primitive::<Autodiff<Flex, C>>(out)
}

#[derive(Debug)]
struct SampleBackward;

#[derive(Clone, Debug)]
struct SampleState {
    taps: Arc<Taps>,
    rows: usize,
}

impl Backward<Flex, 1> for SampleBackward {
    type State = SampleState;

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [node] = ops.parents;
        let grad = grads.consume::<Flex>(&ops.node);
        if let Some(node) = node {
            let s = ops.state;
            grads.register::<Flex>(node.id, backward_flex(&s.taps, s.rows, &grad));
        }
    }
}

fn forward_flex(planes: &FlexTensor, taps: &Taps) -> FlexTensor {
    let c = planes.shape()[1];
    let planes = contiguous(planes);
    let (p, k) = (taps.points, taps.outputs);
    let mut out = vec![0.0f32; p * k * c];
    out.par_chunks_mut(POINTS_PER_TASK * k * c)
        .enumerate()
        .for_each(|(task, out)| {
            let first = task * POINTS_PER_TASK;
            for (j, point_out) in out.chunks_exact_mut(k * c).enumerate() {
                for (row, weights) in taps.of_point(first + j, c) {
                    let row = &planes[row..row + c];
                    for (&w, o) in weights.iter().zip(point_out.chunks_exact_mut(c)) {
                        for (o, &v) in o.iter_mut().zip(row) {
                            *o += w * v;
                        }
                    }
                }
            }
        });
    flex_tensor(out, vec![p, k, c])
}

/// The planes' gradient `[rows, channels]` from the outputs' `[points, outputs, channels]`.
fn backward_flex(taps: &Taps, rows: usize, grad: &FlexTensor) -> FlexTensor {
    let c = grad.shape()[2];
    let grad = contiguous(grad);
    let k = taps.outputs;
    let partials: Vec<Vec<f32>> = grad
        .par_chunks(POINTS_PER_TASK * k * c)
        .enumerate()
        .map(|(task, grad)| {
            let mut partial = vec![0.0f32; rows * c];
            let first = task * POINTS_PER_TASK;
            for (j, point_grad) in grad.chunks_exact(k * c).enumerate() {
                for (row, weights) in taps.of_point(first + j, c) {
                    let row = &mut partial[row..row + c];
                    for (&w, g) in weights.iter().zip(point_grad.chunks_exact(c)) {
                        for (r, &g) in row.iter_mut().zip(g) {
                            *r += w * g;
                        }
                    }
                }
            }
            partial
        })
        .collect();
    let mut total = vec![0.0f32; rows * c];
    for partial in &partials {
        for (t, v) in total.iter_mut().zip(partial) {
            *t += v;
        }
    }
    flex_tensor(total, vec![rows, c])
}
