//! One training step (paper section 3.4): a generator phase (every active adversarial term
//! plus the path loss, one Adam step of `G`), then a discriminator phase on the same fakes,
//! detached (one Adam step of every active discriminator, with lazy R1 on reals every
//! `r1_interval` steps). A step whose loss or updated weights are not finite changes nothing.
//!
//! Fakes are lit with the real batch's lighting and seen from the cameras of
//! [`crate::fake_poses`] (by default the reals' own when the dataset has poses, else a prior).
//! Each discriminator sees reals and fakes through the same door: `D_S`'s real shading is
//! brought to the volume resolution and back up as the generator's is, and during the fade-in
//! the high-resolution `D_A` sees both with the ungrown resolutions faded out
//! ([`crate::progressive`]). The discriminator phase reuses
//! the generator phase's fakes instead of rendering a second batch: the generator is by far
//! the dearer network, and the fakes differ from StyleGAN2's only by one generator update.
//! It reuses the discriminators' verdict on them too: one forward pass on the fakes serves
//! both phases ([`train_step`]).

use std::collections::BTreeMap;

use burn::module::Module;
use burn::optim::{GradientsParams, ModuleOptimizer};
use burn::tensor::Tensor;
use volux_data::batch::BatchTensors;
use volux_model::discriminator::Discriminator;
use volux_model::generated::GeneratorWants;
use volux_model::generator::{Generator, GeneratorError};
use volux_model::light_lookup::Lighting;
use volux_model::pose::Pose;
use volux_model::presets::{ByRole, DiscriminatorRole};
use volux_model::profile::{self, Phase as ProfilePhase};

use crate::losses::{
    LossWeights, discriminator_loss, generator_loss, generator_loss_gradient, lazy_r1, path_loss,
    real_shading_condition, shading_condition_lo,
};
use crate::networks::{Discriminators, all_finite};
use crate::progressive::faded_input;
use crate::schedule::ActiveTerms;

/// What one step needs besides the networks.
pub struct StepInputs<'a> {
    /// Latents `[batch, z_dim]` on the training device.
    pub z: Tensor<2>,
    /// One pose per element: the fakes' cameras (see [`crate::fake_poses`]).
    pub poses: &'a [Pose],
    /// The real batch's lighting (needed only when the relit image is).
    pub lighting: Option<&'a Lighting>,
    /// The reals on the training device.
    pub reals: &'a BatchTensors,
    /// The dataset's background as an albedo.
    pub background: [f32; 3],
    pub active: ActiveTerms,
    pub weights: LossWeights,
    /// Upsampler fade-in weights (`None`: fully grown).
    pub fade: Option<Vec<f64>>,
    /// Whether the high-resolution albedo discriminator's inputs fade in with the upsampler
    /// (`[schedule] fade_discriminator`).
    pub fade_discriminator: bool,
    /// Whether this step adds lazy R1 (and its interval).
    pub r1: Option<(f64, usize)>,
    pub lr_g: f64,
    pub lr_d: f64,
    /// Test hook: make this phase's loss NaN.
    pub poison: Option<Phase>,
}

/// The two halves of a step.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    Generator,
    Discriminator,
}

/// What a step did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StepOutcome {
    /// Every loss term's value (unweighted), by name.
    pub losses: BTreeMap<&'static str, f64>,
    /// `None` if the step was applied, else why it was skipped.
    pub skipped: Option<String>,
}

/// The generated images each discriminator looks at (`geometry`: the normals, `shading`:
/// `[I_relit, D, S]`, `photo`: the relit image); `None` where its term is inactive.
type Fakes = ByRole<Option<Tensor<4>>>;

/// The names a term's losses are logged under: generator, discriminator, R1
/// ([`DiscriminatorRole::terms`]).
type TermNames = [&'static str; 3];

/// An active discriminator with what it judges: `(names, role, D, fake, real, weight)`.
type Pair<'a> = (
    TermNames,
    DiscriminatorRole,
    &'a Discriminator,
    Tensor<4>,
    Option<Tensor<4>>,
    f64,
);

