//! Batched matrix products `[batch, m, k] x [batch, k, n]` as a flex operation with a
//! hand-written backward pass: the NeIIF's and the upsampler's per-sample (modulated) layers
//! and the normals' reverse sweep through their transposed weights.
//!
//! Flex's own matmul allocates each output as a zeroed byte vector and then copies it into an
//! aligned buffer (`FlexTensor::empty`: `Bytes::from_bytes_vec` re-aligns a `u8` allocation),
//! so every product wrote its output three times; with the NeIIF's `[4, 32768, 64]` layers
//! that was 9% of a field forward and backward. Here each batch element is one `gemm` call
//! that reads both operands through their strides (a transposed view is not copied) and
//! writes into uninitialised memory that becomes the output. Backward:
//! `dA_b = G_b B_b^T`, `dB_b = A_b^T G_b`, the same calls with the strides swapped.
//!
//! Other backends, and anything but f32, run [`batched_matmul_reference`] (Burn's `matmul`),
//! which the kernel is tested against, beside an f64 loop and f64 central differences.

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

use crate::flex_extension::{Route, autodiff_parts, contiguous, flex_tensor, route};

/// `a: [batch, m, k]` times `b: [batch, k, n]`, batch element by batch element:
/// `[batch, m, n]`.
pub fn batched_matmul(a: Tensor<3>, b: Tensor<3>) -> Tensor<3> {
    let ([ba, _, ka], [bb, kb, _]) = (a.dims(), b.dims());
    assert_eq!(ba, bb, "batch sizes differ: {ba} and {bb}");
    assert_eq!(ka, kb, "inner dimensions differ: {ka} and {kb}");
    if a.dtype() != DType::F32 || b.dtype() != DType::F32 {
        return batched_matmul_reference(a, b);
    }
    match route(&a.device()) {
        Route::Flex => {
            let (Ok(a), Ok(b)) = (
                a.try_into_primitive::<Flex>(),
                b.try_into_primitive::<Flex>(),
            ) else {
                unreachable!("a flex device holds flex tensors")
            };
            Tensor::from_primitive::<Flex>(product(&a, false, &b, false))
        }
        Route::Autodiff(GradientCheckpointingStrategy::Disabled) => {
            matmul_autodiff::<NoCheckpointing>(a, b)
        }
        Route::Autodiff(GradientCheckpointingStrategy::Balanced) => {
            matmul_autodiff::<BalancedCheckpointing>(a, b)
        }
        Route::Other => batched_matmul_reference(a, b),
    }
}

/// Burn's `matmul`: the reference, and what other backends run.
pub fn batched_matmul_reference(a: Tensor<3>, b: Tensor<3>) -> Tensor<3> {
    a.matmul(b)
}

/// The autodiff route, for either checkpointing strategy `C`.
fn matmul_autodiff<C>(a: Tensor<3>, b: Tensor<3>) -> Tensor<3>
where
    C: CheckpointStrategy,
    DispatchTensor: DispatchKindConversion<Autodiff<Flex, C>>,
{
    let (a, a_node) = autodiff_parts::<C, 3>(a);
    let (b, b_node) = autodiff_parts::<C, 3>(b);
    let out = product(&a, false, &b, false);
    let out = match MatmulBackward
        .prepare::<C>([a_node, b_node])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => prep.finish(MatmulState { a, b }, out),
        OpsKind::UnTracked(prep) => prep.finish(out),
    };
    Tensor::from_primitive::<Autodiff<Flex, C>>(out)
}

#[derive(Debug)]
struct MatmulBackward;

#[derive(Clone, Debug)]
struct MatmulState {
    a: FlexTensor,
    b: FlexTensor,
}

impl Backward<Flex, 2> for MatmulBackward {
    type State = MatmulState;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [a_node, b_node] = ops.parents;
        let grad = grads.consume::<Flex>(&ops.node);
        let MatmulState { a, b } = ops.state;
        if let Some(node) = b_node {
            // dB_b = A_b^T G_b.
            grads.register::<Flex>(node.id, product(&a, true, &grad, false));
        }
        if let Some(node) = a_node {
            // dA_b = G_b B_b^T.
            grads.register::<Flex>(node.id, product(&grad, false, &b, true));
        }
    }
}

