//! Running the service: listen, report health (NOT_SERVING until the models are loaded), serve
//! reflection and Prometheus metrics, reload changed models (polling and SIGHUP) without
//! dropping a call, and on SIGTERM/SIGINT stop accepting, drain in-flight calls
//! up to a timeout, and return.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use tokio::net::TcpListener;
use tonic::transport::{Identity, Server, ServerTlsConfig};
use tonic_health::ServingStatus;
use tracing::{error, info, warn};

use super::auth::{AuthLayer, Token};
use super::proto::alignist_server::AlignistServer;
use super::transport::{BodyLimitLayer, BoundedIncoming, TransportLimits};
use super::{AlignistService, BatchConfig, Served, ServiceState};
use crate::engine::{Engine, EngineConfig};

/// How the server runs.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    /// Models directory.
    pub models: PathBuf,
    /// gRPC address.
    pub listen: SocketAddr,
    /// Prometheus address (`None`: no metrics endpoint).
    pub metrics_listen: Option<SocketAddr>,
    /// Engine limits.
    pub engine: EngineConfig,
    /// Batching.
    pub batch: BatchConfig,
    /// Longest the server waits for in-flight calls after a shutdown signal.
    pub drain_timeout: Duration,
    /// Concurrent calls per connection.
    pub max_concurrent_streams: u32,
    /// How often the models directory is checked for changes (`None`: only on SIGHUP).
    pub reload_interval: Option<Duration>,
    /// Connections older than this are closed gracefully (over `drain_timeout`), so that
    /// clients spread onto new replicas (`None`: connections live as long as clients keep them).
    pub max_connection_age: Option<Duration>,
    /// Limits of the work in flight (image bytes).
    pub admission: super::admission::AdmissionConfig,
    /// Connections and request bodies: counts, timeouts, bytes.
    pub transport: TransportLimits,
    /// HTTP/2 pings on a silent connection this often (`None`: none; an answered ping counts as
    /// traffic, so pinged connections never reach the idle timeout).
    pub keepalive_interval: Option<Duration>,
    /// TLS: the certificate chain and private key, PEM (`None`: plaintext).
    pub tls: Option<TlsFiles>,
    /// The bearer token every call but the health checks must carry (`None`: no token).
    pub auth_token: Option<Token>,
    /// A second, plaintext address that serves only `grpc.health.v1` (`None`: none): for
    /// probes that cannot speak TLS, such as Kubernetes' gRPC probes.
    pub health_listen: Option<SocketAddr>,
}

impl ServerConfig {
    /// Serves `models` on `listen` with the default limits, no metrics endpoint, no TLS and no
    /// token.
    pub fn new(models: PathBuf, listen: SocketAddr) -> Self {
        Self {
            models,
            listen,
            metrics_listen: None,
            engine: EngineConfig::default(),
            batch: BatchConfig::default(),
            drain_timeout: Duration::from_secs(20),
            max_concurrent_streams: DEFAULT_MAX_STREAMS,
            reload_interval: None,
            max_connection_age: None,
            admission: Default::default(),
            transport: TransportLimits::default(),
            keepalive_interval: None,
            tls: None,
            auth_token: None,
            health_listen: None,
        }
    }
}

/// Concurrent calls per connection by default: more wait in the client's queue (HTTP/2 flow),
/// they are not refused.
pub const DEFAULT_MAX_STREAMS: u32 = 128;

/// The PEM files of the server's TLS identity.
#[derive(Debug, Clone)]
pub struct TlsFiles {
    /// The certificate chain.
    pub cert: PathBuf,
    /// The private key.
    pub key: PathBuf,
}

impl TlsFiles {
    /// The TLS configuration of these files, the handshake bounded by `handshake_timeout`.
    fn config(&self, handshake_timeout: Duration) -> Result<ServerTlsConfig, ServeError> {
        let read = |path: &PathBuf| {
            std::fs::read(path).map_err(|source| ServeError::Tls {
                path: path.display().to_string(),
                message: source.to_string(),
            })
        };
        let (cert, key) = (read(&self.cert)?, read(&self.key)?);
        Ok(ServerTlsConfig::new()
            .identity(Identity::from_pem(cert, key))
            .timeout(handshake_timeout))
    }
}

