//! Tests of folder datasets on generated spheres: round trips, every bad input, relighting.
use volux_model::pose::Pose;

use super::*;
use crate::relighting::{DEFAULT_SPECULAR_WEIGHTS, relight};
use volux_envmap::EnvMapError;
use volux_envmap::direction::{self, Dir};
use volux_envmap::{EnvMap, LightMap, PreconvolveOptions, preconvolve};
use volux_model::ray_sampling::{CameraConfig, camera_basis, camera_rays};

const W: usize = 24;
const H: usize = 20;
const POSES: [(&str, Pose); 3] = [
    ("a", Pose::new(0.0, 0.0)),
    ("b", Pose::new(0.4, -0.15)),
    ("c", Pose::new(-0.7, 0.25)),
];

/// A sphere of radius 0.3 at `pose`, `W x H`, by ray casting: camera-space normals (zero
/// outside), a mask with a soft inner edge in steps of 1/255, albedo and photo gradients.
fn sphere(stem: &str, pose: Pose) -> FolderSample {
    let camera = CameraConfig::new();
    let [right, up, back] = camera_basis(&camera, pose);
    let (origins, dirs) = camera_rays(&camera, pose, W, H);
    let mut image = IntrinsicImage {
        width: W,
        height: H,
        albedo: Vec::new(),
        normals: Vec::new(),
        mask: Vec::new(),
        pose,
    };
    let mut photo = Vec::new();
    for (i, (o, d)) in origins.iter().zip(&dirs).enumerate() {
        let (x, y) = ((i % W) as f32, (i / W) as f32);
        let b = direction::dot(*o, *d);
        let disc = b * b - (direction::dot(*o, *o) - 0.09);
        let m = ((disc / 0.02).clamp(0.0, 1.0) * 255.0).round() as f32 / 255.0;
        if m > 0.0 {
            let t = -b - disc.sqrt();
            let p: Dir = std::array::from_fn(|k| (o[k] + t * d[k]) / 0.3);
            image
                .normals
                .push([right, up, back].map(|a| direction::dot(p, a) as f32));
        } else {
            image.normals.push([0.0; 3]);
        }
        image.mask.push(m);
        image.albedo.push([
            x / (W - 1) as f32,
            y / (H - 1) as f32,
            0.25 + 0.5 * (x + y) / (W + H) as f32,
        ]);
        let k = ((x * 7.0 + y * 5.0) as u32 % 256) as f32;
        photo.push([k / 255.0, m, (255.0 - k) / 255.0]);
    }
    FolderSample {
        stem: stem.into(),
        photo,
        image,
        renormalised: 0,
        degenerate: 0,
    }
}

fn spheres() -> Vec<FolderSample> {
    POSES.iter().map(|(s, p)| sphere(s, *p)).collect()
}

/// A dataset of the three spheres in a temporary folder; `root` is `dir/faces`.
fn written() -> (tempfile::TempDir, PathBuf, Vec<FolderSample>) {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("faces");
    let samples = spheres();
    write_dataset(&root, &samples).unwrap();
    (dir, root, samples)
}

/// `(n + 1) / 2` in 8 bits, rounded.
fn encode_normal(n: [f32; 3]) -> [u8; 3] {
    n.map(|v| ((v + 1.0) / 2.0 * 255.0).round() as u8)
}

fn save_png_normals(path: &Path, normals: &[[f32; 3]]) {
    let px: Vec<[u8; 3]> = normals.iter().map(|n| encode_normal(*n)).collect();
    io::save_png(path, W, H, &px).unwrap();
}

fn open_err(root: &Path) -> FolderError {
    FolderDataset::open(root).unwrap_err()
}

