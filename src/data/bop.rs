//! Datasets in the BOP layout (T-LESS, YCB-V, the BOP challenge):
//!
//! ```text
//! <root>/models/obj_NNNNNN.ply, models_info.json
//! <root>/<split>/<scene>/rgb/NNNNNN.png, depth/NNNNNN.png, mask_visib/NNNNNN_GGGGGG.png,
//!                         scene_gt.json, scene_camera.json, scene_gt_equivalents.json (ours)
//! ```
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
use crate::cad::{Camera, Mesh, Pose, Render, write_ply};
use crate::so3::{CONTINUOUS_STEPS, So3Error, from_row_major, to_row_major};

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

    /// Writes image `im_id` (RGB, depth, the mask of its one object) with its ground truth and
    /// every equivalent rotation.
    pub fn add_image(
        &mut self,
        im_id: u32,
        obj_id: u32,
        render: &Render,
        camera: &Camera,
        pose: &Pose,
        equivalents: &[Rotation3<f64>],
    ) -> Result<(), DataError> {
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
}

/// An object-centred square crop.
#[derive(Debug, Clone, PartialEq)]
pub struct Crop {
    /// Side in pixels.
    pub size: u32,
    /// RGB8, `size × size × 3`.
    pub rgb: Vec<u8>,
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
}

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
        let mut samples = Vec::new();
        for (scene, dir) in scenes {
            let gt_file = dir.join("scene_gt.json");
            let gts: BTreeMap<u32, Vec<SceneGt>> = read_json(&gt_file)?;
            let cam_file = dir.join("scene_camera.json");
            let cams: BTreeMap<u32, SceneCamera> = read_json(&cam_file)?;
            let eq_file = dir.join("scene_gt_equivalents.json");
            let eqs: Option<BTreeMap<u32, Vec<Vec<[f64; 9]>>>> = if eq_file.exists() {
                Some(read_json(&eq_file)?)
            } else {
                None
            };
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
                    let rotation = from_row_major(gt.cam_r_m2c)
                        .map_err(|e| field(&format!("cam_R_m2c: {e}")))?;
                    let info = models.get(&gt.obj_id).ok_or_else(|| {
                        field(&format!("obj_id {} has no models_info entry", gt.obj_id))
                    })?;
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
                    });
                }
            }
        }
        Ok(Self {
            root: root.to_path_buf(),
            models,
            samples,
        })
    }

    /// The object-centred square crop of `sample`, resized to `size × size` (see [`crop`]).
    pub fn crop(&self, sample: &BopSample, size: u32) -> Result<Crop, DataError> {
        let img = image::open(&sample.rgb_path)
            .map_err(|e| DataError::image(&sample.rgb_path, e))?
            .to_rgb8();
        let radius = self
            .models
            .get(&sample.obj_id)
            .map(|m| m.diameter / 2.0)
            .unwrap_or(1.0);
        let (w, h) = img.dimensions();
        Ok(crop(
            img.as_raw(),
            w,
            h,
            &sample.cam_k,
            &sample.translation,
            radius,
            size,
        ))
    }
}

/// Crops the square around the object's projected bounding sphere (centre = projection of `t`,
/// half-side = the sphere's projected radius × 1.1) and resamples it bilinearly to `size × size`;
/// outside the image is black. Object rotation labels are unchanged by the crop.
pub fn crop(
    rgb: &[u8],
    width: u32,
    height: u32,
    cam_k: &[f64; 9],
    translation: &Vector3<f64>,
    radius: f64,
    size: u32,
) -> Crop {
    let (fx, cx, fy, cy) = (cam_k[0], cam_k[2], cam_k[4], cam_k[5]);
    let z = translation.z.max(1e-9);
    let (u0, v0) = (fx * translation.x / z + cx, fy * translation.y / z + cy);
    let r = radius.min(z * 0.999);
    let half = 1.1 * fx * r / (z * z - r * r).sqrt();
    let scale = 2.0 * half / size as f64;
    let mut out = vec![0u8; (size * size * 3) as usize];
    let at = |x: i64, y: i64, c: usize| -> f64 {
        if x < 0 || y < 0 || x >= width as i64 || y >= height as i64 {
            0.0
        } else {
            rgb[((y as usize * width as usize) + x as usize) * 3 + c] as f64
        }
    };
    for j in 0..size {
        for i in 0..size {
            // Source pixel centre coordinates of the output pixel centre.
            let sx = u0 - half + (i as f64 + 0.5) * scale - 0.5;
            let sy = v0 - half + (j as f64 + 0.5) * scale - 0.5;
            let (x0, y0) = (sx.floor() as i64, sy.floor() as i64);
            let (ax, ay) = (sx - x0 as f64, sy - y0 as f64);
            for c in 0..3 {
                let v = at(x0, y0, c) * (1.0 - ax) * (1.0 - ay)
                    + at(x0 + 1, y0, c) * ax * (1.0 - ay)
                    + at(x0, y0 + 1, c) * (1.0 - ax) * ay
                    + at(x0 + 1, y0 + 1, c) * ax * ay;
                out[((j * size + i) * 3) as usize + c] = v.round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    Crop { size, rgb: out }
}
