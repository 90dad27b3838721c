//! Which Burn backend runs the networks.
//!
//! In Burn 0.22 the backend is a run-time property of the [`Device`]; cargo features only
//! decide which backends are compiled in. `cpu` is Burn's `flex` backend (always built);
//! `wgpu` needs the `wgpu` cargo feature.

use std::fmt;
use std::str::FromStr;

use burn::tensor::{Device, Tensor, activation};

/// A compute backend the user can ask for with `--backend`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum BackendKind {
    /// Burn's `flex` CPU backend.
    #[default]
    Cpu,
    /// Burn's `wgpu` backend on the best adapter wgpu finds (Vulkan, Metal, DX12, or a software
    /// Vulkan driver such as lavapipe).
    Wgpu,
}

/// Errors when picking or checking a backend.
#[derive(Debug, thiserror::Error)]
pub enum BackendError {
    /// The name is not a known backend.
    #[error("unknown backend `{0}`: expected `cpu` or `wgpu`")]
    Unknown(String),
    /// The backend exists but this binary was built without it.
    #[error(
        "backend `{0}` is not compiled into this binary: rebuild with `cargo build --release --features {0}`"
    )]
    NotCompiled(&'static str),
    /// The self-check computed something different from the CPU reference.
    #[error(
        "backend `{backend}` self-check failed: {what} differs from the CPU result by {error:e}"
    )]
    Mismatch {
        backend: BackendKind,
        what: &'static str,
        error: f64,
    },
}

impl BackendKind {
    /// Every backend name, compiled in or not.
    pub const ALL: [BackendKind; 2] = [BackendKind::Cpu, BackendKind::Wgpu];

    /// The name used on the command line and in configs.
    pub fn name(self) -> &'static str {
        match self {
            BackendKind::Cpu => "cpu",
            BackendKind::Wgpu => "wgpu",
        }
    }

    /// Whether this binary was built with this backend.
    pub fn is_compiled(self) -> bool {
        match self {
            BackendKind::Cpu => true,
            BackendKind::Wgpu => cfg!(feature = "wgpu"),
        }
    }

    /// The Burn device for this backend (without autodiff).
    pub fn device(self) -> Result<Device, BackendError> {
        match self {
            BackendKind::Cpu => Ok(Device::flex()),
            #[cfg(feature = "wgpu")]
            BackendKind::Wgpu => Ok(Device::wgpu(burn::tensor::DeviceKind::DefaultDevice)),
            #[cfg(not(feature = "wgpu"))]
            BackendKind::Wgpu => Err(BackendError::NotCompiled("wgpu")),
        }
    }
}

impl fmt::Display for BackendKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for BackendKind {
    type Err = BackendError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "cpu" | "flex" => Ok(BackendKind::Cpu),
            "wgpu" | "gpu" => Ok(BackendKind::Wgpu),
            _ => Err(BackendError::Unknown(s.to_string())),
        }
    }
}

/// What [`self_check`] measured.
#[derive(Clone, Debug)]
pub struct SelfCheck {
    /// The device that ran the check.
    pub device: String,
    /// Largest absolute difference of the forward value from the CPU backend's.
    pub forward_error: f64,
    /// Largest absolute difference of the input gradient from the CPU backend's.
    pub gradient_error: f64,
}

/// Runs a small forward and backward pass (matmul, softplus, conv-free MLP layer) on `kind`
/// and on the CPU backend, and compares values and gradients. A GPU driver that compiles but
/// computes garbage fails here rather than in the middle of training.
pub fn self_check(kind: BackendKind) -> Result<SelfCheck, BackendError> {
    let device = kind.device()?;
    let (value, grad) = mlp_value_and_grad(&device);
    let (value_ref, grad_ref) = mlp_value_and_grad(&Device::flex());
    let forward_error = max_abs_diff(&value, &value_ref);
    let gradient_error = max_abs_diff(&grad, &grad_ref);
    let tolerance = 1e-4;
    if forward_error.is_nan() || forward_error > tolerance {
        return Err(BackendError::Mismatch {
            backend: kind,
            what: "forward value",
            error: forward_error,
        });
    }
    if gradient_error.is_nan() || gradient_error > tolerance {
        return Err(BackendError::Mismatch {
            backend: kind,
            what: "input gradient",
            error: gradient_error,
        });
    }
    Ok(SelfCheck {
        device: format!("{device:?}"),
        forward_error,
        gradient_error,
    })
}

