//! `alignist-train fit`: train the distribution network and write a bundle.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};

use crate::eval::print_eval;
use alignist::net::ResNetLayout;
use alignist::train::fit::{
    FitData, FitInputs, FitSource, fitted_manifest, init_weights, teacher_weights,
};
use alignist::train::{ExpertBranches, MeasureLoss, TrainConfig};

#[derive(clap::Args)]
pub(crate) struct FitArgs {
    /// A BOP dataset of one object (with `train` and `test` splits); repeat per object. Not with
    /// --fresh.
    #[arg(long, required_unless_present = "fresh", conflicts_with = "fresh")]
    data: Vec<PathBuf>,
    /// The expert set of each object (of the `--data` at the same position); repeat per object.
    #[arg(long, required = true)]
    experts: Vec<PathBuf>,
    /// Render new training crops of the experts' meshes at every step (and fresh evaluation
    /// crops) instead of reading --data.
    #[arg(long)]
    fresh: bool,
    /// Realistic fresh training crops (with --fresh): random materials and 1–3 coloured lights,
    /// procedural backgrounds, other objects behind and in front, objects cut by the frame's edge,
    /// detector-like boxes and a camera model (src/data/realism.rs, its training split).
    #[arg(long, requires = "fresh")]
    realistic: bool,
    /// With --realistic: the share of plain crops (flat grey on black, the exact box) at the
    /// first step, annealed linearly to the realism's own 1/10 at the last (a curriculum, for
    /// experiments; without it 1/10 throughout).
    #[arg(long, requires = "realistic", value_parser = crate::new::parse_share)]
    plain_start: Option<f64>,
    /// Supersampling per axis of fresh renders (anti-aliasing).
    #[arg(long, default_value_t = 4)]
    supersample: u32,
    /// Seed of the fresh evaluation renders (keep it apart from training seeds).
    #[arg(long, default_value_t = alignist::train::data::EVAL_SEED)]
    eval_seed: u64,
    /// Print the time per step in each stage at the end.
    #[arg(long)]
    profile: bool,
    /// Output bundle folder (e.g. models/symsol1).
    #[arg(long)]
    out: PathBuf,
    /// The method: alignist (the experts' measures) or ipdf (the baseline).
    #[arg(long, value_enum, default_value_t = MethodArg::Alignist)]
    method: MethodArg,
    /// Measure loss of the alignist method.
    #[arg(long, value_enum, default_value_t = MeasureLoss::Gkl)]
    loss: MeasureLoss,
    /// Sampling of the alignist method.
    #[arg(long, value_enum, default_value_t = SamplingArg::Modes)]
    sampling: SamplingArg,
    /// With mode-focused sampling: the fraction of the K rotations drawn from the mode table
    /// (the rest uniformly; the paper's mix is 3/4).
    #[arg(long, default_value_t = alignist::train::sampling::PAPER_FOCUSED_SHARE)]
    focused_fraction: f64,
    /// Experts fitted by the alignist method; a single-expert run silences the other branch.
    #[arg(long, value_enum, default_value_t = ExpertBranches::Both)]
    fit_experts: ExpertBranches,
    /// Encoder layout.
    #[arg(long, value_enum, default_value_t = ResNetLayout::Tiny)]
    layout: ResNetLayout,
    /// The ImageNet weights an `efficientnet-lite0` encoder starts from
    /// (scripts/fetch_pretrained.sh writes data/pretrained/efficientnet-lite0.pth); without it
    /// that layout starts from random weights.
    #[arg(long)]
    pretrained: Option<PathBuf>,
    /// Rotation encoding.
    #[arg(long, value_enum, default_value_t = EncodingArg::Cube)]
    encoding: EncodingArg,
    /// Crop side in pixels.
    #[arg(long, default_value_t = TrainConfig::default().network.image_size)]
    image_size: u32,
    /// Side of the grid the encoder's last feature map is averaged over (1: global average
    /// pooling). A warm start pooled globally starts any grid.
    #[arg(long, default_value_t = TrainConfig::default().network.pooling())]
    pool_grid: usize,
    /// Width of the head's hidden layers (the paper's: 256).
    #[arg(long, default_value_t = TrainConfig::default().network.hidden)]
    hidden: usize,
    /// Linear layers per head branch (the paper's: 4).
    #[arg(long, default_value_t = TrainConfig::default().network.layers)]
    layers: usize,
    /// Adam steps.
    #[arg(long, default_value_t = TrainConfig::default().steps)]
    steps: usize,
    /// Images per step.
    #[arg(long, default_value_t = TrainConfig::default().batch)]
    batch: usize,
    /// Rotations per image (the paper: 4096).
    #[arg(long, default_value_t = TrainConfig::default().k)]
    k: usize,
    /// Peak learning rate (positive).
    #[arg(long, default_value_t = TrainConfig::default().lr, value_parser = crate::new::parse_lr)]
    lr: f64,
    /// The encoder's learning rate as a share of --lr at every step (the head's stays --lr; for
    /// a pretrained encoder under a fresh head, e.g. 0.1). Without it both learn at --lr.
    #[arg(long, value_parser = crate::new::parse_lr_scale)]
    encoder_lr_scale: Option<f64>,
    /// Weight of a contrast term added to the alignist loss: the ground truth against the
    /// uniformly drawn rotations, as a classifier's softmax, fitted to the experts' measure.
    /// Without it, the paper's loss alone.
    #[arg(long, value_parser = crate::new::parse_weight)]
    contrast: Option<f64>,
    /// The experts' log-targets divided by a temperature annealed geometrically from this at the
    /// first step to 1 at the last (broad bells first). Without it, the paper's targets.
    #[arg(long, value_parser = crate::new::parse_temperature)]
    target_temperature: Option<f64>,
    /// Fraction of each training split used (the paper's low-data regime: 0.1). With --fresh: a
    /// fixed pool of fraction × steps × batch images (the same for every run) instead of a new
    /// render every time.
    #[arg(long, default_value_t = 1.0)]
    fraction: f64,
    /// Seed.
    #[arg(long, default_value_t = TrainConfig::default().seed)]
    seed: u64,
    /// Checkpoint folder (default: <out>.checkpoints).
    #[arg(long)]
    checkpoints: Option<PathBuf>,
    /// Steps between checkpoints.
    #[arg(long, default_value_t = TrainConfig::default().checkpoint_every)]
    checkpoint_every: usize,
    /// Continue from the last checkpoint.
    #[arg(long)]
    resume: bool,
    /// Stop after this step (a time-boxed part of a run): write a checkpoint there and exit
    /// without a bundle; `--resume` continues later. Must be a multiple of --checkpoint-every.
    #[arg(long)]
    stop_at: Option<usize>,
    /// Start from a trained model bundle's weights (same network flags) with a new schedule
    /// instead of a seeded initialisation: a warm restart. The manifest records the file and its
    /// sha256.
    #[arg(long)]
    init: Option<PathBuf>,
    /// Distil the head from this trained model bundle instead of fitting the experts (a
    /// narrower head that serves faster): its encoder is taken and frozen, and the head learns
    /// its two branch scores at the sampled rotations. Same --layout, --image-size and
    /// --encoding as the teacher. With --init (a distilled head trained on), the encoder is
    /// still the teacher's.
    #[arg(long)]
    teacher: Option<PathBuf>,
    /// Grid level of the evaluation.
    #[arg(long, default_value_t = 4)]
    eval_level: u8,
    /// Test images per object in the evaluation (0 skips it).
    #[arg(long, default_value_t = 50)]
    eval_images: usize,
}

