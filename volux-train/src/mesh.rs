//! Shape export (EG3D's `extract_shapes`): the density of one latent sampled on a cube of grid
//! points, its iso-surface by marching cubes, each vertex coloured by the field's albedo and
//! given the field's exact normal (`-grad sigma / |grad sigma|`, the reverse sweep the renderer
//! uses, not a finite difference of the grid), written as binary PLY or OBJ.
//!
//! World coordinates are the generator's (docs/conventions.md): +y up, the frontal camera on
//! +z, the head inside `[-0.5, 0.5]^3`, the cube the frontal camera's frustum spans (half-height
//! 0.45 at the origin, rays from z = 0.45 to z = -0.6).
//!
//! The iso-level: a density has no natural surface value, so unless one is given, the level
//! is read off the field itself as the surface the renderer shows. Along each grid column
//! seen by the frontal camera (from +z), transmittance `exp(-sum sigma dz)` falls from 1; the
//! level is the median, over the columns the head stops (transmittance below 1/2 at the far
//! end), of the density where it crosses 1/2, i.e. where the expected image puts the surface.
//! Grid points on the cube's faces count as outside, so the mesh is closed.
//!
//! A trained field can hold specks of density beside the head (floaters); marching cubes makes
//! each a small closed piece. Pieces with fewer than a given fraction of the largest piece's
//! vertices are left out ([`drop_small_pieces`]; `volux export mesh --min-piece`, 0 keeps
//! them).

use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use burn::tensor::{Tensor, TensorData};
use isosurface::marching_cubes::MarchingCubes;
use isosurface::source::Source;
use volux_envmap::durable::{FileError, write_atomically};
use volux_envmap::io::linear_to_srgb;
use volux_model::backend::to_f32_vec;
use volux_model::field::FieldWants;

use crate::pretrained::TrainedGenerator;
use crate::sampling;

/// Half the side of the exported cube, world units.
pub const HALF_SIDE: f64 = 0.5;

/// Points per field query: bounds the memory of one query (a few MiB per channel).
const CHUNK: usize = 1 << 16;

/// Why a mesh cannot be made or written.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    #[error("--resolution {0}: give 16 to 512 grid points per side")]
    Resolution(usize),
    #[error("--threshold {0}: the iso-level must be a positive finite density")]
    Threshold(f64),
    #[error(
        "--min-piece {0}: give a fraction of the largest piece's vertices from 0 (keep every piece) to 1"
    )]
    MinPiece(f64),
    #[error(
        "the density is empty: no frontal ray is stopped by it (max density {max}), so there is no surface to choose a level for; give --threshold"
    )]
    Empty { max: f32 },
    #[error("the iso-level {level} leaves no surface (density ranges {min} to {max})")]
    NoSurface { level: f32, min: f32, max: f32 },
    #[error("{path}: unknown mesh format (give a .ply or .obj file)")]
    Format { path: PathBuf },
    #[error("writing {path}")]
    Write {
        path: PathBuf,
        #[source]
        source: FileError,
    },
}

/// Densities at `n^3` grid points spanning `[-HALF_SIDE, HALF_SIDE]^3`, x fastest, then y, z.
#[derive(Clone, Debug)]
pub struct DensityGrid {
    pub n: usize,
    pub values: Vec<f32>,
}

impl DensityGrid {
    /// World position of grid point `(i, j, k)` (x, y, z indices).
    pub fn position(n: usize, i: usize, j: usize, k: usize) -> [f32; 3] {
        let at = |i: usize| (-HALF_SIDE + 2.0 * HALF_SIDE * i as f64 / (n - 1) as f64) as f32;
        [at(i), at(j), at(k)]
    }

    /// Evaluates `density` (world points in, densities out) on the grid, `CHUNK` points at a
    /// time.
    pub fn sample(n: usize, mut density: impl FnMut(&[[f32; 3]]) -> Vec<f32>) -> Self {
        let mut values = Vec::with_capacity(n * n * n);
        let mut points = Vec::with_capacity(CHUNK);
        for index in 0..n * n * n {
            let (i, j, k) = (index % n, index / n % n, index / (n * n));
            points.push(Self::position(n, i, j, k));
            if points.len() == CHUNK || index + 1 == n * n * n {
                let d = density(&points);
                assert_eq!(d.len(), points.len(), "one density per point");
                values.extend(d);
                points.clear();
            }
        }
        Self { n, values }
    }

