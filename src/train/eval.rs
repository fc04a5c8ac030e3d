//! Evaluation over a full grid level (docs/DESIGN.md §2 metrics): the network's combined log-density
//! `s_θ + s_φ` on every cell centre, then LL (all equivalents), spread, and the argmax's error.
//! The rotation half of the head's first layer is computed once per level and shared.

use std::time::Instant;

use nalgebra::Rotation3;

pub use crate::bundle::record::{EvalReport, ImageRecord, ServedReport, ServedSummary};
use crate::engine::{EngineError, Model, PredictOptions};
use crate::net::{Network, NetworkConfig, ProjectedGrid, images_tensor};
use crate::so3::metrics::{
    ImageMetrics, MetricsSummary, accuracy_and_median, chance_accuracy, error_to_nearest_deg,
    image_metrics, summarize,
};
use crate::so3::{So3Error, to_quaternion};

/// A test image: crop and every equivalent ground truth.
#[derive(Debug, Clone)]
pub struct EvalImage {
    /// Object name, for per-object tables.
    pub object: String,
    /// RGB8 crop.
    pub rgb: Vec<u8>,
    /// Every equivalent ground truth.
    pub equivalents: Vec<Rotation3<f64>>,
}

impl EvalImage {
    /// The crop `rgb` of object `object` at rotation `r_gt`, with its equivalents under the
    /// object's proper symmetries `group`.
    pub fn labelled(
        object: &str,
        rgb: Vec<u8>,
        r_gt: &Rotation3<f64>,
        group: &[Rotation3<f64>],
    ) -> Self {
        EvalImage {
            object: object.to_string(),
            rgb,
            equivalents: crate::so3::equivalents(r_gt, group),
        }
    }
}

/// The finest level evaluated or scored in full: level 5 already has 2 359 296 cells (level 6,
/// [`crate::so3::MAX_LEVEL`], eight times more, is only searched).
pub const MAX_EVAL_LEVEL: u8 = 5;

/// Evaluates `network` on `images` at grid `level`.
pub fn evaluate(
    network: &Network,
    config: &NetworkConfig,
    images: &[EvalImage],
    level: u8,
    mut progress: impl FnMut(usize),
) -> Result<EvalReport, So3Error> {
    let device = crate::backend::device_for(crate::backend::Workload::Conv);
    let started = Instant::now();
    let projected = ProjectedGrid::new(network, config, level)?;
    let centres = projected.grid.quaternions();
    let mut per_image: Vec<(String, ImageMetrics)> = Vec::with_capacity(images.len());
    let mut records = Vec::with_capacity(images.len());
    let (mut shape_only, mut feature_only) = (Vec::new(), Vec::new());
    let mut ceiling = 0.0;
    for (n, batch) in images.chunks(4).enumerate() {
        let crops: Vec<&[u8]> = batch.iter().map(|i| i.rgb.as_slice()).collect();
        let tensor = images_tensor(&crops, config.image_size as usize, &device);
        let features = network.encoder.forward(tensor);
        for (im, (s, f)) in batch
            .iter()
            .zip(projected.branch_log_weights_of_features(features))
        {
            let metrics = |w: &[f32]| image_metrics(&projected.grid, &centres, w, &im.equivalents);
            let combined: Vec<f32> = s.iter().zip(&f).map(|(a, b)| a + b).collect();
            let m = metrics(&combined)?;
            records.push(ImageRecord {
                object: im.object.clone(),
                truth: im
                    .equivalents
                    .first()
                    .map_or([1.0, 0.0, 0.0, 0.0], to_quaternion),
                log_likelihood: m.log_likelihood,
                argmax_error_deg: m.argmax_error_deg,
                mode_error_deg: m.mode_error_deg,
                argmax: Some(m.argmax),
            });
            per_image.push((im.object.clone(), m));
            shape_only.push(metrics(&s)?);
            feature_only.push(metrics(&f)?);
            ceiling += crate::so3::metrics::ll_ceiling(&projected.grid, &im.equivalents);
        }
        progress((n + 1) * 4);
    }
    let thresholds = THRESHOLDS_DEG;
    let mut objects: Vec<String> = per_image.iter().map(|(o, _)| o.clone()).collect();
    objects.sort();
    objects.dedup();
    let per_object: Vec<(String, MetricsSummary)> = objects
        .into_iter()
        .map(|o| {
            let m: Vec<ImageMetrics> = per_image
                .iter()
                .filter(|(p, _)| *p == o)
                .map(|(_, m)| *m)
                .collect();
            (o, summarize(&m, &thresholds))
        })
        .collect();
    let all: Vec<ImageMetrics> = per_image.iter().map(|(_, m)| *m).collect();
    let chance_ar30 = per_object
        .iter()
        .filter_map(|(name, _)| {
            let im = images.iter().find(|i| i.object == *name)?;
            // The equivalents are R_gt·S with the identity first: S_j = G_0ᵀ·G_j.
            let first = im.equivalents.first()?;
            let group: Vec<Rotation3<f64>> =
                im.equivalents.iter().map(|g| first.inverse() * g).collect();
            Some((name.clone(), chance_accuracy(&group, 30.0, 20_000, 0)))
        })
        .collect();
    Ok(EvalReport {
        level,
        ll_ceiling: ceiling / images.len().max(1) as f64,
        per_object,
        overall: summarize(&all, &thresholds),
        images_per_second: images.len() as f64 / started.elapsed().as_secs_f64(),
        per_branch: Some((
            summarize(&shape_only, &thresholds),
            summarize(&feature_only, &thresholds),
        )),
        chance_ar30,
        served: None,
        images: records,
    })
}

