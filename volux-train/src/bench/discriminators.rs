//! Each active discriminator timed alone, after the benchmark's steps.
//!
//! A training step runs the discriminators side by side on the CPU's threads
//! ([`crate::step`]), so the step's spans time them together; this table says what each
//! costs by itself, with both threads to itself: the generator phase's work (a pass on the
//! fakes and its pullback) and a pass of the discriminator phase (a pass and the backward
//! through it into the weights), on random inputs of the shapes training gives them.

use std::time::Instant;

use burn::tensor::{Device, Distribution, Tensor};
use volux_model::flops::{self, BACKWARD_FACTOR};
use volux_model::presets::DiscriminatorRole;

use crate::config::TrainConfig;
use crate::metrics::median;
use crate::networks::Discriminators;

/// One discriminator's times alone (medians).
#[derive(Clone, Debug)]
pub struct DiscriminatorTiming {
    pub role: DiscriminatorRole,
    /// Its input, `[batch, channels, side, side]`.
    pub input: [usize; 4],
    /// A pass on the fakes and its pullback: the generator phase's work for it.
    pub on_fakes_s: f64,
    pub on_fakes_flops: f64,
    /// A pass and the backward through it into the weights: one of its two passes in the
    /// discriminator phase.
    pub pass_and_backward_s: f64,
    pub pass_and_backward_flops: f64,
}

/// Times every discriminator of `roles` that `d` holds, each `repeats` times.
pub(super) fn time_alone(
    d: &Discriminators,
    config: &TrainConfig,
    roles: &[DiscriminatorRole],
    batch: usize,
    device: &Device,
    repeats: usize,
) -> Vec<DiscriminatorTiming> {
    let time = |f: &dyn Fn()| {
        let times: Vec<f64> = (0..repeats.max(1))
            .map(|_| {
                let started = Instant::now();
                f();
                let _ = device.sync();
                started.elapsed().as_secs_f64()
            })
            .collect();
        median(&times)
    };
    roles
        .iter()
        .filter_map(|&role| {
            let disc = d.get(role)?;
            let c = config.model.discriminator(role).ok()?;
            let input = [batch, c.in_channels, c.resolution, c.resolution];
            let x = Tensor::<4>::random(input, Distribution::Normal(0.0, 1.0), device);
            let on_fakes_s = time(&|| {
                let (logits, pullback) = disc.forward_with_pullback(x.clone());
                let grad = pullback.input_gradient(logits.detach().ones_like());
                let _ = grad.into_data();
            });
            let pass_and_backward_s = time(&|| {
                let _ = disc.forward(x.clone()).sum().backward();
            });
            let forward = flops::discriminator(&c, batch);
            Some(DiscriminatorTiming {
                role,
                input,
                on_fakes_s,
                on_fakes_flops: flops::discriminator_input_gradient(&c, batch),
                pass_and_backward_s,
                pass_and_backward_flops: forward * (1.0 + BACKWARD_FACTOR),
            })
        })
        .collect()
}

/// The table of `rows`, rates against the matmul `peak` (FLOP/s).
pub(super) fn markdown(rows: &[DiscriminatorTiming], peak: f64) -> String {
    let mut s = String::from(
        "Each discriminator alone (median of a few runs on random inputs of its shape):\n\n\
         | discriminator | input | pass on fakes + pullback, ms | GFLOP | % of peak \
         | pass + backward, ms | GFLOP | % of peak |\n|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        let [b, c, h, w] = r.input;
        s += &format!(
            "| {} | {b}x{c}x{h}x{w} | {:.1} | {:.3} | {:.1} | {:.1} | {:.3} | {:.1} |\n",
            r.role.name(),
            1e3 * r.on_fakes_s,
            r.on_fakes_flops / 1e9,
            100.0 * r.on_fakes_flops / r.on_fakes_s / peak,
            1e3 * r.pass_and_backward_s,
            r.pass_and_backward_flops / 1e9,
            100.0 * r.pass_and_backward_flops / r.pass_and_backward_s / peak,
        );
    }
    s
}
