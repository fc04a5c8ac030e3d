//! Rendering a dataset of one object at many poses (SYMSOL style: the object centred, fully in
//! view, every equivalent ground truth recorded).

use std::path::Path;

use nalgebra::{Rotation3, Vector3};

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::virtual_crop::{frame_camera_of, random_placement_in};
use super::{BopWriter, DataError};
use crate::cad::{Camera, Mesh, Pose, RenderOptions, render};
use crate::so3::equivalents;

/// Distance of the object centre from the camera, in NOCS units. With the square camera
/// (focal length = image size) the bounding sphere spans `2/√(3² − 1) ≈ 0.71` of the image.
pub const SYMSOL_DISTANCE: f64 = 3.0;

/// The pose of a SYMSOL-style render: rotation `r`, object centred on the optical axis.
pub fn symsol_pose(r: Rotation3<f64>) -> Pose {
    Pose {
        rotation: r,
        translation: Vector3::new(0.0, 0.0, SYMSOL_DISTANCE),
    }
}

/// What to render.
pub struct RenderJob<'a> {
    /// The object, in NOCS.
    pub mesh: &'a Mesh,
    /// Its symmetries (identity included), for the equivalents of every image.
    pub symmetries: &'a [Rotation3<f64>],
    /// One image per rotation.
    pub rotations: &'a [Rotation3<f64>],
    /// Image side in pixels.
    pub size: u32,
    /// Millimetres per NOCS unit in the written files.
    pub units_mm: f64,
    /// Split name (`train`, `test`).
    pub split: &'a str,
    /// BOP object id.
    pub obj_id: u32,
    /// `Some((W, H))`: place each object at a random position and distance inside a `W × H`
    /// frame ([`super::virtual_crop::random_placement_in`], seeded by `seed`) instead of centring
    /// it in a `size × size` image.
    pub frame: Option<(u32, u32)>,
    /// Seed of the placements in a frame.
    pub seed: u64,
}

/// Renders `job` into `root` in BOP layout (scene 0), calling `progress` after each image.
pub fn render_dataset(
    job: &RenderJob<'_>,
    root: &Path,
    mut progress: impl FnMut(usize),
) -> Result<(), DataError> {
    let mut writer = BopWriter::create(root, job.split, 0, job.units_mm)?;
    writer.write_model(job.obj_id, job.mesh, job.symmetries)?;
    let camera = match job.frame {
        Some((w, h)) => frame_camera_of(w, h),
        None => Camera::square(job.size),
    };
    let options = RenderOptions::default();
    let mut rng = ChaCha8Rng::seed_from_u64(job.seed ^ 0xf4a3e);
    for (i, r) in job.rotations.iter().enumerate() {
        let pose = match job.frame {
            Some(_) => Pose {
                rotation: *r,
                ..random_placement_in(&camera, &mut rng)
            },
            None => symsol_pose(*r),
        };
        let image = render(job.mesh, &camera, &pose, &options);
        writer.add_image(
            i as u32,
            job.obj_id,
            job.mesh,
            &image,
            &camera,
            &pose,
            &equivalents(r, job.symmetries),
        )?;
        progress(i + 1);
    }
    writer.finish()
}
