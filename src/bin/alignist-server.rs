//! `alignist-server`: the gRPC service (its engine and transport land with a later issue).

use anyhow::{Result, bail};
use clap::Parser;
use std::path::PathBuf;

/// Serves orientation distributions over gRPC.
#[derive(Parser)]
#[command(name = "alignist-server", version, about, long_about = None)]
struct Cli {
    /// Directory of model bundles to serve.
    #[arg(long, env = "ALIGNIST_MODELS", default_value = "models")]
    models: PathBuf,
    /// gRPC listen address.
    #[arg(long, env = "ALIGNIST_LISTEN", default_value = "127.0.0.1:50051")]
    listen: String,
    /// Prometheus metrics listen address.
    #[arg(
        long,
        env = "ALIGNIST_METRICS_LISTEN",
        default_value = "127.0.0.1:9100"
    )]
    metrics_listen: String,
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    bail!(
        "serving is not implemented yet (would serve {} on {}, metrics on {})",
        cli.models.display(),
        cli.listen,
        cli.metrics_listen
    )
}
