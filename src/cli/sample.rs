//! `volux sample`: render a checkpoint's EMA generator: grids of every intrinsic layer, the
//! relit image from several cameras, EXR files of the HDR layers, and animations of a rotating
//! camera, a rotating environment and a latent interpolation (the paper's figures 4 and 5).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Args;
use volux_data::contact_sheet::ContactSheet;
use volux_envmap::io;
use volux_model::backend::BackendKind;
use volux_model::pose::Pose;
use volux_train::animation::save_gif;
use volux_train::pretrained::load_for_sampling;
use volux_train::sampling::{self, SampleLayers};
use volux_train::video::save_mp4;

use super::data::parse_seeds;
use super::environment::environments;

#[derive(Debug, Args)]
pub struct SampleArgs {
    /// A checkpoint folder, a run folder (its newest checkpoint is used), or the name of a
    /// model shipped in the binary (`quickstart`).
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// Latent seeds: a range `0-7` or a list `1,5,9`.
    #[arg(long, default_value = "0-7")]
    pub seeds: String,
    /// Camera yaws in degrees (comma-separated); the first is used for the layer grids.
    #[arg(
        long,
        value_delimiter = ',',
        allow_hyphen_values = true,
        default_value = "0"
    )]
    pub yaw: Vec<f64>,
    /// Camera pitches in degrees (comma-separated).
    #[arg(
        long,
        value_delimiter = ',',
        allow_hyphen_values = true,
        default_value = "0"
    )]
    pub pitch: Vec<f64>,
    /// HDR environment maps (EXR or HDR) to light with; default: the shipped sunrise map.
    #[arg(long)]
    pub hdri: Vec<PathBuf>,
    /// Frames of an animation of the first environment turning once around the heads (0: none).
    #[arg(long, default_value_t = 0)]
    pub rotate_light: usize,
    /// Frames of an animation of the camera swinging from -30 to 30 degrees of yaw and back
    /// (0: none).
    #[arg(long, default_value_t = 0)]
    pub rotate_camera: usize,
    /// `A,B,N`: N images interpolating the latent of seed A to that of seed B (a PNG strip and
    /// an animation there and back).
    #[arg(long)]
    pub interpolate: Option<String>,
    /// Frame rate of the animations (GIF and MP4), frames per second.
    #[arg(long, default_value_t = 12.5)]
    pub fps: f64,
    /// Formats of the animations: `gif`, `mp4` (H.264), or both (`gif,mp4`).
    #[arg(long, value_delimiter = ',', default_value = "gif,mp4")]
    pub video: Vec<VideoFormat>,
    /// Compute backend: cpu or wgpu.
    #[arg(long, default_value = "cpu")]
    pub backend: BackendKind,
    /// Output folder.
    #[arg(long, default_value = "samples")]
    pub out: PathBuf,
}

/// The relit images side by side in one row.
fn strip(layers: &SampleLayers) -> ContactSheet {
    let s = layers.side;
    let mut sheet = ContactSheet::new(s, s, layers.relit.len(), 1);
    for (i, tile) in layers.relit.iter().enumerate() {
        sheet.put(i, 0, tile);
    }
    sheet
}

pub(super) fn save_sheet(path: &Path, sheet: &ContactSheet) -> anyhow::Result<()> {
    io::save_png(path, sheet.width(), sheet.height(), &sheet.to_u8())?;
    println!("wrote {}", path.display());
    Ok(())
}

/// A file format of the animations.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum VideoFormat {
    Gif,
    Mp4,
}

/// How animations are written: formats and frame rate.
struct Animations<'a> {
    formats: &'a [VideoFormat],
    fps: f64,
}

impl Animations<'_> {
    /// Writes `frames` as `<stem>.gif` and/or `<stem>.mp4` in `folder`.
    fn save(&self, folder: &Path, stem: &str, frames: &[ContactSheet]) -> anyhow::Result<()> {
        let (w, h) = (frames[0].width(), frames[0].height());
        let pixels: Vec<Vec<[u8; 3]>> = frames.iter().map(|f| f.to_u8()).collect();
        for format in self.formats {
            let path = match format {
                VideoFormat::Gif => {
                    let path = folder.join(format!("{stem}.gif"));
                    save_gif(&path, w, h, &pixels, (1000.0 / self.fps).round() as u32)?;
                    path
                }
                VideoFormat::Mp4 => {
                    let path = folder.join(format!("{stem}.mp4"));
                    save_mp4(&path, w, h, &pixels, self.fps)?;
                    path
                }
            };
            println!(
                "wrote {} ({} frames, {:.1} s at {} fps)",
                path.display(),
                frames.len(),
                frames.len() as f64 / self.fps,
                self.fps
            );
        }
        Ok(())
    }
}

/// The most frames of a rotation (82 s at the default 12.5 fps).
const MAX_FRAMES: usize = 1024;
/// The most cameras (`--yaw` x `--pitch`), and the most environments (`--hdri`), of one call.
const MAX_VIEWS: usize = 64;

