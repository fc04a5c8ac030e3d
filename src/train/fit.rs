//! What `alignist-train fit` assembles around a training run: the objects and their expert sets,
//! the training and test images (fresh renders or BOP datasets), the weights of a warm start, the
//! training set with its baked experts and mode tables, and the bundle's manifest. The binary
//! parses arguments and reports progress; everything it trains on is decided here.

use std::path::{Path, PathBuf};

use crate::bundle::BundleError;
use crate::bundle::experts::ExpertSet;
use crate::bundle::model::{BundleObject, ModelBundle, ModelManifest, NETWORK_FILE, Provenance};
use crate::bundle::record::{
    EvalReport, FileEntry, InitWeights, TeacherWeights, TrainConfig, TrainReport,
};
use crate::data::realism::{Realism, SceneAssets};
use crate::data::{BopDataset, DataError};
use crate::net::NetworkConfig;

use super::data::{FreshRenders, TrainingImage, eval_images, training_images};
use super::eval::EvalImage;
use super::trainer::TrainingSet;

/// Errors assembling a fit; each names the file or the setting.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    /// An expert set or a bundle that cannot be read.
    #[error("{path}: {source}")]
    Bundle {
        /// The folder given.
        path: String,
        /// What is wrong with it.
        source: BundleError,
    },
    /// A dataset that cannot be read.
    #[error("{path}: {source}")]
    Data {
        /// The dataset folder.
        path: String,
        /// What is wrong with it.
        source: DataError,
    },
    /// Settings that do not go together.
    #[error("{0}")]
    Invalid(String),
    /// A mode table that cannot be built.
    #[error("building the mode tables: {0}")]
    Modes(#[from] crate::so3::So3Error),
}

/// Where the training images come from.
#[derive(Debug, Clone, PartialEq)]
pub enum FitSource {
    /// New renders of the experts' meshes at every step, and fresh test crops.
    Fresh {
        /// Realistic renders (`data::realism`, its training split) instead of flat ones.
        realistic: bool,
        /// Supersampling per axis (anti-aliasing), 1 ..= 8.
        supersample: u32,
        /// Seed of the fresh test crops (keep it apart from training seeds).
        eval_seed: u64,
    },
    /// BOP datasets, one per object (its `train` and `test` splits), in the order of the
    /// expert sets.
    Datasets(Vec<PathBuf>),
}

/// What a fit trains and tests on.
#[derive(Debug, Clone, PartialEq)]
pub struct FitInputs {
    /// The expert set of each object.
    pub experts: Vec<PathBuf>,
    /// The images.
    pub source: FitSource,
    /// Crop side in pixels.
    pub image_size: u32,
    /// The low-data regime: the share of each training split used, or with fresh renders a fixed
    /// pool of `fraction × steps × batch` renders shared out over the objects. 1: everything.
    pub fraction: f64,
    /// Test crops per object (0: no evaluation).
    pub eval_images: usize,
}

/// The objects, their expert sets and the images of a fit.
pub struct FitData {
    /// The bundle's objects, in order.
    pub objects: Vec<BundleObject>,
    /// Their expert sets.
    pub sets: Vec<ExpertSet>,
    /// Training images read from datasets (empty with fresh renders).
    pub images: Vec<TrainingImage>,
    /// Test crops.
    pub tests: Vec<EvalImage>,
    /// The renderer of fresh training crops.
    pub fresh: Option<FreshRenders>,
}

fn load_sets(experts: &[PathBuf]) -> Result<Vec<ExpertSet>, FitError> {
    experts
        .iter()
        .map(|e| {
            ExpertSet::load(e).map_err(|source| FitError::Bundle {
                path: e.display().to_string(),
                source,
            })
        })
        .collect()
}

impl FitData {
    /// Reads the expert sets and prepares the images of `inputs` for a run of `steps × batch`
    /// images (the size of a fixed pool of fresh renders).
    pub fn load(inputs: &FitInputs, steps: usize, batch: usize) -> Result<FitData, FitError> {
        if !(inputs.fraction > 0.0 && inputs.fraction <= 1.0) {
            return Err(FitError::Invalid(format!(
                "--fraction must be in (0, 1], got {}",
                inputs.fraction
            )));
        }
        match &inputs.source {
            FitSource::Fresh {
                realistic,
                supersample,
                eval_seed,
            } => fresh_data(inputs, *realistic, *supersample, *eval_seed, steps * batch),
            FitSource::Datasets(data) => dataset_data(inputs, data),
        }
    }

