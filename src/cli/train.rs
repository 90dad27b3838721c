//! `volux train`: run a training config (stage 1, then stage 2), with checkpoints, metrics,
//! sample grids and resume; `volux train bench`: time real steps of a config phase by phase.

use std::io::IsTerminal;
use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use volux_eval::progress::{ProgressEval, ProgressOptions};
use volux_model::backend::BackendKind;
use volux_train::bench::{self, BenchOptions};
use volux_train::config::TrainConfig;
use volux_train::schedule::Stage;
use volux_train::training_loop::{Event, Finish, TrainOptions, Trainer};

/// `volux train --config FILE ...` trains; `volux train bench --config FILE ...` measures.
#[derive(Debug, Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct TrainCommand {
    #[command(subcommand)]
    pub command: Option<TrainSubcommand>,
    #[command(flatten)]
    pub train: TrainArgs,
}

#[derive(Debug, Subcommand)]
pub enum TrainSubcommand {
    /// Time real training steps of a config phase by phase (mapping, field, compositing,
    /// upsampler, relighting, the discriminators on the fakes, backward, discriminator step,
    /// R1) beside their FLOPs and the machine's measured matmul peak, then each discriminator
    /// alone; prints markdown tables and writes them to a file.
    Bench(BenchArgs),
}

#[derive(Debug, Args)]
pub struct TrainArgs {
    /// Training config (TOML): [model], [train], [schedule], [loss], [output], [data].
    #[arg(long, required = true)]
    pub config: Option<PathBuf>,
    /// Compute backend: cpu (Burn's flex) or wgpu (needs the `wgpu` cargo feature).
    #[arg(long, default_value = "cpu")]
    pub backend: BackendKind,
    /// Run folder: checkpoints, grids/, metrics.jsonl (default: runs/<config name>).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Continue from the newest checkpoint in the run folder.
    #[arg(long, conflicts_with = "force")]
    pub resume: bool,
    /// Start afresh in a run folder that already holds a run, deleting its checkpoints,
    /// metrics.jsonl and grids/ (without it such a folder is refused).
    #[arg(long)]
    pub force: bool,
    /// Stop after this many steps, at least 1 (a checkpoint is written first).
    #[arg(long)]
    pub steps: Option<u64>,
}

fn stage_name(stage: Stage) -> &'static str {
    match stage {
        Stage::One => "stage 1",
        Stage::Two => "stage 2",
        Stage::Done => "done",
    }
}

#[derive(Debug, Args)]
pub struct BenchArgs {
    /// Training config (TOML).
    #[arg(long)]
    pub config: PathBuf,
    /// The stage to measure (2 starts the run at stage 2's first image, without stage 1).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=2))]
    pub stage: u8,
    /// Measured steps, after one warm-up step.
    #[arg(long, default_value_t = 5)]
    pub steps: usize,
    /// Compute backend: cpu (Burn's flex) or wgpu (needs the `wgpu` cargo feature).
    #[arg(long, default_value = "cpu")]
    pub backend: BackendKind,
    /// Markdown file for the table (default: runs/bench/<config>-stage<N>-<backend>.md).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Side of the square matmul that measures the machine's fp32 peak.
    #[arg(long, default_value_t = 2048)]
    pub gemm_side: usize,
    /// Run the step's independent parts in turn, not side by side on the CPU's threads: the
    /// same results, slower, with the generator's backward pass and the discriminator step
    /// each timed on its own.
    #[arg(long)]
    pub in_turn: bool,
}

fn config_name(path: &std::path::Path) -> String {
    path.file_stem()
        .map_or("run".into(), |s| s.to_string_lossy().into_owned())
}

pub fn run(cmd: TrainCommand) -> anyhow::Result<()> {
    match cmd.command {
        Some(TrainSubcommand::Bench(args)) => run_bench(args),
        None => run_training(cmd.train),
    }
}

fn run_bench(args: BenchArgs) -> anyhow::Result<()> {
    let config = TrainConfig::load(&args.config)?;
    let options = BenchOptions {
        backend: args.backend,
        stage: if args.stage == 1 {
            Stage::One
        } else {
            Stage::Two
        },
        steps: args.steps,
        gemm_side: args.gemm_side,
        in_turn: args.in_turn,
        ..BenchOptions::default()
    };
    let out = args.out.unwrap_or_else(|| {
        PathBuf::from("runs/bench").join(format!(
            "{}-stage{}-{}.md",
            config_name(&args.config),
            args.stage,
            args.backend
        ))
    });
    super::output_file(&out)?;
    let report = bench::run(config, &options)
        .with_context(|| format!("benchmarking {}", args.config.display()))?;
    let table = report.markdown();
    std::fs::write(&out, &table).with_context(|| format!("writing {}", out.display()))?;
    println!("{table}");
    println!("table written to {}", out.display());
    Ok(())
}

