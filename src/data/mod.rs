//! Datasets: renders written and read in the BOP layout, object-centred crops.

pub mod bop;
pub mod realism;
mod render_set;
pub mod virtual_crop;

pub use bop::{BopDataset, BopSample, BopWriter, Crop, SceneGtInfo};
pub use render_set::{RenderJob, SYMSOL_DISTANCE, render_dataset, symsol_pose};

use std::path::Path;

use crate::cad::CadError;

/// Errors reading or writing datasets; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// A file or folder could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// An image could not be decoded or encoded.
    #[error("{path}: {message}")]
    Image {
        /// The file.
        path: String,
        /// What went wrong.
        message: String,
    },
    /// A file whose content is not what the layout requires.
    #[error("{file}: {message}")]
    Invalid {
        /// The file.
        file: String,
        /// What is wrong, naming the field.
        message: String,
    },
    /// A mesh problem.
    #[error(transparent)]
    Cad(#[from] CadError),
}

impl DataError {
    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        DataError::Io {
            path: path.display().to_string(),
            source,
        }
    }

    pub(crate) fn image(path: &Path, e: impl std::fmt::Display) -> Self {
        DataError::Image {
            path: path.display().to_string(),
            message: e.to_string(),
        }
    }
}
