//! The per-phase training benchmark (`volux train bench`): real training steps of a config,
//! timed phase by phase through the spans of [`volux_model::profile`] that the training code
//! itself opens, beside the FLOPs of each phase ([`volux_model::flops`]) and the machine's
//! measured matmul peak.
//!
//! The run is placed at the start of the asked stage ([`Trainer::seek`]), so stage 2 is
//! measured without training stage 1. One warm-up step (step 0, which runs R1 when it is on)
//! is not measured; the measured steps start at step `r1_interval`, so the first of them runs
//! R1 and the others do not, as in training. Every step trains at the stage's first image
//! count, so the stage, fade-in and active terms stay those of the stage's start.
//!
//! Where a step runs its parts side by side ([`side_by_side_on`]) those parts share a row;
//! [`BenchOptions::in_turn`] times them apart, and each discriminator is also timed alone
//! after the steps (`discriminators`).

use std::path::PathBuf;
use std::time::Instant;

use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use volux_model::backend::{BackendError, BackendKind};
use volux_model::field::FieldWants;
use volux_model::flops::{self, BACKWARD_FACTOR};
use volux_model::presets::DiscriminatorRole;
use volux_model::profile::{AlreadyRunning, Phase, PhaseTime, Profiler};

use crate::config::TrainConfig;
use crate::losses::DENSITY_REGULARISER_POINTS;
use crate::metrics::{median, peak_rss_mib};
use crate::schedule::{ActiveTerms, Stage};
use crate::step::{generator_wants, side_by_side_on};
use crate::training_loop::{TrainError, TrainOptions, Trainer};

mod discriminators;
pub use discriminators::DiscriminatorTiming;

/// Repeats of each discriminator's timing alone (the median is reported).
const DISCRIMINATOR_REPEATS: usize = 3;

/// Why a benchmark could not run.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error(transparent)]
    Train(#[from] TrainError),
    #[error(transparent)]
    Backend(#[from] BackendError),
    #[error(transparent)]
    Profiler(#[from] AlreadyRunning),
    #[error("{config}: {why}")]
    Stage { config: PathBuf, why: String },
    #[error("at least one measured step is needed")]
    NoSteps,
    #[error("{steps} measured steps: give at most {MAX_BENCH_STEPS}")]
    TooManySteps { steps: usize },
    #[error("a matmul side of {side}: give {} to {}", GEMM_SIDES.start(), GEMM_SIDES.end())]
    GemmSide { side: usize },
}

/// The most measured steps of one benchmark (a median needs a few, not thousands).
pub const MAX_BENCH_STEPS: usize = 1000;
/// The sides of the peak-measuring matmul: below 16 it measures call overhead; at 8192 its
/// operands take 768 MiB and each of its repeats about 1.1 TFLOP.
pub const GEMM_SIDES: std::ops::RangeInclusive<usize> = 16..=8192;

/// What to measure.
#[derive(Clone, Debug)]
pub struct BenchOptions {
    pub backend: BackendKind,
    /// [`Stage::One`] or [`Stage::Two`].
    pub stage: Stage,
    /// Measured steps (after one warm-up step).
    pub steps: usize,
    /// Side of the square matmul that measures the peak.
    pub gemm_side: usize,
    /// Best of this many matmuls.
    pub gemm_repeats: usize,
    /// Run each step's independent parts in turn ([`Trainer::set_in_turn`]).
    pub in_turn: bool,
}

impl Default for BenchOptions {
    fn default() -> Self {
        BenchOptions {
            backend: BackendKind::Cpu,
            stage: Stage::One,
            steps: 5,
            gemm_side: 2048,
            gemm_repeats: 5,
            in_turn: false,
        }
    }
}

/// How a row's FLOPs were counted.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Counting {
    /// Every matmul and convolution, from the shapes.
    Exact,
    /// Per-element costs, or a backward pass as a multiple of its forward.
    Estimate,
}

/// One row of the table.
#[derive(Clone, Debug)]
pub struct PhaseRow {
    /// `None`: the rest of the step (data wait, losses, copies), outside every span.
    pub phase: Option<Phase>,
    /// Median over the measured steps that ran the phase.
    pub median_s: f64,
    /// How many measured steps ran it.
    pub steps: usize,
    pub flops: Option<(f64, Counting)>,
}

impl PhaseRow {
    pub fn label(&self) -> &'static str {
        self.phase
            .map_or("other (data wait, losses, copies)", Phase::label)
    }
}

