//! The inference engine: loaded bundles, request images, full distributions, coarse-to-fine top-k,
//! modes and RGB-D fusion. No transport here: the gRPC service (src/serve) is a thin layer over
//! [`Engine`], and everything below is testable without a socket.

pub mod calibrate;
pub mod cancel;
pub mod depth;
pub mod frame;
pub mod fusion;
pub mod image;
pub mod search;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use burn::tensor::{Device, Tensor};
use rayon::prelude::*;

pub use self::image::{
    CropBox, FrameCrop, ImageLimits, ImageRequest, Intrinsics, prepare_frame, prepare_image,
};
pub use cancel::{Cancel, CancelOnDrop};
pub use depth::{BackProjected, DepthMap, DepthRequest, back_project, decode_depth, decode_mask};
pub use frame::{CropDepth, DetectionDepth};
pub use fusion::{CameraPoints, DepthFusion, ViewTable};
pub use search::{CellProbability, Mode, SearchResult, coarse_to_fine_many, group_modes};

use crate::bundle::BundleError;
use crate::bundle::model::ModelBundle;
use crate::net::network::feature_rows;
use crate::net::{
    FusedHead, Network, NetworkConfig, Precision, ProjectedGrid, Rows, images_tensor,
};
use crate::so3::{GridLevel, MAX_LEVEL, to_row_major_f32};

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

/// Most rotations one Predict may return (the search keeps `top_k / 8` cells per level, so this
/// also bounds its work).
pub const MAX_TOP_K: usize = 16_384;

/// The keep tapers a search accepts ([`SearchParams::keep_taper`]): from an eighth to eight times
/// as many cells per finer level.
pub use crate::bundle::study::KEEP_TAPER;

/// How the engine serves.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EngineConfig {
    /// Highest level served in full (its rotation projections are precomputed at load).
    pub max_full_level: u8,
    /// Default finest level of the search.
    pub search_default_level: u8,
    /// Highest level a search may reach.
    pub search_max_level: u8,
    /// The coarse-to-fine search: its start level, the cells it keeps per level and the
    /// arithmetic of its coarse levels.
    pub search: SearchParams,
    /// Limits on request images.
    pub image_limits: ImageLimits,
    /// Most depth points per request.
    pub max_depth_points: usize,
    /// Depth pixels of a depth image used per detection (evenly spaced in the box).
    pub depth_image_points: usize,
    /// With `Some(ms)`, the search is chosen at load on this CPU ([`calibrate`]) among the
    /// bundle's studied searches: the most agreeing one predicted within `ms`; with `None`, the
    /// search above is served as it is.
    pub search_budget_ms: Option<f64>,
    /// The agreement with the exhaustive argmax a calibrated search must have reached in the
    /// bundle's study.
    pub search_agreement: f64,
    /// The widest head kernels the model may use.
    pub kernels: crate::net::Kernels,
}

/// How a coarse-to-fine search runs: the level it scores in full, and the cells it refines.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SearchParams {
    /// Level scored in full first.
    pub start_level: u8,
    /// Most cells kept per level.
    pub keep: usize,
    /// Keep the cells holding this fraction of each level's mass, at most `keep` (`None`:
    /// always `keep`).
    pub keep_mass: Option<f64>,
    /// Each finer level keeps `keep_taper` times as many cells as the one before (1: `keep` at
    /// every level).
    pub keep_taper: f64,
    /// The arithmetic of every level but the finest, which is scored in f32: bfloat16 ranks
    /// the cells to refine at about 2.6 times the f32 rate.
    pub coarse_precision: Precision,
}

impl SearchParams {
    /// The cells it keeps, in words: `128`, `0.99 mass ≤512`, `512 ×0.5/level`.
    pub fn keep_description(&self) -> String {
        let mut keep = match self.keep_mass {
            Some(m) => format!("{m} mass ≤{}", self.keep),
            None => self.keep.to_string(),
        };
        if self.keep_taper != 1.0 {
            keep += &format!(" ×{}/level", self.keep_taper);
        }
        keep
    }
}

impl std::fmt::Display for SearchParams {
    /// `start 2, keep 1024 ×0.5/level, coarse bf16` (a keep by mass: `keep 0.999 mass ≤512`).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "start {}, keep {}, coarse {}",
            self.start_level,
            self.keep_description(),
            self.coarse_precision
        )
    }
}

impl EngineConfig {
    /// The levels a bundle is served at: this configuration's, capped by the levels its
    /// manifest records (the trainer writes the engine's defaults there).
    pub fn within(&self, levels: &crate::bundle::model::GridLevels) -> EngineConfig {
        EngineConfig {
            max_full_level: self.max_full_level.min(levels.full_max),
            search: SearchParams {
                start_level: self.search.start_level.min(levels.full_max),
                ..self.search
            },
            search_default_level: self.search_default_level.min(levels.search_max),
            search_max_level: self.search_max_level.min(levels.search_max),
            ..*self
        }
    }

    /// The search this configuration runs.
    pub fn search(&self) -> SearchParams {
        self.search
    }

