//! The engine and the gRPC service over real loopback: a tiny bundle is made with the trainer's
//! CLI (render → experts → fit), then `alignist-server` is started as a process on ephemeral
//! ports and called with the generated client, health, reflection, Prometheus and signals.

mod common;

use std::process::Command;
use std::time::Duration;

use alignist::cad::Shape;
use alignist::engine::{
    DepthInput, Engine, EngineConfig, ImageRequest, PredictOptions, SeenPoints,
};
use alignist::serve::proto::alignist_client::AlignistClient;
use alignist::serve::proto::{
    CropBox, DepthPoints, DistributionRequest, GetModelRequest, ImageInput, ListModelsRequest,
    PredictRequest,
};
use alignist::so3::haar_rotations;
use common::*;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tonic::Code;
use tonic::transport::Channel;

/// A PNG through the model's own preparation: the crop its encoder takes.
fn prepared(model: &alignist::engine::Model, png: &[u8]) -> Vec<u8> {
    model
        .prepare(&ImageRequest {
            data: png,
            raw_size: None,
            crop: None,
        })
        .unwrap()
}

/// Image features of a PNG through the model's own preparation and encoder.
fn features_of(model: &alignist::engine::Model, png: &[u8]) -> Vec<f32> {
    model
        .features(&[&prepared(model, png)])
        .expect("crops of the input side")
        .swap_remove(0)
}

/// The engine's frame front door without a socket: each box's answer is the crop-only answer of
/// its planned crop, turned by its ray.
#[test]
fn the_engines_predict_frame_answers_each_planned_crop_in_the_camera_frame() {
    use alignist::engine::{Detection, FrameQuery, Intrinsics};
    let engine = Engine::load_dir(models_dir(), EngineConfig::default()).unwrap();
    let model = engine.model("tiny").unwrap();
    let r_cam = haar_rotations(&mut ChaCha8Rng::seed_from_u64(21), 1)[0];
    let (png, b, k) = frame_png(r_cam, 520.0, 130.0);
    let query = FrameQuery {
        image: ImageRequest {
            data: &png,
            raw_size: None,
            crop: None,
        },
        intrinsics: Intrinsics {
            fx: k[0],
            fy: k[4],
            cx: k[2],
            cy: k[5],
        },
        detections: [b, [20, 300, 90, 120]]
            .iter()
            .map(|b| Detection {
                bbox: alignist::engine::CropBox::pixels(b[0], b[1], b[2], b[3]),
                object: "",
                mask: None,
            })
            .collect(),
        depth: None,
    };
    let options = PredictOptions {
        top_k: 3,
        level: Some(3),
        ..Default::default()
    };
    let (plan, answers) = model.predict_frame(&query, &options).unwrap();
    assert_eq!((plan.crops.len(), answers.len()), (2, 2));
    for ((crop, ray), answer) in plan.crops.iter().zip(&plan.rays).zip(&answers) {
        let features = model
            .features(&[crop])
            .expect("crops of the input side")
            .swap_remove(0);
        let alone = model.predict(&features, &options, None).unwrap();
        let turned = alone.in_camera_frame(ray);
        // The frame's crops share one encoder batch: equal cells, probabilities within 1e-4.
        let cells =
            |p: &alignist::engine::Prediction| p.top.iter().map(|c| c.cell).collect::<Vec<_>>();
        assert_eq!(cells(answer), cells(&turned));
        for (a, t) in answer.top.iter().zip(&turned.top) {
            assert!((a.probability - t.probability).abs() <= 1e-4 * t.probability.max(1e-12));
        }
        for (a, t) in answer.rotations.iter().zip(&turned.rotations) {
            let angle = alignist::so3::quaternion_angle(a, t);
            assert!(angle < 1e-9, "{angle}");
        }
    }
}

#[test]
fn coarse_to_fine_top1_is_the_exhaustive_argmax_at_level_4() {
    let engine = Engine::load_dir(models_dir(), EngineConfig::default()).unwrap();
    let model = engine.model("tiny").unwrap();
    for seed in 0..3 {
        let features = features_of(&model, &cube_png(100 + seed));
        let full = model.distribution(&features, 4, None).unwrap();
        let total: f64 = full.probability.iter().map(|&p| p as f64).sum();
        assert!((total - 1.0).abs() < 1e-4, "{total}");
        let argmax = (0..full.probability.len())
            .max_by(|&a, &b| full.probability[a].total_cmp(&full.probability[b]))
            .unwrap() as u64;
        let options = PredictOptions {
            top_k: 5,
            level: Some(4),
            mode_angle_deg: None,
            ..Default::default()
        };
        let p = model.predict(&features, &options, None).unwrap();
        assert_eq!(p.top[0].cell, argmax, "seed {seed}");
        // The search's probabilities are those of the full distribution, rescaled by the mass it
        // kept; with 512 cells kept per level it keeps nearly all of it.
        let exact = full.probability[argmax as usize] as f64;
        assert!(
            (p.top[0].probability - exact).abs() <= 0.02 * exact + 1e-9,
            "{} vs {exact}",
            p.top[0].probability
        );
        assert!(p.covered_mass > 0.0 && p.covered_mass <= 1.0 + 1e-9);
    }
}

/// The bench's search study counts a search that scores every cell of the level as agreeing on
/// every image, and lists each image a one-cell search from level 0 disagrees on.
#[test]
fn the_search_study_counts_agreements_and_lists_disagreements() {
    use alignist::bench::search::study;
    use alignist::engine::SearchParams;
    let engine = Engine::load_dir(models_dir(), EngineConfig::default()).unwrap();
    let model = engine.model("tiny").unwrap();
    let crops: Vec<Vec<u8>> = (0..4)
        .map(|seed| prepared(&model, &cube_png(300 + seed)))
        .collect();
    let search = |start_level, keep| SearchParams {
        start_level,
        keep,
        keep_mass: None,
        keep_taper: 1.0,
        coarse_precision: alignist::net::Precision::F32,
        rescore_finest: false,
        shape_only_to: None,
    };
    // From level 2 keeping all 4 608 cells, level 3 is scored in full: the exhaustive argmax.
    let (figures, _) = study(
        &model,
        &crops,
        &[search(2, 4608), search(0, 1)],
        (3, 5),
        &[],
    )
    .unwrap();
    assert_eq!(figures[0].agreement, 1.0);
    assert!(figures[0].disagreements.is_empty());
    assert_eq!(figures[0].mean_gap, 0.0);
    let narrow = &figures[1];
    let agreed = (narrow.agreement * crops.len() as f64).round() as usize;
    assert_eq!(agreed + narrow.disagreements.len(), crops.len());
    for &(i, tied) in &narrow.disagreements {
        assert!(i < crops.len());
        // A disagreement "within 0.01 of the maximum" counts as a found maximum.
        if tied {
            assert!(narrow.found_maximum > 0.0);
        }
    }
}