/// What a benchmark measured.
#[derive(Clone, Debug)]
pub struct BenchReport {
    pub config: PathBuf,
    pub preset: String,
    pub backend: BackendKind,
    pub stage: Stage,
    pub batch: usize,
    pub steps: usize,
    pub r1_interval: usize,
    pub rows: Vec<PhaseRow>,
    /// Median wall time of a whole step.
    pub step_median_s: f64,
    /// Steps skipped for non-finite values (should be 0).
    pub skipped: usize,
    pub peak_rss_mib: Option<f64>,
    /// The matmul peak, FLOP/s, and the side it was measured at.
    pub gemm_peak: f64,
    pub gemm_side: usize,
    /// Whether the step's parts ran side by side ([`side_by_side_on`]; not with `--in-turn`).
    pub side_by_side: bool,
    /// Each active discriminator timed alone, after the steps.
    pub discriminators: Vec<DiscriminatorTiming>,
}

impl BenchReport {
    pub fn images_per_s(&self) -> f64 {
        self.batch as f64 / self.step_median_s
    }

    /// The row of a phase.
    pub fn row(&self, phase: Phase) -> Option<&PhaseRow> {
        self.rows.iter().find(|r| r.phase == Some(phase))
    }

    /// The phase rows, slowest first.
    pub fn slowest(&self) -> Vec<&PhaseRow> {
        let mut rows: Vec<&PhaseRow> = self.rows.iter().filter(|r| r.phase.is_some()).collect();
        rows.sort_by(|a, b| b.median_s.total_cmp(&a.median_s));
        rows
    }

    /// The report as markdown: a summary and the table.
    pub fn markdown(&self) -> String {
        let stage = if self.stage == Stage::One { 1 } else { 2 };
        let peak = self.gemm_peak;
        let mut s = format!(
            "`{}` ({} preset), stage {stage}, batch {}, backend {}: median of {} steps after \
             1 warm-up step.\n\n",
            self.config.display(),
            self.preset,
            self.batch,
            self.backend,
            self.steps
        );
        s += &format!(
            "- step: {:.3} s median, {:.2} images/s; peak memory {}; skipped steps {}\n",
            self.step_median_s,
            self.images_per_s(),
            self.peak_rss_mib
                .map_or("unknown".into(), |m| format!("{:.0} MiB (process RSS)", m)),
            self.skipped
        );
        s += &format!(
            "- fp32 matmul peak: {:.1} GFLOP/s ({side}x{side} Burn matmul, best of several)\n",
            peak / 1e9,
            side = self.gemm_side,
        );
        let per_step: f64 = self
            .rows
            .iter()
            .filter(|r| r.phase != Some(Phase::R1))
            .filter_map(|r| r.flops.map(|f| f.0))
            .sum();
        s += &format!(
            "- FLOPs of a step without R1: {:.2} GFLOP, {:.1}% of peak over the step median\n",
            per_step / 1e9,
            100.0 * per_step / self.step_median_s / peak
        );
        if self.r1_interval > 0 {
            s += &format!(
                "- R1 runs on 1 step in {}; its row is the time of the phase holding the \
                 discriminator step on that step less its median on the others\n",
                self.r1_interval
            );
        }
        s += if self.side_by_side {
            "- the discriminators ran side by side on the CPU's threads, and the generator's \
             backward pass beside the discriminator step (`--in-turn` times them apart); each \
             discriminator is timed alone in the second table\n"
        } else {
            "- the step's parts ran in turn (`--in-turn`, a GPU, or discriminators too large to \
             gain from running side by side); each discriminator is timed alone in the second \
             table\n"
        };
        s += "\n| phase | median ms | share of step | GFLOP | counted | GFLOP/s | % of peak |\n";
        s += "|---|---|---|---|---|---|---|\n";
        for r in &self.rows {
            let (gflop, counted, rate, frac) = match r.flops {
                Some((f, c)) => (
                    format!("{:.3}", f / 1e9),
                    match c {
                        Counting::Exact => "exact",
                        Counting::Estimate => "estimate",
                    },
                    format!("{:.2}", f / r.median_s / 1e9),
                    format!("{:.1}", 100.0 * f / r.median_s / peak),
                ),
                None => ("-".into(), "-", "-".into(), "-".into()),
            };
            s += &format!(
                "| {} | {:.1} | {:.1}% | {gflop} | {counted} | {rate} | {frac} |\n",
                r.label(),
                1e3 * r.median_s,
                100.0 * r.median_s / self.step_median_s,
            );
        }
        s += &format!(
            "| **whole step** | {:.1} | 100% | | | | |\n",
            1e3 * self.step_median_s
        );
        if !self.discriminators.is_empty() {
            s += "\n";
            s += &discriminators::markdown(&self.discriminators, peak);
        }
        s
    }
}