/// Every active discriminator with its fake and (if given) real inputs, as it sees them:
/// the high-resolution albedo faded in step with the upsampler (`fade`; `None` once grown),
/// the reals' shading at the fakes' resolution.
fn pairs<'a>(
    d: &'a Discriminators,
    fakes: &Fakes,
    reals: Option<&BatchTensors>,
    w: &LossWeights,
    fade: Option<&[f64]>,
) -> Vec<Pair<'a>> {
    // Where the dataset lacks a term's reals the term is left out (`TrainConfig::left_out`),
    // so an active term always finds them.
    let real_shading = reals.and_then(|r| {
        let (relit, low) = (r.relit.clone()?, r.normals_lo.as_ref()?);
        let factor = relit.dims()[2] / low.dims()[2];
        Some(real_shading_condition(
            relit,
            r.diffuse.clone()?,
            r.specular.clone()?,
            factor,
        ))
    });
    let entries = [
        (
            DiscriminatorRole::AlbedoLow,
            fakes.albedo_lo.clone(),
            reals.and_then(|r| r.albedo_lo.clone()),
            w.albedo,
        ),
        (
            DiscriminatorRole::AlbedoHigh,
            fakes
                .albedo_hi
                .as_ref()
                .map(|a| faded_input(a.clone(), fade)),
            reals.and_then(|r| Some(faded_input(r.albedo_hi.clone()?, fade))),
            w.albedo,
        ),
        (
            DiscriminatorRole::Geometry,
            fakes.geometry.clone(),
            reals.and_then(|r| r.normals_lo.clone()),
            w.geometry,
        ),
        (
            DiscriminatorRole::Shading,
            fakes.shading.clone(),
            real_shading,
            w.shading,
        ),
        (
            DiscriminatorRole::Photo,
            fakes.photo.clone(),
            reals.and_then(|r| r.photo.clone()),
            w.photo,
        ),
    ];
    entries
        .into_iter()
        .filter_map(|(role, fake, real, weight)| {
            Some((role.terms(), role, d.get(role)?, fake?, real, weight))
        })
        .collect()
}

/// `acc += t`, starting from nothing.
fn add(acc: &mut Option<Tensor<1>>, t: Tensor<1>) {
    *acc = Some(match acc.take() {
        Some(a) => a + t,
        None => t,
    });
}

fn scalar(t: &Tensor<1>) -> f64 {
    let v: f32 = t.clone().into_scalar();
    v as f64
}

/// What the generator renders for the active terms.
pub fn generator_wants(a: ActiveTerms) -> GeneratorWants {
    let albedo = a.albedo || a.path;
    GeneratorWants {
        albedo_lo: albedo,
        normals_lo: a.geometry,
        diffuse_lo: a.shading,
        specular_lo: a.shading,
        features_lo: false,
        depth: false,
        albedo_hi: albedo,
        relit: a.needs_relit(),
    }
}

/// Runs the generator for the active terms and returns the fakes and the path loss.
fn generate(
    g: &Generator,
    inputs: &StepInputs,
) -> Result<(Fakes, Option<Tensor<1>>), GeneratorError> {
    let a = inputs.active;
    let wants = generator_wants(a);
    let out = g.forward(
        inputs.z.clone(),
        inputs.poses,
        inputs.lighting.filter(|_| wants.relit),
        inputs.background,
        wants,
        inputs.fade.as_deref(),
        true,
    )?;
    let path = match (a.path, &out.layers.albedo_lo, &out.layers.albedo_hi) {
        (true, Some(lo), Some(hi)) => Some(path_loss(lo.clone(), hi.clone())),
        _ => None,
    };
    let shading = match (
        a.shading,
        &out.layers.relit,
        &out.layers.diffuse_lo,
        &out.layers.specular_lo,
    ) {
        (true, Some(relit), Some(d), Some(s)) => {
            Some(shading_condition_lo(relit.clone(), d.clone(), s.clone()))
        }
        _ => None,
    };
    let fakes = Fakes {
        albedo_lo: out.layers.albedo_lo.filter(|_| a.albedo),
        albedo_hi: out.layers.albedo_hi.filter(|_| a.albedo),
        geometry: out.layers.normals_lo,
        shading,
        photo: out.layers.relit.filter(|_| a.photo),
    };
    Ok((fakes, path))
}

/// The discriminators' verdict on the fakes, for both phases.
struct Verdicts {
    /// The weighted sum of the generator's adversarial losses.
    value: f64,
    /// `sum_x sum(x * dL_G/dx)` over the fakes `x`: its gradient in the generator is the
    /// adversarial losses'; `None` if no discriminator is active.
    root: Option<Tensor<1>>,
    /// Each discriminator's logits on its (detached) fakes, in `judged`'s order, tracked for
    /// its weights.
    fake_logits: Vec<Tensor<2>>,
}

