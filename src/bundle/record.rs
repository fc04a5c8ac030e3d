//! Every record a bundle's files hold (docs/DESIGN.md §4): the model manifest and what it embeds —
//! the training configuration and report, the evaluation report, the checksums of the files.
//! Plain serde data, below everything that reads or writes it (`bundle`, `train`, `engine`,
//! `serve`); the behaviour on these types lives with its users.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

use crate::net::NetworkConfig;
use crate::so3::metrics::MetricsSummary;

/// Checksum and size of one file of a bundle.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileEntry {
    /// Lower-case hex sha256.
    pub sha256: String,
    /// Size in bytes.
    pub bytes: u64,
}

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
    /// Input normalisation: crops are RGB scaled to `[0, 1]`, object-centred (docs/DESIGN.md §2).
    pub input: String,
    /// Objects, in the order the bundle was trained on them.
    pub objects: Vec<BundleObject>,
    /// A cap on the levels the server serves this bundle at, set by whoever ships it (the
    /// trainer sets none: the server's own settings decide, docs/DESIGN.md §4).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub levels: Option<GridLevels>,
    /// Training provenance.
    pub provenance: Provenance,
    /// Evaluation on held-out images, when it was run.
    pub evaluation: Option<EvalReport>,
    /// The temperature folded into the network's output layers, when it was calibrated
    /// (`alignist-train calibrate`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<TemperatureFit>,
    /// How `alignist-train new` spent its time budget (bundles made otherwise have none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub budget: Option<BudgetRecord>,
    /// Checksums of every file except the manifest, relative to the bundle.
    pub files: BTreeMap<String, FileEntry>,
}

/// The input convention every bundle records (`ModelManifest::input`).
pub const INPUT_CONVENTION: &str = "RGB crop as a virtual camera looking at the centre of the \
    object's box sees it: a square of 1.2 × the box's longer side (never stretched), side \
    image_size, values / 255 (src/data/virtual_crop.rs)";

impl ModelManifest {
    /// The manifest of a bundle trained now (no files yet: [`crate::bundle::model::ModelBundle::save`] adds them), with
    /// the [`INPUT_CONVENTION`].
    pub fn new(
        name: String,
        network: NetworkConfig,
        objects: Vec<BundleObject>,
        provenance: Provenance,
        evaluation: Option<EvalReport>,
    ) -> ModelManifest {
        ModelManifest {
            format_version: MODEL_FORMAT_VERSION,
            name,
            network,
            input: INPUT_CONVENTION.into(),
            objects,
            levels: None,
            provenance,
            evaluation: evaluation.map(EvalReport::summary),
            calibration: None,
            budget: None,
            files: Default::default(),
        }
    }
}

/// How a model made by `alignist-train new` spent its budget: the plan its probes sized, and the
/// wall time of every stage (across resumes).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BudgetRecord {
    /// The budget, seconds.
    pub budget_seconds: f64,
    /// Wall time of the whole job when the bundle was written, seconds.
    pub spent_seconds: f64,
    /// The plan.
    pub plan: BudgetPlan,
    /// `(stage, seconds)` in order: probes, experts, fit, evaluation.
    pub stages: Vec<(String, f64)>,
}

/// The steps a budget buys, from timed probes on the machine that runs the job.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BudgetPlan {
    /// Adam steps of each object's SDF expert.
    pub sdf_steps: usize,
    /// Adam steps of each object's feature expert.
    pub feature_steps: usize,
    /// Seconds per SDF / feature expert step in the probe.
    pub probe_sdf_step: f64,
    /// Seconds per feature expert step in the probe.
    pub probe_feature_step: f64,
    /// Steps of the network's one schedule (0 until the experts are trained and the fit probed);
    /// as the fit re-plans it to the pace it measures, the schedule it ended with.
    pub fit_steps: usize,
    /// The steps the probe first planned, and the schedule's warm-up from them (kept through
    /// re-plans; 0 in a job written before re-planning).
    #[serde(default)]
    pub first_fit_steps: usize,
    /// Times the fit re-planned its schedule to its measured pace.
    #[serde(default)]
    pub replans: usize,
    /// Seconds per training step in the probe.
    pub probe_fit_step: f64,
    /// Seconds per evaluation image in the probe.
    pub probe_eval_image: f64,
    /// Held-out realistic test crops per object.
    pub eval_images: usize,
}

