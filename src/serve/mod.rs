//! The gRPC service: transport only. Requests are validated into engine calls, the image encoder
//! is batched across concurrent requests, and engine errors become named status codes. The maths
//! lives in [`crate::engine`].

pub mod admission;
pub mod auth;
pub mod batcher;
pub mod heads;
pub mod observe;
pub mod server;
pub mod status;
pub mod transport;

use std::collections::BTreeMap;
use std::pin::Pin;
use std::sync::{Arc, RwLock};
use std::time::Instant;

use tokio_stream::Stream;
use tonic::{Request, Response, Status};

pub use batcher::{BatchConfig, BatchError, Batcher};

use crate::engine::{
    Cancel, CheckedPredict, CropBox, CropDepth, DepthRequest, Detection, Engine, FrameQuery,
    ImageRequest, Model, PredictOptions, SeenPoints,
};

/// Generated protobuf types and the service's file descriptor set (for reflection).
#[allow(missing_docs, clippy::all)]
pub mod proto {
    tonic::include_proto!("alignist.v1");
    /// The encoded `FileDescriptorSet` of `alignist.proto`.
    pub const FILE_DESCRIPTOR_SET: &[u8] =
        include_bytes!(concat!(env!("OUT_DIR"), "/alignist_descriptor.bin"));
}

use proto::alignist_server::Alignist;
use proto::*;

/// Most cells per distribution chunk.
pub const MAX_CHUNK: u32 = 65_536;
/// Default cells per distribution chunk.
pub const DEFAULT_CHUNK: u32 = 16_384;

/// An engine with its workers: what the service answers with. Replaced whole on reload.
pub struct Served {
    /// The models.
    pub engine: Engine,
    batchers: BTreeMap<String, Batcher>,
    heads: BTreeMap<String, heads::HeadStage>,
}

impl Served {
    /// Starts a batcher (an encoder thread) and a head stage (a pool of head threads) per model.
    pub fn new(engine: Engine, batch: BatchConfig) -> std::io::Result<Served> {
        Self::reloaded(engine, None, batch)
    }

    /// What a reload serves: the newly loaded models with new batchers, and, for each bundle that
    /// failed to load now but was served before, the previous model with its running batcher.
    pub fn reloaded(
        mut engine: Engine,
        previous: Option<&Served>,
        batch: BatchConfig,
    ) -> std::io::Result<Served> {
        let mut kept = BTreeMap::new();
        if let Some(previous) = previous {
            let failed: Vec<String> = engine.failures().keys().cloned().collect();
            for name in failed {
                if let (Ok(model), Some(batcher), Some(head)) = (
                    previous.engine.model(&name),
                    previous.batchers.get(&name),
                    previous.heads.get(&name),
                ) {
                    engine.keep_previous(model);
                    kept.insert(name, (batcher.clone(), head.clone()));
                }
            }
        }
        let (mut batchers, mut heads) = (BTreeMap::new(), BTreeMap::new());
        for m in engine.models() {
            let (b, h) = match kept.remove(&m.name) {
                Some(workers) => workers,
                None => (
                    Batcher::start(m.clone(), batch)?,
                    heads::HeadStage::start(m.clone(), batch, batch.head_workers)?,
                ),
            };
            batchers.insert(m.name.clone(), b);
            heads.insert(m.name.clone(), h);
        }
        Ok(Served {
            engine,
            batchers,
            heads,
        })
    }
}

/// The shared, swappable state of the service.
#[derive(Clone, Default)]
pub struct ServiceState {
    served: Arc<RwLock<Option<Arc<Served>>>>,
}

impl ServiceState {
    /// Installs (or replaces) what is served, and says which model versions serve
    /// (`alignist_model_info{model,sha256} 1`, 0 for versions no longer served).
    pub fn install(&self, served: Served) {
        let mut slot = self.served.write().unwrap_or_else(|e| e.into_inner());
        if let Some(old) = slot.as_ref() {
            for m in old.engine.models() {
                metrics::gauge!("alignist_model_info", "model" => m.name.clone(), "sha256" => m.version().to_string())
                    .set(0.0);
            }
        }
        for m in served.engine.models() {
            metrics::gauge!("alignist_model_info", "model" => m.name.clone(), "sha256" => m.version().to_string())
                .set(1.0);
            if let Some(c) = m.calibration() {
                let model = m.name.clone();
                metrics::gauge!("alignist_search_predicted_ms", "model" => model.clone())
                    .set(c.predicted_ms);
                metrics::gauge!("alignist_search_measured_ms", "model" => model.clone())
                    .set(c.measured_ms);
                metrics::gauge!("alignist_search_keep", "model" => model.clone())
                    .set(c.chosen.keep as f64);
                metrics::gauge!("alignist_search_within_budget", "model" => model)
                    .set(if c.within_budget { 1.0 } else { 0.0 });
            }
        }
        *slot = Some(Arc::new(served));
    }

