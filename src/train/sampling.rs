//! The K rotations each training image is scored on (DESIGN.md §2, "Sampling").
//!
//! Mode-focused (the paper's): the experts' combined measure `a^SDF·a^SE` of this image is
//! searched coarse-to-fine — every cell of a coarse level, then the children of the best `keep`
//! cells, level by level down to a fine one ([`ModeSearch::expert_modes`]); `focused` fine cells are drawn with
//! probability ∝ their measure and a rotation is jittered uniformly inside each; the rest are
//! Haar-uniform; the ground truth comes first. Uniform (IPDF's, and the "random sampling"
//! ablation): the ground truth, then K − 1 Haar-uniform rotations.
//!
//! Why fine cells: the experts' targets are sharp (λ chosen by LL at level 3). Jittered inside
//! coarse level-2 cells (~7°), almost no focused sample lands where the target has mass, so the
//! network would be told that the neighbourhoods of the modes are empty; at level 4 (~2°) most do.

use nalgebra::Rotation3;
use rand::{Rng, RngExt};
use serde::{Deserialize, Serialize};

use crate::so3::{GridLevel, So3Error, haar_rotation, jitter_in_cell, to_row_major_f32};

/// How the K rotations of an image are drawn.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum SamplingStrategy {
    /// `focused` rotations near the experts' modes, the rest uniform, the GT first.
    ModeFocused {
        /// How many of the K are drawn near the modes (paper: 3000 of 4096).
        focused: usize,
        /// Level scored in full at the start of the mode search.
        level: u8,
        /// Level of the cells the focused rotations are jittered in.
        fine_level: u8,
        /// Cells kept per level of the search.
        keep: usize,
    },
    /// The GT, then uniform rotations.
    Uniform,
}

impl SamplingStrategy {
    /// The paper's mix at a given K: three quarters near the modes, searched from level 2 down to
    /// level 4 keeping 512 cells per level (enough for the 360 modes of a cone at ~4° apart).
    pub fn mode_focused(k: usize) -> Self {
        SamplingStrategy::ModeFocused {
            focused: k * 3 / 4,
            level: 2,
            fine_level: 4,
            keep: 512,
        }
    }
}

/// The experts' modes of one image: the best cells of the fine level and their combined
/// log-measure `log a^SDF + log a^SE`.
#[derive(Debug, Clone, PartialEq)]
pub struct ExpertModes {
    /// Cell indices at the fine level.
    pub cells: Vec<u64>,
    /// Their log-measures.
    pub log_weights: Vec<f32>,
}

/// The grids a mode search walks, coarse to fine.
#[derive(Debug, Clone)]
pub struct ModeSearch {
    grids: Vec<GridLevel>,
    coarse_cells: Vec<[f32; 9]>,
    keep: usize,
}

impl ModeSearch {
    /// Grids `level ..= fine_level`; `keep` cells survive each level.
    pub fn new(level: u8, fine_level: u8, keep: usize) -> Result<Self, So3Error> {
        let grids = (level..=fine_level.max(level))
            .map(GridLevel::new)
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self {
            coarse_cells: grids[0].matrices_f32(),
            grids,
            keep: keep.max(1),
        })
    }

    /// The fine grid the modes' cells belong to.
    pub fn fine_grid(&self) -> &GridLevel {
        self.grids.last().expect("at least one level")
    }

    /// Coarse-to-fine search of the measure `log_measure` (log-weights of a batch of row-major
    /// rotations): the coarse level in full, then the children of the best `keep` cells of each
    /// level. Returns the best `keep` cells of the fine level.
    pub fn expert_modes(
        &self,
        mut log_measure: impl FnMut(&[[f32; 9]]) -> Vec<f32>,
    ) -> ExpertModes {
        let mut cells: Vec<u64> = (0..self.grids[0].len() as u64).collect();
        let mut weights = log_measure(&self.coarse_cells);
        for (parent, grid) in self.grids.iter().zip(&self.grids[1..]) {
            let best = top_cells(&cells, &weights, self.keep);
            cells = best
                .iter()
                .flat_map(|&i| parent.children(cells[i]))
                .collect();
            let mats: Vec<[f32; 9]> = cells
                .iter()
                .map(|&c| to_row_major_f32(&grid.rotation(c)))
                .collect();
            weights = log_measure(&mats);
        }
        let best = top_cells(&cells, &weights, self.keep);
        ExpertModes {
            cells: best.iter().map(|&i| cells[i]).collect(),
            log_weights: best.iter().map(|&i| weights[i]).collect(),
        }
    }
}

/// Positions of the `keep` cells with the largest weights (ties broken by cell index, so the
/// result is deterministic), in decreasing weight.
fn top_cells(cells: &[u64], weights: &[f32], keep: usize) -> Vec<usize> {
    let mut order: Vec<usize> = (0..cells.len()).collect();
    let by_weight = |&a: &usize, &b: &usize| {
        weights[b]
            .total_cmp(&weights[a])
            .then(cells[a].cmp(&cells[b]))
    };
    if order.len() > keep {
        order.select_nth_unstable_by(keep - 1, by_weight);
        order.truncate(keep);
    }
    order.sort_by(by_weight);
    order
}

/// Draws the K rotations: index 0 is `r_gt`. `modes` (the fine grid and this image's
/// [`ExpertModes`]) are needed by [`SamplingStrategy::ModeFocused`]; without them every
/// non-GT rotation is uniform.
pub fn sample_rotations<R: Rng + ?Sized>(
    strategy: &SamplingStrategy,
    k: usize,
    r_gt: &Rotation3<f64>,
    modes: Option<(&GridLevel, &ExpertModes)>,
    rng: &mut R,
) -> Vec<Rotation3<f64>> {
    let mut out = Vec::with_capacity(k);
    out.push(*r_gt);
    if let (SamplingStrategy::ModeFocused { focused, .. }, Some((grid, modes))) = (strategy, modes)
        && !modes.cells.is_empty()
    {
        let log_w = &modes.log_weights;
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
            let i = cumulative.partition_point(|&c| c <= u).min(log_w.len() - 1);
            out.push(jitter_in_cell(grid, modes.cells[i], rng));
        }
    }
    while out.len() < k {
        out.push(haar_rotation(rng));
    }
    out
}
