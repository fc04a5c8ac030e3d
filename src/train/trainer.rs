//! The training loop. One step: `batch` images drawn from the set, K rotations sampled per image,
//! targets from the baked experts (Alignist) or the ground truth's index (IPDF), one Adam step.
//! Every step's randomness is derived from `(seed, step)`, so a run is deterministic for a seed and
//! a resumed run continues exactly where the interrupted one would have gone.

use std::ops::ControlFlow;
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, RwLock};
use std::time::Instant;

use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor, TensorData};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::TrainError;
use super::checkpoint::{CheckpointState, latest_checkpoint, load_checkpoint, save_checkpoint};
pub use super::config::{ExpertBranches, MeasureLoss, Method, TrainConfig, learning_rate};
pub use super::data::{FreshRenders, TrainingImage};
use super::distil::Teacher;
use super::sampling::{ModeSampler, OwnTwins, SamplingStrategy, sample_rotations, uniform_from};
pub use crate::bundle::record::{OwnTwinsFound, StepProfile, TrainReport};
use crate::experts::energy::{BakedExperts, LogTargets};
use crate::experts::modes::ModeTable;
use crate::net::{
    HeadGrads, HeadPass, LossGrad, TrainingEncoder, TrainingHead, contrast_loss,
    contrast_loss_grad, gkl_loss, gkl_loss_grad, ipdf_loss, ipdf_loss_grad, l1_measure_loss,
    l1_measure_loss_grad,
};
use crate::net::{Network, images_tensor};
use crate::so3::to_row_major_f32;
use nalgebra::Rotation3;
use rayon::prelude::*;

/// Images and the baked experts of their objects.
pub struct TrainingSet {
    /// Baked experts per object.
    pub objects: Vec<BakedExperts>,
    /// Mode table per object (needed by mode-focused sampling; may be empty otherwise).
    pub modes: Vec<ModeTable>,
    /// Per object, the twins of its near-symmetry (relative rotations `S`: `R_gt·S` looks
    /// nearly like `R_gt`) that mode-focused sampling with a twin share draws around; may be
    /// empty, or shorter than `objects` (no twins for the rest).
    pub twins: Vec<Vec<nalgebra::Rotation3<f64>>>,
    /// Per object, its proper symmetries (for telling the network's own half-turn misses,
    /// [`super::own_twins`]); may be empty, or shorter than `objects` (the identity alone).
    pub symmetries: Vec<Vec<nalgebra::Rotation3<f64>>>,
    /// When set, every step renders new images instead of drawing from `images`.
    pub fresh: Option<FreshRenders>,
    /// The images.
    pub images: Vec<TrainingImage>,
}

/// Which code runs the head's forward and backward in training. Both compute the same
/// gradients (within float rounding: `tests/head_grad.rs`); `ALIGNIST_TRAIN_HEAD=burn` selects
/// burn's autodiff, to measure one against the other.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum HeadPath {
    /// The hand-written forward and backward ([`TrainingHead`]); burn runs the encoder only.
    #[default]
    Fused,
    /// burn's autodiff through the whole network.
    Burn,
}

impl HeadPath {
    /// `ALIGNIST_TRAIN_HEAD` (`fused` or `burn`), else [`HeadPath::Fused`].
    pub fn from_env() -> HeadPath {
        match std::env::var("ALIGNIST_TRAIN_HEAD").as_deref() {
            Ok("burn") => HeadPath::Burn,
            _ => HeadPath::Fused,
        }
    }
}

/// Which code runs the encoder's forward and backward when the head is hand-written
/// ([`HeadPath::Fused`]). Both compute the same gradients and running statistics (within float
/// rounding: `tests/encoder_grad.rs`); `ALIGNIST_TRAIN_ENCODER=burn` selects burn's autodiff, to
/// measure one against the other. Layouts the hand-written encoder does not run (a stem
/// max-pool, bottleneck blocks) train on burn's either way.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum EncoderPath {
    /// The hand-written forward and backward ([`TrainingEncoder`]) where the layout allows.
    #[default]
    Fused,
    /// burn's autodiff.
    Burn,
}

impl EncoderPath {
    /// `ALIGNIST_TRAIN_ENCODER` (`fused` or `burn`), else [`EncoderPath::Fused`].
    pub fn from_env() -> EncoderPath {
        match std::env::var("ALIGNIST_TRAIN_ENCODER").as_deref() {
            Ok("burn") => EncoderPath::Burn,
            _ => EncoderPath::Fused,
        }
    }
}

