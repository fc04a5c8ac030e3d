//! `alignist-train`: the offline side of alignist — grids, renders, experts, training, evaluation.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};

use alignist::experts::feature::FeatureTrainConfig;
use alignist::experts::modes::ModeTableConfig;
use alignist::experts::select::WidthCriterion;
use alignist::so3::{GridLevel, MAX_LEVEL, to_quaternion};

/// Trains and inspects alignist models.
#[derive(Parser)]
#[command(name = "alignist-train", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Write the centres of one level of the nested SO(3) grid as CSV
    /// (`index,qw,qx,qy,qz`, index order, w ≥ 0).
    Grid {
        /// Grid level L (0 ..= 6): 72·8^L cells.
        #[arg(long)]
        level: u8,
        /// Output CSV file (written to a temporary name, then renamed).
        #[arg(long)]
        out: PathBuf,
    },
    /// Render a dataset of one object in BOP layout (SYMSOL style: centred, fully in view,
    /// every equivalent ground truth recorded in scene_gt_equivalents.json).
    Render(RenderArgs),
    /// Train the two CAD experts of an object (SDF and SurfEmb features), bake them, choose λ by
    /// the LL of their targets, and write the expert set.
    Experts(ExpertsArgs),
    /// Write the target distribution the experts give for one rotation on every cell of a grid
    /// level (`index,log_a_sdf,log_a_se`).
    Score(ScoreArgs),
    /// Train the distribution network on BOP datasets (one per object, with its expert set),
    /// evaluate it on their test splits, and write a model bundle.
    Fit(FitArgs),
    /// Evaluate a model bundle on the test split of BOP datasets.
    Eval(EvalArgs),
    /// Print the evaluation figures of model bundles as Markdown tables (per object and
    /// averaged, with the ceiling of the level, the training budget and wall time).
    Results {
        /// Model bundle folders.
        #[arg(required = true)]
        bundles: Vec<PathBuf>,
    },
    /// Print performance figures of a model bundle: the backend's matmul peak, full-grid head
    /// throughput at levels 3 and 4 against it, coarse-to-fine top-k latency, encoder images/s,
    /// and gRPC against in-process Predict throughput.
    Bench {
        /// Model bundle folder.
        #[arg(long, default_value = "models/symsol1")]
        model: PathBuf,
        /// Test images rendered from the bundle's first object.
        #[arg(long, default_value_t = 8)]
        images: usize,
    },
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Grid { level, out } => write_grid(level, &out),
        Command::Render(args) => render_cmd(&args),
        Command::Experts(args) => experts_cmd(&args),
        Command::Score(args) => score_cmd(&args),
        Command::Fit(args) => fit_cmd(&args),
        Command::Eval(args) => eval_cmd(&args),
        Command::Results { bundles } => results_cmd(&bundles),
        Command::Bench { model, images } => bench_cmd(&model, images),
    }
}

fn results_cmd(bundles: &[PathBuf]) -> Result<()> {
    use alignist::bundle::model::ModelManifest;
    let mut rows: Vec<(String, ModelManifest)> = Vec::new();
    for b in bundles {
        let path = b.join("manifest.json");
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("reading {}", path.display()))?;
        let m: ModelManifest =
            serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
        if m.evaluation.is_none() {
            bail!(
                "{}: evaluation: the bundle was not evaluated",
                path.display()
            );
        }
        let name = b
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default();
        rows.push((name, m));
    }
    let ar = |s: &alignist::so3::metrics::MetricsSummary| {
        s.accuracy_at.first().map_or(f64::NAN, |a| a.1)
    };
    let mut objects: Vec<String> = Vec::new();
    for (_, m) in &rows {
        for (o, _) in &m.evaluation.as_ref().expect("checked").per_object {
            if !objects.contains(o) {
                objects.push(o.clone());
            }
        }
    }
    println!("| model | object | images | LL | ceiling | spread ° | AR@30 | median ° |");
    println!("|---|---|---|---|---|---|---|---|");
    for object in objects.iter().map(Some).chain([None]) {
        for (name, m) in &rows {
            let e = m.evaluation.as_ref().expect("checked");
            let summary = match object {
                Some(o) => match e.per_object.iter().find(|(n, _)| n == o) {
                    Some((_, s)) => s,
                    None => continue,
                },
                None => &e.overall,
            };
            println!(
                "| {name} | {} | {} | {:.2} | {} | {:.1} | {:.2} | {:.1} |",
                object.map_or("**mean**", |o| o.as_str()),
                summary.images,
                summary.log_likelihood,
                if object.is_none() {
                    format!("{:.2}", e.ll_ceiling)
                } else {
                    "".into()
                },
                summary.spread_deg,
                ar(summary),
                summary.median_error_deg
            );
        }
    }
    println!();
    println!(
        "| model | method | images | steps × batch × K | train wall | eval level | eval img/s |"
    );
    println!("|---|---|---|---|---|---|---|");
    for (name, m) in &rows {
        let t = &m.provenance.train;
        let method = match t.method {
            alignist::train::Method::Alignist { .. } => "alignist (GKL)",
            alignist::train::Method::Ipdf => "ipdf",
        };
        let images: usize = m.objects.iter().map(|o| o.train_images).sum();
        let e = m.evaluation.as_ref().expect("checked");
        println!(
            "| {name} | {method} | {images} | {} × {} × {} | {:.0} s | {} | {:.2} |",
            t.steps, t.batch, t.k, m.provenance.report.seconds, e.level, e.images_per_second
        );
    }
    Ok(())
}

