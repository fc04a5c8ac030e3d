//! The command-line client's calls: connect, send, and turn answers and status codes into
//! tables (for people), JSON (for programs) or CSV.

pub mod load;

use std::fmt::Write as _;
use std::time::Duration;

use tonic::transport::{Channel, Endpoint};

use crate::serve::proto::alignist_client::AlignistClient;
use crate::serve::proto::{
    DistributionRequest, FrameRequest, FrameResponse, ImageInput, ListModelsRequest,
    ListModelsResponse, ModelInfo, PixelBox, PredictRequest, PredictResponse, Rotation, SearchInfo,
};

/// Client errors; a server status keeps its code and message.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The server could not be reached.
    #[error("cannot connect to {url}: {message}")]
    Connect {
        /// Server URL.
        url: String,
        /// Why.
        message: String,
    },
    /// The server answered with an error status.
    #[error("server answered {code}: {message}{details}")]
    Status {
        /// The gRPC status code's name.
        code: String,
        /// The server's message.
        message: String,
        /// The status's rich details, as text: reason, retry delay, field violations (empty
        /// when it has none).
        details: String,
    },
}

impl From<tonic::Status> for ClientError {
    fn from(s: tonic::Status) -> Self {
        use tonic_types::StatusExt;
        let d = s.get_error_details();
        let mut parts = Vec::new();
        if let Some(info) = d.error_info() {
            parts.push(format!("reason {}", info.reason));
        }
        if let Some(delay) = d.retry_info().and_then(|r| r.retry_delay) {
            parts.push(format!("retry after {:.1} s", delay.as_secs_f64()));
        }
        if let Some(bad) = d.bad_request() {
            for v in &bad.field_violations {
                parts.push(format!("field {}: {}", v.field, v.description));
            }
        }
        ClientError::Status {
            code: format!("{:?}", s.code()),
            message: s.message().to_string(),
            details: if parts.is_empty() {
                String::new()
            } else {
                format!(" [{}]", parts.join("; "))
            },
        }
    }
}

/// Adds `authorization: Bearer TOKEN` to every call, when a token is given.
#[derive(Clone, Default)]
pub struct Bearer(Option<tonic::metadata::MetadataValue<tonic::metadata::Ascii>>);

impl tonic::service::Interceptor for Bearer {
    fn call(
        &mut self,
        mut request: tonic::Request<()>,
    ) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(value) = &self.0 {
            request
                .metadata_mut()
                .insert("authorization", value.clone());
        }
        Ok(request)
    }
}

/// A connection to a server: the channel, with the token (if any) on every call.
pub type Connection = tonic::service::interceptor::InterceptedService<Channel, Bearer>;

/// How to reach a server beyond its URL.
#[derive(Debug, Clone, Default)]
pub struct ConnectOptions {
    /// Connect and call timeout.
    pub timeout: Duration,
    /// For `https://`: the PEM certificate(s) to trust (a private CA or a self-signed server);
    /// `None`: the public web roots.
    pub ca_file: Option<std::path::PathBuf>,
    /// The bearer token sent with every call.
    pub token: Option<crate::serve::auth::Token>,
}

/// Connects to `url` (e.g. `http://127.0.0.1:50051`) with no token.
pub async fn connect(url: &str, timeout: Duration) -> Result<Connection, ClientError> {
    connect_with(
        url,
        &ConnectOptions {
            timeout,
            ..Default::default()
        },
    )
    .await
}

/// Connects to `url`: `https://` speaks TLS (trusting `options.ca_file`, or the public roots),
/// `http://` plaintext; the token, if any, goes with every call.
pub async fn connect_with(url: &str, options: &ConnectOptions) -> Result<Connection, ClientError> {
    let err = |message: String| ClientError::Connect {
        url: url.to_string(),
        message,
    };
    let mut endpoint = Endpoint::from_shared(url.to_string())
        .map_err(|e| err(e.to_string()))?
        .connect_timeout(options.timeout)
        .timeout(options.timeout);
    match (url.starts_with("https://"), &options.ca_file) {
        (true, ca) => {
            let tls = tonic::transport::ClientTlsConfig::new();
            let tls = match ca {
                Some(path) => {
                    let pem = std::fs::read(path)
                        .map_err(|e| err(format!("--ca-file {}: {e}", path.display())))?;
                    tls.ca_certificate(tonic::transport::Certificate::from_pem(pem))
                }
                None => tls.with_webpki_roots(),
            };
            endpoint = endpoint
                .tls_config(tls)
                .map_err(|e| err(format!("TLS: {e}")))?;
        }
        (false, Some(_)) => {
            return Err(err(
                "--ca-file is for https:// servers; this URL is plaintext".into(),
            ));
        }
        (false, None) => {}
    }
    let bearer = match &options.token {
        Some(token) => Some(
            format!("Bearer {}", token.as_str())
                .parse()
                .map_err(|e| err(format!("the token cannot be a header: {e}")))?,
        ),
        None => None,
    };
    let channel = endpoint.connect().await.map_err(|e| {
        // tonic's own text ("transport error") hides the cause; name it.
        let mut message = e.to_string();
        let mut source = std::error::Error::source(&e);
        while let Some(s) = source {
            message = format!("{message}: {s}");
            source = s.source();
        }
        err(message)
    })?;
    Ok(tonic::service::interceptor::InterceptedService::new(
        channel,
        Bearer(bearer),
    ))
}

