//! Choosing λ_SDF and λ_SE by the log-likelihood of the target distributions they give
//! (DESIGN.md §2: "choose them by measured LL, and record them").
//!
//! For a few random poses, the raw energies (λ = 1) of every cell centre of a grid level are
//! computed once; each λ then gives targets `a = exp(−λ·U)`, scored as a distribution on the
//! grid against every equivalent ground truth (LL, uniform = 0). The best λ of each expert wins.

use nalgebra::{Rotation3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::energy::{BakedExperts, EnergyParams, LogTargets, visible_points};
use crate::cad::{Camera, Mesh, RenderOptions, render};
use crate::data::symsol_pose;
use crate::so3::metrics::{log_likelihood, softmax};
use crate::so3::{GridLevel, equivalents, haar_rotation};

/// Side of the NOCS render that visible points are taken from.
pub const TARGET_RENDER_SIZE: u32 = 128;

/// Number of visible points per image (DESIGN.md §2: about 100).
pub const VISIBLE_POINTS: usize = 100;

/// The visible canonical points of `mesh` at rotation `r_gt` (SYMSOL pose), seeded.
pub fn visible_points_at(mesh: &Mesh, r_gt: &Rotation3<f64>, seed: u64) -> Vec<Vector3<f32>> {
    let image = render(
        mesh,
        &Camera::square(TARGET_RENDER_SIZE),
        &symsol_pose(*r_gt),
        &RenderOptions::default(),
    );
    visible_points(&image, VISIBLE_POINTS, &mut ChaCha8Rng::seed_from_u64(seed))
}

/// The values tried and where they are measured.
#[derive(Debug, Clone)]
pub struct LambdaSweep {
    /// λ_SDF values.
    pub sdf: Vec<f64>,
    /// λ_SE values.
    pub se: Vec<f64>,
    /// Grid level of the LL.
    pub level: u8,
    /// Random poses per value.
    pub poses: usize,
    /// Seed of the poses.
    pub seed: u64,
}

/// Sweeps λ_SDF and λ_SE (other parameters from `experts.params`); returns the chosen
/// parameters and the sweep's LLs.
pub fn select_lambdas(
    experts: &BakedExperts,
    mesh: &Mesh,
    symmetries: &[Rotation3<f64>],
    sweep_values: &LambdaSweep,
) -> (EnergyParams, EnergySelection) {
    let LambdaSweep {
        sdf: sdf_values,
        se: se_values,
        level,
        poses,
        seed,
    } = sweep_values.clone();
    let grid = GridLevel::new(level).expect("selection level is a valid grid level");
    let cells = grid.matrices_f32();
    let unit = EnergyParams {
        lambda_sdf: 1.0,
        lambda_se: 1.0,
        ..experts.params
    };
    let raw_experts = BakedExperts {
        params: unit,
        ..experts.clone()
    };
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let raw: Vec<(LogTargets, Vec<Rotation3<f64>>)> = (0..poses)
        .map(|k| {
            let r_gt = haar_rotation(&mut rng);
            let x0 = visible_points_at(mesh, &r_gt, seed.wrapping_add(k as u64));
            (
                raw_experts.log_targets(&r_gt, &x0, &cells),
                equivalents(&r_gt, symmetries),
            )
        })
        .collect();
    let mean_ll = |pick: &dyn Fn(&LogTargets) -> &Vec<f32>, lambda: f64| {
        raw.iter()
            .map(|(t, eq)| {
                let w: Vec<f32> = pick(t).iter().map(|u| u * lambda as f32).collect();
                let p = softmax(&grid, &w).expect("finite targets");
                log_likelihood(&grid, &p, eq)
            })
            .sum::<f64>()
            / raw.len().max(1) as f64
    };
    let sweep = |pick: &dyn Fn(&LogTargets) -> &Vec<f32>, values: &[f64]| -> Vec<(f64, f64)> {
        values.iter().map(|&l| (l, mean_ll(pick, l))).collect()
    };
    let sdf_sweep = sweep(&|t| &t.log_a_sdf, &sdf_values);
    let se_sweep = sweep(&|t| &t.log_a_se, &se_values);
    let best = |s: &[(f64, f64)], fallback: f64| {
        s.iter()
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .map_or(fallback, |b| b.0)
    };
    let chosen = EnergyParams {
        lambda_sdf: best(&sdf_sweep, experts.params.lambda_sdf),
        lambda_se: best(&se_sweep, experts.params.lambda_se),
        ..experts.params
    };
    (
        chosen,
        EnergySelection {
            lambda_sdf: sdf_sweep,
            lambda_se: se_sweep,
            level,
            poses,
        },
    )
}

/// The λ sweeps that chose the energy hyper-parameters by the LL of the targets they give.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct EnergySelection {
    /// `(λ_SDF, LL)` pairs tried.
    pub lambda_sdf: Vec<(f64, f64)>,
    /// `(λ_SE, LL)` pairs tried.
    pub lambda_se: Vec<(f64, f64)>,
    /// Grid level the LL was measured at.
    pub level: u8,
    /// Number of random poses per value.
    pub poses: usize,
}
