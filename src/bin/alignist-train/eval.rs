//! `alignist-train eval`: evaluate a bundle at a grid level.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use indicatif::ProgressBar;

pub(crate) fn print_eval(e: &alignist::train::eval::EvalReport) {
    eprintln!(
        "evaluation at level {} (LL ceiling {:.2}), {:.1} images/s:",
        e.level, e.ll_ceiling, e.images_per_second
    );
    for (name, m) in e
        .per_object
        .iter()
        .map(|(n, m)| (n.as_str(), m))
        .chain([("all", &e.overall)])
    {
        let chance = if name == "all" {
            let n = e.chance_ar30.len().max(1) as f64;
            e.chance_ar30.iter().map(|c| c.1).sum::<f64>() / n
        } else {
            e.chance_ar30
                .iter()
                .find(|c| c.0 == name)
                .map_or(f64::NAN, |c| c.1)
        };
        eprintln!(
            "  {name:8} LL {:6.2}  spread {:6.1}°  AR@30 {:.3} (chance {:.3})  median {:6.1}°  \
             wrong & sure {:5.1} %  half-turn twin {:5.1} %  ({} images)",
            m.log_likelihood,
            m.spread_deg,
            m.accuracy_at.first().map_or(f64::NAN, |a| a.1),
            chance,
            m.median_error_deg,
            100.0 * m.confidently_wrong,
            100.0 * m.half_turn_wrong,
            m.images
        );
        eprintln!(
            "  {:8} first mode instead of the argmax: AR@30 {:.3}  median {:6.1}°",
            "",
            m.mode_accuracy_at.first().map_or(f64::NAN, |a| a.1),
            m.mode_median_error_deg
        );
    }
    if let Some(s) = &e.served {
        eprintln!(
            "  served as alignist-server answers (search {}, to level {}, top-{}; search p50 {:.1} ms):",
            s.search, s.level, s.top_k, s.search_p50_ms
        );
        for (name, m) in s
            .per_object
            .iter()
            .map(|(n, m)| (n.as_str(), m))
            .chain([("all", &s.overall)])
        {
            eprintln!(
                "  {name:8} top-1 AR@30 {:.3}  median {:6.1}°   first mode AR@30 {:.3}  median {:6.1}°  ({} images)",
                m.top1_accuracy_at.first().map_or(f64::NAN, |a| a.1),
                m.top1_median_error_deg,
                m.mode_accuracy_at.first().map_or(f64::NAN, |a| a.1),
                m.mode_median_error_deg,
                m.images
            );
        }
    }
    if let Some((shape, feature)) = &e.per_branch {
        for (name, m) in [("shape branch", shape), ("feature branch", feature)] {
            eprintln!(
                "  {name} alone: LL {:.2}  AR@30 {:.3}  median {:.1}°",
                m.log_likelihood,
                m.accuracy_at.first().map_or(f64::NAN, |a| a.1),
                m.median_error_deg
            );
        }
    }
    eprintln!(
        "  (uniform, the best image-independent answer for Haar-random poses: LL 0; LL ceiling {:.2})",
        e.ll_ceiling
    );
}