    /// What is served now, if anything (for reloads).
    pub fn installed(&self) -> Option<Arc<Served>> {
        self.served
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// What is served now, or UNAVAILABLE while models load.
    pub fn current(&self) -> Result<Arc<Served>, Status> {
        self.served
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
            .ok_or_else(status::models_loading)
    }
}

/// The `alignist.v1.Alignist` service.
pub struct AlignistService {
    state: ServiceState,
    admission: admission::Admission,
}

impl AlignistService {
    /// A service over `state` with the default admission limits.
    pub fn new(state: ServiceState) -> Self {
        Self::with_admission(state, admission::AdmissionConfig::default())
    }

    /// A service over `state` admitting at most what `admission` allows in flight.
    pub fn with_admission(state: ServiceState, admission: admission::AdmissionConfig) -> Self {
        Self {
            state,
            admission: admission::Admission::new(admission),
        }
    }
}

use status::invalid_field;
pub use status::{batch_status, status_of};

/// Runs CPU work off the async threads; a panic inside becomes INTERNAL (and is counted), never
/// a crash. The work gets a [`Cancel`] that is set when this future is dropped (the caller went
/// away: cancelled, deadline): work not yet started is skipped, and long work stops at its next
/// chunk or level boundary.
async fn blocking<T: Send + 'static>(
    work: impl FnOnce(&Cancel) -> Result<T, Status> + Send + 'static,
) -> Result<T, Status> {
    let cancel = Cancel::new();
    let guard = cancel.on_drop();
    let result = tokio::task::spawn_blocking(move || {
        if cancel.is_cancelled() {
            metrics::counter!("alignist_abandoned_work_total").increment(1);
            return Err(Status::cancelled("the caller went away"));
        }
        work(&cancel)
    })
    .await
    .map_err(|e| {
        if e.is_panic() {
            metrics::counter!("alignist_worker_panics_total", "worker" => "head").increment(1);
        }
        status::refused(
            tonic::Code::Internal,
            status::Reason::ModelFailed,
            format!("computation failed: {e}"),
            None,
        )
    })?;
    guard.disarm();
    result
}

/// The validated parts common to Predict and PredictDistribution.
struct Prepared {
    model: Arc<Model>,
    object: Option<usize>,
    /// The depth points, when depth was given.
    depth: Option<CropDepth>,
    batcher: Batcher,
    head: heads::HeadStage,
    image: ImageInput,
    /// The call's share of the in-flight budget, held until it is answered.
    _admitted: admission::Admitted,
}

fn required_image(image: Option<ImageInput>) -> Result<ImageInput, Status> {
    image.ok_or_else(|| invalid_field("image", "is required"))
}

/// The box of `whole` (pixels) or `fractional` (sub-pixel), at most one of them set; `field`
/// names the pair.
fn box_of(
    whole: Option<proto::CropBox>,
    fractional: Option<proto::PixelBox>,
    field: &str,
) -> Result<Option<CropBox>, Status> {
    match (whole, fractional) {
        (Some(_), Some(_)) => Err(invalid_field(field, "set one of the two boxes, not both")),
        (Some(c), None) => Ok(Some(CropBox::pixels(c.x, c.y, c.width, c.height))),
        (None, Some(b)) => Ok(Some(CropBox {
            x: b.x,
            y: b.y,
            width: b.width,
            height: b.height,
        })),
        (None, None) => Ok(None),
    }
}

fn crop_of(image: &ImageInput) -> Result<Option<CropBox>, Status> {
    box_of(image.crop, image.crop_box, "image.crop")
}

fn raw_size(image: &ImageInput) -> Result<Option<(u32, u32)>, Status> {
    match (image.width, image.height) {
        (0, 0) => Ok(None),
        (w, h) if w > 0 && h > 0 => Ok(Some((w, h))),
        (w, h) => Err(invalid_field(
            "image.width",
            format!(
                "image.width and image.height must both be set for raw RGB8 or both 0 for \
                 PNG/JPEG (got {w}×{h})"
            ),
        )),
    }
}

