//! Choosing λ_SDF and λ_SE without the object's symmetry group (docs/DESIGN.md §2).
//!
//! The experts must find the symmetry from the CAD model alone, so nothing here may read the
//! group: a criterion that needs equivalents would pick the sharpest λ for a part whose symmetry
//! nobody declared (only the ground truth counts), and the target mass would sit on the ground
//! truth's own mode. The criterion is a **target width**: the ground truth is always a mode, so
//! the energies' rise at a geodesic distance `σ` from it, averaged over random poses and random
//! axes, is measured with λ = 1, and each λ is set so that its expert's log-target has fallen by
//! ¼ there: the product of both experts then falls by ½ at `σ`, a bell of width `σ` around every
//! pose that the experts cannot tell from the ground truth — its symmetric equivalents included,
//! whichever they are.

use nalgebra::{Rotation3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::energy::{BakedExperts, EnergyParams, LogTargets, visible_points};
use crate::cad::{Camera, Mesh, RenderOptions, render};
use crate::data::symsol_pose;
use crate::so3::{haar_rotation, random_axis, to_row_major_f32};

/// Side of the NOCS render that visible points are taken from.
pub const TARGET_RENDER_SIZE: u32 = 128;

/// Number of visible points per image (docs/DESIGN.md §2: about 100).
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

/// The width criterion: where and how the energies' rise is measured.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct WidthCriterion {
    /// Width `σ` of the combined target around each mode, in degrees.
    pub width_deg: f64,
    /// Random ground-truth poses.
    pub poses: usize,
    /// Random rotation axes per pose.
    pub axes: usize,
    /// Seed of the poses and axes.
    pub seed: u64,
}

impl Default for WidthCriterion {
    /// σ = 2.5°: measured on the cube's mesh with no symmetry given (level 4, 4 poses), 2°, 2.5°
    /// and 3° put 96 %, 90 % and 80 % of the target mass within 8° of the 24 equivalents.
    fn default() -> Self {
        WidthCriterion {
            width_deg: 2.5,
            poses: 8,
            axes: 16,
            seed: 0,
        }
    }
}

/// How λ was chosen, recorded in the expert manifest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct EnergySelection {
    /// `"width"` (format 2); empty in sets of format 1, whose λs were chosen by the LL of the
    /// targets against the declared equivalents.
    #[serde(default)]
    pub criterion: String,
    /// The criterion's parameters (format 2).
    #[serde(default)]
    pub width: Option<WidthCriterion>,
    /// Mean rise of the raw SDF energy (λ = 1) at `σ` from the ground truth.
    #[serde(default)]
    pub rise_sdf: f64,
    /// Mean rise of the raw feature energy (λ = 1) at `σ` from the ground truth.
    #[serde(default)]
    pub rise_se: f64,
    /// The chosen targets' profile: `(angle°, mean log a^SDF, mean log a^SE)` relative to the
    /// ground truth, at ½, 1, 2, 4 and 8 widths.
    #[serde(default)]
    pub profile: Vec<(f64, f64, f64)>,
    /// Format 1 only: `(λ_SDF, LL)` pairs tried.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub lambda_sdf: Vec<(f64, f64)>,
    /// Format 1 only: `(λ_SE, LL)` pairs tried.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub lambda_se: Vec<(f64, f64)>,
    /// Number of random poses.
    #[serde(default)]
    pub poses: usize,
}

/// Mean raw energy rise (`U(R) − U(R_gt)` with λ = 1) of each expert at each angle of
/// `angles_deg`, over the criterion's poses and axes. No symmetry is involved: only rotations at
/// a known distance from the ground truth are scored.
fn mean_rises(
    raw: &BakedExperts,
    mesh: &Mesh,
    criterion: &WidthCriterion,
    angles_deg: &[f64],
) -> Vec<(f64, f64)> {
    let mut rng = ChaCha8Rng::seed_from_u64(criterion.seed ^ 0x71d7);
    let mut sums = vec![(0.0f64, 0.0f64); angles_deg.len()];
    let mut count = 0usize;
    for p in 0..criterion.poses {
        let r_gt = haar_rotation(&mut rng);
        let x0 = visible_points_at(mesh, &r_gt, criterion.seed.wrapping_add(p as u64));
        if x0.is_empty() {
            continue;
        }
        let axes: Vec<_> = (0..criterion.axes).map(|_| random_axis(&mut rng)).collect();
        let mut rotations = vec![to_row_major_f32(&r_gt)];
        for angle in angles_deg {
            for a in &axes {
                let r = r_gt * Rotation3::from_axis_angle(a, angle.to_radians());
                rotations.push(to_row_major_f32(&r));
            }
        }
        let LogTargets {
            log_a_sdf,
            log_a_se,
        } = raw.log_targets(&r_gt, &x0, &rotations);
        for (i, sum) in sums.iter_mut().enumerate() {
            let range = 1 + i * axes.len()..1 + (i + 1) * axes.len();
            // log a = −U, so the rise is log a(R_gt) − log a(R).
            sum.0 += range
                .clone()
                .map(|k| (log_a_sdf[0] - log_a_sdf[k]) as f64)
                .sum::<f64>();
            sum.1 += range
                .map(|k| (log_a_se[0] - log_a_se[k]) as f64)
                .sum::<f64>();
        }
        count += axes.len();
    }
    let n = count.max(1) as f64;
    sums.into_iter().map(|(a, b)| (a / n, b / n)).collect()
}

/// Chooses λ_SDF and λ_SE by the width criterion (norms and ε from `experts.params`): each
/// expert's log-target falls by ¼ at `σ` from the ground truth, the product by ½. An expert
/// whose energy does not rise at all (a featureless object) gets λ = 0: it says nothing.
pub fn select_by_width(
    experts: &BakedExperts,
    mesh: &Mesh,
    criterion: &WidthCriterion,
) -> (EnergyParams, EnergySelection) {
    let raw = BakedExperts {
        params: EnergyParams {
            lambda_sdf: 1.0,
            lambda_se: 1.0,
            ..experts.params
        },
        ..experts.clone()
    };
    let multiples = [0.5, 1.0, 2.0, 4.0, 8.0];
    let angles: Vec<f64> = multiples.iter().map(|m| m * criterion.width_deg).collect();
    let rises = mean_rises(&raw, mesh, criterion, &angles);
    let (rise_sdf, rise_se) = rises[1];
    let lambda = |rise: f64| if rise > 1e-12 { 0.25 / rise } else { 0.0 };
    let chosen = EnergyParams {
        lambda_sdf: lambda(rise_sdf),
        lambda_se: lambda(rise_se),
        ..experts.params
    };
    let profile = angles
        .iter()
        .zip(&rises)
        .map(|(&deg, &(s, f))| (deg, -chosen.lambda_sdf * s, -chosen.lambda_se * f))
        .collect();
    (
        chosen,
        EnergySelection {
            criterion: "width".into(),
            width: Some(*criterion),
            rise_sdf,
            rise_se,
            profile,
            lambda_sdf: Vec::new(),
            lambda_se: Vec::new(),
            poses: criterion.poses,
        },
    )
}
