//! Top-k by coarse-to-fine search (SpyroPose) and the grouping of the top cells into modes.
//!
//! A level is scored, the best `keep` cells are kept, their children are scored at the next
//! level, and so on. A child's probability is its softmax among the expanded cells times the
//! mass the kept parents held (SpyroPose's estimate); `covered_mass` is the product of the kept
//! fractions, i.e. the share of the distribution the finest cells are believed to hold.

pub use crate::so3::modes::Mode;
use crate::so3::{GridLevel, modes};

/// One scored cell.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CellProbability {
    /// Grid level.
    pub level: u8,
    /// Cell index at that level.
    pub cell: u64,
    /// Probability mass of the cell.
    pub probability: f64,
    /// Log-density at the cell (per unit of the π²-normalised Haar measure).
    pub log_density: f64,
}

/// What a search found at its finest level, most probable first.
#[derive(Debug, Clone, PartialEq)]
pub struct SearchResult {
    /// Every expanded cell of the finest level, most probable first.
    pub cells: Vec<CellProbability>,
    /// The estimated mass the finest cells cover.
    pub covered_mass: f64,
}

/// Numerically stable `log Σ exp`.
pub fn log_sum_exp(v: &[f32]) -> f64 {
    let max = v.iter().copied().fold(f32::NEG_INFINITY, f32::max) as f64;
    if !max.is_finite() {
        return max;
    }
    max + v.iter().map(|&x| (x as f64 - max).exp()).sum::<f64>().ln()
}

/// Indices of the `keep` largest values, largest first (ties by index).
pub fn top_indices(values: &[f64], keep: usize) -> Vec<usize> {
    let mut order: Vec<usize> = (0..values.len()).collect();
    let cmp = |&a: &usize, &b: &usize| values[b].total_cmp(&values[a]).then(a.cmp(&b));
    if keep > 0 && order.len() > keep {
        order.select_nth_unstable_by(keep - 1, cmp);
        order.truncate(keep);
    }
    order.sort_by(cmp);
    order
}

/// Which cells a coarse-to-fine search refines at each level.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Keep {
    /// Most cells kept.
    pub max: usize,
    /// Fewest cells kept.
    pub min: usize,
    /// With `Some(f)`, only the most probable cells that hold the fraction `f` of the level's
    /// estimated mass (between `min` and `max` of them); with `None`, always `max`.
    pub mass: Option<f64>,
    /// Each refinement keeps `taper` times as many cells as the one before (1: `max` at every
    /// level; 0.5: `max`, then `max/2`, …, never fewer than `min`).
    pub taper: f64,
}

impl Keep {
    /// The most cells kept at the `refinement`-th refinement (0: the start level's):
    /// `max · taper^refinement`, rounded, at least `min`.
    pub fn max_at(&self, refinement: usize) -> usize {
        let scaled = self.max as f64 * self.taper.powi(refinement.min(64) as i32);
        (scaled.round() as usize).max(self.min)
    }

    /// Indices of the cells to refine at the `refinement`-th refinement, most probable first, of
    /// a level whose cells hold `probs` (summing to `covered`).
    pub fn cells(&self, probs: &[f64], covered: f64, refinement: usize) -> Vec<usize> {
        let mut kept = top_indices(probs, self.max_at(refinement));
        if let Some(fraction) = self.mass {
            let goal = fraction * covered;
            let mut sum = 0.0;
            let needed = kept
                .iter()
                .position(|&j| {
                    sum += probs[j];
                    sum >= goal
                })
                .map_or(kept.len(), |i| i + 1);
            kept.truncate(needed.max(self.min));
        }
        kept
    }
}

