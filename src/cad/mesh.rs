//! Triangle meshes: loading (OBJ via tobj, PLY via ply-rs-bw, STL via stl_io), NOCS
//! normalisation, welding, closure checks, and area-weighted surface sampling.

use std::collections::HashMap;
use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use nalgebra::Vector3;
use rand::{Rng, RngExt};
use serde::{Deserialize, Serialize};

use super::CadError;

/// Colours of a mesh, when it has any.
#[derive(Debug, Clone, PartialEq)]
pub enum MeshColors {
    /// One RGB colour per triangle.
    PerFace(Vec<[u8; 3]>),
    /// One RGB colour per vertex (rendered per face as the mean of its vertices).
    PerVertex(Vec<[u8; 3]>),
    /// A texture image and each vertex's coordinates in it (OBJ + MTL `map_Kd`).
    Texture(Texture),
}

/// What [`bilinear`] reads beyond an image's edge.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Edges {
    /// The image repeats (textures).
    Wrap,
    /// The edge pixels extend (photographs).
    Clamp,
}

/// `image` at pixel coordinates `(x, y)` (pixel centres at whole numbers), each of the four
/// nearest texels mapped by `texel` and then bilinearly interpolated.
pub fn bilinear(
    image: &image::RgbImage,
    x: f32,
    y: f32,
    edges: Edges,
    texel: impl Fn(u8) -> f32,
) -> [f32; 3] {
    let (w, h) = (image.width() as i64, image.height() as i64);
    let (xf, yf) = (x.floor(), y.floor());
    let (tx, ty) = (x - xf, y - yf);
    let (x0, y0) = (xf as i64, yf as i64);
    let at = |i: i64, j: i64| {
        let (i, j) = match edges {
            Edges::Wrap => (i.rem_euclid(w), j.rem_euclid(h)),
            Edges::Clamp => (i.clamp(0, w - 1), j.clamp(0, h - 1)),
        };
        image.get_pixel(i as u32, j as u32).0.map(&texel)
    };
    let (a, b, c, d) = (
        at(x0, y0),
        at(x0 + 1, y0),
        at(x0, y0 + 1),
        at(x0 + 1, y0 + 1),
    );
    std::array::from_fn(|k| {
        (a[k] * (1.0 - tx) + b[k] * tx) * (1.0 - ty) + (c[k] * (1.0 - tx) + d[k] * tx) * ty
    })
}

/// A texture image with per-vertex coordinates `(u, v)` in `[0, 1]`, `v` up (OBJ's convention:
/// image row `(1 − v) · height`); coordinates outside wrap around.
#[derive(Debug, Clone, PartialEq)]
pub struct Texture {
    /// Per-vertex texture coordinates.
    pub uv: Vec<[f32; 2]>,
    /// The image (sRGB).
    pub image: std::sync::Arc<image::RgbImage>,
}

impl Texture {
    /// The sRGB colour at `(u, v)`, bilinearly interpolated between texel centres.
    pub fn sample(&self, uv: [f32; 2]) -> [f32; 3] {
        let (w, h) = (self.image.width() as f32, self.image.height() as f32);
        bilinear(
            &self.image,
            uv[0].rem_euclid(1.0) * w - 0.5,
            (1.0 - uv[1].rem_euclid(1.0)) * h - 0.5,
            Edges::Wrap,
            |c| c as f32,
        )
    }

    /// The texture's colour at each vertex (what a PLY file can hold of it).
    pub fn vertex_colours(&self) -> Vec<[u8; 3]> {
        self.uv
            .iter()
            .map(|&uv| self.sample(uv).map(|c| c.round().clamp(0.0, 255.0) as u8))
            .collect()
    }
}

/// A triangle mesh. `source` names where it came from (a file path or `shape:<name>`), so that
/// every error about it can say which mesh is wrong.
#[derive(Debug, Clone, PartialEq)]
pub struct Mesh {
    /// Where the mesh came from, for messages.
    pub source: String,
    /// Vertex positions.
    pub vertices: Vec<Vector3<f32>>,
    /// Triangles as indices into `vertices`, counter-clockwise seen from outside.
    pub triangles: Vec<[u32; 3]>,
    /// Optional colours.
    pub colors: Option<MeshColors>,
}