/// A temperature calibration: the combined log-density of the network was multiplied by `scale`
/// (`1 / T`, folded into both branches' output layers), the scale that maximised the LL of
/// calibration crops from the training distribution (`train::calibrate`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TemperatureFit {
    /// The factor applied to the combined log-density (`1 / T`); with `branch_scales`, the best
    /// single factor, for comparison (not applied).
    pub scale: f64,
    /// The factors applied to the shape and the feature branch each, when each branch got its
    /// own (`calibrate --per-branch`): a product of the two experts at their own temperatures.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub branch_scales: Option<[f64; 2]>,
    /// Mean LL of the calibration crops before (scale 1).
    pub ll_before: f64,
    /// Mean LL of the calibration crops at the factors applied.
    pub ll_after: f64,
    /// Calibration crops.
    pub images: usize,
    /// Grid level of the LL.
    pub level: u8,
    /// What the crops were, in words (their split and seed).
    pub crops: String,
    /// The command that calibrated the bundle.
    pub command: String,
}

impl TemperatureFit {
    /// The factors applied to the shape and the feature branch: `branch_scales` when recorded,
    /// else `scale` on both.
    pub fn applied(&self) -> [f64; 2] {
        self.branch_scales.unwrap_or([self.scale; 2])
    }
}

/// A cap on a bundle's grid levels: the server serves it up to these at most
/// (`EngineConfig::within`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct GridLevels {
    /// Full distributions up to this level.
    pub full_max: u8,
    /// Coarse-to-fine top-k up to this level.
    pub search_max: u8,
}

/// The measure loss of the Alignist objective.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum MeasureLoss {
    /// Generalised KL (paper Eq. 5).
    Gkl,
    /// L1 between measures (ablation).
    L1,
}

/// Which experts' targets an Alignist run fits (the paper's ablation of the experts).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum ExpertBranches {
    /// Both: the shape branch fits the SDF expert, the feature branch the feature expert.
    #[default]
    Both,
    /// Only the SDF expert; the feature branch is silenced (a constant output).
    #[value(name = "shape")]
    ShapeOnly,
    /// Only the feature expert; the shape branch is silenced.
    #[value(name = "feature")]
    FeatureOnly,
}

/// What the network is trained to do.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Method {
    /// Both branches fit the experts' measures.
    Alignist {
        /// The loss per branch.
        loss: MeasureLoss,
        /// How the K rotations are drawn.
        sampling: SamplingStrategy,
        /// Which experts are fitted (runs recorded before this field fitted both).
        #[serde(default)]
        experts: ExpertBranches,
    },
    /// IPDF: one score (both branches summed), `−log softmax` of the GT among uniform samples.
    Ipdf,
}

