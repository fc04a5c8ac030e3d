//! The SDF expert `f_SDF: R³ → R` (docs/DESIGN.md §2): a SIREN (4 sine layers, 256 wide, ω₀ = 30)
//! fitted with an L1 loss to exact signed distances (parry3d) of points near the surface and in
//! the bounding volume of the NOCS mesh.

use std::time::Instant;

use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Device, Tensor, TensorData};
use nalgebra::Vector3;
use rand::{Rng, RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

use super::{ExpertError, Siren, SirenConfig, run_batched};
use crate::cad::{Mesh, SignedDistance};

/// How the SDF expert is trained.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct SdfTrainConfig {
    /// Adam steps.
    pub steps: usize,
    /// Points per step.
    pub batch: usize,
    /// Learning rate (cosine-decayed to 5 % over the run).
    pub lr: f64,
    /// Size of the pool of points with exact distances that batches are drawn from.
    pub pool: usize,
    /// Seed of the point sampling and the initialisation.
    pub seed: u64,
    /// Width of the hidden layers.
    pub hidden: usize,
    /// Number of sine layers.
    pub layers: usize,
}

impl Default for SdfTrainConfig {
    fn default() -> Self {
        SdfTrainConfig {
            steps: 500,
            batch: 1024,
            lr: 1e-4,
            pool: 200_000,
            seed: 0,
            hidden: 256,
            layers: 4,
        }
    }
}

/// How well the SDF expert fits, measured on held-out points.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct SdfFit {
    /// Mean |f − sdf| on held-out near-surface points (surface + N(0, 0.02²) per axis), in NOCS
    /// units (= fraction of the bounding-sphere radius).
    pub mae_near_surface: f64,
    /// Fraction of held-out points with |sdf| > 0.02 whose sign the expert gets right.
    pub sign_accuracy_off_surface: f64,
    /// Training wall time in seconds.
    pub train_seconds: f64,
}

/// Points near the surface (two noise scales) and uniform in the bounding cube, in proportions
/// 40 / 30 / 30 %.
pub fn sample_training_points<R: Rng + ?Sized>(
    mesh: &Mesh,
    n: usize,
    rng: &mut R,
) -> Vec<Vector3<f32>> {
    let n_near = n * 7 / 10;
    let surface = mesh.sample_surface(n_near, rng);
    let mut points: Vec<Vector3<f32>> = surface
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let sigma = if i < n * 4 / 10 { 0.01 } else { 0.05 };
            s.point + gaussian3(rng) * sigma
        })
        .collect();
    while points.len() < n {
        points.push(Vector3::from_fn(|_, _| rng.random_range(-1.1f32..1.1)));
    }
    points
}

/// Held-out evaluation points: surface + N(0, 0.02²) per axis.
pub fn sample_near_surface<R: Rng + ?Sized>(
    mesh: &Mesh,
    n: usize,
    rng: &mut R,
) -> Vec<Vector3<f32>> {
    mesh.sample_surface(n, rng)
        .iter()
        .map(|s| s.point + gaussian3(rng) * 0.02)
        .collect()
}

fn gaussian3<R: Rng + ?Sized>(rng: &mut R) -> Vector3<f32> {
    Vector3::from_fn(|_, _| rng.sample::<f32, _>(StandardNormal))
}

/// Points as a `[n, 3]` tensor.
pub fn points_tensor(points: &[Vector3<f32>], device: &Device) -> Tensor<2> {
    let flat: Vec<f32> = points.iter().flat_map(|p| [p.x, p.y, p.z]).collect();
    Tensor::from_data(TensorData::new(flat, [points.len(), 3]), device)
}

/// Evaluates a 3 → 1 SIREN at many points (in batches of 8192).
pub fn eval_sdf(model: &Siren, points: &[Vector3<f32>], device: &Device) -> Vec<f32> {
    run_batched(model, points, 1, device)
}

/// Trains the SDF expert on `mesh` (in NOCS). `progress(step, loss)` is called after each step.
pub fn train_sdf(
    mesh: &Mesh,
    config: &SdfTrainConfig,
    mut progress: impl FnMut(usize, f64),
) -> Result<(Siren, SdfFit), ExpertError> {
    let started = Instant::now();
    let sdf = SignedDistance::new(mesh)?;
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let pool = sample_training_points(mesh, config.pool, &mut rng);
    let pool_sdf = sdf.distances(&pool);
    let held_out = sample_near_surface(
        mesh,
        5000,
        &mut ChaCha8Rng::seed_from_u64(config.seed ^ 0x5eed),
    );
    let held_out_sdf = sdf.distances(&held_out);

    let plain = crate::backend::device();
    let device = plain.clone().autodiff();
    let mut model = crate::backend::seeded_init(&device, config.seed, || {
        SirenConfig::new(3, config.hidden, config.layers, 1).init(&device)
    });
    let mut optim = AdamConfig::new().init();
    let mut points = Vec::with_capacity(config.batch);
    let mut targets = Vec::with_capacity(config.batch);
    for step in 0..config.steps {
        points.clear();
        targets.clear();
        for _ in 0..config.batch {
            let i = rng.random_range(0..pool.len());
            points.push(pool[i]);
            targets.push(pool_sdf[i]);
        }
        let x = points_tensor(&points, &device);
        let y: Tensor<2> =
            Tensor::from_data(TensorData::new(targets.clone(), [config.batch, 1]), &device);
        let loss = (model.forward(x) - y).abs().mean();
        let loss_value = loss.clone().into_scalar::<f32>() as f64;
        if !loss_value.is_finite() {
            return Err(ExpertError::Diverged {
                step,
                loss: loss_value,
            });
        }
        let grads = GradientsParams::from_grads(loss.backward(), &model);
        model = optim.step(cosine_lr(config.lr, step, config.steps), model, grads);
        progress(step + 1, loss_value);
    }
    let model = model.valid();
    let predicted = eval_sdf(&model, &held_out, &plain);
    let mae = super::mean_abs_difference(&predicted, &held_out_sdf);
    let off: Vec<(f32, f32)> = predicted
        .iter()
        .zip(&held_out_sdf)
        .filter(|(_, t)| t.abs() > 0.02)
        .map(|(p, t)| (*p, *t))
        .collect();
    let sign_ok = off.iter().filter(|(p, t)| p.signum() == t.signum()).count();
    Ok((
        model,
        SdfFit {
            mae_near_surface: mae,
            sign_accuracy_off_surface: sign_ok as f64 / off.len().max(1) as f64,
            train_seconds: started.elapsed().as_secs_f64(),
        },
    ))
}

/// Cosine decay from `lr` to 5 % of it over `steps` (no warm-up).
pub fn cosine_lr(lr: f64, step: usize, steps: usize) -> f64 {
    crate::schedule::CosineSchedule {
        peak: lr,
        warmup: 0,
        steps,
        floor: 0.05,
    }
    .at(step)
}