#[derive(clap::Args)]
pub(crate) struct EvalArgs {
    /// A model bundle folder.
    #[arg(long)]
    model: PathBuf,
    /// OBJECT=DIR: a BOP dataset of one of the bundle's objects; repeat per object.
    #[arg(long, required_unless_present = "fresh", conflicts_with = "fresh")]
    data: Vec<String>,
    /// Render --images fresh test crops of every object of the bundle (from its expert set's
    /// mesh, at Haar-random rotations drawn from --seed) instead of reading --data.
    #[arg(long)]
    fresh: bool,
    /// Seed of the fresh test renders: use one that no training run used.
    #[arg(long, default_value_t = alignist::train::data::EVAL_SEED)]
    seed: u64,
    /// Supersampling per axis of fresh test renders.
    #[arg(long, default_value_t = 4)]
    supersample: u32,
    /// Grid level.
    #[arg(long, default_value_t = 4)]
    level: u8,
    /// Test images per object.
    #[arg(long, default_value_t = 50)]
    images: usize,
    /// Output JSON report.
    #[arg(long)]
    out: PathBuf,
    /// With --fresh: also render the same poses in whole 640×480 frames, cut them out by their
    /// boxes as the server does for full images (perspective crops), and print the camera-frame
    /// figures with the ray correction and without it, beside the directly rendered crops'.
    #[arg(long, requires = "fresh", conflicts_with = "depth")]
    frames: bool,
    /// With --fresh: also evaluate on realistic crops unlike the training ones (the held-out
    /// split of src/data/realism.rs: other background families, the other bands of every colour,
    /// light, material and camera range, seed --seed + 1), around the exact boxes and around
    /// boxes with a detector's error (σ --box-sigma of the side per edge), printed beside the
    /// clean renders' figures and those of fresh realistic crops of the training split (exact
    /// boxes): the last against the held-out row is what the split's other looks cost.
    #[arg(long, requires = "fresh", conflicts_with_all = ["depth", "frames"])]
    realistic: bool,
    /// With --realistic: σ of each box edge's error, as a fraction of the box's side.
    #[arg(long, default_value_t = 0.08, requires = "realistic")]
    box_sigma: f64,
    /// With --fresh: RGB-D fusion measured. Each crop is scored from the image alone, fused with
    /// the depth of its render, and fused with that depth spoiled (--depth-noise,
    /// --depth-missing), through the serving engine: LL and AR@30 at --level, the served top-1's
    /// AR@30 and its translation error.
    #[arg(long, requires = "fresh")]
    depth: bool,
    /// Gaussian noise on depth values, as a fraction of the object's radius (0.02: 2 mm on an
    /// object of 10 cm radius).
    #[arg(long, default_value_t = 0.02, requires = "depth")]
    depth_noise: f64,
    /// Fraction of the object's depth pixels dropped.
    #[arg(long, default_value_t = 0.1, requires = "depth")]
    depth_missing: f64,
    /// Also answer every test crop as `alignist-server` does: the bundle loaded into the serving
    /// engine (its search calibrated on this machine), one search per crop with --top-k; prints
    /// the AR@30 and median error of the answer's top-1 rotation and of its first mode beside
    /// the full grid's argmax, and writes them in the report (`served`).
    #[arg(long, conflicts_with_all = ["depth", "frames"])]
    served: bool,
    /// With --served: the top-k asked of each search (the `alignist` client's default).
    #[arg(long, default_value_t = 10, requires = "served")]
    top_k: usize,
}

/// `eval --fresh --depth`: image only against fused with clean and spoiled depth.
fn depth_report(args: &EvalArgs, renders: &alignist::train::data::BundleRenders) -> Result<()> {
    use alignist::engine::{Engine, EngineConfig};
    use alignist::train::depth_eval::{DepthNoise, depth_eval_images, evaluate_depth};
    if !(args.depth_noise.is_finite() && args.depth_noise >= 0.0) {
        bail!(
            "--depth-noise must be a fraction of the radius ≥ 0, got {}",
            args.depth_noise
        );
    }
    if !(0.0..1.0).contains(&args.depth_missing) {
        bail!(
            "--depth-missing must be in [0, 1), got {}",
            args.depth_missing
        );
    }
    let model = Engine::load_model(&args.model, EngineConfig::default())
        .with_context(|| format!("loading --model {} for the engine", args.model.display()))?;
    let images = depth_eval_images(&model, renders, args.images, args.seed)?;
    let noise = DepthNoise {
        sigma: args.depth_noise,
        missing: args.depth_missing,
    };
    let bar = ProgressBar::new(images.len() as u64);
    let started = std::time::Instant::now();
    let report = evaluate_depth(&model, &images, args.level, noise, args.seed, |n| {
        bar.set_position(n as u64)
    })?;
    bar.finish_and_clear();
    let text = serde_json::to_string_pretty(&report)?;
    std::fs::write(&args.out, text).with_context(|| format!("writing {}", args.out.display()))?;
    eprintln!(
        "RGB-D fusion at level {} (LL ceiling {:.2}), {} images in {:.0} s; noisy depth: σ {} of \
         the radius, {:.0} % of pixels missing; served: the top-1 of the search to level {}",
        report.level,
        report.ll_ceiling,
        images.len(),
        started.elapsed().as_secs_f64(),
        noise.sigma,
        noise.missing * 100.0,
        model.config().search_default_level,
    );
    eprintln!(
        "  {:8} {:>22} {:>22} {:>22} {:>22}",
        "object",
        "LL img/clean/noisy",
        "AR@30 img/clean/noisy",
        "served AR@30 i/c/n",
        "t error % c/n (median)"
    );
    for (name, [img, clean, noisy]) in &report.rows {
        eprintln!(
            "  {name:8} {:>6.2} {:>6.2} {:>6.2}    {:>5.3} {:>5.3} {:>5.3}    {:>5.3} {:>5.3} {:>5.3}    {:>5.2} {:>5.2} ({:.2} {:.2})",
            img.log_likelihood,
            clean.log_likelihood,
            noisy.log_likelihood,
            img.ar30,
            clean.ar30,
            noisy.ar30,
            img.served_ar30,
            clean.served_ar30,
            noisy.served_ar30,
            clean.translation_error_mean_pct,
            noisy.translation_error_mean_pct,
            clean.translation_error_median_pct,
            noisy.translation_error_median_pct,
        );
    }
    Ok(())
}

