//! Training the distribution network: sampling, the Alignist (GKL from the experts) and IPDF
//! objectives, Adam with warm-up and cosine decay, atomic checkpoints and resume.

pub mod bench;
pub mod calibrate;
pub mod checkpoint;
pub mod config;
pub mod data;
pub mod depth_eval;
pub mod distil;
pub mod eval;
pub mod experts;
pub mod fit;
pub mod new_model;
pub mod own_twins;
pub mod results;
pub mod sampling;
pub mod trainer;

pub use crate::net::{Network, NetworkConfig};
pub use sampling::{ModeSampler, OwnTwins, SamplingStrategy, sample_rotations};
pub use trainer::{
    ExpertBranches, MeasureLoss, Method, TrainConfig, TrainReport, TrainingImage, TrainingSet,
    train, train_replanned,
};

/// Errors of training.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// A checkpoint could not be written or read.
    #[error("{path}: {message}")]
    Checkpoint {
        /// The file or folder.
        path: String,
        /// What went wrong.
        message: String,
    },
    /// The loss became NaN or infinite.
    #[error("training diverged at step {step} (loss {loss})")]
    Diverged {
        /// The step.
        step: usize,
        /// The loss.
        loss: f64,
    },
    /// A training set that cannot be trained on.
    #[error("{0}")]
    Data(String),
    /// A grid level that cannot be used.
    #[error(transparent)]
    So3(#[from] crate::so3::So3Error),
}
