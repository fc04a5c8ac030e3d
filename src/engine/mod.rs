//! The inference engine: loaded bundles, request images, full distributions, coarse-to-fine top-k,
//! modes and RGB-D fusion. No transport here: the gRPC service (src/serve) converts its messages
//! into these calls, and everything is testable without a socket.
//!
//! The front door, on a [`Model`] of the [`Engine`], features as plain rows
//! ([`Model::features`]):
//! - [`Model::predict`] (one image) and [`Model::predict_checked`] (images whose options were
//!   checked once by [`Model::check_predict`]): top-k, modes, translations with depth;
//! - [`Model::predict_frame`]: a camera frame's detections, planned by [`Model::plan_frame`] (crops,
//!   rays, depth) and answered in the real camera's frame ([`FramePlan::in_camera_frame`]);
//! - [`Model::distribution`]: a full level.
//!
//! Files: `config` (settings), `model` (the model and its scoring), `depth_search` (depth in the
//! search), `frame` (camera frames), `loader` (the models directory), and the parts they use
//! (`image`, `depth`, `fusion`, `search`, `calibrate`, `cancel`).

pub mod calibrate;
pub mod cancel;
pub mod config;
pub mod depth;
mod depth_search;
pub mod frame;
pub mod fusion;
pub mod image;
mod loader;
mod model;
pub mod search;

pub use self::image::{
    CropBox, FrameCrop, ImageLimits, ImageRequest, Intrinsics, prepare_frame, prepare_image,
};
pub use cancel::{Cancel, CancelOnDrop};
pub use config::{EngineConfig, KEEP_TAPER, MAX_TOP_K, RESCORED_CELLS, SearchParams};
pub use depth::{BackProjected, DepthMap, DepthRequest, back_project, decode_depth, decode_mask};
pub use depth_search::{DepthInput, SeenPoints};
pub use frame::{CropDepth, Detection, DetectionDepth, FramePlan, FrameQuery, MAX_DETECTIONS};
pub use fusion::{CameraPoints, DepthFusion, ViewTable};
pub use loader::Engine;
pub use model::{
    CheckedPredict, DEFAULT_MODE_ANGLE_DEG, Distribution, Model, ModelObject, PredictOptions,
    Prediction,
};
pub use search::{CellProbability, Mode, SearchResult, coarse_to_fine_many, group_modes};

use std::path::PathBuf;

use crate::bundle::BundleError;

/// Errors of the engine; each maps to one gRPC status code in the service.
#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    /// A request field is malformed.
    #[error("{field}: {message}")]
    InvalidArgument {
        /// The request field.
        field: String,
        /// What is wrong with it.
        message: String,
    },
    /// An unknown model or object.
    #[error("{0}")]
    NotFound(String),
    /// A request over a size limit.
    #[error("{field}: {message}")]
    ResourceExhausted {
        /// The request field.
        field: String,
        /// The limit.
        message: String,
    },
    /// A bundle that cannot be loaded.
    #[error("{0}")]
    Bundle(#[from] BundleError),
    /// A grid level that cannot be built.
    #[error("grid: {0}")]
    Grid(#[from] crate::so3::So3Error),
    /// A models directory that cannot be read.
    #[error("{path}: {source}")]
    Io {
        /// The directory.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// A models directory that cannot be served (no bundle in it, or none loads).
    #[error("{0}")]
    Models(String),
    /// The work was abandoned: its caller went away ([`Cancel`]).
    #[error("cancelled: the caller went away")]
    Cancelled,
}

/// A name from a request as messages and logs show it: quoted, control characters escaped, at
/// most 64 characters (a longer one would not fit a status's metadata; a `\n` would forge a log
/// line).
pub fn quoted_name(name: &str) -> String {
    const MOST: usize = 64;
    let escaped: String = name
        .chars()
        .take(MOST)
        .flat_map(char::escape_debug)
        .collect();
    match name.chars().count() > MOST {
        true => format!("'{escaped}…' ({} characters)", name.chars().count()),
        false => format!("'{escaped}'"),
    }
}

fn invalid(field: &str, message: impl Into<String>) -> EngineError {
    EngineError::InvalidArgument {
        field: field.into(),
        message: message.into(),
    }
}
