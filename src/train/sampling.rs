//! The K rotations each training image is scored on (DESIGN.md §2, "Sampling").
//!
//! Mode-focused (the paper's): the experts' combined measure is computed on the cell centres of a
//! coarse grid for this image, `focused` cells are drawn with probability ∝ `a^SDF·a^SE`, and a
//! rotation is jittered uniformly inside each; the rest are Haar-uniform; the ground truth comes
//! first. Uniform (IPDF's, and the "random sampling" ablation): the ground truth, then K − 1
//! Haar-uniform rotations.

use nalgebra::Rotation3;
use rand::{Rng, RngExt};
use serde::{Deserialize, Serialize};

use crate::so3::{GridLevel, haar_rotation, jitter_in_cell};

/// How the K rotations of an image are drawn.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum SamplingStrategy {
    /// `focused` rotations near the experts' modes, the rest uniform, the GT first.
    ModeFocused {
        /// How many of the K are drawn near the modes (paper: 3000 of 4096).
        focused: usize,
        /// Level of the coarse grid the modes are found on.
        level: u8,
    },
    /// The GT, then uniform rotations.
    Uniform,
}

/// Draws the K rotations: index 0 is `r_gt`. `coarse_log_weights` are the experts' combined
/// log-weights on every cell of `coarse` (needed by [`SamplingStrategy::ModeFocused`]).
pub fn sample_rotations<R: Rng + ?Sized>(
    strategy: &SamplingStrategy,
    k: usize,
    r_gt: &Rotation3<f64>,
    coarse: Option<(&GridLevel, &[f32])>,
    rng: &mut R,
) -> Vec<Rotation3<f64>> {
    let mut out = Vec::with_capacity(k);
    out.push(*r_gt);
    if let (SamplingStrategy::ModeFocused { focused, .. }, Some((grid, log_w))) = (strategy, coarse)
    {
        let max = log_w.iter().cloned().fold(f32::NEG_INFINITY, f32::max);
        let mut cumulative = Vec::with_capacity(log_w.len());
        let mut total = 0.0f64;
        for &w in log_w {
            total += ((w - max) as f64).exp();
            cumulative.push(total);
        }
        let n = (*focused).min(k.saturating_sub(1));
        for _ in 0..n {
            let u = rng.random_range(0.0..total);
            let cell = cumulative.partition_point(|&c| c <= u).min(log_w.len() - 1);
            out.push(jitter_in_cell(grid, cell as u64, rng));
        }
    }
    while out.len() < k {
        out.push(haar_rotation(rng));
    }
    out
}
