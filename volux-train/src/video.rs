//! MP4 videos (H.264) of frame sequences, for the animations `volux sample` makes: frames are
//! encoded by OpenH264 (Cisco's encoder, compiled from source by the `openh264` crate, so no
//! system library or ffmpeg is needed) and put in an MP4 container by the `mp4` crate. The file
//! plays in browsers and common players (constrained baseline profile, YUV 4:2:0).

use std::io::BufWriter;
use std::path::{Path, PathBuf};

use mp4::{
    AvcConfig, FourCC, MediaConfig, Mp4Config, Mp4Sample, Mp4Writer, TrackConfig, TrackType,
};
use openh264::OpenH264API;
use openh264::encoder::{
    BitRate, Encoder, EncoderConfig, FrameRate, IntraFramePeriod, QpRange, RateControlMode,
    UsageType,
};
use openh264::formats::{RgbSliceU8, YUVBuffer};
use volux_envmap::durable::{FileError, write_atomically};

/// The quantiser of every frame (0 lossless .. 51 coarsest): nearly transparent on renders.
const QP: u8 = 20;

/// Ticks per second of the video track.
const TIMESCALE: u32 = 90_000;

/// Why a video cannot be written.
#[derive(Debug, thiserror::Error)]
pub enum VideoError {
    #[error("{path}: no frames to write")]
    Empty { path: PathBuf },
    #[error("{path}: frame {frame} holds {got} pixels, not {width} x {height}")]
    FrameSize {
        path: PathBuf,
        frame: usize,
        got: usize,
        width: usize,
        height: usize,
    },
    #[error(
        "{path}: {width} x {height} pixels is outside what H.264 encodes here (2 to 4096 per side)"
    )]
    Dimensions {
        path: PathBuf,
        width: usize,
        height: usize,
    },
    #[error("--fps {0}: give a frame rate from 1 to 120")]
    FrameRate(f64),
    #[error("{path}: encoding frame {frame}")]
    Encode {
        path: PathBuf,
        frame: usize,
        #[source]
        source: openh264::Error,
    },
    #[error("{path}: the encoder gave no sequence or picture parameter set")]
    NoParameterSets { path: PathBuf },
    #[error("writing {path}")]
    Write {
        path: PathBuf,
        #[source]
        source: FileError,
    },
}

/// An H.264 NAL unit without its Annex-B start code.
fn strip_start_code(nal: &[u8]) -> &[u8] {
    let zeros = nal.iter().take_while(|&&b| b == 0).count();
    if zeros >= 2 && nal.get(zeros) == Some(&1) {
        &nal[zeros + 1..]
    } else {
        nal
    }
}

/// A frame (row-major sRGB pixels of `width x height`) as RGB bytes padded to even sides, as
/// YUV 4:2:0 needs, by repeating the last row and column.
fn padded(frame: &[[u8; 3]], width: usize, height: usize) -> Vec<u8> {
    let (w, h) = (width + width % 2, height + height % 2);
    let mut rgb = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            rgb.extend_from_slice(&frame[y.min(height - 1) * width + x.min(width - 1)]);
        }
    }
    rgb
}

