//! Checkpoints: `<dir>/step-NNNNNNNN/{model.bpk, optim.bpk, state.json}` and `<dir>/latest`
//! naming the newest complete one.
//!
//! A checkpoint is written into `step-NNNNNNNN.partial/`, every file fsynced, the folder renamed
//! into place, and only then is `latest` replaced (write, fsync, rename). A run killed at any
//! point leaves `latest` naming a complete checkpoint; it loses at most the steps since it. The
//! model is stored in burnpack, which keeps parameter ids, so the optimizer's state (keyed by
//! them) applies to the restored model.

use std::fs;
use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::optim::ModuleOptimizer;
use burn::store::{BurnpackStore, ModuleSnapshot};
use burn::tensor::Device;
use serde::{Deserialize, Serialize};

use super::TrainError;
use super::config::TrainConfig;
use crate::net::Network;
use crate::so3::{from_row_major, to_row_major};
use nalgebra::Rotation3;

/// What a checkpoint records besides the weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointState {
    /// Steps completed.
    pub step: usize,
    /// The run's configuration.
    pub config: TrainConfig,
    /// Per object, the network's own twins in effect from this step (row-major rotations;
    /// [`crate::train::sampling::OwnTwins`]), so that a resumed run draws what the run it
    /// continues drew.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub own_twins: Vec<Vec<[f64; 9]>>,
}

impl CheckpointState {
    /// The state after `step` steps of `config`, with the network's own twins `own_twins`.
    pub fn new(step: usize, config: TrainConfig, own_twins: &[Vec<Rotation3<f64>>]) -> Self {
        CheckpointState {
            step,
            config,
            own_twins: own_twins
                .iter()
                .map(|t| t.iter().map(to_row_major).collect())
                .collect(),
        }
    }

    /// The network's own twins recorded, as rotations.
    pub fn own_twins(&self) -> Result<Vec<Vec<Rotation3<f64>>>, TrainError> {
        self.own_twins
            .iter()
            .map(|t| {
                t.iter()
                    .map(|m| {
                        from_row_major(*m).map_err(|e| TrainError::Checkpoint {
                            path: format!("checkpoint of step {}", self.step),
                            message: format!("own_twins: {e}"),
                        })
                    })
                    .collect()
            })
            .collect()
    }
}

fn err(path: &Path, message: impl std::fmt::Display) -> TrainError {
    TrainError::Checkpoint {
        path: path.display().to_string(),
        message: message.to_string(),
    }
}

fn write_synced(path: &Path, bytes: &[u8]) -> Result<(), TrainError> {
    use std::io::Write;
    let mut f = fs::File::create(path).map_err(|e| err(path, e))?;
    f.write_all(bytes).map_err(|e| err(path, e))?;
    f.sync_all().map_err(|e| err(path, e))
}

/// Writes a checkpoint atomically and points `latest` at it; keeps the two newest.
pub fn save_checkpoint(
    dir: &Path,
    network: &Network,
    optim: &ModuleOptimizer,
    state: &CheckpointState,
) -> Result<PathBuf, TrainError> {
    let name = format!("step-{:08}", state.step);
    let final_dir = dir.join(&name);
    let tmp = dir.join(format!("{name}.partial"));
    if tmp.exists() {
        fs::remove_dir_all(&tmp).map_err(|e| err(&tmp, e))?;
    }
    fs::create_dir_all(&tmp).map_err(|e| err(&tmp, e))?;
    let model_path = tmp.join("model.bpk");
    let mut store = BurnpackStore::from_file(&model_path)
        .overwrite(true)
        .auto_extension(false);
    network
        .save_into(&mut store)
        .map_err(|e| err(&model_path, e))?;
    fs::File::open(&model_path)
        .and_then(|f| f.sync_all())
        .map_err(|e| err(&model_path, e))?;
    let optim_path = tmp.join("optim.bpk");
    let bytes = optim
        .into_bytes()
        .map_err(|e| err(&optim_path, format!("{e:?}")))?;
    write_synced(&optim_path, &bytes)?;
    let state_path = tmp.join("state.json");
    let json = serde_json::to_vec_pretty(state).map_err(|e| err(&state_path, e))?;
    write_synced(&state_path, &json)?;
    if final_dir.exists() {
        fs::remove_dir_all(&final_dir).map_err(|e| err(&final_dir, e))?;
    }
    fs::rename(&tmp, &final_dir).map_err(|e| err(&final_dir, e))?;
    let latest_tmp = dir.join("latest.partial");
    write_synced(&latest_tmp, name.as_bytes())?;
    fs::rename(&latest_tmp, dir.join("latest")).map_err(|e| err(&dir.join("latest"), e))?;
    // Keep the two newest complete checkpoints.
    let mut old: Vec<PathBuf> = fs::read_dir(dir)
        .map_err(|e| err(dir, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("step-") && !n.ends_with(".partial"))
        })
        .collect();
    old.sort();
    let keep_from = old.len().saturating_sub(2);
    for p in &old[..keep_from] {
        let _ = fs::remove_dir_all(p);
    }
    Ok(final_dir)
}

/// The checkpoint `latest` names, if there is one.
pub fn latest_checkpoint(dir: &Path) -> Result<Option<PathBuf>, TrainError> {
    let latest = dir.join("latest");
    if !latest.exists() {
        return Ok(None);
    }
    let name = fs::read_to_string(&latest).map_err(|e| err(&latest, e))?;
    let path = dir.join(name.trim());
    if !path.join("state.json").exists() {
        return Err(err(
            &latest,
            format!(
                "names {} which is not a complete checkpoint",
                path.display()
            ),
        ));
    }
    Ok(Some(path))
}

/// Restores the network and the optimizer from a checkpoint folder.
pub fn load_checkpoint(
    path: &Path,
    mut network: Network,
    optim: ModuleOptimizer,
    device: &Device,
) -> Result<(Network, ModuleOptimizer, CheckpointState), TrainError> {
    let state_path = path.join("state.json");
    let text = fs::read_to_string(&state_path).map_err(|e| err(&state_path, e))?;
    let state: CheckpointState = serde_json::from_str(&text).map_err(|e| err(&state_path, e))?;
    let model_path = path.join("model.bpk");
    let mut store = BurnpackStore::from_file(&model_path).auto_extension(false);
    let result = network
        .load_from(&mut store)
        .map_err(|e| err(&model_path, e))?;
    if !result.errors.is_empty() || !result.missing.is_empty() {
        return Err(err(
            &model_path,
            format!(
                "does not fit the network: {:?} {:?}",
                result.errors, result.missing
            ),
        ));
    }
    // Loading runs ops on the parameters; fork gives them a graph of their own.
    let network = network.valid().train().fork(device);
    let optim_path = path.join("optim.bpk");
    let optim = optim
        .load(&optim_path)
        .map_err(|e| err(&optim_path, format!("{e:?}")))?;
    Ok((network, optim, state))
}
