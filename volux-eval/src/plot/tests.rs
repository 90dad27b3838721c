use super::*;

/// A log of two training groups and two evaluations, one training value NaN (`null`).
const LOG: &str = r#"{"step":0,"images":0,"kimg":0.0,"minutes":0.0,"eval_seconds":2.0,"eval":{"swd_albedo":90.0,"swd_albedo_floor":20.0,"multiview_albedo_psnr":20.0,"multiview_albedo_psnr_data":31.0}}
{"step":10,"images":40,"kimg":0.04,"minutes":0.5,"stage":1,"images_per_sec":1.5,"losses":{"G_total":0.7,"D_total":1.3,"R1_photo":null}}
{"step":20,"images":80,"kimg":0.08,"minutes":1.0,"stage":1,"images_per_sec":1.7,"losses":{"G_total":0.9,"D_total":1.1,"R1_photo":0.2,"density_reg":0.05}}
{"step":20,"images":80,"kimg":0.08,"minutes":1.1,"eval_seconds":2.0,"eval":{"swd_albedo":60.0,"swd_albedo_floor":20.0,"multiview_albedo_psnr":22.0,"multiview_albedo_psnr_data":31.0}}
"#;

fn write_log(text: &str) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("metrics.jsonl");
    std::fs::write(&path, text).unwrap();
    (dir, path)
}

#[test]
fn a_log_parses_into_training_and_evaluation_points() {
    let (_dir, path) = write_log(LOG);
    let m = RunMetrics::read(&path).unwrap();
    assert_eq!(m.training.len(), 2);
    assert_eq!(m.evals.len(), 2);
    assert!(m.has_minutes());
    // NaN is logged as null and left out, not read as 0.
    assert!(!m.training[0].values.contains_key("R1_photo"));
    assert_eq!(m.training[1].values["R1_photo"], 0.2);
    assert_eq!(m.training[1].values["images_per_sec"], 1.7);
    assert_eq!(m.evals[1].minutes, Some(1.1));
}

#[test]
fn panels_pair_each_score_with_its_reference_in_one_colour() {
    let (_dir, path) = write_log(LOG);
    let m = RunMetrics::read(&path).unwrap();
    let by_kimg = panels(&m, XAxis::Kimg);
    let swd = &by_kimg[0];
    assert!(swd.title.starts_with("Sample quality"));
    assert_eq!(swd.curves.len(), 2);
    assert_eq!(swd.curves[0].points, vec![(0.0, 90.0), (0.08, 60.0)]);
    assert!(swd.curves[1].dashed && swd.curves[1].name == "swd_albedo (floor)");
    assert_eq!(swd.curves[0].colour, swd.curves[1].colour);
    // Panels without data (consistent fraction, angles) are left out.
    let titles: Vec<&str> = by_kimg.iter().map(|p| p.title.as_str()).collect();
    assert_eq!(titles.len(), 6, "{titles:?}");
    let by_minutes = panels(&m, XAxis::Minutes);
    let g = by_minutes
        .iter()
        .find(|p| p.title == "Generator losses")
        .unwrap();
    assert_eq!(g.curves[0].points, vec![(0.5, 0.7), (1.0, 0.9)]);
    let r1 = by_minutes
        .iter()
        .find(|p| p.title.starts_with("Regularisers"))
        .unwrap();
    assert_eq!(r1.curves[0].points, vec![(1.0, 0.2)]);
    let density = r1.curves.iter().find(|c| c.name == "density_reg").unwrap();
    assert_eq!(density.points, vec![(1.0, 0.05)]);
}

#[test]
fn bad_lines_are_named_by_file_and_line() {
    for (text, wanted) in [
        (
            "{\"kimg\":0.0,\"losses\":{}}\nnot json\n",
            "line 2: not a metrics line",
        ),
        ("{\"step\":1,\"losses\":{}}\n", "line 1: no finite \"kimg\""),
        ("{\"kimg\":1.0}\n", "line 1: neither"),
        (
            "{\"kimg\":1.0,\"eval\":3}\n",
            "line 1: \"eval\" is not an object",
        ),
        ("\n", "holds no metrics lines"),
    ] {
        let (_dir, path) = write_log(text);
        let e = RunMetrics::read(&path).unwrap_err().to_string();
        assert!(e.contains("metrics.jsonl") && e.contains(wanted), "{e}");
    }
    let e = RunMetrics::read(Path::new("no/such/metrics.jsonl")).unwrap_err();
    assert!(e.to_string().contains("no/such/metrics.jsonl"), "{e}");
    assert!(
        std::error::Error::source(&e).is_some(),
        "the OS error is kept"
    );
}

#[test]
fn ranges_are_never_empty_or_infinite() {
    assert_eq!(padded(1.0, 1.0), (0.5, 1.5));
    assert_eq!(padded(f64::INFINITY, f64::NEG_INFINITY), (0.0, 1.0));
    let (lo, hi) = padded(1e6, 1e6);
    assert!(lo < 1e6 && hi > 1e6);
    let (lo, hi) = padded(0.0, 10.0);
    assert!((lo + 0.5).abs() < 1e-12 && (hi - 10.5).abs() < 1e-12);
}

