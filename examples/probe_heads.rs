//! Predict throughput of single searches (`Model::predict`) on 1, 2 and 8 threads against lockstep
//! batches (`Model::predict_many`), level 3, top-5, on the shipped model: the measurement behind
//! the head stage's one-search-per-call design (`src/serve/heads.rs`).
//! `cargo run --release --example probe_heads`
use alignist::engine::{Engine, EngineConfig, PredictOptions};
use std::sync::Arc;
use std::time::Instant;
fn main() {
    let model = Arc::new(
        Engine::load_model(
            std::path::Path::new("models/symsol1"),
            EngineConfig::default(),
        )
        .unwrap(),
    );
    let crop = vec![128u8; (model.input_size() * model.input_size() * 3) as usize];
    let f1 = model
        .features(&[&crop])
        .expect("crops of the input side")
        .swap_remove(0);
    let options = PredictOptions {
        top_k: 5,
        level: Some(3),
        mode_angle_deg: None,
        ..Default::default()
    };
    let n = 96;
    for threads in [1usize, 2, 8] {
        let t = Instant::now();
        std::thread::scope(|s| {
            for w in 0..threads {
                let model = model.clone();
                let f1 = f1.clone();
                let options = options.clone();
                s.spawn(move || {
                    for _ in (w..n).step_by(threads) {
                        model.predict(&f1, &options, None).unwrap();
                    }
                });
            }
        });
        println!(
            "predict, {threads} threads: {:.1} calls/s",
            n as f64 / t.elapsed().as_secs_f64()
        );
    }
    for (threads, b) in [(1usize, 8usize), (2, 4), (2, 8), (1, 2)] {
        let rows: Vec<Vec<f32>> = vec![f1.clone(); b];
        let t = Instant::now();
        std::thread::scope(|s| {
            for w in 0..threads {
                let model = model.clone();
                let rows = rows.clone();
                let options = options.clone();
                s.spawn(move || {
                    for _ in (w..n / b).step_by(threads) {
                        let depth = vec![None; b];
                        model.predict_many(&rows, &options, &depth).unwrap();
                    }
                });
            }
        });
        println!(
            "predict_many b={b}, {threads} threads: {:.1} calls/s",
            n as f64 / t.elapsed().as_secs_f64()
        );
    }
}
