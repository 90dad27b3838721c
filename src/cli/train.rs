//! `volux train`: run a training config (stage 1, then stage 2), with checkpoints, metrics,
//! sample grids and resume.

use std::io::IsTerminal;
use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use volux_model::backend::BackendKind;
use volux_train::config::TrainConfig;
use volux_train::schedule::Stage;
use volux_train::training_loop::{Event, Finish, TrainOptions, Trainer};

#[derive(Debug, Args)]
pub struct TrainArgs {
    /// Training config (TOML): [model], [train], [schedule], [loss], [output], [data].
    #[arg(long)]
    pub config: PathBuf,
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
    /// Stop after this many steps (a checkpoint is written first).
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

pub fn run(args: TrainArgs) -> anyhow::Result<()> {
    let config = TrainConfig::load(&args.config)?;
    let out = args.out.clone().unwrap_or_else(|| {
        let name = args
            .config
            .file_stem()
            .map_or("run".into(), |s| s.to_string_lossy().into_owned());
        PathBuf::from("runs").join(name)
    });
    let g = config.generator();
    tracing::info!(
        "{}: {} model ({}x{} volume, {}x{} output), batch {}, {} + {} kimg, backend {}",
        args.config.display(),
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
            if terminal {
                bar.println(line);
            } else {
                println!("{line}");
            }
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