#[test]
fn a_written_dataset_opens_and_loads_back() {
    let (_dir, root, samples) = written();
    // Sample c has no mask: it comes from its normals.
    fs::remove_file(root.join("masks/c.png")).unwrap();
    let ds = FolderDataset::open(&root).unwrap();
    assert_eq!(ds.len(), 3);
    assert!(!ds.is_empty());
    assert_eq!(ds.stems().collect::<Vec<_>>(), ["a", "b", "c"]);
    assert!(ds.ignored().is_empty(), "{:?}", ds.ignored());
    for (i, want) in samples.iter().enumerate() {
        assert_eq!(ds.pose(i), want.image.pose, "poses are written exactly");
        let got = ds.load(i).unwrap();
        assert_eq!(got.stem, want.stem);
        assert_eq!((got.image.width, got.image.height), (W, H));
        assert_eq!(got.image.pose, want.image.pose);
        assert_eq!((got.renormalised, got.degenerate), (0, 0));
        // 8-bit PNG photos and masks of values in steps of 1/255 come back exactly.
        assert_eq!(got.photo, want.photo);
        // EXR albedo is lossless.
        assert_eq!(got.image.albedo, want.image.albedo);
        let want_mask: Vec<f32> = if want.stem == "c" {
            want.image
                .mask
                .iter()
                .map(|&m| f32::from(u8::from(m > 0.0)))
                .collect()
        } else {
            want.image.mask.clone()
        };
        assert_eq!(got.image.mask, want_mask, "{}", want.stem);
        // EXR normals are lossless up to renormalisation (an ulp or two).
        for (g, w) in got.image.normals.iter().zip(&want.image.normals) {
            for k in 0..3 {
                assert!((g[k] - w[k]).abs() < 1e-6, "{g:?} vs {w:?}");
            }
        }
    }
    let foreground = samples[0].image.mask.iter().filter(|&&m| m > 0.0).count();
    let partial = samples[0]
        .image
        .mask
        .iter()
        .filter(|&&m| m > 0.0 && m < 1.0)
        .count();
    assert!(foreground > 100 && partial > 10, "{foreground} {partial}");
}

#[test]
fn png_normals_and_albedo_are_decoded_within_their_quantisation() {
    let (_dir, root, samples) = written();
    for s in &samples {
        let stem = &s.stem;
        fs::remove_file(root.join(format!("normals/{stem}.exr"))).unwrap();
        save_png_normals(&root.join(format!("normals/{stem}.png")), &s.image.normals);
        fs::remove_file(root.join(format!("albedo/{stem}.exr"))).unwrap();
        let srgb: Vec<[u8; 3]> = s
            .image
            .albedo
            .iter()
            .map(|c| c.map(|v| (io::linear_to_srgb(v) * 255.0).round() as u8))
            .collect();
        io::save_png(&root.join(format!("albedo/{stem}.PNG")), W, H, &srgb).unwrap();
    }
    let ds = FolderDataset::open(&root).unwrap();
    let (mut worst_normal, mut worst_angle, mut worst_albedo) = (0f32, 0f64, 0f32);
    for (i, want) in samples.iter().enumerate() {
        let got = ds.load(i).unwrap();
        assert_eq!((got.renormalised, got.degenerate), (0, 0), "{}", want.stem);
        assert_eq!(got.image.mask, want.image.mask);
        for ((g, w), &m) in got
            .image
            .normals
            .iter()
            .zip(&want.image.normals)
            .zip(&want.image.mask)
        {
            if m == 0.0 {
                assert_eq!(*g, [0.0; 3]);
                continue;
            }
            for k in 0..3 {
                worst_normal = worst_normal.max((g[k] - w[k]).abs());
            }
            let cos = direction::dot(g.map(f64::from), w.map(f64::from));
            worst_angle = worst_angle.max(cos.min(1.0).acos());
        }
        for (g, w) in got.image.albedo.iter().zip(&want.image.albedo) {
            for k in 0..3 {
                // Half an 8-bit step in sRGB, at the steepest of the curve's inverse.
                worst_albedo = worst_albedo.max((g[k] - w[k]).abs());
            }
        }
    }
    assert!(worst_normal < 1.0 / 127.0, "component error {worst_normal}");
    assert!(worst_angle < 1.0 / 127.0, "angle error {worst_angle} rad");
    assert!(
        worst_albedo < 0.5 / 255.0 * 2.4 + 1e-6,
        "albedo error {worst_albedo}"
    );
    assert!(
        worst_normal > 0.0 && worst_albedo > 0.0,
        "PNG was read, not EXR"
    );
}

