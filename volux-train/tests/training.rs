//! Training end to end on a tiny config: both stages, checkpoints, resume equality, the
//! non-finite guard, shape mismatches.

use std::path::Path;
use std::sync::Mutex;

use volux_model::backend::BackendKind;
use volux_model::backend::to_f32_vec;
use volux_train::checkpoint;
use volux_train::config::TrainConfig;
use volux_train::schedule::Stage;
use volux_train::step::Phase;
use volux_train::training_loop::{Event, Finish, TrainError, TrainOptions, Trainer};

/// Two steps of stage 1 (the upsampler fading in), two of stage 2, batch 2, few samples per
/// ray, three procedural environments.
const TINY: &str = r#"
[model]
preset = "small"
stratified = 4
importance = 2

[train]
batch = 2
seed = 3
r1_interval = 2
ema_rampup = 0.5

[schedule]
stage1_kimg = 0.004
stage2_kimg = 0.004
fade_kimg = 0.002

[output]
log_every = 1
grid_kimg = 0.004
grid_seeds = [0, 1]
checkpoint_kimg = 0.004
keep = 2

[data]
seed = 1
resolution = 64
volume_resolution = 32

[data.lighting]
builtin = false
skies = 1
overcast = 1
studios = 1
procedural_height = 16
"#;

/// The backend's random generator is process-wide: runs in parallel test threads would draw
/// from it in turns, so each test holds this while it trains.
static ONE_RUN_AT_A_TIME: Mutex<()> = Mutex::new(());

fn config(dir: &Path, text: &str) -> TrainConfig {
    let path = dir.join("tiny.toml");
    std::fs::write(&path, text).unwrap();
    TrainConfig::load(&path).unwrap()
}

fn options(out: &Path, resume: bool, max_steps: Option<u64>) -> TrainOptions {
    TrainOptions {
        backend: BackendKind::Cpu,
        out: out.to_path_buf(),
        resume,
        max_steps,
        force: false,
    }
}

/// A step's number, stage and losses.
type Seen = (u64, Stage, Vec<(String, f64)>);

/// Runs and returns the losses of every step, in order.
fn losses(trainer: &mut Trainer) -> (Finish, Vec<Seen>) {
    let mut seen = Vec::new();
    let finish = trainer
        .run(&mut |e| {
            if let Event::Step(r) = e {
                let l = r.losses.iter().map(|(k, v)| (k.to_string(), *v)).collect();
                seen.push((r.step, r.stage, l));
            }
        })
        .unwrap();
    (finish, seen)
}

