//! The performance figures of `alignist-train bench`, measured in one run on one bundle: the
//! backend's f32 matmul peak, full-grid head throughput against it, coarse-to-fine latency,
//! encoder throughput, and gRPC against in-process throughput. Figures are printed, not asserted.

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::BatchConfig;
use super::proto::{ImageInput, PredictRequest};
use super::server::{ServerConfig, run};
use crate::client::load::quantile;
use crate::engine::{Engine, EngineConfig, ImageRequest, Model, PredictOptions};

/// Best-of-`reps` seconds of `f`.
fn best_of(reps: usize, mut f: impl FnMut()) -> f64 {
    f();
    (0..reps)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::MAX, f64::min)
}

/// FLOPs of the head per rotation once the rotation half of the first layer is precomputed.
pub fn head_flops_per_rotation(model: &Model) -> f64 {
    let c = model.network_config();
    let h = c.hidden as f64;
    let per_branch = (c.layers.saturating_sub(1)) as f64 * 2.0 * h * h + 2.0 * h;
    2.0 * per_branch
}

/// Runs every measurement on the bundle at `bundle` and prints the figures.
pub fn bench(bundle: &Path, images: &[Vec<u8>]) -> anyhow::Result<()> {
    let engine_config = EngineConfig::default();
    let model = Arc::new(Engine::load_model(bundle, engine_config)?);
    let size = model.input_size();
    println!(
        "bundle {} (input {size}², head {}×{}), {} threads",
        bundle.display(),
        model.network_config().hidden,
        model.network_config().layers,
        rayon::current_num_threads()
    );
    // The engine runs the head on the dense backend and the encoder on the convolution one.
    let dense = crate::backend::device_for(crate::backend::Workload::Dense);
    let conv = crate::backend::device_for(crate::backend::Workload::Conv);
    let peak = crate::backend::matmul_gflops(&dense, 4096, 256, 256);
    println!(
        "matmul 4096×256·256×256 f32: {peak:.1} GFLOP/s on the head's backend ({}); {:.1} GFLOP/s on the encoder's ({})",
        crate::backend::backend_for(crate::backend::Workload::Dense),
        crate::backend::matmul_gflops(&conv, 4096, 256, 256),
        crate::backend::backend_for(crate::backend::Workload::Conv)
    );
    let crops: Vec<Vec<u8>> = images
        .iter()
        .map(|png| {
            model.prepare(&ImageRequest {
                data: png,
                raw_size: None,
                crop: None,
            })
        })
        .collect::<Result<_, _>>()?;
    let one = model.features(&[&crops[0]]);
    let flops = head_flops_per_rotation(&model);
    for level in [3u8, 4] {
        let grid_len = model.grid(level).map_or(0, |g| g.len());
        let s = best_of(3, || {
            let _ = model.distribution(&one, level, None);
        });
        let rate = grid_len as f64 / s;
        let gflops = rate * flops / 1e9;
        println!(
            "full grid level {level} ({grid_len} rotations): {:.1} ms, {:.2} M rotations/s, head {gflops:.1} GFLOP/s = {:.0} % of the matmul peak",
            s * 1e3,
            rate / 1e6,
            100.0 * gflops / peak
        );
    }
    let options = PredictOptions {
        top_k: 10,
        level: Some(5),
        mode_angle_deg: None,
    };
    let mut lat: Vec<f64> = Vec::new();
    for i in 0..30 {
        let crop = &crops[i % crops.len()];
        let t = Instant::now();
        let f = model.features(&[crop]);
        model.predict(&f, &options, None)?;
        lat.push(t.elapsed().as_secs_f64() * 1e3);
    }
    println!(
        "coarse-to-fine top-10 to level 5 (keep {}), encoder included: p50 {:.1} ms, p99 {:.1} ms",
        engine_config.keep,
        quantile(&lat, 0.5),
        quantile(&lat, 0.99)
    );
    for batch in [1usize, BatchConfig::default().max_batch] {
        let refs: Vec<&[u8]> = (0..batch)
            .map(|i| crops[i % crops.len()].as_slice())
            .collect();
        let s = best_of(5, || {
            let _ = model.features(&refs).into_data();
        });
        println!("encoder at batch {batch}: {:.1} images/s", batch as f64 / s);
    }
    grpc_vs_in_process(model, bundle, &images[0])
}

