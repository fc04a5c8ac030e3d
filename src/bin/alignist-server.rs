//! `alignist-server`: serves orientation distributions over gRPC (see `proto/alignist/v1`).

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use alignist::engine::{EngineConfig, ImageLimits, SearchParams};
use alignist::net::{Kernels, Precision};
use alignist::serve::BatchConfig;
use alignist::serve::auth::Token;
use alignist::serve::server::{DEFAULT_MAX_STREAMS, ServerConfig, TlsFiles, run, shutdown_signal};
use alignist::serve::transport::TransportLimits;
use anyhow::{Context, Result, bail};
use clap::Parser;

/// Serves orientation distributions of known objects over gRPC, with health, reflection and
/// Prometheus metrics. A changed models directory (or SIGHUP) reloads the bundles, keeping the
/// old ones if the new ones fail validation. SIGTERM or SIGINT stops accepting calls, drains the
/// ones in flight, and exits 0.
#[derive(Parser)]
#[command(name = "alignist-server", version, about, long_about = None)]
struct Cli {
    /// Directory of model bundles to serve (each subfolder with a manifest.json).
    #[arg(long, env = "ALIGNIST_MODELS", default_value = "models")]
    models: PathBuf,
    /// gRPC listen address (port 0 picks a free port; the bound address is printed).
    #[arg(long, env = "ALIGNIST_LISTEN", default_value = "127.0.0.1:50051")]
    listen: SocketAddr,
    /// Prometheus metrics listen address ("off" to disable).
    #[arg(
        long,
        env = "ALIGNIST_METRICS_LISTEN",
        default_value = "127.0.0.1:9469"
    )]
    metrics_listen: String,
    /// Highest grid level served in full by PredictDistribution.
    #[arg(long, env = "ALIGNIST_MAX_LEVEL", default_value_t = EngineConfig::default().max_full_level)]
    max_level: u8,
    /// Highest level a Predict search may reach (default 5 per call).
    #[arg(long, env = "ALIGNIST_MAX_SEARCH_LEVEL", default_value_t = EngineConfig::default().search_max_level)]
    max_search_level: u8,
    /// Most images per encoder batch.
    #[arg(long, env = "ALIGNIST_MAX_BATCH", default_value_t = BatchConfig::default().max_batch)]
    max_batch: usize,
    /// Longest a request waits for a batch to fill, in milliseconds.
    #[arg(long, env = "ALIGNIST_MAX_DELAY_MS", default_value_t = BatchConfig::default().max_delay.as_millis() as u64)]
    max_delay_ms: u64,
    /// Most requests queued per model before UNAVAILABLE.
    #[arg(long, env = "ALIGNIST_QUEUE", default_value_t = BatchConfig::default().queue_capacity)]
    queue: usize,
    /// Latency budget of the default Predict search (top-10 to level 5, encoder included), in
    /// milliseconds: at load, each model's search is chosen on this CPU among the searches its
    /// bundle's study (`search-study.json`) found to reach --search-agreement, the most agreeing
    /// one predicted within the budget (agreements one studied image apart count as equal, and
    /// among equals the fastest wins; when none fits, the fastest, with a warning).
    /// Setting any --search-* flag below serves that search instead; 0 turns calibration off.
    #[arg(long, env = "ALIGNIST_SEARCH_BUDGET_MS", default_value_t = alignist::engine::calibrate::DEFAULT_SEARCH_BUDGET_MS)]
    search_budget_ms: f64,
    /// Agreement with the exhaustive level-5 argmax, in the bundle's study, that a calibrated
    /// search must have reached (0–1).
    #[arg(long, env = "ALIGNIST_SEARCH_AGREEMENT", default_value_t = EngineConfig::default().search_agreement)]
    search_agreement: f64,
    /// Widest head kernels used: `widest` (AMX tiles for bfloat16 and AVX-512 where the core
    /// has them, else AVX2), `avx512` (no AMX), `avx2`, or `portable` (matrixmultiply's GEMM;
    /// bfloat16, f16 and i8 emulated).
    #[arg(long, env = "ALIGNIST_KERNELS", default_value_t = Kernels::Widest)]
    kernels: Kernels,
    /// Level a Predict search scores in full first (at most --max-level). Default: calibrated,
    /// else 2.
    #[arg(long, env = "ALIGNIST_SEARCH_START_LEVEL")]
    search_start_level: Option<u8>,
    /// Cells a Predict search refines at its first refinement (then times --search-keep-taper at
    /// each finer level). Default: calibrated, else 1024.
    #[arg(long, env = "ALIGNIST_SEARCH_KEEP")]
    search_keep: Option<usize>,
    /// Each finer level of a Predict search keeps this many times as many cells as the one
    /// before (1: --search-keep at every level; 0.5: --search-keep, then half, …). Default:
    /// calibrated, else 0.5.
    #[arg(long, env = "ALIGNIST_SEARCH_KEEP_TAPER")]
    search_keep_taper: Option<f64>,
    /// Arithmetic of a Predict search's levels before the finest (which is f32, or rescored in
    /// f32: `--search-rescore-finest`): `bf16`
    /// ranks the cells to refine at about 2.6 times the f32 rate where the core has fast AVX-512
    /// BF16 (AMD Zen 4), `f16` at about 1.8–1.9 times it where the core has AVX-512 FP16 (Intel since
    /// Sapphire Rapids), `i8` (8-bit integers, scores a few % from f32's) at about 3 times it where
    /// the core has AVX-512 VNNI (or AVX-VNNI, 256-bit); each is emulated, slower than f32,
    /// elsewhere. Default:
    /// calibrated, else bf16.
    #[arg(long, env = "ALIGNIST_SEARCH_COARSE_PRECISION")]
    search_coarse_precision: Option<Precision>,
    /// Score a Predict search's finest level in the coarse precision too, then its best 64 cells
    /// (or the top-k, where more) again in f32: the finest level's rows at the coarse rate. No
    /// effect with `--search-coarse-precision f32`. Default: calibrated, else off.
    #[arg(long, env = "ALIGNIST_SEARCH_RESCORE_FINEST")]
    search_rescore_finest: Option<bool>,
    /// Rank a Predict search's cells by the shape branch alone at the levels up to this one
    /// (never the finest, whose scores both branches give): about half the arithmetic of a row
    /// there. `none`: both branches at every level. Default: calibrated, else none.
    #[arg(long, env = "ALIGNIST_SEARCH_SHAPE_ONLY_TO", value_parser = parse_shape_only_to)]
    search_shape_only_to: Option<ShapeOnlyTo>,
    /// Head worker threads per model, each running one call's head work at a time: a Predict or
    /// PredictFrame search, a PredictDistribution grid (default: one per core).
    #[arg(long, env = "ALIGNIST_HEAD_WORKERS")]
    head_workers: Option<usize>,
    /// Depth pixels used per detection of a depth image (evenly spaced in its box): more cost
    /// more time per depth request.
    #[arg(long, env = "ALIGNIST_DEPTH_POINTS", default_value_t = EngineConfig::default().depth_image_points)]
    depth_points: usize,
    /// Largest request image, in bytes.
    #[arg(long, env = "ALIGNIST_MAX_IMAGE_BYTES", default_value_t = ImageLimits::default().max_bytes)]
    max_image_bytes: usize,
    /// Largest request image, in pixels.
    #[arg(long, env = "ALIGNIST_MAX_IMAGE_PIXELS", default_value_t = ImageLimits::default().max_pixels)]
    max_image_pixels: u64,
    /// Seconds between checks of the models directory for changed bundles (0: only on SIGHUP).
    #[arg(long, env = "ALIGNIST_RELOAD_INTERVAL_S", default_value_t = 10)]
    reload_interval_s: u64,
    /// Seconds to wait for in-flight calls after SIGTERM/SIGINT.
    #[arg(long, env = "ALIGNIST_DRAIN_TIMEOUT_S", default_value_t = 20)]
    drain_timeout_s: u64,
    /// Most MiB of request images in flight (encoded plus decoded size); a call that does not
    /// fit is refused at once with RESOURCE_EXHAUSTED and a retry delay.
    #[arg(long, env = "ALIGNIST_MAX_IN_FLIGHT_MIB", default_value_t = 256)]
    max_in_flight_mib: usize,
    /// Seconds after which a client connection is closed gracefully (the drain timeout is its
    /// grace), so that clients behind a headless Service spread onto new replicas; 0 (the
    /// default) keeps connections open. Calls a client starts just as its connection closes can
    /// fail (tonic reports UNKNOWN); clients should retry them.
    #[arg(long, env = "ALIGNIST_MAX_CONNECTION_AGE_S", default_value_t = 0)]
    max_connection_age_s: u64,
    /// Most client connections held at once. At the cap a new connection replaces the oldest
    /// one that has not sent its first bytes, or is refused (counted in
    /// alignist_connections_refused_total and logged).
    #[arg(long, env = "ALIGNIST_MAX_CONNECTIONS", default_value_t = TransportLimits::default().max_connections)]
    max_connections: usize,
    /// Concurrent calls per connection (HTTP/2 streams); more wait in the client.
    #[arg(long, env = "ALIGNIST_MAX_STREAMS", default_value_t = DEFAULT_MAX_STREAMS)]
    max_streams: u32,
    /// Seconds a new connection has to send its first bytes (the HTTP/2 preface or the TLS
    /// hello; the TLS handshake too).
    #[arg(long, env = "ALIGNIST_HANDSHAKE_TIMEOUT_S", default_value_t = TransportLimits::default().handshake_timeout.as_secs())]
    handshake_timeout_s: u64,
    /// Seconds a connection may move no byte either way before it is closed.
    #[arg(long, env = "ALIGNIST_IDLE_TIMEOUT_S", default_value_t = TransportLimits::default().idle_timeout.as_secs())]
    idle_timeout_s: u64,
    /// Seconds a request body may take to arrive (DEADLINE_EXCEEDED after).
    #[arg(long, env = "ALIGNIST_BODY_TIMEOUT_S", default_value_t = TransportLimits::default().body_timeout.as_secs())]
    body_timeout_s: u64,
    /// Most MiB of unfinished request bodies held at once, over all connections
    /// (RESOURCE_EXHAUSTED with a retry delay beyond).
    #[arg(long, env = "ALIGNIST_MAX_RECEIVING_MIB", default_value_t = TransportLimits::default().max_receiving_bytes >> 20)]
    max_receiving_mib: usize,
    /// Seconds between HTTP/2 pings on a silent connection (0: none). An answered ping is
    /// traffic: pinged connections do not reach the idle timeout.
    #[arg(long, env = "ALIGNIST_KEEPALIVE_S", default_value_t = 0)]
    keepalive_s: u64,
    /// TLS certificate chain (PEM); with --tls-key, the server speaks only TLS.
    #[arg(long, env = "ALIGNIST_TLS_CERT", requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// TLS private key (PEM).
    #[arg(long, env = "ALIGNIST_TLS_KEY", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// A file holding a bearer token: every call but the health checks must then carry
    /// `authorization: Bearer TOKEN` (UNAUTHENTICATED otherwise). Use it with TLS.
    #[arg(long, env = "ALIGNIST_AUTH_TOKEN_FILE")]
    auth_token_file: Option<PathBuf>,
    /// A second address, plaintext, serving only the health checks (grpc.health.v1), for
    /// probes that cannot speak TLS (Kubernetes' gRPC probes); "off" (the default) for none.
    #[arg(long, env = "ALIGNIST_HEALTH_LISTEN", default_value = "off")]
    health_listen: String,
}

