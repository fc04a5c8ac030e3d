//! Energies of candidate rotations and the target measures they give (paper Eq. 3–4,
//! docs/DESIGN.md §2).
//!
//! `x⁰_i` are visible surface points in canonical coordinates (from a NOCS render at `R_gt`).
//! A candidate `R` explains them as `x'_i = Rᵀ·R_gt·x⁰_i`; at `R = R_gt·S` for a symmetry `S`,
//! every `x'_i` is on the surface again, and (with symmetry-aware keys) has the key of `x⁰_i`.

use nalgebra::{Matrix3, Rotation3, Vector3};
use rand::{Rng, RngExt};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::baked::VoxelGrid;
use super::joint::{JointGrid, Record};
use crate::cad::Render;

/// The norm of the SDF energy.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SdfNorm {
    /// The paper's "L0 norm": the fraction of points with `|f_SDF(x')| > ε`.
    L0,
    /// `mean |f_SDF(x')| / ε`.
    L1,
    /// `mean f_SDF(x')² / ε²`: graded, and quadratic in the angle near a mode, so that
    /// `exp(−U)` is a bell a few degrees wide around every pose that puts the points back on the
    /// surface (the training default, see [`EnergyParams::default`]).
    L2,
}

/// How the feature energy measures the distance between the keys of `x'` and `x⁰`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum KeyNorm {
    /// `mean_i ‖f_SE(x'_i) − f_SE(x⁰_i)‖₂` (the paper's).
    #[default]
    Distance,
    /// `mean_i ‖f_SE(x'_i) − f_SE(x⁰_i)‖₂²`: graded like [`SdfNorm::L2`].
    Squared,
}

/// Hyper-parameters of the energies, recorded in the expert manifest.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EnergyParams {
    /// `λ_SDF`.
    pub lambda_sdf: f64,
    /// `ε`, in NOCS units (fraction of the bounding-sphere radius).
    pub epsilon: f64,
    /// Norm of the SDF energy.
    pub norm: SdfNorm,
    /// `λ_SE`, per unit of key distance.
    pub lambda_se: f64,
    /// How key distances are measured (expert sets of format 1 have [`KeyNorm::Distance`]).
    #[serde(default)]
    pub key_norm: KeyNorm,
}

impl Default for EnergyParams {
    /// The graded energies (L2 SDF, squared key distance, ε = 0.02); the λs are placeholders
    /// that [`super::select::select_by_width`] replaces when an expert set is trained.
    fn default() -> Self {
        EnergyParams {
            lambda_sdf: 1.0,
            epsilon: 0.02,
            norm: SdfNorm::L2,
            lambda_se: 1.0,
            key_norm: KeyNorm::Squared,
        }
    }
}

/// `U_SDF = λ_SDF · ‖f_SDF(x')‖₀` (fraction of `|f| > ε`), or `λ_SDF · mean|f|/ε` for L1.
pub fn sdf_energy(sdf_values: &[f32], params: &EnergyParams) -> f64 {
    let n = sdf_values.len().max(1) as f64;
    let eps = params.epsilon as f32;
    let norm = match params.norm {
        SdfNorm::L0 => sdf_values.iter().filter(|v| v.abs() > eps).count() as f64 / n,
        SdfNorm::L1 => sdf_values.iter().map(|v| v.abs() as f64).sum::<f64>() / n / params.epsilon,
        SdfNorm::L2 => {
            sdf_values.iter().map(|&v| (v as f64).powi(2)).sum::<f64>() / n / params.epsilon.powi(2)
        }
    };
    params.lambda_sdf * norm
}

/// `mean_i ‖a_i − b_i‖₂` over keys given row-major as `n × dim`.
pub fn mean_key_distance(a: &[f32], b: &[f32], dim: usize) -> f64 {
    let n = (a.len() / dim).max(1) as f64;
    a.chunks(dim)
        .zip(b.chunks(dim))
        .map(|(u, v)| {
            u.iter()
                .zip(v)
                .map(|(p, q)| (p - q).powi(2))
                .sum::<f32>()
                .sqrt() as f64
        })
        .sum::<f64>()
        / n
}

/// `mean_i ‖a_i − b_i‖₂²` over keys given row-major as `n × dim`.
pub fn mean_squared_key_distance(a: &[f32], b: &[f32], dim: usize) -> f64 {
    let n = (a.len() / dim).max(1) as f64;
    a.iter()
        .zip(b)
        .map(|(p, q)| ((p - q) as f64).powi(2))
        .sum::<f64>()
        / n
}

