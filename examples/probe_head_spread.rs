//! How much single runs of the f32 head move against the FMA probe: rounds of one probe (best of
//! five, as the bench takes it) then `RUNS` single full grids of `LEVEL` (`Model::logits_at`),
//! each as a share of that round's probe; prints each round's range, median, and the best of the
//! first 3 / 5 / 10 / all runs (the bench's figure is the best of 3).
//! `cargo run --release --example probe_head_spread [BUNDLE] [LEVEL] [ROUNDS] [RUNS]`
use std::time::Instant;

use alignist::bench::peak::fma_peak;
use alignist::engine::{Engine, EngineConfig};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let bundle = args.get(1).map_or("models/symsol1", String::as_str);
    let level: u8 = args.get(2).map_or(Ok(3), |s| s.parse())?;
    let rounds: usize = args.get(3).map_or(Ok(3), |s| s.parse())?;
    let runs: usize = args.get(4).map_or(Ok(20), |s| s.parse())?;
    anyhow::ensure!(runs >= 10, "RUNS must be at least 10");
    let model = Engine::load_model(std::path::Path::new(bundle), EngineConfig::default())?;
    let crop = vec![128u8; (model.input_size() * model.input_size() * 3) as usize];
    let features = model.features(&[&crop])?.swap_remove(0);
    let flops = alignist::bench::head_flops_per_rotation(&model);
    let rows = model.grid(level).map_or(0, |g| g.len()) as f64;
    for _ in 0..rounds {
        let peak = fma_peak(true).gflops;
        let mut shares = Vec::with_capacity(runs);
        for _ in 0..runs {
            let t = Instant::now();
            model.logits_at(&features, level)?;
            shares.push(100.0 * rows * flops / t.elapsed().as_secs_f64() / 1e9 / peak);
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
    }
    Ok(())
}
