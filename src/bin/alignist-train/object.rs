//! The object a command works on: a SYMSOL shape or a mesh file.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};

/// The object a command works on: a SYMSOL shape or a mesh file.
#[derive(clap::Args)]
#[command(group(clap::ArgGroup::new("object").required(true).args(["shape", "mesh"])))]
pub(crate) struct ObjectArgs {
    /// A SYMSOL shape: tet, cube, icosa, cone, cyl, tetX, cylO, sphereX.
    #[arg(long)]
    shape: Option<String>,
    /// A mesh file (.obj, .ply, .stl, .gltf, .glb); it is normalised to NOCS.
    #[arg(long)]
    mesh: Option<PathBuf>,
    /// Symmetry group of --mesh (none, T, O, I, C<n>, D<n>, cone, cylinder), when known; the
    /// experts discover it either way and the manifest reports both.
    #[arg(long, default_value = "none", requires = "mesh")]
    symmetry: String,
    /// Unit of --mesh's coordinates: m, mm, or auto (a bounding-sphere radius above 2 is taken
    /// for millimetres). Recorded in the manifest with the mesh frame.
    #[arg(long, default_value = "auto", requires = "mesh")]
    units: String,
}

impl ObjectArgs {
    /// The object's name, its mesh in NOCS with the normalisation, and its symmetries.
    pub(crate) fn resolve(
        &self,
    ) -> Result<(
        String,
        alignist::cad::Mesh,
        alignist::cad::Normalisation,
        Vec<nalgebra::Rotation3<f64>>,
    )> {
        use alignist::cad::Shape;
        use alignist::so3::SymmetryGroup;
        match (&self.shape, &self.mesh) {
            (Some(name), _) => {
                let shape: Shape = name.parse().context("--shape")?;
                let (mesh, normalisation) = shape.mesh().normalised();
                Ok((
                    shape.name().to_string(),
                    mesh,
                    normalisation,
                    shape.symmetries(),
                ))
            }
            (None, Some(path)) => {
                let group: SymmetryGroup = self.symmetry.parse().context("--symmetry")?;
                let units = parse_units(&self.units)?;
                let (name, mesh, normalisation) = alignist::cad::load_part(path, units)
                    .with_context(|| format!("--mesh {}", path.display()))?;
                Ok((name, mesh, normalisation, group.rotations()))
            }
            (None, None) => bail!("give --shape NAME or --mesh FILE"),
        }
    }
}

/// `--units`: `auto` (`None`, guessed from the part's size), `m` or `mm`.
pub(crate) fn parse_units(s: &str) -> Result<Option<alignist::cad::LengthUnit>> {
    match s {
        "auto" => Ok(None),
        other => other
            .parse()
            .map(Some)
            .map_err(|e: String| anyhow::anyhow!("--units: {e} or auto")),
    }
}
