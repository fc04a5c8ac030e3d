//! The feature expert (SurfEmb, Haugaard & Buch 2022; docs/DESIGN.md §2): a key SIREN
//! `f_SE: R³ → R¹²` (3 → 256 → 256 → 12, ω₀ = 30) and a query CNN (a small U-Net) that maps an
//! RGB crop to a mask logit and a 12-d query per pixel. Trained jointly on renders at random
//! poses with mask BCE + InfoNCE: each sampled foreground pixel's query is scored against the key
//! of its true surface point (from the NOCS render), the keys of the other sampled pixels, and the
//! keys of negatives sampled uniformly on the surface. A pixel looks the same under symmetric
//! poses, so the loss is lowest when symmetric points share a key: that is what makes the expert
//! symmetry-aware.

use std::time::Instant;

use burn::config::Config;
use burn::module::Module;
use burn::nn::PaddingConfig2d;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::pool::{MaxPool2d, MaxPool2dConfig};
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::activation::{log_softmax, relu};
use burn::tensor::module::interpolate;
use burn::tensor::ops::{InterpolateMode, InterpolateOptions};
use burn::tensor::{Device, Int, Tensor, TensorData};
use nalgebra::Vector3;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::sdf::{cosine_lr, points_tensor};
use super::{ExpertError, Siren, SirenConfig, run_batched};
use crate::cad::{Camera, Mesh, RenderOptions, render};
use crate::data::symsol_pose;
use crate::so3::haar_rotation;

/// Dimension of SurfEmb's keys and queries.
pub const FEATURE_DIM: usize = 12;

/// Two 3×3 convolutions with ReLU.
#[derive(Module, Debug)]
pub struct DoubleConv {
    a: Conv2d,
    b: Conv2d,
}

fn conv3(c_in: usize, c_out: usize, device: &Device) -> Conv2d {
    Conv2dConfig::new([c_in, c_out], [3, 3])
        .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
        .init(device)
}

impl DoubleConv {
    fn new(c_in: usize, c_out: usize, device: &Device) -> Self {
        DoubleConv {
            a: conv3(c_in, c_out, device),
            b: conv3(c_out, c_out, device),
        }
    }

    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        relu(self.b.forward(relu(self.a.forward(x))))
    }
}

/// Shape of the query U-Net.
#[derive(Config, Debug)]
pub struct QueryNetConfig {
    /// Channels of the first level; each lower level doubles them.
    #[config(default = 16)]
    pub width: usize,
}

/// A three-level U-Net: RGB `[B, 3, H, W]` (H, W divisible by 4) → `[B, 1 + 12, H, W]`
/// (mask logit, then the query).
#[derive(Module, Debug)]
pub struct QueryNet {
    enc1: DoubleConv,
    enc2: DoubleConv,
    enc3: DoubleConv,
    dec2: DoubleConv,
    dec1: DoubleConv,
    head: Conv2d,
    pool: MaxPool2d,
}

impl QueryNetConfig {
    /// Builds the network on `device`.
    pub fn init(&self, device: &Device) -> QueryNet {
        let w = self.width;
        QueryNet {
            enc1: DoubleConv::new(3, w, device),
            enc2: DoubleConv::new(w, 2 * w, device),
            enc3: DoubleConv::new(2 * w, 4 * w, device),
            dec2: DoubleConv::new(6 * w, 2 * w, device),
            dec1: DoubleConv::new(3 * w, w, device),
            head: Conv2dConfig::new([w, 1 + FEATURE_DIM], [1, 1]).init(device),
            pool: MaxPool2dConfig::new([2, 2]).init(),
        }
    }
}

impl QueryNet {
    /// `[B, 3, H, W]` in `[0, 1]` → `[B, 13, H, W]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let up = || InterpolateOptions::new(InterpolateMode::Nearest).with_scale_factor([2.0, 2.0]);
        let e1 = self.enc1.forward(x);
        let e2 = self.enc2.forward(self.pool.forward(e1.clone()));
        let e3 = self.enc3.forward(self.pool.forward(e2.clone()));
        let d2 = self
            .dec2
            .forward(Tensor::cat(vec![interpolate(e3, up()), e2], 1));
        let d1 = self
            .dec1
            .forward(Tensor::cat(vec![interpolate(d2, up()), e1], 1));
        self.head.forward(d1)
    }
}

