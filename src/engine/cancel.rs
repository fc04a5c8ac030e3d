//! Cooperative cancellation: a flag the caller's side sets when nobody waits for the answer any
//! more (a dropped call or stream), read by the engine's long loops at their chunk and level
//! boundaries so that abandoned work gives its cores back.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use super::EngineError;

/// SDF lookups (rotations × depth points) between two looks at the flag in the fused (depth)
/// term: ~10 ms of one core, so that cancelled work stops well within a second.
pub const CANCEL_LOOKUPS: usize = 1 << 19;

/// Rotations per chunk of the fused term for `points` depth points ([`CANCEL_LOOKUPS`]; 52 at
/// 10 000 points), at least 16 so that each chunk still spreads over the cores.
pub fn cancel_chunk(points: usize) -> usize {
    (CANCEL_LOOKUPS / points.max(1)).max(16)
}

/// A shared cancellation flag. The default one is never cancelled.
#[derive(Debug, Clone, Default)]
pub struct Cancel(Arc<AtomicBool>);

impl Cancel {
    /// A fresh flag, not cancelled.
    pub fn new() -> Self {
        Self::default()
    }

    /// Asks every holder to stop.
    pub fn cancel(&self) {
        self.0.store(true, Ordering::SeqCst);
    }

    /// Whether [`Cancel::cancel`] was called.
    pub fn is_cancelled(&self) -> bool {
        self.0.load(Ordering::Relaxed)
    }

    /// `Err(EngineError::Cancelled)` once cancelled: the check at a chunk or level boundary.
    pub fn check(&self) -> Result<(), EngineError> {
        match self.is_cancelled() {
            true => Err(EngineError::Cancelled),
            false => Ok(()),
        }
    }

    /// A guard that cancels this flag when dropped: held by the future that waits for the work,
    /// so that dropping the call (the client went away) cancels the work.
    pub fn on_drop(&self) -> CancelOnDrop {
        CancelOnDrop(Some(self.clone()))
    }
}

/// Cancels its flag when dropped, unless [`CancelOnDrop::disarm`]ed.
#[derive(Debug)]
pub struct CancelOnDrop(Option<Cancel>);

impl CancelOnDrop {
    /// The work was answered: dropping no longer cancels.
    pub fn disarm(mut self) {
        self.0 = None;
    }
}

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        if let Some(c) = &self.0 {
            c.cancel();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_dropped_guard_cancels_and_a_disarmed_one_does_not() {
        let (a, b) = (Cancel::new(), Cancel::new());
        assert!(a.check().is_ok());
        drop(a.on_drop());
        assert!(matches!(a.check(), Err(EngineError::Cancelled)));
        b.on_drop().disarm();
        assert!(!b.is_cancelled());
    }
}
