//! Realistic crops of a bundle's objects written to a flat file, for a comparison outside the
//! project (a pretrained image encoder in PyTorch against the same network from scratch, on the
//! same crops): `COUNT` crops per object of the `train` or `held-out` realism at `SIZE` px, from
//! `SEED` (`eval` draws its held-out set from `EVAL_SEED + 1`: pass `eval` for that seed).
//! The file holds, per crop, the object index (u32), its rotation in the crop's camera (9 f64,
//! row-major) and `SIZE² × 3` RGB8 bytes, after a header `ALGNCROP`, u32 count, u32 size.
//! `cargo run --release --example export_crops BUNDLE OUT SPLIT COUNT SIZE SEED`
use std::io::Write;

use alignist::bundle::model::ModelBundle;
use alignist::data::realism::Realism;
use alignist::train::data::{BundleRenders, EVAL_SEED};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    anyhow::ensure!(
        args.len() == 7,
        "usage: export_crops BUNDLE OUT SPLIT(train|held-out) COUNT SIZE SEED(number|eval)"
    );
    let bundle = ModelBundle::load(std::path::Path::new(&args[1]))?;
    let realism = match args[3].as_str() {
        "train" => Realism::TRAIN,
        "held-out" => Realism::HELD_OUT,
        other => anyhow::bail!("SPLIT must be train or held-out, not {other}"),
    };
    let count: usize = args[4].parse()?;
    let size: u32 = args[5].parse()?;
    let seed = match args[6].as_str() {
        "eval" => EVAL_SEED + 1,
        s => s.parse()?,
    };
    let renders = BundleRenders::of(&bundle, 2);
    let start = std::time::Instant::now();
    let mut out = std::io::BufWriter::new(std::fs::File::create(&args[2])?);
    out.write_all(b"ALGNCROP")?;
    let objects = renders.names.len();
    out.write_all(&((count * objects) as u32).to_le_bytes())?;
    out.write_all(&size.to_le_bytes())?;
    // In chunks (a crop keeps its supersampled render: 40 000 at once filled this machine's 24
    // GiB before any was written): the first from `seed` itself, so
    // that a set of at most `CHUNK` is `eval`'s for its seed; chunk c from `seed + c·2²⁴`.
    const CHUNK: usize = 1000;
    for (c, first) in (0..count).step_by(CHUNK).enumerate() {
        let n = CHUNK.min(count - first);
        let seed = seed.wrapping_add((c as u64) << 24);
        let crops = renders.fresh.realistic_eval_crops(size, n, seed, realism);
        for (object, crop) in &crops {
            out.write_all(&(*object as u32).to_le_bytes())?;
            for v in crop.r_virtual.matrix().transpose().iter() {
                out.write_all(&v.to_le_bytes())?;
            }
            out.write_all(&crop.rgb)?;
        }
    }
    out.flush()?;
    println!(
        "{} crops of {size} px ({}) in {:.1} s to {}",
        count * objects,
        args[3],
        start.elapsed().as_secs_f64(),
        args[2]
    );
    Ok(())
}
