//! Requests and bundles that used to take the server down, over real loopback: an image whose
//! padded square would not fit in memory, and manifests whose shapes or paths are out of range,
//! refused alone at start and on reload while the good bundle keeps serving.

mod common;

use std::path::Path;
use std::time::Duration;

use alignist::serve::proto::alignist_client::AlignistClient;
use alignist::serve::proto::{
    DistributionRequest, ImageInput, ListModelsRequest, ModelFailure, PredictRequest,
};
use common::*;

/// 1 048 576 × 1 white pixels: a PNG of a few KB, under the pixel limit, whose padded square is 3.3 TB.
fn long_row_png() -> Vec<u8> {
    let img = image::RgbImage::from_pixel(1 << 20, 1, image::Rgb([255, 255, 255]));
    let mut png = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    png
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_long_thin_image_and_its_raw_twin_are_refused_and_the_server_keeps_serving() {
    let server = start_server(&[]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    let mut client = AlignistClient::new(ch.clone());
    let png = long_row_png();
    assert!(png.len() < 32 << 10, "{} bytes", png.len());
    let raw = ImageInput {
        data: vec![255; 3 << 20],
        width: 1 << 20,
        height: 1,
        ..Default::default()
    };
    for input in [image(png).unwrap(), raw] {
        let status = client
            .predict(PredictRequest {
                model: "tiny".into(),
                image: Some(input.clone()),
                top_k: 1,
                ..Default::default()
            })
            .await
            .unwrap_err();
        assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
        assert!(status.message().contains("elongated"), "{status:?}");
        let status = match client
            .predict_distribution(DistributionRequest {
                model: "tiny".into(),
                image: Some(input),
                level: 1,
                ..Default::default()
            })
            .await
        {
            // The refusal may come as the stream's first message.
            Ok(stream) => stream.into_inner().message().await.unwrap_err(),
            Err(status) => status,
        };
        assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
    }
    assert_eq!(health(ch.clone()).await, 1, "SERVING after the refusals");
    let answer = client
        .predict(predict_request(7, 2, 1))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(answer.top.len(), 2);
}

/// A copy of `tiny` named `name` inside `models` whose manifest `edit` changes.
fn bad_bundle(models: &Path, name: &str, edit: impl Fn(&mut serde_json::Value)) {
    let staging = models.join(format!(".{name}"));
    copy_tree(&models.join("tiny"), &staging);
    let path = staging.join("manifest.json");
    let mut manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    edit(&mut manifest);
    std::fs::write(&path, serde_json::to_vec_pretty(&manifest).unwrap()).unwrap();
    std::fs::rename(&staging, models.join(name)).unwrap();
}

/// Bundles that would abort a server that trusted them, each with the field its refusal names.
fn add_bad_bundles(models: &Path) -> Vec<(&'static str, &'static str)> {
    bad_bundle(models, "huge_layers", |m| {
        m["network"]["layers"] = 100_000_000.into()
    });
    bad_bundle(models, "huge_size", |m| {
        m["network"]["image_size"] = 4_000_000_000u64.into()
    });
    bad_bundle(models, "outside", |m| {
        let entry = m["files"]["network.safetensors"].clone();
        m["files"]["../../../../etc/hostname"] = entry;
    });
    bad_bundle(models, "outside_experts", |m| {
        m["objects"][0]["experts"] = "/etc".into()
    });
    vec![
        ("huge_layers", "network.layers"),
        ("huge_size", "network.image_size"),
        ("outside", "outside the bundle"),
        ("outside_experts", "objects[0].experts"),
    ]
}

async fn listed(server: &Server) -> (Vec<String>, Vec<ModelFailure>) {
    let list = AlignistClient::new(channel(server).await)
        .list_models(ListModelsRequest {})
        .await
        .unwrap()
        .into_inner();
    (
        list.models.into_iter().map(|m| m.name).collect(),
        list.failed,
    )
}

fn check_refusals(failed: &[ModelFailure], expected: &[(&str, &str)]) {
    let names: Vec<&str> = failed.iter().map(|f| f.name.as_str()).collect();
    let want: Vec<&str> = expected.iter().map(|(n, _)| *n).collect();
    assert_eq!(names, want, "{failed:?}");
    for (f, (_, field)) in failed.iter().zip(expected) {
        assert!(f.error.contains(field), "{}: {}", f.name, f.error);
        assert!(!f.error.contains("/etc/hostname\":"), "{}", f.error);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn bundles_out_of_range_are_refused_alone_at_start_and_on_reload() {
    // At start.
    let models = copy_models();
    let expected = add_bad_bundles(models.path());
    let server = start_server_on(models.path(), &[]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    let (names, failed) = listed(&server).await;
    assert_eq!(names, ["tiny"]);
    check_refusals(&failed, &expected);
    drop(server);

    // On reload: the same bundles appear under a running server.
    let models = copy_models();
    let server = start_server_on(models.path(), &["--reload-interval-s", "1"]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    let expected = add_bad_bundles(models.path());
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    loop {
        let (names, failed) = listed(&server).await;
        if failed.len() == expected.len() {
            assert_eq!(names, ["tiny"]);
            check_refusals(&failed, &expected);
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "never reloaded: {failed:?}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let answer = AlignistClient::new(ch.clone())
        .predict(predict_request(8, 1, 1))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(answer.top.len(), 1);
    assert_eq!(health(ch).await, 1);
}
