//! Reading and writing environment maps and light maps.
//!
//! Reads OpenEXR (any compression the `exr` crate supports, DWAA/DWAB included), Radiance
//! `.hdr`, and 8- or 16-bit PNG/JPEG (sRGB-decoded to linear, or kept as stored values by
//! [`read_encoded`]), from a file or from its bytes in memory ([`load_bytes`], for embedded
//! assets). Writes OpenEXR (f32, lossless ZIP) and 8-bit PNG (tone-mapped previews, encoded
//! data). Every write goes to a temporary file beside the
//! target and is renamed into place, so an interrupted write never leaves a half-written file
//! under the final name.

use std::fs;
use std::io::{BufWriter, Write};
use std::path::Path;

use crate::durable::write_atomically;
use crate::envmap::{EnvMap, Rgb, luminance};
use crate::error::{BoxError, EnvMapError};

/// File formats by extension.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    Exr,
    Hdr,
    /// 8- or 16-bit PNG or JPEG, sRGB-encoded.
    Ldr,
}

impl Format {
    /// The format of `path`, from its extension (case-insensitive).
    pub fn of(path: &Path) -> Result<Format, EnvMapError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match ext.as_deref() {
            Some("exr") => Ok(Format::Exr),
            Some("hdr") => Ok(Format::Hdr),
            Some("png" | "jpg" | "jpeg") => Ok(Format::Ldr),
            _ => Err(EnvMapError::UnsupportedFormat {
                path: path.to_path_buf(),
            }),
        }
    }
}

/// Decoded pixels before validation: `(width, height, row-major RGB)`, linear from
/// [`read_raw`], stored values from [`read_encoded`]. Values may be negative or non-finite;
/// [`EnvMap::validated`] decides what to do with them.
#[derive(Clone, Debug, PartialEq)]
pub struct RawImage {
    pub width: usize,
    pub height: usize,
    pub texels: Vec<Rgb>,
}

/// Reads any supported file into linear RGB without validating it.
pub fn read_raw(path: &Path) -> Result<RawImage, EnvMapError> {
    match Format::of(path)? {
        Format::Exr => {
            let bytes = fs::read(path).map_err(|source| EnvMapError::Io {
                path: path.to_path_buf(),
                source,
            })?;
            decode_exr(&bytes, path)
        }
        Format::Hdr | Format::Ldr => {
            let reader = image::ImageReader::open(path).map_err(|source| EnvMapError::Io {
                path: path.to_path_buf(),
                source,
            })?;
            decode_with_image(reader, path)
        }
    }
}

/// Decodes the bytes of a file into linear RGB without validating them. `path` is where the
/// bytes came from: its extension picks the decoder and it is named in errors.
pub fn read_raw_bytes(bytes: &[u8], path: &Path) -> Result<RawImage, EnvMapError> {
    match Format::of(path)? {
        Format::Exr => decode_exr(bytes, path),
        Format::Hdr | Format::Ldr => {
            decode_with_image(image::ImageReader::new(std::io::Cursor::new(bytes)), path)
        }
    }
}

/// Reads and validates an environment map (see [`EnvMap::validated`] for the rules).
pub fn load(path: &Path) -> Result<EnvMap, EnvMapError> {
    validate(read_raw(path)?, path)
}

/// Decodes and validates an environment map held in memory (an embedded asset, or a file
/// already read to hash it), exactly as [`load`] would read it from `path`: the extension of
/// `path` picks the decoder, and errors and warnings name `path`.
pub fn load_bytes(bytes: &[u8], path: &Path) -> Result<EnvMap, EnvMapError> {
    validate(read_raw_bytes(bytes, path)?, path)
}

fn validate(raw: RawImage, path: &Path) -> Result<EnvMap, EnvMapError> {
    EnvMap::validated(
        raw.width,
        raw.height,
        raw.texels,
        &path.display().to_string(),
    )
}

/// The most texels an image file may hold: a 16384 x 8192 environment map (1.5 GiB as
/// linear RGB f32). Checked against the file's header before any pixel is allocated, so that
/// a header that lies cannot ask for hundreds of gigabytes.
pub const MAX_TEXELS: usize = 16384 * 8192;

fn too_large(path: &Path, width: usize, height: usize) -> EnvMapError {
    EnvMapError::TooLarge {
        path: path.to_path_buf(),
        width,
        height,
        max: MAX_TEXELS,
    }
}