/// The K rotations of image `id` at `step`, the first of them drawn uniformly
/// ([`uniform_from`]), and (Alignist, unless a teacher gives the targets) their expert targets.
fn sample_image(
    config: &TrainConfig,
    set: &TrainingSet,
    im: &TrainingImage,
    samplers: &[ModeSampler],
    (step, steps): (usize, usize),
    rng: &mut ChaCha8Rng,
    profile: &mut StepProfile,
) -> (Vec<[f32; 9]>, usize, Option<LogTargets>) {
    let experts = &set.objects[im.object];
    let started = Instant::now();
    let (strategy, modes) = match &config.method {
        Method::Alignist { sampling, .. } => {
            (sampling.at_step(step, steps), samplers.get(im.object))
        }
        Method::Ipdf => (SamplingStrategy::Uniform, None),
    };
    let samples = sample_rotations(&strategy, config.k, &im.rotation, modes, rng);
    let uniform = uniform_from(&strategy, config.k, modes);
    let mats: Vec<[f32; 9]> = samples.iter().map(to_row_major_f32).collect();
    profile.sampling += started.elapsed().as_secs_f64();
    let started = Instant::now();
    let targets = match config.method {
        Method::Alignist { .. } if config.teacher.is_none() => {
            let mut t = experts.log_targets(&im.rotation, &im.visible, &mats);
            let temperature = config.target_temperature_at(step, steps) as f32;
            if temperature != 1.0 {
                let cool = |v: &mut Vec<f32>| v.iter_mut().for_each(|x| *x /= temperature);
                cool(&mut t.log_a_sdf);
                cool(&mut t.log_a_se);
            }
            Some(t)
        }
        _ => None,
    };
    profile.targets += started.elapsed().as_secs_f64();
    (mats, uniform, targets)
}

/// The images of `step` of `steps`: `batch` draws from the fixed set, or (with
/// [`TrainingSet::fresh`]) `batch` new renders of random objects at Haar-random rotations, all
/// from `rng`; realistic ones with the step's share of plain crops ([`TrainConfig::plain_share`]).
fn step_images(
    config: &TrainConfig,
    set: &TrainingSet,
    (step, steps): (usize, usize),
    rng: &mut ChaCha8Rng,
) -> Vec<TrainingImage> {
    match &set.fresh {
        None => (0..config.batch)
            .map(|_| set.images[rng.random_range(0..set.images.len())].clone())
            .collect(),
        Some(fresh) => {
            let plain = fresh
                .realism
                .as_ref()
                .map(|assets| config.plain_share(step, steps, assets.realism.plain));
            // One seed per image drawn in order, then rendered in parallel: deterministic.
            let draws: Vec<(usize, u64)> = (0..config.batch)
                .map(|_| {
                    let object = rng.random_range(0..fresh.meshes.len());
                    (object, fresh.image_seed(object, rng))
                })
                .collect();
            draws
                .par_iter()
                .map(|&(object, seed)| {
                    fresh.training_image(
                        object,
                        config.network.image_size,
                        plain,
                        &mut ChaCha8Rng::seed_from_u64(seed),
                    )
                })
                .collect()
        }
    }
}

/// Log of the mean target of each branch over the samples of up to `n` images (the seed's
/// first ones): where the Alignist branches' output biases start.
fn mean_log_targets(
    config: &TrainConfig,
    set: &TrainingSet,
    n: usize,
    samplers: &[ModeSampler],
) -> (f32, f32) {
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed ^ 0xB1A5);
    let (mut sdf, mut se, mut count) = (0.0f64, 0.0f64, 0usize);
    let mut profile = StepProfile::default();
    let at_start = (0, config.steps);
    for im in step_images(
        &TrainConfig {
            batch: n,
            ..config.clone()
        },
        set,
        at_start,
        &mut rng,
    ) {
        // The experts' targets, also where a teacher gives the steps' (a distilled head).
        let experts_only = TrainConfig {
            teacher: None,
            ..config.clone()
        };
        if let (_, _, Some(t)) = sample_image(
            &experts_only,
            set,
            &im,
            samplers,
            at_start,
            &mut rng,
            &mut profile,
        ) {
            sdf += t.log_a_sdf.iter().map(|&l| (l as f64).exp()).sum::<f64>();
            se += t.log_a_se.iter().map(|&l| (l as f64).exp()).sum::<f64>();
            count += t.log_a_sdf.len();
        }
    }
    let mean_log = |total: f64| (total / count.max(1) as f64).max(1e-12).ln() as f32;
    (mean_log(sdf), mean_log(se))
}

/// One sampler per object for mode-focused sampling (none otherwise).
fn mode_samplers(config: &TrainConfig, set: &TrainingSet) -> Result<Vec<ModeSampler>, TrainError> {
    let Method::Alignist {
        sampling: SamplingStrategy::ModeFocused { temperature, .. },
        ..
    } = config.method
    else {
        return Ok(Vec::new());
    };
    if set.modes.len() != set.objects.len() {
        return Err(TrainError::Data(format!(
            "mode-focused sampling needs a mode table per object: {} tables for {} objects",
            set.modes.len(),
            set.objects.len()
        )));
    }
    set.modes
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let twins = set.twins.get(i).cloned().unwrap_or_default();
            Ok(ModeSampler::new(t, temperature)?.with_twins(twins))
        })
        .collect()
}

/// The network's own twins in a run ([`OwnTwins`]): the search's settings, the samplers with the
/// parts' recorded twins, the own twins in effect and every search so far.
struct OwnTwinsRun {
    own: Option<OwnTwins>,
    recorded: Vec<ModeSampler>,
    now: Vec<Vec<Rotation3<f64>>>,
    found: Vec<OwnTwinsFound>,
}