/// An image input from file bytes and an optional box `[x, y, width, height]` (sub-pixel; it may
/// extend beyond the image).
pub fn image_input(data: Vec<u8>, crop: Option<[f64; 4]>) -> ImageInput {
    ImageInput {
        data,
        width: 0,
        height: 0,
        crop: None,
        crop_box: crop.map(pixel_box),
    }
}

/// `[x, y, width, height]` as a [`PixelBox`].
pub fn pixel_box([x, y, width, height]: [f64; 4]) -> PixelBox {
    PixelBox {
        x,
        y,
        width,
        height,
    }
}

/// Predict.
pub async fn predict(
    channel: Connection,
    request: PredictRequest,
) -> Result<PredictResponse, ClientError> {
    let mut client = AlignistClient::new(channel).max_decoding_message_size(64 << 20);
    Ok(client.predict(request).await?.into_inner())
}

/// PredictFrame: one answer per detection box of a full image.
pub async fn predict_frame(
    channel: Connection,
    request: FrameRequest,
) -> Result<FrameResponse, ClientError> {
    let mut client = AlignistClient::new(channel).max_decoding_message_size(64 << 20);
    Ok(client.predict_frame(request).await?.into_inner())
}

/// The full distribution, reassembled from its chunks: `(level, probabilities, log-densities)`.
pub async fn distribution(
    channel: Connection,
    request: DistributionRequest,
) -> Result<(u32, Vec<f32>, Vec<f32>), ClientError> {
    let mut client = AlignistClient::new(channel).max_decoding_message_size(64 << 20);
    let mut stream = client.predict_distribution(request).await?.into_inner();
    let (mut level, mut probs, mut logs) = (0, Vec::new(), Vec::new());
    while let Some(chunk) = stream.message().await? {
        if chunk.offset as usize != probs.len() {
            return Err(ClientError::Status {
                details: String::new(),
                code: "DataLoss".into(),
                message: format!(
                    "chunk at offset {} arrived after {} cells",
                    chunk.offset,
                    probs.len()
                ),
            });
        }
        level = chunk.level;
        probs.extend(chunk.probability);
        logs.extend(chunk.log_density);
    }
    Ok((level, probs, logs))
}

/// ListModels.
pub async fn models(channel: Connection) -> Result<ListModelsResponse, ClientError> {
    let mut client = AlignistClient::new(channel);
    Ok(client.list_models(ListModelsRequest {}).await?.into_inner())
}

/// `grpc.health.v1` Check of `service` ("" for the whole server): the status's name.
pub async fn health(channel: Connection, service: &str) -> Result<String, ClientError> {
    let mut client = tonic_health::pb::health_client::HealthClient::new(channel);
    let answer = client
        .check(tonic_health::pb::HealthCheckRequest {
            service: service.to_string(),
        })
        .await?
        .into_inner();
    Ok(format!(
        "{:?}",
        tonic_health::pb::health_check_response::ServingStatus::try_from(answer.status)
            .unwrap_or(tonic_health::pb::health_check_response::ServingStatus::Unknown)
    ))
}

fn quaternion(q: &[f64]) -> String {
    let v: Vec<String> = q.iter().map(|x| format!("{x:+.4}")).collect();
    format!("({})", v.join(", "))
}

/// The quaternion `(w, x, y, z)` of an answer: the typed rotation, or the older `quaternion`
/// field of servers that do not send one.
#[allow(deprecated)]
fn quaternion_of(rotation: &Option<Rotation>, old: &[f64]) -> Vec<f64> {
    match rotation {
        Some(r) => vec![r.w, r.x, r.y, r.z],
        None => old.to_vec(),
    }
}

