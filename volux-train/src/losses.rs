//! The adversarial losses of the paper (section 3.4; docs/conventions.md, "Losses"):
//! StyleGAN2's non-saturating logistic loss for every discriminator, lazily regularised R1 on
//! reals, the path loss tying the low- and high-resolution albedo, EG3D's density
//! regulariser (an option, not in the paper), and the weights of the terms.
//!
//! Every loss is a mean over the batch, `[1]`. Softplus is Burn's, which stays finite for
//! logits of any size (it returns `x` itself above a threshold).

use burn::tensor::activation::{sigmoid, softplus};
use burn::tensor::{Device, Distribution, Tensor};
use serde::{Deserialize, Serialize};
use volux_data::layers::{Layer, Layers};
use volux_model::discriminator::{Discriminator, r1_penalty};
use volux_model::upsampler::bilinear_upsample;

/// Generator loss against one discriminator: `mean softplus(-D(fake))`.
pub fn generator_loss(fake_logits: Tensor<2>) -> Tensor<1> {
    softplus(fake_logits.neg(), 1.0).mean()
}

/// The derivative of [`generator_loss`] with respect to each logit, as a constant:
/// `-sigmoid(-D(fake)) / batch`, finite for logits of any size (Burn's sigmoid saturates to 0
/// and 1). It is the cotangent a discriminator's pullback turns into the generator's input
/// gradient (`crate::step`).
pub fn generator_loss_gradient(fake_logits: Tensor<2>) -> Tensor<2> {
    let n = fake_logits.dims().iter().product::<usize>() as f64;
    sigmoid(fake_logits.detach().neg()).div_scalar(-n)
}

/// Discriminator loss: `mean softplus(D(fake)) + mean softplus(-D(real))`.
pub fn discriminator_loss(real_logits: Tensor<2>, fake_logits: Tensor<2>) -> Tensor<1> {
    softplus(fake_logits, 1.0).mean() + softplus(real_logits.neg(), 1.0).mean()
}

/// StyleGAN2's lazy R1: on the steps where it runs (every `interval` discriminator steps) the
/// penalty `gamma / 2 * E ||grad_x D(x)||^2` on reals is multiplied by `interval`, so that
/// its average weight is `gamma`. Returns the reals' logits and the scaled penalty.
pub fn lazy_r1(
    d: &Discriminator,
    reals: Tensor<4>,
    gamma: f64,
    interval: usize,
) -> (Tensor<2>, Tensor<1>) {
    let (logits, penalty) = r1_penalty(d, reals, gamma);
    (logits, penalty.mul_scalar(interval as f64))
}

/// `a` averaged over `factor x factor` blocks: `[b, c, h, w] -> [b, c, h / f, w / f]`.
pub fn area_downsample(a: Tensor<4>, factor: usize) -> Tensor<4> {
    let [b, c, h, w] = a.dims();
    let (ho, wo) = (h / factor, w / factor);
    a.reshape([b, c, ho, factor, wo, factor])
        .mean_dim(5)
        .mean_dim(3)
        .reshape([b, c, ho, wo])
}

/// The path loss: `mean |A_lo - downsample(A_hi)|`, the high-resolution albedo area-averaged
/// to the low resolution (the dataset's low-resolution albedo is made the same way).
pub fn path_loss(albedo_lo: Tensor<4>, albedo_hi: Tensor<4>) -> Tensor<1> {
    let factor = albedo_hi.dims()[2] / albedo_lo.dims()[2];
    (albedo_lo - area_downsample(albedo_hi, factor))
        .abs()
        .mean()
}

/// Half the side of the cube [`density_regulariser_points`] draws from (world units): every
/// ray sample of a training camera lies within it (docs/model.md, "Template planes").
pub const DENSITY_REGULARISER_REACH: f64 = 0.8;

/// Points per batch element [`density_regulariser_points`] draws (EG3D's 1000).
pub const DENSITY_REGULARISER_POINTS: usize = 1000;

