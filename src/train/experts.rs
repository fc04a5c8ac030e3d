//! Training an object's expert set (paper Sec. 3.2): both experts fitted to the mesh, baked
//! into voxel grids, the energies' λs chosen by the width criterion, and the mode table built.
//! The result is an [`ExpertSet`], written by its format module (`bundle::experts`).

use std::collections::BTreeMap;

use nalgebra::Rotation3;

use crate::bundle::experts::{
    BakeInfo, EXPERTS_FORMAT_VERSION, ExpertSet, ExpertsManifest, FeatureSection, ObjectInfo,
    SdfSection, bake_experts, symmetries_row_major,
};
use crate::cad::{Mesh, Normalisation};
use crate::experts::energy::{BakedExperts, EnergyParams};
use crate::experts::feature::{FEATURE_DIM, FeatureTrainConfig};
use crate::experts::modes::{ModeTable, ModeTableConfig};
use crate::experts::run_batched;
use crate::experts::sdf::SdfTrainConfig;
use crate::experts::select::WidthCriterion;
use crate::experts::symmetry::{DiscoveryConfig, discover_symmetry};

/// The voxel bake resolution per axis of `alignist-train experts` (64³ cells over ±1.05).
pub const DEFAULT_BAKE_RESOLUTION: usize = 64;

/// What [`train_expert_set`] needs besides the mesh.
pub struct ExpertsJob {
    /// Object name.
    pub name: String,
    /// The mesh in NOCS.
    pub mesh: Mesh,
    /// How the source mesh was normalised.
    pub normalisation: Normalisation,
    /// The object's symmetries (identity first).
    pub symmetries: Vec<Rotation3<f64>>,
    /// SDF expert training.
    pub sdf: SdfTrainConfig,
    /// Feature expert training.
    pub features: FeatureTrainConfig,
    /// Voxel bake resolution and bound.
    pub bake_resolution: usize,
    /// The energies' norms and ε (their λs are chosen by `width`).
    pub energy: EnergyParams,
    /// The width criterion that chooses λ_SDF and λ_SE.
    pub width: WidthCriterion,
    /// How the mode table is built.
    pub modes: ModeTableConfig,
    /// The command line, for the manifest.
    pub command: String,
}

/// Progress of [`train_expert_set`]: `(phase, step, steps, loss)`.
pub type ExpertsProgress<'a> = dyn FnMut(&str, usize, usize, f64) + 'a;

/// The bake's error against the networks: the SDF's mean absolute error on 5 000 points near the
/// surface, and the keys' mean distance on 5 000 surface points relative to the mean distance
/// between the keys of two unrelated points.
fn bake_errors(
    mesh: &Mesh,
    sdf: &crate::experts::Siren,
    keys: &crate::experts::Siren,
    baked: &BakedExperts,
    seed: u64,
    device: &burn::tensor::Device,
) -> (f64, f64) {
    use crate::experts::sdf::{eval_sdf, sample_near_surface};
    use rand::SeedableRng;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0xba4e);
    let near = sample_near_surface(mesh, 5000, &mut rng);
    let sdf_mean_error = crate::experts::mean_abs_difference(
        &eval_sdf(sdf, &near, device),
        &baked.sdf.sample(&near),
    );
    let surface = mesh.sample_surface_points(5000, &mut rng);
    let others = mesh.sample_surface_points(5000, &mut rng);
    let key_net = run_batched(keys, &surface, FEATURE_DIM, device);
    let key_other = run_batched(keys, &others, FEATURE_DIM, device);
    let key_baked = baked.keys.sample(&surface);
    let mean_dist =
        |a: &[f32], b: &[f32]| crate::experts::energy::mean_key_distance(a, b, FEATURE_DIM);
    let key_scale = mean_dist(&key_net, &key_other).max(1e-9);
    (sdf_mean_error, mean_dist(&key_net, &key_baked) / key_scale)
}

/// Trains both experts, bakes them, measures the bakes' error, selects λ_SDF and λ_SE by the
/// width criterion and builds the mode table. `job.symmetries` are only written to the manifest
/// and used for the feature expert's reported symmetry ratio.
pub fn train_expert_set(
    job: ExpertsJob,
    progress: &mut ExpertsProgress<'_>,
) -> Result<ExpertSet, crate::experts::ExpertError> {
    use crate::experts::feature::train_features;
    use crate::experts::sdf::train_sdf;
    use crate::experts::select::select_by_width;

    let device = crate::backend::device();
    let sdf_steps = job.sdf.steps;
    let (sdf, sdf_fit) = train_sdf(&job.mesh, &job.sdf, |s, l| progress("sdf", s, sdf_steps, l))?;
    let feat_steps = job.features.steps;
    let (features, feature_fit) =
        train_features(&job.mesh, &job.symmetries, &job.features, |s, l| {
            progress("features", s, feat_steps, l)
        })?;
    progress("bake", 0, 1, 0.0);
    let bound = 1.05f32;
    let baked = bake_experts(
        &sdf,
        &features.keys,
        job.bake_resolution,
        bound,
        job.energy,
        &device,
    );
    let (sdf_mean_error, keys_relative_error) = bake_errors(
        &job.mesh,
        &sdf,
        &features.keys,
        &baked,
        job.sdf.seed,
        &device,
    );
    progress("select", 0, 1, 0.0);
    let baked = BakedExperts {
        params: job.energy,
        ..baked
    };
    let (energy, selection) = select_by_width(&baked, &job.mesh, &job.width);
    progress("modes", 0, 1, 0.0);
    let baked = BakedExperts {
        params: energy,
        ..baked
    };
    let modes = ModeTable::build(&baked, &job.mesh, &job.modes)?;
    progress("symmetry", 0, 1, 0.0);
    let symmetry = discover_symmetry(
        &|p| baked.sdf.sample(p),
        &job.mesh,
        &modes.centres()?,
        &DiscoveryConfig {
            seed: job.sdf.seed,
            ..DiscoveryConfig::default()
        },
    )?;
    Ok(ExpertSet {
        manifest: ExpertsManifest {
            format_version: EXPERTS_FORMAT_VERSION,
            object: ObjectInfo {
                name: job.name,
                source: job.mesh.source.clone(),
                mesh_sha256: String::new(),
                normalisation: job.normalisation,
                // Declared symmetries, or else the discovered ones (for evaluation and reports).
                symmetries: if job.symmetries.len() > 1 {
                    symmetries_row_major(&job.symmetries)
                } else {
                    symmetry.found.clone()
                },
            },
            sdf: SdfSection {
                config: job.sdf,
                fit: sdf_fit,
            },
            features: FeatureSection {
                config: job.features,
                fit: feature_fit,
            },
            energy,
            energy_selection: selection,
            modes: Some(modes.config),
            symmetry: Some(symmetry),
            bake: BakeInfo {
                resolution: job.bake_resolution,
                bound,
                sdf_mean_error,
                keys_relative_error,
            },
            command: job.command,
            files: BTreeMap::new(),
        },
        mesh: job.mesh,
        sdf,
        keys: features.keys,
        query: features.query,
        modes: Some(modes),
    })
}