impl OwnTwinsRun {
    /// The own twins in effect at a run's start: a checkpoint's when resumed, else searched now
    /// (none when the run searches none).
    fn start(
        config: &TrainConfig,
        set: &TrainingSet,
        network: &Network,
        recorded: Vec<ModeSampler>,
        resumed: Option<&CheckpointState>,
    ) -> Result<Self, TrainError> {
        let own = match &config.method {
            Method::Alignist { sampling, .. } => sampling.own_twins(),
            Method::Ipdf => None,
        };
        let mut run = OwnTwinsRun {
            own,
            recorded,
            now: Vec::new(),
            found: Vec::new(),
        };
        match (own, resumed) {
            (None, _) => {}
            (Some(_), Some(state)) => run.now = state.own_twins()?,
            (Some(_), None) => run.search(config, set, network, 0)?,
        }
        Ok(run)
    }

    /// Whether a search is due after step `done` of `steps`.
    fn due(&self, done: usize, steps: usize) -> bool {
        self.own
            .is_some_and(|o| done.is_multiple_of(o.every.max(1)) && done < steps)
    }

    /// Searches the network's own twins at `step` ([`super::own_twins::own_twins`], crops drawn
    /// from the run's seed and the step's) from its weights as they are; they replace the last.
    fn search(
        &mut self,
        config: &TrainConfig,
        set: &TrainingSet,
        network: &Network,
        step: usize,
    ) -> Result<(), TrainError> {
        let Some(own) = self.own else {
            return Ok(());
        };
        let started = Instant::now();
        network.encoder.sync_running_stats();
        let seed = config
            .seed
            .wrapping_mul(0x7e1f_5eed)
            .wrapping_add(step as u64);
        let fresh = set.fresh.as_ref().ok_or_else(|| {
            TrainError::Data(
                "the network's own twins are searched on fresh renders; the set has none".into(),
            )
        })?;
        self.now = super::own_twins::own_twins(
            &network.valid(),
            &config.network,
            fresh,
            &set.symmetries,
            own,
            seed,
        )?;
        self.found.push(OwnTwinsFound {
            step,
            misses: self.now.iter().map(Vec::len).collect(),
            seconds: started.elapsed().as_secs_f64(),
        });
        Ok(())
    }

    /// The samplers with the own twins in effect added to each part's recorded ones.
    fn samplers(&self) -> Vec<ModeSampler> {
        self.recorded
            .iter()
            .enumerate()
            .map(|(i, sampler)| match self.now.get(i) {
                Some(more) if !more.is_empty() => sampler.clone().with_more_twins(more),
                _ => sampler.clone(),
            })
            .collect()
    }
}

/// Saves the checkpoint after step `done` of a schedule of `steps`: the weights with their
/// BatchNorm statistics, the optimiser, the config at that length and the own twins in effect.
fn checkpoint_at(
    dir: &Path,
    (network, optim): (&Network, &ModuleOptimizer),
    config: &TrainConfig,
    (done, steps): (usize, usize),
    own_twins: &[Vec<Rotation3<f64>>],
) -> Result<(), TrainError> {
    network.encoder.sync_running_stats();
    let config = TrainConfig {
        steps,
        ..config.clone()
    };
    save_checkpoint(
        dir,
        network,
        optim,
        &CheckpointState::new(done, config, own_twins),
    )?;
    Ok(())
}

/// Refuses a training set that cannot train: no images, or fresh renders without a mesh per
/// object.
fn check_set(set: &TrainingSet) -> Result<(), TrainError> {
    match &set.fresh {
        None if set.images.is_empty() => {
            Err(TrainError::Data("the training set has no images".into()))
        }
        Some(fresh) if fresh.meshes.len() != set.objects.len() => Err(TrainError::Data(format!(
            "fresh renders need one mesh per object: {} meshes for {} objects",
            fresh.meshes.len(),
            set.objects.len()
        ))),
        _ => Ok(()),
    }
}

