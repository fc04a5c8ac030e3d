//! Datasets in the BOP layout (T-LESS, YCB-V, the BOP challenge):
//!
//! ```text
//! <root>/models/obj_NNNNNN.ply, models_info.json
//! <root>/<split>/<scene>/rgb/NNNNNN.png, depth/NNNNNN.png, mask_visib/NNNNNN_GGGGGG.png,
//!                         scene_gt.json, scene_gt_info.json, scene_camera.json,
//!                         scene_gt_equivalents.json (ours)
//! ```
//!
//! Crops follow the project's one convention ([`super::virtual_crop`]): the virtual camera of the
//! object's box `bbox_obj` from `scene_gt_info.json`, and the labels of a crop are the rotations
//! in that virtual camera.
//!
//! Units follow BOP: model coordinates and `cam_t_m2c` in millimetres, depth PNGs in
//! `depth_scale` millimetres. `scene_gt_equivalents.json` is our addition: for every image and
//! every ground truth, every equivalent `cam_R_m2c` (SYMSOL style). Datasets without it (real BOP
//! data) get their equivalents from `models_info.json`'s `symmetries_discrete` and
//! `symmetries_continuous`.

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};

use nalgebra::{Rotation3, Unit, Vector3};
use serde::{Deserialize, Serialize};

use super::DataError;
use super::virtual_crop::perspective_crop;
use crate::cad::{Camera, Mesh, Pose, Render, write_ply};
use crate::so3::{CONTINUOUS_STEPS, So3Error, from_row_major, nearest_rotation, to_row_major};

/// One ground truth of `scene_gt.json` (BOP field names).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneGt {
    /// `R`, object to camera, row-major.
    #[serde(rename = "cam_R_m2c")]
    pub cam_r_m2c: [f64; 9],
    /// `t` in millimetres.
    pub cam_t_m2c: [f64; 3],
    /// Object id (`models/obj_{obj_id:06}.ply`).
    pub obj_id: u32,
}

/// One entry of `scene_gt_info.json` (BOP field names; boxes `(x, y, w, h)` in pixels).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SceneGtInfo {
    /// Box of the whole projected object.
    pub bbox_obj: [f64; 4],
    /// Box of its visible pixels.
    pub bbox_visib: [f64; 4],
    /// Fraction of the object's pixels that are visible.
    pub visib_fract: f64,
}

/// One camera of `scene_camera.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneCamera {
    /// `K`, row-major.
    #[serde(rename = "cam_K")]
    pub cam_k: [f64; 9],
    /// Millimetres per unit of the depth PNGs.
    #[serde(default = "one")]
    pub depth_scale: f64,
}

fn one() -> f64 {
    1.0
}

/// A continuous symmetry of `models_info.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ContinuousSymmetry {
    /// Axis of rotation.
    pub axis: [f64; 3],
    /// Offset of the axis, millimetres.
    pub offset: [f64; 3],
}

/// One model of `models_info.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelInfo {
    /// Largest distance between two vertices, millimetres.
    pub diameter: f64,
    /// Bounding box.
    pub min_x: f64,
    /// Bounding box.
    pub min_y: f64,
    /// Bounding box.
    pub min_z: f64,
    /// Bounding box.
    pub size_x: f64,
    /// Bounding box.
    pub size_y: f64,
    /// Bounding box.
    pub size_z: f64,
    /// Discrete symmetries as row-major 4×4 matrices (translation in millimetres).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub symmetries_discrete: Option<Vec<[f64; 16]>>,
    /// Continuous symmetries.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub symmetries_continuous: Option<Vec<ContinuousSymmetry>>,
}

impl ModelInfo {
    /// The rotations that map the model onto itself: the identity, the discrete symmetries, and
    /// each continuous one sampled every 1° (combined with the discrete ones).
    /// A symmetry matrix that is not a rotation is an error.
    pub fn symmetry_rotations(&self) -> Result<Vec<Rotation3<f64>>, So3Error> {
        let mut discrete = vec![Rotation3::identity()];
        for m in self.symmetries_discrete.iter().flatten() {
            discrete.push(from_row_major([
                m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10],
            ])?);
        }
        let mut out = discrete.clone();
        for c in self.symmetries_continuous.iter().flatten() {
            let axis = Unit::new_normalize(Vector3::from(c.axis));
            out = (0..CONTINUOUS_STEPS)
                .flat_map(|k| {
                    let about = Rotation3::from_axis_angle(
                        &axis,
                        std::f64::consts::TAU * k as f64 / CONTINUOUS_STEPS as f64,
                    );
                    discrete.iter().map(move |d| about * d)
                })
                .collect();
        }
        Ok(out)
    }
}