/// `U_SE = λ_SE · mean_i ‖f_SE(x'_i) − f_SE(x⁰_i)‖₂` (paper Eq. 4), or its squared form
/// ([`KeyNorm::Squared`]); keys are row-major `n × d`.
pub fn se_energy(keys_moved: &[f32], keys_seen: &[f32], dim: usize, params: &EnergyParams) -> f64 {
    params.lambda_se
        * match params.key_norm {
            KeyNorm::Distance => mean_key_distance(keys_moved, keys_seen, dim),
            KeyNorm::Squared => mean_squared_key_distance(keys_moved, keys_seen, dim),
        }
}

/// Up to `n` visible canonical points: NOCS values of pixels drawn uniformly inside the mask.
pub fn visible_points<R: Rng + ?Sized>(
    render: &Render,
    n: usize,
    rng: &mut R,
) -> Vec<Vector3<f32>> {
    let fg: Vec<usize> = (0..render.mask.len()).filter(|&k| render.mask[k]).collect();
    if fg.is_empty() {
        return Vec::new();
    }
    (0..n)
        .map(|_| Vector3::from(render.nocs[fg[rng.random_range(0..fg.len())]]))
        .collect()
}

/// Log target weights of many candidate rotations: `log a^SDF_k = −U_SDF(R_k)` and
/// `log a^SE_k = −U_SE(R_k)`.
#[derive(Debug, Clone, PartialEq)]
pub struct LogTargets {
    /// `−U_SDF` per candidate.
    pub log_a_sdf: Vec<f32>,
    /// `−U_SE` per candidate.
    pub log_a_se: Vec<f32>,
}

impl LogTargets {
    /// `log a^SDF + log a^SE` per candidate: the log of the product of experts (paper Eq. 3–4).
    pub fn combined(&self) -> Vec<f32> {
        self.log_a_sdf
            .iter()
            .zip(&self.log_a_se)
            .map(|(a, b)| a + b)
            .collect()
    }
}

/// The experts, baked, with their energy hyper-parameters.
#[derive(Debug, Clone)]
pub struct BakedExperts {
    /// `f_SDF` on a grid (1 channel).
    pub sdf: VoxelGrid,
    /// `f_SE` on a grid (12 channels).
    pub keys: VoxelGrid,
    /// λ, ε, norm.
    pub params: EnergyParams,
    /// `sdf` and `keys` in one grid of cache-line records, made on first use: one lookup per
    /// point instead of two (the targets are bound by these lookups).
    pub(crate) joint: std::sync::OnceLock<Option<JointGrid>>,
}

impl BakedExperts {
    /// Baked experts from their grids and energy parameters.
    pub fn new(sdf: VoxelGrid, keys: VoxelGrid, params: EnergyParams) -> Self {
        BakedExperts {
            sdf,
            keys,
            params,
            joint: std::sync::OnceLock::new(),
        }
    }

    /// Scores `candidates` (row-major `f32` matrices) for an image whose ground truth is `r_gt`
    /// and whose visible canonical points are `x0` (parallel over candidates).
    pub fn log_targets(
        &self,
        r_gt: &Rotation3<f64>,
        x0: &[Vector3<f32>],
        candidates: &[[f32; 9]],
    ) -> LogTargets {
        let dim = self.keys.channels();
        let seen = self.keys.sample(x0);
        let gt: Matrix3<f32> = r_gt.matrix().cast();
        let joint = self
            .joint
            .get_or_init(|| JointGrid::new(&self.sdf, &self.keys))
            .as_ref();
        // The training default's energies are summed as the points are looked up.
        let squared = self.params.norm == SdfNorm::L2 && self.params.key_norm == KeyNorm::Squared;
        let fused: Option<(&JointGrid, Vec<Record>)> = joint
            .filter(|_| squared)
            .map(|j| (j, seen.chunks_exact(dim).map(|k| j.seen(k)).collect()));
        let scored: Vec<(f32, f32)> = candidates
            .par_iter()
            .map_init(
                || (vec![0f32; x0.len()], vec![0f32; x0.len() * dim]),
                |buffers, m| {
                    // x' = Rᵀ·R_gt·x⁰.
                    let map = Matrix3::from_row_slice(m).transpose() * gt;
                    match &fused {
                        Some((joint, seen)) => self.squared_log_targets(joint, &map, x0, seen),
                        None => self.looked_up_log_targets(joint, &map, x0, &seen, buffers),
                    }
                },
            )
            .collect();
        LogTargets {
            log_a_sdf: scored.iter().map(|s| s.0).collect(),
            log_a_se: scored.iter().map(|s| s.1).collect(),
        }
    }

