//! The tower layer every gRPC call passes through at the server builder: what each call gets
//! without its handler saying so (like linkerd2-proxy's per-request stack).
//!
//! - a request id: the caller's `x-request-id` (first 64 characters) or `r<n>`, echoed in the
//!   response headers;
//! - a tracing span `call{method, request_id}` around the handler, and one log line per call;
//! - `alignist_in_flight_requests{method}` while the call lives, then
//!   `alignist_requests_total{method, code}` and `alignist_request_seconds{method, code}`, the
//!   latency to the call's last frame: a streamed answer counts until its trailers, and a call
//!   whose client goes away before them counts as `CANCELLED`.
//!
//! The code is the gRPC status of the answer: from the response headers (a trailers-only answer,
//! as tonic sends every error of a handler) or from the trailers.

use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::task::{Context, Poll};
use std::time::Instant;

use http::{HeaderMap, HeaderValue, Request, Response};
use tonic::body::Body;
use tonic::{Code, Status};
use tower::{Layer, Service};
use tracing::{Instrument, Span, info, info_span, warn};

/// The header that carries a call's request id, both ways.
pub const REQUEST_ID: &str = "x-request-id";

/// Adds [`Observe`] to every service of a server.
#[derive(Debug, Clone, Default)]
pub struct ObserveLayer {
    next_id: Arc<AtomicU64>,
}

impl<S> Layer<S> for ObserveLayer {
    type Service = Observe<S>;

    fn layer(&self, inner: S) -> Observe<S> {
        Observe {
            inner,
            next_id: self.next_id.clone(),
        }
    }
}

/// A service with its calls observed (module doc).
#[derive(Debug, Clone)]
pub struct Observe<S> {
    inner: S,
    next_id: Arc<AtomicU64>,
}

impl<S, B> Service<Request<B>> for Observe<S>
where
    S: Service<Request<B>, Response = Response<Body>> + Clone + Send + 'static,
    S::Future: Send + 'static,
    B: Send + 'static,
{
    type Response = Response<Body>;
    type Error = S::Error;
    type Future = Pin<Box<dyn Future<Output = Result<Response<Body>, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut request: Request<B>) -> Self::Future {
        let method = method_of(request.uri().path()).to_string();
        let id = self.request_id(request.headers());
        let id_header = HeaderValue::from_str(&id).ok();
        if let Some(value) = &id_header {
            request.headers_mut().insert(REQUEST_ID, value.clone());
        }
        let span = info_span!("call", method = %method, request_id = %id);
        let call = Call::start(method, span.clone());
        // The service polled ready is the one to call; a clone waits for the next call.
        let ready = self.inner.clone();
        let future = std::mem::replace(&mut self.inner, ready)
            .call(request)
            .instrument(span);
        Box::pin(async move {
            let mut response = match future.await {
                Ok(response) => response,
                Err(error) => {
                    call.finish(&Status::unknown("the transport failed"));
                    return Err(error);
                }
            };
            let status = Status::from_header_map(response.headers());
            // The codec's refusals, named as the handlers' are.
            let named = status.as_ref().and_then(super::status::codec_status);
            if let Some(named) = &named {
                response = named.clone().into_http();
            }
            if let Some(value) = id_header {
                response.headers_mut().insert(REQUEST_ID, value);
            }
            match named.or(status) {
                Some(status) => {
                    call.finish(&status);
                    Ok(response)
                }
                None => Ok(response.map(|body| {
                    Body::new(ObservedBody {
                        inner: body,
                        call: Some(call),
                    })
                })),
            }
        })
    }
}

impl<S> Observe<S> {
    /// The caller's id (first 64 characters), or the next of this server's own.
    fn request_id(&self, headers: &HeaderMap) -> String {
        headers
            .get(REQUEST_ID)
            .and_then(|v| v.to_str().ok())
            .filter(|s| !s.is_empty())
            .map(|s| s.chars().take(64).collect())
            .unwrap_or_else(|| format!("r{}", self.next_id.fetch_add(1, Ordering::Relaxed) + 1))
    }
}

