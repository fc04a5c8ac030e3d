//! The PyTorch probe of docs/RESULTS.md ("An ImageNet-pretrained encoder learns the drill from
//! realistic crops", `scripts/compare_pretrained.py`) trained through burn instead: the
//! project's EfficientNet-Lite0 from its ImageNet weights, one linear layer over the cells of a
//! grid level, cross-entropy against a Gaussian of `SIGMA` degrees on the geodesic angle from the
//! truth to each cell, AdamW (lr 1e-3, weight decay 1e-4, warm-up over a tenth of the steps up
//! to 200, cosine decay), batch 16 of fresh realistic crops of the training realism. The answer
//! is the most probable cell; AR@30 and the median error on `eval`'s held-out crops (its seed,
//! exact boxes). It tells whether burn's training of the encoder learns as PyTorch's did on the
//! same objective: if it does, what the trainer lacks is in its objective, not its framework.
//!
//! `cargo run --release --example probe_cell_classifier -- BUNDLE STEPS [LEVEL SIGMA SIZE EVAL_EVERY]`
//! (defaults 2, 8°, 96 px, 500; the bundle only names the object and its mesh).
use std::path::Path;
use std::time::Instant;

use alignist::bundle::model::ModelBundle;
use alignist::data::realism::Realism;
use alignist::net::EfficientNetLite0;
use alignist::net::network::images_tensor;
use alignist::so3::grid::GridLevel;
use alignist::train::data::{BundleRenders, EVAL_SEED};
use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::optim::{AdamWConfig, GradientsParams};
use burn::tensor::activation::log_softmax;
use burn::tensor::{Device, Tensor, TensorData};
use nalgebra::Rotation3;

const BATCH: usize = 16;

#[derive(Module, Debug)]
struct Classifier {
    encoder: EfficientNetLite0,
    cells: Linear,
}

impl Classifier {
    /// `[B, 3, S, S]` → the cells' logits `[B, cells]` from the globally pooled features.
    fn forward(&self, images: Tensor<4>) -> Tensor<2> {
        let f = self.encoder.forward(images);
        let [b, c, h, w] = f.dims();
        let pooled = f.reshape([b, c, h * w]).mean_dim(2).reshape([b, c]);
        self.cells.forward(pooled)
    }
}

/// The geodesic angle (radians) from each of `truths` to each of `cells`, `[truths, cells]`.
fn angles(truths: &[Rotation3<f64>], cells: &[Rotation3<f64>]) -> Vec<f64> {
    truths
        .iter()
        .flat_map(|t| cells.iter().map(move |c| c.angle_to(t)))
        .collect()
}

/// The soft targets: a Gaussian of `sigma` on each row's angles, normalised per row.
fn soft_targets(angles: &[f64], cells: usize, sigma: f64) -> Vec<f32> {
    angles
        .chunks_exact(cells)
        .flat_map(|row| {
            let w: Vec<f64> = row
                .iter()
                .map(|a| (-a * a / (2.0 * sigma * sigma)).exp())
                .collect();
            let sum: f64 = w.iter().sum();
            w.into_iter().map(move |v| (v / sum) as f32)
        })
        .collect()
}

/// AR@30 and the median error (degrees) of the most probable cell on `set`.
fn evaluate(
    network: &Classifier,
    set: &[(Vec<u8>, Rotation3<f64>)],
    cells: &[Rotation3<f64>],
    size: usize,
) -> anyhow::Result<(f64, f64)> {
    network.encoder.sync_running_stats();
    let plain = network.valid();
    let device = plain.cells.weight.device();
    let mut errors = Vec::with_capacity(set.len());
    for chunk in set.chunks(50) {
        let crops: Vec<&[u8]> = chunk.iter().map(|(rgb, _)| rgb.as_slice()).collect();
        let logits = plain.forward(images_tensor(&crops, size, &device));
        let picks: Vec<i64> = logits
            .argmax(1)
            .into_data()
            .convert::<i64>()
            .try_to_vec::<i64>()
            .map_err(|e| anyhow::anyhow!("the logits' argmax: {e:?}"))?;
        for ((_, truth), pick) in chunk.iter().zip(picks) {
            errors.push(cells[pick as usize].angle_to(truth).to_degrees());
        }
    }
    let ar = errors.iter().filter(|&&e| e < 30.0).count() as f64 / errors.len() as f64;
    errors.sort_by(f64::total_cmp);
    Ok((ar, errors[errors.len() / 2]))
}

