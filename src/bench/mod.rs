//! The performance figures of `alignist-train bench`, measured in one run on one bundle: the
//! head library's matmul peak, full-grid head throughput against it and against numpy, the
//! study of the coarse-to-fine search against the exhaustive level-5 argmax, encoder
//! throughput, and gRPC against in-process calls. Figures are printed, not asserted. This layer
//! sits above the engine, the transport and the client (it uses all three).

pub mod depth;
pub mod peak;
pub mod search;

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use rayon::prelude::*;

use crate::engine::{Engine, EngineConfig, ImageRequest, Model, PredictOptions};
use crate::net::Precision;
use crate::serve::BatchConfig;
use crate::serve::proto::{ImageInput, PredictRequest};
use crate::serve::server::{ServerConfig, run};
use crate::so3::metrics::quantile;

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

/// The heads' library GEMM (`dense::gemm`: the `gemm` crate, or matrixmultiply when the kernels
/// are capped to `kernels`) at its best: a 4096×256 · 256×256 f32 product in row tiles of
/// `tile` rows, one tile per task over the cores, as the head runs its layers; GFLOP/s, best
/// of 20.
pub fn matmul_peak_gflops(kernels: crate::net::Kernels, tile: usize) -> f64 {
    let (m, k, n) = (4096usize, 256usize, 256usize);
    let a: Vec<f32> = (0..m * k)
        .map(|i| ((i * 7919) % 1000) as f32 / 1e3)
        .collect();
    let b: Vec<f32> = (0..k * n)
        .map(|i| ((i * 104_729) % 1000) as f32 / 1e3)
        .collect();
    let mut c = vec![0f32; m * n];
    let s = best_of(20, || {
        c.par_chunks_mut(tile * n)
            .zip(a.par_chunks(tile * k))
            .for_each(|(c, a)| {
                let rows = a.len() / k;
                crate::net::dense::gemm(
                    kernels,
                    [rows, k, n],
                    crate::net::dense::Strided::rows(a, k),
                    crate::net::dense::Strided::rows(&b, n),
                    0.0,
                    c,
                );
            });
    });
    2.0 * (m * k * n) as f64 / s / 1e9
}

/// Runs every measurement on the bundle at `bundle` with rendered RGB8 crops of its input size
/// (several objects, for the search study; `objects[i]` names crop `i`'s) and prints the
/// figures.
pub fn bench(
    bundle: &Path,
    crops: &[Vec<u8>],
    objects: &[String],
    write_study: Option<u64>,
) -> anyhow::Result<()> {
    anyhow::ensure!(!crops.is_empty(), "the bench needs at least one image");
    anyhow::ensure!(
        objects.len() == crops.len(),
        "{} object names for {} crops",
        objects.len(),
        crops.len()
    );
    let model = Arc::new(Engine::load_model(bundle, EngineConfig::served())?);
    let size = model.input_size();
    println!(
        "bundle {} (input {size}², head {}×{}), {} threads, {} images",
        bundle.display(),
        model.network_config().hidden,
        model.network_config().layers,
        rayon::current_num_threads(),
        crops.len()
    );
    let peaks = print_peaks(&model);
    full_grid_figures(&model, &crops[0], bundle, &peaks)?;
    // The coarse-to-fine search against the exhaustive level-5 argmax.
    let (figures, references) =
        search::study(&model, crops, &search::candidates(), (STUDY_LEVEL, 10), &[])?;
    search::print(&figures, &model.config().search(), objects);
    if let Some(seed) = write_study {
        let command = std::env::args().collect::<Vec<_>>().join(" ");
        let references = search::study_references(crops, &references);
        let network = network_sha256(&model);
        search::record(&figures, STUDY_LEVEL, seed, command, network, references).save(bundle)?;
        println!(
            "search study written to {}",
            bundle
                .join(crate::bundle::study::SEARCH_STUDY_FILE)
                .display()
        );
    }
    let in_process_p50 = top_k_latency(&model, crops)?;
    encoder_rates(&model, crops);
    let mut png = Vec::new();
    image::RgbImage::from_raw(size, size, crops[0].clone())
        .ok_or_else(|| anyhow::anyhow!("crop size"))?
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)?;
    grpc_vs_in_process(model, bundle, &png, in_process_p50)
}