    /// The training set: the experts baked, their mode tables built, the images (moved out of
    /// this).
    pub fn training_set(&mut self) -> Result<TrainingSet, FitError> {
        let baked: Vec<_> = self.sets.iter().map(|s| s.bake()).collect();
        let modes = self
            .sets
            .iter()
            .zip(&baked)
            .map(|(s, b)| s.mode_table(b))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(TrainingSet {
            objects: baked,
            modes,
            twins: self.sets.iter().map(|s| s.near_twins()).collect(),
            symmetries: self.sets.iter().map(|s| s.symmetries()).collect(),
            images: std::mem::take(&mut self.images),
            fresh: self.fresh.take(),
        })
    }

    /// What the data is, in a line (for logs).
    pub fn describe(&self) -> String {
        match &self.fresh {
            Some(fresh) => format!(
                "{} objects, {}; {} fresh test crops",
                self.sets.len(),
                match fresh.pool {
                    None => "fresh renders every step".to_string(),
                    Some(n) => format!("a fixed pool of {n} rendered images per object"),
                },
                self.tests.len(),
            ),
            None => format!(
                "{} objects, {} training images, {} test crops",
                self.sets.len(),
                self.images.len(),
                self.tests.len()
            ),
        }
    }
}

/// Fresh renders of the experts' meshes and `eval_images` fresh test crops per object.
fn fresh_data(
    inputs: &FitInputs,
    realistic: bool,
    supersample: u32,
    eval_seed: u64,
    images_seen: usize,
) -> Result<FitData, FitError> {
    if !(1..=8).contains(&supersample) {
        return Err(FitError::Invalid(format!(
            "--supersample must be in 1 ..= 8, got {supersample}"
        )));
    }
    let sets = load_sets(&inputs.experts)?;
    let meshes: Vec<_> = sets.iter().map(|s| s.mesh.clone()).collect();
    let fresh = FreshRenders {
        realism: realistic.then(|| SceneAssets::new(&meshes, Realism::TRAIN)),
        meshes,
        supersample,
        // The low-data regime on fresh renders: a fixed pool holding `fraction` of the images a
        // run of this budget sees, shared out over the objects.
        pool: (inputs.fraction < 1.0)
            .then(|| ((inputs.fraction * images_seen as f64) / sets.len() as f64).ceil() as usize),
    };
    let names: Vec<String> = sets
        .iter()
        .map(|s| s.manifest.object.name.clone())
        .collect();
    let symmetries: Vec<_> = sets.iter().map(|s| s.symmetries()).collect();
    let tests = fresh.eval_images(
        &names,
        &symmetries,
        inputs.image_size,
        inputs.eval_images,
        eval_seed,
    );
    let data = match fresh.pool {
        None => format!(
            "fresh {}renders ({supersample}x supersampled)",
            if realistic { "realistic " } else { "" },
        ),
        Some(n) => format!("a fixed pool of {n} renders ({supersample}x supersampled)"),
    };
    let objects = names
        .iter()
        .map(|name| BundleObject {
            name: name.clone(),
            experts: format!("experts/{name}"),
            data: data.clone(),
            train_images: fresh.pool.unwrap_or(0),
        })
        .collect();
    Ok(FitData {
        objects,
        sets,
        images: Vec::new(),
        tests,
        fresh: Some(fresh),
    })
}

/// Training and test images from BOP datasets, one per expert set.
fn dataset_data(inputs: &FitInputs, data: &[PathBuf]) -> Result<FitData, FitError> {
    if data.len() != inputs.experts.len() {
        return Err(FitError::Invalid(format!(
            "give one --experts per --data ({} --data, {} --experts)",
            data.len(),
            inputs.experts.len()
        )));
    }
    let sets = load_sets(&inputs.experts)?;
    let (mut objects, mut images, mut tests) = (Vec::new(), Vec::new(), Vec::new());
    for (i, (dir, set)) in data.iter().zip(&sets).enumerate() {
        let data_err = |source| FitError::Data {
            path: dir.display().to_string(),
            source,
        };
        let train = BopDataset::open(dir, "train").map_err(data_err)?;
        let imgs = training_images(&train, i, &set.mesh, inputs.image_size, inputs.fraction)
            .map_err(data_err)?;
        let name = set.manifest.object.name.clone();
        objects.push(BundleObject {
            name: name.clone(),
            experts: format!("experts/{name}"),
            data: dir.display().to_string(),
            train_images: imgs.len(),
        });
        images.extend(imgs);
        if inputs.eval_images > 0 {
            let test = BopDataset::open(dir, "test").map_err(data_err)?;
            tests.extend(
                eval_images(&test, &name, inputs.image_size, inputs.eval_images)
                    .map_err(data_err)?,
            );
        }
    }
    Ok(FitData {
        objects,
        sets,
        images,
        tests,
        fresh: None,
    })
}