    /// Checks the levels against each other and the grid, and the limits: a server must not
    /// start with settings that make every default call fail.
    pub fn validate(&self) -> Result<(), EngineError> {
        let bad = |field: &str, message: String| Err(invalid(field, message));
        if self.max_full_level > MAX_LEVEL {
            return bad(
                "max_full_level",
                format!(
                    "{} is above the grid's highest level {MAX_LEVEL}",
                    self.max_full_level
                ),
            );
        }
        if self.search_max_level > MAX_LEVEL {
            return bad(
                "search_max_level",
                format!(
                    "{} is above the grid's highest level {MAX_LEVEL}",
                    self.search_max_level
                ),
            );
        }
        if self.search.start_level > self.search_default_level
            || self.search_default_level > self.search_max_level
        {
            return bad(
                "search levels",
                format!(
                    "need start ({}) ≤ default ({}) ≤ maximum ({})",
                    self.search.start_level, self.search_default_level, self.search_max_level
                ),
            );
        }
        if self.search.start_level > self.max_full_level {
            return bad(
                "search_start_level",
                format!(
                    "{} is above the highest full level {} (the search starts from a full level)",
                    self.search.start_level, self.max_full_level
                ),
            );
        }
        if let Some(f) = self.search.keep_mass
            && !(f > 0.0 && f <= 1.0)
        {
            return bad("keep_mass", format!("{f} must be in (0, 1]"));
        }
        if !KEEP_TAPER.contains(&self.search.keep_taper) {
            return bad(
                "keep_taper",
                format!("{} must be in {KEEP_TAPER:?}", self.search.keep_taper),
            );
        }
        if self.search.keep == 0
            || self.image_limits.max_bytes == 0
            || self.image_limits.max_pixels == 0
        {
            return bad(
                "limits",
                "keep and the image limits must be positive".into(),
            );
        }
        if !(1..=self.max_depth_points).contains(&self.depth_image_points) {
            return bad(
                "depth_image_points",
                format!(
                    "{} must be in 1 ..= {} (max_depth_points)",
                    self.depth_image_points, self.max_depth_points
                ),
            );
        }
        Ok(())
    }
}

impl Default for EngineConfig {
    fn default() -> Self {
        Self {
            max_full_level: 4,
            search_default_level: 5,
            search_max_level: 6,
            // Chosen by the search study of `alignist-train bench` (held-out renders, top-10 to
            // level 5, against the exhaustive level-5 argmax; docs/BENCHMARKS.md): with the
            // coarse levels in bfloat16, 1024 cells halving per level (1024, 512, 256) agreed on
            // 189 of 190 distinct images over the bench's sets of 150 and 50, at p50 ~22 ms;
            // 768 halving, ~4 ms faster, on 188 (98.9 %). The search before, 128 at every level in
            // f32, agreed on 93–94 %.
            search: SearchParams {
                start_level: 2,
                keep: 1024,
                keep_mass: None,
                keep_taper: 0.5,
                coarse_precision: Precision::Bf16,
            },
            image_limits: ImageLimits::default(),
            max_depth_points: 10_000,
            depth_image_points: 256,
            search_budget_ms: None,
            search_agreement: 0.99,
            kernels: crate::net::Kernels::from_env(),
        }
    }
}

/// One object of a model.
pub struct ModelObject {
    /// Name.
    pub name: String,
    /// The proper symmetries recorded with the object's experts (identity first).
    pub symmetries: Vec<nalgebra::Rotation3<f64>>,
    /// Their group, when they form a named one.
    pub symmetry_group: Option<crate::so3::SymmetryGroup>,
    /// The symmetry the experts discovered (expert sets made before discovery have none).
    pub discovered: Option<crate::experts::symmetry::DiscoveredSymmetry>,
    /// How the source mesh maps to the object frame.
    pub normalisation: crate::cad::Normalisation,
    /// Training images.
    pub train_images: usize,
    /// The SDF expert, for RGB-D fusion.
    pub fusion: DepthFusion,
}

/// A loaded, validated model: immutable once built, shared behind an `Arc`.
pub struct Model {
    /// Name (the bundle's folder name).
    pub name: String,
    /// Where it was loaded from.
    pub path: PathBuf,
    /// The bundle's manifest.
    pub manifest: crate::bundle::model::ModelManifest,
    /// Objects.
    pub objects: Vec<ModelObject>,
    /// The network on the convolution backend: its encoder runs here.
    network: Network,
    device: Device,
    /// The head for inference, fused ([`FusedHead`]): every scoring of the engine runs on it.
    fused: Arc<FusedHead>,
    /// Grids 0 ..= max level, with precomputed projections up to the full level.
    grids: Vec<GridLevel>,
    projected: Vec<ProjectedGrid>,
    config: EngineConfig,
    /// The load-time calibration that chose the search, when there was one.
    calibration: Option<calibrate::Calibration>,
}

/// The full distribution of one image at one level.
#[derive(Debug, Clone, PartialEq)]
pub struct Distribution {
    /// Level.
    pub level: u8,
    /// Probability of each cell (sums to 1).
    pub probability: Vec<f32>,
    /// Log-density of each cell (`log p + log(N/π²)`).
    pub log_density: Vec<f32>,
}

/// A Predict answer from the engine.
#[derive(Debug, Clone, PartialEq)]
pub struct Prediction {
    /// The top-k cells of the finest level, most probable first.
    pub top: Vec<CellProbability>,
    /// Rotation of each top cell's centre.
    pub rotations: Vec<[f64; 4]>,
    /// The modes.
    pub modes: Vec<Mode>,
    /// Mass the search's finest cells are estimated to cover.
    pub covered_mass: f64,
    /// With camera depth points, the translation of each top cell (`x_camera = R·x_mesh + t`, in
    /// the mesh's units, the frame of `rotations`); empty otherwise.
    pub translations: Vec<[f64; 3]>,
}

impl Prediction {
    /// The same answer for a crop whose virtual camera is turned by `r_ray` in the real camera:
    /// every rotation (top cells and modes) becomes `R_ray·R` and every translation `R_ray·t`.
    /// Cells keep indexing the grid of `R`, the crop camera's frame.
    pub fn in_camera_frame(mut self, r_ray: &nalgebra::Rotation3<f64>) -> Prediction {
        let turn = |q: &mut [f64; 4]| {
            let r = crate::so3::from_quaternion(*q).expect("the engine's quaternions are unit");
            *q = crate::so3::to_quaternion(&(r_ray * r));
        };
        self.rotations.iter_mut().for_each(turn);
        self.modes.iter_mut().for_each(|m| turn(&mut m.quaternion));
        for t in &mut self.translations {
            *t = (r_ray * nalgebra::Vector3::from(*t)).into();
        }
        self
    }
}

