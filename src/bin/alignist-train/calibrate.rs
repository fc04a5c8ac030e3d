//! `alignist-train calibrate`: fold a temperature into a bundle's network, chosen by the LL of
//! calibration crops from the training distribution, and write the calibrated bundle.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};

use crate::eval::print_eval;

#[derive(clap::Args)]
pub(crate) struct CalibrateArgs {
    /// The bundle to calibrate.
    #[arg(long)]
    model: PathBuf,
    /// Where the calibrated bundle is written (a new folder; the input is left as it is).
    #[arg(long)]
    out: PathBuf,
    /// Calibration crops per object: realistic crops of the training split (its ranges,
    /// backgrounds and photographs; never the held-out split `eval --realistic` tests on).
    #[arg(long, default_value_t = 50)]
    images: usize,
    /// Seed of the calibration crops (keep it apart from training and evaluation seeds).
    #[arg(long, default_value_t = 7 << 40)]
    seed: u64,
    /// Grid level of the LL that is maximised.
    #[arg(long, default_value_t = 3)]
    level: u8,
    /// Supersampling per axis of the renders.
    #[arg(long, default_value_t = 2)]
    supersample: u32,
    /// Clean fresh test crops per object evaluated afterwards for the manifest (seed 2⁴⁰, as
    /// `fit`'s; 0 skips it and drops the stale evaluation).
    #[arg(long, default_value_t = 50)]
    eval_images: usize,
    /// Give each branch its own scale (the shape expert's and the feature expert's temperature),
    /// chosen by the same LL, instead of one for their sum. Unlike one temperature, this can
    /// change which rotation is the most probable.
    #[arg(long)]
    per_branch: bool,
}

pub(crate) fn calibrate_cmd(args: &CalibrateArgs) -> Result<()> {
    use alignist::bundle::model::ModelBundle;
    use alignist::data::realism::Realism;
    use alignist::train::calibrate::fit_temperature;
    use alignist::train::data::BundleRenders;

    if args.level > alignist::train::eval::MAX_EVAL_LEVEL || args.level == 0 {
        bail!(
            "--level {} must be in 1 ..= {}",
            args.level,
            alignist::train::eval::MAX_EVAL_LEVEL
        );
    }
    if args.images == 0 {
        bail!("--images must be at least 1");
    }
    if !(1..=8).contains(&args.supersample) {
        bail!("--supersample must be in 1 ..= 8, got {}", args.supersample);
    }
    if args.out == args.model {
        bail!("--out must be a new folder, not --model");
    }
    let bundle = ModelBundle::load(&args.model)
        .with_context(|| format!("loading --model {}", args.model.display()))?;
    if let Some(c) = &bundle.manifest.calibration {
        bail!(
            "--model {} is calibrated already (scale {:.3}); calibrate the bundle it was made \
             from (`alignist-train new --calibration-images 0` makes one left at T = 1)",
            args.model.display(),
            c.scale
        );
    }
    let size = bundle.manifest.network.image_size;
    let renders = BundleRenders::of(&bundle, args.supersample);
    let crops = renders.realistic_eval_images(size, args.images, args.seed, Realism::TRAIN);
    eprintln!(
        "{} calibration crops (realistic, training split, seed {})",
        crops.len(),
        args.seed
    );
    let fit = fit_temperature(
        &bundle.network,
        &bundle.manifest.network,
        &crops,
        args.level,
        args.per_branch,
        format!(
            "{} realistic crops per object of the training split (seed {}, {}x supersampled)",
            args.images, args.seed, args.supersample
        ),
        std::env::args().collect::<Vec<_>>().join(" "),
    )?;
    print_fit(&fit);
    let [shape, feature] = fit.applied();
    let ModelBundle {
        mut manifest,
        network,
        experts: _,
    } = bundle;
    let network = alignist::net::Network {
        head: network
            .head
            .with_branch_output_scales(shape as f32, feature as f32),
        ..network
    };
    manifest.calibration = Some(fit);
    manifest.evaluation = None;
    if args.eval_images > 0 {
        let tests = renders.eval_images(size, args.eval_images, alignist::train::data::EVAL_SEED);
        let report = alignist::train::eval::evaluate(
            &network,
            &manifest.network,
            &tests,
            args.level,
            |_| {},
        )?;
        print_eval(&report);
        manifest.evaluation = Some(report.summary());
    }
    let dirs = manifest
        .objects
        .iter()
        .map(|o| alignist::bundle::inside(&args.model, &o.experts).map_err(anyhow::Error::msg))
        .collect::<Result<Vec<_>>>()?;
    let dirs: Vec<&std::path::Path> = dirs.iter().map(|d| d.as_path()).collect();
    ModelBundle::save(&mut manifest, &network, &dirs, &args.out)
        .with_context(|| format!("writing the bundle to {}", args.out.display()))?;
    eprintln!("calibrated bundle written to {}", args.out.display());
    Ok(())
}

/// Prints what a calibration chose and the calibration crops' LL before and after.
fn print_fit(fit: &alignist::bundle::record::TemperatureFit) {
    match fit.branch_scales {
        Some([shape, feature]) => println!(
            "branch scales: shape {shape:.3}, feature {feature:.3} (the best single scale {:.3}): \
             calibration LL {:.3} → {:.3} at level {}",
            fit.scale, fit.ll_before, fit.ll_after, fit.level
        ),
        None => println!(
            "temperature {:.3} (scale {:.3}): calibration LL {:.3} → {:.3} at level {}",
            1.0 / fit.scale,
            fit.scale,
            fit.ll_before,
            fit.ll_after,
            fit.level
        ),
    }
}