    /// `(−U_SDF, −U_SE)` of one candidate (`map = Rᵀ·R_gt`) for the training default's
    /// energies (L2 SDF, squared key distance), summed as the points are looked up
    /// ([`JointGrid::squared_energies`]).
    fn squared_log_targets(
        &self,
        joint: &JointGrid,
        map: &Matrix3<f32>,
        x0: &[Vector3<f32>],
        seen: &[Record],
    ) -> (f32, f32) {
        let n = x0.len().max(1) as f64;
        let p = &self.params;
        let (sdf, keys) = joint.squared_energies(map, x0, seen);
        (
            (-p.lambda_sdf * sdf as f64 / n / p.epsilon.powi(2)) as f32,
            (-p.lambda_se * keys as f64 / n) as f32,
        )
    }

    /// `(−U_SDF, −U_SE)` of one candidate for any energy: the points' values looked up into
    /// `buffers` (one value, then `dim` keys per point), then [`sdf_energy`] and [`se_energy`].
    fn looked_up_log_targets(
        &self,
        joint: Option<&JointGrid>,
        map: &Matrix3<f32>,
        x0: &[Vector3<f32>],
        seen: &[f32],
        (sdf_buf, key_buf): &mut (Vec<f32>, Vec<f32>),
    ) -> (f32, f32) {
        let dim = self.keys.channels();
        for (i, x) in x0.iter().enumerate() {
            let moved = map * x;
            let keys = &mut key_buf[i * dim..(i + 1) * dim];
            match joint {
                Some(joint) => {
                    let both = joint.sample(&moved);
                    sdf_buf[i] = both[0];
                    keys.copy_from_slice(&both[1..=dim]);
                }
                None => {
                    self.sdf.sample_into(&moved, &mut sdf_buf[i..i + 1]);
                    self.keys.sample_into(&moved, keys);
                }
            }
        }
        (
            -sdf_energy(sdf_buf, &self.params) as f32,
            -se_energy(key_buf, seen, dim, &self.params) as f32,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::so3::{haar_rotation, haar_rotations, to_row_major_f32};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// The fused sums (the training default) give the targets that looking every point up and
    /// then applying [`sdf_energy`] and [`se_energy`] gives.
    #[test]
    fn the_fused_squared_targets_equal_the_general_ones() {
        let sdf = VoxelGrid::bake(17, 1.05, 1, |p| {
            p.iter().map(|v| v.norm() - 0.6 + 0.2 * v.x * v.z).collect()
        });
        let keys = VoxelGrid::bake(17, 1.05, 12, |p| {
            p.iter()
                .flat_map(|v| (0..12).map(move |k| (k as f32 + v.x * 3.0).cos() * v.y + v.z))
                .collect()
        });
        let params = EnergyParams {
            lambda_sdf: 0.7,
            lambda_se: 3.0,
            ..EnergyParams::default()
        };
        let experts = BakedExperts::new(sdf, keys, params);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let r_gt = haar_rotation(&mut rng);
        let x0: Vec<Vector3<f32>> = (0..100)
            .map(|i| {
                let a = i as f32 * 0.61;
                Vector3::new(a.cos(), a.sin(), (a * 0.4).cos()).normalize() * 0.6
            })
            .collect();
        let candidates: Vec<[f32; 9]> = haar_rotations(&mut rng, 64)
            .iter()
            .map(to_row_major_f32)
            .collect();
        let fused = experts.log_targets(&r_gt, &x0, &candidates);
        let seen = experts.keys.sample(&x0);
        let gt: Matrix3<f32> = r_gt.matrix().cast();
        let mut buffers = (vec![0f32; x0.len()], vec![0f32; x0.len() * 12]);
        let general: Vec<(f32, f32)> = candidates
            .iter()
            .map(|m| {
                let map = Matrix3::from_row_slice(m).transpose() * gt;
                experts.looked_up_log_targets(None, &map, &x0, &seen, &mut buffers)
            })
            .collect();
        let spread = fused.log_a_se.iter().cloned().fold(0f32, f32::min);
        assert!(spread < -0.5, "energies that vary ({spread})");
        for (k, (s, e)) in general.iter().enumerate() {
            let close = |a: f32, b: f32| (a - b).abs() <= 1e-4 * (1.0 + b.abs());
            assert!(
                close(fused.log_a_sdf[k], *s),
                "{k}: {} {s}",
                fused.log_a_sdf[k]
            );
            assert!(
                close(fused.log_a_se[k], *e),
                "{k}: {} {e}",
                fused.log_a_se[k]
            );
        }
    }
}