/// Pixels of exactly `colour`.
fn count(pixels: &[[u8; 3]], colour: [u8; 3]) -> usize {
    pixels.iter().filter(|&&p| p == colour).count()
}

#[test]
fn a_rendered_plot_shows_its_curves_and_its_text() {
    let curve = |colour, dashed| Curve {
        name: "x".into(),
        points: (0..50).map(|i| (i as f64, (i * i) as f64)).collect(),
        dashed,
        colour,
    };
    let panel = |curves| Panel {
        title: "test".into(),
        curves,
    };
    let (w, h, pixels) = render(
        "a title",
        &[panel(vec![curve(0, false)]), panel(vec![curve(1, true)])],
        XAxis::Kimg,
    )
    .unwrap();
    assert_eq!((w, h), (2 * PANEL_WIDTH, PANEL_HEIGHT + 40));
    assert_eq!(pixels.len(), w * h);
    let rgb = |i| {
        let c = Palette99::pick(i).to_rgba();
        [c.0, c.1, c.2]
    };
    let (solid, dashed) = (count(&pixels, rgb(0)), count(&pixels, rgb(1)));
    // A 2-pixel line across most of a panel, and a dashed one with about 60% of it.
    assert!(solid > 600, "{solid} pixels of the solid curve");
    assert!(
        dashed > 300 && dashed < solid,
        "{dashed} dashed, {solid} solid"
    );
    // Text is anti-aliased: grey pixels exist in the header, which holds only the title.
    let header_grey = pixels[..w * 40]
        .iter()
        .filter(|p| p[0] == p[1] && p[1] == p[2] && p[0] > 30 && p[0] < 220)
        .count();
    assert!(header_grey > 20, "{header_grey} grey title pixels");
}

#[test]
fn a_run_folder_gets_both_plots() {
    let (dir, _) = write_log(LOG);
    let out = dir.path().join("plots");
    let written = plot_run(dir.path(), &out, "run").unwrap();
    assert_eq!(
        written,
        vec![out.join("curves-kimg.png"), out.join("curves-minutes.png")]
    );
    for p in &written {
        assert!(std::fs::metadata(p).unwrap().len() > 1000);
    }
    // A log without the run clock gets the images axis only.
    let old = LOG.replace("\"minutes\":", "\"old_minutes\":");
    let (dir, _) = write_log(&old);
    let written = plot_run(dir.path(), &dir.path().join("p"), "run").unwrap();
    assert_eq!(written.len(), 1);
}

#[test]
fn runs_compare_score_by_score_with_the_first_runs_reference() {
    let (_a, path_a) = write_log(LOG);
    let (_b, path_b) = write_log(&LOG.replace("\"swd_albedo\":60.0", "\"swd_albedo\":40.0"));
    let runs = vec![
        ("a".to_string(), RunMetrics::read(&path_a).unwrap()),
        ("b".to_string(), RunMetrics::read(&path_b).unwrap()),
    ];
    let by_minutes = compare_panels(&runs, XAxis::Minutes);
    let titles: Vec<&str> = by_minutes.iter().map(|p| p.title.as_str()).collect();
    assert_eq!(
        titles,
        ["multiview_albedo_psnr", "swd_albedo", "images_per_sec"]
    );
    let swd = &by_minutes[1];
    let names: Vec<&str> = swd.curves.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["a", "b", "floor"]);
    assert_eq!(swd.curves[0].points, vec![(0.0, 90.0), (1.1, 60.0)]);
    assert_eq!(swd.curves[1].points, vec![(0.0, 90.0), (1.1, 40.0)]);
    assert!(swd.curves[2].dashed && swd.curves[2].colour == 2);
    assert!(!swd.curves[0].dashed && swd.curves[0].colour != swd.curves[1].colour);

    // Through the files: one image per axis; a run without evaluations is named.
    let out = tempfile::tempdir().unwrap();
    let folders = [
        ("a".to_string(), path_a.parent().unwrap().to_path_buf()),
        ("b".to_string(), path_b.parent().unwrap().to_path_buf()),
    ];
    let written = plot_runs(&folders, out.path()).unwrap();
    assert_eq!(written.len(), 2);
    assert!(written.iter().all(|p| p.is_file()));
    let (_c, path_c) = write_log(
        &LOG.lines()
            .filter(|l| !l.contains("\"eval\""))
            .collect::<Vec<_>>()
            .join("\n"),
    );
    let no_evals = [
        folders[0].clone(),
        ("c".to_string(), path_c.parent().unwrap().to_path_buf()),
    ];
    let e = plot_runs(&no_evals, out.path()).unwrap_err().to_string();
    assert!(e.contains("eval_kimg"), "{e}");
}
