//! An expert set on disk: a folder with `manifest.json`, the normalised mesh (`mesh.ply`),
//! safetensors weights of the SDF SIREN, the key SIREN and the query CNN, and (format 2) the
//! object's table of relative rotations where targets have mass (`modes.json`).
//!
//! Format 1 sets (λ chosen against the declared symmetry, no mode table) are still read: the
//! server needs only their SDF expert, and the trainer builds their mode table when it starts.

use std::collections::BTreeMap;
use std::fs;
use std::path::Path;

use burn::tensor::Device;
use nalgebra::Rotation3;
use serde::{Deserialize, Serialize};

use super::{BundleError, FileEntry, load_weights, save_weights, sha256_file};
use crate::cad::{Mesh, Normalisation, write_ply};
use crate::experts::baked::VoxelGrid;
use crate::experts::energy::{BakedExperts, EnergyParams};
use crate::experts::feature::{
    FEATURE_DIM, FeatureFit, FeatureTrainConfig, QueryNet, QueryNetConfig,
};
use crate::experts::modes::{ModeTable, ModeTableConfig};
use crate::experts::sdf::{SdfFit, SdfTrainConfig};
use crate::experts::select::EnergySelection;
use crate::experts::symmetry::DiscoveredSymmetry;
use crate::experts::{Siren, SirenConfig, run_batched};
use crate::so3::{from_row_major, to_row_major};

/// Format version of expert manifests this build writes.
pub const EXPERTS_FORMAT_VERSION: u32 = 2;

/// The oldest format version this build reads.
pub const EXPERTS_OLDEST_FORMAT_VERSION: u32 = 1;

/// The object an expert set was trained for.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ObjectInfo {
    /// Name (a SYMSOL shape name or the mesh file's stem).
    pub name: String,
    /// Where the mesh came from.
    pub source: String,
    /// sha256 of the normalised mesh file `mesh.ply`.
    pub mesh_sha256: String,
    /// How the original mesh was mapped to NOCS.
    pub normalisation: Normalisation,
    /// The object's symmetries (row-major rotations, identity first), for evaluation and
    /// reports only: nothing in expert training or λ selection reads them.
    pub symmetries: Vec<[f64; 9]>,
}

/// How the voxel bakes are made, and how far they are from the networks.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BakeInfo {
    /// Grid points per axis.
    pub resolution: usize,
    /// The grid covers `[−bound, bound]³`.
    pub bound: f32,
    /// Mean |baked − network| of the SDF at points near the surface (NOCS units).
    pub sdf_mean_error: f64,
    /// Mean ‖baked − network‖ of the keys at surface points, relative to the mean distance
    /// between keys of random surface points.
    pub keys_relative_error: f64,
}

/// `manifest.json` of an expert set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ExpertsManifest {
    /// [`EXPERTS_FORMAT_VERSION`].
    pub format_version: u32,
    /// The object.
    pub object: ObjectInfo,
    /// SDF expert training and fit.
    pub sdf: SdfSection,
    /// Feature expert training and fit.
    pub features: FeatureSection,
    /// Energy hyper-parameters (λ, ε, norm).
    pub energy: EnergyParams,
    /// How λ was chosen (format 2: the width criterion) and the targets' profile.
    pub energy_selection: EnergySelection,
    /// How the mode table was built (format 2).
    #[serde(default)]
    pub modes: Option<ModeTableConfig>,
    /// The symmetry the SDF expert shows (sets written before discovery have none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub symmetry: Option<DiscoveredSymmetry>,
    /// The voxel bakes.
    pub bake: BakeInfo,
    /// The command that made this set.
    pub command: String,
    /// Checksums of every file in the folder except the manifest.
    pub files: BTreeMap<String, FileEntry>,
}

/// The SDF expert's part of the manifest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SdfSection {
    /// Training configuration (also the network's shape).
    pub config: SdfTrainConfig,
    /// Fit figures.
    pub fit: SdfFit,
}

/// The feature expert's part of the manifest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FeatureSection {
    /// Training configuration (also the networks' shape).
    pub config: FeatureTrainConfig,
    /// Fit figures.
    pub fit: FeatureFit,
}

/// A loaded expert set.
pub struct ExpertSet {
    /// The manifest.
    pub manifest: ExpertsManifest,
    /// The normalised mesh.
    pub mesh: Mesh,
    /// `f_SDF`.
    pub sdf: Siren,
    /// `f_SE` keys.
    pub keys: Siren,
    /// The query CNN.
    pub query: QueryNet,
    /// The relative rotations where targets have mass (`None` in format 1 sets).
    pub modes: Option<ModeTable>,
}

