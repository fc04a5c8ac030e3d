//! CAD models: mesh I/O and normalisation, the SYMSOL shapes, the rasteriser, signed distance.

mod mesh;
pub mod render;
pub mod scene;
mod sdf;
pub mod shapes;

pub use mesh::{
    CentreOf, Edges, LengthUnit, Mesh, MeshColors, Normalisation, SurfacePoint, Texture, bilinear,
    load_part, write_ply,
};
pub use render::{Camera, Pose, Render, RenderOptions, render};
pub use scene::{
    CornerNormals, Light, Lighting, Material, SceneObject, SceneRaster, SceneRender, render_scene,
};
pub use sdf::SignedDistance;
pub use shapes::Shape;

/// Errors about meshes; every one names the mesh (file path or `shape:<name>`).
#[derive(Debug, thiserror::Error)]
pub enum CadError {
    /// The file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The file extension is not one we read.
    #[error("{0}: unknown mesh format (expected .obj, .ply or .stl)")]
    UnknownFormat(String),
    /// The file is not valid in its format.
    #[error("{mesh}: {message}")]
    Parse {
        /// The mesh.
        mesh: String,
        /// What is wrong.
        message: String,
    },
    /// No vertices or no faces.
    #[error("{0}: the mesh is empty (no vertices or no triangles)")]
    Empty(String),
    /// A face that is not a triangle.
    #[error("{mesh}: face {face} has {corners} corners; only triangle meshes are accepted")]
    NotTriangular {
        /// The mesh.
        mesh: String,
        /// Index of the face.
        face: usize,
        /// Its number of corners.
        corners: usize,
    },
    /// A face index past the vertex list.
    #[error("{mesh}: face {face} uses vertex {index} but the mesh has {vertices} vertices")]
    BadIndex {
        /// The mesh.
        mesh: String,
        /// Index of the face.
        face: usize,
        /// The bad index.
        index: u32,
        /// Number of vertices.
        vertices: usize,
    },
    /// A vertex with a NaN or infinite coordinate.
    #[error("{mesh}: vertex {vertex} has a non-finite coordinate")]
    NonFinite {
        /// The mesh.
        mesh: String,
        /// Index of the vertex.
        vertex: usize,
    },
    /// Signed distance needs a closed, consistently oriented surface.
    #[error(
        "{mesh}: the mesh is not closed and consistently oriented ({bad_edges} edges are not \
         shared by exactly two triangles in opposite directions); signed distance needs a \
         watertight mesh"
    )]
    NotClosed {
        /// The mesh.
        mesh: String,
        /// Number of bad directed edges.
        bad_edges: usize,
    },
    /// A shape name that is not one of the SYMSOL shapes.
    #[error("unknown shape '{0}' (expected tet, cube, icosa, cone, cyl, tetX, cylO or sphereX)")]
    UnknownShape(String),
}
