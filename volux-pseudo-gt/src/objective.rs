//! What the estimator is trained on and judged by. The losses (on the device, over a batch):
//! albedo L1 and normal error `1 - cos` over the true foreground (weighted by its coverage),
//! and the mask's binary cross-entropy over every pixel. The accuracy (on the host, in f64,
//! per image): mean normal angle in degrees and mean absolute albedo error over the true
//! foreground (coverage >= 1/2), and the mask's intersection over union at 1/2.

use burn::tensor::Tensor;
use burn::tensor::activation::log_sigmoid;
use serde::{Deserialize, Serialize};
use volux_envmap::Rgb;

use crate::estimator::EstimateTensors;

/// The true layers of a batch on the device.
pub struct Targets {
    /// `[b, 3, r, r]` linear albedo.
    pub albedo: Tensor<4>,
    /// `[b, 3, r, r]` unit normals (zero where nothing is covered).
    pub normals: Tensor<4>,
    /// `[b, 1, r, r]` coverage.
    pub mask: Tensor<4>,
}

/// The three loss terms, each a `[1]` tensor.
pub struct Losses {
    pub albedo: Tensor<1>,
    pub normals: Tensor<1>,
    pub mask: Tensor<1>,
}

impl Losses {
    /// Their sum, what is minimised.
    pub fn total(&self) -> Tensor<1> {
        self.albedo.clone() + self.normals.clone() + self.mask.clone()
    }
}

/// The losses of `estimate` against `targets`.
pub fn losses(estimate: &EstimateTensors, targets: &Targets) -> Losses {
    let w = targets.mask.clone();
    let area = w.clone().sum().add_scalar(1e-6);
    let albedo = ((estimate.albedo.clone() - targets.albedo.clone()).abs() * w.clone())
        .sum()
        .div(area.clone().mul_scalar(3.0));
    let cos = (estimate.normals.clone() * targets.normals.clone()).sum_dim(1);
    let normals = (cos.neg().add_scalar(1.0) * w).sum().div(area);
    let x = estimate.mask_logit.clone();
    let y = targets.mask.clone();
    let mask = (y.clone() * log_sigmoid(x.clone())
        + y.neg().add_scalar(1.0) * log_sigmoid(x.neg()))
    .mean()
    .neg();
    Losses {
        albedo,
        normals,
        mask,
    }
}

/// The accuracy of one image's estimates, or the mean over several.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Accuracy {
    /// Mean angle between estimated and true normals, degrees, over the true foreground.
    pub normal_degrees: f64,
    /// Mean absolute error of the linear albedo per channel, over the true foreground.
    pub albedo_error: f64,
    /// Intersection over union of the masks thresholded at 1/2.
    pub mask_iou: f64,
}

/// The accuracy of estimated layers against true ones (all `side x side`, row-major).
pub fn accuracy(
    (albedo, normals, mask): (&[Rgb], &[[f32; 3]], &[f32]),
    (true_albedo, true_normals, true_mask): (&[Rgb], &[[f32; 3]], &[f32]),
) -> Accuracy {
    let (mut angle, mut albedo_sum, mut fg) = (0.0f64, 0.0f64, 0usize);
    let (mut both, mut either) = (0usize, 0usize);
    for i in 0..true_mask.len() {
        let (ours, truth) = (mask[i] >= 0.5, true_mask[i] >= 0.5);
        both += usize::from(ours && truth);
        either += usize::from(ours || truth);
        if !truth {
            continue;
        }
        fg += 1;
        let dot = |a: [f32; 3], b: [f32; 3]| {
            (0..3)
                .map(|c| f64::from(a[c]) * f64::from(b[c]))
                .sum::<f64>()
        };
        let (n, t) = (normals[i], true_normals[i]);
        let cos = dot(n, t) / (dot(n, n) * dot(t, t)).sqrt().max(1e-12);
        angle += cos.clamp(-1.0, 1.0).acos().to_degrees();
        albedo_sum += (0..3)
            .map(|c| (f64::from(albedo[i][c]) - f64::from(true_albedo[i][c])).abs())
            .sum::<f64>()
            / 3.0;
    }
    let fg = fg.max(1) as f64;
    Accuracy {
        normal_degrees: angle / fg,
        albedo_error: albedo_sum / fg,
        mask_iou: if either == 0 {
            1.0
        } else {
            both as f64 / either as f64
        },
    }
}