fn prepare(
    served: &Served,
    admission: &admission::Admission,
    model: &str,
    object: &str,
    image: Option<ImageInput>,
    depth: Option<DepthPoints>,
) -> Result<Prepared, Status> {
    let model = served.engine.model(model).map_err(status_of)?;
    let image = required_image(image)?;
    let admitted = admission.admit(admission::image_cost(&image.data, raw_size(&image)?))?;
    let object = match (&depth, object.is_empty()) {
        (None, true) => None,
        _ => Some(model.object_index(object).map_err(status_of)?),
    };
    let depth = match (depth, object) {
        (Some(d), Some(i)) => Some(CropDepth {
            object: i,
            points: SeenPoints::Centred(
                model.objects[i]
                    .fusion
                    .parse_points(&d.xyz, model.config().max_depth_points)
                    .map_err(status_of)?,
            ),
        }),
        _ => None,
    };
    let batcher = batcher_of(served, &model)?;
    let head = head_of(served, &model)?;
    Ok(Prepared {
        model,
        object,
        depth,
        batcher,
        head,
        image,
        _admitted: admitted,
    })
}

/// Decodes the image off the async threads and encodes it through the batcher.
async fn encode(p: &mut Prepared) -> Result<batcher::Encoded, Status> {
    let model = p.model.clone();
    let image = std::mem::take(&mut p.image);
    let crop = blocking(move |_| {
        let request = ImageRequest {
            data: &image.data,
            raw_size: raw_size(&image)?,
            crop: crop_of(&image)?,
        };
        model.prepare(&request).map_err(status_of)
    })
    .await?;
    let encoded = p.batcher.encode(crop).await.map_err(batch_status)?;
    metrics::histogram!("alignist_queue_seconds").record(encoded.queued.as_secs_f64());
    Ok(encoded)
}

/// A typed rotation from a unit quaternion `(w, x, y, z)`.
fn rotation_message(q: [f64; 4]) -> proto::Rotation {
    let r = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
        q[0], q[1], q[2], q[3],
    ))
    .to_rotation_matrix();
    let m = r.matrix();
    proto::Rotation {
        w: q[0],
        x: q[1],
        y: q[2],
        z: q[3],
        matrix: (0..9).map(|i| m[(i / 3, i % 3)]).collect(),
    }
}

// The deprecated `quaternion` fields are still filled, for clients built before `rotation`.
#[allow(deprecated)]
fn rotation_probability(
    level: u8,
    cell: &crate::engine::CellProbability,
    q: [f64; 4],
    translation: Option<&[f64; 3]>,
) -> RotationProbability {
    RotationProbability {
        quaternion: q.to_vec(),
        probability: cell.probability,
        log_density: cell.log_density,
        level: level as u32,
        cell: cell.cell,
        rotation: Some(rotation_message(q)),
        translation: translation.map(|t| proto::Vector3 {
            x: t[0],
            y: t[1],
            z: t[2],
        }),
    }
}

#[allow(deprecated)]
fn mode_message(m: &crate::engine::search::Mode) -> proto::Mode {
    proto::Mode {
        quaternion: m.quaternion.to_vec(),
        probability: m.probability,
        spread_deg: m.spread_deg,
        cells: m.cells as u32,
        rotation: Some(rotation_message(m.quaternion)),
    }
}

/// The Predict answer of one image.
fn predict_response(
    model: &Model,
    object: Option<usize>,
    level: u8,
    prediction: &crate::engine::Prediction,
    depth_fused: bool,
    started: Instant,
    queued: std::time::Duration,
) -> PredictResponse {
    let top: Vec<RotationProbability> = prediction
        .top
        .iter()
        .zip(&prediction.rotations)
        .enumerate()
        .map(|(i, (c, q))| rotation_probability(level, c, *q, prediction.translations.get(i)))
        .collect();
    PredictResponse {
        model: model.name.clone(),
        object: object
            .map(|i| model.objects[i].name.clone())
            .unwrap_or_default(),
        map: top.first().cloned(),
        top,
        modes: prediction.modes.iter().map(mode_message).collect(),
        covered_mass: prediction.covered_mass,
        depth_fused,
        compute_ms: started.elapsed().saturating_sub(queued).as_secs_f64() * 1e3,
        queue_ms: queued.as_secs_f64() * 1e3,
        model_version: model.version().to_string(),
    }
}

