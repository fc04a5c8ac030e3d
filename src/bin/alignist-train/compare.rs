//! `alignist-train compare`: two evaluation reports of the same crops compared image by image
//! ([`alignist::train::eval::compare_paired`]).

use std::path::{Path, PathBuf};

use alignist::train::eval::{EvalReport, PairedHits, compare_paired};
use anyhow::{Context, Result, bail};

/// Arguments of `alignist-train compare`.
#[derive(clap::Args, Debug)]
pub(crate) struct CompareArgs {
    /// The first report (A): a file `eval --out` wrote.
    pub a: PathBuf,
    /// The second report (B), of the same crops (the same `--seed`, `--images` and sets; the
    /// images are paired by object and ground truth).
    pub b: PathBuf,
    /// The threshold of AR@θ, degrees.
    #[arg(long, default_value_t = 30.0)]
    pub theta: f64,
}

/// The sets of a report file: `eval`'s plain report (one set, "all"), or the list that
/// `--realistic` (`set`) and `--frames` (`crops`) write, each with its report.
fn read_sets(path: &Path) -> Result<Vec<(String, EvalReport)>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let json: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    let parse = |value: &serde_json::Value, at: &str| {
        EvalReport::deserialize(value)
            .with_context(|| format!("{}: {at} is not an evaluation report", path.display()))
    };
    use serde::Deserialize;
    match &json {
        serde_json::Value::Array(sets) => sets
            .iter()
            .enumerate()
            .map(|(i, set)| {
                let label = set
                    .get("set")
                    .or_else(|| set.get("crops"))
                    .and_then(|l| l.as_str())
                    .with_context(|| format!("{}: [{i}] has no \"set\" label", path.display()))?;
                Ok((
                    label.to_string(),
                    parse(&set["report"], &format!("[{i}].report"))?,
                ))
            })
            .collect(),
        _ => Ok(vec![("all".to_string(), parse(&json, "the file")?)]),
    }
}

fn hits_line(name: &str, h: &PairedHits) {
    println!(
        "    {name:13} {:.3} → {:.3}  {:+.3} ± {:.3}  (right in A only {}, in B only {}; McNemar p {:.3})",
        h.rates.0,
        h.rates.1,
        h.rates.1 - h.rates.0,
        h.se,
        h.only.0,
        h.only.1,
        h.p_value
    );
}

pub(crate) fn compare_cmd(args: &CompareArgs) -> Result<()> {
    if !(args.theta.is_finite() && args.theta > 0.0 && args.theta <= 180.0) {
        bail!("--theta must be in (0, 180] degrees, got {}", args.theta);
    }
    let (a, b) = (read_sets(&args.a)?, read_sets(&args.b)?);
    println!("A: {}\nB: {}", args.a.display(), args.b.display());
    println!(
        "paired on the same crops, B − A, ± one standard error of the paired difference (AR@{}):",
        args.theta
    );
    let mut compared = 0;
    for (label, ra) in &a {
        let Some((_, rb)) = b.iter().find(|(l, _)| l == label) else {
            println!("  {label}: not in B, skipped");
            continue;
        };
        let c = compare_paired(&ra.images, &rb.images, args.theta).with_context(|| {
            format!(
                "set '{label}' of {} and {}",
                args.a.display(),
                args.b.display()
            )
        })?;
        println!("  {label} ({} images)", c.images);
        println!(
            "    {:13} {:.2} → {:.2}  {:+.2} ± {:.2}",
            "LL",
            c.ll.0,
            c.ll.1,
            c.ll.1 - c.ll.0,
            c.ll_se
        );
        hits_line("argmax", &c.argmax);
        hits_line("first mode", &c.mode);
        compared += 1;
    }
    for (label, _) in b.iter().filter(|(l, _)| !a.iter().any(|(m, _)| m == l)) {
        println!("  {label}: not in A, skipped");
    }
    if compared == 0 {
        bail!(
            "{} and {} share no set to compare",
            args.a.display(),
            args.b.display()
        );
    }
    Ok(())
}
