//! Bounds on the transport, below the gRPC handlers: how many connections the server holds, how
//! long a connection may take to say anything and may stay silent, and how long a request body
//! may take to arrive and how many bytes of unfinished bodies the server holds.
//!
//! - [`BoundedIncoming`] accepts TCP connections up to [`TransportLimits::max_connections`]. At
//!   the cap, a new connection evicts the oldest one that has not yet sent its first bytes (an
//!   idle socket must not lock out a real client); with none such it is refused, counted and
//!   logged (at most once a second).
//! - [`GuardedIo`] closes a connection that sends fewer than [`HANDSHAKE_BYTES`] within the
//!   handshake timeout, or that moves no byte either way for the idle timeout.
//! - [`BodyLimitLayer`] fails a call whose request body has not arrived within the body timeout
//!   (DEADLINE_EXCEEDED) or whose unfinished bodies, with everyone else's, would hold more than
//!   the receive budget (RESOURCE_EXHAUSTED): the body and what was buffered of it are dropped.

use std::collections::VecDeque;
use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::task::{Context, Poll, Waker};
use std::time::{Duration, Instant};

use bytes::Bytes;
use http::Request;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::time::Sleep;
use tonic::body::Body;
use tonic::transport::server::{Connected, TcpConnectInfo};
use tower::{Layer, Service};
use tracing::warn;

use super::status::{Reason, refused};

/// Bytes a connection must send within the handshake timeout: the HTTP/2 client preface
/// (`PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n`) is 24; a TLS ClientHello is longer.
pub const HANDSHAKE_BYTES: usize = 24;

/// The transport's limits.
#[derive(Debug, Clone, Copy)]
pub struct TransportLimits {
    /// Most connections held at once.
    pub max_connections: usize,
    /// Longest a new connection may take to send [`HANDSHAKE_BYTES`].
    pub handshake_timeout: Duration,
    /// Longest a connection may move no byte either way.
    pub idle_timeout: Duration,
    /// Longest a request body may take to arrive, from its first byte of headers.
    pub body_timeout: Duration,
    /// Most bytes of unfinished request bodies held at once, over all connections.
    pub max_receiving_bytes: usize,
}

impl Default for TransportLimits {
    fn default() -> Self {
        Self {
            // Under the container's usual `ulimit -n` of 1 024, with room for files and models.
            max_connections: 512,
            handshake_timeout: Duration::from_secs(10),
            idle_timeout: Duration::from_secs(300),
            body_timeout: Duration::from_secs(30),
            max_receiving_bytes: 256 << 20,
        }
    }
}

/// What the accept loop and a connection share: whether it may be evicted and how to wake it.
#[derive(Debug, Default)]
struct ConnState {
    /// It has sent its handshake bytes: no longer evictable.
    handshaken: AtomicBool,
    /// Its slot under the cap is given back, by eviction or by its end, whichever came first
    /// (exactly one of them counts it off). Once evicted, its next poll fails.
    evicted: AtomicBool,
    waker: Mutex<Option<Waker>>,
}

impl ConnState {
    /// Marks the connection evicted and wakes it; false if it is past its handshake or its slot
    /// was given back already.
    fn evict(&self) -> bool {
        if self.handshaken.load(Ordering::SeqCst) || self.evicted.swap(true, Ordering::SeqCst) {
            return false;
        }
        if let Some(w) = self.waker.lock().unwrap_or_else(|e| e.into_inner()).take() {
            w.wake();
        }
        true
    }
}

/// The connections held, and those not yet past their handshake (oldest first).
#[derive(Debug, Default)]
struct Registry {
    open: AtomicUsize,
    pending: Mutex<VecDeque<Weak<ConnState>>>,
    /// The second since [`Registry::epoch`] (plus one) of the last "connection cap" log line.
    last_log: AtomicU64,
    epoch: Option<Instant>,
}

