//! Dynamic batching of the image encoder: concurrent requests for one model are collected up to
//! `max_batch` images or `max_delay`, whichever comes first, and encoded in one pass on a
//! dedicated thread. The encoder waits for company only under load (when its last batch had
//! more than one image); a lone call is encoded at once. The queue is bounded; a full queue is
//! answered at once (UNAVAILABLE) rather than letting latency grow without limit. Requests whose
//! caller has gone away are dropped before they are encoded.

use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::sync::{mpsc, oneshot};

use crate::engine::Model;

/// Batching limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BatchConfig {
    /// Most images per encoder pass.
    pub max_batch: usize,
    /// Longest a request waits for others to join its batch.
    pub max_delay: Duration,
    /// Most requests waiting per model.
    pub queue_capacity: usize,
    /// Head worker threads per model: every method's head work runs there, one call per worker
    /// at a time ([`super::heads`]).
    pub head_workers: usize,
}

impl Default for BatchConfig {
    fn default() -> Self {
        Self {
            max_batch: 16,
            max_delay: Duration::from_millis(5),
            queue_capacity: 256,
            head_workers: std::thread::available_parallelism().map_or(2, |n| n.get()),
        }
    }
}

/// Image features of one request, and how long it waited and ran.
#[derive(Debug, Clone)]
pub struct Encoded {
    /// The feature vector.
    pub features: Vec<f32>,
    /// Time in the queue.
    pub queued: Duration,
    /// Size of the batch it was encoded in.
    pub batch_size: usize,
}

struct Job {
    crop: Vec<u8>,
    enqueued: Instant,
    /// The features, or why the encoder failed on this job's batch.
    reply: oneshot::Sender<Result<Encoded, String>>,
}

/// Why a request could not be batched.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BatchError {
    /// The queue is full.
    #[error("the encoder queue of model '{model}' is full ({capacity} requests); retry later")]
    QueueFull {
        /// Model.
        model: String,
        /// Queue capacity.
        capacity: usize,
    },
    /// The batcher stopped (shutting down or model replaced).
    #[error("model '{0}' is not accepting requests (shutting down)")]
    Stopped(String),
    /// The encoder failed (panicked) on this request's batch; it recovered for the next ones.
    #[error("the encoder of model '{model}' failed on this request's batch: {message}")]
    WorkerFailed {
        /// Model.
        model: String,
        /// What failed.
        message: String,
    },
}

/// The batching front of one model's encoder.
#[derive(Clone)]
pub struct Batcher {
    model: String,
    capacity: usize,
    sender: mpsc::Sender<Job>,
}

impl Batcher {
    /// Starts the batching thread of `model`.
    pub fn start(model: Arc<Model>, config: BatchConfig) -> std::io::Result<Batcher> {
        let (sender, receiver) = mpsc::channel(config.queue_capacity.max(1));
        let name = model.name.clone();
        std::thread::Builder::new()
            .name(format!("encoder-{name}"))
            .spawn(move || run(model, config, receiver))?;
        Ok(Batcher {
            model: name,
            capacity: config.queue_capacity,
            sender,
        })
    }

    /// Queues a prepared crop and waits for its features.
    pub async fn encode(&self, crop: Vec<u8>) -> Result<Encoded, BatchError> {
        let answer = self.submit(crop)?;
        self.receive(answer).await
    }

    async fn receive(
        &self,
        answer: oneshot::Receiver<Result<Encoded, String>>,
    ) -> Result<Encoded, BatchError> {
        answer
            .await
            .map_err(|_| BatchError::Stopped(self.model.clone()))?
            .map_err(|message| BatchError::WorkerFailed {
                model: self.model.clone(),
                message,
            })
    }

    /// Encodes several crops of one request: all are queued at once, so that they share encoder
    /// batches (up to `max_batch` each); the features come back in the crops' order.
    pub async fn encode_many(&self, crops: Vec<Vec<u8>>) -> Result<Vec<Encoded>, BatchError> {
        let answers = crops
            .into_iter()
            .map(|c| self.submit(c))
            .collect::<Result<Vec<_>, _>>()?;
        let mut out = Vec::with_capacity(answers.len());
        for answer in answers {
            out.push(self.receive(answer).await?);
        }
        Ok(out)
    }

    /// Queues one crop (refused at once when the queue is full).
    fn submit(
        &self,
        crop: Vec<u8>,
    ) -> Result<oneshot::Receiver<Result<Encoded, String>>, BatchError> {
        let (reply, answer) = oneshot::channel();
        let job = Job {
            crop,
            enqueued: Instant::now(),
            reply,
        };
        let sent = self.sender.try_send(job);
        metrics::gauge!("alignist_queue_depth", "model" => self.model.clone())
            .set((self.capacity - self.sender.capacity()) as f64);
        sent.map_err(|e| match e {
            mpsc::error::TrySendError::Full(_) => BatchError::QueueFull {
                model: self.model.clone(),
                capacity: self.capacity,
            },
            mpsc::error::TrySendError::Closed(_) => BatchError::Stopped(self.model.clone()),
        })?;
        Ok(answer)
    }
}

