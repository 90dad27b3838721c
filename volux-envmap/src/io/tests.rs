#[test]
fn headers_that_claim_huge_images_are_refused_before_allocating() {
    let dir = tempfile::tempdir().unwrap();
    // Radiance HDR: a 100000 x 200000 header over a few bytes of "pixels" (240 GB as f32).
    let hdr = dir.path().join("huge.hdr");
    let mut bytes = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 100000 +X 200000\n".to_vec();
    bytes.extend([0u8; 64]);
    std::fs::write(&hdr, bytes).unwrap();
    let err = super::read_raw(&hdr).unwrap_err();
    // The decoder's own limit, with its error kept as the cause.
    assert!(
        matches!(err, crate::EnvMapError::DecodeLimit { .. })
            && std::error::Error::source(&err).is_some(),
        "{err:?}"
    );
    let e = err.to_string();
    assert!(e.contains("huge.hdr") && e.contains("at most"), "{e}");
    // OpenEXR: a real 2x1 file whose data window is patched to 2e8 x 1 texels (one line,
    // so the chunk table still matches; 2.4 GB as f32, past the limit).
    let exr = dir.path().join("huge.exr");
    super::save_exr(&exr, 2, 1, &[[0.5, 0.5, 0.5]; 2]).unwrap();
    let mut bytes = std::fs::read(&exr).unwrap();
    let key = b"dataWindow\0box2i\0";
    let at = bytes
        .windows(key.len())
        .position(|w| w == key)
        .expect("a data window")
        + key.len()
        + 4; // the attribute's size
    bytes[at + 8..at + 12].copy_from_slice(&199_999_999i32.to_le_bytes()); // x max
    std::fs::write(&exr, bytes).unwrap();
    let e = super::read_raw(&exr).unwrap_err();
    assert!(
        matches!(
            e,
            crate::EnvMapError::TooLarge {
                width: 200_000_000,
                height: 1,
                ..
            }
        ),
        "{e}"
    );
}

use super::*;

fn sample_map() -> EnvMap {
    EnvMap::from_fn(8, |d| {
        [
            (d[1] + 1.0) as f32 * 3.0,
            (d[0] * d[0]) as f32 * 1e4,
            (d[2] + 1.0) as f32 * 1e-3,
        ]
    })
    .unwrap()
}

#[test]
fn exr_round_trip_is_lossless() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.exr");
    let m = sample_map();
    save_envmap_exr(&path, &m).unwrap();
    assert_eq!(load(&path).unwrap(), m);
    // No temporary file is left behind.
    assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);
}

#[test]
fn truncated_exr_is_an_error_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cut.exr");
    save_envmap_exr(&path, &sample_map()).unwrap();
    let bytes = fs::read(&path).unwrap();
    for keep in [10, bytes.len() / 2, bytes.len() - 7] {
        fs::write(&path, &bytes[..keep]).unwrap();
        let e = load(&path).unwrap_err();
        assert!(matches!(e, EnvMapError::Decode { .. }), "{keep}: {e}");
        assert!(e.to_string().contains("cut.exr"), "{e}");
    }
}

#[test]
fn bytes_in_memory_decode_as_the_file_does() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.exr");
    save_envmap_exr(&path, &sample_map()).unwrap();
    let bytes = fs::read(&path).unwrap();
    let named = Path::new("assets/embedded.exr");
    assert_eq!(load_bytes(&bytes, named).unwrap(), load(&path).unwrap());
    // Radiance HDR from memory too.
    let hdr = dir.path().join("m.hdr");
    let pixels = vec![image::Rgb([2.0f32, 0.5, 1e-2]); 32];
    let f = fs::File::create(&hdr).unwrap();
    image::codecs::hdr::HdrEncoder::new(f)
        .encode(&pixels, 8, 4)
        .unwrap();
    let hdr_bytes = fs::read(&hdr).unwrap();
    assert_eq!(
        load_bytes(&hdr_bytes, Path::new("x.hdr")).unwrap(),
        load(&hdr).unwrap()
    );
    // Corrupt bytes and unknown extensions are errors naming the given path.
    let e = load_bytes(&bytes[..bytes.len() / 2], named).unwrap_err();
    assert!(matches!(e, EnvMapError::Decode { .. }), "{e}");
    assert!(e.to_string().contains("assets/embedded.exr"), "{e}");
    let e = load_bytes(b"garbage", Path::new("x.hdr")).unwrap_err();
    assert!(e.to_string().contains("x.hdr"), "{e}");
    let e = load_bytes(&bytes, Path::new("x.tiff")).unwrap_err();
    assert!(matches!(e, EnvMapError::UnsupportedFormat { .. }), "{e}");
}