/// How to train.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// The network.
    pub network: NetworkConfig,
    /// The objective.
    pub method: Method,
    /// Adam steps.
    pub steps: usize,
    /// Images per step.
    pub batch: usize,
    /// Rotations per image.
    pub k: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// Linear warm-up steps.
    pub warmup: usize,
    /// Seed of everything.
    pub seed: u64,
    /// Steps between checkpoints.
    pub checkpoint_every: usize,
    /// Weights to start from instead of a seeded initialisation (a warm restart: a new schedule
    /// from a trained model's weights). `None`: seeded initialisation.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub init: Option<InitWeights>,
    /// A trained model whose head this run's head learns to reproduce (`src/train/distil.rs`):
    /// its encoder is taken and frozen, and its branch scores replace the experts' targets.
    /// `None`: the experts' targets, the paper's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub teacher: Option<TeacherWeights>,
    /// With realistic fresh renders: the share of plain crops (flat grey on black, the exact
    /// box) at the first step, annealed linearly to the realism's own share at the last step
    /// ([`TrainConfig::plain_share`]): a curriculum, the part's shape on plain renders first.
    /// `None`: the realism's share at every step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plain_start: Option<f64>,
    /// The ImageNet weights file a fresh EfficientNet-Lite0 encoder starts from
    /// (`scripts/fetch_pretrained.sh`; [`crate::net::EfficientNetLite0::pretrained`]). `None`:
    /// the seeded initialisation. Read only at a fresh start (not when resuming or warm-starting).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pretrained: Option<String>,
    /// The checksum and size of [`TrainConfig::pretrained`]'s file when the run started, so
    /// that a model records exactly which weights it started from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pretrained_file: Option<FileEntry>,
    /// The encoder's learning rate as a share of [`TrainConfig::lr`] at every step (the head's
    /// stays `lr`): the usual split when a pretrained encoder meets a fresh head, whose first,
    /// noisy gradients would otherwise move the pretrained features at the head's pace.
    /// `None`: the same rate for both.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub encoder_lr_scale: Option<f64>,
    /// The weight of the contrast term added to an Alignist run's loss
    /// ([`crate::net::contrast_loss`]: the ground truth against the uniformly drawn rotations,
    /// as a classifier's softmax). `None`: the paper's loss alone.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub contrast: Option<f64>,
    /// The experts' log-targets are divided by a temperature annealed geometrically from this at
    /// the first step to 1 at the last ([`TrainConfig::target_temperature_at`]; ours, `new`'s
    /// recipe uses 100): the measure's bells `√T` times wider at first, the paper's at the end.
    /// `None`: the paper's targets at every step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target_temperature: Option<f64>,
}

impl TrainConfig {
    /// The temperature the experts' log-targets are divided by at `step` of `steps`:
    /// `T₀^(1 − step/steps)` for a start temperature `T₀`, 1 without one.
    pub fn target_temperature_at(&self, step: usize, steps: usize) -> f64 {
        match self.target_temperature {
            None => 1.0,
            Some(t0) => t0.powf(1.0 - (step as f64 / steps.max(1) as f64).min(1.0)),
        }
    }

    /// The share of plain crops at `step` of `steps` when the realism's own share is `end`:
    /// [`TrainConfig::plain_start`] annealed linearly to `end`, or `end` without one.
    pub fn plain_share(&self, step: usize, steps: usize, end: f64) -> f64 {
        match self.plain_start {
            None => end,
            Some(start) => crate::schedule::linear_anneal(start, end, step, steps),
        }
    }
}

impl Default for TrainConfig {
    /// The defaults of `alignist-train fit`: the tiny encoder and the cube encoding on 64 px
    /// crops, Alignist (GKL, mode-focused, both experts), 1 000 steps of 8 images × 256
    /// rotations, peak learning rate 1e-3 after a 5 % warm-up, a checkpoint every 100 steps.
    fn default() -> Self {
        let (steps, k) = (1000, 256);
        TrainConfig {
            network: NetworkConfig::new(
                crate::net::ResNetLayout::Tiny,
                crate::encoding::RotationEncoding::Cube,
            ),
            method: Method::Alignist {
                loss: MeasureLoss::Gkl,
                sampling: SamplingStrategy::mode_focused(k),
                experts: ExpertBranches::Both,
            },
            steps,
            batch: 8,
            k,
            lr: 1e-3,
            warmup: warmup_steps(steps),
            seed: 0,
            checkpoint_every: 100,
            init: None,
            teacher: None,
            plain_start: None,
            pretrained: None,
            pretrained_file: None,
            encoder_lr_scale: None,
            contrast: None,
            target_temperature: None,
        }
    }
}

/// The linear warm-up of a run of `steps`: 5 % of it (at least one step).
pub fn warmup_steps(steps: usize) -> usize {
    (steps / 20).max(1)
}

/// A trained network's weights file, named with its checksum so that a run records exactly what
/// it started from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InitWeights {
    /// The weights file (a bundle's `network.safetensors`).
    pub path: String,
    /// Its checksum and size, checked before loading.
    pub file: FileEntry,
    /// The command that trained it (from its bundle's manifest), so that the chain of runs
    /// behind a model stays on record.
    #[serde(default)]
    pub trained_by: String,
    /// The crop side the weights were trained at, when it is not this run's (the encoder pools
    /// globally, so its weights carry over to another size).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image_size: Option<u32>,
    /// The encoder layout the weights were trained in, when this run's grows it (its added
    /// blocks start as identities, its added channels unread).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub layout: Option<crate::net::ResNetLayout>,
    /// The encoder's pooling grid the weights were trained with (1, global pooling), when this
    /// run pools over a grid (the head's image projection is spread over the cells).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pool_grid: Option<usize>,
}