/// The next batch of a worker's queue: blocks for the first job, then takes what else is queued
/// and, when `wait`, what else arrives within `max_delay`, up to `max_batch` jobs. `None` once
/// every sender is gone.
fn next_batch<T>(
    receiver: &mut mpsc::Receiver<T>,
    config: &BatchConfig,
    wait: bool,
) -> Option<Vec<T>> {
    let first = receiver.blocking_recv()?;
    let deadline = Instant::now()
        + if wait {
            config.max_delay
        } else {
            Duration::ZERO
        };
    let mut jobs = vec![first];
    while jobs.len() < config.max_batch {
        match receiver.try_recv() {
            Ok(job) => jobs.push(job),
            Err(mpsc::error::TryRecvError::Empty) => {
                let now = Instant::now();
                if now >= deadline {
                    break;
                }
                std::thread::sleep((deadline - now).min(Duration::from_micros(200)));
            }
            Err(mpsc::error::TryRecvError::Disconnected) => break,
        }
    }
    Some(jobs)
}

/// The text of a caught panic.
pub(super) fn panic_message(panic: &(dyn std::any::Any + Send)) -> String {
    panic
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| panic.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "panic".into())
}

fn run(model: Arc<Model>, config: BatchConfig, mut receiver: mpsc::Receiver<Job>) {
    // Wait for a batch to fill only under load (the last batch had company): a lone call is
    // encoded at once instead of waiting `max_delay` for calls that are not coming.
    let mut busy = false;
    while let Some(mut jobs) = next_batch(&mut receiver, &config, busy) {
        // What is still queued once this batch is taken: the gauge falls as the queue drains.
        metrics::gauge!("alignist_queue_depth", "model" => model.name.clone())
            .set(receiver.len() as f64);
        busy = jobs.len() > 1;
        // A caller that gave up (cancelled, deadline) is not worth encoding.
        jobs.retain(|j| !j.reply.is_closed());
        if jobs.is_empty() {
            continue;
        }
        let crops: Vec<&[u8]> = jobs.iter().map(|j| j.crop.as_slice()).collect();
        let started = Instant::now();
        // A panic in the encoder fails this batch's calls (INTERNAL) and is counted; the thread
        // goes on with the next batch, so one bad input cannot stop the model.
        let encoded = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            #[cfg(feature = "fault-injection")]
            fault::maybe_panic();
            model.features(&crops)
        }));
        // The engine refusing the crops (prepared crops always have the input side, so that
        // would be a bug upstream) fails the batch's calls the same way.
        let encoded = encoded
            .map_err(|panic| {
                metrics::counter!("alignist_worker_panics_total", "worker" => "encoder")
                    .increment(1);
                format!("encoder panicked: {}", panic_message(panic.as_ref()))
            })
            .and_then(|f| f.map_err(|e| format!("encoder refused the batch: {e}")));
        let features = match encoded {
            Ok(f) => f,
            Err(message) => {
                tracing::error!("model '{}': {message}", model.name);
                for job in jobs {
                    let _ = job.reply.send(Err(message.clone()));
                }
                continue;
            }
        };
        let b = features.len();
        metrics::histogram!("alignist_batch_size").record(b as f64);
        metrics::counter!("alignist_batches_total").increment(1);
        metrics::counter!("alignist_batched_images_total").increment(b as u64);
        metrics::histogram!("alignist_encoder_seconds").record(started.elapsed().as_secs_f64());
        for (job, features) in jobs.into_iter().zip(features) {
            let _ = job.reply.send(Ok(Encoded {
                features,
                queued: started.duration_since(job.enqueued),
                batch_size: b,
            }));
        }
    }
}

/// Test-only faults (the `fault-injection` feature, enabled for the project's tests only):
/// `ALIGNIST_FAULT_ENCODER_PANICS=N` makes the encoder panic on its next `N` batches.
#[cfg(feature = "fault-injection")]
mod fault {
    use std::sync::atomic::{AtomicI64, Ordering};

    static LEFT: AtomicI64 = AtomicI64::new(-1);

    pub(super) fn maybe_panic() {
        if LEFT.load(Ordering::SeqCst) < 0 {
            let n = std::env::var("ALIGNIST_FAULT_ENCODER_PANICS")
                .ok()
                .and_then(|v| v.parse().ok())
                .unwrap_or(0);
            let _ = LEFT.compare_exchange(-1, n, Ordering::SeqCst, Ordering::SeqCst);
        }
        if LEFT
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| {
                (n > 0).then(|| n - 1)
            })
            .is_ok()
        {
            panic!("injected encoder fault (ALIGNIST_FAULT_ENCODER_PANICS)");
        }
    }
}