/// `sum(softplus(x W) ^ 2)` and its gradient with respect to `x`, for fixed `x` and `W`.
fn mlp_value_and_grad(device: &Device) -> (Vec<f32>, Vec<f32>) {
    let device = device.clone().autodiff();
    let (n, k, m) = (16usize, 8usize, 4usize);
    let x: Vec<f32> = (0..n * k)
        .map(|i| ((i * 37 % 23) as f32 - 11.0) / 7.0)
        .collect();
    let w: Vec<f32> = (0..k * m)
        .map(|i| ((i * 13 % 17) as f32 - 8.0) / 9.0)
        .collect();
    let x = Tensor::<1>::from_floats(x.as_slice(), &device)
        .reshape([n, k])
        .require_grad();
    let w = Tensor::<1>::from_floats(w.as_slice(), &device).reshape([k, m]);
    let h = activation::softplus(x.clone().matmul(w), 1.0);
    let loss = h.clone().powf_scalar(2.0).sum();
    let grads = loss.backward();
    let grad = x.grad(&grads).expect("x requires a gradient");
    (to_f32_vec(h), to_f32_vec(grad))
}

/// A tensor's values as f32, row-major (reads back from the device).
pub fn to_f32_vec<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .expect("f32 tensor data")
}

/// A tensor's values as f64, row-major (reads back from the device; an f64 tensor exactly).
pub fn to_f64_vec<const D: usize>(t: Tensor<D>) -> Vec<f64> {
    t.into_data()
        .convert::<f64>()
        .try_to_vec::<f64>()
        .expect("f64 tensor data")
}

/// Largest absolute difference; NaN if any value is NaN (so garbage never reads as agreement).
fn max_abs_diff(a: &[f32], b: &[f32]) -> f64 {
    if a.len() != b.len() {
        return f64::INFINITY;
    }
    a.iter()
        .zip(b)
        .map(|(x, y)| (f64::from(*x) - f64::from(*y)).abs())
        .fold(0.0, |m, d| {
            if m.is_nan() || d.is_nan() {
                f64::NAN
            } else {
                m.max(d)
            }
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_names_and_rejects_unknown() {
        assert_eq!("cpu".parse::<BackendKind>().unwrap(), BackendKind::Cpu);
        assert_eq!("WGPU".parse::<BackendKind>().unwrap(), BackendKind::Wgpu);
        let err = "cuda9".parse::<BackendKind>().unwrap_err().to_string();
        assert!(err.contains("cuda9"), "{err}");
    }

    #[test]
    fn cpu_self_check_matches_analytic_gradient() {
        let check = self_check(BackendKind::Cpu).unwrap();
        assert_eq!(check.forward_error, 0.0);
        // The gradient itself against a hand-written one: d/dx sum(sp(xW)^2) = (2 sp sigmoid) W^T.
        let device = Device::flex();
        let (h, grad) = mlp_value_and_grad(&device);
        let (n, k, m) = (16usize, 8usize, 4usize);
        let w: Vec<f32> = (0..k * m)
            .map(|i| ((i * 13 % 17) as f32 - 8.0) / 9.0)
            .collect();
        for r in 0..n {
            for c in 0..k {
                let mut g = 0.0f64;
                for j in 0..m {
                    let sp = f64::from(h[r * m + j]);
                    let sig = 1.0 - (-sp).exp(); // sigmoid(z) = 1 - exp(-softplus(z))
                    g += 2.0 * sp * sig * f64::from(w[c * m + j]);
                }
                assert!((g - f64::from(grad[r * k + c])).abs() < 1e-4, "({r},{c})");
            }
        }
    }

    #[test]
    fn nan_never_reads_as_agreement() {
        assert!(max_abs_diff(&[1.0, f32::NAN], &[1.0, 2.0]).is_nan());
        assert!(max_abs_diff(&[f32::NAN, 1.0], &[1.0, 1.0]).is_nan());
        assert_eq!(max_abs_diff(&[1.0], &[1.0, 2.0]), f64::INFINITY);
        assert_eq!(max_abs_diff(&[1.0, 3.0], &[1.5, 2.0]), 1.0);
    }

    #[cfg(not(feature = "wgpu"))]
    #[test]
    fn missing_backend_says_how_to_build_it() {
        let err = BackendKind::Wgpu.device().unwrap_err().to_string();
        assert!(err.contains("--features wgpu"), "{err}");
    }

    /// Runs the GPU path for real; CI runs it on a software Vulkan driver.
    #[cfg(feature = "wgpu")]
    #[test]
    fn wgpu_self_check_agrees_with_cpu() {
        let check = self_check(BackendKind::Wgpu).unwrap();
        assert!(check.gradient_error < 1e-4);
    }
}
