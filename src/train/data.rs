//! Training and evaluation images — from BOP datasets, or rendered fresh — as object-centred
//! crops, ground truths, and the visible canonical points the experts score.

use std::sync::Arc;

use nalgebra::{Rotation3, Vector3};
use rand::{Rng, RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::bundle::model::ModelBundle;
use crate::cad::{Mesh, RenderOptions};
use crate::data::realism::{Realism, RealisticCrop, SceneAssets, Split, realistic_crop};
use crate::data::virtual_crop::{RenderedCrop, frame_camera, random_placement, render_crop};
use crate::data::{BopDataset, DataError};
use crate::experts::energy::visible_points;
use crate::experts::select::{VISIBLE_POINTS, visible_points_at};

use super::eval::EvalImage;

/// The default seed of `alignist-train eval`'s fresh crops (its `--seed`); its realistic sets
/// place their looks from the next one. No training run draws from either.
pub const EVAL_SEED: u64 = 1 << 40;

/// One training image: its crop, ground truth, object, and visible canonical points.
#[derive(Debug, Clone)]
pub struct TrainingImage {
    /// Index of the object in [`TrainingSet::objects`].
    pub object: usize,
    /// RGB8 crop, `image_size² × 3`.
    pub rgb: Vec<u8>,
    /// Ground-truth rotation.
    pub rotation: Rotation3<f64>,
    /// Visible canonical points `x⁰` (from a NOCS render at the ground truth).
    pub visible: Vec<Vector3<f32>>,
}

/// The first `⌈fraction·N⌉` images of `dataset` (all of one object) as training images of
/// object index `object`, with crops of `size` and visible points from `mesh` (NOCS).
pub fn training_images(
    dataset: &BopDataset,
    object: usize,
    mesh: &Mesh,
    size: u32,
    fraction: f64,
) -> Result<Vec<TrainingImage>, DataError> {
    let n = ((dataset.samples.len() as f64 * fraction.clamp(0.0, 1.0)).ceil() as usize)
        .clamp(1, dataset.samples.len().max(1));
    dataset
        .samples
        .iter()
        .take(n)
        .enumerate()
        .map(|(i, s)| {
            let crop = dataset.crop(s, size)?;
            Ok(TrainingImage {
                object,
                rgb: crop.rgb,
                rotation: crop.rotation,
                visible: visible_points_at(mesh, &crop.rotation, i as u64),
            })
        })
        .collect()
}

/// Up to `limit` images of `dataset` as evaluation images of object `name`.
pub fn eval_images(
    dataset: &BopDataset,
    name: &str,
    size: u32,
    limit: usize,
) -> Result<Vec<EvalImage>, DataError> {
    dataset
        .samples
        .iter()
        .take(limit)
        .map(|s| {
            let crop = dataset.crop(s, size)?;
            Ok(EvalImage {
                object: name.to_string(),
                rgb: crop.rgb,
                equivalents: crop.equivalents,
            })
        })
        .collect()
}

/// Training and evaluation images rendered on demand ([`crate::data::fresh`]): every step sees
/// new poses, so a run never sees an image twice.
#[derive(Debug, Clone)]
pub struct FreshRenders {
    /// The objects' meshes in NOCS, in object order.
    pub meshes: Vec<Mesh>,
    /// Supersampling factor per axis (anti-aliasing).
    pub supersample: u32,
    /// `Some(n)`: every training image is one of a fixed pool of `n` images per object (the same
    /// pool for every run, whatever its seed), for the low-data regime; `None`: a new render
    /// every time.
    pub pool: Option<usize>,
    /// `Some`: training crops are realistic ([`crate::data::realism`]: materials, lights,
    /// backgrounds, clutter, detector boxes, a camera model); `None`: flat grey on black.
    pub realism: Option<Arc<SceneAssets>>,
}

impl FreshRenders {
    /// The seed of a training image of `object`: a new one from `rng`, or, with a pool, the
    /// seed of one of the pool's images drawn from `rng`.
    pub fn image_seed<R: Rng + ?Sized>(&self, object: usize, rng: &mut R) -> u64 {
        match self.pool {
            None => rng.random::<u64>(),
            Some(n) => {
                let index = rng.random_range(0..n.max(1)) as u64;
                let mut pool =
                    ChaCha8Rng::seed_from_u64(0x9001_d47a ^ ((object as u64) << 40) ^ index);
                pool.random::<u64>()
            }
        }
    }

    /// The crop of object `object` placed at random in the frame (from `rng`).
    fn random_crop<R: Rng + ?Sized>(&self, object: usize, size: u32, rng: &mut R) -> RenderedCrop {
        render_crop(
            &self.meshes[object],
            &random_placement(rng),
            &frame_camera(),
            size,
            self.supersample,
            &RenderOptions::default(),
        )
    }

    /// A crop of object `object` placed at random in the frame (from `rng`), with its label in
    /// the virtual camera and the visible points of its render. With realism, `plain` (when
    /// given) replaces the realism's share of plain crops ([`Realism::plain`]).
    pub fn training_image<R: Rng + ?Sized>(
        &self,
        object: usize,
        size: u32,
        plain: Option<f64>,
        rng: &mut R,
    ) -> TrainingImage {
        if let Some(assets) = &self.realism
            && rng.random::<f64>() >= plain.unwrap_or(assets.realism.plain)
        {
            let crop = realistic_crop(assets, object, size, self.supersample, rng);
            return TrainingImage {
                object,
                rgb: crop.rgb,
                rotation: crop.r_virtual,
                visible: visible_points(&crop.render, VISIBLE_POINTS, rng),
            };
        }
        let crop = self.random_crop(object, size, rng);
        TrainingImage {
            object,
            rgb: crop.rgb,
            rotation: crop.r_virtual,
            visible: visible_points(&crop.render, VISIBLE_POINTS, rng),
        }
    }

    /// The same poses as [`FreshRenders::eval_images`] (same `seed`), but each object is rendered
    /// in the whole frame and cut out as a server does for a full image with a detector's box
    /// (the projected mesh's box rounded out to whole pixels): the perspective crop
    /// ([`crate::data::virtual_crop::perspective_crop`]). Returns two labellings of those crops:
    /// the ground truths in the crop's virtual camera (`R_rayᵀ·R_cam`: what the network's answer,
    /// turned by `R_ray`, is measured against in the camera frame) and the camera-frame ground
    /// truths as they are (`R_cam`: an answer taken as camera-frame without the ray correction).
    pub fn frame_eval_images(
        &self,
        names: &[String],
        symmetries: &[Vec<Rotation3<f64>>],
        size: u32,
        per_object: usize,
        seed: u64,
    ) -> (Vec<EvalImage>, Vec<EvalImage>) {
        use crate::cad::render;
        use crate::data::virtual_crop::{object_box, perspective_crop};
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xe7a1);
        let camera = frame_camera();
        let (mut corrected, mut uncorrected) = (Vec::new(), Vec::new());
        for i in 0..self.meshes.len() {
            for _ in 0..per_object {
                let pose = random_placement(&mut rng);
                let full = render(&self.meshes[i], &camera, &pose, &RenderOptions::default());
                let b = object_box(&self.meshes[i], &pose, &camera);
                let (x0, y0) = (b[0].floor(), b[1].floor());
                let bbox = [x0, y0, (b[0] + b[2]).ceil() - x0, (b[1] + b[3]).ceil() - y0];
                let (rgb, view) = perspective_crop(
                    &full.rgb,
                    camera.width,
                    camera.height,
                    &camera.k(),
                    bbox,
                    size,
                )
                .expect("a placed object's box has an area");
                let in_virtual = view.r_ray.inverse() * pose.rotation;
                let labelled = |rgb, r| EvalImage::labelled(&names[i], rgb, r, &symmetries[i]);
                corrected.push(labelled(rgb.clone(), &in_virtual));
                uncorrected.push(labelled(rgb, &pose.rotation));
            }
        }
        (corrected, uncorrected)
    }

    /// `per_object` fresh evaluation crops of each object placed at random from `seed`, with
    /// every equivalent ground truth in the virtual camera (`symmetries[i]` of object `i`,
    /// `names[i]` its name).
    pub fn eval_images(
        &self,
        names: &[String],
        symmetries: &[Vec<Rotation3<f64>>],
        size: u32,
        per_object: usize,
        seed: u64,
    ) -> Vec<EvalImage> {
        self.eval_crops(size, per_object, seed)
            .into_iter()
            .map(|(i, crop)| {
                EvalImage::labelled(&names[i], crop.rgb, &crop.r_virtual, &symmetries[i])
            })
            .collect()
    }

    /// `per_object` realistic evaluation crops of each object from `seed`, made as `realism`
    /// says ([`crate::data::realism`]; its held-out split for a test unlike training), with every
    /// equivalent ground truth in the virtual camera.
    pub fn realistic_eval_images(
        &self,
        names: &[String],
        symmetries: &[Vec<Rotation3<f64>>],
        size: u32,
        per_object: usize,
        seed: u64,
        realism: Realism,
    ) -> Vec<EvalImage> {
        self.realistic_eval_crops(size, per_object, seed, realism)
            .into_iter()
            .map(|(i, crop)| {
                EvalImage::labelled(&names[i], crop.rgb, &crop.r_virtual, &symmetries[i])
            })
            .collect()
    }

    /// The crops of [`FreshRenders::realistic_eval_images`] (same `seed`, same scenes) with their
    /// renders, visible fractions and object indices; object by object, `per_object` each.
    pub fn realistic_eval_crops(
        &self,
        size: u32,
        per_object: usize,
        seed: u64,
        realism: Realism,
    ) -> Vec<(usize, RealisticCrop)> {
        self.realistic_crops_of(
            &SceneAssets::new(&self.meshes, realism),
            size,
            per_object,
            seed,
        )
    }

    /// [`FreshRenders::realistic_eval_crops`] from scene assets already built (the training set's
    /// own, [`FreshRenders::realism`]) rather than new ones.
    pub fn realistic_crops_of(
        &self,
        assets: &SceneAssets,
        size: u32,
        per_object: usize,
        seed: u64,
    ) -> Vec<(usize, RealisticCrop)> {
        use rayon::prelude::*;
        let draws: Vec<(usize, u64)> = (0..self.meshes.len())
            .flat_map(|i| (0..per_object as u64).map(move |j| (i, j)))
            .collect();
        draws
            .par_iter()
            .map(|&(i, j)| {
                let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x4ea1 ^ ((i as u64) << 32) ^ j);
                (
                    i,
                    realistic_crop(assets, i, size, self.supersample, &mut rng),
                )
            })
            .collect()
    }

    /// The crops of [`FreshRenders::eval_images`] (same `seed`, same poses) with their renders
    /// (depth included) and object indices.
    pub fn eval_crops(
        &self,
        size: u32,
        per_object: usize,
        seed: u64,
    ) -> Vec<(usize, RenderedCrop)> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xe7a1);
        let mut out = Vec::with_capacity(per_object * self.meshes.len());
        for i in 0..self.meshes.len() {
            for _ in 0..per_object {
                out.push((i, self.random_crop(i, size, &mut rng)));
            }
        }
        out
    }
}