/// The network and optimiser a run starts from, and its first step: the last checkpoint of
/// `checkpoints` when resuming, else the `init` weights (a warm restart), else a seeded
/// initialisation whose output biases start at the targets' mean (a silenced branch for a
/// single-expert run). When distilling, the encoder is the teacher's in either start.
fn starting_point(
    config: &TrainConfig,
    set: &TrainingSet,
    checkpoints: Option<&Path>,
    resume: bool,
    samplers: &[ModeSampler],
    teacher_encoder: Option<crate::net::Encoder>,
    device: &Device,
) -> Result<(Network, ModuleOptimizer, Option<CheckpointState>), TrainError> {
    let mut network =
        crate::backend::seeded_init(device, config.seed, || config.network.init(device));
    let optim = AdamConfig::new().init();
    if let (Some(dir), true) = (checkpoints, resume)
        && let Some(latest) = latest_checkpoint(dir)?
    {
        let (net, opt, state) = load_checkpoint(&latest, network, optim, device)?;
        return Ok((net, opt, Some(state)));
    }
    if let Some(init) = &config.init {
        let to = config.network.layout;
        let from = init.layout.unwrap_or(to);
        // A pooling grid is recorded only where it differs from the run's.
        let grid = config.network.pooling();
        let their_grid = init.pool_grid.unwrap_or(grid);
        let fail = |message: String| TrainError::Checkpoint {
            path: init.path.clone(),
            message,
        };
        // The run's own network takes the weights, or one of their layout and pooling.
        let start = if from == to && init.pool_grid.is_none() {
            network
        } else {
            let theirs = crate::net::NetworkConfig {
                layout: from,
                ..config.network.clone().pooled_over(their_grid)
            };
            crate::backend::seeded_init(device, config.seed, || theirs.init(device))
        };
        let mut loaded = crate::bundle::load_weights(start, Path::new(&init.path), &init.file)
            .map_err(|e| fail(format!("the weights to start from: {e}")))?;
        if from != to {
            // The added blocks' and channels' convolutions are drawn from the run's seed, as a
            // fresh network's.
            loaded.encoder = crate::backend::seeded_init(device, config.seed, || {
                loaded.encoder.grown(from, to, device)
            })
            .ok_or_else(|| fail(format!("a {from:?} encoder does not warm-start {to:?}")))?;
        }
        if init.pool_grid.is_some() {
            if their_grid != 1 {
                return Err(fail(format!(
                    "weights pooled over a {their_grid}×{their_grid} grid do not warm-start a {grid}×{grid} one"
                )));
            }
            loaded.encoder = loaded.encoder.with_pool_grid(grid);
            loaded.head = loaded.head.with_image_cells(grid * grid);
        }
        // A wider encoder's added features (channel-major, after the old ones) start unread.
        loaded.head = loaded
            .head
            .with_image_features(config.network.encoder().feature_dim());
        // A distilled head's encoder is its teacher's, whatever the warm start held.
        if let Some(encoder) = teacher_encoder {
            loaded.encoder = encoder;
        }
        // As after a checkpoint: loading runs ops on the parameters, fork gives them a graph.
        return Ok((loaded.valid().train().fork(device), optim, None));
    }
    if let Some(encoder) = teacher_encoder {
        network.encoder = encoder;
    } else if let Some(path) = &config.pretrained {
        let fail = |message: String| TrainError::Checkpoint {
            path: path.clone(),
            message,
        };
        let layout = config.network.layout;
        network.encoder = config
            .network
            .encoder()
            .init_pretrained(Path::new(path), device)
            .ok_or_else(|| {
                fail(format!(
                    "pretrained weights are for EfficientNet-Lite0, not {layout:?}"
                ))
            })?
            .map_err(|e| fail(e.to_string()))?;
        // As after loading a checkpoint: the loaded parameters get a graph.
        network = network.valid().train().fork(device);
    }
    if let Method::Alignist { experts, .. } = config.method {
        let (sdf, se) = mean_log_targets(config, set, config.batch, samplers);
        network.head = network.head.with_output_biases(sdf, se);
        match experts {
            ExpertBranches::ShapeOnly => network.head = network.head.with_silenced_branch(false),
            ExpertBranches::FeatureOnly => network.head = network.head.with_silenced_branch(true),
            ExpertBranches::Both => {}
        }
    }
    Ok((network, optim, None))
}

/// The loss of one batch (scores of `rotations` for the encoder's `features`) for the method:
/// per branch against the experts' log-targets (Alignist), or IPDF's softmax loss.
fn method_loss(
    config: &TrainConfig,
    network: &Network,
    features: Tensor<2>,
    rotations: &[Vec<[f32; 9]>],
    (log_sdf, log_se): (Vec<f32>, Vec<f32>),
    uniform_from: &[usize],
) -> Tensor<1> {
    let scores = network.scores_of_features(features, rotations, &config.network.encoding);
    let Method::Alignist { loss, experts, .. } = &config.method else {
        return ipdf_loss(scores.combined());
    };
    let device = scores.shape.device();
    let target = |v: Vec<f32>| -> Tensor<2> {
        Tensor::from_data(TensorData::new(v, [rotations.len(), config.k]), &device)
    };
    let f = match loss {
        MeasureLoss::Gkl => gkl_loss,
        MeasureLoss::L1 => l1_measure_loss,
    };
    let contrast = config.contrast.filter(|&w| w != 0.0).map(|w| {
        let log_a = target(log_sdf.clone()) + target(log_se.clone());
        contrast_loss(log_a, scores.combined(), uniform_from).mul_scalar(w)
    });
    let measures = match experts {
        ExpertBranches::Both => {
            f(target(log_sdf), scores.shape) + f(target(log_se), scores.feature)
        }
        ExpertBranches::ShapeOnly => f(target(log_sdf), scores.shape),
        ExpertBranches::FeatureOnly => f(target(log_se), scores.feature),
    };
    match contrast {
        Some(c) => measures + c,
        None => measures,
    }
}