/// The basis of [`UNIT_TOLERANCE`]: how far 8-bit encoding moves unit normals' length.
#[test]
fn eight_bit_quantisation_stays_inside_the_unit_tolerance() {
    let decode = |p: [u8; 3]| p.map(|v| 2.0 * f32::from(v) / 255.0 - 1.0);
    let (mut rounded, mut truncated, mut angle) = (0f32, 0f32, 0f64);
    let count = 200_000;
    for i in 0..count {
        // A Fibonacci sphere: evenly spread unit directions.
        let z = 1.0 - 2.0 * (i as f64 + 0.5) / count as f64;
        let phi = i as f64 * std::f64::consts::PI * (3.0 - 5f64.sqrt());
        let r = (1.0 - z * z).sqrt();
        let n = [r * phi.cos(), r * phi.sin(), z].map(|v| v as f32);
        let d = decode(encode_normal(n));
        rounded = rounded.max((length(d) - 1.0).abs());
        let cos = direction::dot(d.map(f64::from), n.map(f64::from)) / f64::from(length(d));
        angle = angle.max(cos.min(1.0).acos());
        let t = decode(n.map(|v| ((v + 1.0) / 2.0 * 255.0) as u8));
        truncated = truncated.max((length(t) - 1.0).abs());
    }
    eprintln!(
        "8-bit normals: |len - 1| <= {rounded:.5} rounded, {truncated:.5} truncated; \
         angle <= {angle:.5} rad"
    );
    assert!(rounded <= 3f32.sqrt() / 255.0, "{rounded}");
    assert!(
        rounded < UNIT_TOLERANCE / 3.0 && truncated < UNIT_TOLERANCE,
        "{truncated}"
    );
    assert!(angle < 1.0 / 127.0, "{angle}");
    // The zero normal (background grey) is far below the degenerate and mask thresholds.
    let zero = length(decode(encode_normal([0.0; 3])));
    assert!(zero < 0.007, "{zero}");
    assert!(zero < DEGENERATE_LENGTH / 10.0, "{zero}");
}

#[test]
fn without_masks_the_mask_is_where_normals_are_long() {
    let (_dir, root, samples) = written();
    fs::remove_dir_all(root.join("masks")).unwrap();
    // a: PNG normals (grey background), b and c: EXR normals (zero background).
    fs::remove_file(root.join("normals/a.exr")).unwrap();
    save_png_normals(&root.join("normals/a.png"), &samples[0].image.normals);
    let ds = FolderDataset::open(&root).unwrap();
    for (i, want) in samples.iter().enumerate() {
        let got = ds.load(i).unwrap();
        let ones = got.image.mask.iter().filter(|&&m| m == 1.0).count();
        let zeros = got.image.mask.iter().filter(|&&m| m == 0.0).count();
        let foreground = want.image.mask.iter().filter(|&&m| m > 0.0).count();
        assert_eq!(
            (ones, zeros),
            (foreground, W * H - foreground),
            "{}",
            want.stem
        );
        for (g, w) in got.image.mask.iter().zip(&want.image.mask) {
            assert_eq!(*g > 0.0, *w > 0.0);
        }
        assert_eq!((got.renormalised, got.degenerate), (0, 0));
    }
}

#[test]
fn non_unit_normals_are_renormalised_and_counted() {
    let (_dir, root, samples) = written();
    let want = &samples[0];
    let fg: Vec<usize> = (0..W * H).filter(|&i| want.image.mask[i] > 0.0).collect();
    let partial = *fg.iter().find(|&&i| want.image.mask[i] < 1.0).unwrap();
    let bg = (0..W * H).find(|&i| want.image.mask[i] == 0.0).unwrap();
    let mut normals = want.image.normals.clone();
    let (long, slightly, short, zero) = (fg[3], fg[10], fg[20], fg[30]);
    normals[long] = normals[long].map(|v| 2.0 * v);
    normals[partial] = normals[partial].map(|v| 0.3 * v);
    normals[slightly] = normals[slightly].map(|v| 1.01 * v);
    normals[short] = normals[short].map(|v| 0.05 * v);
    normals[zero] = [0.0; 3];
    normals[bg] = [0.0, 3.0, 0.0];
    io::save_exr(&root.join("normals/a.exr"), W, H, &normals).unwrap();
    let got = FolderDataset::open(&root).unwrap().load(0).unwrap();
    assert_eq!((got.renormalised, got.degenerate), (2, 2));
    for i in [long, partial, slightly] {
        for k in 0..3 {
            let (g, w) = (got.image.normals[i][k], want.image.normals[i][k]);
            assert!((g - w).abs() < 1e-6, "pixel {i}: {g} vs {w}");
        }
    }
    assert_eq!(got.image.normals[short], [0.0, 0.0, 1.0]);
    assert_eq!(got.image.normals[zero], [0.0, 0.0, 1.0]);
    assert_eq!(
        got.image.normals[bg], [0.0; 3],
        "background normals are zero"
    );
    for &i in &fg {
        assert!((length(got.image.normals[i]) - 1.0).abs() < 1e-6);
    }
}

