//! The training step benchmark (`alignist-train bench --training`): the IPDF and the Alignist
//! step on the same network, batch, K and crops, each with its stage profile, on a small set it
//! makes itself (fresh cube renders, experts of random SIRENs baked at the real resolution, so
//! the targets cost what they cost in a real run).

use std::ops::ControlFlow;

use serde::{Deserialize, Serialize};

use std::path::Path;

use super::TrainError;
use super::config::{MeasureLoss, Method, TrainConfig};
use super::data::FreshRenders;
use super::sampling::SamplingStrategy;
use super::trainer::{StepProfile, TrainingSet, train};
use crate::bundle::experts::{bake_experts, key_siren_config};
use crate::cad::Shape;
use crate::data::realism::{Realism, SceneAssets};
use crate::encoding::RotationEncoding;
use crate::experts::SirenConfig;
use crate::experts::energy::EnergyParams;
use crate::experts::modes::{ModeTable, ModeTableConfig};
use crate::net::{NetworkConfig, ResNetLayout};

/// What the benchmark runs.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrainingBenchConfig {
    /// Images per step.
    pub batch: usize,
    /// Rotations per image.
    pub k: usize,
    /// Crop side.
    pub image_size: u32,
    /// Encoder layout.
    pub layout: ResNetLayout,
    /// Measured steps per method (after `warmup` unmeasured ones).
    pub steps: usize,
    /// Unmeasured steps first.
    pub warmup: usize,
}

impl Default for TrainingBenchConfig {
    fn default() -> Self {
        TrainingBenchConfig {
            batch: 16,
            k: 256,
            image_size: 32,
            layout: ResNetLayout::Tiny,
            steps: 30,
            warmup: 5,
        }
    }
}

/// The figures of one run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainingBench {
    /// Mean ms per stage of the IPDF step.
    pub ipdf: StepProfile,
    /// Mean ms per stage of the Alignist step.
    pub alignist: StepProfile,
    /// FLOPs of the head's forward pass in one step (both branches, all `batch · K` rows).
    pub head_forward_flops: f64,
    /// The training backend's f32 matmul peak (`4096×256·256×256`), GFLOP/s.
    pub matmul_peak_gflops: f64,
}

impl TrainingBench {
    /// GFLOP/s of the head's forward pass in the Alignist step.
    pub fn head_forward_gflops(&self) -> f64 {
        self.head_forward_flops / (self.alignist.head_forward * 1e-3) / 1e9
    }

    /// Alignist step time over IPDF step time.
    pub fn ratio(&self) -> f64 {
        self.alignist.total / self.ipdf.total
    }
}

/// Runs both methods and returns their profiles.
pub fn bench_training(config: &TrainingBenchConfig) -> Result<TrainingBench, TrainError> {
    let device = crate::backend::device();
    let mesh = Shape::Cube.mesh();
    let baked = bake_experts(
        &SirenConfig::new(3, 32, 2, 1).init(&device),
        &key_siren_config().init(&device),
        64,
        1.05,
        EnergyParams::default(),
        &device,
    );
    let modes = ModeTable::build(
        &baked,
        &mesh,
        &ModeTableConfig {
            views: 2,
            coarse_level: 2,
            level: 3,
            keep_fraction: 0.01,
            seed: 0,
        },
    )?;
    let set = TrainingSet {
        objects: vec![baked],
        modes: vec![modes],
        twins: Vec::new(),
        symmetries: Vec::new(),
        images: Vec::new(),
        // Realistic renders at 2× supersampling, as the realistic training runs make them.
        fresh: Some(FreshRenders {
            realism: Some(SceneAssets::new(
                std::slice::from_ref(&mesh),
                Realism::TRAIN,
            )),
            meshes: vec![mesh],
            supersample: 2,
            pool: None,
        }),
    };
    let network = NetworkConfig::new(config.layout, RotationEncoding::Cube)
        .with_image_size(config.image_size);
    let run = |method: Method, steps: usize| {
        let cfg = TrainConfig {
            network: network.clone(),
            method,
            steps,
            batch: config.batch,
            k: config.k,
            lr: 1e-3,
            warmup: 1,
            seed: 0,
            checkpoint_every: usize::MAX,
            init: None,
            teacher: None,
            plain_start: None,
            pretrained: None,
            pretrained_file: None,
            encoder_lr_scale: None,
            contrast: None,
            target_temperature: None,
        };
        train(&cfg, &set, None, false, |_, _, _| ControlFlow::Continue(()))
            .map(|(_, report)| report.profile)
    };
    let alignist = Method::Alignist {
        loss: MeasureLoss::Gkl,
        sampling: SamplingStrategy::mode_focused(config.k),
        experts: Default::default(),
    };
    run(Method::Ipdf, config.warmup)?;
    let ipdf = run(Method::Ipdf, config.steps)?;
    run(alignist, config.warmup)?;
    let alignist = run(alignist, config.steps)?;
    let (h, e) = (network.hidden as f64, RotationEncoding::Cube.dim() as f64);
    let per_row = 2.0 * (e * h + 2.0 * ((network.layers - 1) as f64 * h * h + h));
    let train_device = crate::backend::device_for(crate::backend::Workload::Conv);
    Ok(TrainingBench {
        ipdf,
        alignist,
        head_forward_flops: per_row * (config.batch * config.k) as f64,
        matmul_peak_gflops: crate::backend::matmul_gflops(&train_device, 4096, 256, 256),
    })
}

/// The same step in PyTorch (`benches/reference_training_step.py`): ms per IPDF and per
/// Alignist step, when `python3` has torch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PyTorchSteps {
    /// IPDF step.
    pub ipdf: f64,
    /// Alignist step.
    pub alignist: f64,
}

/// Runs the PyTorch reference on the benchmark's batch, K, crop size and step counts; the error
/// says why it did not run (no python3, no torch, a failure).
pub fn pytorch_reference(config: &TrainingBenchConfig) -> Result<PyTorchSteps, String> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/reference_training_step.py");
    let out = std::process::Command::new("python3")
        .arg(&script)
        .args(
            [
                config.batch,
                config.k,
                config.image_size as usize,
                config.steps,
                config.warmup,
            ]
            .map(|v| v.to_string()),
        )
        .output()
        .map_err(|e| format!("python3: {e}"))?;
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        return Err(err.lines().last().unwrap_or("failed").to_string());
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let ms = |name: &str| -> Result<f64, String> {
        text.lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.strip_suffix(" ms"))
            .and_then(|v| v.trim().parse().ok())
            .ok_or_else(|| format!("no `{name}… ms` line in its output: {text}"))
    };
    Ok(PyTorchSteps {
        ipdf: ms("ipdf step: ")?,
        alignist: ms("alignist step: ")?,
    })
}