    fn at(&self, i: usize, j: usize, k: usize) -> f32 {
        self.values[(k * self.n + j) * self.n + i]
    }

    /// The level the frontal camera sees as the surface (module docs); `None` when no column
    /// is stopped.
    pub fn frontal_level(&self) -> Option<f32> {
        let n = self.n;
        let dz = 2.0 * HALF_SIDE / (n - 1) as f64;
        let mut crossings = Vec::new();
        for j in 0..n {
            for i in 0..n {
                let mut optical = 0.0f64;
                for k in (0..n).rev() {
                    let sigma = self.at(i, j, k);
                    optical += sigma.max(0.0) as f64 * dz;
                    if optical > std::f64::consts::LN_2 {
                        crossings.push(sigma);
                        break;
                    }
                }
            }
        }
        if crossings.is_empty() {
            return None;
        }
        let middle = crossings.len() / 2;
        let (_, median, _) = crossings.select_nth_unstable_by(middle, f32::total_cmp);
        Some(*median)
    }

    fn range(&self) -> (f32, f32) {
        self.values
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            })
    }
}

/// A grid edge: its lower corner and its axis (3: not an edge, a vertex kept as it was).
type EdgeKey = (i64, i64, i64, usize);

/// The grid as `isosurface`'s source: `level - sigma` (negative inside), with the cube's faces
/// and anything beyond them outside.
struct Inside<'a> {
    grid: &'a DensityGrid,
    level: f32,
}

impl Inside<'_> {
    /// The value at integer grid point `p` (any integers; outside the open cube: outside).
    fn value(&self, p: [i64; 3]) -> f32 {
        let n = self.grid.n as i64;
        if p.iter().all(|&c| c >= 1 && c <= n - 2) {
            self.level - self.grid.at(p[0] as usize, p[1] as usize, p[2] as usize)
        } else {
            1.0
        }
    }

    /// The grid edge a vertex of `isosurface` (at `t` in `[0, 1]^3`) lies on, as its key
    /// (lower corner, axis) and its crossing recomputed from the edge's two values in a fixed
    /// order, in grid units: the same bits from every cell that shares the edge.
    fn on_edge(&self, t: [f32; 3]) -> Option<(EdgeKey, [f64; 3])> {
        let g = t.map(|c| c as f64 * (self.grid.n - 1) as f64);
        let off_grid = g.map(|c| (c - c.round()).abs());
        let axis = (0..3).max_by(|&a, &b| off_grid[a].total_cmp(&off_grid[b]))?;
        let corner = g.map(|c| c.round() as i64);
        let base = g[axis].floor() as i64;
        [base, base - 1, base + 1].into_iter().find_map(|lower| {
            let mut p0 = corner;
            p0[axis] = lower;
            let mut p1 = p0;
            p1[axis] = lower + 1;
            let (v0, v1) = (self.value(p0), self.value(p1));
            if (v0 <= 0.0) == (v1 <= 0.0) {
                return None;
            }
            let along = lower as f64 + v0 as f64 / (v0 as f64 - v1 as f64);
            if (along - g[axis]).abs() > 0.5 {
                return None;
            }
            let mut at = p0.map(|c| c as f64);
            at[axis] = along;
            Some(((p0[0], p0[1], p0[2], axis), at))
        })
    }
}

impl Source for Inside<'_> {
    fn sample(&self, x: f32, y: f32, z: f32) -> f32 {
        let scale = (self.grid.n - 1) as f32;
        self.value([x, y, z].map(|t| (t * scale).round() as i64))
    }
}