#[test]
fn a_loaded_sample_relights_under_a_constant_environment() {
    let (_dir, root, _) = written();
    let ds = FolderDataset::open(&root).unwrap();
    let c = [0.8f32, 1.1, 1.6];
    let set = preconvolve(
        &EnvMap::constant(16, c).unwrap(),
        &PreconvolveOptions::default(),
    )
    .unwrap();
    let lights: Vec<&LightMap> = set.maps().iter().collect();
    let w_sum: f32 = DEFAULT_SPECULAR_WEIGHTS.iter().sum();
    for i in 0..ds.len() {
        let sample = ds.load(i).unwrap();
        let out = relight(
            &sample.image,
            &lights,
            &DEFAULT_SPECULAR_WEIGHTS,
            0.7,
            &CameraConfig::new(),
            [0.1; 3],
        )
        .unwrap();
        assert_eq!((out.renormalised, out.degenerate), (0, 0));
        for (p, &m) in sample.image.mask.iter().enumerate() {
            for (k, ck) in c.iter().enumerate() {
                let (d, s) = (out.diffuse[p][k], out.specular[p][k]);
                assert!((d - m * ck).abs() < 1e-3 * ck, "pixel {p}: D {d}");
                assert!((s - m * w_sum * ck).abs() < 1e-3 * ck, "pixel {p}: S {s}");
            }
            if m == 0.0 {
                assert_eq!(out.relit[p], [0.1; 3]);
            }
        }
    }
}

#[test]
fn unknown_and_hidden_files_are_ignored_and_extensions_are_case_insensitive() {
    let (_dir, root, _) = written();
    fs::rename(root.join("photos/b.png"), root.join("photos/b.PNG")).unwrap();
    fs::write(root.join("photos/notes.txt"), "hello").unwrap();
    fs::write(root.join("photos/.DS_Store"), "x").unwrap();
    fs::write(root.join("normals/a.jpg"), "a lossy normal map").unwrap();
    fs::create_dir(root.join("albedo/old")).unwrap();
    fs::write(root.join("README.md"), "outside the layout's folders").unwrap();
    let ds = FolderDataset::open(&root).unwrap();
    assert_eq!(ds.stems().collect::<Vec<_>>(), ["a", "b", "c"]);
    let ignored: Vec<PathBuf> = ds
        .ignored()
        .iter()
        .map(|p| p.strip_prefix(&root).unwrap().to_path_buf())
        .collect();
    let want: Vec<PathBuf> = ["photos/notes.txt", "albedo/old", "normals/a.jpg"]
        .iter()
        .map(PathBuf::from)
        .collect();
    assert_eq!(ignored, want);
    assert_eq!(ds.load(1).unwrap().stem, "b");
}

#[test]
fn missing_counterparts_are_listed_per_folder() {
    let (_dir, root, _) = written();
    fs::remove_file(root.join("albedo/a.exr")).unwrap();
    fs::remove_file(root.join("albedo/c.exr")).unwrap();
    fs::remove_file(root.join("normals/b.exr")).unwrap();
    fs::write(root.join("albedo/zed.png"), "").unwrap();
    fs::write(root.join("masks/stray.png"), "").unwrap();
    fs::write(root.join("masks/zed.jpg"), "").unwrap();
    let e = open_err(&root);
    assert!(matches!(e, FolderError::Unmatched { .. }), "{e:?}");
    assert_eq!(
        e.to_string(),
        format!(
            "{}: files do not match up by name: \
             albedo/ has no .png/.jpg/.jpeg/.exr file for: a, c; \
             normals/ has no .png/.exr file for: b; \
             albedo/ has files with no photo: zed; \
             masks/ has files with no photo: stray, zed",
            root.display()
        )
    );
}

#[test]
fn long_lists_are_cut_short() {
    let names: Vec<String> = (0..25).map(|i| format!("n{i:02}")).collect();
    let s = name_list(&names);
    assert!(
        s.starts_with("n00, n01, ") && s.ends_with("n19 and 5 more"),
        "{s}"
    );
}