/// Writes one scene of a dataset in BOP layout.
pub struct BopWriter {
    root: PathBuf,
    scene_dir: PathBuf,
    gts: BTreeMap<u32, Vec<SceneGt>>,
    infos: BTreeMap<u32, Vec<SceneGtInfo>>,
    cameras: BTreeMap<u32, SceneCamera>,
    equivalents: BTreeMap<u32, Vec<Vec<[f64; 9]>>>,
    models: BTreeMap<u32, ModelInfo>,
    units_mm: f64,
}

/// Depth PNG resolution: 0.1 mm per unit.
const DEPTH_SCALE: f64 = 0.1;

impl BopWriter {
    /// Starts scene `scene` of `split` under `root`. `units_mm` is how many millimetres one unit
    /// of the rendered meshes and poses is (e.g. 100 for NOCS shapes of radius 10 cm).
    pub fn create(root: &Path, split: &str, scene: u32, units_mm: f64) -> Result<Self, DataError> {
        let scene_dir = root.join(split).join(format!("{scene:06}"));
        for sub in ["rgb", "depth", "mask_visib"] {
            let d = scene_dir.join(sub);
            fs::create_dir_all(&d).map_err(|e| DataError::io(&d, e))?;
        }
        let models = root.join("models");
        fs::create_dir_all(&models).map_err(|e| DataError::io(&models, e))?;
        Ok(Self {
            root: root.to_path_buf(),
            scene_dir,
            gts: BTreeMap::new(),
            infos: BTreeMap::new(),
            cameras: BTreeMap::new(),
            equivalents: BTreeMap::new(),
            models: BTreeMap::new(),
            units_mm,
        })
    }

    /// Writes `models/obj_{obj_id:06}.ply` (scaled to millimetres) and its `models_info.json`
    /// entry; `symmetries` are written as `symmetries_discrete` (identity left out).
    pub fn write_model(
        &mut self,
        obj_id: u32,
        mesh: &Mesh,
        symmetries: &[Rotation3<f64>],
    ) -> Result<(), DataError> {
        let mut scaled = mesh.clone();
        for v in &mut scaled.vertices {
            *v *= self.units_mm as f32;
        }
        let path = self
            .root
            .join("models")
            .join(format!("obj_{obj_id:06}.ply"));
        write_ply(&scaled, &path)?;
        let (lo, hi) = scaled.bounds();
        let radius = scaled.normalisation().scale;
        let discrete: Vec<[f64; 16]> = symmetries
            .iter()
            .filter(|s| s.angle() > 1e-9)
            .map(|s| {
                let m = to_row_major(s);
                [
                    m[0], m[1], m[2], 0.0, m[3], m[4], m[5], 0.0, m[6], m[7], m[8], 0.0, 0.0, 0.0,
                    0.0, 1.0,
                ]
            })
            .collect();
        self.models.insert(
            obj_id,
            ModelInfo {
                diameter: 2.0 * radius,
                min_x: lo.x,
                min_y: lo.y,
                min_z: lo.z,
                size_x: hi.x - lo.x,
                size_y: hi.y - lo.y,
                size_z: hi.z - lo.z,
                symmetries_discrete: (!discrete.is_empty()).then_some(discrete),
                symmetries_continuous: None,
            },
        );
        Ok(())
    }