/// The fp32 matmul rate of `device` in FLOP/s: the best of `repeats` `side x side` products.
pub fn gemm_peak(device: &Device, side: usize, repeats: usize) -> f64 {
    let values = |seed: usize| -> Vec<f32> {
        (0..side * side)
            .map(|i| ((i * 7 + seed) % 13) as f32 / 13.0 - 0.5)
            .collect()
    };
    let a = Tensor::<2>::from_data(TensorData::new(values(1), [side, side]), device);
    let b = Tensor::<2>::from_data(TensorData::new(values(5), [side, side]), device);
    let _ = device.sync();
    let mut best = f64::INFINITY;
    for _ in 0..repeats.max(1) {
        let started = Instant::now();
        let c = a.clone().matmul(b.clone());
        let _ = device.sync();
        best = best.min(started.elapsed().as_secs_f64());
        drop(c);
    }
    flops::matmul(side, side, side) / best
}

/// The discriminators the active terms run, in the table's order.
fn active_roles(a: ActiveTerms) -> Vec<DiscriminatorRole> {
    DiscriminatorRole::ALL
        .into_iter()
        .filter(|r| match r {
            DiscriminatorRole::AlbedoLow | DiscriminatorRole::AlbedoHigh => a.albedo,
            DiscriminatorRole::Geometry => a.geometry,
            DiscriminatorRole::Shading => a.shading,
            DiscriminatorRole::Photo => a.photo,
        })
        .collect()
}

/// FLOPs of every phase a step at `active` runs, with how they were counted.
fn phase_flops(
    config: &TrainConfig,
    active: ActiveTerms,
    g_params: usize,
    d_params: usize,
) -> Vec<(Phase, f64, Counting)> {
    use Counting::{Estimate, Exact};
    let batch = config.train.batch;
    let mut g = flops::generator(&config.generator(), batch, generator_wants(active));
    if active.density {
        // The density regulariser's query of its point pairs, timed with the field.
        g.field += flops::field(
            &config.generator().neiif,
            batch,
            2 * DENSITY_REGULARISER_POINTS,
            FieldWants::DENSITY,
        );
    }
    let disc = |role| {
        let c = config.model.discriminator(role).expect("validated config");
        (flops::discriminator(&c, batch), c)
    };
    let roles = active_roles(active);
    let mut out = vec![
        (Phase::Mapping, g.mapping, Exact),
        (Phase::Field, g.field, Exact),
        (Phase::Compositing, g.compositing, Estimate),
        (Phase::Upsampler, g.upsampler, Exact),
        (Phase::Relighting, g.relighting, Exact),
    ];
    if config.generator().renderer.proposal > 0 {
        out.push((Phase::Proposal, g.proposal, Estimate));
    }
    let mut d_forward = 0.0;
    let mut on_fakes = 0.0;
    for &role in &roles {
        let (f, c) = disc(role);
        d_forward += f;
        // The pass and its explicit reverse sweep (1x forward).
        on_fakes += flops::discriminator_input_gradient(&c, batch);
    }
    out.push((Phase::DiscriminatorsOnFakes, on_fakes, Exact));
    let g_backward = BACKWARD_FACTOR * g.differentiated();
    // The reals' pass (the fakes' is the generator phase's) and the backward of both.
    let d_step = d_forward * (1.0 + 2.0 * BACKWARD_FACTOR);
    // Side by side the two are one row, in turn two.
    out.push((Phase::BackwardPasses, g_backward + d_step, Estimate));
    out.push((Phase::GeneratorBackward, g_backward, Estimate));
    out.push((Phase::DiscriminatorStep, d_step, Estimate));
    out.push((Phase::GeneratorUpdate, flops::adam(g_params), Estimate));
    out.push((Phase::DiscriminatorUpdate, flops::adam(d_params), Estimate));
    // R1 replaces the reals' pass (1x forward) and its backward (2x) by the pass with its
    // input gradient (2x) and that graph's backward (4x): 3x forward more.
    out.push((Phase::R1, 3.0 * d_forward, Estimate));
    out.push((Phase::Ema, flops::ema(g_params), Estimate));
    out
}