/// The PyTorch probe's schedule (`compare_pretrained.py`'s `LambdaLR`): a linear ramp over a tenth
/// of the steps (at most 200) times a cosine over the whole run, to 0. Not the project's
/// [`alignist::schedule::CosineSchedule`] (its cosine starts after the warm-up and ends at a
/// floor): this probe repeats PyTorch's run, not the trainer's.
fn learning_rate(step: usize, steps: usize) -> f64 {
    let warm = (steps / 10).clamp(1, 200);
    let ramp = ((step + 1) as f64 / warm as f64).min(1.0);
    let cosine = 0.5 * (1.0 + (std::f64::consts::PI * step as f64 / steps as f64).cos());
    1e-3 * ramp * cosine
}

fn crops_of(
    renders: &BundleRenders,
    size: u32,
    n: usize,
    seed: u64,
    realism: Realism,
) -> Vec<(Vec<u8>, Rotation3<f64>)> {
    renders
        .fresh
        .realistic_eval_crops(size, n, seed, realism)
        .into_iter()
        .map(|(_, crop)| (crop.rgb, crop.r_virtual))
        .collect()
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    anyhow::ensure!(
        (3..=7).contains(&args.len()),
        "usage: probe_cell_classifier BUNDLE STEPS [LEVEL SIGMA_DEG SIZE EVAL_EVERY]"
    );
    let arg = |i: usize, default: &str| args.get(i).map_or(default.to_string(), |s| s.clone());
    let bundle = ModelBundle::load(Path::new(&args[1]))?;
    let steps: usize = args[2].parse()?;
    let level: u8 = arg(3, "2").parse()?;
    let sigma = arg(4, "8").parse::<f64>()?.to_radians();
    let size: u32 = arg(5, "96").parse()?;
    let eval_every: usize = arg(6, "500").parse()?;
    anyhow::ensure!(
        bundle.manifest.objects.len() == 1,
        "one object a bundle (it has {})",
        bundle.manifest.objects.len()
    );
    let grid = GridLevel::new(level)?;
    let cells: Vec<Rotation3<f64>> = (0..grid.len() as u64).map(|c| grid.rotation(c)).collect();
    let renders = BundleRenders::of(&bundle, 2);
    let held_out = crops_of(&renders, size, 300, EVAL_SEED + 1, Realism::HELD_OUT);
    let device: Device =
        alignist::backend::device_for(alignist::backend::Workload::Conv).autodiff();
    let weights = Path::new("data/pretrained/efficientnet-lite0.pth");
    let mut network = alignist::backend::seeded_init(&device, 0, || Classifier {
        encoder: EfficientNetLite0::new(&device),
        cells: LinearConfig::new(alignist::net::efficientnet::FEATURES, cells.len()).init(&device),
    });
    network.encoder = network.encoder.with_weights_of(weights)?;
    let mut optim = AdamWConfig::new().with_weight_decay(1e-4).init();
    println!(
        "burn cell classifier: {} cells (level {level}), sigma {:.1} deg, {steps} steps of {BATCH} fresh {size} px crops",
        cells.len(),
        sigma.to_degrees()
    );
    let started = Instant::now();
    let (mut data_s, mut step_s) = (0.0, 0.0);
    for step in 0..steps {
        let clock = Instant::now();
        let batch = crops_of(
            &renders,
            size,
            BATCH,
            7 + ((step as u64) << 20),
            Realism::TRAIN,
        );
        let truths: Vec<Rotation3<f64>> = batch.iter().map(|(_, r)| *r).collect();
        let targets = soft_targets(&angles(&truths, &cells), cells.len(), sigma);
        let crops: Vec<&[u8]> = batch.iter().map(|(rgb, _)| rgb.as_slice()).collect();
        let images = images_tensor(&crops, size as usize, &device);
        data_s += clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let logits = network.forward(images);
        let targets =
            Tensor::<2>::from_data(TensorData::new(targets, [BATCH, cells.len()]), &device);
        let loss = (targets * log_softmax(logits, 1)).sum_dim(1).mean().neg();
        let loss_value = loss.clone().into_scalar::<f32>();
        let grads = GradientsParams::from_grads(loss.backward(), &network);
        network = optim.step(learning_rate(step, steps), network, grads);
        step_s += clock.elapsed().as_secs_f64();
        let done = step + 1;
        if done % 100 == 0 {
            let per = started.elapsed().as_secs_f64() / done as f64;
            println!(
                "step {done} loss {loss_value:.3}: {per:.3} s a step (data {:.3}, step {:.3}), {:.1} min left",
                data_s / done as f64,
                step_s / done as f64,
                per * (steps - done) as f64 / 60.0
            );
        }
        if done % eval_every == 0 || done == steps {
            let (ar, median) = evaluate(&network, &held_out, &cells, size as usize)?;
            println!(
                "  step {done} held-out (300 crops): AR@30 {ar:.3}, median error {median:.1} deg"
            );
        }
    }
    Ok(())
}