/// The object a command works on: a SYMSOL shape or a mesh file.
#[derive(clap::Args)]
#[command(group(clap::ArgGroup::new("object").required(true).args(["shape", "mesh"])))]
struct ObjectArgs {
    /// A SYMSOL shape: tet, cube, icosa, cone, cyl, tetX, cylO, sphereX.
    #[arg(long)]
    shape: Option<String>,
    /// A mesh file (.obj, .ply, .stl); it is normalised to NOCS.
    #[arg(long)]
    mesh: Option<PathBuf>,
    /// Symmetry group of --mesh (none, T, O, I, C<n>, D<n>, cone, cylinder).
    #[arg(long, default_value = "none", requires = "mesh")]
    symmetry: String,
}

impl ObjectArgs {
    /// The object's name, its mesh in NOCS with the normalisation, and its symmetries.
    fn resolve(
        &self,
    ) -> Result<(
        String,
        alignist::cad::Mesh,
        alignist::cad::Normalisation,
        Vec<nalgebra::Rotation3<f64>>,
    )> {
        use alignist::cad::{Mesh, Shape};
        use alignist::so3::SymmetryGroup;
        let (name, mesh, symmetries) = match (&self.shape, &self.mesh) {
            (Some(name), _) => {
                let shape: Shape = name.parse().context("--shape")?;
                (shape.name().to_string(), shape.mesh(), shape.symmetries())
            }
            (None, Some(path)) => {
                let group: SymmetryGroup = self.symmetry.parse().context("--symmetry")?;
                let mesh =
                    Mesh::load(path).with_context(|| format!("--mesh {}", path.display()))?;
                let stem = path
                    .file_stem()
                    .and_then(|s| s.to_str())
                    .unwrap_or("object");
                (stem.to_string(), mesh, group.rotations())
            }
            (None, None) => bail!("give --shape NAME or --mesh FILE"),
        };
        let (mesh, normalisation) = mesh.normalised();
        Ok((name, mesh, normalisation, symmetries))
    }
}

#[derive(clap::Args)]
struct RenderArgs {
    #[command(flatten)]
    object: ObjectArgs,
    /// Number of images (ignored with --rotations).
    #[arg(long, default_value_t = 100)]
    count: usize,
    /// Image side in pixels.
    #[arg(long, default_value_t = 224)]
    size: u32,
    /// Seed of the random rotations.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output dataset root (BOP layout).
    #[arg(long)]
    out: PathBuf,
    /// Render exactly these rotations: a CSV of `qw,qx,qy,qz` rows (a header line is allowed).
    #[arg(long)]
    rotations: Option<PathBuf>,
    /// Split name.
    #[arg(long, default_value = "train")]
    split: String,
    /// Millimetres per NOCS unit in the written files (the object's bounding-sphere radius).
    #[arg(long, default_value_t = 100.0)]
    units_mm: f64,
    /// BOP object id.
    #[arg(long, default_value_t = 1)]
    obj_id: u32,
    /// WxH: render full frames of this size with each object at a random position and distance
    /// (seeded by --seed), instead of centred `--size` squares.
    #[arg(long, value_parser = parse_frame)]
    frame: Option<(u32, u32)>,
}

fn parse_frame(s: &str) -> std::result::Result<(u32, u32), String> {
    let bad = || format!("'{s}': expected WxH, e.g. 640x480, each side in 16 ..= 4096");
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    let (w, h): (u32, u32) = (
        w.trim().parse().map_err(|_| bad())?,
        h.trim().parse().map_err(|_| bad())?,
    );
    if !(16..=4096).contains(&w) || !(16..=4096).contains(&h) {
        return Err(bad());
    }
    Ok((w, h))
}

