//! What a training run is: the objective, the budget, the schedule. Shared by the trainer and
//! the checkpoints (which record it), so neither imports the other.

pub use crate::bundle::record::{
    ExpertBranches, InitWeights, MeasureLoss, Method, TeacherWeights, TrainConfig, warmup_steps,
};

/// Learning rate at `step` of a schedule of `steps` (`config.steps`, or what a re-plan made of
/// it): linear warm-up over `config.warmup`, then cosine decay to 1 % of the peak.
pub fn learning_rate(config: &TrainConfig, steps: usize, step: usize) -> f64 {
    crate::schedule::CosineSchedule {
        peak: config.lr,
        warmup: config.warmup,
        steps,
        floor: 0.01,
    }
    .at(step)
}
