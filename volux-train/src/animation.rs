//! Animated GIFs of sample sequences (a rotating camera, a rotating environment, a latent
//! interpolation), looping forever.

use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, RgbaImage};

/// Why an animation cannot be written.
#[derive(Debug, thiserror::Error)]
pub enum AnimationError {
    #[error("{path}: {message}")]
    Write {
        path: std::path::PathBuf,
        message: String,
    },
}

/// Writes `frames` (8-bit sRGB, row-major, `width x height` each) as a looping GIF showing
/// each frame for `delay_ms` milliseconds. The file appears only once complete.
pub fn save_gif(
    path: &Path,
    width: usize,
    height: usize,
    frames: &[Vec<[u8; 3]>],
    delay_ms: u32,
) -> Result<(), AnimationError> {
    let fail = |message: String| AnimationError::Write {
        path: path.to_path_buf(),
        message,
    };
    let tmp = path.with_extension("gif.partial");
    let write = || -> Result<(), AnimationError> {
        let file = File::create(&tmp).map_err(|e| fail(e.to_string()))?;
        let mut encoder = GifEncoder::new_with_speed(BufWriter::new(file), 10);
        encoder
            .set_repeat(Repeat::Infinite)
            .map_err(|e| fail(e.to_string()))?;
        for pixels in frames {
            assert_eq!(pixels.len(), width * height, "frame size");
            let rgba: Vec<u8> = pixels
                .iter()
                .flat_map(|p| [p[0], p[1], p[2], 255])
                .collect();
            let image = RgbaImage::from_raw(width as u32, height as u32, rgba)
                .ok_or_else(|| fail("frame buffer size".into()))?;
            let delay = Delay::from_numer_denom_ms(delay_ms, 1);
            encoder
                .encode_frame(Frame::from_parts(image, 0, 0, delay))
                .map_err(|e| fail(e.to_string()))?;
        }
        drop(encoder);
        std::fs::rename(&tmp, path).map_err(|e| fail(e.to_string()))
    };
    let result = write();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::AnimationDecoder;
    use image::codecs::gif::GifDecoder;

    #[test]
    fn a_gif_holds_every_frame() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.gif");
        let frames: Vec<Vec<[u8; 3]>> = (0..5u8)
            .map(|i| vec![[i * 50, 255 - i * 50, 0]; 6 * 4])
            .collect();
        save_gif(&path, 6, 4, &frames, 80).unwrap();
        let decoder = GifDecoder::new(std::io::BufReader::new(File::open(&path).unwrap())).unwrap();
        let decoded = decoder.into_frames().collect_frames().unwrap();
        assert_eq!(decoded.len(), 5);
        let px = decoded[2].buffer().get_pixel(1, 1).0;
        assert!(
            (px[0] as i32 - 100).abs() <= 8 && (px[1] as i32 - 155).abs() <= 8,
            "{px:?}"
        );
        assert!(!dir.path().join("a.gif.partial").exists());
    }
}