/// EG3D's density regulariser: for `sigma: [b, 2n]` the density at `n` points and then at
/// the same points moved by a small offset ([`density_regulariser_points`]),
/// `mean |sigma(x) - sigma(x + e)|`, an L1 total variation of the density sampled
/// everywhere in the volume. A speck of density has a large boundary for its size, so it
/// costs more than a surface does; empty space costs nothing. On the density itself, not
/// its logit: the sphere prior's slope is in every logit, and would turn the term into a
/// push against it.
pub fn density_regulariser(sigma: Tensor<2>) -> Tensor<1> {
    let n = sigma.dims()[1] / 2;
    (sigma.clone().narrow(1, 0, n) - sigma.narrow(1, n, n))
        .abs()
        .mean()
}

/// `[batch, 2 n, 3]` points for [`density_regulariser`]: per element, `n` drawn uniformly
/// in `[-reach, reach]^3`, then the same `n` each moved by `N(0, spread^2)` per coordinate.
pub fn density_regulariser_points(
    batch: usize,
    n: usize,
    reach: f64,
    spread: f64,
    device: &Device,
) -> Tensor<3> {
    let x = Tensor::<3>::random([batch, n, 3], Distribution::Uniform(-reach, reach), device);
    let e = Tensor::<3>::random([batch, n, 3], Distribution::Normal(0.0, spread), device);
    Tensor::cat(vec![x.clone(), x + e], 1)
}

/// What `D_S` sees: the relit image with the diffuse and specular maps it was shaded with,
/// detached (the paper's conditioning), HDR shading through `log1p` as in the relighting
/// network. `[b, 9, H, W]`.
pub fn shading_condition(relit: Tensor<4>, diffuse: Tensor<4>, specular: Tensor<4>) -> Tensor<4> {
    Tensor::cat(
        vec![relit, diffuse.detach().log1p(), specular.detach().log1p()],
        1,
    )
}

/// `D_S`'s condition from shading at the volume resolution, as the generator makes it: the
/// diffuse and specular maps upsampled bilinearly to the relit image's resolution (the
/// relighting network sees the same upsampled maps). `[b, 9, H, W]`.
pub fn shading_condition_lo(
    relit: Tensor<4>,
    diffuse_lo: Tensor<4>,
    specular_lo: Tensor<4>,
) -> Tensor<4> {
    let factor = relit.dims()[2] / diffuse_lo.dims()[2];
    shading_condition(
        relit,
        bilinear_upsample(diffuse_lo.detach(), factor),
        bilinear_upsample(specular_lo.detach(), factor),
    )
}

/// `D_S`'s condition for the reals: their diffuse and specular maps, given at the output
/// resolution, are area-averaged to the volume resolution (`factor` times smaller) and then
/// treated exactly as the fakes' ([`shading_condition_lo`]), so `D_S` cannot tell the two
/// apart by detail the generator's shading cannot have.
pub fn real_shading_condition(
    relit: Tensor<4>,
    diffuse: Tensor<4>,
    specular: Tensor<4>,
    factor: usize,
) -> Tensor<4> {
    shading_condition_lo(
        relit,
        area_downsample(diffuse, factor),
        area_downsample(specular, factor),
    )
}

/// The largest `[loss] density_reg_spread`: offsets of a whole head would compare the
/// density of unrelated points.
pub const MAX_DENSITY_REG_SPREAD: f64 = 0.5;

/// Weights of the loss terms (`[loss]` in a training config). A weight of 0 turns its term
/// off, and with it its discriminator and the renders only it needs.
#[derive(Clone, Copy, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct LossWeights {
    /// `L_A`: albedo, low and high resolution.
    pub albedo: f64,
    /// `L_G`: normal maps.
    pub geometry: f64,
    /// `L_S`: shading, on `[I_relit, D, S]`.
    pub shading: f64,
    /// `L_P`: the relit image against photos.
    pub photo: f64,
    /// L1 between `A_lo` and the downsampled `A_hi`.
    pub path: f64,
    /// EG3D's density regulariser ([`density_regulariser`]; EG3D's `density_reg`, 0.25 on
    /// FFHQ); 0, the default and the paper's: none.
    pub density_reg: f64,
    /// The standard deviation of its offsets, world units (EG3D's `density_reg_p_dist`
    /// is 0.004 of a box about 0.6 heads wide; this one is 0.01 of a box 2 heads wide, about
    /// a third of a 32-pixel volume's pixel).
    pub density_reg_spread: f64,
}

