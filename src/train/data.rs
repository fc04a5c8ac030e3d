//! Training and evaluation images from BOP datasets: object-centred crops, ground truths, and the
//! visible canonical points the experts score.

use crate::cad::Mesh;
use crate::data::{BopDataset, DataError};
use crate::experts::select::visible_points_at;

use super::eval::EvalImage;
use super::trainer::TrainingImage;

/// The first `⌈fraction·N⌉` images of `dataset` (all of one object) as training images of
/// object index `object`, with crops of `size` and visible points from `mesh` (NOCS).
pub fn training_images(
    dataset: &BopDataset,
    object: usize,
    mesh: &Mesh,
    size: u32,
    fraction: f64,
) -> Result<Vec<TrainingImage>, DataError> {
    let n = ((dataset.samples.len() as f64 * fraction.clamp(0.0, 1.0)).ceil() as usize)
        .clamp(1, dataset.samples.len().max(1));
    dataset
        .samples
        .iter()
        .take(n)
        .enumerate()
        .map(|(i, s)| {
            Ok(TrainingImage {
                object,
                rgb: dataset.crop(s, size)?.rgb,
                rotation: s.rotation,
                visible: visible_points_at(mesh, &s.rotation, i as u64),
            })
        })
        .collect()
}

/// Up to `limit` images of `dataset` as evaluation images of object `name`.
pub fn eval_images(
    dataset: &BopDataset,
    name: &str,
    size: u32,
    limit: usize,
) -> Result<Vec<EvalImage>, DataError> {
    dataset
        .samples
        .iter()
        .take(limit)
        .map(|s| {
            Ok(EvalImage {
                object: name.to_string(),
                rgb: dataset.crop(s, size)?.rgb,
                equivalents: s.equivalents.clone(),
            })
        })
        .collect()
}
