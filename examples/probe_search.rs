//! Where a coarse-to-fine search's time goes: runs one search (start level, keep, coarse
//! precision from the arguments) to level 5 on a few held-out renders of a bundle, repeatedly,
//! and prints its p50; run it under `perf record -g` for the profile.
//! `cargo run --release --example probe_search [BUNDLE] [START] [KEEP] [f32|bf16] [REPEATS] [TAPER]`
use std::time::Instant;

use alignist::engine::{Engine, EngineConfig, PredictOptions, SearchParams};
use alignist::net::Precision;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let arg = |i: usize, default: &str| args.get(i).cloned().unwrap_or_else(|| default.into());
    let path = std::path::PathBuf::from(arg(1, "models/symsol1"));
    let search = SearchParams {
        start_level: arg(2, "2").parse()?,
        keep: arg(3, "512").parse()?,
        keep_mass: None,
        keep_taper: arg(6, "1").parse()?,
        coarse_precision: arg(4, "bf16")
            .parse::<Precision>()
            .map_err(anyhow::Error::msg)?,
    };
    let repeats: usize = arg(5, "20").parse()?;
    let bundle = alignist::bundle::model::ModelBundle::load(&path)?;
    let images = bundle
        .renders(2)
        .eval_images(bundle.manifest.network.image_size, 2, 7);
    let model = Engine::load_model(&path, EngineConfig::default())?;
    let options = PredictOptions {
        top_k: 10,
        level: Some(5),
        mode_angle_deg: None,
    };
    let mut times = Vec::new();
    for _ in 0..repeats {
        for im in &images {
            let t = Instant::now();
            let f = model.features(&[&im.rgb]);
            model.predict_searching(&f, &options, &search, &[None])?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    times.sort_by(f64::total_cmp);
    println!(
        "{search:?}: p50 {:.1} ms over {} calls",
        times[times.len() / 2],
        times.len()
    );
    Ok(())
}