/// How a mesh was mapped to NOCS: `x_nocs = (x − centre) / scale`, where `centre` is the point
/// named by `centre_of` and `scale` the radius of the bounding sphere around it (docs/DESIGN.md
/// §1), both in the file's `units`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Normalisation {
    /// The centre, in the file's units.
    pub centre: [f64; 3],
    /// Bounding-sphere radius around the centre, in the file's units.
    pub scale: f64,
    /// Which point the centre is (sets written before this field: the bounding box's centre).
    #[serde(default)]
    pub centre_of: CentreOf,
    /// The unit of the file's coordinates, when known.
    #[serde(default)]
    pub units: LengthUnit,
}

/// The point of a mesh that NOCS puts at the origin.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CentreOf {
    /// The centre of the axis-aligned bounding box (the SYMSOL shapes, and sets written before
    /// the centroid).
    #[default]
    BoundingBox,
    /// The area-weighted centroid of the surface: on every symmetry axis of the part, whatever
    /// its bounding box (an odd `Cn` part is not symmetric about its box's centre).
    SurfaceCentroid,
}

/// The unit of a mesh file's coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LengthUnit {
    /// Not stated (the SYMSOL shapes are unitless).
    #[default]
    Unknown,
    /// Metres (scans are often in metres).
    Metre,
    /// Millimetres (BOP's CAD models).
    Millimetre,
}

impl LengthUnit {
    /// The unit a part of bounding-sphere radius `radius` (in the file's numbers) is most likely
    /// drawn in: a robot's parts are between a few millimetres and a metre or two across, so a
    /// radius above 2 is millimetres and one below is metres.
    pub fn guess(radius: f64) -> LengthUnit {
        if radius > 2.0 {
            LengthUnit::Millimetre
        } else {
            LengthUnit::Metre
        }
    }

    /// Metres per unit (`None` when unknown).
    pub fn metres(&self) -> Option<f64> {
        match self {
            LengthUnit::Unknown => None,
            LengthUnit::Metre => Some(1.0),
            LengthUnit::Millimetre => Some(1e-3),
        }
    }
}

impl std::fmt::Display for LengthUnit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            LengthUnit::Unknown => "unknown",
            LengthUnit::Metre => "m",
            LengthUnit::Millimetre => "mm",
        })
    }
}

impl std::str::FromStr for LengthUnit {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "m" | "metre" | "meter" | "metres" | "meters" => Ok(LengthUnit::Metre),
            "mm" | "millimetre" | "millimeter" | "millimetres" | "millimeters" => {
                Ok(LengthUnit::Millimetre)
            }
            "unknown" => Ok(LengthUnit::Unknown),
            other => Err(format!("unknown length unit '{other}' (expected m or mm)")),
        }
    }
}

impl Normalisation {
    /// Maps a point in the file's units to NOCS.
    pub fn to_nocs(&self, p: &Vector3<f64>) -> Vector3<f64> {
        (p - Vector3::from(self.centre)) / self.scale
    }

    /// Maps a NOCS point back to the file's units.
    pub fn from_nocs(&self, p: &Vector3<f64>) -> Vector3<f64> {
        p * self.scale + Vector3::from(self.centre)
    }
}

/// A user's part read from `path` and mapped to NOCS about its surface centroid, with its name
/// (the file's stem) and normalisation; `units` (guessed from its size when `None`) is recorded
/// in the normalisation, so answers can be given in the user's units.
pub fn load_part(
    path: &Path,
    units: Option<LengthUnit>,
) -> Result<(String, Mesh, Normalisation), CadError> {
    let mesh = Mesh::load(path)?;
    let mut n = mesh.centroid_normalisation();
    n.units = units.unwrap_or_else(|| LengthUnit::guess(n.scale));
    let (nocs, n) = mesh.normalised_by(n);
    let name = path
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("object")
        .to_string();
    Ok((name, nocs, n))
}

/// A point sampled on the surface, with the triangle it lies on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfacePoint {
    /// The point.
    pub point: Vector3<f32>,
    /// Index of its triangle.
    pub face: u32,
}

