use super::*;

fn length(p: [f32; 3]) -> f64 {
    p.iter().map(|&c| (c as f64).powi(2)).sum::<f64>().sqrt()
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f64; 3] {
    [0, 1, 2].map(|c| a[c] as f64 - b[c] as f64)
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Area-weighted face normals summed at each vertex, normalised: the mesh's own normals.
fn geometric_normals(mesh: &Mesh) -> Vec<[f64; 3]> {
    let mut sum = vec![[0.0f64; 3]; mesh.positions.len()];
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.positions[i as usize]);
        let n = cross(sub(b, a), sub(c, a));
        for &i in t {
            for k in 0..3 {
                sum[i as usize][k] += n[k];
            }
        }
    }
    sum.into_iter()
        .map(|n| {
            let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt().max(1e-30);
            n.map(|c| c / l)
        })
        .collect()
}

/// A ball of radius `r` whose density rises from 0 to `peak` over a shell of width `width`.
fn ball(r: f64, peak: f64, width: f64) -> impl Fn(&[[f32; 3]]) -> Vec<f32> {
    move |points| {
        points
            .iter()
            .map(|&p| (peak / (1.0 + ((length(p) - r) / width).exp())) as f32)
            .collect()
    }
}

#[test]
fn a_sphere_comes_out_at_its_radius_closed_and_facing_outwards() {
    let (r, n) = (0.3, 64);
    let grid = DensityGrid::sample(n, ball(r, 100.0, 0.03));
    let mesh = marching_cubes(&grid, 50.0);
    assert!(mesh.triangles.len() > 1000, "{}", mesh.triangles.len());
    // Every vertex on the sphere, to a small fraction of a cell (0.016 here).
    let worst = mesh
        .positions
        .iter()
        .map(|&p| (length(p) - r).abs())
        .fold(0.0, f64::max);
    assert!(worst < 0.003, "worst radius error {worst}");
    // Closed: every edge is shared by exactly two triangles, in opposite directions.
    let mut edges = std::collections::HashMap::new();
    for t in &mesh.triangles {
        for k in 0..3 {
            *edges.entry((t[k], t[(k + 1) % 3])).or_insert(0) += 1;
        }
    }
    for (&(a, b), &count) in &edges {
        assert_eq!(count, 1, "edge {a}-{b} used {count} times one way");
        assert_eq!(edges.get(&(b, a)), Some(&1), "edge {a}-{b} has no twin");
    }
    // Counter-clockwise from outside: the mesh's normals point away from the centre, within
    // a few degrees of the exact radial direction.
    let normals = geometric_normals(&mesh);
    let mut worst_degrees = 0.0f64;
    for (p, n) in mesh.positions.iter().zip(&normals) {
        let l = length(*p);
        let dot: f64 = (0..3).map(|k| n[k] * p[k] as f64 / l).sum();
        worst_degrees = worst_degrees.max(dot.clamp(-1.0, 1.0).acos().to_degrees());
    }
    assert!(worst_degrees < 8.0, "worst normal {worst_degrees} deg");
    // The volume of the mesh is the ball's, to the grid's accuracy.
    let volume: f64 = mesh
        .triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| mesh.positions[i as usize].map(|x| x as f64));
            let [ax, ay, az] = a;
            (ax * (b[1] * c[2] - b[2] * c[1]) - ay * (b[0] * c[2] - b[2] * c[0])
                + az * (b[0] * c[1] - b[1] * c[0]))
                / 6.0
        })
        .sum();
    let exact = 4.0 / 3.0 * std::f64::consts::PI * r.powi(3);
    assert!(
        (volume / exact - 1.0).abs() < 0.01,
        "volume {volume} against {exact}"
    );
}

