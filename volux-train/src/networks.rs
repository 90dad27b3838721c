//! What training optimises: the generator, its exponential moving average (what the sampler
//! uses), and the discriminators a config needs (section 3.4: `D_A` at low and high
//! resolution, `D_G`, `D_S`, `D_P`). A discriminator whose loss weight is 0 is not built.

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::tensor::{Device, Tensor};
use volux_model::backend::to_f32_vec;
use volux_model::discriminator::Discriminator;
use volux_model::presets::DiscriminatorRole;

use crate::config::TrainConfig;

/// The discriminators of a run; `None` where the term's weight is 0.
#[derive(Module, Debug)]
pub struct Discriminators {
    /// `D_A` on `A_lo`.
    pub albedo_lo: Option<Discriminator>,
    /// `D_A` on `A_hi`.
    pub albedo_hi: Option<Discriminator>,
    /// `D_G` on normal maps.
    pub geometry: Option<Discriminator>,
    /// `D_S` on `[I_relit, D, S]`.
    pub shading: Option<Discriminator>,
    /// `D_P` on `I_relit` against photos.
    pub photo: Option<Discriminator>,
}

impl Discriminators {
    /// The discriminators `config`'s weights need, freshly initialised on `device`.
    pub fn init(config: &TrainConfig, device: &Device) -> Discriminators {
        let w = &config.loss;
        let make = |role: DiscriminatorRole, weight: f64| {
            (weight > 0.0).then(|| {
                config
                    .model
                    .discriminator(role)
                    .expect("validated")
                    .init(device)
            })
        };
        Discriminators {
            albedo_lo: make(DiscriminatorRole::AlbedoLow, w.albedo),
            albedo_hi: make(DiscriminatorRole::AlbedoHigh, w.albedo),
            geometry: make(DiscriminatorRole::Geometry, w.geometry),
            shading: make(DiscriminatorRole::Shading, w.shading),
            photo: make(DiscriminatorRole::Photo, w.photo),
        }
    }

    /// The discriminator of `role`, if the run has one.
    pub fn get(&self, role: DiscriminatorRole) -> Option<&Discriminator> {
        match role {
            DiscriminatorRole::AlbedoLow => self.albedo_lo.as_ref(),
            DiscriminatorRole::AlbedoHigh => self.albedo_hi.as_ref(),
            DiscriminatorRole::Geometry => self.geometry.as_ref(),
            DiscriminatorRole::Shading => self.shading.as_ref(),
            DiscriminatorRole::Photo => self.photo.as_ref(),
        }
    }

    /// Names of the discriminators that exist (stored in checkpoints).
    pub fn names(&self) -> Vec<&'static str> {
        DiscriminatorRole::ALL
            .into_iter()
            .filter(|&role| self.get(role).is_some())
            .map(DiscriminatorRole::key)
            .collect()
    }
}

/// StyleGAN2-ADA's EMA coefficient for one step of `batch` images after `images` images:
/// the half-life is `ema_kimg` thousand images, at most `rampup` times the images seen.
pub fn ema_beta(batch: usize, images: u64, ema_kimg: f64, rampup: f64) -> f64 {
    let mut half_life = ema_kimg * 1000.0;
    if rampup > 0.0 {
        half_life = half_life.min(images as f64 * rampup);
    }
    if half_life <= 0.0 {
        return 0.0;
    }
    0.5f64.powf(batch as f64 / half_life)
}

/// Every float parameter of a module, flattened, in visiting order, without autodiff.
struct Collect(Vec<Tensor<1>>);

impl ModuleVisitor for Collect {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let t = param.val().inner();
        let n = t.shape().num_elements();
        self.0.push(t.reshape([n]));
    }
}

/// Moves each parameter towards the collected one: `p = beta p + (1 - beta) q`.
struct Lerp {
    targets: std::vec::IntoIter<Tensor<1>>,
    beta: f64,
}

impl ModuleMapper for Lerp {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let target = self.targets.next().expect("same module structure");
        let beta = self.beta;
        param.map(|p| {
            let shape = p.shape();
            let q = target.reshape(shape).to_device(&p.device());
            p.mul_scalar(beta) + q.mul_scalar(1.0 - beta)
        })
    }
}

/// `ema = beta ema + (1 - beta) model`, parameter by parameter (the two share a structure).
pub fn update_ema<M: Module>(ema: M, model: &M, beta: f64) -> M {
    let mut collect = Collect(Vec::new());
    model.visit(&mut collect);
    ema.map(&mut Lerp {
        targets: collect.0.into_iter(),
        beta,
    })
}