/// The level a search study compares with exhaustively.
const STUDY_LEVEL: u8 = 5;

/// The sha256 of the network `model` loaded, from its manifest.
fn network_sha256(model: &Model) -> Option<String> {
    let files = &model.manifest.files;
    files
        .get(crate::bundle::model::NETWORK_FILE)
        .map(|entry| entry.sha256.clone())
}

/// Adds to the bundle's search study the candidate searches it does not hold, on the study's own
/// images (`render(seed, images)` renders them again: each crop with its object's name, from
/// the study's seed, `None` in studies written before it), and writes it back: each image's
/// exhaustive argmax is read from the study where it holds the same image, so only the new
/// searches run. Refused when the study measured another network.
pub fn extend_study(
    bundle: &Path,
    render: impl FnOnce(Option<u64>, usize) -> anyhow::Result<(Vec<String>, Vec<Vec<u8>>)>,
) -> anyhow::Result<()> {
    use crate::bundle::study::{SEARCH_STUDY_FILE, SearchStudy};
    let file = bundle.join(SEARCH_STUDY_FILE);
    let mut study = SearchStudy::load(bundle)?.ok_or_else(|| {
        anyhow::anyhow!(
            "{}: no search study to extend (write one with --write-study)",
            file.display()
        )
    })?;
    let (_, entry) = crate::bundle::model::ModelBundle::load_weights_entry(bundle)?;
    let network = entry.sha256;
    if let Some(studied) = &study.network_sha256 {
        anyhow::ensure!(
            *studied == network,
            "{}: network_sha256: the study measured network {studied}, the bundle holds \
             {network}: write the study again with --write-study",
            file.display()
        );
    }
    let new = search::unstudied(&study, &search::candidates());
    if new.is_empty() {
        println!(
            "{}: every candidate search is studied already",
            file.display()
        );
        return Ok(());
    }
    let (objects, crops) = render(study.seed, study.images)?;
    anyhow::ensure!(
        crops.len() == study.images && objects.len() == crops.len(),
        "{}: images: the study has {}, {} were rendered again",
        file.display(),
        study.images,
        crops.len()
    );
    let crops = &crops[..];
    let model = Engine::load_model(bundle, EngineConfig::default())?;
    let known = search::known_references(&study, crops);
    println!(
        "{} searches to add to {}, on its {} images (seed {}); {} of them with their exhaustive \
         argmax from the study",
        new.len(),
        file.display(),
        crops.len(),
        study.seed.map_or("unknown".into(), |s| s.to_string()),
        known.iter().filter(|k| k.is_some()).count()
    );
    let (figures, references) = search::study(&model, crops, &new, (study.level, 10), &known)?;
    search::print(&figures, &model.config().search(), &objects);
    study
        .searches
        .extend(figures.iter().map(search::studied_search));
    study.references = search::study_references(crops, &references);
    study.network_sha256 = Some(network);
    study
        .extended_by
        .push(std::env::args().collect::<Vec<_>>().join(" "));
    study.save(bundle)?;
    println!("{} searches added to {}", figures.len(), file.display());
    Ok(())
}

/// The probed peaks the head's rates are compared with, in GFLOP/s.
struct Peaks {
    /// The widest f32 FMA the kernels may use (256-bit under `--kernels avx2` or `portable`).
    f32: f64,
    /// `VDPBF16PS`, `VFMADD231PH` and `VPDPBUSD`, where the core has them.
    bf16: Option<f64>,
    f16: Option<f64>,
    i8: Option<f64>,
    /// `VPMADDWD` with its `VPADDD`, 256-bit, where the core has AVX2.
    i8_pairs: Option<f64>,
    /// `TDPBF16PS` and `TDPBUSD` on AMX tiles, where the core has them and the OS grants them.
    amx: Option<f64>,
    amx_i8: Option<f64>,
}

