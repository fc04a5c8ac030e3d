//! RGB-D fusion measured: the same fresh test crops scored from the image alone and fused with
//! the depth their render gives (clean, and with noise and missing pixels), through the serving
//! engine ([`Model`]): LL and AR@30 of the full distribution at a level, the served top-1's
//! rotation error and the error of its translation.

use nalgebra::{Rotation3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use crate::engine::{
    DepthInput, DepthMap, EngineError, Intrinsics, Model, PredictOptions, SeenPoints, back_project,
};
use crate::so3::metrics::{error_to_nearest_deg, image_metrics, ll_ceiling};
use crate::so3::{GridLevel, equivalents};
use crate::train::data::BundleRenders;

/// How the depth of a test image is spoiled before fusion.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DepthNoise {
    /// Gaussian noise on each depth value, as a fraction of the object's radius.
    pub sigma: f64,
    /// Fraction of the object's pixels whose depth is dropped (set to 0).
    pub missing: f64,
}

/// One test crop with its depth.
pub struct DepthEvalImage {
    /// The object's index in the model.
    pub object: usize,
    /// The crop as the network sees it.
    pub rgb: Vec<u8>,
    /// Every equivalent ground-truth rotation (crop camera).
    pub equivalents: Vec<Rotation3<f64>>,
    /// The depth map of the render (mesh units; 0 off the object) and its camera.
    pub depth: DepthMap,
    /// The intrinsics of `depth`.
    pub intrinsics: Intrinsics,
    /// The ground-truth translation in the crop camera (`x = R·x_mesh + t`, mesh units).
    pub translation: Vector3<f64>,
}

/// Figures of one condition (image only, or fused with one kind of depth), over some images.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DepthFigures {
    /// Images.
    pub images: usize,
    /// Mean LL of the full distribution at the level.
    pub log_likelihood: f64,
    /// AR@30 of the full distribution's argmax.
    pub ar30: f64,
    /// AR@30 of the served top-1 (the coarse-to-fine search to its default level).
    pub served_ar30: f64,
    /// Mean and median error of the served top-1's translation, in % of the object's radius
    /// (NaN for image only).
    pub translation_error_mean_pct: f64,
    /// See `translation_error_mean_pct`.
    pub translation_error_median_pct: f64,
}

/// The report of `alignist-train eval --depth`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DepthReport {
    /// Grid level of the full distributions.
    pub level: u8,
    /// Mean LL ceiling of the level for these images.
    pub ll_ceiling: f64,
    /// The noisy condition.
    pub noise: DepthNoise,
    /// Per object name, then `all`: image only, fused clean, fused noisy.
    pub rows: Vec<(String, [DepthFigures; 3])>,
}

/// The fresh test crops of `renders` (the poses of [`BundleRenders::eval_images`] for the same
/// `seed`) with the depth of their renders, in the model's object order.
pub fn depth_eval_images(
    model: &Model,
    renders: &BundleRenders,
    per_object: usize,
    seed: u64,
) -> Result<Vec<DepthEvalImage>, EngineError> {
    let size = model.input_size();
    renders
        .fresh
        .eval_crops(size, per_object, seed)
        .into_iter()
        .map(|(i, crop)| {
            let object = model.object_index(&renders.names[i])?;
            let n = &model.objects[object].normalisation;
            // The renders are of the normalised mesh: back to the source mesh's units.
            let depth = DepthMap {
                width: crop.render.width,
                height: crop.render.height,
                values: crop
                    .render
                    .depth
                    .iter()
                    .map(|&z| z * n.scale as f32)
                    .collect(),
            };
            Ok(DepthEvalImage {
                object,
                rgb: crop.rgb,
                equivalents: equivalents(&crop.r_virtual, &renders.symmetries[i]),
                depth,
                intrinsics: Intrinsics::from(&crop.render_camera),
                translation: crop.t_virtual * n.scale - crop.r_virtual * Vector3::from(n.centre),
            })
        })
        .collect()
}

/// `map` with Gaussian noise of `sigma` mesh units on every valid value and a `missing` fraction
/// of them dropped, from `rng`.
pub fn spoil(map: &DepthMap, sigma: f64, missing: f64, rng: &mut ChaCha8Rng) -> DepthMap {
    use rand::RngExt;
    let normal = Normal::new(0.0, sigma.max(0.0)).expect("a finite σ ≥ 0");
    let values = map
        .values
        .iter()
        .map(|&z| {
            if z <= 0.0 || rng.random::<f64>() < missing {
                0.0
            } else {
                (z as f64 + normal.sample(rng)).max(0.0) as f32
            }
        })
        .collect();
    DepthMap { values, ..*map }
}

