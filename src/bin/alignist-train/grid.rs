//! `alignist-train grid`: the centres of a grid level as CSV.

use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};

use alignist::so3::{GridLevel, MAX_LEVEL};

pub(crate) fn write_grid(level: u8, out: &Path) -> Result<()> {
    if level > MAX_LEVEL {
        bail!(
            "--level {level} is above the maximum grid level {MAX_LEVEL} \
             (level {MAX_LEVEL} already has {} cells)",
            72u64 * 8u64.pow(MAX_LEVEL as u32)
        );
    }
    let grid = GridLevel::new(level).context("building the grid")?;
    let tmp = out.with_extension("csv.partial");
    let file = File::create(&tmp)
        .with_context(|| format!("cannot create the output file {}", tmp.display()))?;
    let mut w = BufWriter::new(file);
    let bar = ProgressBar::new(grid.len() as u64).with_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} cells  {per_sec}  eta {eta}")
            .expect("static progress template"),
    );
    let write_err = || format!("writing {}", tmp.display());
    alignist::so3::grid::write_centres_csv(&grid, &mut w, |i| bar.set_position(i))
        .with_context(write_err)?;
    let file = w
        .into_inner()
        .map_err(|e| e.into_error())
        .with_context(write_err)?;
    file.sync_all().with_context(write_err)?;
    std::fs::rename(&tmp, out)
        .with_context(|| format!("renaming {} to {}", tmp.display(), out.display()))?;
    bar.finish_and_clear();
    eprintln!(
        "wrote {} cells of level {level} to {}",
        grid.len(),
        out.display()
    );
    Ok(())
}