impl Mesh {
    /// Loads an OBJ, PLY, STL or glTF (`.gltf`, `.glb`) file (by extension) and validates it (non-empty, triangles only,
    /// indices in range, finite coordinates). It is not normalised; see [`Mesh::normalised`].
    pub fn load(path: &Path) -> Result<Mesh, CadError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .unwrap_or_default();
        let mesh = match ext.as_str() {
            "obj" => load_obj(path)?,
            "ply" => load_ply(path)?,
            "stl" => load_stl(path)?,
            "gltf" | "glb" => load_gltf(path)?,
            _ => return Err(CadError::UnknownFormat(path.display().to_string())),
        };
        mesh.validate()?;
        Ok(mesh)
    }

    /// Checks that the mesh is non-empty, has in-range indices and finite coordinates.
    pub fn validate(&self) -> Result<(), CadError> {
        if self.vertices.is_empty() || self.triangles.is_empty() {
            return Err(CadError::Empty(self.source.clone()));
        }
        if let Some(v) = self
            .vertices
            .iter()
            .position(|v| !v.iter().all(|c| c.is_finite()))
        {
            return Err(CadError::NonFinite {
                mesh: self.source.clone(),
                vertex: v,
            });
        }
        let n = self.vertices.len() as u32;
        for (face, tri) in self.triangles.iter().enumerate() {
            if let Some(&index) = tri.iter().find(|&&i| i >= n) {
                return Err(CadError::BadIndex {
                    mesh: self.source.clone(),
                    face,
                    index,
                    vertices: n as usize,
                });
            }
        }
        match &self.colors {
            Some(MeshColors::PerFace(c)) if c.len() != self.triangles.len() => {
                Err(CadError::Parse {
                    mesh: self.source.clone(),
                    message: format!(
                        "{} face colours for {} faces",
                        c.len(),
                        self.triangles.len()
                    ),
                })
            }
            Some(MeshColors::Texture(t)) if t.uv.len() != self.vertices.len() => {
                Err(CadError::Parse {
                    mesh: self.source.clone(),
                    message: format!(
                        "{} texture coordinates for {} vertices",
                        t.uv.len(),
                        self.vertices.len()
                    ),
                })
            }
            Some(MeshColors::PerVertex(c)) if c.len() != self.vertices.len() => {
                Err(CadError::Parse {
                    mesh: self.source.clone(),
                    message: format!(
                        "{} vertex colours for {} vertices",
                        c.len(),
                        self.vertices.len()
                    ),
                })
            }
            _ => Ok(()),
        }
    }

    /// Axis-aligned bounding box `(min, max)` of the vertices.
    pub fn bounds(&self) -> (Vector3<f64>, Vector3<f64>) {
        let mut lo = Vector3::repeat(f64::INFINITY);
        let mut hi = Vector3::repeat(f64::NEG_INFINITY);
        for v in &self.vertices {
            let v = v.cast::<f64>();
            lo = lo.inf(&v);
            hi = hi.sup(&v);
        }
        (lo, hi)
    }

    /// The NOCS normalisation of this mesh about its bounding box's centre (the SYMSOL shapes'
    /// convention), with the bounding-sphere radius around it.
    pub fn normalisation(&self) -> Normalisation {
        let (lo, hi) = self.bounds();
        self.normalisation_about((lo + hi) / 2.0, CentreOf::BoundingBox)
    }

    /// The NOCS normalisation of a part about its surface centroid, with the bounding-sphere
    /// radius around it: the frame a user's CAD part is trained and served in.
    pub fn centroid_normalisation(&self) -> Normalisation {
        self.normalisation_about(self.surface_centroid(), CentreOf::SurfaceCentroid)
    }

    fn normalisation_about(&self, centre: Vector3<f64>, centre_of: CentreOf) -> Normalisation {
        let scale = self
            .vertices
            .iter()
            .map(|v| (v.cast::<f64>() - centre).norm())
            .fold(0.0, f64::max);
        Normalisation {
            centre: centre.into(),
            scale: if scale > 0.0 { scale } else { 1.0 },
            centre_of,
            units: LengthUnit::Unknown,
        }
    }

    /// The area-weighted centroid of the surface (the vertices' mean for a surface without
    /// area).
    pub fn surface_centroid(&self) -> Vector3<f64> {
        let (mut sum, mut area) = (Vector3::zeros(), 0.0);
        for t in &self.triangles {
            let [a, b, c] = t.map(|i| self.vertices[i as usize].cast::<f64>());
            let w = 0.5 * (b - a).cross(&(c - a)).norm();
            sum += w * (a + b + c) / 3.0;
            area += w;
        }
        if area > 0.0 {
            sum / area
        } else {
            self.vertices
                .iter()
                .map(|v| v.cast::<f64>())
                .sum::<Vector3<f64>>()
                / self.vertices.len().max(1) as f64
        }
    }

    /// The mesh mapped to NOCS about its bounding box's centre, with the normalisation that did
    /// it.
    pub fn normalised(&self) -> (Mesh, Normalisation) {
        self.normalised_by(self.normalisation())
    }

    /// The mesh mapped to NOCS by `n`.
    pub fn normalised_by(&self, n: Normalisation) -> (Mesh, Normalisation) {
        let mut out = self.clone();
        for v in &mut out.vertices {
            *v = n.to_nocs(&v.cast::<f64>()).cast::<f32>();
        }
        (out, n)
    }

    /// The triangles that enclose a volume, with how many were left out: degenerate ones (a
    /// repeated vertex), repeats of a triangle with the same winding, and pairs of one triangle
    /// wound both ways (a zero-thickness sliver, common in scans). Call on a welded mesh.
    pub fn enclosing_triangles(&self) -> (Vec<[u32; 3]>, usize) {
        // A triangle's vertex set, and whether its winding is an even permutation of it.
        let key = |t: &[u32; 3]| {
            let mut k = *t;
            k.sort_unstable();
            let even = (t[0] == k[0] && t[1] == k[1])
                || (t[1] == k[0] && t[2] == k[1])
                || (t[2] == k[0] && t[0] == k[1]);
            (k, even)
        };
        let mut windings: HashMap<[u32; 3], [bool; 2]> = HashMap::new();
        for t in &self.triangles {
            let (k, even) = key(t);
            windings.entry(k).or_default()[usize::from(even)] = true;
        }
        let mut seen = std::collections::HashSet::new();
        let kept: Vec<[u32; 3]> = self
            .triangles
            .iter()
            .filter(|t| {
                let (k, _) = key(t);
                t[0] != t[1]
                    && t[1] != t[2]
                    && t[0] != t[2]
                    && windings[&k] != [true, true]
                    && seen.insert(k)
            })
            .copied()
            .collect();
        let dropped = self.triangles.len() - kept.len();
        (kept, dropped)
    }

    /// The same surface with vertices at identical positions merged (STL and some OBJ/PLY files
    /// repeat them per face). Per-vertex colours keep the first occurrence's colour.
    pub fn welded(&self) -> Mesh {
        let mut index_of: HashMap<[u32; 3], u32> = HashMap::new();
        let mut remap = Vec::with_capacity(self.vertices.len());
        let mut vertices = Vec::new();
        let mut kept = Vec::new();
        for (i, v) in self.vertices.iter().enumerate() {
            let key = [v.x.to_bits(), v.y.to_bits(), v.z.to_bits()];
            let id = *index_of.entry(key).or_insert_with(|| {
                vertices.push(*v);
                kept.push(i);
                (vertices.len() - 1) as u32
            });
            remap.push(id);
        }
        let triangles = self
            .triangles
            .iter()
            .map(|t| t.map(|i| remap[i as usize]))
            .collect();
        let colors = match &self.colors {
            Some(MeshColors::PerVertex(c)) => {
                Some(MeshColors::PerVertex(kept.iter().map(|&i| c[i]).collect()))
            }
            Some(MeshColors::Texture(t)) => Some(MeshColors::Texture(Texture {
                uv: kept.iter().map(|&i| t.uv[i]).collect(),
                image: t.image.clone(),
            })),
            other => other.clone(),
        };
        Mesh {
            source: self.source.clone(),
            vertices,
            triangles,
            colors,
        }
    }

    /// Checks that the (welded) mesh is closed and consistently oriented: every directed edge
    /// appears once and its reverse once. Errors name the mesh and count the bad edges.
    pub fn check_closed(&self) -> Result<(), CadError> {
        let mut directed: HashMap<(u32, u32), u32> = HashMap::new();
        for t in &self.triangles {
            for k in 0..3 {
                *directed.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
            }
        }
        let bad = directed
            .iter()
            .filter(|&(&(a, b), &count)| count != 1 || directed.get(&(b, a)) != Some(&1))
            .count();
        if bad > 0 {
            return Err(CadError::NotClosed {
                mesh: self.source.clone(),
                bad_edges: bad,
            });
        }
        Ok(())
    }

    /// Signed volume (positive when triangles wind counter-clockwise seen from outside).
    pub fn signed_volume(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| self.vertices[i as usize].cast::<f64>());
                a.dot(&b.cross(&c)) / 6.0
            })
            .sum()
    }

    /// Area of triangle `face`.
    pub fn face_area(&self, face: usize) -> f32 {
        let [a, b, c] = self.triangles[face].map(|i| self.vertices[i as usize]);
        0.5 * (b - a).cross(&(c - a)).norm()
    }

    /// Outward unit normal of triangle `face` (zero for a degenerate triangle).
    pub fn face_normal(&self, face: usize) -> Vector3<f32> {
        let [a, b, c] = self.triangles[face].map(|i| self.vertices[i as usize]);
        (b - a)
            .cross(&(c - a))
            .try_normalize(0.0)
            .unwrap_or_default()
    }

    /// Colour of triangle `face`: its own, the mean of its vertices', or `default`.
    pub fn face_color(&self, face: usize, default: [u8; 3]) -> [u8; 3] {
        match &self.colors {
            Some(MeshColors::PerFace(c)) => c[face],
            Some(MeshColors::PerVertex(c)) => {
                let t = self.triangles[face];
                std::array::from_fn(|k| {
                    let sum: u32 = t.iter().map(|&i| c[i as usize][k] as u32).sum();
                    (sum / 3) as u8
                })
            }
            Some(MeshColors::Texture(tex)) => {
                let t = self.triangles[face];
                let uv = std::array::from_fn(|k| {
                    t.iter().map(|&i| tex.uv[i as usize][k]).sum::<f32>() / 3.0
                });
                tex.sample(uv).map(|c| c.round().clamp(0.0, 255.0) as u8)
            }
            None => default,
        }
    }

    /// `n` points uniform over the surface, without their triangles.
    pub fn sample_surface_points<R: Rng + ?Sized>(
        &self,
        n: usize,
        rng: &mut R,
    ) -> Vec<Vector3<f32>> {
        self.sample_surface(n, rng)
            .iter()
            .map(|s| s.point)
            .collect()
    }

    /// `n` points uniform over the surface (area-weighted choice of triangle, then uniform
    /// barycentric coordinates by the square-root trick).
    pub fn sample_surface<R: Rng + ?Sized>(&self, n: usize, rng: &mut R) -> Vec<SurfacePoint> {
        let mut cumulative = Vec::with_capacity(self.triangles.len());
        let mut total = 0.0f64;
        for f in 0..self.triangles.len() {
            total += self.face_area(f) as f64;
            cumulative.push(total);
        }
        (0..n)
            .map(|_| {
                let u = rng.random_range(0.0..total);
                let face = cumulative
                    .partition_point(|&c| c <= u)
                    .min(self.triangles.len() - 1);
                let [a, b, c] = self.triangles[face].map(|i| self.vertices[i as usize]);
                let (r1, r2): (f32, f32) = (rng.random(), rng.random());
                let s = r1.sqrt();
                let point = a * (1.0 - s) + b * (s * (1.0 - r2)) + c * (s * r2);
                SurfacePoint {
                    point,
                    face: face as u32,
                }
            })
            .collect()
    }
}