/// Evaluates `bundle` on `tests` at `level` with a progress bar; with `served` (the bundle as
/// the serving engine loaded it, and the top-k), also the server's answers.
fn evaluate_shown(
    bundle: &alignist::bundle::model::ModelBundle,
    tests: &[alignist::train::eval::EvalImage],
    level: u8,
    served: Option<(&alignist::engine::Model, usize)>,
) -> Result<alignist::train::eval::EvalReport> {
    let bar = ProgressBar::new(tests.len() as u64);
    let mut report = alignist::train::eval::evaluate(
        &bundle.network,
        &bundle.manifest.network,
        tests,
        level,
        |n| bar.set_position(n as u64),
    )?;
    if let Some((model, top_k)) = served {
        bar.set_position(0);
        report.served = Some(alignist::train::eval::evaluate_served(
            model,
            tests,
            top_k,
            |n| bar.set_position(n as u64),
        )?);
    }
    bar.finish_and_clear();
    Ok(report)
}

/// With `--served`: the bundle loaded as `alignist-server` loads it (search calibrated here).
fn served_model(args: &EvalArgs) -> Result<Option<alignist::engine::Model>> {
    use alignist::engine::{Engine, EngineConfig};
    if !args.served {
        return Ok(None);
    }
    // As the server answers with its default flags: the search calibrated on this CPU.
    let model = Engine::load_model(&args.model, EngineConfig::served())
        .with_context(|| format!("loading --model {} for the engine", args.model.display()))?;
    match model.calibration() {
        Some(c) => eprintln!("served search, calibrated {c}"),
        None => eprintln!(
            "served search: {} (not calibrated)",
            model.config().search()
        ),
    }
    Ok(Some(model))
}

/// `eval --fresh --frames`: the same poses as directly rendered crops, as perspective crops of
/// whole frames with the ray correction, and without it.
fn frames_report(
    args: &EvalArgs,
    bundle: &alignist::bundle::model::ModelBundle,
    sets: [Vec<alignist::train::eval::EvalImage>; 3],
) -> Result<()> {
    let labels = [
        "rendered crops (virtual camera)",
        "full frames, R_ray·R_virtual (served)",
        "full frames, no ray correction",
    ];
    let mut reports = Vec::new();
    for (label, tests) in labels.iter().zip(&sets) {
        eprintln!("{label}: {} images", tests.len());
        let report = evaluate_shown(bundle, tests, args.level, None)?;
        reports.push(serde_json::json!({ "crops": label, "report": report }));
    }
    let text = serde_json::to_string_pretty(&reports)?;
    std::fs::write(&args.out, text).with_context(|| format!("writing {}", args.out.display()))?;
    eprintln!(
        "top-1 at level {} of the same {} poses ({} per object):",
        args.level,
        sets[0].len(),
        args.images
    );
    for (label, r) in labels.iter().zip(&reports) {
        let o = &r["report"]["overall"];
        eprintln!(
            "  {label:40} AR@30 {:.3}  median {:6.1}°  LL {:6.2}",
            o["accuracy_at"][0][1].as_f64().unwrap_or(f64::NAN),
            o["median_error_deg"].as_f64().unwrap_or(f64::NAN),
            o["log_likelihood"].as_f64().unwrap_or(f64::NAN),
        );
    }
    Ok(())
}

