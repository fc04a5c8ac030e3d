//! `alignist-train results`: evaluation tables of bundles in Markdown
//! ([`alignist::train::results`]).

use std::path::PathBuf;

use anyhow::{Context, Result, bail};

pub(crate) fn results_cmd(bundles: &[PathBuf]) -> Result<()> {
    use alignist::bundle::model::ModelManifest;
    let mut rows: Vec<(String, ModelManifest)> = Vec::new();
    for b in bundles {
        let path = b.join("manifest.json");
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("reading {}", path.display()))?;
        let m: ModelManifest =
            serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
        if m.evaluation.is_none() {
            bail!(
                "{}: evaluation: the bundle was not evaluated",
                path.display()
            );
        }
        let name = b
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default();
        rows.push((name, m));
    }
    print!("{}", alignist::train::results::results_tables(&rows));
    Ok(())
}
