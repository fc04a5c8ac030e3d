//! Running the service: listen, report health (NOT_SERVING until the models are loaded), serve
//! reflection and Prometheus metrics, and on SIGTERM/SIGINT stop accepting, drain in-flight calls
//! up to a timeout, and return.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use tokio::net::TcpListener;
use tonic::transport::Server;
use tracing::{error, info, warn};

use super::proto::alignist_server::AlignistServer;
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
    #[error("loading models from {path}: {message}")]
    Models {
        /// The models directory.
        path: String,
        /// Why.
        message: String,
    },
    /// Transport failure.
    #[error("gRPC transport: {0}")]
    Transport(#[from] tonic::transport::Error),
}

/// Resolves when SIGTERM or SIGINT arrives.
pub async fn shutdown_signal() {
    let ctrl_c = tokio::signal::ctrl_c();
    #[cfg(unix)]
    {
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
            .expect("install SIGTERM handler");
        tokio::select! {
            _ = ctrl_c => {},
            _ = term.recv() => {},
        }
    }
    #[cfg(not(unix))]
    let _ = ctrl_c.await;
}

/// Serves until `shutdown` resolves, then drains. Prints `listening on ADDR` once bound (tests and
/// scripts read the port from it when the address's port is 0).
pub async fn run(
    config: ServerConfig,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<(), ServeError> {
    if let Some(addr) = config.metrics_listen {
        metrics_exporter_prometheus::PrometheusBuilder::new()
            .with_http_listener(addr)
            .install()
            .map_err(|e| ServeError::Metrics {
                addr,
                message: e.to_string(),
            })?;
        info!(%addr, "metrics listening");
    }
    let listener = TcpListener::bind(config.listen)
        .await
        .map_err(|source| ServeError::Bind {
            addr: config.listen,
            source,
        })?;
    let local = listener.local_addr().map_err(|source| ServeError::Bind {
        addr: config.listen,
        source,
    })?;
    println!("listening on {local}");
    info!(%local, "gRPC listening");

    let (health, health_service) = tonic_health::server::health_reporter();
    health
        .set_not_serving::<AlignistServer<AlignistService>>()
        .await;
    health
        .set_service_status("", tonic_health::ServingStatus::NotServing)
        .await;
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(super::proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()
        .map_err(|e| ServeError::Models {
            path: "reflection".into(),
            message: e.to_string(),
        })?;

    let state = ServiceState::default();
    let service = AlignistServer::new(AlignistService::new(state.clone()))
        .max_decoding_message_size(64 << 20);

    // Load the models while already answering health checks (NOT_SERVING meanwhile).
    let loader = {
        let (state, health) = (state.clone(), health.clone());
        let (models, engine_config, batch) = (config.models.clone(), config.engine, config.batch);
        tokio::spawn(async move {
            let path = models.display().to_string();
            let loaded =
                tokio::task::spawn_blocking(move || Engine::load_dir(&models, engine_config)).await;
            match loaded {
                Ok(Ok(engine)) => {
                    info!(models = ?engine.names(), "models loaded");
                    state.install(Served::new(engine, batch));
                    health
                        .set_serving::<AlignistServer<AlignistService>>()
                        .await;
                    health
                        .set_service_status("", tonic_health::ServingStatus::Serving)
                        .await;
                    Ok(())
                }
                Ok(Err(e)) => Err(ServeError::Models {
                    path,
                    message: e.to_string(),
                }),
                Err(e) => Err(ServeError::Models {
                    path,
                    message: format!("loader failed: {e}"),
                }),
            }
        })
    };

    let (stop_accepting, stopped) = tokio::sync::oneshot::channel::<()>();
    let incoming = tokio_stream::wrappers::TcpListenerStream::new(listener);
    let server = Server::builder()
        .max_concurrent_streams(config.max_concurrent_streams)
        .add_service(health_service)
        .add_service(reflection)
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
                match loaded {
                    Ok(Ok(())) => {}
                    Ok(Err(e)) => { error!("{e}"); return Err(e); }
                    Err(e) => return Err(ServeError::Models { path: config.models.display().to_string(), message: e.to_string() }),
                }
            }
            _ = &mut shutdown => break,
        }
    }
    info!(
        timeout_s = config.drain_timeout.as_secs_f64(),
        "shutdown: draining in-flight calls"
    );
    health
        .set_not_serving::<AlignistServer<AlignistService>>()
        .await;
    health
        .set_service_status("", tonic_health::ServingStatus::NotServing)
        .await;
    let _ = stop_accepting.send(());
    match tokio::time::timeout(config.drain_timeout, &mut server).await {
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