#[allow(deprecated)]
fn top_quaternion(t: &crate::serve::proto::RotationProbability) -> Vec<f64> {
    quaternion_of(&t.rotation, &t.quaternion)
}

#[allow(deprecated)]
fn mode_quaternion(m: &crate::serve::proto::Mode) -> Vec<f64> {
    quaternion_of(&m.rotation, &m.quaternion)
}

/// A Predict answer as a table.
pub fn predict_table(r: &PredictResponse) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "model {}{}{}: {} modes, search covered {:.1} % of the mass{} ({:.1} ms)",
        r.model,
        if r.model_version.is_empty() {
            String::new()
        } else {
            format!(
                " (version {})",
                &r.model_version[..r.model_version.len().min(12)]
            )
        },
        if r.object.is_empty() {
            String::new()
        } else {
            format!(" / {}", r.object)
        },
        r.modes.len(),
        r.covered_mass * 100.0,
        if r.depth_fused { ", depth fused" } else { "" },
        r.compute_ms
    );
    let with_t = r.top.iter().any(|t| t.translation.is_some());
    let _ = writeln!(
        s,
        "\n rank  probability  log-density  quaternion (w, x, y, z){}",
        if with_t {
            "            translation (mesh units)"
        } else {
            ""
        }
    );
    for (i, t) in r.top.iter().enumerate() {
        let _ = writeln!(
            s,
            " {:>4}  {:>11.6}  {:>11.3}  {}{}",
            i + 1,
            t.probability,
            t.log_density,
            quaternion(&top_quaternion(t)),
            t.translation
                .as_ref()
                .map(|v| format!("  ({:.4}, {:.4}, {:.4})", v.x, v.y, v.z))
                .unwrap_or_default()
        );
    }
    let _ = writeln!(s, "\n mode  probability  spread°  cells  mean quaternion");
    for (i, m) in r.modes.iter().enumerate() {
        let _ = writeln!(
            s,
            " {:>4}  {:>11.4}  {:>7.2}  {:>5}  {}",
            i + 1,
            m.probability,
            m.spread_deg,
            m.cells,
            quaternion(&mode_quaternion(m))
        );
    }
    s
}

/// A Predict answer as JSON.
pub fn predict_json(r: &PredictResponse) -> serde_json::Value {
    let rot = |t: &crate::serve::proto::RotationProbability| {
        serde_json::json!({
            "quaternion": top_quaternion(t),
            "matrix": t.rotation.as_ref().map(|r| r.matrix.clone()),
            "probability": t.probability,
            "log_density": t.log_density, "level": t.level, "cell": t.cell,
            "translation": t.translation.as_ref().map(|v| [v.x, v.y, v.z]),
        })
    };
    serde_json::json!({
        "model": r.model,
        "model_version": r.model_version,
        "object": r.object,
        "top": r.top.iter().map(rot).collect::<Vec<_>>(),
        "map": r.map.as_ref().map(rot),
        "modes": r.modes.iter().map(|m| serde_json::json!({
            "quaternion": mode_quaternion(m), "probability": m.probability,
            "spread_deg": m.spread_deg, "cells": m.cells,
        })).collect::<Vec<_>>(),
        "covered_mass": r.covered_mass,
        "depth_fused": r.depth_fused,
        "compute_ms": r.compute_ms,
    })
}

/// A PredictFrame answer as a table: one block per detection, rotations in the camera frame.
pub fn frame_table(r: &FrameResponse) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "{} detections, rotations in the camera frame ({:.1} ms)",
        r.detections.len(),
        r.compute_ms
    );
    for (i, d) in r.detections.iter().enumerate() {
        // The box as the server used it (sub-pixel; `box` is only the whole-pixel echo).
        let b = d.bbox.unwrap_or_default();
        let ray = d
            .ray
            .as_ref()
            .map(|q| quaternion(&[q.w, q.x, q.y, q.z]))
            .unwrap_or_default();
        let _ = writeln!(
            s,
            "\n== box {} at ({:.1}, {:.1}) {:.1}×{:.1}, ray {ray}",
            i + 1,
            b.x,
            b.y,
            b.width,
            b.height
        );
        if let Some(p) = &d.prediction {
            s.push_str(&predict_table(p));
        }
    }
    s
}