/// The options of Predict and PredictFrame, validated.
fn predict_options(top_k: u32, level: u32, mode_angle_deg: f32) -> Result<PredictOptions, Status> {
    if !mode_angle_deg.is_finite() {
        return Err(invalid_field(
            "mode_angle_deg",
            "must be a finite number of degrees",
        ));
    }
    Ok(PredictOptions {
        top_k: top_k as usize,
        level: match level {
            0 => None,
            l => Some(small_level(l, "level")?),
        },
        mode_angle_deg: (mode_angle_deg != 0.0).then_some(mode_angle_deg as f64),
        ..Default::default()
    })
}

/// The encoder batcher of a loaded model.
fn batcher_of(served: &Served, model: &Model) -> Result<Batcher, Status> {
    served.batchers.get(&model.name).cloned().ok_or_else(|| {
        status::refused(
            tonic::Code::Internal,
            status::Reason::ModelFailed,
            format!("model '{}' has no batcher", model.name),
            None,
        )
    })
}

/// The head stage of a loaded model.
fn head_of(served: &Served, model: &Model) -> Result<heads::HeadStage, Status> {
    served.heads.get(&model.name).cloned().ok_or_else(|| {
        status::refused(
            tonic::Code::Internal,
            status::Reason::ModelFailed,
            format!("model '{}' has no head stage", model.name),
            None,
        )
    })
}

/// Most detections in one PredictFrame request.
pub use crate::engine::MAX_DETECTIONS;

fn small_level(value: u32, field: &str) -> Result<u8, Status> {
    u8::try_from(value)
        .ok()
        .filter(|&l| l <= crate::so3::MAX_LEVEL)
        .ok_or_else(|| {
            invalid_field(
                field,
                format!(
                    "{value} is above the highest grid level {}",
                    crate::so3::MAX_LEVEL
                ),
            )
        })
}

impl AlignistService {
    async fn do_predict(&self, req: PredictRequest) -> Result<PredictResponse, Status> {
        let started = Instant::now();
        let served = self.state.current()?;
        let mut p = prepare(
            &served,
            &self.admission,
            &req.model,
            &req.object,
            req.image,
            req.depth,
        )?;
        let options = predict_options(req.top_k, req.level, req.mode_angle_deg)?;
        let checked = p.model.check_predict(&options).map_err(status_of)?;
        let level = checked.level();
        let encoded = encode(&mut p).await?;
        let (features, queued) = (encoded.features, encoded.queued);
        let depth = p.depth.take();
        let fused = depth.is_some();
        let compute = Instant::now();
        let prediction = p.head.predict(features, checked, depth).await?;
        metrics::histogram!("alignist_compute_seconds", "method" => "Predict")
            .record(compute.elapsed().as_secs_f64());
        Ok(predict_response(
            &p.model,
            p.object,
            level,
            &prediction,
            fused,
            started,
            queued,
        ))
    }