impl Default for LossWeights {
    fn default() -> Self {
        LossWeights {
            albedo: 1.0,
            geometry: 0.5,
            shading: 0.25,
            photo: 0.75,
            path: 0.5,
            density_reg: 0.0,
            density_reg_spread: 0.01,
        }
    }
}

impl LossWeights {
    /// Checks every weight is in `[0, MAX_WEIGHT]` (finite in f32 arithmetic), naming the bad one.
    pub fn validate(&self) -> Result<(), String> {
        for (key, v) in self.named() {
            if !(0.0..=crate::config::MAX_WEIGHT).contains(&v) {
                return Err(format!(
                    "loss.{key} = {v:?} must be in [0, {:e}]",
                    crate::config::MAX_WEIGHT
                ));
            }
        }
        let spread = self.density_reg_spread;
        if !(spread.is_finite() && spread > 0.0 && spread <= MAX_DENSITY_REG_SPREAD) {
            return Err(format!(
                "loss.density_reg_spread = {spread:?} must be in (0, {MAX_DENSITY_REG_SPREAD}]"
            ));
        }
        Ok(())
    }

    /// `(name, weight)` of every term.
    pub fn named(&self) -> [(&'static str, f64); 6] {
        [
            ("albedo", self.albedo),
            ("geometry", self.geometry),
            ("shading", self.shading),
            ("photo", self.photo),
            ("path", self.path),
            ("density_reg", self.density_reg),
        ]
    }

    /// The weights with every adversarial term whose reals the dataset does not `provide`
    /// set to 0 (so that its discriminator is neither built nor run), and the terms left out
    /// for that reason with the layers they lack. The path loss needs no data.
    pub fn restricted_to(&self, provided: &Layers<bool>) -> (LossWeights, Vec<LeftOut>) {
        let mut w = *self;
        let mut left_out = Vec::new();
        for (term, needs) in TERM_LAYERS {
            let missing: Vec<Layer> = needs
                .iter()
                .copied()
                .filter(|&l| !provided.get(l))
                .collect();
            let weight = match term {
                "albedo" => &mut w.albedo,
                "geometry" => &mut w.geometry,
                "shading" => &mut w.shading,
                _ => &mut w.photo,
            };
            if !missing.is_empty() && *weight > 0.0 {
                *weight = 0.0;
                left_out.push(LeftOut { term, missing });
            }
        }
        (w, left_out)
    }
}

/// Each adversarial term with the layers of the reals its discriminator judges.
pub const TERM_LAYERS: [(&str, &[Layer]); 4] = [
    ("albedo", &[Layer::AlbedoLo, Layer::AlbedoHi]),
    ("geometry", &[Layer::NormalsLo]),
    ("shading", &[Layer::Relit, Layer::Diffuse, Layer::Specular]),
    ("photo", &[Layer::Photo]),
];

/// An adversarial term left out because the dataset lacks its reals.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LeftOut {
    pub term: &'static str,
    /// The layers it would judge that the dataset does not provide.
    pub missing: Vec<Layer>,
}

