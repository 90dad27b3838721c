//! What the hand-written flex operations (this crate's kernels and `volux-train`'s fused
//! Adam) share: which path a device takes, conversions between flex tensors and slices, and
//! the instruction set a kernel is compiled for ([`dispatch_simd`]).
//!
//! Burn 0.22 picks the backend at run time from the device. A custom operation reaches flex's
//! tensors through Burn's backend-extension API (`Tensor::try_into_primitive` /
//! `from_primitive`) and, under autodiff, registers its own backward node
//! (`burn-autodiff`'s `Backward` trait). Every other backend runs the operation's plain
//! tensor-op reference.

use std::borrow::Cow;
use std::cell::RefCell;
use std::mem::MaybeUninit;

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

/// `len` values written by `fill`, which receives the vector's uninitialised storage: no
/// zeroing pass before a kernel that overwrites every element (`vec![0.0; len]` is a
/// `calloc`, and the `volux` binary keeps freed memory mapped, so each one was a `memset`:
/// 5-12% of the CPU samples of a discriminator step).
///
/// # Safety
/// `fill` must initialise every one of the `len` elements.
pub(crate) unsafe fn written_by(
    len: usize,
    fill: impl FnOnce(&mut [MaybeUninit<f32>]),
) -> Vec<f32> {
    let mut values = Vec::with_capacity(len);
    fill(&mut values.spare_capacity_mut()[..len]);
    // SAFETY: the caller's `fill` initialised all `len` elements.
    unsafe { values.set_len(len) };
    values
}

/// `out` zeroed, as initialised values.
pub(crate) fn zeroed(out: &mut [MaybeUninit<f32>]) -> &mut [f32] {
    out.fill(MaybeUninit::new(0.0));
    // SAFETY: every element was initialised just above; `MaybeUninit<f32>` has `f32`'s layout.
    unsafe { &mut *(out as *mut [MaybeUninit<f32>] as *mut [f32]) }
}

thread_local! {
    static SCRATCH: RefCell<Vec<f32>> = const { RefCell::new(Vec::new()) };
}

/// Runs `f` on `len` elements of this thread's scratch buffer, which holds whatever the last
/// user left there (never uninitialised memory, but not zeros either): for a kernel's
/// temporary that it overwrites before reading, such as a convolution's patch matrix. The
/// buffer grows to the largest `len` asked for on the thread and is kept for the next call,
/// so a layer applied to every image of a batch allocates and zeroes nothing after the
/// first. A nested call on the same thread gets a fresh vector.
pub(crate) fn with_scratch<R>(len: usize, f: impl FnOnce(&mut [f32]) -> R) -> R {
    SCRATCH.with(|cell| match cell.try_borrow_mut() {
        Ok(mut buffer) => {
            if buffer.len() < len {
                buffer.resize(len, 0.0);
            }
            f(&mut buffer[..len])
        }
        Err(_) => f(&mut vec![0.0; len]),
    })
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

/// The instruction sets the kernels are compiled for, best last.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) enum Simd {
    /// The baseline target.
    Baseline,
    /// AVX2 and FMA: eight lanes.
    Avx2,
    /// AVX-512 (F, DQ, VL, BW) and FMA: sixteen lanes and 32 vector registers, which the
    /// polynomials' constants need.
    Avx512,
}

/// The best instruction set this CPU has (capped by [`SIMD_CAP`] in tests).
pub(crate) fn simd() -> Simd {
    #[cfg(target_arch = "x86_64")]
    let best = if ["avx512f", "avx512dq", "avx512vl", "avx512bw", "fma"]
        .iter()
        .all(|f| detected(f))
    {
        Simd::Avx512
    } else if detected("avx2") && detected("fma") {
        Simd::Avx2
    } else {
        Simd::Baseline
    };
    #[cfg(not(target_arch = "x86_64"))]
    let best = Simd::Baseline;
    #[cfg(test)]
    let best = best.min(simd_cap::get());
    best
}