    async fn do_frame(&self, req: FrameRequest) -> Result<FrameResponse, Status> {
        let started = Instant::now();
        let served = self.state.current()?;
        let model = served.engine.model(&req.model).map_err(status_of)?;
        let image = required_image(req.image)?;
        let depth_bytes = req.depth.as_ref().map_or(0, |d| {
            let raw = (d.width > 0 && d.height > 0).then_some((d.width, d.height));
            admission::image_cost(&d.data, raw)
        });
        let _admitted = self.admission.admit(
            admission::image_cost(&image.data, raw_size(&image)?).saturating_add(depth_bytes),
        )?;
        let intrinsics = frame_intrinsics(req.intrinsics)?;
        let boxes = detection_boxes(&req.detections)?;
        let options = predict_options(req.top_k, req.level, req.mode_angle_deg)?;
        let checked = model
            .check_frame(boxes.len(), &options)
            .map_err(status_of)?;
        let level = checked.level();
        let batcher = batcher_of(&served, &model)?;
        let head = head_of(&served, &model)?;
        let whole: Vec<_> = req.detections.iter().map(|d| d.r#box).collect();
        let mut plan = {
            let (model, detections, depth) = (model.clone(), req.detections, req.depth);
            blocking(move |_| {
                let query = FrameQuery {
                    image: ImageRequest {
                        data: &image.data,
                        raw_size: raw_size(&image)?,
                        crop: crop_of(&image)?,
                    },
                    intrinsics,
                    detections: detections
                        .iter()
                        .zip(boxes)
                        .map(|(d, bbox)| Detection {
                            bbox,
                            object: &d.object,
                            mask: (!d.mask.is_empty()).then_some(&d.mask[..]),
                        })
                        .collect(),
                    depth: depth.as_ref().map(depth_request).transpose()?,
                };
                model.plan_frame(&query).map_err(status_of)
            })
            .await?
        };
        let encoded = batcher
            .encode_many(std::mem::take(&mut plan.crops))
            .await
            .map_err(batch_status)?;
        for e in &encoded {
            metrics::histogram!("alignist_queue_seconds").record(e.queued.as_secs_f64());
        }
        let queued = encoded.iter().map(|e| e.queued).max().unwrap_or_default();
        let compute = Instant::now();
        let predictions = predict_boxes(&head, encoded, &plan.depth, &checked).await?;
        let predictions = plan.in_camera_frame(predictions);
        metrics::histogram!("alignist_compute_seconds", "method" => "PredictFrame")
            .record(compute.elapsed().as_secs_f64());
        let detections = plan
            .boxes
            .iter()
            .zip(whole)
            .zip(predictions)
            .enumerate()
            .map(|(i, ((b, whole), p))| DetectionPrediction {
                r#box: whole,
                bbox: Some(proto::PixelBox {
                    x: b.x,
                    y: b.y,
                    width: b.width,
                    height: b.height,
                }),
                prediction: Some(predict_response(
                    &model,
                    plan.objects[i],
                    level,
                    &p,
                    plan.depth[i].is_some(),
                    started,
                    queued,
                )),
                ray: Some(rotation_message(crate::so3::to_quaternion(&plan.rays[i]))),
            })
            .collect();
        Ok(FrameResponse {
            model: model.name.clone(),
            model_version: model.version().to_string(),
            detections,
            compute_ms: started.elapsed().as_secs_f64() * 1e3,
        })
    }
}

/// The frame's intrinsics, required (the engine checks their values).
fn frame_intrinsics(
    intrinsics: Option<proto::Intrinsics>,
) -> Result<crate::engine::Intrinsics, Status> {
    let i = intrinsics.ok_or_else(|| invalid_field("intrinsics", "is required"))?;
    Ok(crate::engine::Intrinsics {
        fx: i.fx,
        fy: i.fy,
        cx: i.cx,
        cy: i.cy,
    })
}

/// The box of each detection (`box` or `bbox`, one of them required).
fn detection_boxes(detections: &[proto::Detection]) -> Result<Vec<CropBox>, Status> {
    detections
        .iter()
        .enumerate()
        .map(|(i, d)| {
            let field = format!("detections[{i}].box");
            box_of(d.r#box, d.bbox, &field)?
                .ok_or_else(|| invalid_field(&field, "is required (box or bbox)"))
        })
        .collect()
}

/// A frame's depth image as the engine reads it.
fn depth_request(depth: &proto::DepthImage) -> Result<DepthRequest<'_>, Status> {
    let raw_size = match (depth.width, depth.height) {
        (0, 0) => None,
        (w, h) if w > 0 && h > 0 => Some((w, h)),
        (w, h) => {
            return Err(invalid_field(
                "depth.width",
                format!(
                    "depth.width and depth.height must both be set for raw u16 or both 0 for \
                     PNG (got {w}×{h})"
                ),
            ));
        }
    };
    Ok(DepthRequest {
        data: &depth.data,
        raw_size,
        scale: depth.scale,
    })
}

/// Every box's prediction (in its crop camera's frame): their head work is queued at once, so
/// that the boxes share the head stage's workers.
async fn predict_boxes(
    head: &heads::HeadStage,
    encoded: Vec<batcher::Encoded>,
    depth: &[Option<CropDepth>],
    options: &CheckedPredict,
) -> Result<Vec<crate::engine::Prediction>, Status> {
    /// Aborts the boxes' head calls when the frame call is dropped (its caller went away):
    /// an aborted call drops its future, which cancels its search.
    struct AbortOnDrop(Vec<tokio::task::JoinHandle<Result<crate::engine::Prediction, Status>>>);
    impl Drop for AbortOnDrop {
        fn drop(&mut self) {
            self.0.iter().for_each(|c| c.abort());
        }
    }
    let mut calls = AbortOnDrop(
        encoded
            .into_iter()
            .zip(depth.iter().cloned())
            .map(|(e, depth)| {
                let (head, options) = (head.clone(), options.clone());
                tokio::spawn(async move { head.predict(e.features, options, depth).await })
            })
            .collect(),
    );
    let mut predictions = Vec::with_capacity(calls.0.len());
    for call in calls.0.iter_mut() {
        let p = call.await.map_err(|e| {
            status::refused(
                tonic::Code::Internal,
                status::Reason::ModelFailed,
                format!("computation failed: {e}"),
                None,
            )
        })??;
        predictions.push(p);
    }
    Ok(predictions)
}

type ChunkStream = Pin<Box<dyn Stream<Item = Result<DistributionChunk, Status>> + Send>>;

#[tonic::async_trait]
impl Alignist for AlignistService {
    async fn predict(
        &self,
        request: Request<PredictRequest>,
    ) -> Result<Response<PredictResponse>, Status> {
        self.do_predict(request.into_inner())
            .await
            .map(Response::new)
    }