/// The model a distilled head learns from: its weights file, checked before loading, and the
/// network they are.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TeacherWeights {
    /// The weights file (a bundle's `network.safetensors`).
    pub path: String,
    /// Its checksum and size, checked before loading.
    pub file: FileEntry,
    /// The teacher's network (its head may be wider than this run's).
    pub network: NetworkConfig,
    /// The command that trained it (from its bundle's manifest).
    #[serde(default)]
    pub trained_by: String,
}

/// How the K rotations of an image are drawn.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum SamplingStrategy {
    /// `focused` rotations from the object's mode table, the rest uniform, the GT first.
    ModeFocused {
        /// How many of the K are drawn near the modes (paper: 3000 of 4096).
        focused: usize,
        /// Cells are drawn ∝ `exp(temperature · log_weight)`: 0 = uniformly over the table.
        #[serde(default)]
        temperature: f64,
        /// When set, the focused count is annealed linearly from `focused` at the first step to
        /// this at the last (the recipe of `alignist-train new`: 3/4 of K down to 1/20).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        focused_end: Option<usize>,
        /// Share of the focused rotations drawn around a twin of the pose instead (`R_gt·S·Q`,
        /// `S` a turn of the object's near-symmetry): rotations the image nearly cannot tell
        /// from the truth, where the target is low; 0 (the paper's) draws none.
        #[serde(default, skip_serializing_if = "is_zero")]
        twin_share: f64,
        /// When set, the twins also include the network's own half-turn misses, found as it
        /// trains ([`OwnTwins`]); the twin share is drawn around those too.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        own_twins: Option<OwnTwins>,
    },
    /// The GT, then uniform rotations.
    Uniform,
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

/// Twins found in the network's own answers (ours, an experiment of `alignist-train new
/// --own-twins`): every `every` steps, and before the first, the network's argmax on `crops` fresh
/// crops of each object (the training split's kind) is compared with the truth, and the turns
/// `D = R_t⁻¹·R̂` of its half-turn misses (at least `HALF_TURN_DEG` from every equivalent truth)
/// become that object's twins until the next time: the poses the network confuses with the truth
/// now, whether or not the part's geometry records a near-symmetry there.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct OwnTwins {
    /// Crops per object each time.
    pub crops: usize,
    /// Steps between two searches.
    pub every: usize,
}

/// The paper's share of the K rotations drawn from the mode table.
pub const PAPER_FOCUSED_SHARE: f64 = 0.75;

impl SamplingStrategy {
    /// The paper's mix at a given K: three quarters from the mode table, drawn uniformly.
    pub fn mode_focused(k: usize) -> Self {
        Self::mode_focused_share(k, PAPER_FOCUSED_SHARE)
    }

    /// `⌊share·K⌋` of the K rotations from the mode table (drawn uniformly over it), the rest
    /// uniform over SO(3).
    pub fn mode_focused_share(k: usize, share: f64) -> Self {
        SamplingStrategy::ModeFocused {
            focused: (k as f64 * share).floor() as usize,
            temperature: 0.0,
            focused_end: None,
            twin_share: 0.0,
            own_twins: None,
        }
    }

    /// The focused share annealed linearly from `start` of K at the first step to `end` at the
    /// last.
    pub fn annealed_share(k: usize, start: f64, end: f64) -> Self {
        SamplingStrategy::ModeFocused {
            focused: (k as f64 * start).floor() as usize,
            temperature: 0.0,
            focused_end: Some((k as f64 * end).floor() as usize),
            twin_share: 0.0,
            own_twins: None,
        }
    }

    /// This strategy with `share` of its focused rotations drawn around the pose's twins (a
    /// mode-focused one; others are returned as they are).
    pub fn with_twin_share(mut self, share: f64) -> Self {
        if let SamplingStrategy::ModeFocused { twin_share, .. } = &mut self {
            *twin_share = share;
        }
        self
    }

