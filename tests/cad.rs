//! Meshes, signed distance, the rasteriser, and symmetry in the rendered images.

use alignist::cad::{CadError, Camera, Mesh, Pose, RenderOptions, Shape, SignedDistance, render};
use alignist::data::symsol_pose;
use alignist::so3::{SymmetryGroup, haar_rotation, haar_rotations};
use nalgebra::{Rotation3, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A cube of half-side 3 centred at (5, −2, 1), as 8 corners and 12 outward triangles.
fn cube_data() -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
    let mut v = Vec::new();
    for x in [-1.0, 1.0] {
        for y in [-1.0, 1.0] {
            for z in [-1.0, 1.0] {
                v.push([5.0 + 3.0 * x, -2.0 + 3.0 * y, 1.0 + 3.0 * z]);
            }
        }
    }
    // Index = 4·(x>0) + 2·(y>0) + (z>0).
    let f = vec![
        [0, 1, 3],
        [0, 3, 2], // x = −1
        [4, 6, 7],
        [4, 7, 5], // x = +1
        [0, 4, 5],
        [0, 5, 1], // y = −1
        [2, 3, 7],
        [2, 7, 6], // y = +1
        [0, 2, 6],
        [0, 6, 4], // z = −1
        [1, 5, 7],
        [1, 7, 3], // z = +1
    ];
    (v, f)
}

fn write_cube_files(dir: &std::path::Path) -> [std::path::PathBuf; 4] {
    let (v, f) = cube_data();
    let obj = dir.join("cube.obj");
    let mut text = String::from("# cube\n");
    for p in &v {
        text += &format!("v {} {} {}\n", p[0], p[1], p[2]);
    }
    for t in &f {
        text += &format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    std::fs::write(&obj, text).unwrap();

    let ply = dir.join("cube.ply");
    let mut text = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty double x\nproperty double y\n\
         property double z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        v.len(),
        f.len()
    );
    for p in &v {
        text += &format!("{} {} {}\n", p[0], p[1], p[2]);
    }
    for t in &f {
        text += &format!("3 {} {} {}\n", t[0], t[1], t[2]);
    }
    std::fs::write(&ply, text).unwrap();

    let stl = dir.join("cube.stl");
    let tris: Vec<stl_io::Triangle> = f
        .iter()
        .map(|t| stl_io::Triangle {
            normal: stl_io::Normal::new([0.0, 0.0, 0.0]),
            vertices: t.map(|i| {
                let p = v[i as usize];
                stl_io::Vertex::new([p[0] as f32, p[1] as f32, p[2] as f32])
            }),
        })
        .collect();
    let mut file = std::fs::File::create(&stl).unwrap();
    stl_io::write_stl(&mut file, tris.iter()).unwrap();
    [obj, ply, stl, write_gltf_cube(dir, &v, &f)]
}

/// The cube as glTF 2.0: vertices about the origin in a `.bin` buffer, moved to their place by
/// the node's translation (so the loader must apply node transforms).
fn write_gltf_cube(dir: &std::path::Path, v: &[[f64; 3]], f: &[[u32; 3]]) -> std::path::PathBuf {
    let shift = [5.0, -2.0, 1.0];
    let mut bin = Vec::new();
    for p in v {
        for k in 0..3 {
            bin.extend(((p[k] - shift[k]) as f32).to_le_bytes());
        }
    }
    for t in f {
        for i in t {
            bin.extend(i.to_le_bytes());
        }
    }
    std::fs::write(dir.join("cube.bin"), &bin).unwrap();
    let json = serde_json::json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "translation": shift}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "buffers": [{"uri": "cube.bin", "byteLength": bin.len()}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 96},
            {"buffer": 0, "byteOffset": 96, "byteLength": 144}
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3",
             "min": [-3.0, -3.0, -3.0], "max": [3.0, 3.0, 3.0]},
            {"bufferView": 1, "componentType": 5125, "count": 36, "type": "SCALAR"}
        ]
    });
    let path = dir.join("cube.gltf");
    std::fs::write(&path, serde_json::to_vec_pretty(&json).unwrap()).unwrap();
    path
}

/// The triangles of a mesh as sorted coordinate triples, independent of vertex order.
fn triangle_set(mesh: &Mesh) -> Vec<Vec<[i64; 3]>> {
    let mut out: Vec<Vec<[i64; 3]>> = mesh
        .triangles
        .iter()
        .map(|t| {
            // Keep the winding: rotate so the smallest corner comes first.
            let c: Vec<[i64; 3]> = t
                .iter()
                .map(|&i| {
                    mesh.vertices[i as usize]
                        .map(|x| (x * 1e5).round() as i64)
                        .into()
                })
                .collect();
            let k = (0..3).min_by_key(|&k| c[k]).unwrap();
            vec![c[k], c[(k + 1) % 3], c[(k + 2) % 3]]
        })
        .collect();
    out.sort();
    out
}