#[test]
fn the_frontal_level_puts_the_surface_where_the_renderer_sees_it() {
    // A soft shell: the surface a frontal ray sees is where transmittance falls to 1/2.
    let (r, peak, width) = (0.3, 200.0, 0.01);
    let grid = DensityGrid::sample(96, ball(r, peak, width));
    let level = grid.frontal_level().expect("the ball stops rays");
    // The crossing along the central column, integrated finely in f64.
    let sigma = |z: f64| peak / (1.0 + ((z.abs() - r) / width).exp());
    let (mut z, mut optical, dz) = (HALF_SIDE, 0.0, 1e-6);
    while optical < std::f64::consts::LN_2 {
        optical += sigma(z) * dz;
        z -= dz;
    }
    let mesh = marching_cubes(&grid, level);
    // The mesh's front point on the axis is where the fine integration put the surface, to a
    // grid cell (0.0105).
    let front = mesh
        .positions
        .iter()
        .filter(|p| p[0].abs() < 0.02 && p[1].abs() < 0.02)
        .map(|p| p[2] as f64)
        .fold(f64::NEG_INFINITY, f64::max);
    assert!((front - z).abs() < 0.0105, "front {front} against {z}");
    assert!(level > 0.0 && (level as f64) < peak);
}

#[test]
fn empty_fields_extreme_levels_and_bad_paths_are_refused() {
    let empty = DensityGrid::sample(16, |p| vec![0.0; p.len()]);
    assert_eq!(empty.frontal_level(), None);
    assert!(marching_cubes(&empty, 1.0).triangles.is_empty());
    // A level above every density leaves nothing; a solid cube is closed by its faces.
    let solid = DensityGrid::sample(16, |p| vec![1e4; p.len()]);
    assert!(marching_cubes(&solid, 2e4).triangles.is_empty());
    let cube = marching_cubes(&solid, 1.0);
    assert!(!cube.triangles.is_empty());
    assert!(
        cube.positions
            .iter()
            .all(|p| p.iter().all(|c| c.abs() <= 0.5))
    );
    let dir = tempfile::tempdir().unwrap();
    let e = save_mesh(&dir.path().join("head.stl"), &cube).unwrap_err();
    assert!(e.to_string().contains("head.stl"), "{e}");
    let e = save_mesh(&dir.path().join("missing/head.ply"), &cube).unwrap_err();
    assert!(e.to_string().contains("missing/head.ply"), "{e}");
}

#[test]
fn ply_and_obj_files_hold_every_vertex_and_triangle() {
    let grid = DensityGrid::sample(24, ball(0.3, 100.0, 0.01));
    let mut mesh = marching_cubes(&grid, 50.0);
    mesh.normals = vec![[0.0, 0.0, 1.0]; mesh.positions.len()];
    mesh.colors = vec![[10, 20, 30]; mesh.positions.len()];
    let dir = tempfile::tempdir().unwrap();
    let ply = dir.path().join("ball.ply");
    save_mesh(&ply, &mesh).unwrap();
    let bytes = std::fs::read(&ply).unwrap();
    let end = b"end_header\n";
    let body = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
    let header = String::from_utf8_lossy(&bytes[..body]);
    let (v, f) = (mesh.positions.len(), mesh.triangles.len());
    assert!(header.contains(&format!("element vertex {v}")), "{header}");
    assert!(header.contains(&format!("element face {f}")), "{header}");
    assert_eq!(bytes.len() - body, v * (24 + 3) + f * 13);
    // The first vertex reads back.
    let x = f32::from_le_bytes(bytes[body..body + 4].try_into().unwrap());
    assert_eq!(x, mesh.positions[0][0]);
    let obj = dir.path().join("ball.obj");
    save_mesh(&obj, &mesh).unwrap();
    let text = std::fs::read_to_string(&obj).unwrap();
    assert_eq!(text.lines().filter(|l| l.starts_with("v ")).count(), v);
    assert_eq!(text.lines().filter(|l| l.starts_with("vn ")).count(), v);
    assert_eq!(text.lines().filter(|l| l.starts_with("f ")).count(), f);
}