    type PredictDistributionStream = ChunkStream;

    async fn predict_distribution(
        &self,
        request: Request<DistributionRequest>,
    ) -> Result<Response<Self::PredictDistributionStream>, Status> {
        self.do_distribution(request.into_inner())
            .await
            .map(Response::new)
    }

    async fn predict_frame(
        &self,
        request: Request<FrameRequest>,
    ) -> Result<Response<FrameResponse>, Status> {
        self.do_frame(request.into_inner()).await.map(Response::new)
    }

    async fn list_models(
        &self,
        _request: Request<ListModelsRequest>,
    ) -> Result<Response<ListModelsResponse>, Status> {
        let served = self.state.current()?;
        Ok(Response::new(ListModelsResponse {
            models: served.engine.models().map(|m| model_info(m)).collect(),
            failed: served
                .engine
                .failures()
                .iter()
                .map(|(name, error)| ModelFailure {
                    name: name.clone(),
                    error: error.clone(),
                    serving_previous: served.engine.model(name).is_ok(),
                })
                .collect(),
        }))
    }

    async fn get_model(
        &self,
        request: Request<GetModelRequest>,
    ) -> Result<Response<ModelInfo>, Status> {
        let name = request.into_inner().name;
        let served = self.state.current()?;
        if name.is_empty() {
            return Err(invalid_field("name", "is required"));
        }
        served
            .engine
            .model(&name)
            .map(|m| Response::new(model_info(&m)))
            .map_err(status_of)
    }
}

impl AlignistService {
    async fn do_distribution(&self, req: DistributionRequest) -> Result<ChunkStream, Status> {
        let served = self.state.current()?;
        let mut p = prepare(
            &served,
            &self.admission,
            &req.model,
            &req.object,
            req.image,
            req.depth,
        )?;
        // 0 is the default, as in Predict (level 0's 72 cells are not served).
        let level = match req.level {
            0 => p.model.config().max_full_level.min(4),
            l => small_level(l, "level")?,
        };
        p.model.check_full_level(level).map_err(status_of)?;
        let chunk = match req.chunk_size {
            0 => DEFAULT_CHUNK,
            c if c > MAX_CHUNK => {
                return Err(invalid_field(
                    "chunk_size",
                    format!("{c} is above the limit of {MAX_CHUNK} cells"),
                ));
            }
            c => c,
        } as usize;
        let features = encode(&mut p).await?.features;
        let compute = Instant::now();
        let distribution = p.head.distribution(features, level, p.depth.take()).await?;
        metrics::histogram!("alignist_compute_seconds", "method" => "PredictDistribution")
            .record(compute.elapsed().as_secs_f64());
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        let (name, version) = (p.model.name.clone(), p.model.version().to_string());
        tokio::spawn(async move {
            let total = distribution.probability.len();
            for start in (0..total).step_by(chunk) {
                let end = (start + chunk).min(total);
                let message = DistributionChunk {
                    level: level as u32,
                    total_cells: total as u64,
                    offset: start as u64,
                    probability: distribution.probability[start..end].to_vec(),
                    log_density: distribution.log_density[start..end].to_vec(),
                    model: name.clone(),
                    model_version: version.clone(),
                };
                // The caller went away: stop producing.
                if tx.send(Ok(message)).await.is_err() {
                    break;
                }
            }
        });
        Ok(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx)))
    }
}

