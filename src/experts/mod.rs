//! The two frozen CAD experts of the paper (Sec. 3, Eq. 3–4; docs/DESIGN.md §2): a neural SDF and
//! SurfEmb-style surface features, the energies they give to candidate rotations, and dense
//! voxel bakes of both for fast scoring during training.

pub mod baked;
pub mod energy;
pub mod feature;
pub mod joint;
pub mod modes;
pub mod sdf;
pub mod select;
mod siren;
pub mod symmetry;

pub use siren::{Siren, SirenConfig};

use burn::tensor::{Device, Tensor};
use nalgebra::Vector3;

use crate::cad::CadError;

/// Errors of the experts.
#[derive(Debug, thiserror::Error)]
pub enum ExpertError {
    /// A mesh problem.
    #[error(transparent)]
    Cad(#[from] CadError),
    /// A render at a random pose showed nothing of the object.
    #[error("{0}: a training render shows no pixel of the object")]
    EmptyRender(String),
    /// A grid level that cannot be used.
    #[error(transparent)]
    So3(#[from] crate::so3::So3Error),
    /// Training produced a non-finite loss.
    #[error("training diverged at step {step} (loss {loss})")]
    Diverged {
        /// The step.
        step: usize,
        /// The loss.
        loss: f64,
    },
}

/// `mean_i |a_i − b_i|`.
pub fn mean_abs_difference(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(p, q)| (p - q).abs() as f64)
        .sum::<f64>()
        / a.len().max(1) as f64
}

/// Evaluates a SIREN with `d_out` outputs at many points, 8192 at a time; row-major `n × d_out`.
pub fn run_batched(
    model: &Siren,
    points: &[Vector3<f32>],
    d_out: usize,
    device: &Device,
) -> Vec<f32> {
    let mut out = Vec::with_capacity(points.len() * d_out);
    for chunk in points.chunks(8192) {
        let y: Tensor<2> = model.forward(sdf::points_tensor(chunk, device));
        out.extend(
            y.into_data()
                .try_to_vec::<f32>()
                .expect("a float tensor reads back as f32"),
        );
    }
    out
}
