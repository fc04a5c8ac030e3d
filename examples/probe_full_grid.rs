//! The f32 full grid as the bench times it (`Model::distribution`), beside the FMA peak probed
//! just before and after, repeated: where the head's "% of peak" comes from, and a target for
//! `perf record`. `cargo run --release --example probe_full_grid [BUNDLE] [LEVEL] [REPEATS]`
use std::time::Instant;

use alignist::bench::peak::fma_peak;
use alignist::engine::{Engine, EngineConfig};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let bundle = args.get(1).map_or("models/symsol1", String::as_str);
    let level: u8 = args.get(2).map_or(Ok(4), |s| s.parse())?;
    let repeats: usize = args.get(3).map_or(Ok(5), |s| s.parse())?;
    let model = Engine::load_model(std::path::Path::new(bundle), EngineConfig::default())?;
    let crop = vec![128u8; (model.input_size() * model.input_size() * 3) as usize];
    let features = model.features(&[&crop])?.swap_remove(0);
    let flops = alignist::bench::head_flops_per_rotation(&model);
    let rows = model.grid(level).map_or(0, |g| g.len()) as f64;
    for _ in 0..repeats {
        let before = fma_peak(true).gflops;
        let t = Instant::now();
        let d = model.distribution(&features, level, None)?;
        let s = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let logits = model.logits_at(&features, level)?;
        let head_s = t.elapsed().as_secs_f64();
        let after = fma_peak(true).gflops;
        let gflops = rows * flops / s / 1e9;
        println!(
            "level {level}: distribution {:.1} ms, {gflops:.1} GFLOP/s; peak before {before:.1}, after {after:.1}: {:.0} % of their mean ({} cells); the head's logits alone {:.1} ms ({:.0} %, {} cells)",
            s * 1e3,
            200.0 * gflops / (before + after),
            d.probability.len(),
            head_s * 1e3,
            200.0 * rows * flops / head_s / 1e9 / (before + after),
            logits.len(),
        );
    }
    Ok(())
}
