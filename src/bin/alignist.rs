//! `alignist`: the command-line client of the gRPC service (lands with a later issue).

use anyhow::{Result, bail};
use clap::{Parser, Subcommand};

/// Asks an alignist server how an object is oriented.
#[derive(Parser)]
#[command(name = "alignist", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Top-k rotations, MAP and modes for an image (not yet implemented).
    Predict,
    /// List the models a server holds (not yet implemented).
    Models,
    /// Check a server's health (not yet implemented).
    Health,
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    let name = match cli.command {
        Command::Predict => "predict",
        Command::Models => "models",
        Command::Health => "health",
    };
    bail!("`alignist {name}` is not implemented yet")
}