/// Coarse-to-fine search, `n` of them in lockstep (`grids` are consecutive levels, coarse first),
/// so that each level's scoring is one call for all of
/// them (a batch across requests): `score(grid, cells)` gets every search's cells of that level
/// (the same number for each) and returns their log-weights in the same order, or an error that
/// ends the search at that level (a cancelled call).
pub fn coarse_to_fine_many<E>(
    grids: &[&GridLevel],
    keep: Keep,
    n: usize,
    mut score: impl FnMut(&GridLevel, &[Vec<u64>]) -> Result<Vec<Vec<f32>>, E>,
) -> Result<Vec<SearchResult>, E> {
    let first = grids[0];
    let mut cells: Vec<Vec<u64>> = vec![(0..first.len() as u64).collect(); n];
    let mut covered = vec![1.0f64; n];
    let mut probs: Vec<Vec<f64>> = vec![Vec::new(); n];
    for (i, grid) in grids.iter().enumerate() {
        if i > 0 {
            let parent = grids[i - 1];
            for s in 0..n {
                let kept = keep.cells(&probs[s], covered[s], i - 1);
                // `probs` already carry the mass kept so far: the kept ones' sum is the new cover.
                covered[s] = kept.iter().map(|&j| probs[s][j]).sum::<f64>();
                cells[s] = kept
                    .iter()
                    .flat_map(|&j| parent.children(cells[s][j]))
                    .collect();
            }
        }
        let logits = score(grid, &cells)?;
        for s in 0..n {
            let lse = log_sum_exp(&logits[s]);
            probs[s] = logits[s]
                .iter()
                .map(|&l| covered[s] * (l as f64 - lse).exp())
                .collect();
        }
    }
    let grid = grids[grids.len() - 1];
    let log_cell_volume = grid.cell_volume().ln();
    Ok((0..n)
        .map(|s| {
            let order = top_indices(&probs[s], probs[s].len());
            SearchResult {
                cells: order
                    .into_iter()
                    .map(|j| CellProbability {
                        level: grid.level(),
                        cell: cells[s][j],
                        probability: probs[s][j],
                        log_density: probs[s][j].ln() - log_cell_volume,
                    })
                    .collect(),
                covered_mass: covered[s],
            }
        })
        .collect())
}

/// Groups the search's cells (most probable first) into modes: [`so3::modes::group_modes`] on
/// their cells and masses.
pub fn group_modes(
    grid: &GridLevel,
    cells: &[CellProbability],
    angle_rad: f64,
    mass_fraction: f64,
    min_mass: f64,
) -> Vec<Mode> {
    let cells: Vec<(u64, f64)> = cells.iter().map(|c| (c.cell, c.probability)).collect();
    modes::group_modes(grid, &cells, angle_rad, mass_fraction, min_mass)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A halving keep refines `keep`, `keep/2`, … cells (never fewer than `min`), a flat one
    /// `keep` at every level: counted from the cells the search asks to score.
    #[test]
    fn a_tapered_keep_refines_fewer_cells_at_each_finer_level() {
        let grids: Vec<GridLevel> = (1..=4).map(|l| GridLevel::new(l).unwrap()).collect();
        let grids: Vec<&GridLevel> = grids.iter().collect();
        let scored = |taper: f64, min: usize| {
            let keep = Keep {
                max: 64,
                min,
                mass: None,
                taper,
            };
            let mut counts = Vec::new();
            let results = coarse_to_fine_many(&grids, keep, 2, |grid, cells| {
                counts.push(cells[0].len());
                // A smooth, image-free score: the cosine of the rotation angle.
                Ok::<_, std::convert::Infallible>(
                    cells
                        .iter()
                        .map(|cells| {
                            cells
                                .iter()
                                .map(|&c| grid.rotation(c).angle().cos() as f32)
                                .collect()
                        })
                        .collect(),
                )
            })
            .unwrap();
            assert_eq!(results.len(), 2);
            counts
        };
        assert_eq!(scored(1.0, 1), vec![576, 8 * 64, 8 * 64, 8 * 64]);
        assert_eq!(scored(0.5, 1), vec![576, 8 * 64, 8 * 32, 8 * 16]);
        assert_eq!(scored(0.5, 24), vec![576, 8 * 64, 8 * 32, 8 * 24]);
        assert_eq!(scored(2.0, 1), vec![576, 8 * 64, 8 * 128, 8 * 256]);
    }
}
