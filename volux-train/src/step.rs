//! One training step (paper section 3.4): a generator phase (every active adversarial term
//! plus the path loss and, if asked, the density regulariser; one Adam step of `G`), then a
//! discriminator phase on the same fakes, detached (one Adam step of every active
//! discriminator, with lazy R1 on reals every `r1_interval` steps). A step whose loss or updated weights are not finite changes nothing.
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
//!
//! On the CPU, with small discriminators ([`side_by_side_on`]), the step's independent parts
//! run side by side on rayon's threads: the discriminators (each on its fakes, then each
//! one's discriminator phase), and the generator's backward pass beside the discriminator
//! phase. Their autodiff graphs are separate and each part's arithmetic is the same whichever
//! thread runs it, so the results are those of running them in turn, bit for bit.

use std::collections::BTreeMap;

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::{GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor};
use rayon::prelude::*;
use volux_data::batch::BatchTensors;
use volux_model::discriminator::Discriminator;
use volux_model::field::{Field, FieldWants};
use volux_model::flex_extension::{Route, route};
use volux_model::flops;
use volux_model::generated::GeneratorWants;
use volux_model::generator::{Generator, GeneratorError};
use volux_model::light_lookup::Lighting;
use volux_model::neiif::LatentField;
use volux_model::pose::Pose;
use volux_model::presets::{ByRole, DiscriminatorRole};
use volux_model::profile::{self, Phase as ProfilePhase};

