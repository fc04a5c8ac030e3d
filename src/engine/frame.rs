//! The depth side of a camera frame: each detection's depth pixels, back-projected with the
//! frame's intrinsics, in the normalised units of its object and the frame of its crop's virtual
//! camera (`R_rayᵀ·p`), where the engine's rotations live.

use nalgebra::Rotation3;

use super::{
    CropBox, DepthInput, DepthRequest, EngineError, Intrinsics, Model, SeenPoints, back_project,
    decode_depth, decode_mask,
};

/// The depth of one crop: the object its points belong to (its index in the model) and the
/// points, in the crop camera's frame.
#[derive(Debug, Clone)]
pub struct CropDepth {
    /// The object's index in the model.
    pub object: usize,
    /// The points.
    pub points: SeenPoints,
}

impl CropDepth {
    /// The engine's depth input for this crop, of `model`.
    pub fn input<'a>(&'a self, model: &'a Model) -> DepthInput<'a> {
        DepthInput {
            object: &model.objects[self.object],
            points: &self.points,
        }
    }
}

/// One detection of a frame, as its depth is read: its box, its mask (PNG bytes, if any), its
/// object and the ray of its crop's virtual camera.
#[derive(Debug, Clone, Copy)]
pub struct DetectionDepth<'a> {
    /// The box, in the frame's pixels.
    pub bbox: &'a CropBox,
    /// A mask of the object's pixels, the frame's size (PNG), or `None` for the whole box.
    pub mask: Option<&'a [u8]>,
    /// The object's index in the model.
    pub object: usize,
    /// `R_ray` of the detection's crop.
    pub ray: &'a Rotation3<f64>,
}

impl Model {
    /// The depth points of every detection of a frame from its depth image (registered to the
    /// colour image of `image_size`): the valid pixels inside each box (and mask),
    /// back-projected with `intrinsics`, turned into the crop's virtual camera. Errors name the
    /// request's fields (`depth.data`, `detections[i].mask`, `detections[i].box`, `depth.scale`).
    pub fn frame_depth(
        &self,
        depth: &DepthRequest<'_>,
        image_size: (u32, u32),
        intrinsics: &Intrinsics,
        detections: &[DetectionDepth<'_>],
    ) -> Result<Vec<CropDepth>, EngineError> {
        let limits = &self.config().image_limits;
        let map = decode_depth(depth, limits)?;
        if (map.width, map.height) != image_size {
            return Err(EngineError::InvalidArgument {
                field: "depth.data".into(),
                message: format!(
                    "is {}×{}, not the image's {}×{}: the depth image must be registered to the \
                     colour image",
                    map.width, map.height, image_size.0, image_size.1
                ),
            });
        }
        detections
            .iter()
            .enumerate()
            .map(|(i, d)| {
                let mask = d
                    .mask
                    .map(|m| {
                        let field = format!("detections[{i}].mask");
                        decode_mask(m, map.width, map.height, limits, &field)
                    })
                    .transpose()?;
                let points = back_project(
                    &map,
                    intrinsics,
                    d.bbox,
                    mask.as_deref(),
                    self.config().depth_image_points,
                    &format!("detections[{i}].box"),
                )?;
                let seen = self.objects[d.object]
                    .fusion
                    .camera_points(&points, "depth.scale")?;
                let to_virtual = d.ray.inverse().cast::<f32>();
                Ok(CropDepth {
                    object: d.object,
                    points: SeenPoints::Camera(seen.turned(&to_virtual)),
                })
            })
            .collect()
    }
}