/// `--method`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum MethodArg {
    /// Alignist: both branches fit the experts' measures.
    Alignist,
    /// IPDF: the softmax of the ground truth among uniform rotations.
    Ipdf,
}

/// `--sampling`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum SamplingArg {
    /// Mode-focused (the paper's).
    Modes,
    /// Uniform (ablation).
    Random,
}

/// `--encoding`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum EncodingArg {
    /// The cube encoding (the paper's).
    Cube,
    /// IPDF's positional encoding (3 frequencies).
    Ipdf,
}

impl From<EncodingArg> for alignist::encoding::RotationEncoding {
    fn from(e: EncodingArg) -> Self {
        match e {
            EncodingArg::Cube => Self::Cube,
            EncodingArg::Ipdf => Self::Ipdf { frequencies: 3 },
        }
    }
}

impl FitArgs {
    /// The training method the flags ask for.
    fn method(&self) -> alignist::train::Method {
        use alignist::train::{Method, SamplingStrategy};
        match self.method {
            MethodArg::Ipdf => Method::Ipdf,
            MethodArg::Alignist => Method::Alignist {
                loss: self.loss,
                sampling: match self.sampling {
                    SamplingArg::Modes => {
                        SamplingStrategy::mode_focused_share(self.k, self.focused_fraction)
                    }
                    SamplingArg::Random => SamplingStrategy::Uniform,
                },
                experts: self.fit_experts,
            },
        }
    }