fn render_cmd(args: &RenderArgs) -> Result<()> {
    use alignist::data::{RenderJob, render_dataset};
    use alignist::so3::haar_rotations;
    use rand::SeedableRng;

    if args.size < 8 || args.size > 4096 {
        bail!("--size {} is outside 8 ..= 4096 pixels", args.size);
    }
    if !(args.units_mm.is_finite() && args.units_mm > 0.0) {
        bail!(
            "--units-mm must be a positive number, got {}",
            args.units_mm
        );
    }
    let (_, mesh, _, symmetries) = args.object.resolve()?;
    let rotations = match &args.rotations {
        Some(path) => read_rotations(path)?,
        None => {
            if args.count == 0 {
                bail!("--count must be at least 1");
            }
            haar_rotations(
                &mut rand_chacha::ChaCha8Rng::seed_from_u64(args.seed),
                args.count,
            )
        }
    };
    let bar = ProgressBar::new(rotations.len() as u64).with_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} images  {per_sec}  eta {eta}")
            .expect("static progress template"),
    );
    let frame = args.frame;
    let job = RenderJob {
        mesh: &mesh,
        symmetries: &symmetries,
        rotations: &rotations,
        size: args.size,
        units_mm: args.units_mm,
        split: &args.split,
        obj_id: args.obj_id,
        frame,
        seed: args.seed,
    };
    let started = std::time::Instant::now();
    render_dataset(&job, &args.out, |done| bar.set_position(done as u64))
        .with_context(|| format!("rendering into {}", args.out.display()))?;
    bar.finish_and_clear();
    eprintln!(
        "rendered {} images of {} ({} triangles, {}x{}) into {} in {:.1} s",
        rotations.len(),
        mesh.source,
        mesh.triangles.len(),
        args.size,
        args.size,
        args.out.display(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// Reads `qw,qx,qy,qz` rows; a first line that does not parse as numbers is a header.
fn read_rotations(path: &Path) -> Result<Vec<nalgebra::Rotation3<f64>>> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read --rotations {}", path.display()))?;
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        let fields: Result<Vec<f64>, _> =
            line.split(',').map(|f| f.trim().parse::<f64>()).collect();
        let fields = match fields {
            Ok(f) => f,
            Err(_) if n == 0 => continue,
            Err(e) => bail!("{}: line {}: {e} in '{line}'", path.display(), n + 1),
        };
        if fields.len() != 4 {
            bail!(
                "{}: line {}: expected 4 values qw,qx,qy,qz, found {}",
                path.display(),
                n + 1,
                fields.len()
            );
        }
        let q = [fields[0], fields[1], fields[2], fields[3]];
        out.push(
            alignist::so3::from_quaternion(q)
                .with_context(|| format!("{}: line {}", path.display(), n + 1))?,
        );
    }
    if out.is_empty() {
        bail!("{}: no rotations in the file", path.display());
    }
    Ok(out)
}