/// Prints the matmul peak of the library GEMM, the FMA peaks of this CPU and the load-time
/// calibration; returns the peaks.
fn print_peaks(model: &Model) -> Peaks {
    let kernels = model.config().kernels;
    let library = matmul_peak_gflops(kernels, crate::net::tiles::tile_rows());
    println!(
        "matmul peak of the library GEMM, {} (4096×256·256×256 f32 in tiles of {} rows over the cores): {library:.1} GFLOP/s",
        crate::net::dense::library_name(kernels),
        crate::net::tiles::tile_rows()
    );
    let widest = peak::fma_peak(true);
    let narrow = peak::fma_peak(false);
    println!(
        "FMA peak of this CPU (probe): {}-bit {:.1} GFLOP/s, 256-bit {:.1} GFLOP/s; kernels: {}",
        widest.bits,
        widest.gflops,
        narrow.gflops,
        model.kernel_paths()
    );
    let (f16, bf16, i8) = (
        peak::reduced_peak(peak::ReducedOp::F16Fma),
        peak::reduced_peak(peak::ReducedOp::Bf16Dot),
        peak::reduced_peak(peak::ReducedOp::I8Dot),
    );
    let (amx, amx_i8) = (peak::amx_peak(), peak::amx_int8_peak());
    let i8_pairs = peak::reduced_peak(peak::ReducedOp::I8Pairs);
    let shown = |g: Option<f64>| g.map_or("not on this CPU".into(), |g| format!("{g:.1} GFLOP/s"));
    println!(
        "reduced-precision peaks (probe, 512-bit): f16 FMA (VFMADD231PH) {}, bfloat16 dot (VDPBF16PS) {}, int8 dot (VPDPBUSD) {}; 256-bit int8 pairs (VPMADDWD + VPADDD) {}; AMX tiles: bfloat16 (TDPBF16PS) {}, int8 (TDPBUSD) {}",
        shown(f16),
        shown(bf16),
        shown(i8).replace("GFLOP/s", "GOP/s"),
        shown(i8_pairs).replace("GFLOP/s", "GOP/s"),
        shown(amx),
        shown(amx_i8).replace("GFLOP/s", "GOP/s")
    );
    let peaks = Peaks {
        f32: if kernels.allows_avx512() {
            widest.gflops
        } else {
            narrow.gflops
        },
        bf16,
        f16,
        i8,
        i8_pairs,
        amx,
        amx_i8,
    };
    match model.calibration() {
        Some(c) => println!("calibration {c}"),
        None => println!("calibration: none"),
    }
    peaks
}

/// Rounds of a head's rate each beside an FMA probe of its own ([`besides_probe`]).
const ROUNDS: usize = 5;

/// A head's rates, each measured right after an FMA probe, in rounds: on a shared host the
/// machine's speed drifts between a probe at the start and a head measured a minute later, and a
/// rate measured beside its own probe is a fraction of the peak of that moment.
struct ProbedRounds {
    /// The best rate of the rounds (GFLOP/s).
    best: f64,
    /// Each round's rate over its probe's, sorted.
    shares: Vec<f64>,
}

impl ProbedRounds {
    fn describe(&self) -> String {
        let (lo, hi) = (self.shares[0], self.shares[self.shares.len() - 1]);
        format!(
            "{:.0} % of the probe run beside it (median of {} rounds, {:.0}–{:.0} %)",
            100.0 * quantile(&self.shares, 0.5),
            self.shares.len(),
            100.0 * lo,
            100.0 * hi
        )
    }
}

/// `rounds` rounds of the FMA probe (512-bit where `widest`, else 256-bit) then one run of
/// `rate` (its GFLOP/s), after one untimed run of `rate`.
fn besides_probe(rounds: usize, widest: bool, mut rate: impl FnMut() -> f64) -> ProbedRounds {
    let _ = rate();
    let mut best = 0f64;
    let mut shares: Vec<f64> = (0..rounds)
        .map(|_| {
            let probe = peak::fma_peak(widest).gflops;
            let r = rate();
            best = best.max(r);
            r / probe
        })
        .collect();
    shares.sort_by(f64::total_cmp);
    ProbedRounds { best, shares }
}