/// What ListModels / GetModel say about an object: its symmetry as a group label (the rotations
/// for finite groups, the axis for rotations about one axis) and its frame.
pub fn object_info(o: &crate::engine::ModelObject) -> ObjectInfo {
    let vector = |v: [f64; 3]| proto::Vector3 {
        x: v[0],
        y: v[1],
        z: v[2],
    };
    let group = o.symmetry_group;
    let finite = !group.is_some_and(|g| g.is_continuous());
    ObjectInfo {
        name: o.name.clone(),
        symmetry: group.map_or_else(|| "custom".to_string(), |g| g.to_string()),
        train_images: o.train_images as u64,
        symmetry_rotations: if finite {
            o.symmetries
                .iter()
                .map(|r| rotation_message(crate::so3::to_quaternion(r)))
                .collect()
        } else {
            Vec::new()
        },
        symmetry_axis: group
            .and_then(|g| g.axis())
            .map(|a| vector([a.x, a.y, a.z])),
        frame_centre: Some(vector(o.normalisation.centre)),
        frame_scale: o.normalisation.scale,
        discovered_symmetry: o
            .discovered
            .as_ref()
            .map_or_else(String::new, |d| d.label.clone()),
        discovered_axes: o
            .discovered
            .iter()
            .flat_map(|d| d.axes.iter().map(|a| vector(*a)))
            .collect(),
        discovered_confidence: o.discovered.as_ref().map_or(0.0, |d| d.confidence),
        near_symmetry: o
            .discovered
            .as_ref()
            .and_then(|d| d.near.as_ref())
            .map_or_else(String::new, |n| n.label.clone()),
        frame_units: o.normalisation.units.to_string(),
    }
}

/// What ListModels / GetModel say about a model.
pub fn model_info(model: &Model) -> ModelInfo {
    let m = &model.manifest;
    let eval = m.evaluation.as_ref();
    let method = match m.provenance.train.method {
        crate::bundle::record::Method::Alignist { .. } => "alignist",
        crate::bundle::record::Method::Ipdf => "ipdf",
    };
    ModelInfo {
        name: model.name.clone(),
        objects: model.objects.iter().map(object_info).collect(),
        input_size: model.input_size(),
        full_max_level: model.config().max_full_level as u32,
        search_max_level: model.config().search_max_level as u32,
        training: Some(TrainingFigures {
            method: method.into(),
            steps: m.provenance.train.steps as u64,
            command: m.provenance.command.clone(),
            eval_level: eval.map_or(0, |e| e.level as u32),
            log_likelihood: eval.map_or(f64::NAN, |e| e.overall.log_likelihood),
            spread_deg: eval.map_or(f64::NAN, |e| e.overall.spread_deg),
            accuracy_at_30: eval
                .and_then(|e| e.overall.accuracy_at.first().map(|a| a.1))
                .unwrap_or(f64::NAN),
            median_error_deg: eval.map_or(f64::NAN, |e| e.overall.median_error_deg),
        }),
        network_sha256: m
            .files
            .get(crate::bundle::model::NETWORK_FILE)
            .map(|f| f.sha256.clone())
            .unwrap_or_default(),
        search: Some(search_info(model)),
    }
}

/// The default search a model serves, and how it was chosen.
fn search_info(model: &Model) -> SearchInfo {
    let search = model.config().search();
    let c = model.calibration();
    SearchInfo {
        start_level: search.start_level as u32,
        keep: search.keep as u32,
        keep_taper: search.keep_taper,
        keep_mass: search.keep_mass.unwrap_or(0.0),
        coarse_precision: search.coarse_precision.name().into(),
        rescore_finest: search.rescores(),
        shape_only_to: search.shape_only_to.map(u32::from),
        chosen_by: if c.is_some() {
            "calibration"
        } else {
            "configuration"
        }
        .into(),
        agreement: c.and_then(|c| c.agreement).unwrap_or(f64::NAN),
        predicted_ms: c.map_or(f64::NAN, |c| c.predicted_ms),
        measured_ms: c.map_or(f64::NAN, |c| c.measured_ms),
        budget_ms: c.map_or(f64::NAN, |c| c.budget_ms),
        within_budget: c.is_some_and(|c| c.within_budget),
        reason: c.map(|c| c.reason.clone()).unwrap_or_default(),
        kernels: model.kernel_paths(),
    }
}