impl Registry {
    /// Evicts the oldest connection that has not sent its handshake bytes and gives its slot
    /// back at once (its task closes the socket when next polled, which under load can come
    /// after the next accepts); false if none.
    fn evict_oldest_pending(&self) -> bool {
        let mut pending = self.pending.lock().unwrap_or_else(|e| e.into_inner());
        while let Some(weak) = pending.pop_front() {
            if let Some(conn) = weak.upgrade()
                && conn.evict()
            {
                self.release();
                metrics::counter!("alignist_connections_closed_total", "reason" => "evicted")
                    .increment(1);
                return true;
            }
        }
        false
    }

    /// Logs the refusal at most once a second.
    fn log_refusal(&self, max: usize) {
        // The second since the epoch, plus one: 0 means "never logged".
        let second = self.epoch.map_or(0, |e| e.elapsed().as_secs()) + 1;
        if self.last_log.swap(second, Ordering::Relaxed) != second {
            warn!(
                max_connections = max,
                "connection refused: the server holds its most connections"
            );
        }
    }
}

impl Registry {
    /// One connection's slot given back.
    fn release(&self) {
        let open = self.open.fetch_sub(1, Ordering::SeqCst) - 1;
        metrics::gauge!("alignist_connections_open").set(open as f64);
    }
}

/// Holds an open connection's slot until dropped, unless an eviction gave it back first.
#[derive(Debug)]
struct Open {
    registry: Arc<Registry>,
    state: Arc<ConnState>,
}

impl Drop for Open {
    fn drop(&mut self) {
        if !self.state.evicted.swap(true, Ordering::SeqCst) {
            self.registry.release();
        }
    }
}

/// The accepted connections of a listener, bounded (module doc).
pub struct BoundedIncoming {
    listener: TcpListener,
    limits: TransportLimits,
    registry: Arc<Registry>,
    /// A pause after an accept error.
    pause: Option<Pin<Box<Sleep>>>,
}

impl BoundedIncoming {
    /// Accepts from `listener` within `limits`.
    pub fn new(listener: TcpListener, limits: TransportLimits) -> Self {
        Self {
            listener,
            limits,
            registry: Arc::new(Registry {
                epoch: Some(Instant::now()),
                ..Registry::default()
            }),
            pause: None,
        }
    }

    /// The connection, or `None` when it is refused at the cap.
    fn admit(&self, stream: TcpStream) -> Option<GuardedIo> {
        let registry = &self.registry;
        if registry.open.load(Ordering::SeqCst) >= self.limits.max_connections
            && !registry.evict_oldest_pending()
        {
            metrics::counter!("alignist_connections_refused_total").increment(1);
            registry.log_refusal(self.limits.max_connections);
            return None;
        }
        let _ = stream.set_nodelay(true);
        let open = registry.open.fetch_add(1, Ordering::SeqCst) + 1;
        metrics::gauge!("alignist_connections_open").set(open as f64);
        let state = Arc::new(ConnState::default());
        let mut pending = registry.pending.lock().unwrap_or_else(|e| e.into_inner());
        // Forget the connections that are gone or past their handshake, now and then.
        if pending.len() >= self.limits.max_connections {
            pending.retain(|w| {
                w.upgrade()
                    .is_some_and(|c| !c.handshaken.load(Ordering::SeqCst))
            });
        }
        pending.push_back(Arc::downgrade(&state));
        Some(GuardedIo {
            inner: stream,
            state: state.clone(),
            received: 0,
            deadline: Box::pin(tokio::time::sleep(self.limits.handshake_timeout)),
            idle_timeout: self.limits.idle_timeout,
            _open: Open {
                registry: registry.clone(),
                state,
            },
        })
    }
}

impl tokio_stream::Stream for BoundedIncoming {
    type Item = io::Result<GuardedIo>;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        if let Some(pause) = self.pause.as_mut() {
            if pause.as_mut().poll(cx).is_pending() {
                return Poll::Pending;
            }
            self.pause = None;
        }
        loop {
            match self.listener.poll_accept(cx) {
                Poll::Ready(Ok((stream, _))) => {
                    if let Some(io) = self.admit(stream) {
                        return Poll::Ready(Some(Ok(io)));
                    }
                }
                // Out of file descriptors and the like: counted and logged; accepting goes on
                // after a pause (the error would repeat at once).
                Poll::Ready(Err(e)) => {
                    metrics::counter!("alignist_connections_refused_total").increment(1);
                    self.registry.log_refusal(self.limits.max_connections);
                    warn!("accepting a connection failed: {e}");
                    let mut pause = Box::pin(tokio::time::sleep(Duration::from_millis(50)));
                    if pause.as_mut().poll(cx).is_pending() {
                        self.pause = Some(pause);
                        return Poll::Pending;
                    }
                }
                Poll::Pending => return Poll::Pending,
            }
        }
    }
}

