//! Matmul peak of candidate libraries for the fused head: row tiles of a 4096×256 · 256×256
//! product, one tile per rayon task, each library single-threaded inside a tile. Needs the
//! `gemm` crate as a dev-dependency to compare: measured on the 2-core machine, gemm 0.19
//! reached 211–241 GFLOP/s and matrixmultiply 0.3 291–369 GFLOP/s (tiles of 64–512 rows), so
//! the fused head uses matrixmultiply; this probe now measures matrixmultiply alone.
//! `cargo run --release --example probe_gemm`
use rayon::prelude::*;
use std::time::Instant;
fn main() {
    let (m, k, n) = (4096usize, 256usize, 256usize);
    let a: Vec<f32> = (0..m * k)
        .map(|i| ((i * 7919) % 1000) as f32 / 1000.0)
        .collect();
    let b: Vec<f32> = (0..k * n)
        .map(|i| ((i * 104729) % 1000) as f32 / 1000.0)
        .collect();
    for tile in [64usize, 128, 256, 512] {
        for lib in ["matrixmultiply"] {
            let mut c = vec![0f32; m * n];
            let mut best = f64::MAX;
            for _ in 0..20 {
                let t = Instant::now();
                c.par_chunks_mut(tile * n)
                    .zip(a.par_chunks(tile * k))
                    .for_each(|(c, a)| {
                        let rows = a.len() / k;
                        unsafe {
                            matrixmultiply::sgemm(
                                rows,
                                k,
                                n,
                                1.0,
                                a.as_ptr(),
                                k as isize,
                                1,
                                b.as_ptr(),
                                n as isize,
                                1,
                                0.0,
                                c.as_mut_ptr(),
                                n as isize,
                                1,
                            );
                        }
                    });
                best = best.min(t.elapsed().as_secs_f64());
            }
            println!(
                "{lib:>15} tile {tile:>3}: {:.1} GFLOP/s",
                2.0 * (m * k * n) as f64 / best / 1e9
            );
        }
    }
}