    /// The training configuration the flags ask for, for `network`.
    fn train_config(
        &self,
        network: &alignist::train::NetworkConfig,
    ) -> Result<alignist::train::TrainConfig> {
        Ok(alignist::train::TrainConfig {
            network: network.clone(),
            method: self.method(),
            steps: self.steps,
            batch: self.batch,
            k: self.k,
            lr: self.lr,
            warmup: alignist::train::config::warmup_steps(self.steps),
            seed: self.seed,
            checkpoint_every: self.checkpoint_every,
            init: self
                .init
                .as_deref()
                .map(|dir| {
                    init_weights(dir, network).with_context(|| format!("--init {}", dir.display()))
                })
                .transpose()?,
            teacher: self
                .teacher
                .as_deref()
                .map(|dir| {
                    teacher_weights(dir, network)
                        .with_context(|| format!("--teacher {}", dir.display()))
                })
                .transpose()?,
            plain_start: self.plain_start,
            pretrained: self.pretrained.as_ref().map(|p| p.display().to_string()),
            pretrained_file: self
                .pretrained
                .as_deref()
                .map(|p| {
                    alignist::bundle::sha256_file(p)
                        .with_context(|| format!("--pretrained {}", p.display()))
                })
                .transpose()?,
            encoder_lr_scale: self.encoder_lr_scale,
            contrast: self.contrast,
            target_temperature: self.target_temperature,
        })
    }

    /// Checks what clap cannot: counts, ranges and the flags that go together.
    fn check(&self) -> Result<()> {
        if self.pretrained.is_some() && !self.layout.is_efficientnet() {
            bail!("--pretrained goes with --layout efficientnet-lite0");
        }
        // The data's own settings (--fraction, --supersample, one --experts per --data) are
        // checked where the data is assembled (alignist::train::fit).
        if !(0.0..=1.0).contains(&self.focused_fraction) {
            bail!(
                "--focused-fraction must be in [0, 1], got {}",
                self.focused_fraction
            );
        }
        if self.image_size < 16 || !self.image_size.is_multiple_of(8) {
            bail!(
                "--image-size must be a multiple of 8 and at least 16, got {}",
                self.image_size
            );
        }
        if self.eval_level > alignist::train::eval::MAX_EVAL_LEVEL {
            bail!(
                "--eval-level {} is above {}",
                self.eval_level,
                alignist::train::eval::MAX_EVAL_LEVEL
            );
        }
        for (flag, v) in [
            ("--steps", self.steps),
            ("--batch", self.batch),
            ("--k", self.k),
        ] {
            if v == 0 {
                bail!("{flag} must be at least 1");
            }
        }
        if let Some(stop) = self.stop_at
            && (stop == 0
                || stop > self.steps
                || !stop.is_multiple_of(self.checkpoint_every.max(1)))
        {
            bail!(
                "--stop-at {stop} must be in 1 ..= --steps ({}) and a multiple of \
                 --checkpoint-every ({}), so that the run stops at a checkpoint",
                self.steps,
                self.checkpoint_every
            );
        }
        Ok(())
    }
}