#[test]
fn the_shipped_heads_field_normals_agree_with_their_meshes() {
    // On a trained generator the exact normals of the field and the normals of the extracted
    // mesh describe one surface.
    let model = crate::pretrained::shipped("quickstart")
        .unwrap()
        .load(volux_model::backend::BackendKind::Cpu)
        .unwrap();
    let options = |min_piece| MeshOptions {
        resolution: 48,
        threshold: None,
        min_piece,
    };
    let out = generator_mesh(&model, 0, options(0.0)).unwrap();
    let mesh = &out.mesh;
    assert_eq!(out.pieces.dropped, 0);
    assert_eq!(out.pieces.dropped_vertices, 0);
    assert!(mesh.triangles.len() > 500, "{}", mesh.triangles.len());
    assert_eq!(mesh.normals.len(), mesh.positions.len());
    assert_eq!(mesh.colors.len(), mesh.positions.len());
    let geometric = geometric_normals(mesh);
    let mut angles: Vec<f64> = mesh
        .normals
        .iter()
        .zip(&geometric)
        .map(|(n, g)| {
            let dot: f64 = (0..3).map(|k| n[k] as f64 * g[k]).sum();
            dot.clamp(-1.0, 1.0).acos().to_degrees()
        })
        .collect();
    angles.sort_by(f64::total_cmp);
    let median = angles[angles.len() / 2];
    assert!(median < 15.0, "median angle {median} deg");
    // A head, not a box: the head, the mesh's largest piece, holds nearly every vertex and
    // none near the cube's sides, front, back or top (the neck may leave through the bottom,
    // where the faces close it). The other pieces are the specks of density the shipped
    // model's template planes leave beside the head (docs/RESULTS.md, "Latest"): few, and
    // with `min_piece` 0 the mesh keeps them.
    let piece = pieces(mesh);
    let mut sizes = std::collections::HashMap::new();
    for &r in &piece {
        *sizes.entry(r).or_insert(0usize) += 1;
    }
    let (&head, &head_size) = sizes.iter().max_by_key(|&(_, &n)| n).unwrap();
    assert!(
        head_size * 100 >= 98 * mesh.positions.len(),
        "the head holds {head_size} of {} vertices",
        mesh.positions.len()
    );
    assert!(
        mesh.positions
            .iter()
            .zip(&piece)
            .filter(|&(_, &r)| r == head)
            .all(|(p, _)| p[0].abs() < 0.45 && p[2].abs() < 0.45 && p[1] < 0.45)
    );
    assert!(out.level > 0.0 && out.level < out.max);
    // The export's default filter leaves the head alone: the pieces are dropped before the
    // vertices' albedo and normals are queried, and what remains is the same as dropping them
    // from the whole mesh.
    let filtered = generator_mesh(&model, 0, options(MeshOptions::MIN_PIECE)).unwrap();
    let (expected, counts) = drop_small_pieces(mesh, MeshOptions::MIN_PIECE).unwrap();
    assert_eq!(filtered.mesh, expected);
    assert_eq!(filtered.pieces, counts);
    assert_eq!(counts.kept, 1, "{counts:?}");
    assert_eq!(counts.dropped, sizes.len() - 1);
    assert!(
        filtered
            .mesh
            .positions
            .iter()
            .all(|p| p[0].abs() < 0.45 && p[2].abs() < 0.45 && p[1] < 0.45)
    );
}

/// Both of two pieces kept, none dropped.
const TWO_KEPT: Pieces = Pieces {
    kept: 2,
    dropped: 0,
    dropped_vertices: 0,
};

/// Two balls far apart, of radius 0.25 and 0.06, as densities on a grid of 48.
fn two_balls() -> Mesh {
    let big = ball(0.25, 100.0, 0.01);
    let small = ball(0.06, 100.0, 0.01);
    let grid = DensityGrid::sample(48, |points| {
        let moved: Vec<[f32; 3]> = points
            .iter()
            .map(|p| [p[0] - 0.3, p[1] - 0.3, p[2] - 0.3])
            .collect();
        let (a, b) = (big(points), small(&moved));
        a.iter().zip(&b).map(|(a, b)| a + b).collect()
    });
    let mut mesh = marching_cubes(&grid, 50.0);
    mesh.normals = mesh.positions.iter().map(|p| [p[0], p[1], p[2]]).collect();
    mesh.colors = (0..mesh.positions.len())
        .map(|i| [i as u8, (i >> 8) as u8, 7])
        .collect();
    mesh
}