#[test]
fn a_batched_search_answers_each_image_as_its_own_search_does() {
    let engine = Engine::load_dir(models_dir(), EngineConfig::default()).unwrap();
    let model = engine.model("tiny").unwrap();
    let crops: Vec<Vec<u8>> = (0..3)
        .map(|seed| prepared(&model, &cube_png(200 + seed)))
        .collect();
    let refs: Vec<&[u8]> = crops.iter().map(|c| c.as_slice()).collect();
    let features = model.features(&refs).expect("crops of the input side");
    let options = PredictOptions {
        top_k: 10,
        level: Some(4),
        mode_angle_deg: None,
        ..Default::default()
    };
    let many = model
        .predict_many(&features, &options, &[None, None, None])
        .unwrap();
    assert_eq!(many.len(), 3);
    for (i, batched) in many.iter().enumerate() {
        let one = model
            .features(&[refs[i]])
            .expect("crops of the input side")
            .swap_remove(0);
        let single = model.predict(&one, &options, None).unwrap();
        let cells =
            |p: &alignist::engine::Prediction| p.top.iter().map(|c| c.cell).collect::<Vec<_>>();
        assert_eq!(cells(batched), cells(&single), "image {i}");
        for (a, b) in batched.top.iter().zip(&single.top) {
            assert!((a.probability - b.probability).abs() <= 1e-4 * b.probability.max(1e-12));
        }
    }
}