impl FitArgs {
    /// What the flags ask to train and test on.
    fn inputs(&self) -> FitInputs {
        FitInputs {
            experts: self.experts.clone(),
            source: match self.fresh {
                true => FitSource::Fresh {
                    realistic: self.realistic,
                    supersample: self.supersample,
                    eval_seed: self.eval_seed,
                },
                false => FitSource::Datasets(self.data.clone()),
            },
            image_size: self.image_size,
            fraction: self.fraction,
            eval_images: self.eval_images,
        }
    }
}

pub(crate) fn fit_cmd(args: &FitArgs) -> Result<()> {
    use alignist::bundle::model::ModelBundle;
    use alignist::train::NetworkConfig;

    args.check()?;
    let network = NetworkConfig::new(args.layout, args.encoding.into())
        .with_image_size(args.image_size)
        .pooled_over(args.pool_grid)
        .with_hidden(args.hidden)
        .with_layers(args.layers);
    network
        .validate()
        .map_err(|e| anyhow::anyhow!("the network flags: {e}"))?;
    let mut data = FitData::load(&args.inputs(), args.steps, args.batch)?;
    eprintln!("{}", data.describe());
    let config = args.train_config(&network)?;
    let training = data.training_set()?;
    let Some((trained, report)) = train_with_progress(args, &config, &training)? else {
        return Ok(());
    };
    if args.profile {
        print_profile(&report.profile);
    }
    let evaluation = evaluate_fit(args, &trained, &network, &data.tests)?;
    let name = args
        .out
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or("model");
    let command = std::env::args().collect::<Vec<_>>().join(" ");
    let mut manifest = fitted_manifest(
        name.to_string(),
        data.objects,
        command,
        config,
        report.clone(),
        evaluation.clone(),
    );
    let dirs: Vec<&Path> = args.experts.iter().map(|p| p.as_path()).collect();
    ModelBundle::save(&mut manifest, &trained, &dirs, &args.out)
        .with_context(|| format!("writing the bundle to {}", args.out.display()))?;
    eprintln!(
        "trained {} steps in {:.0} s (final loss {:.4}); bundle written to {}",
        report.steps_run,
        report.seconds,
        report.final_loss,
        args.out.display()
    );
    if let Some(e) = evaluation {
        print_eval(&e);
    }
    Ok(())
}

/// The trained network evaluated on the test images at `--eval-level` (none without images).
fn evaluate_fit(
    args: &FitArgs,
    trained: &alignist::net::Network,
    network: &alignist::train::NetworkConfig,
    tests: &[alignist::train::eval::EvalImage],
) -> Result<Option<alignist::train::eval::EvalReport>> {
    if tests.is_empty() {
        return Ok(None);
    }
    let bar = ProgressBar::new(tests.len() as u64);
    let report = alignist::train::eval::evaluate(trained, network, tests, args.eval_level, |n| {
        bar.set_position(n as u64)
    })?;
    bar.finish_and_clear();
    Ok(Some(report))
}