/// A triangle mesh in world coordinates; triangles wind counter-clockwise seen from outside.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub positions: Vec<[f32; 3]>,
    /// Unit normals pointing out of the surface.
    pub normals: Vec<[f32; 3]>,
    /// sRGB colours.
    pub colors: Vec<[u8; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

/// Marching cubes on `grid` at `level`: positions and triangles (counter-clockwise from
/// outside), without normals or colours. Vertices on one grid edge are one vertex, so a surface
/// inside the cube comes out closed.
pub fn marching_cubes(grid: &DensityGrid, level: f32) -> Mesh {
    let source = Inside { grid, level };
    let mut flat = Vec::new();
    let mut indices = Vec::new();
    MarchingCubes::new(grid.n).extract(&source, &mut flat, &mut indices);
    // `isosurface` computes a shared edge's vertex once per cell, from the edge's ends in the
    // cell's order (and its vertex cache misses some), so its copies differ in the last bits:
    // each vertex is recomputed on its edge and vertices are merged by edge.
    let to_world = |g: f64| (-HALF_SIDE + 2.0 * HALF_SIDE * g / (grid.n - 1) as f64) as f32;
    let mut by_edge = std::collections::HashMap::with_capacity(flat.len() / 3);
    let mut positions = Vec::with_capacity(flat.len() / 3);
    let remap: Vec<u32> = flat
        .chunks_exact(3)
        .map(|t| {
            let t = [t[0], t[1], t[2]];
            let (key, at) = source.on_edge(t).unwrap_or_else(|| {
                // Not on an edge with a crossing (cannot happen for the crate's vertices): kept
                // as it is, merged only with bit-identical copies.
                let bits = t.map(|c| -(c.to_bits() as i64) - 1);
                (
                    (bits[0], bits[1], bits[2], 3),
                    t.map(|c| c as f64 * (grid.n - 1) as f64),
                )
            });
            *by_edge.entry(key).or_insert_with(|| {
                positions.push(at.map(to_world));
                (positions.len() - 1) as u32
            })
        })
        .collect();
    // `isosurface` winds its triangles clockwise seen from outside.
    let triangles = indices
        .chunks_exact(3)
        .map(|t| [t[0], t[2], t[1]].map(|i| remap[i as usize]))
        .filter(|t| t[0] != t[1] && t[1] != t[2] && t[0] != t[2])
        .collect();
    Mesh {
        positions,
        triangles,
        ..Mesh::default()
    }
}

/// The connected piece of each vertex (vertices joined by the triangles' edges), as the index
/// of one vertex of its piece: union-find with path halving.
pub fn pieces(mesh: &Mesh) -> Vec<u32> {
    fn root(parent: &mut [u32], mut v: u32) -> u32 {
        while parent[v as usize] != v {
            parent[v as usize] = parent[parent[v as usize] as usize];
            v = parent[v as usize];
        }
        v
    }
    let mut parent: Vec<u32> = (0..mesh.positions.len() as u32).collect();
    for t in &mesh.triangles {
        for k in 1..3 {
            let (a, b) = (root(&mut parent, t[0]), root(&mut parent, t[k]));
            parent[a as usize] = b;
        }
    }
    (0..parent.len() as u32)
        .map(|v| root(&mut parent, v))
        .collect()
}

/// What [`drop_small_pieces`] kept and left out.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Pieces {
    /// Connected pieces kept and dropped.
    pub kept: usize,
    pub dropped: usize,
    /// Vertices of the dropped pieces.
    pub dropped_vertices: usize,
}

/// `mesh` without its connected pieces of fewer than `min_piece` times the largest piece's
/// vertices (the specks of density a GAN leaves beside a head); `0` keeps every piece, `1`
/// the largest (and any as large). Vertices and triangles keep their order; normals and
/// colours, where present, go with their vertices.
pub fn drop_small_pieces(mesh: &Mesh, min_piece: f64) -> Result<(Mesh, Pieces), MeshError> {
    if !(0.0..=1.0).contains(&min_piece) {
        return Err(MeshError::MinPiece(min_piece));
    }
    let piece = pieces(mesh);
    let mut sizes = std::collections::HashMap::<u32, usize>::new();
    for &r in &piece {
        *sizes.entry(r).or_default() += 1;
    }
    let largest = sizes.values().copied().max().unwrap_or(0);
    let keep = |r: &u32| sizes[r] as f64 >= min_piece * largest as f64;
    let kept = sizes.keys().filter(|r| keep(r)).count();
    let mut index = vec![u32::MAX; piece.len()];
    let mut out = Mesh::default();
    for (v, r) in piece.iter().enumerate() {
        if keep(r) {
            index[v] = out.positions.len() as u32;
            out.positions.push(mesh.positions[v]);
            if let Some(&n) = mesh.normals.get(v) {
                out.normals.push(n);
            }
            if let Some(&c) = mesh.colors.get(v) {
                out.colors.push(c);
            }
        }
    }
    out.triangles = mesh
        .triangles
        .iter()
        .filter(|t| index[t[0] as usize] != u32::MAX)
        .map(|t| t.map(|v| index[v as usize]))
        .collect();
    let pieces = Pieces {
        kept,
        dropped: sizes.len() - kept,
        dropped_vertices: mesh.positions.len() - out.positions.len(),
    };
    Ok((out, pieces))
}