#[test]
fn two_files_with_one_name_are_an_error_naming_both() {
    let (_dir, root, _) = written();
    fs::copy(root.join("photos/b.png"), root.join("photos/b.jpg")).unwrap();
    let e = open_err(&root);
    assert!(matches!(e, FolderError::DuplicateNames { ref pairs } if pairs.len() == 1));
    let msg = e.to_string();
    assert!(
        msg.contains("photos/b.jpg and ") && msg.ends_with("photos/b.png"),
        "{msg}"
    );
}

#[test]
fn layers_of_another_size_are_errors_naming_stem_layer_and_sizes() {
    let (_dir, root, _) = written();
    io::save_exr(&root.join("albedo/b.exr"), 10, 12, &[[0.5; 3]; 120]).unwrap();
    io::save_png(
        &root.join("masks/c.png"),
        W,
        H - 1,
        &[[255; 3]; W * (H - 1)],
    )
    .unwrap();
    let ds = FolderDataset::open(&root).unwrap();
    let e = ds.load(1).unwrap_err();
    assert!(
        matches!(
            e,
            FolderError::SizeMismatch { ref stem, layer: "albedo", size: (10, 12), photo: (W, H), .. }
                if stem == "b"
        ),
        "{e:?}"
    );
    let msg = e.to_string();
    assert!(
        msg.starts_with("b: albedo ") && msg.contains("albedo/b.exr"),
        "{msg}"
    );
    assert!(msg.ends_with("is 10x12, the photo is 24x20"), "{msg}");
    let msg = ds.load(2).unwrap_err().to_string();
    assert!(
        msg.contains("masks/c.png is 24x19, the photo is 24x20"),
        "{msg}"
    );
    ds.load(0).unwrap();
}

#[test]
fn unreadable_files_are_errors_naming_the_file_and_the_reason() {
    let (_dir, root, _) = written();
    fs::write(root.join("photos/b.png"), b"\x89PNG not really").unwrap();
    let exr = fs::read(root.join("normals/c.exr")).unwrap();
    fs::write(root.join("normals/c.exr"), &exr[..exr.len() / 2]).unwrap();
    // Opening decodes nothing.
    let ds = FolderDataset::open(&root).unwrap();
    ds.load(0).unwrap();
    for (i, file, format) in [
        (1, "photos/b.png", "PNG/JPEG"),
        (2, "normals/c.exr", "OpenEXR"),
    ] {
        let e = ds.load(i).unwrap_err();
        assert!(
            matches!(e, FolderError::Image(EnvMapError::Decode { .. })),
            "{e:?}"
        );
        let msg = volux_envmap::error::chain(&e);
        assert!(
            msg.contains(file) && msg.contains(&format!("cannot decode {format} image: ")),
            "{msg}"
        );
    }
}

#[test]
fn non_finite_exr_texels_are_errors_naming_file_and_pixel() {
    let (_dir, root, samples) = written();
    let mut albedo = samples[2].image.albedo.clone();
    albedo[2 * W + 3][1] = f32::NAN;
    albedo[7 * W + 5][0] = f32::INFINITY;
    albedo[7 * W + 5][2] = f32::NEG_INFINITY;
    io::save_exr(&root.join("albedo/c.exr"), W, H, &albedo).unwrap();
    let e = FolderDataset::open(&root).unwrap().load(2).unwrap_err();
    assert!(
        matches!(
            e,
            FolderError::NonFinite {
                count: 2,
                x: 3,
                y: 2,
                ..
            }
        ),
        "{e:?}"
    );
    let msg = e.to_string();
    assert!(
        msg.contains("albedo/c.exr")
            && msg.ends_with("2 pixel(s) with NaN or infinite values (first at x=3, y=2)"),
        "{msg}"
    );
}