/// The thresholds `θ` of the `AR@θ` an evaluation reports.
const THRESHOLDS_DEG: [f64; 1] = [30.0];

/// Answers `images` as the server does (docs/DESIGN.md §2, "served"): each crop's features,
/// then one search of `model`'s default (its calibrated search to its default level) with
/// `top_k`, timed alone; the errors of the answer's top-1 rotation and of its first mode
/// against the nearest equivalent truth, per object and overall.
pub fn evaluate_served(
    model: &Model,
    images: &[EvalImage],
    top_k: usize,
    mut progress: impl FnMut(usize),
) -> Result<ServedReport, EngineError> {
    let options = PredictOptions {
        top_k,
        ..Default::default()
    };
    let checked = model.check_predict(&options)?;
    // Per image: (object, top-1 error, first mode's error), and each search's seconds.
    let mut rows: Vec<(&str, f64, f64)> = Vec::with_capacity(images.len());
    let mut seconds = Vec::with_capacity(images.len());
    for batch in images.chunks(4) {
        let crops: Vec<&[u8]> = batch.iter().map(|i| i.rgb.as_slice()).collect();
        for (im, features) in batch.iter().zip(model.features(&crops)?) {
            let started = Instant::now();
            let answer = model
                .predict_checked(&[features], &checked, &[None])?
                .swap_remove(0);
            seconds.push(started.elapsed().as_secs_f64());
            let error = |q: &[f64; 4]| -> Result<f64, EngineError> {
                let r = crate::so3::from_quaternion(*q)?;
                Ok(error_to_nearest_deg(&r, &im.equivalents))
            };
            let top1 = answer.rotations.first().map_or(Ok(f64::NAN), error)?;
            let mode = answer
                .modes
                .first()
                .map_or(Ok(f64::NAN), |m| error(&m.quaternion))?;
            rows.push((im.object.as_str(), top1, mode));
        }
        progress(rows.len());
    }
    let summary = |keep: &dyn Fn(&str) -> bool| {
        let picked: Vec<&(&str, f64, f64)> = rows.iter().filter(|r| keep(r.0)).collect();
        let top1: Vec<f64> = picked.iter().map(|r| r.1).collect();
        let mode: Vec<f64> = picked.iter().map(|r| r.2).collect();
        let (top1_accuracy_at, top1_median_error_deg) = accuracy_and_median(&top1, &THRESHOLDS_DEG);
        let (mode_accuracy_at, mode_median_error_deg) = accuracy_and_median(&mode, &THRESHOLDS_DEG);
        ServedSummary {
            images: picked.len(),
            top1_accuracy_at,
            top1_median_error_deg,
            mode_accuracy_at,
            mode_median_error_deg,
        }
    };
    let mut objects: Vec<&str> = rows.iter().map(|r| r.0).collect();
    objects.sort_unstable();
    objects.dedup();
    Ok(ServedReport {
        search: model.config().search().to_string(),
        calibrated: model.calibration().is_some(),
        level: checked.level(),
        top_k,
        per_object: objects
            .iter()
            .map(|o| (o.to_string(), summary(&|p| p == *o)))
            .collect(),
        overall: summary(&|_| true),
        search_p50_ms: crate::so3::metrics::quantile(&seconds, 0.5) * 1e3,
    })
}

