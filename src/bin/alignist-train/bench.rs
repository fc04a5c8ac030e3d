//! `alignist-train bench`: performance figures of a bundle, or of the training step.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};

#[derive(clap::Args)]
pub(crate) struct BenchArgs {
    /// Model bundle folder.
    #[arg(long, default_value = "models/symsol1")]
    model: PathBuf,
    /// Held-out images rendered from the bundle's objects (spread evenly over them); the search
    /// study scores every cell of level 5 for each (~6 s an image on 2 cores).
    #[arg(long, default_value_t = 50)]
    images: usize,
    /// Write the search study into the bundle (`search-study.json`): the agreement of each
    /// studied search, which a server's calibration reads to choose among them. Its images are
    /// rendered from a seed of their own, apart from the images a plain `bench` checks on.
    #[arg(long, conflicts_with_all = ["training", "depth"])]
    write_study: bool,
    /// Add to the bundle's search study the candidate searches it does not hold yet, on the
    /// study's own images (its seed and number; --images is not read), then stop. Each image's
    /// exhaustive argmax is read from the study where it holds it (studies written since the
    /// field), so only the new searches run; the study must have measured this network.
    #[arg(long, conflicts_with_all = ["training", "depth", "write_study"])]
    extend_study: bool,
    /// Measure the training step instead (IPDF and Alignist, with their profiles), on a small
    /// set the benchmark makes itself.
    #[arg(long)]
    training: bool,
    /// Measure what RGB-D fusion costs a request instead: --images whole-frame requests of the
    /// bundle's objects, from the image alone and with a depth image (in-process).
    #[arg(long, conflicts_with = "training")]
    depth: bool,
    /// Training: images per step.
    #[arg(long, default_value_t = 16)]
    batch: usize,
    /// Training: rotations per image.
    #[arg(long, default_value_t = 256)]
    k: usize,
    /// Training: crop side (a multiple of 8).
    #[arg(long, default_value_t = 32)]
    image_size: u32,
    /// Training: encoder layout.
    #[arg(long, value_enum, default_value_t = alignist::net::ResNetLayout::Tiny)]
    layout: alignist::net::ResNetLayout,
    /// Training: measured steps per method.
    #[arg(long, default_value_t = 30)]
    steps: usize,
}

pub(crate) fn bench_cmd(args: &BenchArgs) -> Result<()> {
    if args.training {
        return bench_training(args);
    }
    let loaded = alignist::bundle::model::ModelBundle::load(&args.model)
        .with_context(|| format!("--model {}", args.model.display()))?;
    let size = loaded.manifest.network.image_size;
    let renders = alignist::train::data::BundleRenders::of(&loaded, 4);
    if args.depth {
        let started = std::time::Instant::now();
        let model = alignist::engine::Engine::load_model(&args.model, Default::default())
            .with_context(|| format!("--model {}", args.model.display()))?;
        println!(
            "bundle {} loaded, depth fusion of {} objects built, in {:.1} s",
            args.model.display(),
            model.objects.len(),
            started.elapsed().as_secs_f64()
        );
        return alignist::bench::depth::depth_cost(&model, &renders, args.images);
    }
    if args.extend_study {
        return extend_study(args, &loaded, &renders);
    }
    let per_object = args.images.max(1).div_ceil(renders.names.len().max(1));
    // Seeds no training run uses (training draws from its own seeds, evaluation from 2^40): the
    // study's images and the check's are apart, so that the served search's agreement printed
    // below is measured on images its calibration's study never saw.
    let (seed, whose) = if args.write_study {
        (STUDY_SEED, "the study's seed")
    } else {
        (CHECK_SEED, "the check's seed, not the study's")
    };
    match alignist::bundle::study::SearchStudy::load(&args.model) {
        Ok(Some(study)) if !args.write_study && study.seed.unwrap_or(CHECK_SEED) == CHECK_SEED => {
            eprintln!(
                "note: {}'s search study was rendered from the bench's own seed {CHECK_SEED}: the \
                 agreement below is measured on the study's images (re-write it with --write-study)",
                args.model.display()
            )
        }
        _ => {}
    }
    println!(
        "images: {} from seed {seed} ({whose})",
        per_object * renders.names.len()
    );
    let (objects, crops): (Vec<String>, Vec<Vec<u8>>) = renders
        .eval_images(size, per_object, seed)
        .into_iter()
        .map(|im| (im.object, im.rgb))
        .unzip();
    drop(loaded);
    alignist::bench::bench(
        &args.model,
        &crops,
        &objects,
        args.write_study.then_some(seed),
    )
}