fn decode_exr(bytes: &[u8], path: &Path) -> Result<RawImage, EnvMapError> {
    use exr::prelude::*;
    let decode_err = |e: exr::error::Error| EnvMapError::Decode {
        path: path.to_path_buf(),
        format: "OpenEXR",
        source: e.into(),
    };
    let meta = exr::meta::MetaData::read_from_buffered(std::io::Cursor::new(bytes), true)
        .map_err(decode_err)?;
    for header in &meta.headers {
        let size = header.layer_size;
        if size
            .width()
            .checked_mul(size.height())
            .is_none_or(|n| n > MAX_TEXELS)
        {
            return Err(too_large(path, size.width(), size.height()));
        }
    }
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .rgba_channels(
            |size, _| RawImage {
                width: size.width(),
                height: size.height(),
                texels: vec![[0.0; 3]; size.area()],
            },
            |img: &mut RawImage, pos, (r, g, b, _a): (f32, f32, f32, f32)| {
                img.texels[pos.y() * img.width + pos.x()] = [r, g, b];
            },
        )
        .first_valid_layer()
        .all_attributes()
        // Pedantic: a truncated or corrupt file is an error, not an image with holes.
        .pedantic()
        .from_buffered(std::io::Cursor::new(bytes))
        .map_err(decode_err)?;
    Ok(image.layer_data.channel_data.pixels)
}

/// Decodes with the `image` crate (Radiance HDR, PNG, JPEG); `path` names the source.
fn decode_dynamic<R: std::io::BufRead + std::io::Seek>(
    reader: image::ImageReader<R>,
    path: &Path,
) -> Result<image::DynamicImage, EnvMapError> {
    let format = if Format::of(path)? == Format::Hdr {
        "Radiance HDR"
    } else {
        "PNG/JPEG"
    };
    let decode_err = |source: BoxError| EnvMapError::Decode {
        path: path.to_path_buf(),
        format,
        source,
    };
    let mut reader = reader
        .with_guessed_format()
        .map_err(|e| decode_err(e.into()))?;
    // The decoders check these against the header before allocating.
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(MAX_TEXELS as u64 * 16);
    reader.limits(limits);
    reader.decode().map_err(|e| match e {
        image::ImageError::Limits(_) => EnvMapError::DecodeLimit {
            path: path.to_path_buf(),
            format,
            max: MAX_TEXELS,
            source: e.into(),
        },
        e => decode_err(e.into()),
    })
}

/// [`decode_dynamic`] into linear RGB.
fn decode_with_image<R: std::io::BufRead + std::io::Seek>(
    reader: image::ImageReader<R>,
    path: &Path,
) -> Result<RawImage, EnvMapError> {
    let img = decode_dynamic(reader, path)?;
    let (width, height) = (img.width() as usize, img.height() as usize);
    use image::ColorType as C;
    let texels: Vec<Rgb> = match img.color() {
        // Float images (Radiance HDR) are linear already.
        C::Rgb32F | C::Rgba32F => img
            .into_rgb32f()
            .pixels()
            .map(|p| [p.0[0], p.0[1], p.0[2]])
            .collect(),
        C::L16 | C::La16 | C::Rgb16 | C::Rgba16 => img
            .into_rgb16()
            .pixels()
            .map(|p| p.0.map(|v| srgb_to_linear(f32::from(v) / 65535.0)))
            .collect(),
        _ => {
            let lut: Vec<f32> = (0..256).map(|v| srgb_to_linear(v as f32 / 255.0)).collect();
            img.into_rgb8()
                .pixels()
                .map(|p| p.0.map(|v| lut[v as usize]))
                .collect()
        }
    };
    Ok(RawImage {
        width,
        height,
        texels,
    })
}

