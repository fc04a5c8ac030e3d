//! Metrics of a distribution over a grid level against the equivalent ground truths of an image
//! (IPDF conventions, docs/DESIGN.md §2).
//!
//! A distribution is given as unnormalised log-weights `s_i`, one per cell of the level, in index
//! order; its mass is `p_i = softmax(s)_i`.

use nalgebra::Rotation3;
use rayon::prelude::*;

use super::modes::{self, Mode};
use super::{
    GridLevel, So3Error, from_quaternion, quaternion_angle, quaternion_dot, to_quaternion,
};

/// The metrics of one image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImageMetrics {
    /// `LL = mean_j log(p_{cell(G_j)} · N)`, see [`log_likelihood`].
    pub log_likelihood: f64,
    /// `Σ_i p_i · min_j angle(R_i, G_j)` in degrees, see [`spread_deg`].
    pub spread_deg: f64,
    /// `min_j angle(R_argmax, G_j)` in degrees.
    pub argmax_error_deg: f64,
    /// `min_j angle(R_mode, G_j)` in degrees for the first mode's mean rotation `R_mode`: the
    /// most massive group of the distribution's top cells, grouped as the server groups its
    /// answer's ([`first_mode`]).
    pub mode_error_deg: f64,
    /// The argmax cell's rotation as a unit quaternion `[w, x, y, z]`: where a miss lies.
    pub argmax: [f64; 4],
}

/// The most probable cells [`first_mode`] groups, at most: the server's answer lists fewer, and
/// a flat distribution's first mode is not worth grouping tens of thousands of cells for.
pub const MODE_CELLS: usize = 4096;

/// The first mode of a full distribution `probs` on `grid`: its [`MODE_CELLS`] most probable
/// cells grouped at the server's defaults ([`modes::group_modes`], 15°, 90 % of their mass).
/// A point estimate beside the argmax: a mode whose mass is spread over a few cells outweighs a
/// single sharper cell elsewhere. `None` for no cells.
pub fn first_mode(grid: &GridLevel, probs: &[f64]) -> Option<Mode> {
    let mut order: Vec<usize> = (0..probs.len()).collect();
    let by_mass = |a: &usize, b: &usize| probs[*b].total_cmp(&probs[*a]).then(a.cmp(b));
    if order.len() > MODE_CELLS {
        order.select_nth_unstable_by(MODE_CELLS, by_mass);
        order.truncate(MODE_CELLS);
    }
    order.sort_unstable_by(by_mass);
    let cells: Vec<(u64, f64)> = order.iter().map(|&i| (i as u64, probs[i])).collect();
    let angle = modes::DEFAULT_MODE_ANGLE_DEG.to_radians();
    modes::group_modes(
        grid,
        &cells,
        angle,
        modes::MODE_MASS_FRACTION,
        modes::MODE_MIN_MASS,
    )
    .into_iter()
    .next()
}

/// Normalised masses `p = softmax(s)`; errors when the length is not the grid's or a weight is
/// NaN/+∞.
pub fn softmax(grid: &GridLevel, log_weights: &[f32]) -> Result<Vec<f64>, So3Error> {
    if log_weights.len() != grid.len() {
        return Err(So3Error::WrongLength {
            got: log_weights.len(),
            level: grid.level(),
            expected: grid.len(),
        });
    }
    let max = log_weights
        .iter()
        .copied()
        .fold(f32::NEG_INFINITY, f32::max);
    if !max.is_finite() || log_weights.iter().any(|v| v.is_nan()) {
        return Err(So3Error::NonFiniteWeights);
    }
    let exp: Vec<f64> = log_weights
        .par_iter()
        .map(|&s| ((s - max) as f64).exp())
        .collect();
    let total: f64 = exp.par_iter().sum();
    Ok(exp.into_par_iter().map(|e| e / total).collect())
}

/// Log-likelihood with IPDF's `+log π²` (uniform = 0), averaged over every equivalent ground
/// truth `G_j` of the image:
///
/// `LL = (1/J) Σ_j log(p_{c(G_j)} · N)`, where `c = cell_of` (the cell that contains `G_j` by
/// construction) and `N = 72·8^L`. The density of cell `c` is `p_c / (π²/N)`, so
/// `log density + log π² = log(p_c·N)`.
pub fn log_likelihood(grid: &GridLevel, probs: &[f64], ground_truths: &[Rotation3<f64>]) -> f64 {
    let n = grid.len() as f64;
    ground_truths
        .iter()
        .map(|g| (probs[grid.cell_of(g) as usize] * n).ln())
        .sum::<f64>()
        / ground_truths.len() as f64
}

/// Spread in degrees, `Σ_i p_i · min_j angle(R_i, G_j)`, where `R_i` are the cell centres.
/// `centres` are the grid's quaternions ([`GridLevel::quaternions`], computed once per level).
pub fn spread_deg(probs: &[f64], centres: &[[f64; 4]], ground_truths: &[Rotation3<f64>]) -> f64 {
    let gts: Vec<[f64; 4]> = ground_truths.iter().map(to_quaternion).collect();
    probs
        .par_iter()
        .zip(centres.par_iter())
        .filter(|(p, _)| **p > 0.0)
        .map(|(p, q)| p * min_angle(q, &gts))
        .sum::<f64>()
        .to_degrees()
}

