//! The object's table of relative rotations where targets have mass (docs/DESIGN.md §2, "Sampling").
//!
//! The targets of an image depend on a candidate `R` only through `Q = R_gtᵀ·R` and the visible
//! points, so for every view they have mass at `R_gt·Q` for `Q` in one fixed set: the object's
//! symmetries and near-symmetries, with their shoulders. That set is found once per object from
//! the experts — never from a declared symmetry group: over random views, the combined measure
//! `a^SDF·a^SE` of every cell `Q` of a coarse level (relative to each view's peak, which is the
//! ground truth), its best cells refined one level, and the cells of the fine level whose best
//! value over the views is highest kept. The trainer draws its mode-focused samples as
//! `R_gt·jitter(Q)` from this table, so the per-image mode search is gone.

use nalgebra::Rotation3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::energy::BakedExperts;
use super::select::visible_points_at;
use crate::cad::Mesh;
use crate::so3::{GridConvention, GridLevel, So3Error, haar_rotation, to_row_major_f32};

/// How the table is built.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ModeTableConfig {
    /// Random views whose targets are searched.
    pub views: usize,
    /// Level scored in full.
    pub coarse_level: u8,
    /// Level of the table's cells (`coarse_level + 1`).
    pub level: u8,
    /// Fraction of the fine level's cells kept (the modes with their shoulders).
    pub keep_fraction: f64,
    /// Seed of the views.
    pub seed: u64,
}

impl Default for ModeTableConfig {
    /// 16 views, level 3 in full, the best 1 % of level 4 (2 949 cells of ~2°).
    fn default() -> Self {
        ModeTableConfig {
            views: 16,
            coarse_level: 3,
            level: 4,
            keep_fraction: 0.01,
            seed: 0,
        }
    }
}

/// Cells `Q` of a fine level near which the object's targets have mass, with the best
/// log-measure (relative to the view's ground truth) any view gave them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModeTable {
    /// How it was built.
    pub config: ModeTableConfig,
    /// The grid convention of `cells` (tables written before compact polar cells have none and
    /// are read in the old one).
    #[serde(default)]
    pub grid: GridConvention,
    /// Cell indices at `config.level`, best first.
    pub cells: Vec<u64>,
    /// `max over views of log a(R_gt·Q) − log a(R_gt)` per cell.
    pub log_weights: Vec<f32>,
}

/// `log a^SDF + log a^SE` of `R_gt·Q` for every `Q` of `relative` (row-major), minus the value at
/// the ground truth.
fn relative_log_measure(
    experts: &BakedExperts,
    r_gt: &Rotation3<f64>,
    x0: &[nalgebra::Vector3<f32>],
    relative: &[Rotation3<f64>],
) -> Vec<f32> {
    let mut mats = vec![to_row_major_f32(r_gt)];
    mats.extend(relative.iter().map(|q| to_row_major_f32(&(r_gt * q))));
    let total = experts.log_targets(r_gt, x0, &mats).combined();
    total[1..].iter().map(|v| v - total[0]).collect()
}

/// Elementwise max of `acc` and `values`.
fn max_into(acc: &mut [f32], values: &[f32]) {
    acc.iter_mut().zip(values).for_each(|(a, v)| *a = a.max(*v));
}

/// Positions of the `n` largest values, largest first (ties by position).
fn best_positions(values: &[f32], n: usize) -> Vec<usize> {
    let mut order: Vec<usize> = (0..values.len()).collect();
    let by_value = |a: &usize, b: &usize| values[*b].total_cmp(&values[*a]).then(a.cmp(b));
    if order.len() > n && n > 0 {
        order.select_nth_unstable_by(n - 1, by_value);
        order.truncate(n);
    }
    order.sort_by(by_value);
    order
}