fn parse_err(path: &Path, message: impl Into<String>) -> CadError {
    CadError::Parse {
        mesh: path.display().to_string(),
        message: message.into(),
    }
}

fn open(path: &Path) -> Result<BufReader<File>, CadError> {
    File::open(path)
        .map(BufReader::new)
        .map_err(|source| CadError::Io {
            path: path.display().to_string(),
            source,
        })
}

fn load_obj(path: &Path) -> Result<Mesh, CadError> {
    let options = tobj::LoadOptions {
        single_index: true,
        triangulate: false,
        ..Default::default()
    };
    let mut reader = open(path)?;
    let folder = path.parent().unwrap_or(Path::new("."));
    // Materials (`mtllib`) are read beside the OBJ; one that cannot be read leaves the mesh
    // without its colours, not without its shape.
    let (models, materials) = tobj::load_obj_buf(&mut reader, &options, |mtl| {
        tobj::load_mtl(folder.join(mtl))
    })
    .map_err(|e| parse_err(path, e.to_string()))?;
    let materials = materials.unwrap_or_else(|e| {
        tracing::warn!(mesh = %path.display(), "materials not read: {e}");
        Vec::new()
    });
    let mut vertices = Vec::new();
    let mut triangles = Vec::new();
    let mut colors = Vec::new();
    let mut diffuse = Vec::new();
    let mut uv = Vec::new();
    let mut textures = std::collections::BTreeSet::new();
    for model in models {
        let m = model.mesh;
        if let Some(face) = m.face_arities.iter().position(|&a| a != 3) {
            return Err(CadError::NotTriangular {
                mesh: path.display().to_string(),
                face,
                corners: m.face_arities[face] as usize,
            });
        }
        let base = vertices.len() as u32;
        vertices.extend(
            m.positions
                .chunks_exact(3)
                .map(|p| Vector3::new(p[0], p[1], p[2])),
        );
        triangles.extend(
            m.indices
                .chunks_exact(3)
                .map(|t| [t[0] + base, t[1] + base, t[2] + base]),
        );
        let to_byte = |c: &[f32]| -> [u8; 3] {
            std::array::from_fn(|k| (c[k].clamp(0.0, 1.0) * 255.0).round() as u8)
        };
        colors.extend(m.vertex_color.chunks_exact(3).map(to_byte));
        let material = m.material_id.and_then(|i| materials.get(i));
        let n = m.positions.len() / 3;
        let kd = material.and_then(|mat| mat.diffuse).map(|d| to_byte(&d));
        diffuse.extend(std::iter::repeat_n(kd, n));
        match material.and_then(|mat| mat.diffuse_texture.clone()) {
            Some(texture) if m.texcoords.len() == 2 * n => {
                textures.insert(texture);
                uv.extend(m.texcoords.chunks_exact(2).map(|t| [t[0], t[1]]));
            }
            _ => uv.extend(std::iter::repeat_n([f32::NAN; 2], n)),
        }
    }
    let colors = if textures.len() == 1 && uv.iter().all(|t| t[0].is_finite()) {
        // One texture over the whole mesh (several would need an atlas: their Kd colours serve).
        let name = textures.first().cloned().unwrap_or_default();
        let file = folder.join(name.replace('\\', "/"));
        let image = image::open(&file)
            .map_err(|e| parse_err(path, format!("texture {}: {e}", file.display())))?
            .to_rgb8();
        Some(MeshColors::Texture(Texture {
            uv,
            image: std::sync::Arc::new(image),
        }))
    } else if !colors.is_empty() && colors.len() == vertices.len() {
        Some(MeshColors::PerVertex(colors))
    } else if diffuse.iter().any(Option::is_some) {
        Some(MeshColors::PerVertex(
            diffuse.into_iter().map(|c| c.unwrap_or([255; 3])).collect(),
        ))
    } else {
        None
    };
    Ok(Mesh {
        source: path.display().to_string(),
        vertices,
        triangles,
        colors,
    })
}