/// Predict throughput at concurrency 8: in-process engine calls against gRPC calls to a server on
/// loopback with the same bundle and request (search to level 3, top-5).
fn grpc_vs_in_process(model: Arc<Model>, bundle: &Path, png: &[u8]) -> anyhow::Result<()> {
    let concurrency = 8;
    let requests = 96;
    let options = PredictOptions {
        top_k: 5,
        level: Some(3),
        mode_angle_deg: None,
    };
    let t = Instant::now();
    std::thread::scope(|scope| {
        let workers: Vec<_> = (0..concurrency)
            .map(|w| {
                let (model, options) = (&model, &options);
                scope.spawn(move || -> Result<(), crate::engine::EngineError> {
                    for _ in (w..requests).step_by(concurrency) {
                        let crop = model.prepare(&ImageRequest {
                            data: png,
                            raw_size: None,
                            crop: None,
                        })?;
                        let f = model.features(&[&crop]);
                        model.predict(&f, options, None)?;
                    }
                    Ok(())
                })
            })
            .collect();
        workers.into_iter().try_for_each(|w| {
            w.join()
                .map_err(|_| anyhow::anyhow!("bench worker panicked"))?
                .map_err(anyhow::Error::from)
        })
    })?;
    let in_process = requests as f64 / t.elapsed().as_secs_f64();
    drop(model);

    // The same bundle served over gRPC on an ephemeral loopback port.
    let dir = tempfile_dir()?;
    let link = dir.join(bundle.file_name().unwrap_or_default());
    crate::bundle::model::copy_dir(bundle, &link)?;
    let runtime = tokio::runtime::Runtime::new()?;
    let grpc = runtime.block_on(async {
        let port = std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port();
        let listen: std::net::SocketAddr = format!("127.0.0.1:{port}").parse()?;
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let config = ServerConfig {
            models: dir.clone(),
            listen,
            metrics_listen: None,
            engine: EngineConfig::default(),
            batch: BatchConfig::default(),
            drain_timeout: Duration::from_secs(5),
            max_concurrent_streams: 1024,
            reload_interval: None,
            max_connection_age: None,
            admission: Default::default(),
        };
        let server = tokio::spawn(run(config, async {
            let _ = stopped.await;
        }));
        let url = format!("http://{listen}");
        let mut channel = None;
        for _ in 0..600 {
            if let Ok(c) = crate::client::connect(&url, Duration::from_secs(120)).await
                && crate::client::health(c.clone(), "alignist.v1.Alignist").await.ok().as_deref() == Some("Serving")
            {
                channel = Some(c);
                break;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let channel = channel.ok_or_else(|| anyhow::anyhow!("bench server never served"))?;
        let request = PredictRequest {
            image: Some(ImageInput {
                data: png.to_vec(),
                ..Default::default()
            }),
            top_k: 5,
            level: 3,
            ..Default::default()
        };
        // Warm-up, then the measured run.
        crate::client::load::run_load(vec![channel.clone()], request.clone(), 16, 8, Duration::from_secs(60)).await?;
        let report = crate::client::load::run_load(
            vec![channel.clone()],
            request.clone(),
            requests,
            concurrency,
            Duration::from_secs(120),
        )
        .await?;
        // Latency of single calls (nothing else in flight) on the served model.
        let default_predict = PredictRequest {
            top_k: 10,
            level: 0,
            ..request.clone()
        };
        let single = crate::client::load::run_load(
            vec![channel.clone()],
            default_predict,
            30,
            1,
            Duration::from_secs(120),
        )
        .await?;
        println!(
            "gRPC Predict (top-10, search to level 5), one call at a time: p50 {:.1} ms, p99 {:.1} ms",
            single.p50_ms, single.p99_ms
        );
        let mut dist_ms = Vec::new();
        for _ in 0..8 {
            let t = Instant::now();
            let (_, probs, _) = crate::client::distribution(
                channel.clone(),
                super::proto::DistributionRequest {
                    image: request.image.clone(),
                    level: 4,
                    ..Default::default()
                },
            )
            .await?;
            anyhow::ensure!(probs.len() == 294_912, "level-4 distribution has {} cells", probs.len());
            dist_ms.push(t.elapsed().as_secs_f64() * 1e3);
        }
        println!(
            "gRPC PredictDistribution level 4 (294912 cells, streamed): p50 {:.0} ms, p99 {:.0} ms",
            quantile(&dist_ms, 0.5),
            quantile(&dist_ms, 0.99)
        );
        let _ = stop.send(());
        let _ = server.await;
        if report.failures() + single.failures() > 0 {
            anyhow::bail!("gRPC bench calls failed: {report}");
        }
        anyhow::Ok(report.requests_per_second)
    })?;
    let _ = std::fs::remove_dir_all(&dir);
    println!(
        "Predict (level 3, top-5) at concurrency {concurrency}: in-process {in_process:.1} calls/s, gRPC {grpc:.1} calls/s, ratio {:.2}",
        grpc / in_process
    );
    Ok(())
}

fn tempfile_dir() -> std::io::Result<std::path::PathBuf> {
    let dir = std::env::temp_dir().join(format!("alignist-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    Ok(dir)
}
