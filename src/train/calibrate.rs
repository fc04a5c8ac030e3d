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

/// One image's two branch log-weights on the grid and the cells of its equivalent ground truths.
struct Scored {
    shape: Vec<f32>,
    feature: Vec<f32>,
    truth_cells: Vec<usize>,
}

/// The moments of one image's LL at branch scales `(β_θ, β_φ)`: the LL, its gradient and its
/// Hessian in the two scales.
struct LlMoments {
    ll: f64,
    gradient: [f64; 2],
    hessian: [[f64; 2]; 2],
}

impl Scored {
    /// Its LL at scale `beta` on the combined log-density (uniform = 0).
    fn ll(&self, beta: f64) -> f64 {
        self.moments([beta, beta]).ll
    }

    /// Its LL at scales `beta = (β_θ, β_φ)` on the two branches, `β_θ·s_θ + β_φ·s_φ` (uniform =
    /// 0), with its gradient and Hessian: the truths' mean of `(s_θ, s_φ)` less its mean under the
    /// density, and minus its covariance under the density (so the LL is concave in the scales).
    fn moments(&self, beta: [f64; 2]) -> LlMoments {
        let logit = |i: usize| beta[0] * self.shape[i] as f64 + beta[1] * self.feature[i] as f64;
        let n = self.shape.len();
        let max = (0..n).map(logit).fold(f64::NEG_INFINITY, f64::max);
        let (mut sum, mut mean, mut second) = (0.0, [0.0; 2], [[0.0; 2]; 2]);
        for i in 0..n {
            let w = (logit(i) - max).exp();
            let x = [self.shape[i] as f64, self.feature[i] as f64];
            sum += w;
            for a in 0..2 {
                mean[a] += w * x[a];
                for b in 0..2 {
                    second[a][b] += w * x[a] * x[b];
                }
            }
        }
        let mean = mean.map(|m| m / sum);
        let truths = self.truth_cells.len() as f64;
        let truth = self.truth_cells.iter().fold([0.0; 2], |t, &c| {
            [
                t[0] + self.shape[c] as f64 / truths,
                t[1] + self.feature[c] as f64 / truths,
            ]
        });
        let hessian = std::array::from_fn(|a| {
            std::array::from_fn(|b| mean[a] * mean[b] - second[a][b] / sum)
        });
        LlMoments {
            ll: beta[0] * truth[0] + beta[1] * truth[1] - max - sum.ln() + (n as f64).ln(),
            gradient: [truth[0] - mean[0], truth[1] - mean[1]],
            hessian,
        }
    }
}

fn mean_ll(scored: &[Scored], beta: f64) -> f64 {
    scored.iter().map(|s| s.ll(beta)).sum::<f64>() / scored.len().max(1) as f64
}

/// The mean of [`Scored::moments`] over the images.
fn mean_moments(scored: &[Scored], beta: [f64; 2]) -> LlMoments {
    let mut mean = LlMoments {
        ll: 0.0,
        gradient: [0.0; 2],
        hessian: [[0.0; 2]; 2],
    };
    let n = scored.len().max(1) as f64;
    for m in scored.iter().map(|s| s.moments(beta)) {
        mean.ll += m.ll / n;
        for a in 0..2 {
            mean.gradient[a] += m.gradient[a] / n;
            for b in 0..2 {
                mean.hessian[a][b] += m.hessian[a][b] / n;
            }
        }
    }
    mean
}

/// The two branch log-weights of every image on grid `level`, with its truths' cells.
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
                shape: s,
                feature: f,
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

/// The scale in [`SCALE_RANGE`] that maximises the mean LL of `images` at `level`; with
/// `per_branch`, the scales `(β_θ, β_φ)`, each in that range, that maximise it when each branch's
/// log-weight is multiplied by its own (a product of experts, each at its own temperature), and
/// `scale` in the fit is then the best single scale, for comparison. `crops` and `command` say
/// what the crops were and what ran, for the record.
pub fn fit_temperature(
    network: &Network,
    config: &NetworkConfig,
    images: &[EvalImage],
    level: u8,
    per_branch: bool,
    crops: String,
    command: String,
) -> Result<TemperatureFit, So3Error> {
    let scored = score(network, config, images, level)?;
    let scale = best_scale(&scored);
    let mut fit = TemperatureFit {
        scale,
        branch_scales: per_branch.then(|| best_branch_scales(&scored, scale)),
        ll_before: mean_ll(&scored, 1.0),
        ll_after: 0.0,
        images: images.len(),
        level,
        crops,
        command,
    };
    fit.ll_after = mean_moments(&scored, fit.applied()).ll;
    Ok(fit)
}

