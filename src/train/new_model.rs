//! `alignist-train new`: from a user's CAD files to a served model within a time budget
//! (docs/DESIGN.md §5, "One command").
//!
//! The job runs in stages, each resumable, in a folder beside the bundle (`<out>.job`):
//! 1. **probe**: a few timed steps of each expert and, once the experts exist, of the network
//!    and its evaluation, on this machine; they size the plan ([`BudgetPlan`]);
//! 2. **experts** of every object (SDF, features, bake, λ, mode table, discovered symmetry),
//!    objects side by side on the cores, each written when done;
//! 3. **fit**: one schedule of [`RECIPE`] (realistic fresh renders, the focused share annealed
//!    from 3/4 to 1/20) sized to the time left, checkpointed; stopped early only if the machine
//!    turns out slower than the probe said;
//! 4. **calibration**: one temperature folded into the network, the one that maximises the LL of
//!    realistic crops of the *training* split ([`super::calibrate`]; measured to raise the
//!    held-out realistic LL, docs/RESULTS.md);
//! 5. **evaluation** on held-out realistic crops (another background source, light and
//!    material ranges, seed), and the bundle, with the plan and the time of every stage.
//!
//! The time spent is kept in the job's state across kills and resumes, so the budget is the
//! job's, not one process's.

use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::bundle::experts::ExpertSet;
use crate::bundle::model::ModelBundle;
use crate::bundle::record::{
    BudgetPlan, BudgetRecord, EvalReport, InitWeights, ModelManifest, TrainConfig, TrainReport,
};
use crate::cad::{LengthUnit, Mesh, Normalisation};
use crate::data::realism::Realism;
use crate::encoding::RotationEncoding;
use crate::experts::energy::EnergyParams;
use crate::experts::feature::FeatureTrainConfig;
use crate::experts::modes::ModeTableConfig;
use crate::experts::sdf::SdfTrainConfig;
use crate::experts::select::WidthCriterion;
use crate::net::{NetworkConfig, ResNetLayout};

use super::experts::{DEFAULT_BAKE_RESOLUTION, ExpertsJob, train_expert_set};
use super::fit::{FitData, FitInputs, FitSource, fitted_manifest};
use super::sampling::SamplingStrategy;
use super::trainer::{ExpertBranches, MeasureLoss, Method};

/// The recipe of one schedule, folded from the stages of the shipped SYMSOL model
/// (docs/RESULTS.md): what `new` trains with unless an experiment says otherwise.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Recipe {
    /// The image encoder's layout.
    pub layout: ResNetLayout,
    /// Crop side (px).
    pub image_size: u32,
    /// Images per step.
    pub batch: usize,
    /// Rotations per image.
    pub k: usize,
    /// Peak learning rate (warm-up, then cosine decay to zero).
    pub lr: f64,
    /// Focused share of the K at the first step, annealed linearly to `focused_end`.
    pub focused_start: f64,
    /// Focused share at the last step (the shipped model's last stage: 1/20).
    pub focused_end: f64,
    /// Supersampling of the fresh renders.
    pub supersample: u32,
    /// Share of the focused rotations drawn around the pose's twins (0 is the paper's
    /// sampling; the recipe's is 1/2).
    #[serde(default)]
    pub twin_share: f64,
    /// Crops per part on which the network's own half-turn misses are searched every
    /// [`OWN_TWINS_EVERY`] steps, to become twins besides the near-symmetry's
    /// ([`super::sampling::OwnTwins`]; needs a twin share; 0 for none; the recipe's is 32).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub own_twins: usize,
    /// Side of the grid the encoder's last feature map is averaged over (1: global average
    /// pooling, every job before it; the recipe's is 3; [`crate::net::EncoderConfig::pool_grid`]).
    #[serde(default = "global_pooling", skip_serializing_if = "is_one")]
    pub pool_grid: usize,
    /// Share of plain crops at the first step, annealed to the realism's (1/10) at the last: a
    /// curriculum ([`TrainConfig::plain_start`]; an experiment, none in the recipe).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plain_start: Option<f64>,
    /// The encoder's learning rate as a share of `lr` ([`TrainConfig::encoder_lr_scale`]; an
    /// experiment, none in the recipe).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub encoder_lr_scale: Option<f64>,
    /// The weight of the contrast term ([`TrainConfig::contrast`]; an experiment, none in the
    /// recipe).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub contrast: Option<f64>,
    /// The experts' log-targets' start temperature ([`TrainConfig::target_temperature`]; the
    /// recipe's is 100; none is the paper's untempered targets, as jobs recorded without it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target_temperature: Option<f64>,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

fn is_one(n: &usize) -> bool {
    *n == 1
}

fn global_pooling() -> usize {
    1
}

/// Steps between two searches of the network's own twins ([`Recipe::own_twins`]).
pub const OWN_TWINS_EVERY: usize = 250;

/// The recipe: batch 16 × K 256 at 48 px on the `tiny_deep` encoder, peak lr 1e-3, the focused
/// share 3/4 → 1/20, half of it drawn around the pose's twins (the near-symmetry's and the
/// network's own half-turn misses on 32 crops a part), the encoder's last map pooled over 3 × 3
/// cells, the experts' targets tempered from T 100 to 1. The warm start, [`NewModel::init`], is
/// the binary's default: the shipped `models/symsol1`. Chosen arm by arm in docs/RESULTS.md ("A
/// user's parts"): side by side, this start won at 48 px over 32 px on the duplo, own twins won
/// on the duplo and the drill, and 3 × 3 cells over global pooling on the drill and the mug;
/// against the first recipe it lost on no part. Tempering, at `--budget 2h` against the
/// untempered recipe: held-out AR@30 0.50 → 0.74 on the drill, 0.57 → 0.60 on the mug; the
/// mustard bottle 0.83 against 0.69 untempered and globally pooled.
pub const RECIPE: Recipe = Recipe {
    layout: ResNetLayout::TinyDeep,
    image_size: 48,
    batch: 16,
    k: 256,
    lr: 1e-3,
    focused_start: 0.75,
    focused_end: 0.05,
    supersample: 2,
    twin_share: 0.5,
    own_twins: 32,
    pool_grid: 3,
    plain_start: None,
    encoder_lr_scale: None,
    contrast: None,
    target_temperature: Some(TARGET_TEMPERATURE),
};

