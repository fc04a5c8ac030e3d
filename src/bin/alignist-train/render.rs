//! `alignist-train render`: datasets in BOP layout.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};

use crate::object::ObjectArgs;

#[derive(clap::Args)]
pub(crate) struct RenderArgs {
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

pub(crate) fn parse_frame(s: &str) -> std::result::Result<(u32, u32), String> {
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

pub(crate) fn render_cmd(args: &RenderArgs) -> Result<()> {
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
pub(crate) fn read_rotations(path: &Path) -> Result<Vec<nalgebra::Rotation3<f64>>> {
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
