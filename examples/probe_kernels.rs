//! The head's f32 kernels against each other and the machine's FMA peak, on a bundle's full grid
//! at one level: the native 512-bit kernel, the portable one (matrixmultiply), and bfloat16.
//! `cargo run --release --example probe_kernels [BUNDLE] [LEVEL]`
use std::time::Instant;

use alignist::bench::peak::fma_peak;
use alignist::net::{FusedHead, Kernels, Precision, Rows};
use alignist::so3::GridLevel;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let bundle = args.get(1).map_or("models/symsol1", String::as_str);
    let level: u8 = args.get(2).map_or(Ok(3), |s| s.parse())?;
    // Optionally only one set of kernels (`widest`, `avx2`, `portable`), f32 only: for `perf`.
    let only: Option<Kernels> = args
        .get(3)
        .map(|s| s.parse())
        .transpose()
        .map_err(anyhow::Error::msg)?;
    let loaded = alignist::bundle::model::ModelBundle::load(std::path::Path::new(bundle))?;
    for widest in [true, false] {
        let p = fma_peak(widest);
        println!("FMA peak, {}-bit: {:.1} GFLOP/s", p.bits, p.gflops);
    }
    let grid = GridLevel::new(level)?;
    let encoding = &loaded.manifest.network.encoding;
    let c = &loaded.manifest.network;
    let h = c.hidden as f64;
    let flops = 2.0 * ((c.layers - 1) as f64 * 2.0 * h * h + 2.0 * h);
    let mut reference: Option<Vec<f32>> = None;
    for kernels in [Kernels::Widest, Kernels::Avx2, Kernels::Portable] {
        if only.is_some_and(|o| o != kernels) {
            continue;
        }
        let head = FusedHead::with_kernels(&loaded.network.head, kernels);
        let projected = head.project_rotations(&encoding.encode(&grid.matrices_f32()));
        let features: Vec<f32> = (0..head.image_dim())
            .map(|i| ((i * 37 % 101) as f32 / 50.0 - 1.0).max(0.0))
            .collect();
        let image = head.image_term(&features);
        for precision in [Precision::F32, Precision::Bf16] {
            if only.is_some() && precision == Precision::Bf16 {
                continue;
            }
            let mut best = f64::MAX;
            let mut scores = Vec::new();
            for _ in 0..5 {
                let t = Instant::now();
                scores = head.scores_in(precision, &image, Rows::Projected(&projected));
                best = best.min(t.elapsed().as_secs_f64());
            }
            let gap = reference.as_ref().map_or(0.0, |r| {
                r.iter()
                    .zip(&scores)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0f32, f32::max)
            });
            println!(
                "{kernels:?} {precision} ({}): {:.1} ms, {:.1} GFLOP/s, max |Δ| to the first {gap:.5}",
                head.kernel_paths(),
                best * 1e3,
                grid.len() as f64 * flops / best / 1e9
            );
            reference.get_or_insert(scores);
        }
    }
    Ok(())
}
