//! `alignist-train experts`: train, bake and select an object's CAD experts.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};

use crate::object::ObjectArgs;
use alignist::experts::feature::FeatureTrainConfig;
use alignist::experts::modes::ModeTableConfig;
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
    #[arg(long, default_value_t = 500)]
    steps: usize,
    /// Points per SDF step.
    #[arg(long, default_value_t = 1024)]
    sdf_batch: usize,
    /// Adam steps of the feature expert.
    #[arg(long, default_value_t = FeatureTrainConfig::default().steps)]
    feature_steps: usize,
    /// Renders per feature step.
    #[arg(long, default_value_t = 8)]
    images: usize,
    /// Render side of the feature training (divisible by 4).
    #[arg(long, default_value_t = 32)]
    image_size: u32,
    /// Foreground pixels per render (InfoNCE positives).
    #[arg(long, default_value_t = 128)]
    pixels: usize,
    /// Surface negatives per feature step.
    #[arg(long, default_value_t = 512)]
    negatives: usize,
    /// Learning rate of the key SIREN.
    #[arg(long, default_value_t = FeatureTrainConfig::default().lr_keys)]
    lr_keys: f64,
    /// Learning rate of the query CNN.
    #[arg(long, default_value_t = FeatureTrainConfig::default().lr_query)]
    lr_query: f64,
    /// Voxel bake resolution per axis.
    #[arg(long, default_value_t = 64)]
    bake_resolution: usize,
    /// Width σ in degrees of the combined target around each mode (chooses λ_SDF and λ_SE; no
    /// symmetry is needed).
    #[arg(long, default_value_t = WidthCriterion::default().width_deg)]
    width: f64,
    /// Norm of the SDF energy: l0 (the paper's fraction off the surface), l1, l2 (graded).
    #[arg(long, default_value = "l2", value_parser = ["l0", "l1", "l2"])]
    norm: String,
    /// Key distance of the feature energy: distance (the paper's) or squared (graded).
    #[arg(long, default_value = "squared", value_parser = ["distance", "squared"])]
    key_norm: String,
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

pub(crate) fn experts_cmd(args: &ExpertsArgs) -> Result<()> {
    use alignist::bundle::experts::{ExpertsJob, train_expert_set};
    use alignist::experts::energy::{EnergyParams, KeyNorm, SdfNorm};
    use alignist::experts::sdf::SdfTrainConfig;

    if !(args.width > 0.0 && args.width <= 45.0) {
        bail!("--width must be in (0, 45] degrees, got {}", args.width);
    }
    if !(args.table_fraction > 0.0 && args.table_fraction <= 0.25) {
        bail!(
            "--table-fraction must be in (0, 0.25], got {}",
            args.table_fraction
        );
    }
    for (flag, v) in [("--lr-keys", args.lr_keys), ("--lr-query", args.lr_query)] {
        if !(v > 0.0 && v < 1.0) {
            bail!("{flag} must be in (0, 1), got {v}");
        }
    }

    if args.image_size < 8 || !args.image_size.is_multiple_of(4) {
        bail!(
            "--image-size must be a multiple of 4 and at least 8, got {}",
            args.image_size
        );
    }
    if !(8..=256).contains(&args.bake_resolution) {
        bail!(
            "--bake-resolution must be in 8 ..= 256, got {}",
            args.bake_resolution
        );
    }
    for (flag, v) in [
        ("--steps", args.steps),
        ("--sdf-batch", args.sdf_batch),
        ("--feature-steps", args.feature_steps),
        ("--images", args.images),
        ("--pixels", args.pixels),
        ("--negatives", args.negatives),
    ] {
        if v == 0 {
            bail!("{flag} must be at least 1");
        }
    }
    let (name, mesh, normalisation, symmetries) = args.object.resolve()?;
    alignist::cad::SignedDistance::new(&mesh).context("the SDF expert needs a closed mesh")?;
    let job = ExpertsJob {
        name,
        mesh,
        normalisation,
        symmetries,
        sdf: SdfTrainConfig {
            steps: args.steps,
            batch: args.sdf_batch,
            seed: args.seed,
            ..Default::default()
        },
        features: FeatureTrainConfig {
            steps: args.feature_steps,
            images: args.images,
            image_size: args.image_size,
            pixels: args.pixels,
            negatives: args.negatives,
            lr_keys: args.lr_keys,
            lr_query: args.lr_query,
            seed: args.seed,
            ..Default::default()
        },
        bake_resolution: args.bake_resolution,
        energy: EnergyParams {
            norm: match args.norm.as_str() {
                "l0" => SdfNorm::L0,
                "l1" => SdfNorm::L1,
                _ => SdfNorm::L2,
            },
            key_norm: match args.key_norm.as_str() {
                "distance" => KeyNorm::Distance,
                _ => KeyNorm::Squared,
            },
            ..EnergyParams::default()
        },
        width: WidthCriterion {
            width_deg: args.width,
            seed: args.seed,
            ..WidthCriterion::default()
        },
        modes: ModeTableConfig {
            views: args.table_views.max(1),
            keep_fraction: args.table_fraction,
            seed: args.seed,
            ..ModeTableConfig::default()
        },
        command: std::env::args().collect::<Vec<_>>().join(" "),
    };
    let style = ProgressStyle::with_template("{prefix:>9} {bar:40} {pos}/{len}  {msg}  eta {eta}")
        .expect("static progress template");
    let mut bar: Option<(String, ProgressBar)> = None;
    let started = std::time::Instant::now();
    let mut set = train_expert_set(job, &mut |phase, step, steps, loss| {
        if bar.as_ref().is_none_or(|(p, _)| p != phase) {
            if let Some((_, b)) = bar.take() {
                b.finish();
            }
            let b = ProgressBar::new(steps as u64).with_style(style.clone());
            b.set_prefix(phase.to_string());
            bar = Some((phase.to_string(), b));
        }
        if let Some((_, b)) = &bar {
            b.set_position(step as u64);
            if step > 0 {
                b.set_message(format!("loss {loss:.4}"));
            }
        }
    })
    .context("training the experts")?;
    if let Some((_, b)) = bar.take() {
        b.finish();
    }
    set.save(&args.out)
        .with_context(|| format!("writing the expert set to {}", args.out.display()))?;
    let m = &set.manifest;
    eprintln!(
        "expert set for {} written to {} in {:.0} s",
        m.object.name,
        args.out.display(),
        started.elapsed().as_secs_f64()
    );
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
        args.width,
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
    Ok(())
}