/// Allocations of 1 MiB and more (request bodies, images, distributions) are mapped from the OS
/// and unmapped when freed. glibc's default raises this threshold to the largest block freed so
/// far, after which a burst of large buffers (say, 24 unfinished 8 MiB bodies) stays in the
/// process's heap after it is dropped: measured 110 → 281 → 211 MiB against 110 → 281 → ~110
/// with the threshold fixed (tests/transport.rs). An operator's own `MALLOC_MMAP_THRESHOLD_`
/// (glibc's tunable, read before `main`) wins: the threshold is then left as it set it.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn return_large_buffers_to_the_os() {
    if std::env::var_os("MALLOC_MMAP_THRESHOLD_").is_some() {
        return;
    }
    // SAFETY: mallopt only sets an allocator parameter; called before any thread starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 1 << 20);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn return_large_buffers_to_the_os() {}

fn main() -> Result<()> {
    return_large_buffers_to_the_os();
    let cli = Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("ALIGNIST_LOG")
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    let config = server_config(cli)?;
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(run(config, shutdown_signal()))?;
    Ok(())
}

/// Refuses counts and sizes that would make every call fail, and a models path that is not a
/// folder.
fn check_limits(cli: &Cli) -> Result<()> {
    if cli.max_batch == 0 || cli.queue == 0 || cli.head_workers == Some(0) {
        bail!("--max-batch, --queue and --head-workers must be at least 1");
    }
    if cli.max_connections == 0
        || cli.max_streams == 0
        || cli.handshake_timeout_s == 0
        || cli.idle_timeout_s == 0
        || cli.body_timeout_s == 0
        || cli.max_receiving_mib == 0
    {
        bail!(
            "--max-connections, --max-streams, --handshake-timeout-s, --idle-timeout-s, \
             --body-timeout-s and --max-receiving-mib must be at least 1"
        );
    }
    if cli.max_in_flight_mib << 20 < cli.max_image_bytes {
        bail!(
            "--max-in-flight-mib {} is below one image (--max-image-bytes {}): no call could be \
             admitted",
            cli.max_in_flight_mib,
            cli.max_image_bytes
        );
    }
    if !cli.models.is_dir() {
        bail!(
            "--models {}: not a directory (train a bundle with `alignist-train fit`, or point at \
             the shipped models/)",
            cli.models.display()
        );
    }
    Ok(())
}