/// The depth points of one image.
#[derive(Debug, Clone, PartialEq)]
pub enum SeenPoints {
    /// Points relative to the object's centre, normalised units, camera frame (`τ = 0`).
    Centred(Vec<nalgebra::Vector3<f32>>),
    /// Points as the camera saw them (from a depth image): the translation is found.
    Camera(CameraPoints),
}

/// Depth of one image for RGB-D fusion: the object the points belong to, and the points.
#[derive(Clone, Copy)]
pub struct DepthInput<'a> {
    /// The object (its SDF expert scores the points).
    pub object: &'a ModelObject,
    /// The points.
    pub points: &'a SeenPoints,
}

impl DepthInput<'_> {
    /// The fused term of every cell centre of `grid` given (row-major rotations):
    /// `κ_L·(−U_SDF)` ([`DepthFusion::tempering`]), at `τ = 0` for centred points, at the
    /// estimate `τ₀(R)` for camera points ([`fusion`]).
    /// Stops with [`EngineError::Cancelled`] between chunks ([`cancel::cancel_chunk`]) once
    /// `cancel` is set.
    pub fn cell_log_measure(
        &self,
        grid: &GridLevel,
        rotations: &[[f32; 9]],
        cancel: &Cancel,
    ) -> Result<Vec<f32>, EngineError> {
        let kappa = self.object.fusion.tempering(grid);
        let mut terms = Vec::with_capacity(rotations.len());
        let points = match self.points {
            SeenPoints::Centred(p) => p.len(),
            SeenPoints::Camera(p) => p.points.len(),
        };
        for chunk in rotations.chunks(cancel::cancel_chunk(points)) {
            cancel.check()?;
            terms.extend(self.log_measure(chunk).into_iter().map(|t| t * kappa));
        }
        Ok(terms)
    }

    /// The fused term `−U_SDF` of every candidate (row-major rotations): at `τ = 0` for centred
    /// points, at the estimate `τ₀(R)` for camera points ([`fusion`]).
    pub fn log_measure(&self, rotations: &[[f32; 9]]) -> Vec<f32> {
        let fusion = &self.object.fusion;
        match self.points {
            SeenPoints::Centred(points) => fusion.log_measure(points, rotations),
            SeenPoints::Camera(points) => fusion.posed_log_measure(points, rotations),
        }
    }

    /// For camera points, the best-fitting translation of rotation `r` (row-major) and the fused
    /// term there ([`DepthFusion::fit_translation`]); `None` for centred points.
    pub fn fit(&self, r: &[f32; 9]) -> Option<(nalgebra::Vector3<f32>, f32)> {
        match self.points {
            SeenPoints::Centred(_) => None,
            SeenPoints::Camera(points) => Some(self.object.fusion.fit_translation(points, r)),
        }
    }

    /// `τ` (normalised units, camera frame) as the mesh's translation `t`, with
    /// `x_camera = R·x_mesh + t`: `t = s·τ − R·centre` (`x_object = (x_mesh − centre)/s`).
    pub fn mesh_translation(
        &self,
        r: &nalgebra::Rotation3<f64>,
        tau: &nalgebra::Vector3<f32>,
    ) -> [f64; 3] {
        let n = &self.object.normalisation;
        let t = tau.cast::<f64>() * n.scale - r * nalgebra::Vector3::from(n.centre);
        [t.x, t.y, t.z]
    }
}

/// The angle within which top cells are grouped into one mode, unless a call gives its own.
pub const DEFAULT_MODE_ANGLE_DEG: f64 = 15.0;

/// What a prediction asks for beyond the image.
#[derive(Debug, Clone, Default)]
pub struct PredictOptions {
    /// Top-k (≥ 1).
    pub top_k: usize,
    /// Finest search level (`None`: the default).
    pub level: Option<u8>,
    /// Mode grouping angle in degrees (`None`: [`DEFAULT_MODE_ANGLE_DEG`]).
    pub mode_angle_deg: Option<f64>,
    /// Set when the caller went away: the search stops at its next level or chunk.
    pub cancel: Cancel,
}

impl Model {
    /// Builds a model from a loaded bundle: precomputes the rotation projections of every level up
    /// to `config.max_full_level`.
    pub fn from_bundle(
        name: &str,
        path: &Path,
        bundle: ModelBundle,
        config: EngineConfig,
    ) -> Result<Model, EngineError> {
        let config = config.within(&bundle.manifest.levels);
        config.validate()?;
        let device = crate::backend::device_for(crate::backend::Workload::Conv);
        let top = config.search_max_level.max(config.max_full_level);
        if top > MAX_LEVEL {
            return Err(EngineError::Models(format!(
                "grid level {top} is above the highest supported level {MAX_LEVEL}"
            )));
        }
        let grids = (0..=top)
            .map(GridLevel::new)
            .collect::<Result<Vec<_>, _>>()?;
        let fused = Arc::new(FusedHead::with_kernels(
            &bundle.network.head,
            config.kernels,
        ));
        let projected = (0..=config.max_full_level)
            .map(|l| ProjectedGrid::with_head(fused.clone(), &bundle.manifest.network.encoding, l))
            .collect::<Result<Vec<_>, _>>()?;
        let objects = bundle
            .manifest
            .objects
            .iter()
            .zip(bundle.experts)
            .map(|(o, set)| ModelObject {
                name: o.name.clone(),
                symmetries: set.symmetries(),
                symmetry_group: crate::so3::SymmetryGroup::identify(&set.symmetries()),
                discovered: set.manifest.symmetry.clone(),
                normalisation: set.manifest.object.normalisation,
                train_images: o.train_images,
                fusion: DepthFusion::new(set),
            })
            .collect();
        Ok(Model {
            name: name.to_string(),
            path: path.to_path_buf(),
            manifest: bundle.manifest,
            objects,
            network: bundle.network,
            device,
            fused,
            grids,
            projected,
            config,
            calibration: None,
        })
    }

