//! What the load-time calibration costs and chooses on this CPU: loads a bundle once without
//! calibrating, then runs the calibration (engine/calibrate.rs) with the server's defaults a
//! number of times and prints each run's time, where it went, and the search chosen; the first
//! run is the one a server start pays (its caches cold).
//! `cargo run --release --example probe_calibration [BUNDLE] [RUNS]`
use alignist::bundle::study::SearchStudy;
use alignist::engine::calibrate::{DEFAULT_SEARCH_BUDGET_MS, calibrate};
use alignist::engine::{Engine, EngineConfig};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let path = std::path::PathBuf::from(args.get(1).map_or("models/symsol1", |s| s.as_str()));
    let runs: usize = args.get(2).map_or(Ok(10), |s| s.parse())?;
    let config = EngineConfig {
        search_budget_ms: None,
        ..EngineConfig::default()
    };
    let model = Engine::load_model(&path, config)?;
    let study = SearchStudy::load(&path)?;
    let mut took = Vec::new();
    for run in 0..runs {
        let c = calibrate(
            &model,
            study.as_ref(),
            &config.search(),
            config.search_agreement,
            DEFAULT_SEARCH_BUDGET_MS,
            config.search_default_level,
        )?;
        println!(
            "run {run}: {:.1} ms ({}); chose {} of {} eligible, predicted {:.1} ms, measured {:.1} ms",
            c.took_ms, c.spent, c.chosen, c.eligible, c.predicted_ms, c.measured_ms
        );
        took.push(c.took_ms);
    }
    took.sort_by(f64::total_cmp);
    println!(
        "calibration time over {runs} runs: min {:.1} ms, median {:.1} ms, max {:.1} ms; kernels {}",
        took[0],
        took[took.len() / 2],
        took[took.len() - 1],
        model.kernel_paths()
    );
    Ok(())
}
