//! A model bundle (DESIGN.md §3): `models/<name>/` with `manifest.json`, the network's weights
//! (`network.safetensors`), and, per object, the expert set it was trained with
//! (`experts/<object>/`, which holds the object's normalised mesh).

use std::collections::BTreeMap;
use std::fs;
use std::path::Path;

use burn::tensor::Device;
use serde::{Deserialize, Serialize};

use super::experts::ExpertSet;
use super::{BundleError, FileEntry, load_weights, save_weights, sha256_file};
use crate::train::eval::EvalReport;
use crate::train::{Network, NetworkConfig, TrainConfig, TrainReport};

/// Format version of model manifests this build reads and writes.
pub const MODEL_FORMAT_VERSION: u32 = 1;

/// One object a bundle knows.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BundleObject {
    /// Name (as in requests).
    pub name: String,
    /// Its expert set, relative to the bundle.
    pub experts: String,
    /// The training data it was fitted on.
    pub data: String,
    /// Training images used.
    pub train_images: usize,
}

/// How the network was trained.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
    /// The exact command.
    pub command: String,
    /// The training configuration (seed, steps, method, …).
    pub train: TrainConfig,
    /// What the run did.
    pub report: TrainReport,
}

/// `manifest.json` of a model bundle.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelManifest {
    /// [`MODEL_FORMAT_VERSION`].
    pub format_version: u32,
    /// Bundle name.
    pub name: String,
    /// The network (input size, layout, encoding, head).
    pub network: NetworkConfig,
    /// Input normalisation: crops are RGB scaled to `[0, 1]`, object-centred (DESIGN.md §2).
    pub input: String,
    /// Objects, in the order the bundle was trained on them.
    pub objects: Vec<BundleObject>,
    /// Highest grid level served in full, and highest level of the coarse-to-fine search.
    pub levels: GridLevels,
    /// Training provenance.
    pub provenance: Provenance,
    /// Evaluation on held-out images, when it was run.
    pub evaluation: Option<EvalReport>,
    /// Checksums of every file except the manifest, relative to the bundle.
    pub files: BTreeMap<String, FileEntry>,
}

/// The input convention every bundle records (`ModelManifest::input`).
pub const INPUT_CONVENTION: &str = "RGB crop as a virtual camera looking at the centre of the \
    object's box sees it: a square of 1.2 × the box's longer side (never stretched), side \
    image_size, values / 255 (src/data/virtual_crop.rs)";

impl ModelManifest {
    /// The manifest of a bundle trained now (no files yet: [`ModelBundle::save`] adds them), with
    /// the [`INPUT_CONVENTION`].
    pub fn new(
        name: String,
        network: NetworkConfig,
        objects: Vec<BundleObject>,
        levels: GridLevels,
        provenance: Provenance,
        evaluation: Option<EvalReport>,
    ) -> ModelManifest {
        ModelManifest {
            format_version: MODEL_FORMAT_VERSION,
            name,
            network,
            input: INPUT_CONVENTION.into(),
            objects,
            levels,
            provenance,
            evaluation,
            files: Default::default(),
        }
    }
}

/// Grid levels of a bundle: the server serves it up to these at most
/// (`EngineConfig::within`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct GridLevels {
    /// Full distributions up to this level.
    pub full_max: u8,
    /// Coarse-to-fine top-k up to this level.
    pub search_max: u8,
}

/// A loaded bundle.
pub struct ModelBundle {
    /// The manifest.
    pub manifest: ModelManifest,
    /// The network, on the convolution device.
    pub network: Network,
    /// Expert sets, one per object, in manifest order.
    pub experts: Vec<ExpertSet>,
}

/// The network's weight file inside a bundle.
pub const NETWORK_FILE: &str = "network.safetensors";
const MANIFEST_FILE: &str = "manifest.json";

/// Copies the folder `from` into `to` (created), subfolders included.
pub fn copy_dir(from: &Path, to: &Path) -> Result<(), BundleError> {
    fs::create_dir_all(to).map_err(|e| super::io_err(to, e))?;
    for entry in fs::read_dir(from).map_err(|e| super::io_err(from, e))? {
        let entry = entry.map_err(|e| super::io_err(from, e))?;
        let target = to.join(entry.file_name());
        if entry.path().is_dir() {
            copy_dir(&entry.path(), &target)?;
        } else {
            fs::copy(entry.path(), &target).map_err(|e| super::io_err(&target, e))?;
        }
    }
    Ok(())
}