/// The loss of one batch on the hand-written head's scores and its gradient with respect to each
/// branch's scores (`None` for a branch the method leaves out of the loss): the same losses as
/// [`method_loss`], for the images whose first uniform columns are `uniform_from`.
fn fused_loss(
    config: &TrainConfig,
    pass: &HeadPass,
    (log_sdf, log_se): (&[f32], &[f32]),
    uniform_from: &[usize],
) -> (f64, [Option<Vec<f32>>; 2]) {
    let images = uniform_from.len();
    let [shape, feature] = pass.scores();
    let Method::Alignist { loss, experts, .. } = &config.method else {
        let combined: Vec<f32> = shape.iter().zip(&feature).map(|(s, f)| s + f).collect();
        let LossGrad { loss, grad } = ipdf_loss_grad(&combined, combined.len() / images.max(1));
        return (loss, [Some(grad.clone()), Some(grad)]);
    };
    let f = match loss {
        MeasureLoss::Gkl => gkl_loss_grad,
        MeasureLoss::L1 => l1_measure_loss_grad,
    };
    let contrast = config.contrast.filter(|&w| w != 0.0).map(|w| {
        let sum =
            |a: &[f32], b: &[f32]| -> Vec<f32> { a.iter().zip(b).map(|(a, b)| a + b).collect() };
        let c = contrast_loss_grad(
            &sum(log_sdf, log_se),
            &sum(&shape, &feature),
            config.k,
            uniform_from,
        );
        (
            w * c.loss,
            c.grad
                .into_iter()
                .map(|g| g * w as f32)
                .collect::<Vec<f32>>(),
        )
    });
    let shape = || Some(f(log_sdf, &shape, images));
    let feature = || Some(f(log_se, &feature, images));
    let [s, f] = match experts {
        ExpertBranches::Both => [shape(), feature()],
        ExpertBranches::ShapeOnly => [shape(), None],
        ExpertBranches::FeatureOnly => [None, feature()],
    };
    let mut total = s.as_ref().map_or(0.0, |s| s.loss) + f.as_ref().map_or(0.0, |f| f.loss);
    let mut grads = [s.map(|s| s.grad), f.map(|f| f.grad)];
    if let Some((loss, d)) = contrast {
        total += loss;
        for g in grads.iter_mut().flatten() {
            g.iter_mut().zip(&d).for_each(|(g, d)| *g += d);
        }
    }
    (total, grads)
}

/// Stops a run whose loss is no longer a number.
fn check_finite(step: usize, loss: f64) -> Result<(), TrainError> {
    if loss.is_finite() {
        Ok(())
    } else {
        Err(TrainError::Diverged { step, loss })
    }
}

/// What every step of a run reads: its configuration, data, mode samplers and device.
struct Run<'a> {
    config: &'a TrainConfig,
    /// Steps of the schedule now: `config.steps` until a progress callback re-plans it
    /// ([`train_replanned`]); the learning rate and the focused share follow it.
    steps: AtomicUsize,
    set: &'a TrainingSet,
    /// The mode samplers now: their twins change where the network's own are searched
    /// ([`OwnTwins`]), between steps, never while a batch is drawn.
    samplers: RwLock<Arc<Vec<ModeSampler>>>,
    device: &'a Device,
    head: HeadPath,
    encoder: EncoderPath,
    /// The hand-written paths' GEMM kernels (`ALIGNIST_KERNELS`, read once per run).
    kernels: crate::net::Kernels,
    /// The model whose scores a distilled head learns ([`super::distil`]).
    teacher: Option<Teacher>,
}

/// One step's inputs, drawn from the step's own seed alone (so a batch prepared on another thread,
/// ahead of its step, is the batch the step would have drawn itself).
struct Batch {
    images: Vec<TrainingImage>,
    /// The K rotations of each image.
    rotations: Vec<Vec<[f32; 9]>>,
    /// The first uniformly drawn column of each image's rotations.
    uniform_from: Vec<usize>,
    /// The experts' log-targets, `[B, K]` (Alignist; empty for IPDF).
    log_sdf: Vec<f32>,
    log_se: Vec<f32>,
    /// Time spent on data, sampling and targets.
    profile: StepProfile,
}