/// The recipe's start temperature of the experts' targets ([`Recipe::target_temperature`]).
pub const TARGET_TEMPERATURE: f64 = 100.0;

/// Share of the budget the experts of all objects get at most (the rest trains the network).
pub const EXPERTS_SHARE: f64 = 0.2;

/// Share of the budget the fit's probe times steps for, within [`PROBE_MIN_S`] and
/// [`PROBE_MAX_S`] seconds (after its first two steps), and at least [`PROBE_MIN_STEPS`] steps.
const PROBE_SHARE: f64 = 0.005;
const PROBE_MIN_S: f64 = 1.0;
const PROBE_MAX_S: f64 = 30.0;
const PROBE_MIN_STEPS: usize = 8;

/// Evaluation level of the held-out set.
pub const EVAL_LEVEL: u8 = 3;

/// Realistic crops per object of the training split the calibration stage fits its temperature
/// on, unless a job says otherwise ([`NewModel::calibration_images`]).
pub const CALIBRATION_IMAGES: usize = 100;

/// Added to the job's seed for the calibration crops: apart from the training renders' seeds and
/// the held-out set's (`seed + 2⁴⁰`).
const CALIBRATION_SEED: u64 = 3 << 40;

/// Seconds kept back for writing the bundle and the job's state.
const WRITE_RESERVE_S: f64 = 3.0;

