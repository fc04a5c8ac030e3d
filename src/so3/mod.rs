//! The SO(3) core: the nested equivolumetric grid, sampling, angles and conversions, symmetry
//! groups, and the metrics of distributions over the grid.

pub mod grid;
pub mod metrics;
pub mod modes;
mod rotation;
mod sample;
mod symmetry;

pub use grid::{GridConvention, GridLevel, MAX_LEVEL, covering_radius};
pub use rotation::{
    from_quaternion, from_row_major, geodesic_angle, nearest_rotation, quaternion_angle,
    quaternion_dot, rot_x, rot_y, rot_z, to_quaternion, to_row_major, to_row_major_f32,
};
pub use sample::{haar_rotation, haar_rotations, jitter_in_cell, random_axis};
pub use symmetry::{
    CONTINUOUS_STEPS, GOLDEN_RATIO, SymmetryGroup, cube_vertices, equivalents,
    icosahedron_vertices, maps_set_to_itself, tetrahedron_vertices,
};

/// Errors of the SO(3) core.
#[derive(Debug, thiserror::Error)]
pub enum So3Error {
    /// A grid level above the supported maximum.
    #[error("grid level {level} is above the maximum {max} (level {max} already has {} cells)", 72u64 * 8u64.pow(*max as u32))]
    LevelTooHigh {
        /// The level asked for.
        level: u8,
        /// The highest level supported.
        max: u8,
    },
    /// A cell index outside the level.
    #[error("cell index {index} is outside grid level {level} (which has {len} cells)")]
    IndexOutOfRange {
        /// The index asked for.
        index: u64,
        /// The grid level.
        level: u8,
        /// Number of cells of the level.
        len: u64,
    },
    /// A quaternion that cannot be normalised.
    #[error("quaternion (w, x, y, z) = {0:?} is zero or not finite")]
    BadQuaternion([f64; 4]),
    /// A matrix that is not a rotation.
    #[error("matrix is not a rotation: determinant {det:.6}, orthonormality error {ortho_err:.2e}")]
    NotARotation {
        /// Its determinant.
        det: f64,
        /// `max |MᵀM − I|`.
        ortho_err: f64,
    },
    /// A symmetry group name that is not known.
    #[error("unknown symmetry group '{0}' (expected none, T, O, I, C<n>, D<n>, cone or cylinder)")]
    UnknownGroup(String),
    /// A distribution whose length is not the grid's.
    #[error("distribution has {got} weights but grid level {level} has {expected} cells")]
    WrongLength {
        /// Number of weights given.
        got: usize,
        /// The grid level.
        level: u8,
        /// Number of cells of the level.
        expected: usize,
    },
    /// A distribution with NaN or no finite weight.
    #[error("distribution has NaN weights or no finite weight")]
    NonFiniteWeights,
    /// Metrics asked for an image without ground truth.
    #[error("no ground-truth rotation given")]
    NoGroundTruth,
}