/// A numeric PLY property as `f64` (`None` when absent or a list).
fn ply_scalar(p: Option<&ply_rs_bw::ply::Property>) -> Option<f64> {
    use ply_rs_bw::ply::Property;
    Some(match p? {
        Property::Float(v) => *v as f64,
        Property::Double(v) => *v,
        Property::Char(v) => *v as f64,
        Property::UChar(v) => *v as f64,
        Property::Short(v) => *v as f64,
        Property::UShort(v) => *v as f64,
        Property::Int(v) => *v as f64,
        Property::UInt(v) => *v as f64,
        _ => return None,
    })
}

/// An element's `red`, `green`, `blue`, when it has all three.
fn ply_rgb(e: &ply_rs_bw::ply::DefaultElement) -> Option<[u8; 3]> {
    let c = |name: &str| ply_scalar(e.get(name)).map(|v| v as u8);
    Some([c("red")?, c("green")?, c("blue")?])
}

/// The corners of PLY face `face` (`f`): a triangle of valid vertex indices.
fn ply_triangle(
    path: &Path,
    face: usize,
    f: &ply_rs_bw::ply::DefaultElement,
) -> Result<[u32; 3], CadError> {
    use ply_rs_bw::ply::Property;
    let list = f
        .get("vertex_indices")
        .or_else(|| f.get("vertex_index"))
        .ok_or_else(|| parse_err(path, format!("face {face} has no 'vertex_indices' list")))?;
    let idx: Vec<i64> = match list {
        Property::ListInt(v) => v.iter().map(|&x| x as i64).collect(),
        Property::ListUInt(v) => v.iter().map(|&x| x as i64).collect(),
        Property::ListShort(v) => v.iter().map(|&x| x as i64).collect(),
        Property::ListUShort(v) => v.iter().map(|&x| x as i64).collect(),
        Property::ListChar(v) => v.iter().map(|&x| x as i64).collect(),
        Property::ListUChar(v) => v.iter().map(|&x| x as i64).collect(),
        _ => {
            return Err(parse_err(
                path,
                format!("face {face}: 'vertex_indices' is not an integer list"),
            ));
        }
    };
    if idx.len() != 3 {
        return Err(CadError::NotTriangular {
            mesh: path.display().to_string(),
            face,
            corners: idx.len(),
        });
    }
    if let Some(&bad) = idx.iter().find(|&&i| i < 0 || i > u32::MAX as i64) {
        return Err(parse_err(
            path,
            format!("face {face} has vertex index {bad}"),
        ));
    }
    Ok([idx[0] as u32, idx[1] as u32, idx[2] as u32])
}