#[test]
fn training_runs_both_stages_and_resumes_with_identical_losses() {
    let _one = ONE_RUN_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = tempfile::tempdir().unwrap();
    let c = config(dir.path(), TINY);

    // Uninterrupted.
    let full = dir.path().join("full");
    let mut t = Trainer::new(c.clone(), options(&full, false, None)).unwrap();
    let (finish, all) = losses(&mut t);
    assert_eq!(finish, Finish::Done);
    assert_eq!(all.len(), 4);
    let stages: Vec<Stage> = all.iter().map(|s| s.1).collect();
    assert_eq!(stages, [Stage::One, Stage::One, Stage::Two, Stage::Two]);
    let names = |i: usize| all[i].2.iter().map(|(k, _)| k.clone()).collect::<Vec<_>>();
    // Stage 1 runs albedo, geometry and path terms only; R1 on even steps.
    assert!(names(0).contains(&"R1_albedo_hi".to_string()));
    assert!(
        !names(0)
            .iter()
            .any(|n| n.contains("shading") || n.contains("photo"))
    );
    assert!(!names(1).iter().any(|n| n.starts_with("R1")));
    for n in [
        "G_shading",
        "G_photo",
        "D_shading",
        "D_photo",
        "path",
        "R1_photo",
    ] {
        assert!(
            names(2).contains(&n.to_string()),
            "{n} missing in {:?}",
            names(2)
        );
    }
    for (_, _, l) in &all {
        assert!(l.iter().all(|(_, v)| v.is_finite()), "{l:?}");
    }
    // Checkpoints (kept: the newest 2), grids, metrics.
    let kept = checkpoint::list(&full);
    assert_eq!(kept.iter().map(|k| k.0).collect::<Vec<_>>(), [2, 4]);
    assert!(full.join("grids/grid-00000000.png").is_file());
    assert!(full.join("grids/grid-00000008.png").is_file());
    let metrics = std::fs::read_to_string(full.join("metrics.jsonl")).unwrap();
    assert_eq!(metrics.lines().count(), 4);
    let state = checkpoint::read_state(&kept[1].1).unwrap();
    assert_eq!((state.step, state.images), (4, 8));

    // The step's parts in turn instead of side by side: the same losses, bit for bit.
    let in_turn = dir.path().join("in-turn");
    let mut t = Trainer::new(c.clone(), options(&in_turn, false, None)).unwrap();
    t.set_in_turn(true);
    let (_, turned) = losses(&mut t);
    assert_eq!(turned.len(), 4);
    for (a, b) in all.iter().zip(&turned) {
        assert_eq!(a.2, b.2, "step {} differs in turn", a.0);
    }
    drop(t);

    // Interrupted after 1 step (mid fade-in, before any checkpoint of its own), then resumed.
    let split = dir.path().join("split");
    let mut t = Trainer::new(c.clone(), options(&split, false, Some(1))).unwrap();
    let (finish, first) = losses(&mut t);
    assert_eq!(finish, Finish::Steps);
    drop(t);
    let mut t = Trainer::new(c.clone(), options(&split, true, None)).unwrap();
    assert_eq!(t.state().step, 1);
    let (_, rest) = losses(&mut t);
    let resumed: Vec<_> = first.into_iter().chain(rest).collect();
    assert_eq!(resumed.len(), 4);
    for (a, b) in all.iter().zip(&resumed) {
        assert_eq!(a.0, b.0);
        assert_eq!(a.2, b.2, "step {} differs after resuming", a.0);
    }
    // The metrics log holds each step once.
    let metrics = std::fs::read_to_string(split.join("metrics.jsonl")).unwrap();
    assert_eq!(metrics.lines().count(), 4);

    // A config with other shapes is refused, naming what differs.
    let other = config(
        dir.path(),
        &TINY.replace("importance = 2", "importance = 3"),
    );
    let e = Trainer::new(other, options(&full, true, None))
        .err()
        .expect("mismatch refused")
        .to_string();
    assert!(
        e.contains("importance = 2") && e.contains("importance = 3"),
        "{e}"
    );
}

#[test]
fn octaves_open_on_schedule_in_training_and_sampling() {
    let _one = ONE_RUN_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = tempfile::tempdir().unwrap();
    let text = TINY
        .replace("importance = 2", "importance = 2\nfrequencies = 5")
        .replace(
            "fade_kimg = 0.002",
            "fade_kimg = 0.002\nopen_octaves = 4\noctave_fade_start_kimg = 0.002\noctave_fade_kimg = 0.004",
        );
    let c = config(dir.path(), &text);
    let out = dir.path().join("run");
    let mut t = Trainer::new(c.clone(), options(&out, false, Some(3))).unwrap();
    let windows = |t: &Trainer| {
        (
            t.generator().neiif.encoding.window,
            t.ema().neiif.encoding.window,
        )
    };
    assert_eq!(windows(&t), (Some(4.0), Some(4.0)));
    let first = t.step().unwrap();
    assert_eq!(windows(&t), (Some(4.0), Some(4.0)), "2 images: not started");
    t.step().unwrap();
    assert_eq!(windows(&t), (Some(4.5), Some(4.5)), "4 images: half open");
    t.step().unwrap();
    t.checkpoint().unwrap();
    assert_eq!(t.state().images, 6);
    drop(t);
    // Sampling sees the field as trained at the checkpoint's 6 images.
    let sampled = volux_train::pretrained::load_for_sampling(&out, BackendKind::Cpu).unwrap();
    assert_eq!(sampled.g.neiif.encoding.window, None, "6 images: all open");
    let mut t = Trainer::new(c.clone(), options(&out, true, None)).unwrap();
    t.seek(1, 4);
    assert_eq!(windows(&t), (Some(4.5), Some(4.5)));
    drop(t);

    // The window reaches the field: the first step's losses differ from all octaves open.
    let open = config(dir.path(), &text.replace("open_octaves = 4\n", ""));
    let mut t = Trainer::new(open, options(&dir.path().join("open"), false, Some(1))).unwrap();
    assert_eq!(windows(&t), (None, None));
    let all_open = t.step().unwrap();
    assert_ne!(first.losses, all_open.losses);
}