#[derive(clap::Args)]
struct ExpertsArgs {
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

fn experts_cmd(args: &ExpertsArgs) -> Result<()> {
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

#[derive(clap::Args)]
struct ScoreArgs {
    /// An expert set folder (from `alignist-train experts`).
    #[arg(long)]
    experts: PathBuf,
    /// The ground-truth rotation as qw,qx,qy,qz (default: --poses random ones).
    #[arg(long, allow_hyphen_values = true)]
    rotation: Option<String>,
    /// Random ground truths to report on when no --rotation is given.
    #[arg(long, default_value_t = 1)]
    poses: usize,
    /// Grid level (0 ..= 5).
    #[arg(long)]
    level: u8,
    /// Output CSV of the targets of the (first) ground truth: index,log_a_sdf,log_a_se.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Report the balance against this symmetry group (none, T, O, I, C<n>, D<n>, cone,
    /// cylinder): the target mass within --radius of each equivalent, min/max, the mass
    /// outside. The group is used for this report only.
    #[arg(long)]
    symmetry: Option<String>,
    /// Radius of the balance report in degrees.
    #[arg(long, default_value_t = 8.0)]
    radius: f64,
    /// Seed of the visible-point sampling and of the random ground truths.
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

fn parse_rotation(text: &str) -> Result<nalgebra::Rotation3<f64>> {
    let q: Vec<f64> = text
        .split(',')
        .map(|v| v.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("--rotation '{text}' is not four numbers qw,qx,qy,qz"))?;
    if q.len() != 4 {
        bail!("--rotation needs 4 values qw,qx,qy,qz, got {}", q.len());
    }
    alignist::so3::from_quaternion([q[0], q[1], q[2], q[3]]).context("--rotation")
}

fn write_targets_csv(out: &Path, targets: &alignist::experts::energy::LogTargets) -> Result<()> {
    let tmp = out.with_extension("csv.partial");
    let mut w = BufWriter::new(
        File::create(&tmp).with_context(|| format!("cannot create {}", tmp.display()))?,
    );
    let write_err = || format!("writing {}", tmp.display());
    writeln!(w, "index,log_a_sdf,log_a_se").with_context(write_err)?;
    for (i, (s, f)) in targets.log_a_sdf.iter().zip(&targets.log_a_se).enumerate() {
        writeln!(w, "{i},{s},{f}").with_context(write_err)?;
    }
    w.into_inner()
        .map_err(|e| e.into_error())
        .with_context(write_err)?;
    std::fs::rename(&tmp, out)
        .with_context(|| format!("renaming {} to {}", tmp.display(), out.display()))
}

fn score_cmd(args: &ScoreArgs) -> Result<()> {
    use alignist::bundle::experts::ExpertSet;
    use alignist::experts::select::visible_points_at;
    use alignist::so3::metrics::{MassNearEquivalents, mass_near_equivalents, softmax};
    use alignist::so3::{SymmetryGroup, equivalents, haar_rotation};
    use rand::SeedableRng;

    if args.level > 5 {
        bail!(
            "--level {} is above 5 (level 5 already has 2 359 296 cells)",
            args.level
        );
    }
    if args.out.is_none() && args.symmetry.is_none() {
        bail!("give --out FILE.csv, --symmetry GROUP (a balance report), or both");
    }
    if args.poses == 0 {
        bail!("--poses must be at least 1");
    }
    if !(args.radius > 0.0 && args.radius <= 90.0) {
        bail!("--radius must be in (0, 90] degrees, got {}", args.radius);
    }
    let group: Option<SymmetryGroup> = args
        .symmetry
        .as_deref()
        .map(str::parse)
        .transpose()
        .context("--symmetry")?;
    let rotations = match &args.rotation {
        Some(text) => vec![parse_rotation(text)?],
        None => {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(args.seed);
            (0..args.poses).map(|_| haar_rotation(&mut rng)).collect()
        }
    };
    let set = ExpertSet::load(&args.experts)
        .with_context(|| format!("loading --experts {}", args.experts.display()))?;
    let baked = set.bake();
    let grid = GridLevel::new(args.level)?;
    let cells = grid.matrices_f32();
    let centres = group.map(|_| grid.quaternions());
    let mut reports: Vec<[MassNearEquivalents; 3]> = Vec::new();
    for (k, r_gt) in rotations.iter().enumerate() {
        let x0 = visible_points_at(&set.mesh, r_gt, args.seed.wrapping_add(k as u64));
        if x0.is_empty() {
            bail!("the object is not visible at rotation {k}");
        }
        let targets = baked.log_targets(r_gt, &x0, &cells);
        if k == 0
            && let Some(out) = &args.out
        {
            write_targets_csv(out, &targets)?;
            eprintln!(
                "wrote {} cells of level {} to {}",
                grid.len(),
                args.level,
                out.display()
            );
        }
        if let (Some(group), Some(centres)) = (group, &centres) {
            let eq = equivalents(r_gt, &group.rotations());
            let combined: Vec<f32> = targets
                .log_a_sdf
                .iter()
                .zip(&targets.log_a_se)
                .map(|(a, b)| a + b)
                .collect();
            let report = |w: &[f32]| -> Result<MassNearEquivalents> {
                Ok(mass_near_equivalents(
                    &softmax(&grid, w)?,
                    centres,
                    &eq,
                    args.radius,
                ))
            };
            reports.push([
                report(&combined)?,
                report(&targets.log_a_sdf)?,
                report(&targets.log_a_se)?,
            ]);
        }
    }
    if let Some(group) = group {
        println!(
            "balance against {group} ({} equivalents), level {}, radius {}°, {} ground truth(s):",
            group.order(),
            args.level,
            args.radius,
            reports.len()
        );
        println!("| targets | mass inside | mass outside | min/max | min | max |");
        println!("|---|---|---|---|---|---|");
        for (j, name) in ["both experts", "SDF expert", "feature expert"]
            .iter()
            .enumerate()
        {
            let n = reports.len() as f64;
            let mean = |f: &dyn Fn(&MassNearEquivalents) -> f64| {
                reports.iter().map(|r| f(&r[j])).sum::<f64>() / n
            };
            let fold = |init: f64, pick: fn(f64, f64) -> f64| {
                move |m: &MassNearEquivalents| m.per_equivalent.iter().cloned().fold(init, pick)
            };
            println!(
                "| {name} | {:.3} | {:.3} | {:.3} | {:.4} | {:.4} |",
                mean(&|m| m.inside),
                mean(&|m| m.outside),
                mean(&|m| m.balance),
                mean(&fold(f64::INFINITY, f64::min)),
                mean(&fold(0.0, f64::max)),
            );
        }
    }
    Ok(())
}

#[derive(clap::Args)]
struct FitArgs {
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
    /// Supersampling per axis of fresh renders (anti-aliasing).
    #[arg(long, default_value_t = 4)]
    supersample: u32,
    /// Seed of the fresh evaluation renders (keep it apart from training seeds).
    #[arg(long, default_value_t = 1 << 40)]
    eval_seed: u64,
    /// Print the time per step in each stage at the end.
    #[arg(long)]
    profile: bool,
    /// Output bundle folder (e.g. models/symsol1).
    #[arg(long)]
    out: PathBuf,
    /// alignist (GKL from the experts, both branches) or ipdf (the baseline).
    #[arg(long, default_value = "alignist")]
    method: String,
    /// Measure loss of the alignist method: gkl or l1.
    #[arg(long, default_value = "gkl")]
    loss: String,
    /// Sampling of the alignist method: modes (mode-focused) or random (uniform).
    #[arg(long, default_value = "modes")]
    sampling: String,
    /// Encoder layout: tiny, resnet18, resnet50.
    #[arg(long, default_value = "tiny")]
    layout: String,
    /// Rotation encoding: cube or ipdf.
    #[arg(long, default_value = "cube")]
    encoding: String,
    /// Crop side in pixels.
    #[arg(long, default_value_t = 64)]
    image_size: u32,
    /// Adam steps.
    #[arg(long, default_value_t = 1000)]
    steps: usize,
    /// Images per step.
    #[arg(long, default_value_t = 8)]
    batch: usize,
    /// Rotations per image (the paper: 4096).
    #[arg(long, default_value_t = 256)]
    k: usize,
    /// Peak learning rate.
    #[arg(long, default_value_t = 1e-3)]
    lr: f64,
    /// Fraction of each training split used (the paper's low-data regime: 0.1).
    #[arg(long, default_value_t = 1.0)]
    fraction: f64,
    /// Seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Checkpoint folder (default: <out>.checkpoints).
    #[arg(long)]
    checkpoints: Option<PathBuf>,
    /// Steps between checkpoints.
    #[arg(long, default_value_t = 100)]
    checkpoint_every: usize,
    /// Continue from the last checkpoint.
    #[arg(long)]
    resume: bool,
    /// Grid level of the evaluation.
    #[arg(long, default_value_t = 4)]
    eval_level: u8,
    /// Test images per object in the evaluation (0 skips it).
    #[arg(long, default_value_t = 50)]
    eval_images: usize,
}

fn parse_layout(s: &str) -> Result<alignist::net::ResNetLayout> {
    use alignist::net::ResNetLayout;
    Ok(match s {
        "tiny" => ResNetLayout::Tiny,
        "resnet18" => ResNetLayout::Resnet18,
        "resnet50" => ResNetLayout::Resnet50,
        _ => bail!("--layout must be tiny, resnet18 or resnet50, got '{s}'"),
    })
}

/// What `fit` trains and evaluates on.
struct FitData {
    objects: Vec<alignist::bundle::model::BundleObject>,
    sets: Vec<alignist::bundle::experts::ExpertSet>,
    images: Vec<alignist::train::TrainingImage>,
    tests: Vec<alignist::train::eval::EvalImage>,
    fresh: Option<alignist::train::data::FreshRenders>,
}

/// Training and test images from `--data` BOP datasets.
fn dataset_fit_data(args: &FitArgs) -> Result<FitData> {
    use alignist::bundle::experts::ExpertSet;
    use alignist::bundle::model::BundleObject;
    use alignist::data::BopDataset;
    use alignist::train::data::{eval_images, training_images};

    let mut data_out = FitData {
        objects: Vec::new(),
        sets: Vec::new(),
        images: Vec::new(),
        tests: Vec::new(),
        fresh: None,
    };
    for (i, (data, experts)) in args.data.iter().zip(&args.experts).enumerate() {
        let set =
            ExpertSet::load(experts).with_context(|| format!("--experts {}", experts.display()))?;
        let train_ds = BopDataset::open(data, "train")
            .with_context(|| format!("--data {}", data.display()))?;
        let imgs = training_images(&train_ds, i, &set.mesh, args.image_size, args.fraction)
            .with_context(|| format!("reading --data {}", data.display()))?;
        let name = set.manifest.object.name.clone();
        eprintln!(
            "{name}: {} training images from {}",
            imgs.len(),
            data.display()
        );
        data_out.objects.push(BundleObject {
            name: name.clone(),
            experts: format!("experts/{name}"),
            data: data.display().to_string(),
            train_images: imgs.len(),
        });
        data_out.images.extend(imgs);
        if args.eval_images > 0 {
            let test_ds = BopDataset::open(data, "test")
                .with_context(|| format!("--data {} (test split)", data.display()))?;
            data_out.tests.extend(eval_images(
                &test_ds,
                &name,
                args.image_size,
                args.eval_images,
            )?);
        }
        data_out.sets.push(set);
    }
    Ok(data_out)
}

/// Fresh renders of the experts' meshes, and `--eval-images` fresh test crops per object from
/// `--eval-seed`.
fn fresh_fit_data(args: &FitArgs) -> Result<FitData> {
    use alignist::bundle::experts::ExpertSet;
    use alignist::bundle::model::BundleObject;
    use alignist::train::data::FreshRenders;

    if !(1..=8).contains(&args.supersample) {
        bail!("--supersample must be in 1 ..= 8, got {}", args.supersample);
    }
    let sets = args
        .experts
        .iter()
        .map(|e| ExpertSet::load(e).with_context(|| format!("--experts {}", e.display())))
        .collect::<Result<Vec<_>>>()?;
    let fresh = FreshRenders {
        meshes: sets.iter().map(|s| s.mesh.clone()).collect(),
        supersample: args.supersample,
    };
    let names: Vec<String> = sets
        .iter()
        .map(|s| s.manifest.object.name.clone())
        .collect();
    let symmetries: Vec<_> = sets.iter().map(|s| s.symmetries()).collect();
    let tests = fresh.eval_images(
        &names,
        &symmetries,
        args.image_size,
        args.eval_images,
        args.eval_seed,
    );
    let objects = names
        .iter()
        .map(|name| BundleObject {
            name: name.clone(),
            experts: format!("experts/{name}"),
            data: format!("fresh renders ({}x supersampled)", args.supersample),
            train_images: 0,
        })
        .collect();
    eprintln!(
        "{} objects, fresh renders every step; {} fresh test crops (seed {})",
        sets.len(),
        tests.len(),
        args.eval_seed
    );
    Ok(FitData {
        objects,
        sets,
        images: Vec::new(),
        tests,
        fresh: Some(fresh),
    })
}

fn fit_cmd(args: &FitArgs) -> Result<()> {
    use alignist::bundle::model::{
        GridLevels, MODEL_FORMAT_VERSION, ModelBundle, ModelManifest, Provenance,
    };
    use alignist::encoding::RotationEncoding;
    use alignist::train::eval::evaluate;
    use alignist::train::{
        MeasureLoss, Method, NetworkConfig, SamplingStrategy, TrainConfig, TrainingSet, train,
    };

    if !args.fresh && args.data.len() != args.experts.len() {
        bail!(
            "give one --experts per --data ({} --data, {} --experts)",
            args.data.len(),
            args.experts.len()
        );
    }
    if !(args.fraction > 0.0 && args.fraction <= 1.0) {
        bail!("--fraction must be in (0, 1], got {}", args.fraction);
    }
    if args.image_size < 16 || !args.image_size.is_multiple_of(8) {
        bail!(
            "--image-size must be a multiple of 8 and at least 16, got {}",
            args.image_size
        );
    }
    if args.eval_level > 5 {
        bail!("--eval-level {} is above 5", args.eval_level);
    }
    for (flag, v) in [
        ("--steps", args.steps),
        ("--batch", args.batch),
        ("--k", args.k),
    ] {
        if v == 0 {
            bail!("{flag} must be at least 1");
        }
    }
    let method = match args.method.as_str() {
        "alignist" => Method::Alignist {
            loss: match args.loss.as_str() {
                "gkl" => MeasureLoss::Gkl,
                "l1" => MeasureLoss::L1,
                other => bail!("--loss must be gkl or l1, got '{other}'"),
            },
            sampling: match args.sampling.as_str() {
                "modes" => SamplingStrategy::mode_focused(args.k),
                "random" => SamplingStrategy::Uniform,
                other => bail!("--sampling must be modes or random, got '{other}'"),
            },
        },
        "ipdf" => Method::Ipdf,
        other => bail!("--method must be alignist or ipdf, got '{other}'"),
    };
    let encoding = match args.encoding.as_str() {
        "cube" => RotationEncoding::Cube,
        "ipdf" => RotationEncoding::Ipdf { frequencies: 3 },
        other => bail!("--encoding must be cube or ipdf, got '{other}'"),
    };
    let network =
        NetworkConfig::new(parse_layout(&args.layout)?, encoding).with_image_size(args.image_size);
    let FitData {
        objects,
        sets,
        images,
        tests,
        fresh,
    } = if args.fresh {
        fresh_fit_data(args)?
    } else {
        dataset_fit_data(args)?
    };
    let baked: Vec<_> = sets.iter().map(|s| s.bake()).collect();
    let modes = sets
        .iter()
        .zip(&baked)
        .map(|(s, b)| s.mode_table(b))
        .collect::<Result<Vec<_>, _>>()
        .context("building the mode tables")?;
    let training = TrainingSet {
        objects: baked,
        modes,
        images,
        fresh,
    };
    let config = TrainConfig {
        network: network.clone(),
        method,
        steps: args.steps,
        batch: args.batch,
        k: args.k,
        lr: args.lr,
        warmup: (args.steps / 20).max(1),
        seed: args.seed,
        checkpoint_every: args.checkpoint_every,
    };
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
    let (trained, report) = train(
        &config,
        &training,
        Some(&checkpoints),
        args.resume,
        |step, steps, loss| {
            bar.set_position(step as u64);
            bar.set_message(format!("loss {loss:.4}"));
            log_progress(&mut log, step, steps, loss);
            std::ops::ControlFlow::Continue(())
        },
    )
    .context("training")?;
    bar.finish();
    if args.profile {
        print_profile(&report.profile);
    }
    let evaluation = if tests.is_empty() {
        None
    } else {
        let bar = ProgressBar::new(tests.len() as u64);
        let r = evaluate(&trained, &network, &tests, args.eval_level, |n| {
            bar.set_position(n as u64)
        })?;
        bar.finish_and_clear();
        Some(r)
    };
    let mut manifest = ModelManifest {
        format_version: MODEL_FORMAT_VERSION,
        name: args
            .out
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or("model")
            .to_string(),
        network,
        input: "RGB crop centred on the object, side image_size, values / 255".into(),
        objects,
        levels: GridLevels {
            full_max: 4,
            search_max: 5,
        },
        provenance: Provenance {
            command: std::env::args().collect::<Vec<_>>().join(" "),
            train: config,
            report: report.clone(),
        },
        evaluation: evaluation.clone(),
        files: Default::default(),
    };
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

fn print_eval(e: &alignist::train::eval::EvalReport) {
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
            "  {name:8} LL {:6.2}  spread {:6.1}°  AR@30 {:.3} (chance {:.3})  median {:6.1}°  ({} images)",
            m.log_likelihood,
            m.spread_deg,
            m.accuracy_at.first().map_or(f64::NAN, |a| a.1),
            chance,
            m.median_error_deg,
            m.images
        );
    }
    eprintln!(
        "  (uniform, the best image-independent answer for Haar-random poses: LL 0; LL ceiling {:.2})",
        e.ll_ceiling
    );
}

#[derive(clap::Args)]
struct EvalArgs {
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
    #[arg(long, default_value_t = 1 << 40)]
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
}

fn eval_cmd(args: &EvalArgs) -> Result<()> {
    use alignist::bundle::model::ModelBundle;
    use alignist::data::BopDataset;
    use alignist::train::data::eval_images;
    use alignist::train::eval::evaluate;

    if args.level > 5 {
        bail!("--level {} is above 5", args.level);
    }
    let bundle = ModelBundle::load(&args.model)
        .with_context(|| format!("loading --model {}", args.model.display()))?;
    let size = bundle.manifest.network.image_size;
    let mut tests = Vec::new();
    if args.fresh {
        if !(1..=8).contains(&args.supersample) {
            bail!("--supersample must be in 1 ..= 8, got {}", args.supersample);
        }
        let fresh = alignist::train::data::FreshRenders {
            meshes: bundle.experts.iter().map(|s| s.mesh.clone()).collect(),
            supersample: args.supersample,
        };
        let names: Vec<String> = bundle
            .manifest
            .objects
            .iter()
            .map(|o| o.name.clone())
            .collect();
        let symmetries: Vec<_> = bundle.experts.iter().map(|s| s.symmetries()).collect();
        tests = fresh.eval_images(&names, &symmetries, size, args.images, args.seed);
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
        tests.extend(eval_images(&ds, name, size, args.images)?);
    }
    let bar = ProgressBar::new(tests.len() as u64);
    let report = evaluate(
        &bundle.network,
        &bundle.manifest.network,
        &tests,
        args.level,
        |n| bar.set_position(n as u64),
    )?;
    bar.finish_and_clear();
    let text = serde_json::to_string_pretty(&report)?;
    std::fs::write(&args.out, text).with_context(|| format!("writing {}", args.out.display()))?;
    print_eval(&report);
    Ok(())
}

fn bench_cmd(bundle: &Path, count: usize) -> Result<()> {
    let loaded = alignist::bundle::model::ModelBundle::load(bundle)
        .with_context(|| format!("--model {}", bundle.display()))?;
    let size = loaded.manifest.network.image_size;
    let mesh = &loaded.experts[0].mesh;
    let camera = alignist::cad::Camera::square(size);
    let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(99);
    let images: Vec<Vec<u8>> = alignist::so3::haar_rotations(&mut rng, count.max(1))
        .into_iter()
        .map(|r| {
            let rgb = alignist::cad::render(
                mesh,
                &camera,
                &alignist::data::symsol_pose(r),
                &alignist::cad::RenderOptions::default(),
            )
            .rgb;
            let mut png = Vec::new();
            image::RgbImage::from_raw(size, size, rgb)
                .context("render size")?
                .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)?;
            Ok(png)
        })
        .collect::<Result<_>>()?;
    drop(loaded);
    alignist::serve::bench::bench(bundle, &images)
}

fn write_grid(level: u8, out: &Path) -> Result<()> {
    if level > MAX_LEVEL {
        bail!(
            "--level {level} is above the maximum grid level {MAX_LEVEL} \
             (level {MAX_LEVEL} already has {} cells)",
            72u64 * 8u64.pow(MAX_LEVEL as u32)
        );
    }
    let grid = GridLevel::new(level).context("building the grid")?;
    let tmp = out.with_extension("csv.partial");
    let file = File::create(&tmp)
        .with_context(|| format!("cannot create the output file {}", tmp.display()))?;
    let mut w = BufWriter::new(file);
    let bar = ProgressBar::new(grid.len() as u64).with_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} cells  {per_sec}  eta {eta}")
            .expect("static progress template"),
    );
    let write_err = || format!("writing {}", tmp.display());
    writeln!(w, "index,qw,qx,qy,qz").with_context(write_err)?;
    for i in 0..grid.len() as u64 {
        let q = to_quaternion(&grid.rotation(i));
        writeln!(w, "{i},{:.9},{:.9},{:.9},{:.9}", q[0], q[1], q[2], q[3])
            .with_context(write_err)?;
        if i % 65_536 == 0 {
            bar.set_position(i);
        }
    }
    let file = w
        .into_inner()
        .map_err(|e| e.into_error())
        .with_context(write_err)?;
    file.sync_all().with_context(write_err)?;
    std::fs::rename(&tmp, out)
        .with_context(|| format!("renaming {} to {}", tmp.display(), out.display()))?;
    bar.finish_and_clear();
    eprintln!(
        "wrote {} cells of level {level} to {}",
        grid.len(),
        out.display()
    );
    Ok(())
}