/// The pieces by breadth-first search over the triangles' edges, each vertex labelled with
/// the smallest vertex index of its piece: the plain reference of [`pieces`].
fn pieces_by_search(mesh: &Mesh) -> Vec<usize> {
    let n = mesh.positions.len();
    let mut neighbours = vec![Vec::new(); n];
    for t in &mesh.triangles {
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            neighbours[a as usize].push(b as usize);
            neighbours[b as usize].push(a as usize);
        }
    }
    let mut label = vec![usize::MAX; n];
    for start in 0..n {
        if label[start] != usize::MAX {
            continue;
        }
        let mut queue = std::collections::VecDeque::from([start]);
        label[start] = start;
        while let Some(v) = queue.pop_front() {
            for &u in &neighbours[v] {
                if label[u] == usize::MAX {
                    label[u] = start;
                    queue.push_back(u);
                }
            }
        }
    }
    label
}

#[test]
fn pieces_match_a_breadth_first_search_and_small_ones_are_dropped() {
    let mesh = two_balls();
    // The same partition as the reference: two vertices share a label in one exactly when
    // they share it in the other.
    use std::collections::HashSet;
    let (fast, reference) = (pieces(&mesh), pieces_by_search(&mesh));
    let pairs: HashSet<(u32, usize)> = fast.iter().copied().zip(reference.clone()).collect();
    assert_eq!(pairs.len(), 2, "two balls, two pieces: {pairs:?}");
    assert_eq!(fast.iter().collect::<HashSet<_>>().len(), 2);
    assert_eq!(reference.iter().collect::<HashSet<_>>().len(), 2);
    let near_small = |p: &[f32; 3]| length([p[0] - 0.3, p[1] - 0.3, p[2] - 0.3]) < 0.1;
    let small = mesh.positions.iter().filter(|p| near_small(p)).count();
    assert!(small > 20 && small * 4 < mesh.positions.len(), "{small}");

    // Below the small ball's share nothing goes; above it the small ball goes, whole, and
    // every kept triangle is an original triangle with its vertices' normals and colours.
    let share = small as f64 / (mesh.positions.len() - small) as f64;
    for min_piece in [0.0, share * 0.99] {
        let (kept, counts) = drop_small_pieces(&mesh, min_piece).unwrap();
        assert_eq!(kept, mesh, "min_piece {min_piece}");
        assert_eq!(counts, TWO_KEPT);
    }
    for min_piece in [share * 1.01, 0.5, 1.0] {
        let (kept, counts) = drop_small_pieces(&mesh, min_piece).unwrap();
        let expected = Pieces {
            kept: 1,
            dropped: 1,
            dropped_vertices: small,
        };
        assert_eq!(counts, expected, "min_piece {min_piece}");
        assert_eq!(kept.positions.len(), mesh.positions.len() - small);
        assert!(!kept.positions.iter().any(near_small));
        assert_eq!(kept.normals.len(), kept.positions.len());
        assert_eq!(kept.colors.len(), kept.positions.len());
        let corners = |m: &Mesh, t: &[u32; 3]| {
            t.map(|v| {
                (
                    m.positions[v as usize],
                    m.normals[v as usize],
                    m.colors[v as usize],
                )
            })
        };
        let expected: Vec<_> = mesh
            .triangles
            .iter()
            .filter(|t| !near_small(&mesh.positions[t[0] as usize]))
            .map(|t| corners(&mesh, t))
            .collect();
        let got: Vec<_> = kept.triangles.iter().map(|t| corners(&kept, t)).collect();
        assert_eq!(got, expected);
    }
}

#[test]
fn pieces_of_equal_size_empty_meshes_and_bad_fractions() {
    // A mesh of two separate triangles: two pieces of three vertices, both the largest.
    let mesh = Mesh {
        positions: vec![[0.0; 3]; 6],
        triangles: vec![[0, 1, 2], [3, 4, 5]],
        ..Mesh::default()
    };
    let (kept, counts) = drop_small_pieces(&mesh, 1.0).unwrap();
    assert_eq!(kept, mesh);
    assert_eq!(counts, TWO_KEPT);
    let (kept, counts) = drop_small_pieces(&Mesh::default(), 0.5).unwrap();
    assert_eq!(kept, Mesh::default());
    assert_eq!(counts, Pieces::default());
    for bad in [-0.01, 1.5, f64::NAN, f64::INFINITY] {
        let e = drop_small_pieces(&mesh, bad).unwrap_err();
        assert!(e.to_string().contains("--min-piece"), "{e}");
    }
}