/// A PredictFrame answer as JSON.
pub fn frame_json(r: &FrameResponse) -> serde_json::Value {
    serde_json::json!({
        "model": r.model,
        "model_version": r.model_version,
        "compute_ms": r.compute_ms,
        "detections": r.detections.iter().map(|d| {
            // The box as the server used it (sub-pixel; `box` is only the whole-pixel echo).
        let b = d.bbox.unwrap_or_default();
            serde_json::json!({
                "box": [b.x, b.y, b.width, b.height],
                "ray": d.ray.as_ref().map(|q| [q.w, q.x, q.y, q.z]),
                "prediction": d.prediction.as_ref().map(predict_json),
            })
        }).collect::<Vec<_>>(),
    })
}

/// The `search:` line of a model in [`models_table`]: the search it serves and how it was chosen.
fn search_line(q: &SearchInfo) -> String {
    let calibrated = if q.chosen_by == "calibration" {
        format!(
            " (calibrated: agreement {:.3}, predicted {:.1} ms, measured {:.1} ms, budget {} ms{}; {})",
            q.agreement,
            q.predicted_ms,
            q.measured_ms,
            q.budget_ms,
            if q.within_budget { "" } else { ", over budget" },
            q.reason
        )
    } else {
        " (configured)".into()
    };
    format!(
        "  search: start {}, keep {}{}{}, coarse {}{}{}{calibrated}; kernels {}",
        q.start_level,
        q.keep,
        if q.keep_taper == 1.0 {
            String::new()
        } else {
            format!(" ×{}/level", q.keep_taper)
        },
        if q.keep_mass > 0.0 {
            format!(" ({} of the mass)", q.keep_mass)
        } else {
            String::new()
        },
        q.coarse_precision,
        if q.rescore_finest {
            format!(", finest {} rescored in f32", q.coarse_precision)
        } else {
            String::new()
        },
        q.shape_only_to
            .map(|l| format!(", ranked by the shape branch to level {l}"))
            .unwrap_or_default(),
        q.kernels
    )
}

/// Models as a table, then the bundles that were refused.
pub fn models_table(list: &ListModelsResponse) -> String {
    let models: &[ModelInfo] = &list.models;
    let mut s = String::new();
    for m in models {
        let t = m.training.clone().unwrap_or_default();
        let _ = writeln!(
            s,
            "{}: input {}², full levels ≤ {}, search ≤ {}, {} ({} steps); eval LL {:.2} at level {}, \
             spread {:.1}°, AR@30 {:.2}, median {:.1}°",
            m.name,
            m.input_size,
            m.full_max_level,
            m.search_max_level,
            t.method,
            t.steps,
            t.log_likelihood,
            t.eval_level,
            t.spread_deg,
            t.accuracy_at_30,
            t.median_error_deg
        );
        if let Some(q) = &m.search {
            let _ = writeln!(s, "{}", search_line(q));
        }
        for o in &m.objects {
            let axis = o
                .symmetry_axis
                .map(|a| format!(" about ({:+.3}, {:+.3}, {:+.3})", a.x, a.y, a.z))
                .unwrap_or_default();
            let c = o.frame_centre.unwrap_or_default();
            let _ = writeln!(
                s,
                "  {}: symmetry {}{axis} ({} rotations listed), frame = (mesh − ({:.4}, {:.4}, \
                 {:.4})) / {:.4} {}, {} training images",
                o.name,
                o.symmetry,
                o.symmetry_rotations.len(),
                c.x,
                c.y,
                c.z,
                o.frame_scale,
                o.frame_units,
                o.train_images
            );
            if !o.discovered_symmetry.is_empty() {
                let _ = writeln!(s, "    {}", discovered_line(o));
            }
        }
    }
    for f in &list.failed {
        let _ = writeln!(
            s,
            "REFUSED {}{}: {}",
            f.name,
            if f.serving_previous {
                " (its previous version still serves)"
            } else {
                ""
            },
            f.error
        );
    }
    s
}

/// What the experts found about an object's symmetry, in a line.
fn discovered_line(o: &crate::serve::proto::ObjectInfo) -> String {
    let axes: Vec<String> = o
        .discovered_axes
        .iter()
        .map(|a| format!("({:+.3}, {:+.3}, {:+.3})", a.x, a.y, a.z))
        .collect();
    format!(
        "discovered symmetry {}{} (confidence {:.2}){}",
        o.discovered_symmetry,
        match axes.len() {
            0 => String::new(),
            1 => format!(" about {}", axes[0]),
            n => format!(" with {n} axes of highest order, e.g. {}", axes[0]),
        },
        o.discovered_confidence,
        if o.near_symmetry.is_empty() {
            String::new()
        } else {
            format!(", nearly {}", o.near_symmetry)
        }
    )
}