fn load_ply(path: &Path) -> Result<Mesh, CadError> {
    use ply_rs_bw::parser::Parser;
    use ply_rs_bw::ply::DefaultElement;

    let mut reader = open(path)?;
    let ply = Parser::<DefaultElement>::new()
        .read_ply(&mut reader)
        .map_err(|e| parse_err(path, e.to_string()))?;
    let empty = Vec::new();
    let vertex_elems = ply.payload.get("vertex").unwrap_or(&empty);
    let mut vertices = Vec::with_capacity(vertex_elems.len());
    let mut colors = Vec::new();
    for (i, v) in vertex_elems.iter().enumerate() {
        let coord = |name: &str| {
            ply_scalar(v.get(name))
                .ok_or_else(|| parse_err(path, format!("vertex {i} has no numeric '{name}'")))
        };
        vertices.push(Vector3::new(
            coord("x")? as f32,
            coord("y")? as f32,
            coord("z")? as f32,
        ));
        colors.extend(ply_rgb(v));
    }
    let face_elems = ply.payload.get("face").unwrap_or(&empty);
    let mut triangles = Vec::with_capacity(face_elems.len());
    let mut face_colors = Vec::new();
    for (face, f) in face_elems.iter().enumerate() {
        triangles.push(ply_triangle(path, face, f)?);
        face_colors.extend(ply_rgb(f));
    }
    let colors = if !face_colors.is_empty() && face_colors.len() == triangles.len() {
        Some(MeshColors::PerFace(face_colors))
    } else {
        (colors.len() == vertices.len() && !colors.is_empty())
            .then_some(MeshColors::PerVertex(colors))
    };
    Ok(Mesh {
        source: path.display().to_string(),
        vertices,
        triangles,
        colors,
    })
}