    /// The search this model serves chosen on this CPU ([`calibrate::calibrate`]) among the
    /// searches of the bundle's study at `folder`, to the default search level, when the
    /// configuration has a budget; logged and kept in [`Model::calibration`].
    fn calibrated(mut self, folder: &Path) -> Result<Model, EngineError> {
        let Some(budget) = self.config.search_budget_ms else {
            return Ok(self);
        };
        let study = crate::bundle::study::SearchStudy::load(folder)?;
        let c = calibrate::calibrate(
            &self,
            study.as_ref(),
            &self.config.search(),
            self.config.search_agreement,
            budget,
            self.config.search_default_level,
        )?;
        tracing::info!(
            model = %self.name,
            search = %c.chosen,
            agreement = ?c.agreement,
            predicted_ms = c.predicted_ms,
            measured_ms = c.measured_ms,
            budget_ms = budget,
            within_budget = c.within_budget,
            calibration_ms = c.took_ms,
            kernels = %self.fused.kernel_paths(),
            "search calibrated: {}",
            c.reason
        );
        if !c.within_budget {
            tracing::warn!(
                model = %self.name,
                "no search that reaches the agreement target fits {budget} ms on this CPU: serving the fastest ({:.1} ms predicted)",
                c.predicted_ms
            );
        }
        self.config.search = c.chosen;
        self.calibration = Some(c);
        Ok(self)
    }

    /// The load-time calibration of this model's search, when it had one.
    pub fn calibration(&self) -> Option<&calibrate::Calibration> {
        self.calibration.as_ref()
    }

    /// The kernel each precision runs on, in words.
    pub fn kernel_paths(&self) -> String {
        self.fused.kernel_paths()
    }

    /// The network's configuration (input size, encoding, …).
    pub fn network_config(&self) -> &NetworkConfig {
        &self.manifest.network
    }

    /// Side of the input crops.
    pub fn input_size(&self) -> u32 {
        self.manifest.network.image_size
    }

    /// The object named `name` (empty: the only object, when there is one).
    pub fn object(&self, name: &str) -> Result<&ModelObject, EngineError> {
        Ok(&self.objects[self.object_index(name)?])
    }

    /// Index in [`Model::objects`] of the object named `name` (empty: the only object).
    pub fn object_index(&self, name: &str) -> Result<usize, EngineError> {
        if name.is_empty() {
            return match self.objects.len() {
                1 => Ok(0),
                n => Err(invalid(
                    "object",
                    format!(
                        "is required: model '{}' has {n} objects ({})",
                        self.name,
                        self.object_names()
                    ),
                )),
            };
        }
        self.objects
            .iter()
            .position(|o| o.name == name)
            .ok_or_else(|| {
                EngineError::NotFound(format!(
                    "object {} is not in model '{}' (objects: {})",
                    quoted_name(name),
                    self.name,
                    self.object_names()
                ))
            })
    }

