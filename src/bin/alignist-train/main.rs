//! `alignist-train`: the offline side of alignist — grids, renders, experts, training, evaluation.

//! Each subcommand lives in its own module; this file parses the command line and dispatches.

mod bench;
mod calibrate;
mod compare;
mod eval;
mod experts;
mod fit;
mod grid;
mod new;
mod object;
mod render;
mod results;
mod score;
mod symmetry;

use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand};

use eval::EvalArgs;
use experts::ExpertsArgs;
use fit::FitArgs;
use render::RenderArgs;
use score::ScoreArgs;

/// Trains and inspects alignist models.
#[derive(Parser)]
#[command(name = "alignist-train", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Write the centres of one level of the nested SO(3) grid as CSV
    /// (`index,qw,qx,qy,qz`, index order, w ≥ 0).
    Grid {
        /// Grid level L (0 ..= 6): 72·8^L cells.
        #[arg(long)]
        level: u8,
        /// Output CSV file (written to a temporary name, then renamed).
        #[arg(long)]
        out: PathBuf,
    },
    /// Render a dataset of one object in BOP layout (SYMSOL style: centred, fully in view,
    /// every equivalent ground truth recorded in scene_gt_equivalents.json).
    Render(RenderArgs),
    /// Train the two CAD experts of an object (SDF and SurfEmb features), bake them, choose λ by
    /// the LL of their targets, and write the expert set.
    Experts(ExpertsArgs),
    /// Print the symmetry of a part as its SDF shows it (a mesh's exact SDF, or an expert set's
    /// baked one): none, C<n>, D<n>, cone, cylinder, T, O, I, with its axes, a confidence, and
    /// the larger group the part nearly has.
    Symmetry(symmetry::SymmetryArgs),
    /// Write the target distribution the experts give for one rotation on every cell of a grid
    /// level (`index,log_a_sdf,log_a_se`).
    Score(ScoreArgs),
    /// From CAD files to a served model within a time budget: the experts of every part, one
    /// network on realistic renders by the recipe, a held-out realistic evaluation, the bundle
    /// (resumable with --resume; the symmetry of each part is discovered and reported).
    New(new::NewArgs),
    /// Train the distribution network on BOP datasets (one per object, with its expert set),
    /// evaluate it on their test splits, and write a model bundle.
    Fit(FitArgs),
    /// Evaluate a model bundle on the test split of BOP datasets.
    Eval(EvalArgs),
    /// Fold a temperature into a bundle's network, chosen by the LL of realistic crops of the
    /// training distribution (a model that is unsure should say so), and write the calibrated
    /// bundle.
    Calibrate(calibrate::CalibrateArgs),
    /// Compare two evaluation reports of the same crops image by image (paired: LL, AR@30 of
    /// the argmax and of the first mode, B − A with standard errors and McNemar's p).
    Compare(compare::CompareArgs),
    /// Print the evaluation figures of model bundles as Markdown tables (per object and
    /// averaged, with the ceiling of the level, the training budget and wall time).
    Results {
        /// Model bundle folders.
        #[arg(required = true)]
        bundles: Vec<PathBuf>,
    },
    /// Print performance figures of a model bundle (the backend's matmul peak, full-grid head
    /// throughput at levels 3 and 4 against it, coarse-to-fine top-k latency, encoder images/s,
    /// gRPC against in-process Predict throughput), or with --training, of the training step.
    Bench(bench::BenchArgs),
}

/// A training step frees and re-allocates the same few large buffers (activations, im2col
/// columns, gradients) every step. Under glibc's defaults each is mapped from the OS and unmapped
/// again, or trimmed off the heap's top when freed, and every step then pays for page faults on
/// fresh pages (and TLB shootdowns across the threads). Here they stay in the heap: large
/// allocations are not mapped separately and the heap is not trimmed. Measured on a 64 px
/// realistic `fit` step (batch 16, K 256, 2 cores), alternated: 248 / 253 ms → 187 / 184 ms, the
/// encoder's backward 126 → 65 ms (BENCHMARKS.md, "The allocator in the trainer"). An
/// operator's own `MALLOC_MMAP_THRESHOLD_` or `MALLOC_TRIM_THRESHOLD_` (glibc's tunables, read
/// before `main`) wins over the setting it names.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn keep_freed_buffers_in_the_heap() {
    let unset = |tunable: &str| std::env::var_os(tunable).is_none();
    // SAFETY: mallopt only sets allocator parameters; called before any thread starts.
    unsafe {
        // glibc 2.36 takes 1 GiB; a glibc that refuses a threshold above 32 MiB (the largest
        // its dynamic threshold reaches on 64-bit) gets that.
        if unset("MALLOC_MMAP_THRESHOLD_") && libc::mallopt(libc::M_MMAP_THRESHOLD, 1 << 30) == 0 {
            libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        }
        if unset("MALLOC_TRIM_THRESHOLD_") {
            libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30);
        }
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn keep_freed_buffers_in_the_heap() {}

fn main() -> Result<()> {
    keep_freed_buffers_in_the_heap();
    let cli = Cli::parse();
    match cli.command {
        Command::Grid { level, out } => grid::write_grid(level, &out),
        Command::Render(args) => render::render_cmd(&args),
        Command::Experts(args) => experts::experts_cmd(&args),
        Command::Score(args) => score::score_cmd(&args),
        Command::Symmetry(args) => symmetry::symmetry_cmd(&args),
        Command::Fit(args) => fit::fit_cmd(&args),
        Command::New(args) => new::new_cmd(&args),
        Command::Eval(args) => eval::eval_cmd(&args),
        Command::Calibrate(args) => calibrate::calibrate_cmd(&args),
        Command::Compare(args) => compare::compare_cmd(&args),
        Command::Results { bundles } => results::results_cmd(&bundles),
        Command::Bench(args) => bench::bench_cmd(&args),
    }
}