    /// This strategy with the network's own twins searched as `own` says (a mode-focused one;
    /// others are returned as they are).
    pub fn with_own_twins(mut self, own: Option<OwnTwins>) -> Self {
        if let SamplingStrategy::ModeFocused { own_twins, .. } = &mut self {
            *own_twins = own;
        }
        self
    }

    /// The network's own twins this strategy searches, if any.
    pub fn own_twins(&self) -> Option<OwnTwins> {
        match self {
            SamplingStrategy::ModeFocused { own_twins, .. } => *own_twins,
            SamplingStrategy::Uniform => None,
        }
    }

    /// The strategy at `step` of a run of `steps`: an annealed focused count resolved to its
    /// value there.
    pub fn at_step(&self, step: usize, steps: usize) -> SamplingStrategy {
        match *self {
            SamplingStrategy::ModeFocused {
                focused,
                temperature,
                focused_end: Some(end),
                twin_share,
                own_twins,
            } => {
                let now = crate::schedule::linear_anneal(focused as f64, end as f64, step, steps);
                SamplingStrategy::ModeFocused {
                    focused: now.round() as usize,
                    temperature,
                    focused_end: None,
                    twin_share,
                    own_twins,
                }
            }
            other => other,
        }
    }
}

/// What a run did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainReport {
    /// Steps run in this call (a resumed run counts only its own).
    pub steps_run: usize,
    /// The step the run started from (0, or the checkpoint's).
    pub resumed_from: usize,
    /// Mean loss over the last 10 % of steps.
    pub final_loss: f64,
    /// Wall time of this call.
    pub seconds: f64,
    /// Mean milliseconds per step in each stage.
    #[serde(default)]
    pub profile: StepProfile,
    /// Every search of the network's own twins this call ran ([`OwnTwins`]; none without).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub own_twins: Vec<OwnTwinsFound>,
}

/// One search of the network's own twins ([`OwnTwins`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OwnTwinsFound {
    /// The step it ran before.
    pub step: usize,
    /// Per object, how many of its crops the network missed by a half-turn: its twins until the
    /// next search.
    pub misses: Vec<usize>,
    /// Seconds the search took.
    pub seconds: f64,
}

/// Time per training step in each stage (seconds summed while training; milliseconds per step
/// in [`TrainReport::profile`]). The stages run one after the other, so they add up to the step
/// time but for the checkpoints and the loop itself (`total` is measured around the whole step).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct StepProfile {
    /// Steps measured.
    pub steps: usize,
    /// Time a step waited for its batch. The batch (data, sampling, targets) is prepared on
    /// another thread while the step before it computes, so only this wait is on the step's path.
    #[serde(default)]
    pub waiting: f64,
    /// Drawing or rendering the images (prepared ahead).
    pub data: f64,
    /// Drawing the K rotations per image (prepared ahead).
    pub sampling: f64,
    /// The experts' targets of the K rotations (prepared ahead).
    pub targets: f64,
    /// Making the images' tensor and the image encoder's forward.
    pub encoder_forward: f64,
    /// Rotation encoding, head forward and the loss.
    pub head_forward: f64,
    /// The encoder's backward (hand-written or burn's), and the head's on burn's head path; with
    /// the gradients' registration for the optimiser.
    pub backward: f64,
    /// The hand-written head's backward (the hand-written head path of the trainer; 0 on burn's).
    #[serde(default)]
    pub head_backward: f64,
    /// The Adam step.
    pub optimiser: f64,
    /// The whole step, checkpoints included.
    pub total: f64,
}

impl StepProfile {
    /// Seconds summed → milliseconds per step.
    pub fn mean_ms(&self) -> StepProfile {
        let k = 1e3 / self.steps.max(1) as f64;
        StepProfile {
            steps: self.steps,
            waiting: self.waiting * k,
            data: self.data * k,
            sampling: self.sampling * k,
            targets: self.targets * k,
            encoder_forward: self.encoder_forward * k,
            head_forward: self.head_forward * k,
            backward: self.backward * k,
            head_backward: self.head_backward * k,
            optimiser: self.optimiser * k,
            total: self.total * k,
        }
    }

