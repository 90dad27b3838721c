//! What the hand-written flex operations (this crate's kernels and `volux-train`'s fused
//! Adam) share: which path a device takes, and conversions
//! between flex tensors and slices.
//!
//! Burn 0.22 picks the backend at run time from the device. A custom operation reaches flex's
//! tensors through Burn's backend-extension API (`Tensor::try_into_primitive` /
//! `from_primitive`) and, under autodiff, registers its own backward node
//! (`burn-autodiff`'s `Backward` trait). Every other backend runs the operation's plain
//! tensor-op reference.

use std::borrow::Cow;

use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::ops::NodeGuard;
use burn::backend::flex::FlexTensor;
use burn::backend::{Autodiff, DispatchDevice, Flex, GradientCheckpointingStrategy};
use burn::tensor::{Device, DispatchTensor, Tensor, TensorData};
use burn_dispatch::DispatchKindConversion;

/// Where a custom operation runs on a device.
pub enum Route {
    /// Flex without autodiff: the fast kernel.
    Flex,
    /// Autodiff over flex with this checkpointing strategy: the fast kernel and its
    /// hand-written backward.
    Autodiff(GradientCheckpointingStrategy),
    /// Any other backend: the tensor-op reference.
    Other,
}

pub fn route(device: &Device) -> Route {
    #[allow(unreachable_patterns)] // with only flex compiled in, `_` covers nothing
    match device.as_dispatch() {
        DispatchDevice::Flex(_) => Route::Flex,
        DispatchDevice::Autodiff(inner) => match &**inner {
            DispatchDevice::Flex(_) => Route::Autodiff(inner.gradient_checkpointing_strategy()),
            _ => Route::Other,
        },
        _ => Route::Other,
    }
}

/// A contiguous f32 view of a flex tensor (copied only if it is strided).
pub fn contiguous(t: &FlexTensor) -> Cow<'_, [f32]> {
    match t.as_slice::<f32>() {
        Some(s) => Cow::Borrowed(s),
        None => Cow::Owned(t.to_contiguous().as_slice::<f32>().unwrap().to_vec()),
    }
}

/// A flex tensor owning `values` with `shape`.
pub fn flex_tensor(values: Vec<f32>, shape: Vec<usize>) -> FlexTensor {
    FlexTensor::from_data(TensorData::new(values, shape))
}

/// An autodiff flex tensor's inner flex tensor and its node guard, for the checkpointing
/// strategy `C` of the device's route (generic over `C`, so that one function serves
/// [`Route::Autodiff`] with either strategy).
pub fn autodiff_parts<C, const D: usize>(t: Tensor<D>) -> (FlexTensor, NodeGuard)
where
    C: CheckpointStrategy,
    DispatchTensor: DispatchKindConversion<Autodiff<Flex, C>>,
{
    let Ok(t) = t.try_into_primitive::<Autodiff<Flex, C>>() else {
        unreachable!("an autodiff flex device holds autodiff flex tensors")
    };
    t.into_parts()
}