#[test]
fn depth_points_from_the_true_pose_sharpen_the_distribution() {
    let engine = Engine::load_dir(models_dir(), EngineConfig::default()).unwrap();
    let model = engine.model("tiny").unwrap();
    // Depth fusion is built while the bundle loads, before any request.
    assert!(model.objects.iter().all(|o| o.fusion.is_warm()));
    let object = model.object("cube").unwrap();
    let r = haar_rotations(&mut ChaCha8Rng::seed_from_u64(7), 1)[0];
    // Visible surface points in the camera frame, relative to the object's centre.
    let x0 = alignist::experts::select::visible_points_at(&object.fusion.experts().mesh, &r, 7);
    let xyz: Vec<f32> = x0
        .iter()
        .flat_map(|p| {
            let q = r.matrix().cast::<f32>() * p;
            [q.x, q.y, q.z]
        })
        .collect();
    let points = SeenPoints::Centred(object.fusion.parse_points(&xyz, 10_000).unwrap());
    let features = features_of(&model, &cube_png(7));
    let grid = model.grid(3).unwrap();
    let gts = alignist::so3::equivalents(&r, &Shape::Cube.symmetries());
    let mass_near = |probs: &[f32]| -> f64 {
        let centres = grid.quaternions();
        probs
            .iter()
            .zip(&centres)
            .filter(|(_, q)| {
                gts.iter().any(|g| {
                    alignist::so3::quaternion_angle(q, &alignist::so3::to_quaternion(g))
                        < 20f64.to_radians()
                })
            })
            .map(|(&p, _)| p as f64)
            .sum()
    };
    let plain = model.distribution(&features, 3, None).unwrap();
    let fused = model
        .distribution(
            &features,
            3,
            Some(DepthInput {
                object,
                points: &points,
            }),
        )
        .unwrap();
    let (before, after) = (mass_near(&plain.probability), mass_near(&fused.probability));
    assert!(after > 2.0 * before && after > 0.3, "{before} → {after}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn serves_predict_distribution_models_health_and_reflection() {
    let server = start_server(&[]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    let mut client = AlignistClient::new(ch.clone());
    predict_is_the_top_of_the_streamed_distribution(&mut client).await;
    models_are_listed_with_their_training(&mut client).await;
    reflection_lists_the_service(ch.clone()).await;
    the_cli_predicts_plots_and_checks_health(&server);
}

/// Predict's top-k, ordered, is the top-k of the full distribution streamed at the same level.
async fn predict_is_the_top_of_the_streamed_distribution(client: &mut AlignistClient<Channel>) {
    let answer = client
        .predict(predict_request(3, 10, 3))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(answer.top.len(), 10);
    assert_eq!(answer.map.as_ref().unwrap(), &answer.top[0]);
    assert!(!answer.modes.is_empty());
    for w in answer.top.windows(2) {
        assert!(w[0].probability >= w[1].probability);
    }

    let mut stream = client
        .predict_distribution(DistributionRequest {
            model: "tiny".into(),
            image: image(cube_png(3)),
            level: 3,
            chunk_size: 10_000,
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    let mut probs = Vec::new();
    let mut chunks = 0;
    while let Some(c) = stream.message().await.unwrap() {
        assert_eq!(c.offset as usize, probs.len());
        assert_eq!(c.total_cells, 36_864);
        probs.extend(c.probability);
        chunks += 1;
    }
    assert_eq!(probs.len(), 36_864);
    assert_eq!(chunks, 4);
    let total: f64 = probs.iter().map(|&p| p as f64).sum();
    assert!((total - 1.0).abs() < 1e-4, "{total}");
    // Predict's top-k is the top-k of the full distribution at the same level.
    let mut order: Vec<usize> = (0..probs.len()).collect();
    order.sort_by(|&a, &b| probs[b].total_cmp(&probs[a]));
    // Same cells; the order may differ only between cells whose probabilities tie to 1e-3 (the
    // search scores its finer level's children afresh, the full grid from precomputed layers).
    let mut top: Vec<u64> = answer.top.iter().map(|t| t.cell).collect();
    for (i, t) in answer.top.iter().enumerate() {
        let in_full = probs[t.cell as usize] as f64;
        let rank_i = probs[order[i]] as f64;
        assert!(
            (in_full - rank_i).abs() <= 1e-3 * rank_i,
            "rank {i}: {in_full} vs {rank_i}"
        );
        assert!(
            (t.probability - in_full).abs() <= 0.02 * in_full,
            "{} vs {in_full}",
            t.probability
        );
    }
    let mut full_top: Vec<u64> = order[..10].iter().map(|&i| i as u64).collect();
    top.sort();
    full_top.sort();
    assert_eq!(top, full_top);
}

/// ListModels and GetModel describe the one model alike, with its training.
async fn models_are_listed_with_their_training(client: &mut AlignistClient<Channel>) {
    let models = client
        .list_models(ListModelsRequest {})
        .await
        .unwrap()
        .into_inner()
        .models;
    assert_eq!(models.len(), 1);
    assert_eq!(models[0].name, "tiny");
    assert_eq!(models[0].objects[0].name, "cube");
    assert_eq!(models[0].input_size, 32);
    let one = client
        .get_model(GetModelRequest {
            name: "tiny".into(),
        })
        .await
        .unwrap()
        .into_inner();
    // (NaN figures of an unevaluated bundle do not compare equal, so field by field.)
    assert_eq!(one.name, models[0].name);
    assert_eq!(one.objects, models[0].objects);
    assert_eq!(one.network_sha256, models[0].network_sha256);
    assert_eq!(one.network_sha256.len(), 64);
    let training = one.training.unwrap();
    assert_eq!(training.steps, 3);
    assert!(training.command.contains("fit") && training.log_likelihood.is_nan());
}

/// Reflection lists the service, so grpcurl and Postman can call it.
async fn reflection_lists_the_service(ch: Channel) {
    // Reflection lists the service, so grpcurl and Postman can call it.
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
    let mut reflection = ServerReflectionClient::new(ch.clone());
    let request = tonic_reflection::pb::v1::ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut answers = reflection
        .server_reflection_info(tokio_stream::iter(vec![request]))
        .await
        .unwrap()
        .into_inner();
    let first = answers.message().await.unwrap().unwrap();
    let Some(MessageResponse::ListServicesResponse(list)) = first.message_response else {
        panic!("{first:?}")
    };
    let names: Vec<String> = list.service.into_iter().map(|s| s.name).collect();
    assert!(
        names.contains(&"alignist.v1.Alignist".to_string()),
        "{names:?}"
    );
    assert!(
        names.contains(&"grpc.health.v1.Health".to_string()),
        "{names:?}"
    );
    // v1alpha as well (Python's grpcio-reflection, older grpcurl and Postman ask it).
    {
        use tonic_reflection::pb::v1alpha::server_reflection_client::ServerReflectionClient;
        use tonic_reflection::pb::v1alpha::server_reflection_request::MessageRequest;
        use tonic_reflection::pb::v1alpha::server_reflection_response::MessageResponse;
        let request = tonic_reflection::pb::v1alpha::ServerReflectionRequest {
            host: String::new(),
            message_request: Some(MessageRequest::ListServices(String::new())),
        };
        let first = ServerReflectionClient::new(ch.clone())
            .server_reflection_info(tokio_stream::iter(vec![request]))
            .await
            .unwrap()
            .into_inner()
            .message()
            .await
            .unwrap()
            .unwrap();
        let Some(MessageResponse::ListServicesResponse(list)) = first.message_response else {
            panic!("{first:?}")
        };
        assert!(
            list.service
                .iter()
                .any(|s| s.name == "alignist.v1.Alignist")
        );
    }
}

/// The CLI client predicts (JSON and a plot), checks health, and names a missing model.
fn the_cli_predicts_plots_and_checks_health(server: &Server) {
    // The CLI client against the same server.
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("cube.png");
    std::fs::write(&png, cube_png(3)).unwrap();
    let plot = dir.path().join("plot.png");
    let json = cli_json(&[
        "--server",
        &server.grpc,
        "predict",
        "--image",
        png.to_str().unwrap(),
        "--top-k",
        "3",
        "--json",
        "--plot",
        plot.to_str().unwrap(),
    ]);
    assert_eq!(json["top"].as_array().unwrap().len(), 3);
    assert!(image::open(dir.path().join("plot.png")).is_ok());
    let out = Command::new(env!("CARGO_BIN_EXE_alignist"))
        .args(["--server", &server.grpc, "health"])
        .output()
        .unwrap();
    assert!(out.status.success());
    assert_eq!(String::from_utf8_lossy(&out.stdout).trim(), "Serving");
    let out = Command::new(env!("CARGO_BIN_EXE_alignist"))
        .args([
            "--server",
            &server.grpc,
            "predict",
            "--model",
            "nope",
            "--image",
        ])
        .arg(&png)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("NotFound") && err.contains("nope"), "{err}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn bad_input_gets_its_status_code_and_the_server_keeps_serving() {
    let server = start_server(&[
        "--max-image-bytes",
        "200000",
        "--max-image-pixels",
        "250000",
    ]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    let mut client = AlignistClient::new(ch.clone());
    let ok = || predict_request(5, 3, 3);
    for (name, request, code, field) in bad_images(ok).into_iter().chain(bad_options(ok)) {
        let status = client.predict(request).await.expect_err(name);
        assert_refused(name, &status, code, field);
    }
    let status = client
        .predict_distribution(DistributionRequest {
            model: "tiny".into(),
            image: image(cube_png(5)),
            level: 4,
            ..Default::default()
        })
        .await
        .expect_err("level above --max-level");
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(status.message().contains("level"));
    let status = client
        .get_model(GetModelRequest {
            name: "nope".into(),
        })
        .await
        .expect_err("unknown model");
    assert_eq!(status.code(), Code::NotFound);
    // Still serving.
    let answer = client.predict(ok()).await.unwrap().into_inner();
    assert_eq!(answer.top.len(), 3);
    let text = common::http_get(&server.metrics).await;
    assert!(
        metric(
            &text,
            "alignist_requests_total",
            &["method=\"Predict\"", "code=\"INVALID_ARGUMENT\""]
        ) >= 8.0,
        "{text}"
    );
}

/// A bad request's status: its code, a message naming `field`, and for field errors a
/// BadRequest violation naming the field.
fn assert_refused(name: &str, status: &tonic::Status, code: Code, field: &str) {
    assert_eq!(status.code(), code, "{name}: {}", status.message());
    assert!(
        status.message().contains(field),
        "{name}: message {:?} does not name {field}",
        status.message()
    );
    // Field errors carry a BadRequest violation naming the field.
    use tonic_types::StatusExt;
    if code == Code::InvalidArgument || code == Code::ResourceExhausted {
        let bad = status
            .get_details_bad_request()
            .unwrap_or_else(|| panic!("{name}: no BadRequest details"));
        assert!(
            !bad.field_violations.is_empty()
                && bad
                    .field_violations
                    .iter()
                    .all(|v| !v.field.is_empty() && status.message().starts_with(&v.field)),
            "{name}: {bad:?} vs {}",
            status.message()
        );
    }
}

/// Predict requests with a bad image (over the limits of `--max-image-bytes 200000
/// --max-image-pixels 250000`), each with its code and the field its message names.
fn bad_images(
    ok: impl Fn() -> PredictRequest,
) -> Vec<(&'static str, PredictRequest, Code, &'static str)> {
    let big_png = {
        let mut png = Vec::new();
        image::RgbImage::new(600, 600)
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        png
    };
    vec![
        (
            "not an image",
            PredictRequest {
                image: image(b"definitely not a png".to_vec()),
                ..ok()
            },
            Code::InvalidArgument,
            "image.data",
        ),
        (
            "empty",
            PredictRequest {
                image: image(Vec::new()),
                ..ok()
            },
            Code::InvalidArgument,
            "image.data",
        ),
        (
            "no image",
            PredictRequest {
                image: None,
                ..ok()
            },
            Code::InvalidArgument,
            "image",
        ),
        (
            "too many bytes",
            PredictRequest {
                image: image(vec![0u8; 300_000]),
                ..ok()
            },
            Code::ResourceExhausted,
            "image.data",
        ),
        (
            "too many pixels",
            PredictRequest {
                image: image(big_png),
                ..ok()
            },
            Code::ResourceExhausted,
            "pixels",
        ),
        (
            "raw of the wrong length",
            PredictRequest {
                image: Some(ImageInput {
                    data: vec![0; 10],
                    width: 4,
                    height: 4,
                    crop: None,
                    crop_box: None,
                }),
                ..ok()
            },
            Code::InvalidArgument,
            "raw RGB8",
        ),
        (
            "crop outside",
            PredictRequest {
                image: Some(ImageInput {
                    data: cube_png(5),
                    crop: Some(CropBox {
                        x: 40,
                        y: 0,
                        width: 20,
                        height: 10,
                    }),
                    ..Default::default()
                }),
                ..ok()
            },
            Code::InvalidArgument,
            "image.crop",
        ),
    ]
}

/// Predict requests with a bad model, object, option or depth, each with its code and the field
/// its message names.
fn bad_options(
    ok: impl Fn() -> PredictRequest,
) -> Vec<(&'static str, PredictRequest, Code, &'static str)> {
    vec![
        (
            "unknown model",
            PredictRequest {
                model: "nope".into(),
                ..ok()
            },
            Code::NotFound,
            "nope",
        ),
        (
            "unknown object",
            PredictRequest {
                object: "teapot".into(),
                ..ok()
            },
            Code::NotFound,
            "teapot",
        ),
        (
            "k = 0",
            PredictRequest { top_k: 0, ..ok() },
            Code::InvalidArgument,
            "top_k",
        ),
        (
            "k above the grid",
            PredictRequest {
                top_k: 1_000_000,
                level: 1,
                ..ok()
            },
            Code::InvalidArgument,
            "top_k",
        ),
        (
            "level above the maximum",
            PredictRequest { level: 7, ..ok() },
            Code::InvalidArgument,
            "level",
        ),
        (
            "malformed depth",
            PredictRequest {
                depth: Some(DepthPoints {
                    xyz: vec![0.1, 0.2],
                }),
                ..ok()
            },
            Code::InvalidArgument,
            "depth.xyz",
        ),
        (
            "depth not finite",
            PredictRequest {
                depth: Some(DepthPoints {
                    xyz: vec![0.1, f32::NAN, 0.3],
                }),
                ..ok()
            },
            Code::InvalidArgument,
            "depth.xyz",
        ),
    ]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn concurrent_requests_are_batched() {
    let server = start_server(&["--max-batch", "16", "--max-delay-ms", "20"]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    let png = cube_png(11);
    let results = futures_join(spawn_predicts(&ch, &png, 200, 1, 2).into_iter()).await;
    assert_eq!(results.len(), 200);
    let first = results[0].as_ref().unwrap().top[0].cell;
    for r in &results {
        assert_eq!(r.as_ref().unwrap().top[0].cell, first);
    }
    let text = common::http_get(&server.metrics).await;
    let batches = metric(&text, "alignist_batches_total", &[]);
    let images = metric(&text, "alignist_batched_images_total", &[]);
    assert!(images >= 200.0, "{text}");
    assert!(
        images / batches > 1.0,
        "{images} images in {batches} batches: no batching"
    );
    // Histograms with buckets (aggregatable across replicas), end to end per method and code;
    // nothing left in flight; the served model's version.
    assert!(
        metric(
            &text,
            "alignist_request_seconds_count",
            &["method=\"Predict\"", "code=\"OK\""]
        ) >= 200.0,
        "{text}"
    );
    assert!(text.contains("alignist_request_seconds_bucket{"), "{text}");
    assert!(text.contains("alignist_batch_size_bucket{"), "{text}");
    assert_eq!(
        metric(
            &text,
            "alignist_in_flight_requests",
            &["method=\"Predict\""]
        ),
        0.0
    );
    assert_eq!(
        metric(&text, "alignist_model_info", &["model=\"tiny\""]),
        1.0
    );
    // compute_ms leaves the queue out; queue_ms says how long it was.
    let r = results[0].as_ref().unwrap();
    assert!(r.queue_ms >= 0.0 && r.compute_ms > 0.0);
}

/// The observing layer at the server builder: every method (the Alignist service's and health)
/// gets its request id echoed, and is counted per method and code when its answer ends (a
/// streamed answer at its trailers, one dropped by its client as CANCELLED).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_call_is_observed_with_its_request_id_and_its_code() {
    let server = start_server(&[]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    let mut client = AlignistClient::new(ch.clone());
    let mut request = tonic::Request::new(predict_request(3, 3, 3));
    request
        .metadata_mut()
        .insert("x-request-id", "planner-42".parse().unwrap());
    let answer = client.predict(request).await.unwrap();
    assert_eq!(answer.metadata().get("x-request-id").unwrap(), "planner-42");
    let own = client.list_models(ListModelsRequest {}).await.unwrap();
    let own = own
        .metadata()
        .get("x-request-id")
        .unwrap()
        .to_str()
        .unwrap();
    assert!(
        own.starts_with('r') && own[1..].parse::<u64>().is_ok(),
        "{own}"
    );
    let missing = client
        .get_model(GetModelRequest {
            name: "nope".into(),
        })
        .await
        .expect_err("unknown model");
    assert_eq!(
        missing.metadata().get("x-request-id").map(|v| v.is_empty()),
        Some(false)
    );
    // The dropped stream comes one cell a chunk (36 864 messages, megabytes): more than the
    // HTTP/2 window and the server's send buffer, so that it is still being answered when its
    // client goes away.
    let distribution = |chunk_size| DistributionRequest {
        model: "tiny".into(),
        image: image(cube_png(3)),
        level: 3,
        chunk_size,
        ..Default::default()
    };
    let mut stream = client
        .predict_distribution(distribution(10_000))
        .await
        .unwrap()
        .into_inner();
    while stream.message().await.unwrap().is_some() {}
    let mut abandoned = client
        .predict_distribution(distribution(1))
        .await
        .unwrap()
        .into_inner();
    abandoned.message().await.unwrap().expect("a first chunk");
    drop(abandoned);
    let counted = |text: &str, method: &str, code: &str| {
        metric(
            text,
            "alignist_requests_total",
            &[&format!("method=\"{method}\""), &format!("code=\"{code}\"")],
        )
    };
    let mut text = String::new();
    for _ in 0..50 {
        text = common::http_get(&server.metrics).await;
        if counted(&text, "PredictDistribution", "CANCELLED") >= 1.0 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(counted(&text, "Predict", "OK"), 1.0, "{text}");
    assert_eq!(counted(&text, "ListModels", "OK"), 1.0, "{text}");
    assert_eq!(counted(&text, "GetModel", "NOT_FOUND"), 1.0, "{text}");
    assert_eq!(counted(&text, "PredictDistribution", "OK"), 1.0, "{text}");
    assert_eq!(
        counted(&text, "PredictDistribution", "CANCELLED"),
        1.0,
        "{text}"
    );
    assert!(
        counted(&text, "Check", "OK") >= 1.0,
        "health is observed too: {text}"
    );
    for method in ["Predict", "PredictDistribution", "ListModels", "GetModel"] {
        assert_eq!(
            metric(
                &text,
                "alignist_in_flight_requests",
                &[&format!("method=\"{method}\"")]
            ),
            0.0,
            "{method}: {text}"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn server_levels_are_checked_at_start_up_and_level_0_is_the_default_everywhere() {
    // A search maximum below the usual default lowers the default with it: default calls work.
    let server = start_server(&["--max-search-level", "3"]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    let mut client = AlignistClient::new(ch);
    let answer = client
        .predict(predict_request(4, 3, 0))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(answer.top[0].level, 3);
    // PredictDistribution's level 0 is the default too (4, or the server's maximum, 3 here).
    let mut stream = client
        .predict_distribution(DistributionRequest {
            model: "tiny".into(),
            image: image(cube_png(4)),
            level: 0,
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    let first = stream.message().await.unwrap().unwrap();
    assert_eq!((first.level, first.total_cells), (3, 36_864));
    // Settings that cannot work stop the server at start-up with a message naming them.
    for (args, named) in [
        (["--max-level", "7"], "level"),
        (["--max-search-level", "1"], "level"),
        (["--max-level", "1"], "level"),
        (["--search-keep-taper", "0"], "keep_taper"),
        (["--search-keep-taper", "NaN"], "keep_taper"),
        (["--search-coarse-precision", "fp8"], "precision"),
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_alignist-server"))
            .args([
                "--models",
                models_dir().to_str().unwrap(),
                "--listen",
                "127.0.0.1:0",
            ])
            .args(["--metrics-listen", "off"])
            .args(args)
            .output()
            .unwrap();
        assert!(!out.status.success(), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(named), "{args:?}: {err}");
    }
}

/// Starts `n` Predict calls of the same image concurrently, each on its own client.
fn spawn_predicts(
    ch: &tonic::transport::Channel,
    png: &[u8],
    n: usize,
    top_k: u32,
    level: u32,
) -> Vec<tokio::task::JoinHandle<Result<alignist::serve::proto::PredictResponse, tonic::Status>>> {
    (0..n)
        .map(|_| {
            let mut client = AlignistClient::new(ch.clone());
            let request = PredictRequest {
                model: "tiny".into(),
                image: image(png.to_vec()),
                top_k,
                level,
                ..Default::default()
            };
            tokio::spawn(async move { client.predict(request).await.map(|r| r.into_inner()) })
        })
        .collect()
}

async fn futures_join<T>(handles: impl Iterator<Item = tokio::task::JoinHandle<T>>) -> Vec<T> {
    let mut out = Vec::new();
    for h in handles.collect::<Vec<_>>() {
        out.push(h.await.unwrap());
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn sigterm_drains_accepted_calls_and_exits_0() {
    let mut server = start_server(&["--max-batch", "4"]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    let png = cube_png(12);
    let calls = spawn_predicts(&ch, &png, 24, 5, 5);
    tokio::time::sleep(Duration::from_millis(300)).await;
    let pid = server.child.id().to_string();
    assert!(
        Command::new("kill")
            .args(["-TERM", &pid])
            .status()
            .unwrap()
            .success()
    );
    for call in calls {
        let answer = call.await.unwrap();
        assert!(answer.is_ok(), "{answer:?}");
    }
    let status = server.child.wait().unwrap();
    assert_eq!(status.code(), Some(0));
}

#[test]
fn modes_of_a_tetrahedral_distribution_are_its_12_equivalents() {
    use alignist::engine::{CellProbability, group_modes};
    use alignist::so3::{GridLevel, SymmetryGroup, equivalents, quaternion_angle, to_quaternion};
    let grid = GridLevel::new(3).unwrap();
    let r = haar_rotations(&mut ChaCha8Rng::seed_from_u64(5), 1)[0];
    let gts = equivalents(&r, &SymmetryGroup::Tetrahedral.rotations());
    // Mass ∝ exp(−angle²/2σ²) to the nearest equivalent (σ = 4°), on every cell.
    let quats: Vec<[f64; 4]> = grid.quaternions();
    let gq: Vec<[f64; 4]> = gts.iter().map(to_quaternion).collect();
    let mut cells: Vec<CellProbability> = quats
        .iter()
        .enumerate()
        .map(|(i, q)| {
            let a = gq
                .iter()
                .map(|g| quaternion_angle(q, g))
                .fold(f64::MAX, f64::min);
            CellProbability {
                level: 3,
                cell: i as u64,
                probability: (-(a / 4f64.to_radians()).powi(2) / 2.0).exp(),
                log_density: 0.0,
            }
        })
        .collect();
    let total: f64 = cells.iter().map(|c| c.probability).sum();
    cells.iter_mut().for_each(|c| c.probability /= total);
    cells.sort_by(|a, b| b.probability.total_cmp(&a.probability));
    let modes = group_modes(&grid, &cells, 15f64.to_radians(), 0.9, 0.01);
    assert_eq!(modes.len(), 12);
    for m in &modes {
        let nearest = gq
            .iter()
            .map(|g| quaternion_angle(&m.quaternion, g))
            .fold(f64::MAX, f64::min);
        assert!(nearest.to_degrees() < 3.0, "{}", nearest.to_degrees());
        assert!(
            (m.probability - 0.9 / 12.0).abs() < 0.03,
            "{}",
            m.probability
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_full_queue_answers_unavailable_and_an_expired_call_gives_up() {
    let server = start_server(&["--queue", "1", "--max-batch", "1", "--max-delay-ms", "0"]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    let png = cube_png(31);
    let calls = spawn_predicts(&ch, &png, 40, 1, 5);
    let (mut ok, mut unavailable) = (0, 0);
    for call in calls {
        match call.await.unwrap() {
            Ok(_) => ok += 1,
            Err(s) => {
                assert_eq!(s.code(), Code::Unavailable, "{s:?}");
                assert!(s.message().contains("queue"), "{}", s.message());
                // The reason and a retry delay come as rich details, not only as text.
                use tonic_types::StatusExt;
                let d = s.get_error_details();
                assert_eq!(d.error_info().unwrap().reason, "QUEUE_FULL");
                assert!(d.retry_info().unwrap().retry_delay.is_some());
                unavailable += 1;
            }
        }
    }
    assert!(
        ok >= 1 && unavailable >= 1,
        "{ok} ok, {unavailable} unavailable"
    );

    // A call whose deadline passes gets DEADLINE_EXCEEDED or CANCELLED, and the server goes on.
    let mut client = AlignistClient::new(ch.clone());
    let mut call = tonic::Request::new(PredictRequest {
        model: "tiny".into(),
        image: image(png.clone()),
        top_k: 1,
        level: 6,
        ..Default::default()
    });
    call.set_timeout(Duration::from_millis(5));
    let status = client.predict(call).await.expect_err("deadline");
    assert!(
        matches!(status.code(), Code::DeadlineExceeded | Code::Cancelled),
        "{status:?}"
    );
    // The abandoned call may still hold the one-place queue for a moment: the next call is
    // refused with UNAVAILABLE and a retry delay until it is dropped, then answered (as a client
    // honouring RetryInfo would see it).
    let mut answer = client.predict(predict_request(31, 2, 2)).await;
    for _ in 0..50 {
        match &answer {
            Err(s) if s.code() == Code::Unavailable => {
                tokio::time::sleep(Duration::from_millis(100)).await;
                answer = client.predict(predict_request(31, 2, 2)).await;
            }
            _ => break,
        }
    }
    assert_eq!(answer.unwrap().into_inner().top.len(), 2);
}

/// A 640×480 PNG with the cube at `(u, v)` in the frame camera, its integer box, and `K`.
fn frame_png(rotation: nalgebra::Rotation3<f64>, u: f64, v: f64) -> (Vec<u8>, [u32; 4], [f64; 9]) {
    let frame = frame_rgbd(rotation, u, v);
    (frame.png, frame.bbox, frame.k)
}

/// A 640×480 frame of the normalised cube at `rotation`, its centre seen at pixel `(u, v)` 5
/// radii away: the colour PNG, the depth (along the optical axis, in normalised units, 0 off the
/// object), the cube's box, `K` and the translation.
struct RgbdFrame {
    png: Vec<u8>,
    depth: Vec<f32>,
    bbox: [u32; 4],
    k: [f64; 9],
    translation: nalgebra::Vector3<f64>,
}

fn frame_rgbd(rotation: nalgebra::Rotation3<f64>, u: f64, v: f64) -> RgbdFrame {
    use alignist::cad::{Pose, RenderOptions, render};
    use alignist::data::virtual_crop::{frame_camera, object_pixel_box};
    let mesh = Shape::Cube.mesh().normalised().0;
    let camera = frame_camera();
    let z = 5.0;
    let pose = Pose {
        rotation,
        translation: nalgebra::Vector3::new(
            (u - camera.cx) / camera.fx * z,
            (v - camera.cy) / camera.fy * z,
            z,
        ),
    };
    let full = render(&mesh, &camera, &pose, &RenderOptions::default());
    let bbox = object_pixel_box(&mesh, &pose, &camera);
    let mut png = Vec::new();
    image::RgbImage::from_raw(camera.width, camera.height, full.rgb)
        .unwrap()
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    RgbdFrame {
        png,
        depth: full.depth,
        bbox,
        k: camera.k(),
        translation: pose.translation,
    }
}

/// A 16-bit PNG of `depth / unit` (rounded), `width × height`.
fn depth_png(depth: &[f32], width: u32, height: u32, unit: f32) -> Vec<u8> {
    let values: Vec<u16> = depth.iter().map(|&z| (z / unit).round() as u16).collect();
    let mut png = Vec::new();
    image::ImageBuffer::<image::Luma<u16>, _>::from_raw(width, height, values)
        .unwrap()
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    png
}

/// A depth frame request of the cube for the tiny model, with what it was made from.
struct DepthCase {
    frame: RgbdFrame,
    depth: alignist::serve::proto::DepthImage,
    request: alignist::serve::proto::FrameRequest,
    /// Mesh units per normalised unit, and the mesh frame's centre.
    scale: f64,
    centre: nalgebra::Vector3<f64>,
    unit: f32,
}

/// The cube at a random pose in a 640×480 RGB-D frame, asked with its depth image at level 4.
async fn depth_case(client: &mut AlignistClient<Channel>) -> DepthCase {
    use alignist::serve::proto::{DepthImage, Detection, FrameRequest, Intrinsics};
    let info = client
        .get_model(GetModelRequest {
            name: "tiny".into(),
        })
        .await
        .unwrap()
        .into_inner();
    let cube = info.objects.iter().find(|o| o.name == "cube").unwrap();
    // The renders are of the normalised cube; the server speaks the source mesh's units.
    let scale = cube.frame_scale;
    let centre = cube.frame_centre.unwrap();
    let centre = nalgebra::Vector3::new(centre.x, centre.y, centre.z);

    let r_cam = case_rotation();
    let frame = frame_rgbd(r_cam, 300.0, 220.0);
    let unit = 1e-3; // normalised units per depth unit
    let depth = DepthImage {
        data: depth_png(&frame.depth, 640, 480, unit),
        width: 0,
        height: 0,
        scale: unit as f64 * scale,
    };
    let k = frame.k;
    let [x, y, width, height] = frame.bbox;
    let request = FrameRequest {
        model: "tiny".into(),
        image: image(frame.png.clone()),
        intrinsics: Some(Intrinsics {
            fx: k[0],
            fy: k[4],
            cx: k[2],
            cy: k[5],
        }),
        detections: vec![Detection {
            r#box: Some(CropBox {
                x,
                y,
                width,
                height,
            }),
            object: "cube".into(),
            mask: Vec::new(),
            bbox: None,
        }],
        top_k: 3,
        level: 4,
        mode_angle_deg: 0.0,
        depth: Some(depth.clone()),
    };
    DepthCase {
        frame,
        depth,
        request,
        scale,
        centre,
        unit,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn frame_requests_fuse_a_depth_image_and_answer_the_translation() {
    let server = start_server(&[]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    let mut client = AlignistClient::new(ch.clone());
    let case = depth_case(&mut client).await;
    let t = the_fused_answer_has_the_pose_and_translation(&mut client, &case).await;
    the_cli_fuses_depth_alike(&server, &case, t);
    bad_depth_names_its_field(&mut client, &case).await;
}

/// The fused answer: near the true pose (loosely: the tiny model), with a translation near the
/// truth; without depth, no translation. Returns the top-1's translation.
async fn the_fused_answer_has_the_pose_and_translation(
    client: &mut AlignistClient<Channel>,
    case: &DepthCase,
) -> alignist::serve::proto::Vector3 {
    use alignist::serve::proto::FrameRequest;
    use alignist::so3::{from_quaternion, geodesic_angle};
    let DepthCase {
        frame,
        request,
        scale,
        centre,
        ..
    } = case;
    let (scale, r_cam) = (*scale, case_rotation());
    let answer = client
        .predict_frame(request.clone())
        .await
        .unwrap()
        .into_inner();
    let p = answer.detections[0].prediction.as_ref().unwrap();
    assert!(p.depth_fused);
    assert_eq!(p.object, "cube");
    assert_eq!(p.top.len(), 3);
    // The tiny model's experts are trained for seconds (a 16³ SDF bake), so this checks the
    // plumbing and the frames, loosely; tests/depth.rs measures accuracy with a real expert.
    let top = &p.top[0];
    let t = top.translation.as_ref().expect("a translation with depth");
    let q = top.rotation.as_ref().unwrap();
    let r = from_quaternion([q.w, q.x, q.y, q.z]).unwrap();
    let t_gt = frame.translation * scale - r_cam * centre;
    let error = (nalgebra::Vector3::new(t.x, t.y, t.z) - t_gt).norm() / scale;
    assert!(error < 0.25, "translation off by {error} radii");
    let nearest = Shape::Cube
        .symmetries()
        .iter()
        .map(|s| geodesic_angle(&r, &(r_cam * s)).to_degrees())
        .fold(f64::INFINITY, f64::min);
    assert!(
        nearest < 30.0,
        "top-1 {nearest}° from the nearest equivalent"
    );
    // Without depth, no translation.
    let plain = client
        .predict_frame(FrameRequest {
            depth: None,
            ..request.clone()
        })
        .await
        .unwrap()
        .into_inner();
    let plain = plain.detections[0].prediction.as_ref().unwrap();
    assert!(!plain.depth_fused && plain.top[0].translation.is_none());

    *t
}

/// The CLI's --depth and --depth-scale give the same fusion; --depth without --depth-scale is
/// refused, naming the flag.
fn the_cli_fuses_depth_alike(
    server: &Server,
    case: &DepthCase,
    t: alignist::serve::proto::Vector3,
) {
    let DepthCase { frame, depth, .. } = case;
    let k = frame.k;
    let [x, y, width, height] = frame.bbox;
    // The CLI: --depth and --depth-scale give the same fusion, with a translation per rotation.
    let dir = tempfile::tempdir().unwrap();
    let (rgb_path, depth_path) = (dir.path().join("rgb.png"), dir.path().join("depth.png"));
    std::fs::write(&rgb_path, &frame.png).unwrap();
    std::fs::write(&depth_path, &depth.data).unwrap();
    let json = cli_json(&[
        "--server",
        &server.grpc,
        "predict",
        "--model",
        "tiny",
        "--object",
        "cube",
        "--image",
        rgb_path.to_str().unwrap(),
        "--depth",
        depth_path.to_str().unwrap(),
        "--depth-scale",
        &depth.scale.to_string(),
        "--intrinsics",
        &format!("{},{},{},{}", k[0], k[4], k[2], k[5]),
        "--box",
        &format!("{x},{y},{width},{height}"),
        "--top-k",
        "3",
        "--level",
        "4",
        "--json",
    ]);
    let cli = &json["detections"][0]["prediction"];
    assert_eq!(cli["depth_fused"], true);
    let t_cli: Vec<f64> = serde_json::from_value(cli["top"][0]["translation"].clone()).unwrap();
    assert!(
        (t_cli[0] - t.x).abs() < 1e-9 && (t_cli[2] - t.z).abs() < 1e-9,
        "{t_cli:?}"
    );
    // --depth without --depth-scale is refused by the CLI, naming the flag.
    let out = Command::new(env!("CARGO_BIN_EXE_alignist"))
        .args(["--server", &server.grpc, "predict", "--image"])
        .arg(&rgb_path)
        .arg("--depth")
        .arg(&depth_path)
        .args(["--intrinsics", "500,500,320,240", "--box", "1,2,3,4"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--depth-scale"));
}

/// Bad depth: INVALID_ARGUMENT naming the field.
async fn bad_depth_names_its_field(client: &mut AlignistClient<Channel>, case: &DepthCase) {
    for (name, req, field) in bad_depths(case) {
        let status = client.predict_frame(req).await.expect_err(name);
        assert_eq!(status.code(), Code::InvalidArgument, "{name}: {status:?}");
        assert!(
            status.message().contains(field),
            "{name}: {} does not name {field}",
            status.message()
        );
    }
}

/// Frame requests with a bad depth image, each with the field its refusal names.
fn bad_depths(
    case: &DepthCase,
) -> Vec<(
    &'static str,
    alignist::serve::proto::FrameRequest,
    &'static str,
)> {
    use alignist::serve::proto::{DepthImage, Detection, FrameRequest};
    let DepthCase {
        frame,
        depth,
        request,
        unit,
        ..
    } = case;
    let unit = *unit;
    let with_depth = |d: DepthImage| FrameRequest {
        depth: Some(d),
        ..request.clone()
    };
    let gray8 = {
        let mut png = Vec::new();
        image::GrayImage::new(640, 480)
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        png
    };
    let mut cases = vec![
        (
            "8-bit PNG",
            with_depth(DepthImage {
                data: gray8,
                ..depth.clone()
            }),
            "depth.data",
        ),
        (
            "wrong size",
            with_depth(DepthImage {
                data: depth_png(&frame.depth[..320 * 240], 320, 240, unit),
                ..depth.clone()
            }),
            "depth.data",
        ),
        (
            "all invalid",
            with_depth(DepthImage {
                data: depth_png(&vec![0.0; 640 * 480], 640, 480, unit),
                ..depth.clone()
            }),
            "detections[0].box",
        ),
        (
            "raw of the wrong length",
            with_depth(DepthImage {
                data: vec![0; 10],
                width: 640,
                height: 480,
                scale: depth.scale,
            }),
            "depth.data",
        ),
        (
            "raw with one side 0",
            with_depth(DepthImage {
                width: 640,
                ..depth.clone()
            }),
            "depth.width",
        ),
        (
            "box on empty depth",
            FrameRequest {
                detections: vec![Detection {
                    r#box: Some(CropBox {
                        x: 0,
                        y: 0,
                        width: 20,
                        height: 20,
                    }),
                    object: "cube".into(),
                    mask: Vec::new(),
                    bbox: None,
                }],
                ..with_depth(depth.clone())
            },
            "detections[0].box",
        ),
    ];
    cases.extend(bad_depth_scales(depth, &with_depth));
    cases
}

/// Frame requests whose depth scale is 0 or 1000× off, each with the field its refusal names.
fn bad_depth_scales(
    depth: &alignist::serve::proto::DepthImage,
    with_depth: &dyn Fn(alignist::serve::proto::DepthImage) -> alignist::serve::proto::FrameRequest,
) -> Vec<(
    &'static str,
    alignist::serve::proto::FrameRequest,
    &'static str,
)> {
    use alignist::serve::proto::DepthImage;
    vec![
        (
            "scale 1000× too large",
            with_depth(DepthImage {
                scale: depth.scale * 1000.0,
                ..depth.clone()
            }),
            "depth.scale",
        ),
        (
            "scale 1000× too small",
            with_depth(DepthImage {
                scale: depth.scale / 1000.0,
                ..depth.clone()
            }),
            "depth.scale",
        ),
        (
            "scale 0",
            with_depth(DepthImage {
                scale: 0.0,
                ..depth.clone()
            }),
            "depth.scale",
        ),
    ]
}

/// The cube's pose in [`depth_case`].
fn case_rotation() -> nalgebra::Rotation3<f64> {
    haar_rotations(&mut ChaCha8Rng::seed_from_u64(33), 1)[0]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn frame_requests_answer_every_box_in_the_camera_frame() {
    use alignist::serve::proto::{Detection, FrameRequest, Intrinsics};
    let server = start_server(&[]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    let mut client = AlignistClient::new(ch.clone());

    let r_cam = haar_rotations(&mut ChaCha8Rng::seed_from_u64(21), 1)[0];
    let (png, bbox, k) = frame_png(r_cam, 520.0, 130.0);
    let other = [20u32, 300, 90, 120];
    // A detector's box: sub-pixel, reaching past the frame's left edge (pad, don't refuse).
    let cut = [-25.5, 300.25, 90.5, 120.0];
    let fractional = Detection {
        r#box: None,
        bbox: Some(alignist::client::pixel_box(cut)),
        object: String::new(),
        mask: Vec::new(),
    };
    let intrinsics = Some(Intrinsics {
        fx: k[0],
        fy: k[4],
        cx: k[2],
        cy: k[5],
    });
    let request = FrameRequest {
        model: "tiny".into(),
        image: image(png.clone()),
        intrinsics,
        detections: vec![detection_of(bbox), detection_of(other), fractional],
        top_k: 5,
        level: 3,
        mode_angle_deg: 0.0,
        depth: None,
    };
    let answer = client
        .predict_frame(request.clone())
        .await
        .unwrap()
        .into_inner();
    assert_eq!(answer.detections.len(), 3);
    assert_eq!(answer.model, "tiny");
    assert!(answer.detections[2].r#box.is_none());
    let echoed = answer.detections[2].bbox.unwrap();
    assert_eq!([echoed.x, echoed.y, echoed.width, echoed.height], cut);
    let whole = |b: [u32; 4]| b.map(|v| v as f64);
    let boxes = [whole(bbox), whole(other), cut];
    each_box_is_its_crops_answer_turned_by_the_ray(&mut client, &answer, &png, &k, &boxes).await;
    bad_frames_name_their_field(&mut client, &request).await;
    the_cli_answers_each_box(&server, &png, &k, bbox);
    objects_are_described_for_planners(&mut client).await;
}

/// A detection of the whole-pixel box `b` (`x, y, width, height`), its object unnamed.
fn detection_of(b: [u32; 4]) -> alignist::serve::proto::Detection {
    alignist::serve::proto::Detection {
        r#box: Some(CropBox {
            x: b[0],
            y: b[1],
            width: b[2],
            height: b[3],
        }),
        object: String::new(),
        mask: Vec::new(),
        bbox: None,
    }
}

/// Each answer of a frame is the crop-only answer for that box's perspective crop, turned by
/// `R_ray`, from the same model version.
async fn each_box_is_its_crops_answer_turned_by_the_ray(
    client: &mut AlignistClient<Channel>,
    answer: &alignist::serve::proto::FrameResponse,
    png: &[u8],
    k: &[f64; 9],
    boxes: &[[f64; 4]],
) {
    use alignist::data::virtual_crop::{VirtualCamera, perspective_crop};
    use alignist::so3::{from_quaternion, geodesic_angle};
    let k = *k;
    let sha = client
        .get_model(GetModelRequest {
            name: "tiny".into(),
        })
        .await
        .unwrap()
        .into_inner()
        .network_sha256;
    assert_eq!(answer.model_version, sha);
    let rgb = image::load_from_memory(png).unwrap().to_rgb8();
    for (d, &bf) in answer.detections.iter().zip(boxes) {
        let (crop, view) = perspective_crop(rgb.as_raw(), 640, 480, &k, bf, 32).unwrap();
        assert_eq!(
            view.r_ray,
            VirtualCamera::looking_at(&k, bf, 32).unwrap().r_ray
        );
        let ray = d.ray.as_ref().unwrap();
        let ray = from_quaternion([ray.w, ray.x, ray.y, ray.z]).unwrap();
        assert!(geodesic_angle(&ray, &view.r_ray) < 1e-9);
        let centred = client
            .predict(PredictRequest {
                model: "tiny".into(),
                image: Some(ImageInput {
                    data: crop,
                    width: 32,
                    height: 32,
                    crop: None,
                    crop_box: None,
                }),
                top_k: 5,
                level: 3,
                ..Default::default()
            })
            .await
            .unwrap()
            .into_inner();
        let framed = d.prediction.as_ref().unwrap();
        assert_eq!(framed.model_version, sha);
        assert_eq!(framed.top.len(), 5);
        for (f, c) in framed.top.iter().zip(&centred.top) {
            assert_eq!(f.cell, c.cell);
            let q = |r: &alignist::serve::proto::Rotation| {
                from_quaternion([r.w, r.x, r.y, r.z]).unwrap()
            };
            let (rf, rc) = (
                q(f.rotation.as_ref().unwrap()),
                q(c.rotation.as_ref().unwrap()),
            );
            assert!(geodesic_angle(&rf, &(view.r_ray * rc)) < 1e-9);
            // The typed rotation's matrix is its quaternion's.
            let m = &f.rotation.as_ref().unwrap().matrix;
            assert_eq!(m.len(), 9);
            for (i, v) in m.iter().enumerate() {
                assert!((v - rf.matrix()[(i / 3, i % 3)]).abs() < 1e-12);
            }
        }
    }
}

/// Bad frames: each INVALID_ARGUMENT names its field.
async fn bad_frames_name_their_field(
    client: &mut AlignistClient<Channel>,
    request: &alignist::serve::proto::FrameRequest,
) {
    use alignist::serve::proto::FrameRequest;
    let detection = detection_of;
    let bad = |f: &dyn Fn(&mut FrameRequest)| {
        let mut r = request.clone();
        f(&mut r);
        r
    };
    let cases: Vec<(FrameRequest, &str)> = vec![
        (
            bad(&|r| r.detections[1] = detection([640, 400, 100, 100])),
            "detections[1].box",
        ),
        (
            bad(&|r| r.detections[0] = detection([10, 10, 0, 20])),
            "detections[0].box",
        ),
        (
            bad(&|r| r.intrinsics.as_mut().unwrap().fx = 0.0),
            "intrinsics.fx",
        ),
        (
            bad(&|r| r.intrinsics.as_mut().unwrap().fy = -5.0),
            "intrinsics.fy",
        ),
        (bad(&|r| r.intrinsics = None), "intrinsics"),
        (bad(&|r| r.detections.clear()), "detections"),
        (bad(&|r| r.detections[0].r#box = None), "detections[0].box"),
        (
            bad(&|r| {
                r.image.as_mut().unwrap().crop = Some(CropBox {
                    x: 0,
                    y: 0,
                    width: 5,
                    height: 5,
                })
            }),
            "image.crop",
        ),
    ];
    for (req, field) in cases {
        let status = client.predict_frame(req).await.unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "{field}: {status:?}");
        assert!(
            status.message().contains(field),
            "{field}: {}",
            status.message()
        );
    }
}

/// The CLI: one block per box, rotations in the camera frame; a box without intrinsics is
/// refused by the CLI itself, naming the flag.
fn the_cli_answers_each_box(server: &Server, png: &[u8], k: &[f64; 9], bbox: [u32; 4]) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("frame.png");
    std::fs::write(&path, png).unwrap();
    let json = cli_json(&[
        "--server",
        &server.grpc,
        "predict",
        "--image",
        path.to_str().unwrap(),
        "--intrinsics",
        &format!("{},{},{},{}", k[0], k[4], k[2], k[5]),
        "--box",
        &format!("{},{},{},{}", bbox[0], bbox[1], bbox[2], bbox[3]),
        "--box",
        "20,300,90,120",
        "--top-k",
        "3",
        "--json",
    ]);
    let detections = json["detections"].as_array().unwrap();
    assert_eq!(detections.len(), 2);
    assert_eq!(
        detections[0]["prediction"]["top"].as_array().unwrap().len(),
        3
    );
    // A box without intrinsics is refused by the CLI itself, naming the flag.
    let out = Command::new(env!("CARGO_BIN_EXE_alignist"))
        .args(["--server", &server.grpc, "predict", "--image"])
        .arg(&path)
        .args(["--box", "1,2,3,4"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--intrinsics"));
}

/// Objects are described for planners: the cube's group, its rotations, its frame.
async fn objects_are_described_for_planners(client: &mut AlignistClient<Channel>) {
    let models = client
        .list_models(ListModelsRequest {})
        .await
        .unwrap()
        .into_inner()
        .models;
    let cube = &models[0].objects[0];
    assert_eq!(cube.symmetry, "O");
    assert_eq!(cube.symmetry_rotations.len(), 24);
    assert!(cube.symmetry_axis.is_none());
    assert!(cube.frame_scale > 0.0 && cube.frame_centre.is_some());
}
