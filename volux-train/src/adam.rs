//! Adam as one pass over each parameter tensor on the CPU.
//!
//! Burn's `Adam` updates a parameter in about thirteen tensor operations (the two moments,
//! the bias corrections, the square root, the division, the step), each a pass over the
//! parameter that allocates its result: for the quickstart's five discriminators (5.9M
//! parameters) that is about 0.9 GB of memory traffic per step. [`FusedAdam`] reads the
//! parameter, its gradient and both moments once and writes the new parameter and moments
//! once, on flex tensors; on any other backend, or for dtypes other than f32, it runs Burn's
//! `Adam` itself, which is also the reference its tests compare against.
//!
//! The arithmetic is Burn's (`burn-optim`'s `adam.rs`): with `t` the step count,
//! `m = b1 m + (1 - b1) g`, `v = b2 v + (1 - b2) g^2`, `c2 = sqrt(1 - b2^t)`,
//! `p -= lr (c2 / (1 - b1^t)) m / (sqrt(v) + eps c2)`. Its state is Burn's `AdamState`, so
//! checkpoints hold the same record either way.

use burn::backend::flex::FlexTensor;
use burn::backend::{Flex, TensorMetadata};
use burn::optim::Optimizer;
use burn::optim::{Adam, AdamConfig, AdamState, AdaptiveMomentumState, LearningRate};
use burn::tensor::{DType, Device, Tensor};
use rayon::prelude::*;
use volux_model::flex_extension::{Route, contiguous, flex_tensor, route};

/// Elements per parallel task.
const TASK_ELEMENTS: usize = 1 << 15;

/// Adam (no weight decay, no AMSGrad) with a fused flex kernel; see the module documentation.
#[derive(Clone)]
pub struct FusedAdam {
    beta_1: f32,
    beta_2: f32,
    epsilon: f32,
    /// Burn's Adam with the same settings: what other backends run.
    reference: Adam,
}

impl FusedAdam {
    /// Adam with these moment decays and epsilon.
    pub fn new(beta_1: f32, beta_2: f32, epsilon: f32) -> Self {
        let reference = AdamConfig::new()
            .with_beta_1(beta_1)
            .with_beta_2(beta_2)
            .with_epsilon(epsilon)
            .build();
        Self {
            beta_1,
            beta_2,
            epsilon,
            reference,
        }
    }
}

impl Optimizer for FusedAdam {
    type State<const D: usize> = AdamState<D>;

    fn step<const D: usize>(
        &self,
        lr: LearningRate,
        tensor: Tensor<D>,
        grad: Tensor<D>,
        state: Option<Self::State<D>>,
    ) -> (Tensor<D>, Option<Self::State<D>>) {
        let f32s = tensor.dtype() == DType::F32 && grad.dtype() == DType::F32;
        if !f32s || !matches!(route(&tensor.device()), Route::Flex) {
            return self.reference.step(lr, tensor, grad, state);
        }
        let shape = tensor.dims();
        let flex = |t: Tensor<D>| {
            t.try_into_primitive::<Flex>()
                .unwrap_or_else(|_| unreachable!("a flex device holds flex tensors"))
        };
        let (time, moments) = match state {
            Some(s) => (
                s.momentum.time + 1,
                Some((flex(s.momentum.moment_1), flex(s.momentum.moment_2))),
            ),
            None => (1, None),
        };
        let (param, m, v) = self.update(
            lr,
            time,
            &flex(tensor),
            &flex(grad),
            moments.as_ref().map(|(m, v)| (m, v)),
        );
        let back = |t: FlexTensor| Tensor::<D>::from_primitive::<Flex>(t).reshape(shape);
        let momentum = AdaptiveMomentumState::new(time, back(m), back(v));
        (back(param), Some(AdamState::new(momentum)))
    }

    fn to_device<const D: usize>(state: Self::State<D>, device: &Device) -> Self::State<D> {
        <Adam as Optimizer>::to_device(state, device)
    }
}

impl FusedAdam {
    /// The new parameter and moments after step `time` (1 for the first).
    fn update(
        &self,
        lr: LearningRate,
        time: usize,
        param: &FlexTensor,
        grad: &FlexTensor,
        moments: Option<(&FlexTensor, &FlexTensor)>,
    ) -> (FlexTensor, FlexTensor, FlexTensor) {
        let shape = param.shape().to_vec();
        let (b1, b2) = (self.beta_1, self.beta_2);
        let t = time as i32;
        let c2 = (1.0 - b2.powi(t)).sqrt();
        let factor = c2 / (1.0 - b1.powi(t));
        let (eps, lr) = (self.epsilon * c2, lr as f32);
        let (param, grad) = (contiguous(param), contiguous(grad));
        let moments = moments.map(|(m, v)| (contiguous(m), contiguous(v)));
        let n = param.len();
        let (mut p_out, mut m_out, mut v_out) = (vec![0.0f32; n], vec![0.0f32; n], vec![0.0f32; n]);
        p_out
            .par_chunks_mut(TASK_ELEMENTS)
            .zip(m_out.par_chunks_mut(TASK_ELEMENTS))
            .zip(v_out.par_chunks_mut(TASK_ELEMENTS))
            .enumerate()
            .for_each(|(task, ((p_out, m_out), v_out))| {
                let at = task * TASK_ELEMENTS;
                let range = at..at + p_out.len();
                let (p, g) = (&param[range.clone()], &grad[range.clone()]);
                for i in 0..p_out.len() {
                    let (m0, v0) = match &moments {
                        Some((m, v)) => (m[at + i], v[at + i]),
                        None => (0.0, 0.0),
                    };
                    let g = g[i];
                    let m = m0 * b1 + g * (1.0 - b1);
                    let v = v0 * b2 + g * g * (1.0 - b2);
                    m_out[i] = m;
                    v_out[i] = v;
                    p_out[i] = p[i] - (m * factor / (v.sqrt() + eps)) * lr;
                }
            });
        (
            flex_tensor(p_out, shape.clone()),
            flex_tensor(m_out, shape.clone()),
            flex_tensor(v_out, shape),
        )
    }
}

#[cfg(test)]
mod tests;