impl Run<'_> {
    /// The batch of `step`: its images, rotations and targets from the step's seed.
    fn batch(&self, step: usize) -> Batch {
        let Run { config, set, .. } = *self;
        let samplers = Arc::clone(&self.samplers.read().unwrap_or_else(|p| p.into_inner()));
        let samplers = samplers.as_slice();
        let steps = self.steps.load(Ordering::Relaxed);
        let seed = config
            .seed
            .wrapping_mul(1_000_003)
            .wrapping_add(step as u64);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut profile = StepProfile::default();
        let started = Instant::now();
        let images = step_images(config, set, (step, steps), &mut rng);
        profile.data += started.elapsed().as_secs_f64();
        let mut rotations = Vec::with_capacity(images.len());
        let mut log_sdf = Vec::with_capacity(images.len() * config.k);
        let mut log_se = Vec::with_capacity(images.len() * config.k);
        let mut uniform = Vec::with_capacity(images.len());
        for im in &images {
            let (mats, from, targets) = sample_image(
                config,
                set,
                im,
                samplers,
                (step, steps),
                &mut rng,
                &mut profile,
            );
            if let Some(t) = targets {
                log_sdf.extend(t.log_a_sdf);
                log_se.extend(t.log_a_se);
            }
            rotations.push(mats);
            uniform.push(from);
        }
        Batch {
            images,
            rotations,
            uniform_from: uniform,
            log_sdf,
            log_se,
            profile,
        }
    }

    /// One optimiser step at `step` on its `batch`: the network after it, and the loss.
    fn step(
        &self,
        network: Network,
        optim: &mut ModuleOptimizer,
        step: usize,
        batch: Batch,
        profile: &mut StepProfile,
    ) -> Result<(Network, f64), TrainError> {
        let (config, device) = (self.config, self.device);
        let started = Instant::now();
        if let Some(teacher) = &self.teacher {
            let (loss_value, grads) =
                self.distilled_head(&network, teacher, batch, step, profile)?;
            let steps = self.steps.load(Ordering::Relaxed);
            let network = optim.step(learning_rate(config, steps, step), network, grads);
            return Ok((network, loss_value));
        }
        let hand_encoder = match (self.head, self.encoder) {
            (HeadPath::Fused, EncoderPath::Fused) => {
                TrainingEncoder::of(&network.encoder, self.kernels)
            }
            _ => None,
        };
        let (loss_value, grads) = match hand_encoder {
            Some(encoder) => {
                // Reading the weights is part of the encoder's forward.
                profile.encoder_forward += started.elapsed().as_secs_f64();
                self.fused_network(&network, &encoder, batch, step, profile)?
            }
            None => {
                let crops: Vec<&[u8]> = batch.images.iter().map(|im| im.rgb.as_slice()).collect();
                let images = images_tensor(&crops, config.network.image_size as usize, device);
                let features = network.encoder.forward(images);
                profile.encoder_forward += started.elapsed().as_secs_f64();
                match self.head {
                    HeadPath::Burn => self.burn_head(&network, features, batch, step, profile)?,
                    HeadPath::Fused => self.fused_head(&network, features, batch, step, profile)?,
                }
            }
        };
        let started = Instant::now();
        let steps = self.steps.load(Ordering::Relaxed);
        let lr = learning_rate(config, steps, step);
        let network = match config.encoder_lr_scale {
            Some(scale) if scale != 1.0 => {
                let mut head_grads = grads;
                let encoder_grads = take_grads_of(&mut head_grads, &network.encoder);
                let network = optim.step(lr, network, head_grads);
                optim.step(lr * scale, network, encoder_grads)
            }
            _ => optim.step(lr, network, grads),
        };
        profile.optimiser += started.elapsed().as_secs_f64();
        Ok((network, loss_value))
    }

    /// The loss and every gradient by burn's autodiff through head and encoder.
    fn burn_head(
        &self,
        network: &Network,
        features: Tensor<2>,
        batch: Batch,
        step: usize,
        profile: &mut StepProfile,
    ) -> Result<(f64, GradientsParams), TrainError> {
        let started = Instant::now();
        let Batch {
            rotations,
            uniform_from,
            log_sdf,
            log_se,
            ..
        } = batch;
        let loss = method_loss(
            self.config,
            network,
            features,
            &rotations,
            (log_sdf, log_se),
            &uniform_from,
        );
        let loss_value = loss.clone().into_scalar::<f32>() as f64;
        profile.head_forward += started.elapsed().as_secs_f64();
        check_finite(step, loss_value)?;
        let started = Instant::now();
        let grads = GradientsParams::from_grads(loss.backward(), network);
        profile.backward += started.elapsed().as_secs_f64();
        Ok((loss_value, grads))
    }

    /// The head's forward, the loss and the head's backward by hand, from the image features
    /// (`[images, image_dim]`): the loss, the head read for the step, and its gradients.
    fn hand_head(
        &self,
        network: &Network,
        features: Vec<f32>,
        batch: Batch,
        step: usize,
        profile: &mut StepProfile,
    ) -> Result<(f64, TrainingHead, HeadGrads), TrainError> {
        let started = Instant::now();
        let head = TrainingHead::of(&network.head, self.kernels);
        let images = batch.rotations.len();
        let flat: Vec<[f32; 9]> = batch.rotations.into_iter().flatten().collect();
        let pass = head.forward(
            features,
            self.config.network.encoding.encode(&flat),
            images,
            flat.len() / images.max(1),
        );
        let (loss_value, d_scores) = fused_loss(
            self.config,
            &pass,
            (&batch.log_sdf, &batch.log_se),
            &batch.uniform_from,
        );
        profile.head_forward += started.elapsed().as_secs_f64();
        check_finite(step, loss_value)?;
        let started = Instant::now();
        let head_grads = head.backward(&pass, d_scores.each_ref().map(|d| d.as_deref()));
        profile.head_backward += started.elapsed().as_secs_f64();
        Ok((loss_value, head, head_grads))
    }

    /// The whole step's forward and backward by hand ([`TrainingEncoder`], [`TrainingHead`]):
    /// the loss and every gradient; the encoder's BatchNorm running statistics are updated.
    fn fused_network(
        &self,
        network: &Network,
        encoder: &TrainingEncoder,
        batch: Batch,
        step: usize,
        profile: &mut StepProfile,
    ) -> Result<(f64, GradientsParams), TrainError> {
        let started = Instant::now();
        let crops: Vec<&[u8]> = batch.images.iter().map(|im| im.rgb.as_slice()).collect();
        let pass = encoder.forward(&crops, self.config.network.image_size as usize);
        profile.encoder_forward += started.elapsed().as_secs_f64();
        let features = pass.features().to_vec();
        let (loss_value, head, head_grads) =
            self.hand_head(network, features, batch, step, profile)?;
        let started = Instant::now();
        let encoder_grads = encoder.backward(&pass, &head_grads.features);
        let mut grads = GradientsParams::new();
        encoder_grads.register(encoder, &network.encoder, &mut grads, self.device);
        head_grads.register(&head, &mut grads, self.device);
        profile.backward += started.elapsed().as_secs_f64();
        Ok((loss_value, grads))
    }

    /// A distilled head's step ([`super::distil`]): the teacher's frozen encoder gives the
    /// features, its head the targets; the loss and the head's gradients alone.
    fn distilled_head(
        &self,
        network: &Network,
        teacher: &Teacher,
        batch: Batch,
        step: usize,
        profile: &mut StepProfile,
    ) -> Result<(f64, GradientsParams), TrainError> {
        let started = Instant::now();
        let crops: Vec<&[u8]> = batch.images.iter().map(|im| im.rgb.as_slice()).collect();
        let features = teacher.features(&crops, self.config.network.image_size as usize);
        profile.encoder_forward += started.elapsed().as_secs_f64();
        // The teacher's scoring runs on the step's path, so it is counted as head forward (the
        // profile's "targets" are prepared ahead, on other threads).
        let started = Instant::now();
        let (log_sdf, log_se) = teacher.targets(&features, &batch.rotations);
        profile.head_forward += started.elapsed().as_secs_f64();
        let batch = Batch {
            log_sdf,
            log_se,
            ..batch
        };
        let (loss_value, head, head_grads) =
            self.hand_head(network, features.concat(), batch, step, profile)?;
        let mut grads = GradientsParams::new();
        head_grads.register(&head, &mut grads, self.device);
        Ok((loss_value, grads))
    }

    /// The loss and the head's gradients on the hand-written head ([`TrainingHead`]); the
    /// encoder's (burn's encoder) by burn's backward of `Σ F ⊙ dF`, whose gradient with respect
    /// to the features `F` is the head's `dF`.
    fn fused_head(
        &self,
        network: &Network,
        features: Tensor<2>,
        batch: Batch,
        step: usize,
        profile: &mut StepProfile,
    ) -> Result<(f64, GradientsParams), TrainError> {
        let dims = features.dims();
        let read = crate::net::dense::read(features.clone());
        let (loss_value, head, head_grads) = self.hand_head(network, read, batch, step, profile)?;
        let started = Instant::now();
        let d_features = Tensor::<2>::from_data(
            TensorData::new(head_grads.features.clone(), dims),
            self.device,
        );
        let surrogate = (features * d_features).sum();
        let mut grads = GradientsParams::from_grads(surrogate.backward(), network);
        head_grads.register(&head, &mut grads, self.device);
        profile.backward += started.elapsed().as_secs_f64();
        Ok((loss_value, grads))
    }
}

