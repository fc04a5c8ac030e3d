//! Matmul peak of the heads' library GEMM for tiles of 64–512 rows (`bench::matmul_peak_gflops`:
//! a 4096×256 · 256×256 product, one tile per rayon task, the GEMM single-threaded inside a tile),
//! for each library: the `gemm` crate (with its `x86-v4` kernels: 512-bit FMAs on AVX-512 cores)
//! under `widest` kernels, matrixmultiply (256-bit at most) under `avx2`.
//! `cargo run --release --example probe_gemm`
use alignist::net::Kernels;

fn main() {
    for kernels in [Kernels::Widest, Kernels::Avx2] {
        for tile in [64usize, 128, 256, 512] {
            println!(
                "{kernels:>7} library GEMM, tile {tile:>3}: {:.1} GFLOP/s",
                alignist::bench::matmul_peak_gflops(kernels, tile)
            );
        }
    }
}