/// `bench --extend-study`: the searches the study lacks, run on its images rendered again from
/// its seed (the bench's own for a study written before the seed was recorded).
fn extend_study(
    args: &BenchArgs,
    loaded: &alignist::bundle::model::ModelBundle,
    renders: &alignist::train::data::BundleRenders,
) -> Result<()> {
    let size = loaded.manifest.network.image_size;
    let render = |seed: Option<u64>, images: usize| {
        let objects = renders.names.len().max(1);
        if !images.is_multiple_of(objects) {
            bail!(
                "{}: images: {images} is not a multiple of the bundle's {objects} objects, so the \
                 study's images cannot be rendered again",
                args.model
                    .join(alignist::bundle::study::SEARCH_STUDY_FILE)
                    .display()
            );
        }
        Ok(renders
            .eval_images(size, images / objects, seed.unwrap_or(CHECK_SEED))
            .into_iter()
            .map(|im| (im.object, im.rgb))
            .unzip())
    };
    alignist::bench::extend_study(&args.model, render)
        .with_context(|| format!("--model {}", args.model.display()))
}

/// The seed of the images a search study is written from (`--write-study`).
const STUDY_SEED: u64 = 98;

/// The seed of the images the bench checks a bundle's searches on otherwise: apart from
/// [`STUDY_SEED`], so that the served (calibrated) search is checked on images its study did not
/// see.
const CHECK_SEED: u64 = 99;

fn bench_training(args: &BenchArgs) -> Result<()> {
    use alignist::train::bench::{TrainingBenchConfig, bench_training, pytorch_reference};
    if args.batch == 0 || args.k < 2 || args.steps == 0 {
        bail!("--batch and --steps must be at least 1 and --k at least 2");
    }
    if args.image_size < 16 || !args.image_size.is_multiple_of(8) {
        bail!(
            "--image-size must be a multiple of 8 and at least 16, got {}",
            args.image_size
        );
    }
    let config = TrainingBenchConfig {
        batch: args.batch,
        k: args.k,
        image_size: args.image_size,
        layout: args.layout,
        steps: args.steps,
        ..TrainingBenchConfig::default()
    };
    eprintln!(
        "training step: batch {}, K {}, {} px crops, {:?} encoder, {} steps per method after {} \
         warm-up steps",
        config.batch, config.k, config.image_size, config.layout, config.steps, config.warmup
    );
    let b = bench_training(&config).context("running the training steps")?;
    println!("ipdf step: {:.1} ms", b.ipdf.total);
    crate::fit::print_profile(&b.ipdf);
    println!("alignist step: {:.1} ms", b.alignist.total);
    crate::fit::print_profile(&b.alignist);
    println!(
        "head forward: {:.1} GFLOP/s = {:.0} % of the training backend's matmul peak ({:.1} GFLOP/s)",
        b.head_forward_gflops(),
        100.0 * b.head_forward_gflops() / b.matmul_peak_gflops,
        b.matmul_peak_gflops
    );
    println!("alignist/ipdf step time ratio: {:.2}", b.ratio());
    // The tool a user would pick instead, on the same CPU, last.
    match pytorch_reference(&config) {
        Ok(torch) => {
            println!(
                "pytorch (benches/reference_training_step.py): ipdf step {:.1} ms, alignist step \
                 {:.1} ms (its images random, its targets random: rendering and experts not \
                 included)",
                torch.ipdf, torch.alignist
            );
            println!(
                "ipdf step / pytorch ipdf step: {:.2}; alignist step / pytorch alignist step: {:.2}",
                b.ipdf.total / torch.ipdf,
                b.alignist.total / torch.alignist
            );
        }
        Err(why) => println!("pytorch reference not run ({why})"),
    }
    Ok(())
}