    /// Writes image `im_id` (RGB, depth, the mask of its one object) with its ground truth, its
    /// `scene_gt_info.json` entry (`bbox_obj`: the box of the projected `mesh`) and every
    /// equivalent rotation.
    #[allow(clippy::too_many_arguments)]
    pub fn add_image(
        &mut self,
        im_id: u32,
        obj_id: u32,
        mesh: &Mesh,
        render: &Render,
        camera: &Camera,
        pose: &Pose,
        equivalents: &[Rotation3<f64>],
    ) -> Result<(), DataError> {
        self.infos
            .insert(im_id, vec![gt_info(mesh, render, camera, pose)]);
        let (w, h) = (render.width, render.height);
        let rgb_path = self.scene_dir.join("rgb").join(format!("{im_id:06}.png"));
        image::save_buffer(&rgb_path, &render.rgb, w, h, image::ExtendedColorType::Rgb8)
            .map_err(|e| DataError::image(&rgb_path, e))?;
        let mask: Vec<u8> = render
            .mask
            .iter()
            .map(|&m| if m { 255 } else { 0 })
            .collect();
        let mask_path = self
            .scene_dir
            .join("mask_visib")
            .join(format!("{im_id:06}_000000.png"));
        image::save_buffer(&mask_path, &mask, w, h, image::ExtendedColorType::L8)
            .map_err(|e| DataError::image(&mask_path, e))?;
        let depth: Vec<u16> = render
            .depth
            .iter()
            .map(|&d| {
                (d as f64 * self.units_mm / DEPTH_SCALE)
                    .round()
                    .min(65535.0) as u16
            })
            .collect();
        let depth_path = self.scene_dir.join("depth").join(format!("{im_id:06}.png"));
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(w, h, depth)
            .ok_or_else(|| DataError::Invalid {
                file: depth_path.display().to_string(),
                message: "depth buffer size does not match the image".into(),
            })?
            .save(&depth_path)
            .map_err(|e| DataError::image(&depth_path, e))?;

        let t = pose.translation * self.units_mm;
        self.gts.insert(
            im_id,
            vec![SceneGt {
                cam_r_m2c: to_row_major(&pose.rotation),
                cam_t_m2c: [t.x, t.y, t.z],
                obj_id,
            }],
        );
        self.cameras.insert(
            im_id,
            SceneCamera {
                cam_k: camera.k(),
                depth_scale: DEPTH_SCALE,
            },
        );
        self.equivalents
            .insert(im_id, vec![equivalents.iter().map(to_row_major).collect()]);
        Ok(())
    }

    /// Writes the scene's JSON files and `models_info.json`.
    pub fn finish(self) -> Result<(), DataError> {
        write_json(&self.scene_dir.join("scene_gt.json"), &self.gts)?;
        write_json(&self.scene_dir.join("scene_gt_info.json"), &self.infos)?;
        write_json(&self.scene_dir.join("scene_camera.json"), &self.cameras)?;
        write_json(
            &self.scene_dir.join("scene_gt_equivalents.json"),
            &self.equivalents,
        )?;
        write_json(
            &self.root.join("models").join("models_info.json"),
            &self.models,
        )
    }
}

/// The `scene_gt_info.json` entry of the one object of a render: its projected box, the box of
/// its mask, and the fraction of its projection that the frame shows (the projected box's area
/// inside the frame over its whole area; one object, so nothing occludes it).
fn gt_info(mesh: &Mesh, render: &Render, camera: &Camera, pose: &Pose) -> SceneGtInfo {
    let bbox_obj = super::virtual_crop::object_box(mesh, pose, camera);
    let (w, h) = (render.width as usize, render.height as usize);
    let (mut lo, mut hi) = ([usize::MAX; 2], [0usize; 2]);
    for (k, _) in render.mask.iter().enumerate().filter(|(_, m)| **m) {
        let (x, y) = (k % w, k / w);
        lo = [lo[0].min(x), lo[1].min(y)];
        hi = [hi[0].max(x), hi[1].max(y)];
    }
    let bbox_visib = if lo[0] == usize::MAX {
        [0.0; 4]
    } else {
        [
            lo[0] as f64,
            lo[1] as f64,
            (hi[0] - lo[0] + 1) as f64,
            (hi[1] - lo[1] + 1) as f64,
        ]
    };
    let [x, y, bw, bh] = bbox_obj;
    let inside_w = ((x + bw).min(w as f64) - x.max(0.0)).max(0.0);
    let inside_h = ((y + bh).min(h as f64) - y.max(0.0)).max(0.0);
    let visib_fract = (inside_w * inside_h / (bw * bh).max(1e-12)).min(1.0);
    SceneGtInfo {
        bbox_obj,
        bbox_visib,
        visib_fract,
    }
}

fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<(), DataError> {
    let text = serde_json::to_string(value).map_err(|e| DataError::Invalid {
        file: path.display().to_string(),
        message: e.to_string(),
    })?;
    fs::write(path, text).map_err(|e| DataError::io(path, e))
}

fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T, DataError> {
    let text = fs::read_to_string(path).map_err(|e| DataError::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| DataError::Invalid {
        file: path.display().to_string(),
        message: e.to_string(),
    })
}

/// One object instance in one image of a BOP dataset.
#[derive(Debug, Clone, PartialEq)]
pub struct BopSample {
    /// Scene id.
    pub scene: u32,
    /// Image id within the scene.
    pub im_id: u32,
    /// Index of the ground truth within the image.
    pub gt_index: usize,
    /// Object id.
    pub obj_id: u32,
    /// The image file.
    pub rgb_path: PathBuf,
    /// The camera (size read from the image when it is loaded; 0 until then).
    pub cam_k: [f64; 9],
    /// `R`, object to camera.
    pub rotation: Rotation3<f64>,
    /// `t` in millimetres.
    pub translation: Vector3<f64>,
    /// Every equivalent ground-truth rotation (at least `rotation` itself).
    pub equivalents: Vec<Rotation3<f64>>,
    /// The object's box from `scene_gt_info.json`, when the dataset has one.
    pub bbox_obj: Option<[f64; 4]>,
}