/// A fresh run folder for the trainer's logs, removed afterwards.
fn scratch_dir() -> PathBuf {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.subsec_nanos());
    std::env::temp_dir().join(format!("volux-bench-{}-{nanos}", std::process::id()))
}

/// Runs the benchmark of `config` (see the module documentation).
pub fn run(config: TrainConfig, options: &BenchOptions) -> Result<BenchReport, BenchError> {
    if options.steps == 0 {
        return Err(BenchError::NoSteps);
    }
    if options.steps > MAX_BENCH_STEPS {
        return Err(BenchError::TooManySteps {
            steps: options.steps,
        });
    }
    if !GEMM_SIDES.contains(&options.gemm_side) {
        return Err(BenchError::GemmSide {
            side: options.gemm_side,
        });
    }
    let schedule = config.schedule;
    let stage = options.stage;
    let start_images = match stage {
        Stage::One => 0,
        Stage::Two => (schedule.stage1_kimg * 1000.0).round() as u64,
        Stage::Done => {
            return Err(BenchError::Stage {
                config: config.path.clone(),
                why: "only stage 1 or 2 can be measured".into(),
            });
        }
    };
    if schedule.stage(start_images) != stage {
        return Err(BenchError::Stage {
            config: config.path.clone(),
            why: format!(
                "the schedule has no {stage:?} stage (stage1_kimg = {}, stage2_kimg = {})",
                schedule.stage1_kimg, schedule.stage2_kimg
            ),
        });
    }
    let device = options.backend.device()?;
    tracing::info!(
        "measuring the {0}x{0} matmul peak on {1}",
        options.gemm_side,
        options.backend
    );
    let gemm = gemm_peak(&device, options.gemm_side, options.gemm_repeats);
    tracing::info!("matmul peak {:.1} GFLOP/s", gemm / 1e9);

    let out = scratch_dir();
    let batch = config.train.batch;
    let interval = config.train.r1_interval;
    let active = schedule.active(start_images, &config.loss);
    let mut trainer = Trainer::new(
        config.clone(),
        TrainOptions {
            backend: options.backend,
            out: out.clone(),
            resume: false,
            force: false,
            max_steps: None,
        },
    )?;
    trainer.set_in_turn(options.in_turn);
    let side_by_side = !options.in_turn && side_by_side_on(trainer.device(), &config);
    let g_params = trainer.generator().num_params();
    let d_params = trainer.discriminators().num_params();
    let flops = phase_flops(&config, active, g_params, d_params);

    let profiler = Profiler::start(trainer.device())?;
    let first_measured = interval.max(1) as u64;
    let mut steps: Vec<(f64, Vec<PhaseTime>)> = Vec::new();
    let mut skipped = 0;
    for i in 0..=options.steps as u64 {
        let step = if i == 0 { 0 } else { first_measured + i - 1 };
        trainer.seek(step, start_images);
        profiler.take();
        let started = Instant::now();
        let report = trainer.step()?;
        let _ = trainer.device().sync();
        let seconds = started.elapsed().as_secs_f64();
        let times = profiler.take();
        skipped += usize::from(report.skipped.is_some());
        tracing::info!(
            "{} step {step}: {seconds:.3} s",
            if i == 0 { "warm-up" } else { "measured" }
        );
        if i > 0 {
            steps.push((seconds, times));
        }
    }
    drop(profiler);
    let alone = discriminators::time_alone(
        trainer.discriminators(),
        &config,
        &active_roles(active),
        batch,
        trainer.device(),
        DISCRIMINATOR_REPEATS,
    );
    drop(trainer);
    // The scratch folder holds only the trainer's empty logs.
    let _ = std::fs::remove_dir_all(&out);

    let mut rows = Vec::new();
    for (phase, f, counting) in &flops {
        let ran: Vec<f64> = if *phase == Phase::R1 {
            r1_extra(&steps, interval).into_iter().collect()
        } else {
            steps
                .iter()
                .filter_map(|(_, t)| phase_seconds(t, *phase))
                .collect()
        };
        if ran.is_empty() {
            continue;
        }
        rows.push(PhaseRow {
            phase: Some(*phase),
            steps: ran.len(),
            median_s: median(&ran),
            flops: Some((*f, *counting)),
        });
    }
    let other: Vec<f64> = steps
        .iter()
        .map(|(total, t)| (total - t.iter().map(|p| p.seconds).sum::<f64>()).max(0.0))
        .collect();
    rows.push(PhaseRow {
        phase: None,
        steps: other.len(),
        median_s: median(&other),
        flops: None,
    });
    Ok(BenchReport {
        config: config.path.clone(),
        preset: config.model.preset.clone(),
        backend: options.backend,
        stage,
        batch,
        steps: steps.len(),
        r1_interval: interval,
        rows,
        step_median_s: median(&steps.iter().map(|s| s.0).collect::<Vec<_>>()),
        skipped,
        peak_rss_mib: peak_rss_mib(),
        gemm_peak: gemm,
        gemm_side: options.gemm_side,
        side_by_side,
        discriminators: alone,
    })
}