/// Moves the gradients of `module`'s parameters out of `grads` into a set of their own, so that
/// they can be stepped at another learning rate ([`TrainConfig::encoder_lr_scale`]). Adam keeps
/// its moments per parameter, so two steps on the two sets are one step at two rates.
fn take_grads_of<M: Module>(grads: &mut GradientsParams, module: &M) -> GradientsParams {
    struct Take<'a> {
        from: &'a mut GradientsParams,
        to: GradientsParams,
    }
    impl burn::module::ModuleVisitor for Take<'_> {
        fn visit_float<const D: usize>(&mut self, param: &burn::module::Param<Tensor<D>>) {
            if let Some(g) = self.from.remove::<D>(param.id) {
                self.to.register(param.id, g);
            }
        }
    }
    let mut take = Take {
        from: grads,
        to: GradientsParams::new(),
    };
    module.visit(&mut take);
    take.to
}

/// The threads that prepare the next step's batch while this one computes. On the step's pool its
/// long tasks (a render, an image's targets) would hold up each of the encoder's many short
/// parallel ops until a worker is free; on its own threads the OS shares the cores between them.
/// (At a lower priority they starved whenever anything else ran: the step then waited for its
/// batch.)
fn batch_pool() -> Result<rayon::ThreadPool, TrainError> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(rayon::current_num_threads())
        .thread_name(|i| format!("alignist-batch-{i}"))
        .build()
        .map_err(|e| TrainError::Data(format!("starting the batch threads: {e}")))
}

/// The mean loss over the last tenth of a schedule of `steps` (or, in a run stopped before it,
/// over the last tenth of the steps it ran): `losses` are this process's, from step `start`.
fn tail_loss(losses: &[f64], start: usize, steps: usize) -> f64 {
    let tail_from = (steps - steps.div_ceil(10)).saturating_sub(start);
    let tail = match losses.get(tail_from..) {
        Some(tail) if !tail.is_empty() => tail,
        _ => &losses[losses.len() - losses.len().div_ceil(10)..],
    };
    tail.iter().sum::<f64>() / tail.len().max(1) as f64
}

/// A run's network, optimiser and checkpoint to resume from, and its teacher.
type Start = (
    Network,
    ModuleOptimizer,
    Option<CheckpointState>,
    Option<Teacher>,
);

/// Where a run starts ([`starting_point`]) and, when it distils, its teacher (whose encoder
/// the student takes, frozen).
fn start_with_teacher(
    config: &TrainConfig,
    set: &TrainingSet,
    (checkpoints, resume): (Option<&Path>, bool),
    recorded: &[ModeSampler],
    device: &Device,
) -> Result<Start, TrainError> {
    let kernels = crate::net::Kernels::from_env();
    let (teacher, encoder) = match &config.teacher {
        None => (None, None),
        Some(_) if matches!(config.method, Method::Ipdf) => {
            return Err(TrainError::Data(
                "a distilled head learns its teacher's two branches: give the Alignist method"
                    .into(),
            ));
        }
        Some(t) => {
            let (teacher, encoder) = Teacher::load(t, &config.network, kernels, device)?;
            (Some(teacher), Some(encoder))
        }
    };
    let (network, optim, resumed) =
        starting_point(config, set, checkpoints, resume, recorded, encoder, device)?;
    Ok((network, optim, resumed, teacher))
}

