//! `volux export`: what a trained generator makes, in formats other tools open. `volux export
//! mesh` writes one latent's head as a triangle mesh (marching cubes on its density, albedo
//! vertex colours, exact normals), PLY or OBJ.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::{Args, Subcommand};
use volux_model::backend::BackendKind;
use volux_train::mesh::{MeshOptions, generator_mesh, save_mesh};
use volux_train::pretrained::load_for_sampling;

#[derive(Debug, Subcommand)]
pub enum ExportCommand {
    /// One latent's head as a mesh: marching cubes on the density in the cube [-0.5, 0.5]^3,
    /// vertex colours from the albedo, normals from the density's exact gradient.
    Mesh(MeshArgs),
}

#[derive(Debug, Args)]
pub struct MeshArgs {
    /// A checkpoint folder, a run folder (its newest checkpoint is used), or the name of a
    /// model shipped in the binary (`quickstart`).
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// Latent seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Grid points per side of the cube.
    #[arg(long, default_value_t = 128)]
    pub resolution: usize,
    /// Iso-level of the density; default: the density at which a frontal ray's transmittance
    /// falls to one half (the median over the rays the head stops), where the renderer puts
    /// the surface.
    #[arg(long, allow_hyphen_values = true)]
    pub threshold: Option<f64>,
    /// Leave out connected pieces with fewer than this fraction of the largest piece's
    /// vertices (specks of density beside the head); 0 keeps every piece.
    #[arg(long, default_value_t = MeshOptions::MIN_PIECE, allow_hyphen_values = true)]
    pub min_piece: f64,
    /// Compute backend: cpu or wgpu.
    #[arg(long, default_value = "cpu")]
    pub backend: BackendKind,
    /// Output file: `.ply` (binary) or `.obj`.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(cmd: ExportCommand) -> anyhow::Result<()> {
    match cmd {
        ExportCommand::Mesh(args) => mesh(args),
    }
}

fn mesh(args: MeshArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    super::output_file(&args.out)?;
    let options = MeshOptions {
        resolution: args.resolution,
        threshold: args.threshold,
        min_piece: args.min_piece,
    };
    options.check()?;
    let model = load_for_sampling(&args.checkpoint, args.backend)?;
    println!(
        "checkpoint {} ({} model, {:.2} kimg)",
        model.origin.display(),
        model.config.model.preset,
        model.state.images as f64 / 1000.0
    );
    let made = generator_mesh(&model, args.seed, options)
        .with_context(|| format!("seed {} at --resolution {}", args.seed, args.resolution))?;
    save_mesh(&args.out, &made.mesh)?;
    let pieces = made.pieces;
    println!(
        "wrote {}: {} vertices, {} triangles in {} piece{}, {} smaller piece{} ({} vertices) left out; iso-level {:.4} ({}; density {:.3e} to {:.3e} on the grid) in {:.1} s",
        args.out.display(),
        made.mesh.positions.len(),
        made.mesh.triangles.len(),
        pieces.kept,
        if pieces.kept == 1 { "" } else { "s" },
        pieces.dropped,
        if pieces.dropped == 1 { "" } else { "s" },
        pieces.dropped_vertices,
        made.level,
        if args.threshold.is_some() {
            "given"
        } else {
            "frontal"
        },
        made.min,
        made.max,
        started.elapsed().as_secs_f64()
    );
    Ok(())
}
