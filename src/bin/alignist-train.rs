//! `alignist-train`: the offline side of alignist — grids, renders, experts, training, evaluation.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};

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
    /// Train the CAD experts of an object (not yet implemented).
    Experts,
    /// Score a target distribution with trained experts (not yet implemented).
    Score,
    /// Train a distribution network and write a model bundle (not yet implemented).
    Fit,
    /// Evaluate a model bundle on a dataset (not yet implemented).
    Eval,
    /// Print performance figures (not yet implemented).
    Bench,
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Grid { level, out } => write_grid(level, &out),
        Command::Render(args) => render_cmd(&args),
        Command::Experts => not_yet("experts"),
        Command::Score => not_yet("score"),
        Command::Fit => not_yet("fit"),
        Command::Eval => not_yet("eval"),
        Command::Bench => not_yet("bench"),
    }
}

#[derive(clap::Args)]
#[command(group(clap::ArgGroup::new("object").required(true).args(["shape", "mesh"])))]
struct RenderArgs {
    /// A SYMSOL shape: tet, cube, icosa, cone, cyl, tetX, cylO, sphereX.
    #[arg(long)]
    shape: Option<String>,
    /// A mesh file (.obj, .ply, .stl); it is normalised to NOCS.
    #[arg(long)]
    mesh: Option<PathBuf>,
    /// Symmetry group of --mesh (none, T, O, I, C<n>, D<n>, cone, cylinder).
    #[arg(long, default_value = "none", requires = "mesh")]
    symmetry: String,
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
}

fn render_cmd(args: &RenderArgs) -> Result<()> {
    use alignist::cad::{Mesh, Shape};
    use alignist::data::{RenderJob, render_dataset};
    use alignist::so3::{SymmetryGroup, haar_rotations};
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
    let (mesh, symmetries) = match (&args.shape, &args.mesh) {
        (Some(name), _) => {
            let shape: Shape = name.parse().context("--shape")?;
            (shape.mesh(), shape.symmetries())
        }
        (None, Some(path)) => {
            let group: SymmetryGroup = args.symmetry.parse().context("--symmetry")?;
            let mesh = Mesh::load(path).with_context(|| format!("--mesh {}", path.display()))?;
            (mesh.normalised().0, group.rotations())
        }
        (None, None) => bail!("give --shape NAME or --mesh FILE"),
    };
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
    let job = RenderJob {
        mesh: &mesh,
        symmetries: &symmetries,
        rotations: &rotations,
        size: args.size,
        units_mm: args.units_mm,
        split: &args.split,
        obj_id: args.obj_id,
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

fn not_yet(name: &str) -> Result<()> {
    bail!("`alignist-train {name}` is not implemented yet")
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