/// `eval --fresh --realistic`: clean renders, realistic held-out crops with exact boxes and with
/// a detector's boxes, and realistic crops of the training split with exact boxes (fresh seeds:
/// how much of the held-out gap is the split's other materials, light and backgrounds), each
/// evaluated and printed, the four reports written together.
fn realistic_report(
    args: &EvalArgs,
    bundle: &alignist::bundle::model::ModelBundle,
    renders: &alignist::train::data::BundleRenders,
    clean: Vec<alignist::train::eval::EvalImage>,
) -> Result<()> {
    use alignist::data::realism::{Realism, Split};
    if !(args.box_sigma.is_finite() && (0.0..=0.5).contains(&args.box_sigma)) {
        bail!("--box-sigma must be in [0, 0.5], got {}", args.box_sigma);
    }
    let size = bundle.manifest.network.image_size;
    let realistic = |realism| {
        renders.realistic_eval_images(size, args.images, args.seed.wrapping_add(1), realism)
    };
    let sets = [
        ("clean renders", clean),
        (
            "realistic (held-out split), exact boxes",
            realistic(Realism::HELD_OUT),
        ),
        (
            "realistic, detector boxes",
            realistic(Realism::held_out_boxes(args.box_sigma)),
        ),
        (
            "realistic (training split), exact boxes",
            realistic(Realism {
                split: Split::Train,
                ..Realism::HELD_OUT
            }),
        ),
    ];
    let model = served_model(args)?;
    let served = model.as_ref().map(|m| (m, args.top_k));
    let mut reports = Vec::new();
    for (label, tests) in &sets {
        eprintln!("{label}: {} images", tests.len());
        let report = evaluate_shown(bundle, tests, args.level, served)?;
        print_eval(&report);
        reports.push((label, report));
    }
    eprintln!(
        "side by side at level {} ({} images per object and set; uniform LL 0):",
        args.level, args.images
    );
    eprintln!(
        "  {:42} {:>7} {:>7} {:>10} {:>9} {:>12} {:>12}",
        "set", "LL", "AR@30", "mode AR@30", "wrong&sure", "served top-1", "served mode"
    );
    for (label, r) in &reports {
        let served = |pick: fn(&alignist::train::eval::ServedSummary) -> &Vec<(f64, f64)>| {
            r.served
                .as_ref()
                .and_then(|s| pick(&s.overall).first())
                .map_or(f64::NAN, |a| a.1)
        };
        eprintln!(
            "  {label:42} {:7.2} {:7.3} {:10.3} {:8.1} % {:12.3} {:12.3}",
            r.overall.log_likelihood,
            r.overall.accuracy_at.first().map_or(f64::NAN, |a| a.1),
            r.overall.mode_accuracy_at.first().map_or(f64::NAN, |a| a.1),
            100.0 * r.overall.confidently_wrong,
            served(|s| &s.top1_accuracy_at),
            served(|s| &s.mode_accuracy_at),
        );
    }
    let json: Vec<_> = reports
        .iter()
        .map(|(label, r)| serde_json::json!({ "set": label, "box_sigma": args.box_sigma, "report": r }))
        .collect();
    std::fs::write(&args.out, serde_json::to_string_pretty(&json)?)
        .with_context(|| format!("writing {}", args.out.display()))?;
    Ok(())
}

pub(crate) fn eval_cmd(args: &EvalArgs) -> Result<()> {
    use alignist::bundle::model::ModelBundle;
    use alignist::data::BopDataset;
    use alignist::train::data::eval_images;

    if args.level > alignist::train::eval::MAX_EVAL_LEVEL {
        bail!(
            "--level {} is above {}",
            args.level,
            alignist::train::eval::MAX_EVAL_LEVEL
        );
    }
    let bundle = ModelBundle::load(&args.model)
        .with_context(|| format!("loading --model {}", args.model.display()))?;
    let size = bundle.manifest.network.image_size;
    let mut tests = Vec::new();
    if args.fresh {
        if !(1..=8).contains(&args.supersample) {
            bail!("--supersample must be in 1 ..= 8, got {}", args.supersample);
        }
        let renders = alignist::train::data::BundleRenders::of(&bundle, args.supersample);
        if args.depth {
            return depth_report(args, &renders);
        }
        tests = renders.eval_images(size, args.images, args.seed);
        if args.realistic {
            return realistic_report(args, &bundle, &renders, tests);
        }
        if args.frames {
            let (corrected, uncorrected) = renders.fresh.frame_eval_images(
                &renders.names,
                &renders.symmetries,
                size,
                args.images,
                args.seed,
            );
            return frames_report(args, &bundle, [tests, corrected, uncorrected]);
        }
    }
    for spec in &args.data {
        let (name, dir) = spec
            .split_once('=')
            .with_context(|| format!("--data '{spec}' is not OBJECT=DIR"))?;
        if !bundle.manifest.objects.iter().any(|o| o.name == name) {
            let known: Vec<&str> = bundle
                .manifest
                .objects
                .iter()
                .map(|o| o.name.as_str())
                .collect();
            bail!("--data '{spec}': the bundle has no object '{name}' (it has {known:?})");
        }
        let ds =
            BopDataset::open(Path::new(dir), "test").with_context(|| format!("--data {spec}"))?;
        if ds.rotations_corrected > 0 {
            eprintln!(
                "--data {spec}: {} of {} ground-truth rotations were not orthonormal and were \
                 replaced by the nearest rotation (tolerance {:.0e})",
                ds.rotations_corrected,
                ds.samples.len(),
                alignist::data::bop::ROTATION_TOLERANCE
            );
        }
        tests.extend(eval_images(&ds, name, size, args.images)?);
    }
    let model = served_model(args)?;
    let report = evaluate_shown(
        &bundle,
        &tests,
        args.level,
        model.as_ref().map(|m| (m, args.top_k)),
    )?;
    let text = serde_json::to_string_pretty(&report)?;
    std::fs::write(&args.out, text).with_context(|| format!("writing {}", args.out.display()))?;
    print_eval(&report);
    Ok(())
}