#[test]
fn non_finite_steps_are_skipped_then_stop_the_run() {
    let _one = ONE_RUN_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = tempfile::tempdir().unwrap();
    let text = TINY.replace("seed = 3", "seed = 3\nmax_nonfinite = 3");
    let c = config(dir.path(), &text);
    let out = dir.path().join("run");

    // A poisoned step is skipped and changes nothing, the generator included when it is the
    // discriminator's half that fails; the run goes on.
    let weights = |t: &Trainer| to_f32_vec(t.generator().mapping.layers[0].weight.val());
    let mut t = Trainer::new(c.clone(), options(&out, false, Some(2))).unwrap();
    let initial = weights(&t);
    t.poison_steps(&[(0, Phase::Discriminator)]);
    let report = t.step().unwrap();
    assert_eq!(weights(&t), initial, "a skipped step moved the generator");
    assert_eq!((t.state().skipped, t.state().images), (1, 0));
    // The warning counts steps as metrics.jsonl does (this is its step 1).
    let message = volux_train::training_loop::skipped_step_message(
        t.state(),
        report.skipped.as_deref().expect("skipped"),
    );
    assert!(
        message.starts_with("step 1 skipped (1 in a row, 1 in all): "),
        "{message}"
    );
    t.poison_steps(&[(1, Phase::Generator)]);
    t.step().unwrap();
    assert_eq!(weights(&t), initial);
    assert_eq!((t.state().skipped, t.state().nonfinite_in_row), (2, 2));
    let (_, steps) = losses(&mut t);
    assert_eq!(steps.len(), 2);
    assert_eq!(t.state().nonfinite_in_row, 0);
    assert_eq!(t.state().images, 4, "only the two good steps trained");
    assert_ne!(weights(&t), initial);
    let good = checkpoint::latest(&out).unwrap();

    // Three in a row stop it with a message naming the last good checkpoint.
    let mut t = Trainer::new(c, options(&out, true, None)).unwrap();
    t.poison_steps(&[
        (4, Phase::Generator),
        (5, Phase::Discriminator),
        (6, Phase::Generator),
    ]);
    let e = t.run(&mut |_| {}).expect_err("stopped");
    assert!(matches!(e, TrainError::NonFinite { count: 3, .. }), "{e}");
    let message = e.to_string();
    assert!(message.contains(&good.display().to_string()), "{message}");
    // No checkpoint of the broken state was written.
    assert_eq!(checkpoint::latest(&out).unwrap(), good);
}

#[test]
fn every_shipped_config_loads() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs");
    let mut names = Vec::new();
    for folder in ["", "ablations"] {
        for entry in std::fs::read_dir(root.join(folder)).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "toml") {
                let c = TrainConfig::load(&path).unwrap_or_else(|e| panic!("{e}"));
                assert!(c.train.batch > 0);
                let stem = path.file_stem().unwrap().to_string_lossy().into_owned();
                names.push(if folder.is_empty() {
                    stem
                } else {
                    format!("{folder}/{stem}")
                });
            }
        }
    }
    names.sort();
    assert_eq!(
        names,
        [
            "ablations/full",
            "ablations/no-geometry-loss",
            "ablations/no-photo-loss",
            "ablations/no-shading-loss",
            "ablations/surface-relighting",
            "celeba128",
            "ffhq256",
            "quickstart",
            "synthetic-volume64",
            "synthetic2h",
            "synthetic64"
        ]
    );
}