/// One forward pass of every active discriminator on its fakes, logging each generator loss
/// under its name: the logits for the discriminator phase, and through each pass's pullback
/// the generator's input gradient.
fn judge(judged: &[Pair], outcome: &mut StepOutcome) -> Verdicts {
    let mut verdicts = Verdicts {
        value: 0.0,
        root: None,
        fake_logits: Vec::with_capacity(judged.len()),
    };
    for ([g_name, ..], role, disc, fake, _, weight) in judged {
        let (logits, pullback) = profile::timed(ProfilePhase::DiscriminatorForward(*role), || {
            disc.forward_with_pullback(fake.clone().detach())
        });
        let seen = logits.clone().detach();
        let value = scalar(&generator_loss(seen.clone()));
        outcome.losses.insert(g_name, value);
        verdicts.value += weight * value;
        let g_x = profile::timed(ProfilePhase::GeneratorBackward, || {
            pullback.input_gradient(generator_loss_gradient(seen).mul_scalar(*weight))
        });
        add(&mut verdicts.root, (fake.clone() * g_x).sum());
        verdicts.fake_logits.push(logits);
    }
    verdicts
}

/// What an optimiser step descends: the loss's value (logged and checked) and the tensor
/// whose `backward()` gives its gradient. The two differ where part of the gradient comes in
/// through a pullback: `sum(x * dL/dx)` has `L`'s gradient in everything upstream of `x`.
struct Objective {
    value: f64,
    root: Tensor<1>,
}

impl Objective {
    fn new(loss: Tensor<1>) -> Self {
        Self {
            value: scalar(&loss),
            root: loss,
        }
    }

    /// The objective made NaN if `poison` (the non-finite guard's test hook).
    fn poisoned(self, poison: bool) -> Self {
        if poison {
            Self {
                value: f64::NAN,
                root: self.root.mul_scalar(f64::NAN),
            }
        } else {
            self
        }
    }
}