/// The mean of several accuracies.
pub fn mean(all: &[Accuracy]) -> Accuracy {
    let n = all.len().max(1) as f64;
    Accuracy {
        normal_degrees: all.iter().map(|a| a.normal_degrees).sum::<f64>() / n,
        albedo_error: all.iter().map(|a| a.albedo_error).sum::<f64>() / n,
        mask_iou: all.iter().map(|a| a.mask_iou).sum::<f64>() / n,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};
    use volux_envmap::random::SplitMix64;
    use volux_model::backend::to_f32_vec;

    fn tensor(values: &[f32], c: usize, side: usize, device: &Device) -> Tensor<4> {
        Tensor::from_data(TensorData::new(values.to_vec(), [1, c, side, side]), device)
    }

    /// The losses in f64 loops over planar `[c, side * side]` values.
    fn reference(logits: &[f64], truth: &[f64], plane: usize) -> [f64; 3] {
        let sigmoid = |x: f64| 1.0 / (1.0 + (-x).exp());
        let (mut l1, mut cos_term, mut area, mut bce) = (0.0, 0.0, 0.0, 0.0);
        for p in 0..plane {
            let w = truth[6 * plane + p];
            area += w;
            for c in 0..3 {
                l1 += w * (sigmoid(logits[c * plane + p]) - truth[c * plane + p]).abs();
            }
            let n: Vec<f64> = (3..6).map(|c| logits[c * plane + p]).collect();
            let len = (n.iter().map(|v| v * v).sum::<f64>() + 1e-8).sqrt();
            let cos: f64 = (0..3)
                .map(|c| n[c] / len * truth[(3 + c) * plane + p])
                .sum();
            cos_term += w * (1.0 - cos);
            let x = logits[6 * plane + p];
            bce -= w * sigmoid(x).ln() + (1.0 - w) * (1.0 - sigmoid(x)).ln();
        }
        [
            l1 / (3.0 * (area + 1e-6)),
            cos_term / (area + 1e-6),
            bce / plane as f64,
        ]
    }

    #[test]
    fn losses_match_an_f64_reference_and_their_gradient_finite_differences() {
        let device = Device::flex().autodiff();
        let side = 4;
        let plane = side * side;
        let mut rng = SplitMix64::new(5);
        let logits: Vec<f64> = (0..7 * plane).map(|_| 4.0 * rng.next_f64() - 2.0).collect();
        let mut truth: Vec<f64> = (0..7 * plane).map(|_| rng.next_f64()).collect();
        for p in 0..plane {
            let n: Vec<f64> = (3..6).map(|c| truth[c * plane + p] - 0.5).collect();
            let len = n.iter().map(|v| v * v).sum::<f64>().sqrt();
            for c in 0..3 {
                truth[(3 + c) * plane + p] = n[c] / len;
            }
            truth[6 * plane + p] = if p % 3 == 0 {
                0.0
            } else {
                truth[6 * plane + p]
            };
        }
        let run = |logits: &[f64]| {
            let f: Vec<f32> = logits.iter().map(|&v| v as f32).collect();
            let t: Vec<f32> = truth.iter().map(|&v| v as f32).collect();
            let out = tensor(&f, 7, side, &device).require_grad();
            let estimate = EstimateTensors {
                albedo: burn::tensor::activation::sigmoid(out.clone().narrow(1, 0, 3)),
                normals: {
                    let n = out.clone().narrow(1, 3, 3);
                    let l = n
                        .clone()
                        .powf_scalar(2.0)
                        .sum_dim(1)
                        .add_scalar(1e-8)
                        .sqrt();
                    n / l
                },
                mask_logit: out.clone().narrow(1, 6, 1),
            };
            let targets = Targets {
                albedo: tensor(&t[..3 * plane], 3, side, &device),
                normals: tensor(&t[3 * plane..6 * plane], 3, side, &device),
                mask: tensor(&t[6 * plane..], 1, side, &device),
            };
            let l = losses(&estimate, &targets);
            (
                l.total(),
                [l.albedo, l.normals, l.mask].map(|t| f64::from(to_f32_vec(t)[0])),
                out,
            )
        };
        let (total, terms, out) = run(&logits);
        let want = reference(&logits, &truth, plane);
        for k in 0..3 {
            assert!(
                (terms[k] - want[k]).abs() < 1e-5 * want[k].max(1.0),
                "{k}: {} vs {}",
                terms[k],
                want[k]
            );
        }
        let grads = total.backward();
        let grad = to_f32_vec(out.grad(&grads).unwrap());
        let h = 1e-5;
        for i in [
            0,
            5,
            3 * plane + 2,
            4 * plane + 7,
            6 * plane + 1,
            6 * plane + 3,
        ] {
            let (mut up, mut down) = (logits.clone(), logits.clone());
            up[i] += h;
            down[i] -= h;
            let f = |l: &[f64]| reference(l, &truth, plane).iter().sum::<f64>();
            let fd = (f(&up) - f(&down)) / (2.0 * h);
            assert!(
                (f64::from(grad[i]) - fd).abs() < 2e-3 * fd.abs().max(0.05),
                "{i}: {} vs {fd}",
                grad[i]
            );
        }
    }

    #[test]
    fn accuracy_of_known_cases() {
        let n = [0.0f32, 0.0, 1.0];
        let tilted = [
            0.0f32,
            (30f32).to_radians().sin(),
            (30f32).to_radians().cos(),
        ];
        let truth = (
            &[[0.5f32; 3]; 4][..],
            &[n; 4][..],
            &[1.0f32, 1.0, 0.0, 0.0][..],
        );
        let ours = (
            &[[0.6f32, 0.5, 0.2]; 4][..],
            &[tilted; 4][..],
            &[1.0f32, 0.0, 1.0, 0.0][..],
        );
        let a = accuracy(ours, truth);
        assert!((a.normal_degrees - 30.0).abs() < 1e-4, "{a:?}");
        assert!((a.albedo_error - 0.4 / 3.0).abs() < 1e-6, "{a:?}");
        assert!((a.mask_iou - 1.0 / 3.0).abs() < 1e-12);
        assert_eq!(
            accuracy(truth, truth),
            Accuracy {
                normal_degrees: 0.0,
                albedo_error: 0.0,
                mask_iou: 1.0
            }
        );
    }
}