    fn object_names(&self) -> String {
        self.objects
            .iter()
            .map(|o| o.name.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// Decodes, crops and resizes a request image to the model's input.
    pub fn prepare(&self, image: &ImageRequest<'_>) -> Result<Vec<u8>, EngineError> {
        prepare_image(image, self.input_size(), &self.config.image_limits)
    }

    /// Decodes a full camera image once and makes each box's perspective crop
    /// ([`image::prepare_frame`]).
    pub fn prepare_frame(
        &self,
        image: &ImageRequest<'_>,
        intrinsics: &Intrinsics,
        boxes: &[CropBox],
    ) -> Result<Vec<FrameCrop>, EngineError> {
        prepare_frame(
            image,
            intrinsics,
            boxes,
            self.input_size(),
            &self.config.image_limits,
        )
    }

    /// The model's version: the sha256 of its network weights.
    pub fn version(&self) -> &str {
        self.manifest
            .files
            .get(crate::bundle::model::NETWORK_FILE)
            .map_or("", |f| f.sha256.as_str())
    }

    /// Image features `[B, D]` of prepared crops (one encoder pass for the batch). The fused
    /// head reads them as plain rows, so they stay on the encoder's device.
    pub fn features(&self, crops: &[&[u8]]) -> Tensor<2> {
        let images = images_tensor(crops, self.input_size() as usize, &self.device);
        self.network.encoder.forward(images)
    }

    /// `b` images' features, `d` each, concatenated, as a `[b, d]` tensor.
    pub fn features_tensor_many(&self, features: &[f32], b: usize, d: usize) -> Tensor<2> {
        Tensor::from_data(
            burn::tensor::TensorData::new(features.to_vec(), [b, d]),
            &self.device,
        )
    }

    /// One image's features (as the batcher hands them over) as a `[1, D]` tensor.
    pub fn features_tensor(&self, features: &[f32]) -> Tensor<2> {
        Tensor::from_data(
            burn::tensor::TensorData::new(features.to_vec(), [1, features.len()]),
            &self.device,
        )
    }

    /// Checks a full-distribution level.
    pub fn check_full_level(&self, level: u8) -> Result<(), EngineError> {
        if level > self.config.max_full_level {
            return Err(invalid(
                "level",
                format!(
                    "{level} is above the highest full level this server computes ({})",
                    self.config.max_full_level
                ),
            ));
        }
        Ok(())
    }

    /// Unnormalised log-weights `s_θ + s_φ` of every cell of `level` for one image's features
    /// `[1, D]`, plus the fused depth term when given.
    fn full_logits(
        &self,
        features: &Tensor<2>,
        level: u8,
        depth: Option<DepthInput<'_>>,
        cancel: &Cancel,
    ) -> Result<Vec<f32>, EngineError> {
        let mut logits = self.projected[level as usize]
            .log_weights_of_features(features.clone())
            .swap_remove(0);
        if let Some(depth) = depth {
            let grid = &self.grids[level as usize];
            let mut terms = depth.cell_log_measure(grid, &grid.matrices_f32(), cancel)?;
            if let Some(children) = self.grids.get(level as usize + 1) {
                cell_means(&depth, grid, children, &mut terms, cancel)?;
            }
            for (l, d) in logits.iter_mut().zip(terms) {
                *l += d;
            }
        }
        Ok(logits)
    }

    /// `s_θ + s_φ` of every cell of `level` for one image's features `[1, D]`: from the
    /// precomputed projections at the full levels, above them projected chunk by chunk (an
    /// exhaustive reference for studies of the search; level 5 has 2.4 M cells).
    pub fn logits_at(&self, features: &Tensor<2>, level: u8) -> Result<Vec<f32>, EngineError> {
        self.logits_in(Precision::F32, features, level)
    }

    /// [`Model::logits_at`] in `precision`.
    pub fn logits_in(
        &self,
        precision: Precision,
        features: &Tensor<2>,
        level: u8,
    ) -> Result<Vec<f32>, EngineError> {
        if let Some(projected) = self.projected.get(level as usize) {
            return Ok(projected
                .log_weights_in(precision, features.clone())
                .swap_remove(0));
        }
        let grid = self.grids.get(level as usize).ok_or_else(|| {
            invalid(
                "level",
                format!(
                    "{level} is above this model's grids (0–{})",
                    self.grids.len() - 1
                ),
            )
        })?;
        let rows = feature_rows(features.clone());
        let image = self.fused.image_term(&rows[0]);
        let encoding = &self.manifest.network.encoding;
        let n = grid.len() as u64;
        let mut logits = Vec::with_capacity(grid.len());
        for start in (0..n).step_by(1 << 16) {
            let mats: Vec<[f32; 9]> = (start..(start + (1 << 16)).min(n))
                .map(|c| to_row_major_f32(&grid.rotation(c)))
                .collect();
            let encodings = encoding.encode(&mats);
            logits.extend(
                self.fused
                    .scores_in(precision, &image, Rows::Encoded(&encodings)),
            );
        }
        Ok(logits)
    }

    /// The full distribution at `level` (docs/DESIGN.md §2: `log p` per cell, `+ log(N/π²)`).
    pub fn distribution(
        &self,
        features: &Tensor<2>,
        level: u8,
        depth: Option<DepthInput<'_>>,
    ) -> Result<Distribution, EngineError> {
        self.distribution_cancellable(features, level, depth, &Cancel::default())
    }

    /// [`Model::distribution`] that stops with [`EngineError::Cancelled`] at the next chunk of
    /// the fused term once `cancel` is set.
    pub fn distribution_cancellable(
        &self,
        features: &Tensor<2>,
        level: u8,
        depth: Option<DepthInput<'_>>,
        cancel: &Cancel,
    ) -> Result<Distribution, EngineError> {
        self.check_full_level(level)?;
        let logits = self.full_logits(features, level, depth, cancel)?;
        let lse = search::log_sum_exp(&logits);
        let log_n_over_volume = -self.grids[level as usize].cell_volume().ln();
        let log_p: Vec<f64> = logits.iter().map(|&l| l as f64 - lse).collect();
        Ok(Distribution {
            level,
            probability: log_p.iter().map(|&l| l.exp() as f32).collect(),
            log_density: log_p
                .iter()
                .map(|&l| (l + log_n_over_volume) as f32)
                .collect(),
        })
    }

    /// Checks the options of a prediction; returns the finest level.
    pub fn check_predict(&self, options: &PredictOptions) -> Result<u8, EngineError> {
        let level = options.level.unwrap_or(self.config.search_default_level);
        if level > self.config.search_max_level {
            return Err(invalid(
                "level",
                format!(
                    "{level} is above the highest search level this server allows ({})",
                    self.config.search_max_level
                ),
            ));
        }
        let grid = &self.grids[level as usize];
        if options.top_k == 0 {
            return Err(invalid("top_k", "must be at least 1"));
        }
        if options.top_k > grid.len() {
            return Err(invalid(
                "top_k",
                format!(
                    "{} is above the {} cells of level {level}",
                    options.top_k,
                    grid.len()
                ),
            ));
        }
        if options.top_k > MAX_TOP_K {
            return Err(invalid(
                "top_k",
                format!("{} is above the limit of {MAX_TOP_K}", options.top_k),
            ));
        }
        if let Some(a) = options.mode_angle_deg
            && !(a > 0.0 && a <= 180.0)
        {
            return Err(invalid(
                "mode_angle_deg",
                format!("{a} must be in (0, 180] degrees"),
            ));
        }
        Ok(level)
    }

    /// Top-k by coarse-to-fine search from the start level to `options.level`, the modes of the
    /// result, and the covered mass.
    pub fn predict(
        &self,
        features: &Tensor<2>,
        options: &PredictOptions,
        depth: Option<DepthInput<'_>>,
    ) -> Result<Prediction, EngineError> {
        Ok(self
            .predict_many(features, options, &[depth])?
            .swap_remove(0))
    }

    /// [`Model::predict`] for the `B` images of `features` `[B, D]` with the same options, in
    /// one batch: every level of their searches is scored in one pass of the head for all of
    /// them. `depth[b]` is image `b`'s depth input.
    pub fn predict_many(
        &self,
        features: &Tensor<2>,
        options: &PredictOptions,
        depth: &[Option<DepthInput<'_>>],
    ) -> Result<Vec<Prediction>, EngineError> {
        self.predict_searching(features, options, &self.config.search(), depth)
    }

    /// [`Model::predict_many`] with the search's start level and keep given instead of the
    /// server's (for studies of the search).
    pub fn predict_searching(
        &self,
        features: &Tensor<2>,
        options: &PredictOptions,
        search: &SearchParams,
        depth: &[Option<DepthInput<'_>>],
    ) -> Result<Vec<Prediction>, EngineError> {
        let level = self.check_predict(options)?;
        if search.start_level > self.config.max_full_level
            || search.keep == 0
            || !KEEP_TAPER.contains(&search.keep_taper)
        {
            return Err(invalid(
                "search",
                format!(
                    "start level {} above the full levels ({}), keep 0, or keep taper {} outside {KEEP_TAPER:?}",
                    search.start_level, self.config.max_full_level, search.keep_taper
                ),
            ));
        }
        let [b, _] = features.dims();
        if depth.len() != b {
            return Err(invalid(
                "depth",
                format!("{} depth inputs for {b} images", depth.len()),
            ));
        }
        let start = search.start_level.min(level);
        let grids: Vec<&GridLevel> = self.grids[start as usize..=level as usize].iter().collect();
        // Enough cells kept for the top-k at the finest level (8 children each).
        let min = options.top_k.div_ceil(8);
        let keep = search::Keep {
            max: search.keep.max(min),
            min,
            mass: search.keep_mass,
            taper: search.keep_taper,
        };
        let mut fusion = DepthSearch::new(depth, level, options.top_k.max(MIN_REFITS));
        let results = coarse_to_fine_many(&grids, keep, b, |grid, cells| {
            let precision = if grid.level() == level {
                Precision::F32
            } else {
                search.coarse_precision
            };
            // A level boundary: a call whose caller went away stops here.
            options.cancel.check()?;
            let (mut logits, mats) = self.search_logits(features, grid, cells, start, precision);
            fusion.add_terms(grid, cells, &mats, &mut logits, &options.cancel)?;
            Ok::<_, EngineError>(logits)
        })?;
        let grid = &self.grids[level as usize];
        let angle = options
            .mode_angle_deg
            .unwrap_or(DEFAULT_MODE_ANGLE_DEG)
            .to_radians();
        Ok(results
            .into_iter()
            .zip(depth.iter().zip(&fusion.fitted))
            .map(|(result, (depth, fitted))| {
                prediction_of(grid, result, options.top_k, angle, depth.as_ref(), fitted)
            })
            .collect())
    }

    /// `s_θ + s_φ` of each search's `cells` of `grid` in `precision`: read from the precomputed
    /// projections at the start level, scored on their rotations above it. Also returns those
    /// rotations (row-major; empty at the start level, which does not compute them).
    fn search_logits(
        &self,
        features: &Tensor<2>,
        grid: &GridLevel,
        cells: &[Vec<u64>],
        start: u8,
        precision: Precision,
    ) -> (Vec<Vec<f32>>, Vec<Vec<[f32; 9]>>) {
        if grid.level() == start && (start as usize) < self.projected.len() {
            let all = self.projected[start as usize].log_weights_in(precision, features.clone());
            let logits = all
                .into_iter()
                .zip(cells)
                .map(|(all, cells)| {
                    if cells.len() == all.len() {
                        all
                    } else {
                        cells.iter().map(|&c| all[c as usize]).collect()
                    }
                })
                .collect();
            return (logits, Vec::new());
        }
        let mats: Vec<Vec<[f32; 9]>> = cells
            .iter()
            .map(|cells| {
                cells
                    .iter()
                    .map(|&c| to_row_major_f32(&grid.rotation(c)))
                    .collect()
            })
            .collect();
        (self.score_rotations_many(features, &mats, precision), mats)
    }

    /// `s_θ + s_φ` of `rotations[b]` (row-major, the same number for every image) for each image
    /// `b` of `features` `[B, D]`, in one pass of the head, in `precision`.
    pub fn score_rotations_many(
        &self,
        features: &Tensor<2>,
        rotations: &[Vec<[f32; 9]>],
        precision: Precision,
    ) -> Vec<Vec<f32>> {
        let encoding = &self.manifest.network.encoding;
        feature_rows(features.clone())
            .iter()
            .zip(rotations)
            .map(|(f, rotations)| {
                let encodings = encoding.encode(rotations);
                self.fused.scores_in(
                    precision,
                    &self.fused.image_term(f),
                    Rows::Encoded(&encodings),
                )
            })
            .collect()
    }

    /// Whether bfloat16 scoring runs on this core's own instructions (else it is emulated).
    pub fn bf16_native(&self) -> bool {
        self.fused.bf16_native()
    }

    /// The grid of `level` (up to the highest level this model serves).
    pub fn grid(&self, level: u8) -> Option<&GridLevel> {
        self.grids.get(level as usize)
    }

    /// The engine configuration the model was built with.
    pub fn config(&self) -> &EngineConfig {
        &self.config
    }
}

/// How far below the best cell's fused term a cell of a full distribution still gets its term
/// from its children ([`cell_means`]); below, its mass is negligible either way.
const CELL_MEAN_RANGE: f32 = 30.0;

/// Replaces the fused term of the cells of `grid` within [`CELL_MEAN_RANGE`] of the best by
/// `log mean_k exp(term(child_k))` over their 8 children (each scored at `children`'s level):
/// the cell's share of the depth factor's mass, where a centre alone misses a peak narrower than
/// the cell.
fn cell_means(
    depth: &DepthInput<'_>,
    grid: &GridLevel,
    children: &GridLevel,
    terms: &mut [f32],
    cancel: &Cancel,
) -> Result<(), EngineError> {
    let best = terms.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let near: Vec<usize> = (0..terms.len())
        .filter(|&i| terms[i] >= best - CELL_MEAN_RANGE)
        .collect();
    let rotations: Vec<[f32; 9]> = near
        .iter()
        .flat_map(|&i| grid.children(i as u64))
        .map(|c| to_row_major_f32(&children.rotation(c)))
        .collect();
    let child_terms = depth.cell_log_measure(children, &rotations, cancel)?;
    for (&i, eight) in near.iter().zip(child_terms.chunks_exact(8)) {
        terms[i] = search::log_sum_exp(eight) as f32 - 8f32.ln();
    }
    Ok(())
}

/// The depth side of a batch of coarse-to-fine searches: each image's fused term added at every
/// level, from a quarter of the camera points above the finest level; at the finest, the best
/// cells' translations fitted ([`refit_best`]) and kept for the answer.
struct DepthSearch<'a> {
    depth: &'a [Option<DepthInput<'a>>],
    coarse: Vec<Option<SeenPoints>>,
    finest: u8,
    refits: usize,
    fitted: Vec<Vec<(u64, nalgebra::Vector3<f32>)>>,
}

impl<'a> DepthSearch<'a> {
    fn new(depth: &'a [Option<DepthInput<'a>>], finest: u8, refits: usize) -> Self {
        let coarse = depth
            .iter()
            .map(|d| match d.map(|d| d.points) {
                Some(SeenPoints::Camera(p)) => Some(SeenPoints::Camera(p.subsample(COARSE_POINTS))),
                _ => None,
            })
            .collect();
        DepthSearch {
            depth,
            coarse,
            finest,
            refits,
            fitted: vec![Vec::new(); depth.len()],
        }
    }

    /// Adds the fused term of each image with depth to its `logits` of `grid`'s `cells`
    /// (`mats`: their rotations, or empty to compute them here).
    fn add_terms(
        &mut self,
        grid: &GridLevel,
        cells: &[Vec<u64>],
        mats: &[Vec<[f32; 9]>],
        logits: &mut [Vec<f32>],
        cancel: &Cancel,
    ) -> Result<(), EngineError> {
        for (i, d) in self.depth.iter().enumerate() {
            let Some(d) = d else { continue };
            let own;
            let m: &[[f32; 9]] = match mats.get(i) {
                Some(m) => m,
                None => {
                    own = cells[i]
                        .iter()
                        .map(|&c| to_row_major_f32(&grid.rotation(c)))
                        .collect::<Vec<_>>();
                    &own
                }
            };
            let finest = grid.level() == self.finest;
            let fused = match (&self.coarse[i], finest) {
                (Some(points), false) => {
                    DepthInput { points, ..*d }.cell_log_measure(grid, m, cancel)?
                }
                _ => d.cell_log_measure(grid, m, cancel)?,
            };
            if finest {
                let kappa = d.object.fusion.tempering(grid);
                self.fitted[i] =
                    refit_best(d, m, &cells[i], &mut logits[i], &fused, self.refits, kappa);
            }
            for (l, d) in logits[i].iter_mut().zip(&fused) {
                *l += d;
            }
        }
        Ok(())
    }
}

/// A search's answer: the top-k cells of its finest level, their rotations, the modes, and with
/// camera points the translation of each top cell (the fitted ones reused, the others fitted).
fn prediction_of(
    grid: &GridLevel,
    result: SearchResult,
    top_k: usize,
    mode_angle: f64,
    depth: Option<&DepthInput<'_>>,
    fitted: &[(u64, nalgebra::Vector3<f32>)],
) -> Prediction {
    let modes = group_modes(grid, &result.cells, mode_angle, 0.9, 0.01);
    let top: Vec<CellProbability> = result.cells[..top_k.min(result.cells.len())].to_vec();
    let rotations: Vec<_> = top.iter().map(|c| grid.rotation(c.cell)).collect();
    let translations = match depth {
        Some(d) if matches!(d.points, SeenPoints::Camera(_)) => top
            .iter()
            .zip(&rotations)
            .map(|(c, r)| {
                let tau = match fitted.iter().find(|(cell, _)| *cell == c.cell) {
                    Some((_, tau)) => *tau,
                    None => d
                        .fit(&to_row_major_f32(r))
                        .map_or_else(nalgebra::Vector3::zeros, |(tau, _)| tau),
                };
                d.mesh_translation(r, &tau)
            })
            .collect(),
        _ => Vec::new(),
    };
    Prediction {
        rotations: rotations.iter().map(crate::so3::to_quaternion).collect(),
        top,
        modes,
        covered_mass: result.covered_mass,
        translations,
    }
}

/// Fewest cells of a search's finest level whose translation is fitted, with camera depth points.
const MIN_REFITS: usize = 16;

/// Camera depth points scored at the levels of a search above its finest (which scores all).
const COARSE_POINTS: usize = 64;

/// With camera points, fits the translation of the `n` best cells of a search's finest level (by
/// image log-weight plus the fused term at `τ₀`), so that their total is the image's plus the
/// fitted term (tempered by `kappa`, as `fused`); returns the fitted translations by cell.
/// Nothing for centred points.
fn refit_best(
    depth: &DepthInput<'_>,
    rotations: &[[f32; 9]],
    cells: &[u64],
    logits: &mut [f32],
    fused: &[f32],
    n: usize,
    kappa: f32,
) -> Vec<(u64, nalgebra::Vector3<f32>)> {
    if !matches!(depth.points, SeenPoints::Camera(_)) {
        return Vec::new();
    }
    let total: Vec<f64> = logits
        .iter()
        .zip(fused)
        .map(|(l, f)| (l + f) as f64)
        .collect();
    let best = search::top_indices(&total, n);
    let fits: Vec<(usize, nalgebra::Vector3<f32>, f32)> = best
        .par_iter()
        .filter_map(|&j| depth.fit(&rotations[j]).map(|(tau, term)| (j, tau, term)))
        .collect();
    fits.into_iter()
        .map(|(j, tau, term)| {
            // `logits` gets the difference, so that `logits + fused` is the fitted total.
            logits[j] += kappa * term - fused[j];
            (cells[j], tau)
        })
        .collect()
}

/// Every model of a models directory, by name, and the bundles that failed to load.
pub struct Engine {
    models: BTreeMap<String, Arc<Model>>,
    failed: BTreeMap<String, String>,
}

impl Engine {
    /// Loads every bundle in `dir` (each subfolder with a `manifest.json`), validating each, one
    /// by one: a bundle that fails is logged, counted (`alignist_model_load_failures_total`) and
    /// listed by [`Engine::failures`] while the others load. An error only when the directory
    /// cannot be read, holds no bundle, or no bundle loads (naming each failure).
    pub fn load_dir(dir: &Path, config: EngineConfig) -> Result<Engine, EngineError> {
        let engine = Self::load_bundles(dir, config)?;
        if engine.models.is_empty() {
            return Err(engine.none_loads(dir));
        }
        Ok(engine)
    }

