//! How much a network grown wider at a warm start (`Encoder::grown`: the old channels first in
//! every layer, the added ones after) reads its added channels after training: the mean norm of
//! the head's image-projection rows for the old features against the added ones, and for every
//! convolution of the encoder the mean |w| from old into old channels, added into old, old into
//! added and added into added. Right after growing, "added into old" and the added rows are zero.
//! `cargo run --release --example probe_grown -- BUNDLE [OLD_LAST_WIDTH]` (the layout grown
//! from's last width: 128 for `tiny_deep`; every stage is taken as grown by the same ratio).
use alignist::bundle::model::ModelBundle;
use burn::store::ModuleSnapshot;
use burn::store::bridge::into_data;

fn mean_abs(
    w: &[f32],
    rows: std::ops::Range<usize>,
    cols: std::ops::Range<usize>,
    n: usize,
) -> f64 {
    let mut sum = 0.0;
    let mut count = 0usize;
    for r in rows {
        for c in cols.clone() {
            sum += w[r * n + c].abs() as f64;
            count += 1;
        }
    }
    sum / count.max(1) as f64
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let path = std::path::PathBuf::from(args.get(1).map_or("models/symsol1", |s| s.as_str()));
    let old_last: usize = args.get(2).map_or(Ok(128), |s| s.parse())?;
    let bundle = ModelBundle::load(&path)?;
    let config = &bundle.manifest.network;
    let cells = config.pool_grid.unwrap_or(1).pow(2);
    let mut tensors = bundle.network.collect(None, None, false);
    tensors.sort_by(|a, b| a.name.cmp(&b.name));
    let mut last = 0;
    for t in &tensors {
        if t.name.ends_with("conv.weight") {
            last = last.max(t.shape[0]);
        }
    }
    anyhow::ensure!(
        last > old_last,
        "{}: last width {last} is not wider than {old_last}",
        path.display()
    );
    let ratio = last as f64 / old_last as f64;
    println!(
        "{}: last width {last}, grown from {old_last} (×{ratio:.2}); \
         mean |w| old→old, added→old, old→added, added→added",
        path.display()
    );
    for t in tensors {
        let name = t.name.clone();
        let shape: Vec<usize> = t.shape.to_vec();
        let w: Vec<f32> = into_data(t)?
            .try_to_vec()
            .map_err(|e| anyhow::anyhow!("{name}: {e:?}"))?;
        if name.ends_with("image_proj.weight") {
            // [features, hidden]: features are channel-major, old channels first.
            let (d, h) = (shape[0], shape[1]);
            let old = old_last * cells;
            let norm = |r: usize| {
                (0..h)
                    .map(|c| (w[r * h + c] as f64).powi(2))
                    .sum::<f64>()
                    .sqrt()
            };
            let mean = |rows: std::ops::Range<usize>| {
                let n = rows.len().max(1) as f64;
                rows.map(norm).sum::<f64>() / n
            };
            println!(
                "  {name}: row norm, {old} old features {:.3}, {} added {:.3}",
                mean(0..old),
                d - old,
                mean(old..d)
            );
        } else if name.ends_with("conv.weight") && shape.len() == 4 {
            let (o, i, k) = (shape[0], shape[1], shape[2] * shape[3]);
            let old_o = (o as f64 / ratio).round() as usize;
            let old_i = if i == 3 {
                3
            } else {
                (i as f64 / ratio).round() as usize
            };
            let n = i * k;
            let q = |rows: std::ops::Range<usize>, cols: std::ops::Range<usize>| {
                mean_abs(&w, rows, (cols.start * k)..(cols.end * k), n)
            };
            println!(
                "  {name:40} {:.4} {:.4} {:.4} {:.4}",
                q(0..old_o, 0..old_i),
                q(0..old_o, old_i..i),
                q(old_o..o, 0..old_i),
                q(old_o..o, old_i..i)
            );
        }
    }
    Ok(())
}