use crate::config::TrainConfig;
use crate::losses::{
    DENSITY_REGULARISER_POINTS, DENSITY_REGULARISER_REACH, LossWeights, density_regulariser,
    density_regulariser_points, discriminator_loss, generator_loss, generator_loss_gradient,
    lazy_r1, path_loss, real_shading_condition, shading_condition_lo,
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
    /// Run the independent parts of the step side by side on rayon's threads (the
    /// discriminators; the generator's backward pass beside the discriminator phase):
    /// [`side_by_side_on`] the device, unless a benchmark asks for them in turn. The results
    /// are the same either way.
    pub side_by_side: bool,
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

/// The generator's terms that no discriminator judges, unweighted, by name: the path loss
/// and the density regulariser, where active.
type Regularisers = Vec<(&'static str, f64, Tensor<1>)>;

/// Runs the generator for the active terms and returns the fakes and the regularisers.
fn generate(g: &Generator, inputs: &StepInputs) -> Result<(Fakes, Regularisers), GeneratorError> {
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
    let w = inputs.weights;
    let mut regularisers = Regularisers::new();
    if let (true, Some(lo), Some(hi)) = (a.path, &out.layers.albedo_lo, &out.layers.albedo_hi) {
        regularisers.push(("path", w.path, path_loss(lo.clone(), hi.clone())));
    }
    if a.density {
        let points = density_regulariser_points(
            out.w.dims()[0],
            DENSITY_REGULARISER_POINTS,
            DENSITY_REGULARISER_REACH,
            w.density_reg_spread,
            &out.w.device(),
        );
        let field = LatentField {
            field: &g.neiif,
            w: out.w.clone(),
        };
        let sigma = field.query(points, FieldWants::DENSITY).sigma;
        regularisers.push(("density_reg", w.density_reg, density_regulariser(sigma)));
    }
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
    Ok((fakes, regularisers))
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
/// the generator's input gradient. The discriminators run side by side ([`side_by_side`]).
fn judge(judged: &[Pair], cpu: bool, outcome: &mut StepOutcome) -> Verdicts {
    let each = side_by_side(judged, cpu, |(_, _, disc, fake, _, weight)| {
        let (logits, pullback) = disc.forward_with_pullback(fake.clone().detach());
        let seen = logits.clone().detach();
        let value = scalar(&generator_loss(seen.clone()));
        let g_x = pullback.input_gradient(generator_loss_gradient(seen).mul_scalar(*weight));
        (value, g_x, logits)
    });
    let mut verdicts = Verdicts {
        value: 0.0,
        root: None,
        fake_logits: Vec::with_capacity(judged.len()),
    };
    for (([g_name, ..], _, _, fake, _, weight), (value, g_x, logits)) in judged.iter().zip(each) {
        outcome.losses.insert(g_name, value);
        verdicts.value += weight * value;
        add(&mut verdicts.root, (fake.clone() * g_x).sum());
        verdicts.fake_logits.push(logits);
    }
    verdicts
}

/// `f` on every item, in order; on the CPU the items side by side on rayon's threads.
///
/// The discriminators are independent networks whose autodiff graphs are separate (Burn
/// locks each graph on its own), each made of many small operations that keep two cores only
/// partly busy; two at once fill them (docs/performance.md). Each item's arithmetic is the same
/// whichever thread runs it, so the results do not depend on the scheduling: a step is the
/// same, bit for bit, as one that runs the items in turn (at one thread, tested) or again
/// (at a fixed thread count). A GPU backend gains nothing from it and runs them in turn.
fn side_by_side<T: Sync, R: Send>(
    items: &[T],
    together: bool,
    f: impl Fn(&T) -> R + Sync + Send,
) -> Vec<R> {
    if together {
        items.par_iter().with_max_len(1).map(f).collect()
    } else {
        items.iter().map(f).collect()
    }
}

/// The largest discriminator forward pass (FLOPs, at the training batch) for which a step
/// runs its parts side by side. Small discriminators are many small operations that leave
/// two cores partly idle, and two at once fill them (the quickstart's, 1-1.5 GFLOP: 1.3x on
/// the step); large ones already fill both cores operation by operation, and two at once only
/// share the caches and add their working sets (`paper128`'s, 66-127 GFLOP: its
/// discriminator and backward phases 1.08x slower, peak memory 11.6 to 14.5 GiB). The
/// threshold sits between the two measured sizes (docs/performance.md).
pub const SIDE_BY_SIDE_MAX_FLOPS: f64 = 10e9;

/// Whether a step of `config` on `device` runs its independent parts side by side: on the
/// CPU's threads (flex, with or without autodiff; a GPU gains nothing from it), when the
/// largest discriminator forward pass at the training batch is at most
/// [`SIDE_BY_SIDE_MAX_FLOPS`].
pub fn side_by_side_on(device: &Device, config: &TrainConfig) -> bool {
    let largest = DiscriminatorRole::ALL
        .into_iter()
        .filter_map(|role| config.model.discriminator(role).ok())
        .map(|d| flops::discriminator(&d, config.train.batch))
        .fold(0.0, f64::max);
    !matches!(route(device), Route::Other) && largest <= SIDE_BY_SIDE_MAX_FLOPS
}

/// One discriminator's part of the discriminator phase.
struct Judged {
    /// The discriminator loss (unweighted).
    loss: f64,
    /// The lazy R1 penalty, where it ran.
    r1: Option<f64>,
    /// `weight * (loss + r1)`.
    term: f64,
    /// The term's gradient in this discriminator's weights (`None` if the term is not
    /// finite: the step is then skipped).
    grads: Option<GradientsParams>,
}

/// The discriminator phase of one discriminator: its reals' pass (with lazy R1 where it runs),
/// its loss against the fakes' logits of the generator phase, and the backward pass through
/// both passes, into this discriminator's weights.
fn judge_reals(pair: &Pair, fake_logits: Tensor<2>, r1: Option<(f64, usize)>) -> Judged {
    let (_, _, disc, _, real, weight) = pair;
    let real = real
        .clone()
        .expect("the config leaves out terms whose reals the dataset lacks");
    let (real_logits, penalty) = match r1 {
        Some((gamma, interval)) if gamma > 0.0 => {
            let (logits, penalty) = lazy_r1(disc, real, gamma, interval);
            (logits, Some(penalty))
        }
        _ => (disc.forward(real), None),
    };
    let l = discriminator_loss(real_logits, fake_logits);
    let loss = scalar(&l);
    let r1 = penalty.as_ref().map(scalar);
    let term = match penalty {
        Some(p) => l + p,
        None => l,
    }
    .mul_scalar(*weight);
    let value = scalar(&term);
    let grads = value.is_finite().then(|| {
        let mut grads = term.backward();
        GradientsParams::from_module(&mut grads, *disc)
    });
    Judged {
        loss,
        r1,
        term: value,
        grads,
    }
}

/// Moves every gradient of `module`'s parameters from `from` into `into`.
fn move_gradients<M: Module>(module: &M, from: &mut GradientsParams, into: &mut GradientsParams) {
    struct Move<'a> {
        from: &'a mut GradientsParams,
        into: &'a mut GradientsParams,
    }
    impl ModuleVisitor for Move<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            if let Some(g) = self.from.remove::<D>(param.id) {
                self.into.register(param.id, g);
            }
        }
    }
    module.visit(&mut Move { from, into });
}