/// A bundle's objects as fresh renders, in object order: the renderer of their meshes, their
/// names and their symmetries (what `eval_images` and `frame_eval_images` take).
pub struct BundleRenders {
    /// The renderer.
    pub fresh: crate::train::data::FreshRenders,
    /// Object names.
    pub names: Vec<String>,
    /// Each object's proper symmetries.
    pub symmetries: Vec<Vec<nalgebra::Rotation3<f64>>>,
}

impl BundleRenders {
    /// `per_object` fresh evaluation crops of `size` of every object, placed from `seed`.
    pub fn eval_images(
        &self,
        size: u32,
        per_object: usize,
        seed: u64,
    ) -> Vec<crate::train::eval::EvalImage> {
        self.fresh
            .eval_images(&self.names, &self.symmetries, size, per_object, seed)
    }
}

impl ModelBundle {
    /// Its objects as fresh renders, supersampled `supersample` times per axis.
    pub fn renders(&self, supersample: u32) -> BundleRenders {
        BundleRenders {
            fresh: crate::train::data::FreshRenders {
                meshes: self.experts.iter().map(|e| e.mesh.clone()).collect(),
                supersample,
                pool: None,
                realism: None,
            },
            names: self
                .manifest
                .objects
                .iter()
                .map(|o| o.name.clone())
                .collect(),
            symmetries: self.experts.iter().map(|e| e.symmetries()).collect(),
        }
    }

    /// Writes the bundle into `dir`: the network, a copy of each object's expert set (from the
    /// folders it was loaded from), and the manifest last.
    pub fn save(
        manifest: &mut ModelManifest,
        network: &Network,
        expert_dirs: &[&Path],
        dir: &Path,
    ) -> Result<(), BundleError> {
        fs::create_dir_all(dir).map_err(|e| super::io_err(dir, e))?;
        let mut files = BTreeMap::new();
        files.insert(
            NETWORK_FILE.to_string(),
            save_weights(network, &dir.join(NETWORK_FILE))?,
        );
        for (object, from) in manifest.objects.iter().zip(expert_dirs) {
            let to = dir.join(&object.experts);
            copy_dir(from, &to)?;
            for entry in fs::read_dir(&to).map_err(|e| super::io_err(&to, e))? {
                let path = entry.map_err(|e| super::io_err(&to, e))?.path();
                let rel = format!(
                    "{}/{}",
                    object.experts,
                    path.file_name()
                        .and_then(|n| n.to_str())
                        .unwrap_or_default()
                );
                files.insert(rel, sha256_file(&path)?);
            }
        }
        manifest.files = files;
        super::write_manifest(&dir.join(MANIFEST_FILE), manifest)
    }

    /// Loads and validates a bundle: format version, every file's checksum, every tensor's shape,
    /// every expert set (each validated by [`ExpertSet::load`]).
    pub fn load(dir: &Path) -> Result<ModelBundle, BundleError> {
        let manifest_path = dir.join(MANIFEST_FILE);
        let manifest: ModelManifest = super::read_versioned_manifest(
            &manifest_path,
            MODEL_FORMAT_VERSION,
            |m: &ModelManifest| m.format_version,
        )?;
        let field = |message: String| BundleError::Manifest {
            path: manifest_path.display().to_string(),
            message,
        };
        if manifest.objects.is_empty() {
            return Err(field("objects: the bundle names no object".into()));
        }
        manifest.network.validate().map_err(field)?;
        for (name, level) in [
            ("levels.full_max", manifest.levels.full_max),
            ("levels.search_max", manifest.levels.search_max),
        ] {
            crate::net::check_range(name, level, &(0..=crate::so3::MAX_LEVEL)).map_err(field)?;
        }
        for (rel, entry) in &manifest.files {
            let path = super::inside(dir, rel).map_err(|e| field(format!("files: {e}")))?;
            super::verify_file(&path, entry)?;
        }
        let expert_dirs = manifest
            .objects
            .iter()
            .enumerate()
            .map(|(i, o)| {
                super::inside(dir, &o.experts)
                    .map_err(|e| field(format!("objects[{i}].experts: {e}")))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let network_entry = manifest
            .files
            .get(NETWORK_FILE)
            .ok_or_else(|| field(format!("files: no entry for {NETWORK_FILE}")))?;
        let device: Device = crate::backend::device_for(crate::backend::Workload::Conv);
        let network = load_weights(
            manifest.network.init(&device),
            &dir.join(NETWORK_FILE),
            network_entry,
        )?;
        let experts = expert_dirs
            .iter()
            .map(|d| ExpertSet::load(d))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(ModelBundle {
            manifest,
            network,
            experts,
        })
    }
}
