//! The K rotations each training image is scored on (DESIGN.md §2, "Sampling").
//!
//! Mode-focused (the paper's): `focused` rotations `R_gt·Q`, with `Q` jittered uniformly inside a
//! cell drawn from the object's [`ModeTable`] (the relative rotations where the experts' targets
//! have mass, with their shoulders; uniformly over the table's cells by default, or tempered by
//! their weights), the rest Haar-uniform, the ground truth first. Uniform (IPDF's, and the
//! "random sampling" ablation): the ground truth, then K − 1 Haar-uniform rotations.
//!
//! Why uniform over the table rather than ∝ the targets: the targets are bells a few degrees wide,
//! and samples drawn ∝ a bell land on its peak and teach nothing about its shoulders.

use nalgebra::Rotation3;
use rand::{Rng, RngExt};
use serde::{Deserialize, Serialize};

use crate::experts::modes::ModeTable;
use crate::so3::{GridLevel, So3Error, haar_rotation, jitter_in_cell};

/// How the K rotations of an image are drawn.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum SamplingStrategy {
    /// `focused` rotations from the object's mode table, the rest uniform, the GT first.
    ModeFocused {
        /// How many of the K are drawn near the modes (paper: 3000 of 4096).
        focused: usize,
        /// Cells are drawn ∝ `exp(temperature · log_weight)`: 0 = uniformly over the table.
        #[serde(default)]
        temperature: f64,
    },
    /// The GT, then uniform rotations.
    Uniform,
}

impl SamplingStrategy {
    /// The paper's mix at a given K: three quarters from the mode table, drawn uniformly.
    pub fn mode_focused(k: usize) -> Self {
        SamplingStrategy::ModeFocused {
            focused: k * 3 / 4,
            temperature: 0.0,
        }
    }
}

/// Draws cells of an object's [`ModeTable`].
#[derive(Debug, Clone)]
pub struct ModeSampler {
    grid: GridLevel,
    cells: Vec<u64>,
    /// Cumulative weights (empty when uniform).
    cumulative: Vec<f64>,
}

impl ModeSampler {
    /// A sampler over `table` at `temperature` (0 = uniform over its cells).
    pub fn new(table: &ModeTable, temperature: f64) -> Result<Self, So3Error> {
        let grid = table.grid()?;
        let cumulative = if temperature == 0.0 {
            Vec::new()
        } else {
            let max = table
                .log_weights
                .iter()
                .cloned()
                .fold(f32::NEG_INFINITY, f32::max);
            let mut total = 0.0;
            table
                .log_weights
                .iter()
                .map(|&w| {
                    total += (temperature * (w - max) as f64).exp();
                    total
                })
                .collect()
        };
        Ok(Self {
            grid,
            cells: table.cells.clone(),
            cumulative,
        })
    }

    /// One relative rotation `Q`, uniform inside a drawn cell.
    pub fn draw<R: Rng + ?Sized>(&self, rng: &mut R) -> Rotation3<f64> {
        let i = match self.cumulative.last() {
            Some(&total) if total > 0.0 => {
                let u = rng.random_range(0.0..total);
                self.cumulative
                    .partition_point(|&c| c <= u)
                    .min(self.cells.len() - 1)
            }
            _ => rng.random_range(0..self.cells.len()),
        };
        jitter_in_cell(&self.grid, self.cells[i], rng)
    }
}

/// Draws the K rotations: index 0 is `r_gt`. `modes` (the object's [`ModeSampler`]) is needed by
/// [`SamplingStrategy::ModeFocused`]; without it every non-GT rotation is uniform.
pub fn sample_rotations<R: Rng + ?Sized>(
    strategy: &SamplingStrategy,
    k: usize,
    r_gt: &Rotation3<f64>,
    modes: Option<&ModeSampler>,
    rng: &mut R,
) -> Vec<Rotation3<f64>> {
    let mut out = Vec::with_capacity(k);
    out.push(*r_gt);
    if let (SamplingStrategy::ModeFocused { focused, .. }, Some(modes)) = (strategy, modes)
        && !modes.cells.is_empty()
    {
        for _ in 0..(*focused).min(k.saturating_sub(1)) {
            out.push(r_gt * modes.draw(rng));
        }
    }
    while out.len() < k {
        out.push(haar_rotation(rng));
    }
    out
}