/// The address of `--flag value`, or `None` for `off` (or empty).
fn optional_address(flag: &str, value: &str) -> Result<Option<SocketAddr>> {
    match value {
        "off" | "" => Ok(None),
        s => Ok(Some(s.parse::<SocketAddr>().with_context(|| {
            format!("--{flag} '{s}' is not an address or 'off'")
        })?)),
    }
}

/// `--search-shape-only-to`: a level, or `none`.
#[derive(Debug, Clone, Copy)]
struct ShapeOnlyTo(Option<u8>);

fn parse_shape_only_to(value: &str) -> Result<ShapeOnlyTo, String> {
    match value {
        "none" => Ok(ShapeOnlyTo(None)),
        s => s
            .parse::<u8>()
            .map(|l| ShapeOnlyTo(Some(l)))
            .map_err(|_| format!("'{s}' is not a grid level (0–255) or 'none'")),
    }
}

/// The engine's settings from the flags: explicit `--search-*` flags serve that search; otherwise
/// a positive budget calibrates it at load.
fn engine_config(cli: &Cli) -> Result<EngineConfig> {
    let defaults = EngineConfig::default();
    let search_set = cli.search_start_level.is_some()
        || cli.search_keep.is_some()
        || cli.search_keep_taper.is_some()
        || cli.search_coarse_precision.is_some()
        || cli.search_rescore_finest.is_some()
        || cli.search_shape_only_to.is_some();
    anyhow::ensure!(
        cli.search_budget_ms.is_finite() && cli.search_budget_ms >= 0.0,
        "--search-budget-ms {} must be a number of milliseconds ≥ 0",
        cli.search_budget_ms
    );
    anyhow::ensure!(
        (0.0..=1.0).contains(&cli.search_agreement),
        "--search-agreement {} must be in 0–1",
        cli.search_agreement
    );
    let engine = EngineConfig {
        max_full_level: cli.max_level,
        search_max_level: cli.max_search_level,
        search: SearchParams {
            start_level: cli
                .search_start_level
                .unwrap_or(defaults.search.start_level),
            keep: cli.search_keep.unwrap_or(defaults.search.keep),
            keep_taper: cli.search_keep_taper.unwrap_or(defaults.search.keep_taper),
            coarse_precision: cli
                .search_coarse_precision
                .unwrap_or(defaults.search.coarse_precision),
            rescore_finest: cli
                .search_rescore_finest
                .unwrap_or(defaults.search.rescore_finest),
            shape_only_to: cli
                .search_shape_only_to
                .map_or(defaults.search.shape_only_to, |s| s.0),
            ..defaults.search
        },
        search_budget_ms: (!search_set && cli.search_budget_ms > 0.0)
            .then_some(cli.search_budget_ms),
        search_agreement: cli.search_agreement,
        kernels: cli.kernels,
        // A lower search maximum lowers the default search with it.
        search_default_level: defaults.search_default_level.min(cli.max_search_level),
        image_limits: ImageLimits {
            max_bytes: cli.max_image_bytes,
            max_pixels: cli.max_image_pixels,
        },
        depth_image_points: cli.depth_points,
        ..defaults
    };
    engine.validate().context(
        "the levels and limits given (--max-level, --max-search-level, --search-*, image limits, \
         --depth-points)",
    )?;
    Ok(engine)
}