/// Encodes `frames` at `fps` frames per second into an MP4 file at `path`, atomically.
pub fn save_mp4(
    path: &Path,
    width: usize,
    height: usize,
    frames: &[Vec<[u8; 3]>],
    fps: f64,
) -> Result<(), VideoError> {
    let path_buf = || path.to_path_buf();
    if frames.is_empty() {
        return Err(VideoError::Empty { path: path_buf() });
    }
    if !(fps.is_finite() && (1.0..=120.0).contains(&fps)) {
        return Err(VideoError::FrameRate(fps));
    }
    if !(2..=4096).contains(&width) || !(2..=4096).contains(&height) {
        return Err(VideoError::Dimensions {
            path: path_buf(),
            width,
            height,
        });
    }
    if let Some((frame, f)) = frames
        .iter()
        .enumerate()
        .find(|(_, f)| f.len() != width * height)
    {
        return Err(VideoError::FrameSize {
            path: path_buf(),
            frame,
            got: f.len(),
            width,
            height,
        });
    }
    // No rate control: every frame at one fine quantiser (these are short clips of small
    // frames), and none skipped.
    let config = EncoderConfig::new()
        .bitrate(BitRate::from_bps(4_000_000))
        .max_frame_rate(FrameRate::from_hz(fps as f32))
        .rate_control_mode(RateControlMode::Off)
        .qp(QpRange::new(QP, QP))
        .usage_type(UsageType::CameraVideoRealTime)
        .skip_frames(false)
        .intra_frame_period(IntraFramePeriod::from_num_frames(
            (fps.round() as u32).max(1) * 2,
        ));
    let encode_error = |frame, source| VideoError::Encode {
        path: path_buf(),
        frame,
        source,
    };
    let mut encoder = Encoder::with_api_config(OpenH264API::from_source(), config)
        .map_err(|e| encode_error(0, e))?;
    let (mut sps, mut pps) = (None, None);
    let mut samples = Vec::with_capacity(frames.len());
    let (w, h) = (width + width % 2, height + height % 2);
    for (i, frame) in frames.iter().enumerate() {
        let rgb = padded(frame, width, height);
        let yuv = YUVBuffer::from_rgb8_source(RgbSliceU8::new(&rgb, (w, h)));
        let stream = encoder.encode(&yuv).map_err(|e| encode_error(i, e))?;
        // MP4 stores NAL units with 4-byte lengths, and the parameter sets in the track header.
        let mut sample = Vec::new();
        let mut sync = false;
        for l in 0..stream.num_layers() {
            let layer = stream.layer(l).expect("layer in range");
            for n in 0..layer.nal_count() {
                let nal = strip_start_code(layer.nal_unit(n).expect("NAL in range"));
                match nal.first().map(|b| b & 0x1f) {
                    Some(7) => sps = sps.or_else(|| Some(nal.to_vec())),
                    Some(8) => pps = pps.or_else(|| Some(nal.to_vec())),
                    Some(kind) => {
                        sync |= kind == 5;
                        sample.extend_from_slice(&(nal.len() as u32).to_be_bytes());
                        sample.extend_from_slice(nal);
                    }
                    None => {}
                }
            }
        }
        samples.push((sample, sync));
    }
    let (Some(sps), Some(pps)) = (sps, pps) else {
        return Err(VideoError::NoParameterSets { path: path_buf() });
    };
    let io = |p: &Path, e: std::io::Error| FileError::at(p)(e);
    let duration = (TIMESCALE as f64 / fps).round() as u32;
    write_atomically(path, |tmp| {
        let file = std::fs::File::create(tmp).map_err(|e| io(tmp, e))?;
        let mp4_error = |e: mp4::Error| io(tmp, std::io::Error::other(e));
        let container = Mp4Config {
            major_brand: FourCC { value: *b"isom" },
            minor_version: 512,
            compatible_brands: [*b"isom", *b"iso2", *b"avc1", *b"mp41"]
                .map(|value| FourCC { value })
                .to_vec(),
            timescale: 1000,
        };
        let mut writer =
            Mp4Writer::write_start(BufWriter::new(file), &container).map_err(mp4_error)?;
        writer
            .add_track(&TrackConfig {
                track_type: TrackType::Video,
                timescale: TIMESCALE,
                language: "und".to_string(),
                media_conf: MediaConfig::AvcConfig(AvcConfig {
                    width: w as u16,
                    height: h as u16,
                    seq_param_set: sps.clone(),
                    pic_param_set: pps.clone(),
                }),
            })
            .map_err(mp4_error)?;
        for (i, (bytes, is_sync)) in samples.iter().enumerate() {
            let sample = Mp4Sample {
                start_time: i as u64 * duration as u64,
                duration,
                rendering_offset: 0,
                is_sync: *is_sync,
                bytes: bytes::Bytes::copy_from_slice(bytes),
            };
            writer.write_sample(1, &sample).map_err(mp4_error)?;
        }
        writer.write_end().map_err(mp4_error)?;
        let mut out = writer.into_writer();
        std::io::Write::flush(&mut out).map_err(|e| io(tmp, e))
    })
    .map_err(|source| VideoError::Write {
        path: path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use openh264::decoder::Decoder;
    use openh264::formats::YUVSource;

    /// A moving colour gradient with a square: what a decoder must give back.
    fn frames(width: usize, height: usize, count: usize) -> Vec<Vec<[u8; 3]>> {
        (0..count)
            .map(|f| {
                (0..width * height)
                    .map(|i| {
                        let (x, y) = (i % width, i / width);
                        let square = (x + 2 * f) % width < 12 && y > height / 3 && y < height / 2;
                        if square {
                            [230, 40, 40]
                        } else {
                            [
                                (x * 255 / width) as u8,
                                (y * 255 / height) as u8,
                                ((f * 20) % 256) as u8,
                            ]
                        }
                    })
                    .collect()
            })
            .collect()
    }

    fn psnr(a: &[u8], b: &[u8]) -> f64 {
        let mse = a
            .iter()
            .zip(b)
            .map(|(&x, &y)| (x as f64 - y as f64).powi(2))
            .sum::<f64>()
            / a.len() as f64;
        10.0 * (255.0f64.powi(2) / mse.max(1e-12)).log10()
    }

    #[test]
    fn an_mp4_reads_back_with_every_frame_at_its_rate_and_decodes_to_the_frames() {
        let (w, h, n, fps) = (96, 64, 12, 12.0);
        let input = frames(w, h, n);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("clip.mp4");
        save_mp4(&path, w, h, &input, fps).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let size = bytes.len() as u64;
        let mut reader = mp4::Mp4Reader::read_header(std::io::Cursor::new(bytes), size).unwrap();
        assert_eq!(reader.tracks().len(), 1);
        let track = reader.tracks().get(&1).unwrap();
        assert_eq!((track.width(), track.height()), (w as u16, h as u16));
        assert_eq!(track.sample_count(), n as u32);
        assert!(
            (track.frame_rate() - fps).abs() < 1e-6,
            "{}",
            track.frame_rate()
        );
        assert!((reader.duration().as_secs_f64() - n as f64 / fps).abs() < 0.01);
        let (sps, pps) = (
            track.sequence_parameter_set().unwrap().to_vec(),
            track.picture_parameter_set().unwrap().to_vec(),
        );
        // Decode every sample (lengths back to start codes) and compare with the input.
        let mut decoder = Decoder::new().unwrap();
        let annex_b = |nal: &[u8]| [&[0, 0, 0, 1][..], nal].concat();
        let mut stream = [annex_b(&sps), annex_b(&pps)].concat();
        let mut worst = f64::INFINITY;
        for (i, frame) in input.iter().enumerate() {
            let sample = reader.read_sample(1, i as u32 + 1).unwrap().unwrap();
            if i == 0 {
                assert!(sample.is_sync, "the first frame is a key frame");
            }
            let mut data = &sample.bytes[..];
            while data.len() >= 4 {
                let len = u32::from_be_bytes(data[..4].try_into().unwrap()) as usize;
                stream.extend(annex_b(&data[4..4 + len]));
                data = &data[4 + len..];
            }
            let yuv = decoder
                .decode(&stream)
                .unwrap()
                .expect("a picture per sample");
            assert_eq!(yuv.dimensions(), (w, h));
            let mut rgb = vec![0; w * h * 3];
            yuv.write_rgb8(&mut rgb);
            let want: Vec<u8> = frame.iter().flatten().copied().collect();
            worst = worst.min(psnr(&rgb, &want));
            stream.clear();
        }
        // 37.4 dB at QP 20 when written.
        assert!(worst > 33.0, "worst frame PSNR {worst:.1} dB");
    }

    #[test]
    fn odd_sides_are_padded_and_bad_inputs_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("odd.mp4");
        save_mp4(&path, 33, 17, &frames(33, 17, 3), 25.0).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let size = bytes.len() as u64;
        let reader = mp4::Mp4Reader::read_header(std::io::Cursor::new(bytes), size).unwrap();
        let track = reader.tracks().get(&1).unwrap();
        assert_eq!((track.width(), track.height()), (34, 18));
        for (result, expected) in [
            (save_mp4(&path, 4, 4, &[], 10.0), "no frames"),
            (save_mp4(&path, 4, 4, &frames(4, 4, 2), 0.0), "--fps 0"),
            (
                save_mp4(&path, 4, 4, &frames(4, 4, 2), f64::NAN),
                "--fps NaN",
            ),
            (
                save_mp4(&path, 4, 4, &frames(4, 3, 2), 10.0),
                "frame 0 holds 12",
            ),
            (save_mp4(&path, 1, 4, &frames(1, 4, 2), 10.0), "1 x 4"),
            (
                save_mp4(
                    &dir.path().join("no/such.mp4"),
                    4,
                    4,
                    &frames(4, 4, 2),
                    10.0,
                ),
                "no/such.mp4",
            ),
        ] {
            let e = result.unwrap_err().to_string();
            assert!(e.contains(expected), "{e}");
        }
    }
}