/// Reads an 8- or 16-bit PNG or JPEG as the values it stores, scaled to [0, 1], without the
/// sRGB decoding of [`read_raw`]: for sRGB images kept encoded (photos) and for data kept in
/// images (normal maps, masks). Grey images give three equal channels; alpha is dropped.
pub fn read_encoded(path: &Path) -> Result<RawImage, EnvMapError> {
    if Format::of(path)? != Format::Ldr {
        return Err(EnvMapError::UnsupportedFormat {
            path: path.to_path_buf(),
        });
    }
    let reader = image::ImageReader::open(path).map_err(|source| EnvMapError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let img = decode_dynamic(reader, path)?;
    let (width, height) = (img.width() as usize, img.height() as usize);
    use image::ColorType as C;
    let texels: Vec<Rgb> = match img.color() {
        C::L16 | C::La16 | C::Rgb16 | C::Rgba16 => img
            .into_rgb16()
            .pixels()
            .map(|p| p.0.map(|v| f32::from(v) / 65535.0))
            .collect(),
        _ => img
            .into_rgb8()
            .pixels()
            .map(|p| p.0.map(|v| f32::from(v) / 255.0))
            .collect(),
    };
    Ok(RawImage {
        width,
        height,
        texels,
    })
}

/// The sRGB transfer function, decoded: 8-bit display value in [0, 1] to linear.
pub fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// The sRGB transfer function, encoded: linear in [0, 1] to display value in [0, 1].
pub fn linear_to_srgb(v: f32) -> f32 {
    let v = v.clamp(0.0, 1.0);
    if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// Writes linear RGB texels as a 32-bit float OpenEXR file (ZIP, lossless), atomically.
pub fn save_exr(
    path: &Path,
    width: usize,
    height: usize,
    texels: &[Rgb],
) -> Result<(), EnvMapError> {
    use exr::prelude::*;
    assert_eq!(texels.len(), width * height, "texel buffer size");
    write_atomically(path, |tmp| {
        let channels = SpecificChannels::rgb(|Vec2(x, y): Vec2<usize>| {
            let c = texels[y * width + x];
            (c[0], c[1], c[2])
        });
        Image::from_encoded_channels((width, height), Encoding::SMALL_LOSSLESS, channels)
            .write()
            .to_file(tmp)
            .map_err(|e| EnvMapError::Encode {
                path: path.to_path_buf(),
                format: "OpenEXR",
                source: e.into(),
            })
    })
}

/// Writes an environment map as OpenEXR.
pub fn save_envmap_exr(path: &Path, map: &EnvMap) -> Result<(), EnvMapError> {
    save_exr(path, map.width(), map.height(), map.texels())
}

/// Writes 8-bit sRGB pixels as PNG, atomically.
pub fn save_png(
    path: &Path,
    width: usize,
    height: usize,
    pixels: &[[u8; 3]],
) -> Result<(), EnvMapError> {
    assert_eq!(pixels.len(), width * height, "pixel buffer size");
    write_atomically(path, |tmp| {
        let encode_err = |e: image::ImageError| EnvMapError::Encode {
            path: path.to_path_buf(),
            format: "PNG",
            source: e.into(),
        };
        let file = fs::File::create(tmp).map_err(|source| EnvMapError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let mut out = BufWriter::new(file);
        let bytes: Vec<u8> = pixels.iter().flatten().copied().collect();
        image::ImageEncoder::write_image(
            image::codecs::png::PngEncoder::new(&mut out),
            &bytes,
            width as u32,
            height as u32,
            image::ExtendedColorType::Rgb8,
        )
        .map_err(encode_err)?;
        out.flush().map_err(|source| EnvMapError::Io {
            path: path.to_path_buf(),
            source,
        })
    })
}

/// Exposure that maps the log-average luminance to middle grey (Reinhard et al. 2002), so that
/// a preview of a dim night and of a noon sky both show their structure. 1 for a black map.
pub fn auto_exposure(texels: &[Rgb]) -> f32 {
    if texels.is_empty() {
        return 1.0;
    }
    let delta = 1e-4;
    let log_avg = texels
        .iter()
        .map(|c| (delta + luminance(*c).max(0.0)).ln())
        .sum::<f64>()
        / texels.len() as f64;
    let key = log_avg.exp() - delta;
    if key > 1e-12 {
        (0.18 / key) as f32
    } else {
        1.0
    }
}

/// Tone-maps one linear HDR colour to sRGB in [0, 1]: scale by `exposure`, then Reinhard's
/// `L / (1 + L)` on luminance (hue kept), then the sRGB curve. Always finite. The relit images
/// of the datasets and of the generator (`volux_model::relighting::tonemap_srgb`) use this
/// curve at exposure 1.
pub fn tonemap_pixel(c: Rgb, exposure: f32) -> Rgb {
    let scaled = c.map(|v| v.max(0.0) * exposure);
    let lum = luminance(scaled) as f32;
    let k = 1.0 / (1.0 + lum);
    scaled.map(|v| linear_to_srgb(v * k))
}

/// [`tonemap_pixel`] to 8-bit sRGB.
pub fn tonemap(texels: &[Rgb], exposure: f32) -> Vec<[u8; 3]> {
    texels
        .iter()
        .map(|c| tonemap_pixel(*c, exposure).map(|v| (v * 255.0 + 0.5) as u8))
        .collect()
}

/// Writes a tone-mapped PNG preview of a map (automatic exposure).
pub fn save_preview_png(path: &Path, map: &EnvMap) -> Result<(), EnvMapError> {
    let pixels = tonemap(map.texels(), auto_exposure(map.texels()));
    save_png(path, map.width(), map.height(), &pixels)
}

#[cfg(test)]
mod tests;
