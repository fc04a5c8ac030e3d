//! RGB-D fusion (beyond the paper): object points seen by a depth camera are scored by the
//! object's SDF expert on the candidate rotations and multiplied into the image's distribution
//! (a product of experts, like the paper's training targets).
//!
//! For a candidate `R` the camera-frame points `p_i` (relative to the object's centre) sit at
//! `x_i = Rᵀ·p_i` in the object's frame; the fused term is `−U_SDF(R)` on those points, with the
//! λ, ε and norm the expert set was selected with (DESIGN.md §2).

use std::sync::OnceLock;

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::EngineError;
use crate::bundle::experts::ExpertSet;
use crate::experts::baked::VoxelGrid;
use crate::experts::energy::{EnergyParams, sdf_energy};
use crate::experts::run_batched;

/// The SDF expert of one object, baked once ([`DepthFusion::warm`], which the server runs in the
/// background after loading, or on first use).
pub struct DepthFusion {
    set: ExpertSet,
    baked: OnceLock<VoxelGrid>,
}

impl DepthFusion {
    /// Wraps an object's expert set.
    pub fn new(set: ExpertSet) -> Self {
        Self {
            set,
            baked: OnceLock::new(),
        }
    }

    /// The energy parameters of the expert set.
    pub fn params(&self) -> &EnergyParams {
        &self.set.manifest.energy
    }

    /// The expert set.
    pub fn experts(&self) -> &ExpertSet {
        &self.set
    }

    /// Bakes the SDF grid now if it is not baked yet (so that no request pays for it).
    pub fn warm(&self) {
        let _ = self.sdf();
    }

    /// Whether the SDF grid is baked.
    pub fn is_warm(&self) -> bool {
        self.baked.get().is_some()
    }

    fn sdf(&self) -> &VoxelGrid {
        self.baked.get_or_init(|| {
            let device = crate::backend::device();
            let bake = &self.set.manifest.bake;
            VoxelGrid::bake(bake.resolution, bake.bound, 1, |p| {
                run_batched(&self.set.sdf, p, 1, &device)
            })
        })
    }

    /// Parses flattened camera-frame `xyz` (in the source mesh's units, relative to the object's
    /// centre) into normalised object units.
    pub fn parse_points(
        &self,
        xyz: &[f32],
        max_points: usize,
    ) -> Result<Vec<Vector3<f32>>, EngineError> {
        let field = "depth.xyz";
        let invalid = |message: String| EngineError::InvalidArgument {
            field: field.into(),
            message,
        };
        if xyz.is_empty() {
            return Err(invalid("has no points".into()));
        }
        if !xyz.len().is_multiple_of(3) {
            return Err(invalid(format!(
                "has {} values, not a multiple of 3 (x, y, z triples)",
                xyz.len()
            )));
        }
        let n = xyz.len() / 3;
        if n > max_points {
            return Err(EngineError::ResourceExhausted {
                field: field.into(),
                message: format!("{n} points is over the limit of {max_points}"),
            });
        }
        if let Some(i) = xyz.iter().position(|v| !v.is_finite()) {
            return Err(invalid(format!("value {i} is not finite")));
        }
        let scale = self.set.manifest.object.normalisation.scale as f32;
        let points: Vec<Vector3<f32>> = xyz
            .chunks_exact(3)
            .map(|c| Vector3::new(c[0], c[1], c[2]) / scale)
            .collect();
        let bound = self.set.manifest.bake.bound * 4.0;
        if let Some(i) = points.iter().position(|p| p.norm() > bound) {
            return Err(invalid(format!(
                "point {i} is {:.2} object radii from the centre; points must be relative to the \
                 object's centre, in the units of its mesh",
                points[i].norm()
            )));
        }
        Ok(points)
    }

    /// `−U_SDF(R)` of the points for every candidate (row-major rotations).
    pub fn log_measure(&self, points: &[Vector3<f32>], rotations: &[[f32; 9]]) -> Vec<f32> {
        let sdf = self.sdf();
        let params = self.params();
        rotations
            .par_iter()
            .map_init(
                || vec![0f32; points.len()],
                |buf, m| {
                    let rt = Matrix3::from_row_slice(m).transpose();
                    for (v, p) in buf.iter_mut().zip(points) {
                        let mut out = [0f32];
                        sdf.sample_into(&(rt * p), &mut out);
                        *v = out[0];
                    }
                    -sdf_energy(buf, params) as f32
                },
            )
            .collect()
    }
}