/// Errors of a job; each says what to do.
#[derive(Debug, thiserror::Error)]
pub enum NewModelError {
    /// A mesh that cannot be used.
    #[error("{path}: {message}")]
    Mesh {
        /// The file.
        path: String,
        /// What is wrong.
        message: String,
    },
    /// Settings or a state that do not go together.
    #[error("{0}")]
    Invalid(String),
    /// The budget cannot pay for the smallest model.
    #[error(
        "a budget of {budget:.0} s is too small: {spent:.0} s went to probes and experts, and \
         {needed:.0} s more are needed for {min_steps} training steps and the evaluation \
         (measured: {step:.3} s per step, {eval:.3} s per test image)"
    )]
    BudgetTooSmall {
        /// The budget.
        budget: f64,
        /// Spent so far.
        spent: f64,
        /// Needed beyond that.
        needed: f64,
        /// The least steps trained.
        min_steps: usize,
        /// Seconds per step.
        step: f64,
        /// Seconds per test image.
        eval: f64,
    },
    /// A file of the job.
    #[error("{path}: {message}")]
    Io {
        /// The file.
        path: String,
        /// What went wrong.
        message: String,
    },
    /// Training the experts.
    #[error("experts of {object}: {source}")]
    Experts {
        /// The object.
        object: String,
        /// What went wrong.
        source: crate::experts::ExpertError,
    },
    /// Assembling the fit.
    #[error(transparent)]
    Fit(#[from] super::fit::FitError),
    /// Training the network.
    #[error(transparent)]
    Train(#[from] super::TrainError),
    /// Writing or reading a bundle.
    #[error(transparent)]
    Bundle(#[from] crate::bundle::BundleError),
    /// A grid level of the evaluation.
    #[error(transparent)]
    So3(#[from] crate::so3::So3Error),
}

/// What to make.
#[derive(Debug, Clone, PartialEq)]
pub struct NewModel {
    /// The parts' mesh files (one object each; names are the files' stems).
    pub meshes: Vec<PathBuf>,
    /// Their unit (`None`: guessed per part from its size).
    pub units: Option<LengthUnit>,
    /// The bundle folder to write.
    pub out: PathBuf,
    /// The whole job's wall-time budget, seconds.
    pub budget_seconds: f64,
    /// Held-out realistic test crops per object.
    pub eval_images: usize,
    /// Realistic crops per object of the training split that the calibration stage fits a
    /// temperature on ([`CALIBRATION_IMAGES`]; 0: no calibration, the network served as trained).
    pub calibration_images: usize,
    /// At most this many training steps (experiments and tests; `None`: what the budget buys).
    pub max_steps: Option<usize>,
    /// At most this many steps of each expert (experiments and tests).
    pub max_expert_steps: Option<usize>,
    /// Seed of the experts and the training data.
    pub seed: u64,
    /// A bundle whose network starts the fit (a warm start; it must have the recipe's encoding
    /// and head, and its layout or one that it grows), recorded with its checksum in the
    /// manifest.
    pub init: Option<PathBuf>,
    /// The schedule: [`RECIPE`] unless an experiment changes it.
    pub recipe: Recipe,
    /// The ImageNet weights an EfficientNet-Lite0 encoder starts from
    /// ([`TrainConfig::pretrained`]; needs that layout and no warm start).
    pub pretrained: Option<PathBuf>,
    /// The command line, for the manifests.
    pub command: String,
}

/// The job's state on disk (`<out>.job/job.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobState {
    /// The command that started the job.
    pub command: String,
    /// The meshes, in order.
    pub meshes: Vec<PathBuf>,
    /// The budget, seconds.
    pub budget_seconds: f64,
    /// Wall time spent by every run of the job so far, seconds.
    pub spent_seconds: f64,
    /// The plan, once probed.
    pub plan: Option<BudgetPlan>,
    /// `(stage, seconds)` of the stages finished.
    pub stages: Vec<(String, f64)>,
    /// `(stage, spent seconds when it began)` of the stage under way, so that a stage a kill
    /// interrupted is timed from its first start, not from the resume.
    #[serde(default)]
    pub running: Option<(String, f64)>,
    /// The schedule the job trains by (jobs from before it was recorded trained by the recipe
    /// of then, [`FIRST_RECIPE`]).
    #[serde(default = "first_recipe")]
    pub recipe: Recipe,
}

/// The recipe before jobs recorded theirs: `tiny` at 32 px, no twins, untempered.
pub const FIRST_RECIPE: Recipe = Recipe {
    layout: ResNetLayout::Tiny,
    image_size: 32,
    twin_share: 0.0,
    own_twins: 0,
    pool_grid: 1,
    target_temperature: None,
    ..RECIPE
};

fn first_recipe() -> Recipe {
    FIRST_RECIPE
}

/// The job's folder for the bundle `out`.
pub fn job_dir(out: &Path) -> PathBuf {
    let mut name = out.file_name().unwrap_or_default().to_os_string();
    name.push(".job");
    out.with_file_name(name)
}

/// The job's clock: what earlier runs spent plus this run's time.
struct Clock {
    before: f64,
    started: Instant,
    budget: f64,
}

impl Clock {
    fn spent(&self) -> f64 {
        self.before + self.started.elapsed().as_secs_f64()
    }

    fn left(&self) -> f64 {
        self.budget - self.spent()
    }
}

/// The job's state, saved atomically after every stage and now and then within one.
struct Job {
    dir: PathBuf,
    state: JobState,
    clock: Clock,
}

impl Job {
    fn save(&mut self) -> Result<(), NewModelError> {
        self.state.spent_seconds = self.clock.spent();
        let path = self.dir.join("job.json");
        let tmp = self.dir.join("job.json.tmp");
        let io = |e: std::io::Error| NewModelError::Io {
            path: path.display().to_string(),
            message: e.to_string(),
        };
        let json = serde_json::to_vec_pretty(&self.state).expect("the job state serialises");
        std::fs::write(&tmp, json).map_err(io)?;
        std::fs::rename(&tmp, &path).map_err(io)
    }

    /// Runs `stage`, recording its time: from when it began, in this run or in the run a kill
    /// interrupted (the job's clock counts neither the time between runs nor twice). A stage that
    /// finished before the kill, run again on the way back to the one the kill interrupted (its
    /// closure finds its work done), is neither timed again nor put on record as running in that
    /// stage's place.
    fn stage<T>(
        &mut self,
        name: &str,
        run: impl FnOnce(&mut Job) -> Result<T, NewModelError>,
    ) -> Result<T, NewModelError> {
        let finished = self.state.stages.iter().any(|(n, _)| n == name);
        if finished && matches!(&self.state.running, Some((n, _)) if n != name) {
            return run(self);
        }
        let started = match &self.state.running {
            Some((n, began)) if n == name => *began,
            _ => {
                let now = self.clock.spent();
                self.state.running = Some((name.to_string(), now));
                self.save()?;
                now
            }
        };
        let out = run(self)?;
        let seconds = self.clock.spent() - started;
        self.state.running = None;
        match self.state.stages.iter_mut().find(|(n, _)| n == name) {
            Some((_, s)) => *s += seconds,
            None => self.state.stages.push((name.to_string(), seconds)),
        }
        self.save()?;
        Ok(out)
    }

    fn say(&self, progress: &(dyn Fn(&str) + Sync), message: &str) {
        progress(&format!(
            "[{:6.0} s spent, {:6.0} s left] {message}",
            self.clock.spent(),
            self.clock.left().max(0.0)
        ));
    }
}

/// Opens the job folder: a new one, or with `resume` the one a killed run left (same meshes).
fn open_job(model: &NewModel, resume: bool) -> Result<Job, NewModelError> {
    let dir = job_dir(&model.out);
    let state_file = dir.join("job.json");
    let io = |path: &Path, e: std::io::Error| NewModelError::Io {
        path: path.display().to_string(),
        message: e.to_string(),
    };
    let state = if state_file.exists() {
        if !resume {
            return Err(NewModelError::Invalid(format!(
                "{} holds a job already: continue it with --resume, or remove the folder",
                dir.display()
            )));
        }
        let bytes = std::fs::read(&state_file).map_err(|e| io(&state_file, e))?;
        let state: JobState = serde_json::from_slice(&bytes).map_err(|e| NewModelError::Io {
            path: state_file.display().to_string(),
            message: e.to_string(),
        })?;
        if state.meshes != model.meshes {
            return Err(NewModelError::Invalid(format!(
                "{}: the job was started for other meshes ({:?}); give the same --mesh flags",
                state_file.display(),
                state.meshes
            )));
        }
        if state.recipe != model.recipe {
            return Err(NewModelError::Invalid(format!(
                "{}: the job was started with another recipe ({}); give the same --layout, \
                 --image-size, --batch, --k, --lr, --twin-share, --own-twins, --pool-grid and \
                 --target-temperature (a job recorded without pool_grid pooled globally: \
                 --pool-grid 1; one recorded without target_temperature was not tempered: \
                 --target-temperature 1)",
                state_file.display(),
                serde_json::to_string(&state.recipe).unwrap_or_default()
            )));
        }
        state
    } else {
        std::fs::create_dir_all(&dir).map_err(|e| io(&dir, e))?;
        JobState {
            command: model.command.clone(),
            meshes: model.meshes.clone(),
            budget_seconds: model.budget_seconds,
            spent_seconds: 0.0,
            plan: None,
            stages: Vec::new(),
            running: None,
            recipe: model.recipe,
        }
    };
    let clock = Clock {
        before: state.spent_seconds,
        started: Instant::now(),
        budget: state.budget_seconds,
    };
    Ok(Job { dir, state, clock })
}

/// A part: its name, its mesh in NOCS and the normalisation.
type Part = (String, Mesh, Normalisation);

/// Reads every part, checks that each is closed and that names differ.
fn load_parts(model: &NewModel) -> Result<Vec<Part>, NewModelError> {
    let mut parts: Vec<Part> = Vec::new();
    for path in &model.meshes {
        let err = |message: String| NewModelError::Mesh {
            path: path.display().to_string(),
            message,
        };
        let (name, mesh, n) =
            crate::cad::load_part(path, model.units).map_err(|e| err(e.to_string()))?;
        crate::cad::SignedDistance::new(&mesh)
            .map_err(|e| err(format!("the SDF expert needs a closed mesh: {e}")))?;
        if parts.iter().any(|(other, _, _)| *other == name) {
            return Err(err(format!(
                "two meshes are named '{name}' (the file's stem names the object); rename one"
            )));
        }
        parts.push((name, mesh, n));
    }
    if parts.is_empty() {
        return Err(NewModelError::Invalid("give at least one --mesh".into()));
    }
    Ok(parts)
}

/// The expert job of `part` with `sdf_steps` and `feature_steps`; no symmetry declared (the
/// experts discover it).
fn experts_job(
    part: &Part,
    sdf_steps: usize,
    feature_steps: usize,
    seed: u64,
    command: &str,
) -> ExpertsJob {
    let (name, mesh, normalisation) = part;
    ExpertsJob {
        name: name.clone(),
        mesh: mesh.clone(),
        normalisation: *normalisation,
        symmetries: vec![nalgebra::Rotation3::identity()],
        sdf: SdfTrainConfig {
            steps: sdf_steps,
            seed,
            ..SdfTrainConfig::default()
        },
        features: FeatureTrainConfig {
            steps: feature_steps,
            seed,
            ..FeatureTrainConfig::default()
        },
        bake_resolution: DEFAULT_BAKE_RESOLUTION,
        energy: EnergyParams::default(),
        width: WidthCriterion {
            seed,
            ..WidthCriterion::default()
        },
        modes: ModeTableConfig {
            seed,
            ..ModeTableConfig::default()
        },
        command: command.to_string(),
    }
}

/// Times a few steps of each expert on the first part, and sizes the experts to
/// [`EXPERTS_SHARE`] of the budget (at most their default steps, at least 20 SDF and 10 feature
/// steps).
fn plan_experts(
    job: &Job,
    parts: &[Part],
    seed: u64,
    max_expert_steps: Option<usize>,
) -> Result<BudgetPlan, NewModelError> {
    use crate::experts::feature::train_features;
    use crate::experts::sdf::train_sdf;
    let mesh = &parts[0].1;
    let expert_err = |source| NewModelError::Experts {
        object: parts[0].0.clone(),
        source,
    };
    const PROBE_SDF: usize = 10;
    const PROBE_FEATURES: usize = 4;
    let t = Instant::now();
    train_sdf(
        mesh,
        &SdfTrainConfig {
            steps: PROBE_SDF,
            seed,
            ..SdfTrainConfig::default()
        },
        |_, _| {},
    )
    .map_err(expert_err)?;
    let sdf_step = t.elapsed().as_secs_f64() / PROBE_SDF as f64;
    let t = Instant::now();
    train_features(
        mesh,
        &[nalgebra::Rotation3::identity()],
        &FeatureTrainConfig {
            steps: PROBE_FEATURES,
            seed,
            ..FeatureTrainConfig::default()
        },
        |_, _| {},
    )
    .map_err(expert_err)?;
    let feature_step = t.elapsed().as_secs_f64() / PROBE_FEATURES as f64;
    let (sdf_default, feat_default) = (
        SdfTrainConfig::default().steps,
        FeatureTrainConfig::default().steps,
    );
    // Objects train side by side, one per core; the bake, λ selection, mode table and symmetry
    // take about a tenth of the share.
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get()) as f64;
    let rounds = (parts.len() as f64 / cores).ceil().max(1.0);
    let per_object = 0.9 * EXPERTS_SHARE * job.clock.budget / rounds;
    let full = sdf_default as f64 * sdf_step + feat_default as f64 * feature_step;
    let scale = (per_object / full).min(1.0);
    let cap = |steps: usize| max_expert_steps.map_or(steps, |m| steps.min(m.max(1)));
    Ok(BudgetPlan {
        sdf_steps: cap(((sdf_default as f64 * scale) as usize).max(20)),
        feature_steps: cap(((feat_default as f64 * scale) as usize).max(10)),
        probe_sdf_step: sdf_step,
        probe_feature_step: feature_step,
        fit_steps: 0,
        first_fit_steps: 0,
        replans: 0,
        probe_fit_step: 0.0,
        probe_eval_image: 0.0,
        eval_images: 0,
    })
}

/// Trains the experts of every part not yet written to `<job>/experts/<name>`, side by side.
fn train_experts(
    job: &Job,
    parts: &[Part],
    plan: &BudgetPlan,
    model: &NewModel,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<Vec<PathBuf>, NewModelError> {
    use rayon::prelude::*;
    let dirs: Vec<PathBuf> = parts
        .iter()
        .map(|(name, _, _)| job.dir.join("experts").join(name))
        .collect();
    let job_say = Mutex::new(());
    let say = |m: &str| {
        let _guard = job_say.lock();
        job.say(progress, m);
    };
    parts
        .par_iter()
        .zip(&dirs)
        .filter(|(_, dir)| !dir.join("manifest.json").exists())
        .try_for_each(|(part, dir)| {
            let name = &part.0;
            say(&format!(
                "experts of {name}: {} SDF and {} feature steps",
                plan.sdf_steps, plan.feature_steps
            ));
            let mut last = Instant::now();
            let mut set = train_expert_set(
                experts_job(
                    part,
                    plan.sdf_steps,
                    plan.feature_steps,
                    model.seed,
                    &model.command,
                ),
                &mut |phase, step, steps, loss| {
                    if last.elapsed().as_secs_f64() >= 30.0 {
                        last = Instant::now();
                        say(&format!(
                            "experts of {name}: {phase} {step}/{steps} (loss {loss:.4})"
                        ));
                    }
                },
            )
            .map_err(|source| NewModelError::Experts {
                object: name.clone(),
                source,
            })?;
            set.save(dir).map_err(|e| NewModelError::Io {
                path: dir.display().to_string(),
                message: e.to_string(),
            })?;
            if let Some(s) = &set.manifest.symmetry {
                say(&format!(
                    "experts of {name} written; symmetry {} (confidence {:.2}){}",
                    s.label,
                    s.confidence,
                    s.near
                        .as_ref()
                        .map_or_else(String::new, |n| format!(", nearly {}", n.label))
                ));
            }
            Ok::<(), NewModelError>(())
        })?;
    Ok(dirs)
}

impl NewModel {
    /// The training configuration of this job's recipe for `steps`, its encoder started from
    /// the pretrained weights where the job has them.
    fn train_config(&self, steps: usize, seed: u64) -> Result<TrainConfig, NewModelError> {
        let file = |p: &PathBuf| {
            crate::bundle::sha256_file(p).map_err(|e| {
                NewModelError::Invalid(format!("the pretrained weights {}: {e}", p.display()))
            })
        };
        Ok(TrainConfig {
            pretrained: self.pretrained.as_ref().map(|p| p.display().to_string()),
            pretrained_file: self.pretrained.as_ref().map(file).transpose()?,
            ..self.recipe.config(steps, seed)
        })
    }
}

impl Recipe {
    /// The network and training configuration of this recipe for `steps`.
    pub fn config(&self, steps: usize, seed: u64) -> TrainConfig {
        let network = NetworkConfig::new(self.layout, RotationEncoding::Cube)
            .with_image_size(self.image_size)
            .pooled_over(self.pool_grid);
        TrainConfig {
            network,
            method: Method::Alignist {
                loss: MeasureLoss::Gkl,
                sampling: SamplingStrategy::annealed_share(
                    self.k,
                    self.focused_start,
                    self.focused_end,
                )
                .with_twin_share(self.twin_share)
                .with_own_twins((self.own_twins > 0).then_some(super::sampling::OwnTwins {
                    crops: self.own_twins,
                    every: OWN_TWINS_EVERY,
                })),
                experts: ExpertBranches::Both,
            },
            steps,
            batch: self.batch,
            k: self.k,
            lr: self.lr,
            warmup: super::config::warmup_steps(steps),
            seed,
            checkpoint_every: 50,
            init: None,
            teacher: None,
            plain_start: self.plain_start,
            pretrained: None,
            pretrained_file: None,
            encoder_lr_scale: self.encoder_lr_scale,
            contrast: self.contrast,
            target_temperature: self.target_temperature,
        }
    }
}

/// Makes the model: every stage not done yet, then the bundle. `progress` gets a line now and
/// then, with the time spent and left.
pub fn new_model(
    model: &NewModel,
    resume: bool,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<ModelManifest, NewModelError> {
    if !(model.budget_seconds.is_finite() && model.budget_seconds > 0.0) {
        return Err(NewModelError::Invalid(format!(
            "the budget must be a positive time, got {} s",
            model.budget_seconds
        )));
    }
    let lite = model.recipe.layout.is_efficientnet();
    if lite != model.pretrained.is_some() || (lite && model.init.is_some()) {
        return Err(NewModelError::Invalid(format!(
            "pretrained weights go with the efficientnet-lite0 layout and no warm start, and that \
             layout with them (layout {:?}, pretrained {:?}, warm start {:?})",
            model.recipe.layout, model.pretrained, model.init
        )));
    }
    if let Some(path) = &model.pretrained {
        // Read once here, so that a wrong file is refused before any work.
        let device = crate::backend::device_for(crate::backend::Workload::Conv);
        crate::net::EfficientNetLite0::pretrained(path, &device)
            .map_err(|e| NewModelError::Invalid(e.to_string()))?;
    }
    let parts = load_parts(model)?;
    // A warm start that does not fit the recipe is refused before any work.
    let init = match &model.init {
        Some(dir) => Some(super::fit::init_weights(
            dir,
            &model.recipe.config(1, 0).network,
        )?),
        None => None,
    };
    let mut job = open_job(model, resume)?;
    job.say(
        progress,
        &format!(
            "{} part(s): {}",
            parts.len(),
            parts
                .iter()
                .map(|(n, _, norm)| format!("{n} (radius {:.4} {})", norm.scale, norm.units))
                .collect::<Vec<_>>()
                .join(", ")
        ),
    );
    let plan = match job.state.plan.clone() {
        Some(plan) => plan,
        None => {
            let plan = job.stage("probe", |job| {
                plan_experts(job, &parts, model.seed, model.max_expert_steps)
            })?;
            job.state.plan = Some(plan.clone());
            job.save()?;
            plan
        }
    };
    let dirs = job.stage("experts", |job| {
        train_experts(job, &parts, &plan, model, progress)
    })?;
    fit_and_write(&mut job, model, plan, &dirs, init, resume, progress)
}

/// The fit stage (probed and sized first), the evaluation and the bundle.
fn fit_and_write(
    job: &mut Job,
    model: &NewModel,
    mut plan: BudgetPlan,
    dirs: &[PathBuf],
    init: Option<InitWeights>,
    resume: bool,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<ModelManifest, NewModelError> {
    let inputs = FitInputs {
        experts: dirs.to_vec(),
        source: FitSource::Fresh {
            realistic: true,
            supersample: model.recipe.supersample,
            eval_seed: model.seed ^ (7 << 40),
        },
        image_size: model.recipe.image_size,
        fraction: 1.0,
        eval_images: 0,
    };
    let mut data = FitData::load(&inputs, 1, model.recipe.batch)?;
    let [tests, calibration] = [
        (model.eval_images, super::data::EVAL_SEED, Realism::HELD_OUT),
        (model.calibration_images, CALIBRATION_SEED, Realism::TRAIN),
    ]
    .map(|(per_object, seed, realism)| realistic_crops(&data, model, per_object, seed, realism));
    let training = data.training_set()?;
    // The images scored after the fit: the calibration's and the evaluation's.
    let scored = tests.len() + calibration.len();
    if plan.fit_steps == 0 {
        plan = job.stage("probe", |job| {
            size_fit(job, plan.clone(), model, &training, (&tests, scored))
        })?;
        job.state.plan = Some(plan.clone());
        job.save()?;
    }
    let mut config = TrainConfig {
        init,
        ..model.train_config(plan.fit_steps, model.seed)?
    };
    if plan.first_fit_steps > 0 {
        config.warmup = super::config::warmup_steps(plan.first_fit_steps);
    }
    job.say(progress, &fit_line(&plan, &model.recipe, &config));
    let reserve = plan.probe_eval_image * scored as f64 * 1.2 + WRITE_RESERVE_S;
    let (network, report) = run_fit(
        job,
        &config,
        &training,
        (reserve, model.max_steps),
        resume,
        progress,
    )?;
    say_own_twins(job, &report, progress);
    // The schedule the fit ended with (re-planned to its pace).
    let plan = job.state.plan.clone().unwrap_or(plan);
    config.steps = plan.fit_steps;
    let (network, calibration) =
        calibrate_stage(job, network, &config, &calibration, model, progress)?;
    let evaluation = evaluate_stage(job, &network, &config, &tests, progress)?;
    let name = model
        .out
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or("model")
        .to_string();
    let mut manifest = fitted_manifest(
        name,
        data.objects,
        model.command.clone(),
        config,
        report,
        evaluation,
    );
    manifest.calibration = calibration;
    manifest.budget = Some(BudgetRecord {
        budget_seconds: job.clock.budget,
        spent_seconds: job.clock.spent(),
        plan,
        stages: job.state.stages.clone(),
    });
    let dir_refs: Vec<&Path> = dirs.iter().map(PathBuf::as_path).collect();
    ModelBundle::save(&mut manifest, &network, &dir_refs, &model.out)?;
    job.save()?;
    job.say(
        progress,
        &format!("bundle written to {}", model.out.display()),
    );
    Ok(manifest)
}

/// `per_object` realistic crops of every part at the recipe's size, drawn with the job's seed plus
/// `seed` from the ranges of `realism`.
fn realistic_crops(
    data: &FitData,
    model: &NewModel,
    per_object: usize,
    seed: u64,
    realism: Realism,
) -> Vec<super::eval::EvalImage> {
    let names: Vec<String> = data
        .sets
        .iter()
        .map(|s| s.manifest.object.name.clone())
        .collect();
    let symmetries: Vec<_> = data.sets.iter().map(ExpertSet::symmetries).collect();
    data.fresh
        .as_ref()
        .expect("fresh renders")
        .realistic_eval_images(
            &names,
            &symmetries,
            model.recipe.image_size,
            per_object,
            model.seed.wrapping_add(seed),
            realism,
        )
}

/// The progress line that opens the fit: its schedule, its probe's pace and its warm start.
fn fit_line(plan: &BudgetPlan, recipe: &Recipe, config: &TrainConfig) -> String {
    format!(
        "fit: {} steps of batch {} × K {} ({:.3} s per step in the probe), focused share {} → {}{}{}{}{}{}{}",
        plan.fit_steps,
        recipe.batch,
        recipe.k,
        plan.probe_fit_step,
        recipe.focused_start,
        recipe.focused_end,
        if recipe.twin_share > 0.0 {
            format!(
                " ({} of it around {}twins)",
                recipe.twin_share,
                if recipe.own_twins > 0 {
                    format!(
                        "near-symmetry and own (searched on {} crops a part every {} steps) ",
                        recipe.own_twins, OWN_TWINS_EVERY
                    )
                } else {
                    "near-symmetry ".into()
                }
            )
        } else {
            String::new()
        },
        recipe.plain_start.map_or(String::new(), |p| format!(
            ", plain crops {p} → {}",
            Realism::TRAIN.plain
        )),
        recipe.encoder_lr_scale.map_or(String::new(), |s| format!(
            ", the encoder at {s} × the head's learning rate"
        )),
        recipe.contrast.map_or(String::new(), |w| format!(
            ", a contrast term of weight {w}"
        )),
        recipe.target_temperature.map_or(String::new(), |t| format!(
            ", the targets tempered from T {t} to 1"
        )),
        config
            .init
            .as_ref()
            .map_or(String::new(), |i| format!(", warm start from {}", i.path))
    )
}

/// The calibration stage: the temperature that maximises the LL of `crops` (realistic, the
/// training split) at [`EVAL_LEVEL`], folded into the network's output layers; the network as it
/// is when there are no crops.
fn calibrate_stage(
    job: &mut Job,
    network: crate::net::Network,
    config: &TrainConfig,
    crops: &[super::eval::EvalImage],
    model: &NewModel,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<
    (
        crate::net::Network,
        Option<super::calibrate::TemperatureFit>,
    ),
    NewModelError,
> {
    if crops.is_empty() {
        return Ok((network, None));
    }
    job.stage("calibration", |job| {
        job.say(
            progress,
            &format!(
                "calibrating a temperature on {} realistic crops of the training split",
                crops.len()
            ),
        );
        let fit = super::calibrate::fit_temperature(
            &network,
            &config.network,
            crops,
            EVAL_LEVEL,
            false,
            format!(
                "{} realistic crops per object of the training split (seed {}, {}x supersampled)",
                model.calibration_images,
                model.seed.wrapping_add(CALIBRATION_SEED),
                model.recipe.supersample
            ),
            model.command.clone(),
        )?;
        job.say(
            progress,
            &format!(
                "calibration: temperature {:.3}, LL of its crops {:.3} → {:.3}",
                1.0 / fit.scale,
                fit.ll_before,
                fit.ll_after
            ),
        );
        let [shape, feature] = fit.applied();
        let network = crate::net::Network {
            head: network
                .head
                .with_branch_output_scales(shape as f32, feature as f32),
            ..network
        };
        Ok((network, Some(fit)))
    })
}

/// The evaluation stage: the network on the held-out realistic crops at [`EVAL_LEVEL`].
fn evaluate_stage(
    job: &mut Job,
    network: &crate::net::Network,
    config: &TrainConfig,
    tests: &[super::eval::EvalImage],
    progress: &(dyn Fn(&str) + Sync),
) -> Result<Option<EvalReport>, NewModelError> {
    job.stage("evaluation", |job| {
        job.say(
            progress,
            &format!("evaluating on {} held-out realistic crops", tests.len()),
        );
        if tests.is_empty() {
            return Ok(None);
        }
        Ok(Some(super::eval::evaluate(
            network,
            &config.network,
            tests,
            EVAL_LEVEL,
            |_| {},
        )?))
    })
}

/// How far back the fit's pace is measured for a re-plan, seconds.
const PACE_WINDOW_S: f64 = 300.0;
/// The least time a pace is measured over before the schedule is re-planned from it, seconds.
const PACE_MIN_S: f64 = 30.0;

/// The fit's recent pace: (step, seconds) marks, one a checkpoint, of the last [`PACE_WINDOW_S`].
#[derive(Debug, Default)]
struct Pace {
    marks: std::collections::VecDeque<(usize, f64)>,
}

impl Pace {
    /// Marks `step` done at `now` seconds; the seconds a step took over the window, once it spans
    /// [`PACE_MIN_S`].
    fn mark(&mut self, step: usize, now: f64) -> Option<f64> {
        self.marks.push_back((step, now));
        while self.marks.len() > 2 && self.marks[1].1 <= now - PACE_WINDOW_S {
            self.marks.pop_front();
        }
        let (first_step, first) = *self.marks.front()?;
        (now - first >= PACE_MIN_S && step > first_step)
            .then(|| (now - first) / (step - first_step) as f64)
    }
}

/// The fit's schedule re-sized to the time it has: `step` of `steps` done, a step taking
/// `per_step` seconds lately, `available` seconds left before the evaluation's reserve, at most
/// `max_steps`. `None` while the schedule ends within 1 % of its steps of that.
///
/// The probe's pace does not hold for a whole job: the machine's other load changes it (the
/// 60-minute drill run slowed from 0.091 to 0.109 s a step in its last quarter and was stopped
/// at 89 % of its schedule, its learning rate and focused share short of their ends).
fn replanned_steps(
    step: usize,
    steps: usize,
    per_step: f64,
    available: f64,
    max_steps: Option<usize>,
) -> Option<usize> {
    if !(per_step > 0.0 && available.is_finite()) {
        return None;
    }
    let fits = step + (available.max(0.0) / per_step).floor() as usize;
    let target = max_steps.map_or(fits, |m| fits.min(m)).max(step + 1);
    (target.abs_diff(steps) > (steps / 100).max(1)).then_some(target)
}

/// The line after a fit that searched the network's own twins: how often, how long, and the
/// half-turn misses per part at its first and last search.
fn say_own_twins(job: &Job, report: &TrainReport, progress: &(dyn Fn(&str) + Sync)) {
    if let (Some(first), Some(last)) = (report.own_twins.first(), report.own_twins.last()) {
        let seconds: f64 = report.own_twins.iter().map(|f| f.seconds).sum();
        job.say(
            progress,
            &format!(
                "fit: own twins searched {} times ({:.1} s in all); half-turn misses per part at \
                 step {}: {:?}, at step {}: {:?}",
                report.own_twins.len(),
                seconds,
                first.step,
                first.misses,
                last.step,
                last.misses
            ),
        );
    }
}

/// The fit stage: `config`'s schedule with checkpoints in the job's folder, progress every 30 s,
/// re-planned at checkpoints to the pace measured (at most `max_steps`), and stopped early when
/// less than `reserve` seconds of the budget are left.
fn run_fit(
    job: &mut Job,
    config: &TrainConfig,
    training: &super::TrainingSet,
    (reserve, max_steps): (f64, Option<usize>),
    resume: bool,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<(crate::net::Network, TrainReport), NewModelError> {
    let checkpoints = job.dir.join("checkpoints");
    std::fs::create_dir_all(&checkpoints).map_err(|e| NewModelError::Io {
        path: checkpoints.display().to_string(),
        message: e.to_string(),
    })?;
    job.stage("fit", |job| {
        let mut last = Instant::now();
        let started = Instant::now();
        let mut pace = Pace::default();
        let out = super::train_replanned(
            config,
            training,
            Some(&checkpoints),
            resume,
            |step, steps, loss| {
                if last.elapsed().as_secs_f64() >= 30.0 || step == steps {
                    last = Instant::now();
                    job.say(
                        progress,
                        &format!("fit: step {step}/{steps}, loss {loss:.4}"),
                    );
                    let _ = job.save();
                }
                if job.clock.left() < reserve {
                    job.say(
                        progress,
                        &format!("fit: stopped at step {step} to keep the budget"),
                    );
                    return std::ops::ControlFlow::Break(());
                }
                // Paced and re-planned only where a checkpoint was just written, so that a resume
                // from it continues the same schedule.
                if step % config.checkpoint_every.max(1) != 0 {
                    return std::ops::ControlFlow::Continue(None);
                }
                // The job's clock on record with every checkpoint: a kill loses the time of the
                // steps after the last one, which the resume does again, and no more.
                let _ = job.save();
                let per_step = pace.mark(step, started.elapsed().as_secs_f64());
                let replanned = per_step.and_then(|per_step| {
                    let available = job.clock.left() - reserve;
                    replanned_steps(step, steps, per_step, available, max_steps)
                        .map(|to| (to, per_step))
                });
                let Some((to, per_step)) = replanned else {
                    return std::ops::ControlFlow::Continue(None);
                };
                if let Some(plan) = job.state.plan.as_mut() {
                    plan.fit_steps = to;
                    plan.replans += 1;
                }
                let _ = job.save();
                job.say(
                    progress,
                    &format!(
                        "fit: re-planned at step {step} from {steps} to {to} steps ({per_step:.3} s \
                         a step lately)"
                    ),
                );
                std::ops::ControlFlow::Continue(Some(to))
            },
        )?;
        Ok(out)
    })
}

/// Times a few training steps and test images, and sizes the schedule to the time left.
fn size_fit(
    job: &Job,
    mut plan: BudgetPlan,
    model: &NewModel,
    training: &super::TrainingSet,
    (tests, scored): (&[super::eval::EvalImage], usize),
) -> Result<BudgetPlan, NewModelError> {
    // The probe runs steps until its window has passed after the second (the first ones start
    // threads and the prefetch; at 64 px the next few were measured still slower: 8 steps
    // predicted 0.242 s a step where the fit then ran at 0.16), up to `PROBE_MAX_STEPS`.
    const PROBE_MAX_STEPS: usize = 400;
    const MIN_STEPS: usize = 20;
    let window = (PROBE_SHARE * job.clock.budget).clamp(PROBE_MIN_S, PROBE_MAX_S);
    let probe = model.train_config(PROBE_MAX_STEPS, model.seed ^ 0x9b0b)?;
    let t = Instant::now();
    let mut after_two = None;
    let mut last = (0, 0.0);
    let (network, _) = super::train(&probe, training, None, false, |step, _, _| {
        let now = t.elapsed().as_secs_f64();
        last = (step, now);
        match after_two {
            None if step >= 2 => after_two = Some(now),
            Some(two) if now - two >= window && step >= PROBE_MIN_STEPS => {
                return std::ops::ControlFlow::Break(());
            }
            _ => {}
        }
        std::ops::ControlFlow::Continue(())
    })?;
    let start_up = after_two.unwrap_or(0.0);
    plan.probe_fit_step = (last.1 - start_up) / last.0.saturating_sub(2).max(1) as f64;
    let start_up = (start_up - 2.0 * plan.probe_fit_step).max(0.0);
    let few = &tests[..tests.len().min(4)];
    let t = Instant::now();
    if !few.is_empty() {
        super::eval::evaluate(&network, &probe.network, few, EVAL_LEVEL, |_| {})?;
    }
    plan.probe_eval_image = t.elapsed().as_secs_f64() / few.len().max(1) as f64;
    plan.eval_images = model.eval_images;
    let reserve = plan.probe_eval_image * scored as f64 * 1.2 + 2.0 * WRITE_RESERVE_S + start_up;
    let for_steps = job.clock.left() - reserve;
    let steps = (for_steps / plan.probe_fit_step).floor().max(0.0) as usize;
    if steps < MIN_STEPS {
        return Err(NewModelError::BudgetTooSmall {
            budget: job.clock.budget,
            spent: job.clock.spent(),
            needed: MIN_STEPS as f64 * plan.probe_fit_step + reserve,
            min_steps: MIN_STEPS,
            step: plan.probe_fit_step,
            eval: plan.probe_eval_image,
        });
    }
    plan.fit_steps = model.max_steps.map_or(steps, |m| steps.min(m));
    plan.first_fit_steps = plan.fit_steps;
    Ok(plan)
}

#[cfg(test)]
mod tests {
    use super::{
        Clock, FIRST_RECIPE, Job, JobState, PACE_MIN_S, PACE_WINDOW_S, Pace, replanned_steps,
    };

    #[test]
    fn a_stage_a_kill_interrupted_is_timed_from_its_first_start() {
        let dir = tempfile::tempdir().unwrap();
        // A job killed 60 s into its fit, which began when the job had spent 40 s.
        let state = JobState {
            command: String::new(),
            meshes: Vec::new(),
            budget_seconds: 1_000.0,
            spent_seconds: 100.0,
            plan: None,
            stages: vec![("experts".into(), 35.0)],
            running: Some(("fit".into(), 40.0)),
            recipe: FIRST_RECIPE,
        };
        let clock = Clock {
            before: state.spent_seconds,
            started: std::time::Instant::now(),
            budget: state.budget_seconds,
        };
        let mut job = Job {
            dir: dir.path().to_path_buf(),
            state,
            clock,
        };
        // The experts, finished before the kill, are passed through: not timed again, and the
        // fit stays on record as the stage under way.
        job.stage("experts", |job| {
            assert_eq!(job.state.running, Some(("fit".into(), 40.0)));
            Ok(())
        })
        .unwrap();
        assert_eq!(job.state.stages, vec![("experts".into(), 35.0)]);
        job.stage("fit", |_| Ok(())).unwrap();
        let fit = job.state.stages[1].1;
        assert!((60.0..61.0).contains(&fit), "{fit}");
        assert_eq!(job.state.running, None);
        // A stage that begins in this run is timed from now; while it runs it is on record.
        job.stage("evaluation", |job| {
            let (name, began) = job.state.running.clone().unwrap();
            assert_eq!(name, "evaluation");
            assert!((100.0..101.0).contains(&began), "{began}");
            let saved: JobState =
                serde_json::from_slice(&std::fs::read(dir.path().join("job.json")).unwrap())
                    .unwrap();
            assert_eq!(saved.running, job.state.running);
            Ok(())
        })
        .unwrap();
        assert!(job.state.stages[2].1 < 1.0);
        assert_eq!(job.state.running, None);
    }

    #[test]
    fn a_slower_pace_shortens_the_schedule_and_a_faster_one_lengthens_it() {
        // 1 000 of 10 000 steps done, 900 s left: at 0.1 s a step 9 000 more fit exactly.
        assert_eq!(replanned_steps(1_000, 10_000, 0.1, 900.0, None), None);
        // Within 1 % of the schedule: left alone.
        assert_eq!(replanned_steps(1_000, 10_000, 0.1, 909.0, None), None);
        // 10 % slower: the schedule ends where the time does.
        assert_eq!(
            replanned_steps(1_000, 10_000, 0.11, 900.0, None),
            Some(9_181)
        );
        // Faster: longer, but never past --max-steps.
        assert_eq!(
            replanned_steps(1_000, 10_000, 0.05, 900.0, None),
            Some(19_000)
        );
        assert_eq!(
            replanned_steps(1_000, 10_000, 0.05, 900.0, Some(12_000)),
            Some(12_000)
        );
        assert_eq!(
            replanned_steps(1_000, 10_000, 0.05, 900.0, Some(10_000)),
            None
        );
        // No time left: one more step (the budget's stop rule ends the run).
        assert_eq!(replanned_steps(1_000, 10_000, 0.1, -5.0, None), Some(1_001));
        // No pace measured: nothing to re-plan from.
        assert_eq!(replanned_steps(1_000, 10_000, 0.0, 900.0, None), None);
        assert_eq!(replanned_steps(1_000, 10_000, f64::NAN, 900.0, None), None);
    }

    #[test]
    fn the_pace_is_measured_over_the_recent_window() {
        let mut pace = Pace::default();
        // Not before it spans PACE_MIN_S.
        assert_eq!(pace.mark(1, 0.0), None);
        assert_eq!(pace.mark(100, 0.5 * PACE_MIN_S), None);
        // 0.1 s a step for the first window, then 0.2 s a step: the window forgets the first.
        let mut pace = Pace::default();
        let mut t = 0.0;
        let mut step = 1;
        while t < PACE_WINDOW_S {
            t += 0.1;
            step += 1;
            pace.mark(step, t);
        }
        let first = pace.mark(step + 1, t + 0.1).unwrap();
        assert!((first - 0.1).abs() < 1e-3, "{first}");
        let (t0, s0) = (t + 0.1, step + 1);
        let mut last = 0.0;
        for i in 1..=(2.0 * PACE_WINDOW_S / 0.2) as usize {
            last = pace.mark(s0 + i, t0 + 0.2 * i as f64).unwrap();
        }
        assert!((last - 0.2).abs() < 1e-3, "{last}");
    }
}
