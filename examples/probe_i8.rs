//! The 8-bit head's kernels without tiles against each other on a bundle's full grid at one
//! level: AVX-512 VNNI (`--kernels avx512`), AVX-VNNI (`--kernels avx2`) and AVX2's `VPMADDWD`
//! pairs, each where the core has it, the shape branch alone and both branches, in rounds that
//! alternate the kernels (best of `REPEATS` calls each a round), so that a window's slowdown
//! meets all of them. Prints each round's milliseconds, then the medians with their GOP/s (the
//! operations counted as `bench::head_flops_per_rotation` counts the f32 head's FLOPs).
//! `cargo run --release --example probe_i8 [BUNDLE] [LEVEL] [ROUNDS] [REPEATS]`
use std::time::Instant;

use alignist::net::{Branches, FusedHead, Kernels, Precision, ReducedHead, Rows};
use alignist::so3::GridLevel;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let bundle = args.get(1).map_or("models/symsol1", String::as_str);
    let level: u8 = args.get(2).map_or(Ok(3), |s| s.parse())?;
    let rounds: usize = args.get(3).map_or(Ok(5), |s| s.parse())?;
    let repeats: usize = args.get(4).map_or(Ok(3), |s| s.parse())?;
    anyhow::ensure!(
        rounds >= 1 && repeats >= 1,
        "ROUNDS and REPEATS must be at least 1"
    );
    let loaded = alignist::bundle::model::ModelBundle::load(std::path::Path::new(bundle))?;
    let grid = GridLevel::new(level)?;
    // Each kernel's head once; the 512-bit one also projects the grid (f32) and the image.
    let avx512 = FusedHead::with_kernels(&loaded.network.head, Kernels::Avx512);
    let avx2 = FusedHead::with_kernels(&loaded.network.head, Kernels::Avx2);
    let pairs = ReducedHead::i8_avx2_pairs(&avx2);
    let projected = avx512.project_rotations(
        &loaded
            .manifest
            .network
            .encoding
            .encode(&grid.matrices_f32()),
    );
    let features: Vec<f32> = (0..avx512.image_dim())
        .map(|i| ((i * 37 % 101) as f32 / 50.0 - 1.0).max(0.0))
        .collect();
    let image = avx512.image_term(&features);
    // Each kernel: (name, its head scoring `branches`).
    type Score<'a> = Box<dyn Fn(Branches) -> (Vec<f32>, Vec<f32>) + 'a>;
    let mut kernels: Vec<(&str, Score)> = Vec::new();
    for (head, name) in [(&avx512, "avx512"), (&avx2, "avx2")] {
        if head.native(Precision::I8) {
            kernels.push((
                head.kernel_name(Precision::I8),
                Box::new(|b| {
                    head.branch_scores_of(Precision::I8, &image, Rows::Projected(&projected), b)
                }),
            ));
        } else {
            println!("{name}: no native 8-bit kernel on this core");
        }
    }
    if let Some(pairs) = &pairs {
        kernels.push((
            pairs.kernel_name(),
            Box::new(|b| pairs.branch_scores_of(&image, Rows::Projected(&projected), b)),
        ));
    }
    // As `bench::head_flops_per_rotation`: the branches' square layers and output dots.
    let (h, layers) = (
        loaded.manifest.network.hidden as f64,
        loaded.manifest.network.layers as f64,
    );
    let flops = 2.0 * ((layers - 1.0) * 2.0 * h * h + 2.0 * h);
    println!(
        "level {level}: {} rotations, {:.0} operations a rotation for both branches",
        grid.len(),
        flops
    );
    let mut times = vec![vec![Vec::new(); 2]; kernels.len()];
    for round in 0..rounds {
        let mut line = format!("round {round}:");
        for (k, (_, score)) in kernels.iter().enumerate() {
            for (b, branches) in [Branches::Shape, Branches::Both].into_iter().enumerate() {
                let mut best = f64::MAX;
                for _ in 0..repeats {
                    let t = Instant::now();
                    std::hint::black_box(score(branches));
                    best = best.min(t.elapsed().as_secs_f64());
                }
                times[k][b].push(best);
                line += &format!(" {:.2}", best * 1e3);
            }
        }
        println!("{line} ms");
    }
    for ((name, _), times) in kernels.iter().zip(times) {
        let [shape, both] = [median(times[0].clone()), median(times[1].clone())];
        println!(
            "{name}: shape branch {:.2} ms ({:.0} GOP/s), both {:.2} ms ({:.0} GOP/s), medians of {rounds}",
            shape * 1e3,
            grid.len() as f64 * flops / 2.0 / shape / 1e9,
            both * 1e3,
            grid.len() as f64 * flops / both / 1e9,
        );
    }
    Ok(())
}