/// Why two evaluations cannot be compared image by image.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PairingError {
    /// A report without per-image records (one written before them, or a manifest's summary).
    #[error("no per-image records (a report written before them, or a manifest's summary)")]
    NoRecords,
    /// Different numbers of images.
    #[error("{0} images against {1}: not the same crops")]
    Count(usize, usize),
    /// Image `index` is another object or another pose in the two.
    #[error("image {index} is {a} in one and {b} in the other: not the same crops")]
    Image {
        /// Position in the evaluation's order.
        index: usize,
        /// What the first report holds there.
        a: String,
        /// What the second holds.
        b: String,
    },
}

/// A hit rate (`error < θ`) of two evaluations of the same images, compared image by image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PairedHits {
    /// The rate in A and in B.
    pub rates: (f64, f64),
    /// Images right in A and not in B, and in B and not in A (the discordant pairs).
    pub only: (usize, usize),
    /// The standard error of the rates' difference `B − A`, paired.
    pub se: f64,
    /// McNemar's exact two-sided p-value: the chance of discordant pairs at least this uneven
    /// if A and B were equally good.
    pub p_value: f64,
}

/// Two evaluations of the same crops compared image by image, `B − A`: the paired differences
/// have a far smaller spread than two sets' figures side by side, so an ablation on 100 crops can
/// tell smaller effects apart.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PairedComparison {
    /// Images paired.
    pub images: usize,
    /// Mean LL in A and in B.
    pub ll: (f64, f64),
    /// The standard error of the mean LL difference, paired.
    pub ll_se: f64,
    /// AR@θ of the argmax.
    pub argmax: PairedHits,
    /// AR@θ of the first mode.
    pub mode: PairedHits,
}

/// Pairs `a` and `b` image by image (the same object and ground truth at each position, as two
/// evaluations of the same seed and count give) and compares them at threshold `theta_deg`.
pub fn compare_paired(
    a: &[ImageRecord],
    b: &[ImageRecord],
    theta_deg: f64,
) -> Result<PairedComparison, PairingError> {
    if a.is_empty() || b.is_empty() {
        return Err(PairingError::NoRecords);
    }
    if a.len() != b.len() {
        return Err(PairingError::Count(a.len(), b.len()));
    }
    let describe = |r: &ImageRecord| format!("{} at {:?}", r.object, r.truth);
    for (index, (x, y)) in a.iter().zip(b).enumerate() {
        let same_pose = crate::so3::quaternion_dot(&x.truth, &y.truth).abs() > 1.0 - 1e-9;
        if x.object != y.object || !same_pose {
            return Err(PairingError::Image {
                index,
                a: describe(x),
                b: describe(y),
            });
        }
    }
    let ll_differences: Vec<f64> = a
        .iter()
        .zip(b)
        .map(|(x, y)| y.log_likelihood - x.log_likelihood)
        .collect();
    let mean = |v: &[ImageRecord], f: &dyn Fn(&ImageRecord) -> f64| {
        v.iter().map(f).sum::<f64>() / v.len() as f64
    };
    let hits = |error: fn(&ImageRecord) -> f64| {
        let hit = |r: &ImageRecord| f64::from(u8::from(error(r) < theta_deg));
        // Per image B − A: −1 right in A only, +1 in B only.
        let d: Vec<f64> = a.iter().zip(b).map(|(x, y)| hit(y) - hit(x)).collect();
        let only = |side: f64| d.iter().filter(|&&v| v == side).count();
        let (only_a, only_b) = (only(-1.0), only(1.0));
        PairedHits {
            rates: (mean(a, &hit), mean(b, &hit)),
            only: (only_a, only_b),
            se: standard_error(&d),
            p_value: mcnemar_p(only_a, only_b),
        }
    };
    Ok(PairedComparison {
        images: a.len(),
        ll: (
            mean(a, &|r| r.log_likelihood),
            mean(b, &|r| r.log_likelihood),
        ),
        ll_se: standard_error(&ll_differences),
        argmax: hits(|r| r.argmax_error_deg),
        mode: hits(|r| r.mode_error_deg),
    })
}

/// The standard error of the mean of `d` (sample variance; 0 for fewer than two values).
fn standard_error(d: &[f64]) -> f64 {
    let n = d.len() as f64;
    if d.len() < 2 {
        return 0.0;
    }
    let mean = d.iter().sum::<f64>() / n;
    let variance = d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
    (variance / n).sqrt()
}

