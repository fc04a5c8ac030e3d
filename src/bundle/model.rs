//! A model bundle (docs/DESIGN.md §4): `models/<name>/` with `manifest.json`, the network's weights
//! (`network.safetensors`), and, per object, the expert set it was trained with
//! (`experts/<object>/`, which holds the object's normalised mesh).

use std::collections::BTreeMap;
use std::fs;
use std::path::Path;

use burn::tensor::Device;

use super::experts::ExpertSet;
pub use super::record::{
    BundleObject, GridLevels, INPUT_CONVENTION, MODEL_FORMAT_VERSION, ModelManifest, Provenance,
};
use super::{BundleError, FileEntry, load_weights, save_weights, sha256_file};
use crate::net::Network;

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

impl ModelBundle {
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
        let manifest = Self::checked_manifest(dir)?;
        let manifest_path = dir.join(MANIFEST_FILE);
        let field = |message: String| BundleError::Manifest {
            path: manifest_path.display().to_string(),
            message,
        };
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

    /// The manifest of the bundle in `dir` and its weights file's entry, checked as [`load`]
    /// checks them (format version, fields, the weights file's checksum), without the experts:
    /// what a warm start or a teacher needs (`fit --init`, `new --init`, `fit --teacher`). A
    /// folder that holds a bundle's manifest and weights alone passes (`training/warm-starts/`
    /// keeps some so); it is no bundle to serve, and [`load`] refuses it.
    ///
    /// [`load`]: ModelBundle::load
    pub fn load_weights_entry(dir: &Path) -> Result<(ModelManifest, FileEntry), BundleError> {
        let manifest = Self::checked_manifest(dir)?;
        let entry =
            manifest
                .files
                .get(NETWORK_FILE)
                .cloned()
                .ok_or_else(|| BundleError::Manifest {
                    path: dir.join(MANIFEST_FILE).display().to_string(),
                    message: format!("files: no entry for {NETWORK_FILE}"),
                })?;
        super::verify_file(&dir.join(NETWORK_FILE), &entry)?;
        Ok((manifest, entry))
    }

    /// The manifest in `dir`, read at its format version, naming an object, with valid network
    /// fields and grid levels.
    fn checked_manifest(dir: &Path) -> Result<ModelManifest, BundleError> {
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
        if let Some(levels) = manifest.levels {
            for (name, level) in [
                ("levels.full_max", levels.full_max),
                ("levels.search_max", levels.search_max),
            ] {
                crate::net::check_range(name, level, &(0..=crate::so3::MAX_LEVEL))
                    .map_err(field)?;
            }
        }
        Ok(manifest)
    }
}