/// Scores every image from its crop alone, then fused with its clean depth, then with depth
/// spoiled by `noise`: per object and overall (see [`DepthReport`]).
pub fn evaluate_depth(
    model: &Model,
    images: &[DepthEvalImage],
    level: u8,
    noise: DepthNoise,
    seed: u64,
    mut progress: impl FnMut(usize),
) -> Result<DepthReport, EngineError> {
    let grid = model
        .grid(level)
        .ok_or_else(|| EngineError::Models(format!("level {level} is not served by the model")))?
        .clone();
    let centres = grid.quaternions();
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xde97);
    // Per image: (LL, argmax error, served error, translation error %) for the three conditions.
    let mut rows: Vec<(usize, [[f64; 4]; 3])> = Vec::with_capacity(images.len());
    let mut ceiling = 0.0;
    let clean = DepthNoise {
        sigma: 0.0,
        missing: 0.0,
    };
    for (n, im) in images.iter().enumerate() {
        let mut figures = [[f64::NAN; 4]; 3];
        let features = model.features(&[&im.rgb])?.swap_remove(0);
        for (k, condition) in [None, Some(clean), Some(noise)].into_iter().enumerate() {
            figures[k] = score_image(model, im, &features, &grid, &centres, condition, &mut rng)?;
        }
        ceiling += ll_ceiling(&grid, &im.equivalents);
        rows.push((im.object, figures));
        progress(n + 1);
    }
    let mut out: Vec<(String, [DepthFigures; 3])> = model
        .objects
        .iter()
        .enumerate()
        .filter(|(i, _)| rows.iter().any(|(o, _)| o == i))
        .map(|(i, o)| (o.name.clone(), summarise(&rows, &|x| x == i)))
        .collect();
    out.push(("all".into(), summarise(&rows, &|_| true)));
    Ok(DepthReport {
        level,
        ll_ceiling: ceiling / images.len().max(1) as f64,
        noise,
        rows: out,
    })
}

/// One image's figures (from its `features`) in one condition (image only, or fused with its
/// depth spoiled by `noise`): LL and argmax error of the full distribution at `grid`'s level, the served top-1's
/// error, and its translation error in % of the radius (NaN for image only).
fn score_image(
    model: &Model,
    im: &DepthEvalImage,
    features: &[f32],
    grid: &GridLevel,
    centres: &[[f64; 4]],
    noise: Option<DepthNoise>,
    rng: &mut ChaCha8Rng,
) -> Result<[f64; 4], EngineError> {
    let object = &model.objects[im.object];
    let radius = object.normalisation.scale;
    let seen = match noise {
        None => None,
        Some(noise) => {
            let map = match noise.sigma > 0.0 || noise.missing > 0.0 {
                true => spoil(&im.depth, noise.sigma * radius, noise.missing, rng),
                false => im.depth.clone(),
            };
            let whole = crate::engine::CropBox::pixels(0, 0, map.width, map.height);
            let points = back_project(
                &map,
                &im.intrinsics,
                &whole,
                None,
                model.config().depth_image_points,
                "depth",
            )?;
            Some(SeenPoints::Camera(
                object.fusion.camera_points(&points, "depth")?,
            ))
        }
    };
    let input = seen.as_ref().map(|points| DepthInput { object, points });
    let distribution = model.distribution(features, grid.level(), input)?;
    let m = image_metrics(grid, centres, &distribution.log_density, &im.equivalents)?;
    let options = PredictOptions {
        top_k: 1,
        ..Default::default()
    };
    let served = model.predict(features, &options, input)?;
    let top = crate::so3::from_quaternion(served.rotations[0])?;
    let t_error = served.translations.first().map_or(f64::NAN, |t| {
        (Vector3::from(*t) - im.translation).norm() / radius * 100.0
    });
    Ok([
        m.log_likelihood,
        m.argmax_error_deg,
        error_to_nearest_deg(&top, &im.equivalents),
        t_error,
    ])
}

/// The figures of the `rows` whose object passes `filter`, per condition.
fn summarise(rows: &[(usize, [[f64; 4]; 3])], filter: &dyn Fn(usize) -> bool) -> [DepthFigures; 3] {
    std::array::from_fn(|k| {
        let picked: Vec<[f64; 4]> = rows
            .iter()
            .filter(|(o, _)| filter(*o))
            .map(|(_, f)| f[k])
            .collect();
        let n = picked.len().max(1) as f64;
        let within = |i: usize| picked.iter().filter(|f| f[i] <= 30.0).count() as f64 / n;
        let mut t: Vec<f64> = picked
            .iter()
            .map(|f| f[3])
            .filter(|v| v.is_finite())
            .collect();
        t.sort_by(f64::total_cmp);
        DepthFigures {
            images: picked.len(),
            log_likelihood: picked.iter().map(|f| f[0]).sum::<f64>() / n,
            ar30: within(1),
            served_ar30: within(2),
            translation_error_mean_pct: if t.is_empty() {
                f64::NAN
            } else {
                t.iter().sum::<f64>() / t.len() as f64
            },
            translation_error_median_pct: t.get(t.len() / 2).copied().unwrap_or(f64::NAN),
        }
    })
}
