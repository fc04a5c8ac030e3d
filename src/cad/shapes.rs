//! The SYMSOL shapes, built so that their symmetry sets are exactly the groups of the SO(3) core
//! (docs/DESIGN.md §1), and textured variants in the spirit of SYMSOL-II.
//!
//! Every shape is returned in NOCS (bounding-box centre at 0, bounding-sphere radius 1). The cone
//! and cylinder are tessellated with 360 segments at whole degrees, so the sampled continuous
//! symmetry sets (1° about z, and the flip about x for the cylinder) map the mesh onto itself
//! exactly, and renders of symmetric poses are identical.

use std::f64::consts::TAU;
use std::fmt;
use std::str::FromStr;

use nalgebra::{Rotation3, Vector3};

use super::{CadError, Mesh, MeshColors};
use crate::so3::{SymmetryGroup, cube_vertices, icosahedron_vertices, rot_x, tetrahedron_vertices};

/// The base colour of every shape.
pub const SHAPE_COLOR: [u8; 3] = [190, 190, 200];
/// The marker colour of the textured shapes (orange).
pub const MARKER_COLOR: [u8; 3] = [240, 130, 20];

/// Segments around the axis of the cone and cylinder (one per degree).
const ROUND_SEGMENTS: usize = 360;

/// A SYMSOL shape.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Shape {
    /// Regular tetrahedron, symmetry T (12).
    Tetrahedron,
    /// Cube, symmetry O (24).
    Cube,
    /// Regular icosahedron, symmetry I (60).
    Icosahedron,
    /// Cone with its apex on +z, the cone set (360).
    Cone,
    /// Cylinder along z, the cylinder set (720).
    Cylinder,
    /// Tetrahedron with one face orange (the face opposite vertex (1,1,1)): 3 symmetries.
    TetX,
    /// Cylinder with an orange disc on its side at +x: the identity and the flip about x.
    CylO,
    /// Sphere with an orange X at +x whose strokes cross at 60°: the identity and the flip about x.
    SphereX,
}

/// All shapes, SYMSOL-I first.
pub const ALL_SHAPES: [Shape; 8] = [
    Shape::Tetrahedron,
    Shape::Cube,
    Shape::Icosahedron,
    Shape::Cone,
    Shape::Cylinder,
    Shape::TetX,
    Shape::CylO,
    Shape::SphereX,
];

/// The five untextured SYMSOL-I shapes.
pub const SYMSOL_I: [Shape; 5] = [
    Shape::Tetrahedron,
    Shape::Cube,
    Shape::Icosahedron,
    Shape::Cone,
    Shape::Cylinder,
];

impl Shape {
    /// The SYMSOL name (`tet`, `cube`, `icosa`, `cone`, `cyl`, `tetX`, `cylO`, `sphereX`).
    pub fn name(&self) -> &'static str {
        match self {
            Shape::Tetrahedron => "tet",
            Shape::Cube => "cube",
            Shape::Icosahedron => "icosa",
            Shape::Cone => "cone",
            Shape::Cylinder => "cyl",
            Shape::TetX => "tetX",
            Shape::CylO => "cylO",
            Shape::SphereX => "sphereX",
        }
    }

    /// Whether the shape carries a marker (SYMSOL-II style).
    pub fn is_textured(&self) -> bool {
        matches!(self, Shape::TetX | Shape::CylO | Shape::SphereX)
    }

    /// The shape's symmetry group, where it is one of the named groups.
    pub fn symmetry_group(&self) -> Option<SymmetryGroup> {
        match self {
            Shape::Tetrahedron => Some(SymmetryGroup::Tetrahedral),
            Shape::Cube => Some(SymmetryGroup::Octahedral),
            Shape::Icosahedron => Some(SymmetryGroup::Icosahedral),
            Shape::Cone => Some(SymmetryGroup::Cone),
            Shape::Cylinder => Some(SymmetryGroup::Cylinder),
            Shape::CylO | Shape::SphereX => Some(SymmetryGroup::Dihedral(1)),
            Shape::TetX => None,
        }
    }

    /// Every rotation `S` with `S·shape = shape`, markers included (identity first).
    pub fn symmetries(&self) -> Vec<Rotation3<f64>> {
        match self.symmetry_group() {
            Some(g) => g.rotations(),
            None => {
                // TetX: the 3-fold rotations about (1, 1, 1), i.e. the cyclic permutations of
                // the axes, which fix the marked face.
                let p = Rotation3::from_matrix_unchecked(nalgebra::Matrix3::new(
                    0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0,
                ));
                vec![Rotation3::identity(), p, p * p]
            }
        }
    }

    /// The shape's mesh in NOCS, with per-face colours.
    pub fn mesh(&self) -> Mesh {
        let (vertices, triangles) = match self {
            Shape::Tetrahedron | Shape::TetX => convex_hull_faces(&tetrahedron_vertices()),
            Shape::Cube => cube_faces(),
            Shape::Icosahedron => convex_hull_faces(&icosahedron_vertices()),
            Shape::Cone => cone(),
            Shape::Cylinder => cylinder(1),
            Shape::CylO => cylinder(24),
            Shape::SphereX => uv_sphere(96, 48),
        };
        let mut mesh = Mesh {
            source: format!("shape:{}", self.name()),
            vertices: vertices.iter().map(|v| v.cast::<f32>()).collect(),
            triangles,
            colors: None,
        };
        let (normalised, _) = mesh.normalised();
        mesh = normalised;
        let colors = (0..mesh.triangles.len())
            .map(|f| {
                let c = centroid(&mesh, f);
                if self.marks(&c) {
                    MARKER_COLOR
                } else {
                    SHAPE_COLOR
                }
            })
            .collect();
        mesh.colors = Some(MeshColors::PerFace(colors));
        mesh
    }

    /// Whether a face with this centroid (NOCS) is part of the marker.
    fn marks(&self, c: &Vector3<f64>) -> bool {
        match self {
            Shape::TetX => c.dot(&Vector3::new(1.0, 1.0, 1.0)) < 0.0,
            Shape::CylO => {
                // A disc of radius 0.3 (arc length on the side) centred at angle 0, z = 0.
                let radius = (c.x * c.x + c.y * c.y).sqrt();
                let arc = c.y.atan2(c.x) * radius;
                c.x > 0.0 && (arc * arc + c.z * c.z).sqrt() < 0.3 && radius > 0.5
            }
            Shape::SphereX => {
                // Two strokes through (1, 0, 0), at ±30° from the y axis in the (y, z) plane.
                let n = c.normalize();
                if n.x < 0.8 {
                    return false;
                }
                let (a, b) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
                [(a, b), (a, -b)].iter().any(|&(dy, dz)| {
                    let along = n.y * dy + n.z * dz;
                    let across = (n.y * -dz + n.z * dy).abs();
                    along.abs() < 0.45 && across < 0.07
                })
            }
            _ => false,
        }
    }
}

