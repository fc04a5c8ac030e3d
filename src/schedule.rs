//! The learning-rate schedule every trainer of the project uses (the distribution network, the
//! SDF and the feature experts): a linear warm-up to the peak, then a cosine decay to a floor;
//! and the linear anneal of a training share (the focused rotations, the plain crops).

/// `start` at step 0, `end` at the last step `steps − 1` (and after), linear between.
pub fn linear_anneal(start: f64, end: f64, step: usize, steps: usize) -> f64 {
    let t = step as f64 / steps.saturating_sub(1).max(1) as f64;
    start + (end - start) * t.min(1.0)
}

/// Linear warm-up over `warmup` steps, then cosine decay from `peak` to `floor × peak` at `steps`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CosineSchedule {
    /// Peak learning rate.
    pub peak: f64,
    /// Warm-up steps (0: none).
    pub warmup: usize,
    /// Steps of the whole run.
    pub steps: usize,
    /// The final rate as a fraction of the peak.
    pub floor: f64,
}

impl CosineSchedule {
    /// The learning rate at `step`.
    pub fn at(&self, step: usize) -> f64 {
        if step < self.warmup {
            return self.peak * (step + 1) as f64 / self.warmup as f64;
        }
        let t =
            (step - self.warmup) as f64 / (self.steps.saturating_sub(self.warmup)).max(1) as f64;
        self.peak
            * (self.floor
                + (1.0 - self.floor) * 0.5 * (1.0 + (std::f64::consts::PI * t.min(1.0)).cos()))
    }
}

#[cfg(test)]
mod tests {
    use super::CosineSchedule;

    #[test]
    fn warms_up_then_decays_to_the_floor() {
        let s = CosineSchedule {
            peak: 1e-3,
            warmup: 10,
            steps: 110,
            floor: 0.01,
        };
        assert!((s.at(0) - 1e-4).abs() < 1e-12);
        assert!((s.at(9) - 1e-3).abs() < 1e-12);
        assert!((s.at(10) - 1e-3).abs() < 1e-12);
        assert!((s.at(60) - 1e-3 * (0.01 + 0.99 * 0.5)).abs() < 1e-12);
        assert!((s.at(110) - 1e-5).abs() < 1e-12);
        assert!((s.at(500) - 1e-5).abs() < 1e-12);
        let mut last = f64::MAX;
        for step in 10..=110 {
            assert!(s.at(step) <= last);
            last = s.at(step);
        }
    }
}