fn load_stl(path: &Path) -> Result<Mesh, CadError> {
    let mut file = File::open(path).map_err(|source| CadError::Io {
        path: path.display().to_string(),
        source,
    })?;
    let stl = stl_io::read_stl(&mut file).map_err(|e| parse_err(path, e.to_string()))?;
    Ok(Mesh {
        source: path.display().to_string(),
        vertices: stl
            .vertices
            .iter()
            .map(|v| Vector3::new(v[0], v[1], v[2]))
            .collect(),
        triangles: stl
            .faces
            .iter()
            .map(|f| f.vertices.map(|i| i as u32))
            .collect(),
        colors: None,
    })
}

/// A glTF 2.0 file (`.gltf` with its buffers, or `.glb`): the triangles of every mesh of the
/// default scene (else the first), placed by their nodes' transforms, with the base colour of
/// each primitive's material as the colour of its faces.
fn load_gltf(path: &Path) -> Result<Mesh, CadError> {
    let (document, buffers, _images) =
        gltf::import(path).map_err(|e| parse_err(path, e.to_string()))?;
    let scene = document
        .default_scene()
        .or_else(|| document.scenes().next())
        .ok_or_else(|| parse_err(path, String::from("no scene")))?;
    let mut mesh = Mesh {
        source: path.display().to_string(),
        vertices: Vec::new(),
        triangles: Vec::new(),
        colors: None,
    };
    let mut face_colours = Vec::new();
    let mut stack: Vec<(gltf::Node, nalgebra::Matrix4<f32>)> = scene
        .nodes()
        .map(|n| (n, nalgebra::Matrix4::identity()))
        .collect();
    while let Some((node, parent)) = stack.pop() {
        let local = nalgebra::Matrix4::from_column_slice(&node.transform().matrix().concat());
        let world = parent * local;
        stack.extend(node.children().map(|c| (c, world)));
        let Some(m) = node.mesh() else { continue };
        for primitive in m.primitives() {
            if primitive.mode() != gltf::mesh::Mode::Triangles {
                return Err(parse_err(
                    path,
                    format!("mesh {}: only triangle primitives are read", m.index()),
                ));
            }
            let reader = primitive.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
            let Some(positions) = reader.read_positions() else {
                continue;
            };
            let base = mesh.vertices.len() as u32;
            mesh.vertices.extend(positions.map(|p| {
                let v = world * nalgebra::Vector4::new(p[0], p[1], p[2], 1.0);
                Vector3::new(v.x, v.y, v.z)
            }));
            let count = mesh.vertices.len() as u32 - base;
            let indices: Vec<u32> = match reader.read_indices() {
                Some(i) => i.into_u32().collect(),
                None => (0..count).collect(),
            };
            let before = mesh.triangles.len();
            mesh.triangles.extend(
                indices
                    .chunks_exact(3)
                    .map(|t| [t[0] + base, t[1] + base, t[2] + base]),
            );
            let c = primitive
                .material()
                .pbr_metallic_roughness()
                .base_color_factor();
            let rgb = [c[0], c[1], c[2]].map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8);
            face_colours.extend(std::iter::repeat_n(rgb, mesh.triangles.len() - before));
        }
    }
    // A node mirrored by a negative scale turns its triangles inside out; the SDF flips a mesh
    // wound inward as a whole, which holds for the common single-node file.
    if face_colours.iter().any(|c| *c != [255, 255, 255]) {
        mesh.colors = Some(MeshColors::PerFace(face_colours));
    }
    Ok(mesh)
}