/// An object-centred square crop.
#[derive(Debug, Clone, PartialEq)]
pub struct Crop {
    /// Side in pixels.
    pub size: u32,
    /// RGB8, `size × size × 3`.
    pub rgb: Vec<u8>,
    /// The ground truth in the crop's virtual camera: `R_rayᵀ·R_cam`.
    pub rotation: Rotation3<f64>,
    /// Every equivalent ground truth in the crop's virtual camera.
    pub equivalents: Vec<Rotation3<f64>>,
}

/// A BOP dataset split, read from disk.
#[derive(Debug, Clone)]
pub struct BopDataset {
    /// Dataset root.
    pub root: PathBuf,
    /// Models by id.
    pub models: BTreeMap<u32, ModelInfo>,
    /// Every object instance of the split, by scene, image and ground truth.
    pub samples: Vec<BopSample>,
    /// How many `cam_R_m2c` were not orthonormal to [`CORRECTED_ABOVE`] and were replaced by the
    /// nearest rotation (within [`ROTATION_TOLERANCE`]).
    pub rotations_corrected: usize,
}

/// How far a recorded `cam_R_m2c` may be from a rotation (`max |MᵀM − I|`): real datasets store
/// poses orthonormal only to a few 1e-3; further than this is an error in the file.
pub const ROTATION_TOLERANCE: f64 = 1e-2;

/// Recorded rotations less orthonormal than this (more than JSON's printed digits explain) count
/// as corrected.
pub const CORRECTED_ABOVE: f64 = 1e-6;

impl BopDataset {
    /// Reads `root/models/models_info.json` and every scene of `root/<split>`.
    pub fn open(root: &Path, split: &str) -> Result<Self, DataError> {
        let models: BTreeMap<u32, ModelInfo> =
            read_json(&root.join("models").join("models_info.json"))?;
        let split_dir = root.join(split);
        let mut scenes: Vec<(u32, PathBuf)> = fs::read_dir(&split_dir)
            .map_err(|e| DataError::io(&split_dir, e))?
            .filter_map(|e| e.ok())
            .filter_map(|e| {
                let id = e.file_name().to_str()?.parse::<u32>().ok()?;
                e.path().is_dir().then_some((id, e.path()))
            })
            .collect();
        scenes.sort();
        if scenes.is_empty() {
            return Err(DataError::Invalid {
                file: split_dir.display().to_string(),
                message: "no scene folders (NNNNNN) in this split".into(),
            });
        }
        let (mut samples, mut rotations_corrected) = (Vec::new(), 0);
        for (scene, dir) in scenes {
            let (scene_samples, corrected) = scene_samples(root, &models, scene, &dir)?;
            samples.extend(scene_samples);
            rotations_corrected += corrected;
        }
        Ok(Self {
            root: root.to_path_buf(),
            models,
            samples,
            rotations_corrected,
        })
    }

    /// The crop of `sample` as the virtual camera of its box sees it, `size × size`
    /// ([`super::virtual_crop::perspective_crop`]), and the ground truths in that camera. The box
    /// is `bbox_obj` from `scene_gt_info.json`; datasets without one get the square box of the
    /// projected bounding sphere.
    pub fn crop(&self, sample: &BopSample, size: u32) -> Result<Crop, DataError> {
        let img = image::open(&sample.rgb_path)
            .map_err(|e| DataError::image(&sample.rgb_path, e))?
            .to_rgb8();
        let bbox = match sample.bbox_obj {
            Some(b) => b,
            None => {
                let radius = self
                    .models
                    .get(&sample.obj_id)
                    .map_or(1.0, |m| m.diameter / 2.0);
                sphere_box(&sample.cam_k, &sample.translation, radius)
            }
        };
        let (w, h) = img.dimensions();
        let (rgb, view) = perspective_crop(img.as_raw(), w, h, &sample.cam_k, bbox, size)
            .ok_or_else(|| DataError::Invalid {
                file: sample.rgb_path.display().to_string(),
                message: format!(
                    "image {} gt {}: box {bbox:?} or cam_K {:?} has no area",
                    sample.im_id, sample.gt_index, sample.cam_k
                ),
            })?;
        let back = view.r_ray.inverse();
        Ok(Crop {
            size,
            rgb,
            rotation: back * sample.rotation,
            equivalents: sample.equivalents.iter().map(|e| back * e).collect(),
        })
    }
}

