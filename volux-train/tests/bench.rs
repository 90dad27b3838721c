//! The per-phase benchmark on a tiny config: real steps of each stage, every active phase
//! timed and counted, inactive discriminators absent. Nothing here asserts on speed.

use volux_model::presets::DiscriminatorRole;
use volux_model::profile::Phase;
use volux_train::bench::{self, BenchOptions, Counting};
use volux_train::config::TrainConfig;
use volux_train::schedule::Stage;

/// Batch 2, few samples per ray, R1 every 2 steps, three procedural environments; the
/// stages are shorter than the benchmark's steps (it stays at each stage's start).
const TINY: &str = r#"
[model]
preset = "small"
stratified = 4
importance = 2

[train]
batch = 2
seed = 3
r1_interval = 2

[schedule]
stage1_kimg = 0.004
stage2_kimg = 0.002
fade_kimg = 0.002

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

#[test]
fn bench_times_and_counts_every_active_phase_of_both_stages() {
    for proposal in [false, true] {
        phases_of_both_stages(proposal);
    }
}

/// The bench of [`TINY`], or of TINY with its importance samples placed by density-only
/// proposal passes (then a "density-only proposal" row is timed and counted too).
fn phases_of_both_stages(proposal: bool) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tiny.toml");
    let text = if proposal {
        TINY.replace(
            "stratified = 4\nimportance = 2",
            "stratified = 0\nproposal = 6\nrefine = 2\nimportance = 3",
        )
    } else {
        TINY.to_string()
    };
    std::fs::write(&path, text).unwrap();
    let config = TrainConfig::load(&path).unwrap();
    assert_eq!(config.generator().renderer.proposal > 0, proposal);
    // Stage 1 with the step's parts in turn, stage 2 side by side (the default).
    let options = |stage| BenchOptions {
        stage,
        steps: 2,
        gemm_side: 128,
        in_turn: stage == Stage::One,
        ..BenchOptions::default()
    };

    let common = [
        Phase::Mapping,
        Phase::Field,
        Phase::Compositing,
        Phase::Upsampler,
        Phase::DiscriminatorsOnFakes,
        Phase::GeneratorUpdate,
        Phase::DiscriminatorUpdate,
        Phase::R1,
        Phase::Ema,
    ];
    let stage2_only = [Phase::Relighting];
    for stage in [Stage::One, Stage::Two] {
        let report = bench::run(config.clone(), &options(stage)).unwrap();
        assert_eq!((report.stage, report.steps, report.batch), (stage, 2, 2));
        assert_eq!(report.skipped, 0);
        assert!(report.gemm_peak.is_finite() && report.gemm_peak > 0.0);
        assert!(report.step_median_s > 0.0 && report.images_per_s() > 0.0);
        let (mut present, mut absent): (Vec<Phase>, Vec<Phase>) = if stage == Stage::One {
            (common.to_vec(), stage2_only.to_vec())
        } else {
            (common.iter().chain(&stage2_only).copied().collect(), vec![])
        };
        if proposal {
            present.push(Phase::Proposal);
        } else {
            absent.push(Phase::Proposal);
        }
        let in_turn = [Phase::GeneratorBackward, Phase::DiscriminatorStep];
        if stage == Stage::One {
            present.extend(in_turn);
            absent.push(Phase::BackwardPasses);
        } else {
            present.push(Phase::BackwardPasses);
            absent.extend(in_turn);
        }
        for phase in present {
            let row = report
                .row(phase)
                .unwrap_or_else(|| panic!("{phase:?} missing at {stage:?}"));
            // R1's row is a difference of two steps' times: finite, of either sign in noise.
            assert!(
                row.median_s.is_finite() && (phase == Phase::R1 || row.median_s > 0.0),
                "{phase:?}: {row:?}"
            );
            let (flops, _) = row.flops.expect("counted");
            assert!(flops.is_finite() && flops > 0.0, "{phase:?}: {row:?}");
            // R1 runs on the first measured step only, compared with the other.
            let steps = if phase == Phase::R1 { 1 } else { 2 };
            assert_eq!(row.steps, steps, "{phase:?}");
        }
        for phase in absent {
            assert!(report.row(phase).is_none(), "{phase:?} ran at {stage:?}");
        }
        assert_eq!(
            report.row(Phase::Field).unwrap().flops.unwrap().1,
            Counting::Exact
        );
        let table = report.markdown();
        for r in &report.rows {
            assert!(table.contains(r.label()), "{} missing:\n{table}", r.label());
        }
        assert!(table.contains("GFLOP/s") && table.contains("% of peak"));
        // Each active discriminator is timed alone too.
        let roles: Vec<DiscriminatorRole> = report.discriminators.iter().map(|d| d.role).collect();
        let mut want = vec![
            DiscriminatorRole::AlbedoLow,
            DiscriminatorRole::AlbedoHigh,
            DiscriminatorRole::Geometry,
        ];
        if stage == Stage::Two {
            want.extend([DiscriminatorRole::Shading, DiscriminatorRole::Photo]);
        }
        assert_eq!(roles, want);
        for d in &report.discriminators {
            assert_eq!(d.input[0], 2);
            assert!(d.on_fakes_s > 0.0 && d.pass_and_backward_s > 0.0, "{d:?}");
            assert!(d.on_fakes_flops > 0.0 && d.pass_and_backward_flops > d.on_fakes_flops / 2.0);
            assert!(
                table.contains(d.role.name()),
                "{} missing:\n{table}",
                d.role.name()
            );
        }
        assert_eq!(stage == Stage::Two, table.contains("D_S (relit, D, S)"));
    }
}

#[test]
fn bench_refuses_a_stage_the_schedule_lacks() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("one-stage.toml");
    std::fs::write(
        &path,
        TINY.replace("stage2_kimg = 0.002", "stage2_kimg = 0.0"),
    )
    .unwrap();
    let config = TrainConfig::load(&path).unwrap();
    let options = BenchOptions {
        stage: Stage::Two,
        ..BenchOptions::default()
    };
    let err = bench::run(config, &options).unwrap_err().to_string();
    assert!(
        err.contains("one-stage.toml") && err.contains("stage2_kimg = 0"),
        "{err}"
    );
}