#[test]
fn missing_and_unknown_files_are_clear_errors() {
    let e = load(Path::new("no/such/map.exr")).unwrap_err();
    assert!(
        matches!(e, EnvMapError::Io { .. }) && e.to_string().contains("map.exr"),
        "{e}"
    );
    let e = load(Path::new("no/such/map.hdr")).unwrap_err();
    assert!(e.to_string().contains("map.hdr"), "{e}");
    let e = load(Path::new("map.tiff")).unwrap_err();
    assert!(matches!(e, EnvMapError::UnsupportedFormat { .. }), "{e}");
    let dir = tempfile::tempdir().unwrap();
    let garbage = dir.path().join("garbage.png");
    fs::write(&garbage, b"not a png at all").unwrap();
    let e = load(&garbage).unwrap_err();
    assert!(e.to_string().contains("garbage.png"), "{e}");
}

#[test]
fn non_finite_and_non_equirect_files_are_rejected() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("nan.exr");
    let mut t = vec![[1.0f32; 3]; 32];
    t[5][2] = f32::NAN;
    t[6][0] = f32::INFINITY;
    save_exr(&path, 8, 4, &t).unwrap();
    let e = load(&path).unwrap_err();
    assert!(e.to_string().contains("2 texel values") && e.to_string().contains("nan.exr"));
    let path = dir.path().join("square.exr");
    save_exr(&path, 4, 4, &[[1.0; 3]; 16]).unwrap();
    let e = load(&path).unwrap_err();
    assert!(matches!(e, EnvMapError::AspectRatio { .. }), "{e}");
}

#[test]
fn hdr_and_png_are_read_as_linear() {
    let dir = tempfile::tempdir().unwrap();
    // Radiance HDR written by the image crate.
    let hdr = dir.path().join("m.hdr");
    let pixels: Vec<image::Rgb<f32>> = (0..32)
        .map(|i| image::Rgb([i as f32 * 10.0, 0.5, 1e-2]))
        .collect();
    let f = fs::File::create(&hdr).unwrap();
    image::codecs::hdr::HdrEncoder::new(f)
        .encode(&pixels, 8, 4)
        .unwrap();
    let m = load(&hdr).unwrap();
    assert_eq!((m.width(), m.height()), (8, 4));
    let rel = (m.texel(3, 1)[0] - 110.0).abs() / 110.0;
    assert!(
        rel < 0.01,
        "RGBE keeps about 1% precision: {}",
        m.texel(3, 1)[0]
    );
    // 8-bit PNG: 255 -> 1.0, 128 -> 0.2158 (sRGB), 0 -> 0.
    let png = dir.path().join("m.png");
    let mut px = vec![[0u8, 128, 255]; 32];
    px[1] = [255, 255, 255];
    save_png(&png, 8, 4, &px).unwrap();
    let m = load(&png).unwrap();
    assert_eq!(m.texel(0, 0)[0], 0.0);
    assert!((m.texel(0, 0)[1] - 0.215_861).abs() < 1e-5);
    assert_eq!(m.texel(1, 0), [1.0, 1.0, 1.0]);
}

#[test]
fn srgb_curves_invert_each_other() {
    for i in 0..=255 {
        let v = i as f32 / 255.0;
        assert!((linear_to_srgb(srgb_to_linear(v)) - v).abs() < 1e-5);
    }
}

#[test]
fn tonemap_is_finite_for_a_huge_sun_and_black() {
    let px = tonemap(&[[1e6, 1e6, 1e6], [0.0; 3], [1.0, 0.0, 0.0]], 1.0);
    assert_eq!(px[0], [255, 255, 255]);
    assert_eq!(px[1], [0, 0, 0]);
    assert!(px[2][0] > 0 && px[2][1] == 0);
    assert_eq!(auto_exposure(&[[0.0; 3]; 4]), 1.0);
}

#[test]
fn encoded_reading_keeps_the_stored_values() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("n.png");
    save_png(&png, 2, 1, &[[0, 128, 255], [64, 64, 64]]).unwrap();
    let raw = read_encoded(&png).unwrap();
    assert_eq!((raw.width, raw.height), (2, 1));
    assert_eq!(raw.texels[0], [0.0, 128.0 / 255.0, 1.0]);
    assert_eq!(raw.texels[1], [64.0 / 255.0; 3]);
    // 16-bit grey: three equal channels at 16-bit precision.
    let grey = dir.path().join("g.png");
    image::ImageBuffer::<image::Luma<u16>, _>::from_raw(1, 1, vec![1000u16])
        .unwrap()
        .save(&grey)
        .unwrap();
    assert_eq!(
        read_encoded(&grey).unwrap().texels[0],
        [1000.0 / 65535.0; 3]
    );
    let e = read_encoded(&dir.path().join("m.exr")).unwrap_err();
    assert!(matches!(e, EnvMapError::UnsupportedFormat { .. }), "{e}");
    fs::write(&png, b"garbage").unwrap();
    let e = read_encoded(&png).unwrap_err();
    assert!(
        matches!(e, EnvMapError::Decode { .. }) && e.to_string().contains("n.png"),
        "{e}"
    );
}
