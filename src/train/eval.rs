//! Evaluation over a full grid level (docs/DESIGN.md §2 metrics): the network's combined log-density
//! `s_θ + s_φ` on every cell centre, then LL (all equivalents), spread, and the argmax's error.
//! The rotation half of the head's first layer is computed once per level and shared.

use std::time::Instant;

use nalgebra::Rotation3;

pub use crate::bundle::record::{EvalReport, ServedReport, ServedSummary};
use crate::engine::{EngineError, Model, PredictOptions};
use crate::net::{Network, NetworkConfig, ProjectedGrid, images_tensor};
use crate::so3::So3Error;
use crate::so3::metrics::{
    ImageMetrics, MetricsSummary, accuracy_and_median, chance_accuracy, error_to_nearest_deg,
    image_metrics, summarize,
};

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
            per_image.push((im.object.clone(), metrics(&combined)?));
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
