//! Where the serving encoder's time goes at batch 1: each folded convolution of one crop's
//! forward (`net::InferenceEncoder::unit_times`), median milliseconds over ROUNDS, its GFLOP/s
//! and share, beside the same unit on im2col and the GEMM (no direct 3 × 3 kernel); then the
//! whole forward of both, alternating call by call. The
//! kernels are the widest this CPU has, capped by `ALIGNIST_KERNELS` as the server is.
//! `cargo run --release --example probe_inference_encoder [MODEL] [ROUNDS]`
use alignist::net::{InferenceEncoder, Kernels};
use std::time::Instant;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let model = std::path::PathBuf::from(args.get(1).map_or("models/symsol1", String::as_str));
    let rounds: usize = args.get(2).map_or(Ok(200), |r| r.parse())?;
    let bundle = alignist::bundle::model::ModelBundle::load(&model)?;
    let side = bundle.manifest.network.image_size as usize;
    let kernels = Kernels::from_env();
    let encoder = InferenceEncoder::of(&bundle.network.encoder, kernels).ok_or_else(|| {
        anyhow::anyhow!(
            "{}: a layout the hand-written path does not run",
            model.display()
        )
    })?;
    let crop: Vec<u8> = (0..side * side * 3)
        .map(|i| ((i * 131) % 251) as u8)
        .collect();
    for _ in 0..10 {
        encoder.unit_times(&crop, side);
    }
    let plain = encoder.clone().im2col_only();
    let mut per_unit: Vec<Vec<f64>> = Vec::new();
    let mut plain_per_unit: Vec<Vec<f64>> = Vec::new();
    let mut whole = Vec::with_capacity(rounds);
    let mut units = Vec::new();
    for _ in 0..rounds {
        units = encoder.unit_times(&crop, side);
        per_unit.resize(units.len(), Vec::new());
        for (times, u) in per_unit.iter_mut().zip(&units) {
            times.push(u.ms);
        }
        let plain_units = plain.unit_times(&crop, side);
        plain_per_unit.resize(plain_units.len(), Vec::new());
        for (times, u) in plain_per_unit.iter_mut().zip(&plain_units) {
            times.push(u.ms);
        }
        let started = Instant::now();
        std::hint::black_box(encoder.features(&[&crop], side));
        whole.push(started.elapsed().as_secs_f64() * 1e3);
    }
    // Alternating call by call, so that both arms see the same moments of the machine.
    let (mut direct_ms, mut plain_ms) = (Vec::new(), Vec::new());
    for _ in 0..rounds {
        for (arm, times) in [(&encoder, &mut direct_ms), (&plain, &mut plain_ms)] {
            let started = Instant::now();
            std::hint::black_box(arm.features(&[&crop], side));
            times.push(started.elapsed().as_secs_f64() * 1e3);
        }
    }
    let medians: Vec<f64> = per_unit.into_iter().map(median).collect();
    let plain_medians: Vec<f64> = plain_per_unit.into_iter().map(median).collect();
    let sum: f64 = medians.iter().sum();
    println!(
        "{} ({side} px), kernels {kernels}, {} threads, {rounds} rounds",
        model.display(),
        rayon::current_num_threads()
    );
    println!(
        "{:18} {:24} {:>7} {:>8} {:>8} {:>6} {:>12}",
        "unit", "shape", "MMAC", "ms", "GFLOP/s", "share", "im2col ms"
    );
    for ((u, ms), plain_ms) in units.iter().zip(&medians).zip(&plain_medians) {
        println!(
            "{:18} {:24} {:>7.2} {:>8.3} {:>8.1} {:>5.1}% {:>12.3}",
            u.name,
            u.shape,
            u.multiply_adds as f64 / 1e6,
            ms,
            2.0 * u.multiply_adds as f64 / ms / 1e6,
            100.0 * ms / sum,
            plain_ms
        );
    }
    let macs: usize = units.iter().map(|u| u.multiply_adds).sum();
    println!(
        "sum of the units' medians {sum:.3} ms ({:.1} GFLOP/s); the whole forward's median {:.3} ms",
        2.0 * macs as f64 / sum / 1e6,
        median(whole)
    );
    println!(
        "alternating, {rounds} calls each: direct 3×3 kernel {} — median {:.3} ms; im2col and GEMM only {:.3} ms (sum of its units' medians {:.3} ms)",
        if encoder.has_direct() {
            "on"
        } else {
            "absent on this core"
        },
        median(direct_ms),
        median(plain_ms),
        plain_medians.iter().sum::<f64>()
    );
    Ok(())
}
