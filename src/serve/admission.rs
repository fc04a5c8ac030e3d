//! Admission before work: every call that carries an image takes its share of a budget of
//! in-flight image bytes before anything is decoded, and gives it back when it is answered. A call
//! that does not fit is refused at once (RESOURCE_EXHAUSTED, `ADMISSION_FULL`, with a retry
//! delay) instead of growing the server's memory. Head computations run on each model's head stage
//! ([`super::heads`]), sized by one setting (`--head-workers`).

use std::sync::Arc;
use std::time::Duration;

use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tonic::{Code, Status};

use super::status::{Reason, refused};

/// Limits of the work in flight.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AdmissionConfig {
    /// Most image bytes in flight: the encoded bytes plus the decoded RGB8 size of every
    /// admitted call's image.
    pub max_in_flight_bytes: usize,
}

impl Default for AdmissionConfig {
    fn default() -> Self {
        Self {
            max_in_flight_bytes: 256 << 20,
        }
    }
}

/// The budget, shared by every call.
#[derive(Debug, Clone)]
pub struct Admission {
    bytes: Arc<Semaphore>,
    capacity_kib: usize,
}

/// A call's admitted share of the budget; returned when dropped (and the gauge lowered).
#[derive(Debug)]
pub struct Admitted {
    permit: Option<OwnedSemaphorePermit>,
    budget: Option<(Arc<Semaphore>, usize)>,
    /// The bytes it accounts for.
    pub bytes: usize,
}

impl Drop for Admitted {
    fn drop(&mut self) {
        drop(self.permit.take());
        if let Some((bytes, capacity_kib)) = &self.budget {
            set_admitted_gauge(bytes, *capacity_kib);
        }
    }
}

/// `alignist_admitted_bytes`: the image bytes admitted and not yet answered.
fn set_admitted_gauge(bytes: &Semaphore, capacity_kib: usize) {
    metrics::gauge!("alignist_admitted_bytes")
        .set((capacity_kib.saturating_sub(bytes.available_permits()) * 1024) as f64);
}

impl Admission {
    /// A budget of `config`.
    pub fn new(config: AdmissionConfig) -> Admission {
        let capacity_kib = (config.max_in_flight_bytes / 1024).max(1);
        Admission {
            bytes: Arc::new(Semaphore::new(capacity_kib)),
            capacity_kib,
        }
    }

    /// Admits a call whose image costs `bytes` ([`image_cost`]), or refuses it at once.
    pub fn admit(&self, bytes: usize) -> Result<Admitted, Status> {
        let kib = bytes.div_ceil(1024).clamp(1, self.capacity_kib);
        match self.bytes.clone().try_acquire_many_owned(kib as u32) {
            Ok(permit) => {
                set_admitted_gauge(&self.bytes, self.capacity_kib);
                Ok(Admitted {
                    permit: Some(permit),
                    budget: Some((self.bytes.clone(), self.capacity_kib)),
                    bytes,
                })
            }
            Err(_) => {
                metrics::counter!("alignist_admission_refused_total").increment(1);
                Err(refused(
                    Code::ResourceExhausted,
                    Reason::AdmissionFull,
                    format!(
                        "the server is busy with {} MiB of images in flight (budget {} MiB); \
                         retry shortly",
                        (self.capacity_kib - self.bytes.available_permits()) / 1024,
                        self.capacity_kib / 1024
                    ),
                    Some(Duration::from_millis(200)),
                ))
            }
        }
    }
}

/// What an image costs before it is decoded: its encoded bytes plus its RGB8 size, read from the
/// header (raw RGB8: from the given size). An unreadable header costs its bytes only; decoding
/// then refuses it.
pub fn image_cost(data: &[u8], raw_size: Option<(u32, u32)>) -> usize {
    let pixels = match raw_size {
        Some((w, h)) => w as usize * h as usize,
        None => image::ImageReader::new(std::io::Cursor::new(data))
            .with_guessed_format()
            .ok()
            .and_then(|r| r.into_dimensions().ok())
            .map_or(0, |(w, h)| w as usize * h as usize),
    };
    data.len().saturating_add(pixels.saturating_mul(3))
}