/// How the feature expert is trained.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct FeatureTrainConfig {
    /// Adam steps.
    pub steps: usize,
    /// Renders per step.
    pub images: usize,
    /// Render side in pixels (divisible by 4).
    pub image_size: u32,
    /// Foreground pixels sampled per image (positives).
    pub pixels: usize,
    /// Surface negatives per step.
    pub negatives: usize,
    /// Learning rate of the query CNN.
    pub lr_query: f64,
    /// Learning rate of the keys.
    pub lr_keys: f64,
    /// Width of the U-Net's first level.
    pub width: usize,
    /// Seed.
    pub seed: u64,
}

impl Default for FeatureTrainConfig {
    fn default() -> Self {
        FeatureTrainConfig {
            steps: 1500,
            images: 8,
            image_size: 32,
            pixels: 128,
            negatives: 512,
            lr_query: 1e-3,
            lr_keys: 1e-4,
            width: 16,
            seed: 0,
        }
    }
}

/// How symmetry-aware the keys are, and the training loss at the end.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct FeatureFit {
    /// Mean InfoNCE loss over the last 10 % of steps.
    pub final_info_nce: f64,
    /// Mean mask BCE over the last 10 % of steps.
    pub final_mask_bce: f64,
    /// `mean ‖f(x) − f(S·x)‖ / mean ‖f(x) − f(y)‖` over surface points `x`, random symmetries
    /// `S ≠ I` of the object and random surface points `y` (0 = fully symmetry-aware); 1 for an
    /// object without symmetries.
    pub symmetry_ratio: f64,
    /// Training wall time in seconds.
    pub train_seconds: f64,
}

/// Both networks of the feature expert as one module (for seeded initialisation).
#[derive(Module, Debug)]
struct FeatureNets {
    keys: Siren,
    query: QueryNet,
}

impl FeatureNets {
    fn into_parts(self) -> (Siren, QueryNet) {
        (self.keys, self.query)
    }
}

/// The two trained networks of the feature expert.
pub struct FeatureExpert {
    /// Keys `f_SE`.
    pub keys: Siren,
    /// Query CNN.
    pub query: QueryNet,
}

/// Image `[H·W·3]` u8 → tensor `[1, 3, H, W]` in `[0, 1]`, appended to `out` (channel-major).
fn push_chw(rgb: &[u8], out: &mut Vec<f32>) {
    for c in 0..3 {
        out.extend(rgb.chunks_exact(3).map(|p| p[c] as f32 / 255.0));
    }
}

/// Numerically stable binary cross-entropy with logits, averaged.
fn bce_with_logits(logits: Tensor<4>, targets: Tensor<4>) -> Tensor<1> {
    let softplus = logits.clone().abs().neg().exp().add_scalar(1.0).log();
    (logits.clone().clamp_min(0.0) - logits * targets + softplus).mean()
}

/// One step's renders: CHW images, masks, and `pixels` foreground pixels per render (their flat
/// index in the batch and their NOCS point, the InfoNCE positives).
struct RenderBatch {
    images: Vec<f32>,
    masks: Vec<f32>,
    pixel_index: Vec<i64>,
    positives: Vec<Vector3<f32>>,
}