/// A bundle's objects as fresh renders, in object order: the renderer of their meshes, their
/// names and their symmetries (what `eval_images` and `frame_eval_images` take).
pub struct BundleRenders {
    /// The renderer.
    pub fresh: FreshRenders,
    /// Object names.
    pub names: Vec<String>,
    /// Each object's proper symmetries.
    pub symmetries: Vec<Vec<Rotation3<f64>>>,
}

impl BundleRenders {
    /// `bundle`'s objects as fresh renders, supersampled `supersample` times per axis.
    pub fn of(bundle: &ModelBundle, supersample: u32) -> BundleRenders {
        BundleRenders {
            fresh: FreshRenders {
                meshes: bundle.experts.iter().map(|e| e.mesh.clone()).collect(),
                supersample,
                pool: None,
                realism: None,
            },
            names: bundle
                .manifest
                .objects
                .iter()
                .map(|o| o.name.clone())
                .collect(),
            symmetries: bundle.experts.iter().map(|e| e.symmetries()).collect(),
        }
    }

    /// `per_object` fresh evaluation crops of `size` of every object, placed from `seed`.
    pub fn eval_images(&self, size: u32, per_object: usize, seed: u64) -> Vec<EvalImage> {
        self.fresh
            .eval_images(&self.names, &self.symmetries, size, per_object, seed)
    }

    /// The realistic crops `alignist-train eval --fresh --realistic` scores by default (seed
    /// [`EVAL_SEED`] + 1, exact boxes), with the looks of `split`: the probes' test set.
    pub fn eval_realistic_images(
        &self,
        size: u32,
        per_object: usize,
        split: Split,
    ) -> Vec<EvalImage> {
        let realism = Realism {
            split,
            ..Realism::HELD_OUT
        };
        self.realistic_eval_images(size, per_object, EVAL_SEED.wrapping_add(1), realism)
    }

    /// `per_object` realistic evaluation crops of `size` of every object from `seed`, made as
    /// `realism` says ([`FreshRenders::realistic_eval_images`]).
    pub fn realistic_eval_images(
        &self,
        size: u32,
        per_object: usize,
        seed: u64,
        realism: Realism,
    ) -> Vec<EvalImage> {
        self.fresh.realistic_eval_images(
            &self.names,
            &self.symmetries,
            size,
            per_object,
            seed,
            realism,
        )
    }
}
