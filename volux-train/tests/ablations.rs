//! The ablation configs (`configs/ablations/`, the rows of the paper's tables 1 and 2): each
//! differs from `full.toml` in exactly its one key, builds exactly the discriminators it
//! should, and trains.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use volux_model::backend::BackendKind;
use volux_model::volume_rendering::Shading;
use volux_train::config::TrainConfig;
use volux_train::schedule::Stage;
use volux_train::training_loop::{TrainOptions, Trainer};

const ALL: [&str; 5] = ["albedo_lo", "albedo_hi", "geometry", "shading", "photo"];

/// File stem, the one key that differs from `full.toml` and its value there, the
/// discriminators the run has, the shading mode.
type Ablation = (
    &'static str,
    Option<(&'static str, &'static str)>,
    Vec<&'static str>,
    Shading,
);

fn ablations() -> Vec<Ablation> {
    let without = |name: &str| ALL.iter().copied().filter(|d| *d != name).collect();
    vec![
        ("full", None, ALL.to_vec(), Shading::Volume),
        (
            "no-shading-loss",
            Some(("loss.shading", "0.0")),
            without("shading"),
            Shading::Volume,
        ),
        (
            "no-geometry-loss",
            Some(("loss.geometry", "0.0")),
            without("geometry"),
            Shading::Volume,
        ),
        (
            "no-photo-loss",
            Some(("loss.photo", "0.0")),
            without("photo"),
            Shading::Volume,
        ),
        (
            "surface-relighting",
            Some(("model.shading", "\"surface\"")),
            ALL.to_vec(),
            Shading::Surface,
        ),
    ]
}

fn path(stem: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../configs/ablations/{stem}.toml"))
}

fn table(stem: &str) -> toml::Table {
    toml::from_str(&std::fs::read_to_string(path(stem)).unwrap()).unwrap()
}

/// Every leaf of a table as `a.b.c = value`.
fn leaves(prefix: &str, table: &toml::Table, out: &mut BTreeMap<String, String>) {
    for (key, value) in table {
        let name = if prefix.is_empty() {
            key.clone()
        } else {
            format!("{prefix}.{key}")
        };
        match value {
            toml::Value::Table(t) => leaves(&name, t, out),
            other => {
                out.insert(name, other.to_string());
            }
        }
    }
}

#[test]
fn each_ablation_differs_from_the_full_model_in_its_one_key() {
    let mut full = BTreeMap::new();
    leaves("", &table("full"), &mut full);
    let quickstart: toml::Table = toml::from_str(
        &std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/quickstart.toml"),
        )
        .unwrap(),
    )
    .unwrap();
    let mut base = BTreeMap::new();
    leaves("", &quickstart, &mut base);
    // The full model is the quickstart with an image budget instead of its time limit.
    let changed: Vec<_> = full
        .iter()
        .filter(|(k, v)| base.get(*k) != Some(v))
        .map(|(k, v)| (k.as_str(), v.as_str()))
        .collect();
    assert_eq!(
        changed,
        [("output.minutes", "0"), ("schedule.stage2_kimg", "2.0")]
    );
    for (stem, key, _, _) in ablations() {
        let mut leaves_of = BTreeMap::new();
        leaves("", &table(stem), &mut leaves_of);
        let keys: std::collections::BTreeSet<&String> =
            full.keys().chain(leaves_of.keys()).collect();
        let differ: Vec<(&str, &str)> = keys
            .into_iter()
            .filter(|k| full.get(*k) != leaves_of.get(*k))
            .map(|k| {
                (
                    k.as_str(),
                    leaves_of.get(k).map_or("(absent)", |v| v.as_str()),
                )
            })
            .collect();
        assert_eq!(differ, key.into_iter().collect::<Vec<_>>(), "{stem}");
    }
}

/// The shipped file with its model, data and schedule shrunk to a few seconds of training:
/// one step of stage 1, one of stage 2; its `[loss]` and `[model] shading` are kept.
fn tiny(stem: &str, dir: &Path) -> TrainConfig {
    let mut t = table(stem);
    let set = |t: &mut toml::Table, section: &str, key: &str, value: toml::Value| {
        t.get_mut(section)
            .and_then(|s| s.as_table_mut())
            .unwrap()
            .insert(key.into(), value);
    };
    set(&mut t, "model", "stratified", 4.into());
    set(&mut t, "model", "importance", 2.into());
    set(&mut t, "train", "batch", 2.into());
    set(&mut t, "train", "r1_interval", 2.into());
    for key in ["stage1_kimg", "stage2_kimg", "fade_kimg"] {
        set(&mut t, "schedule", key, 0.002.into());
    }
    let lighting: toml::Table = toml::from_str(
        "builtin = false\nskies = 1\novercast = 1\nstudios = 1\nprocedural_height = 16",
    )
    .unwrap();
    set(&mut t, "data", "lighting", lighting.into());
    let file = dir.join(format!("{stem}.toml"));
    std::fs::write(&file, toml::to_string(&t).unwrap()).unwrap();
    TrainConfig::load(&file).unwrap()
}

#[test]
fn ablations_build_their_discriminators_and_train() {
    let dir = tempfile::tempdir().unwrap();
    for (stem, _, discriminators, shading) in ablations() {
        let config = tiny(stem, dir.path());
        assert_eq!(config.generator().renderer.shading, shading, "{stem}");
        let options = TrainOptions {
            backend: BackendKind::Cpu,
            out: dir.path().join(stem),
            resume: false,
            force: false,
            max_steps: None,
        };
        let mut trainer = Trainer::new(config, options).unwrap();
        assert_eq!(trainer.state().discriminators, discriminators, "{stem}");
        trainer.step().unwrap();
        let report = trainer.step().unwrap();
        assert_eq!(report.stage, Stage::Two, "{stem}");
        assert!(report.skipped.is_none(), "{stem}: {:?}", report.skipped);
        // Stage 2 runs a generator and a discriminator term for each discriminator it has,
        // and none for the ones it does not.
        for d in ["geometry", "shading", "photo"] {
            let has = discriminators.contains(&d);
            for side in ["G", "D"] {
                let name = format!("{side}_{d}");
                assert_eq!(
                    report.losses.contains_key(name.as_str()),
                    has,
                    "{stem}: {name} in {:?}",
                    report.losses
                );
            }
        }
        assert!(
            report.losses.values().all(|v| v.is_finite()),
            "{stem}: {:?}",
            report.losses
        );
    }
}