/// Trains (or resumes, when `checkpoints` holds one and `resume` is set) and returns the network
/// on the plain (non-autodiff) device. `progress(step, steps, loss)` runs after every step (and
/// its checkpoint); returning `ControlFlow::Break` stops the run there, as an interruption would.
pub fn train(
    config: &TrainConfig,
    set: &TrainingSet,
    checkpoints: Option<&Path>,
    resume: bool,
    mut progress: impl FnMut(usize, usize, f64) -> ControlFlow<()>,
) -> Result<(Network, TrainReport), TrainError> {
    train_replanned(
        config,
        set,
        checkpoints,
        resume,
        |step, steps, loss| match progress(step, steps, loss) {
            ControlFlow::Break(()) => ControlFlow::Break(()),
            ControlFlow::Continue(()) => ControlFlow::Continue(None),
        },
    )
}

/// [`train`] whose schedule can be re-planned as it runs: `progress` returning
/// `ControlFlow::Continue(Some(n))` makes `n` the schedule's steps from the next step on (at least
/// one more than done): the learning rate's cosine and the focused share's anneal stretch or
/// shrink to end at `n`. A run resumed from a checkpoint with `config.steps = n` continues it
/// exactly: the next step's batch, prepared ahead, is drawn again for the new schedule.
pub fn train_replanned(
    config: &TrainConfig,
    set: &TrainingSet,
    checkpoints: Option<&Path>,
    resume: bool,
    mut progress: impl FnMut(usize, usize, f64) -> ControlFlow<(), Option<usize>>,
) -> Result<(Network, TrainReport), TrainError> {
    check_set(set)?;
    let started = Instant::now();
    let device = crate::backend::device_for(crate::backend::Workload::Conv).autodiff();
    let recorded = mode_samplers(config, set)?;
    let (network, mut optim, resumed, teacher) =
        start_with_teacher(config, set, (checkpoints, resume), &recorded, &device)?;
    let start = resumed.as_ref().map_or(0, |s| s.step);
    let mut own = OwnTwinsRun::start(config, set, &network, recorded, resumed.as_ref())?;
    let run = Run {
        config,
        steps: AtomicUsize::new(config.steps),
        set,
        samplers: RwLock::new(Arc::new(own.samplers())),
        device: &device,
        head: HeadPath::from_env(),
        encoder: EncoderPath::from_env(),
        kernels: crate::net::Kernels::from_env(),
        teacher,
    };
    // Every step's loss in this process, for the mean over the schedule's last tenth.
    let mut losses = Vec::new();
    let mut profile = StepProfile::default();
    let batch_pool = batch_pool()?;
    let network = std::thread::scope(|scope| -> Result<Network, TrainError> {
        let mut network = network;
        let (run, batch_pool) = (&run, &batch_pool);
        let prepare = |step: usize| {
            (step < run.steps.load(Ordering::Relaxed))
                .then(|| scope.spawn(move || batch_pool.install(|| run.batch(step))))
        };
        // The next step's batch, drawn before a change of schedule or twins: draw it again.
        let redraw = |stale: Option<std::thread::ScopedJoinHandle<'_, Batch>>, from: usize| {
            if let Some(stale) = stale {
                let _ = stale.join();
            }
            prepare(from)
        };
        let mut pending = prepare(start);
        let mut step = start;
        while step < run.steps.load(Ordering::Relaxed) {
            let steps = run.steps.load(Ordering::Relaxed);
            let step_started = Instant::now();
            let batch = pending
                .take()
                .expect("every step's batch is prepared by the step before")
                .join()
                .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
            profile.waiting += step_started.elapsed().as_secs_f64();
            profile.data += batch.profile.data;
            profile.sampling += batch.profile.sampling;
            profile.targets += batch.profile.targets;
            pending = prepare(step + 1);
            let loss_value;
            (network, loss_value) = run.step(network, &mut optim, step, batch, &mut profile)?;
            losses.push(loss_value);
            let done = step + 1;
            if own.due(done, steps) {
                own.search(config, set, &network, done)?;
                *run.samplers.write().unwrap_or_else(|p| p.into_inner()) = Arc::new(own.samplers());
                pending = redraw(pending.take(), done);
            }
            if let Some(dir) = checkpoints
                && (done % config.checkpoint_every.max(1) == 0 || done == steps)
            {
                checkpoint_at(dir, (&network, &optim), config, (done, steps), &own.now)?;
            }
            profile.steps += 1;
            profile.total += step_started.elapsed().as_secs_f64();
            match progress(done, steps, loss_value) {
                ControlFlow::Break(()) => break,
                ControlFlow::Continue(Some(replanned)) if replanned.max(done + 1) != steps => {
                    run.steps.store(replanned.max(done + 1), Ordering::Relaxed);
                    pending = redraw(pending.take(), done);
                }
                ControlFlow::Continue(_) => {}
            }
            step = done;
        }
        Ok(network)
    })?;
    network.encoder.sync_running_stats();
    Ok((
        network.valid(),
        TrainReport {
            steps_run: losses.len(),
            resumed_from: start,
            final_loss: tail_loss(&losses, start, run.steps.load(Ordering::Relaxed)),
            seconds: started.elapsed().as_secs_f64(),
            profile: profile.mean_ms(),
            own_twins: own.found,
        },
    ))
}
