//! Animated GIFs of sample sequences (a rotating camera, a rotating environment, a latent
//! interpolation), looping forever.

use std::path::{Path, PathBuf};

use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, RgbaImage};
use volux_envmap::durable::{FileError, write_atomically};

/// Why an animation cannot be written.
#[derive(Debug, thiserror::Error)]
pub enum AnimationError {
    #[error(transparent)]
    File(#[from] FileError),
    #[error("{}: cannot encode the GIF", path.display())]
    Encode {
        path: PathBuf,
        #[source]
        source: image::ImageError,
    },
}

/// Writes `frames` (8-bit sRGB, row-major, `width x height` each) as a looping GIF showing
/// each frame for `delay_ms` milliseconds, atomically (the file appears only once complete).
pub fn save_gif(
    path: &Path,
    width: usize,
    height: usize,
    frames: &[Vec<[u8; 3]>],
    delay_ms: u32,
) -> Result<(), AnimationError> {
    let fail = |source| AnimationError::Encode {
        path: path.to_path_buf(),
        source,
    };
    write_atomically(path, |tmp| {
        // Encoded in memory (a few MB), so that a failed write is seen, not lost in a drop.
        let mut bytes = Vec::new();
        let mut encoder = GifEncoder::new_with_speed(&mut bytes, 10);
        encoder.set_repeat(Repeat::Infinite).map_err(fail)?;
        for pixels in frames {
            assert_eq!(pixels.len(), width * height, "frame size");
            let rgba: Vec<u8> = pixels
                .iter()
                .flat_map(|p| [p[0], p[1], p[2], 255])
                .collect();
            let image = RgbaImage::from_raw(width as u32, height as u32, rgba)
                .expect("the frame holds width x height pixels (asserted)");
            let delay = Delay::from_numer_denom_ms(delay_ms, 1);
            encoder
                .encode_frame(Frame::from_parts(image, 0, 0, delay))
                .map_err(fail)?;
        }
        drop(encoder);
        std::fs::write(tmp, &bytes).map_err(FileError::at(tmp))?;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::AnimationDecoder;
    use image::codecs::gif::GifDecoder;
    use std::fs::File;

    #[test]
    fn a_gif_that_cannot_be_written_is_an_error_and_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("missing").join("a.gif");
        let e = save_gif(&path, 2, 2, &[vec![[0, 0, 0]; 4]], 50).unwrap_err();
        assert!(matches!(e, AnimationError::File(_)), "{e:?}");
        assert!(volux_envmap::error::chain(&e).contains("missing"), "{e}");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

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