/// Logs a loss's `value` under `total` and refuses a value that is not finite.
fn checked(
    value: f64,
    (total, what): (&'static str, &str),
    outcome: &mut StepOutcome,
) -> Result<(), String> {
    outcome.losses.insert(total, value);
    if value.is_finite() {
        Ok(())
    } else {
        Err(format!("{what} loss is {value}"))
    }
}

/// One optimiser step of `model` along `grads`, unless the updated weights are not finite:
/// then `model` and `opt` are left as they were and the reason is returned. Profiled as
/// `phase`.
fn updated<M: Module + Clone>(
    model: &mut M,
    opt: &mut ModuleOptimizer,
    lr: f64,
    grads: GradientsParams,
    what: &str,
    phase: ProfilePhase,
) -> Result<(), String> {
    let _update = profile::span(phase);
    let (before, opt_before) = (model.clone(), opt.clone());
    *model = opt.step(lr, model.clone(), grads);
    if !all_finite(&*model) {
        *model = before;
        *opt = opt_before;
        return Err(format!("{what} weights became non-finite"));
    }
    Ok(())
}

/// NaN if `poison` (the non-finite guard's test hook), else `value`.
fn poisoned(value: f64, poison: bool) -> f64 {
    if poison { f64::NAN } else { value }
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
    let (fakes, regularisers) = generate(g, inputs)?;
    let judged = pairs(d, &fakes, Some(inputs.reals), &w, fade);
    let Verdicts {
        value: mut g_value,
        root: mut g_root,
        fake_logits,
    } = profile::timed(ProfilePhase::DiscriminatorsOnFakes, || {
        judge(&judged, inputs.side_by_side, &mut outcome)
    });
    for (name, weight, term) in regularisers {
        let value = scalar(&term);
        outcome.losses.insert(name, value);
        g_value += weight * value;
        add(&mut g_root, term.mul_scalar(weight));
    }
    let Some(g_root) = g_root else {
        return Ok(outcome);
    };
    if let Err(why) = checked(
        poisoned(g_value, inputs.poison == Some(Phase::Generator)),
        ("G_total", "generator"),
        &mut outcome,
    ) {
        outcome.skipped = Some(why);
        return Ok(outcome);
    }

    // The two backward passes: the generator's, from the pullbacks down, and the
    // discriminator phase, each discriminator's reals and the backward through both its
    // passes. They share no graph, and neither reads what the other writes (the updates come
    // after both), so on the CPU they run side by side too.
    let with_logits: Vec<(&Pair, Tensor<2>)> = judged.iter().zip(fake_logits).collect();
    let generator: &Generator = g;
    let g_backward = || {
        let mut grads = g_root.backward();
        GradientsParams::from_module(&mut grads, generator)
    };
    let d_phase = || {
        side_by_side(&with_logits, inputs.side_by_side, |(pair, logits)| {
            judge_reals(pair, logits.clone(), inputs.r1)
        })
    };
    let (g_grads, each) = if inputs.side_by_side {
        profile::timed(ProfilePhase::BackwardPasses, || {
            rayon::join(g_backward, d_phase)
        })
    } else {
        (
            profile::timed(ProfilePhase::GeneratorBackward, g_backward),
            profile::timed(ProfilePhase::DiscriminatorStep, d_phase),
        )
    };

    let (g_before, opt_g_before) = (g.clone(), opt_g.clone());
    if let Err(why) = updated(
        g,
        opt_g,
        inputs.lr_g,
        g_grads,
        "generator",
        ProfilePhase::GeneratorUpdate,
    ) {
        outcome.skipped = Some(why);
        return Ok(outcome);
    }
    let mut d_value = 0.0;
    let mut d_grads = GradientsParams::new();
    for (([_, d_name, r1_name], _, disc, ..), judged) in judged.iter().zip(each) {
        outcome.losses.insert(d_name, judged.loss);
        if let Some(r1) = judged.r1 {
            outcome.losses.insert(r1_name, r1);
        }
        d_value += judged.term;
        if let Some(mut grads) = judged.grads {
            move_gradients(*disc, &mut grads, &mut d_grads);
        }
    }
    if judged.is_empty() {
        return Ok(outcome);
    }
    let d_result = checked(
        poisoned(d_value, inputs.poison == Some(Phase::Discriminator)),
        ("D_total", "discriminator"),
        &mut outcome,
    )
    .and_then(|()| {
        updated(
            d,
            opt_d,
            inputs.lr_d,
            d_grads,
            "discriminator",
            ProfilePhase::DiscriminatorUpdate,
        )
    });
    if let Err(why) = d_result {
        // The whole step is undone, the generator's half included.
        *g = g_before;
        *opt_g = opt_g_before;
        outcome.skipped = Some(why);
    }
    Ok(outcome)
}

#[cfg(test)]
mod tests;
