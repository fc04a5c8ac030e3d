//! `alignist-train symmetry`: the symmetry of a part, discovered from its SDF.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};

use alignist::experts::symmetry::{DiscoveredSymmetry, DiscoveryConfig};

#[derive(clap::Args)]
pub(crate) struct SymmetryArgs {
    /// A mesh file (.obj, .ply, .stl, .gltf, .glb; closed): its exact SDF, centred on its surface centroid.
    #[arg(long, conflicts_with = "experts")]
    mesh: Option<PathBuf>,
    /// An expert set: its baked SDF expert, with its mode table's cells as extra candidates.
    #[arg(long)]
    experts: Option<PathBuf>,
    /// Print the report as JSON (the manifest's `symmetry` record).
    #[arg(long)]
    json: bool,
    /// How far (NOCS units, radius 1) a symmetry's mean surface distance may exceed the
    /// identity's.
    #[arg(long, default_value_t = DiscoveryConfig::default().tolerance)]
    tolerance: f64,
    /// The same for a near-symmetry.
    #[arg(long, default_value_t = DiscoveryConfig::default().near_tolerance)]
    near_tolerance: f64,
}

pub(crate) fn symmetry_cmd(args: &SymmetryArgs) -> Result<()> {
    if !(args.tolerance > 0.0 && args.tolerance < args.near_tolerance && args.near_tolerance < 0.5)
    {
        bail!(
            "need 0 < --tolerance ({}) < --near-tolerance ({}) < 0.5",
            args.tolerance,
            args.near_tolerance
        );
    }
    let config = DiscoveryConfig {
        tolerance: args.tolerance,
        near_tolerance: args.near_tolerance,
        ..DiscoveryConfig::default()
    };
    let found = match (&args.mesh, &args.experts) {
        (Some(path), _) => {
            let (_, mesh, _) = alignist::cad::load_part(path, None)
                .with_context(|| format!("--mesh {}", path.display()))?;
            alignist::experts::symmetry::mesh_symmetry(&mesh, &config)
                .with_context(|| format!("--mesh {}", path.display()))?
        }
        (None, Some(dir)) => {
            let set = alignist::bundle::experts::ExpertSet::load(dir)
                .with_context(|| format!("--experts {}", dir.display()))?;
            let baked = set.bake();
            let extra = match &set.modes {
                Some(t) => t.centres().context("the mode table")?,
                None => Vec::new(),
            };
            alignist::experts::symmetry::discover_symmetry(
                &|p| baked.sdf.sample(p),
                &set.mesh,
                &extra,
                &config,
            )?
        }
        (None, None) => bail!("give --mesh FILE or --experts DIR"),
    };
    if args.json {
        println!("{}", serde_json::to_string_pretty(&found)?);
    } else {
        println!("{}", describe(&found));
    }
    Ok(())
}

/// The report in a line.
pub(crate) fn describe(d: &DiscoveredSymmetry) -> String {
    let axes = match d.axes.as_slice() {
        [] => String::new(),
        [a] => format!(" about ({:+.3}, {:+.3}, {:+.3})", a[0], a[1], a[2]),
        [a, ..] => format!(
            " ({} axes of highest order, e.g. ({:+.3}, {:+.3}, {:+.3}))",
            d.axes.len(),
            a[0],
            a[1],
            a[2]
        ),
    };
    let near = d.near.as_ref().map_or_else(String::new, |n| {
        format!(
            "; nearly {} (residual {:.4} above the identity's)",
            n.label, n.residual
        )
    });
    format!(
        "symmetry {}{axes}, confidence {:.2}, {} rotations found (SDF residual at the identity \
         {:.4}){near}",
        d.label, d.confidence, d.rotations, d.baseline
    )
}