/// Damped Newton ascent of the concave mean LL over `(β_θ, β_φ)` in the box [`SCALE_RANGE`]²,
/// from the best single scale `start` (each step backtracked until the LL rises and clamped to
/// the box; the gradient's direction where Newton's does not rise).
fn best_branch_scales(scored: &[Scored], start: f64) -> [f64; 2] {
    let clamp = |b: [f64; 2]| b.map(|v| v.clamp(SCALE_RANGE.0, SCALE_RANGE.1));
    let mut beta = clamp([start, start]);
    let mut at = mean_moments(scored, beta);
    for _ in 0..100 {
        let [[a, b], [c, d]] = at.hessian;
        let det = a * d - b * c;
        let g = at.gradient;
        let newton =
            (det > 1e-12).then(|| [-(d * g[0] - b * g[1]) / det, -(a * g[1] - c * g[0]) / det]);
        let curvature = (-a).max(-d).max(1e-6);
        let ascent = [g[0] / curvature, g[1] / curvature];
        let step = newton.into_iter().chain([ascent]).find_map(|dir| {
            (0..40).find_map(|halvings| {
                let t = 0.5f64.powi(halvings);
                let next = clamp([beta[0] + t * dir[0], beta[1] + t * dir[1]]);
                let moments = mean_moments(scored, next);
                (moments.ll > at.ll).then_some((next, moments))
            })
        });
        match step {
            Some((next, moments)) if moments.ll - at.ll > 1e-10 => (beta, at) = (next, moments),
            Some((next, _)) => return next,
            None => break,
        }
    }
    beta
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
            shape: vec![4.0, 0.0, 0.0, 0.0],
            feature: vec![0.0; 4],
            truth_cells: vec![0],
        };
        let wrong = Scored {
            shape: vec![4.0, 0.0, 0.0, 0.0],
            feature: vec![0.0; 4],
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

    /// A shape branch that points at the truth and a feature branch that points elsewhere half
    /// the time: the branch scales found match a brute-force search of the box, the shape branch
    /// is made sharper and the feature branch wider, and the LL beats the best single scale.
    #[test]
    fn the_branch_scales_that_maximise_the_mean_ll_are_found() {
        let image = |truth: usize, feature_at: usize| {
            let mut feature = vec![0.0; 6];
            feature[feature_at] = 3.0;
            Scored {
                shape: vec![2.0, 2.0, 0.0, 0.0, 0.0, 0.0],
                feature,
                truth_cells: vec![truth],
            }
        };
        let scored = [
            image(0, 0),
            image(0, 1),
            image(1, 1),
            image(1, 0),
            image(0, 2),
        ];
        let ll = |b: [f64; 2]| mean_moments(&scored, b).ll;
        let steps = 400;
        let at = |i: usize| {
            (SCALE_RANGE.0.ln() + (SCALE_RANGE.1 / SCALE_RANGE.0).ln() * i as f64 / steps as f64)
                .exp()
        };
        let brute = (0..=steps)
            .flat_map(|i| (0..=steps).map(move |j| [at(i), at(j)]))
            .max_by(|&x, &y| ll(x).total_cmp(&ll(y)))
            .unwrap();
        let single = best_scale(&scored);
        let found = best_branch_scales(&scored, single);
        assert!(
            ll(found) >= ll(brute) - 1e-6,
            "Newton {found:?} (LL {}), brute force {brute:?} (LL {})",
            ll(found),
            ll(brute)
        );
        assert!(
            found[0] > single && found[1] < single,
            "{found:?} against {single}"
        );
        assert!(ll(found) > mean_ll(&scored, single) + 1e-3);
        // The moments' LL at equal scales is the single-scale LL, and its gradient is the LL's slope.
        let m = mean_moments(&scored, [0.7, 1.3]);
        let h = 1e-6;
        let slope = (ll([0.7 + h, 1.3]) - ll([0.7 - h, 1.3])) / (2.0 * h);
        assert!(
            (m.gradient[0] - slope).abs() < 1e-6,
            "{} against {slope}",
            m.gradient[0]
        );
        assert!((mean_moments(&scored, [0.9, 0.9]).ll - mean_ll(&scored, 0.9)).abs() < 1e-12);
    }
}
