//! The f32 full grid as the bench times it (`Model::distribution`), beside the FMA peak probed
//! just before and after, repeated: where the head's "% of peak" comes from, and a target for
//! `perf record`. With `RUNS`, each repetition is instead one probe (best of five, as the bench
//! takes it) then `RUNS` single heads (`Model::logits_at`), each as a share of that probe: their
//! range, median, and the best of the first 3 / 5 / 10 / all (the bench's figure is the best of
//! 3), to see how much single runs move.
//! `cargo run --release --example probe_full_grid [BUNDLE] [LEVEL] [REPEATS] [RUNS]`
use std::time::Instant;

use alignist::bench::peak::fma_peak;
use alignist::engine::{Engine, EngineConfig, Model};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let bundle = args.get(1).map_or("models/symsol1", String::as_str);
    let level: u8 = args.get(2).map_or(Ok(4), |s| s.parse())?;
    let repeats: usize = args.get(3).map_or(Ok(5), |s| s.parse())?;
    let runs: Option<usize> = args.get(4).map(|s| s.parse()).transpose()?;
    let model = Engine::load_model(std::path::Path::new(bundle), EngineConfig::default())?;
    let crop = vec![128u8; (model.input_size() * model.input_size() * 3) as usize];
    let features = model.features(&[&crop])?.swap_remove(0);
    let flops = alignist::bench::head_flops_per_rotation(&model);
    let rows = model.grid(level).map_or(0, |g| g.len()) as f64;
    let gflops = |seconds: f64| rows * flops / seconds / 1e9;
    for _ in 0..repeats {
        match runs {
            Some(runs) => spread(&model, &features, level, runs, gflops)?,
            None => {
                let before = fma_peak(true).gflops;
                let t = Instant::now();
                let d = model.distribution(&features, level, None)?;
                let s = t.elapsed().as_secs_f64();
                let t = Instant::now();
                let logits = model.logits_at(&features, level)?;
                let head_s = t.elapsed().as_secs_f64();
                let after = fma_peak(true).gflops;
                let mean = (before + after) / 2.0;
                println!(
                    "level {level}: distribution {:.1} ms, {:.1} GFLOP/s; peak before {before:.1}, after {after:.1}: {:.0} % of their mean ({} cells); the head's logits alone {:.1} ms ({:.0} %, {} cells)",
                    s * 1e3,
                    gflops(s),
                    100.0 * gflops(s) / mean,
                    d.probability.len(),
                    head_s * 1e3,
                    100.0 * gflops(head_s) / mean,
                    logits.len(),
                );
            }
        }
    }
    Ok(())
}

/// One probe, then `runs` single heads of `level` as shares of it.
fn spread(
    model: &Model,
    features: &[f32],
    level: u8,
    runs: usize,
    gflops: impl Fn(f64) -> f64,
) -> anyhow::Result<()> {
    anyhow::ensure!(runs >= 10, "RUNS must be at least 10");
    let peak = fma_peak(true).gflops;
    let mut shares = Vec::with_capacity(runs);
    for _ in 0..runs {
        let t = Instant::now();
        model.logits_at(features, level)?;
        shares.push(100.0 * gflops(t.elapsed().as_secs_f64()) / peak);
    }
    let best = |n: usize| shares[..n].iter().copied().fold(0.0, f64::max);
    let (b3, b5, b10, all) = (best(3), best(5), best(10), best(runs));
    shares.sort_by(f64::total_cmp);
    println!(
        "level {level}, probe {peak:.1} GFLOP/s: single runs {:.0}–{:.0} % of it, median {:.0} %; best of 3 / 5 / 10 / {runs}: {b3:.0} / {b5:.0} / {b10:.0} / {all:.0} %",
        shares[0],
        shares[runs - 1],
        shares[runs / 2],
    );
    Ok(())
}