/// Renders `config.images` Haar-random poses of `mesh` and picks their positives.
fn render_batch(
    mesh: &Mesh,
    camera: &Camera,
    options: &RenderOptions,
    config: &FeatureTrainConfig,
    rng: &mut ChaCha8Rng,
) -> Result<RenderBatch, ExpertError> {
    let (size, p, b) = (config.image_size as usize, config.pixels, config.images);
    let mut batch = RenderBatch {
        images: Vec::with_capacity(b * 3 * size * size),
        masks: Vec::with_capacity(b * size * size),
        pixel_index: Vec::with_capacity(b * p),
        positives: Vec::with_capacity(b * p),
    };
    for i in 0..b {
        let pose = symsol_pose(haar_rotation(rng));
        let r = render(mesh, camera, &pose, options);
        push_chw(&r.rgb, &mut batch.images);
        batch.masks.extend(r.mask.iter().map(|&m| m as u8 as f32));
        let fg: Vec<usize> = (0..r.mask.len()).filter(|&k| r.mask[k]).collect();
        if fg.is_empty() {
            return Err(ExpertError::EmptyRender(mesh.source.clone()));
        }
        for _ in 0..p {
            let k = fg[rng.random_range(0..fg.len())];
            batch.pixel_index.push((i * size * size + k) as i64);
            batch.positives.push(Vector3::from(r.nocs[k]));
        }
    }
    Ok(batch)
}

/// InfoNCE of `queries` `[N, D]` against `keys` `[M, D]` (M ≥ N) whose first N rows are the
/// queries' positives (row i's is key i) and the rest negatives.
fn info_nce_loss(queries: Tensor<2>, keys: Tensor<2>) -> Tensor<1> {
    let [n, _] = queries.dims();
    let [m, _] = keys.dims();
    let device = queries.device();
    let log_p = log_softmax(queries.matmul(keys.transpose()), 1);
    let eye: Tensor<2> = Tensor::from_data(
        TensorData::new(
            (0..n)
                .flat_map(|i| (0..m).map(move |j| (i == j) as u8 as f32))
                .collect::<Vec<f32>>(),
            [n, m],
        ),
        &device,
    );
    (log_p * eye).sum().neg().div_scalar(n as f64)
}

/// One step's losses: InfoNCE of the query maps at the batch's pixels against the keys of their
/// points (and of the `negatives`), and the mask's binary cross-entropy.
fn step_losses(
    keys: &Siren,
    query: &QueryNet,
    batch: RenderBatch,
    negatives: Vec<Vector3<f32>>,
    config: &FeatureTrainConfig,
    device: &Device,
) -> (Tensor<1>, Tensor<1>) {
    let (size, p, b) = (config.image_size as usize, config.pixels, config.images);
    let x: Tensor<4> = Tensor::from_data(TensorData::new(batch.images, [b, 3, size, size]), device);
    let out = query.forward(x);
    let mask_logits = out.clone().narrow(1, 0, 1);
    let mask_t: Tensor<4> =
        Tensor::from_data(TensorData::new(batch.masks, [b, 1, size, size]), device);
    let bce = bce_with_logits(mask_logits, mask_t);
    // Queries at the sampled pixels: [B·P, 12].
    let q_map = out
        .narrow(1, 1, FEATURE_DIM)
        .permute([0, 2, 3, 1])
        .reshape([b * size * size, FEATURE_DIM]);
    let idx: Tensor<1, Int> =
        Tensor::from_data(TensorData::new(batch.pixel_index, [b * p]), device);
    let queries = q_map.select(0, idx);
    let mut all_points = batch.positives;
    all_points.extend(negatives);
    let all_keys = keys.forward(points_tensor(&all_points, device));
    (info_nce_loss(queries, all_keys), bce)
}