/// Draws every lazily initialised parameter now, in visiting order, so that a seeded device
/// gives the same weights whatever runs first later.
pub fn materialize<M: Module>(module: &M) {
    module.visit(&mut Collect(Vec::new()));
}

/// Whether every parameter of a module is finite.
pub fn all_finite<M: Module>(module: &M) -> bool {
    let mut collect = Collect(Vec::new());
    module.visit(&mut collect);
    // One sum of all parameters, read back once: NaN or infinity anywhere makes it non-finite.
    collect
        .0
        .into_iter()
        .map(|t| t.sum())
        .reduce(|a, b| a + b)
        .is_none_or(|total| total.into_scalar::<f32>().is_finite())
}

/// The path (`field.field...`, as Burn's module derive names them) of the first float parameter
/// of a module that holds a NaN or an infinity, if any. Reads every parameter back: for
/// loading, not for every step (that is [`all_finite`]).
pub fn first_non_finite<M: Module>(module: &M) -> Option<String> {
    struct Find {
        path: Vec<String>,
        found: Option<String>,
    }
    impl ModuleVisitor for Find {
        fn enter_module(&mut self, name: &str, _: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _: &str, _: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            if self.found.is_none()
                && to_f32_vec(param.val().inner())
                    .iter()
                    .any(|v| !v.is_finite())
            {
                self.found = Some(self.path.join("."));
            }
        }
    }
    let mut find = Find {
        path: Vec::new(),
        found: None,
    };
    module.visit(&mut find);
    find.found
}

#[cfg(test)]
mod tests {
    use super::*;
    use volux_model::discriminator::DiscriminatorConfig;

    #[test]
    fn ema_beta_follows_stylegan2_ada() {
        // Half-life 10k images, batch 32: 0.5^(32/10000).
        let b = ema_beta(32, 1_000_000, 10.0, 0.05);
        assert!((b - 0.5f64.powf(0.0032)).abs() < 1e-15);
        // Ramp-up: after 1000 images the half-life is 50 images.
        let b = ema_beta(32, 1000, 10.0, 0.05);
        assert!((b - 0.5f64.powf(32.0 / 50.0)).abs() < 1e-15);
        assert_eq!(ema_beta(32, 0, 10.0, 0.05), 0.0);
        assert!((ema_beta(32, 0, 10.0, 0.0) - 0.5f64.powf(0.0032)).abs() < 1e-15);
    }

    #[test]
    fn ema_moves_every_parameter_towards_the_model() {
        let device = Device::flex();
        device.seed(1);
        let a = DiscriminatorConfig::small(3, 8).init(&device);
        let b = DiscriminatorConfig::small(3, 8).init(&device);
        let mix = update_ema(a.clone(), &b, 0.25);
        let (pa, pb, pm) = (
            to_f32_vec(a.fc.weight.val()),
            to_f32_vec(b.fc.weight.val()),
            to_f32_vec(mix.fc.weight.val()),
        );
        for ((x, y), m) in pa.iter().zip(&pb).zip(&pm) {
            assert!((m - (0.25 * x + 0.75 * y)).abs() < 1e-6);
        }
        assert!(all_finite(&mix));
        let broken = mix.clone().map(&mut Lerp {
            targets: {
                let mut c = Collect(Vec::new());
                mix.visit(&mut c);
                let mut v = c.0;
                v[0] = v[0].clone().mul_scalar(f32::NAN);
                v.into_iter()
            },
            beta: 0.0,
        });
        assert!(!all_finite(&broken));
        assert_eq!(first_non_finite(&mix), None);
        // The first parameter visited is the input layer's weight; an infinity in the last
        // one (the output layer's) is named as well.
        let first = first_non_finite(&broken).expect("the NaN is found");
        assert!(first.ends_with("weight"), "{first}");
        let mut count = Collect(Vec::new());
        mix.visit(&mut count);
        let last = count.0.len() - 1;
        let infinite = mix.clone().map(&mut Lerp {
            targets: {
                let mut c = Collect(Vec::new());
                mix.visit(&mut c);
                let mut v = c.0;
                v[last] = v[last].clone().add_scalar(f32::INFINITY);
                v.into_iter()
            },
            beta: 0.0,
        });
        let named = first_non_finite(&infinite).expect("the infinity is found");
        assert_ne!(named, first);
        assert!(named.starts_with("out"), "{named}");
    }
}
