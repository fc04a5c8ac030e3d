//! A bounded load generator for loopback servers: N Predict calls, C at a time, on one HTTP/2
//! connection per worker; reports throughput, latency quantiles and counts by status code.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use super::ClientError;
use crate::serve::proto::PredictRequest;
use crate::serve::proto::alignist_client::AlignistClient;
use crate::so3::metrics::quantile;

/// What a load run measured.
#[derive(Debug, Clone, PartialEq)]
pub struct LoadReport {
    /// Calls made.
    pub requests: usize,
    /// Wall time.
    pub seconds: f64,
    /// Calls per second.
    pub requests_per_second: f64,
    /// Latency quantiles in milliseconds: p50, p90, p99.
    pub p50_ms: f64,
    /// 90th percentile.
    pub p90_ms: f64,
    /// 99th percentile.
    pub p99_ms: f64,
    /// Calls by status code name ("Ok", "Unavailable", …).
    pub codes: BTreeMap<String, usize>,
}

impl LoadReport {
    /// Calls that did not end OK.
    pub fn failures(&self) -> usize {
        self.codes
            .iter()
            .filter(|(c, _)| c.as_str() != "Ok")
            .map(|(_, n)| n)
            .sum()
    }
}

impl std::fmt::Display for LoadReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "{} requests in {:.2} s: {:.1} requests/s",
            self.requests, self.seconds, self.requests_per_second
        )?;
        writeln!(
            f,
            "latency p50 {:.2} ms, p90 {:.2} ms, p99 {:.2} ms",
            self.p50_ms, self.p90_ms, self.p99_ms
        )?;
        let codes: Vec<String> = self.codes.iter().map(|(c, n)| format!("{c} {n}")).collect();
        write!(f, "status codes: {}", codes.join(", "))
    }
}

/// Whether `url` names this machine (the generator refuses anything else).
pub fn is_loopback(url: &str) -> bool {
    let rest = url
        .strip_prefix("http://")
        .or_else(|| url.strip_prefix("https://"))
        .unwrap_or(url);
    let host = rest.split('/').next().unwrap_or("");
    let host = match host.rsplit_once(':') {
        Some((h, port)) if port.chars().all(|c| c.is_ascii_digit()) => h,
        _ => host,
    };
    let host = host.trim_start_matches('[').trim_end_matches(']');
    host == "localhost"
        || host
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

/// Sends `requests` copies of `request`, `concurrency` at a time, over `channels` (round-robin).
pub async fn run_load(
    channels: Vec<super::Connection>,
    request: PredictRequest,
    requests: usize,
    concurrency: usize,
    per_call_timeout: Duration,
) -> Result<LoadReport, ClientError> {
    if channels.is_empty() || concurrency == 0 {
        return Err(ClientError::Connect {
            url: String::new(),
            message: "load needs at least one connection and a concurrency of 1 or more".into(),
        });
    }
    let next = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let started = Instant::now();
    let workers: Vec<_> = (0..concurrency.min(requests.max(1)))
        .map(|w| {
            let mut client = AlignistClient::new(channels[w % channels.len()].clone());
            let request = request.clone();
            let next = next.clone();
            tokio::spawn(async move {
                let mut out = Vec::new();
                while next.fetch_add(1, std::sync::atomic::Ordering::Relaxed) < requests {
                    let mut call = tonic::Request::new(request.clone());
                    call.set_timeout(per_call_timeout);
                    let t = Instant::now();
                    let code = match client.predict(call).await {
                        Ok(_) => tonic::Code::Ok,
                        Err(s) => s.code(),
                    };
                    out.push((t.elapsed().as_secs_f64() * 1e3, code));
                }
                out
            })
        })
        .collect();
    let mut latencies = Vec::with_capacity(requests);
    let mut codes = BTreeMap::new();
    for w in workers {
        let results = w.await.map_err(|e| ClientError::Connect {
            url: String::new(),
            message: format!("load worker failed: {e}"),
        })?;
        for (ms, code) in results {
            latencies.push(ms);
            *codes.entry(format!("{code:?}")).or_insert(0) += 1;
        }
    }
    let seconds = started.elapsed().as_secs_f64();
    Ok(LoadReport {
        requests: latencies.len(),
        seconds,
        requests_per_second: latencies.len() as f64 / seconds.max(1e-9),
        p50_ms: quantile(&latencies, 0.5),
        p90_ms: quantile(&latencies, 0.9),
        p99_ms: quantile(&latencies, 0.99),
        codes,
    })
}
