//! A loaded model: its objects, the fused head on the grids, full distributions and the
//! coarse-to-fine search (docs/DESIGN.md §2, "Inference"). Features come in as plain rows, one per image,
//! as the encoder gives them ([`Model::features`]).

pub use crate::so3::modes::DEFAULT_MODE_ANGLE_DEG;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use burn::tensor::Device;

use super::depth_search::{DepthInput, DepthSearch, MIN_REFITS, cell_means, prediction_of};
use super::search::{CellProbability, Mode};
use super::{
    Cancel, CropBox, DepthFusion, EngineConfig, EngineError, FrameCrop, ImageRequest, Intrinsics,
    KEEP_TAPER, MAX_TOP_K, RESCORED_CELLS, SearchParams, calibrate, coarse_to_fine_many, invalid,
    prepare_frame, prepare_image, quoted_name, search,
};
use crate::bundle::model::ModelBundle;
use crate::net::network::feature_rows;
use crate::net::{
    Branches, FusedHead, Network, NetworkConfig, Precision, ProjectedGrid, Rows, images_tensor,
};
use crate::so3::{GridLevel, MAX_LEVEL, to_row_major_f32};

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
    /// The network on the convolution backend: its encoder runs here where [`Model::encoder`]
    /// does not.
    pub(super) network: Network,
    /// The encoder with its BatchNorms folded in, by hand ([`crate::net::InferenceEncoder`]),
    /// for the layouts it runs (the CPU ones); `None` leaves the encoder to burn.
    pub(super) encoder: Option<crate::net::InferenceEncoder>,
    pub(super) device: Device,
    /// The head for inference, fused ([`FusedHead`]): every scoring of the engine runs on it.
    pub(super) fused: Arc<FusedHead>,
    /// Grids 0 ..= max level, with precomputed projections up to the full level.
    pub(super) grids: Vec<GridLevel>,
    pub(super) projected: Vec<ProjectedGrid>,
    pub(super) config: EngineConfig,
    /// The load-time calibration that chose the search, when there was one.
    pub(super) calibration: Option<calibrate::Calibration>,
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

/// Cells of a full level scored between two looks at a call's [`Cancel`] (8 chunks at level 4;
/// ~0.1 s of both cores each on the slowest machine measured).
const FULL_LEVEL_CHUNK: usize = 36_864;

/// Predict options a model has checked ([`Model::check_predict`]): what its search runs with.
#[derive(Debug, Clone)]
pub struct CheckedPredict {
    level: u8,
    top_k: usize,
    /// Radians.
    mode_angle: f64,
    /// Set when the caller went away: the search stops at its next level or chunk.
    pub cancel: Cancel,
}

impl CheckedPredict {
    /// The finest level of the search.
    pub fn level(&self) -> u8 {
        self.level
    }