/// Progress lines for logs (a bar is drawn only on a terminal): every 2 % of the run or every
/// 60 s, with the loss, the rate and the time left.
struct ProgressLog {
    started: std::time::Instant,
    last: std::time::Instant,
    first_step: Option<usize>,
    on_terminal: bool,
}

impl ProgressLog {
    fn new() -> Self {
        use std::io::IsTerminal;
        let now = std::time::Instant::now();
        ProgressLog {
            started: now,
            last: now,
            first_step: None,
            on_terminal: std::io::stderr().is_terminal(),
        }
    }
}

fn log_progress(log: &mut ProgressLog, step: usize, steps: usize, loss: f64) {
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
        "step {step}/{steps}  loss {loss:.4}  {:.0} ms/step  elapsed {:.0} s  left {:.0} s",
        per_step * 1e3,
        elapsed,
        per_step * (steps - step) as f64
    );
}

fn print_profile(p: &alignist::train::trainer::StepProfile) {
    println!("step profile (ms per step, mean of {} steps):", p.steps);
    for (name, v) in [
        ("data", p.data),
        ("sampling", p.sampling),
        ("targets", p.targets),
        ("encoder forward", p.encoder_forward),
        ("head forward + loss", p.head_forward),
        ("backward", p.backward),
        ("optimiser", p.optimiser),
    ] {
        println!(
            "  {name:<20} {v:8.1}  {:5.1} %",
            100.0 * v / p.total.max(1e-9)
        );
    }
    println!(
        "  {:<20} {:8.1}  (stages sum {:.1}; supervision = sampling + targets = {:.1} %)",
        "step",
        p.total,
        p.stages(),
        100.0 * (p.sampling + p.targets) / p.total.max(1e-9)
    );
}
