//! Reliability under load and faults, over real loopback: 10 000 calls at concurrency 32 through
//! the `alignist load` tool, a model swap under load, a corrupt bundle refused on reload, and the
//! trainer killed with SIGKILL while checkpointing.

mod common;

use std::process::Command;
use std::time::Duration;

use alignist::client::load::run_load;
use alignist::serve::proto::alignist_client::AlignistClient;
use alignist::serve::proto::{ListModelsRequest, PredictRequest};
use common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn ten_thousand_calls_at_concurrency_32_all_succeed() {
    let server = start_server(&["--max-batch", "32", "--queue", "1024"]);
    wait_serving(channel(&server).await).await;
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("cube.png");
    std::fs::write(&png, cube_png(21)).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_alignist"))
        .args(["--server", &server.grpc, "load", "--image"])
        .arg(&png)
        .args([
            "--requests",
            "10000",
            "--concurrency",
            "32",
            "--top-k",
            "1",
            "--level",
            "1",
        ])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("10000 requests"), "{stdout}");
    assert!(stdout.contains("status codes: Ok 10000"), "{stdout}");
    // The tool refuses anything but loopback.
    let out = Command::new(env!("CARGO_BIN_EXE_alignist"))
        .args(["--server", "http://example.com:50051", "load"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("only targets this machine"));
}