/// A 3D operand read through its strides: element `(batch, i, j)` of the (possibly
/// transposed) matrix at `data[offset + batch * strides[0] + i * strides[1] + j * strides[2]]`.
struct Operand<'a> {
    data: std::borrow::Cow<'a, [f32]>,
    offset: usize,
    strides: [isize; 3],
    /// `[batch, rows, columns]` as read.
    dims: [usize; 3],
}

impl<'a> Operand<'a> {
    /// `t`, or its transpose in the last two dimensions; a layout with negative strides is
    /// copied to a contiguous one first.
    fn new(t: &'a FlexTensor, transposed: bool) -> Self {
        let layout = t.layout();
        let shape = t.shape();
        let dims = [shape[0], shape[1], shape[2]];
        let (data, offset, strides) = match layout.strides() {
            s if s.len() == 3 && s.iter().all(|v| *v >= 0) => (
                std::borrow::Cow::Borrowed(t.storage::<f32>()),
                layout.start_offset(),
                [s[0], s[1], s[2]],
            ),
            _ => (
                contiguous(t),
                0,
                [(dims[1] * dims[2]) as isize, dims[2] as isize, 1],
            ),
        };
        if transposed {
            Self {
                data,
                offset,
                strides: [strides[0], strides[2], strides[1]],
                dims: [dims[0], dims[2], dims[1]],
            }
        } else {
            Self {
                data,
                offset,
                strides,
                dims,
            }
        }
    }

    /// Pointer to batch element `b`'s first entry.
    fn batch_ptr(&self, b: usize) -> *const f32 {
        let at = self.offset as isize + b as isize * self.strides[0];
        debug_assert!(at >= 0 && (at as usize) <= self.data.len());
        // SAFETY: the layout addresses elements inside the storage, so the start of every
        // batch element is inside it too (or one past its end for an empty matrix).
        unsafe { self.data.as_ptr().offset(at) }
    }
}

/// A pointer that may cross to another thread: each task writes its own batch element.
#[derive(Clone, Copy)]
struct OutPtr(*mut f32);
// SAFETY: the tasks write disjoint batch elements of one output buffer that outlives them.
unsafe impl Send for OutPtr {}
unsafe impl Sync for OutPtr {}

impl OutPtr {
    /// The pointer `i` elements on (a method, so that closures capture the whole `OutPtr`).
    ///
    /// # Safety
    /// `i` must stay inside the allocation.
    unsafe fn add(self, i: usize) -> *mut f32 {
        // SAFETY: the caller keeps `i` inside the allocation.
        unsafe { self.0.add(i) }
    }
}

/// `op(a) op(b)` per batch element, `op` the transpose where asked: `[batch, m, n]`.
fn product(a: &FlexTensor, a_t: bool, b: &FlexTensor, b_t: bool) -> FlexTensor {
    let (a, b) = (Operand::new(a, a_t), Operand::new(b, b_t));
    let [batch, m, k] = a.dims;
    let n = b.dims[2];
    debug_assert_eq!([b.dims[0], b.dims[1]], [batch, k]);
    let len = batch * m * n;
    if k == 0 || len == 0 {
        return flex_tensor(vec![0.0; len], vec![batch, m, n]);
    }
    let mut out: Vec<f32> = Vec::with_capacity(len);
    let base = OutPtr(out.as_mut_ptr());
    let parallel = batch >= rayon::current_num_threads();
    let parallelism = if parallel {
        gemm::Parallelism::None
    } else {
        gemm::Parallelism::Rayon(0)
    };
    let one = |bi: usize| {
        // SAFETY: `a` and `b` address `m x k` and `k x n` elements of batch `bi` through
        // their strides; the output's batch `bi` is `m x n` row-major inside its capacity.
        // With `read_dst` false gemm writes every output element without reading any.
        unsafe {
            gemm::gemm(
                m,
                n,
                k,
                base.add(bi * m * n),
                1,
                n as isize,
                false,
                a.batch_ptr(bi),
                a.strides[2],
                a.strides[1],
                b.batch_ptr(bi),
                b.strides[2],
                b.strides[1],
                0.0,
                1.0,
                false,
                false,
                false,
                parallelism,
            );
        }
    };
    if parallel {
        (0..batch).into_par_iter().for_each(one);
    } else {
        (0..batch).for_each(one);
    }
    // SAFETY: gemm wrote all `batch m n` elements above.
    unsafe { out.set_len(len) };
    flex_tensor(out, vec![batch, m, n])
}

#[cfg(test)]
mod tests;
