//! End-to-end tests of the `volux` binary.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn volux(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_volux"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("run volux")
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// The DOM of `page` after headless Chromium loaded it (scripts run), or `None` where Chromium
/// is not installed. `.ci/run` installs it and sets `VOLUX_REQUIRE_CHROMIUM=1`, which makes a
/// missing browser a failure.
fn headless_dom(page: &Path) -> Option<String> {
    let browser = ["chromium", "chromium-browser"].into_iter().find(|b| {
        Command::new(b)
            .arg("--version")
            .output()
            .is_ok_and(|o| o.status.success())
    });
    let Some(browser) = browser else {
        assert!(
            std::env::var_os("VOLUX_REQUIRE_CHROMIUM").is_none(),
            "VOLUX_REQUIRE_CHROMIUM is set but no chromium is installed"
        );
        eprintln!("chromium not installed: the report page is not loaded in a browser");
        return None;
    };
    let profile = tempfile::tempdir().unwrap();
    let url = format!("file://{}", page.canonicalize().unwrap().display());
    let o = Command::new(browser)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--virtual-time-budget=20000",
            "--dump-dom",
        ])
        .arg(format!("--user-data-dir={}", profile.path().display()))
        .arg(url)
        .output()
        .expect("run chromium");
    assert!(o.status.success(), "chromium: {}", text(&o));
    Some(String::from_utf8_lossy(&o.stdout).into_owned())
}

fn asset(name: &str) -> String {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("assets/hdri")
        .join(name)
        .display()
        .to_string()
}

#[test]
fn envmap_info_describes_a_shipped_map() {
    let dir = tempfile::tempdir().unwrap();
    let preview = dir.path().join("preview.png");
    let o = volux(&[
        "envmap",
        "info",
        &asset("sunrise.exr"),
        "--preview",
        preview.to_str().unwrap(),
    ]);
    assert!(preview.exists());
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("1024 x 512"), "{t}");
    assert!(t.contains("brightest texel"), "{t}");
    assert!(t.contains("negative values"), "{t}");
}

#[test]
fn envmap_preconvolve_writes_one_exr_per_lobe_and_a_contact_sheet() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("lm");
    let o = volux(&[
        "envmap",
        "preconvolve",
        &asset("studio.exr"),
        "--exponents",
        "1,16,64",
        "--yaw",
        "-30",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    for f in [
        "light_n001.exr",
        "light_n016.exr",
        "light_n064.exr",
        "light_maps.png",
    ] {
        assert!(out.join(f).exists(), "{f} missing: {}", text(&o));
    }
    let lm = volux_envmap::io::read_raw(&out.join("light_n001.exr")).unwrap();
    assert_eq!(lm.width, 2 * lm.height);
}

#[test]
fn bad_inputs_fail_with_a_message_naming_the_problem() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("broken.exr");
    std::fs::write(&bad, b"\x76\x2f\x31\x01 truncated").unwrap();
    let o = volux(&["envmap", "info", bad.to_str().unwrap()]);
    assert!(!o.status.success());
    assert!(text(&o).contains("broken.exr"), "{}", text(&o));

    let o = volux(&[
        "envmap",
        "preconvolve",
        &asset("night.exr"),
        "--exponents",
        "0,16",
    ]);
    assert!(!o.status.success());
    assert!(text(&o).contains("exponent 0"), "{}", text(&o));

    let o = volux(&["envmap", "preconvolve", "no/such/file.hdr"]);
    assert!(!o.status.success());
    assert!(text(&o).contains("no/such/file.hdr"), "{}", text(&o));

    // A taper is named as a taper; a yaw of NaN or infinity is refused instead of making
    // all-zero light maps.
    let night = asset("night.exr");
    for (args, says) in [
        (["--taper", "2"], "taper 2 must be in [0, 1)"),
        (["--yaw", "nan"], "--yaw NaN"),
        (["--yaw", "inf"], "--yaw inf"),
    ] {
        let o = volux(&[&["envmap", "preconvolve", night.as_str()][..], &args[..]].concat());
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{t}");
        assert!(t.contains(says), "{says}: {t}");
    }
}

