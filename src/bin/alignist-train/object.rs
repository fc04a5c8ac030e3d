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
    /// A mesh file (.obj, .ply, .stl); it is normalised to NOCS.
    #[arg(long)]
    mesh: Option<PathBuf>,
    /// Symmetry group of --mesh (none, T, O, I, C<n>, D<n>, cone, cylinder).
    #[arg(long, default_value = "none", requires = "mesh")]
    symmetry: String,
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
