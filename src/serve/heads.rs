//! The head stage: the head work of every call for one model — Predict's and PredictFrame's
//! searches and PredictDistribution's full grids — on a bounded queue shared by one fixed pool of
//! worker threads (`--head-workers`, one per core by default). A full queue is refused at once; a
//! call whose caller went away is dropped before its work, and stops at its next level or chunk
//! during it; a panic fails only its call (INTERNAL) and is counted, and the worker goes on.
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
use crate::engine::{
    Cancel, CheckedPredict, CropDepth, Distribution, EngineError, Model, Prediction,
};

/// One call's head work: run on a worker with the model, it answers its caller itself.
struct HeadJob {
    /// Set when the caller went away.
    cancel: Cancel,
    work: Box<dyn FnOnce(&Model) + Send>,
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

    /// The top-k prediction for one image's features (and its depth, when given).
    pub async fn predict(
        &self,
        features: Vec<f32>,
        mut options: CheckedPredict,
        depth: Option<CropDepth>,
    ) -> Result<Prediction, Status> {
        self.call("predict", move |model, cancel| {
            options.cancel = cancel.clone();
            let depth = depth.as_ref().map(|d| d.input(model));
            let mut answers = model.predict_checked(&[features], &options, &[depth])?;
            Ok(answers.swap_remove(0))
        })
        .await
    }

    /// The full distribution at `level` for one image's features (and its depth, when given).
    pub async fn distribution(
        &self,
        features: Vec<f32>,
        level: u8,
        depth: Option<CropDepth>,
    ) -> Result<Distribution, Status> {
        self.call("distribution", move |model, cancel| {
            let depth = depth.as_ref().map(|d| d.input(model));
            model.distribution_cancellable(&features, level, depth, cancel)
        })
        .await
    }

    /// Queues `work` and waits for its answer. Dropping the returned future (the caller went
    /// away) sets the work's [`Cancel`]: work not started is skipped, and running work stops at
    /// its next level or chunk.
    async fn call<T: Send + 'static>(
        &self,
        method: &'static str,
        work: impl FnOnce(&Model, &Cancel) -> Result<T, EngineError> + Send + 'static,
    ) -> Result<T, Status> {
        let (reply, answer) = oneshot::channel();
        let cancel = Cancel::new();
        let guard = cancel.on_drop();
        let job = HeadJob {
            cancel: cancel.clone(),
            work: Box::new(move |model: &Model| {
                let started = Instant::now();
                let outcome =
                    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| work(model, &cancel)));
                metrics::histogram!("alignist_head_seconds", "method" => method)
                    .record(started.elapsed().as_secs_f64());
                let _ = reply.send(match outcome {
                    Ok(result) => result.map_err(status_of),
                    Err(panic) => Err(panicked(model, panic.as_ref())),
                });
            }),
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

/// The INTERNAL answer of a call whose work panicked (logged and counted).
fn panicked(model: &Model, panic: &(dyn std::any::Any + Send)) -> Status {
    let message = super::batcher::panic_message(panic);
    tracing::error!("head of model '{}' panicked: {message}", model.name);
    metrics::counter!("alignist_worker_panics_total", "worker" => "head").increment(1);
    refused(
        Code::Internal,
        Reason::ModelFailed,
        format!("the head of model '{}' failed: {message}", model.name),
        None,
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
        // A caller that gave up (cancelled, deadline) is not worth computing for.
        if job.cancel.is_cancelled() {
            metrics::counter!("alignist_abandoned_work_total").increment(1);
            continue;
        }
        (job.work)(&model);
    }
}