impl std::fmt::Display for LeftOut {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let names: Vec<&str> = self.missing.iter().map(|l| l.name()).collect();
        write!(f, "{} (no {})", self.term, names.join(", "))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, Distribution, TensorData};
    use volux_model::backend::to_f32_vec;

    fn t2(v: &[f32]) -> Tensor<2> {
        Tensor::<1>::from_floats(v, &Device::flex()).reshape([v.len(), 1])
    }

    fn scalar(t: Tensor<1>) -> f64 {
        f64::from(to_f32_vec(t)[0])
    }

    fn softplus64(x: f64) -> f64 {
        x.max(0.0) + (-x.abs()).exp().ln_1p()
    }

    #[test]
    fn terms_without_their_reals_are_left_out() {
        let w = LossWeights::default();
        let (all, none) = w.restricted_to(&Layers::from_fn(|_| true));
        assert_eq!((all, none), (w, vec![]));
        let (photos, left_out) = w.restricted_to(&Layers::from_fn(|l| l == Layer::Photo));
        assert_eq!(
            photos,
            LossWeights {
                albedo: 0.0,
                geometry: 0.0,
                shading: 0.0,
                ..w
            }
        );
        let said: Vec<String> = left_out.iter().map(ToString::to_string).collect();
        assert_eq!(
            said,
            [
                "albedo (no albedo_lo, albedo_hi)",
                "geometry (no normals_lo)",
                "shading (no relit, diffuse, specular)"
            ]
        );
        // A term already off is not reported as left out; one missing layer is enough.
        let no_shading = LossWeights { shading: 0.0, ..w };
        let (_, left_out) = no_shading.restricted_to(&Layers::from_fn(|l| l != Layer::Specular));
        assert!(left_out.is_empty());
        let (only, left_out) = w.restricted_to(&Layers::from_fn(|l| l != Layer::NormalsLo));
        assert_eq!((only.geometry, left_out.len()), (0.0, 1));
    }

    #[test]
    fn logistic_losses_match_an_f64_reference() {
        let (real, fake) = ([0.0, 2.0, -3.0, 0.5], [1.0, -1.5, 4.0, 0.0]);
        let g = scalar(generator_loss(t2(&fake.map(|v| v as f32))));
        let want_g = fake.iter().map(|&f| softplus64(-f)).sum::<f64>() / 4.0;
        assert!((g - want_g).abs() < 1e-6, "{g} vs {want_g}");
        let d = scalar(discriminator_loss(
            t2(&real.map(|v| v as f32)),
            t2(&fake.map(|v| v as f32)),
        ));
        let want_d = fake.iter().map(|&f| softplus64(f)).sum::<f64>() / 4.0
            + real.iter().map(|&r| softplus64(-r)).sum::<f64>() / 4.0;
        assert!((d - want_d).abs() < 1e-6, "{d} vs {want_d}");
        // At D = 0 everywhere both players see ln 2 per term.
        let zero = t2(&[0.0; 3]);
        assert!((scalar(discriminator_loss(zero.clone(), zero)) - 2.0 * 2f64.ln()).abs() < 1e-6);
    }

    #[test]
    fn losses_and_their_gradients_stay_finite_for_extreme_logits() {
        let device = Device::flex().autodiff();
        let logits = Tensor::<1>::from_floats([1e4f32, -1e4, 88.0, -88.0, 0.0].as_slice(), &device)
            .reshape([5, 1])
            .require_grad();
        let loss =
            discriminator_loss(logits.clone(), logits.clone()) + generator_loss(logits.clone());
        let value = scalar(loss.clone().inner());
        assert!(value.is_finite(), "{value}");
        // softplus(1e4) = 1e4: the loss is dominated by it, exactly.
        assert!((value - (1e4 + 1e4 + 1e4 + 3.0 * 88.0) / 5.0 - 3.0 * 2f64.ln() / 5.0).abs() < 1.0);
        let grads = loss.backward();
        let g = to_f32_vec(logits.grad(&grads).unwrap());
        assert!(g.iter().all(|v| v.is_finite()), "{g:?}");
        // d/dx [softplus(x) + softplus(-x) + softplus(-x)] / 5 = (sigmoid(x) - 2 sigmoid(-x)) / 5.
        let want = |x: f64| (1.0 / (1.0 + (-x).exp()) - 2.0 / (1.0 + x.exp())) / 5.0;
        for (x, gx) in [1e4, -1e4, 88.0, -88.0, 0.0].iter().zip(&g) {
            assert!(
                (f64::from(*gx) - want(*x)).abs() < 1e-6,
                "x {x}: {gx} vs {}",
                want(*x)
            );
        }
    }

    /// The closed form against autodiff of the loss itself, and finite where `exp` of the
    /// logit overflows.
    #[test]
    fn generator_loss_gradient_is_the_losss_derivative() {
        let device = Device::flex().autodiff();
        let values = [1e4f32, -1e4, 88.0, -88.0, 20.0, -20.0, 0.0, 0.7];
        let logits = Tensor::<1>::from_floats(values.as_slice(), &device)
            .reshape([values.len(), 1])
            .require_grad();
        let grads = generator_loss(logits.clone()).backward();
        let want = to_f32_vec(logits.grad(&grads).unwrap());
        let got = to_f32_vec(generator_loss_gradient(logits));
        let n = values.len() as f64;
        for ((x, g), a) in values.iter().zip(&got).zip(&want) {
            let exact = -1.0 / (1.0 + f64::from(*x).exp()) / n;
            assert!(g.is_finite(), "logit {x}: {g}");
            assert!(
                (f64::from(*g) - exact).abs() <= 1e-7 * (1.0 + exact.abs()),
                "logit {x}: {g} vs {exact}"
            );
            assert!((g - a).abs() <= 1e-7, "logit {x}: {g} vs autodiff {a}");
        }
    }

    #[test]
    fn path_loss_is_zero_for_consistent_albedo_and_the_offset_otherwise() {
        let device = Device::flex();
        let lo = Tensor::<4>::from_data(
            TensorData::new(
                (0..2 * 3 * 4 * 4).map(|i| i as f32 / 96.0).collect(),
                [2, 3, 4, 4],
            ),
            &device,
        );
        // Nearest-neighbour x2 upsampling: every 2x2 block averages back to its pixel.
        let hi = lo
            .clone()
            .reshape([2, 3, 4, 1, 4, 1])
            .repeat_dim(3, 2)
            .repeat_dim(5, 2)
            .reshape([2, 3, 8, 8]);
        assert!(scalar(path_loss(lo.clone(), hi.clone())) < 1e-7);
        assert!((scalar(path_loss(lo.add_scalar(0.25), hi)) - 0.25).abs() < 1e-6);
    }

    #[test]
    fn shading_condition_stacks_nine_channels_and_stops_gradients_to_the_shading() {
        let device = Device::flex().autodiff();
        let ones = |c| Tensor::<4>::ones([1, c, 2, 2], &device).require_grad();
        let (relit, d, s) = (ones(3), ones(3), ones(3));
        let x = shading_condition(relit.clone(), d.clone(), s.clone());
        assert_eq!(x.dims(), [1, 9, 2, 2]);
        let v = to_f32_vec(x.clone().inner());
        // Channel 0 is the relit image as it is, channel 3 (index 12) log1p of the diffuse.
        assert_eq!(v[0], 1.0);
        assert!((v[12] - 1f32.ln_1p()).abs() < 1e-6);
        let grads = x.sum().backward();
        assert!(relit.grad(&grads).is_some());
        assert!(d.grad(&grads).is_none() && s.grad(&grads).is_none());
    }

    #[test]
    fn reals_and_fakes_with_the_same_shading_reach_d_s_identical() {
        let device = Device::flex();
        device.seed(8);
        let random = |c, side| {
            Tensor::<4>::random([2, c, side, side], Distribution::Uniform(0.0, 4.0), &device)
        };
        let (relit, d_hi, s_hi) = (random(3, 16), random(3, 16), random(3, 16));
        // The generator renders the shading at the volume resolution; the data's is given at
        // the output resolution. With the same content, D_S sees the same input.
        let d_lo = area_downsample(d_hi.clone(), 2);
        let s_lo = area_downsample(s_hi.clone(), 2);
        let fake = shading_condition_lo(relit.clone(), d_lo, s_lo);
        let real = real_shading_condition(relit.clone(), d_hi.clone(), s_hi.clone(), 2);
        assert_eq!(fake.dims(), [2, 9, 16, 16]);
        let (f, r) = (to_f32_vec(fake), to_f32_vec(real));
        assert!(f.iter().zip(&r).all(|(a, b)| a == b));
        // Given to D_S at the output resolution as they are, the reals would differ by
        // detail the generator's shading cannot have.
        let sharp = to_f32_vec(shading_condition(relit, d_hi, s_hi));
        let differ = f
            .iter()
            .zip(&sharp)
            .filter(|(a, b)| (*a - *b).abs() > 1e-3)
            .count();
        assert!(differ > f.len() / 4, "{differ} of {}", f.len());
    }

    #[test]
    fn lazy_r1_is_the_penalty_times_the_interval() {
        use volux_model::discriminator::DiscriminatorConfig;
        let device = Device::flex();
        device.seed(3);
        let d = DiscriminatorConfig::small(3, 16).init(&device);
        let reals = Tensor::<4>::random(
            [2, 3, 16, 16],
            burn::tensor::Distribution::Normal(0.0, 1.0),
            &device,
        );
        let (_, once) = r1_penalty(&d, reals.clone(), 10.0);
        let (_, lazy) = lazy_r1(&d, reals, 10.0, 16);
        let (once, lazy) = (scalar(once), scalar(lazy));
        assert!(
            once > 0.0 && (lazy - 16.0 * once).abs() < 1e-4 * lazy,
            "{lazy} vs 16 x {once}"
        );
    }

    #[test]
    fn weights_default_to_the_papers_and_reject_bad_values() {
        assert_eq!(
            LossWeights::default().named().map(|(_, w)| w),
            [1.0, 0.5, 0.25, 0.75, 0.5, 0.0]
        );
        let w: LossWeights = toml::from_str("photo = 0.0").unwrap();
        assert_eq!((w.photo, w.albedo), (0.0, 1.0));
        assert!(
            toml::from_str::<LossWeights>("phot = 1.0")
                .unwrap_err()
                .to_string()
                .contains("phot")
        );
        let bad = LossWeights {
            shading: -1.0,
            ..LossWeights::default()
        };
        assert!(bad.validate().unwrap_err().contains("loss.shading"));
        for spread in [0.0, -0.01, f64::NAN, f64::INFINITY, 0.6] {
            let bad = LossWeights {
                density_reg_spread: spread,
                ..LossWeights::default()
            };
            let why = bad.validate().unwrap_err();
            assert!(why.contains("loss.density_reg_spread"), "{why}");
        }
        let w: LossWeights = toml::from_str("density_reg = 0.25").unwrap();
        assert_eq!((w.density_reg, w.density_reg_spread), (0.25, 0.01));
        assert!(w.validate().is_ok());
    }

    /// The regulariser is `mean |sigma(x) - sigma(x + e)|` (against f64), its gradient
    /// `sign / (b n)` on the first half and the opposite on the second; the points are the
    /// cube's, then the same points moved by offsets of the spread asked.
    #[test]
    fn density_regulariser_is_the_mean_absolute_difference_of_its_point_pairs() {
        let device = Device::flex().autodiff();
        device.seed(5);
        let (b, n) = (2, 7);
        let values: Vec<f32> = (0..b * 2 * n)
            .map(|i| ((i * 37 % 11) as f32 - 5.0) * 0.3)
            .collect();
        let sigma = Tensor::<2>::from_data(TensorData::new(values.clone(), [b, 2 * n]), &device)
            .require_grad();
        let loss = density_regulariser(sigma.clone());
        let mut want = 0.0f64;
        let mut grad = vec![0.0f64; b * 2 * n];
        for e in 0..b {
            for i in 0..n {
                let (a, c) = (e * 2 * n + i, e * 2 * n + n + i);
                let d = f64::from(values[a]) - f64::from(values[c]);
                want += d.abs() / (b * n) as f64;
                grad[a] = d.signum() / (b * n) as f64;
                grad[c] = -d.signum() / (b * n) as f64;
            }
        }
        assert!((scalar(loss.clone()) - want).abs() <= 1e-6, "{want}");
        let got = to_f32_vec(sigma.grad(&loss.backward()).unwrap());
        for (g, w) in got.iter().zip(&grad) {
            assert!((f64::from(*g) - w).abs() <= 1e-7, "{g} vs {w}");
        }

        let device = Device::flex();
        device.seed(6);
        let (b, n, reach, spread) = (3, 4000, 0.8, 0.01);
        let points = density_regulariser_points(b, n, reach, spread, &device);
        assert_eq!(points.dims(), [b, 2 * n, 3]);
        let p = to_f32_vec(points);
        let (mut sum, mut square, mut count) = (0.0f64, 0.0f64, 0usize);
        for e in 0..b {
            for i in 0..n {
                for k in 0..3 {
                    let x = f64::from(p[(e * 2 * n + i) * 3 + k]);
                    let moved = f64::from(p[(e * 2 * n + n + i) * 3 + k]);
                    // The cube's edge as the f32 the points are drawn in (0.8 rounds up).
                    assert!(x.abs() <= f64::from(reach as f32), "{x} outside the cube");
                    sum += moved - x;
                    square += (moved - x).powi(2);
                    count += 1;
                }
            }
        }
        let mean = sum / count as f64;
        let sd = (square / count as f64 - mean * mean).sqrt();
        assert!(
            mean.abs() < 1e-3 && (sd / spread - 1.0).abs() < 0.05,
            "{mean} {sd}"
        );
    }
}
