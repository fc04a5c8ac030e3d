//! The models directory: every bundle loaded and validated, the ones that fail listed.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use rayon::prelude::*;

use super::{EngineConfig, EngineError, Model, invalid, quoted_name};
use crate::bundle::model::ModelBundle;

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

    /// Loads one bundle folder, depth fusion included ([`super::DepthFusion::warm`] for every object).
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