#[cfg(target_arch = "x86_64")]
fn detected(feature: &str) -> bool {
    match feature {
        "avx512f" => std::is_x86_feature_detected!("avx512f"),
        "avx512dq" => std::is_x86_feature_detected!("avx512dq"),
        "avx512vl" => std::is_x86_feature_detected!("avx512vl"),
        "avx512bw" => std::is_x86_feature_detected!("avx512bw"),
        "avx2" => std::is_x86_feature_detected!("avx2"),
        "fma" => std::is_x86_feature_detected!("fma"),
        _ => false,
    }
}

/// Runs `kernel(args: $args_ty) -> Vec<f32>` (or `-> $ret`) compiled for the best
/// instruction set of [`simd`]: the same source, vectorised sixteen, eight or four lanes
/// wide.
macro_rules! dispatch_simd {
    ($kernel:ident, $args:expr, $args_ty:ty) => {
        $crate::flex_extension::dispatch_simd!($kernel, $args, $args_ty => Vec<f32>)
    };
    ($kernel:ident, $args:expr, $args_ty:ty => $ret:ty) => {{
        let args: $args_ty = $args;
        match $crate::flex_extension::simd() {
            #[cfg(target_arch = "x86_64")]
            $crate::flex_extension::Simd::Avx512 => {
                #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx512bw,avx2,fma")]
                unsafe fn widest(args: $args_ty) -> $ret {
                    $kernel(args)
                }
                // SAFETY: `simd` found the features `widest` is compiled for.
                unsafe { widest(args) }
            }
            #[cfg(target_arch = "x86_64")]
            $crate::flex_extension::Simd::Avx2 => {
                #[target_feature(enable = "avx2,fma")]
                unsafe fn wide(args: $args_ty) -> $ret {
                    $kernel(args)
                }
                // SAFETY: `simd` found the features `wide` is compiled for.
                unsafe { wide(args) }
            }
            _ => $kernel(args),
        }
    }};
}

pub(crate) use dispatch_simd;

/// A cap on [`simd`] for tests that run every instruction set: they hold [`simd_cap::with`]'s
/// lock while the cap is lowered; other tests meet only correct kernels meanwhile.
#[cfg(test)]
pub(crate) mod simd_cap {
    use std::sync::Mutex;
    use std::sync::atomic::{AtomicU8, Ordering};

    use super::Simd;

    static CAP: AtomicU8 = AtomicU8::new(2);
    static LOCK: Mutex<()> = Mutex::new(());

    pub(crate) fn get() -> Simd {
        match CAP.load(Ordering::Relaxed) {
            0 => Simd::Baseline,
            1 => Simd::Avx2,
            _ => Simd::Avx512,
        }
    }

    /// Runs `f` once per instruction set this CPU has, with the kernels capped at it.
    pub(crate) fn each(mut f: impl FnMut(Simd)) {
        let _guard = LOCK.lock().unwrap_or_else(|e| e.into_inner());
        let top = super::simd();
        for (cap, level) in [(0, Simd::Baseline), (1, Simd::Avx2), (2, Simd::Avx512)] {
            if level > top {
                continue;
            }
            CAP.store(cap, Ordering::Relaxed);
            assert_eq!(super::simd(), level);
            f(level);
        }
        CAP.store(2, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scratch_is_reused_and_a_nested_call_gets_its_own() {
        let first = with_scratch(8, |outer| {
            outer.fill(1.0);
            // A nested call on the same thread must not alias the outer buffer.
            with_scratch(4, |inner| {
                inner.fill(2.0);
                assert_eq!(inner.len(), 4);
            });
            assert!(outer.iter().all(|v| *v == 1.0));
            outer.as_ptr() as usize
        });
        // The next call gets the same storage back, larger if asked.
        let again = with_scratch(4, |s| {
            assert_eq!(s.len(), 4);
            s.as_ptr() as usize
        });
        assert_eq!(first, again);
        with_scratch(1 << 12, |s| assert_eq!(s.len(), 1 << 12));
    }

    #[test]
    fn written_by_keeps_what_fill_wrote() {
        // SAFETY: every element is written.
        let v = unsafe {
            written_by(5, |out| {
                for (i, o) in out.iter_mut().enumerate() {
                    o.write(i as f32);
                }
            })
        };
        assert_eq!(v, [0.0, 1.0, 2.0, 3.0, 4.0]);
        // SAFETY: nothing to write.
        assert!(unsafe { written_by(0, |_| {}) }.is_empty());
    }
}