async fn model_names(server: &Server) -> Vec<String> {
    let mut client = AlignistClient::new(channel(server).await);
    client
        .list_models(ListModelsRequest {})
        .await
        .unwrap()
        .into_inner()
        .models
        .into_iter()
        .map(|m| m.name)
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn models_swap_under_load_without_a_failed_call_and_a_corrupt_one_is_refused() {
    let models = copy_models();
    let server = start_server_on(models.path(), &["--reload-interval-s", "1"]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    assert_eq!(model_names(&server).await, ["tiny"]);

    // Load runs while a second bundle is added: the reload swaps engines under it.
    let request = PredictRequest {
        model: "tiny".into(),
        image: image(cube_png(22)),
        top_k: 3,
        level: 2,
        ..Default::default()
    };
    let load = tokio::spawn(run_load(
        vec![
            alignist::client::connect(&server.grpc, Duration::from_secs(60))
                .await
                .unwrap(),
        ],
        request.clone(),
        1500,
        8,
        Duration::from_secs(60),
    ));
    tokio::time::sleep(Duration::from_millis(500)).await;
    // Written beside, then renamed in: a bundle appears whole.
    let staging = models.path().join(".staging");
    copy_tree(&models.path().join("tiny"), &staging);
    std::fs::rename(&staging, models.path().join("tiny2")).unwrap();
    let report = load.await.unwrap().unwrap();
    assert_eq!(report.failures(), 0, "{report}");
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    while model_names(&server).await != ["tiny", "tiny2"] {
        assert!(std::time::Instant::now() < deadline, "never reloaded");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let text = http_get(&server.metrics).await;
    assert!(
        metric(&text, "alignist_reloads_total", &["result=\"ok\""]) >= 1.0,
        "{text}"
    );

    // A corrupt bundle is refused on its own; the models being served stay and keep answering.
    let broken = models.path().join("broken");
    copy_tree(&models.path().join("tiny"), &broken);
    corrupt_weights(&broken);
    let failed = wait_failed(&server, &["broken"]).await;
    assert!(
        failed[0].error.contains("network.safetensors"),
        "{failed:?}"
    );
    assert!(!failed[0].serving_previous);
    assert_eq!(model_names(&server).await, ["tiny", "tiny2"]);
    let mut client = AlignistClient::new(ch.clone());
    let answer = client.predict(request.clone()).await.unwrap().into_inner();
    assert_eq!(answer.top.len(), 3);

    // A served bundle that turns corrupt keeps its previous version serving, listed as refused.
    corrupt_weights(&models.path().join("tiny2"));
    let failed = wait_failed(&server, &["broken", "tiny2"]).await;
    assert!(failed[1].serving_previous, "{failed:?}");
    assert_eq!(model_names(&server).await, ["tiny", "tiny2"]);
    let answer = client
        .predict(PredictRequest {
            model: "tiny2".into(),
            ..request
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(answer.top.len(), 3);
}

/// Flips a byte of a bundle's weights (its checksum no longer matches).
fn corrupt_weights(bundle: &std::path::Path) {
    let weights = bundle.join("network.safetensors");
    let mut bytes = std::fs::read(&weights).unwrap();
    let n = bytes.len();
    bytes[n - 5] ^= 0x5a;
    std::fs::write(&weights, bytes).unwrap();
}

/// Waits until ListModels lists exactly `names` as refused, and returns them.
async fn wait_failed(server: &Server, names: &[&str]) -> Vec<alignist::serve::proto::ModelFailure> {
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    loop {
        let failed = AlignistClient::new(channel(server).await)
            .list_models(ListModelsRequest {})
            .await
            .unwrap()
            .into_inner()
            .failed;
        if failed.iter().map(|f| f.name.as_str()).collect::<Vec<_>>() == names {
            return failed;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "refused {failed:?}, expected {names:?}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn an_encoder_panic_fails_one_call_and_the_next_ones_succeed() {
    let server =
        start_server_with_env(models_dir(), &[], &[("ALIGNIST_FAULT_ENCODER_PANICS", "1")]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    let mut client = AlignistClient::new(ch.clone());
    let request = |seed| PredictRequest {
        model: "tiny".into(),
        image: image(cube_png(seed)),
        top_k: 2,
        level: 2,
        ..Default::default()
    };
    let status = client.predict(request(30)).await.unwrap_err();
    assert_eq!(status.code(), tonic::Code::Internal, "{status:?}");
    assert!(
        status.message().contains("panicked"),
        "{}",
        status.message()
    );
    for seed in 31..34 {
        let answer = client.predict(request(seed)).await.unwrap().into_inner();
        assert_eq!(answer.top.len(), 2);
    }
    let text = http_get(&server.metrics).await;
    assert_eq!(
        metric(
            &text,
            "alignist_worker_panics_total",
            &["worker=\"encoder\""]
        ),
        1.0,
        "{text}"
    );
    assert_eq!(health(ch).await, 1, "still SERVING");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_corrupt_bundle_beside_a_good_one_does_not_stop_start_up() {
    let models = copy_models();
    let broken = models.path().join("broken");
    copy_tree(&models.path().join("tiny"), &broken);
    corrupt_weights(&broken);
    let server = start_server_on(models.path(), &[]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    assert_eq!(model_names(&server).await, ["tiny"]);
    let failed = wait_failed(&server, &["broken"]).await;
    assert!(failed[0].error.contains("sha256"), "{failed:?}");
    let answer = AlignistClient::new(ch)
        .predict(PredictRequest {
            model: "tiny".into(),
            image: image(cube_png(23)),
            top_k: 2,
            level: 2,
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(answer.top.len(), 2);
    let text = http_get(&server.metrics).await;
    assert_eq!(
        metric(
            &text,
            "alignist_model_load_failures_total",
            &["model=\"broken\""]
        ),
        1.0,
        "{text}"
    );
    // The CLI lists the refused bundle with its error.
    let out = Command::new(env!("CARGO_BIN_EXE_alignist"))
        .args(["--server", &server.grpc, "models"])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && stdout.contains("REFUSED broken"),
        "{stdout}"
    );
}

#[test]
fn trainer_killed_while_checkpointing_resumes_from_the_last_good_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let s = |p: &std::path::Path| p.to_str().unwrap().to_string();
    let data = dir.path().join("data");
    let experts = models_dir().join("tiny/experts/cube");
    let out = Command::new(env!("CARGO_BIN_EXE_alignist-train"))
        .args(["render", "--shape", "cube", "--count", "6", "--size", "32"])
        .args(["--seed", "3", "--out", &s(&data)])
        .output()
        .unwrap();
    assert!(out.status.success());
    let bundle = dir.path().join("models/killed");
    let fit = || {
        let mut c = Command::new(env!("CARGO_BIN_EXE_alignist-train"));
        c.args(["fit", "--data", &s(&data), "--experts", &s(&experts)])
            .args([
                "--out",
                &s(&bundle),
                "--steps",
                "60",
                "--batch",
                "2",
                "--k",
                "16",
            ])
            .args([
                "--image-size",
                "32",
                "--checkpoint-every",
                "1",
                "--eval-images",
                "0",
            ])
            .args(["--resume"])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null());
        c
    };
    let checkpoints = bundle.with_extension("checkpoints");
    // SIGKILL at staggered times: with a checkpoint every step, many kills land mid-write.
    for delay_ms in [1500u64, 1700, 1900, 2300] {
        let mut child = fit().spawn().unwrap();
        std::thread::sleep(Duration::from_millis(delay_ms));
        let _ = child.kill();
        let _ = child.wait();
        if bundle.join("manifest.json").exists() {
            break;
        }
    }
    let latest_before = std::fs::read_to_string(checkpoints.join("latest")).ok();
    let status = fit().status().unwrap();
    assert!(
        status.success(),
        "resume after SIGKILL failed (latest was {latest_before:?})"
    );
    let m = alignist::bundle::model::ModelBundle::load(&bundle)
        .unwrap()
        .manifest;
    assert_eq!(m.provenance.train.steps, 60);
    if latest_before.is_some() {
        // It resumed: the run after the kills trained fewer than all 60 steps.
        assert!(m.provenance.report.resumed_from > 0 || m.provenance.report.steps_run == 0);
    }
}

/// An RGB noise PNG of `w × h` (noise does not compress: about `3·w·h` bytes).
fn noise_png(w: u32, h: u32) -> Vec<u8> {
    use rand::{RngExt, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let rgb: Vec<u8> = (0..w * h * 3).map(|_| rng.random::<u8>()).collect();
    let mut png = Vec::new();
    image::RgbImage::from_raw(w, h, rgb)
        .unwrap()
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    png
}

/// Peak resident memory of a process, in MiB (`VmHWM` of `/proc/PID/status`).
fn peak_rss_mib(pid: u32) -> f64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let line = status.lines().find(|l| l.starts_with("VmHWM:")).unwrap();
    let kib: f64 = line.split_whitespace().nth(1).unwrap().parse().unwrap();
    kib / 1024.0
}

/// The flood's bound on the server's peak memory, in MiB: 64 calls of 8 MB in flight are read
/// whole by the transport before admission (~512 MiB), plus a 64 MiB decode budget and the model.
/// Measured: 699 MiB (88 MiB before the flood).
const FLOOD_RSS_BOUND_MIB: f64 = 1024.0;

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_flood_of_large_images_is_admitted_within_budget_and_memory_stays_bounded() {
    use tonic_types::StatusExt;
    let server = start_server(&["--max-in-flight-mib", "64"]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    let pid = server.child.id();
    let before = peak_rss_mib(pid);
    let big = noise_png(1600, 1600);
    assert!(
        big.len() > 7 << 20 && big.len() < 8 << 20,
        "{} bytes",
        big.len()
    );
    let request = PredictRequest {
        model: "tiny".into(),
        image: image(big),
        top_k: 1,
        level: 2,
        ..Default::default()
    };
    // 200 calls, 64 in flight at a time, each with a 60 s deadline.
    let semaphore = std::sync::Arc::new(tokio::sync::Semaphore::new(64));
    let mut calls = Vec::new();
    for _ in 0..200 {
        let permit = semaphore.clone().acquire_owned().await.unwrap();
        let (ch, request) = (ch.clone(), request.clone());
        calls.push(tokio::spawn(async move {
            let _permit = permit;
            let mut client = AlignistClient::new(ch);
            tokio::time::timeout(Duration::from_secs(60), client.predict(request)).await
        }));
    }
    let (mut ok, mut refused) = (0, 0);
    for call in calls {
        match call.await.unwrap() {
            Err(_) => panic!("a call hung past its deadline"),
            Ok(Ok(_)) => ok += 1,
            Ok(Err(s)) => {
                assert!(
                    matches!(
                        s.code(),
                        tonic::Code::ResourceExhausted | tonic::Code::Unavailable
                    ),
                    "{s:?}"
                );
                let retry = s.get_details_retry_info();
                assert!(
                    retry.and_then(|r| r.retry_delay).is_some(),
                    "a refusal says when to retry: {s:?}"
                );
                refused += 1;
            }
        }
    }
    let peak = peak_rss_mib(pid);
    eprintln!(
        "flood: {ok} answered, {refused} refused with a retry delay; server peak RSS \
         {before:.0} MiB before, {peak:.0} MiB after (bound {FLOOD_RSS_BOUND_MIB} MiB)"
    );
    assert_eq!(ok + refused, 200);
    assert!(ok >= 1, "some calls are admitted");
    assert!(peak < FLOOD_RSS_BOUND_MIB, "peak RSS {peak:.0} MiB");
    // Afterwards small requests are served normally.
    let answer = AlignistClient::new(ch)
        .predict(PredictRequest {
            model: "tiny".into(),
            image: image(cube_png(40)),
            top_k: 2,
            level: 2,
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(answer.top.len(), 2);
}
