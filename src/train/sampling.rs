//! The K rotations each training image is scored on (docs/DESIGN.md §2, "Sampling").
//!
//! Mode-focused (the paper's): `focused` rotations `R_gt·Q`, with `Q` jittered uniformly in a
//! small ball around the centre of a cell drawn from the object's [`ModeTable`] (the relative rotations where the experts' targets
//! have mass, with their shoulders; uniformly over the table's cells by default, or tempered by
//! their weights), the rest Haar-uniform, the ground truth first. Uniform (IPDF's, and the
//! "random sampling" ablation): the ground truth, then K − 1 Haar-uniform rotations.
//!
//! Twin sampling (ours, an experiment of `alignist-train new --twin-share`): a share of the
//! focused rotations is drawn around `R_gt·S·Q` instead, `S` a turn of the part's
//! near-symmetry: poses the image nearly cannot tell from the truth, where the target is low and
//! the network was measured to grow a second mode (docs/RESULTS.md, the drill's half-turn twins).
//!
//! Why uniform over the table rather than ∝ the targets: the targets are bells a few degrees wide,
//! and samples drawn ∝ a bell land on its peak and teach nothing about its shoulders.

use nalgebra::Rotation3;
use rand::{Rng, RngExt};

pub use crate::bundle::record::{OwnTwins, PAPER_FOCUSED_SHARE, SamplingStrategy};
use crate::experts::modes::ModeTable;
use crate::so3::{So3Error, haar_rotation, random_axis};

/// Draws cells of an object's [`ModeTable`].
#[derive(Debug, Clone)]
pub struct ModeSampler {
    /// Cells of the table's level (for the jitter radius).
    level_cells: usize,
    /// The centres of the table's cells.
    centres: Vec<Rotation3<f64>>,
    /// Cumulative weights (empty when uniform).
    cumulative: Vec<f64>,
    /// The twins of the object's near-symmetry ([`ModeSampler::with_twins`]).
    twins: Vec<Rotation3<f64>>,
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
            level_cells: grid.len(),
            centres: table.centres()?,
            cumulative,
            twins: Vec::new(),
        })
    }

    /// The sampler with the twins of the object's near-symmetry (relative rotations `S`): a
    /// strategy's twin share of the focused rotations is drawn around `R_gt·S` instead.
    pub fn with_twins(mut self, twins: Vec<Rotation3<f64>>) -> Self {
        self.twins = twins;
        self
    }

    /// The sampler with `more` twins besides its own (the network's own, [`OwnTwins`]).
    pub fn with_more_twins(mut self, more: &[Rotation3<f64>]) -> Self {
        self.twins.extend_from_slice(more);
        self
    }

    /// One relative rotation `Q`: a drawn cell's centre turned by a rotation drawn uniformly
    /// (Haar) from the ball of radius [`ModeSampler::radius`] around the identity.
    ///
    /// A ball rather than the cell itself: with the old grid's ~90° polar slivers, samples spread
    /// along them missed the modes there (measured on the cube: 2 of 2 000 samples within 8° of
    /// a polar equivalent against ~30 elsewhere), and a ball is the same shape everywhere.
    pub fn draw<R: Rng + ?Sized>(&self, rng: &mut R) -> Rotation3<f64> {
        let i = match self.cumulative.last() {
            Some(&total) if total > 0.0 => {
                let u = rng.random_range(0.0..total);
                self.cumulative
                    .partition_point(|&c| c <= u)
                    .min(self.centres.len() - 1)
            }
            _ => rng.random_range(0..self.centres.len()),
        };
        self.centres[i] * ball_rotation(self.radius(), rng)
    }

    /// Radius of the jitter: the edge of a cube of one cell's volume, `(π²/N)^⅓` (1.85° at
    /// level 4), so that the balls around neighbouring centres overlap.
    pub fn radius(&self) -> f64 {
        (std::f64::consts::PI.powi(2) / self.level_cells as f64).cbrt()
    }
}

/// A rotation drawn uniformly (Haar) from the ball of angle `radius` around the identity: a
/// uniform axis, and an angle with density ∝ `1 − cos θ` on `[0, radius]` (by rejection).
pub fn ball_rotation<R: Rng + ?Sized>(radius: f64, rng: &mut R) -> Rotation3<f64> {
    let axis = random_axis(rng);
    let peak = 1.0 - radius.cos();
    let angle = loop {
        let theta = rng.random_range(0.0..=radius);
        if rng.random_range(0.0..=peak) <= 1.0 - theta.cos() {
            break theta;
        }
    };
    Rotation3::from_axis_angle(&axis, angle)
}

/// The first of [`sample_rotations`]' columns drawn Haar-uniformly: after the ground truth and
/// the focused rotations (the contrast term's columns, [`crate::net::contrast_loss`]).
pub fn uniform_from(strategy: &SamplingStrategy, k: usize, modes: Option<&ModeSampler>) -> usize {
    let focused = match (strategy, modes) {
        (SamplingStrategy::ModeFocused { focused, .. }, Some(modes))
            if !modes.centres.is_empty() =>
        {
            (*focused).min(k.saturating_sub(1))
        }
        _ => 0,
    };
    1 + focused
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
    let focused = uniform_from(strategy, k, modes).saturating_sub(1);
    if let (SamplingStrategy::ModeFocused { twin_share, .. }, Some(modes)) = (strategy, modes) {
        let twins = if *twin_share > 0.0 {
            modes.twins.as_slice()
        } else {
            &[]
        };
        for _ in 0..focused {
            // No draw for the twin's coin without twins: a run without them keeps its stream.
            let twin = (!twins.is_empty() && rng.random::<f64>() < *twin_share)
                .then(|| twins[rng.random_range(0..twins.len())]);
            out.push(match twin {
                Some(s) => r_gt * s * modes.draw(rng),
                None => r_gt * modes.draw(rng),
            });
        }
    }
    while out.len() < k {
        out.push(haar_rotation(rng));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn ball_rotations_stay_inside_and_fill_the_ball() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let r = 2f64.to_radians();
        let angles: Vec<f64> = (0..20_000)
            .map(|_| ball_rotation(r, &mut rng).angle())
            .collect();
        assert!(angles.iter().all(|&a| a <= r + 1e-12));
        // Haar in a small ball: density ∝ θ², so the mean angle is ¾ of the radius.
        let mean = angles.iter().sum::<f64>() / angles.len() as f64;
        assert!((mean / r - 0.75).abs() < 0.01, "mean {mean} of radius {r}");
    }
}