/// Prints the full grids of levels 3 and 4 in f32 (against the FMA `peak` and numpy), in
/// bfloat16, in f16 and in 8-bit integers.
fn full_grid_figures(
    model: &Model,
    crop: &[u8],
    bundle: &Path,
    peaks: &Peaks,
) -> anyhow::Result<()> {
    let one = model.features(&[crop])?.swap_remove(0);
    let flops = head_flops_per_rotation(model);
    let widest = model.config().kernels.allows_avx512();
    let mut ours_ms = Vec::new();
    for level in [3u8, 4] {
        let grid_len = model.grid(level).map_or(0, |g| g.len());
        let rounds = besides_probe(ROUNDS, widest, || {
            let t = Instant::now();
            let _ = model.distribution(&one, level, None);
            grid_len as f64 * flops / 1e9 / t.elapsed().as_secs_f64()
        });
        let gflops = rounds.best;
        let s = grid_len as f64 * flops / 1e9 / gflops;
        ours_ms.push((level, s * 1e3));
        println!(
            "full grid level {level} ({grid_len} rotations): {:.1} ms, {:.2} M rotations/s, {gflops:.1} GFLOP/s, head: {:.0} % of the FMA peak above; {}{}",
            s * 1e3,
            grid_len as f64 / s / 1e6,
            100.0 * gflops / peaks.f32,
            rounds.describe(),
            if widest {
                ""
            } else {
                " (256-bit: the kernels are capped)"
            }
        );
    }
    numpy_ratio(bundle, &ours_ms);
    // The same grids in bfloat16, f16 and i8 (the coarse levels of the search).
    // The probed peaks are 512-bit: a capped run's 256-bit kernels are not compared with them.
    let wide = model.config().kernels.allows_avx512();
    let bf16_peak = if model.kernel_name(Precision::Bf16) == crate::net::amx::KERNEL_NAME {
        peaks.amx
    } else {
        peaks.bf16
    };
    // The pairs kernel is 256-bit: its probe is, too.
    let pairs = model.kernel_name(Precision::I8) == crate::net::i8::KERNEL_NAME_PAIRS;
    let i8_peak = match model.kernel_name(Precision::I8) {
        crate::net::amx::KERNEL_NAME_I8 => peaks.amx_i8,
        _ if pairs => peaks.i8_pairs,
        _ => peaks.i8,
    };
    for (precision, peak) in [
        (Precision::Bf16, bf16_peak),
        (Precision::F16, peaks.f16),
        (Precision::I8, i8_peak),
    ] {
        for &(level, f32_ms) in &ours_ms {
            let grid_len = model.grid(level).map_or(0, |g| g.len());
            let s = best_of(3, || {
                let _ = model.logits_in(precision, &one, level);
            });
            let gflops = grid_len as f64 / s * flops / 1e9;
            let against_peak =
                model.native(precision) && (wide || pairs && precision == Precision::I8);
            println!(
                "full grid level {level} in {precision} ({}): {:.1} ms, {:.2} M rotations/s, {gflops:.1} {}{}, {:.2}× the f32 head",
                model.kernel_name(precision),
                s * 1e3,
                grid_len as f64 / s / 1e6,
                // Integer multiply-adds are operations, not floating-point ones.
                if precision == Precision::I8 {
                    "GOP/s"
                } else {
                    "GFLOP/s"
                },
                match peak.filter(|_| against_peak) {
                    Some(p) => format!(" ({:.0} % of its instruction's peak)", 100.0 * gflops / p),
                    None => String::new(),
                },
                f32_ms / (s * 1e3)
            );
        }
    }
    Ok(())
}