/// Trains with a progress bar and a log line now and then, checkpointing to `--checkpoints`;
/// `None` when the run stopped at `--stop-at` as asked.
fn train_with_progress(
    args: &FitArgs,
    config: &alignist::train::TrainConfig,
    training: &alignist::train::TrainingSet,
) -> Result<Option<(alignist::net::Network, alignist::train::TrainReport)>> {
    let checkpoints = args
        .checkpoints
        .clone()
        .unwrap_or_else(|| args.out.with_extension("checkpoints"));
    std::fs::create_dir_all(&checkpoints)
        .with_context(|| format!("creating {}", checkpoints.display()))?;
    let bar = ProgressBar::new(args.steps as u64).with_style(
        ProgressStyle::with_template("train {bar:40} {pos}/{len}  {msg}  {per_sec}  eta {eta}")
            .expect("static progress template"),
    );
    let mut log = ProgressLog::new();
    let (trained, report) = alignist::train::train(
        config,
        training,
        Some(&checkpoints),
        args.resume,
        |step, steps, loss| {
            bar.set_position(step as u64);
            bar.set_message(format!("loss {loss:.4}"));
            log_progress(&mut log, step, steps, loss);
            if args.stop_at == Some(step) {
                std::ops::ControlFlow::Break(())
            } else {
                std::ops::ControlFlow::Continue(())
            }
        },
    )
    .context("training")?;
    bar.finish();
    if let Some(stop) = args.stop_at
        && report.resumed_from + report.steps_run == stop
        && stop < args.steps
    {
        println!(
            "stopped at step {stop} of {} as asked (--stop-at); checkpoint in {}; continue with \
             --resume",
            args.steps,
            checkpoints.display()
        );
        return Ok(None);
    }
    Ok(Some((trained, report)))
}

/// Progress lines for logs (a bar is drawn only on a terminal): every 2 % of the run or every
/// 60 s, with the loss, the rate and the time left.
pub(crate) struct ProgressLog {
    started: std::time::Instant,
    last: std::time::Instant,
    first_step: Option<usize>,
    on_terminal: bool,
    /// Printed before each line (a phase's name, or nothing).
    label: String,
}

impl ProgressLog {
    pub(crate) fn new() -> Self {
        Self::labelled("")
    }

    /// A log whose lines start with `label` (e.g. `sdf: `).
    pub(crate) fn labelled(label: &str) -> Self {
        use std::io::IsTerminal;
        let now = std::time::Instant::now();
        ProgressLog {
            started: now,
            last: now,
            first_step: None,
            on_terminal: std::io::stderr().is_terminal(),
            label: label.to_string(),
        }
    }
}

pub(crate) fn log_progress(log: &mut ProgressLog, step: usize, steps: usize, loss: f64) {
    if log.on_terminal {
        return;
    }
    let first = *log.first_step.get_or_insert(step.saturating_sub(1));
    let every = (steps / 50).max(1);
    if !(step.is_multiple_of(every) || step == steps || log.last.elapsed().as_secs() >= 60) {
        return;
    }
    log.last = std::time::Instant::now();
    let elapsed = log.started.elapsed().as_secs_f64();
    let per_step = elapsed / (step - first).max(1) as f64;
    eprintln!(
        "{}step {step}/{steps}  loss {loss:.4}  {:.0} ms/step  elapsed {:.0} s  left {:.0} s",
        log.label,
        per_step * 1e3,
        elapsed,
        per_step * (steps - step) as f64
    );
}

pub(crate) fn print_profile(p: &alignist::train::trainer::StepProfile) {
    println!("step profile (ms per step, mean of {} steps):", p.steps);
    let share = |v: f64| 100.0 * v / p.total.max(1e-9);
    println!("  prepared ahead, on another thread while the step before computes:");
    for (name, v) in [
        ("data (rendering)", p.data),
        ("sampling", p.sampling),
        ("targets", p.targets),
    ] {
        println!("    {name:<18} {v:8.1}  {:5.1} %", share(v));
    }
    println!("  on the step's path:");
    for (name, v) in [
        ("waiting for batch", p.waiting),
        ("encoder forward", p.encoder_forward),
        ("head forward + loss", p.head_forward),
        ("head backward", p.head_backward),
        ("encoder backward", p.backward),
        ("optimiser", p.optimiser),
    ] {
        println!("    {name:<18} {v:8.1}  {:5.1} %", share(v));
    }
    println!(
        "  {:<20} {:8.1}  (path stages sum {:.1}; supervision = sampling + targets = {:.1} %)",
        "step",
        p.total,
        p.stages(),
        share(p.sampling + p.targets)
    );
}
