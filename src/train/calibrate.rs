//! Temperature calibration of a trained network: a distribution that does not know must be wide,
//! not sharp and wrong. The combined log-density `s_θ + s_φ` is multiplied by one factor
//! `β = 1/T`, chosen to maximise the LL (docs/DESIGN.md §2, "Metrics") on calibration crops drawn
//! from the **training** distribution (never from a held-out split), and folded into both
//! branches' output layers ([`crate::net::DualHead::with_output_scale`]), so the engine, the
//! evaluation and the server all serve the calibrated model unchanged.
//!
//! The LL of one image at scale β is `mean_j β·s(c_j) − logsumexp_i β·s_i + log N` over the
//! cells `c_j` of its equivalent ground truths: `β` times a linear term minus a log-sum-exp,
//! which is convex in β. So the mean LL is concave in β and a golden-section search finds its
//! maximum.

use burn::tensor::Tensor;

pub use crate::bundle::record::TemperatureFit;

use super::eval::EvalImage;
use crate::net::{Network, NetworkConfig, ProjectedGrid, images_tensor};
use crate::so3::So3Error;

/// The scales searched: temperatures from 1/4 to 8.
pub const SCALE_RANGE: (f64, f64) = (0.125, 4.0);

/// One image's combined log-density on the grid and the cells of its equivalent ground truths.
struct Scored {
    logits: Vec<f32>,
    truth_cells: Vec<usize>,
}

impl Scored {
    /// Its LL at scale `beta` (uniform = 0).
    fn ll(&self, beta: f64) -> f64 {
        let max = self.logits.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v)) as f64;
        let sum: f64 = self
            .logits
            .iter()
            .map(|&v| (beta * (v as f64 - max)).exp())
            .sum();
        let log_z = beta * max + sum.ln();
        let n = self.logits.len() as f64;
        let truth: f64 = self
            .truth_cells
            .iter()
            .map(|&c| beta * self.logits[c] as f64)
            .sum::<f64>()
            / self.truth_cells.len() as f64;
        truth - log_z + n.ln()
    }
}

fn mean_ll(scored: &[Scored], beta: f64) -> f64 {
    scored.iter().map(|s| s.ll(beta)).sum::<f64>() / scored.len().max(1) as f64
}

/// The combined log-density of every image on grid `level`, with its truths' cells.
fn score(
    network: &Network,
    config: &NetworkConfig,
    images: &[EvalImage],
    level: u8,
) -> Result<Vec<Scored>, So3Error> {
    let device = crate::backend::device_for(crate::backend::Workload::Conv);
    let projected = ProjectedGrid::new(network, config, level)?;
    let mut scored = Vec::with_capacity(images.len());
    for batch in images.chunks(4) {
        let crops: Vec<&[u8]> = batch.iter().map(|i| i.rgb.as_slice()).collect();
        let tensor: Tensor<4> = images_tensor(&crops, config.image_size as usize, &device);
        let features = network.encoder.forward(tensor);
        for (image, (s, f)) in batch
            .iter()
            .zip(projected.branch_log_weights_of_features(features))
        {
            if image.equivalents.is_empty() {
                return Err(So3Error::NoGroundTruth);
            }
            scored.push(Scored {
                logits: s.iter().zip(&f).map(|(a, b)| a + b).collect(),
                truth_cells: image
                    .equivalents
                    .iter()
                    .map(|g| projected.grid.cell_of(g) as usize)
                    .collect(),
            });
        }
    }
    Ok(scored)
}

/// The scale in [`SCALE_RANGE`] that maximises the mean LL of `images` at `level` (`crops` and
/// `command` say what they were and what ran, for the record).
pub fn fit_temperature(
    network: &Network,
    config: &NetworkConfig,
    images: &[EvalImage],
    level: u8,
    crops: String,
    command: String,
) -> Result<TemperatureFit, So3Error> {
    let scored = score(network, config, images, level)?;
    let scale = best_scale(&scored);
    Ok(TemperatureFit {
        scale,
        ll_before: mean_ll(&scored, 1.0),
        ll_after: mean_ll(&scored, scale),
        images: images.len(),
        level,
        crops,
        command,
    })
}

/// Golden-section search of the concave mean LL over log β in [`SCALE_RANGE`].
fn best_scale(scored: &[Scored]) -> f64 {
    let (mut lo, mut hi) = (SCALE_RANGE.0.ln(), SCALE_RANGE.1.ln());
    let ratio = (5f64.sqrt() - 1.0) / 2.0;
    let ll = |log_beta: f64| mean_ll(scored, log_beta.exp());
    let (mut a, mut b) = (hi - ratio * (hi - lo), lo + ratio * (hi - lo));
    let (mut fa, mut fb) = (ll(a), ll(b));
    while hi - lo > 1e-4 {
        if fa > fb {
            hi = b;
            (b, fb) = (a, fa);
            a = hi - ratio * (hi - lo);
            fa = ll(a);
        } else {
            lo = a;
            (a, fa) = (b, fb);
            b = lo + ratio * (hi - lo);
            fb = ll(b);
        }
    }
    ((lo + hi) / 2.0).exp()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two cells out of four: a sharp answer on the wrong cell half the time is best made wider.
    #[test]
    fn the_scale_that_maximises_the_mean_ll_is_found() {
        let right = Scored {
            logits: vec![4.0, 0.0, 0.0, 0.0],
            truth_cells: vec![0],
        };
        let wrong = Scored {
            logits: vec![4.0, 0.0, 0.0, 0.0],
            truth_cells: vec![1],
        };
        let scored = [right, wrong];
        // Brute force on a fine grid of β against the golden-section search.
        let brute = (125..4000)
            .map(|i| i as f64 * 1e-3)
            .max_by(|&x, &y| mean_ll(&scored, x).total_cmp(&mean_ll(&scored, y)))
            .unwrap();
        let found = best_scale(&scored);
        assert!(
            brute < 0.9,
            "a half-wrong sharp answer should be widened: {brute}"
        );
        assert!(
            (found - brute).abs() < 2e-3,
            "golden section {found}, brute force {brute}"
        );
        // A right answer alone is made sharper, up to the range's end.
        let sharp = best_scale(&scored[..1]);
        assert!((sharp - SCALE_RANGE.1).abs() < 1e-2, "{sharp}");
        // The LL at β = 1 matches the definition: log(p·N).
        let p = 4f64.exp() / (4f64.exp() + 3.0);
        assert!((scored[0].ll(1.0) - (p * 4.0).ln()).abs() < 1e-12);
    }
}
