//! The modes of a distribution over a grid level: its most probable cells grouped by angle, each
//! group's mass and mean rotation. The server answers them (`Predict`'s modes, from the search's
//! cells) and the evaluation scores the first one as a point estimate beside the argmax
//! (the metrics' first-mode error).

use nalgebra::{Quaternion, Rotation3, UnitQuaternion};

use super::{GridLevel, quaternion_angle, quaternion_dot, to_quaternion};

/// The angle within which top cells are grouped into one mode, unless a call gives its own
/// (degrees).
pub const DEFAULT_MODE_ANGLE_DEG: f64 = 15.0;
/// The share of the listed mass whose cells are grouped into modes.
pub const MODE_MASS_FRACTION: f64 = 0.9;
/// Modes under this share of the listed mass are dropped (the most probable is always kept).
pub const MODE_MIN_MASS: f64 = 0.01;

/// A mode: top cells within an angle of its most probable cell.
#[derive(Debug, Clone, PartialEq)]
pub struct Mode {
    /// Mass-weighted mean rotation (unit quaternion `(w, x, y, z)`, `w ≥ 0`).
    pub quaternion: [f64; 4],
    /// Mass of the mode's cells.
    pub probability: f64,
    /// Mass-weighted mean angle of its cells to the mean, in degrees.
    pub spread_deg: f64,
    /// Number of cells.
    pub cells: usize,
}

/// Groups cells `(index, mass)` (most probable first) into modes: each cell joins the first mode whose seed (its
/// most probable cell) is within `angle_rad`, or starts a new one. Only the cells that make up
/// `mass_fraction` of the listed mass are grouped, and modes under `min_mass` of it are dropped,
/// so that stray cells do not count as modes (the most probable mode is always kept).
pub fn group_modes(
    grid: &GridLevel,
    cells: &[(u64, f64)],
    angle_rad: f64,
    mass_fraction: f64,
    min_mass: f64,
) -> Vec<Mode> {
    let total: f64 = cells.iter().map(|c| c.1).sum();
    let mut seeds: Vec<[f64; 4]> = Vec::new();
    let mut members: Vec<Vec<([f64; 4], f64)>> = Vec::new();
    let mut so_far = 0.0;
    for &(cell, probability) in cells {
        // The first cell always seeds a mode (even when every mass is zero).
        if !seeds.is_empty() && so_far >= mass_fraction * total {
            break;
        }
        so_far += probability;
        let q = to_quaternion(&grid.rotation(cell));
        match seeds
            .iter()
            .position(|s| quaternion_angle(s, &q) <= angle_rad)
        {
            Some(m) => members[m].push((q, probability)),
            None => {
                seeds.push(q);
                members.push(vec![(q, probability)]);
            }
        }
    }
    let mut modes: Vec<Mode> = seeds
        .iter()
        .zip(&members)
        .map(|(seed, cells)| mode_of(seed, cells))
        .collect();
    modes.sort_by(|a, b| b.probability.total_cmp(&a.probability));
    // The most probable mode is always reported (a flat distribution has one, wide mode).
    let mut kept = modes.into_iter().enumerate();
    kept.by_ref()
        .filter(|(i, m)| *i == 0 || m.probability >= min_mass * total)
        .map(|(_, m)| m)
        .collect()
}

fn mode_of(seed: &[f64; 4], cells: &[([f64; 4], f64)]) -> Mode {
    let mut sum = [0.0f64; 4];
    let mut mass = 0.0;
    for (q, p) in cells {
        let sign = if quaternion_dot(seed, q) < 0.0 {
            -1.0
        } else {
            1.0
        };
        for (s, v) in sum.iter_mut().zip(q) {
            *s += sign * p * v;
        }
        mass += p;
    }
    // Cells of no mass (underflowed) have no weighted mean: their seed stands for them.
    let mean = match mass > 0.0 {
        true => to_quaternion(&Rotation3::from(UnitQuaternion::from_quaternion(
            Quaternion::new(sum[0], sum[1], sum[2], sum[3]),
        ))),
        false => *seed,
    };
    let spread = cells
        .iter()
        .map(|(q, p)| p * quaternion_angle(&mean, q))
        .sum::<f64>()
        / mass.max(f64::MIN_POSITIVE);
    Mode {
        quaternion: mean,
        probability: mass,
        spread_deg: spread.to_degrees(),
        cells: cells.len(),
    }
}