/// Writes `mesh` as a binary little-endian PLY with per-vertex colours when it has them (the BOP
/// model format). Per-face colours are written as a `face` property `red/green/blue`.
pub fn write_ply(mesh: &Mesh, path: &Path) -> Result<(), CadError> {
    use std::io::Write;
    let io_err = |source| CadError::Io {
        path: path.display().to_string(),
        source,
    };
    // A texture is kept as the colours at the vertices (what PLY holds).
    let baked;
    let mesh = match &mesh.colors {
        Some(MeshColors::Texture(t)) => {
            baked = Mesh {
                colors: Some(MeshColors::PerVertex(t.vertex_colours())),
                ..mesh.clone()
            };
            &baked
        }
        _ => mesh,
    };
    let mut out = Vec::new();
    let vertex_colors = matches!(mesh.colors, Some(MeshColors::PerVertex(_)));
    let face_colors = matches!(mesh.colors, Some(MeshColors::PerFace(_)));
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment written by alignist\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\n",
        mesh.vertices.len()
    );
    if vertex_colors {
        header += "property uchar red\nproperty uchar green\nproperty uchar blue\n";
    }
    header += &format!(
        "element face {}\nproperty list uchar int vertex_indices\n",
        mesh.triangles.len()
    );
    if face_colors {
        header += "property uchar red\nproperty uchar green\nproperty uchar blue\n";
    }
    header += "end_header\n";
    out.extend_from_slice(header.as_bytes());
    for (i, v) in mesh.vertices.iter().enumerate() {
        for c in v.iter() {
            out.extend_from_slice(&c.to_le_bytes());
        }
        if let Some(MeshColors::PerVertex(c)) = &mesh.colors {
            out.extend_from_slice(&c[i]);
        }
    }
    for (f, t) in mesh.triangles.iter().enumerate() {
        out.push(3);
        for &i in t {
            out.extend_from_slice(&(i as i32).to_le_bytes());
        }
        if let Some(MeshColors::PerFace(c)) = &mesh.colors {
            out.extend_from_slice(&c[f]);
        }
    }
    let mut file = File::create(path).map_err(io_err)?;
    file.write_all(&out).map_err(io_err)?;
    Ok(())
}