#[test]
fn pose_files_are_checked_row_by_row() {
    let (_dir, root, _) = written();
    let poses = root.join(POSES_FILE);
    let file = poses.display().to_string();
    let cases = [
        (
            "name,yaw\na,0\n",
            "line 1: the header must be `name,yaw,pitch`, found `name,yaw`",
        ),
        ("", "line 1: the header must be `name,yaw,pitch`, found ``"),
        (
            "name,yaw,pitch\na,0,0\nb,0\n",
            "line 3: expected 3 fields `name,yaw,pitch`, found 2",
        ),
        (
            "name,yaw,pitch\na,0,0\n\nb,zero,0\nc,0,0\n",
            "line 4: yaw `zero` is not a number",
        ),
        (
            "name,yaw,pitch\na,0,0\nb,0.1,inf\nc,0,0\n",
            "line 3: pitch `inf` is not finite",
        ),
        (
            "name,yaw,pitch\na,NaN,0\n",
            "line 2: yaw `NaN` is not finite",
        ),
        (
            "name,yaw,pitch\na,0,1.6\n",
            "line 2: pitch `1.6` must be strictly between -pi/2 and pi/2 radians",
        ),
        (
            "name,yaw,pitch\na,0,0\nb,0,0\nc,0,0\nb.png,0,0\n",
            "line 5: no photo named `b.png` (names are file stems, without extension)",
        ),
        (
            "name,yaw,pitch\na,0,0\nb,0,0\na,0.2,0\n",
            "line 4: a second row for `a` (the first is on line 2)",
        ),
        ("name,yaw,pitch\nb,0,0\n", "no row for a, c"),
        (
            "name,yaw,pitch\na,1e300,0\n",
            "line 2: yaw `1e300` must be within [-2 pi, 2 pi] radians (degrees given?)",
        ),
        (
            "name,yaw,pitch\na,-30,0\n",
            "line 2: yaw `-30` must be within [-2 pi, 2 pi] radians (degrees given?)",
        ),
    ];
    for (text, want) in cases {
        fs::write(&poses, text).unwrap();
        let msg = open_err(&root).to_string();
        assert_eq!(msg, format!("{file}: {want}"), "for {text:?}");
    }
    // A byte order mark, CRLF, spaces, blank lines and a capitalised header are fine.
    fs::write(
        &poses,
        "\u{feff}Name, Yaw, Pitch\r\n\r\n c , -0.5 , 0.25 \r\na,1e-1,0\r\nb,0,-1.5\r\n",
    )
    .unwrap();
    let ds = FolderDataset::open(&root).unwrap();
    assert_eq!(
        (0..3).map(|i| ds.pose(i)).collect::<Vec<_>>(),
        [
            Pose::new(0.1, 0.0),
            Pose::new(0.0, -1.5),
            Pose::new(-0.5, 0.25)
        ]
    );
    // Without poses.csv every photo is frontal.
    fs::remove_file(&poses).unwrap();
    let ds = FolderDataset::open(&root).unwrap();
    assert!((0..3).all(|i| ds.pose(i) == Pose::new(0.0, 0.0)));
}

#[test]
fn empty_and_missing_folders_are_errors_naming_them() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("faces");
    let e = open_err(&root);
    assert!(matches!(e, FolderError::NoSuchFolder { .. }), "{e:?}");
    assert_eq!(e.to_string(), format!("{}: no such folder", root.display()));
    fs::write(&root, "a file").unwrap();
    assert_eq!(
        open_err(&root).to_string(),
        format!("{}: not a folder", root.display())
    );
    fs::remove_file(&root).unwrap();
    fs::create_dir_all(root.join("photos")).unwrap();
    assert_eq!(
        open_err(&root).to_string(),
        format!(
            "{}: missing albedo/, normals/; a folder dataset holds photos/, albedo/ and \
             normals/ (masks/ and poses.csv are optional); for photos alone set \
             layers = [\"photo\"] in [data.source]",
            root.display()
        )
    );
    // A photos-only dataset needs photos/ alone (and still some photos).
    let e = FolderDataset::open_with(&root, FolderContent::Photos).unwrap_err();
    assert!(matches!(e, FolderError::NoPhotos { .. }), "{e:?}");
    fs::create_dir(root.join("albedo")).unwrap();
    fs::write(root.join("normals"), "").unwrap();
    let e = open_err(&root);
    assert_eq!(
        e.to_string(),
        format!("{}: not a folder", root.join("normals").display())
    );
    fs::remove_file(root.join("normals")).unwrap();
    fs::create_dir(root.join("normals")).unwrap();
    fs::write(root.join("photos/.hidden.png"), "").unwrap();
    fs::write(root.join("photos/list.txt"), "").unwrap();
    let e = open_err(&root);
    assert!(
        matches!(e, FolderError::NoPhotos { ignored: 1, .. }),
        "{e:?}"
    );
    assert_eq!(
        e.to_string(),
        format!(
            "{}: no photos (.png, .jpg or .jpeg); 1 other file(s) ignored",
            root.join("photos").display()
        )
    );
    fs::write(root.join("masks"), "").unwrap();
    let e = open_err(&root);
    assert_eq!(
        e.to_string(),
        format!("{}: not a folder", root.join("masks").display())
    );
}