fn run_training(args: TrainArgs) -> anyhow::Result<()> {
    if args.steps == Some(0) {
        // As StyleGAN2-ADA refuses `--kimg 0`: a run of no steps only writes an untrained
        // checkpoint, and into a folder holding a run it would stand for that run.
        bail!(
            "--steps 0: give at least 1 (a run of no steps would only write an untrained checkpoint)"
        );
    }
    let config_path = args.config.clone().expect("clap requires --config");
    let config = TrainConfig::load(&config_path)?;
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("runs").join(config_name(&config_path)));
    if out.exists() && !out.is_dir() {
        bail!(
            "--out {} is a file: give a folder for the run",
            out.display()
        );
    }
    let g = config.generator();
    tracing::info!(
        "{}: {} model ({}x{} volume, {}x{} output), batch {}, {} + {} kimg, backend {}",
        config_path.display(),
        config.model.preset,
        g.volume_resolution,
        g.volume_resolution,
        g.output_resolution,
        g.output_resolution,
        config.train.batch,
        config.schedule.stage1_kimg,
        config.schedule.stage2_kimg,
        args.backend
    );
    let mut trainer = Trainer::new(
        config,
        TrainOptions {
            backend: args.backend,
            out: out.clone(),
            resume: args.resume,
            force: args.force,
            max_steps: args.steps,
        },
    )
    .with_context(|| format!("starting the run in {}", out.display()))?;
    let o = &trainer.config().output;
    if o.eval_kimg > 0.0 {
        tracing::info!(
            "light evaluation every {} kimg on {} samples: drawing its fixed dataset sets",
            o.eval_kimg,
            o.eval_samples
        );
        let evaluator = ProgressEval::new(
            trainer.config(),
            trainer.device().clone().inner(),
            ProgressOptions::new(o.eval_samples),
        )
        .context("preparing the light evaluation ([output] eval_kimg)")?;
        trainer.set_evaluator(Box::new(evaluator));
    }
    let total = trainer.total_images();
    let terminal = std::io::stderr().is_terminal();
    let bar = if terminal {
        let bar = ProgressBar::new(total);
        bar.set_style(
            ProgressStyle::with_template(
                "[{elapsed_precise}] {bar:30} {pos}/{len} img ({eta} left) {msg}",
            )
            .expect("valid template"),
        );
        bar.set_position(trainer.state().images);
        bar
    } else {
        ProgressBar::hidden()
    };
    let (started, first_images) = (std::time::Instant::now(), trainer.state().images);
    // A line above the progress bar on a terminal, plain stdout otherwise.
    let say = |line: String| {
        if terminal {
            bar.println(line);
        } else {
            println!("{line}");
        }
    };
    let finish = trainer.run(&mut |event| match event {
        Event::Step(r) => {
            bar.set_position(r.images);
            let g = r.losses.get("G_total").copied().unwrap_or(f64::NAN);
            let d = r.losses.get("D_total").copied().unwrap_or(f64::NAN);
            let kimg_s =
                (r.images - first_images) as f64 / 1000.0 / started.elapsed().as_secs_f64();
            bar.set_message(format!(
                "{} | G {g:.3} D {d:.3} | {:.2} s/step, {kimg_s:.4} kimg/s",
                stage_name(r.stage),
                r.seconds,
            ));
        }
        Event::Metrics(m) => {
            let losses: Vec<String> = m
                .losses
                .iter()
                .map(|(k, v)| format!("{k} {v:.3}"))
                .collect();
            let line = format!(
                "step {} | {:.2} kimg | stage {} | {:.2} s/step, {:.2} img/s | {}",
                m.step,
                m.kimg,
                m.stage,
                m.sec_per_step,
                m.images_per_sec,
                losses.join(", ")
            );
            say(line);
        }
        Event::Eval(e) => {
            let scores: Vec<String> = e
                .eval
                .iter()
                .filter(|(k, _)| !k.ends_with("_floor") && !k.ends_with("_data"))
                .map(|(k, v)| format!("{k} {v:.3}"))
                .collect();
            let line = format!(
                "eval at {:.2} kimg ({:.1} s) | {}",
                e.kimg,
                e.eval_seconds,
                scores.join(", ")
            );
            say(line);
        }
        Event::Grid(p) => bar.suspend(|| tracing::info!("sample grid {}", p.display())),
        Event::Checkpoint(p) => bar.suspend(|| tracing::info!("checkpoint {}", p.display())),
    })?;
    bar.finish_and_clear();
    let s = trainer.state();
    let why = match finish {
        Finish::Done => "schedule complete",
        Finish::Steps => "step limit reached",
        Finish::Time => "time budget used",
    };
    println!(
        "{why}: step {}, {:.2} kimg, {} non-finite steps skipped; run folder {}",
        s.step,
        s.images as f64 / 1000.0,
        s.skipped,
        out.display()
    );
    Ok(())
}
