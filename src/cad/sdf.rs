//! Exact signed distance of points to a closed, oriented mesh (parry3d), batched.
//!
//! parry3d speaks glam; the conversion happens here and nowhere else (docs/DESIGN.md §1).

use nalgebra::Vector3;
use parry3d::math::Vector as GlamVec;
use parry3d::query::PointQuery;
use parry3d::shape::{TriMesh, TriMeshFlags};
use rayon::prelude::*;

use super::{CadError, Mesh};

/// Signed distance to a closed mesh: negative inside, positive outside.
pub struct SignedDistance {
    shape: TriMesh,
}

impl SignedDistance {
    /// Builds the distance query for `mesh`, which must be closed and consistently oriented
    /// after welding identical vertices and leaving out the triangles that enclose nothing
    /// ([`Mesh::enclosing_triangles`]: degenerate ones and zero-thickness slivers of scans). A
    /// mesh wound inward is flipped.
    pub fn new(mesh: &Mesh) -> Result<Self, CadError> {
        mesh.validate()?;
        let mut welded = mesh.welded();
        welded.triangles = welded.enclosing_triangles().0;
        welded.colors = None;
        welded.check_closed()?;
        let mut triangles = welded.triangles.clone();
        if welded.signed_volume() < 0.0 {
            for t in &mut triangles {
                t.swap(1, 2);
            }
        }
        let vertices = welded
            .vertices
            .iter()
            .map(|v| GlamVec::new(v.x, v.y, v.z))
            .collect();
        let shape =
            TriMesh::with_flags(vertices, triangles, TriMeshFlags::ORIENTED).map_err(|e| {
                CadError::Parse {
                    mesh: mesh.source.clone(),
                    message: format!("cannot build the distance structure: {e:?}"),
                }
            })?;
        Ok(Self { shape })
    }

    /// Signed distance of one point.
    pub fn distance(&self, p: &Vector3<f32>) -> f32 {
        let q = GlamVec::new(p.x, p.y, p.z);
        let proj = self.shape.project_local_point(q, false);
        let d = (proj.point - q).length();
        if proj.is_inside { -d } else { d }
    }

    /// Signed distances of many points (parallel).
    pub fn distances(&self, points: &[Vector3<f32>]) -> Vec<f32> {
        points.par_iter().map(|p| self.distance(p)).collect()
    }
}
