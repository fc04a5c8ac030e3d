//! gRPC statuses with the standard rich details (`google.rpc` `BadRequest`, `ErrorInfo`,
//! `RetryInfo`, through `tonic-types`), so that a client can tell situations apart without
//! reading the message: which field is wrong, why a call was refused, and whether and when to
//! retry.

use std::time::Duration;

use tonic::{Code, Status};
use tonic_types::{ErrorDetails, StatusExt};

use super::BatchError;
use crate::engine::EngineError;

/// The `ErrorInfo` domain of every reason below.
pub const DOMAIN: &str = "alignist.v1";

/// Why a call was refused or failed, as `ErrorInfo.reason`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reason {
    /// The model's encoder queue is full (UNAVAILABLE, retry).
    QueueFull,
    /// The in-flight image budget is spent (RESOURCE_EXHAUSTED, retry).
    AdmissionFull,
    /// The server has not loaded its models yet (UNAVAILABLE, retry).
    ModelsLoading,
    /// The server or the model is shutting down (UNAVAILABLE, retry on another replica).
    ShuttingDown,
    /// The model failed on this call (INTERNAL; the next call may succeed).
    ModelFailed,
    /// A request field is malformed (INVALID_ARGUMENT, with a `BadRequest` violation).
    InvalidField,
    /// A request is over a size limit (RESOURCE_EXHAUSTED, no retry helps).
    TooLarge,
    /// An unknown model or object (NOT_FOUND).
    NotFound,
    /// The caller went away and its work was stopped (CANCELLED; nobody reads it).
    Cancelled,
    /// A request message that does not decode (INVALID_ARGUMENT).
    MalformedMessage,
    /// A request body that did not arrive within the body timeout (DEADLINE_EXCEEDED).
    BodyTimeout,
}

impl Reason {
    /// The reason's name, `[A-Z0-9_]+`.
    pub fn name(self) -> &'static str {
        match self {
            Reason::QueueFull => "QUEUE_FULL",
            Reason::AdmissionFull => "ADMISSION_FULL",
            Reason::ModelsLoading => "MODELS_LOADING",
            Reason::ShuttingDown => "SHUTTING_DOWN",
            Reason::ModelFailed => "MODEL_FAILED",
            Reason::InvalidField => "INVALID_FIELD",
            Reason::TooLarge => "TOO_LARGE",
            Reason::NotFound => "NOT_FOUND",
            Reason::Cancelled => "CANCELLED",
            Reason::MalformedMessage => "MALFORMED_MESSAGE",
            Reason::BodyTimeout => "BODY_TIMEOUT",
        }
    }
}

/// A status with an `ErrorInfo` reason and, when `retry` is given, a `RetryInfo` delay.
pub fn refused(code: Code, reason: Reason, message: String, retry: Option<Duration>) -> Status {
    let mut details = ErrorDetails::new();
    details.set_error_info(
        reason.name(),
        DOMAIN,
        std::collections::HashMap::<String, String>::new(),
    );
    if retry.is_some() {
        details.set_retry_info(retry);
    }
    Status::with_error_details(code, message, details)
}

/// INVALID_ARGUMENT naming `field` in the message and in a `BadRequest` field violation.
pub fn invalid_field(field: &str, description: impl Into<String>) -> Status {
    let description = description.into();
    let mut details = ErrorDetails::with_bad_request_violation(field, description.clone());
    details.set_error_info(
        Reason::InvalidField.name(),
        DOMAIN,
        std::collections::HashMap::<String, String>::new(),
    );
    Status::with_error_details(
        Code::InvalidArgument,
        format!("{field}: {description}"),
        details,
    )
}

/// UNAVAILABLE while models load.
pub fn models_loading() -> Status {
    refused(
        Code::Unavailable,
        Reason::ModelsLoading,
        "models are still loading; retry shortly".into(),
        Some(Duration::from_secs(1)),
    )
}

/// The gRPC status of an engine error.
pub fn status_of(error: EngineError) -> Status {
    match error {
        EngineError::InvalidArgument { field, message } => invalid_field(&field, message),
        EngineError::NotFound(message) => refused(Code::NotFound, Reason::NotFound, message, None),
        EngineError::ResourceExhausted { field, message } => {
            let mut details = ErrorDetails::with_bad_request_violation(&field, message.clone());
            details.set_error_info(
                Reason::TooLarge.name(),
                DOMAIN,
                std::collections::HashMap::<String, String>::new(),
            );
            Status::with_error_details(
                Code::ResourceExhausted,
                format!("{field}: {message}"),
                details,
            )
        }
        EngineError::Bundle(_)
        | EngineError::Models(_)
        | EngineError::Grid(_)
        | EngineError::Io { .. } => {
            refused(Code::Internal, Reason::ModelFailed, error.to_string(), None)
        }
        EngineError::Cancelled => {
            metrics::counter!("alignist_abandoned_work_total").increment(1);
            refused(Code::Cancelled, Reason::Cancelled, error.to_string(), None)
        }
    }
}

/// The gRPC status of a batching error.
pub fn batch_status(error: BatchError) -> Status {
    let message = error.to_string();
    match error {
        BatchError::QueueFull { .. } => refused(
            Code::Unavailable,
            Reason::QueueFull,
            message,
            Some(Duration::from_millis(100)),
        ),
        BatchError::Stopped(_) => refused(
            Code::Unavailable,
            Reason::ShuttingDown,
            message,
            Some(Duration::from_millis(100)),
        ),
        BatchError::WorkerFailed { .. } => {
            refused(Code::Internal, Reason::ModelFailed, message, None)
        }
    }
}

/// The named status of an error the gRPC codec raised before any handler ran, or `None` for
/// the statuses of handlers. tonic answers a message that does not decode with INTERNAL and no
/// details, and one over the size limit with OUT_OF_RANGE: here they become INVALID_ARGUMENT
/// (`MALFORMED_MESSAGE`) and RESOURCE_EXHAUSTED (`TOO_LARGE`), as in DEPLOY.md's table.
pub fn codec_status(status: &Status) -> Option<Status> {
    let message = status.message();
    match status.code() {
        Code::Internal
            if message.starts_with("failed to decode Protobuf message")
                || message.starts_with("Unexpected EOF decoding stream")
                || message.starts_with("protocol error: received message with") =>
        {
            Some(refused(
                Code::InvalidArgument,
                Reason::MalformedMessage,
                format!("the request message does not decode: {message}"),
                None,
            ))
        }
        Code::OutOfRange if message.contains("decoded message length too large") => {
            let mut details = ErrorDetails::new();
            details.set_error_info(
                Reason::TooLarge.name(),
                DOMAIN,
                std::collections::HashMap::<String, String>::new(),
            );
            Some(Status::with_error_details(
                Code::ResourceExhausted,
                format!("the request message is over the size limit: {message}"),
                details,
            ))
        }
        _ => None,
    }
}