#[test]
fn write_dataset_checks_before_writing() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("out");
    let samples = spheres();
    let e = write_dataset(&root, &[]).unwrap_err();
    assert!(matches!(e, FolderError::NothingToWrite { .. }), "{e}");
    let mut bad = samples.clone();
    bad[1].stem = "x,y".into();
    let msg = write_dataset(&root, &bad).unwrap_err().to_string();
    assert!(msg.starts_with("sample `x,y`: a name must be"), "{msg}");
    let mut bad = samples.clone();
    bad[2].stem = "a".into();
    let msg = write_dataset(&root, &bad).unwrap_err().to_string();
    assert_eq!(msg, "sample `a`: two samples have this name");
    let mut bad = samples.clone();
    bad[0].photo.pop();
    let msg = write_dataset(&root, &bad).unwrap_err().to_string();
    assert_eq!(msg, "sample `a`: photo has 479 pixels, the image is 24x20");
    let mut bad = samples.clone();
    bad[1].image.normals[5] = [f32::NAN; 3];
    let msg = write_dataset(&root, &bad).unwrap_err().to_string();
    assert_eq!(
        msg,
        "sample `b`: normals has a non-finite value at pixel (5, 0)"
    );
    let mut bad = samples.clone();
    bad[2].image.pose.pitch = -2.0;
    let msg = write_dataset(&root, &bad).unwrap_err().to_string();
    assert!(
        msg.starts_with("sample `c`: pose (-0.7, -2) must be finite"),
        "{msg}"
    );
    // A dataset is never written that reading would refuse: the yaw has the same bound.
    let mut bad = samples.clone();
    bad[0].image.pose.yaw = 7.0;
    let msg = write_dataset(&root, &bad).unwrap_err().to_string();
    assert!(
        msg.starts_with("sample `a`: pose (7, 0) must be finite with yaw within"),
        "{msg}"
    );
    assert!(!root.exists(), "nothing was written");
    write_dataset(&root, &samples).unwrap();
    let e = write_dataset(&root, &samples).unwrap_err();
    assert_eq!(
        e.to_string(),
        format!(
            "{}: not empty; write a folder dataset into a new or empty folder",
            root.display()
        )
    );
    // Atomic writes leave no temporary files behind.
    for folder in ["photos", "albedo", "normals", "masks"] {
        let names: Vec<String> = fs::read_dir(root.join(folder))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names.len(), 3, "{folder}: {names:?}");
    }
    assert_eq!(fs::read_dir(&root).unwrap().count(), 5);
}