/// The square box around the projection of a sphere of `radius` centred at `t`.
fn sphere_box(k: &[f64; 9], t: &Vector3<f64>, radius: f64) -> [f64; 4] {
    let (fx, cx, fy, cy) = (k[0], k[2], k[4], k[5]);
    let z = t.z.max(1e-9);
    let (u, v) = (fx * t.x / z + cx, fy * t.y / z + cy);
    let r = radius.min(z * 0.999);
    let half = fx * r / (z * z - r * r).sqrt();
    [u - half, v - half, 2.0 * half, 2.0 * half]
}

/// Every object instance of one scene folder of a split (`scene_gt.json`, `scene_camera.json`,
/// and, when present, `scene_gt_info.json` and `scene_gt_equivalents.json`), and how many of its
/// rotations were corrected to the nearest rotation.
fn scene_samples(
    root: &Path,
    models: &BTreeMap<u32, ModelInfo>,
    scene: u32,
    dir: &Path,
) -> Result<(Vec<BopSample>, usize), DataError> {
    let (mut samples, mut corrected) = (Vec::new(), 0);
    let gt_file = dir.join("scene_gt.json");
    let gts: BTreeMap<u32, Vec<SceneGt>> = read_json(&gt_file)?;
    let cam_file = dir.join("scene_camera.json");
    let cams: BTreeMap<u32, SceneCamera> = read_json(&cam_file)?;
    let info_file = dir.join("scene_gt_info.json");
    let infos: Option<BTreeMap<u32, Vec<SceneGtInfo>>> = read_optional_json(&info_file)?;
    let eq_file = dir.join("scene_gt_equivalents.json");
    let eqs: Option<BTreeMap<u32, Vec<Vec<[f64; 9]>>>> = read_optional_json(&eq_file)?;
    for (im_id, list) in gts {
        let cam = cams.get(&im_id).ok_or_else(|| DataError::Invalid {
            file: cam_file.display().to_string(),
            message: format!("no camera for image {im_id}"),
        })?;
        for (gt_index, gt) in list.into_iter().enumerate() {
            let field = |what: &str| DataError::Invalid {
                file: gt_file.display().to_string(),
                message: format!("image {im_id}, gt {gt_index}: {what}"),
            };
            let (rotation, ortho_err) = nearest_rotation(gt.cam_r_m2c, ROTATION_TOLERANCE)
                .map_err(|e| {
                    field(&format!(
                        "cam_R_m2c: {e} (tolerance {ROTATION_TOLERANCE:.0e})"
                    ))
                })?;
            corrected += usize::from(ortho_err > CORRECTED_ABOVE);
            let info = models
                .get(&gt.obj_id)
                .ok_or_else(|| field(&format!("obj_id {} has no models_info entry", gt.obj_id)))?;
            let equivalents = match eqs.as_ref().and_then(|e| e.get(&im_id)) {
                Some(per_gt) => per_gt
                    .get(gt_index)
                    .ok_or_else(|| DataError::Invalid {
                        file: eq_file.display().to_string(),
                        message: format!("image {im_id} has no entry for gt {gt_index}"),
                    })?
                    .iter()
                    .map(|m| {
                        from_row_major(*m).map_err(|e| DataError::Invalid {
                            file: eq_file.display().to_string(),
                            message: format!("image {im_id}: {e}"),
                        })
                    })
                    .collect::<Result<Vec<_>, _>>()?,
                None => info
                    .symmetry_rotations()
                    .map_err(|e| DataError::Invalid {
                        file: root.join("models/models_info.json").display().to_string(),
                        message: format!("obj {}: symmetries_discrete: {e}", gt.obj_id),
                    })?
                    .iter()
                    .map(|s| rotation * s)
                    .collect(),
            };
            samples.push(BopSample {
                scene,
                im_id,
                gt_index,
                obj_id: gt.obj_id,
                rgb_path: dir.join("rgb").join(format!("{im_id:06}.png")),
                cam_k: cam.cam_k,
                rotation,
                translation: Vector3::from(gt.cam_t_m2c),
                equivalents,
                bbox_obj: infos
                    .as_ref()
                    .and_then(|i| i.get(&im_id))
                    .and_then(|list| list.get(gt_index))
                    .map(|i| i.bbox_obj),
            });
        }
    }
    Ok((samples, corrected))
}

/// `file` parsed, or `None` when it does not exist.
fn read_optional_json<T: serde::de::DeserializeOwned>(file: &Path) -> Result<Option<T>, DataError> {
    match file.exists() {
        true => read_json(file).map(Some),
        false => Ok(None),
    }
}
