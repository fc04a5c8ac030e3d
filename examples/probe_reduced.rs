//! A reduced-precision head (bfloat16, f16 or 8-bit integers) against the f32 one on a bundle's
//! full grid at one level: rotations/s of each, and how far the reduced scores (native and
//! emulated) fall from the f32 ones. `cargo run --release --example probe_reduced [BUNDLE] [LEVEL] [bf16|f16|i8]`
use std::time::Instant;

use alignist::net::ReducedHead;
use alignist::net::{FusedHead, Precision, Rows};
use alignist::so3::GridLevel;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let bundle = args.get(1).map_or("models/symsol1", String::as_str);
    let level: u8 = args.get(2).map_or(Ok(3), |s| s.parse())?;
    let reduced: Precision = args
        .get(3)
        .map_or(Ok(Precision::Bf16), |s| s.parse())
        .map_err(anyhow::Error::msg)?;
    let loaded = alignist::bundle::model::ModelBundle::load(std::path::Path::new(bundle))?;
    let head = FusedHead::new(&loaded.network.head);
    println!("{reduced} native: {}", head.native(reduced));
    let grid = GridLevel::new(level)?;
    let encoding = &loaded.manifest.network.encoding;
    let projected = head.project_rotations(&encoding.encode(&grid.matrices_f32()));
    let features: Vec<f32> = (0..head.image_dim())
        .map(|i| ((i * 37 % 101) as f32 / 50.0 - 1.0).max(0.0))
        .collect();
    let image = head.image_term(&features);
    let mut best = [f64::MAX; 2];
    let mut scores = Vec::new();
    for (k, precision) in [Precision::F32, reduced].into_iter().enumerate() {
        for _ in 0..5 {
            let t = Instant::now();
            let s = head.scores_in(precision, &image, Rows::Projected(&projected));
            best[k] = best[k].min(t.elapsed().as_secs_f64());
            if scores.len() == k {
                scores.push(s);
            }
        }
        println!(
            "{precision}: {:.1} ms, {:.2} M rotations/s",
            best[k] * 1e3,
            grid.len() as f64 / best[k] / 1e6
        );
    }
    println!("{reduced}/f32 speed: {:.2}", best[0] / best[1]);
    let emulated =
        ReducedHead::emulated(&head, reduced).branch_scores(&image, Rows::Projected(&projected));
    let emulated: Vec<f32> = emulated
        .0
        .iter()
        .zip(&emulated.1)
        .map(|(a, b)| a + b)
        .collect();
    let diff = |a: &[f32], b: &[f32]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max)
    };
    let range = scores[0].iter().fold(f32::MIN, |m, &v| m.max(v))
        - scores[0].iter().fold(f32::MAX, |m, &v| m.min(v));
    println!(
        "score range {range:.2}; max |{reduced} − f32| {:.4}; max |native − emulated| {:.5}",
        diff(&scores[1], &scores[0]),
        diff(&scores[1], &emulated)
    );
    let argmax = |s: &[f32]| (0..s.len()).max_by(|&a, &b| s[a].total_cmp(&s[b])).unwrap();
    println!(
        "argmax f32 {} {reduced} {} emulated {}",
        argmax(&scores[0]),
        argmax(&scores[1]),
        argmax(&emulated)
    );
    let max = scores[0][argmax(&scores[0])];
    for within in [5.0f32, 10.0, 20.0] {
        let near: Vec<usize> = (0..scores[0].len())
            .filter(|&i| scores[0][i] > max - within)
            .collect();
        let err = near
            .iter()
            .map(|&i| (scores[1][i] - scores[0][i]).abs())
            .fold(0.0f32, f32::max);
        println!(
            "{} cells within {within} of the max: max |{reduced} − f32| {err:.4}",
            near.len()
        );
    }
    let top = |s: &[f32], k: usize| {
        let mut o: Vec<usize> = (0..s.len()).collect();
        o.sort_by(|&a, &b| s[b].total_cmp(&s[a]));
        o.truncate(k);
        o
    };
    for k in [128, 512] {
        let a: std::collections::HashSet<usize> = top(&scores[0], k).into_iter().collect();
        let shared = top(&scores[1], k)
            .into_iter()
            .filter(|i| a.contains(i))
            .count();
        println!("top {k}: {shared} shared");
    }
    Ok(())
}
