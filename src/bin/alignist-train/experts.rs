//! `alignist-train experts`: train, bake and select an object's CAD experts.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};

use crate::fit::{ProgressLog, log_progress};

use crate::object::ObjectArgs;
use alignist::experts::energy::{KeyNorm, SdfNorm};
use alignist::experts::feature::FeatureTrainConfig;
use alignist::experts::modes::ModeTableConfig;
use alignist::experts::sdf::SdfTrainConfig;
use alignist::experts::select::WidthCriterion;

#[derive(clap::Args)]
pub(crate) struct ExpertsArgs {
    /// The object (its mesh must be closed).
    #[command(flatten)]
    object: ObjectArgs,
    /// Output folder of the expert set.
    #[arg(long)]
    out: PathBuf,
    /// Adam steps of the SDF expert.
    #[arg(long, default_value_t = SdfTrainConfig::default().steps)]
    steps: usize,
    /// Points per SDF step.
    #[arg(long, default_value_t = SdfTrainConfig::default().batch)]
    sdf_batch: usize,
    /// Adam steps of the feature expert.
    #[arg(long, default_value_t = FeatureTrainConfig::default().steps)]
    feature_steps: usize,
    /// Renders per feature step.
    #[arg(long, default_value_t = FeatureTrainConfig::default().images)]
    images: usize,
    /// Render side of the feature training (divisible by 4).
    #[arg(long, default_value_t = FeatureTrainConfig::default().image_size)]
    image_size: u32,
    /// Foreground pixels per render (InfoNCE positives).
    #[arg(long, default_value_t = FeatureTrainConfig::default().pixels)]
    pixels: usize,
    /// Surface negatives per feature step.
    #[arg(long, default_value_t = FeatureTrainConfig::default().negatives)]
    negatives: usize,
    /// Learning rate of the key SIREN.
    #[arg(long, default_value_t = FeatureTrainConfig::default().lr_keys)]
    lr_keys: f64,
    /// Learning rate of the query CNN.
    #[arg(long, default_value_t = FeatureTrainConfig::default().lr_query)]
    lr_query: f64,
    /// Voxel bake resolution per axis.
    #[arg(long, default_value_t = alignist::train::experts::DEFAULT_BAKE_RESOLUTION)]
    bake_resolution: usize,
    /// Width σ in degrees of the combined target around each mode (chooses λ_SDF and λ_SE; no
    /// symmetry is needed).
    #[arg(long, default_value_t = WidthCriterion::default().width_deg)]
    width: f64,
    /// Norm of the SDF energy.
    #[arg(long, value_enum, default_value_t = NormArg::L2)]
    norm: NormArg,
    /// Key distance of the feature energy.
    #[arg(long, value_enum, default_value_t = KeyNormArg::Squared)]
    key_norm: KeyNormArg,
    /// Fraction of the level-4 cells kept in the mode table.
    #[arg(long, default_value_t = ModeTableConfig::default().keep_fraction)]
    table_fraction: f64,
    /// Random views searched for the mode table.
    #[arg(long, default_value_t = ModeTableConfig::default().views)]
    table_views: usize,
    /// Seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

/// `--norm`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum NormArg {
    /// The paper's: the fraction of points off the surface.
    L0,
    /// Mean |f| / ε.
    L1,
    /// Mean f² / ε² (graded).
    L2,
}

impl From<NormArg> for SdfNorm {
    fn from(n: NormArg) -> Self {
        match n {
            NormArg::L0 => SdfNorm::L0,
            NormArg::L1 => SdfNorm::L1,
            NormArg::L2 => SdfNorm::L2,
        }
    }
}

/// `--key-norm`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum KeyNormArg {
    /// The paper's: the distance between keys.
    Distance,
    /// The squared distance (graded).
    Squared,
}

impl From<KeyNormArg> for KeyNorm {
    fn from(n: KeyNormArg) -> Self {
        match n {
            KeyNormArg::Distance => KeyNorm::Distance,
            KeyNormArg::Squared => KeyNorm::Squared,
        }
    }
}

impl ExpertsArgs {
    /// Checks what clap cannot: ranges and counts.
    fn check(&self) -> Result<()> {
        if !(self.width > 0.0 && self.width <= 45.0) {
            bail!("--width must be in (0, 45] degrees, got {}", self.width);
        }
        if !(self.table_fraction > 0.0 && self.table_fraction <= 0.25) {
            bail!(
                "--table-fraction must be in (0, 0.25], got {}",
                self.table_fraction
            );
        }
        for (flag, v) in [("--lr-keys", self.lr_keys), ("--lr-query", self.lr_query)] {
            if !(v > 0.0 && v < 1.0) {
                bail!("{flag} must be in (0, 1), got {v}");
            }
        }
        if self.image_size < 8 || !self.image_size.is_multiple_of(4) {
            bail!(
                "--image-size must be a multiple of 4 and at least 8, got {}",
                self.image_size
            );
        }
        if !(8..=256).contains(&self.bake_resolution) {
            bail!(
                "--bake-resolution must be in 8 ..= 256, got {}",
                self.bake_resolution
            );
        }
        for (flag, v) in [
            ("--steps", self.steps),
            ("--sdf-batch", self.sdf_batch),
            ("--feature-steps", self.feature_steps),
            ("--images", self.images),
            ("--pixels", self.pixels),
            ("--negatives", self.negatives),
        ] {
            if v == 0 {
                bail!("{flag} must be at least 1");
            }
        }
        Ok(())
    }