/// A fingerprint of every file under the models directory: relative path, length and
/// modification time. A change to any of them triggers a reload.
pub fn models_fingerprint(dir: &std::path::Path) -> Vec<(String, u64, u128)> {
    fn walk(root: &std::path::Path, dir: &std::path::Path, out: &mut Vec<(String, u64, u128)>) {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return;
        };
        for entry in entries.flatten() {
            let path = entry.path();
            let Ok(meta) = entry.metadata() else { continue };
            if meta.is_dir() {
                walk(root, &path, out);
            } else {
                let modified = meta
                    .modified()
                    .ok()
                    .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
                    .map_or(0, |d| d.as_nanos());
                let rel = path.strip_prefix(root).unwrap_or(&path);
                out.push((rel.display().to_string(), meta.len(), modified));
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.sort();
    out
}

/// Resolves on every SIGHUP (never on platforms without it).
async fn hangup(signal: &mut Option<tokio::signal::unix::Signal>) {
    match signal {
        Some(s) => {
            s.recv().await;
        }
        None => std::future::pending::<()>().await,
    }
}

/// Watches the models directory (polling and SIGHUP) and swaps in a new engine when it changed
/// and loads cleanly. A bundle that fails validation is refused with an error log, and the
/// engine being served stays; requests in flight finish on the engine they started with.
async fn watch_models(
    models: PathBuf,
    engine_config: EngineConfig,
    batch: BatchConfig,
    interval: Option<Duration>,
    state: ServiceState,
    mut seen: Vec<(String, u64, u128)>,
    mut hup: Option<tokio::signal::unix::Signal>,
) {
    let mut tick = tokio::time::interval(interval.unwrap_or(Duration::from_secs(3600)));
    tick.tick().await;
    loop {
        let forced = tokio::select! {
            _ = tick.tick(), if interval.is_some() => false,
            _ = hangup(&mut hup) => true,
        };
        let dir = models.clone();
        let now = match tokio::task::spawn_blocking(move || models_fingerprint(&dir)).await {
            Ok(f) => f,
            Err(_) => continue,
        };
        if now == seen && !forced {
            continue;
        }
        seen = now;
        match load_served(models.clone(), engine_config, batch, state.installed()).await {
            Ok(served) => {
                info!(
                    models = ?served.engine.names(),
                    refused = ?served.engine.failures().keys().collect::<Vec<_>>(),
                    "models reloaded"
                );
                state.install(served);
                metrics::counter!("alignist_reloads_total", "result" => "ok").increment(1);
            }
            Err(e) => {
                error!("reload refused, still serving the previous models: {e}");
                metrics::counter!("alignist_reloads_total", "result" => "refused").increment(1);
            }
        }
    }
}

/// Loads the models of `models` off the async threads and starts their workers: the one loading
/// routine of start-up (`previous` = `None`) and of reloads, where a bundle that fails to load
/// now keeps serving as it was ([`Served::reloaded`]), its refusal listed. A reload prepares the
/// bundles (depth fusion's tables: tens of seconds of CPU for a large model) on one thread of
/// low priority, so that the calls being served keep the cores.
async fn load_served(
    models: PathBuf,
    engine_config: EngineConfig,
    batch: BatchConfig,
    previous: Option<std::sync::Arc<Served>>,
) -> Result<Served, ServeError> {
    let path = models.display().to_string();
    let reload = previous.is_some();
    let dir = models.clone();
    let engine = tokio::task::spawn_blocking(move || match reload {
        false => Engine::load_dir(&dir, engine_config),
        true => match background_pool() {
            Some(pool) => pool.install(|| Engine::load_bundles(&dir, engine_config)),
            None => Engine::load_bundles(&dir, engine_config),
        },
    })
    .await
    .map_err(|e| ServeError::Loader {
        path: path.clone(),
        source: e,
    })?
    .map_err(|source| ServeError::Models {
        path: path.clone(),
        source,
    })?;
    let served = Served::reloaded(engine, previous.as_deref(), batch).map_err(|source| {
        ServeError::Workers {
            path: path.clone(),
            source,
        }
    })?;
    if served.engine.models().next().is_none() {
        return Err(ServeError::Models {
            source: served.engine.none_loads(&models),
            path,
        });
    }
    Ok(served)
}

/// One thread at low priority (nice 10) for reloads' preparation: rayon work started inside
/// [`rayon::ThreadPool::install`] stays on it. `None` if it cannot be started (then reloads use
/// the shared pool).
fn background_pool() -> Option<&'static rayon::ThreadPool> {
    static POOL: std::sync::OnceLock<Option<rayon::ThreadPool>> = std::sync::OnceLock::new();
    POOL.get_or_init(|| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .thread_name(|_| "alignist-reload".into())
            .start_handler(|_| lower_this_threads_priority())
            .build()
            .map_err(|e| warn!("no low-priority reload thread ({e}); reloads share the cores"))
            .ok()
    })
    .as_ref()
}

