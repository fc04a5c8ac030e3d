//! The head stage: the Predict work (scoring and coarse-to-fine search) of concurrent calls for
//! one model, on a bounded queue shared by a fixed pool of worker threads (one per core). A full
//! queue is refused at once; a call whose caller went away is dropped before its work; a panic
//! fails only its call (INTERNAL) and is counted, and the worker goes on.
//!
//! Each call runs its own search. Running the searches of concurrent calls in lockstep
//! ([`Model::predict_many`], one pass of the head per level for all of them) was measured slower
//! on the burn backend: 12.8 calls/s for lockstep batches of 8 on one thread against 22.0 calls/s
//! for single searches (level 3, top-5; `examples/probe_heads.rs`), and the single searches
//! spread over the cores.

use std::sync::{Arc, Mutex};
use std::time::Instant;

use tokio::sync::{mpsc, oneshot};
use tonic::{Code, Status};

use super::BatchConfig;
use super::status::{Reason, refused, status_of};
use crate::engine::{Cancel, Model, PredictOptions, Prediction};

/// One call's head work.
struct HeadJob {
    features: Vec<f32>,
    options: PredictOptions,
    /// The depth points, when depth was given.
    depth: Option<crate::engine::CropDepth>,
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
    /// Starts `workers` threads for `model`, with a queue bounded as `config` says.
    pub fn start(
        model: Arc<Model>,
        config: BatchConfig,
        workers: usize,
    ) -> std::io::Result<HeadStage> {
        // Calls reach this queue only through the encoder's (the bound callers set), so it is
        // bounded more loosely: a tight encoder queue must not turn into refusals here.
        let capacity = config.queue_capacity.max(4 * config.max_batch).max(64);
        let (sender, receiver) = mpsc::channel(capacity);
        let receiver = Arc::new(Mutex::new(receiver));
        let name = model.name.clone();
        for i in 0..workers.max(1) {
            let (model, receiver) = (model.clone(), receiver.clone());
            std::thread::Builder::new()
                .name(format!("alignist-head-{name}-{i}"))
                .spawn(move || run(model, receiver))?;
        }
        Ok(HeadStage {
            model: name,
            capacity,
            sender,
        })
    }

    /// The prediction for one image's features. Dropping the returned future (the caller went
    /// away) cancels the search at its next level or chunk ([`PredictOptions::cancel`]).
    pub async fn predict(
        &self,
        features: Vec<f32>,
        mut options: PredictOptions,
        depth: Option<crate::engine::CropDepth>,
    ) -> Result<Prediction, Status> {
        let (reply, answer) = oneshot::channel();
        options.cancel = Cancel::new();
        let guard = options.cancel.on_drop();
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
        let answered = answer.await.map_err(|_| stopped(&self.model))?;
        guard.disarm();
        answered
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

fn run(model: Arc<Model>, receiver: Arc<Mutex<mpsc::Receiver<HeadJob>>>) {
    loop {
        // One job at a time: the lock is held only while waiting for the next job.
        let job = match receiver.lock() {
            Ok(mut r) => r.blocking_recv(),
            Err(_) => None,
        };
        let Some(job) = job else { return };
        // A caller that gave up (cancelled, deadline) is not worth scoring.
        if job.reply.is_closed() {
            metrics::counter!("alignist_abandoned_work_total").increment(1);
            continue;
        }
        answer(&model, job);
    }
}

/// Runs one call's search and answers it.
fn answer(model: &Model, job: HeadJob) {
    let started = Instant::now();
    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        let features = model.features_tensor(&job.features);
        let depth = job.depth.as_ref().map(|d| d.input(model));
        model.predict(&features, &job.options, depth)
    }));
    metrics::histogram!("alignist_head_seconds").record(started.elapsed().as_secs_f64());
    let reply = match outcome {
        Ok(result) => result.map_err(status_of),
        Err(panic) => {
            let message = super::batcher::panic_message(panic.as_ref());
            tracing::error!("head of model '{}' panicked: {message}", model.name);
            metrics::counter!("alignist_worker_panics_total", "worker" => "head").increment(1);
            Err(refused(
                Code::Internal,
                Reason::ModelFailed,
                format!("the head of model '{}' failed: {message}", model.name),
                None,
            ))
        }
    };
    let _ = job.reply.send(reply);
}