#[test]
fn a_folder_holding_a_run_is_refused_unless_resumed_or_forced() {
    let _one = ONE_RUN_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = tempfile::tempdir().unwrap();
    let c = config(dir.path(), TINY);
    let out = dir.path().join("run");
    let mut t = Trainer::new(c.clone(), options(&out, false, Some(1))).unwrap();
    let _ = losses(&mut t);
    drop(t);
    let metrics = std::fs::read_to_string(out.join("metrics.jsonl")).unwrap();
    let kept = checkpoint::list(&out);
    assert_eq!(kept.len(), 1);

    // A second run into the same folder would mix with (and delete) the first: refused, and
    // nothing of the first run is touched.
    let e = Trainer::new(c.clone(), options(&out, false, Some(1)))
        .err()
        .expect("refused");
    assert!(matches!(e, TrainError::RunExists { .. }), "{e}");
    let message = e.to_string();
    assert!(
        message.contains("--resume")
            && message.contains("--force")
            && message.contains("metrics.jsonl"),
        "{message}"
    );
    assert_eq!(
        std::fs::read_to_string(out.join("metrics.jsonl")).unwrap(),
        metrics
    );
    assert_eq!(checkpoint::list(&out), kept);

    // Forced: the old run is gone and the new one starts at step 0.
    std::fs::write(out.join("notes.txt"), "mine").unwrap();
    let forced = TrainOptions {
        force: true,
        ..options(&out, false, Some(1))
    };
    let t = Trainer::new(c.clone(), forced).unwrap();
    assert_eq!(t.state().step, 0);
    assert!(checkpoint::list(&out).is_empty());
    assert!(!out.join("grids").exists());
    let fresh = std::fs::read_to_string(out.join("metrics.jsonl")).unwrap_or_default();
    assert!(fresh.is_empty(), "{fresh}");
    assert!(
        out.join("notes.txt").is_file(),
        "files not of a run are kept"
    );
    drop(t);

    // What a run that failed before its first checkpoint leaves (its log, a step-0 grid) is
    // refused too, but --resume is not offered: there is nothing to resume.
    std::fs::create_dir_all(out.join("grids")).unwrap();
    std::fs::write(out.join("metrics.jsonl"), "").unwrap();
    let e = Trainer::new(c, options(&out, false, Some(1)))
        .err()
        .expect("refused");
    let message = e.to_string();
    assert!(
        message.contains("nothing to resume")
            && message.contains("--force")
            && !message.contains("--resume"),
        "{message}"
    );
}

/// A folder of four 64x64 photos alone (no albedo/ or normals/), one with a mask, and the
/// tiny config reading it with `layers = ["photo"]` and the schedule `stage`.
fn photos_only(dir: &Path, stage: &str) -> String {
    let root = dir.join("photos_only");
    std::fs::create_dir_all(root.join("photos")).unwrap();
    std::fs::create_dir_all(root.join("masks")).unwrap();
    for k in 0..4u8 {
        let pixels: Vec<[u8; 3]> = (0..64 * 64)
            .map(|i| [(i % 64 * 4) as u8, (i / 64 * 4) as u8, 60 * k])
            .collect();
        let path = root.join(format!("photos/p{k}.png"));
        volux_envmap::io::save_png(&path, 64, 64, &pixels).unwrap();
    }
    let mask: Vec<[u8; 3]> = (0..64 * 64)
        .map(|i| [if i % 64 < 40 { 255 } else { 0 }; 3])
        .collect();
    volux_envmap::io::save_png(&root.join("masks/p0.png"), 64, 64, &mask).unwrap();
    let text = TINY
        .replace(
            "[schedule]\nstage1_kimg = 0.004\nstage2_kimg = 0.004\nfade_kimg = 0.002\n",
            stage,
        )
        .replace(
            "[data.lighting]",
            "[data.source]\nkind = \"folder\"\npath = \"photos_only\"\nlayers = [\"photo\"]\n\n[data.lighting]",
        );
    assert!(
        text.contains("layers") && text.contains(stage),
        "TINY changed"
    );
    text
}

