//! The head stage: the head work of concurrent calls for one model — Predict's and PredictFrame's
//! coarse-to-fine searches, PredictDistribution's full levels — on a bounded queue shared by one
//! fixed pool of worker threads (`--head-workers`, one per core by default). A full
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
use crate::engine::{Cancel, CropDepth, Distribution, Model, PredictOptions, Prediction};

/// One call's head work: an image's features, its depth points when depth was given, and what to
/// compute.
struct HeadJob {
    features: Vec<f32>,
    depth: Option<CropDepth>,
    work: Work,
}

/// What a [`HeadJob`] computes, and where its answer goes.
enum Work {
    /// A search (Predict, one box of PredictFrame).
    Predict {
        options: PredictOptions,
        reply: oneshot::Sender<Result<Prediction, Status>>,
    },
    /// Every cell of a level (PredictDistribution).
    Distribution {
        level: u8,
        cancel: Cancel,
        reply: oneshot::Sender<Result<Distribution, Status>>,
    },
}

impl Work {
    /// Whether the caller went away (its answer would be dropped).
    fn abandoned(&self) -> bool {
        match self {
            Work::Predict { reply, .. } => reply.is_closed(),
            Work::Distribution { reply, .. } => reply.is_closed(),
        }
    }
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
        depth: Option<CropDepth>,
    ) -> Result<Prediction, Status> {
        let (reply, answer) = oneshot::channel();
        options.cancel = Cancel::new();
        let guard = options.cancel.on_drop();
        let work = Work::Predict { options, reply };
        self.queue(HeadJob {
            features,
            depth,
            work,
        })?;
        let answered = answer.await.map_err(|_| stopped(&self.model))?;
        guard.disarm();
        answered
    }

    /// Every cell of `level` for one image's features. Dropping the returned future cancels the
    /// scoring at its next chunk.
    pub async fn distribution(
        &self,
        features: Vec<f32>,
        level: u8,
        depth: Option<CropDepth>,
    ) -> Result<Distribution, Status> {
        let (reply, answer) = oneshot::channel();
        let cancel = Cancel::new();
        let guard = cancel.on_drop();
        let work = Work::Distribution {
            level,
            cancel,
            reply,
        };
        self.queue(HeadJob {
            features,
            depth,
            work,
        })?;
        let answered = answer.await.map_err(|_| stopped(&self.model))?;
        guard.disarm();
        answered
    }

    /// Queues `job`, or refuses it at once when the queue is full.
    fn queue(&self, job: HeadJob) -> Result<(), Status> {
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
        })
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
        if job.work.abandoned() {
            metrics::counter!("alignist_abandoned_work_total").increment(1);
            continue;
        }
        answer(&model, job);
    }
}

/// Runs one call's head work and answers it.
fn answer(model: &Model, job: HeadJob) {
    let HeadJob {
        features,
        depth,
        work,
    } = job;
    let features = || model.features_tensor(&features);
    let fusion = || depth.as_ref().map(|d| d.input(model));
    match work {
        Work::Predict { options, reply } => {
            let answer = guarded(model, || model.predict(&features(), &options, fusion()));
            let _ = reply.send(answer);
        }
        Work::Distribution {
            level,
            cancel,
            reply,
        } => {
            let answer = guarded(model, || {
                model.distribution_cancellable(&features(), level, fusion(), &cancel)
            });
            let _ = reply.send(answer);
        }
    }
}

/// `compute`'s answer, timed; a panic fails only this call (INTERNAL) and is counted.
fn guarded<T>(
    model: &Model,
    compute: impl FnOnce() -> Result<T, crate::engine::EngineError>,
) -> Result<T, Status> {
    let started = Instant::now();
    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(compute));
    metrics::histogram!("alignist_head_seconds").record(started.elapsed().as_secs_f64());
    match outcome {
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
    }
}
