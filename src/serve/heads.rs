//! The head stage: the Predict work (scoring and coarse-to-fine search) of concurrent calls for
//! one model, batched — the calls that ask the same level, top-k and mode angle run as one
//! lockstep search whose every level is one pass of the head ([`Model::predict_many`]) — on a
//! bounded queue and one worker thread per model. A full queue is refused at once; a call whose
//! caller went away is dropped before its work; a panic fails only its batch (INTERNAL) and is
//! counted, and the worker goes on.

use std::sync::Arc;
use std::time::Instant;

use nalgebra::Vector3;
use tokio::sync::{mpsc, oneshot};
use tonic::{Code, Status};

use super::BatchConfig;
use super::status::{Reason, refused, status_of};
use crate::engine::{Model, PredictOptions, Prediction};

/// One call's head work.
struct HeadJob {
    features: Vec<f32>,
    options: PredictOptions,
    /// The object's index and its depth points, when depth was given.
    depth: Option<(usize, Vec<Vector3<f32>>)>,
    reply: oneshot::Sender<Result<Prediction, Status>>,
}

/// The head stage of one model.
#[derive(Clone)]
pub struct HeadStage {
    model: String,
    capacity: usize,
    sender: mpsc::Sender<HeadJob>,
}

impl HeadStage {
    /// Starts the worker thread of `model`, batching as `config` says (the same limits as the
    /// encoder's batching).
    pub fn start(model: Arc<Model>, config: BatchConfig) -> std::io::Result<HeadStage> {
        // Calls reach this queue only through the encoder's (the bound callers set), so it is
        // bounded more loosely: a tight encoder queue must not turn into refusals here.
        let capacity = config.queue_capacity.max(4 * config.max_batch).max(64);
        let (sender, receiver) = mpsc::channel(capacity);
        let name = model.name.clone();
        std::thread::Builder::new()
            .name(format!("alignist-head-{name}"))
            .spawn(move || run(model, config, receiver))?;
        Ok(HeadStage {
            model: name,
            capacity,
            sender,
        })
    }

    /// The prediction for one image's features.
    pub async fn predict(
        &self,
        features: Vec<f32>,
        options: PredictOptions,
        depth: Option<(usize, Vec<Vector3<f32>>)>,
    ) -> Result<Prediction, Status> {
        let (reply, answer) = oneshot::channel();
        let job = HeadJob {
            features,
            options,
            depth,
            reply,
        };
        self.sender.try_send(job).map_err(|e| match e {
            mpsc::error::TrySendError::Full(_) => refused(
                Code::Unavailable,
                Reason::QueueFull,
                format!(
                    "the head queue of model '{}' is full ({} calls); retry later",
                    self.model, self.capacity
                ),
                Some(std::time::Duration::from_millis(100)),
            ),
            mpsc::error::TrySendError::Closed(_) => stopped(&self.model),
        })?;
        answer.await.map_err(|_| stopped(&self.model))?
    }
}

fn stopped(model: &str) -> Status {
    refused(
        Code::Unavailable,
        Reason::ShuttingDown,
        format!("model '{model}' is not accepting requests (shutting down)"),
        Some(std::time::Duration::from_millis(100)),
    )
}

/// Whether two calls can share one lockstep search.
fn same_search(a: &PredictOptions, b: &PredictOptions) -> bool {
    a.top_k == b.top_k
        && a.level == b.level
        && a.mode_angle_deg.map(f64::to_bits) == b.mode_angle_deg.map(f64::to_bits)
}

fn run(model: Arc<Model>, config: BatchConfig, mut receiver: mpsc::Receiver<HeadJob>) {
    while let Some(mut jobs) = super::batcher::next_batch(&mut receiver, &config) {
        // A caller that gave up (cancelled, deadline) is not worth scoring.
        let before = jobs.len();
        jobs.retain(|j| !j.reply.is_closed());
        if jobs.len() < before {
            metrics::counter!("alignist_abandoned_work_total")
                .increment((before - jobs.len()) as u64);
        }
        while !jobs.is_empty() {
            let options = jobs[0].options.clone();
            let (group, rest): (Vec<HeadJob>, Vec<HeadJob>) = jobs
                .into_iter()
                .partition(|j| same_search(&j.options, &options));
            jobs = rest;
            answer(&model, &options, group);
        }
    }
}

/// Runs one lockstep search for `group` and answers each call.
fn answer(model: &Model, options: &PredictOptions, group: Vec<HeadJob>) {
    let started = Instant::now();
    let d = group[0].features.len();
    let flat: Vec<f32> = group
        .iter()
        .flat_map(|j| j.features.iter().copied())
        .collect();
    let b = group.len();
    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        let features = model.features_tensor_many(&flat, b, d);
        let depth: Vec<_> = group
            .iter()
            .map(|j| {
                j.depth
                    .as_ref()
                    .map(|(i, points)| (&model.objects[*i], points.as_slice()))
            })
            .collect();
        model.predict_many(&features, options, &depth)
    }));
    metrics::histogram!("alignist_head_batch_size").record(b as f64);
    metrics::histogram!("alignist_head_seconds").record(started.elapsed().as_secs_f64());
    match outcome {
        Ok(Ok(predictions)) => {
            for (job, p) in group.into_iter().zip(predictions) {
                let _ = job.reply.send(Ok(p));
            }
        }
        Ok(Err(e)) => {
            let status = status_of(e);
            for job in group {
                let _ = job.reply.send(Err(status.clone()));
            }
        }
        Err(panic) => {
            let message = super::batcher::panic_message(panic.as_ref());
            tracing::error!("head of model '{}' panicked: {message}", model.name);
            metrics::counter!("alignist_worker_panics_total", "worker" => "head").increment(1);
            for job in group {
                let _ = job.reply.send(Err(refused(
                    Code::Internal,
                    Reason::ModelFailed,
                    format!("the head of model '{}' failed: {message}", model.name),
                    None,
                )));
            }
        }
    }
}