/// Logs `objective`'s value under `names.0`, then one optimiser step of `model` on it, unless
/// the value or the updated weights are not finite: then `model` and `opt` are left as they
/// were and the reason is returned. The backward pass and the update are profiled as
/// `phases`.
fn guarded_update<M: Module + Clone>(
    model: &mut M,
    opt: &mut ModuleOptimizer,
    lr: f64,
    objective: Objective,
    (total, what): (&'static str, &str),
    (backward, update): (ProfilePhase, ProfilePhase),
    outcome: &mut StepOutcome,
) -> Result<(), String> {
    let Objective { value, root } = objective;
    outcome.losses.insert(total, value);
    if !value.is_finite() {
        return Err(format!("{what} loss is {value}"));
    }
    let mut grads = profile::timed(backward, || root.backward());
    let _update = profile::span(update);
    let grads = GradientsParams::from_module(&mut grads, &*model);
    let (before, opt_before) = (model.clone(), opt.clone());
    *model = opt.step(lr, model.clone(), grads);
    if !all_finite(&*model) {
        *model = before;
        *opt = opt_before;
        return Err(format!("{what} weights became non-finite"));
    }
    Ok(())
}

/// One step: updates `g`, `d` and their optimisers in place, or, if any loss or updated
/// weight is not finite, leaves all four as they were.
///
/// Each active discriminator judges the fakes once, for both phases: its forward pass on the
/// detached fakes is tracked for its own weights (the discriminator phase's loss), and its
/// [`Pullback`](volux_model::discriminator::Pullback) gives the generator the input gradient
/// of the generator loss, `dL_G/dx`, which enters the generator's graph as `sum(x * dL_G/dx)`.
/// That is exactly the gradient a pass through the frozen discriminator would give, at one
/// discriminator forward on the fakes fewer per step: the discriminators are not updated
/// until both gradients are taken, and the fakes the discriminator phase sees are these.
pub fn train_step(
    g: &mut Generator,
    d: &mut Discriminators,
    opt_g: &mut ModuleOptimizer,
    opt_d: &mut ModuleOptimizer,
    inputs: &StepInputs,
) -> Result<StepOutcome, GeneratorError> {
    let mut outcome = StepOutcome::default();
    let w = inputs.weights;
    let fade = inputs.fade.as_deref().filter(|_| inputs.fade_discriminator);

    // Generator phase: every active discriminator's verdict on the fakes and its pullback.
    let (fakes, path) = generate(g, inputs)?;
    let judged = pairs(d, &fakes, Some(inputs.reals), &w, fade);
    let Verdicts {
        value: mut g_value,
        root: mut g_root,
        fake_logits,
    } = judge(&judged, &mut outcome);
    if let Some(p) = path {
        let value = scalar(&p);
        outcome.losses.insert("path", value);
        g_value += w.path * value;
        add(&mut g_root, p.mul_scalar(w.path));
    }
    let Some(g_root) = g_root else {
        return Ok(outcome);
    };
    let g_objective = Objective {
        value: g_value,
        root: g_root,
    };
    let (g_before, opt_g_before) = (g.clone(), opt_g.clone());
    if let Err(why) = guarded_update(
        g,
        opt_g,
        inputs.lr_g,
        g_objective.poisoned(inputs.poison == Some(Phase::Generator)),
        ("G_total", "generator"),
        (
            ProfilePhase::GeneratorBackward,
            ProfilePhase::GeneratorUpdate,
        ),
        &mut outcome,
    ) {
        outcome.skipped = Some(why);
        return Ok(outcome);
    }

    // Discriminator phase: the reals, beside the fakes' logits of the generator phase.
    let _d_step = profile::span(ProfilePhase::DiscriminatorStep);
    let mut d_loss: Option<Tensor<1>> = None;
    for (([_, d_name, r1_name], _, disc, _, real, weight), fake_logits) in
        judged.into_iter().zip(fake_logits)
    {
        let real = real.expect("the config leaves out terms whose reals the dataset lacks");
        let (real_logits, r1) = match inputs.r1 {
            Some((gamma, interval)) if gamma > 0.0 => {
                let (logits, penalty) =
                    profile::timed(ProfilePhase::R1, || lazy_r1(disc, real, gamma, interval));
                (logits, Some(penalty))
            }
            _ => (disc.forward(real), None),
        };
        let l = discriminator_loss(real_logits, fake_logits);
        outcome.losses.insert(d_name, scalar(&l));
        let mut term = l;
        if let Some(r1) = r1 {
            outcome.losses.insert(r1_name, scalar(&r1));
            term = term + r1;
        }
        add(&mut d_loss, term.mul_scalar(weight));
    }
    let Some(d_loss) = d_loss else {
        return Ok(outcome);
    };
    if let Err(why) = guarded_update(
        d,
        opt_d,
        inputs.lr_d,
        Objective::new(d_loss).poisoned(inputs.poison == Some(Phase::Discriminator)),
        ("D_total", "discriminator"),
        (
            ProfilePhase::DiscriminatorStep,
            ProfilePhase::DiscriminatorStep,
        ),
        &mut outcome,
    ) {
        // The whole step is undone, the generator's half included.
        *g = g_before;
        *opt_g = opt_g_before;
        outcome.skipped = Some(why);
    }
    Ok(outcome)
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use burn::tensor::{Device, Distribution};
    use volux_model::backend::to_f32_vec;

    use super::*;
    use crate::config::TrainConfig;
    use crate::losses::area_downsample;
    use crate::progressive::faded_input;
    use volux_data::layers::Layers;

    /// One pass per discriminator serves both phases: the generator's gradient through the
    /// pullback equals backpropagation of its loss through the frozen discriminator, and the
    /// discriminator's weight gradient from the kept logits equals a second pass's on the
    /// detached fakes (what the step computed before).
    #[test]
    fn one_verdict_gives_both_phases_the_gradients_of_separate_passes() {
        use burn::module::Param;
        use volux_model::discriminator::DiscriminatorConfig;

        let device = Device::flex().autodiff();
        device.seed(7);
        let disc = |seed| {
            device.seed(seed);
            DiscriminatorConfig::new(3, 16)
                .with_channel_base(128)
                .with_channel_max(32)
                .init(&device)
        };
        let (d_a, d_g) = (disc(8), disc(9));
        // A stand-in generator: fakes are a tracked function of one parameter.
        let theta = Param::from_tensor(Tensor::<4>::random(
            [4, 3, 16, 16],
            Distribution::Normal(0.0, 1.0),
            &device,
        ));
        let fakes = |t: &Tensor<4>| (t.clone().mul_scalar(1.5).tanh(), t.clone().sin());
        let (fa, fg) = fakes(&theta.val());
        let judged: Vec<Pair> = vec![
            (
                DiscriminatorRole::AlbedoLow.terms(),
                DiscriminatorRole::AlbedoLow,
                &d_a,
                fa,
                None,
                1.0,
            ),
            (
                DiscriminatorRole::Geometry.terms(),
                DiscriminatorRole::Geometry,
                &d_g,
                fg,
                None,
                0.3,
            ),
        ];
        let mut outcome = StepOutcome::default();
        let verdicts = judge(&judged, &mut outcome);
        let g_new = theta
            .val()
            .grad(&verdicts.root.unwrap().backward())
            .unwrap();

        // Before: the generator's loss through frozen discriminators, then a second forward.
        let (fa, fg) = fakes(&theta.val());
        let (frozen_a, frozen_g) = (Module::no_grad(d_a.clone()), Module::no_grad(d_g.clone()));
        let la = generator_loss(frozen_a.forward(fa.clone()));
        let lg = generator_loss(frozen_g.forward(fg.clone()));
        let value = scalar(&la) + 0.3 * scalar(&lg);
        let g_old = theta
            .val()
            .grad(&(la + lg.mul_scalar(0.3)).backward())
            .unwrap();
        assert!(
            (verdicts.value - value).abs() <= 1e-6 * value.abs(),
            "{} vs {value}",
            verdicts.value
        );
        assert_eq!(outcome.losses.len(), 2);
        let close = |got: Vec<f32>, want: Vec<f32>, what: &str| {
            let scale = want.iter().fold(0f32, |m, v| m.max(v.abs()));
            let err = got
                .iter()
                .zip(&want)
                .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
            assert!(
                scale > 0.0 && err <= 1e-5 * scale,
                "{what}: error {err:e}, largest {scale:e}"
            );
        };
        close(to_f32_vec(g_new), to_f32_vec(g_old), "generator gradient");

        let real = Tensor::<4>::random([4, 3, 16, 16], Distribution::Normal(0.0, 1.0), &device);
        for (d, logits, fake) in [
            (&d_a, &verdicts.fake_logits[0], fa),
            (&d_g, &verdicts.fake_logits[1], fg),
        ] {
            let w = d.blocks[0].conv0.weight.val();
            let kept = discriminator_loss(d.forward(real.clone()), logits.clone());
            let again = discriminator_loss(d.forward(real.clone()), d.forward(fake.detach()));
            assert_eq!(scalar(&kept), scalar(&again));
            close(
                to_f32_vec(w.grad(&kept.backward()).unwrap()),
                to_f32_vec(w.grad(&again.backward()).unwrap()),
                "discriminator gradient",
            );
        }
    }

    /// The discriminators see what the step hands them: the reals' shading brought to the
    /// fakes' resolution, and the high-resolution albedo (real and fake) faded while the
    /// upsampler fades in, then as it is once grown.
    #[test]
    fn each_discriminator_gets_reals_and_fakes_through_the_same_door() {
        let device = Device::flex();
        device.seed(4);
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/quickstart.toml");
        let config = TrainConfig::load(&path).unwrap();
        let d = Discriminators::init(&config, &device);
        let random = |c, side| {
            Tensor::<4>::random([4, c, side, side], Distribution::Uniform(0.0, 1.0), &device)
        };
        let reals = Layers {
            photo: random(3, 64),
            relit: random(3, 64),
            albedo_hi: random(3, 64),
            albedo_lo: random(3, 32),
            normals_lo: random(3, 32),
            mask: random(1, 64),
            diffuse: random(3, 64),
            specular: random(3, 64),
        };
        let tensors: BatchTensors = reals.map(|_, t| Some(t.clone()));
        let fake_hi = random(3, 64);
        let fakes = Fakes {
            albedo_lo: Some(random(3, 32)),
            albedo_hi: Some(fake_hi.clone()),
            geometry: Some(random(3, 32)),
            shading: Some(random(9, 64)),
            photo: Some(random(3, 64)),
        };
        let same = |a: &Tensor<4>, b: Tensor<4>| to_f32_vec(a.clone()) == to_f32_vec(b);
        let find = |pairs: &[Pair], role| {
            let p = pairs.iter().find(|p| p.1 == role).expect("active");
            (p.3.clone(), p.4.clone().expect("reals given"))
        };
        let w = config.loss;

        let fading = pairs(&d, &fakes, Some(&tensors), &w, Some(&[0.0]));
        assert_eq!(fading.len(), 5);
        let (fake, real) = find(&fading, DiscriminatorRole::AlbedoHigh);
        assert!(same(
            &real,
            faded_input(reals.albedo_hi.clone(), Some(&[0.0]))
        ));
        assert!(!same(&real, reals.albedo_hi.clone()));
        assert!(same(&fake, faded_input(fake_hi.clone(), Some(&[0.0]))));
        let (_, real) = find(&fading, DiscriminatorRole::Shading);
        let want = shading_condition_lo(
            reals.relit.clone(),
            area_downsample(reals.diffuse.clone(), 2),
            area_downsample(reals.specular.clone(), 2),
        );
        assert!(same(&real, want));

        let grown = pairs(&d, &fakes, Some(&tensors), &w, None);
        let (fake, real) = find(&grown, DiscriminatorRole::AlbedoHigh);
        assert!(same(&real, reals.albedo_hi.clone()) && same(&fake, fake_hi));
    }
}