    /// The job the flags describe, for the resolved object (its mesh must be closed).
    fn job(&self) -> Result<alignist::train::experts::ExpertsJob> {
        use alignist::experts::energy::EnergyParams;
        let (name, mesh, normalisation, symmetries) = self.object.resolve()?;
        alignist::cad::SignedDistance::new(&mesh).context("the SDF expert needs a closed mesh")?;
        Ok(alignist::train::experts::ExpertsJob {
            name,
            mesh,
            normalisation,
            symmetries,
            sdf: SdfTrainConfig {
                steps: self.steps,
                batch: self.sdf_batch,
                seed: self.seed,
                ..Default::default()
            },
            features: FeatureTrainConfig {
                steps: self.feature_steps,
                images: self.images,
                image_size: self.image_size,
                pixels: self.pixels,
                negatives: self.negatives,
                lr_keys: self.lr_keys,
                lr_query: self.lr_query,
                seed: self.seed,
                ..Default::default()
            },
            bake_resolution: self.bake_resolution,
            energy: EnergyParams {
                norm: self.norm.into(),
                key_norm: self.key_norm.into(),
                ..EnergyParams::default()
            },
            width: WidthCriterion {
                width_deg: self.width,
                seed: self.seed,
                ..WidthCriterion::default()
            },
            modes: ModeTableConfig {
                views: self.table_views.max(1),
                keep_fraction: self.table_fraction,
                seed: self.seed,
                ..ModeTableConfig::default()
            },
            command: std::env::args().collect::<Vec<_>>().join(" "),
        })
    }
}

pub(crate) fn experts_cmd(args: &ExpertsArgs) -> Result<()> {
    use alignist::train::experts::train_expert_set;
    args.check()?;
    let job = args.job()?;
    let style = ProgressStyle::with_template("{prefix:>9} {bar:40} {pos}/{len}  {msg}  eta {eta}")
        .expect("static progress template");
    let mut bar: Option<(String, ProgressBar, ProgressLog)> = None;
    let started = std::time::Instant::now();
    let mut set = train_expert_set(job, &mut |phase, step, steps, loss| {
        if bar.as_ref().is_none_or(|(p, _, _)| p != phase) {
            if let Some((_, b, _)) = bar.take() {
                b.finish();
            }
            let b = ProgressBar::new(steps as u64).with_style(style.clone());
            b.set_prefix(phase.to_string());
            let log = ProgressLog::labelled(&format!("{phase}: "));
            bar = Some((phase.to_string(), b, log));
        }
        if let Some((_, b, log)) = &mut bar {
            b.set_position(step as u64);
            if step > 0 {
                b.set_message(format!("loss {loss:.4}"));
                // Lines for logs, where no bar is drawn.
                log_progress(log, step, steps, loss);
            }
        }
    })
    .context("training the experts")?;
    if let Some((_, b, _)) = bar.take() {
        b.finish();
    }
    set.save(&args.out)
        .with_context(|| format!("writing the expert set to {}", args.out.display()))?;
    eprintln!(
        "expert set for {} written to {} in {:.0} s",
        set.manifest.object.name,
        args.out.display(),
        started.elapsed().as_secs_f64()
    );
    print_fit(&set, args.width);
    Ok(())
}

/// How well each expert fits, the bake, the selected energies and the mode table.
fn print_fit(set: &alignist::bundle::experts::ExpertSet, width: f64) {
    let m = &set.manifest;
    eprintln!(
        "  SDF: MAE near surface {:.4} (radius units), sign accuracy {:.4}, {:.0} s",
        m.sdf.fit.mae_near_surface, m.sdf.fit.sign_accuracy_off_surface, m.sdf.fit.train_seconds
    );
    eprintln!(
        "  features: InfoNCE {:.3}, mask BCE {:.3}, symmetry ratio {:.3}, {:.0} s",
        m.features.fit.final_info_nce,
        m.features.fit.final_mask_bce,
        m.features.fit.symmetry_ratio,
        m.features.fit.train_seconds
    );
    eprintln!(
        "  bake {}^3: SDF mean error {:.5}, keys relative error {:.4}",
        m.bake.resolution, m.bake.sdf_mean_error, m.bake.keys_relative_error
    );
    eprintln!(
        "  energy: {:?} / {:?}, eps {}, lambda_sdf {:.4}, lambda_se {:.4} (width {}°; profile \
         (deg, log a_sdf, log a_se): {:?})",
        m.energy.norm,
        m.energy.key_norm,
        m.energy.epsilon,
        m.energy.lambda_sdf,
        m.energy.lambda_se,
        width,
        m.energy_selection
            .profile
            .iter()
            .map(|(d, a, b)| format!("({d:.1}, {a:.2}, {b:.2})"))
            .collect::<Vec<_>>()
    );
    if let Some(t) = &set.modes {
        eprintln!(
            "  mode table: {} cells of level {} from {} views",
            t.cells.len(),
            t.config.level,
            t.config.views
        );
    }
}