/// Options of [`generator_mesh`].
#[derive(Clone, Copy, Debug)]
pub struct MeshOptions {
    /// Grid points per side.
    pub resolution: usize,
    /// The iso-level; `None`: the frontal level (module docs).
    pub threshold: Option<f64>,
    /// Connected pieces with fewer than this fraction of the largest piece's vertices are
    /// left out ([`drop_small_pieces`]); `0` keeps every piece.
    pub min_piece: f64,
}

impl MeshOptions {
    /// The default piece filter of `volux export mesh`: a twentieth of the head. The specks of
    /// the shipped model are tens of vertices beside a head of tens of thousands.
    pub const MIN_PIECE: f64 = 0.05;

    /// Refuses a resolution outside 16 to 512, a threshold that is not a positive finite
    /// density and a piece fraction outside `[0, 1]`, naming the flag (before any work).
    pub fn check(&self) -> Result<(), MeshError> {
        if !(16..=512).contains(&self.resolution) {
            return Err(MeshError::Resolution(self.resolution));
        }
        if let Some(t) = self.threshold
            && !(t.is_finite() && t > 0.0)
        {
            return Err(MeshError::Threshold(t));
        }
        if !(0.0..=1.0).contains(&self.min_piece) {
            return Err(MeshError::MinPiece(self.min_piece));
        }
        Ok(())
    }
}

/// What [`generator_mesh`] made.
#[derive(Clone, Debug)]
pub struct GeneratorMesh {
    pub mesh: Mesh,
    /// The iso-level used.
    pub level: f32,
    /// The density's range on the grid.
    pub min: f32,
    pub max: f32,
    /// The connected pieces kept and left out.
    pub pieces: Pieces,
}

