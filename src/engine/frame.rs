//! A camera frame (docs/DESIGN.md §1, crops): each detection's perspective crop and the ray of
//! its virtual camera, its depth pixels back-projected with the frame's intrinsics (in the
//! normalised units of its object and the crop camera's frame, `R_rayᵀ·p`, where the engine's
//! rotations live), and the answers turned back into the real camera's frame.

use nalgebra::Rotation3;

use super::{
    CheckedPredict, CropBox, DepthInput, DepthRequest, EngineError, ImageRequest, Intrinsics,
    MAX_TOP_K, Model, PredictOptions, Prediction, SeenPoints, back_project, decode_depth,
    decode_mask, invalid,
};

/// Most detections in one frame.
pub const MAX_DETECTIONS: usize = 32;

/// One detection of a frame, as a detector gives it.
#[derive(Debug, Clone, Copy)]
pub struct Detection<'a> {
    /// The box, in the frame's pixels (it may reach beyond the frame: a truncated object).
    pub bbox: CropBox,
    /// The object's name; empty when not named (then the model's only object, with depth).
    pub object: &'a str,
    /// A mask of the object's pixels, the frame's size (PNG), or `None` for the whole box.
    pub mask: Option<&'a [u8]>,
}

/// A camera frame and what to find in it: the engine's frame request, without transport types.
#[derive(Debug, Clone)]
pub struct FrameQuery<'a> {
    /// The colour image (whole: `crop` must be unset).
    pub image: ImageRequest<'a>,
    /// Its intrinsics.
    pub intrinsics: Intrinsics,
    /// 1 ..= [`MAX_DETECTIONS`] detections.
    pub detections: Vec<Detection<'a>>,
    /// A depth image registered to the colour image, when there is one.
    pub depth: Option<DepthRequest<'a>>,
}

/// A frame's detections made ready for the encoder and the head, in the order given.
#[derive(Debug, Clone)]
pub struct FramePlan {
    /// Each detection's crop, the model's input.
    pub crops: Vec<Vec<u8>>,
    /// The boxes as they were cropped.
    pub boxes: Vec<CropBox>,
    /// `R_ray` of each crop's virtual camera (`R_camera = R_ray · R_virtual`).
    pub rays: Vec<Rotation3<f64>>,
    /// Each detection's depth points, with a depth image.
    pub depth: Vec<Option<CropDepth>>,
    /// The object each answer is for: the depth's, else the one named, else none.
    pub objects: Vec<Option<usize>>,
}

impl FramePlan {
    /// The crops' answers (box order) in the real camera's frame
    /// ([`Prediction::in_camera_frame`]).
    pub fn in_camera_frame(&self, predictions: Vec<Prediction>) -> Vec<Prediction> {
        predictions
            .into_iter()
            .zip(&self.rays)
            .map(|(p, ray)| p.in_camera_frame(ray))
            .collect()
    }
}

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
    /// Checks a frame's size before any work: 1 ..= [`MAX_DETECTIONS`] detections, and no more
    /// rotations in the answer than one Predict may return; returns the finest level.
    pub fn check_frame(
        &self,
        detections: usize,
        options: &PredictOptions,
    ) -> Result<CheckedPredict, EngineError> {
        if detections == 0 || detections > MAX_DETECTIONS {
            return Err(invalid(
                "detections",
                format!("give 1 ..= {MAX_DETECTIONS} boxes, got {detections}"),
            ));
        }
        let checked = self.check_predict(options)?;
        if options.top_k.saturating_mul(detections) > MAX_TOP_K {
            return Err(invalid(
                "top_k",
                format!(
                    "{} rotations for each of {detections} detections is over the limit of \
                     {MAX_TOP_K} rotations in one answer",
                    options.top_k
                ),
            ));
        }
        Ok(checked)
    }

    /// The objects the detections name (`None` where unnamed). Errors name
    /// `detections[i].object`.
    fn detection_objects(&self, query: &FrameQuery<'_>) -> Result<Vec<Option<usize>>, EngineError> {
        query
            .detections
            .iter()
            .map(|d| match d.object.is_empty() {
                true => Ok(None),
                false => self.object_index(d.object).map(Some),
            })
            .collect()
    }

    /// Decodes the frame once and makes every detection's crop, ray and depth points
    /// ([`super::image::prepare_frame`], [`Model::frame_depth`]). With depth each detection needs
    /// its object (named, or the model's only one).
    pub fn plan_frame(&self, query: &FrameQuery<'_>) -> Result<FramePlan, EngineError> {
        let named = self.detection_objects(query)?;
        let boxes: Vec<CropBox> = query.detections.iter().map(|d| d.bbox).collect();
        let crops = self.prepare_frame(&query.image, &query.intrinsics, &boxes)?;
        let rays: Vec<Rotation3<f64>> = crops.iter().map(|c| c.r_ray).collect();
        let depth = match (&query.depth, crops.first()) {
            (Some(depth), Some(first)) => {
                let objects = named
                    .iter()
                    .enumerate()
                    .map(|(i, named)| match (named, self.objects.len()) {
                        (Some(o), _) => Ok(*o),
                        (None, 1) => Ok(0),
                        (None, n) => Err(invalid(
                            &format!("detections[{i}].object"),
                            format!("is required with depth: this model has {n} objects"),
                        )),
                    })
                    .collect::<Result<Vec<usize>, _>>()?;
                let detections: Vec<DetectionDepth<'_>> = query
                    .detections
                    .iter()
                    .enumerate()
                    .map(|(i, d)| DetectionDepth {
                        bbox: &boxes[i],
                        mask: d.mask,
                        object: objects[i],
                        ray: &rays[i],
                    })
                    .collect();
                self.frame_depth(depth, first.image_size, &query.intrinsics, &detections)?
                    .into_iter()
                    .map(Some)
                    .collect()
            }
            _ => vec![None; boxes.len()],
        };
        let objects = depth
            .iter()
            .zip(&named)
            .map(|(d, named)| d.as_ref().map(|d| d.object).or(*named))
            .collect();
        Ok(FramePlan {
            crops: crops.into_iter().map(|c| c.rgb).collect(),
            boxes,
            rays,
            depth,
            objects,
        })
    }

    /// Every detection's prediction in the real camera's frame, in-process: the frame planned,
    /// its crops encoded in one batch, each searched with its depth. (The server runs the same
    /// steps with the encoder and the head on their own workers.)
    pub fn predict_frame(
        &self,
        query: &FrameQuery<'_>,
        options: &PredictOptions,
    ) -> Result<(FramePlan, Vec<Prediction>), EngineError> {
        let checked = self.check_frame(query.detections.len(), options)?;
        let plan = self.plan_frame(query)?;
        let crops: Vec<&[u8]> = plan.crops.iter().map(Vec::as_slice).collect();
        let features = self.features(&crops)?;
        let depth: Vec<_> = plan
            .depth
            .iter()
            .map(|d| d.as_ref().map(|d| d.input(self)))
            .collect();
        let predictions = self.predict_checked(&features, &checked, &depth)?;
        let predictions = plan.in_camera_frame(predictions);
        Ok((plan, predictions))
    }

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