#[test]
fn photos_alone_train_with_the_photo_discriminator_only() {
    let _one = ONE_RUN_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = tempfile::tempdir().unwrap();
    // A stage 1 has nothing to train on photos alone: refused, saying what to change.
    let with_stage_one = photos_only(
        dir.path(),
        "[schedule]\nstage1_kimg = 0.004\nstage2_kimg = 0.004\nfade_kimg = 0.002\n",
    );
    let path = dir.path().join("tiny.toml");
    std::fs::write(&path, &with_stage_one).unwrap();
    let e = volux_envmap::error::chain(&TrainConfig::load(&path).unwrap_err());
    assert!(
        e.contains("stage1_kimg = 0") && e.contains("albedo (no albedo_lo, albedo_hi)"),
        "{e}"
    );

    let text = photos_only(
        dir.path(),
        "[schedule]\nstage1_kimg = 0.0\nstage2_kimg = 0.008\nfade_kimg = 0.0\n",
    );
    let c = config(dir.path(), &text);
    let left_out: Vec<&str> = c.left_out.iter().map(|l| l.term).collect();
    assert_eq!(left_out, ["albedo", "geometry", "shading"]);
    assert_eq!(
        (c.loss.albedo, c.loss.geometry, c.loss.shading),
        (0.0, 0.0, 0.0)
    );
    assert!(c.loss.photo > 0.0 && c.loss.path > 0.0);
    let out = dir.path().join("run");
    let mut t = Trainer::new(c, options(&out, false, None)).unwrap();
    let (finish, seen) = losses(&mut t);
    assert_eq!(finish, Finish::Done);
    assert_eq!(seen.len(), 4);
    for (step, stage, losses) in &seen {
        assert_eq!(*stage, Stage::Two);
        let mut names: Vec<&str> = losses.iter().map(|(k, _)| k.as_str()).collect();
        names.sort_unstable();
        let mut want = vec!["D_photo", "D_total", "G_photo", "G_total", "path"];
        if step % 2 == 0 {
            want.push("R1_photo");
        }
        want.sort_unstable();
        assert_eq!(names, want, "step {step}");
        assert!(losses.iter().all(|(_, v)| v.is_finite()), "{losses:?}");
    }
    let saved = checkpoint::read_state(&checkpoint::latest(&out).unwrap()).unwrap();
    assert_eq!(saved.discriminators, ["photo"]);
}

/// Multiplies every float parameter by NaN.
struct Poison;

impl burn::module::ModuleMapper for Poison {
    fn map_float<const D: usize>(
        &mut self,
        param: burn::module::Param<burn::tensor::Tensor<D>>,
    ) -> burn::module::Param<burn::tensor::Tensor<D>> {
        param.map(|t| t.mul_scalar(f32::NAN))
    }
}

