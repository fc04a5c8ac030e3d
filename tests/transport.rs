//! The transport's bounds over real loopback connections: unfinished request bodies are dropped
//! after the body timeout and their memory returned, a flood of silent sockets does not lock out
//! a health check, and TLS with a bearer token works end to end through the CLI.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use bytes::Bytes;
use common::*;

/// Resident memory of process `pid`, in MiB.
fn rss_mib(pid: u32) -> f64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let line = status.lines().find(|l| l.starts_with("VmRSS:")).unwrap();
    let kib: f64 = line.split_whitespace().nth(1).unwrap().parse().unwrap();
    kib / 1024.0
}

/// The server's address without the scheme.
fn address(server: &Server) -> String {
    server.grpc.trim_start_matches("http://").to_string()
}

/// A raw HTTP/2 connection to `server` (its driver spawned).
async fn h2_connection(server: &Server) -> h2::client::SendRequest<Bytes> {
    let tcp = tokio::net::TcpStream::connect(address(server))
        .await
        .unwrap();
    let (h2, connection) = h2::client::handshake(tcp).await.unwrap();
    tokio::spawn(connection);
    h2
}

/// The headers of a gRPC Predict call.
fn predict_headers(server: &Server) -> http::Request<()> {
    http::Request::post(format!(
        "http://{}/alignist.v1.Alignist/Predict",
        address(server)
    ))
    .header("content-type", "application/grpc")
    .header("te", "trailers")
    .body(())
    .unwrap()
}

/// A Predict call on `h2` whose message declares `declared` bytes and sends `sent` of them,
/// never finishing: its answer and its open body.
async fn unfinished_predict(
    h2: h2::client::SendRequest<Bytes>,
    server: &Server,
    declared: u32,
    sent: usize,
) -> (
    h2::client::SendRequest<Bytes>,
    (h2::client::ResponseFuture, h2::SendStream<Bytes>),
) {
    let mut h2 = h2.ready().await.unwrap();
    let (response, mut body) = h2.send_request(predict_headers(server), false).unwrap();
    let mut data = vec![0u8; 5 + sent];
    data[1..5].copy_from_slice(&declared.to_be_bytes());
    body.send_data(Bytes::from(data), false).unwrap();
    (h2, (response, body))
}