/// A phase's time in one step's record.
fn phase_seconds(times: &[PhaseTime], phase: Phase) -> Option<f64> {
    times.iter().find(|p| p.phase == phase).map(|p| p.seconds)
}

/// Lazy R1's extra time: the phase holding the discriminator step (its own row in turn, the
/// backward passes' side by side) on the first measured step, the one that runs R1, less the
/// median of the others'. `None` without R1 or without a step to compare.
fn r1_extra(steps: &[(f64, Vec<PhaseTime>)], interval: usize) -> Option<f64> {
    let d_step = |t: &[PhaseTime]| {
        phase_seconds(t, Phase::DiscriminatorStep)
            .or_else(|| phase_seconds(t, Phase::BackwardPasses))
    };
    let (first, rest) = steps.split_first()?;
    let without: Vec<f64> = rest.iter().filter_map(|(_, t)| d_step(t)).collect();
    if interval == 0 || without.is_empty() {
        return None;
    }
    Some(d_step(&first.1)? - median(&without))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_of_odd_and_even_counts() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), 2.5);
    }

    #[test]
    fn r1_extra_is_its_steps_discriminator_step_less_the_others_median() {
        let step = |d: f64| {
            let times = vec![
                PhaseTime {
                    phase: Phase::Field,
                    seconds: 1.0,
                    calls: 1,
                },
                PhaseTime {
                    phase: Phase::DiscriminatorStep,
                    seconds: d,
                    calls: 1,
                },
            ];
            (2.0, times)
        };
        let steps = vec![step(0.5), step(0.2), step(0.3), step(0.25)];
        let extra = r1_extra(&steps, 16).unwrap();
        assert!((extra - 0.25).abs() < 1e-12, "{extra}");
        assert_eq!(r1_extra(&steps, 0), None);
        assert_eq!(r1_extra(&steps[..1], 16), None);
        assert_eq!(r1_extra(&[], 16), None);
    }

    #[test]
    fn the_density_regulariser_is_counted_with_the_field_and_its_backward() {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/quickstart.toml");
        let config = TrainConfig::load(&path).unwrap();
        let without = ActiveTerms {
            albedo: true,
            geometry: true,
            path: true,
            ..ActiveTerms::default()
        };
        let with = ActiveTerms {
            density: true,
            ..without
        };
        let of = |active| {
            let rows = phase_flops(&config, active, 10, 10);
            move |phase: Phase| {
                rows.iter()
                    .find(|(p, _, _)| *p == phase)
                    .map(|&(_, f, _)| f)
                    .unwrap()
            }
        };
        let (a, b) = (of(without), of(with));
        let query = flops::field(
            &config.generator().neiif,
            config.train.batch,
            2 * DENSITY_REGULARISER_POINTS,
            FieldWants::DENSITY,
        );
        assert!(query > 0.0);
        let close = |x: f64, y: f64| (x - y).abs() <= 1e-9 * y.abs();
        assert!(close(b(Phase::Field) - a(Phase::Field), query));
        assert!(close(
            b(Phase::GeneratorBackward) - a(Phase::GeneratorBackward),
            BACKWARD_FACTOR * query
        ));
        assert_eq!(b(Phase::Upsampler), a(Phase::Upsampler));
    }

    #[test]
    fn roles_follow_the_active_terms() {
        let stage1 = ActiveTerms {
            albedo: true,
            geometry: true,
            path: true,
            ..ActiveTerms::default()
        };
        assert_eq!(
            active_roles(stage1),
            [
                DiscriminatorRole::AlbedoLow,
                DiscriminatorRole::AlbedoHigh,
                DiscriminatorRole::Geometry
            ]
        );
    }
}
