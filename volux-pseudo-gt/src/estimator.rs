//! The intrinsic estimator: a U-Net ([`volux_model::unet`]) from a photo to its albedo,
//! camera-space normals and foreground mask. It stands where the paper used Total Relighting
//! to make pseudo ground truth, and is trained by volux on the synthetic heads, whose layers
//! are exact ([`crate::training`]).
//!
//! It runs at its working resolution ([`EstimatorConfig::resolution`]): a photo of any side is
//! area-averaged down to it, and the estimates are interpolated back up (normals made unit
//! again, the mask passed through its sigmoid first). Inputs are sRGB in `[0, 1]`, mapped to
//! `[-1, 1]`; the outputs are seven channels: albedo (linear, through a sigmoid), normals
//! (divided by their length) and the mask's logit.

use burn::module::Module;
use burn::tensor::activation::sigmoid;
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};
use volux_envmap::Rgb;
use volux_model::backend::to_f32_vec;
use volux_model::unet::{UNet, UNetConfig};

use volux_data::resample;

/// Output channels: albedo 3, normals 3, mask logit 1.
const OUT_CHANNELS: usize = 7;

/// The estimator's shape: what its checkpoint's `estimator.toml` stores.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct EstimatorConfig {
    /// The side it runs at (pixels).
    pub resolution: usize,
    /// Channels per U-Net level, finest first.
    pub channels: Vec<usize>,
}

impl Default for EstimatorConfig {
    fn default() -> Self {
        EstimatorConfig {
            resolution: 128,
            channels: vec![16, 32, 64, 128, 128],
        }
    }
}

impl EstimatorConfig {
    fn unet(&self) -> UNetConfig {
        UNetConfig::new(3, OUT_CHANNELS, self.channels.clone())
    }

    /// Why this shape cannot be built, if it cannot.
    pub fn check(&self) -> Result<(), String> {
        if self.channels.is_empty() || self.channels.len() > 6 {
            return Err(format!(
                "channels has {} levels: give 1 to 6",
                self.channels.len()
            ));
        }
        if let Some(c) = self.channels.iter().find(|&&c| !(1..=1024).contains(&c)) {
            return Err(format!("channels holds {c}: each level needs 1 to 1024"));
        }
        let divisor = self.unet().divisor();
        if !(8..=512).contains(&self.resolution) || !self.resolution.is_multiple_of(divisor) {
            return Err(format!(
                "resolution = {} must be in 8..=512 and divide by {divisor} (2 per level below the first)",
                self.resolution
            ));
        }
        Ok(())
    }

    /// A network with freshly initialised parameters on `device`.
    pub fn init(&self, device: &Device) -> Estimator {
        Estimator {
            net: self.unet().init(device),
        }
    }
}

/// The network.
#[derive(Module, Debug)]
pub struct Estimator {
    pub net: UNet,
}

/// What the network gives for a batch, on the device.
pub struct EstimateTensors {
    /// `[b, 3, r, r]` linear albedo in (0, 1).
    pub albedo: Tensor<4>,
    /// `[b, 3, r, r]` unit camera-space normals.
    pub normals: Tensor<4>,
    /// `[b, 1, r, r]` the mask's logit.
    pub mask_logit: Tensor<4>,
}

impl Estimator {
    /// `photos: [b, 3, r, r]` sRGB in `[0, 1]`.
    pub fn forward(&self, photos: Tensor<4>) -> EstimateTensors {
        let out = self.net.forward(photos.mul_scalar(2.0).sub_scalar(1.0));
        let albedo = sigmoid(out.clone().narrow(1, 0, 3));
        let n = out.clone().narrow(1, 3, 3);
        let length = n
            .clone()
            .powf_scalar(2.0)
            .sum_dim(1)
            .add_scalar(1e-8)
            .sqrt();
        EstimateTensors {
            albedo,
            normals: n / length,
            mask_logit: out.narrow(1, 6, 1),
        }
    }

    /// Number of scalar parameters.
    pub fn num_params(&self) -> usize {
        Module::num_params(self)
    }
}

/// One photo's estimates on the host, row-major, `side x side`.
#[derive(Clone, Debug, PartialEq)]
pub struct Estimate {
    pub side: usize,
    /// Linear albedo in [0, 1].
    pub albedo: Vec<Rgb>,
    /// Unit camera-space normals.
    pub normals: Vec<[f32; 3]>,
    /// Foreground probability in [0, 1].
    pub mask: Vec<f32>,
}