/// Nice 10 for the calling thread (Linux schedules threads, so the rest of the process keeps
/// its priority).
fn lower_this_threads_priority() {
    #[cfg(target_os = "linux")]
    // SAFETY: setpriority changes the calling thread's nice value, nothing else.
    unsafe {
        if libc::setpriority(libc::PRIO_PROCESS, 0, 10) != 0 {
            warn!("could not lower the reload thread's priority");
        }
    }
}

/// Errors that stop the server.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// An address cannot be bound.
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// Why.
        source: std::io::Error,
    },
    /// The metrics exporter could not start.
    #[error("metrics exporter on {addr}: {message}")]
    Metrics {
        /// The address.
        addr: SocketAddr,
        /// Why.
        message: String,
    },
    /// The models cannot be loaded.
    #[error("loading models from {path}: {source}")]
    Models {
        /// The models directory.
        path: String,
        /// Why.
        #[source]
        source: crate::engine::EngineError,
    },
    /// The loading task died (a panic while loading).
    #[error("loading models from {path}: the loader failed: {source}")]
    Loader {
        /// The models directory.
        path: String,
        /// The task's failure.
        #[source]
        source: tokio::task::JoinError,
    },
    /// The models' encoder or head threads could not be started.
    #[error("starting the workers of the models from {path}: {source}")]
    Workers {
        /// The models directory.
        path: String,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// Transport failure.
    #[error("gRPC transport: {0}")]
    Transport(#[from] tonic::transport::Error),
    /// The TLS certificate or key cannot be read or used.
    #[error("TLS: {path}: {message}")]
    Tls {
        /// The file (or both, for a pair that does not fit).
        path: String,
        /// Why.
        message: String,
    },
    /// The reflection service could not be built from the file descriptor sets.
    #[error("reflection: {0}")]
    Reflection(#[from] tonic_reflection::server::Error),
}

/// Sets the readiness of the Alignist service (`alignist.v1.Alignist`: SERVING once models are
/// loaded, until shutdown). The whole server (`""`) is the liveness signal: SERVING from the
/// moment it listens until it drains.
async fn report_health(health: &tonic_health::server::HealthReporter, status: ServingStatus) {
    health
        .set_service_status(
            <AlignistServer<AlignistService> as tonic::server::NamedService>::NAME,
            status,
        )
        .await;
}

/// Resolves when SIGTERM or SIGINT arrives.
pub async fn shutdown_signal() {
    let ctrl_c = tokio::signal::ctrl_c();
    #[cfg(unix)]
    match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
        Ok(mut term) => {
            tokio::select! {
                _ = ctrl_c => {},
                _ = term.recv() => {},
            }
        }
        Err(e) => {
            error!("cannot listen for SIGTERM ({e}); only SIGINT stops the server");
            let _ = ctrl_c.await;
        }
    }
    #[cfg(not(unix))]
    let _ = ctrl_c.await;
}

/// Installs the Prometheus exporter on `addr`: histograms with buckets (aggregatable across
/// replicas, unlike summaries), times in seconds from 1 ms to 30 s, batch sizes in powers of two.
fn install_metrics(addr: SocketAddr) -> Result<(), ServeError> {
    use metrics_exporter_prometheus::{Matcher, PrometheusBuilder};
    let err = |e: metrics_exporter_prometheus::BuildError| ServeError::Metrics {
        addr,
        message: e.to_string(),
    };
    PrometheusBuilder::new()
        .with_http_listener(addr)
        .set_buckets_for_metric(
            Matcher::Suffix("_seconds".into()),
            &[
                0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0,
            ],
        )
        .map_err(err)?
        .set_buckets_for_metric(
            Matcher::Suffix("batch_size".into()),
            &[1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0],
        )
        .map_err(err)?
        .install()
        .map_err(err)?;
    info!(%addr, "metrics listening");
    Ok(())
}

/// Binds `listen`; prints `listening on ADDR` (tests and scripts read the port from it when the
/// address's port is 0).
async fn bind(listen: SocketAddr) -> Result<TcpListener, ServeError> {
    let bind_error = |source| ServeError::Bind {
        addr: listen,
        source,
    };
    let listener = TcpListener::bind(listen).await.map_err(bind_error)?;
    let local = listener.local_addr().map_err(bind_error)?;
    println!("listening on {local}");
    info!(%local, "gRPC listening");
    Ok(listener)
}

/// Loads the models while the server already answers health checks (NOT_SERVING meanwhile), then
/// serves them and watches for reloads.
fn spawn_loader(
    config: &ServerConfig,
    state: ServiceState,
    health: tonic_health::server::HealthReporter,
    hup: Option<tokio::signal::unix::Signal>,
) -> tokio::task::JoinHandle<Result<(), ServeError>> {
    let (models, engine_config, batch) = (config.models.clone(), config.engine, config.batch);
    let reload_interval = config.reload_interval;
    tokio::spawn(async move {
        let fingerprint = models_fingerprint(&models);
        let served = load_served(models.clone(), engine_config, batch, None).await?;
        info!(
            models = ?served.engine.names(),
            refused = ?served.engine.failures().keys().collect::<Vec<_>>(),
            "models loaded"
        );
        state.install(served);
        report_health(&health, ServingStatus::Serving).await;
        let watch = watch_models(
            models,
            engine_config,
            batch,
            reload_interval,
            state,
            fingerprint,
            hup,
        );
        tokio::spawn(watch);
        Ok(())
    })
}

/// Serves until `shutdown` resolves, then drains: stops accepting, reports NOT_SERVING, and waits
/// up to the drain timeout for the calls in flight.
pub async fn run(
    config: ServerConfig,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<(), ServeError> {
    if let Some(addr) = config.metrics_listen {
        install_metrics(addr)?;
    }
    // The TLS files are read before the port is bound: a wrong path fails before "listening".
    let tls = match &config.tls {
        Some(files) => Some((files.config(config.transport.handshake_timeout)?, files)),
        None => None,
    };
    let listener = bind(config.listen).await?;
    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_service_status("", ServingStatus::Serving).await;
    report_health(&health, ServingStatus::NotServing).await;
    // Both reflection versions: v1 for current tools, v1alpha for Python's grpcio-reflection and
    // older grpcurl/Postman.
    let reflection_builder = || {
        tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(super::proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    let reflection = reflection_builder().build_v1()?;
    let reflection_v1alpha = reflection_builder().build_v1alpha()?;
    // SIGHUP is handled from the start (its default action would end the process while the
    // models load); hang-ups before the models are loaded trigger a reload check afterwards.
    let hup = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup()).ok();
    let state = ServiceState::default();
    // The transport refuses a message larger than an image may be, plus room for the other
    // fields (depth points are at most 10 000 × 3 floats): nothing larger is read into memory.
    let service = AlignistServer::new(AlignistService::with_admission(
        state.clone(),
        config.admission,
    ))
    .max_decoding_message_size(config.engine.image_limits.max_bytes + (1 << 20));
    if let Some(addr) = config.health_listen {
        serve_health_only(addr, health_service.clone(), config.transport).await?;
    }
    let loader = spawn_loader(&config, state, health.clone(), hup);
    let (stop_accepting, stopped) = tokio::sync::oneshot::channel::<()>();
    // Connections bounded in number and time, TCP_NODELAY on each (with Nagle's algorithm a
    // response waits for the client's delayed ACK, ~40 ms on Linux).
    let incoming = BoundedIncoming::new(listener, config.transport);
    let mut builder = Server::builder();
    if let Some((tls, files)) = tls {
        builder = builder.tls_config(tls).map_err(|e| ServeError::Tls {
            path: format!("{} and {}", files.cert.display(), files.key.display()),
            message: e.to_string(),
        })?;
    }
    let mut builder = builder
        .max_concurrent_streams(config.max_concurrent_streams)
        .http2_keepalive_interval(config.keepalive_interval)
        .http2_keepalive_timeout(Some(Duration::from_secs(20)))
        // Headers are small here (a request id, a token); 16 KiB bounds what one call may send.
        .http2_max_header_list_size(16 << 10)
        .layer(super::observe::ObserveLayer::default())
        .layer(AuthLayer::new(config.auth_token.clone()))
        .layer(BodyLimitLayer::new(&config.transport));
    let server = builder
        .add_service(health_service)
        .add_service(reflection)
        .add_service(reflection_v1alpha)
        .add_service(service)
        .serve_with_incoming_shutdown(incoming, async {
            let _ = stopped.await;
        });
    tokio::pin!(server);
    tokio::pin!(loader);
    let mut loader_done = false;
    let mut shutdown = Box::pin(shutdown);
    loop {
        tokio::select! {
            result = &mut server => return result.map_err(ServeError::from),
            loaded = &mut loader, if !loader_done => {
                loader_done = true;
                let failed = match loaded {
                    Ok(Ok(())) => continue,
                    Ok(Err(e)) => e,
                    Err(source) => ServeError::Loader { path: config.models.display().to_string(), source },
                };
                error!("{failed}");
                return Err(failed);
            }
            _ = &mut shutdown => break,
        }
    }
    drain(&health, stop_accepting, server, config.drain_timeout).await
}

/// Serves the health service alone, in plaintext on `addr`, for as long as the process lives (a
/// draining server still answers NOT_SERVING there).
async fn serve_health_only(
    addr: SocketAddr,
    health_service: tonic_health::pb::health_server::HealthServer<
        impl tonic_health::pb::health_server::Health,
    >,
    transport: TransportLimits,
) -> Result<(), ServeError> {
    let listener = TcpListener::bind(addr)
        .await
        .map_err(|source| ServeError::Bind { addr, source })?;
    info!(%addr, "plaintext health checks listening");
    let health_only = Server::builder()
        .add_service(health_service)
        .serve_with_incoming(BoundedIncoming::new(listener, transport));
    // It lives as long as the process: a draining server still answers NOT_SERVING there.
    tokio::spawn(async move {
        if let Err(e) = health_only.await {
            error!("plaintext health checks stopped: {e}");
        }
    });
    Ok(())
}

/// Stops accepting, reports NOT_SERVING (the service and the whole server), and waits up to
/// `timeout` for the calls in flight.
async fn drain(
    health: &tonic_health::server::HealthReporter,
    stop_accepting: tokio::sync::oneshot::Sender<()>,
    server: impl std::future::Future<Output = Result<(), tonic::transport::Error>>,
    timeout: Duration,
) -> Result<(), ServeError> {
    info!(
        timeout_s = timeout.as_secs_f64(),
        "shutdown: draining in-flight calls"
    );
    report_health(health, ServingStatus::NotServing).await;
    health
        .set_service_status("", ServingStatus::NotServing)
        .await;
    let _ = stop_accepting.send(());
    match tokio::time::timeout(timeout, server).await {
        Ok(result) => {
            info!("drained; exiting");
            result.map_err(ServeError::from)
        }
        Err(_) => {
            warn!("drain timeout reached with calls still in flight; exiting");
            Ok(())
        }
    }
}