#[test]
fn killed_runs_leftovers_are_swept_and_non_finite_weights_are_refused() {
    use burn::module::Module;
    let _one = ONE_RUN_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = tempfile::tempdir().unwrap();
    let c = config(dir.path(), TINY);
    let run = dir.path().join("run");
    let mut t = Trainer::new(c.clone(), options(&run, false, Some(2))).unwrap();
    let _ = losses(&mut t);
    drop(t);
    let second = run.join("checkpoint-00000002");
    assert!(second.join("state.toml").is_file());

    // What kills leave: a checkpoint half deleted by an older version (no state.toml), one
    // caught mid-deletion, a partial write of another step; and a folder that only looks like
    // a checkpoint (it holds a file that is not one), which is not ours to delete.
    let half = run.join("checkpoint-00000001");
    std::fs::create_dir(&half).unwrap();
    std::fs::copy(second.join("generator.bpk"), half.join("generator.bpk")).unwrap();
    let deleting = run.join(".checkpoint-00000000.deleting");
    std::fs::create_dir(&deleting).unwrap();
    std::fs::write(deleting.join("optimizer_d.bpk"), b"x").unwrap();
    let partial = run.join(".checkpoint-00000009.partial");
    std::fs::create_dir(&partial).unwrap();
    let foreign = run.join("checkpoint-00000003");
    std::fs::create_dir(&foreign).unwrap();
    std::fs::write(foreign.join("notes.txt"), "mine").unwrap();
    assert_eq!(
        checkpoint::list(&run).len(),
        1,
        "none of them is a checkpoint"
    );

    // The next save sweeps them.
    let mut t = Trainer::new(c.clone(), options(&run, true, None)).unwrap();
    let _ = losses(&mut t);
    drop(t);
    assert!(!half.exists() && !deleting.exists() && !partial.exists());
    assert!(foreign.join("notes.txt").is_file());
    let kept: Vec<u64> = checkpoint::list(&run).iter().map(|k| k.0).collect();
    assert_eq!(kept, [2, 4]);
    let hidden: Vec<_> = std::fs::read_dir(&run)
        .unwrap()
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(hidden.is_empty(), "{hidden:?}");

    // A damaged optimiser state: NaN moments (every later step was skipped as non-finite,
    // no cause named) and a tensor without its parameter id (Burn's loader panicked) are
    // refused naming the file and the tensor.
    let last = run.join("checkpoint-00000004");
    let opt = last.join("optimizer_g.bpk");
    let original = std::fs::read(&opt).unwrap();
    for (poison_id, problem) in [(false, "NaN"), (true, "no parameter id")] {
        let read = burn_pack::Bytes::from_bytes_vec(std::fs::read(&opt).unwrap());
        let tensors = burn_pack::Reader::from_bytes(read)
            .and_then(burn_pack::Reader::into_tensors)
            .unwrap();
        let poisoned: Vec<burn_pack::Tensor> = tensors
            .into_iter()
            .map(|t| {
                let (name, dtype, shape, id, bytes) = t.into_parts().unwrap();
                let bytes = if poison_id || dtype != burn_pack::DType::F32 {
                    bytes
                } else {
                    let nan: Vec<u8> = bytes
                        .chunks_exact(4)
                        .flat_map(|_| f32::NAN.to_le_bytes())
                        .collect();
                    burn_pack::Bytes::from_bytes_vec(nan)
                };
                let id = if poison_id { None } else { id };
                burn_pack::Tensor::new(name, dtype, shape, id, bytes)
            })
            .collect();
        std::fs::remove_file(&opt).unwrap();
        burn_pack::Writer::new(poisoned)
            .write_to_file(&opt)
            .unwrap();
        let e = Trainer::new(c.clone(), options(&run, true, None))
            .map(drop)
            .expect_err("resuming refused");
        let message = e.to_string();
        assert!(
            message.contains("optimizer_g.bpk") && message.contains(problem),
            "{message}"
        );
        assert!(matches!(
            e,
            TrainError::Checkpoint(checkpoint::CheckpointError::OptimizerState { .. })
        ));
    }
    std::fs::write(&opt, original).unwrap();

    // NaN weights in the EMA generator: sampling and resuming name the file and the parameter.
    let g = volux_train::pretrained::load_for_sampling(&last, BackendKind::Cpu)
        .unwrap()
        .g;
    let ema = last.join("generator_ema.bpk");
    g.map(&mut Poison).save_file(&ema).unwrap();
    for e in [
        volux_train::pretrained::load_for_sampling(&last, BackendKind::Cpu)
            .map(drop)
            .expect_err("sampling refused"),
        Trainer::new(c, options(&run, true, None))
            .map(drop)
            .expect_err("resuming refused"),
    ] {
        let message = e.to_string();
        assert!(
            message.contains("generator_ema.bpk") && message.contains("NaN"),
            "{message}"
        );
        assert!(matches!(
            e,
            TrainError::Checkpoint(checkpoint::CheckpointError::NonFinite { .. })
        ));
    }
}