/// Prints and returns the p50 of a top-10 search to level 5, encoder included, over 30 calls.
fn top_k_latency(model: &Model, crops: &[Vec<u8>]) -> anyhow::Result<f64> {
    let options = PredictOptions {
        top_k: 10,
        level: Some(5),
        mode_angle_deg: None,
        ..Default::default()
    };
    let mut lat: Vec<f64> = Vec::new();
    for i in 0..30 {
        let crop = &crops[i % crops.len()];
        let t = Instant::now();
        let f = model.features(&[crop])?.swap_remove(0);
        model.predict(&f, &options, None)?;
        lat.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let in_process_p50 = quantile(&lat, 0.5);
    println!(
        "top-k p50: {in_process_p50:.1} ms (top-10 to level 5 with the default search, encoder included; p99 {:.1} ms)",
        quantile(&lat, 0.99)
    );
    Ok(in_process_p50)
}

/// Prints the encoder's images per second at batch 1 and at the server's batch.
fn encoder_rates(model: &Model, crops: &[Vec<u8>]) {
    for batch in [1usize, BatchConfig::default().max_batch] {
        let refs: Vec<&[u8]> = (0..batch)
            .map(|i| crops[i % crops.len()].as_slice())
            .collect();
        let s = best_of(5, || {
            let _ = model.features(&refs);
        });
        println!("encoder at batch {batch}: {:.1} images/s", batch as f64 / s);
    }
}

/// Runs the numpy reference (`benches/reference_head.py`) on the same bundle and grids and
/// prints the ratio of its time to ours, when python3 with numpy is present.
fn numpy_ratio(bundle: &Path, ours_ms: &[(u8, f64)]) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/reference_head.py");
    let dir = std::env::temp_dir().join(format!("alignist-bench-grids-{}", std::process::id()));
    let run = || -> anyhow::Result<Vec<String>> {
        std::fs::create_dir_all(&dir)?;
        let mut lines = Vec::new();
        for &(level, ours) in ours_ms {
            let csv = dir.join(format!("grid{level}.csv"));
            let grid = crate::so3::GridLevel::new(level)?;
            let mut w = std::io::BufWriter::new(std::fs::File::create(&csv)?);
            crate::so3::grid::write_centres_csv(&grid, &mut w, |_| {})?;
            drop(w);
            let out = std::process::Command::new("python3")
                .arg(&script)
                .arg(bundle)
                .arg(&csv)
                .output()?;
            anyhow::ensure!(
                out.status.success(),
                "{}",
                String::from_utf8_lossy(&out.stderr)
                    .lines()
                    .last()
                    .unwrap_or("failed")
            );
            let text = String::from_utf8_lossy(&out.stdout).to_string();
            let ms: f64 = text
                .split(": ")
                .nth(1)
                .and_then(|t| t.split(" ms").next())
                .and_then(|t| t.trim().parse().ok())
                .ok_or_else(|| anyhow::anyhow!("unreadable numpy output: {text}"))?;
            lines.push(format!(
                "level {level}: {} numpy ratio: {:.2} (numpy {ms:.1} ms / ours {ours:.1} ms)",
                text.trim(),
                ms / ours
            ));
        }
        Ok(lines)
    };
    match run() {
        Ok(lines) => lines.iter().for_each(|l| println!("{l}")),
        Err(e) => println!("numpy reference not run ({e})"),
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Predict throughput at concurrency 8: in-process engine calls against gRPC calls to a server on
/// loopback with the same bundle and request (search to level 3, top-5); between them, the
/// single-call latency and a streamed level-4 distribution over gRPC.
fn grpc_vs_in_process(
    model: Arc<Model>,
    bundle: &Path,
    png: &[u8],
    in_process_p50: f64,
) -> anyhow::Result<()> {
    let (concurrency, requests) = (8, 96);
    let in_process = in_process_throughput(&model, png, concurrency, requests)?;
    // The server runs the search the in-process model runs (calibrated once, here).
    let engine = EngineConfig {
        search_budget_ms: None,
        ..*model.config()
    };
    drop(model);
    // The same bundle served over gRPC on an ephemeral loopback port.
    let dir = tempfile_dir()?;
    let link = dir.join(bundle.file_name().unwrap_or_default());
    crate::bundle::model::copy_dir(bundle, &link)?;
    let runtime = tokio::runtime::Runtime::new()?;
    let grpc = runtime.block_on(async {
        let (channel, stop, server) = serve_for_bench(&dir, engine).await?;
        let figures = grpc_figures(channel, png, concurrency, requests, in_process_p50).await;
        let _ = stop.send(());
        let _ = server.await;
        figures
    })?;
    let _ = std::fs::remove_dir_all(&dir);
    println!(
        "Predict (level 3, top-5) at concurrency {concurrency}: in-process {in_process:.1} \
         calls/s, gRPC {grpc:.1} calls/s, ratio {:.2}",
        grpc / in_process
    );
    Ok(())
}

/// Calls per second of `requests` in-process predictions (prepare, encode, search to level 3,
/// top-5) from `concurrency` threads.
fn in_process_throughput(
    model: &Model,
    png: &[u8],
    concurrency: usize,
    requests: usize,
) -> anyhow::Result<f64> {
    let options = PredictOptions {
        top_k: 5,
        level: Some(3),
        mode_angle_deg: None,
        ..Default::default()
    };
    let t = Instant::now();
    std::thread::scope(|scope| {
        let workers: Vec<_> = (0..concurrency)
            .map(|w| {
                let options = &options;
                scope.spawn(move || -> Result<(), crate::engine::EngineError> {
                    for _ in (w..requests).step_by(concurrency) {
                        let crop = model.prepare(&ImageRequest {
                            data: png,
                            raw_size: None,
                            crop: None,
                        })?;
                        let f = model.features(&[&crop])?.swap_remove(0);
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
    Ok(requests as f64 / t.elapsed().as_secs_f64())
}

/// A server over the bundles in `models` with `engine`, on an ephemeral loopback port, once it serves: a channel
/// to it, its stop signal and its task.
async fn serve_for_bench(
    models: &Path,
    engine: EngineConfig,
) -> anyhow::Result<(
    crate::client::Connection,
    tokio::sync::oneshot::Sender<()>,
    tokio::task::JoinHandle<Result<(), crate::serve::server::ServeError>>,
)> {
    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    let listen: std::net::SocketAddr = format!("127.0.0.1:{port}").parse()?;
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let config = ServerConfig {
        drain_timeout: Duration::from_secs(5),
        engine,
        ..ServerConfig::new(models.to_path_buf(), listen)
    };
    let server = tokio::spawn(run(config, async {
        let _ = stopped.await;
    }));
    let url = format!("http://{listen}");
    for _ in 0..600 {
        if let Ok(c) = crate::client::connect(&url, Duration::from_secs(120)).await {
            let health = crate::client::health(c.clone(), "alignist.v1.Alignist").await;
            if health.ok().as_deref() == Some("Serving") {
                return Ok((c, stop, server));
            }
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    anyhow::bail!("bench server never served")
}

/// Over `channel`: prints the single-call p50 beside the in-process one and the streamed level-4
/// distribution's latency; returns the calls per second of `requests` Predicts (level 3, top-5)
/// at `concurrency`.
async fn grpc_figures(
    channel: crate::client::Connection,
    png: &[u8],
    concurrency: usize,
    requests: usize,
    in_process_p50: f64,
) -> anyhow::Result<f64> {
    use crate::client::load::run_load;
    let request = PredictRequest {
        image: Some(ImageInput {
            data: png.to_vec(),
            ..Default::default()
        }),
        top_k: 5,
        level: 3,
        ..Default::default()
    };
    let minute = Duration::from_secs(60);
    // Warm-up, then the measured run.
    run_load(vec![channel.clone()], request.clone(), 16, 8, minute).await?;
    let report = run_load(
        vec![channel.clone()],
        request.clone(),
        requests,
        concurrency,
        2 * minute,
    )
    .await?;
    // Latency of single calls (nothing else in flight) on the served model.
    let default_predict = PredictRequest {
        top_k: 10,
        level: 0,
        ..request.clone()
    };
    let single = run_load(vec![channel.clone()], default_predict, 30, 1, 2 * minute).await?;
    println!(
        "single call p50: gRPC {:.1} ms, in-process {in_process_p50:.1} ms (top-10 to level 5, \
         one call at a time; gRPC p99 {:.1} ms)",
        single.p50_ms, single.p99_ms
    );
    let mut dist_ms = Vec::new();
    for _ in 0..8 {
        let t = Instant::now();
        let distribution = crate::serve::proto::DistributionRequest {
            image: request.image.clone(),
            level: 4,
            ..Default::default()
        };
        let (_, probs, _) = crate::client::distribution(channel.clone(), distribution).await?;
        anyhow::ensure!(
            probs.len() == 294_912,
            "level-4 distribution has {} cells",
            probs.len()
        );
        dist_ms.push(t.elapsed().as_secs_f64() * 1e3);
    }
    println!(
        "gRPC PredictDistribution level 4 (294912 cells, streamed): p50 {:.0} ms, p99 {:.0} ms",
        quantile(&dist_ms, 0.5),
        quantile(&dist_ms, 0.99)
    );
    if report.failures() + single.failures() > 0 {
        anyhow::bail!("gRPC bench calls failed: {report}");
    }
    Ok(report.requests_per_second)
}

fn tempfile_dir() -> std::io::Result<std::path::PathBuf> {
    let dir = std::env::temp_dir().join(format!("alignist-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    Ok(dir)
}