#[test]
fn samples_without_foreground_or_usable_normals_are_errors_naming_the_file() {
    let (_dir, root, samples) = written();
    let ds = || FolderDataset::open(&root).unwrap();
    // An all-zero mask.
    io::save_png(&root.join("masks/b.png"), W, H, &vec![[0u8; 3]; W * H]).unwrap();
    let e = ds().load(1).unwrap_err().to_string();
    assert!(
        e.contains("masks/b.png") && e.contains("no foreground pixel in `b`"),
        "{e}"
    );
    // All-zero EXR normals without a mask file: no foreground either, named by the normals.
    fs::remove_file(root.join("masks/c.png")).unwrap();
    io::save_exr(&root.join("normals/c.exr"), W, H, &vec![[0.0f32; 3]; W * H]).unwrap();
    let e = ds().load(2).unwrap_err().to_string();
    assert!(
        e.contains("normals/c.exr") && e.contains("the normals' length"),
        "{e}"
    );
    // With the mask, zero normals have no direction anywhere in the foreground.
    let a = &samples[0];
    io::save_exr(&root.join("normals/a.exr"), W, H, &vec![[0.0f32; 3]; W * H]).unwrap();
    let e = ds().load(0).unwrap_err().to_string();
    assert!(
        e.contains("normals/a.exr") && e.contains("no direction (zero length) in 100%"),
        "{e}"
    );
    // An all-black PNG decodes to (-1, -1, -1): facing away from the camera.
    fs::remove_file(root.join("normals/a.exr")).unwrap();
    io::save_png(&root.join("normals/a.png"), W, H, &vec![[0u8; 3]; W * H]).unwrap();
    let e = ds().load(0).unwrap_err().to_string();
    assert!(
        e.contains("normals/a.png") && e.contains("face away from the camera in 100%"),
        "{e}"
    );
    // World-space normals of a sphere seen from behind (z flipped) are refused too, while
    // a few back-facing pixels (silhouette noise) are not.
    let mut flipped = a.image.normals.clone();
    for n in &mut flipped {
        n[2] = -n[2];
    }
    fs::remove_file(root.join("normals/a.png")).unwrap();
    io::save_exr(&root.join("normals/a.exr"), W, H, &flipped).unwrap();
    let e = ds().load(0).unwrap_err().to_string();
    assert!(e.contains("face away from the camera"), "{e}");
    let mut noisy = a.image.normals.clone();
    let fg: Vec<usize> = (0..W * H).filter(|&i| a.image.mask[i] > 0.0).collect();
    for &i in fg.iter().take(fg.len() / 4) {
        noisy[i][2] = -noisy[i][2].abs() - 0.2;
    }
    io::save_exr(&root.join("normals/a.exr"), W, H, &noisy).unwrap();
    assert!(ds().load(0).is_ok());
    // A grey PNG (white: every normal (1, 1, 1)) faces the camera but is no normal map.
    fs::remove_file(root.join("normals/a.exr")).unwrap();
    io::save_png(&root.join("normals/a.png"), W, H, &vec![[255u8; 3]; W * H]).unwrap();
    let e = ds().load(0).unwrap_err().to_string();
    assert!(
        e.contains("normals/a.png") && e.contains("equal x, y and z") && e.contains("100%"),
        "{e}"
    );
}

#[test]
fn a_photos_only_dataset_reads_photos_masks_and_poses_alone() {
    let (_dir, root, samples) = written();
    fs::remove_file(root.join("masks/c.png")).unwrap();
    // The intrinsic folders may be there (they are not read) or not.
    let with = FolderDataset::open_with(&root, FolderContent::Photos).unwrap();
    fs::remove_dir_all(root.join("albedo")).unwrap();
    fs::remove_dir_all(root.join("normals")).unwrap();
    let ds = FolderDataset::open_with(&root, FolderContent::Photos).unwrap();
    assert_eq!((ds.len(), with.len()), (3, 3));
    assert_eq!(ds.content(), FolderContent::Photos);
    for (i, want) in samples.iter().enumerate() {
        let got = ds.load_photo(i).unwrap();
        assert_eq!(got.stem, want.stem);
        assert_eq!((got.width, got.height), (W, H));
        assert_eq!(got.pose, want.image.pose);
        for (g, w) in got.photo.iter().zip(&want.photo) {
            assert!((0..3).all(|k| (g[k] - w[k]).abs() <= 0.5 / 255.0 + 1e-6));
        }
        // Only c has no mask file; none is made up for it.
        assert_eq!(got.mask.is_some(), want.stem != "c", "{}", want.stem);
    }
    let e = ds.load(0).unwrap_err();
    assert!(matches!(e, FolderError::NoIntrinsics { .. }), "{e:?}");
    assert!(e.to_string().contains("photos-only"), "{e}");
    // The full layout is still refused without them, and the error says how to go on.
    let e = open_err(&root).to_string();
    assert!(e.contains("layers = [\"photo\"]"), "{e}");

    // An empty mask is refused as it is in a full dataset.
    io::save_png(&root.join("masks/a.png"), W, H, &vec![[0u8; 3]; W * H]).unwrap();
    let e = ds.load_photo(0).unwrap_err();
    assert!(matches!(e, FolderError::NoForeground { .. }), "{e:?}");
    // A mask of another size names the file.
    io::save_png(&root.join("masks/a.png"), 2, 2, &[[255u8; 3]; 4]).unwrap();
    let e = ds.load_photo(0).unwrap_err();
    assert!(
        matches!(e, FolderError::SizeMismatch { layer: "mask", .. }),
        "{e:?}"
    );
}