/// Square sRGB photos of one side, planar on `device` as `[b, 3, side, side]`.
pub fn photo_tensor(photos: &[&[Rgb]], side: usize, device: &Device) -> Tensor<4> {
    let mut flat = Vec::with_capacity(photos.len() * 3 * side * side);
    for photo in photos {
        for c in 0..3 {
            flat.extend(photo.iter().map(|t| t[c]));
        }
    }
    Tensor::from_data(TensorData::new(flat, [photos.len(), 3, side, side]), device)
}

/// The planar `[b, n, r, r]` values back as `b` row-major images of `[f32; N]`.
pub fn interleave<const N: usize>(planar: &[f32], batch: usize, side: usize) -> Vec<Vec<[f32; N]>> {
    let plane = side * side;
    (0..batch)
        .map(|b| {
            let base = b * N * plane;
            (0..plane)
                .map(|p| std::array::from_fn(|c| planar[base + c * plane + p]))
                .collect()
        })
        .collect()
}

impl Estimator {
    /// Estimates for square sRGB photos of side `side` (any side): each brought to the working
    /// `resolution`, estimated, and brought back to `side`.
    pub fn estimate(&self, photos: &[&[Rgb]], side: usize, resolution: usize) -> Vec<Estimate> {
        let device = self.net.out.weight.val().device();
        let small: Vec<Vec<Rgb>> = photos
            .iter()
            .map(|p| resample::resize(p, side, resolution))
            .collect();
        let refs: Vec<&[Rgb]> = small.iter().map(Vec::as_slice).collect();
        let out = self.forward(photo_tensor(&refs, resolution, &device));
        let b = photos.len();
        let albedo = interleave::<3>(&to_f32_vec(out.albedo), b, resolution);
        let normals = interleave::<3>(&to_f32_vec(out.normals), b, resolution);
        let mask = interleave::<1>(&to_f32_vec(sigmoid(out.mask_logit)), b, resolution);
        (0..b)
            .map(|i| Estimate {
                side,
                albedo: resample::resize(&albedo[i], resolution, side),
                normals: resample::resize(&normals[i], resolution, side)
                    .into_iter()
                    .map(unit)
                    .collect(),
                mask: resample::resize(&mask[i], resolution, side)
                    .into_iter()
                    .map(|m| m[0])
                    .collect(),
            })
            .collect()
    }
}

/// `n` made unit length (`(0, 0, 1)` if it has none).
fn unit(n: [f32; 3]) -> [f32; 3] {
    let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if l > 1e-6 {
        n.map(|v| v / l)
    } else {
        [0.0, 0.0, 1.0]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outputs_are_in_range_and_estimates_come_back_at_any_side() {
        let device = Device::flex();
        let config = EstimatorConfig {
            resolution: 16,
            channels: vec![4, 8],
        };
        config.check().unwrap();
        let net = config.init(&device);
        let photo: Vec<Rgb> = (0..40 * 40)
            .map(|i| [(i % 40) as f32 / 40.0, 0.5, 1.0])
            .collect();
        let got = net.estimate(&[&photo, &photo], 40, 16);
        assert_eq!(got.len(), 2);
        for e in &got {
            assert_eq!((e.side, e.albedo.len(), e.mask.len()), (40, 1600, 1600));
            assert!(e.albedo.iter().flatten().all(|v| (0.0..=1.0).contains(v)));
            assert!(e.mask.iter().all(|v| (0.0..=1.0).contains(v)));
            for n in &e.normals {
                let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
                assert!((l - 1.0).abs() < 1e-4);
            }
        }
        assert_eq!(got[0], got[1]);
    }

    #[test]
    fn bad_shapes_are_refused_with_the_value() {
        let bad = |resolution, channels: Vec<usize>| {
            EstimatorConfig {
                resolution,
                channels,
            }
            .check()
            .unwrap_err()
        };
        assert!(bad(60, vec![8, 8, 8, 8]).contains("resolution = 60"));
        assert!(bad(64, vec![]).contains("0 levels"));
        assert!(bad(64, vec![8, 0]).contains("holds 0"));
        assert!(bad(4, vec![8]).contains("resolution = 4"));
    }

    #[test]
    fn planar_values_interleave_per_image() {
        // Two 1x2 images ("side" 1 here means 1 pixel; use side 1 and N = 2).
        let planar = [1.0, 2.0, 3.0, 4.0];
        let got = interleave::<2>(&planar, 2, 1);
        assert_eq!(got, vec![vec![[1.0, 2.0]], vec![[3.0, 4.0]]]);
    }
}