#[test]
fn the_same_cube_loads_alike_from_obj_ply_stl_and_gltf() {
    let dir = tempfile::tempdir().unwrap();
    let files = write_cube_files(dir.path());
    let meshes: Vec<(Mesh, _)> = files
        .iter()
        .map(|p| Mesh::load(p).unwrap().welded().normalised())
        .collect();
    for (mesh, norm) in &meshes {
        assert_eq!(mesh.vertices.len(), 8, "{}", mesh.source);
        assert_eq!(mesh.triangles.len(), 12);
        assert!((norm.scale - 3.0 * 3f64.sqrt()).abs() < 1e-5);
        assert!((Vector3::from(norm.centre) - Vector3::new(5.0, -2.0, 1.0)).norm() < 1e-5);
        mesh.check_closed().unwrap();
        let r = mesh
            .vertices
            .iter()
            .map(|v| v.norm())
            .fold(0.0f32, f32::max);
        assert!((r - 1.0).abs() < 1e-6);
    }
    assert_eq!(triangle_set(&meshes[0].0), triangle_set(&meshes[1].0));
    assert_eq!(triangle_set(&meshes[0].0), triangle_set(&meshes[2].0));
    assert_eq!(triangle_set(&meshes[0].0), triangle_set(&meshes[3].0));
}

fn cube_distance(p: &Vector3<f32>, a: f32) -> f32 {
    let q = p.map(|c| c.abs() - a);
    let outside = q.map(|c| c.max(0.0)).norm();
    let inside = q.x.max(q.y).max(q.z).min(0.0);
    outside + inside
}

#[test]
fn signed_distance_matches_the_analytic_cube() {
    let dir = tempfile::tempdir().unwrap();
    let files = write_cube_files(dir.path());
    let (mesh, _) = Mesh::load(&files[2]).unwrap().normalised();
    let sdf = SignedDistance::new(&mesh).unwrap();
    let a = 1.0 / 3f32.sqrt();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let points: Vec<Vector3<f32>> = (0..5000)
        .map(|_| {
            Vector3::new(
                rng.random_range(-1.5..1.5),
                rng.random_range(-1.5..1.5),
                rng.random_range(-1.5..1.5),
            )
        })
        .collect();
    let d = sdf.distances(&points);
    let mut inside = 0;
    for (p, d) in points.iter().zip(&d) {
        let exact = cube_distance(p, a);
        assert!((d - exact).abs() < 1e-4, "{p:?}: {d} vs {exact}");
        if exact < -1e-3 {
            assert!(*d < 0.0);
            inside += 1;
        }
        if exact > 1e-3 {
            assert!(*d > 0.0);
        }
    }
    assert!(inside > 100, "the sample reaches inside the cube");
}

#[test]
fn bad_meshes_are_refused_with_the_file_named() {
    let dir = tempfile::tempdir().unwrap();
    let empty = dir.path().join("empty.obj");
    std::fs::write(&empty, "# nothing\n").unwrap();
    let err = Mesh::load(&empty).unwrap_err();
    assert!(matches!(err, CadError::Empty(_)), "{err}");
    assert!(err.to_string().contains("empty.obj"));

    let quad = dir.path().join("quad.obj");
    std::fs::write(&quad, "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n").unwrap();
    let err = Mesh::load(&quad).unwrap_err();
    assert!(
        matches!(err, CadError::NotTriangular { corners: 4, .. }),
        "{err}"
    );
    assert!(err.to_string().contains("quad.obj"));

    let bad_index = dir.path().join("bad.ply");
    std::fs::write(
        &bad_index,
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
         property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n\
         0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n",
    )
    .unwrap();
    let err = Mesh::load(&bad_index).unwrap_err();
    assert!(
        err.to_string().contains("bad.ply") && err.to_string().contains("vertex 7"),
        "{err}"
    );

    // An open box (one face missing) has no signed distance.
    let files = write_cube_files(dir.path());
    let mut open = Mesh::load(&files[0]).unwrap();
    open.triangles.truncate(10);
    let err = SignedDistance::new(&open).err().expect("open mesh refused");
    assert!(matches!(err, CadError::NotClosed { .. }), "{err}");
    assert!(err.to_string().contains("cube.obj"));

    let txt = dir.path().join("model.txt");
    std::fs::write(&txt, "x").unwrap();
    assert!(matches!(Mesh::load(&txt), Err(CadError::UnknownFormat(_))));
    assert!(matches!(
        Mesh::load(&dir.path().join("missing.stl")),
        Err(CadError::Io { .. })
    ));
}