/// Trains the feature expert on renders of `mesh` (in NOCS, with its colours).
/// `symmetries` (identity first) are used only to report [`FeatureFit::symmetry_ratio`].
pub fn train_features(
    mesh: &Mesh,
    symmetries: &[nalgebra::Rotation3<f64>],
    config: &FeatureTrainConfig,
    mut progress: impl FnMut(usize, f64),
) -> Result<(FeatureExpert, FeatureFit), ExpertError> {
    let started = Instant::now();
    let device = crate::backend::device_for(crate::backend::Workload::Conv).autodiff();
    let (mut keys, mut query) = crate::backend::seeded_init(&device, config.seed, || FeatureNets {
        keys: SirenConfig::new(3, 256, 2, FEATURE_DIM).init(&device),
        query: QueryNetConfig::new().with_width(config.width).init(&device),
    })
    .into_parts();
    let mut opt_keys = AdamConfig::new().init();
    let mut opt_query = AdamConfig::new().init();
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let camera = Camera::square(config.image_size);
    let options = RenderOptions::default();
    let mut tail = (0.0, 0.0, 0usize);

    for step in 0..config.steps {
        let batch = render_batch(mesh, &camera, &options, config, &mut rng)?;
        let negatives = mesh.sample_surface_points(config.negatives, &mut rng);

        let (info_nce, bce) = step_losses(&keys, &query, batch, negatives, config, &device);
        let loss = info_nce.clone() + bce.clone();
        let (nce_v, bce_v) = (
            info_nce.into_scalar::<f32>() as f64,
            bce.into_scalar::<f32>() as f64,
        );
        if !(nce_v.is_finite() && bce_v.is_finite()) {
            return Err(ExpertError::Diverged {
                step,
                loss: nce_v + bce_v,
            });
        }
        if step >= config.steps - config.steps.div_ceil(10) {
            tail = (tail.0 + nce_v, tail.1 + bce_v, tail.2 + 1);
        }
        let mut grads = loss.backward();
        let g_query = GradientsParams::from_module(&mut grads, &query);
        let g_keys = GradientsParams::from_module(&mut grads, &keys);
        let frac = cosine_lr(1.0, step, config.steps);
        query = opt_query.step(config.lr_query * frac, query, g_query);
        keys = opt_keys.step(config.lr_keys * frac, keys, g_keys);
        progress(step + 1, nce_v + bce_v);
    }
    // The keys are read by dense work (bakes, scoring): move them to the dense device.
    let dense = crate::backend::device();
    let expert = FeatureExpert {
        keys: keys.valid().to_device(&dense),
        query: query.valid(),
    };
    let symmetry_ratio = symmetry_ratio(&expert.keys, mesh, symmetries, None, config.seed, &dense);
    let n = tail.2.max(1) as f64;
    Ok((
        expert,
        FeatureFit {
            final_info_nce: tail.0 / n,
            final_mask_bce: tail.1 / n,
            symmetry_ratio,
            train_seconds: started.elapsed().as_secs_f64(),
        },
    ))
}

/// `mean ‖f(x) − f(S·x)‖ / mean ‖f(x) − f(y)‖` (see [`FeatureFit::symmetry_ratio`]); with
/// `only_faces`, `x` is drawn from those faces only.
pub fn symmetry_ratio(
    keys: &Siren,
    mesh: &Mesh,
    symmetries: &[nalgebra::Rotation3<f64>],
    only_faces: Option<&[u32]>,
    seed: u64,
    device: &Device,
) -> f64 {
    let non_trivial: Vec<_> = symmetries.iter().filter(|s| s.angle() > 1e-9).collect();
    if non_trivial.is_empty() {
        return 1.0;
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xfea7);
    let xs: Vec<Vector3<f32>> = mesh
        .sample_surface(20_000, &mut rng)
        .into_iter()
        .filter(|s| only_faces.is_none_or(|f| f.contains(&s.face)))
        .take(2000)
        .map(|s| s.point)
        .collect();
    let ys = mesh.sample_surface_points(xs.len(), &mut rng);
    let sx: Vec<Vector3<f32>> = xs
        .iter()
        .map(|x| {
            let s = non_trivial[rng.random_range(0..non_trivial.len())];
            (s * x.cast::<f64>()).cast::<f32>()
        })
        .collect();
    let f = |pts: &[Vector3<f32>]| run_batched(keys, pts, FEATURE_DIM, device);
    let (fx, fsx, fy) = (f(&xs), f(&sx), f(&ys));
    let dist = |a: &[f32], b: &[f32]| super::energy::mean_key_distance(a, b, FEATURE_DIM);
    dist(&fx, &fsx) / dist(&fx, &fy).max(1e-12)
}
