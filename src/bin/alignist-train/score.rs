//! `alignist-train score`: the experts' targets on a grid level, and their balance.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

use alignist::so3::GridLevel;

#[derive(clap::Args)]
pub(crate) struct ScoreArgs {
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

pub(crate) fn parse_rotation(text: &str) -> Result<nalgebra::Rotation3<f64>> {
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

pub(crate) fn write_targets_csv(
    out: &Path,
    targets: &alignist::experts::energy::LogTargets,
) -> Result<()> {
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

pub(crate) fn score_cmd(args: &ScoreArgs) -> Result<()> {
    use alignist::bundle::experts::ExpertSet;
    use alignist::experts::select::visible_points_at;
    use alignist::so3::metrics::{MassNearEquivalents, mass_near_equivalents, softmax};
    use alignist::so3::{SymmetryGroup, equivalents, haar_rotation};
    use rand::SeedableRng;

    if args.level > alignist::train::eval::MAX_EVAL_LEVEL {
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
            let combined = targets.combined();
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
        print_balance(group, args, &reports);
    }
    Ok(())
}

/// The balance table: the mass inside and outside `--radius` of the equivalents, and how evenly
/// it is shared among them, per expert, averaged over the ground truths.
fn print_balance(
    group: alignist::so3::SymmetryGroup,
    args: &ScoreArgs,
    reports: &[[alignist::so3::metrics::MassNearEquivalents; 3]],
) {
    use alignist::so3::metrics::MassNearEquivalents;
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