/// Area of the convex hull of 2-d points (monotone chain).
fn hull_area(mut pts: Vec<(f64, f64)>) -> f64 {
    pts.sort_by(|a, b| a.partial_cmp(b).unwrap());
    let cross = |o: (f64, f64), a: (f64, f64), b: (f64, f64)| {
        (a.0 - o.0) * (b.1 - o.1) - (a.1 - o.1) * (b.0 - o.0)
    };
    let mut hull: Vec<(f64, f64)> = Vec::new();
    for pass in 0..2 {
        let start = hull.len();
        let iter: Box<dyn Iterator<Item = &(f64, f64)>> = if pass == 0 {
            Box::new(pts.iter())
        } else {
            Box::new(pts.iter().rev())
        };
        for &p in iter {
            while hull.len() >= start + 2
                && cross(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0
            {
                hull.pop();
            }
            hull.push(p);
        }
        hull.pop();
    }
    let n = hull.len();
    (0..n)
        .map(|i| {
            let (a, b) = (hull[i], hull[(i + 1) % n]);
            a.0 * b.1 - b.0 * a.1
        })
        .sum::<f64>()
        .abs()
        / 2.0
}

#[test]
fn mask_area_matches_the_projected_cube() {
    let mesh = Shape::Cube.mesh();
    let camera = Camera::square(224);
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    for _ in 0..10 {
        let pose = symsol_pose(haar_rotation(&mut rng));
        let image = render(&mesh, &camera, &pose, &RenderOptions::default());
        let projected: Vec<(f64, f64)> = mesh
            .vertices
            .iter()
            .map(|v| camera.project(&(pose.rotation * v.cast::<f64>() + pose.translation)))
            .collect();
        let exact = hull_area(projected);
        let got = image.mask_area() as f64;
        assert!(
            (got - exact).abs() / exact < 0.02,
            "mask {got} vs projected {exact}"
        );
    }
}

#[test]
fn nocs_pixels_lie_on_the_surface_and_reproject_to_their_pixel() {
    let camera = Camera::square(128);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for shape in [Shape::Cube, Shape::Icosahedron, Shape::Cylinder] {
        let mesh = shape.mesh();
        let sdf = SignedDistance::new(&mesh).unwrap();
        let pose = symsol_pose(haar_rotation(&mut rng));
        let image = render(&mesh, &camera, &pose, &RenderOptions::default());
        let mut points = Vec::new();
        for (idx, &m) in image.mask.iter().enumerate() {
            if !m {
                assert!(image.nocs[idx][0].is_nan() && image.depth[idx] == 0.0);
                continue;
            }
            let p = Vector3::from(image.nocs[idx]);
            points.push(p);
            let cam = pose.rotation * p.cast::<f64>() + pose.translation;
            let (u, v) = camera.project(&cam);
            let (x, y) = ((idx % 128) as f64 + 0.5, (idx / 128) as f64 + 0.5);
            assert!(
                (u - x).abs() < 1e-3 && (v - y).abs() < 1e-3,
                "{shape}: ({u},{v}) vs ({x},{y})"
            );
            assert!((cam.z - image.depth[idx] as f64).abs() < 1e-4);
        }
        let worst = sdf
            .distances(&points)
            .iter()
            .map(|d| d.abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-4, "{shape}: |sdf| up to {worst}");
        assert!(points.len() > 1000);
    }
}

/// Mean absolute difference per channel (0..255) over pixels that are not edges in either
/// image. An edge pixel differs from one of its 4 neighbours by more than 6 in some channel: a
/// silhouette, a polyhedron's edge or a marker's border, but not the 1-unit shading steps
/// between the 1° facets of the round shapes.
fn interior_difference(a: &[u8], b: &[u8], size: usize) -> f64 {
    let is_edge = |img: &[u8], x: usize, y: usize| {
        let at = |x: usize, y: usize| &img[(y * size + x) * 3..(y * size + x) * 3 + 3];
        let c = at(x, y);
        let differs = |o: &[u8]| o.iter().zip(c).any(|(p, q)| p.abs_diff(*q) > 6);
        (x > 0 && differs(at(x - 1, y)))
            || (x + 1 < size && differs(at(x + 1, y)))
            || (y > 0 && differs(at(x, y - 1)))
            || (y + 1 < size && differs(at(x, y + 1)))
    };
    let (mut total, mut count) = (0.0, 0usize);
    for y in 0..size {
        for x in 0..size {
            if is_edge(a, x, y) || is_edge(b, x, y) {
                continue;
            }
            for c in 0..3 {
                let i = (y * size + x) * 3 + c;
                total += (a[i] as f64 - b[i] as f64).abs();
            }
            count += 3;
        }
    }
    total / count.max(1) as f64
}

fn render_at(mesh: &Mesh, r: &Rotation3<f64>, size: u32) -> Vec<u8> {
    render(
        mesh,
        &Camera::square(size),
        &symsol_pose(*r),
        &RenderOptions::default(),
    )
    .rgb
}

#[test]
fn symmetry_is_exact_in_the_images() {
    let size = 96;
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    for shape in alignist::cad::shapes::SYMSOL_I {
        let mesh = shape.mesh();
        let symmetries = shape.symmetries();
        for r in haar_rotations(&mut rng, 20) {
            let base = render_at(&mesh, &r, size);
            for s in &symmetries {
                let other = render_at(&mesh, &(r * s), size);
                let d = interior_difference(&base, &other, size as usize);
                assert!(d < 1.0, "{shape}: mean difference {d}/255");
            }
        }
    }
}

#[test]
fn markers_break_the_symmetry_of_the_base_shape() {
    let size = 96;
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let cases = [
        (Shape::TetX, SymmetryGroup::Tetrahedral.rotations()),
        (
            Shape::CylO,
            SymmetryGroup::Cylinder
                .rotations()
                .into_iter()
                .step_by(15)
                .collect(),
        ),
        (Shape::SphereX, haar_rotations(&mut rng, 24)),
    ];
    for (shape, base_group) in cases {
        let mesh = shape.mesh();
        let own = shape.symmetries();
        let mut differing = 0;
        for r in haar_rotations(&mut rng, 5) {
            let base = render_at(&mesh, &r, size);
            for s in &own {
                let d =
                    interior_difference(&base, &render_at(&mesh, &(r * s), size), size as usize);
                assert!(
                    d < 1.0,
                    "{shape}: its own symmetry changed the image by {d}"
                );
            }
            for s in &base_group {
                let d =
                    interior_difference(&base, &render_at(&mesh, &(r * s), size), size as usize);
                if d > 2.0 {
                    differing += 1;
                }
            }
        }
        assert!(differing > 0, "{shape}: the marker never showed");
    }
}

#[test]
fn shapes_are_closed_normalised_and_have_their_symmetry_sets() {
    for shape in alignist::cad::shapes::ALL_SHAPES {
        let mesh = shape.mesh();
        SignedDistance::new(&mesh).unwrap_or_else(|e| panic!("{shape}: {e}"));
        let r = mesh
            .vertices
            .iter()
            .map(|v| v.norm())
            .fold(0.0f32, f32::max);
        assert!((r - 1.0).abs() < 1e-5, "{shape}: radius {r}");
        assert!(mesh.signed_volume() > 0.0, "{shape}: wound outward");
        let expected = match shape {
            Shape::Tetrahedron => 12,
            Shape::Cube => 24,
            Shape::Icosahedron => 60,
            Shape::Cone => 360,
            Shape::Cylinder => 720,
            Shape::TetX => 3,
            Shape::CylO | Shape::SphereX => 2,
        };
        assert_eq!(shape.symmetries().len(), expected, "{shape}");
        assert_eq!(shape.name().parse::<Shape>().unwrap(), shape);
    }
    assert!("pyramid".parse::<Shape>().is_err());
}

#[test]
fn pose_translation_moves_the_image() {
    let mesh = Shape::Cube.mesh();
    let camera = Camera::square(64);
    let centred = render(
        &mesh,
        &camera,
        &symsol_pose(Rotation3::identity()),
        &RenderOptions::default(),
    );
    let moved = render(
        &mesh,
        &camera,
        &Pose {
            rotation: Rotation3::identity(),
            translation: Vector3::new(0.5, 0.0, 3.0),
        },
        &RenderOptions::default(),
    );
    let down = render(
        &mesh,
        &camera,
        &Pose {
            rotation: Rotation3::identity(),
            translation: Vector3::new(0.0, 0.5, 3.0),
        },
        &RenderOptions::default(),
    );
    let mean = |m: &[bool], axis: usize| {
        let v: Vec<f64> = m
            .iter()
            .enumerate()
            .filter(|(_, v)| **v)
            .map(|(i, _)| {
                if axis == 0 {
                    (i % 64) as f64
                } else {
                    (i / 64) as f64
                }
            })
            .collect();
        v.iter().sum::<f64>() / v.len() as f64
    };
    // OpenCV camera: +x moves the object right, +y moves it down, by about 64·0.5/3 ≈ 10.7
    // pixels (a little more: perspective shows the side face that turns towards the camera).
    let right = mean(&moved.mask, 0) - mean(&centred.mask, 0);
    let below = mean(&down.mask, 1) - mean(&centred.mask, 1);
    for shift in [right, below] {
        assert!((9.0..15.0).contains(&shift), "{shift}");
    }
    assert!((mean(&moved.mask, 1) - mean(&centred.mask, 1)).abs() < 0.5);
}
