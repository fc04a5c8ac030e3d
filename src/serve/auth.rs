//! An optional bearer token: with one configured, every call but the health checks (which
//! orchestrators' probes make without credentials) must carry `authorization: Bearer TOKEN`,
//! compared in constant time; others get UNAUTHENTICATED before any of their work.

use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};

use http::{Request, Response};
use subtle::ConstantTimeEq;
use tonic::body::Body;
use tower::{Layer, Service};

/// The path prefix of the gRPC health service, open without a token.
pub const HEALTH_PREFIX: &str = "/grpc.health.v1.Health/";

/// A bearer token read from a file (its surrounding whitespace trimmed).
#[derive(Clone)]
pub struct Token(Arc<[u8]>);

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Token(…)")
    }
}

/// Why a token file cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum TokenError {
    /// The file cannot be read.
    #[error("{path}: {source}")]
    Read {
        /// The file.
        path: String,
        /// Why.
        source: std::io::Error,
    },
    /// The file holds no usable token.
    #[error("{path}: {message}")]
    Invalid {
        /// The file.
        path: String,
        /// What is wrong.
        message: String,
    },
}

impl Token {
    /// The token in `path`: one line of visible ASCII (what an HTTP header can carry), at least
    /// 16 characters.
    pub fn from_file(path: &std::path::Path) -> Result<Token, TokenError> {
        let name = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| TokenError::Read {
            path: name.clone(),
            source,
        })?;
        Token::parse(text.trim()).map_err(|message| TokenError::Invalid {
            path: name,
            message,
        })
    }

    /// A token from its text (checked as [`Token::from_file`] says).
    pub fn parse(text: &str) -> Result<Token, String> {
        if text.len() < 16 {
            return Err(format!(
                "the token is {} characters; use at least 16 (e.g. `openssl rand -hex 32`)",
                text.len()
            ));
        }
        if !text.bytes().all(|b| b.is_ascii_graphic()) {
            return Err("the token must be one line of visible ASCII characters".into());
        }
        Ok(Token(text.as_bytes().into()))
    }

    /// The token as sent: the text of the file.
    pub fn as_str(&self) -> &str {
        std::str::from_utf8(&self.0).unwrap_or_default()
    }

    /// Whether an `authorization` header value carries this token (`Bearer TOKEN`), compared in
    /// constant time.
    pub fn admits(&self, header: Option<&[u8]>) -> bool {
        let Some(given) = header.and_then(|h| h.strip_prefix(b"Bearer ")) else {
            return false;
        };
        given.ct_eq(&self.0).into()
    }
}

/// Adds [`Auth`] to every service of a server.
#[derive(Debug, Clone)]
pub struct AuthLayer {
    token: Option<Token>,
}

impl AuthLayer {
    /// Checks calls against `token` (`None`: every call passes).
    pub fn new(token: Option<Token>) -> Self {
        Self { token }
    }
}

impl<S> Layer<S> for AuthLayer {
    type Service = Auth<S>;

    fn layer(&self, inner: S) -> Auth<S> {
        Auth {
            inner,
            token: self.token.clone(),
        }
    }
}

/// A service that refuses calls without the token ([`AuthLayer`]).
#[derive(Debug, Clone)]
pub struct Auth<S> {
    inner: S,
    token: Option<Token>,
}

type BoxFuture<T, E> = Pin<Box<dyn Future<Output = Result<T, E>> + Send>>;

impl<S, B> Service<Request<B>> for Auth<S>
where
    S: Service<Request<B>, Response = Response<Body>>,
    S::Future: Send + 'static,
    S::Error: Send + 'static,
{
    type Response = Response<Body>;
    type Error = S::Error;
    type Future = BoxFuture<Response<Body>, S::Error>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: Request<B>) -> Self::Future {
        let open = request.uri().path().starts_with(HEALTH_PREFIX);
        let admitted = match &self.token {
            None => true,
            Some(token) => {
                open || token.admits(
                    request
                        .headers()
                        .get(http::header::AUTHORIZATION)
                        .map(|v| v.as_bytes()),
                )
            }
        };
        if admitted {
            return Box::pin(self.inner.call(request));
        }
        metrics::counter!("alignist_unauthenticated_total").increment(1);
        let status = tonic::Status::unauthenticated(
            "this server needs `authorization: Bearer TOKEN` (the CLI's --token-file)",
        );
        Box::pin(std::future::ready(Ok(status.into_http())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_exact_bearer_token_is_admitted() -> Result<(), String> {
        let token = Token::parse("0123456789abcdef0123")?;
        assert!(token.admits(Some(b"Bearer 0123456789abcdef0123")));
        for wrong in [
            &b"Bearer 0123456789abcdef012"[..],
            b"Bearer 0123456789abcdef01234",
            b"bearer 0123456789abcdef0123",
            b"0123456789abcdef0123",
            b"",
        ] {
            assert!(!token.admits(Some(wrong)), "{wrong:?}");
        }
        assert!(!token.admits(None));
        assert!(Token::parse("short").is_err());
        assert!(Token::parse("has a space in it!!").is_err());
        Ok(())
    }
}