    /// The error of a directory where no bundle loads, listing each one's refusal.
    pub fn none_loads(&self, dir: &Path) -> EngineError {
        let list: Vec<String> = self
            .failed
            .iter()
            .map(|(n, e)| format!("{n}: {e}"))
            .collect();
        EngineError::Models(format!(
            "{}: no bundle loads ({})",
            dir.display(),
            list.join("; ")
        ))
    }

    /// Every bundle of `dir` that loads, and the refusal of each one that does not, even when
    /// none loads (a reload then keeps serving the previous models, with their refusals listed).
    /// Errs only when `dir` cannot be read or holds no bundle folder.
    pub fn load_bundles(dir: &Path, config: EngineConfig) -> Result<Engine, EngineError> {
        let entries = std::fs::read_dir(dir).map_err(|source| EngineError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        let mut folders: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.join("manifest.json").is_file())
            .collect();
        folders.sort();
        if folders.is_empty() {
            return Err(EngineError::Models(format!(
                "{}: no model bundle (a folder with manifest.json) found",
                dir.display()
            )));
        }
        let mut models = BTreeMap::new();
        let mut failed = BTreeMap::new();
        for folder in folders {
            let name = folder
                .file_name()
                .and_then(|n| n.to_str())
                .unwrap_or_default()
                .to_string();
            match Self::load_model(&folder, config) {
                Ok(model) => {
                    models.insert(model.name.clone(), Arc::new(model));
                }
                Err(e) => {
                    tracing::error!(model = %name, "bundle refused: {e}");
                    metrics::counter!("alignist_model_load_failures_total", "model" => name.clone())
                        .increment(1);
                    // Clients see paths inside the models directory, not the server's own.
                    let inside = format!("{}{}", dir.display(), std::path::MAIN_SEPARATOR);
                    failed.insert(name, e.to_string().replace(&inside, ""));
                }
            }
        }
        Ok(Engine { models, failed })
    }