    /// Cells in the answer.
    pub fn top_k(&self) -> usize {
        self.top_k
    }
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
        let config = match &bundle.manifest.levels {
            Some(levels) => config.within(levels),
            None => config,
        };
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
            encoder: crate::net::InferenceEncoder::of(&bundle.network.encoder, config.kernels),
            network: bundle.network,
            device,
            fused,
            grids,
            projected,
            config,
            calibration: None,
        })
    }

    /// The search this model serves chosen on this CPU ([`super::calibrate::calibrate`]) among the
    /// searches of the bundle's study at `folder`, to the default search level, when the
    /// configuration has a budget; logged and kept in [`Model::calibration`].
    pub(super) fn calibrated(mut self, folder: &Path) -> Result<Model, EngineError> {
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
            calibration_spent = %c.spent,
            kernels = %self.kernel_paths(),
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

    /// The kernel each precision of the head runs on, and the encoder's, in words.
    pub fn kernel_paths(&self) -> String {
        let encoder = self.encoder.as_ref().map_or("burn's forward".into(), |e| {
            e.kernel_paths(self.manifest.network.image_size as usize)
        });
        format!("{}; encoder: {encoder}", self.fused.kernel_paths())
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
    /// ([`super::image::prepare_frame`]).
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

    /// Image features of prepared crops (one encoder pass for the batch), a plain row of `D`
    /// floats per crop: what every scoring method of the model reads. Each crop must be RGB8 of
    /// the model's input side ([`Model::prepare`] makes them); another length is an
    /// `InvalidArgument` naming the crop, never a panic.
    pub fn features(&self, crops: &[&[u8]]) -> Result<Vec<Vec<f32>>, EngineError> {
        let side = self.input_size() as usize;
        let expected = side * side * 3;
        if let Some((i, crop)) = crops.iter().enumerate().find(|(_, c)| c.len() != expected) {
            return Err(invalid(
                &format!("crops[{i}]"),
                format!(
                    "{} bytes, not the {expected} of an RGB8 crop of {side}×{side} (the model's input side)",
                    crop.len()
                ),
            ));
        }
        if crops.is_empty() {
            return Ok(Vec::new());
        }
        if let Some(encoder) = &self.encoder {
            return Ok(on_pool(|| encoder.features(crops, side)));
        }
        let images = images_tensor(crops, side, &self.device);
        Ok(feature_rows(self.network.encoder.forward(images)))
    }

    /// Length of a feature row.
    pub fn feature_dim(&self) -> usize {
        self.fused.image_dim()
    }

    /// Checks that every row has the encoder's width (rows from another model would be scored
    /// as garbage).
    fn check_rows<'r>(&self, rows: impl IntoIterator<Item = &'r [f32]>) -> Result<(), EngineError> {
        let d = self.feature_dim();
        match rows.into_iter().find(|r| r.len() != d) {
            Some(r) => Err(invalid(
                "features",
                format!("a row of {} values, not the encoder's {d}", r.len()),
            )),
            None => Ok(()),
        }
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

    /// Unnormalised log-weights `s_θ + s_φ` of every cell of `level` for one image's features,
    /// plus the fused depth term when given.
    fn full_logits(
        &self,
        features: &[f32],
        level: u8,
        depth: Option<DepthInput<'_>>,
        cancel: &Cancel,
    ) -> Result<Vec<f32>, EngineError> {
        // A level is scored in chunks, so that a caller that went away stops it within a chunk
        // (level 4 in one piece is about a second of both cores).
        let mut logits = self.projected[level as usize].log_weights_of_row_in_chunks(
            Precision::F32,
            features,
            FULL_LEVEL_CHUNK,
            || cancel.check(),
        )?;
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

    /// `s_θ + s_φ` of every cell of `level` for one image's features: from the
    /// precomputed projections at the full levels, above them projected chunk by chunk (an
    /// exhaustive reference for studies of the search; level 5 has 2.4 M cells).
    pub fn logits_at(&self, features: &[f32], level: u8) -> Result<Vec<f32>, EngineError> {
        self.logits_in(Precision::F32, features, level)
    }

    /// [`Model::logits_at`] in `precision`.
    pub fn logits_in(
        &self,
        precision: Precision,
        features: &[f32],
        level: u8,
    ) -> Result<Vec<f32>, EngineError> {
        self.logits_by((precision, Branches::Both), features, level)
    }

    /// [`Model::logits_at`] in `precision`, by `branches`: `s_θ + s_φ`, or `s_θ` alone.
    pub fn logits_by(
        &self,
        (precision, branches): (Precision, Branches),
        features: &[f32],
        level: u8,
    ) -> Result<Vec<f32>, EngineError> {
        self.check_rows([features])?;
        if let Some(projected) = self.projected.get(level as usize) {
            return Ok(projected.log_weights_of_row_by(precision, branches, features));
        }
        let grid = self.grid_at(level)?;
        let image = self.fused.image_term(features);
        let encoding = &self.manifest.network.encoding;
        let n = grid.len() as u64;
        let mut logits = Vec::with_capacity(grid.len());
        for start in (0..n).step_by(1 << 16) {
            let mats: Vec<[f32; 9]> = (start..(start + (1 << 16)).min(n))
                .map(|c| to_row_major_f32(&grid.rotation(c)))
                .collect();
            let encodings = encoding.encode(&mats);
            logits.extend(self.fused.scores_of(
                precision,
                &image,
                Rows::Encoded(&encodings),
                branches,
            ));
        }
        Ok(logits)
    }

    /// The full distribution at `level` (docs/DESIGN.md §2: `log p` per cell, `+ log(N/π²)`).
    pub fn distribution(
        &self,
        features: &[f32],
        level: u8,
        depth: Option<DepthInput<'_>>,
    ) -> Result<Distribution, EngineError> {
        self.distribution_cancellable(features, level, depth, &Cancel::default())
    }

    /// [`Model::distribution`] that stops with [`EngineError::Cancelled`] at the next chunk of
    /// the fused term once `cancel` is set.
    pub fn distribution_cancellable(
        &self,
        features: &[f32],
        level: u8,
        depth: Option<DepthInput<'_>>,
        cancel: &Cancel,
    ) -> Result<Distribution, EngineError> {
        self.check_full_level(level)?;
        self.check_rows([features])?;
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

    /// Checks the options of a prediction once, into what the search runs with.
    pub fn check_predict(&self, options: &PredictOptions) -> Result<CheckedPredict, EngineError> {
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
        Ok(CheckedPredict {
            level,
            top_k: options.top_k,
            mode_angle: options
                .mode_angle_deg
                .unwrap_or(DEFAULT_MODE_ANGLE_DEG)
                .to_radians(),
            cancel: options.cancel.clone(),
        })
    }

    /// Top-k by coarse-to-fine search from the start level to `options.level`, the modes of the
    /// result, and the covered mass.
    pub fn predict(
        &self,
        features: &[f32],
        options: &PredictOptions,
        depth: Option<DepthInput<'_>>,
    ) -> Result<Prediction, EngineError> {
        Ok(self
            .predict_many(&[features.to_vec()], options, &[depth])?
            .swap_remove(0))
    }

    /// [`Model::predict`] for the images of `features` (a row each) with the same options, in
    /// one batch: every level of their searches is scored in one pass of the head for all of
    /// them. `depth[b]` is image `b`'s depth input.
    pub fn predict_many(
        &self,
        features: &[Vec<f32>],
        options: &PredictOptions,
        depth: &[Option<DepthInput<'_>>],
    ) -> Result<Vec<Prediction>, EngineError> {
        self.predict_checked(features, &self.check_predict(options)?, depth)
    }

    /// [`Model::predict_many`] with options checked before ([`Model::check_predict`]).
    pub fn predict_checked(
        &self,
        features: &[Vec<f32>],
        options: &CheckedPredict,
        depth: &[Option<DepthInput<'_>>],
    ) -> Result<Vec<Prediction>, EngineError> {
        self.search(features, options, &self.config.search(), depth)
    }

    /// [`Model::predict_many`] with the search's start level and keep given instead of the
    /// server's (for studies of the search).
    pub fn predict_searching(
        &self,
        features: &[Vec<f32>],
        options: &PredictOptions,
        search: &SearchParams,
        depth: &[Option<DepthInput<'_>>],
    ) -> Result<Vec<Prediction>, EngineError> {
        self.search(features, &self.check_predict(options)?, search, depth)
    }

    /// The coarse-to-fine searches of `features`' images with `search`, to `options`' level.
    fn search(
        &self,
        features: &[Vec<f32>],
        options: &CheckedPredict,
        search: &SearchParams,
        depth: &[Option<DepthInput<'_>>],
    ) -> Result<Vec<Prediction>, EngineError> {
        let level = options.level;
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
        self.check_rows(features.iter().map(Vec::as_slice))?;
        let b = features.len();
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
        let results = on_pool(|| {
            coarse_to_fine_many(&grids, keep, b, |grid, cells| {
                let rescore = grid.level() == level && search.rescores_to(start, level);
                let precision = search.precision_at(grid.level(), start, level);
                let branches = search.branches_at(grid.level(), level);
                // A level boundary: a call whose caller went away stops here.
                options.cancel.check()?;
                let (mut logits, mats) =
                    self.search_logits(features, grid, cells, (precision, branches));
                let network = rescore.then(|| logits.clone());
                fusion.add_terms(grid, cells, &mats, &mut logits, &options.cancel)?;
                if let Some(network) = network {
                    options.cancel.check()?;
                    let rescored = options.top_k.max(RESCORED_CELLS);
                    self.rescore(features, (grid, cells), &network, &mut logits, rescored);
                }
                Ok::<_, EngineError>(logits)
            })
        })?;
        let grid = &self.grids[level as usize];
        let angle = options.mode_angle;
        Ok(results
            .into_iter()
            .zip(depth.iter().zip(&fusion.fitted))
            .map(|(result, (depth, fitted))| {
                prediction_of(grid, result, options.top_k, angle, depth.as_ref(), fitted)
            })
            .collect())
    }

    /// Replaces the network's part of the `count` best of each search's `logits` (the network's
    /// scores `network` in a reduced precision plus any depth terms) by its f32 scores: only the
    /// answer's cells pay for f32 ([`SearchParams::rescore_finest`]).
    fn rescore(
        &self,
        features: &[Vec<f32>],
        (grid, cells): (&GridLevel, &[Vec<u64>]),
        network: &[Vec<f32>],
        logits: &mut [Vec<f32>],
        count: usize,
    ) {
        let best: Vec<Vec<usize>> = logits
            .iter()
            .map(|l| {
                let l: Vec<f64> = l.iter().map(|&v| v as f64).collect();
                search::top_indices(&l, count)
            })
            .collect();
        let best_cells: Vec<Vec<u64>> = best
            .iter()
            .zip(cells)
            .map(|(best, cells)| best.iter().map(|&j| cells[j]).collect())
            .collect();
        let (exact, _) = self.search_logits(
            features,
            grid,
            &best_cells,
            (Precision::F32, Branches::Both),
        );
        for (((logits, network), best), exact) in
            logits.iter_mut().zip(network).zip(&best).zip(exact)
        {
            for (&j, e) in best.iter().zip(exact) {
                logits[j] += e - network[j];
            }
        }
    }

    /// `s_θ + s_φ` (or `s_θ` alone, by `branches`) of each search's `cells` of `grid` in
    /// `precision`: at a full level (up to [`EngineConfig::max_full_level`]) from the
    /// projections precomputed at load (the level in full when `cells` are all its cells in
    /// order, else the cells' projections gathered); above them from the
    /// cells' rotations, encoded. Also returns those rotations (row-major; empty at a full level,
    /// which does not compute them).
    fn search_logits(
        &self,
        features: &[Vec<f32>],
        grid: &GridLevel,
        cells: &[Vec<u64>],
        (precision, branches): (Precision, Branches),
    ) -> (Vec<Vec<f32>>, Vec<Vec<[f32; 9]>>) {
        if let Some(projected) = self.projected.get(grid.level() as usize) {
            let logits = features
                .iter()
                .zip(cells)
                .map(|(f, cells)| {
                    let every = cells.len() == projected.grid.len()
                        && cells.iter().enumerate().all(|(i, &c)| c == i as u64);
                    if every {
                        projected.log_weights_of_row_by(precision, branches, f)
                    } else {
                        projected.log_weights_of_cells_by(precision, branches, f, cells)
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
        (
            self.score_rotations_by(features, &mats, precision, branches),
            mats,
        )
    }

    /// `s_θ + s_φ` of `rotations[b]` (row-major, the same number for every image) for each image
    /// `b` of `features` (a row each), in one pass of the head, in `precision`.
    pub fn score_rotations_many(
        &self,
        features: &[Vec<f32>],
        rotations: &[Vec<[f32; 9]>],
        precision: Precision,
    ) -> Vec<Vec<f32>> {
        self.score_rotations_by(features, rotations, precision, Branches::Both)
    }

    /// [`Model::score_rotations_many`] by `branches`: `s_θ + s_φ`, or `s_θ` alone.
    pub fn score_rotations_by<R: AsRef<[[f32; 9]]>>(
        &self,
        features: &[Vec<f32>],
        rotations: &[R],
        precision: Precision,
        branches: Branches,
    ) -> Vec<Vec<f32>> {
        let encoding = &self.manifest.network.encoding;
        features
            .iter()
            .zip(rotations)
            .map(|(f, rotations)| {
                let encodings = encoding.encode(rotations.as_ref());
                self.fused.scores_of(
                    precision,
                    &self.fused.image_term(f),
                    Rows::Encoded(&encodings),
                    branches,
                )
            })
            .collect()
    }

    /// Whether scoring in `precision` runs on this core's own instructions (else it is emulated).
    pub fn native(&self, precision: Precision) -> bool {
        self.fused.native(precision)
    }

    /// The kernel a reduced `precision` runs on, in words.
    pub fn kernel_name(&self, precision: Precision) -> &'static str {
        self.fused.kernel_name(precision)
    }

    /// The precomputed projections of a full `level` (up to [`EngineConfig::max_full_level`]).
    pub fn projected(&self, level: u8) -> Option<&ProjectedGrid> {
        self.projected.get(level as usize)
    }

    /// The grid of `level` (up to the highest level this model serves).
    pub fn grid(&self, level: u8) -> Option<&GridLevel> {
        self.grids.get(level as usize)
    }

    /// The grid of `level`, or an `InvalidArgument` naming the field `level` when it is above
    /// this model's grids.
    pub fn grid_at(&self, level: u8) -> Result<&GridLevel, EngineError> {
        self.grid(level).ok_or_else(|| {
            invalid(
                "level",
                format!(
                    "{level} is above this model's grids (0–{})",
                    self.grids.len() - 1
                ),
            )
        })
    }

    /// The engine configuration the model was built with.
    pub fn config(&self) -> &EngineConfig {
        &self.config
    }
}

/// Runs `work` on a thread of rayon's pool: a request's encoder and search each make dozens of
/// parallel passes, and a caller outside the pool (a server's blocking task, a benchmark's main
/// thread) hands each of them to the pool and sleeps until it is done; inside it, one hand-over
/// for all of them (the encoder at batch 1 on a 2-core AMD Zen 3: 0.6–1.8 ms of 6–8 saved,
/// docs/BENCHMARKS.md). Inline where the caller is already in the pool.
fn on_pool<R: Send>(work: impl FnOnce() -> R + Send) -> R {
    rayon::scope(|_| work())
}