impl ModeTable {
    /// Builds the table of `experts` (baked, with their chosen λs) for `mesh`.
    pub fn build(
        experts: &BakedExperts,
        mesh: &Mesh,
        config: &ModeTableConfig,
    ) -> Result<ModeTable, So3Error> {
        let coarse = GridLevel::new(config.coarse_level)?;
        let fine = GridLevel::new(config.coarse_level + 1)?;
        let mut rng = ChaCha8Rng::seed_from_u64(config.seed ^ 0x30de5);
        let views: Vec<_> = (0..config.views.max(1))
            .map(|v| {
                let r_gt = haar_rotation(&mut rng);
                let x0 = visible_points_at(mesh, &r_gt, config.seed.wrapping_add(v as u64));
                (r_gt, x0)
            })
            .filter(|(_, x0)| !x0.is_empty())
            .collect();
        let coarse_q: Vec<Rotation3<f64>> = (0..coarse.len() as u64)
            .map(|c| coarse.rotation(c))
            .collect();
        let mut coarse_best = vec![f32::NEG_INFINITY; coarse.len()];
        for (r_gt, x0) in &views {
            max_into(
                &mut coarse_best,
                &relative_log_measure(experts, r_gt, x0, &coarse_q),
            );
        }
        // Twice the kept fraction of the coarse level: their children hold the kept fine cells
        // with a margin.
        let keep_fine = ((fine.len() as f64 * config.keep_fraction).ceil() as usize).max(1);
        let keep_coarse = (2 * keep_fine).div_ceil(8).max(1);
        let candidates: Vec<u64> = best_positions(&coarse_best, keep_coarse)
            .into_iter()
            .flat_map(|i| coarse.children(i as u64))
            .collect();
        let fine_q: Vec<Rotation3<f64>> = candidates.iter().map(|&c| fine.rotation(c)).collect();
        let mut fine_best = vec![f32::NEG_INFINITY; candidates.len()];
        for (r_gt, x0) in &views {
            max_into(
                &mut fine_best,
                &relative_log_measure(experts, r_gt, x0, &fine_q),
            );
        }
        let best = best_positions(&fine_best, keep_fine);
        Ok(ModeTable {
            config: ModeTableConfig {
                level: fine.level(),
                ..*config
            },
            grid: GridConvention::CompactPoles,
            cells: best.iter().map(|&i| candidates[i]).collect(),
            log_weights: best.iter().map(|&i| fine_best[i]).collect(),
        })
    }

    /// The grid level of the cells.
    pub fn grid(&self) -> Result<GridLevel, So3Error> {
        GridLevel::new(self.config.level)
    }

    /// The centre rotations of the cells, in the table's grid convention.
    pub fn centres(&self) -> Result<Vec<Rotation3<f64>>, So3Error> {
        let grid = self.grid()?;
        Ok(self
            .cells
            .iter()
            .map(|&c| grid.rotation_in(self.grid, c))
            .collect())
    }

    /// Checks the table against its own level: cells in range, one weight per cell, finite
    /// weights; the message names the field.
    pub fn validate(&self) -> Result<(), String> {
        let grid = self.grid().map_err(|e| format!("config.level: {e}"))?;
        if self.cells.is_empty() {
            return Err("cells: empty".into());
        }
        if self.cells.len() != self.log_weights.len() {
            return Err(format!(
                "log_weights: {} values for {} cells",
                self.log_weights.len(),
                self.cells.len()
            ));
        }
        if let Some(i) = self.cells.iter().position(|&c| c as usize >= grid.len()) {
            return Err(format!("cells[{i}]: not a cell of level {}", grid.level()));
        }
        if let Some(i) = self.log_weights.iter().position(|w| !w.is_finite()) {
            return Err(format!("log_weights[{i}]: not finite"));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tables_written_before_compact_polar_cells_keep_their_centres() {
        // A format-2 `modes.json` has no `grid` field: its cells are read in the old convention.
        let cells = [0u64, 5, 3000, 20_000];
        let old = serde_json::json!({
            "config": ModeTableConfig::default(),
            "cells": cells,
            "log_weights": [0.0, -0.1, -0.2, -0.3],
        });
        let table: ModeTable = serde_json::from_value(old).unwrap();
        assert_eq!(table.grid, GridConvention::IpdfZyz);
        let grid = table.grid().unwrap();
        for (c, centre) in cells.iter().zip(table.centres().unwrap()) {
            assert_eq!(centre, grid.legacy_rotation(*c));
        }
        // Cell 0 lies in a north polar base pixel, where the conventions differ.
        assert!(crate::so3::geodesic_angle(&grid.legacy_rotation(0), &grid.rotation(0)) > 1e-3);
        // A table written now says so, and reads back in the current convention.
        let now = ModeTable {
            grid: GridConvention::CompactPoles,
            ..table
        };
        let back: ModeTable = serde_json::from_str(&serde_json::to_string(&now).unwrap()).unwrap();
        assert_eq!(back.grid, GridConvention::CompactPoles);
        assert_eq!(back.centres().unwrap()[0], grid.rotation(0));
    }
}