/// The mesh of seed `seed`'s head: density on the grid, marching cubes, the pieces smaller
/// than `options.min_piece` of the largest left out, then albedo and the exact normal at every
/// vertex.
pub fn generator_mesh(
    model: &TrainedGenerator,
    seed: u64,
    options: MeshOptions,
) -> Result<GeneratorMesh, MeshError> {
    options.check()?;
    let (g, device) = (&model.g, &model.device);
    let z_dim = model.config.generator().mapping.z_dim;
    let z = sampling::latents(&[seed], z_dim, device);
    let w = g.mapping.forward(z);
    let query = |points: &[[f32; 3]], wants: FieldWants| {
        let flat: Vec<f32> = points.iter().flatten().copied().collect();
        let p = Tensor::<3>::from_data(TensorData::new(flat, [1, points.len(), 3]), device);
        g.neiif.forward(p, w.clone(), wants)
    };
    let grid = DensityGrid::sample(options.resolution, |points| {
        to_f32_vec(query(points, FieldWants::DENSITY).sigma)
    });
    let (min, max) = grid.range();
    let level = match options.threshold {
        Some(t) => t as f32,
        None => grid.frontal_level().ok_or(MeshError::Empty { max })?,
    };
    let mesh = marching_cubes(&grid, level);
    if mesh.triangles.is_empty() {
        return Err(MeshError::NoSurface { level, min, max });
    }
    // Before the vertices' albedo and normals: a dropped piece needs neither.
    let (mut mesh, pieces) = drop_small_pieces(&mesh, options.min_piece)?;
    let (mut normals, mut colors) = (Vec::new(), Vec::new());
    for points in mesh.positions.chunks(CHUNK) {
        let out = query(points, FieldWants::ALL);
        let n = to_f32_vec(out.normals.expect("asked for normals"));
        let albedo = to_f32_vec(out.albedo.expect("asked for albedo"));
        normals.extend(n.chunks_exact(3).map(|n| [n[0], n[1], n[2]]));
        colors.extend(albedo.chunks_exact(3).map(|a| {
            [0, 1, 2].map(|c| (linear_to_srgb(a[c]).clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
        }));
    }
    (mesh.normals, mesh.colors) = (normals, colors);
    Ok(GeneratorMesh {
        mesh,
        level,
        min,
        max,
        pieces,
    })
}

/// Writes `mesh` as binary little-endian PLY (`.ply`) or OBJ (`.obj`, colours as the common
/// `v x y z r g b` extension), atomically.
pub fn save_mesh(path: &Path, mesh: &Mesh) -> Result<(), MeshError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    let ply = match ext.as_deref() {
        Some("ply") => true,
        Some("obj") => false,
        _ => {
            return Err(MeshError::Format {
                path: path.to_path_buf(),
            });
        }
    };
    write_atomically(path, |tmp| {
        let file = std::fs::File::create(tmp).map_err(FileError::at(tmp))?;
        let mut out = BufWriter::new(file);
        let written = if ply {
            write_ply(&mut out, mesh)
        } else {
            write_obj(&mut out, mesh)
        };
        written
            .and_then(|()| out.flush())
            .map_err(FileError::at(tmp))
    })
    .map_err(|source| MeshError::Write {
        path: path.to_path_buf(),
        source,
    })
}

fn write_ply(out: &mut impl Write, mesh: &Mesh) -> std::io::Result<()> {
    let with_normals = mesh.normals.len() == mesh.positions.len();
    let with_colors = mesh.colors.len() == mesh.positions.len();
    writeln!(out, "ply\nformat binary_little_endian 1.0\ncomment volux")?;
    writeln!(out, "element vertex {}", mesh.positions.len())?;
    writeln!(out, "property float x\nproperty float y\nproperty float z")?;
    if with_normals {
        writeln!(
            out,
            "property float nx\nproperty float ny\nproperty float nz"
        )?;
    }
    if with_colors {
        writeln!(
            out,
            "property uchar red\nproperty uchar green\nproperty uchar blue"
        )?;
    }
    writeln!(out, "element face {}", mesh.triangles.len())?;
    writeln!(out, "property list uchar int vertex_indices\nend_header")?;
    for (v, p) in mesh.positions.iter().enumerate() {
        for c in p {
            out.write_all(&c.to_le_bytes())?;
        }
        if with_normals {
            for c in mesh.normals[v] {
                out.write_all(&c.to_le_bytes())?;
            }
        }
        if with_colors {
            out.write_all(&mesh.colors[v])?;
        }
    }
    for t in &mesh.triangles {
        out.write_all(&[3])?;
        for &i in t {
            out.write_all(&(i as i32).to_le_bytes())?;
        }
    }
    Ok(())
}

fn write_obj(out: &mut impl Write, mesh: &Mesh) -> std::io::Result<()> {
    let with_normals = mesh.normals.len() == mesh.positions.len();
    let with_colors = mesh.colors.len() == mesh.positions.len();
    writeln!(
        out,
        "# volux: {} vertices, {} triangles",
        mesh.positions.len(),
        mesh.triangles.len()
    )?;
    for (v, p) in mesh.positions.iter().enumerate() {
        write!(out, "v {} {} {}", p[0], p[1], p[2])?;
        if with_colors {
            let c = mesh.colors[v].map(|c| c as f32 / 255.0);
            write!(out, " {:.4} {:.4} {:.4}", c[0], c[1], c[2])?;
        }
        writeln!(out)?;
    }
    if with_normals {
        for n in &mesh.normals {
            writeln!(out, "vn {} {} {}", n[0], n[1], n[2])?;
        }
    }
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| i + 1);
        if with_normals {
            writeln!(out, "f {a}//{a} {b}//{b} {c}//{c}")?;
        } else {
            writeln!(out, "f {a} {b} {c}")?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests;