#[test]
fn envmap_bench_prints_error_and_time_tables() {
    let dir = tempfile::tempdir().unwrap();
    let small = dir.path().join("small.exr");
    let map = volux_envmap::io::load(Path::new(&asset("forest.exr")))
        .unwrap()
        .downsampled(8);
    volux_envmap::io::save_envmap_exr(&small, &map).unwrap();
    let report = dir.path().join("report.md");
    let o = volux(&[
        "envmap",
        "bench",
        small.to_str().unwrap(),
        "--exponents",
        "1,32",
        "--tolerances",
        "1e-2,1e-3",
        "--tapers",
        "0.5",
        "--directions",
        "64",
        "--texels",
        "16",
        "--repeats",
        "1",
        "--out",
        report.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let md = std::fs::read_to_string(report).unwrap();
    assert!(md.contains("| small | 32 | 1e-3 | 0.5 |"), "{md}");
    assert!(md.contains("rel RMS look-up"), "{md}");
    // Zero timing runs said "best of 0 runs" and timed one; counts are bounded.
    for (flag, value) in [
        ("--repeats", "0"),
        ("--texels", "0"),
        ("--directions", "100000000"),
    ] {
        let o = volux(&["envmap", "bench", small.to_str().unwrap(), flag, value]);
        let t = text(&o);
        assert!(
            !o.status.success() && t.contains(&format!("{flag} {value}: give 1 to")),
            "{t}"
        );
    }
}

#[test]
fn backend_check_runs_on_the_cpu() {
    let o = volux(&["backend", "--backend", "cpu"]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("cpu: ok"), "{}", text(&o));
}

#[test]
fn model_info_counts_the_parameters_of_every_network() {
    let o = volux(&["model", "info", "--preset", "small"]);
    assert!(o.status.success(), "{}", text(&o));
    let t = text(&o);
    for part in [
        "mapping network",
        "NeIIF",
        "upsampler",
        "relighting network",
        "generator",
        "D_A (low-res albedo)",
        "D_S (relit, D, S)",
        "D_P (relit vs photo)",
    ] {
        assert!(t.contains(part), "{part} missing from:\n{t}");
    }
    assert!(t.contains("261245"), "small generator size changed:\n{t}");
}

#[test]
fn model_sampling_report_prints_a_table_and_rejects_a_missing_hdri() {
    let o = volux(&[
        "model",
        "sampling-report",
        "--side",
        "4",
        "--counts",
        "4",
        "--reference",
        "32",
        "--layouts",
        "0:8:4:4",
        "--hdri",
        &asset("sunrise.exr"),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let t = text(&o);
    assert!(
        t.contains("| scene | stratified | proposal + refine | importance | rule | ms |"),
        "{t}"
    );
    assert!(t.contains("| 0 | 8 + 4 | 4 | midpoint |"), "{t}");
    assert_eq!(
        t.lines().filter(|l| l.starts_with("| ")).count(),
        1 + 4 * 4,
        "{t}"
    );
    let o = volux(&["model", "sampling-report", "--hdri", "no/such/map.exr"]);
    assert!(!o.status.success());
    assert!(text(&o).contains("no/such/map.exr"), "{}", text(&o));
    // Out-of-range sizes are named instead of tripping an assert or printing zeros; without
    // --hdri the shipped map is used, from any working directory.
    for (args, says) in [
        (["--counts", "0"], "--counts 0"),
        (["--side", "0"], "--side 0"),
        (["--layouts", "0:8:4:0"], "both 0"),
    ] {
        let o = volux(&[&["model", "sampling-report"][..], &args[..]].concat());
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{t}");
        assert!(t.contains(says), "{says}: {t}");
    }
    let elsewhere = tempfile::tempdir().unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_volux"))
        .args([
            "model",
            "sampling-report",
            "--side",
            "2",
            "--counts",
            "2",
            "--reference",
            "8",
        ])
        .args(["--layouts", "none"])
        .current_dir(elsewhere.path())
        .output()
        .unwrap();
    let t = text(&o);
    assert!(
        o.status.success() && t.contains("the shipped sunrise map"),
        "{t}"
    );
}

#[test]
fn data_build_renders_a_cache_and_a_rerun_keeps_it() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("tiny.toml");
    std::fs::write(
        &config,
        "[data]\nresolution = 16\nvolume_resolution = 8\n\
         [data.lighting]\nbuiltin = false\nskies = 1\novercast = 1\nstudios = 1\nprocedural_height = 32\n\
         [data.cache]\ndir = \"examples\"\nexamples = 5\nshard_size = 2\n",
    )
    .unwrap();
    let first = volux(&["data", "build", "--config", config.to_str().unwrap()]);
    assert!(first.status.success(), "{}", text(&first));
    assert!(
        text(&first).contains("5 examples in 3 shards (0 kept, 3 built)"),
        "{}",
        text(&first)
    );
    assert!(dir.path().join("examples/manifest.toml").exists());
    let again = volux(&["data", "build", "--config", config.to_str().unwrap()]);
    assert!(
        text(&again).contains("(3 kept, 0 built)"),
        "{}",
        text(&again)
    );
    // A typo in a key is an error naming the file and the key.
    std::fs::write(&config, "[data]\nresolutoin = 16\n").unwrap();
    let bad = volux(&["data", "build", "--config", config.to_str().unwrap()]);
    assert!(!bad.status.success());
    assert!(
        text(&bad).contains("tiny.toml") && text(&bad).contains("resolutoin"),
        "{}",
        text(&bad)
    );
}

#[test]
fn data_heads_writes_a_contact_sheet_and_reports_speed() {
    let dir = tempfile::tempdir().unwrap();
    let o = volux(&[
        "data",
        "heads",
        "--seeds",
        "0-1",
        "--side",
        "16",
        "--out",
        dir.path().to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("images/s"), "{}", text(&o));
    assert!(dir.path().join("heads.png").exists());
    let bad = volux(&["data", "heads", "--seeds", "7-2"]);
    assert!(
        !bad.status.success() && text(&bad).contains("--seeds"),
        "{}",
        text(&bad)
    );
    // A range of 2^64 seeds is refused before anything is allocated, naming the limit.
    let huge = volux(&["data", "heads", "--seeds", "0-18446744073709551615"]);
    let t = text(&huge);
    assert_eq!(huge.status.code(), Some(1), "{t}");
    assert!(
        t.contains("18446744073709551616 seeds: give 1 to 1024"),
        "{t}"
    );
    // A non-finite environment rotation is refused (NaN made black shading and photos).
    for yaw in ["nan", "inf"] {
        let o = volux(&[
            "data",
            "heads",
            "--seeds",
            "0",
            "--side",
            "16",
            &format!("--env-yaw={yaw}"),
            "--out",
            dir.path().to_str().unwrap(),
        ]);
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{t}");
        assert!(t.contains("--env-yaw") && t.contains("finite"), "{t}");
    }
}

/// Three steps of stage 1 and three of stage 2 at batch 2 with few samples per ray.
const TINY_TRAINING: &str = r#"
[model]
preset = "small"
stratified = 4
importance = 2
sphere_prior = 10.0
sphere_radius = 0.35

[train]
batch = 2

[schedule]
stage1_kimg = 0.006
stage2_kimg = 0.006
fade_kimg = 0.003

[output]
log_every = 2
grid_kimg = 0.004
grid_seeds = [0, 1]
checkpoint_kimg = 0.004
keep = 2

[data]
resolution = 64
volume_resolution = 32

[data.lighting]
builtin = false
skies = 1
overcast = 0
studios = 1
procedural_height = 16
"#;

#[test]
fn train_resume_and_sample_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("tiny.toml");
    // With the light evaluation every two steps, on two latents.
    let tiny = TINY_TRAINING.replace("keep = 2", "keep = 2\neval_kimg = 0.004\neval_samples = 2");
    std::fs::write(&config, &tiny).unwrap();
    let run = dir.path().join("run");
    let (config, run_s) = (config.to_str().unwrap(), run.to_str().unwrap());

    // Four steps, stopped; then resumed to the end of the schedule.
    let o = volux(&["train", "--config", config, "--out", run_s, "--steps", "4"]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("step limit reached: step 4"), "{t}");
    assert!(t.contains("eval at 0.00 kimg"), "{t}");
    let state = |step: u64| -> toml::Table {
        let path = run.join(format!("checkpoint-{step:08}/state.toml"));
        toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
    };
    let seconds_at_4 = state(4)["seconds"].as_float().unwrap();
    assert!(seconds_at_4 > 0.0);
    let o = volux(&["train", "--config", config, "--out", run_s, "--resume"]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("resuming from"), "{t}");
    assert!(t.contains("schedule complete: step 6, 0.01 kimg"), "{t}");
    assert!(t.contains("stage 2"), "{t}");
    // The run's clock goes on over the resume instead of starting again.
    assert!(state(6)["seconds"].as_float().unwrap() > seconds_at_4);
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    let lines: Vec<serde_json::Value> = metrics
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let losses = lines.iter().filter(|l| l.get("losses").is_some()).count();
    assert_eq!(losses, 3, "{metrics}");
    let evals: Vec<&serde_json::Value> = lines.iter().filter(|l| l.get("eval").is_some()).collect();
    let steps: Vec<u64> = evals.iter().map(|l| l["step"].as_u64().unwrap()).collect();
    // At the start, at each crossing of 0.004 kimg, where the step limit stopped it and at
    // the end of the schedule (a resumed run does not measure its starting point again).
    assert_eq!(steps, [0, 2, 4, 6], "{metrics}");
    for line in &evals {
        let swd = line["eval"]["swd_albedo"].as_f64().unwrap();
        assert!(swd.is_finite() && swd > 0.0, "{line}");
        assert!(line["eval"]["multiview_albedo_psnr"].as_f64().unwrap() > 0.0);
    }
    let minutes: Vec<f64> = lines
        .iter()
        .map(|l| l["minutes"].as_f64().unwrap())
        .collect();
    assert!(minutes.windows(2).all(|w| w[0] <= w[1]), "{metrics}");
    assert!(run.join("checkpoint-00000006/generator_ema.bpk").is_file());

    // The curves of the run, against images and against minutes.
    let o = volux(&["plot", run_s]);
    assert!(o.status.success(), "{}", text(&o));
    for f in ["curves-kimg.png", "curves-minutes.png"] {
        let png = std::fs::read(run.join("plots").join(f)).unwrap();
        // The IHDR chunk: the width is the big-endian word at byte 16.
        assert_eq!(&png[1..4], b"PNG", "{f}");
        let width = u32::from_be_bytes(png[16..20].try_into().unwrap());
        assert!(width >= 700, "{f}: {width}");
    }
    let o = volux(&["plot", dir.path().join("nothing").to_str().unwrap()]);
    assert!(
        !o.status.success() && text(&o).contains("nothing"),
        "{}",
        text(&o)
    );
    // Two runs (here the same one twice) compare score by score; that needs --out.
    let o = volux(&["plot", run_s, run_s]);
    assert!(
        !o.status.success() && text(&o).contains("--out"),
        "{}",
        text(&o)
    );
    let compare = dir.path().join("compare");
    let o = volux(&["plot", run_s, run_s, "--out", compare.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(compare.join("compare-minutes.png").is_file());

    // Sampling from the run folder takes its newest checkpoint (written into the run folder,
    // where the report below finds it).
    let samples = run.join("samples");
    let o = volux(&[
        "sample",
        "--checkpoint",
        run_s,
        "--seeds",
        "0-1",
        "--yaw=-20,20",
        "--rotate-light",
        "3",
        "--rotate-camera",
        "3",
        "--interpolate",
        "0,1,3",
        "--out",
        samples.to_str().unwrap(),
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    for f in [
        "layers-sunrise.png",
        "views-sunrise.png",
        "rotate-light.gif",
        "rotate-light.mp4",
        "rotate-camera.gif",
        "interpolate-0-1.png",
        "interpolate-0-1.gif",
        "interpolate-0-1.mp4",
        "exr/seed1-sunrise-specular.exr",
    ] {
        assert!(samples.join(f).is_file(), "{f} missing: {t}");
    }

    // The measurements, on three latents in batches of two (and on the synthetic heads), in
    // the run folder, where the report below finds them.
    let eval = run.join("eval");
    let o = volux(&[
        "eval",
        "--checkpoint",
        run_s,
        "--samples",
        "3",
        "--batch",
        "2",
        "--out",
        eval.to_str().unwrap(),
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    for heading in [
        "Multi-view consistency",
        "Relighting consistency",
        "Geometry",
        "Sliced Wasserstein",
    ] {
        assert!(t.contains(heading), "{heading} missing: {t}");
    }
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(eval.join("eval.json")).unwrap()).unwrap();
    assert_eq!(report["samples"], 3);
    assert_eq!(report["multiview"].as_array().unwrap().len(), 4);
    assert!(
        report["multiview"][0]["data"]["consistent"]
            .as_f64()
            .unwrap()
            > 0.5,
        "{report}"
    );
    assert_eq!(report["environments"].as_array().unwrap().len(), 3);
    assert_eq!(report["swd"][1]["layer"], "normals");
    for f in [
        "multiview",
        "relighting",
        "rotating-light",
        "multiview-data",
        "rotating-light-data",
    ] {
        assert!(eval.join(format!("{f}.png")).is_file(), "{f} missing: {t}");
    }
    // The run's page: self-contained, and loaded by a real browser with every image decoded
    // and no script error.
    let o = volux(&["report", run_s]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    let page = run.join("report.html");
    let html = std::fs::read_to_string(&page).unwrap();
    for part in [
        "<h2>Curves</h2>",
        "<h2>Latest light evaluation</h2>",
        "<h2>Sample grids over training</h2>",
        "<h2>Samples</h2>",
        "<h2>Evaluation</h2>",
        "Sliced Wasserstein",
        "<h2>Config</h2>",
        "data:video/mp4;base64,",
        "data:image/gif;base64,",
    ] {
        assert!(html.contains(part), "{part} missing from the page");
    }
    assert!(!html.contains("src=\"http") && !html.contains("src=\"file"));
    let images = html.matches("<img ").count();
    assert!(images >= 8, "{images} images");
    if let Some(dom) = headless_dom(&page) {
        assert!(
            dom.contains(&format!("data-images=\"{images}/{images}\"")),
            "not every image decoded: {}",
            &dom[dom.find("<body").unwrap_or(0)..][..200.min(dom.len())]
        );
        assert!(dom.contains("data-errors=\"0\""), "script errors");
    }
    let o = volux(&["report", dir.path().to_str().unwrap()]);
    assert!(
        !o.status.success() && text(&o).contains("not a run folder"),
        "{}",
        text(&o)
    );
    let bad = volux(&["eval", "--checkpoint", run_s, "--yaw", "0"]);
    assert!(
        !bad.status.success() && text(&bad).contains("--yaw 0"),
        "{}",
        text(&bad)
    );

    // A new run into the folder of this one is refused (nothing of it is lost).
    let o = volux(&["train", "--config", config, "--out", run_s, "--steps", "1"]);
    let t = text(&o);
    assert!(!o.status.success());
    assert!(t.contains("--resume") && t.contains("--force"), "{t}");
    // A resume with a changed model is refused, naming both.
    std::fs::write(
        dir.path().join("tiny.toml"),
        tiny.replace("importance = 2", "importance = 5"),
    )
    .unwrap();
    let o = volux(&["train", "--config", config, "--out", run_s, "--resume"]);
    let t = text(&o);
    assert!(!o.status.success());
    assert!(
        t.contains("importance = 2") && t.contains("importance = 5"),
        "{t}"
    );
    // A typo names the file and the key.
    std::fs::write(
        dir.path().join("tiny.toml"),
        tiny.replace("batch = 2", "bacth = 2"),
    )
    .unwrap();
    let o = volux(&["train", "--config", config, "--out", run_s]);
    let t = text(&o);
    assert!(!o.status.success());
    assert!(t.contains("tiny.toml") && t.contains("bacth"), "{t}");
}

#[test]
fn train_bench_writes_a_per_phase_table_for_stage_2() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("tiny.toml");
    std::fs::write(&config, TINY_TRAINING).unwrap();
    let table = dir.path().join("bench/stage2.md");
    let o = volux(&[
        "train",
        "bench",
        "--config",
        config.to_str().unwrap(),
        "--stage",
        "2",
        "--steps",
        "1",
        "--gemm-side",
        "128",
        "--out",
        table.to_str().unwrap(),
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    let written = std::fs::read_to_string(&table).unwrap();
    for row in [
        "mapping",
        "NeIIF field + normals",
        "relighting net",
        "discriminators on fakes + pullbacks",
        "generator backward + discriminator step (side by side)",
        "discriminator Adam",
        "whole step",
        "matmul peak",
        "Each discriminator alone",
        "D_P (relit vs photo)",
    ] {
        assert!(written.contains(row), "{row} missing:\n{written}");
    }
    assert!(t.contains("D_S (relit, D, S)"), "{t}");
    let bad = volux(&[
        "train",
        "bench",
        "--config",
        config.to_str().unwrap(),
        "--stage",
        "3",
    ]);
    assert!(!bad.status.success() && text(&bad).contains("--stage"));
}

#[test]
fn the_shipped_model_samples_by_name_from_any_folder() {
    let dir = tempfile::tempdir().unwrap();
    let run = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_volux"))
            .args(args)
            .current_dir(dir.path())
            .output()
            .expect("run volux")
    };
    let o = run(&[
        "sample",
        "--checkpoint",
        "quickstart",
        "--seeds",
        "0-1",
        "--rotate-light",
        "3",
        "--video",
        "mp4",
        "--fps",
        "6",
        "--out",
        "out",
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("assets/models/quickstart"), "{t}");
    assert!(
        t.contains("rotate-light.mp4 (3 frames, 0.5 s at 6 fps)"),
        "{t}"
    );
    assert!(!dir.path().join("out/rotate-light.gif").exists());
    let o = run(&["sample", "--checkpoint", "quickstart", "--fps", "0"]);
    assert!(
        !o.status.success() && text(&o).contains("--fps 0"),
        "{}",
        text(&o)
    );
    // Sizes are bounded before any work: frames, cameras, and an --out that is a file.
    for (args, says) in [
        (&["--rotate-light", "100000"][..], "at most 1024 frames"),
        (&["--rotate-camera", "1025"][..], "--rotate-camera 1025"),
        (
            &["--yaw", "0,1,2,3,4,5,6,7,8", "--pitch", "0,1,2,3,4,5,6,7"][..],
            "72 cameras",
        ),
        (&["--out", "out/layers-sunrise.png"][..], "is a file"),
    ] {
        let mut all = vec!["sample", "--checkpoint", "quickstart"];
        all.extend_from_slice(args);
        let o = run(&all);
        assert!(
            !o.status.success() && text(&o).contains(says),
            "{args:?}: {}",
            text(&o)
        );
    }
    assert!(dir.path().join("out/layers-sunrise.png").is_file(), "{t}");
    assert!(
        dir.path()
            .join("out/exr/seed1-sunrise-normals.exr")
            .is_file(),
        "{t}"
    );
    // Its head as a mesh, in both formats; bad values are named.
    let o = run(&[
        "export",
        "mesh",
        "--checkpoint",
        "quickstart",
        "--seed",
        "3",
        "--resolution",
        "32",
        "--out",
        "head.ply",
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("triangles") && t.contains("frontal"), "{t}");
    assert!(t.contains("left out"), "{t}");
    let ply = std::fs::read(dir.path().join("head.ply")).unwrap();
    assert!(ply.starts_with(b"ply\nformat binary_little_endian 1.0\n"));
    let o = run(&[
        "export",
        "mesh",
        "--checkpoint",
        "quickstart",
        "--resolution",
        "24",
        "--threshold",
        "5",
        "--out",
        "head.obj",
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("iso-level 5.0000 (given"), "{t}");
    let obj = std::fs::read_to_string(dir.path().join("head.obj")).unwrap();
    assert!(obj.lines().any(|l| l.starts_with("vn ")));
    for (flag, value, expected) in [
        ("--resolution", "8", "--resolution 8"),
        ("--threshold", "-1", "--threshold -1"),
        ("--min-piece", "-0.1", "--min-piece -0.1"),
        ("--min-piece", "1.5", "--min-piece 1.5"),
        ("--out", "head.stl", "head.stl"),
    ] {
        let mut args = vec![
            "export",
            "mesh",
            "--checkpoint",
            "quickstart",
            "--out",
            "x.ply",
        ];
        if flag == "--out" {
            args[5] = value;
        } else {
            args.extend([flag, value]);
        }
        let o = run(&args);
        let t = text(&o);
        assert!(
            !o.status.success() && t.contains(expected),
            "{flag} {value}: {t}"
        );
    }
    // A name that is neither a folder nor a shipped model lists the shipped ones.
    let o = run(&["sample", "--checkpoint", "quickstrat", "--out", "out"]);
    let t = text(&o);
    assert!(!o.status.success());
    assert!(
        t.contains("quickstrat") && t.contains("shipped: quickstart"),
        "{t}"
    );
}

/// Photos alone, end to end: held-out synthetic heads (never in the estimator's training),
/// photographed with backgrounds, exposure, noise and JPEG, go through
/// `volux data pseudo-gt` (the shipped estimator), `volux data build` and `volux train`.
#[test]
fn photos_alone_become_a_dataset_that_builds_and_trains() {
    use volux_pseudo_gt::augmentation::AugmentationRanges;
    use volux_pseudo_gt::synthetic_pairs::collection_lights;
    use volux_pseudo_gt::training::held_out_inputs;

    let dir = tempfile::tempdir().unwrap();
    let lights = collection_lights().unwrap();
    let side = 64;
    let heads = held_out_inputs(&lights, 4, 11, side, 1, &AugmentationRanges::default()).unwrap();
    let photos = dir.path().join("photos");
    std::fs::create_dir(&photos).unwrap();
    for (i, h) in heads.iter().enumerate() {
        let bytes: Vec<[u8; 3]> = h
            .photo
            .iter()
            .map(|t| t.map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8))
            .collect();
        volux_envmap::io::save_png(&photos.join(format!("face{i}.png")), side, side, &bytes)
            .unwrap();
    }
    let faces = dir.path().join("faces");
    let o = volux(&[
        "data",
        "pseudo-gt",
        "--photos",
        photos.to_str().unwrap(),
        "--out",
        faces.to_str().unwrap(),
        "--resolution",
        "64",
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("4 photos at 64x64 (4 made, 0 kept"), "{t}");
    assert!(faces.join("contact_sheet.png").is_file());

    // The estimated normals are close to the exact ones where the head is.
    let dataset = volux_data::folder_dataset::FolderDataset::open(&faces).unwrap();
    let (mut angle, mut weight) = (0.0f64, 0.0f64);
    for (i, h) in heads.iter().enumerate() {
        let sample = dataset.load(i).unwrap();
        for ((n, e), &m) in h.normals.iter().zip(&sample.image.normals).zip(&h.mask) {
            let cos: f32 = (0..3).map(|c| n[c] * e[c]).sum();
            angle += f64::from(m) * f64::from(cos.clamp(-1.0, 1.0).acos()).to_degrees();
            weight += f64::from(m);
        }
    }
    let mean = angle / weight;
    assert!(mean < 30.0, "mean normal angle {mean:.1} degrees");

    let config = dir.path().join("photos.toml");
    let tiny = TINY_TRAINING.replace(
        "[data.lighting]",
        "[data.source]\nkind = \"folder\"\npath = \"faces\"\n\n\
         [data.cache]\ndir = \"examples\"\nexamples = 4\nshard_size = 2\n\n[data.lighting]",
    );
    std::fs::write(&config, tiny).unwrap();
    let config = config.to_str().unwrap();
    let built = volux(&["data", "build", "--config", config]);
    assert!(built.status.success(), "{}", text(&built));
    assert!(
        text(&built).contains("4 examples in 2 shards"),
        "{}",
        text(&built)
    );
    let run = dir.path().join("run");
    let trained = volux(&[
        "train",
        "--config",
        config,
        "--out",
        run.to_str().unwrap(),
        "--steps",
        "4",
    ]);
    let t = text(&trained);
    assert!(trained.status.success(), "{t}");
    assert!(t.contains("step limit reached: step 4"), "{t}");
}

#[test]
fn pseudo_gt_trains_and_evaluates_an_estimator() {
    let dir = tempfile::tempdir().unwrap();
    let est = dir.path().join("estimator");
    let o = volux(&[
        "data",
        "pseudo-gt",
        "--train",
        "--out",
        est.to_str().unwrap(),
        "--steps",
        "2",
        "--pool",
        "4",
        "--batch",
        "2",
        "--held-out",
        "2",
        "--eval-every",
        "1",
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("step      2") && t.contains("(2 steps"), "{t}");
    assert!(est.join("estimator.bpk").is_file());
    assert_eq!(
        std::fs::read_to_string(est.join("log.jsonl"))
            .unwrap()
            .lines()
            .count(),
        2
    );
    // Into a folder that does not exist yet: it is made.
    let table = dir.path().join("tables/accuracy.md");
    let o = volux(&[
        "data",
        "pseudo-gt",
        "--evaluate",
        "--estimator",
        est.to_str().unwrap(),
        "--out",
        table.to_str().unwrap(),
        "--sides",
        "16,32",
        "--held-out",
        "2",
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    let written = std::fs::read_to_string(&table).unwrap();
    assert!(
        written.contains("| 16 | augmented |") && written.contains("| 32 | clean |"),
        "{written}"
    );
    assert!(dir.path().join("tables/accuracy.png").is_file());
    let bad = volux(&[
        "data",
        "pseudo-gt",
        "--evaluate",
        "--out",
        table.to_str().unwrap(),
        "--sides",
        "4",
    ]);
    assert!(
        !bad.status.success() && text(&bad).contains("--sides"),
        "{}",
        text(&bad)
    );
    let bad = volux(&[
        "data",
        "pseudo-gt",
        "--train",
        "--out",
        est.to_str().unwrap(),
        "--batch",
        "0",
    ]);
    assert!(
        !bad.status.success() && text(&bad).contains("batch = 0"),
        "{}",
        text(&bad)
    );
}

/// An `--out` that is a file, or a size far beyond the limits, is refused before any work with
/// a message naming the flag (it used to say only "File exists", after the work, or to run
/// until memory ran out).
#[test]
fn outputs_that_are_files_and_huge_sizes_are_refused_before_work() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("a_file");
    std::fs::write(&file, "not a folder").unwrap();
    let f = file.to_str().unwrap();
    let hdri = asset("city.exr");
    for (args, says) in [
        (
            vec!["eval", "--checkpoint", "quickstart", "--out", f],
            "is a file",
        ),
        (
            vec!["data", "heads", "--seeds", "0", "--out", f],
            "is a file",
        ),
        (
            vec!["envmap", "preconvolve", &hdri, "--out", f],
            "is a file",
        ),
        (
            vec!["model", "bench", "--batch", "0"],
            "--batch 0: give 1 to 64",
        ),
        (
            vec!["model", "bench", "--batch", "100000"],
            "--batch 100000",
        ),
    ] {
        let o = volux(&args);
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{args:?}: {t}");
        assert!(t.contains(says), "{args:?}: {t}");
    }
}

/// `--steps 0` is refused (it wrote an untrained checkpoint and exited 0), and config values
/// beyond their limits are named with the file before any work: a prefetch of 10^12 aborted
/// on allocation, an R1 gamma of 1e308 overflowed f32 and skipped every step as non-finite.
#[test]
fn train_refuses_zero_steps_and_config_values_beyond_their_limits() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let run_s = run.to_str().unwrap();
    let o = volux(&[
        "train",
        "--config",
        "configs/quickstart.toml",
        "--out",
        run_s,
        "--steps",
        "0",
    ]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("--steps 0: give at least 1"), "{t}");
    assert!(!run.exists(), "nothing written");
    for (from, to, says) in [
        (
            "batch = 2",
            "batch = 2\nprefetch = 1000000000000",
            "train.prefetch = 1000000000000 must be in 0..=16",
        ),
        (
            "batch = 2",
            "batch = 2\nr1_gamma = 1e308",
            "train.r1_gamma = 1e308 must",
        ),
        (
            "sphere_prior = 10.0",
            "sphere_prior = 1e308",
            "model.sphere_prior = 1e308 must",
        ),
    ] {
        let config = dir.path().join("hostile.toml");
        std::fs::write(&config, TINY_TRAINING.replace(from, to)).unwrap();
        let o = volux(&[
            "train",
            "--config",
            config.to_str().unwrap(),
            "--out",
            run_s,
            "--steps",
            "1",
        ]);
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{to}: {t}");
        assert!(t.contains("hostile.toml") && t.contains(says), "{to}: {t}");
        assert!(!run.exists(), "{to}: nothing written");
    }
}

/// `volux report` of a run folder that does not exist fails without creating it (the output
/// file's folder was made first, so a mistyped name left an empty folder behind).
#[test]
fn a_report_of_a_missing_run_folder_creates_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("no_such_run");
    let o = volux(&["report", missing.to_str().unwrap()]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("not a run folder"), "{t}");
    assert!(!missing.exists(), "{t}");
}