/// An accepted connection with its handshake and idle deadlines (module doc).
pub struct GuardedIo {
    inner: TcpStream,
    state: Arc<ConnState>,
    received: usize,
    /// The handshake deadline until [`HANDSHAKE_BYTES`] arrived, the idle deadline after.
    deadline: Pin<Box<Sleep>>,
    idle_timeout: Duration,
    _open: Open,
}

impl GuardedIo {
    /// Bytes moved: the idle deadline starts again (once past the handshake).
    fn moved(&mut self, received: usize) {
        self.received = self.received.saturating_add(received);
        if self.received >= HANDSHAKE_BYTES {
            self.state.handshaken.store(true, Ordering::SeqCst);
            let next = tokio::time::Instant::now() + self.idle_timeout;
            // Resetting the timer on every read is wasted work; a second's slack is enough.
            if next > self.deadline.deadline() + Duration::from_secs(1) {
                self.deadline.as_mut().reset(next);
            }
        }
    }

    /// An error when the connection was evicted or its deadline passed.
    fn expired(&mut self, cx: &mut Context<'_>) -> Option<io::Error> {
        if self.state.evicted.load(Ordering::SeqCst) {
            return Some(io::Error::new(
                io::ErrorKind::ConnectionAborted,
                "evicted at the connection cap before its handshake",
            ));
        }
        *self.state.waker.lock().unwrap_or_else(|e| e.into_inner()) = Some(cx.waker().clone());
        if self.deadline.as_mut().poll(cx).is_ready() {
            let reason = match self.state.handshaken.load(Ordering::SeqCst) {
                true => "idle_timeout",
                false => "handshake_timeout",
            };
            metrics::counter!("alignist_connections_closed_total", "reason" => reason).increment(1);
            return Some(io::Error::new(io::ErrorKind::TimedOut, reason));
        }
        None
    }
}

impl AsyncRead for GuardedIo {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let before = buf.filled().len();
        match Pin::new(&mut self.inner).poll_read(cx, buf) {
            Poll::Ready(Ok(())) => {
                let n = buf.filled().len() - before;
                self.moved(n);
                Poll::Ready(Ok(()))
            }
            Poll::Ready(Err(e)) => Poll::Ready(Err(e)),
            Poll::Pending => match self.expired(cx) {
                Some(e) => Poll::Ready(Err(e)),
                None => Poll::Pending,
            },
        }
    }
}

impl AsyncWrite for GuardedIo {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        data: &[u8],
    ) -> Poll<io::Result<usize>> {
        if let Some(e) = self.expired(cx) {
            return Poll::Ready(Err(e));
        }
        let written = Pin::new(&mut self.inner).poll_write(cx, data);
        if let Poll::Ready(Ok(_)) = written {
            self.moved(0);
        }
        written
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

impl Connected for GuardedIo {
    type ConnectInfo = TcpConnectInfo;

    fn connect_info(&self) -> TcpConnectInfo {
        self.inner.connect_info()
    }
}

/// Bytes of unfinished request bodies held, over all calls.
#[derive(Debug)]
struct ReceiveBudget {
    held: AtomicUsize,
    max: usize,
}

impl ReceiveBudget {
    fn take(&self, bytes: usize) -> bool {
        let taken = self
            .held
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |held| {
                held.checked_add(bytes).filter(|&h| h <= self.max)
            })
            .is_ok();
        if taken {
            metrics::gauge!("alignist_receiving_bytes").increment(bytes as f64);
        }
        taken
    }

    fn release(&self, bytes: usize) {
        self.held.fetch_sub(bytes, Ordering::SeqCst);
        metrics::gauge!("alignist_receiving_bytes").decrement(bytes as f64);
    }
}