/// The weights of the bundle in `dir`, checked to be of `network`: the start of a warm restart,
/// recorded with their checksum and the command that trained them.
///
/// The crop side may differ: every layout ends in average pooling, so the encoder's weights are
/// the same tensors at any input size (a 32 px network warm-starts a 64 px one). So may the
/// layout, where this run's grows theirs (`tiny` → `tiny_deep`: the added blocks start as
/// identities; → `tiny_wide`: the added channels start unread), and the pooling, from global to a grid of cells (the head's image projection
/// spread over the cells: the same scores at the start). The side, layout and pooling the weights
/// were trained with are recorded beside them.
pub fn init_weights(dir: &Path, network: &NetworkConfig) -> Result<InitWeights, FitError> {
    let (path, manifest, file) = bundle_weights(dir)?;
    let theirs = &manifest.network;
    let same_tensors = NetworkConfig {
        image_size: network.image_size,
        layout: if network.layout.grows(theirs.layout) {
            network.layout
        } else {
            theirs.layout
        },
        pool_grid: if theirs.pooling() == 1 {
            network.pool_grid
        } else {
            theirs.pool_grid
        },
        ..theirs.clone()
    };
    if &same_tensors != network {
        let json = |n: &NetworkConfig| serde_json::to_string(n).unwrap_or_default();
        return Err(FitError::Invalid(format!(
            "{path}: its network ({}) is not the one asked for ({}); give the same encoding, \
             hidden width and layers, its layout or one that grows it, and its pooling grid \
             (or any grid from global pooling; the image size may differ)",
            json(theirs),
            json(network)
        )));
    }
    Ok(InitWeights {
        path: dir.join(NETWORK_FILE).display().to_string(),
        file,
        trained_by: manifest.provenance.command.clone(),
        image_size: (theirs.image_size != network.image_size).then_some(theirs.image_size),
        layout: (theirs.layout != network.layout).then_some(theirs.layout),
        pool_grid: (theirs.pooling() != network.pooling()).then_some(theirs.pooling()),
    })
}

/// The bundle in `dir` (its path for messages, its manifest) and its weights file's entry,
/// checked; its experts need not be there ([`ModelBundle::load_weights_entry`]).
fn bundle_weights(dir: &Path) -> Result<(String, ModelManifest, FileEntry), FitError> {
    let path = dir.display().to_string();
    let (manifest, file) =
        ModelBundle::load_weights_entry(dir).map_err(|source| FitError::Bundle {
            path: path.clone(),
            source,
        })?;
    Ok((path, manifest, file))
}

/// The weights of the bundle in `dir` as the teacher of a distilled head
/// ([`super::distil`]): checked to share `network`'s encoder (layout and crop side) and
/// rotation encoding, recorded with their checksum and the command that trained them.
pub fn teacher_weights(dir: &Path, network: &NetworkConfig) -> Result<TeacherWeights, FitError> {
    let (_, manifest, file) = bundle_weights(dir)?;
    let teacher = TeacherWeights {
        path: dir.join(NETWORK_FILE).display().to_string(),
        file,
        network: manifest.network.clone(),
        trained_by: manifest.provenance.command.clone(),
    };
    super::distil::check_pair(&teacher, network).map_err(|e| FitError::Invalid(e.to_string()))?;
    Ok(teacher)
}

/// The manifest of a bundle fitted by `command` (its files are added when it is saved): served
/// up to the engine's default levels.
pub fn fitted_manifest(
    name: String,
    objects: Vec<BundleObject>,
    command: String,
    config: TrainConfig,
    report: TrainReport,
    evaluation: Option<EvalReport>,
) -> ModelManifest {
    ModelManifest::new(
        name,
        config.network.clone(),
        objects,
        Provenance {
            command,
            train: config,
            report,
        },
        evaluation,
    )
}