/// McNemar's exact test of `b` against `c` discordant pairs: two-sided, `2·P(X ≤ min(b, c))` for
/// `X ~ Binomial(b + c, 1/2)`, at most 1 (1 when there are none).
pub fn mcnemar_p(b: usize, c: usize) -> f64 {
    let n = b + c;
    let ln_half_n = -(n as f64) * std::f64::consts::LN_2;
    // ln C(n, k), built up from k = 0.
    let mut ln_choose = 0.0;
    let mut tail = 0.0;
    for k in 0..=b.min(c) {
        if k > 0 {
            ln_choose += ((n - k + 1) as f64).ln() - (k as f64).ln();
        }
        tail += (ln_choose + ln_half_n).exp();
    }
    (2.0 * tail).min(1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(object: &str, angle: f64, ll: f64, error: f64) -> ImageRecord {
        let h = angle / 2.0;
        ImageRecord {
            object: object.into(),
            truth: [h.cos(), h.sin(), 0.0, 0.0],
            log_likelihood: ll,
            argmax_error_deg: error,
            mode_error_deg: error / 2.0,
            argmax: None,
        }
    }

    #[test]
    fn mcnemar_is_the_binomial_tail_twice() {
        assert_eq!(mcnemar_p(0, 0), 1.0);
        assert!((mcnemar_p(0, 6) - 2.0 / 64.0).abs() < 1e-12);
        assert!((mcnemar_p(5, 1) - 2.0 * 7.0 / 64.0).abs() < 1e-12);
        assert_eq!(mcnemar_p(3, 3), 1.0);
        // Large counts stay finite (no 0.5ⁿ underflow): 600 against 400 is far from even.
        let p = mcnemar_p(600, 400);
        assert!(p > 0.0 && p < 1e-9, "{p}");
    }

    #[test]
    fn paired_figures_count_the_discordant_images() {
        let a: Vec<ImageRecord> = [(1.0, 10.0), (2.0, 20.0), (3.0, 40.0), (4.0, 50.0)]
            .iter()
            .enumerate()
            .map(|(i, (ll, e))| record("drill", i as f64 * 0.3, *ll, *e))
            .collect();
        let b: Vec<ImageRecord> = [(2.0, 10.0), (2.0, 35.0), (5.0, 20.0), (6.0, 25.0)]
            .iter()
            .enumerate()
            .map(|(i, (ll, e))| record("drill", i as f64 * 0.3, *ll, *e))
            .collect();
        let c = compare_paired(&a, &b, 30.0).unwrap();
        assert_eq!(c.images, 4);
        assert_eq!(c.ll, (2.5, 3.75));
        // Differences 1, 0, 2, 2: mean 1.25, sample variance 11/12.
        assert!((c.ll_se - (11.0f64 / 12.0 / 4.0).sqrt()).abs() < 1e-12);
        assert_eq!(c.argmax.rates, (0.5, 0.75));
        assert_eq!(c.argmax.only, (1, 2));
        assert!((c.argmax.p_value - 1.0).abs() < 1e-12);
        // Modes at half the errors: every image of both within 30°.
        assert_eq!((c.mode.rates, c.mode.only), ((1.0, 1.0), (0, 0)));
        // A report against itself: no difference at all.
        let same = compare_paired(&a, &a, 30.0).unwrap();
        assert_eq!(
            (same.ll.0, same.ll_se, same.argmax.only),
            (2.5, 0.0, (0, 0))
        );
    }

    #[test]
    fn other_crops_are_refused() {
        let a = vec![
            record("drill", 0.1, 1.0, 5.0),
            record("drill", 0.2, 1.0, 5.0),
        ];
        assert_eq!(
            compare_paired(&a, &a[..1], 30.0),
            Err(PairingError::Count(2, 1))
        );
        assert_eq!(compare_paired(&a, &[], 30.0), Err(PairingError::NoRecords));
        let mut turned = a.clone();
        turned[1] = record("drill", 0.25, 1.0, 5.0);
        assert!(matches!(
            compare_paired(&a, &turned, 30.0),
            Err(PairingError::Image { index: 1, .. })
        ));
        let mut other = a.clone();
        other[0].object = "mug".into();
        let err = compare_paired(&a, &other, 30.0).unwrap_err().to_string();
        assert!(err.contains("image 0") && err.contains("mug"), "{err}");
        // The same pose written with the opposite quaternion sign pairs.
        let mut flipped = a.clone();
        flipped[0].truth = flipped[0].truth.map(|v| -v);
        assert!(compare_paired(&a, &flipped, 30.0).is_ok());
    }
}