/// Angle in degrees from `r` to the nearest equivalent ground truth.
pub fn error_to_nearest_deg(r: &Rotation3<f64>, ground_truths: &[Rotation3<f64>]) -> f64 {
    let gts: Vec<[f64; 4]> = ground_truths.iter().map(to_quaternion).collect();
    min_angle(&to_quaternion(r), &gts).to_degrees()
}

/// Angle to the nearest of `gts`: the nearest has the largest `|⟨q, g⟩|`, so only one angle is
/// computed per call.
fn min_angle(q: &[f64; 4], gts: &[[f64; 4]]) -> f64 {
    let nearest = gts.iter().max_by(|a, b| {
        quaternion_dot(q, a)
            .abs()
            .total_cmp(&quaternion_dot(q, b).abs())
    });
    nearest.map_or(f64::INFINITY, |g| quaternion_angle(q, g))
}

/// All metrics of one image: LL, spread, the argmax's and the first mode's errors (see the
/// functions above).
pub fn image_metrics(
    grid: &GridLevel,
    centres: &[[f64; 4]],
    log_weights: &[f32],
    ground_truths: &[Rotation3<f64>],
) -> Result<ImageMetrics, So3Error> {
    if ground_truths.is_empty() {
        return Err(So3Error::NoGroundTruth);
    }
    let probs = softmax(grid, log_weights)?;
    let argmax = probs
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .map(|(i, _)| i as u64)
        .unwrap_or(0);
    let mode = match first_mode(grid, &probs) {
        Some(m) => from_quaternion(m.quaternion)?,
        None => grid.rotation(argmax),
    };
    Ok(ImageMetrics {
        log_likelihood: log_likelihood(grid, &probs, ground_truths),
        spread_deg: spread_deg(&probs, centres, ground_truths),
        argmax_error_deg: error_to_nearest_deg(&grid.rotation(argmax), ground_truths),
        mode_error_deg: error_to_nearest_deg(&mode, ground_truths),
        argmax: centres[argmax as usize],
    })
}

/// The best LL that a distribution on this level can reach for these ground truths: all mass
/// spread evenly over the `M` distinct cells that hold them gives `log(N/M)` (docs/DESIGN.md §2, "the
/// grid caps LL").
pub fn ll_ceiling(grid: &GridLevel, ground_truths: &[Rotation3<f64>]) -> f64 {
    let mut cells: Vec<u64> = ground_truths.iter().map(|g| grid.cell_of(g)).collect();
    cells.sort_unstable();
    cells.dedup();
    (grid.len() as f64 / cells.len() as f64).ln()
}

/// Metrics averaged over images.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MetricsSummary {
    /// Number of images.
    pub images: usize,
    /// Mean LL (uniform = 0).
    pub log_likelihood: f64,
    /// Mean spread in degrees.
    pub spread_deg: f64,
    /// `AR@θ`: fraction of images whose argmax is within `θ` of the nearest ground truth, as
    /// `(θ in degrees, fraction)`.
    pub accuracy_at: Vec<(f64, f64)>,
    /// Median over images of the argmax's error in degrees.
    pub median_error_deg: f64,
    /// Fraction of images whose density at the truth is below uniform (image LL < 0): the
    /// distribution is sharp somewhere else, *confidently wrong*.
    #[serde(default)]
    pub confidently_wrong: f64,
    /// Fraction of images whose argmax is at least [`HALF_TURN_DEG`] from every ground truth:
    /// the answer is the pose turned about half a turn, a near-lookalike the model did not tell
    /// apart, not a scattered error.
    #[serde(default)]
    pub half_turn_wrong: f64,
    /// `AR@θ` of the first mode ([`ImageMetrics::mode_error_deg`]), at the same `θ`s (empty in
    /// reports written before it).
    #[serde(default)]
    pub mode_accuracy_at: Vec<(f64, f64)>,
    /// Median over images of the first mode's error in degrees (NaN in reports before it).
    #[serde(default = "not_measured")]
    pub mode_median_error_deg: f64,
}

fn not_measured() -> f64 {
    f64::NAN
}

/// The median of `values` (NaN when empty), sorting them.
fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    match values.len() {
        0 => f64::NAN,
        k if k % 2 == 1 => values[k / 2],
        k => 0.5 * (values[k / 2 - 1] + values[k / 2]),
    }
}

/// The `q`-quantile (nearest rank) of `values`, in any order: every latency figure's p50/p99
/// (the benches, the load client, `eval --served`).
pub fn quantile(values: &[f64], q: f64) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

/// The error in degrees from which an argmax counts as the pose's half-turn twin
/// ([`MetricsSummary::half_turn_wrong`]).
pub const HALF_TURN_DEG: f64 = 150.0;