    /// Sum of the stages on the step's path: the wait for the batch and the computing stages
    /// (the batch's own stages run beside them).
    pub fn stages(&self) -> f64 {
        self.waiting
            + self.encoder_forward
            + self.head_forward
            + self.backward
            + self.head_backward
            + self.optimiser
    }
}

/// Metrics of one evaluation, per object and over all images.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct EvalReport {
    /// Grid level of the evaluation.
    pub level: u8,
    /// The LL a perfect distribution would reach on these images at this level (mean).
    pub ll_ceiling: f64,
    /// Per object.
    pub per_object: Vec<(String, MetricsSummary)>,
    /// All images.
    pub overall: MetricsSummary,
    /// Images per second (encoder + head over the full grid + metrics).
    pub images_per_second: f64,
    /// Over all images, the shape branch alone (`s_θ`) and the feature branch alone (`s_φ`).
    #[serde(default)]
    pub per_branch: Option<(MetricsSummary, MetricsSummary)>,
    /// Per object, the AR@30 of an argmax that ignores the image (the symmetry group's chance
    /// level). With Haar-uniform test poses the best image-independent distribution is uniform:
    /// LL 0 and this AR@30.
    #[serde(default)]
    pub chance_ar30: Vec<(String, f64)>,
    /// The same images answered as the server answers them (`eval --served`): absent otherwise
    /// and in reports written before it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub served: Option<ServedReport>,
    /// Every image's figures, in the evaluation's order, for comparing two evaluations of the
    /// same crops image by image (`alignist-train compare`). Written to `eval`'s report file;
    /// absent from manifests and from reports written before it.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub images: Vec<ImageRecord>,
}

impl EvalReport {
    /// The report without its per-image records: what a manifest keeps (the records are the
    /// report file's).
    pub fn summary(self) -> EvalReport {
        EvalReport {
            images: Vec::new(),
            ..self
        }
    }
}

/// One evaluated image's figures ([`EvalReport::images`]).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ImageRecord {
    /// The object.
    pub object: String,
    /// The ground truth (the first of its equivalents) as a unit quaternion `[w, x, y, z]`: what
    /// pairs the images of two reports.
    pub truth: [f64; 4],
    /// `log(p_{cell(G)} · N)` averaged over the equivalents (the LL of this image).
    pub log_likelihood: f64,
    /// The argmax's error to the nearest equivalent, degrees.
    pub argmax_error_deg: f64,
    /// The first mode's error to the nearest equivalent, degrees.
    pub mode_error_deg: f64,
    /// The argmax cell's rotation as a unit quaternion `[w, x, y, z]` (absent in reports written
    /// before it was recorded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub argmax: Option<[f64; 4]>,
}

/// What the server answers for an evaluation's images: the engine loaded as `alignist-server`
/// loads it (its search calibrated on the machine that runs the evaluation), one search per
/// image, the answer's top-1 rotation and its first mode scored like the argmax (docs/DESIGN.md
/// §2, "served").
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ServedReport {
    /// The search the engine ran (the calibration's choice), as the server logs it.
    pub search: String,
    /// Whether that search was calibrated on the machine that ran the evaluation (reports written
    /// before this field ran the engine's default search, uncalibrated, and read as `false`).
    #[serde(default)]
    pub calibrated: bool,
    /// The search's finest level.
    pub level: u8,
    /// Top-k asked of each search.
    pub top_k: usize,
    /// Per object.
    pub per_object: Vec<(String, ServedSummary)>,
    /// All images.
    pub overall: ServedSummary,
    /// Median time of one image's search (the encoder's not included), milliseconds.
    pub search_p50_ms: f64,
}

/// The served answers' errors over a set of images.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ServedSummary {
    /// Number of images.
    pub images: usize,
    /// `AR@θ` of the answer's top-1 rotation (the search's most probable cell), as
    /// `(θ in degrees, fraction)`.
    pub top1_accuracy_at: Vec<(f64, f64)>,
    /// Median error of the top-1 rotation, degrees.
    pub top1_median_error_deg: f64,
    /// `AR@θ` of the answer's first mode (`modes[0]`, the most massive group of its cells).
    pub mode_accuracy_at: Vec<(f64, f64)>,
    /// Median error of the first mode, degrees.
    pub mode_median_error_deg: f64,
}