/// Bounds every request body of a server (module doc).
#[derive(Debug, Clone)]
pub struct BodyLimitLayer {
    timeout: Duration,
    budget: Arc<ReceiveBudget>,
}

impl BodyLimitLayer {
    /// Bodies within `limits`' body timeout and receive budget.
    pub fn new(limits: &TransportLimits) -> Self {
        Self {
            timeout: limits.body_timeout,
            budget: Arc::new(ReceiveBudget {
                held: AtomicUsize::new(0),
                max: limits.max_receiving_bytes,
            }),
        }
    }
}

impl<S> Layer<S> for BodyLimitLayer {
    type Service = BodyLimit<S>;

    fn layer(&self, inner: S) -> BodyLimit<S> {
        BodyLimit {
            inner,
            layer: self.clone(),
        }
    }
}

/// A service whose request bodies are bounded ([`BodyLimitLayer`]).
#[derive(Debug, Clone)]
pub struct BodyLimit<S> {
    inner: S,
    layer: BodyLimitLayer,
}

impl<S> Service<Request<Body>> for BodyLimit<S>
where
    S: Service<Request<Body>>,
{
    type Response = S::Response;
    type Error = S::Error;
    type Future = S::Future;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: Request<Body>) -> S::Future {
        let layer = self.layer.clone();
        self.inner.call(request.map(|body| {
            Body::new(LimitedBody {
                inner: body,
                deadline: Box::pin(tokio::time::sleep(layer.timeout)),
                timeout: layer.timeout,
                budget: layer.budget,
                held: 0,
                done: false,
            })
        }))
    }
}

/// A request body with a deadline and a share of the receive budget.
struct LimitedBody {
    inner: Body,
    deadline: Pin<Box<Sleep>>,
    timeout: Duration,
    budget: Arc<ReceiveBudget>,
    /// Bytes of this body counted in the budget.
    held: usize,
    /// The body has ended: no deadline, nothing held.
    done: bool,
}

impl LimitedBody {
    fn release(&mut self) {
        self.budget.release(std::mem::take(&mut self.held));
    }
}

impl Drop for LimitedBody {
    fn drop(&mut self) {
        self.release();
    }
}

impl http_body::Body for LimitedBody {
    type Data = Bytes;
    type Error = tonic::Status;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, tonic::Status>>> {
        let this = &mut *self;
        let frame = Pin::new(&mut this.inner).poll_frame(cx);
        if this.done {
            return frame;
        }
        match frame {
            Poll::Ready(Some(Ok(frame))) => {
                let bytes = frame.data_ref().map_or(0, Bytes::len);
                if !this.budget.take(bytes) {
                    metrics::counter!("alignist_refused_total", "reason" => "receive_budget")
                        .increment(1);
                    return Poll::Ready(Some(Err(refused(
                        tonic::Code::ResourceExhausted,
                        Reason::AdmissionFull,
                        format!(
                            "the server holds its most bytes of unfinished request bodies ({} MiB); \
                             retry later",
                            this.budget.max >> 20
                        ),
                        Some(Duration::from_millis(200)),
                    ))));
                }
                this.held += bytes;
                Poll::Ready(Some(Ok(frame)))
            }
            Poll::Ready(None) => {
                this.done = true;
                this.release();
                Poll::Ready(None)
            }
            Poll::Ready(Some(Err(e))) => Poll::Ready(Some(Err(e))),
            Poll::Pending => {
                if this.deadline.as_mut().poll(cx).is_ready() {
                    metrics::counter!("alignist_refused_total", "reason" => "body_timeout")
                        .increment(1);
                    return Poll::Ready(Some(Err(refused(
                        tonic::Code::DeadlineExceeded,
                        Reason::BodyTimeout,
                        format!(
                            "the request body did not arrive within {} s",
                            this.timeout.as_secs_f64()
                        ),
                        None,
                    ))));
                }
                Poll::Pending
            }
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}
