//! What a training run is: the objective, the budget, the schedule. Shared by the trainer and
//! the checkpoints (which record it), so neither imports the other.

use serde::{Deserialize, Serialize};

use super::sampling::SamplingStrategy;
use crate::net::NetworkConfig;

/// The measure loss of the Alignist objective.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MeasureLoss {
    /// Generalised KL (paper Eq. 5).
    Gkl,
    /// L1 between measures (ablation).
    L1,
}

/// Which experts' targets an Alignist run fits (the paper's ablation of the experts).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ExpertBranches {
    /// Both: the shape branch fits the SDF expert, the feature branch the feature expert.
    #[default]
    Both,
    /// Only the SDF expert; the feature branch is silenced (a constant output).
    ShapeOnly,
    /// Only the feature expert; the shape branch is silenced.
    FeatureOnly,
}

/// What the network is trained to do.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Method {
    /// Both branches fit the experts' measures.
    Alignist {
        /// The loss per branch.
        loss: MeasureLoss,
        /// How the K rotations are drawn.
        sampling: SamplingStrategy,
        /// Which experts are fitted (runs recorded before this field fitted both).
        #[serde(default)]
        experts: ExpertBranches,
    },
    /// IPDF: one score (both branches summed), `−log softmax` of the GT among uniform samples.
    Ipdf,
}

/// How to train.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// The network.
    pub network: NetworkConfig,
    /// The objective.
    pub method: Method,
    /// Adam steps.
    pub steps: usize,
    /// Images per step.
    pub batch: usize,
    /// Rotations per image.
    pub k: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// Linear warm-up steps.
    pub warmup: usize,
    /// Seed of everything.
    pub seed: u64,
    /// Steps between checkpoints.
    pub checkpoint_every: usize,
    /// Weights to start from instead of a seeded initialisation (a warm restart: a new schedule
    /// from a trained model's weights). `None`: seeded initialisation.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub init: Option<InitWeights>,
}

impl Default for TrainConfig {
    /// The defaults of `alignist-train fit`: the tiny encoder and the cube encoding on 64 px
    /// crops, Alignist (GKL, mode-focused, both experts), 1 000 steps of 8 images × 256
    /// rotations, peak learning rate 1e-3 after a 5 % warm-up, a checkpoint every 100 steps.
    fn default() -> Self {
        let (steps, k) = (1000, 256);
        TrainConfig {
            network: NetworkConfig::new(
                crate::net::ResNetLayout::Tiny,
                crate::encoding::RotationEncoding::Cube,
            ),
            method: Method::Alignist {
                loss: MeasureLoss::Gkl,
                sampling: SamplingStrategy::mode_focused(k),
                experts: ExpertBranches::Both,
            },
            steps,
            batch: 8,
            k,
            lr: 1e-3,
            warmup: warmup_steps(steps),
            seed: 0,
            checkpoint_every: 100,
            init: None,
        }
    }
}

/// The linear warm-up of a run of `steps`: 5 % of it (at least one step).
pub fn warmup_steps(steps: usize) -> usize {
    (steps / 20).max(1)
}

/// A trained network's weights file, named with its checksum so that a run records exactly what
/// it started from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InitWeights {
    /// The weights file (a bundle's `network.safetensors`).
    pub path: String,
    /// Its checksum and size, checked before loading.
    pub file: crate::bundle::FileEntry,
    /// The command that trained it (from its bundle's manifest), so that the chain of runs
    /// behind a model stays on record.
    #[serde(default)]
    pub trained_by: String,
}

/// Learning rate at `step`: linear warm-up, then cosine decay to 1 % of the peak.
pub fn learning_rate(config: &TrainConfig, step: usize) -> f64 {
    crate::schedule::CosineSchedule {
        peak: config.lr,
        warmup: config.warmup,
        steps: config.steps,
        floor: 0.01,
    }
    .at(step)
}