impl fmt::Display for Shape {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Shape {
    type Err = CadError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Ok(match s {
            "tet" | "tetrahedron" => Shape::Tetrahedron,
            "cube" => Shape::Cube,
            "icosa" | "icosahedron" => Shape::Icosahedron,
            "cone" => Shape::Cone,
            "cyl" | "cylinder" => Shape::Cylinder,
            "tetX" => Shape::TetX,
            "cylO" => Shape::CylO,
            "sphereX" => Shape::SphereX,
            _ => return Err(CadError::UnknownShape(s.to_string())),
        })
    }
}

fn centroid(mesh: &Mesh, face: usize) -> Vector3<f64> {
    let [a, b, c] = mesh.triangles[face].map(|i| mesh.vertices[i as usize].cast::<f64>());
    (a + b + c) / 3.0
}

/// Faces of the convex hull of a point set whose faces are triangles (tetrahedron, icosahedron):
/// every triple whose plane has all points on one side, wound outward.
fn convex_hull_faces(points: &[Vector3<f64>]) -> (Vec<Vector3<f64>>, Vec<[u32; 3]>) {
    let n = points.len();
    let mut faces = Vec::new();
    for i in 0..n {
        for j in i + 1..n {
            for k in j + 1..n {
                let normal = (points[j] - points[i]).cross(&(points[k] - points[i]));
                let side: Vec<f64> = points
                    .iter()
                    .map(|p| normal.dot(&(p - points[i])))
                    .collect();
                let outward_pos = side.iter().all(|&s| s <= 1e-9);
                let outward_neg = side.iter().all(|&s| s >= -1e-9);
                if outward_pos {
                    faces.push([i as u32, j as u32, k as u32]);
                } else if outward_neg {
                    faces.push([i as u32, k as u32, j as u32]);
                }
            }
        }
    }
    (points.to_vec(), faces)
}

fn cube_faces() -> (Vec<Vector3<f64>>, Vec<[u32; 3]>) {
    let verts = cube_vertices();
    let index = |x: f64, y: f64, z: f64| {
        verts
            .iter()
            .position(|v| *v == Vector3::new(x, y, z))
            .expect("cube vertex") as u32
    };
    let mut tris = Vec::new();
    for axis in 0..3 {
        for sign in [-1.0, 1.0] {
            // Four corners of the face `axis = sign`, counter-clockwise seen from outside.
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            let corner = |a: f64, b: f64| {
                let mut p = [0.0; 3];
                p[axis] = sign;
                p[u] = a;
                p[v] = b;
                index(p[0], p[1], p[2])
            };
            let quad = [
                corner(-1.0, -1.0),
                corner(1.0, -1.0),
                corner(1.0, 1.0),
                corner(-1.0, 1.0),
            ];
            let (q0, q1, q2, q3) = if sign > 0.0 {
                (quad[0], quad[1], quad[2], quad[3])
            } else {
                (quad[0], quad[3], quad[2], quad[1])
            };
            tris.push([q0, q1, q2]);
            tris.push([q0, q2, q3]);
        }
    }
    (verts, tris)
}