/// The server's settings from the flags, checked.
fn server_config(cli: Cli) -> Result<ServerConfig> {
    check_limits(&cli)?;
    let auth_token = match &cli.auth_token_file {
        Some(path) => Some(Token::from_file(path).context("--auth-token-file")?),
        None => None,
    };
    if auth_token.is_some() && cli.tls_cert.is_none() && !cli.listen.ip().is_loopback() {
        tracing::warn!(
            "a bearer token over plaintext on {}: anyone on the path can read it; add --tls-cert \
             and --tls-key",
            cli.listen
        );
    }
    let metrics_listen = optional_address("metrics-listen", &cli.metrics_listen)?;
    let health_listen = optional_address("health-listen", &cli.health_listen)?;
    let engine = engine_config(&cli)?;
    Ok(ServerConfig {
        models: cli.models,
        listen: cli.listen,
        metrics_listen,
        engine,
        batch: BatchConfig {
            max_batch: cli.max_batch,
            max_delay: Duration::from_millis(cli.max_delay_ms),
            queue_capacity: cli.queue,
            head_workers: cli
                .head_workers
                .unwrap_or(BatchConfig::default().head_workers),
        },
        drain_timeout: Duration::from_secs(cli.drain_timeout_s),
        max_concurrent_streams: cli.max_streams,
        reload_interval: (cli.reload_interval_s > 0)
            .then(|| Duration::from_secs(cli.reload_interval_s)),
        max_connection_age: (cli.max_connection_age_s > 0)
            .then(|| Duration::from_secs(cli.max_connection_age_s)),
        admission: alignist::serve::admission::AdmissionConfig {
            max_in_flight_bytes: cli.max_in_flight_mib << 20,
        },
        transport: TransportLimits {
            max_connections: cli.max_connections,
            handshake_timeout: Duration::from_secs(cli.handshake_timeout_s),
            idle_timeout: Duration::from_secs(cli.idle_timeout_s),
            body_timeout: Duration::from_secs(cli.body_timeout_s),
            max_receiving_bytes: cli.max_receiving_mib << 20,
        },
        keepalive_interval: (cli.keepalive_s > 0).then(|| Duration::from_secs(cli.keepalive_s)),
        tls: cli
            .tls_cert
            .zip(cli.tls_key)
            .map(|(cert, key)| TlsFiles { cert, key }),
        auth_token,
        health_listen,
    })
}
