//! Deterministic parameters and inputs for tests, independent of Burn's global random
//! generator (which tests running in parallel share).

use burn::module::{ModuleMapper, Param};
use burn::tensor::{DType, Tensor, TensorData};
use volux_envmap::random::SplitMix64;

/// A standard normal sample (Box-Muller on SplitMix64).
pub fn normal(rng: &mut SplitMix64) -> f64 {
    let u = rng.next_f64().max(1e-300);
    let v = rng.next_f64();
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
}

/// `n` standard normal samples.
pub fn normals(rng: &mut SplitMix64, n: usize) -> Vec<f64> {
    (0..n).map(|_| normal(rng)).collect()
}

/// Replaces every parameter by deterministic N(0, 1) values (biases included, so that no test
/// relies on zero biases) in `dtype`: `module.map(&mut Reseed::new(seed, dtype))`.
pub struct Reseed {
    rng: SplitMix64,
    dtype: DType,
}

impl Reseed {
    pub fn new(seed: u64, dtype: DType) -> Self {
        Self {
            rng: SplitMix64::new(seed),
            dtype,
        }
    }
}

impl ModuleMapper for Reseed {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let t = param.val();
        let dims = t.dims();
        let values = normals(&mut self.rng, dims.iter().product());
        Param::from_tensor(Tensor::from_data(
            TensorData::new(values, dims),
            (&t.device(), self.dtype),
        ))
    }
}

/// `values` as an f64 tensor of `shape` on `device` (the inputs of f64 reference checks).
pub fn f64_tensor<const D: usize>(
    values: Vec<f64>,
    shape: [usize; D],
    device: &burn::tensor::Device,
) -> Tensor<D> {
    Tensor::from_data(TensorData::new(values, shape), (device, DType::F64))
}

/// Moves element `index` of parameter `p` by `delta` (in f64, stored back in the parameter's
/// dtype on its device): one side of a central difference in a network's weight.
pub fn shift_element<const D: usize>(p: &mut Param<Tensor<D>>, index: usize, delta: f64) {
    let t = p.val();
    let mut values = crate::backend::to_f64_vec(t.clone());
    values[index] += delta;
    *p = Param::from_tensor(Tensor::from_data(
        TensorData::new(values, t.dims()),
        (&t.device(), t.dtype()),
    ));
}

/// A field whose density is another's times a constant (the stiff and empty cases of the
/// renderer's tests).
pub struct Scaled<'a, F: crate::field::Field>(pub &'a F, pub f64);

impl<F: crate::field::Field> crate::field::Field for Scaled<'_, F> {
    fn query(
        &self,
        points: Tensor<3>,
        wants: crate::field::FieldWants,
    ) -> crate::field::FieldOutput {
        let mut out = self.0.query(points, wants);
        out.sigma = out.sigma.mul_scalar(self.1);
        out
    }
}

/// The light-map exponents of the renderer's tests.
pub const EXPONENTS: [u32; 4] = [1, 16, 32, 64];

/// Smooth random light maps (low-frequency waves, all positive, about `scale`), one per
/// exponent of [`EXPONENTS`].
pub fn wave_light_maps(seed: u64, scale: f64) -> Vec<volux_envmap::LightMap> {
    let mut rng = SplitMix64::new(seed);
    EXPONENTS
        .iter()
        .map(|&n| {
            let (w, h) = (32, 16);
            let a: Vec<f64> = (0..9).map(|_| rng.next_f64()).collect();
            let texels = (0..w * h)
                .map(|i| {
                    let (x, y) = ((i % w) as f64 / w as f64, (i / w) as f64 / h as f64);
                    std::array::from_fn(|c| {
                        let wave = (std::f64::consts::TAU * x + 6.0 * a[3 * c]).sin()
                            * (3.0 * y + a[3 * c + 1]).cos();
                        (scale * (1.0 + 0.5 * wave + 0.3 * a[3 * c + 2])) as f32
                    })
                })
                .collect();
            volux_envmap::LightMap::new(n, w, h, texels)
        })
        .collect()
}

/// The renderer's `Lighting` of one set of [`wave_light_maps`] per batch element, rotated by
/// `yaw`.
pub fn lighting(
    maps: &[Vec<volux_envmap::LightMap>],
    yaw: &[f32],
    device: &burn::tensor::Device,
) -> crate::light_lookup::Lighting {
    let batches = (0..EXPONENTS.len())
        .map(|i| {
            let per: Vec<&volux_envmap::LightMap> = maps.iter().map(|m| &m[i]).collect();
            crate::light_lookup::LightMapBatch::new(&per, device).unwrap()
        })
        .collect();
    crate::light_lookup::Lighting::new(batches, Some(Tensor::from_floats(yaw, device))).unwrap()
}

/// A convolution in f64 loops, straight from the definition: `x: [b, ci, h, w]`,
/// `wt: [co, ci, k, k]`, zero padding `pad` on every side; gives `[b, co, ho, wo]` and
/// `[ho, wo]`.
pub fn conv2d_f64(
    x: &[f64],
    [b, ci, h, w]: [usize; 4],
    wt: &[f64],
    [co, k]: [usize; 2],
    stride: usize,
    pad: usize,
) -> (Vec<f64>, [usize; 2]) {
    let ho = (h + 2 * pad - k) / stride + 1;
    let wo = (w + 2 * pad - k) / stride + 1;
    let mut y = vec![0.0; b * co * ho * wo];
    for n in 0..b {
        for o in 0..co {
            for i in 0..ho {
                for j in 0..wo {
                    let mut acc = 0.0;
                    for c in 0..ci {
                        for u in 0..k {
                            for v in 0..k {
                                let (r, s) = (i * stride + u, j * stride + v);
                                if r < pad || s < pad || r - pad >= h || s - pad >= w {
                                    continue;
                                }
                                acc += x[((n * ci + c) * h + r - pad) * w + s - pad]
                                    * wt[((o * ci + c) * k + u) * k + v];
                            }
                        }
                    }
                    y[((n * co + o) * ho + i) * wo + j] = acc;
                }
            }
        }
    }
    (y, [ho, wo])
}