const MODES_FILE: &str = "modes.json";
const MESH_FILE: &str = "mesh.ply";
const SDF_FILE: &str = "sdf.safetensors";
const KEYS_FILE: &str = "keys.safetensors";
const QUERY_FILE: &str = "query.safetensors";
const MANIFEST_FILE: &str = "manifest.json";

impl ExpertSet {
    /// The object's symmetries as rotations.
    pub fn symmetries(&self) -> Vec<Rotation3<f64>> {
        self.manifest
            .object
            .symmetries
            .iter()
            .filter_map(|m| from_row_major(*m).ok())
            .collect()
    }

    /// Writes the set into `dir` (created if needed): weights, mesh, then the manifest with every
    /// file's checksum (written last and atomically, so a half-written set has no manifest).
    pub fn save(&mut self, dir: &Path) -> Result<(), BundleError> {
        fs::create_dir_all(dir).map_err(|e| super::io_err(dir, e))?;
        let mesh_path = dir.join(MESH_FILE);
        write_ply(&self.mesh, &mesh_path)?;
        let mut files = BTreeMap::new();
        files.insert(MESH_FILE.to_string(), sha256_file(&mesh_path)?);
        files.insert(
            SDF_FILE.into(),
            save_weights(&self.sdf, &dir.join(SDF_FILE))?,
        );
        files.insert(
            KEYS_FILE.into(),
            save_weights(&self.keys, &dir.join(KEYS_FILE))?,
        );
        files.insert(
            QUERY_FILE.into(),
            save_weights(&self.query, &dir.join(QUERY_FILE))?,
        );
        if let Some(modes) = &self.modes {
            let path = dir.join(MODES_FILE);
            super::write_manifest(&path, modes)?;
            files.insert(MODES_FILE.into(), sha256_file(&path)?);
            self.manifest.modes = Some(modes.config);
        }
        self.manifest.object.mesh_sha256 = files[MESH_FILE].sha256.clone();
        self.manifest.files = files;
        super::write_manifest(&dir.join(MANIFEST_FILE), &self.manifest)
    }

    /// Loads and validates a set: format version, every file's checksum, every tensor's shape.
    /// The SIRENs go to the dense device, the query CNN to the convolution device.
    pub fn load(dir: &Path) -> Result<ExpertSet, BundleError> {
        let device = &crate::backend::device();
        let conv_device = &crate::backend::device_for(crate::backend::Workload::Conv);
        let manifest_path = dir.join(MANIFEST_FILE);
        let manifest: ExpertsManifest = super::read_manifest(&manifest_path)?;
        if !(EXPERTS_OLDEST_FORMAT_VERSION..=EXPERTS_FORMAT_VERSION)
            .contains(&manifest.format_version)
        {
            return Err(BundleError::Manifest {
                path: manifest_path.display().to_string(),
                message: format!(
                    "format_version is {} but this build reads {EXPERTS_OLDEST_FORMAT_VERSION} ..= \
                     {EXPERTS_FORMAT_VERSION}",
                    manifest.format_version
                ),
            });
        }
        check_manifest(&manifest, &manifest_path)?;
        let field = |message: String| BundleError::Manifest {
            path: manifest_path.display().to_string(),
            message,
        };
        let mesh_path = dir.join(MESH_FILE);
        super::verify_file(&mesh_path, &manifest.files[MESH_FILE])?;
        let mesh = Mesh::load(&mesh_path)?;
        let sdf_cfg = &manifest.sdf.config;
        let sdf = load_weights(
            SirenConfig::new(3, sdf_cfg.hidden, sdf_cfg.layers, 1).init(device),
            &dir.join(SDF_FILE),
            &manifest.files[SDF_FILE],
        )?;
        let keys = load_weights(
            key_siren_config().init(device),
            &dir.join(KEYS_FILE),
            &manifest.files[KEYS_FILE],
        )?;
        let query = load_weights(
            QueryNetConfig::new()
                .with_width(manifest.features.config.width)
                .init(conv_device),
            &dir.join(QUERY_FILE),
            &manifest.files[QUERY_FILE],
        )?;
        let modes = if manifest.format_version >= 2 {
            let entry = manifest
                .files
                .get(MODES_FILE)
                .ok_or_else(|| field(format!("files: no entry for {MODES_FILE}")))?;
            let path = dir.join(MODES_FILE);
            super::verify_file(&path, entry)?;
            let table: ModeTable = super::read_manifest(&path)?;
            table.validate().map_err(|message| BundleError::Manifest {
                path: path.display().to_string(),
                message,
            })?;
            Some(table)
        } else {
            None
        };
        Ok(ExpertSet {
            manifest,
            mesh,
            sdf,
            keys,
            query,
            modes,
        })
    }

