//! The one place where compute devices are chosen (docs/DESIGN.md §6: keep the backend one switch).
//!
//! burn 0.22 compiles both CPU backends in. Measured here (2 cores): ndarray runs the head's and
//! the SIRENs' matmuls ~2× faster than flex, but flex trains the query U-Net ~30× faster than
//! ndarray (`cargo run --release --example probe_conv`: 8×3×64×64 forward+backward 0.43 s on flex,
//! 13.6 s on ndarray). So each workload gets its own default, and `ALIGNIST_BACKEND=ndarray` or
//! `ALIGNIST_BACKEND=flex` forces one backend for everything, to measure them against each other.

use burn::tensor::Device;

/// What a device is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Workload {
    /// Dense layers: SIRENs, the distribution head, scoring (default ndarray).
    Dense,
    /// Convolutions: the query CNN, the image encoder (default flex).
    Conv,
}

/// The backend that runs `workload`: `ALIGNIST_BACKEND` when set, else the measured default.
pub fn backend_for(workload: Workload) -> &'static str {
    match std::env::var("ALIGNIST_BACKEND").as_deref() {
        Ok("ndarray") => "ndarray",
        Ok("flex") => "flex",
        _ => match workload {
            Workload::Dense => "ndarray",
            Workload::Conv => "flex",
        },
    }
}

/// The device for `workload`.
pub fn device_for(workload: Workload) -> Device {
    if backend_for(workload) == "flex" {
        Device::flex()
    } else {
        // burn 0.22 marks ndarray deprecated in favour of flex; it is still the faster choice
        // for matmul-bound work (docs/DESIGN.md §6).
        #[allow(deprecated)]
        Device::ndarray()
    }
}

/// The device for dense work ([`Workload::Dense`]).
pub fn device() -> Device {
    device_for(Workload::Dense)
}

/// Serialises seeded initialisations: burn's backends keep one global RNG and initialise
/// parameters lazily, so two trainings started at once in one process would interleave draws.
static INIT_LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Builds a module with `init` from burn's RNG seeded with `seed`, and materialises every
/// parameter before releasing the RNG, so the weights depend on the seed alone.
pub fn seeded_init<M: burn::module::Module>(
    device: &Device,
    seed: u64,
    init: impl FnOnce() -> M,
) -> M {
    use burn::store::{ModuleSnapshot, SafetensorsStore};
    let _guard = INIT_LOCK
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    device.seed(seed);
    let module = init();
    // Reading every tensor forces the lazy initialisers to run now, under the lock.
    let mut sink = SafetensorsStore::from_bytes(None);
    module
        .save_into(&mut sink)
        .expect("an in-memory store accepts any module");
    module
}

/// GFLOP/s of an f32 `[m, k]·[k, n]` matmul on `device` (best of 20, after one warm-up).
pub fn matmul_gflops(device: &Device, m: usize, k: usize, n: usize) -> f64 {
    use burn::tensor::{Distribution, Tensor};
    let a = Tensor::<2>::random([m, k], Distribution::Default, device);
    let b = Tensor::<2>::random([k, n], Distribution::Default, device);
    let run = || {
        let c = a.clone().matmul(b.clone());
        let _ = c.into_data();
    };
    run();
    let best = (0..20)
        .map(|_| {
            let t = std::time::Instant::now();
            run();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::MAX, f64::min);
    2.0 * (m * k * n) as f64 / best / 1e9
}