/// `/package.Service/Method` → `Method`.
fn method_of(path: &str) -> &str {
    path.rsplit('/').next().unwrap_or(path)
}

/// One call in flight: counted in the gauge while it lives, recorded once when it finishes (or
/// as `CANCELLED` when it is dropped unfinished).
struct Call {
    method: String,
    span: Span,
    started: Instant,
    finished: bool,
}

impl Call {
    fn start(method: String, span: Span) -> Call {
        metrics::gauge!("alignist_in_flight_requests", "method" => method.clone()).increment(1.0);
        Call {
            method,
            span,
            started: Instant::now(),
            finished: false,
        }
    }

    /// Records the call's code, latency and log line.
    fn finish(mut self, status: &Status) {
        self.record(status);
    }

    fn record(&mut self, status: &Status) {
        if std::mem::replace(&mut self.finished, true) {
            return;
        }
        let code = code_name(status.code());
        let method = self.method.clone();
        let seconds = self.started.elapsed().as_secs_f64();
        metrics::counter!("alignist_requests_total", "method" => method.clone(), "code" => code)
            .increment(1);
        metrics::histogram!("alignist_request_seconds", "method" => method, "code" => code)
            .record(seconds);
        let _entered = self.span.enter();
        let ms = seconds * 1e3;
        if status.code() == Code::Ok {
            info!(code, ms, "done");
        } else {
            warn!(code, ms, message = status.message(), "failed");
        }
    }
}

impl Drop for Call {
    fn drop(&mut self) {
        self.record(&Status::cancelled(
            "the client went away before the answer ended",
        ));
        metrics::gauge!("alignist_in_flight_requests", "method" => self.method.clone())
            .decrement(1.0);
    }
}

/// A response body that records its call when its trailers (or its end, or an error) arrive.
struct ObservedBody {
    inner: Body,
    call: Option<Call>,
}

impl ObservedBody {
    fn finish(&mut self, status: &Status) {
        if let Some(call) = self.call.take() {
            call.finish(status);
        }
    }
}

impl http_body::Body for ObservedBody {
    type Data = bytes::Bytes;
    type Error = Status;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<bytes::Bytes>, Status>>> {
        let polled = Pin::new(&mut self.inner).poll_frame(cx);
        match &polled {
            Poll::Ready(Some(Ok(frame))) => {
                if let Some(trailers) = frame.trailers_ref() {
                    let status = Status::from_header_map(trailers)
                        .unwrap_or_else(|| Status::unknown("trailers without a grpc-status"));
                    self.finish(&status);
                }
            }
            Poll::Ready(Some(Err(status))) => self.finish(status),
            Poll::Ready(None) => self.finish(&Status::unknown("the answer ended without a status")),
            Poll::Pending => {}
        }
        polled
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

/// The canonical name of a gRPC code, as metric labels and logs write it.
pub fn code_name(code: Code) -> &'static str {
    use Code::*;
    match code {
        Ok => "OK",
        Cancelled => "CANCELLED",
        Unknown => "UNKNOWN",
        InvalidArgument => "INVALID_ARGUMENT",
        DeadlineExceeded => "DEADLINE_EXCEEDED",
        NotFound => "NOT_FOUND",
        AlreadyExists => "ALREADY_EXISTS",
        PermissionDenied => "PERMISSION_DENIED",
        ResourceExhausted => "RESOURCE_EXHAUSTED",
        FailedPrecondition => "FAILED_PRECONDITION",
        Aborted => "ABORTED",
        OutOfRange => "OUT_OF_RANGE",
        Unimplemented => "UNIMPLEMENTED",
        Internal => "INTERNAL",
        Unavailable => "UNAVAILABLE",
        DataLoss => "DATA_LOSS",
        Unauthenticated => "UNAUTHENTICATED",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_method_is_the_paths_last_segment() {
        assert_eq!(method_of("/alignist.v1.Alignist/Predict"), "Predict");
        assert_eq!(method_of("/grpc.health.v1.Health/Check"), "Check");
    }
}
