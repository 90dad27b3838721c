//! Training on datasets like CelebA or FFHQ: photos without pose labels get fakes from the
//! camera prior, photos with poses keep them.

use std::path::Path;
use std::sync::Mutex;

use volux_data::folder_dataset::{FolderSample, POSES_FILE, write_dataset};
use volux_data::synthetic_head::{self, RenderSettings, SyntheticHead};
use volux_envmap::io::linear_to_srgb;
use volux_model::backend::BackendKind;
use volux_model::pose::Pose;
use volux_train::config::TrainConfig;
use volux_train::training_loop::{TrainOptions, Trainer};

/// Stage 1 of the small model on a folder dataset `faces/` next to the config.
const FOLDER: &str = r#"
[model]
preset = "small"
stratified = 4
importance = 2

[train]
batch = 2
seed = 5

[schedule]
stage1_kimg = 0.004
stage2_kimg = 0.0
fade_kimg = 0.002

[output]
grid_kimg = 0.0
grid_seeds = [0]

[data]
resolution = 64
volume_resolution = 32

[data.source]
kind = "folder"
path = "faces"

[data.lighting]
builtin = false
skies = 1
overcast = 1
studios = 0
procedural_height = 16
"#;

static ONE_RUN_AT_A_TIME: Mutex<()> = Mutex::new(());

const POSES: [Pose; 3] = [
    Pose::new(0.4, 0.1),
    Pose::new(-0.3, 0.0),
    Pose::new(0.1, -0.1),
];

/// Three synthetic heads written as a folder dataset (photo: the albedo, sRGB), with or
/// without `poses.csv`.
fn write_faces(root: &Path, with_poses: bool) {
    let samples: Vec<FolderSample> = POSES
        .iter()
        .enumerate()
        .map(|(i, &pose)| {
            let head = SyntheticHead::from_seed(i as u64);
            let render = synthetic_head::render(&head, pose, &RenderSettings::square(64));
            FolderSample {
                stem: format!("face{i}"),
                photo: render
                    .image
                    .albedo
                    .iter()
                    .map(|c| c.map(linear_to_srgb))
                    .collect(),
                image: render.image,
                renormalised: 0,
                degenerate: 0,
            }
        })
        .collect();
    write_dataset(root, &samples).unwrap();
    if !with_poses {
        std::fs::remove_file(root.join(POSES_FILE)).unwrap();
    }
}

fn trainer(dir: &Path, text: &str) -> Trainer {
    let path = dir.join("folder.toml");
    std::fs::write(&path, text).unwrap();
    let config = TrainConfig::load(&path).unwrap();
    Trainer::new(
        config,
        TrainOptions {
            backend: BackendKind::Cpu,
            out: dir.join("run"),
            resume: false,
            max_steps: None,
            force: false,
        },
    )
    .unwrap()
}

/// The fakes' poses of two steps.
fn fake_poses(t: &mut Trainer) -> Vec<Pose> {
    (0..2).flat_map(|_| t.step().unwrap().fake_poses).collect()
}

#[test]
fn photos_without_poses_train_with_fakes_from_the_camera_prior() {
    let _one = ONE_RUN_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = tempfile::tempdir().unwrap();
    write_faces(&dir.path().join("faces"), false);
    let poses = fake_poses(&mut trainer(dir.path(), FOLDER));
    assert_eq!(poses.len(), 4);
    // Every real is frontal; the fakes are not, and differ from each other.
    assert!(
        poses
            .iter()
            .all(|p| p.yaw.abs() > 1e-6 && p.pitch.abs() > 1e-6),
        "{poses:?}"
    );
    assert!(poses.windows(2).all(|w| w[0] != w[1]), "{poses:?}");
    assert!(
        poses
            .iter()
            .all(|p| p.yaw.abs() <= 0.9 + 1e-9 && p.pitch.abs() <= 0.465 + 1e-9)
    );
}

#[test]
fn photos_with_poses_render_fakes_at_the_reals_poses_unless_told_otherwise() {
    let _one = ONE_RUN_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = tempfile::tempdir().unwrap();
    write_faces(&dir.path().join("faces"), true);
    let poses = fake_poses(&mut trainer(dir.path(), FOLDER));
    assert!(
        poses.iter().all(|p| POSES
            .iter()
            .any(|q| (p.yaw - q.yaw).abs() < 1e-6 && (p.pitch - q.pitch).abs() < 1e-6)),
        "{poses:?}"
    );
    // Asked for the prior, a dataset with poses gets it too.
    let prior = FOLDER.replace("seed = 5", "seed = 5\nfake_poses = \"prior\"");
    let dir = tempfile::tempdir().unwrap();
    write_faces(&dir.path().join("faces"), true);
    let poses = fake_poses(&mut trainer(dir.path(), &prior));
    assert!(
        poses
            .iter()
            .all(|p| POSES.iter().all(|q| (p.yaw - q.yaw).abs() > 1e-6)),
        "{poses:?}"
    );
}

#[test]
fn an_unknown_fake_pose_mode_and_a_bad_prior_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.toml");
    for (text, key) in [
        (
            FOLDER.replace("seed = 5", "seed = 5\nfake_poses = \"sideways\""),
            "sideways",
        ),
        (
            FOLDER.replace("seed = 5", "seed = 5\n[train.pose_prior]\nyaw_sd = -1.0\n"),
            "train.pose_prior.yaw_sd",
        ),
    ] {
        std::fs::write(&path, text).unwrap();
        let e = volux_envmap::error::chain(&TrainConfig::load(&path).expect_err("refused"));
        assert!(e.contains(key) && e.contains("bad.toml"), "{e}");
    }
}

#[test]
fn the_paper_configs_train_the_papers_iterations() {
    use volux_train::schedule::{PAPER_BATCH, PAPER_ITERATIONS};
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs");
    for name in ["celeba128", "ffhq256"] {
        let c = TrainConfig::load(&dir.join(format!("{name}.toml"))).unwrap();
        assert_eq!(c.train.batch as u64, PAPER_BATCH, "{name}");
        let images = |kimg: f64| (kimg * 1000.0).round() as u64;
        assert_eq!(
            (
                images(c.schedule.stage1_kimg),
                images(c.schedule.stage2_kimg)
            ),
            (
                PAPER_ITERATIONS.0 * PAPER_BATCH,
                PAPER_ITERATIONS.1 * PAPER_BATCH
            ),
            "{name}"
        );
        assert!(c.schedule.fade_discriminator, "{name}");
    }
}