    /// The twins of the part's near-symmetry ([`NearSymmetry::twins`]; none when the set
    /// records no near-symmetry).
    ///
    /// [`NearSymmetry::twins`]: crate::experts::symmetry::NearSymmetry::twins
    pub fn near_twins(&self) -> Vec<Rotation3<f64>> {
        self.manifest
            .symmetry
            .as_ref()
            .and_then(|s| s.near.as_ref())
            .map(|n| n.twins())
            .unwrap_or_default()
    }

    /// The mode table: the stored one, or (format 1 sets) one built now from `baked`.
    pub fn mode_table(&self, baked: &BakedExperts) -> Result<ModeTable, crate::so3::So3Error> {
        match &self.modes {
            Some(table) => Ok(table.clone()),
            None => ModeTable::build(baked, &self.mesh, &ModeTableConfig::default()),
        }
    }

    /// Bakes both experts on the manifest's grid and attaches its energy hyper-parameters.
    pub fn bake(&self) -> BakedExperts {
        let device = &crate::backend::device();
        bake_experts(
            &self.sdf,
            &self.keys,
            self.manifest.bake.resolution,
            self.manifest.bake.bound,
            self.manifest.energy,
            device,
        )
    }
}

/// The key SIREN's shape: 3 → 256 → 256 → 12 (SurfEmb).
pub fn key_siren_config() -> SirenConfig {
    SirenConfig::new(3, 256, 2, FEATURE_DIM)
}

/// Bakes the SDF and key networks into voxel grids.
pub fn bake_experts(
    sdf: &Siren,
    keys: &Siren,
    resolution: usize,
    bound: f32,
    params: EnergyParams,
    device: &Device,
) -> BakedExperts {
    BakedExperts::new(
        VoxelGrid::bake(resolution, bound, 1, |p| run_batched(sdf, p, 1, device)),
        VoxelGrid::bake(resolution, bound, FEATURE_DIM, |p| {
            run_batched(keys, p, FEATURE_DIM, device)
        }),
        params,
    )
}

/// Row-major symmetries for the manifest.
pub fn symmetries_row_major(symmetries: &[Rotation3<f64>]) -> Vec<[f64; 9]> {
    symmetries.iter().map(to_row_major).collect()
}

/// Checks an expert manifest's entries and shapes before any network is allocated (a manifest
/// is user input): every file listed, the networks' sizes in range, the mesh's checksum
/// consistent, every symmetry a rotation.
fn check_manifest(manifest: &ExpertsManifest, manifest_path: &Path) -> Result<(), BundleError> {
    let field = |message: String| BundleError::Manifest {
        path: manifest_path.display().to_string(),
        message,
    };
    for name in [MESH_FILE, SDF_FILE, KEYS_FILE, QUERY_FILE] {
        if !manifest.files.contains_key(name) {
            return Err(field(format!("files: no entry for {name}")));
        }
    }
    // Shapes are checked before any network is allocated: a manifest is user input.
    let shapes = &crate::net::NETWORK_LIMITS;
    crate::net::check_range(
        "sdf.config.hidden",
        manifest.sdf.config.hidden,
        &shapes.hidden,
    )
    .and_then(|()| {
        crate::net::check_range(
            "sdf.config.layers",
            manifest.sdf.config.layers,
            &shapes.layers,
        )
    })
    .and_then(|()| {
        crate::net::check_range(
            "features.config.width",
            manifest.features.config.width,
            &(1..=512),
        )
    })
    .map_err(field)?;
    if manifest.object.mesh_sha256 != manifest.files[MESH_FILE].sha256 {
        return Err(field(
            "object.mesh_sha256 differs from files.\"mesh.ply\".sha256".into(),
        ));
    }
    for (i, m) in manifest.object.symmetries.iter().enumerate() {
        from_row_major(*m).map_err(|e| field(format!("object.symmetries[{i}]: {e}")))?;
    }
    Ok(())
}