    /// The bundles that failed to load, by folder name, with their errors.
    pub fn failures(&self) -> &BTreeMap<String, String> {
        &self.failed
    }

    /// Keeps serving `model` (loaded before) in place of a bundle of the same name that failed
    /// to load now; the failure stays listed.
    pub fn keep_previous(&mut self, model: Arc<Model>) {
        self.models.insert(model.name.clone(), model);
    }

    /// Loads one bundle folder, depth fusion included ([`DepthFusion::warm`] for every object).
    pub fn load_model(folder: &Path, config: EngineConfig) -> Result<Model, EngineError> {
        let name = folder
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or_default()
            .to_string();
        let bundle = ModelBundle::load(folder)?;
        let model = Model::from_bundle(&name, folder, bundle, config)?.calibrated(folder)?;
        // Depth fusion is ready before the first request: the SDF grids and view tables are
        // built here, while the bundle loads (a server lists the model only after).
        let started = std::time::Instant::now();
        model.objects.par_iter().for_each(|o| o.fusion.warm());
        metrics::histogram!("alignist_depth_fusion_build_seconds")
            .record(started.elapsed().as_secs_f64());
        tracing::info!(
            model = %name,
            seconds = started.elapsed().as_secs_f64(),
            "depth fusion ready"
        );
        Ok(model)
    }

    /// The model named `name` (empty: the only model, when there is one).
    pub fn model(&self, name: &str) -> Result<Arc<Model>, EngineError> {
        if name.is_empty() {
            if self.models.len() == 1 {
                return Ok(self.models.values().next().expect("one model").clone());
            }
            return Err(invalid(
                "model",
                format!(
                    "is required: this server has {} models ({})",
                    self.models.len(),
                    self.names().join(", ")
                ),
            ));
        }
        self.models.get(name).cloned().ok_or_else(|| {
            EngineError::NotFound(format!(
                "model {} is not loaded (models: {})",
                quoted_name(name),
                self.names().join(", ")
            ))
        })
    }

    /// Names of the loaded models.
    pub fn names(&self) -> Vec<String> {
        self.models.keys().cloned().collect()
    }

    /// Every model.
    pub fn models(&self) -> impl Iterator<Item = &Arc<Model>> {
        self.models.values()
    }
}