/// The `grpc-status` of an answer's headers.
fn grpc_status(response: &http::Response<h2::RecvStream>) -> Option<String> {
    response
        .headers()
        .get("grpc-status")
        .map(|v| v.to_str().unwrap().to_string())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn unfinished_bodies_over_the_receive_budget_are_refused_at_once() {
    let server = start_server(&["--max-receiving-mib", "8", "--body-timeout-s", "20"]);
    wait_serving(channel(&server).await).await;
    let h2 = h2_connection(&server).await;
    // 6 MiB of a first body are held; 6 MiB more of a second do not fit in 8 MiB.
    let (h2, (mut first, _first_body)) = unfinished_predict(h2, &server, 7 << 20, 6 << 20).await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let (_h2, (second, _second_body)) = unfinished_predict(h2, &server, 7 << 20, 6 << 20).await;
    let answer = tokio::time::timeout(Duration::from_secs(5), second)
        .await
        .expect("the call over the budget was not refused at once")
        .unwrap();
    assert_eq!(
        grpc_status(&answer).as_deref(),
        Some("8"),
        "{:?}",
        answer.headers()
    );
    // The first is still waiting for its body (no answer yet).
    assert!(
        tokio::time::timeout(Duration::from_millis(300), &mut first)
            .await
            .is_err()
    );
    let metrics = http_get(&server.metrics).await;
    assert!(
        metric(
            &metrics,
            "alignist_refused_total",
            &["reason=\"receive_budget\""]
        ) >= 1.0
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn unfinished_bodies_are_dropped_after_the_body_timeout_and_their_memory_freed() {
    let server = start_server(&["--body-timeout-s", "3"]);
    let ch = channel(&server).await;
    wait_serving(ch.clone()).await;
    let pid = server.child.id();
    // A finished call first, so that the baseline holds what serving needs.
    let mut client = alignist::serve::proto::alignist_client::AlignistClient::new(ch.clone());
    client.predict(predict_request(1, 1, 2)).await.unwrap();
    let baseline = rss_mib(pid);

    // 24 Predict calls on one connection, each declaring an 8 MiB message and sending 7 MiB of
    // it, never finishing.
    let mut h2 = h2_connection(&server).await;
    let mut calls = Vec::new();
    let started = Instant::now();
    for _ in 0..24 {
        let call;
        (h2, call) = unfinished_predict(h2, &server, 8 << 20, 7 << 20).await;
        calls.push(call);
    }
    // The server takes the bytes in (its memory grows) ...
    let mut peak = baseline;
    while started.elapsed() < Duration::from_secs(2) {
        peak = peak.max(rss_mib(pid));
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(
        peak > baseline + 100.0,
        "the bodies never reached the server: {baseline:.0} → {peak:.0} MiB"
    );
    // ... and after the body timeout answers each call DEADLINE_EXCEEDED and drops its body.
    for (response, _body) in calls.iter_mut() {
        let answer = tokio::time::timeout(Duration::from_secs(10), response)
            .await
            .expect("no answer after the body timeout")
            .unwrap();
        assert_eq!(
            grpc_status(&answer).as_deref(),
            Some("4"),
            "{:?}",
            answer.headers()
        );
    }
    assert!(started.elapsed() >= Duration::from_secs(3));
    tokio::time::sleep(Duration::from_millis(500)).await;
    let after = rss_mib(pid);
    assert!(
        after < baseline + 40.0,
        "memory not returned: baseline {baseline:.0}, peak {peak:.0}, after {after:.0} MiB"
    );
    // The server still answers, and counted the timeouts.
    let answer = client
        .predict(predict_request(2, 1, 2))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(answer.top.len(), 1);
    let metrics = http_get(&server.metrics).await;
    assert_eq!(
        metric(
            &metrics,
            "alignist_refused_total",
            &["reason=\"body_timeout\""]
        ),
        24.0
    );
}

/// Sets this process's soft limit of open files to `n` (at most the hard limit; processes it
/// starts inherit it) and returns the limit set.
fn allow_open_files(n: u64) -> u64 {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit/setrlimit read and write the struct given, nothing else.
    unsafe {
        libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit);
        limit.rlim_cur = n.min(limit.rlim_max);
        libc::setrlimit(libc::RLIMIT_NOFILE, &limit);
    }
    limit.rlim_cur
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn eleven_hundred_silent_sockets_do_not_stop_a_health_check() {
    let sockets = 1100;
    // The server under the usual container limit of 1 024 open files, with the default
    // connection cap (512) and handshake timeout (10 s); this process needs more.
    assert_eq!(
        allow_open_files(1024),
        1024,
        "cannot set the open-files limit"
    );
    let server = start_server(&[]);
    assert!(
        allow_open_files(sockets + 200) >= sockets + 200,
        "this test needs {} open files",
        sockets + 200
    );
    wait_serving(channel(&server).await).await;
    let mut idle = Vec::new();
    for _ in 0..sockets {
        idle.push(
            tokio::net::TcpStream::connect(address(&server))
                .await
                .unwrap(),
        );
    }
    // Within the handshake timeout, while every silent socket could still be held, a new client
    // is answered: it takes the place of the oldest silent one.
    let started = Instant::now();
    let serving = tokio::time::timeout(Duration::from_secs(5), async {
        let ch = channel(&server).await;
        health(ch).await
    })
    .await
    .expect("health check blocked by silent sockets");
    assert_eq!(serving, 1);
    assert!(started.elapsed() < Duration::from_secs(5));
    let metrics = http_get(&server.metrics).await;
    let evicted = metric(
        &metrics,
        "alignist_connections_closed_total",
        &["reason=\"evicted\""],
    );
    assert!(evicted >= (sockets - 512) as f64, "{evicted} evicted");
    assert!(metric(&metrics, "alignist_connections_open", &[]) <= 512.0);
    drop(idle);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_silent_connection_is_closed_after_the_handshake_timeout() {
    use tokio::io::AsyncReadExt;
    let server = start_server(&["--handshake-timeout-s", "1"]);
    wait_serving(channel(&server).await).await;
    let mut silent = tokio::net::TcpStream::connect(address(&server))
        .await
        .unwrap();
    // The server speaks first (its HTTP/2 settings), then closes: the reads end (EOF or reset)
    // instead of waiting forever.
    let closed = tokio::time::timeout(Duration::from_secs(5), async {
        let mut buf = [0u8; 256];
        while let Ok(n) = silent.read(&mut buf).await {
            if n == 0 {
                break;
            }
        }
    })
    .await;
    assert!(
        closed.is_ok(),
        "a silent connection was held past its handshake timeout"
    );
    let metrics = http_get(&server.metrics).await;
    assert!(
        metric(
            &metrics,
            "alignist_connections_closed_total",
            &["reason=\"handshake_timeout\""]
        ) >= 1.0
    );
}

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/tls")
        .join(name)
}

/// Runs the CLI against `url` with `args` and the CA (and token, if given).
fn cli(url: &str, token: Option<&Path>, args: &[&str]) -> std::process::Output {
    let mut command = Command::new(env!("CARGO_BIN_EXE_alignist"));
    command
        .args(["--server", url, "--timeout-s", "20", "--ca-file"])
        .arg(fixture("server.pem"));
    if let Some(t) = token {
        command.arg("--token-file").arg(t);
    }
    command.args(args).output().unwrap()
}

#[test]
fn tls_with_a_self_signed_certificate_and_a_token_work_end_to_end_through_the_cli() {
    let dir = tempfile::tempdir().unwrap();
    let (good, wrong) = (dir.path().join("token"), dir.path().join("wrong"));
    std::fs::write(&good, "s3cret-token-0123456789abcdef\n").unwrap();
    std::fs::write(&wrong, "not-the-token-0123456789abcdef").unwrap();
    let cert = fixture("server.pem");
    let key = fixture("server.key");
    let health_port = free_port();
    let health_listen = format!("127.0.0.1:{health_port}");
    let server = start_server(&[
        "--health-listen",
        &health_listen,
        "--tls-cert",
        cert.to_str().unwrap(),
        "--tls-key",
        key.to_str().unwrap(),
        "--auth-token-file",
        good.to_str().unwrap(),
    ]);
    let port = address(&server).rsplit(':').next().unwrap().to_string();
    let url = format!("https://localhost:{port}");
    // Health checks need no token (orchestrators' probes); wait for the models.
    let started = Instant::now();
    loop {
        let out = cli(&url, None, &["health"]);
        if out.status.success() {
            assert_eq!(String::from_utf8_lossy(&out.stdout).trim(), "Serving");
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "never healthy over TLS: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    // The right token lists the models.
    let out = cli(&url, Some(&good), &["models", "--json"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("\"tiny\""));
    // A wrong token, and none, are UNAUTHENTICATED.
    for token in [Some(wrong.as_path()), None] {
        let out = cli(&url, token, &["models"]);
        assert!(!out.status.success());
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(stderr.contains("Unauthenticated"), "{token:?}: {stderr}");
    }
    // Probes that cannot speak TLS ask the plaintext health port, which serves nothing else.
    let plain_health = format!("http://{health_listen}");
    let probe = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_alignist"))
            .args(["--server", &plain_health, "--timeout-s", "5"])
            .args(args)
            .output()
            .unwrap()
    };
    let out = probe(&["health"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(!probe(&["models"]).status.success());
    // Plaintext to the TLS port does not get an answer.
    let plain = format!("http://127.0.0.1:{port}");
    let out = Command::new(env!("CARGO_BIN_EXE_alignist"))
        .args(["--server", &plain, "--timeout-s", "5", "--token-file"])
        .arg(&good)
        .args(["models"])
        .output()
        .unwrap();
    assert!(!out.status.success());
}

/// Sends one Predict call of raw `body` bytes on a fresh HTTP/2 connection and returns the
/// answer's headers and trailers merged (a refusal comes trailers-only, in the headers).
async fn raw_predict(server: &Server, body: Vec<u8>) -> http::HeaderMap {
    let mut h2 = h2_connection(server).await.ready().await.unwrap();
    let (response, mut send) = h2.send_request(predict_headers(server), false).unwrap();
    send.send_data(Bytes::from(body), true).unwrap();
    let response = response.await.unwrap();
    let mut headers = response.headers().clone();
    let mut body = response.into_body();
    while let Some(data) = body.data().await {
        let _ = data;
    }
    if let Ok(Some(trailers)) = body.trailers().await {
        headers.extend(trailers);
    }
    headers
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn malformed_and_oversized_messages_get_named_codes() {
    let server = start_server(&[]);
    wait_serving(channel(&server).await).await;
    // A message of 3 bytes that is not protobuf (field 31, wire type 7).
    let headers = raw_predict(&server, vec![0, 0, 0, 0, 3, 0xff, 0xff, 0xff]).await;
    assert_eq!(headers["grpc-status"], "3", "{headers:?}");
    assert!(headers.contains_key("grpc-status-details-bin"));
    assert!(headers.contains_key("x-request-id"));
    // A message declaring 1 GiB: refused before any of it is read.
    let mut declared = vec![0u8; 5];
    declared[1..5].copy_from_slice(&(1u32 << 30).to_be_bytes());
    let headers = raw_predict(&server, declared).await;
    assert_eq!(headers["grpc-status"], "8", "{headers:?}");
    assert!(headers.contains_key("grpc-status-details-bin"));
    let metrics = http_get(&server.metrics).await;
    assert!(
        metric(
            &metrics,
            "alignist_requests_total",
            &["code=\"INVALID_ARGUMENT\"", "method=\"Predict\""]
        ) >= 1.0
    );
}