fn ring(z: f64, radius: f64) -> impl Iterator<Item = Vector3<f64>> {
    (0..ROUND_SEGMENTS).map(move |k| {
        let a = TAU * k as f64 / ROUND_SEGMENTS as f64;
        Vector3::new(radius * a.cos(), radius * a.sin(), z)
    })
}

/// Cone: base of radius 1 at z = −1, apex at z = +1 (normalised afterwards).
fn cone() -> (Vec<Vector3<f64>>, Vec<[u32; 3]>) {
    let n = ROUND_SEGMENTS as u32;
    let mut verts: Vec<Vector3<f64>> = ring(-1.0, 1.0).collect();
    let apex = verts.len() as u32;
    verts.push(Vector3::new(0.0, 0.0, 1.0));
    let base = verts.len() as u32;
    verts.push(Vector3::new(0.0, 0.0, -1.0));
    let mut tris = Vec::new();
    for k in 0..n {
        let next = (k + 1) % n;
        tris.push([k, next, apex]);
        tris.push([next, k, base]);
    }
    (verts, tris)
}

/// Cylinder: radius 1, z in [−1, 1], the side cut into `rings` rings (more where a marker is
/// drawn on it).
fn cylinder(rings: usize) -> (Vec<Vector3<f64>>, Vec<[u32; 3]>) {
    let n = ROUND_SEGMENTS as u32;
    let mut verts = Vec::new();
    for r in 0..=rings {
        verts.extend(ring(-1.0 + 2.0 * r as f64 / rings as f64, 1.0));
    }
    let bottom = verts.len() as u32;
    verts.push(Vector3::new(0.0, 0.0, -1.0));
    let top = verts.len() as u32;
    verts.push(Vector3::new(0.0, 0.0, 1.0));
    let mut tris = Vec::new();
    for r in 0..rings as u32 {
        for k in 0..n {
            let next = (k + 1) % n;
            let (a, b) = (r * n + k, r * n + next);
            let (c, d) = ((r + 1) * n + next, (r + 1) * n + k);
            tris.push([a, b, c]);
            tris.push([a, c, d]);
        }
    }
    let top_ring = rings as u32 * n;
    for k in 0..n {
        let next = (k + 1) % n;
        tris.push([next, k, bottom]);
        tris.push([top_ring + k, top_ring + next, top]);
    }
    (verts, tris)
}

/// UV sphere with poles on z; `segments` even so that the flip about x maps it onto itself.
fn uv_sphere(segments: usize, rings: usize) -> (Vec<Vector3<f64>>, Vec<[u32; 3]>) {
    let mut verts = vec![Vector3::new(0.0, 0.0, 1.0)];
    for r in 1..rings {
        let theta = std::f64::consts::PI * r as f64 / rings as f64;
        for k in 0..segments {
            let phi = TAU * k as f64 / segments as f64;
            verts.push(Vector3::new(
                theta.sin() * phi.cos(),
                theta.sin() * phi.sin(),
                theta.cos(),
            ));
        }
    }
    let south = verts.len() as u32;
    verts.push(Vector3::new(0.0, 0.0, -1.0));
    let seg = segments as u32;
    let at = |r: u32, k: u32| 1 + (r - 1) * seg + k % seg;
    let mut tris = Vec::new();
    for k in 0..seg {
        tris.push([0, at(1, k), at(1, k + 1)]);
        tris.push([south, at(rings as u32 - 1, k + 1), at(rings as u32 - 1, k)]);
    }
    for r in 1..rings as u32 - 1 {
        for k in 0..seg {
            tris.push([at(r, k), at(r + 1, k), at(r + 1, k + 1)]);
            tris.push([at(r, k), at(r + 1, k + 1), at(r, k + 1)]);
        }
    }
    (verts, tris)
}

/// A plain UV sphere of radius 1 with `2·segments·(rings − 1)` triangles (for benchmarks and
/// tests that need a mesh of a chosen size).
pub fn uv_sphere_mesh(segments: usize, rings: usize) -> Mesh {
    let (vertices, triangles) = uv_sphere(segments.max(3), rings.max(2));
    Mesh {
        source: format!("shape:uv_sphere_{segments}x{rings}"),
        vertices: vertices.iter().map(|v| v.cast::<f32>()).collect(),
        triangles,
        colors: None,
    }
}

/// The flip about x, the extra symmetry of the cylinder-like shapes.
pub fn flip_x() -> Rotation3<f64> {
    rot_x(std::f64::consts::PI)
}