/// `AR@θ` for each `θ` of `thresholds_deg` (the share of `errors_deg` below it, as `(θ,
/// share)`) and the median error: how a point estimate's errors are summarised.
pub fn accuracy_and_median(errors_deg: &[f64], thresholds_deg: &[f64]) -> (Vec<(f64, f64)>, f64) {
    let n = errors_deg.len().max(1) as f64;
    let accuracy = thresholds_deg
        .iter()
        .map(|&t| (t, errors_deg.iter().filter(|&&e| e < t).count() as f64 / n))
        .collect();
    (accuracy, median(&mut errors_deg.to_vec()))
}

/// Averages per-image metrics; `thresholds_deg` are the `θ` of `AR@θ` (e.g. `[30.0]`).
pub fn summarize(per_image: &[ImageMetrics], thresholds_deg: &[f64]) -> MetricsSummary {
    let n = per_image.len().max(1) as f64;
    let errors: Vec<f64> = per_image.iter().map(|m| m.argmax_error_deg).collect();
    let mode_errors: Vec<f64> = per_image.iter().map(|m| m.mode_error_deg).collect();
    let (accuracy_at, median_error_deg) = accuracy_and_median(&errors, thresholds_deg);
    let (mode_accuracy_at, mode_median_error_deg) =
        accuracy_and_median(&mode_errors, thresholds_deg);
    MetricsSummary {
        images: per_image.len(),
        log_likelihood: per_image.iter().map(|m| m.log_likelihood).sum::<f64>() / n,
        spread_deg: per_image.iter().map(|m| m.spread_deg).sum::<f64>() / n,
        accuracy_at,
        median_error_deg,
        confidently_wrong: per_image.iter().filter(|m| m.log_likelihood < 0.0).count() as f64 / n,
        half_turn_wrong: errors.iter().filter(|&&e| e >= HALF_TURN_DEG).count() as f64 / n,
        mode_accuracy_at,
        mode_median_error_deg,
    }
}

/// How a distribution's mass sits around the equivalent ground truths of an image (the expert
/// targets' *balance*, docs/DESIGN.md §2).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MassNearEquivalents {
    /// The radius in degrees.
    pub radius_deg: f64,
    /// Per equivalent, the mass of the cells within the radius whose nearest equivalent it is.
    pub per_equivalent: Vec<f64>,
    /// Total mass within the radius of some equivalent.
    pub inside: f64,
    /// `1 − inside`.
    pub outside: f64,
    /// `min / max` of [`MassNearEquivalents::per_equivalent`] (1 = perfectly balanced).
    pub balance: f64,
}

/// The mass of `probs` (one per cell, `centres` from [`GridLevel::quaternions`]) within
/// `radius_deg` of each of `ground_truths`, each cell counted for its nearest ground truth only.
pub fn mass_near_equivalents(
    probs: &[f64],
    centres: &[[f64; 4]],
    ground_truths: &[Rotation3<f64>],
    radius_deg: f64,
) -> MassNearEquivalents {
    let gts: Vec<[f64; 4]> = ground_truths.iter().map(to_quaternion).collect();
    // |⟨q, g⟩| ≥ cos(radius / 2) ⇔ angle ≤ radius.
    let min_dot = (radius_deg.to_radians() / 2.0).cos();
    let per_equivalent = probs
        .par_iter()
        .zip(centres.par_iter())
        .filter(|(p, _)| **p > 0.0)
        .fold(
            || vec![0.0f64; gts.len()],
            |mut acc, (p, q)| {
                let best = gts
                    .iter()
                    .map(|g| quaternion_dot(q, g).abs())
                    .enumerate()
                    .max_by(|a, b| a.1.total_cmp(&b.1));
                if let Some((j, dot)) = best
                    && dot >= min_dot
                {
                    acc[j] += p;
                }
                acc
            },
        )
        .reduce(
            || vec![0.0f64; gts.len()],
            |mut a, b| {
                a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
                a
            },
        );
    let inside: f64 = per_equivalent.iter().sum();
    let max = per_equivalent.iter().cloned().fold(0.0f64, f64::max);
    let min = per_equivalent.iter().cloned().fold(f64::INFINITY, f64::min);
    MassNearEquivalents {
        radius_deg,
        balance: if max > 0.0 { min / max } else { 0.0 },
        per_equivalent,
        inside,
        outside: (1.0 - inside).max(0.0),
    }
}

/// `AR@θ` of an argmax that ignores the image: the probability that a Haar-random rotation lies
/// within `threshold_deg` of one of `symmetries` (estimated from `samples` seeded draws).
pub fn chance_accuracy(
    symmetries: &[Rotation3<f64>],
    threshold_deg: f64,
    samples: usize,
    seed: u64,
) -> f64 {
    use rand::SeedableRng;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let rotations = super::haar_rotations(&mut rng, samples);
    let group: Vec<[f64; 4]> = symmetries.iter().map(to_quaternion).collect();
    let threshold = threshold_deg.to_radians();
    let hits = rotations
        .par_iter()
        .filter(|r| min_angle(&to_quaternion(r), &group) < threshold)
        .count();
    hits as f64 / samples.max(1) as f64
}