pub fn run(args: SampleArgs) -> anyhow::Result<()> {
    let seeds = parse_seeds(&args.seeds, 64)?;
    for (flag, values) in [("--yaw", &args.yaw), ("--pitch", &args.pitch)] {
        if let Some(v) = values.iter().find(|v| !v.is_finite() || v.abs() > 90.0) {
            bail!("{flag} {v}: degrees must be finite and within [-90, 90]");
        }
    }
    if !(args.fps.is_finite() && (1.0..=120.0).contains(&args.fps)) {
        bail!("--fps {}: give a frame rate from 1 to 120", args.fps);
    }
    for (flag, frames) in [
        ("--rotate-light", args.rotate_light),
        ("--rotate-camera", args.rotate_camera),
    ] {
        if frames > MAX_FRAMES {
            bail!("{flag} {frames}: give at most {MAX_FRAMES} frames (0 for none)");
        }
    }
    let views = args.yaw.len() * args.pitch.len();
    if views > MAX_VIEWS {
        bail!(
            "--yaw and --pitch give {views} cameras ({} x {}): give at most {MAX_VIEWS}",
            args.yaw.len(),
            args.pitch.len()
        );
    }
    if args.hdri.len() > MAX_VIEWS {
        bail!(
            "--hdri names {} maps: give at most {MAX_VIEWS}",
            args.hdri.len()
        );
    }
    super::output_folder(&args.out)?;
    let animations = Animations {
        formats: &args.video,
        fps: args.fps,
    };
    let interpolation = args
        .interpolate
        .as_deref()
        .map(|text| -> anyhow::Result<(u64, u64, usize)> {
            let bad = || format!("--interpolate {text:?}: expected A,B,N like 0,5,8");
            let parts: Vec<&str> = text.split(',').map(str::trim).collect();
            let [a, b, n] = parts.as_slice() else {
                bail!(bad());
            };
            let n: usize = n.parse().with_context(bad)?;
            if !(2..=64).contains(&n) {
                bail!("{}: N must be in 2..=64", bad());
            }
            Ok((
                a.parse().with_context(bad)?,
                b.parse().with_context(bad)?,
                n,
            ))
        })
        .transpose()?;
    let started = Instant::now();
    let trained = load_for_sampling(&args.checkpoint, args.backend)?;
    let (g, config, device) = (&trained.g, &trained.config, &trained.device);
    println!(
        "checkpoint {} ({} model, {:.2} kimg)",
        trained.origin.display(),
        config.model.preset,
        trained.state.images as f64 / 1000.0
    );
    let envs = environments(&args.hdri, &["sunrise"])?;
    let bg = config.data.albedo_background();
    let z_dim = config.generator().mapping.z_dim;
    let z = sampling::latents(&seeds, z_dim, device);
    let n = seeds.len();
    let first_pose = Pose::from_degrees(args.yaw[0], args.pitch[0]);

    for env in &envs {
        // Every layer, one row per seed.
        let layers =
            sampling::render_under(g, z.clone(), &vec![first_pose; n], &env.lights, 0.0, bg)?;
        save_sheet(
            &args.out.join(format!("layers-{}.png", env.name)),
            &sampling::grid(&layers),
        )?;
        // HDR layers of each seed as EXR.
        let exr = args.out.join("exr");
        std::fs::create_dir_all(&exr)?;
        let s = layers.side;
        for (i, seed) in seeds.iter().enumerate() {
            for (layer, texels) in [
                ("albedo", &layers.albedo[i]),
                ("diffuse", &layers.diffuse[i]),
                ("specular", &layers.specular[i]),
                ("normals", &layers.normals[i]),
            ] {
                let path = exr.join(format!("seed{seed}-{}-{layer}.exr", env.name));
                io::save_exr(&path, s, s, texels)?;
            }
        }
        println!(
            "wrote {} (albedo, diffuse, specular, normals per seed)",
            exr.display()
        );
        // The relit image from every camera: one row per seed, one column per (yaw, pitch).
        let views: Vec<Pose> = args
            .pitch
            .iter()
            .flat_map(|&p| args.yaw.iter().map(move |&y| Pose::from_degrees(y, p)))
            .collect();
        let mut sheet = ContactSheet::new(s, s, views.len(), n);
        for (column, &pose) in views.iter().enumerate() {
            let l = sampling::render_under(g, z.clone(), &vec![pose; n], &env.lights, 0.0, bg)?;
            for (row, tile) in l.relit.iter().enumerate() {
                sheet.put(column, row, tile);
            }
        }
        save_sheet(&args.out.join(format!("views-{}.png", env.name)), &sheet)?;
    }

    let env = &envs[0];
    if args.rotate_light > 0 {
        let frames = (0..args.rotate_light)
            .map(|f| {
                let yaw = std::f64::consts::TAU * f as f64 / args.rotate_light as f64;
                let l = sampling::render_under(
                    g,
                    z.clone(),
                    &vec![first_pose; n],
                    &env.lights,
                    yaw,
                    bg,
                )?;
                Ok(strip(&l))
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        animations.save(&args.out, "rotate-light", &frames)?;
    }
    if args.rotate_camera > 0 {
        let frames = (0..args.rotate_camera)
            .map(|f| {
                let phase = std::f64::consts::TAU * f as f64 / args.rotate_camera as f64;
                let pose = Pose::new(30f64.to_radians() * phase.sin(), first_pose.pitch);
                let l = sampling::render_under(g, z.clone(), &vec![pose; n], &env.lights, 0.0, bg)?;
                Ok(strip(&l))
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        animations.save(&args.out, "rotate-camera", &frames)?;
    }
    if let Some((a, b, steps)) = interpolation {
        let zi = sampling::interpolate(a, b, steps, z_dim, device);
        let l = sampling::render_under(g, zi, &vec![first_pose; steps], &env.lights, 0.0, bg)?;
        let sheet = strip(&l);
        save_sheet(&args.out.join(format!("interpolate-{a}-{b}.png")), &sheet)?;
        let s = l.side;
        let frames: Vec<ContactSheet> = l
            .relit
            .iter()
            .chain(l.relit.iter().rev())
            .map(|tile| {
                let mut f = ContactSheet::new(s, s, 1, 1);
                f.put(0, 0, tile);
                f
            })
            .collect();
        animations.save(&args.out, &format!("interpolate-{a}-{b}"), &frames)?;
    }
    println!("done in {:.1} s", started.elapsed().as_secs_f64());
    Ok(())
}
